//! Surveys of any CRS in one store, on real data: Mont Ventoux in geographic WGS 84 (SRTM3)
//! and in UTM 31N (the same ground resampled), US and French lidar in their UTM zones, and the
//! Copernicus + NASADEM pair. Held to GDAL's warps and PROJ's transformations (through
//! rasterio and pyproj, tests/python/crs_reference.py), and to the invariants: order
//! independence, exact retirement, one answer per point, nothing valid lost.

use crate::common;

use patchwork::config::Config;
use patchwork::engine::{Ctx, Cut, Engine, Origin, SampleRequest, TileRequest};
use patchwork_core::crs::{Crs, Reprojection, Transform};
use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::survey::Survey;
use patchwork_core::resample::Backend;
use patchwork_core::terrain::Terrain;
use patchwork_read::{read_raster, ReadLimits};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

fn crop(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

fn terrain(crs: &Crs, surveys: &[&Arc<Survey>]) -> Terrain {
    let mut t = Terrain::with_crs(IndexConfig::default(), Some(crs), None);
    for s in surveys {
        t.insert((*s).clone());
    }
    t
}

/// The store-plane bounds of a survey, as its terrain placed it.
fn footprint(t: &Terrain, s: &Survey) -> Aabb {
    t.survey(s.id).unwrap().footprint()
}

fn overlap(a: &Aabb, b: &Aabb) -> Aabb {
    a.intersection(b).expect("the surveys overlap")
}

/// Heights of the `width × height` tile over `roi` of `t` at error `e`, NaN where none.
fn tile(t: &Terrain, roi: &Aabb, width: usize, height: usize, e: f64) -> Vec<f32> {
    t.tile(roi, width, height, e).heights
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|z| z.to_bits()).collect()
}

#[test]
fn two_crss_make_one_terrain_whatever_the_order_and_retire_exactly() {
    let geo = common::crop_survey("real/ventoux_geographic.tif");
    let utm = common::crop_survey("real/ventoux_utm31.tif");
    assert_eq!(geo.crs.as_ref().and_then(|c| c.epsg_code()), Some(4326));
    assert_eq!(utm.crs.as_ref().and_then(|c| c.epsg_code()), Some(32631));
    for store in ["EPSG:4326", "EPSG:32631"] {
        let crs = Crs::parse(store).unwrap();
        let ab = terrain(&crs, &[&geo, &utm]);
        let ba = terrain(&crs, &[&utm, &geo]);
        assert_eq!(ab.index().state(), ba.index().state(), "{store}: order");
        ab.index().check().unwrap();
        // Retiring either gives the terrain that never had it.
        let mut r = ab.clone();
        r.retire(utm.id).unwrap();
        assert_eq!(r.index().state(), terrain(&crs, &[&geo]).index().state());
        let mut r = ba.clone();
        r.retire(geo.id).unwrap();
        assert_eq!(r.index().state(), terrain(&crs, &[&utm]).index().state());
        // One answer per point: the same heights in both orders, and a sub-tile that shares
        // the tile's sample positions equals it there.
        let roi = overlap(&footprint(&ab, &geo), &footprint(&ab, &utm));
        for e in [0.0, 10.0, 40.0] {
            let whole = tile(&ab, &roi, 96, 80, e);
            assert_eq!(
                bits(&whole),
                bits(&tile(&ba, &roi, 96, 80, e)),
                "{store} e={e}"
            );
            let valid = whole.iter().filter(|z| !z.is_nan()).count();
            assert!(valid > 96 * 80 * 9 / 10, "{store} e={e}: {valid} valid");
            let (dx, dy) = (roi.width() / 96.0, roi.height() / 80.0);
            let sub = Aabb::new(
                roi.min[0] + 24.0 * dx,
                roi.max[1] - 50.0 * dy,
                roi.min[0] + 72.0 * dx,
                roi.max[1] - 20.0 * dy,
            );
            let part = tile(&ab, &sub, 48, 30, e);
            for j in 0..30 {
                for i in 0..48 {
                    let (a, b) = (part[j * 48 + i], whole[(j + 20) * 96 + i + 24]);
                    assert!(
                        a.is_nan() && b.is_nan() || (a - b).abs() <= 1e-4 + 1e-7 * b.abs(),
                        "{store} e={e} ({i}, {j}): {a} vs {b}"
                    );
                }
            }
        }
    }
}

/// An engine over a store of `crs`, with the committed crops ingested, each with the
/// accuracy given (None: estimated).
fn engine(tmp: &Path, crs: &str, crops: &[(&str, Option<f64>)]) -> Arc<Engine> {
    let cfg = Config {
        data_dir: tmp.join("data"),
        ingest_roots: vec![crop("")],
        crs: Some(crs.into()),
        ..Config::default()
    };
    let engine = Arc::new(Engine::open(cfg).unwrap());
    for (c, a) in crops {
        let done = engine.ingest(&crop(c), *a, Origin::Request).unwrap();
        assert!(done.error.is_empty(), "{c}: {}", done.error);
    }
    engine
}

/// The tile of `cut`, and the largest error of the patches blended.
fn engine_tile(e: &Engine, cut: &Cut, width: u32, height: u32) -> (Vec<f32>, f64) {
    let req = TileRequest::new(cut.clone(), width, height, Backend::Cpu).unwrap();
    let (t, _, _) = e.tile(&req, Ctx::default()).unwrap();
    let max = t.patches.iter().map(|p| p.span.min_z).fold(0.0, f64::max);
    (t.heights, max)
}

/// A survey's samples and the pixel bounds of its grid, in its own CRS (north-up grids).
fn source(name: &str) -> (Vec<f32>, usize, usize, Aabb, Crs) {
    let r = read_raster(&crop(name), &ReadLimits::default()).unwrap();
    let gt = r.geotransform;
    assert!(gt[2] == 0.0 && gt[4] == 0.0, "north-up");
    let roi = Aabb::new(
        gt[0],
        gt[3] + gt[5] * r.rows as f64,
        gt[0] + gt[1] * r.cols as f64,
        gt[3],
    );
    let crs = r.crs.crs.clone().unwrap();
    (r.samples, r.cols, r.rows, roi, crs)
}

#[test]
fn surveys_in_their_own_crs_come_back_as_their_samples_from_a_geographic_store() {
    for name in [
        "real/ventoux_utm31.tif",
        "real/lidar_tiles_padded.tif",
        "real/philondenx_zero_nan.tif",
    ] {
        let tmp = tempfile::tempdir().unwrap();
        let e = engine(tmp.path(), "EPSG:4326", &[(name, Some(0.0))]);
        let (samples, cols, rows, roi, crs) = source(name);
        // A tile in the survey's own CRS whose pixels are the survey's: its samples sit on the
        // survey's, carried into the store and back.
        let cut = Cut::new(Some(crs.clone()), roi, 0.0).unwrap();
        let (heights, _) = engine_tile(&e, &cut, cols as u32, rows as u32);
        let (mut worst, mut lost, mut valid) = (0.0f32, 0, 0);
        for (z, s) in heights.iter().zip(&samples) {
            if s.is_nan() {
                continue;
            }
            valid += 1;
            if z.is_nan() {
                lost += 1;
            } else {
                worst = worst.max((z - s).abs());
            }
        }
        assert_eq!(lost, 0, "{name}: valid samples lost of {valid}");
        assert!(worst <= 1e-3, "{name}: {worst} m from its samples");
        // Points ask the same of the same positions.
        let pts: Vec<[f64; 2]> = (0..cols * rows)
            .step_by(97)
            .map(|k| {
                let (c, r) = ((k % cols) as f64 + 0.5, (k / cols) as f64 + 0.5);
                [
                    roi.min[0] + c * roi.width() / cols as f64,
                    roi.max[1] - r * roi.height() / rows as f64,
                ]
            })
            .collect();
        let at = SampleRequest::new(pts, Some(crs.clone()), 0.0).unwrap();
        let at = e.sample(&at, Ctx::default()).unwrap().heights;
        for (k, z) in (0..cols * rows).step_by(97).zip(&at) {
            assert_eq!(z.to_bits(), heights[k].to_bits(), "{name}: point {k}");
        }
    }
}

/// The middle `f` of a rectangle along each axis.
fn middle(b: &Aabb, f: f64) -> Aabb {
    let (mx, my) = ((1.0 - f) / 2.0 * b.width(), (1.0 - f) / 2.0 * b.height());
    Aabb::new(b.min[0] + mx, b.min[1] + my, b.max[0] - mx, b.max[1] - my)
}

/// GDAL's bilinear warp of a crop onto a tile grid, and where it is the plain bilinear.
fn gdal_warp(name: &str, crs: &str, roi: &Aabb, w: usize, h: usize) -> (Vec<f32>, Vec<bool>) {
    let out = tempfile::NamedTempFile::new().unwrap();
    python(&[
        "warp",
        crop(name).to_str().unwrap(),
        crs,
        &roi.min[0].to_string(),
        &roi.min[1].to_string(),
        &roi.max[0].to_string(),
        &roi.max[1].to_string(),
        &w.to_string(),
        &h.to_string(),
        out.path().to_str().unwrap(),
    ]);
    let bytes = std::fs::read(out.path()).unwrap();
    let n = w * h;
    let z = bytes[..4 * n]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    let mask = bytes[4 * n..].iter().map(|&b| b == 1).collect();
    (z, mask)
}

fn python(args: &[&str]) {
    let script = crop("../python/crs_reference.py");
    let out = Command::new(common::python::python())
        .arg(&script)
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "crs_reference.py {}: {}",
        args[0],
        String::from_utf8_lossy(&out.stderr)
    );
}

/// How far our tile falls outside the heights of the surveys there, by GDAL's warps of them:
/// the blend is a convex combination of patches each within its error of its own survey, so
/// at a point it lies within the error of the range of the surveys' heights there. Checked
/// where each survey's warp is either plain bilinear or nothing (not GDAL's re-weighting by
/// a void's side). Returns the largest excess over that range and the points checked.
fn outside(ours: &[f32], gdal: &[(Vec<f32>, Vec<bool>)]) -> (f64, usize) {
    let (mut worst, mut n) = (0.0f64, 0);
    for (k, a) in ours.iter().enumerate() {
        let mut range: Option<(f64, f64)> = None;
        let mut mixed = false;
        for (z, plain) in gdal {
            match (z[k].is_nan(), plain[k]) {
                (true, _) => {}
                (false, true) => {
                    let v = z[k] as f64;
                    range = Some(range.map_or((v, v), |(lo, hi)| (lo.min(v), hi.max(v))));
                }
                (false, false) => mixed = true,
            }
        }
        let Some((lo, hi)) = range.filter(|_| !mixed) else {
            continue;
        };
        assert!(
            !a.is_nan(),
            "point {k}: GDAL has data where the store has none"
        );
        let a = *a as f64;
        worst = worst.max(lo - a).max(a - hi);
        n += 1;
    }
    (worst, n)
}

#[test]
fn tiles_across_crss_agree_with_gdal_within_their_error() {
    let geo = "real/ventoux_geographic.tif";
    let utm = "real/ventoux_utm31.tif";
    for store in ["EPSG:4326", "EPSG:32631"] {
        let tmp = tempfile::tempdir().unwrap();
        let e = engine(tmp.path(), store, &[(geo, None), (utm, None)]);
        let t = e.snapshot();
        let bounds: Vec<Aabb> = t.surveys().map(|s| s.footprint()).collect();
        // The middle of the overlap, at about a quarter of the surveys' spacing: where GDAL's
        // bilinear is a point's bilinear (see tests/python/crs_reference.py).
        let roi = middle(&overlap(&bounds[0], &bounds[1]), 0.25);
        // Above both surveys' accuracies the tile is within the cut's error of each survey
        // (docs/MODEL.md, "Resampling"); below, within the error of what serves each point.
        let eps = t.surveys().map(|s| s.accuracy).fold(0.0, f64::max);
        for err in [eps, 2.0 * eps + 20.0] {
            let cut = Cut::new(None, roi, err).unwrap();
            let (ours, max_error) = engine_tile(&e, &cut, 120, 120);
            let gdal: Vec<_> = [geo, utm]
                .iter()
                .map(|name| gdal_warp(name, store, &roi, 120, 120))
                .collect();
            let (worst, n) = outside(&ours, &gdal);
            assert!(n > 5_000, "{store}: {n} points compared");
            assert!(
                worst <= max_error + 1e-3,
                "{store} e={err}: {worst:.3} m outside GDAL's warps, error {max_error:.3}"
            );
        }
    }
}

#[test]
fn a_web_mercator_tile_agrees_with_gdalwarp() {
    let cop = "copernicus_n34w119_crop.tif";
    let nasa = "nasadem_n34w119_crop.tif";
    let tmp = tempfile::tempdir().unwrap();
    let e = engine(tmp.path(), "EPSG:4326", &[(cop, None), (nasa, None)]);
    let t = e.snapshot();
    let bounds: Vec<Aabb> = t.surveys().map(|s| s.footprint()).collect();
    let geo_roi = overlap(&bounds[0], &bounds[1]);
    let merc = Crs::epsg(3857).unwrap();
    let to = Transform::new(&Crs::wgs84(), &merc).unwrap();
    let (a, b) = (
        to.apply(geo_roi.min).unwrap(),
        to.apply(geo_roi.max).unwrap(),
    );
    // The middle third, finer than the surveys (see above).
    let roi = middle(&Aabb::new(a[0], a[1], b[0], b[1]), 0.35);
    let eps = t.surveys().map(|s| s.accuracy).fold(0.0, f64::max);
    let cut = Cut::new(Some(merc), roi, eps).unwrap();
    let (ours, max_error) = engine_tile(&e, &cut, 160, 160);
    let gdal: Vec<_> = [cop, nasa]
        .iter()
        .map(|name| gdal_warp(name, "EPSG:3857", &roi, 160, 160))
        .collect();
    let (worst, n) = outside(&ours, &gdal);
    assert!(n > 10_000, "{n} points");
    assert!(
        worst <= max_error + 1e-3,
        "{worst:.3} m outside gdalwarp's surveys, error {max_error:.3}"
    );
}

#[test]
fn transformations_agree_with_proj_to_a_millimetre() {
    // CRSs from the lidar, national grids and global products users bring, with points in
    // each one's area of use: longitude/latitude boxes.
    let cases: &[(u32, [f64; 4])] = &[
        (32631, [0.5, 40.0, 5.5, 50.0]),
        (32733, [12.5, -30.0, 17.5, -5.0]),
        (26915, [-96.5, 30.0, -90.5, 48.0]),
        (25832, [6.5, 47.5, 11.5, 54.0]),
        (3857, [-119.0, 34.0, 5.5, 45.0]),
        (2154, [-4.5, 42.5, 8.0, 51.0]),
        (3035, [-10.0, 35.0, 30.0, 65.0]),
        (5070, [-120.0, 25.0, -70.0, 49.0]),
        (3413, [-60.0, 60.0, 0.0, 85.0]),
        (2193, [167.0, -47.0, 178.0, -35.0]),
        (4269, [-100.0, 30.0, -90.0, 45.0]),
        (28992, [3.5, 50.8, 7.1, 53.4]),
    ];
    let mut next = common::uniform(7);
    let mut json = Vec::new();
    for &(code, [x0, y0, x1, y1]) in cases {
        let pts: Vec<[f64; 2]> = (0..200)
            .map(|_| [x0 + next() * (x1 - x0), y0 + next() * (y1 - y0)])
            .collect();
        json.push(
            serde_json::json!({"from": "EPSG:4326", "to": format!("EPSG:{code}"), "points": pts}),
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let (inp, out) = (dir.path().join("in.json"), dir.path().join("out.json"));
    std::fs::write(&inp, serde_json::to_vec(&json).unwrap()).unwrap();
    python(&["transform", inp.to_str().unwrap(), out.to_str().unwrap()]);
    let answers: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    for (c, &(code, _)) in answers.iter().zip(cases) {
        let to = Crs::epsg(code).unwrap();
        let exact = Transform::new(&Crs::wgs84(), &to).unwrap();
        let lattice = Reprojection::new(&Crs::wgs84(), &to).unwrap();
        // Metres per unit of the target: a degree of latitude for a geographic one.
        let unit = if to.is_geographic() { 111_000.0 } else { 1.0 };
        let mut worst = [0.0f64; 2];
        for (p, q) in c["points"]
            .as_array()
            .unwrap()
            .iter()
            .zip(c["out"].as_array().unwrap())
        {
            let p = [p[0].as_f64().unwrap(), p[1].as_f64().unwrap()];
            let q = [q[0].as_f64().unwrap(), q[1].as_f64().unwrap()];
            for (k, got) in [exact.apply(p).unwrap(), lattice.at(p).unwrap()]
                .into_iter()
                .enumerate()
            {
                worst[k] = worst[k].max((got[0] - q[0]).hypot(got[1] - q[1]) * unit);
            }
        }
        assert!(
            worst[0] <= 1e-3 && worst[1] <= 1e-3,
            "EPSG:{code} ({}): exact {:.2e} m, lattice {:.2e} m from PROJ",
            c["operation"],
            worst[0],
            worst[1]
        );
    }
}

#[test]
fn a_survey_taken_as_exact_is_gdals_warp_of_it_to_a_millimetre() {
    // GDAL's bilinear is a point's bilinear only where the destination's pixels are finer
    // than the source's (it widens the kernel to average over coarser ones, whatever XSCALE
    // says, and the result then depends on the destination grid): tiles of a quarter of the
    // survey's spacing.
    for (store, name) in [
        ("EPSG:32631", "real/ventoux_geographic.tif"),
        ("EPSG:4326", "real/ventoux_utm31.tif"),
        ("EPSG:3857", "real/lidar_tiles_padded.tif"),
    ] {
        let tmp = tempfile::tempdir().unwrap();
        let e = engine(tmp.path(), store, &[(name, Some(0.0))]);
        let t = e.snapshot();
        let b = t.surveys().next().unwrap().footprint();
        let c = [(b.min[0] + b.max[0]) / 2.0, (b.min[1] + b.max[1]) / 2.0];
        let (w, h) = (160usize, 120usize);
        // A quarter of the survey's own cell, in store units, over the middle of it.
        let cell = b.width().min(b.height()) / 160.0 / 4.0;
        let roi = Aabb::new(
            c[0] - cell * w as f64 / 2.0,
            c[1] - cell * h as f64 / 2.0,
            c[0] + cell * w as f64 / 2.0,
            c[1] + cell * h as f64 / 2.0,
        );
        let cut = Cut::new(None, roi, 0.0).unwrap();
        let (ours, _) = engine_tile(&e, &cut, w as u32, h as u32);
        let (gdal, plain) = gdal_warp(name, store, &roi, w, h);
        let (mut worst, mut n) = (0.0f64, 0);
        for k in 0..ours.len() {
            if plain[k] && !gdal[k].is_nan() {
                worst = worst.max((ours[k] as f64 - gdal[k] as f64).abs());
                n += 1;
            }
        }
        assert!(n > w * h / 2, "{store} {name}: {n} points");
        assert!(worst <= 1e-3, "{store} {name}: {worst:.2e} m from GDAL");
    }
}

/// PROJ's answer to how far two surveys disagree, each's samples against the other's
/// bilinear surface (tests/python/crs_reference.py): (max, rms) both ways.
fn proj_deviation(a: &Path, b: &Path) -> [(f64, f64); 2] {
    let out = tempfile::NamedTempFile::new().unwrap();
    let (a, b) = (a.to_str().unwrap(), b.to_str().unwrap());
    python(&["deviation", a, b, out.path().to_str().unwrap()]);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(out.path()).unwrap()).unwrap();
    ["a_in_b", "b_in_a"].map(|k| {
        let f = |m: &str| v[k][m].as_f64().unwrap();
        (f("max_m"), f("rms_m"))
    })
}

#[test]
fn a_shifted_copy_in_another_crs_conflicts_by_as_much_as_proj_says() {
    let tmp = tempfile::tempdir().unwrap();
    // The UTM survey moved three cells (270 m) east: the same heights on the wrong ground.
    let utm = crop("real/ventoux_utm31.tif");
    let r = read_raster(&utm, &ReadLimits::default()).unwrap();
    let mut gt = r.geotransform;
    gt[0] += 3.0 * gt[1];
    let shifted = tmp.path().join("shifted.tif");
    patchwork_read::write_tiff::write_geotiff_f32(
        &shifted,
        r.cols,
        r.rows,
        &r.samples,
        gt,
        r.crs.crs.as_ref(),
        r.nodata,
    )
    .unwrap();
    let geo = crop("real/ventoux_geographic.tif");
    let cfg = Config {
        data_dir: tmp.path().join("data"),
        ingest_roots: vec![crop(""), tmp.path().to_path_buf()],
        crs: Some("EPSG:4326".into()),
        ..Config::default()
    };
    let e = Engine::open(cfg).unwrap();
    let ingest = |p: &Path| {
        let done = e.ingest(p, None, Origin::Request).unwrap();
        assert!(done.error.is_empty(), "{}: {}", p.display(), done.error);
        done
    };
    let (g, u) = (ingest(&geo), ingest(&utm));
    // Their own claims, before any evidence raises them.
    let accuracy = |id| e.snapshot().base(id).unwrap().accuracy;
    let (eg, eu) = (accuracy(g.survey.unwrap()), accuracy(u.survey.unwrap()));
    let s = ingest(&shifted);
    let es = accuracy(s.survey.unwrap());
    // Each conflict is the deviation PROJ's transformation gives, one way or the other (the
    // finer survey's samples against the coarser's surface).
    let mut seen = Vec::new();
    for (other, path, eo) in [(g.survey.unwrap(), &geo, eg), (u.survey.unwrap(), &utm, eu)] {
        let c = s
            .conflicts
            .iter()
            .find(|c| c.survey == other)
            .unwrap_or_else(|| panic!("no conflict with {}: {:?}", path.display(), s.conflicts));
        assert!(c.max_m > es + eo, "{c:?} within ε {es:.2} + {eo:.2}");
        // The copy's claim is the false one, and the original lies 270 m west of it, to a
        // tenth of a cell.
        assert_eq!(c.distrusted, patchwork::engine::Distrusted::This, "{c:?}");
        let [dx, dy, _] = c.shift_m.expect("coregistered");
        assert!((dx + 270.0).abs() < 9.0 && dy.abs() < 9.0, "{c:?}");
        let proj = proj_deviation(&shifted, path);
        let near = |(max, rms): (f64, f64)| {
            (c.max_m - max).abs() <= 0.01 && (c.rms_m - rms).abs() <= 0.01 * rms
        };
        assert!(
            proj.iter().any(|&d| near(d)),
            "{}: ours {c:?}, PROJ's {proj:?}",
            path.display()
        );
        seen.push(format!(
            "{}: max {:.2} m, rms {:.2} m (PROJ {proj:?})",
            path.file_name().unwrap().to_string_lossy(),
            c.max_m,
            c.rms_m
        ));
    }
    println!(
        "the shifted copy (ε {es:.2} m) conflicts with {}; the originals' conflicts: {:?}",
        seen.join("; "),
        u.conflicts
    );
}

/// A survey's footprint, as web maps draw it, is its own grid's pixels carried into
/// longitude and latitude: a UTM crop in a geographic store is the tilted quadrilateral it
/// covers, not the bounding box of where it lies in the store's plane.
#[test]
fn a_footprint_is_the_surveys_own_pixels_carried_into_longitude_and_latitude() {
    let tmp = tempfile::tempdir().unwrap();
    let e = engine(
        tmp.path(),
        "EPSG:4326",
        &[("real/ventoux_utm31.tif", Some(2.0))],
    );
    let r = read_raster(&crop("real/ventoux_utm31.tif"), &ReadLimits::default()).unwrap();
    let utm = r.crs.crs.clone().unwrap();
    let to = Transform::new(&utm, &Crs::wgs84()).unwrap();
    let gt = r.geotransform;
    // The outer corners of the pixels, clockwise from the north-west as the ring runs.
    let corner = |c: f64, r: f64| {
        to.apply([gt[0] + c * gt[1] + r * gt[2], gt[3] + c * gt[4] + r * gt[5]])
            .unwrap()
    };
    let (w, h) = (r.cols as f64, r.rows as f64);
    let want = [
        corner(0.0, 0.0),
        corner(w, 0.0),
        corner(w, h),
        corner(0.0, h),
    ];
    let f = &e.footprints()[0];
    assert_eq!(f.ring.len(), 4 * 16 + 1);
    for (k, p) in want.iter().enumerate() {
        let got = f.ring[16 * k];
        let d = (got[0] - p[0]).abs().max((got[1] - p[1]).abs());
        assert!(d < 1e-7, "corner {k}: {got:?} against PROJ's {p:?}");
    }
    // Tilted: UTM's grid north is not true north away from the central meridian.
    assert!((want[0][0] - want[3][0]).abs() > 1e-4, "{want:?}");
    assert!(f.file.ends_with("ventoux_utm31.tif"), "{}", f.file);
}
