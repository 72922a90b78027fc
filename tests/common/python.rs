//! The Python that the cross-language tests run: a virtual environment under the target
//! folder, made on first use from the pinned tests/python/requirements.txt, and made again when
//! they change, with the client package (clients/python) installed from the working tree on
//! every use. A fresh machine needs only `python3` (with its `venv` module) and the package
//! index; nothing is installed outside the target folder.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The environment's interpreter, with the requirements and the client package installed:
/// once per test binary, whose tests may ask for it at the same time.
pub fn python() -> PathBuf {
    static ONCE: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    ONCE.get_or_init(install).clone()
}

fn install() -> PathBuf {
    let bin = environment();
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    // Built from a copy, since pip builds in the source folder and the working tree should not
    // change under a test.
    let src = Path::new(env!("CARGO_TARGET_TMPDIR")).join("client-src");
    let _ = std::fs::remove_dir_all(&src);
    copy_tree(&repo.join("clients/python"), &src);
    // As a user installs it, so that a broken package fails here; the dependencies are
    // already there, pinned.
    pip(
        &bin,
        &["--no-deps", "--no-build-isolation", "--force-reinstall"],
        &src,
        "pip install ./clients/python",
    );
    bin
}

/// The package's sources, without what a build left beside them.
fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let name = entry.file_name();
        let skip = ["build", "__pycache__"].iter().any(|s| name == *s)
            || name.to_string_lossy().ends_with(".egg-info");
        if skip {
            continue;
        }
        if entry.file_type().unwrap().is_dir() {
            copy_tree(&entry.path(), &to.join(&name));
        } else {
            std::fs::copy(entry.path(), to.join(&name)).unwrap();
        }
    }
}

/// `pip install --quiet` of `target` with `flags`, failing with `what`.
fn pip(bin: &Path, flags: &[&str], target: &Path, what: &str) {
    run(
        Command::new(bin)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
            ])
            .args(flags)
            .arg(target),
        what,
    );
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
    pip(
        &bin,
        &["-r"],
        &reqs_path,
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
