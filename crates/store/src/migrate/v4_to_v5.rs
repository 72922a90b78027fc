//! 4 → 5: overlaps become evidence. Version 4 kept, for each overlapping pair, how far the two
//! disagreed; version 5 keeps what each says of the other's accuracy claims (the
//! coregistration, which one is degraded, the kernels whose claims are contradicted), and the
//! index takes those claims as the evidence leaves them. None of that follows from the old
//! figures, so the step drops them and marks the store for a rebuild, which measures every
//! pair again from the samples and derives the index from the result.

use super::Ctx;
use crate::keys;

pub(super) fn run(tree: &sled::Tree, _: &Ctx) -> Result<sled::Batch, String> {
    let mut b = sled::Batch::default();
    for kv in tree.scan_prefix(keys::OVERLAP_PREFIX) {
        let (k, _) = kv.map_err(|e| e.to_string())?;
        b.remove(k);
    }
    if tree.scan_prefix(keys::SURVEY_PREFIX).next().is_some() {
        b.insert(keys::REBUILD, &[1u8][..]);
    }
    Ok(b)
}
