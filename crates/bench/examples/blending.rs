//! Formula 1 against the paper's proposed blending (§7.3): inside its kernel the most accurate
//! patch alone, blending only across the bands where a more accurate patch's extension zone
//! meets a less accurate one's kernel. Both evaluated a point at a time over the same binned
//! patches, on the Copernicus and NASADEM crops of N34W119 taken as exact, for error, smoothness
//! and speed.
//!
//! cargo run --release -p patchwork-bench --example blending
//!
//! The proposed blend, as built here: patches that reach a point are taken in order of error
//! (then id), each with a weight that is 1 over its kernel and falls to 0 across its extension
//! zone, and laid over one another: a point inside the best patch's kernel gets that patch
//! alone, and where its weight falls off, the next patch fills in. Every answer is a convex
//! combination of patches within e, so the bound holds as for Formula 1.
//!
//! Smoothness is the second difference of heights along rows sampled at a quarter of a source
//! cell, divided by the spacing: the jump in slope between neighbouring steps. Both surfaces
//! bend at the surveys' own cell edges; what differs is what blending adds.

use patchwork_bench::reference;
use patchwork_core::geom::Aabb;
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::survey::Survey;
use patchwork_core::resample::{cpu, PatchSet, ResolvedPatch, SampleGrid, BLOCK};
use patchwork_core::terrain::Terrain;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

/// The proposed weight along one axis: 1 over the kernel, falling linearly to 0 at the window.
fn flat_weight(p: &ResolvedPatch, axis: usize, g: f64) -> f64 {
    let half = 1.0 / p.inv_half[axis];
    let (k0, k1) = if axis == 0 {
        (p.kernel.c0 as f64, p.kernel.c1 as f64)
    } else {
        (p.kernel.r0 as f64, p.kernel.r1 as f64)
    };
    let kernel_half = (k1 - k0) / 2.0;
    let t = ((g - p.centre[axis]) / half).abs();
    let tk = kernel_half / half;
    ((1.0 - t) / (1.0 - tk)).clamp(0.0, 1.0)
}

/// The proposed blend at one point.
fn priority(set: &PatchSet, bin: &[u32], pt: [f64; 2]) -> f32 {
    let mut hits: Vec<(f64, u64, f64, f64, bool)> = Vec::with_capacity(bin.len());
    for &k in bin {
        let p = &set.patches[k as usize];
        let Some((_, hit)) = p.at(pt) else { continue };
        let g = p.to_grid(pt);
        let w = flat_weight(p, 0, g[0]) * flat_weight(p, 1, g[1]) * hit.weight;
        hits.push((p.error, p.id.0, w, hit.z, hit.covered));
    }
    if !hits.iter().any(|h| h.4) {
        return f32::NAN;
    }
    hits.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let (mut acc, mut rest) = (0.0, 1.0);
    for (_, _, w, z, _) in hits {
        let a = w * rest;
        acc += a * z;
        rest -= a;
        if rest <= 0.0 {
            break;
        }
    }
    if rest < 1.0 {
        (acc / (1.0 - rest)) as f32
    } else {
        f32::NAN
    }
}

/// Heights a point at a time with `f`, from the patches binned per block.
fn heights(
    set: &PatchSet,
    grid: &SampleGrid,
    bins: &[Vec<u32>],
    f: impl Fn(&PatchSet, &[u32], [f64; 2]) -> f32,
) -> Vec<f32> {
    let bx = grid.width.div_ceil(BLOCK);
    grid.points()
        .enumerate()
        .map(|(k, p)| {
            let (i, j) = (k % grid.width, k / grid.width);
            f(set, &bins[(j / BLOCK) * bx + i / BLOCK], p)
        })
        .collect()
}

/// Largest deviation outside the surveys' range, and the 99th percentile and largest slope
/// jump along rows.
fn measure(h: &[f32], lo: &[f32], hi: &[f32], width: usize, step_m: f64) -> (f64, f64, f64) {
    let err = patchwork_bench::errors(h, lo, hi)
        .into_iter()
        .fold(0.0, f64::max);
    let mut jumps: Vec<f64> = h
        .chunks(width)
        .flat_map(|row| {
            row.windows(3).filter_map(|w| {
                let d = (w[2] as f64 - 2.0 * w[1] as f64 + w[0] as f64) / step_m;
                d.is_finite().then_some(d.abs())
            })
        })
        .collect();
    jumps.sort_by(f64::total_cmp);
    let p99 = jumps[jumps.len() * 99 / 100];
    (err, p99, *jumps.last().unwrap())
}

fn main() {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data");
    let survey = |name: &str| {
        let r = patchwork_read::read_raster(&data.join(name), &Default::default()).unwrap();
        let crs = r.crs.crs.clone();
        let g = r.into_grid().unwrap();
        Arc::new(Survey::build(g, 0.0, crs, PatchLayout::default()).unwrap())
    };
    let cop = survey("copernicus_n34w119_crop.tif");
    let nasa = survey("nasadem_n34w119_crop.tif");
    let mut t = Terrain::new(Default::default());
    t.insert(cop.clone());
    t.insert(nasa.clone());
    let b = cop.levels[0].world_bounds();
    let n = nasa.levels[0].world_bounds();
    // Where the two overlap, and their union's middle.
    let roi = Aabb::new(
        b.min[0].max(n.min[0]),
        b.min[1].max(n.min[1]),
        b.max[0].min(n.max[0]),
        b.max[1].min(n.max[1]),
    );
    let cell = cop.levels[0].georef.step[0];
    let side = (roi.width() / (cell / 4.0)) as usize;
    let grid = SampleGrid::uniform(&roi, side, side);
    // A quarter of a 1″ cell, in metres, at this latitude.
    let step_m = cell / 4.0 * 111_320.0 * 34.5f64.to_radians().cos();
    let (lo, hi) = reference(&t, &grid);
    println!(
        "{side}² points over the overlap of the Copernicus and NASADEM crops, a quarter cell apart"
    );
    println!("e | blend | patches | max error (m) | slope jump p99 / max (m/m per m) | ms");
    for e in [0.0, 5.0, 10.0, 20.0, 50.0] {
        let ps = t.uniform(&roi, e);
        let set = t.resolve(&ps);
        let bins = cpu::bin(&set.patches, &grid);
        for (name, f) in [
            (
                "formula 1",
                cpu::blend as fn(&PatchSet, &[u32], [f64; 2]) -> f32,
            ),
            ("priority", priority),
        ] {
            let mut times = Vec::new();
            let mut h = Vec::new();
            for _ in 0..3 {
                let t0 = Instant::now();
                h = heights(&set, &grid, &bins, f);
                times.push(t0.elapsed().as_secs_f64() * 1e3);
            }
            times.sort_by(f64::total_cmp);
            let (err, p99, max) = measure(&h, &lo, &hi, side, step_m);
            println!(
                "{e:>4} | {name:>9} | {:>4} | {err:.3} | {p99:.4} / {max:.3} | {:.1}",
                ps.len(),
                times[1]
            );
        }
    }
}
