//! The README's quick start, run as written: its shell blocks, in order, in a fresh folder
//! that holds only the repository's test crops, against the daemon the first block starts.
//! So the first steps a newcomer takes cannot rot: a command renamed, a flag dropped, a crop
//! moved or a tile that no longer serves fails here.
//!
//! Three things differ from a newcomer's shell, each for a reason of the test's: the build is
//! the test's own (`cargo build --release` is left out and `PATH` names the test's binary),
//! the ports are free ones (the README's `50052` is replaced by the HTTP port; the gRPC port
//! goes through `PATCHWORK_LISTEN` and `PATCHWORK_SERVER`), and the daemon is stopped when
//! the script ends, however it ends.

use crate::common::daemon::{free_port, http_port, BIN};
use crate::common::http::{rgba, terrarium};
use std::path::Path;
use std::process::Command;

/// The fenced `sh` blocks of the README's "Quick start" section, in order.
fn quick_start_blocks(readme: &str) -> Vec<String> {
    let start = readme
        .find("\n## Quick start")
        .expect("a Quick start section");
    let rest = &readme[start + 1..];
    let section = &rest[..rest[3..].find("\n## ").map_or(rest.len(), |i| i + 3)];
    let mut blocks = Vec::new();
    let mut lines = section.lines();
    while let Some(l) = lines.next() {
        if l.trim() == "```sh" {
            let body: Vec<&str> = lines.by_ref().take_while(|l| l.trim() != "```").collect();
            blocks.push(body.join("\n"));
        }
    }
    blocks
}

#[test]
fn the_readme_quick_start_serves_a_tile_from_the_dropped_file() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    if Command::new("curl").arg("--version").output().is_err() {
        panic!("the README's quick start uses curl, which is not installed (apt-get install curl)");
    }
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let blocks = quick_start_blocks(&readme);
    assert!(blocks.len() >= 3, "the quick start's blocks: {blocks:?}");
    let port = free_port();
    let http = http_port(port);
    let bin_dir = Path::new(BIN).parent().unwrap();
    let mut script = String::from(
        // However the script ends, the daemon it started in the background ends with it.
        "trap 'kill $(jobs -p) 2>/dev/null; wait' EXIT\n",
    );
    let mut built = false;
    for line in blocks.iter().flat_map(|b| b.lines()) {
        let line = line.replace("127.0.0.1:50052", &format!("127.0.0.1:{http}"));
        if line.trim() == "cargo build --release" {
            built = true;
            continue;
        }
        if line.starts_with("export PATH=") && line.contains("target/release") {
            script.push_str(&format!("export PATH=\"{}:$PATH\"\n", bin_dir.display()));
            continue;
        }
        script.push_str(&line);
        script.push('\n');
    }
    assert!(
        built && script.contains("patchwork serve"),
        "the quick start builds and starts the daemon: {blocks:?}"
    );
    let work = tempfile::tempdir().unwrap();
    std::os::unix::fs::symlink(root.join("tests"), work.path().join("tests")).unwrap();
    let mut cmd = Command::new("timeout");
    cmd.args(["300", "bash", "-e", "-c", &script])
        .current_dir(work.path())
        .env("PATCHWORK_LISTEN", format!("127.0.0.1:{port}"))
        .env("PATCHWORK_HTTP_LISTEN", format!("127.0.0.1:{http}"))
        .env("PATCHWORK_SERVER", format!("http://127.0.0.1:{port}"));
    // Nothing of the test's environment decides what the newcomer's daemon does.
    for (k, _) in std::env::vars() {
        if k.starts_with("PATCHWORK_") && !k.starts_with("PATCHWORK_REQUIRE") {
            cmd.env_remove(&k);
        }
    }
    let out = cmd.output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "the quick start failed ({}):\n{script}\n--- stdout\n{stdout}\n--- stderr\n{stderr}",
        out.status
    );
    // Both crops are surveys that serve.
    for crop in ["copernicus_n34w119_crop.tif", "nasadem_n34w119_crop.tif"] {
        assert!(
            stdout
                .lines()
                .any(|l| l.contains(crop) && l.contains("active")),
            "{crop} is not listed active:\n{stdout}"
        );
    }
    // The height at the point, and the survey it came from: one of the two files dropped.
    let heights: serde_json::Value = stdout
        .lines()
        .find(|l| l.contains("\"heights\":"))
        .map(|l| serde_json::from_str(&l[l.find('{').unwrap()..]).unwrap())
        .unwrap_or_else(|| panic!("no heights printed:\n{stdout}"));
    let h = heights["heights"][0].as_f64().expect("a height");
    assert!((0.0..4000.0).contains(&h), "{heights}");
    let file = heights["sources"][0]["file"].as_str().unwrap_or("");
    assert!(
        file.ends_with("copernicus_n34w119_crop.tif") || file.ends_with("nasadem_n34w119_crop.tif"),
        "{heights}"
    );
    // The tile: a terrarium PNG of the ground dropped, not an empty one.
    let png = std::fs::read(work.path().join("tile.png")).expect("tile.png written");
    let (w, _, px) = rgba(&png);
    let valid: Vec<f64> = px
        .chunks(4)
        .filter(|p| p[3] == 255)
        .map(terrarium)
        .collect();
    assert!(
        valid.len() as u32 > w * w / 4,
        "only {} of {} pixels hold heights",
        valid.len(),
        w * w
    );
    assert!(
        valid.iter().all(|h| (-100.0..4000.0).contains(h)),
        "heights off the ground: {:?}",
        valid.iter().take(5).collect::<Vec<_>>()
    );
}
