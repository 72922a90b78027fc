//! A client not written in this crate talks to the daemon from the proto: Python `grpcio`,
//! with stubs that `grpcio-tools` generates from `proto/` at test time (tests/python/client.py),
//! run in a virtual environment that the test makes under the target folder.

mod common;

use common::daemon::*;
use common::python::python;
use std::path::Path;
use std::process::Command;

#[test]
fn a_python_client_built_from_the_proto_queries_the_daemon() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let python = python();

    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "a.tif");
    d.wait("the Copernicus crop to be active", |s| {
        count(s, "active") == 1
    });

    let out = Command::new(&python)
        .current_dir(repo)
        .arg("tests/python/client.py")
        .arg(format!("127.0.0.1:{}", d.port))
        .output()
        .expect("run python3 tests/python/client.py");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "the Python client failed ({})\n\
         --- stdout\n{stdout}--- stderr\n{stderr}--- daemon log\n{}",
        out.status,
        d.log()
    );
    assert!(stdout.starts_with("ok: "), "unexpected output: {stdout}");
    println!("{}", stdout.trim_end());
}
