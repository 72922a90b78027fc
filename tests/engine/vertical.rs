//! Vertical CRSs: heights measured from another geoid than the store's are converted with
//! the geoid grids the config names, the grids' interpolation error counted in ε; without a
//! grid the survey is refused, naming both CRSs and the config key. Geoid grids written here:
//! undulations that vary across the ground, so that a conversion done with the wrong grid,
//! or at the wrong place, shows.

use patchwork::config::Config;
use patchwork::engine::{
    Backend, Ctx, Cut, Engine, EngineError, Heights, HeightsError, MeshSpec, Metres, Origin,
    Outcome, Reason, Region, SampleRequest, TileRequest,
};
use patchwork_core::crs::{Crs, Transform};
use patchwork_core::geom::Aabb;
use patchwork_read::write_tiff::write_geotiff_f32;
use patchwork_read::{read_raster, ReadLimits};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

fn crop(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/real")
        .join(name)
}

/// A geoid grid over Mont Ventoux and around: `n(lon, lat)` at nodes every 0.05°.
fn geoid(path: &Path, n: impl Fn(f64, f64) -> f64) {
    let (lon0, lat1, step, size) = (4.5, 45.5, 0.05, 41usize);
    let mut z = Vec::with_capacity(size * size);
    for r in 0..size {
        for c in 0..size {
            z.push(n(lon0 + c as f64 * step, lat1 - r as f64 * step) as f32);
        }
    }
    // Pixel-is-area: node (c, r) at the centre of pixel (c, r).
    let gt = [lon0 - step / 2.0, step, 0.0, lat1 + step / 2.0, 0.0, -step];
    write_geotiff_f32(path, size, size, &z, gt, Some(&Crs::wgs84()), None).unwrap();
}

/// EGM96 here: a plane. EGM2008: another, tilted the other way; both reproduced exactly by
/// bilinear interpolation, so that a conversion through them is exact too.
fn n96(lon: f64, lat: f64) -> f64 {
    47.0 + 2.0 * (lon - 5.0) - 1.0 * (lat - 44.0)
}

fn n08(lon: f64, lat: f64) -> f64 {
    12.0 - 3.0 * (lat - 44.0) + 1.5 * (lon - 5.0)
}

/// A copy of a crop with its heights as `f` makes them of each sample's height, longitude
/// and latitude, and a sidecar naming its vertical CRS.
fn copy(
    dir: &Path,
    name: &str,
    vertical: Option<&str>,
    f: impl Fn(f64, f64, f64) -> f64,
) -> PathBuf {
    let r = read_raster(&crop(name), &ReadLimits::default()).unwrap();
    let crs = r.crs.crs.clone().unwrap();
    let to_geo = Transform::new(&crs, &Crs::wgs84()).unwrap();
    let gt = r.geotransform;
    let mut z = r.samples.clone();
    for row in 0..r.rows {
        for col in 0..r.cols {
            let k = row * r.cols + col;
            if z[k].is_nan() {
                continue;
            }
            let (x, y) = r.pixel_centre(col, row);
            let [lon, lat] = to_geo.apply([x, y]).unwrap();
            z[k] = f(z[k] as f64, lon, lat) as f32;
        }
    }
    let out = dir.join(name.replace(".tif", "_copy.tif"));
    write_geotiff_f32(&out, r.cols, r.rows, &z, gt, Some(&crs), Some(-9999.0)).unwrap();
    if let Some(v) = vertical {
        std::fs::write(
            format!("{}.toml", out.display()),
            format!("vertical_crs = \"{v}\"\n"),
        )
        .unwrap();
    }
    out
}

fn engine(dir: &Path, geoids: &[(&str, &Path)]) -> Arc<Engine> {
    let cfg = Config {
        data_dir: dir.join("data"),
        ingest_roots: vec![dir.to_path_buf()],
        crs: Some("EPSG:4326".into()),
        vertical: patchwork::config::Vertical {
            crs: Some("EPSG:5773".into()),
            geoids: geoids
                .iter()
                .map(|(k, p)| (k.to_string(), p.to_path_buf()))
                .collect::<BTreeMap<_, _>>(),
            // These tests' own grids only, whatever PROJ's directories hold.
            proj_data: false,
        },
        ..Config::default()
    };
    Arc::new(Engine::open(cfg).unwrap())
}

#[test]
fn heights_of_another_geoid_are_converted_and_agree_and_unconverted_ones_conflict() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let (g96, g08) = (dir.join("egm96.tif"), dir.join("egm08.tif"));
    geoid(&g96, n96);
    geoid(&g08, n08);
    // The geographic crop in EGM96 heights, and the UTM crop of the same ground carried to
    // EGM2008: H08 = H96 + N96 − N08, some 35 m apart.
    let a = copy(
        dir,
        "ventoux_geographic.tif",
        Some("EPSG:5773"),
        |z, _, _| z,
    );
    let b = copy(
        dir,
        "ventoux_utm31.tif",
        Some("EPSG:3855"),
        |z, lon, lat| z + n96(lon, lat) - n08(lon, lat),
    );
    let e = engine(dir, &[("EPSG:5773", &g96), ("EPSG:3855", &g08)]);
    for f in [&a, &b] {
        let done = e.ingest(f, None, Origin::Request).unwrap();
        assert_eq!(done.outcome, Outcome::Inserted, "{}", done.error);
        // Carried back exactly: the two agree as the originals do. The UTM crop is a
        // resampling of the other's ground, which the overlap finds (it is the distrusted
        // one), but not a height apart: once aligned, under half a metre.
        for c in &done.conflicts {
            assert_eq!(c.distrusted, patchwork::engine::Distrusted::This, "{c:?}");
            assert!(c.shift_m.is_some_and(|s| s[2].abs() < 0.5), "{c:?}");
        }
    }
    let (_, listing) = e.surveys();
    let rb = listing
        .records
        .iter()
        .find(|r| r.source.ends_with("utm31_copy.tif"))
        .unwrap();
    assert_eq!(
        rb.vertical_source.as_ref().map(|v| v.key()),
        Some("EPSG:3855")
    );
    assert_eq!(rb.vertical.as_ref().map(|v| v.key()), Some("EPSG:5773"));
    // Both grids are planes: bilinear interpolation reproduces them, and adds nothing but
    // the rounding of their f32 nodes.
    assert!(rb.vertical_error_m < 1e-5, "{}", rb.vertical_error_m);
    assert!(listing
        .conflicts
        .values()
        .flatten()
        .all(|c| c.shift_m.is_some_and(|s| s[2].abs() < 0.5)));
    // The converted heights are the original's: a sample of the UTM crop comes back as
    // it was before it went to EGM2008, to f32 rounding.
    let orig = read_raster(&crop("ventoux_utm31.tif"), &ReadLimits::default()).unwrap();
    let back = e.snapshot();
    let s = back.survey(rb.id).unwrap();
    let w = back.window(s, 0, s.shapes[0].all()).unwrap();
    let worst = w
        .grid
        .samples
        .iter()
        .zip(&orig.samples)
        .filter(|(_, o)| !o.is_nan())
        .map(|(a, o)| (a - o).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 2e-4, "{worst} m from the original heights");

    // The same file with no sidecar is taken to be in the store's heights: 35 m off, and
    // listed as a conflict that says so.
    let tmp2 = tempfile::tempdir().unwrap();
    let dir2 = tmp2.path();
    let a2 = copy(
        dir2,
        "ventoux_geographic.tif",
        Some("EPSG:5773"),
        |z, _, _| z,
    );
    let b2 = copy(dir2, "ventoux_utm31.tif", None, |z, lon, lat| {
        z + n96(lon, lat) - n08(lon, lat)
    });
    let e2 = engine(dir2, &[]);
    e2.ingest(&a2, None, Origin::Request).unwrap();
    let done = e2.ingest(&b2, None, Origin::Request).unwrap();
    assert_eq!(done.outcome, Outcome::Inserted, "{}", done.error);
    let c = done.conflicts.first().expect("a conflict");
    assert!(c.max_m > 30.0 && c.rms_m > 30.0, "{c:?}");
    let (_, listing) = e2.surveys();
    let rb = listing
        .records
        .iter()
        .find(|r| r.source.ends_with("utm31_copy.tif"))
        .unwrap();
    assert!(rb.vertical_source.is_none());
}

#[test]
fn without_the_geoid_grid_it_needs_a_survey_is_refused_naming_both_crss_and_the_key() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let g96 = dir.join("egm96.tif");
    geoid(&g96, n96);
    let b = copy(dir, "ventoux_utm31.tif", Some("EPSG:3855"), |z, _, _| z);
    let e = engine(dir, &[("EPSG:5773", &g96)]);
    let done = e.ingest(&b, None, Origin::Request).unwrap();
    assert_eq!(done.outcome, Outcome::Failed);
    assert_eq!(done.reason, Some(patchwork::engine::Reason::Geoid));
    for needle in [
        "EPSG:3855",
        "EPSG:5773",
        "[vertical.geoids]",
        "\"EPSG:3855\"",
    ] {
        assert!(
            done.error.contains(needle),
            "{needle:?} not in {:?}",
            done.error
        );
    }
    // Heights above the ellipsoid need only the store's geoid: h = H96 + N96.
    let c = copy(
        dir,
        "ventoux_geographic.tif",
        Some("ellipsoidal"),
        |z, lon, lat| z + n96(lon, lat),
    );
    let done = e.ingest(&c, None, Origin::Request).unwrap();
    assert_eq!(done.outcome, Outcome::Inserted, "{}", done.error);
    let t = e.snapshot();
    let id = done.survey.unwrap();
    let s = t.survey(id).unwrap();
    let w = t.window(s, 0, s.shapes[0].all()).unwrap();
    let orig = read_raster(&crop("ventoux_geographic.tif"), &ReadLimits::default()).unwrap();
    let worst = w
        .grid
        .samples
        .iter()
        .zip(&orig.samples)
        .map(|(a, o)| (a - o).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 2e-4, "{worst} m from the EGM96 heights");
}

#[test]
fn a_geoid_that_bends_between_its_nodes_adds_its_interpolation_error_to_the_accuracy() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let (g96, g08) = (dir.join("egm96.tif"), dir.join("egm08.tif"));
    geoid(&g96, n96);
    // Undulations a few metres high, a few nodes long.
    let wavy = |lon: f64, lat: f64| n08(lon, lat) + 4.0 * (lon * 40.0).sin() * (lat * 30.0).cos();
    geoid(&g08, wavy);
    let b = copy(dir, "ventoux_utm31.tif", Some("EPSG:3855"), |z, _, _| z);
    std::fs::write(
        format!("{}.toml", b.display()),
        "vertical_crs = \"EPSG:3855\"\naccuracy_m = 2.0\n",
    )
    .unwrap();
    let e = engine(dir, &[("EPSG:5773", &g96), ("EPSG:3855", &g08)]);
    let done = e.ingest(&b, None, Origin::Request).unwrap();
    assert_eq!(done.outcome, Outcome::Inserted, "{}", done.error);
    let (_, listing) = e.surveys();
    let r = &listing.records[0];
    // Each undulation's second difference over one node: up to 4·(2·0.05·40)²/8 ≈ 8 m
    // between the crests, well above nothing.
    assert!(r.vertical_error_m > 0.1, "{}", r.vertical_error_m);
    assert!(
        (r.accuracy - (2.0 + r.vertical_error_m)).abs() < 1e-9,
        "ε {} for 2 m and {} m of geoid",
        r.accuracy,
        r.vertical_error_m
    );
}

/// The grid of [`geoid`] as a GTX file, the format of the geoid grids PROJ ships
/// (`egm96_15.gtx` in Debian's `proj-data`): a big-endian header, then the nodes from the
/// southernmost row.
fn geoid_gtx(path: &Path, n: impl Fn(f64, f64) -> f64) {
    let (lon0, lat0, step, size) = (4.5f64, 43.5f64, 0.05f64, 41i32);
    let mut b = Vec::new();
    for x in [lat0, lon0, step, step] {
        b.extend_from_slice(&x.to_be_bytes());
    }
    b.extend_from_slice(&size.to_be_bytes());
    b.extend_from_slice(&size.to_be_bytes());
    for r in 0..size {
        for c in 0..size {
            let z = n(lon0 + c as f64 * step, lat0 + r as f64 * step) as f32;
            b.extend_from_slice(&z.to_be_bytes());
        }
    }
    std::fs::write(path, b).unwrap();
}

#[test]
fn a_gtx_geoid_grid_converts_heights_as_the_same_grid_in_geotiff_does() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let (tif, gtx) = (dir.join("egm08.tif"), dir.join("egm08.gtx"));
    geoid(&tif, n08);
    geoid_gtx(&gtx, n08);
    let b = copy(
        dir,
        "ventoux_utm31.tif",
        Some("EPSG:3855"),
        |z, lon, lat| z + n96(lon, lat) - n08(lon, lat),
    );
    let g96 = dir.join("egm96.tif");
    geoid(&g96, n96);
    let heights = |grid: &Path, name: &str| {
        let sub = dir.join(name);
        std::fs::create_dir_all(&sub).unwrap();
        // The survey and its sidecar inside this engine's ingest root.
        let file = sub.join("b.tif");
        std::fs::copy(&b, &file).unwrap();
        std::fs::copy(
            format!("{}.toml", b.display()),
            format!("{}.toml", file.display()),
        )
        .unwrap();
        let e = engine(&sub, &[("EPSG:5773", &g96), ("EPSG:3855", grid)]);
        let done = e.ingest(&file, None, Origin::Request).unwrap();
        assert_eq!(done.outcome, Outcome::Inserted, "{name}: {}", done.error);
        // Points around the middle of the crop, in the store's longitude and latitude.
        let r = read_raster(&b, &ReadLimits::default()).unwrap();
        let to_geo = Transform::new(r.crs.crs.as_ref().unwrap(), &Crs::wgs84()).unwrap();
        let (x, y) = r.pixel_centre(r.cols / 2, r.rows / 2);
        let c = to_geo.apply([x, y]).unwrap();
        let pts: Vec<[f64; 2]> = (0..400)
            .map(|k| {
                let (i, j) = ((k % 20) as f64 / 20.0 - 0.5, (k / 20) as f64 / 20.0 - 0.5);
                [c[0] + i * 0.02, c[1] + j * 0.02]
            })
            .collect();
        let req = SampleRequest::new(pts, None, 0.0).unwrap();
        let (_, listing) = e.surveys();
        (
            e.sample(&req, Ctx::default()).unwrap().heights,
            listing.records[0].accuracy,
        )
    };
    let (from_tif, eps_tif) = heights(&tif, "tif");
    let (from_gtx, eps_gtx) = heights(&gtx, "gtx");
    assert!(from_tif.iter().filter(|z| !z.is_nan()).count() > 300);
    for (a, b) in from_tif.iter().zip(&from_gtx) {
        assert_eq!(
            a.to_bits(),
            b.to_bits(),
            "the GTX grid converts as the GeoTIFF one"
        );
    }
    assert_eq!(eps_tif, eps_gtx);
}

#[test]
fn a_geoid_grid_that_cannot_be_used_stops_the_start_naming_it() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let bad = dir.join("egm96_15.gtx");
    std::fs::write(&bad, [0u8; 64]).unwrap();
    let cfg = Config {
        data_dir: dir.join("data"),
        vertical: patchwork::config::Vertical {
            crs: Some("EPSG:5773".into()),
            geoids: [("EPSG:5773".to_string(), bad.clone())]
                .into_iter()
                .collect(),
            proj_data: false,
        },
        ..Config::default()
    };
    let err = Engine::open(cfg).err().expect("refused at start");
    assert_eq!(err.reason(), patchwork::engine::Reason::Geoid, "{err}");
    assert!(err.to_string().contains("egm96_15.gtx"), "{err}");
}

/// A store in EGM96 heights holding the geographic crop, with the EGM96 grid `n` and the
/// EGM2008 plane, and points over the crop in longitude and latitude.
fn ventoux_in_egm96(dir: &Path, n: fn(f64, f64) -> f64) -> (Arc<Engine>, Vec<[f64; 2]>) {
    let (g96, g08) = (dir.join("egm96.tif"), dir.join("egm08.tif"));
    geoid(&g96, n);
    geoid(&g08, n08);
    let a = copy(
        dir,
        "ventoux_geographic.tif",
        Some("EPSG:5773"),
        |z, _, _| z,
    );
    let e = engine(dir, &[("EPSG:5773", &g96), ("EPSG:3855", &g08)]);
    let done = e.ingest(&a, None, Origin::Request).unwrap();
    assert_eq!(done.outcome, Outcome::Inserted, "{}", done.error);
    let r = read_raster(&a, &ReadLimits::default()).unwrap();
    let (x, y) = r.pixel_centre(r.cols / 2, r.rows / 2);
    let pts = (0..400)
        .map(|k| {
            let (i, j) = ((k % 20) as f64 - 10.0, (k / 20) as f64 - 10.0);
            [x + i * 0.003, y + j * 0.003]
        })
        .collect();
    (e, pts)
}

#[test]
fn heights_are_given_above_the_ellipsoid_or_another_geoid_as_asked() {
    let tmp = tempfile::tempdir().unwrap();
    let (e, pts) = ventoux_in_egm96(tmp.path(), n96);
    let at = |h: Heights| {
        let req = SampleRequest::new(pts.clone(), None, 0.0)
            .unwrap()
            .with_heights(h);
        e.sample(&req, Ctx::default()).unwrap()
    };
    let store = at(Heights::Store);
    assert_eq!(
        store.frame.vertical.as_ref().map(|v| v.key()),
        Some("EPSG:5773")
    );
    assert_eq!(store.frame.error_m, 0.0);
    let ell = at(Heights::ellipsoid());
    let h08 = at(Heights::parse("EPSG:3855").unwrap());
    assert_eq!(
        ell.frame.vertical.as_ref().map(|v| v.key()),
        Some("ellipsoidal")
    );
    // Planes: bilinear interpolation reproduces them, so the conversion adds only the
    // rounding of the grids' f32 nodes.
    assert!(ell.frame.error_m < 1e-5, "{}", ell.frame.error_m);
    let mut seen = 0;
    for (k, p) in pts.iter().enumerate() {
        let (s, el, e8) = (store.heights[k], ell.heights[k], h08.heights[k]);
        if s.is_nan() {
            assert!(el.is_nan() && e8.is_nan());
            continue;
        }
        seen += 1;
        // h = H96 + N96; H08 = H96 + N96 − N08.
        let n = n96(p[0], p[1]);
        assert!(
            ((el - s) as f64 - n).abs() < 1e-3,
            "point {k}: {el} − {s} ≠ {n}"
        );
        let d = n - n08(p[0], p[1]);
        assert!(((e8 - s) as f64 - d).abs() < 1e-3, "point {k}");
    }
    assert!(seen > 300, "{seen} points with data");

    // A tile and a mesh carry the same heights: each sample is the store's plus N there.
    let roi = Aabb::new(
        pts[0][0],
        pts[0][1],
        pts[pts.len() - 1][0],
        pts[pts.len() - 1][1],
    );
    let cut = Cut::new(None, roi, 0.0).unwrap();
    let (w, h) = (40usize, 30usize);
    let tile = |hs: Heights| {
        let req = TileRequest::new(cut.clone(), w as u32, h as u32, Backend::Cpu)
            .unwrap()
            .with_heights(hs);
        e.tile(&req, Ctx::default()).unwrap()
    };
    let (ts, _, _) = tile(Heights::Store);
    let (te, _, frame) = tile(Heights::ellipsoid());
    assert_eq!(
        frame.vertical.as_ref().map(|v| v.key()),
        Some("ellipsoidal")
    );
    let grid = patchwork_core::resample::SampleGrid::uniform(&roi, w, h);
    let mut checked = 0;
    for (k, p) in grid.points().enumerate() {
        if ts.heights[k].is_nan() {
            continue;
        }
        checked += 1;
        let d = (te.heights[k] - ts.heights[k]) as f64 - n96(p[0], p[1]);
        assert!(d.abs() < 1e-3, "tile sample {k}: {d}");
    }
    assert!(checked > w * h / 2, "{checked}");
    let mesh = |hs: Heights| {
        let spec = MeshSpec {
            roi: Region::new(roi).unwrap(),
            error: Metres::ZERO,
            cols: 33,
            rows: 33,
            mesh_error: Metres::new("mesh_error", 0.5).unwrap(),
            skirt_m: Metres::ZERO,
            border: patchwork_core::mesh::Border::Shared,
            method: patchwork_core::mesh::Method::Rtin,
            hole_reach_m: Metres::ZERO,
            crs: None,
            fill_voids: true,
            heights: hs,
            rim: false,
        };
        e.mesh(&spec, Backend::Cpu, Ctx::default()).unwrap()
    };
    let (ms, me) = (mesh(Heights::Store), mesh(Heights::ellipsoid()));
    assert_eq!(
        me.frame.vertical.as_ref().map(|v| v.key()),
        Some("ellipsoidal")
    );
    let at_store: std::collections::HashMap<[u32; 2], f32> = ms
        .mesh
        .grid
        .iter()
        .zip(&ms.mesh.heights)
        .map(|(g, z)| (*g, *z))
        .collect();
    let mut shared = 0;
    for (g, z) in me.mesh.grid.iter().zip(&me.mesh.heights) {
        let Some(s) = at_store.get(g) else { continue };
        shared += 1;
        let lon = roi.min[0] + g[0] as f64 * roi.width() / 32.0;
        let lat = roi.max[1] - g[1] as f64 * roi.height() / 32.0;
        let d = (z - s) as f64 - n96(lon, lat);
        assert!(d.abs() < 1e-3, "vertex {g:?}: {d}");
    }
    // Adding a plane changes no triangle's error: the two meshes share their vertices.
    assert!(shared * 10 >= me.mesh.grid.len() * 9, "{shared}");
}

#[test]
fn a_bending_geoid_counts_its_interpolation_error_in_the_heights_frame() {
    let tmp = tempfile::tempdir().unwrap();
    // Curved between nodes 0.05° apart: bilinear interpolation misses some of it.
    let bent =
        |lon: f64, lat: f64| 47.0 + 300.0 * (lon - 5.0).powi(2) + 200.0 * (lat - 44.0).powi(2);
    let (e, pts) = ventoux_in_egm96(tmp.path(), bent);
    let req = SampleRequest::new(pts, None, 0.0)
        .unwrap()
        .with_heights(Heights::ellipsoid());
    let s = e.sample(&req, Ctx::default()).unwrap();
    // An eighth of the second differences, 300·0.05² and 200·0.05² m, along each axis.
    let expected = (2.0 * 300.0 + 2.0 * 200.0) * 0.05f64.powi(2) / 8.0;
    assert!(
        (s.frame.error_m - expected).abs() < 1e-3,
        "{} against {expected}",
        s.frame.error_m
    );
}

#[test]
fn without_a_grid_or_a_vertical_crs_heights_stay_in_the_stores_frame_and_say_why() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let a = copy(
        dir,
        "ventoux_geographic.tif",
        Some("EPSG:5773"),
        |z, _, _| z,
    );
    let e = engine(dir, &[]);
    e.ingest(&a, None, Origin::Request).unwrap();
    let req = SampleRequest::new(vec![[5.27, 44.17]], None, 0.0)
        .unwrap()
        .with_heights(Heights::ellipsoid());
    let err = e.sample(&req, Ctx::default()).unwrap_err();
    assert_eq!(err.reason(), Reason::Geoid, "{err}");
    assert!(
        matches!(&err, EngineError::Heights(HeightsError::NoGrid { key, .. }) if key == "EPSG:5773"),
        "{err:?}"
    );
    assert!(err.to_string().contains("[vertical.geoids]"), "{err}");
    assert!(e.can_give(&Heights::Store).is_ok());

    // A store whose surveys name no vertical CRS: nothing says what its heights are from.
    let tmp2 = tempfile::tempdir().unwrap();
    let dir2 = tmp2.path();
    let b = copy(dir2, "ventoux_geographic.tif", None, |z, _, _| z);
    let cfg = Config {
        data_dir: dir2.join("data"),
        ingest_roots: vec![dir2.to_path_buf()],
        crs: Some("EPSG:4326".into()),
        ..Config::default()
    };
    let e2 = Engine::open(cfg).unwrap();
    e2.ingest(&b, None, Origin::Request).unwrap();
    let err = e2.can_give(&Heights::ellipsoid()).unwrap_err();
    assert!(
        matches!(err, EngineError::Heights(HeightsError::Unknown { .. })),
        "{err:?}"
    );
    let s = e2
        .sample(
            &SampleRequest::new(vec![[5.27, 44.17]], None, 0.0).unwrap(),
            Ctx::default(),
        )
        .unwrap();
    assert_eq!(s.frame.vertical, None);
}
