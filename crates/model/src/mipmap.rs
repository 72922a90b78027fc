//! Nodata-aware mipmaps that stay aligned with the original samples.
//!
//! Level k+1 keeps every other sample position of level k and filters it with the separable
//! [1 2 1]/4 kernel. Keeping coarse samples on fine sample positions means every coarse grid
//! line is also a fine grid line, so the difference between a coarse patch and the original
//! surface is bilinear on each original cell; that is what lets the patch error δ be exact
//! rather than estimated (see `patch::Bilinear`).
//!
//! Voids erode: a coarse sample is valid only when every fine sample under its filter is. So
//! every valid coarse cell lies over valid original cells, a coarse patch never invents heights
//! inside a hole, and its δ bounds it everywhere it is evaluated. At the grid's edge the filter
//! is renormalised over the samples that exist.

use super::grid::Grid;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// How a coarse level's samples are made. Every filter keeps the same sample positions and
/// the same erosion, so only the heights differ, and with them each patch's δ.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Filter {
    /// The separable [1 2 1]/4 kernel on the level above.
    Smooth,
    /// The fine sample at the coarse position, unfiltered.
    Decimate,
    /// [`Filter::Smooth`], then each sample moved to centre the deviation from level 0 of the
    /// fine samples nearest it: a Chebyshev fit, aiming at the smallest δ. The default: its
    /// cuts ship a third to a half fewer samples at 10–50 m (docs/BENCHMARKS.md).
    #[default]
    Minimax,
}

impl Filter {
    /// Every filter.
    pub const ALL: [Filter; 3] = [Filter::Smooth, Filter::Decimate, Filter::Minimax];

    /// The name in the config and the store, as serialised.
    pub fn name(self) -> &'static str {
        match self {
            Filter::Smooth => "smooth",
            Filter::Decimate => "decimate",
            Filter::Minimax => "minimax",
        }
    }

    /// The filter called `name`, if any.
    pub fn from_name(name: &str) -> Option<Filter> {
        Filter::ALL.into_iter().find(|f| f.name() == name)
    }
}

/// Halves the resolution. Coarse samples never lie beyond the fine grid, so no coarse cell
/// reaches past the survey's edge: with an odd number of fine cells, the last one is left to
/// the finer level.
pub fn downsample(fine: &Grid) -> Grid {
    let cols = (fine.cols - 1) / 2 + 1;
    let rows = (fine.rows - 1) / 2 + 1;
    const W: [f64; 3] = [0.25, 0.5, 0.25];
    let mut samples = vec![f32::NAN; cols * rows];
    samples
        .par_chunks_mut(cols)
        .enumerate()
        .for_each(|(j, out_row)| {
            for (i, out) in out_row.iter_mut().enumerate() {
                let (mut sum, mut wsum) = (0.0f64, 0.0f64);
                for (dj, wj) in W.iter().enumerate() {
                    let Some(r) = (2 * j + dj).checked_sub(1).filter(|&r| r < fine.rows) else {
                        continue;
                    };
                    let row = &fine.samples[r * fine.cols..(r + 1) * fine.cols];
                    for (di, wi) in W.iter().enumerate() {
                        let Some(c) = (2 * i + di).checked_sub(1).filter(|&c| c < fine.cols) else {
                            continue;
                        };
                        // A NaN here makes the sum NaN: the coarse sample is void.
                        sum += wi * wj * row[c] as f64;
                        wsum += wi * wj;
                    }
                }
                *out = (sum / wsum) as f32;
            }
        });
    Grid {
        cols,
        rows,
        samples,
        georef: fine.georef.coarsened(2.0),
    }
}

/// Every other sample of `fine`, unfiltered, void where [`downsample`] would erode it.
pub fn decimate(fine: &Grid) -> Grid {
    let mut out = downsample(fine);
    for (k, z) in out.samples.iter_mut().enumerate() {
        if !z.is_nan() {
            let (i, j) = (k % out.cols, k / out.cols);
            *z = fine.at(2 * i, 2 * j);
        }
    }
    out
}

/// Fit rounds of [`Filter::Minimax`], and how far each moves a sample towards the middle of
/// its deviations. Measured on the 1″ N34W119 tiles: four rounds of three quarters ship as few
/// samples as six of a half (within 1%), three of nine tenths 2% more, four of a half 5–14%
/// more. Not the whole way, since a sample's neighbours move too.
const FIT_ROUNDS: usize = 4;
const FIT_PULL: f64 = 0.75;

/// Fitted heights are kept to multiples of this (m): δ is measured on the heights as kept, so
/// the bound holds whatever they are, and binary fractions let a 16-bit survey's coarse
/// patches still travel as 16-bit integers.
pub const FIT_STEP: f64 = 1.0 / 16.0;

/// Moves each valid sample of `coarse` (level `level` of `fine`'s pyramid) towards the middle
/// of the deviations from `fine` of the fine samples within half a coarse cell of it, by
/// [`FIT_PULL`] of the way each round.
///
/// A fine sample's deviation depends only on the fine sample and the coarse cell it lies in,
/// not on which coarse sample it counts for: so each fine row is worked out once a round
/// (where a row halfway between two coarse rows used to be worked out for both), into a line
/// of deviations that the compiler vectorises, and each coarse sample then takes the
/// smallest and largest of its stretch of that line. Bands of coarse rows go to the cores.
/// The sums and the comparisons are those of the plain formula, so the heights are the same
/// to the bit (tested against it).
pub fn fit_minimax(coarse: &mut Grid, fine: &Grid, level: usize) {
    let f = 1usize << level;
    let [cw, ch] = coarse.cells();
    if cw == 0 || ch == 0 {
        return;
    }
    // Enough coarse rows a task that its fine rows are some 64, each band working out
    // again only the one fine row it shares with the next.
    let band = (64 / f).max(1);
    // The heights a round starts from, in one buffer for all rounds: a level-1 copy of a
    // 3600² survey is 13 MB, and a fresh one each round was faulted in page by page.
    let mut current = coarse.clone();
    for round in 0..FIT_ROUNDS {
        if round > 0 {
            current.samples.copy_from_slice(&coarse.samples);
        }
        coarse
            .samples
            .par_chunks_mut(current.cols * band)
            .enumerate()
            .for_each(|(b, rows)| fit_band(&current, fine, f, b * band, rows));
    }
    for z in coarse.samples.iter_mut().filter(|z| !z.is_nan()) {
        *z = ((*z as f64 / FIT_STEP).round() * FIT_STEP) as f32;
    }
}

/// One round of [`fit_minimax`] for the coarse rows from `j0` that `rows` holds.
fn fit_band(current: &Grid, fine: &Grid, f: usize, j0: usize, rows: &mut [f32]) {
    let cols = current.cols;
    let (cw, ch) = (cols - 1, current.rows - 1);
    let half = f / 2;
    let inv = 1.0 / f as f64;
    let n = rows.len() / cols;
    // Fine samples past the last coarse line lie under no coarse cell.
    let (last_x, last_y) = (cw * f, ch * f);
    let mut lo = vec![f64::INFINITY; n * cols];
    let mut hi = vec![f64::NEG_INFINITY; n * cols];
    let mut line = vec![0.0f64; cols];
    let mut dev = vec![0.0f64; last_x + 1];
    let (mut row_lo, mut row_hi) = (vec![0.0f64; cols], vec![0.0f64; cols]);
    // Within half a coarse cell, both ends included: a fine line halfway between two coarse
    // lines counts for both, which steadies the fit.
    let ys = (j0 * f).saturating_sub(half)..=((j0 + n - 1) * f + half).min(last_y);
    for y in ys {
        // The coarse surface along this fine row, at every coarse column.
        let (r, fy) = cell_of(y, f, ch);
        let (top, bottom) = (
            &current.samples[r * cols..(r + 1) * cols],
            &current.samples[(r + 1) * cols..(r + 2) * cols],
        );
        for ((a, &t), &b) in line.iter_mut().zip(top).zip(bottom) {
            let t = t as f64;
            *a = t + (b as f64 - t) * fy;
        }
        let z = &fine.samples[y * fine.cols..y * fine.cols + last_x + 1];
        deviations(&line, inv, f, z, &mut dev);
        extremes(&dev, f, half, &mut row_lo, &mut row_hi);
        // The coarse rows within half a cell of this fine row: one, or two halfway.
        let first = (y + f - 1).saturating_sub(half) / f;
        let last = ((y + half) / f).min(j0 + n - 1);
        for j in first.max(j0)..=last {
            let k = (j - j0) * cols;
            for (l, &v) in lo[k..k + cols].iter_mut().zip(&row_lo) {
                *l = if v < *l { v } else { *l };
            }
            for (h, &v) in hi[k..k + cols].iter_mut().zip(&row_hi) {
                *h = if v > *h { v } else { *h };
            }
        }
    }
    for ((z, l), h) in rows.iter_mut().zip(&lo).zip(&hi) {
        if !z.is_nan() && l.is_finite() {
            *z = (*z as f64 - FIT_PULL * 0.5 * (l + h)) as f32;
        }
    }
}

/// Each fine sample's deviation from the coarse surface along its row, `line` holding that
/// surface at every coarse column: sample x lies in cell min(x / f, cells − 1) and its
/// deviation is the cell's left height plus slope times its offset, less its own height. NaN
/// where the cell or the sample is void, which [`extremes`] passes over.
#[inline]
fn deviations(line: &[f64], inv: f64, f: usize, z: &[f32], dev: &mut [f64]) {
    // A width the compiler knows lets it unroll the cells of the finer levels, where a cell
    // holds two or four samples and a loop per cell would cost more than its work: each arm
    // inlines the one loop with its own constant.
    match f {
        2 => deviations_in(line, inv, 2, z, dev),
        4 => deviations_in(line, inv, 4, z, dev),
        8 => deviations_in(line, inv, 8, z, dev),
        16 => deviations_in(line, inv, 16, z, dev),
        _ => deviations_in(line, inv, f, z, dev),
    }
}

#[inline(always)]
fn deviations_in(line: &[f64], inv: f64, f: usize, z: &[f32], dev: &mut [f64]) {
    let cells = line.len() - 1;
    for (c, (d, zs)) in dev
        .chunks_exact_mut(f)
        .zip(z.chunks_exact(f))
        .take(cells)
        .enumerate()
    {
        let a = line[c];
        let s = (line[c + 1] - a) * inv;
        for (k, (d, &z)) in d.iter_mut().zip(zs).enumerate() {
            *d = a + s * k as f64 - z as f64;
        }
    }
    last_sample(line, inv, f, z, dev);
}

/// The sample on the last coarse column: the last cell's right end.
#[inline]
fn last_sample(line: &[f64], inv: f64, f: usize, z: &[f32], dev: &mut [f64]) {
    let cells = line.len() - 1;
    let a = line[cells - 1];
    let s = (line[cells] - a) * inv;
    dev[cells * f] = a + s * f as f64 - z[cells * f] as f64;
}

/// For each coarse column c, the smallest and largest deviation of the fine samples within
/// half a cell of it, NaN passed over (INFINITY and −INFINITY where all are).
#[inline]
fn extremes(dev: &[f64], f: usize, half: usize, lo: &mut [f64], hi: &mut [f64]) {
    let last = dev.len() - 1;
    for (c, (l, h)) in lo.iter_mut().zip(hi.iter_mut()).enumerate() {
        let stretch = &dev[(c * f).saturating_sub(half)..=(c * f + half).min(last)];
        let (mut a, mut b) = (f64::INFINITY, f64::NEG_INFINITY);
        for &d in stretch {
            // A NaN fails both tests, so a void is passed over.
            a = if d < a { d } else { a };
            b = if d > b { d } else { b };
        }
        (*l, *h) = (a, b);
    }
}

/// The coarse cell holding fine sample `x` along one axis, and where in it: a sample on the
/// last line belongs to the last cell.
#[inline]
fn cell_of(x: usize, f: usize, cells: usize) -> (usize, f64) {
    let c = (x / f).min(cells.max(1) - 1);
    (c, (x - c * f) as f64 / f as f64)
}

/// All levels of a grid, level 0 first, down to the first level that one kernel of
/// `kernel_cells` cells covers whole.
pub fn build(level0: Arc<Grid>, kernel_cells: usize) -> Vec<Arc<Grid>> {
    build_with(level0, kernel_cells, Filter::Smooth)
}

/// [`build`] with the given filter.
pub fn build_with(level0: Arc<Grid>, kernel_cells: usize, filter: Filter) -> Vec<Arc<Grid>> {
    let mut levels = vec![level0];
    loop {
        let last = levels.last().expect("level 0 is present");
        let [cw, ch] = last.cells();
        if cw <= kernel_cells && ch <= kernel_cells {
            break;
        }
        let next = match filter {
            Filter::Decimate => decimate(last),
            Filter::Smooth | Filter::Minimax => downsample(last),
        };
        levels.push(Arc::new(next));
    }
    if filter == Filter::Minimax {
        // Each level is fitted to level 0 itself, from the smooth pyramid.
        let fine = levels[0].clone();
        for (level, g) in levels.iter_mut().enumerate().skip(1) {
            fit_minimax(Arc::make_mut(g), &fine, level);
        }
    }
    levels
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Georef;

    fn grid(cols: usize, rows: usize, f: impl Fn(usize, usize) -> f32) -> Grid {
        let s = (0..rows)
            .flat_map(|r| (0..cols).map(move |c| (c, r)))
            .map(|(c, r)| f(c, r))
            .collect();
        Grid::new(cols, rows, s, Georef::north_up([10.0, 20.0], [2.0, 3.0])).unwrap()
    }

    #[test]
    fn coarse_samples_sit_on_fine_samples() {
        let g = grid(9, 6, |c, r| (c + 10 * r) as f32);
        let d = downsample(&g);
        assert_eq!((d.cols, d.rows), (5, 3));
        for j in 0..d.rows {
            for i in 0..d.cols {
                let p = d.georef.to_world(i as f64, j as f64);
                let q = g.georef.to_world(2.0 * i as f64, 2.0 * j as f64);
                assert!((p[0] - q[0]).abs() < 1e-12 && (p[1] - q[1]).abs() < 1e-12);
            }
        }
        // A linear ramp survives the symmetric filter unchanged away from the border.
        assert!((d.at(2, 1) - g.at(4, 2)).abs() < 1e-5);
    }

    #[test]
    fn voids_erode_and_never_enter_the_average() {
        let g = grid(7, 7, |c, r| if c == 1 && r == 1 { f32::NAN } else { 7.0 });
        let d = downsample(&g);
        // Coarse samples 0 and 1 on each axis see fine sample 1 through the filter.
        for j in 0..d.rows {
            for i in 0..d.cols {
                assert_eq!(d.at(i, j).is_nan(), i < 2 && j < 2, "({i}, {j})");
                assert!(d.at(i, j).is_nan() || d.at(i, j) == 7.0);
            }
        }
        // Every valid coarse cell lies over valid fine cells only.
        for r in 0..d.rows - 1 {
            for c in 0..d.cols - 1 {
                if d.cell_valid(c, r) {
                    for fr in 2 * r..2 * r + 2 {
                        for fc in 2 * c..2 * c + 2 {
                            assert!(g.cell_valid(fc, fr));
                        }
                    }
                }
            }
        }
        let all_void = grid(4, 4, |_, _| f32::NAN);
        assert!(downsample(&all_void).samples.iter().all(|z| z.is_nan()));
    }

    #[test]
    fn every_filter_keeps_the_erosion_and_decimation_keeps_the_samples() {
        let g = Arc::new(grid(33, 21, |c, r| {
            if c == 7 && r == 4 {
                f32::NAN
            } else {
                ((c * 7 + r * 13) % 11) as f32
            }
        }));
        let smooth = build_with(g.clone(), 4, Filter::Smooth);
        for filter in [Filter::Decimate, Filter::Minimax] {
            let other = build_with(g.clone(), 4, filter);
            assert_eq!(other.len(), smooth.len());
            for (a, b) in smooth.iter().zip(&other) {
                let voids = |g: &Grid| g.samples.iter().map(|z| z.is_nan()).collect::<Vec<_>>();
                assert_eq!(voids(a), voids(b), "{filter:?}");
            }
        }
        let d = build_with(g.clone(), 4, Filter::Decimate);
        assert_eq!(d[2].at(3, 2), g.at(12, 8));
    }

    #[test]
    fn the_minimax_fit_lowers_the_largest_deviation() {
        use crate::patch::{Bilinear, PatchFunction};
        // Rough ground: a sum of incommensurate ripples.
        let g = Arc::new(grid(129, 129, |c, r| {
            let (x, y) = (c as f64, r as f64);
            (40.0 * (x * 0.37).sin() * (y * 0.23).cos() + 25.0 * (x * 0.11 + y * 0.53).sin()) as f32
        }));
        let worst = |levels: &[Arc<Grid>], level: usize| {
            let [cw, ch] = levels[level].cells();
            let all = crate::patch::CellRect {
                c0: 0,
                r0: 0,
                c1: cw as u32,
                r1: ch as u32,
            };
            Bilinear.max_deviation(levels, level, &all)
        };
        let smooth = build_with(g.clone(), 8, Filter::Smooth);
        let fitted = build_with(g, 8, Filter::Minimax);
        for level in 1..smooth.len() {
            assert!(
                worst(&fitted, level) < worst(&smooth, level),
                "level {level}: {} against {}",
                worst(&fitted, level),
                worst(&smooth, level)
            );
        }
    }

    /// The fit as first written: each coarse row streams its fine rows and works out every
    /// fine sample's deviation for itself. The reference the fast fit must equal.
    fn fit_minimax_plain(coarse: &mut Grid, fine: &Grid, level: usize) {
        let f = 1usize << level;
        let half = f / 2;
        let inv = 1.0 / f as f64;
        let [cw, ch] = coarse.cells();
        if cw == 0 || ch == 0 {
            return;
        }
        // Fine samples past the last coarse line lie under no coarse cell.
        let (last_x, last_y) = (cw * f, ch * f);
        for _ in 0..FIT_ROUNDS {
            let current = coarse.clone();
            coarse
                .samples
                .par_chunks_mut(current.cols)
                .enumerate()
                .for_each(|(j, row)| {
                    let mut lo = vec![f64::INFINITY; current.cols];
                    let mut hi = vec![f64::NEG_INFINITY; current.cols];
                    // Within half a coarse cell, both ends included: a fine line halfway between
                    // two coarse lines counts for both, which steadies the fit.
                    let ys = (j * f).saturating_sub(half)..=(j * f + half).min(last_y);
                    for y in ys {
                        let (r, fy) = cell_of(y, f, ch);
                        let line = &fine.samples[y * fine.cols..y * fine.cols + last_x + 1];
                        for c in 0..cw {
                            let at = |cc: usize, rr: usize| {
                                current.samples[rr * current.cols + cc] as f64
                            };
                            let a = at(c, r) + (at(c, r + 1) - at(c, r)) * fy;
                            let b = at(c + 1, r) + (at(c + 1, r + 1) - at(c + 1, r)) * fy;
                            if a.is_nan() || b.is_nan() {
                                continue;
                            }
                            // The cell's own samples, its right edge only for the last cell (the
                            // next cell starts there with the same value).
                            let end = if c + 1 == cw { f } else { f - 1 };
                            let slope = (b - a) * inv;
                            // The first half of the cell is nearest coarse column c, the second
                            // c + 1, the middle both. f64::min and max pass over a NaN (a void
                            // fine sample), so the loops need no test and vectorise.
                            let seg = &line[c * f..=c * f + end];
                            let (mut l0, mut h0) = (lo[c], hi[c]);
                            for (k, &z) in seg[..=half].iter().enumerate() {
                                let d = a + slope * k as f64 - z as f64;
                                l0 = l0.min(d);
                                h0 = h0.max(d);
                            }
                            let (mut l1, mut h1) = (lo[c + 1], hi[c + 1]);
                            for (k, &z) in seg[half..].iter().enumerate() {
                                let d = a + slope * (k + half) as f64 - z as f64;
                                l1 = l1.min(d);
                                h1 = h1.max(d);
                            }
                            (lo[c], hi[c], lo[c + 1], hi[c + 1]) = (l0, h0, l1, h1);
                        }
                    }
                    for (i, z) in row.iter_mut().enumerate() {
                        if !z.is_nan() && lo[i].is_finite() {
                            *z = (*z as f64 - FIT_PULL * 0.5 * (lo[i] + hi[i])) as f32;
                        }
                    }
                });
        }
        for z in coarse.samples.iter_mut().filter(|z| !z.is_nan()) {
            *z = ((*z as f64 / FIT_STEP).round() * FIT_STEP) as f32;
        }
    }

    #[test]
    fn the_fit_equals_the_plain_formula_to_the_bit() {
        let mut next = patchwork_geom::rng::uniform(27);
        // Odd and even sizes, voids, and levels up to 32 samples a cell (past the unrolled
        // widths), so that every path of the fast fit is taken.
        for (cols, rows) in [(129, 129), (200, 77), (65, 300), (1000, 33)] {
            let g = Arc::new(grid(cols, rows, |c, r| {
                let (x, y) = (c as f64, r as f64);
                let z =
                    40.0 * (x * 0.37).sin() * (y * 0.23).cos() + 25.0 * (x * 0.11 + y * 0.53).sin();
                // A roughness of its own at every sample, from the position alone.
                let n = ((c * 7919 + r * 104_729) % 1013) as f64 / 1013.0;
                (z + 3.0 * n) as f32
            }));
            let mut g = (*g).clone();
            for _ in 0..(cols * rows / 50) {
                let k = (next() * (cols * rows) as f64) as usize % (cols * rows);
                g.samples[k] = f32::NAN;
            }
            let g = Arc::new(g);
            let smooth = build_with(g.clone(), 2, Filter::Smooth);
            for (level, coarse) in smooth.iter().enumerate().skip(1) {
                let (mut fast, mut plain) = ((**coarse).clone(), (**coarse).clone());
                fit_minimax(&mut fast, &g, level);
                fit_minimax_plain(&mut plain, &g, level);
                let bits = |g: &Grid| g.samples.iter().map(|z| z.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&fast), bits(&plain), "{cols}×{rows}, level {level}");
            }
        }
    }

    #[test]
    fn pyramid_stops_when_one_kernel_covers() {
        let g = Arc::new(grid(200, 90, |c, r| (c * r) as f32));
        let levels = build(g, 28);
        let last = levels.last().unwrap();
        assert!(last.cells()[0] <= 28 && last.cells()[1] <= 28);
        let before = &levels[levels.len() - 2];
        assert!(before.cells()[0] > 28 || before.cells()[1] > 28);
    }
}
