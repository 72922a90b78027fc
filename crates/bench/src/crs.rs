//! Surveys of two CRSs in one store: what placing a survey in another CRS's plane costs in
//! time and in error, and what a tile in a third CRS costs beside one in the store's.
//!
//! The pair is Mont Ventoux in geographic WGS 84 (SRTM3) and the same ground in UTM 31N.
//! Each is ingested into a store of its own CRS and into one of the other's; its patches'
//! errors are compared level by level with those of its own CRS (what the reprojection adds);
//! the store-to-survey lattice is timed against PROJ's exact transformation on a tile's
//! points; and tiles over the overlap, in the store's CRS, in Web Mercator and in UTM, are
//! timed and measured against the surveys' own bilinear surfaces at each pixel's centre
//! carried into each survey's CRS by the exact transformation.

use super::{errors, median, timed};
use crate::Fail;
use patchwork_core::crs::{Crs, Reprojection, Transform};
use patchwork_core::geom::Aabb;
use patchwork_core::model::accuracy::AccuracySpec;
use patchwork_core::model::place::Planes;
use patchwork_core::model::survey::Survey;
use patchwork_core::resample::SampleGrid;
use patchwork_core::terrain::Terrain;
use patchwork_engine::config::Config;
use patchwork_engine::{Backend, Ctx, Cut, Engine, Origin, TileRequest};
use patchwork_read::{read_raster, write_npy, ReadLimits};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// One file's ingest into a store of one CRS.
#[derive(Clone, Debug)]
pub struct IngestRow {
    /// The file's name.
    pub file: String,
    /// The store's CRS, as its key.
    pub store: String,
    /// Samples ingested.
    pub samples: u64,
    /// Median over the repeats, each into a fresh store.
    pub seconds: f64,
    /// Of which placing the survey in the store's plane (its frames, residuals and the
    /// errors they add): the median of as many runs of that alone; 0 in its own CRS.
    pub place_s: f64,
}

/// What the reprojection adds to one level's patch errors.
#[derive(Clone, Debug)]
pub struct LevelRow {
    /// The file's name.
    pub file: String,
    /// The CRS the survey is placed in, as its key.
    pub store: String,
    /// The mipmap level, 0 the finest.
    pub level: u8,
    /// Patches at the level.
    pub patches: usize,
    /// The patch error in the survey's own CRS: median.
    pub native_median_m: f64,
    /// The error added: median and largest.
    pub added_median_m: f64,
    /// The largest error added, metres.
    pub added_max_m: f64,
    /// The added error's share of the placed patch's error: median and largest.
    pub share_median: f64,
    /// The largest share of the placed patch's error that is added.
    pub share_max: f64,
}

/// The lattice against the exact transformation on one tile's points.
#[derive(Clone, Debug)]
pub struct LatticeRow {
    /// The store's CRS, as its key.
    pub from: String,
    /// The CRS the points are carried into, as its key.
    pub to: String,
    /// Points carried: the tile's samples.
    pub points: usize,
    /// Median time of the lattice, milliseconds.
    pub lattice_ms: f64,
    /// Median time of PROJ's exact transformation, milliseconds.
    pub exact_ms: f64,
    /// The largest distance between the two answers, metres.
    pub max_diff_m: f64,
}

/// One tile over the overlap in one CRS at one error.
#[derive(Clone, Debug)]
pub struct TileRow {
    /// The tile's CRS, as its key.
    pub crs: String,
    /// The requested error e, metres.
    pub error: f64,
    /// The tile's side, samples.
    pub size: usize,
    /// Median time of the tile request, milliseconds.
    pub ms: f64,
    /// Patches the tile is made from.
    pub patches: usize,
    /// The tile's samples with a height.
    pub samples: usize,
    /// Largest distance of the tile's heights outside the reference range, metres.
    pub max_err: f64,
    /// RMS distance of the tile's heights outside the reference range, metres.
    pub rms_err: f64,
    /// Samples more than e (and 1 mm) outside the reference range.
    pub over: usize,
}

/// Everything this part of the bench measures, as [`run`] returns it.
#[derive(Clone, Debug, Default)]
pub struct Report {
    /// Each file into a store of its own CRS and one of the other's (`crs_ingest.csv`).
    pub ingest: Vec<IngestRow>,
    /// What placing each file in the other's plane adds, level by level (`crs_levels.csv`).
    pub levels: Vec<LevelRow>,
    /// The lattice against the exact transformation (`crs_lattice.csv`).
    pub lattice: Vec<LatticeRow>,
    /// Tiles in the store's CRS, in Web Mercator and in UTM (`crs_tiles.csv`).
    pub tiles: Vec<TileRow>,
}

/// A tile GDAL is compared on (`tiles/manifest.json`): in its own CRS, of its own sources.
pub struct GdalTile {
    /// The tile's CRS, as its key.
    pub crs: String,
    /// The surveys it is made from, as absolute paths.
    pub sources: Vec<PathBuf>,
    /// The tile's side, samples.
    pub size: usize,
    /// The requested error e, metres.
    pub error: f64,
    /// Our tile: an .npy file beside the manifest.
    pub ours: String,
    /// Median time of our tile, milliseconds.
    pub ours_ms: f64,
    /// The low reference: an .npy file beside the manifest.
    pub lo: String,
    /// The high reference: an .npy file beside the manifest.
    pub hi: String,
    /// The tile's bounds in its CRS: min x, min y, max x, max y.
    pub roi: [f64; 4],
}

/// The geographic and the UTM file of the pair.
pub fn inputs(smoke: bool) -> [PathBuf; 2] {
    if smoke {
        let d = Path::new("tests/data/real");
        [
            d.join("ventoux_geographic.tif"),
            d.join("ventoux_utm31.tif"),
        ]
    } else {
        let shared = std::env::var_os("PATCHWORK_SHARED_DATA")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("../shared/data"));
        [shared.join("N44E005.hgt"), shared.join("N44E005_UTM.tif")]
    }
}

fn name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

fn engine(dir: &Path, crs: &Crs, files: &[PathBuf]) -> Result<Engine, Fail> {
    let cfg = Config {
        data_dir: dir.join("data"),
        inbox: vec![],
        ingest_roots: files
            .iter()
            .filter_map(|f| Some(std::path::absolute(f).ok()?.parent()?.to_path_buf()))
            .collect(),
        crs: Some(crs.key().to_string()),
        ..Config::default()
    };
    Ok(Engine::open(cfg)?)
}

fn survey(path: &Path) -> Result<Survey, Fail> {
    let r = read_raster(path, &ReadLimits::default())?;
    let crs = r.crs.crs.clone();
    Ok(Survey::build(
        r.into_grid()?,
        AccuracySpec::Auto,
        crs,
        Default::default(),
    )?)
}

fn crs_of(path: &Path) -> Result<Crs, Fail> {
    read_raster(path, &ReadLimits::default())?
        .crs
        .crs
        .ok_or_else(|| format!("{}: no CRS", path.display()).into())
}

/// Per sample of `grid` (in `crs`), the lowest and highest height of the terrain's surveys
/// there: each survey's bilinear surface at the point carried into its own CRS exactly.
fn reference(t: &Terrain, crs: &Crs, grid: &SampleGrid) -> (Vec<f32>, Vec<f32>) {
    let points: Vec<[f64; 2]> = grid.points().collect();
    let mut lo = vec![f32::INFINITY; points.len()];
    let mut hi = vec![f32::NEG_INFINITY; points.len()];
    for s in t.surveys() {
        let own = s.crs.clone().unwrap_or_else(|| crs.clone());
        let to = Transform::new(crs, &own).expect("a transformation between the pair's CRSs");
        let there: Vec<Option<[f64; 2]>> = points.iter().map(|&p| to.apply(p)).collect();
        let inside: Vec<[f64; 2]> = there.iter().flatten().copied().collect();
        if inside.is_empty() {
            continue;
        }
        let Some(rect) = s.shapes[0].rect_over(&Aabb::of_points(&inside)) else {
            continue;
        };
        let g = t.samples(s, 0, rect).expect("samples readable");
        for (k, q) in there.iter().enumerate() {
            if let Some(h) = q.and_then(|q| g.bilinear(q)) {
                lo[k] = lo[k].min(h as f32);
                hi[k] = hi[k].max(h as f32);
            }
        }
    }
    for (l, h) in lo.iter_mut().zip(hi.iter_mut()) {
        if !l.is_finite() {
            (*l, *h) = (f32::NAN, f32::NAN);
        }
    }
    (lo, hi)
}

/// The rectangle of `crs` that bounds `roi` of `from`'s.
fn bounds_in(from: &Crs, crs: &Crs, roi: &Aabb) -> Aabb {
    let t = Transform::new(from, crs).expect("a transformation between the pair's CRSs");
    // The edges, not only the corners: a parallel is curved in a projected CRS.
    let pts: Vec<[f64; 2]> = (0..=16)
        .flat_map(|i| {
            let f = i as f64 / 16.0;
            let x = roi.min[0] + f * roi.width();
            let y = roi.min[1] + f * roi.height();
            [
                [x, roi.min[1]],
                [x, roi.max[1]],
                [roi.min[0], y],
                [roi.max[0], y],
            ]
        })
        .filter_map(|p| t.apply(p))
        .collect();
    Aabb::of_points(&pts)
}

/// Measures the pair, writes `crs_*.csv` and the tiles under `out`, and lists the tiles in `gdal`.
pub fn run(out: &Path, smoke: bool, gdal: &mut Vec<GdalTile>) -> Result<Report, Fail> {
    let files = inputs(smoke);
    let crss = [crs_of(&files[0])?, crs_of(&files[1])?];
    let repeats = if smoke { 1 } else { 3 };
    let mut report = Report::default();

    // 1. Each file into a store of its own CRS and one of the other's.
    for (k, f) in files.iter().enumerate() {
        for store in [&crss[k], &crss[1 - k]] {
            let mut times = Vec::new();
            let mut samples = 0;
            for _ in 0..repeats {
                let tmp = tempfile::tempdir()?;
                let e = engine(tmp.path(), store, std::slice::from_ref(f))?;
                let r = e.ingest(f, None, Origin::Request)?;
                if !r.error.is_empty() {
                    return Err(format!("{}: {}", f.display(), r.error).into());
                }
                times.push(r.seconds);
                samples = r.samples;
            }
            let place_s = if *store == crss[k] {
                0.0
            } else {
                let s = survey(f)?;
                let planes = Planes::new(store.clone());
                let (ms, placed) = timed(repeats, || s.placed(&planes));
                placed?;
                ms / 1e3
            };
            let row = IngestRow {
                file: name(f),
                store: store.key().to_string(),
                samples,
                seconds: median(times),
                place_s,
            };
            println!(
                "crs: {} into a store of {}: {:.3} s, placing it {:.3} s",
                row.file, row.store, row.seconds, row.place_s
            );
            report.ingest.push(row);
        }
    }

    // 2. What placing each in the other's plane adds to its patches' errors.
    for (k, f) in files.iter().enumerate() {
        let native = survey(f)?;
        let placed = native.placed(&Planes::new(crss[1 - k].clone()))?;
        let levels = native.shapes.len();
        for level in 0..levels as u8 {
            let pairs: Vec<(f64, f64)> = native
                .patches
                .iter()
                .zip(placed.patches.iter())
                .filter(|(p, _)| p.level == level)
                .map(|(p, q)| (p.error, q.error))
                .collect();
            if pairs.is_empty() {
                continue;
            }
            let added: Vec<f64> = pairs.iter().map(|(a, b)| b - a).collect();
            let share: Vec<f64> = pairs
                .iter()
                .map(|(a, b)| if *b > 0.0 { (b - a) / b } else { 0.0 })
                .collect();
            let max = |v: &[f64]| v.iter().cloned().fold(0.0, f64::max);
            report.levels.push(LevelRow {
                file: name(f),
                store: crss[1 - k].key().to_string(),
                level,
                patches: pairs.len(),
                native_median_m: median(pairs.iter().map(|p| p.0).collect()),
                added_median_m: median(added.clone()),
                added_max_m: max(&added),
                share_median: median(share.clone()),
                share_max: max(&share),
            });
        }
        let top = report.levels.iter().rev().find(|r| r.file == name(f));
        if let Some(r) = report.levels.iter().find(|r| r.file == name(f)) {
            println!(
                "crs: {} placed in {}: level 0 patch errors {:.3} m, +{:.2e} m median (+{:.2e} max, {:.1e} of the error); level {} +{:.2e} m",
                r.file,
                r.store,
                r.native_median_m,
                r.added_median_m,
                r.added_max_m,
                r.share_max,
                top.map_or(0, |t| t.level),
                top.map_or(0.0, |t| t.added_median_m)
            );
        }
    }

    // 3. Both in a store of the first file's CRS (geographic): the lattice, then tiles.
    let tmp = tempfile::tempdir()?;
    let e = engine(tmp.path(), &crss[0], &files)?;
    for f in &files {
        let r = e.ingest(f, None, Origin::Request)?;
        if !r.error.is_empty() {
            return Err(format!("{}: {}", f.display(), r.error).into());
        }
    }
    let t = e.snapshot();
    let store = crss[0].clone();
    let both = t
        .surveys()
        .map(|s| s.footprint())
        .reduce(|a, b| a.intersection(&b).unwrap_or(a))
        .ok_or("no survey was ingested")?;
    let c = [
        (both.min[0] + both.max[0]) / 2.0,
        (both.min[1] + both.max[1]) / 2.0,
    ];
    let (hw, hh) = (both.width() / 4.0, both.height() / 4.0);
    let roi = Aabb::new(c[0] - hw, c[1] - hh, c[0] + hw, c[1] + hh);
    let size = if smoke { 64 } else { 512 };
    let web = Crs::epsg(3857)?;
    let targets = [store.clone(), web, crss[1].clone()];

    let m_per_unit = |crs: &Crs| {
        if crs.is_geographic() {
            let m = patchwork_core::crs::metres_per_degree(c[1]);
            m[0].min(m[1])
        } else {
            crs.unit_m().unwrap_or(1.0)
        }
    };
    for to in [&crss[1], &targets[1]] {
        let lattice = Reprojection::new(&store, to)?;
        let grid = SampleGrid::uniform(&roi, size, size);
        let points: Vec<[f64; 2]> = grid.points().collect();
        let (lattice_ms, a) = timed(repeats, || lattice.map(&points));
        let exact = Transform::new(&store, to)?;
        let (exact_ms, b) = timed(repeats, || {
            points
                .iter()
                .map(|&p| exact.apply(p).unwrap_or([f64::NAN; 2]))
                .collect::<Vec<_>>()
        });
        let scale = m_per_unit(to);
        let max_diff_m = a
            .iter()
            .zip(&b)
            .map(|(p, q)| (p[0] - q[0]).hypot(p[1] - q[1]) * scale)
            .fold(0.0, f64::max);
        let row = LatticeRow {
            from: store.key().to_string(),
            to: to.key().to_string(),
            points: points.len(),
            lattice_ms,
            exact_ms,
            max_diff_m,
        };
        println!(
            "crs: {} → {} on {} points: lattice {:.2} ms, exact {:.2} ms, {:.1e} m apart",
            row.from, row.to, row.points, row.lattice_ms, row.exact_ms, row.max_diff_m
        );
        report.lattice.push(row);
    }

    let tiles_dir = out.join("tiles");
    for to in &targets {
        let area = if *to == store {
            roi
        } else {
            bounds_in(&store, to, &roi)
        };
        let grid = SampleGrid::uniform(&area, size, size);
        let (lo, hi) = reference(&t, to, &grid);
        let stem = format!("crs_{}", to.key().replace(':', "_"));
        write_npy(&tiles_dir.join(format!("{stem}_lo.npy")), size, size, &lo)?;
        write_npy(&tiles_dir.join(format!("{stem}_hi.npy")), size, size, &hi)?;
        // Below the surveys' ε (about 10 m), and above it where coarser levels serve.
        for err in [0.0, 20.0, 50.0] {
            let cut = if *to == store {
                Cut::new(None, area, err)?
            } else {
                Cut::new(Some(to.clone()), area, err).unwrap()
            };
            let mut times = Vec::new();
            let mut last = None;
            for _ in 0..repeats.max(1) + 2 {
                let t0 = Instant::now();
                last = Some(
                    e.tile(
                        &TileRequest::new(cut.clone(), size as u32, size as u32, Backend::Cpu)?,
                        Ctx::default(),
                    )?
                    .0,
                );
                times.push(t0.elapsed().as_secs_f64() * 1e3);
            }
            let tile = last.expect("ran once");
            let errs = errors(&tile.heights, &lo, &hi);
            let row = TileRow {
                crs: to.key().to_string(),
                error: err,
                size,
                ms: median(times),
                patches: tile.patches.len(),
                samples: tile.heights.iter().filter(|z| !z.is_nan()).count(),
                max_err: errs.iter().cloned().fold(0.0, f64::max),
                rms_err: (errs.iter().map(|d| d * d).sum::<f64>() / errs.len().max(1) as f64)
                    .sqrt(),
                over: errs.iter().filter(|&&d| d > err + 1e-3).count(),
            };
            println!(
                "crs: {size}² tile in {} at e = {err}: {:.2} ms, {} patches, max error {:.3} m, RMS {:.3} m, {} over e",
                row.crs, row.ms, row.patches, row.max_err, row.rms_err, row.over
            );
            let file = format!("{stem}_e{err}.npy");
            write_npy(&tiles_dir.join(&file), size, size, &tile.heights)?;
            gdal.push(GdalTile {
                crs: to.key().to_string(),
                sources: files
                    .iter()
                    .map(|f| std::path::absolute(f).unwrap_or(f.clone()))
                    .collect(),
                size,
                error: err,
                ours: file,
                ours_ms: row.ms,
                lo: format!("{stem}_lo.npy"),
                hi: format!("{stem}_hi.npy"),
                roi: [area.min[0], area.min[1], area.max[0], area.max[1]],
            });
            report.tiles.push(row);
        }
    }
    write_csv(out, &report)?;
    Ok(report)
}

fn write_csv(out: &Path, r: &Report) -> std::io::Result<()> {
    let mut s = String::from("file,store_crs,samples,seconds,place_seconds\n");
    for i in &r.ingest {
        let _ = writeln!(
            s,
            "{},{},{},{:.3},{:.3}",
            i.file, i.store, i.samples, i.seconds, i.place_s
        );
    }
    std::fs::write(out.join("crs_ingest.csv"), s)?;
    let mut s = String::from("file,store_crs,level,patches,native_error_median_m,added_median_m,added_max_m,share_median,share_max\n");
    for l in &r.levels {
        let _ = writeln!(
            s,
            "{},{},{},{},{:.4},{:.3e},{:.3e},{:.3e},{:.3e}",
            l.file,
            l.store,
            l.level,
            l.patches,
            l.native_median_m,
            l.added_median_m,
            l.added_max_m,
            l.share_median,
            l.share_max
        );
    }
    std::fs::write(out.join("crs_levels.csv"), s)?;
    let mut s = String::from("from,to,points,lattice_ms,exact_ms,max_diff_m\n");
    for l in &r.lattice {
        let _ = writeln!(
            s,
            "{},{},{},{:.3},{:.3},{:.3e}",
            l.from, l.to, l.points, l.lattice_ms, l.exact_ms, l.max_diff_m
        );
    }
    std::fs::write(out.join("crs_lattice.csv"), s)?;
    let mut s = String::from(
        "tile_crs,error_m,size,ms,patches,samples,max_error_m,rms_error_m,samples_over_error\n",
    );
    for t in &r.tiles {
        let _ = writeln!(
            s,
            "{},{},{},{:.3},{},{},{:.4},{:.4},{}",
            t.crs, t.error, t.size, t.ms, t.patches, t.samples, t.max_err, t.rms_err, t.over
        );
    }
    std::fs::write(out.join("crs_tiles.csv"), s)
}
