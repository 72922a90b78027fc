//! `patchwork export`: PMTiles and MBTiles of the Copernicus and NASADEM crops, read by the
//! pmtiles package and sqlite3 and held tile by tile to the daemon's HTTP tiles, and a COG
//! validated by rio-cogeo and read by rasterio (tests/python/exports.py); an export killed
//! part way carried on to the same bytes.

use crate::common;

use common::daemon::*;
use common::python::python;
use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

fn export(data: &Path, args: &[&str], out: &Path) -> Command {
    let mut c = Command::new(BIN);
    c.arg("export")
        .arg("--data-dir")
        .arg(data)
        .args(args)
        .arg(out);
    c
}

fn ok(o: Output, what: &str) -> String {
    let stdout = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{what} failed ({})\n{stdout}{}",
        o.status,
        String::from_utf8_lossy(&o.stderr)
    );
    stdout
}

/// The `N tiles (D distinct, K kept from before)` of an export's last line.
fn counts(stdout: &str) -> (u64, u64) {
    let line = stdout
        .lines()
        .find(|l| l.starts_with("wrote "))
        .expect(stdout);
    let num = |after: &str| -> u64 {
        let i = line.find(after).expect(line);
        line[..i].rsplit(' ').next().unwrap().parse().unwrap()
    };
    (num(" tiles ("), num(" kept from before"))
}

/// Runs the export of `args` into `out` and kills it once its first tiles are durable.
fn kill_once_staged(data: &Path, args: &[&str], out: &Path) {
    let mut index = out.as_os_str().to_owned();
    index.push(".part/index");
    let index = std::path::PathBuf::from(index);
    let mut child = export(data, args, out)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while std::fs::metadata(&index).map_or(0, |m| m.len()) == 0 {
        assert!(
            child.try_wait().unwrap().is_none(),
            "the export finished before any tile was durable: the test needs a longer export"
        );
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "no tile was staged"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
}

#[test]
fn exports_hold_the_http_tiles_and_carry_on_where_they_stopped() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    // The daemon resamples on the CPU, as the export does: a GPU's float32 rounding makes a
    // few heights differ in their last bits, and the archives are held to the server's bytes.
    let cpu = Setup {
        unset: vec!["PATCHWORK_ALLOW_EMULATED_GPU".into()],
        ..Setup::default()
    };
    let mut d = Daemon::start_with(root, cpu.clone());
    // A sidecar's attribution, which the archives' metadata must carry as TileJSON does.
    std::fs::write(
        d.inbox().join("copernicus_n34w119_crop.tif.toml"),
        "attribution = \"© DLR, © Airbus, Copernicus\"\n",
    )
    .unwrap();
    for name in ["copernicus_n34w119_crop.tif", "nasadem_n34w119_crop.tif"] {
        drop_by_rename(&crop(name), &d.inbox(), name);
    }
    d.wait("both surveys to be active", |s| count(s, "active") == 2);
    // One process opens a store at a time: the export runs with the daemon stopped.
    d.stop();
    let data = root.join("data");
    let pm_args = ["--zooms", "9-16", "--size", "256"];

    let a = root.join("a.pmtiles");
    let whole = ok(export(&data, &pm_args, &a).output().unwrap(), "the export");
    let (tiles, kept) = counts(&whole);
    assert_eq!(kept, 0);
    assert!(tiles > 50, "{whole}");
    assert!(!root.join("a.pmtiles.part").exists());

    // The same export killed once its first tiles are durable, then run again.
    let b = root.join("b.pmtiles");
    kill_once_staged(&data, &pm_args, &b);
    assert!(!b.exists(), "a killed export left an archive");
    let again = ok(export(&data, &pm_args, &b).output().unwrap(), "the rerun");
    let (tiles_b, kept_b) = counts(&again);
    assert_eq!(tiles_b, tiles);
    assert!(kept_b > 0 && kept_b < tiles, "{again}");
    assert!(
        std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap(),
        "the carried-on archive differs from the one made at once"
    );
    assert!(!root.join("b.pmtiles.part").exists());

    let c = root.join("c.mbtiles");
    let mb = ok(
        export(
            &data,
            &[
                "--zooms",
                "10-14",
                "--size",
                "256",
                "--image",
                "png",
                "--encoding",
                "mapbox",
            ],
            &c,
        )
        .output()
        .unwrap(),
        "the MBTiles export",
    );
    let (tiles_c, _) = counts(&mb);

    // Options that make no export are refused before any work.
    for bad in [
        &["--zooms", "12-3"][..],
        &["--size", "300"],
        &["--roi", "1,2,3"],
        &["--heights", "EPSG:1"],
    ] {
        let o = export(&data, bad, &root.join("bad.pmtiles"))
            .output()
            .unwrap();
        assert!(!o.status.success(), "{bad:?} was taken");
        assert!(!root.join("bad.pmtiles").exists());
    }

    // A COG at half the crops' cells over both, and the same region as `patchwork tile`
    // writes it, for the heights to be held to.
    let roi = "-119.0,34.43625,-118.88347222222222,34.541805555555555";
    let res = 1.0 / 7200.0;
    let cog = root.join("crops.tif");
    let wrote = ok(
        export(
            &data,
            &["--roi", roi, "--resolution", &res.to_string()],
            &cog,
        )
        .output()
        .unwrap(),
        "the COG export",
    );
    let reference = root.join("reference.tif");
    let (w, h) = (
        ((-118.88347222222222f64 + 119.0) / res - 1e-9).ceil(),
        ((34.541805555555555f64 - 34.43625) / res - 1e-9).ceil(),
    );
    let cut_ymin = 34.541805555555555 - h * res;
    let cut_xmax = -119.0 + w * res;
    ok(
        Command::new(BIN)
            .args(["tile", "--data-dir"])
            .arg(&data)
            .args([
                "--roi",
                &format!("-119.0,{cut_ymin},{cut_xmax},34.541805555555555"),
                "--size",
                &format!("{w}x{h}"),
                "--error",
                "0",
                "--backend",
                "cpu",
                "--out",
            ])
            .arg(&reference)
            .output()
            .unwrap(),
        "patchwork tile",
    );

    let mut d = Daemon::start_with(root, cpu);
    let out = Command::new(python())
        .current_dir(repo)
        .arg("tests/python/exports.py")
        .args(["--http", &d.http])
        .arg("--pmtiles")
        .arg(&a)
        .args(["--pmtiles-count", &tiles.to_string()])
        .arg("--mbtiles")
        .arg(&c)
        .args(["--mbtiles-count", &tiles_c.to_string()])
        .arg("--cog")
        .arg(&cog)
        .arg("--cog-reference")
        .arg(&reference)
        .output()
        .unwrap();
    let stdout = ok(out, "tests/python/exports.py");
    println!("{}{whole}{again}{mb}{wrote}", stdout);
    d.stop();

    // A survey retired between a killed export and its rerun: the rectangle shrinks, and the
    // archive holds the tiles an export of the store as it is now makes, none of the stage's
    // tiles beyond it.
    let e = root.join("e.pmtiles");
    kill_once_staged(&data, &pm_args, &e);
    let nasadem = d.inbox().join("nasadem_n34w119_crop.tif");
    ok(
        Command::new(BIN)
            .args(["retire", "--data-dir"])
            .arg(&data)
            .arg(&nasadem)
            .output()
            .unwrap(),
        "retire",
    );
    let carried = ok(export(&data, &pm_args, &e).output().unwrap(), "the rerun");
    let fresh = root.join("f.pmtiles");
    let made = ok(
        export(&data, &pm_args, &fresh).output().unwrap(),
        "the export",
    );
    assert!(
        counts(&carried).0 < tiles,
        "the rectangle did not shrink: {carried}"
    );
    assert_eq!(counts(&carried).0, counts(&made).0);
    assert!(
        std::fs::read(&e).unwrap() == std::fs::read(&fresh).unwrap(),
        "the archive carried on across a retirement differs from one made after it"
    );
}
