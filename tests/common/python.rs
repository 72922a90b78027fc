//! The Python that the cross-language tests run: a virtual environment under the target
//! folder, made on first use from the pinned tests/python/requirements.txt, and made again when
//! they change, with the client package (clients/python) installed from the working tree on
//! every use. A fresh machine needs only `python3` (with its `venv` module) and the package
//! index; nothing is installed outside the target folder.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The environment's interpreter, with the requirements and the client package installed.
pub fn python() -> PathBuf {
    let bin = environment();
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    // As a user installs it, so that a broken package fails here; the dependencies are
    // already there, pinned.
    run(
        Command::new(&bin)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                "--no-deps",
                "--no-build-isolation",
                "--force-reinstall",
            ])
            .arg(repo.join("clients/python")),
        "pip install ./clients/python",
    );
    bin
}

/// The environment with the pinned requirements.
fn environment() -> PathBuf {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let reqs_path = repo.join("tests/python/requirements.txt");
    let reqs = std::fs::read_to_string(&reqs_path).unwrap();
    let env = Path::new(env!("CARGO_TARGET_TMPDIR")).join("python-env");
    let bin = env.join("bin").join("python");
    // Written last, so that an environment whose install was interrupted is made again.
    let stamp = env.join("installed-requirements.txt");
    if bin.exists() && std::fs::read_to_string(&stamp).ok().as_deref() == Some(reqs.as_str()) {
        return bin;
    }
    // Only tests/python_client.rs makes it, and cargo runs test binaries one at a time, so
    // no other process is making it at once.
    let _ = std::fs::remove_dir_all(&env);
    run(
        Command::new("python3").args(["-m", "venv"]).arg(&env),
        "python3 -m venv (Debian and Ubuntu package it as python3-venv)",
    );
    run(
        Command::new(&bin)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                "-r",
            ])
            .arg(&reqs_path),
        "pip install -r tests/python/requirements.txt (needs the package index)",
    );
    std::fs::write(&stamp, reqs).unwrap();
    bin
}

fn run(cmd: &mut Command, what: &str) {
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("cannot run {what}: {e}"));
    assert!(
        out.status.success(),
        "{what} failed ({})\n{}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
