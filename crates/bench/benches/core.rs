//! Core model benches on real data: patch generation, insertion, uniform and view-dependent
//! queries, and CPU resampling, over the full Copernicus + NASADEM N34W119 pair.
//!
//! cargo bench -p patchwork-bench --bench core
//!
//! Each bench prints the patch counts and errors its figures were bought with.
// `criterion_group!` makes a public function of its own, without a doc comment.
#![allow(missing_docs)]

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::index::query::{Metric, ViewQuery};
use patchwork_core::model::grid::Grid;
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::survey::Survey;
use patchwork_core::resample::SampleGrid;
use patchwork_core::terrain::Terrain;
use patchwork_read::{read_raster, ReadLimits};
use std::path::PathBuf;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

fn data(name: &str) -> PathBuf {
    std::env::var_os("PATCHWORK_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data"))
        .join(name)
}

fn grid(name: &str) -> Grid {
    read_raster(&data(name), &ReadLimits::default())
        .unwrap_or_else(|e| panic!("{name}: {e}"))
        .into_grid()
        .unwrap()
}

fn survey(g: Grid) -> Arc<Survey> {
    Arc::new(
        Survey::build(
            g,
            0.0,
            Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
            PatchLayout::default(),
        )
        .unwrap(),
    )
}

struct Pair {
    cop: Arc<Survey>,
    nasa: Arc<Survey>,
    terrain: Terrain,
}

fn pair() -> &'static Pair {
    static P: OnceLock<Pair> = OnceLock::new();
    P.get_or_init(|| {
        let cop = survey(grid("Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif"));
        let nasa = survey(grid("NASADEM_HGT_n34w119.tif"));
        let mut terrain = Terrain::new(IndexConfig::default());
        terrain.insert(cop.clone());
        terrain.insert(nasa.clone());
        let n0 = cop.levels[0].samples.len() as f64;
        println!(
            "mipmap overhead: {:.1}% of level 0",
            100.0 * (cop.stored_samples() as f64 - n0) / n0
        );
        println!(
            "pair: {} + {} patches, {} active boxes, quadtree {:?}",
            cop.patches.len(),
            nasa.patches.len(),
            terrain.index().active_count(),
            terrain.index().tree_stats()
        );
        Pair { cop, nasa, terrain }
    })
}

fn crop(g: &Grid, col: usize, row: usize, n: usize) -> Grid {
    let samples = (row..row + n)
        .flat_map(|r| {
            g.samples[r * g.cols + col..r * g.cols + col + n]
                .iter()
                .copied()
        })
        .collect();
    let georef = patchwork_core::model::grid::Georef {
        origin: g.georef.to_world(col as f64, row as f64),
        ..g.georef
    };
    Grid::new(n, n, samples, georef).unwrap()
}

fn patch_generation(c: &mut Criterion) {
    let full = &pair().cop.levels[0];
    let g = crop(full, 1000, 1000, 1024);
    let mut group = c.benchmark_group("patch_generation");
    group.sample_size(10);
    group.throughput(Throughput::Elements((g.cols * g.rows) as u64));
    group.bench_function("copernicus_1024x1024", |b| {
        b.iter(|| {
            Survey::build(
                g.clone(),
                0.0,
                Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
                PatchLayout::default(),
            )
            .unwrap()
        })
    });
    group.finish();
}

fn insertion(c: &mut Criterion) {
    let p = pair();
    let mut group = c.benchmark_group("insertion");
    group.sample_size(10);
    group.throughput(Throughput::Elements(p.nasa.patches.len() as u64));
    let mut base = Terrain::new(IndexConfig::default());
    base.insert(p.cop.clone());
    group.bench_function("nasadem_over_copernicus", |b| {
        b.iter_batched(
            || base.clone(),
            |mut t| t.insert(p.nasa.clone()),
            criterion::BatchSize::LargeInput,
        )
    });
    // A store that already holds many surveys: 36 tiles of 600 × 600, and one more survey
    // landing across nine of them.
    let full = &p.cop.levels[0];
    let tiles: Vec<Arc<Survey>> = (0..6)
        .flat_map(|j| (0..6).map(move |i| (i, j)))
        .map(|(i, j)| survey(crop(full, i * 600, j * 600, 601.min(3600 - i.max(j) * 600))))
        .collect();
    let mut many = Terrain::new(IndexConfig::default());
    for t in &tiles {
        many.insert(t.clone());
    }
    let newcomer = survey(crop(&p.nasa.levels[0], 1500, 1500, 1200));
    println!(
        "many: {} surveys, {} boxes; newcomer {} patches",
        tiles.len(),
        many.index().len(),
        newcomer.patches.len()
    );
    group.throughput(Throughput::Elements(newcomer.patches.len() as u64));
    group.bench_function("one_survey_into_36", |b| {
        b.iter_batched(
            || many.clone(),
            |mut t| t.insert(newcomer.clone()),
            criterion::BatchSize::LargeInput,
        )
    });
    group.finish();
}

/// A quarter-degree square in the cell's middle (about 23 × 28 km) and the whole cell.
fn rois() -> [(&'static str, Aabb); 2] {
    [
        (
            "quarter_degree",
            Aabb::new(-118.625, 34.375, -118.375, 34.625),
        ),
        ("whole_cell", Aabb::new(-119.0, 34.0, -118.0, 35.0)),
    ]
}

fn uniform_queries(c: &mut Criterion) {
    let t = &pair().terrain;
    let mut group = c.benchmark_group("uniform_query");
    for (name, roi) in rois() {
        for e in [0.0, 5.0, 20.0, 50.0] {
            println!(
                "uniform {name} e = {e} m: {} patches",
                t.uniform(&roi, e).len()
            );
            group.bench_with_input(BenchmarkId::new(name, e), &e, |b, &e| {
                b.iter(|| t.uniform(&roi, e))
            });
        }
    }
    group.finish();
}

/// A camera 1500 m above the southern foothills, looking north across the cell.
pub fn camera(pixel_error: f64) -> ViewQuery {
    ViewQuery {
        eye: [-118.5, 34.05, 1500.0],
        look: [-118.5, 34.3, 500.0],
        fov_deg: 60.0,
        viewport_px: 1024,
        pixel_error,
        metric: Metric::geographic(34.05),
    }
}

fn view_queries(c: &mut Criterion) {
    let t = &pair().terrain;
    let mut group = c.benchmark_group("view_query");
    for px in [1.0, 3.0] {
        let v = camera(px);
        println!("view {px} px: {} patches", t.view(&v).len());
        group.bench_with_input(BenchmarkId::from_parameter(px), &v, |b, v| {
            b.iter(|| t.view(v))
        });
    }
    group.finish();
}

fn cpu_resampling(c: &mut Criterion) {
    let t = &pair().terrain;
    let roi = Aabb::new(-118.6, 34.4, -118.5, 34.5);
    let ps = t.uniform(&roi, 5.0);
    // The error the speed is bought with: the tile against the surveys' own surfaces.
    let p = pair();
    let tile = t.resample(ps.clone(), &SampleGrid::uniform(&roi, 512, 512));
    let grid = SampleGrid::uniform(&roi, 512, 512);
    let (mut worst, mut sq, mut n) = (0.0f64, 0.0f64, 0usize);
    for (q, z) in grid.points().zip(&tile.heights) {
        let hs: Vec<f64> = [&p.cop, &p.nasa]
            .iter()
            .filter_map(|s| s.levels[0].bilinear(q))
            .collect();
        if hs.is_empty() || z.is_nan() {
            continue;
        }
        let lo = hs.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = hs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let d = (lo - *z as f64).max(*z as f64 - hi).max(0.0);
        worst = worst.max(d);
        sq += d * d;
        n += 1;
    }
    println!(
        "resampling {} patches at e = 5 m: max error {worst:.3} m, RMS {:.3} m over {n} samples",
        ps.len(),
        (sq / n as f64).sqrt()
    );
    // Speed is the more telling beside the work per sample: how many patches reach each one.
    let set = t.resolve(&ps);
    let grid = SampleGrid::uniform(&roi, 512, 512);
    let reaching: usize = grid
        .points()
        .map(|q| set.patches.iter().filter(|p| p.at(q).is_some()).count())
        .sum();
    println!(
        "{:.2} patches reach a sample on average",
        reaching as f64 / grid.points().len() as f64
    );
    let mut group = c.benchmark_group("cpu_resample");
    group.sample_size(10);
    for n in [256usize, 512, 1024, 2048] {
        let grid = SampleGrid::uniform(&roi, n, n);
        group.throughput(Throughput::Elements((n * n) as u64));
        group.bench_with_input(BenchmarkId::from_parameter(n), &grid, |b, g| {
            b.iter(|| t.resample(ps.clone(), g))
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().warm_up_time(Duration::from_secs(1)).measurement_time(Duration::from_secs(4));
    targets = patch_generation, insertion, uniform_queries, view_queries, cpu_resampling
}
criterion_main!(benches);
