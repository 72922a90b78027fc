//! The viewer page (`/`) in a real browser, against a daemon holding the Copernicus and
//! NASADEM crops: MapLibre GL JS and CesiumJS, served by the daemon from `/lib`, draw the
//! store's terrain in a headless Chromium (WebGL on SwiftShader) without a console error or a
//! failed request, show relief, and read heights at points inside the surveys that agree with
//! gRPC's within what their tiles promise; and the quantized-mesh tiles decode, with
//! neighbours sharing their edges' vertices.
//!
//! tests/web/browser.mjs drives the browser and decodes the tiles, and prints what it saw as
//! one JSON object; this test installs tests/web/package.json's packages under the target
//! folder (once, and again when the package files change), starts the daemon with them as its
//! `/lib`, and judges the report. Without Chromium (`/usr/bin/chromium`, or `CHROMIUM`) or
//! Node.js it says plainly that it did not run, and with `PATCHWORK_REQUIRE_BROWSER=1` it fails
//! instead.

use crate::common;

use common::daemon::*;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// Web Mercator's equator, metres: a raster-DEM tile at zoom z is cut at
/// e(z) = ½ · EQUATOR_M / (size · 2^z), half a pixel at the equator.
const EQUATOR_M: f64 = 40_075_016.686;
/// Cesium's geometric error at terrain level 0 (a 65-sample heightmap over two root tiles):
/// G(L) = G0 / 2^L, half for the cut and half for the mesh.
const G0: f64 = 77_067.34;
/// Samples a side of a quantized-mesh tile's grid (crates/server/src/web/pyramid.rs): between two of
/// them the mesh interpolates.
const TERRAIN_GRID: f64 = 257.0;
/// A terrarium PNG's height step (1/256 m), with room for f32 rounding.
const TERRARIUM_STEP: f64 = 0.01;
/// Below this standard deviation of luminance (0–255) a screenshot is one flat colour; the
/// crops' hills give tens.
const RELIEF_STDDEV: f64 = 5.0;

#[test]
fn the_viewer_page_shows_the_store_in_maplibre_and_cesium() {
    let Some(tools) = tools() else { return };
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let modules = node_modules(&tools);

    let tmp = tempfile::tempdir().unwrap();
    let setup = Setup {
        env: vec![(
            "PATCHWORK_HTTP_ASSETS".into(),
            modules.to_string_lossy().into_owned(),
        )],
        ..Setup::default()
    };
    let d = Daemon::start_with(tmp.path(), setup);
    for (name, as_name) in [
        ("copernicus_n34w119_crop.tif", "a.tif"),
        ("nasadem_n34w119_crop.tif", "b.tif"),
    ] {
        drop_by_rename(&crop(name), &d.inbox(), as_name);
    }
    d.wait("both surveys to be active", |s| count(s, "active") == 2);

    // Kept after the run, to look at when it fails.
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR")).join("web-screenshots");
    let t0 = Instant::now();
    let out = Command::new(&tools.node)
        .current_dir(repo)
        .arg("tests/web/browser.mjs")
        .arg("--base")
        .arg(&d.http)
        .arg("--out")
        .arg(&shots)
        .arg("--modules")
        .arg(&modules)
        .env("CHROMIUM", &tools.chromium)
        .output()
        .expect("run node tests/web/browser.mjs");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "tests/web/browser.mjs failed ({})\n--- stderr\n{stderr}--- stdout\n{stdout}--- daemon log\n{}",
        out.status,
        d.log()
    );
    let r: Value = serde_json::from_str(&stdout)
        .unwrap_or_else(|e| panic!("browser.mjs printed no JSON ({e}):\n{stdout}\n{stderr}"));
    println!(
        "browser run: {:.1} s on {} ({})",
        t0.elapsed().as_secs_f64(),
        r["browser"],
        r["webgl"]
    );

    // Nothing went wrong in the pages, and nothing came from anywhere but the daemon.
    for key in ["console_errors", "bad_responses", "external_requests"] {
        assert!(
            list(&r[key]).is_empty(),
            "{key}: {:#}\n--- daemon log\n{}",
            r[key],
            d.log()
        );
    }
    for view in ["maplibre", "cesium"] {
        let v = &r[view];
        assert_eq!(v["ready"], true, "{view} never got ready: {}", v["error"]);
        let stddev = num(&v["relief_stddev"], "relief_stddev");
        println!(
            "{view}: ready in {} ms, luminance σ {stddev:.1} over {} colours",
            v["ready_ms"], v["distinct_colours"]
        );
        assert!(
            stddev > RELIEF_STDDEV && num(&v["distinct_colours"], "distinct_colours") > 20.0,
            "{view}'s screenshot shows no relief (σ {stddev:.2}, {} colours): {}",
            v["distinct_colours"],
            v["screenshot"]
        );
        assert_eq!(v["exaggeration"], 1.0, "{view}: terrain exaggerated");
    }

    // These crops name no vertical CRS, so their heights cannot be carried above the
    // ellipsoid: Cesium gets the store's, and every terrain tile it received said so.
    let t = &r["terrain_responses"];
    let n = num(&t["responses"], "terrain responses");
    assert!(n > 0.0, "Cesium asked for no terrain tile: {t}");
    assert_eq!(
        num(&t["warned"], "warned"),
        n,
        "a terrain tile without its Warning: {t}"
    );
    let warning = t["warning"].as_str().unwrap_or("");
    assert!(
        warning.starts_with("299 patchwork") && warning.contains("no vertical CRS"),
        "{warning}"
    );

    // The heights gRPC gives at the points, and HTTP's /heights the same.
    let points: Vec<[f64; 2]> = list(&r["points"])
        .iter()
        .map(|p| [num(&p[0], "lon"), num(&p[1], "lat")])
        .collect();
    assert!(
        points.len() >= 3,
        "too few points inside the footprints: {points:?}"
    );
    let reference = heights(&d, &points);
    let http = list(&r["reference_heights"]["heights"]);
    assert_eq!(
        http.len(),
        points.len(),
        "/heights: {}",
        r["reference_heights"]
    );
    for (k, h) in http.iter().enumerate() {
        let h = num(h, "/heights");
        assert!(
            (h - reference[k]).abs() <= 1e-3,
            "/heights gives {h} at {:?}, gRPC {}",
            points[k],
            reference[k]
        );
    }

    // In the view the page opens with, and close up over each point at the deepest zoom.
    maplibre_heights(&d, "in the view", &r["maplibre"], &points, &reference);
    maplibre_heights(&d, "close up", &r["maplibre"]["close"], &points, &reference);
    cesium_heights(&d, &r, &points, &reference);
    quantized_mesh(&r["quantized_mesh"]);
}

/// MapLibre's `queryTerrainElevation` reads the DEM tile of the zoom the view renders at,
/// interpolating bilinearly between the four pixels around the point, and it takes pixel i
/// to lie at i, not at its centre i + ½: so it reads the heights of pixel centres up to 1.5
/// pixels away. Each of those is the store's height at its centre within e(z); the point's own
/// height differs from theirs by what the slope gives over that distance, measured at error 0.
fn maplibre_heights(d: &Daemon, how: &str, m: &Value, points: &[[f64; 2]], reference: &[f64]) {
    let samples = list(&m["samples"]);
    assert_eq!(samples.len(), points.len(), "maplibre samples {how}: {m:#}");
    let centres: Vec<[f64; 2]> = samples
        .iter()
        .flat_map(|s| list(&s["centres"]))
        .map(|c| [num(&c[0], "lon"), num(&c[1], "lat")])
        .collect();
    assert_eq!(
        centres.len(),
        4 * points.len(),
        "maplibre samples {how}: {m:#}"
    );
    let at_centres = heights(d, &centres);
    for (k, s) in samples.iter().enumerate() {
        let got = num(&s["elevation"], "maplibre elevation");
        let zoom = num(&s["dem_zoom"], "dem_zoom");
        let size = num(&s["dem_size"], "dem_size");
        let e = 0.5 * EQUATOR_M / (size * 2f64.powf(zoom));
        let around = &at_centres[4 * k..4 * k + 4];
        let slope = around
            .iter()
            .map(|h| (h - reference[k]).abs())
            .fold(0.0, f64::max);
        let tol = e + slope + TERRARIUM_STEP;
        let off = (got - reference[k]).abs();
        println!(
            "maplibre {how} at {:?}: {got:.2} m, gRPC {:.2} m, off {off:.2} ≤ {tol:.2} (zoom {zoom}, e {e:.2}, slope {slope:.2})",
            points[k], reference[k]
        );
        assert!(
            off <= tol,
            "MapLibre reads {got} m at {:?} {how}, gRPC {} m: off by {off:.3}, more than e(z) {e:.3} + \
             {slope:.3} across its pixels at zoom {zoom}\n{s:#}",
            points[k],
            reference[k]
        );
        // The tile's own pixels are the store's heights at their centres, within e(z).
        for (j, dem) in list(&s["dem"]).iter().enumerate() {
            if s["inside"][j] != true {
                continue;
            }
            let dem = num(dem, "dem sample");
            assert!(
                (dem - around[j]).abs() <= e + TERRARIUM_STEP,
                "pixel {} of tile {}/{} holds {dem} m; gRPC gives {} m at its centre {}: \
                 more than e(z) = {e:.3} apart",
                s["pixels"][j],
                zoom,
                s["dem_tile"],
                around[j],
                s["centres"][j]
            );
        }
    }
}

/// Cesium's `sampleTerrainMostDetailed` reads the mesh of the deepest level available at a
/// point, interpolating in the triangle that holds it: within G(L) of the store (half the cut,
/// half the mesh) at the grid's samples, plus what the slope gives across a cell of the 257²
/// grid, plus a step of the tile's height quantization.
fn cesium_heights(d: &Daemon, r: &Value, points: &[[f64; 2]], reference: &[f64]) {
    let c = &r["cesium"];
    let elevations = list(&c["elevations"]);
    let levels = list(&c["levels"]);
    let decoded = list(&r["quantized_mesh"]["samples"]);
    assert_eq!(elevations.len(), points.len(), "cesium: {c:#}");
    assert_eq!(
        decoded.len(),
        points.len(),
        "quantized_mesh samples: {:#}",
        r["quantized_mesh"]
    );
    // The grid's neighbours of each point, a cell away in each direction.
    let mut around = Vec::new();
    for (k, p) in points.iter().enumerate() {
        let level = num(&levels[k], "cesium level");
        let cell = 180.0 / 2f64.powf(level) / (TERRAIN_GRID - 1.0);
        for (dx, dy) in [
            (-1, -1),
            (0, -1),
            (1, -1),
            (-1, 0),
            (1, 0),
            (-1, 1),
            (0, 1),
            (1, 1),
        ] {
            around.push([p[0] + dx as f64 * cell, p[1] + dy as f64 * cell]);
        }
    }
    let at_around = heights(d, &around);
    for (k, p) in points.iter().enumerate() {
        let got = num(&elevations[k], "cesium height");
        let level = num(&levels[k], "cesium level");
        let mesh = &decoded[k];
        assert_eq!(
            num(&mesh["level"], "level"),
            level,
            "Cesium sampled level {level} at {p:?}, layer.json's deepest there is {}",
            mesh["level"]
        );
        let q = num(&mesh["quantization_step"], "quantization_step");
        // What Cesium read is the daemon's tile: the height of its triangle at the point.
        let own = num(&mesh["mesh_height"], "mesh_height");
        assert!(
            (got - own).abs() <= q + 1e-3,
            "Cesium reads {got} m at {p:?}; the tile {} decoded here gives {own} m",
            mesh["tile"]
        );
        let g = G0 / 2f64.powf(level);
        let slope = at_around[8 * k..8 * k + 8]
            .iter()
            .map(|h| (h - reference[k]).abs())
            .fold(0.0, f64::max);
        let tol = g * 1.05 + q + slope;
        let off = (got - reference[k]).abs();
        println!(
            "cesium at {p:?}: {got:.2} m, gRPC {:.2} m, off {off:.2} ≤ {tol:.2} (level {level}, G {g:.2}, slope {slope:.2})",
            reference[k]
        );
        assert!(
            off <= tol,
            "Cesium reads {got} m at {p:?}, gRPC {} m: off by {off:.3}, more than G(L) {g:.3} + \
             {slope:.3} across a grid cell + {q:.3} at level {level}\n{mesh:#}",
            reference[k]
        );
    }
}

/// The tiles decode with sane heights and the extensions asked for, and two pairs of
/// neighbours (west–east, south–north) share their edge's vertices and heights.
fn quantized_mesh(q: &Value) {
    assert!(
        list(&q["errors"]).is_empty(),
        "quantized-mesh: {:#}",
        q["errors"]
    );
    let tiles = list(&q["tiles"]);
    assert!(
        tiles.len() >= 3,
        "too few quantized-mesh tiles checked: {q:#}"
    );
    for t in tiles {
        assert_eq!(
            t["ok"], true,
            "quantized-mesh tile {}: {:#}",
            t["url"], t["errors"]
        );
    }
    let edges = list(&q["edges"]);
    assert_eq!(edges.len(), 2, "edges: {:#}", q["edges"]);
    for e in edges {
        println!(
            "{} edge at level {} ({} vertices): heights within {:.3} m (steps {})",
            e["kind"],
            e["level"],
            e["vertices"][0],
            num(&e["max_height_difference"], "difference"),
            e["quantization_steps"]
        );
        assert_eq!(
            e["positions_match"], true,
            "the {} neighbours {} do not share their edge's vertices: {e:#}",
            e["kind"], e["tiles"]
        );
        assert_eq!(
            e["ok"], true,
            "the {} neighbours {} disagree on their edge's heights by more than a quantization step: {e:#}",
            e["kind"], e["tiles"]
        );
    }
}

/// The heights gRPC gives at `points` (longitude, latitude) at error 0, through the CLI.
fn heights(d: &Daemon, points: &[[f64; 2]]) -> Vec<f64> {
    let csv = points
        .iter()
        .map(|p| format!("{},{}", p[0], p[1]))
        .collect::<Vec<_>>()
        .join(",");
    let v = d.json(&[
        "sample",
        "--points",
        csv.as_str(),
        "--crs",
        "EPSG:4326",
        "--error",
        "0",
        "--json",
    ]);
    let v = list(&v);
    assert_eq!(v.len(), points.len());
    v.iter()
        .zip(points)
        .map(|(s, p)| {
            s["height"]
                .as_f64()
                .unwrap_or_else(|| panic!("gRPC has no height at {p:?}: {s}"))
        })
        .collect()
}

fn list(v: &Value) -> &[Value] {
    v.as_array().map(Vec::as_slice).unwrap_or(&[])
}

fn num(v: &Value, what: &str) -> f64 {
    v.as_f64()
        .unwrap_or_else(|| panic!("{what}: expected a number, got {v}"))
}

struct Tools {
    node: PathBuf,
    npm: PathBuf,
    chromium: PathBuf,
}

/// Chromium, node and npm; None, having said why, where one is missing.
fn tools() -> Option<Tools> {
    let chromium = std::env::var_os("CHROMIUM")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/usr/bin/chromium"));
    let runs = |p: &str| {
        Command::new(p)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
    };
    let why = if !chromium.is_file() {
        Some(format!(
            "no Chromium at {} (install Debian's chromium, or set CHROMIUM)",
            chromium.display()
        ))
    } else if !runs("node") {
        Some("no Node.js (`node` is not on PATH)".to_string())
    } else if !runs("npm") {
        Some("no npm (`npm` is not on PATH)".to_string())
    } else {
        None
    };
    match why {
        None => Some(Tools {
            node: "node".into(),
            npm: "npm".into(),
            chromium,
        }),
        Some(why) => {
            let msg = format!("browser test NOT RUN: {why}");
            if std::env::var("PATCHWORK_REQUIRE_BROWSER").as_deref() == Ok("1") {
                panic!("{msg} (PATCHWORK_REQUIRE_BROWSER=1)");
            }
            println!("{msg}");
            None
        }
    }
}

/// tests/web/package.json's packages, installed under the target folder: the node_modules
/// folder, served as the daemon's `/lib` and loaded by browser.mjs. Installed again only when
/// the package files change.
fn node_modules(tools: &Tools) -> PathBuf {
    // Both browser tests ask for the folder, on threads of one test binary: one at a time, or
    // the second would remove the folder under the first one's npm (which then fails with no
    // working directory) and both would install.
    static INSTALL: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _turn = INSTALL.lock().unwrap_or_else(|e| e.into_inner());
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("web-env");
    let files = ["package.json", "package-lock.json"];
    let wanted: String = files
        .iter()
        .map(|f| std::fs::read_to_string(repo.join("tests/web").join(f)).unwrap_or_default())
        .collect::<Vec<_>>()
        .join("\n--\n");
    let modules = dir.join("node_modules");
    // Written last, so that an install that was interrupted is made again.
    let stamp = dir.join("installed-packages.txt");
    if modules.is_dir() && std::fs::read_to_string(&stamp).ok().as_deref() == Some(wanted.as_str())
    {
        return modules;
    }
    // cargo runs test binaries one at a time, and within this one the lock above holds.
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    for f in files {
        let from = repo.join("tests/web").join(f);
        if from.exists() {
            std::fs::copy(&from, dir.join(f)).unwrap();
        }
    }
    let t0 = Instant::now();
    let out = Command::new(&tools.npm)
        .current_dir(&dir)
        .args(["install", "--no-audit", "--no-fund"])
        // puppeteer-core downloads no browser; this keeps any other package from trying.
        .env("PUPPETEER_SKIP_DOWNLOAD", "1")
        .output()
        .unwrap_or_else(|e| panic!("cannot run npm install: {e}"));
    assert!(
        out.status.success(),
        "npm install of tests/web/package.json failed ({}; it needs the package registry)\n{}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    println!(
        "installed tests/web/package.json in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    std::fs::write(&stamp, wanted).unwrap();
    modules
}

#[test]
fn maplibre_draws_an_exported_pmtiles_archive_from_a_static_file_server() {
    let Some(tools) = tools() else { return };
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let modules = node_modules(&tools);
    let tmp = tempfile::tempdir().unwrap();
    // On the CPU, as the export resamples (see tests/daemon/exports.rs).
    let cpu = Setup {
        unset: vec!["PATCHWORK_ALLOW_EMULATED_GPU".into()],
        ..Setup::default()
    };
    let mut d = Daemon::start_with(tmp.path(), cpu.clone());
    for name in ["copernicus_n34w119_crop.tif", "nasadem_n34w119_crop.tif"] {
        drop_by_rename(&crop(name), &d.inbox(), name);
    }
    d.wait("both surveys to be active", |s| count(s, "active") == 2);
    // One process opens a store at a time.
    d.stop();
    let site = tmp.path().join("site");
    std::fs::create_dir_all(&site).unwrap();
    let archive = site.join("crops.pmtiles");
    let out = Command::new(BIN)
        .args(["export", "--data-dir"])
        .arg(tmp.path().join("data"))
        .args(["--zooms", "8-14", "--size", "256", "--image", "webp"])
        .arg(&archive)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "export: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Inside both crops, and the overlap's corners.
    let points = [
        [-118.95, 34.49],
        [-118.93, 34.47],
        [-118.98, 34.525],
        [-118.90, 34.45],
    ];
    let run = Command::new(&tools.node)
        .current_dir(repo)
        .arg("tests/web/pmtiles.mjs")
        .arg("--dir")
        .arg(&site)
        .args(["--archive", "crops.pmtiles", "--modules"])
        .arg(&modules)
        .args([
            "--points",
            &points
                .iter()
                .flatten()
                .map(|v| v.to_string())
                .collect::<Vec<_>>()
                .join(","),
        ])
        .env("CHROMIUM", &tools.chromium)
        .output()
        .expect("run node tests/web/pmtiles.mjs");
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "tests/web/pmtiles.mjs failed ({})\n{}{stdout}",
        run.status,
        String::from_utf8_lossy(&run.stderr)
    );
    let r: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(r["ready"], true, "MapLibre never got ready: {r:#}");
    assert!(list(&r["console_errors"]).is_empty(), "{r:#}");
    assert!(list(&r["bad"]).is_empty(), "{r:#}");
    // The tiles came by byte ranges of the one file.
    assert!(num(&r["ranges"], "ranges") >= 2.0, "{r:#}");

    // Each DEM pixel MapLibre drew is the daemon's own tile's, decoded as MapLibre decodes it.
    let d = Daemon::start_with(tmp.path(), cpu);
    let samples = list(&r["samples"]);
    assert_eq!(samples.len(), points.len(), "{r:#}");
    for s in samples {
        let t: Vec<u64> = list(&s["tile"])
            .iter()
            .map(|v| v.as_u64().unwrap())
            .collect();
        // MapLibre draws terrain from a level under the view's; close up, the deepest two.
        assert!(t[0] >= 13, "drawn from zoom {} only: {s:#}", t[0]);
        let url = format!(
            "{}/tiles/{}/{}/{}.webp?encoding=terrarium&size=256",
            d.http, t[0], t[1], t[2]
        );
        let reply = common::http::get(&url, &[]);
        assert_eq!(reply.status, 200, "{url}");
        let (w, _, px) = common::http::webp_rgba(&reply.body);
        let dem: Vec<f64> = list(&s["dem"]).iter().map(|v| num(v, "dem")).collect();
        for (k, p) in list(&s["pixels"]).iter().enumerate() {
            let (i, j) = (p[0].as_i64().unwrap(), p[1].as_i64().unwrap());
            if i < 0 || j < 0 || i >= w as i64 || j >= w as i64 {
                // MapLibre's border, copied from the neighbouring tile.
                continue;
            }
            let at = (j as usize * w as usize + i as usize) * 4;
            let served = common::http::terrarium(&px[at..at + 4]);
            assert!(
                (served - dem[k]).abs() <= TERRARIUM_STEP,
                "pixel {i},{j} of {url}: MapLibre drew {} m from the archive, the daemon serves {served} m",
                dem[k]
            );
        }
        // Drawn between the pixels around the point.
        let e = num(&s["elevation"], "elevation");
        let (lo, hi) = dem
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        assert!(
            e >= lo - TERRARIUM_STEP && e <= hi + TERRARIUM_STEP,
            "terrain height {e} m outside its pixels' {lo}..{hi} m: {s:#}"
        );
    }
    println!(
        "pmtiles in the browser: ready in {} ms, {} requests, {} of them ranges",
        r["ready_ms"], r["requests"], r["ranges"]
    );
}
