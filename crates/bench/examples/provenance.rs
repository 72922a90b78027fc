//! Times provenance: heights at 10,000 points drawn at random over the Copernicus + NASADEM
//! N34W119 pair, with and without what served each, at three errors. Prints the medians of 21
//! runs of each.
//!
//! cargo run --release -p patchwork-bench --example provenance -- [DATA_DIR]
//!
//! DATA_DIR defaults to ../shared/data.

use patchwork_engine::config::Config;
use patchwork_engine::{Ctx, Engine, Origin, SampleRequest};
use std::path::PathBuf;
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let data = PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "../shared/data".into()),
    );
    let tmp = tempfile::tempdir().unwrap();
    let e = Engine::open(Config {
        data_dir: tmp.path().join("store"),
        ingest_roots: vec![data.clone()],
        ..Config::default()
    })
    .unwrap();
    for (f, a) in [
        ("Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif", 3.0),
        ("NASADEM_HGT_n34w119.tif", 8.0),
    ] {
        let done = e.ingest(&data.join(f), Some(a), Origin::Request).unwrap();
        assert!(done.error.is_empty(), "{f}: {}", done.error);
    }
    let mut next = patchwork_core::geom::rng::uniform(7);
    let pts: Vec<[f64; 2]> = (0..10_000)
        .map(|_| [-119.0 + next(), 34.0 + next()])
        .collect();
    let t = e.snapshot();
    let bounds = patchwork_core::geom::Aabb::of_points(&pts);
    for error in [0.0, 5.0, 20.0] {
        let t0 = Instant::now();
        let ps = t.uniform(&bounds, error);
        let cut_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t0 = Instant::now();
        let set = t.try_resolve(&ps).unwrap();
        println!(
            "e {error:>4} m: the cut, {} patches, {cut_ms:.1} ms; resolved in {:.1} ms",
            set.patches.len(),
            t0.elapsed().as_secs_f64() * 1e3
        );
    }
    for error in [0.0, 5.0, 20.0] {
        let req = SampleRequest::new(pts.clone(), None, error).unwrap();
        let with = req.clone().with_sources(true);
        // Warm: the chunks the points read are in the cache for both.
        e.sample(&with, Ctx::default()).unwrap();
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for _ in 0..21 {
            let t = Instant::now();
            e.sample(&req, Ctx::default()).unwrap();
            a.push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            let s = e.sample(&with, Ctx::default()).unwrap();
            b.push(t.elapsed().as_secs_f64() * 1e3);
            assert_eq!(s.sources.len(), pts.len());
        }
        let (a, b) = (median(a), median(b));
        println!(
            "e {error:>4} m: 10,000 points {a:.1} ms, with sources {b:.1} ms ({:.2}×)",
            b / a
        );
    }
}
