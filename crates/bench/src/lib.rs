//! `patchwork-bench`: speed beside accuracy, on real surveys, with GDAL on the same tiles.
//!
//! Ingests the surveys into a temporary store, then measures uniform cuts over three ROIs at
//! a range of errors (query time, patches, bytes on the wire, resample time, samples, and the
//! measured error of each tile against the surveys' own surfaces), view-dependent cuts along a
//! flight path, ingest throughput and store size. Writes CSV and charts, and the tiles GDAL
//! is compared on.

pub mod blend;
pub mod charts;
pub use patchwork_testkit::copies;
pub mod crs;
pub mod draws;
pub mod evidence;
pub mod flight;
pub mod many;
pub mod meet;
pub mod meshes;
pub mod stability;
pub mod variants;
pub mod wavelet;

use patchwork_core::geom::Aabb;
use patchwork_core::index::query::{Metric, ViewQuery};
use patchwork_core::model::grid::Grid;
use patchwork_core::resample::SampleGrid;
use patchwork_core::terrain::Terrain;
use patchwork_engine::config::Config;
use patchwork_engine::{Cut, Engine};
use patchwork_read::write_npy;
use patchwork_server::convert;
use prost::Message;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// An error of the bench, said to whoever runs it.
pub type Fail = Box<dyn std::error::Error>;

/// Errors, in metres, the uniform cuts are asked at (three of them in a smoke run).
pub const ERRORS: [f64; 9] = [0.0, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0];
/// Screen errors, in pixels, the view-dependent cuts are asked at.
pub const PIXEL_ERRORS: [f64; 4] = [0.5, 1.0, 2.0, 4.0];

/// What the bench runs on, where it writes, and how long it takes.
#[derive(Clone, Debug)]
pub struct Options {
    /// The surveys to ingest.
    pub files: Vec<PathBuf>,
    /// Where the CSV, charts and tiles go.
    pub out: PathBuf,
    /// A few seconds' worth: small tiles, one repeat, fewer errors.
    pub smoke: bool,
}

/// One uniform cut over one ROI at one error, and the tile resampled from it.
#[derive(Clone, Debug)]
pub struct UniformRow {
    /// The ROI: `small`, `medium` or `large`, a square about the largest survey's centre.
    pub roi: &'static str,
    /// The requested error e, metres.
    pub error: f64,
    /// Median time of the cut's query, milliseconds.
    pub query_ms: f64,
    /// Patches the cut returns.
    pub patches: usize,
    /// The cut's patches as encoded on the wire, bytes.
    pub wire_bytes: usize,
    /// The tile's side, samples.
    pub tile: usize,
    /// Median time of resampling the patches into the tile, milliseconds.
    pub resample_ms: f64,
    /// The tile's samples with a height.
    pub samples: usize,
    /// Largest distance of the tile's heights outside the reference range, metres.
    pub max_err: f64,
    /// RMS distance of the tile's heights outside the reference range, metres.
    pub rms_err: f64,
    /// Samples more than e (and 1 mm) outside the reference range.
    pub over: usize,
}

/// View-dependent cuts along a flight at one screen error.
#[derive(Clone, Debug)]
pub struct ViewRow {
    /// The screen error asked for, pixels.
    pub pixel_error: f64,
    /// Median query time over the flight's stops, milliseconds.
    pub query_ms: f64,
    /// Patches per view, the mean over the flight's stops.
    pub patches: f64,
}

/// The ingest of one file.
#[derive(Clone, Debug)]
pub struct IngestRow {
    /// The file's name.
    pub file: String,
    /// Samples ingested.
    pub samples: u64,
    /// Time the ingest took, seconds.
    pub seconds: f64,
    /// The file's size, bytes.
    pub input_bytes: u64,
}

/// Everything the bench measures, as [`run`] returns it.
pub struct Report {
    /// Uniform cuts over the three ROIs (`uniform.csv`).
    pub uniform: Vec<UniformRow>,
    /// Frames of the view-session flights (`view_session.csv`).
    pub flight: Vec<flight::FlightRow>,
    /// The recipes side by side (`variants.csv`).
    pub variants: Vec<variants::VariantRow>,
    /// View-dependent cuts at each screen error (`view.csv`).
    pub view: Vec<ViewRow>,
    /// The ingest of each file (`ingest.csv`).
    pub ingest: Vec<IngestRow>,
    /// The store's size on disk once every file is in, bytes.
    pub disk_bytes: u64,
    /// Where surveys meet, and the estimator's check (`mixed.csv`, `estimator.csv`).
    pub scenes: meet::Scenes,
    /// Where methods break (`stability.csv`).
    pub stability: Vec<stability::StabilityRow>,
    /// Surveys of two CRSs in one store (`crs_*.csv`).
    pub across: crs::Report,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn timed<T>(repeats: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut times = Vec::with_capacity(repeats);
    let mut last = None;
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        last = Some(f());
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    (median(times), last.expect("ran once"))
}

/// Per sample, the lowest and highest height of the surveys with data there: the point
/// reference. With one survey both are its bilinear surface; where surveys overlap, the bound
/// holds against the range they span.
pub fn reference(t: &Terrain, grid: &SampleGrid) -> (Vec<f32>, Vec<f32>) {
    let bounds = patchwork_core::geom::Aabb::of_points(&grid.points().collect::<Vec<_>>());
    // Each survey's level 0 where the grid is: the whole of it would not fit a large store.
    let surveys: Vec<Grid> = t
        .surveys()
        .filter_map(|s| {
            let rect = s.shapes[0].rect_over(&bounds)?;
            Some(t.samples(s, 0, rect).expect("samples readable"))
        })
        .collect();
    grid.points()
        .map(|p| {
            let hs = surveys.iter().filter_map(|g| g.bilinear(p));
            let (lo, hi) = hs.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), h| {
                (a.min(h), b.max(h))
            });
            if lo.is_finite() {
                (lo as f32, hi as f32)
            } else {
                (f32::NAN, f32::NAN)
            }
        })
        .unzip()
}

/// Distance of each valid height outside the reference range.
pub fn errors(heights: &[f32], lo: &[f32], hi: &[f32]) -> Vec<f64> {
    heights
        .iter()
        .zip(lo.iter().zip(hi))
        .filter(|(h, (l, _))| !h.is_nan() && !l.is_nan())
        .map(|(h, (l, u))| ((*l - *h).max(*h - *u).max(0.0)) as f64)
        .collect()
}

fn square(c: [f64; 2], half: f64) -> Aabb {
    Aabb::new(c[0] - half, c[1] - half, c[0] + half, c[1] + half)
}

/// The mesh triangulations alone (`rtin.csv`): the part of the bench `--meshes-only` runs.
pub fn run_meshes(opts: &Options) -> Result<(), Fail> {
    std::fs::create_dir_all(&opts.out)?;
    let meshes = meshes::run(&opts.files, if opts.smoke { 129 } else { 2049 })?;
    meshes::write_csv(&opts.out, &meshes)?;
    Ok(())
}

/// The whole bench: measures every part and writes its CSV, charts and tiles under `opts.out`.
pub fn run(opts: &Options) -> Result<Report, Fail> {
    std::fs::create_dir_all(opts.out.join("tiles"))?;
    let Store {
        _dir,
        engine,
        ingest,
        first,
        first_survey,
    } = store_of(opts)?;
    let disk_bytes = engine.stats().disk_bytes;
    let t = engine.snapshot();
    let c = [
        (first.min[0] + first.max[0]) / 2.0,
        (first.min[1] + first.max[1]) / 2.0,
    ];
    let span = first.width().min(first.height());
    let rois = [
        ("small", square(c, span / 50.0)),
        ("medium", square(c, span / 10.0)),
        ("large", square(c, span / 2.0)),
    ];
    let (repeats, tile_side) = if opts.smoke { (1, 64) } else { (5, 512) };
    let errors_used: Vec<f64> = if opts.smoke {
        vec![0.0, 5.0, 50.0]
    } else {
        ERRORS.to_vec()
    };

    let mut uniform = Vec::new();
    let mut manifest = Vec::new();
    for (name, roi) in &rois {
        let grid = SampleGrid::uniform(roi, tile_side, tile_side);
        let (lo, hi) = reference(&t, &grid);
        for &e in &errors_used {
            let cut = Cut::new(None, *roi, e)?;
            let (query_ms, (_, ps)) = timed(repeats, || engine.query(&cut).expect("query"));
            let wire_bytes = ps
                .iter()
                .filter_map(|x| convert::patch(&t, x).expect("samples readable"))
                .map(|p| p.encoded_len())
                .sum();
            let (resample_ms, tile) = timed(repeats.min(3), || t.resample(ps.clone(), &grid));
            let errs = errors(&tile.heights, &lo, &hi);
            let over = errs.iter().filter(|&&d| d > e + 1e-3).count();
            let row = UniformRow {
                roi: name,
                error: e,
                query_ms,
                patches: ps.len(),
                wire_bytes,
                tile: tile_side,
                resample_ms,
                samples: tile.heights.iter().filter(|z| !z.is_nan()).count(),
                max_err: errs.iter().cloned().fold(0.0, f64::max),
                rms_err: (errs.iter().map(|d| d * d).sum::<f64>() / errs.len().max(1) as f64)
                    .sqrt(),
                over,
            };
            println!(
                "{name:>6} e = {e:>5} m: query {query_ms:.3} ms, {} patches, {} bytes, resample {resample_ms:.2} ms, max error {:.3} m, RMS {:.3} m, {over} over e",
                row.patches, row.wire_bytes, row.max_err, row.rms_err
            );
            uniform.push(row);
        }
        // The tiles GDAL is compared on: the medium ROI, two sizes, three errors.
        if *name == "medium" {
            let sizes: &[usize] = if opts.smoke { &[64] } else { &[512, 1024] };
            for &n in sizes {
                let grid = SampleGrid::uniform(roi, n, n);
                let (lo, hi) = reference(&t, &grid);
                let stem = format!("medium_{n}");
                write_npy(&opts.out.join(format!("tiles/{stem}_lo.npy")), n, n, &lo)?;
                write_npy(&opts.out.join(format!("tiles/{stem}_hi.npy")), n, n, &hi)?;
                for e in [0.0, 5.0, 20.0] {
                    let cut = Cut::new(None, *roi, e)?;
                    let (ms, tile) = timed(repeats.min(3), || {
                        let (_, ps) = engine.query(&cut).expect("query");
                        t.resample(ps, &grid)
                    });
                    let file = format!("{stem}_e{e}.npy");
                    write_npy(&opts.out.join("tiles").join(&file), n, n, &tile.heights)?;
                    manifest.push(ManifestTile {
                        crs: None,
                        sources: None,
                        size: n,
                        error: e,
                        ours: file,
                        ours_ms: ms,
                        lo: format!("{stem}_lo.npy"),
                        hi: format!("{stem}_hi.npy"),
                        roi: [roi.min[0], roi.min[1], roi.max[0], roi.max[1]],
                    });
                }
            }
        }
    }
    let crs = engine.crs();
    write_manifest(
        &opts.out.join("tiles/manifest.json"),
        crs.as_ref().map_or(String::new(), |c| c.key().to_string()),
        &opts.files,
        manifest,
    )?;
    // Surveys of two CRSs in one store, and tiles in a third.
    let across = run_crs(opts)?;

    // A flight along the survey's diagonal, 1,500 m up, looking ahead.
    let metric = match engine.crs() {
        Some(c) if c.is_geographic() => Metric::geographic(c_lat(&first)),
        _ => Metric::PROJECTED,
    };
    let stops = if opts.smoke { 2 } else { 8 };
    let mut view = Vec::new();
    for &px in &PIXEL_ERRORS {
        let (mut times, mut counts) = (Vec::new(), Vec::new());
        for k in 0..stops {
            let f = 0.1 + 0.5 * k as f64 / stops as f64;
            let at = |g: f64| {
                [
                    first.min[0] + g * first.width(),
                    first.min[1] + g * first.height(),
                ]
            };
            let (e, l) = (at(f), at(f + 0.3));
            let v = ViewQuery {
                eye: [e[0], e[1], 1500.0],
                look: [l[0], l[1], 300.0],
                fov_deg: 60.0,
                viewport_px: 1024,
                pixel_error: px,
                metric,
            };
            let (ms, ps) = timed(repeats, || t.view(&v));
            times.push(ms);
            counts.push(ps.len() as f64);
        }
        let row = ViewRow {
            pixel_error: px,
            query_ms: median(times),
            patches: counts.iter().sum::<f64>() / counts.len() as f64,
        };
        println!(
            "view {px} px: {:.3} ms, {:.0} patches",
            row.query_ms, row.patches
        );
        view.push(row);
    }
    let flight = flight::fly(&engine, &first, if opts.smoke { 12 } else { 200 })?;
    flight::write_csv(&opts.out, &flight)?;
    let prefetch = flight::fly_prefetch(&engine, &first, if opts.smoke { 12 } else { 200 })?;
    flight::write_prefetch_csv(&opts.out, &prefetch)?;
    let variants = variants::run(&opts.files, &errors_used, tile_side)?;
    variants::write_csv(&opts.out, &variants)?;
    run_meshes(opts)?;
    // Where surveys meet, made from the first file's survey (its middle, at most 1,800
    // samples a side, so the scenes take seconds).
    let base = first_survey
        .and_then(|id| t.survey(id))
        .ok_or("no survey was ingested")?;
    let shape = base.shapes[0];
    let side = shape
        .cols
        .min(shape.rows)
        .min(if opts.smoke { 300 } else { 1800 });
    let rect = patchwork_core::model::grid::SampleRect {
        c0: (shape.cols - side) / 2,
        r0: (shape.rows - side) / 2,
        c1: (shape.cols - side) / 2 + side,
        r1: (shape.rows - side) / 2 + side,
    };
    let g = t.samples(base, 0, rect)?;
    let scenes = meet::run(&g, base.crs.clone(), tile_side, &errors_used)?;
    for m in &scenes.mixed {
        println!(
            "{:>6} e = {:>5} m: {} patches ({} of the finer survey), max error {:.3} m, RMS {:.3} m, sub-tiles within {:.2e} m",
            m.scene, m.error, m.patches, m.finer, m.max_err, m.rms_err, m.split_diff
        );
    }
    println!(
        "copies: the finer survey's ε {:.2} m, its 90 m copy's {:.2} m",
        scenes.copies_accuracy.0, scenes.copies_accuracy.1
    );
    for c in &scenes.copies {
        println!(
            "copy by {}: estimated ε {:.2} m, measured {:.2} m max, {:.2} m RMS",
            c.factor, c.estimated, c.measured_max, c.measured_rms
        );
    }
    println!(
        "mosaic of four: {:.2e} m from the whole at e = 0, {} samples open at the seams",
        scenes.mosaic.0, scenes.mosaic.1
    );
    meet::write_csv(&opts.out, &scenes)?;
    // Where methods break: the middle 600² of that crop (its whole, smoke-sized, in a smoke
    // run), 2,000 points a row.
    let s_side = g.cols.min(g.rows).min(600);
    let middle = g.window((g.cols - s_side) / 2, (g.rows - s_side) / 2, s_side, s_side);
    let stability = stability::run(
        &middle,
        base.crs.clone(),
        if opts.smoke { 300 } else { 2000 },
    )?;
    stability::write_csv(&opts.out, &stability)?;
    run_copies(opts)?;
    let report = Report {
        uniform,
        flight,
        variants,
        view,
        ingest,
        disk_bytes,
        scenes,
        stability,
        across,
    };
    write_csv(&opts.out, &report)?;
    charts::draw(&opts.out, &report, &t, &rois[1].1, opts.smoke)?;
    Ok(report)
}

/// A fresh store of the bench's files, as [`store_of`] makes it.
struct Store {
    /// The store's folder, removed when dropped.
    _dir: tempfile::TempDir,
    engine: Engine,
    /// What each ingest took.
    ingest: Vec<IngestRow>,
    /// The bounds of the largest survey: the flights' and the ROIs' ground.
    first: Aabb,
    /// The first file's survey.
    first_survey: Option<patchwork_core::model::ids::SurveyId>,
}

/// A fresh store of the bench's files.
fn store_of(opts: &Options) -> Result<Store, Fail> {
    let tmp = tempfile::tempdir()?;
    let cfg = Config {
        data_dir: tmp.path().join("data"),
        inbox: vec![],
        // The bench names its files itself: wherever they are may be ingested.
        ingest_roots: opts
            .files
            .iter()
            .filter_map(|f| Some(std::path::absolute(f).ok()?.parent()?.to_path_buf()))
            .collect(),
        ..Config::default()
    };
    let engine = Engine::open(cfg)?;
    let mut ingest = Vec::new();
    let mut first_survey = None;
    for f in &opts.files {
        let r = engine.ingest(f, None, patchwork_engine::Origin::Request)?;
        first_survey = first_survey.or(r.survey);
        if r.outcome == patchwork_engine::Outcome::Failed {
            return Err(format!("{}: {}", f.display(), r.error).into());
        }
        println!(
            "ingested {} ({} samples, {:.2} s)",
            f.display(),
            r.samples,
            r.seconds
        );
        ingest.push(IngestRow {
            file: f
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            samples: r.samples,
            seconds: r.seconds,
            input_bytes: std::fs::metadata(f)?.len(),
        });
    }
    let first = engine
        .snapshot()
        .surveys()
        // Ties broken by id: the surveys come in hash order.
        .max_by_key(|s| (s.shapes[0].cols * s.shapes[0].rows, s.id))
        .ok_or("no survey was ingested")?
        .shapes[0]
        .world_bounds();
    Ok(Store {
        _dir: tmp,
        engine,
        ingest,
        first,
        first_survey,
    })
}

/// Only the view sessions' flights: [`flight::fly`] and [`flight::fly_prefetch`] over a store
/// of the bench's files (`patchwork-bench --sessions`).
pub fn run_sessions(opts: &Options) -> Result<(), Fail> {
    std::fs::create_dir_all(&opts.out)?;
    let s = store_of(opts)?;
    let frames = if opts.smoke { 12 } else { 200 };
    flight::write_csv(&opts.out, &flight::fly(&s.engine, &s.first, frames)?)?;
    flight::write_prefetch_csv(
        &opts.out,
        &flight::fly_prefetch(&s.engine, &s.first, frames)?,
    )?;
    Ok(())
}

/// Copies of the surveys beside their originals (`copies.csv`, `coreg.csv`, the `copies`
/// chart): the middle 600² of the first file, with the same ground of the second as a third
/// survey, and the middle 600² of the third file alone (300² and the committed crops in a smoke
/// run).
pub fn run_copies(opts: &Options) -> Result<Vec<evidence::Case>, Fail> {
    std::fs::create_dir_all(&opts.out)?;
    let side = if opts.smoke { 300 } else { 600 };
    type Read = Result<Option<(Grid, Option<patchwork_core::crs::Crs>)>, Fail>;
    let read = |k: usize| -> Read {
        let Some(f) = opts.files.get(k) else {
            return Ok(None);
        };
        let r = patchwork_read::read_raster(f, &Default::default())?;
        let crs = r.crs.crs.clone();
        Ok(Some((r.into_grid()?, crs)))
    };
    let middle = |g: &Grid| {
        let n = g.cols.min(g.rows).min(side);
        g.window((g.cols - n) / 2, (g.rows - n) / 2, n, n)
    };
    let name = |k: usize| {
        opts.files[k]
            .file_name()
            .map_or(String::new(), |n| n.to_string_lossy().to_string())
    };
    let mut scenes = Vec::new();
    let mut crs = None;
    if let Some((g, c)) = read(0)? {
        let orig = middle(&g);
        // The second file over the same ground, where it has it.
        let third = read(1)?.and_then(|(h, _)| {
            let r = h.shape().rect_over(&orig.world_bounds())?;
            Some(h.window(r.c0, r.r0, r.cols(), r.rows()))
        });
        scenes.push((name(0), orig, third));
        crs = c;
    }
    if let Some((g, c)) = read(2)? {
        if c == crs {
            scenes.push((name(2), middle(&g), None));
        }
    }
    let cases = evidence::run(&scenes, crs)?;
    evidence::print(&cases);
    evidence::write_csv(&opts.out, &cases)?;
    charts::copies(&opts.out, &cases)?;
    Ok(cases)
}

/// Surveys of two CRSs in one store (`crs_*.csv`, and `tiles/crs_manifest.json`, the tiles
/// GDAL is compared on): the part of the bench `--crs-only` runs.
pub fn run_crs(opts: &Options) -> Result<crs::Report, Fail> {
    std::fs::create_dir_all(opts.out.join("tiles"))?;
    let mut tiles = Vec::new();
    let report = crs::run(&opts.out, opts.smoke, &mut tiles)?;
    let sources = tiles.first().map(|t| t.sources.clone()).unwrap_or_default();
    let tiles = tiles.into_iter().map(ManifestTile::from).collect();
    write_manifest(
        &opts.out.join("tiles/crs_manifest.json"),
        String::new(),
        &sources,
        tiles,
    )?;
    Ok(report)
}

fn write_manifest(
    path: &Path,
    crs: String,
    sources: &[PathBuf],
    tiles: Vec<ManifestTile>,
) -> std::io::Result<()> {
    let m = Manifest {
        crs,
        sources: sources
            .iter()
            .map(|f| std::path::absolute(f).unwrap_or(f.clone()))
            .collect(),
        tiles,
    };
    std::fs::write(
        path,
        serde_json::to_string_pretty(&m).expect("a manifest serializes"),
    )
}

/// `tiles/manifest.json`: the tiles GDAL is compared on (bench/gdal_compare.py reads it).
#[derive(serde::Serialize)]
struct Manifest {
    crs: String,
    sources: Vec<PathBuf>,
    tiles: Vec<ManifestTile>,
}

#[derive(serde::Serialize)]
struct ManifestTile {
    /// The tile's CRS and sources where they are not the manifest's.
    #[serde(skip_serializing_if = "Option::is_none")]
    crs: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    sources: Option<Vec<PathBuf>>,
    size: usize,
    error: f64,
    /// Our tile and the low and high reference, as .npy files beside the manifest.
    ours: String,
    ours_ms: f64,
    lo: String,
    hi: String,
    roi: [f64; 4],
}

impl From<crs::GdalTile> for ManifestTile {
    fn from(t: crs::GdalTile) -> Self {
        ManifestTile {
            crs: Some(t.crs),
            sources: Some(t.sources),
            size: t.size,
            error: t.error,
            ours: t.ours,
            ours_ms: t.ours_ms,
            lo: t.lo,
            hi: t.hi,
            roi: t.roi,
        }
    }
}

fn c_lat(b: &Aabb) -> f64 {
    (b.min[1] + b.max[1]) / 2.0
}

fn write_csv(out: &Path, r: &Report) -> std::io::Result<()> {
    let mut s = String::from("roi,error_m,query_ms,patches,wire_bytes,tile,resample_ms,samples,max_error_m,rms_error_m,samples_over_error\n");
    for u in &r.uniform {
        let _ = writeln!(
            s,
            "{},{},{:.4},{},{},{},{:.3},{},{:.4},{:.4},{}",
            u.roi,
            u.error,
            u.query_ms,
            u.patches,
            u.wire_bytes,
            u.tile,
            u.resample_ms,
            u.samples,
            u.max_err,
            u.rms_err,
            u.over
        );
    }
    std::fs::write(out.join("uniform.csv"), s)?;
    let mut s = String::from("pixel_error,query_ms,patches\n");
    for v in &r.view {
        let _ = writeln!(s, "{},{:.4},{:.1}", v.pixel_error, v.query_ms, v.patches);
    }
    std::fs::write(out.join("view.csv"), s)?;
    let mut s = String::from("file,samples,seconds,samples_per_s,input_bytes\n");
    for i in &r.ingest {
        let _ = writeln!(
            s,
            "{},{},{:.3},{:.0},{}",
            i.file,
            i.samples,
            i.seconds,
            i.samples as f64 / i.seconds,
            i.input_bytes
        );
    }
    let _ = writeln!(s, "# store size on disk: {} bytes", r.disk_bytes);
    std::fs::write(out.join("ingest.csv"), s)
}
