//! GPU against CPU resampling over the full Copernicus N34W119 tile: samples per second for
//! 256² to 2048² uniform tiles at a few cut errors (so a few patch counts), with the GPU's
//! time split into the CPU's preparation (binning, packing, placing patches), queuing the
//! uploads and dispatches, the device's time from submission until the heights can be read,
//! and the readback.
//!
//! cargo bench -p patchwork-bench --bench gpu   (PATCHWORK_SHARED_DATA points at the data folder)
//!
//! "cold" is the first request, which uploads every patch's samples and record; "warm" finds
//! them on the device and uploads only the grid's axes, 32 bytes a patch and the bins ("up
//! KB"), and reads back 4 bytes a sample ("read KB"). A second table does the same for grids
//! whose positions the device makes: a view, and a tile in another CRS.

use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::survey::Survey;
use patchwork_core::resample::{cpu, SampleGrid};
use patchwork_core::terrain::Terrain;
use patchwork_engine::gpu::{Emulated, GpuResampler, GpuTimings};
use patchwork_read::{read_raster, ReadLimits};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

fn data(name: &str) -> PathBuf {
    std::env::var_os("PATCHWORK_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data"))
        .join(name)
}

/// The largest |GPU − CPU| where both have a height.
fn max_diff(got: &[f32], want: &[f32]) -> f64 {
    got.iter()
        .zip(want)
        .filter(|(a, b)| !a.is_nan() && !b.is_nan())
        .map(|(a, b)| (*a as f64 - *b as f64).abs())
        .fold(0.0, f64::max)
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn main() {
    // `cargo test --benches` runs this with --bench absent; only time when asked to.
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let mut gpu = match GpuResampler::new(Emulated::Allow) {
        Ok(g) => g,
        Err(e) => {
            println!("no GPU adapter ({e}); nothing to compare");
            return;
        }
    };
    println!("adapter: {}", gpu.adapter());
    let name = "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif";
    let t0 = Instant::now();
    let grid = read_raster(&data(name), &ReadLimits::default())
        .unwrap_or_else(|e| panic!("{name}: {e}"))
        .into_grid()
        .unwrap();
    let s = Arc::new(
        Survey::build(
            grid,
            0.0,
            Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
            PatchLayout::default(),
        )
        .unwrap(),
    );
    let mut t = Terrain::new(IndexConfig::default());
    t.insert(s.clone());
    println!(
        "{name}: {} patches, built in {:.1} s",
        s.patches.len(),
        t0.elapsed().as_secs_f64()
    );
    let full = s.levels[0].world_bounds();
    // A quarter of the tile (900 × 900 samples) and the whole tile (3600 × 3600).
    let quarter = Aabb {
        min: full.min,
        max: [
            full.min[0] + 0.25 * full.width(),
            full.min[1] + 0.25 * full.height(),
        ],
    };
    println!(
        "{:>9} {:>5} {:>6} {:>8} | {:>10} | {:>10} {:>10} | {:>8} {:>8} {:>8} {:>8} | {:>8} {:>8} | {:>9} {:>9}",
        "roi",
        "e",
        "size",
        "patches",
        "cpu Ms/s",
        "gpu Ms/s",
        "gpu+x Ms/s",
        "prep ms",
        "queue ms",
        "dev ms",
        "read ms",
        "up KB",
        "read KB",
        "cold",
        "max |Δ|"
    );
    for (label, roi) in [("quarter", quarter), ("full", full)] {
        for e in [0.0, 20.0] {
            let ps = t.uniform(&roi, e);
            let set = t.resolve(&ps);
            for n in [256usize, 512, 1024, 2048] {
                let grid = SampleGrid::uniform(&roi, n, n);
                let samples = (n * n) as f64;
                let t1 = Instant::now();
                let want = cpu::resample(&set, &grid);
                let cpu_s = t1.elapsed().as_secs_f64();

                // A fresh cache, so the first request is cold.
                gpu = GpuResampler::new(Emulated::Allow).unwrap();
                let (_, cold) = gpu.resample_timed(&set, &grid).unwrap();
                let mut best: Option<GpuTimings> = None;
                let mut got = Vec::new();
                for _ in 0..2 {
                    let (h, tm) = gpu.resample_timed(&set, &grid).unwrap();
                    got = h;
                    if best.as_ref().is_none_or(|b| tm.device < b.device) {
                        best = Some(tm);
                    }
                }
                let tm = best.unwrap();
                let worst = max_diff(&got, &want);
                let total = tm.prepare + tm.queue + tm.device + tm.readback;
                println!(
                    "{label:>9} {e:>5} {n:>6} {:>8} | {:>10.2} | {:>10.2} {:>10.2} | {:>8.2} {:>8.2} {:>8.1} {:>8.1} | {:>8.0} {:>8.0} | {:>6.1} ms {:>9.1e}",
                    set.patches.len(),
                    samples / cpu_s / 1e6,
                    samples / tm.device.as_secs_f64() / 1e6,
                    samples / total.as_secs_f64() / 1e6,
                    ms(tm.prepare),
                    ms(tm.queue),
                    ms(tm.device),
                    ms(tm.readback),
                    tm.uploaded_bytes as f64 / 1024.0,
                    tm.read_bytes as f64 / 1024.0,
                    ms(cold.prepare + cold.queue + cold.device + cold.readback),
                    worst
                );
            }
        }
    }
    println!(
        "cpu: {} rayon threads; gpu Ms/s counts the device's time (uploads, dispatches, copy) \
         alone, gpu+x adds the CPU's preparation, queuing and readback of a warm request; cold \
         is the first request end to end",
        rayon::current_num_threads()
    );
    made_on_the_device(&t, &quarter);
}

/// Grids whose positions the device makes: a view over the quarter tile (two points a row)
/// and a tile in UTM zone 11 over it (carried into the store's plane by a lattice kept on the
/// device), against what listing a position a sample would upload.
fn made_on_the_device(t: &Terrain, quarter: &Aabb) {
    use patchwork_core::crs::{Crs, Reprojection};
    use patchwork_core::index::query::{Metric, ViewQuery};
    println!(
        "\n{:>14} {:>6} {:>8} | {:>10} {:>10} | {:>8} {:>8} | {:>8} {:>9} | {:>9}",
        "grid",
        "size",
        "patches",
        "cpu Ms/s",
        "gpu Ms/s",
        "prep ms",
        "dev ms",
        "up KB",
        "listed KB",
        "max |Δ|"
    );
    let utm = Crs::epsg(32611).unwrap();
    let to_store = Arc::new(Reprojection::new(&utm, &Crs::wgs84()).unwrap());
    let back = Reprojection::new(&Crs::wgs84(), &utm).unwrap();
    let (a, b) = (
        back.exact().apply(quarter.min).unwrap(),
        back.exact().apply(quarter.max).unwrap(),
    );
    // Inside the quarter's image, so that every sample has data.
    let own = Aabb::new(
        a[0].max(b[0] - 20_000.0),
        a[1],
        b[0],
        b[1].min(a[1] + 20_000.0),
    );
    for n in [512usize, 2048] {
        let view = ViewQuery {
            eye: [quarter.min[0], quarter.min[1], 2500.0],
            look: [quarter.max[0], quarter.max[1], 800.0],
            fov_deg: 60.0,
            viewport_px: n as u32,
            pixel_error: 1.0,
            metric: Metric::geographic(quarter.min[1]),
        };
        let carried = SampleGrid::carried(
            SampleGrid::uniform(&own, n, n).axes.unwrap(),
            to_store.clone(),
        );
        let cut = Aabb::of_points(carried.list());
        for (label, ps, grid) in [
            (
                "view",
                t.view(&view),
                patchwork_core::terrain::view_grid(&view, n, n),
            ),
            ("UTM 11N tile", t.uniform(&cut, 20.0), carried.clone()),
        ] {
            let set = t.resolve(&ps);
            let t1 = Instant::now();
            let want = cpu::resample(&set, &grid);
            let cpu_s = t1.elapsed().as_secs_f64();
            let mut gpu = GpuResampler::new(Emulated::Allow).unwrap();
            gpu.resample_timed(&set, &grid).unwrap();
            let (got, tm) = gpu.resample_timed(&set, &grid).unwrap();
            let worst = max_diff(&got, &want);
            let samples = (n * n) as f64;
            println!(
                "{label:>14} {n:>6} {:>8} | {:>10.2} {:>10.2} | {:>8.2} {:>8.1} | {:>8.0} {:>9.0} | {:>9.1e}",
                set.patches.len(),
                samples / cpu_s / 1e6,
                samples / tm.device.as_secs_f64() / 1e6,
                ms(tm.prepare),
                ms(tm.device),
                tm.uploaded_bytes as f64 / 1024.0,
                16.0 * samples / 1024.0,
                worst
            );
        }
    }
}
