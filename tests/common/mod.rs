//! Helpers shared by the daemon's integration tests: the shared surveys and oracles, a daemon
//! in a child process, and the Python environment.
#![allow(dead_code, unused_imports)]

pub mod daemon;
pub mod http;
pub mod python;
pub mod s3;

pub use patchwork_testkit::fixtures::*;

/// A copy of the folder `from` and everything under it at `to`.
pub fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let p = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &p);
        } else {
            std::fs::copy(e.path(), p).unwrap();
        }
    }
}

/// Every file under `dir` with a hash of its bytes, by path: what "byte for byte" compares.
pub fn dir_digest(dir: &std::path::Path) -> Vec<(std::path::PathBuf, String)> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let e = e.unwrap();
            if e.file_type().unwrap().is_dir() {
                todo.push(e.path());
            } else {
                let bytes = std::fs::read(e.path()).unwrap();
                out.push((e.path(), blake3::hash(&bytes).to_hex().to_string()));
            }
        }
    }
    assert!(!out.is_empty(), "no files under {}", dir.display());
    out.sort();
    out
}
