//! A client not written in this crate talks to the daemon from the proto: Python `grpcio`,
//! with stubs that `grpcio-tools` generates from `proto/` at test time (tests/python/client.py).
//! Needs `python3 -m pip install -r tests/python/requirements.txt`; without it this test fails.

mod common;

use common::daemon::*;
use std::path::Path;
use std::process::Command;

const INSTALL: &str = "python3 -m pip install -r tests/python/requirements.txt";

fn python_ready(repo: &Path) {
    let out = Command::new("python3")
        .current_dir(repo)
        .args([
            "-c",
            "import grpc, grpc_tools.protoc, grpc_health.v1.health_pb2",
        ])
        .output()
        .unwrap_or_else(|e| panic!("cannot run python3 ({e}); install Python 3, then: {INSTALL}"));
    assert!(
        out.status.success(),
        "python3 cannot import grpc / grpc_tools / grpc_health: run `{INSTALL}`\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn a_python_client_built_from_the_proto_queries_the_daemon() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    python_ready(repo);

    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "a.tif");
    d.wait("the Copernicus crop to be active", |s| {
        count(s, "active") == 1
    });

    let out = Command::new("python3")
        .current_dir(repo)
        .arg("tests/python/client.py")
        .arg(format!("127.0.0.1:{}", d.port))
        .output()
        .expect("run python3 tests/python/client.py");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "the Python client failed ({}); if it could not import grpc, run `{INSTALL}`\n\
         --- stdout\n{stdout}--- stderr\n{stderr}--- daemon log\n{}",
        out.status,
        d.log()
    );
    assert!(stdout.starts_with("ok: "), "unexpected output: {stdout}");
    println!("{}", stdout.trim_end());
}
