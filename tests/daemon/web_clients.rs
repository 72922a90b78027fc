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

/// Where PROJ's packages put EGM96's grid: `PROJ_DATA`, else Debian's proj-data.
fn egm96_grid() -> Option<std::path::PathBuf> {
    let mut dirs: Vec<std::path::PathBuf> = std::env::var_os("PROJ_DATA")
        .map(|v| std::env::split_paths(&v).collect())
        .unwrap_or_default();
    dirs.push("/usr/share/proj".into());
    dirs.iter()
        .flat_map(|d| ["us_nga_egm96_15.tif", "egm96_15.gtx"].map(|f| d.join(f)))
        .find(|p| p.is_file())
}

#[test]
fn cesium_heights_are_above_the_ellipsoid_as_pyproj_puts_them_with_the_same_geoid_grid() {
    let Some(grid) = egm96_grid() else {
        let msg = "not run: no EGM96 geoid grid (apt install proj-data gives \
                   /usr/share/proj/egm96_15.gtx)";
        if std::env::var("PATCHWORK_REQUIRE_PROJ_DATA").as_deref() == Ok("1") {
            panic!("{msg} (PATCHWORK_REQUIRE_PROJ_DATA=1)");
        }
        eprintln!("{msg}");
        return;
    };
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let python = python();
    let tmp = tempfile::tempdir().unwrap();
    let setup = Setup {
        // The grid is found where PROJ's packages put it, with no line of config.
        env: vec![(
            "PROJ_DATA".into(),
            grid.parent().unwrap().to_string_lossy().into_owned(),
        )],
        ..Setup::default()
    };
    let d = Daemon::start_with(tmp.path(), setup);
    // SRTM's heights are EGM96's (the reader says so: EPSG:5773).
    drop_by_rename(&crop("real/hgt/N44E005.hgt"), &d.inbox(), "N44E005.hgt");
    d.wait("the survey", |s| count(s, "active") == 1);

    let out = Command::new(&python)
        .current_dir(repo)
        .arg("tests/python/geoid_heights.py")
        .arg("--http")
        .arg(&d.http)
        .arg("--grid")
        .arg(&grid)
        .output()
        .expect("run tests/python/geoid_heights.py");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "the geoid check failed ({})\n--- stdout\n{stdout}--- stderr\n{stderr}--- daemon log\n{}",
        out.status,
        d.log()
    );
    assert!(
        stdout.lines().any(|l| l.starts_with("ok: ")),
        "unexpected output: {stdout}"
    );
    println!("{}", stdout.trim_end());
}
