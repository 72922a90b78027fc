//! Formula 1 on the CPU: every output sample is the weighted mean of the patches whose window
//! holds it, with weights W = w(tx)·w(ty) / (dx·dy) so that smaller, more accurate patches
//! count more. A sample no valid kernel holds is nodata.
//!
//! Where a cut falls back below the data's accuracy, patches come in tiers: the cut's own
//! patches, then the fallback patches ranked by error. At a point some cut patch covers, only
//! the cut's patches blend; elsewhere the best-ranked fallback patch that covers the point
//! sets the tier, and the patches of that rank or better blend. A point's height then depends
//! only on the point and the patches that reach it, never on the ROI, and it is within the
//! error of the most accurate data that covers it.

use super::{PatchSet, ResolvedPatch, SampleGrid, BLOCK};
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
pub fn resample(set: &PatchSet, grid: &SampleGrid) -> Vec<f32> {
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
                *o = blend(set, bin, p);
            }
        });
    out
}

/// Sums of one tier at one point.
#[derive(Clone, Copy, Default)]
struct Tier {
    sum: f64,
    wsum: f64,
    covered: bool,
}

impl Tier {
    #[inline]
    fn add(&mut self, w: f64, z: f64, covered: bool) {
        self.sum += w * z;
        self.wsum += w;
        self.covered |= covered;
    }

    #[inline]
    fn merge(&mut self, o: &Tier) {
        self.sum += o.sum;
        self.wsum += o.wsum;
        self.covered |= o.covered;
    }

    fn height(&self) -> f32 {
        if self.covered && self.wsum > 0.0 {
            (self.sum / self.wsum) as f32
        } else {
            f32::NAN
        }
    }
}

/// Distinct fallback ranks one point can keep apart; more is handled by a second pass.
const RANKS: usize = 16;

/// Formula 1 at one point.
#[inline]
pub fn blend(set: &PatchSet, bin: &[u32], p: [f64; 2]) -> f32 {
    let mut cut = Tier::default();
    if !set.has_fallback {
        for &k in bin {
            if let Some((w, h)) = set.patches[k as usize].at(p) {
                cut.add(w, h.z, h.covered);
            }
        }
        return cut.height();
    }
    let mut tiers: [(u32, Tier); RANKS] = [(u32::MAX, Tier::default()); RANKS];
    let mut n = 0;
    for &k in bin {
        let q = &set.patches[k as usize];
        let Some((w, h)) = q.at(p) else {
            continue;
        };
        if !q.fallback {
            cut.add(w, h.z, h.covered);
            continue;
        }
        match tiers[..n].iter_mut().find(|t| t.0 == q.rank) {
            Some(t) => t.1.add(w, h.z, h.covered),
            None if n < RANKS => {
                tiers[n].0 = q.rank;
                tiers[n].1.add(w, h.z, h.covered);
                n += 1;
            }
            None => return blend_two_pass(set, bin, p),
        }
    }
    if cut.covered {
        return cut.height();
    }
    let Some(best) = tiers[..n].iter().filter(|t| t.1.covered).map(|t| t.0).min() else {
        return f32::NAN;
    };
    for t in tiers[..n].iter().filter(|t| t.0 <= best) {
        cut.merge(&t.1);
    }
    cut.height()
}

/// The tiered blend for a point that more fallback ranks reach than [`blend`] keeps apart.
#[cold]
fn blend_two_pass(set: &PatchSet, bin: &[u32], p: [f64; 2]) -> f32 {
    let hits: Vec<(&ResolvedPatch, f64, super::Hit)> = bin
        .iter()
        .filter_map(|&k| {
            let q = &set.patches[k as usize];
            q.at(p).map(|(w, h)| (q, w, h))
        })
        .collect();
    let cut_covers = hits.iter().any(|(q, _, h)| !q.fallback && h.covered);
    let best = hits
        .iter()
        .filter(|(q, _, h)| q.fallback && h.covered)
        .map(|(q, _, _)| q.rank)
        .min();
    let mut t = Tier::default();
    for (q, w, h) in &hits {
        let take = !q.fallback || (!cut_covers && best.is_some_and(|b| q.rank <= b));
        if take {
            t.add(*w, h.z, h.covered);
        }
    }
    t.height()
}
