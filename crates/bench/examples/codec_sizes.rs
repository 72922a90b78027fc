//! Measures the chunk codec against its alternatives on the full Copernicus (float heights) and
//! NASADEM (16-bit heights) N34W119 tiles, every mipmap level, in the store's chunks:
//! raw f32, zstd of the raw bytes, and the store's codec (byte planes with the float predictor,
//! or integer deltas) at several zstd levels.
//!
//! cargo run --release -p patchwork-bench --example codec_sizes -- [DATA_DIR]

use patchwork_core::model::grid::Grid;
use patchwork_core::model::mipmap;
use patchwork_read::{read_raster, ReadLimits};
use patchwork_store::chunks::{chunk_counts, chunk_rect, encode_at};
use rayon::prelude::*;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

fn chunks(g: &Grid) -> Vec<(Vec<f32>, usize)> {
    let shape = g.shape();
    let [nx, ny] = chunk_counts(&shape);
    (0..nx * ny)
        .map(|k| {
            let r = chunk_rect(&shape, k);
            let mut v = Vec::with_capacity(r.len());
            for row in r.r0..r.r1 {
                v.extend_from_slice(&g.samples[row * g.cols + r.c0..row * g.cols + r.c1]);
            }
            (v, r.cols())
        })
        .collect()
}

fn main() {
    let data = std::env::args_os()
        .nth(1)
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("../shared/data"));
    for name in [
        "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif",
        "NASADEM_HGT_n34w119.tif",
    ] {
        let path = data.join(name);
        let input = std::fs::metadata(&path).unwrap().len();
        let grid = read_raster(&path, &ReadLimits::default())
            .unwrap()
            .into_grid()
            .unwrap();
        let levels = mipmap::build(Arc::new(grid), 28);
        let all: Vec<(Vec<f32>, usize)> = levels.iter().flat_map(|g| chunks(g)).collect();
        let raw: usize = all.iter().map(|(v, _)| 4 * v.len()).sum();
        println!(
            "{name}: {} levels, input file {:.1} MiB, raw f32 {:.1} MiB",
            levels.len(),
            input as f64 / 1048576.0,
            raw as f64 / 1048576.0
        );
        let t = Instant::now();
        let plain: usize = all
            .par_iter()
            .map(|(v, _)| {
                let b: Vec<u8> = v.iter().flat_map(|z| z.to_le_bytes()).collect();
                zstd::bulk::compress(&b, 3).unwrap().len()
            })
            .sum();
        println!(
            "  zstd 3 of the raw bytes: {:.1} MiB ({:.2}× the input), {:.0} ms",
            plain as f64 / 1048576.0,
            plain as f64 / input as f64,
            t.elapsed().as_secs_f64() * 1e3
        );
        for level in [1, 3, 9, 19] {
            let t = Instant::now();
            let n: usize = all
                .par_iter()
                .map(|(v, cols)| encode_at(v, *cols, level).len())
                .sum();
            println!(
                "  store codec, zstd {level}: {:.1} MiB ({:.2}× the input), {:.0} ms",
                n as f64 / 1048576.0,
                n as f64 / input as f64,
                t.elapsed().as_secs_f64() * 1e3
            );
        }
    }
}
