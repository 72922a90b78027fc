//! The daemon's HTTP server as web map clients read it: terrarium and mapbox PNG tiles, GeoTIFF
//! tiles and Cesium's quantized-mesh tiles over the Copernicus and NASADEM crops, decoded by
//! independent readers (Pillow, rasterio, quantized-mesh-tile) and held to GDAL's bilinear warp
//! of the crops, to `/heights` and to gRPC (tests/python/web_tiles.py), with its caching
//! headers and its errors.

use crate::common;

use common::daemon::*;
use common::python::python;
use std::path::Path;
use std::process::Command;

#[test]
fn web_tiles_read_back_with_independent_decoders() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let python = python();
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start_with(tmp.path(), Setup::default());
    for name in ["copernicus_n34w119_crop.tif", "nasadem_n34w119_crop.tif"] {
        drop_by_rename(&crop(name), &d.inbox(), name);
    }
    d.wait("both surveys to be active", |s| count(s, "active") == 2);

    let out = Command::new(&python)
        .current_dir(repo)
        .arg("tests/python/web_tiles.py")
        .arg("--http")
        .arg(&d.http)
        .arg("--grpc")
        .arg(format!("127.0.0.1:{}", d.port))
        .output()
        .expect("run tests/python/web_tiles.py");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "the web tile checks failed ({})\n\
         --- stdout\n{stdout}--- stderr\n{stderr}--- daemon log\n{}",
        out.status,
        d.log()
    );
    assert!(
        stdout.lines().any(|l| l.starts_with("ok: ")),
        "unexpected output: {stdout}"
    );
    println!("{}", stdout.trim_end());
}
