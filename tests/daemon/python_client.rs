//! The Python client package (clients/python), installed as a user installs it into a virtual
//! environment under the target folder, against a daemon: every Terrain call, `resample`
//! against the daemon's tiles, a view session, and the README's example
//! (tests/python/client.py), `resample` again in a store of bicubic patches, with the accurate
//! blend, and across CRSs
//! in a geographic store holding a UTM survey. Its committed
//! stubs must match the protos.

use crate::common;

use common::daemon::*;
use common::python::python;
use std::path::Path;
use std::process::Command;

#[test]
fn the_python_client_package_reproduces_the_daemon() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let python = python();
    let check = Command::new(&python)
        .current_dir(repo)
        .args(["clients/python/generate_stubs.py", "--check"])
        .output()
        .expect("run generate_stubs.py");
    assert!(
        check.status.success(),
        "{}{}",
        String::from_utf8_lossy(&check.stdout),
        String::from_utf8_lossy(&check.stderr)
    );

    let tmp = tempfile::tempdir().unwrap();
    let d = four_surveys(tmp.path(), Setup::default());
    run_client(&python, &d, &[]);
}

#[test]
fn the_python_client_resamples_bicubic_patches() {
    let python = python();
    let tmp = tempfile::tempdir().unwrap();
    let setup = Setup {
        env: vec![("PATCHWORK_PATCHES".into(), "bicubic".into())],
        ..Setup::default()
    };
    let d = four_surveys(tmp.path(), setup);
    run_client(&python, &d, &["--bicubic"]);
}

#[test]
fn the_python_client_resamples_with_the_accurate_blend() {
    let python = python();
    for kind in ["bilinear", "bicubic"] {
        let tmp = tempfile::tempdir().unwrap();
        let setup = Setup {
            env: vec![
                ("PATCHWORK_BLEND".into(), "accurate".into()),
                ("PATCHWORK_PATCHES".into(), kind.into()),
            ],
            ..Setup::default()
        };
        let d = four_surveys(tmp.path(), setup);
        run_client(&python, &d, &["--accurate"]);
    }
}

#[test]
fn the_python_client_resamples_across_crss() {
    let python = python();
    let tmp = tempfile::tempdir().unwrap();
    let setup = Setup {
        env: vec![("PATCHWORK_CRS".into(), "EPSG:4326".into())],
        ..Setup::default()
    };
    let d = Daemon::start_with(tmp.path(), setup);
    for (name, as_name) in [
        ("real/ventoux_geographic.tif", "geo.tif"),
        ("real/ventoux_utm31.tif", "utm.tif"),
    ] {
        drop_by_rename(&crop(name), &d.inbox(), as_name);
    }
    d.wait("both surveys to be active", |s| count(s, "active") == 2);
    run_client(&python, &d, &["--crs"]);
}

/// A daemon under `root` holding the Copernicus, NASADEM and SRTM voids crops, and a coarser
/// copy of part of the first on a rotated lattice.
fn four_surveys(root: &Path, setup: Setup) -> Daemon {
    let d = Daemon::start_with(root, setup);
    for (name, as_name) in [
        ("copernicus_n34w119_crop.tif", "a.tif"),
        ("nasadem_n34w119_crop.tif", "b.tif"),
        ("srtm_n44e005_voids_crop.tif", "c.tif"),
    ] {
        drop_by_rename(&crop(name), &d.inbox(), as_name);
    }
    // A coarser survey of the same ground on a rotated lattice, off the others' pixels: its
    // edges blend with the Copernicus patches through the edge ramps.
    let mut rotated = common::window(
        &common::decimate(&common::real_crop("copernicus_n34w119_crop.tif"), 3),
        15,
        10,
        60,
        60,
    );
    rotated.georef.theta = 0.15;
    rotated.georef.origin[0] += 0.3 * rotated.georef.step[0];
    let staged = root.join("rotated.tif");
    patchwork_read::write_tiff::write_geotiff_f32(
        &staged,
        rotated.cols,
        rotated.rows,
        &rotated.samples,
        rotated.georef.geotransform(),
        Some(&patchwork_core::crs::Crs::epsg(4326).unwrap()),
        Some(-9999.0),
    )
    .unwrap();
    drop_by_rename(&staged, &d.inbox(), "d.tif");
    d.wait("the four surveys to be active", |s| count(s, "active") == 4);
    d
}

/// Runs tests/python/client.py against the daemon, with `args` after its address.
fn run_client(python: &Path, d: &Daemon, args: &[&str]) {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = Command::new(python)
        .current_dir(repo)
        .arg("tests/python/client.py")
        .arg(format!("127.0.0.1:{}", d.port))
        .args(args)
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
