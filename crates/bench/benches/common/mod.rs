//! What the daemon benches share.

use std::path::{Path, PathBuf};

/// A file of the shared data folder: `PATCHWORK_SHARED_DATA`, or `../shared/data` beside the
/// checkout.
pub fn shared(name: &str) -> PathBuf {
    std::env::var_os("PATCHWORK_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data"))
        .join(name)
}

/// The `q` quantile of sorted figures, nearest rank.
pub fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// The daemon's binary, built beside this bench (`cargo build --release -p patchwork` puts it
/// where `cargo bench` looks: the bench is a crate of its own, so cargo does not build
/// another package's binary for it).
pub fn daemon_exe() -> PathBuf {
    let exe = std::env::current_exe().expect("the bench's own path");
    // target/<profile>/deps/<bench> → target/<profile>/patchwork
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("a bench binary under target/");
    let daemon = dir.join("patchwork");
    assert!(
        daemon.is_file(),
        "no daemon at {}: build it first with `cargo build --release -p patchwork`",
        daemon.display()
    );
    daemon
}
