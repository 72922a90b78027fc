//! Formula 1 on the CPU: every output sample is the weighted mean of the patches whose window
//! holds it, with weights W = w(tx)·w(ty) / (dx·dy) so that smaller, more accurate patches
//! count more. A sample no valid kernel holds is nodata.

use super::{PatchSet, ResolvedPatch, SampleGrid, BLOCK};
use crate::model::patch::PatchFunction;
use rayon::prelude::*;

/// Patch indices per block of output samples, so each sample visits only patches near it.
pub fn bin(patches: &[ResolvedPatch], grid: &SampleGrid) -> Vec<Vec<u32>> {
    let blocks = grid.block_bounds();
    blocks
        .par_iter()
        .map(|b| match b {
            Some(b) => patches
                .iter()
                .enumerate()
                .filter(|(_, p)| p.window_aabb.intersects(b))
                .map(|(i, _)| i as u32)
                .collect(),
            None => Vec::new(),
        })
        .collect()
}

/// Heights at every point of the grid, NaN where no valid kernel reaches.
pub fn resample<F: PatchFunction>(set: &PatchSet, grid: &SampleGrid, func: &F) -> Vec<f32> {
    let bins = bin(&set.patches, grid);
    let bx = grid.width.div_ceil(BLOCK);
    let mut out = vec![f32::NAN; grid.width * grid.height];
    out.par_chunks_mut(grid.width)
        .enumerate()
        .for_each(|(j, row)| {
            let pts = &grid.points[j * grid.width..(j + 1) * grid.width];
            for (i, (o, &p)) in row.iter_mut().zip(pts).enumerate() {
                if p[0].is_nan() {
                    continue;
                }
                let bin = &bins[(j / BLOCK) * bx + i / BLOCK];
                *o = blend(set, bin, p, func);
            }
        });
    out
}

/// Formula 1 at one point.
#[inline]
pub fn blend<F: PatchFunction>(set: &PatchSet, bin: &[u32], p: [f64; 2], func: &F) -> f32 {
    let (mut sum, mut wsum) = (0.0f64, 0.0f64);
    let mut covered = false;
    for &k in bin {
        let q = &set.patches[k as usize];
        let g = q.to_grid(p);
        let tx = (g[0] - q.centre[0]) * q.inv_half[0];
        let ty = (g[1] - q.centre[1]) * q.inv_half[1];
        if tx.abs() >= 1.0 || ty.abs() >= 1.0 {
            continue;
        }
        let Some(z) = func.eval(&q.level, &q.window, g) else {
            continue;
        };
        let w = func.weight(tx) * func.weight(ty) * q.norm;
        sum += w * z;
        wsum += w;
        covered |= q.kernel.contains_grid(g);
    }
    if covered && wsum > 0.0 {
        (sum / wsum) as f32
    } else {
        f32::NAN
    }
}
