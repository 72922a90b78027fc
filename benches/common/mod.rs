//! What the daemon benches share.

use std::path::{Path, PathBuf};

/// A file of the shared data folder: `PATCHWORK_SHARED_DATA`, or `../shared/data` beside the
/// checkout.
pub fn shared(name: &str) -> PathBuf {
    std::env::var_os("PATCHWORK_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data"))
        .join(name)
}

/// The `q` quantile of sorted figures, nearest rank.
pub fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}
