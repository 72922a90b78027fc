//! 5 → 6: a failed file is known by its content. Version 5 kept a failure's size and mtime,
//! and the inbox took a file with the same ones as the same file; a file rewritten in place
//! with its size and mtime kept (`cp -p`, `rsync -a`, tar) was then never tried again.
//! Version 6 adds the hash of the bytes that failed. The step rewrites each failure with an
//! empty hash, which matches no file: each failed file is tried once more, and recorded with
//! its hash if it fails again. Version 6 also knows `meta/quarantined` (the damaged surveys
//! the stored index leaves out), which no version-5 store holds.

use super::Ctx;
use crate::{keys, FailedRecord};
use serde::{Deserialize, Serialize};

/// A failure as version 5 wrote it.
#[derive(Serialize, Deserialize)]
struct FailedV5 {
    source: String,
    error: String,
    size: u64,
    mtime_unix: u64,
    at_unix: u64,
}

pub(super) fn run(tree: &sled::Tree, _: &Ctx) -> Result<sled::Batch, String> {
    let config = bincode::config::standard();
    let mut b = sled::Batch::default();
    for kv in tree.scan_prefix(keys::FAILURE_PREFIX) {
        let (k, v) = kv.map_err(|e| e.to_string())?;
        let (old, _): (FailedV5, _) = bincode::serde::decode_from_slice(&v, config)
            .map_err(|e| format!("failure {}: {e}", String::from_utf8_lossy(&k)))?;
        let new = FailedRecord {
            source: old.source,
            error: old.error,
            size: old.size,
            mtime_unix: old.mtime_unix,
            at_unix: old.at_unix,
            content_id: String::new(),
        };
        let v = bincode::serde::encode_to_vec(&new, config).map_err(|e| e.to_string())?;
        b.insert(k, v);
    }
    Ok(b)
}
