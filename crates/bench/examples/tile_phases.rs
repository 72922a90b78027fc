//! Where a tile's time goes, phase by phase, on the Copernicus + NASADEM N34W119 pair: the cut,
//! reading the patches' samples, binning and blending. The sizes and extents are those of the
//! tile bench (`bench/tile_latency.py`), so its end-to-end figures can be read against these.
//!
//! cargo run --release -p patchwork-bench --example tile_phases -- [DATA_DIR] [STORE_DIR]
//!
//! DATA_DIR defaults to ../shared/data. STORE_DIR, when given, is kept between runs, so that a
//! second run skips the ingest.

use patchwork_core::geom::Aabb;
use patchwork_core::resample::{cpu, SampleGrid};
use patchwork_engine::config::Config;
use patchwork_engine::{Cut, Engine, Origin};
use std::path::PathBuf;
use std::time::Instant;

const CENTRE: [f64; 2] = [-118.5, 34.5];

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let mut args = std::env::args().skip(1);
    let data = PathBuf::from(args.next().unwrap_or_else(|| "../shared/data".into()));
    let (store, _keep) = match args.next() {
        Some(d) => (PathBuf::from(d), None),
        None => {
            let t = tempfile::tempdir().expect("temporary directory");
            (t.path().to_path_buf(), Some(t))
        }
    };
    let cfg = Config {
        data_dir: store,
        ingest_roots: vec![data.clone()],
        ..Config::default()
    };
    let engine = Engine::open(cfg).expect("open the store");
    if engine.snapshot().surveys().next().is_none() {
        for f in [
            "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif",
            "NASADEM_HGT_n34w119.tif",
        ] {
            let done = engine
                .ingest(&data.join(f), None, Origin::Request)
                .expect("ingest");
            assert!(done.error.is_empty(), "{f}: {}", done.error);
        }
    }
    // PHASES_ONLY="2048 1 5" times one case alone, for a profiler.
    let only: Option<Vec<f64>> = std::env::var("PHASES_ONLY").ok().map(|s| {
        s.split_whitespace()
            .map(|w| w.parse().expect("a number"))
            .collect()
    });
    println!(
        "size extent e patches | cut resolve grid bin+blend total (ms, medians) | blend M samples/s, blocks one patch serves alone"
    );
    for n in [64usize, 512, 2048] {
        for extent in [0.05, 0.2, 1.0] {
            for e in [0.0, 5.0] {
                let h = extent / 2.0;
                let roi = Aabb::new(CENTRE[0] - h, CENTRE[1] - h, CENTRE[0] + h, CENTRE[1] + h);
                if only
                    .as_ref()
                    .is_some_and(|o| o[..] != [n as f64, extent, e])
                {
                    continue;
                }
                let cut = Cut::new(None, roi, e).expect("a valid cut");
                let reps = if only.is_some() {
                    60
                } else if n == 2048 {
                    5
                } else {
                    15
                };
                let (mut q, mut r, mut g, mut b, mut all, mut count) =
                    (vec![], vec![], vec![], vec![], vec![], 0);
                let mut alone = (0, 0);
                for _ in 0..reps {
                    let t0 = Instant::now();
                    let (t, ps) = engine.query(&cut).expect("cut");
                    let t1 = Instant::now();
                    let set = t.try_resolve(&ps).expect("samples");
                    let t2 = Instant::now();
                    let grid = SampleGrid::uniform(&roi, n, n);
                    let tg = Instant::now();
                    let hs = cpu::resample(&set, &grid);
                    let t3 = Instant::now();
                    alone = cpu::blocks_alone(&set, &grid);
                    g.push((tg - t2).as_secs_f64() * 1e3);
                    std::hint::black_box(hs);
                    count = ps.len();
                    q.push((t1 - t0).as_secs_f64() * 1e3);
                    r.push((t2 - t1).as_secs_f64() * 1e3);
                    b.push((t3 - tg).as_secs_f64() * 1e3);
                    all.push((t3 - t0).as_secs_f64() * 1e3);
                }
                let blend = median(b);
                println!(
                    "{n:>4} {extent:>4} {e} {count:>6} | {:7.2} {:7.2} {:7.2} {blend:7.2} {:7.2} | {:6.0} {:5.1}%",
                    median(q),
                    median(r),
                    median(g),
                    median(all),
                    (n * n) as f64 / blend / 1e3,
                    100.0 * alone.0 as f64 / alone.1.max(1) as f64,
                );
            }
        }
    }
}
