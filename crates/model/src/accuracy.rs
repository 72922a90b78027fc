//! A survey's accuracy ε: given (a sidecar, a flag, the config) or estimated from its own
//! samples, and kept per level-0 kernel so that rough ground gets a larger ε than smooth.
//!
//! # The estimate
//!
//! ε is the largest error made by evaluating the grid's bilinear surface instead of the ground
//! it sampled. The ground is unknown, but the grid can be compared with coarser copies of
//! itself: dropping every other sample and interpolating the rest back gives an error d₂ that
//! is known exactly at every dropped sample, and dropping three in four gives d₄. Interpolation
//! error grows like a power of the spacing, d(h) ∝ h^α: α = 2 on smooth ground (curvature),
//! 1 or less on rough, fractal ground (real DEMs measure 0.5–1.3). So the ratio of the two
//! gives α for the survey, kept in [0.3, 2], and the grid's own error, one halving finer than
//! d₂, is d₂ / 2^α.
//!
//! α comes from the RMS of d₂ and d₄ over the whole survey, which is stable; the scale comes
//! from the largest d₂ in each kernel's window, which is local. `docs/MODEL.md` shows the
//! estimate against the measured error of decimated copies of real surveys.

use super::grid::Grid;
use super::patch::{CellRect, Tiling};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Where a survey's ε came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AccuracySource {
    /// `accuracy_m` in the file's `<file>.toml`.
    Sidecar,
    /// `--accuracy` on the command line, or `accuracy_m` in an Ingest request.
    Flag,
    /// A number in the config's `accuracy_m`.
    Config,
    /// Estimated from the survey's own samples (`accuracy_m = "auto"`).
    Estimated,
    /// Stored before the store recorded where accuracies came from.
    Unknown,
}

impl AccuracySource {
    /// The lowercase name, as serialised.
    pub fn as_str(&self) -> &'static str {
        match self {
            AccuracySource::Sidecar => "sidecar",
            AccuracySource::Flag => "flag",
            AccuracySource::Config => "config",
            AccuracySource::Estimated => "estimated",
            AccuracySource::Unknown => "unknown",
        }
    }
}

/// How a survey's ε is decided.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AccuracySpec {
    /// The same ε, in metres, everywhere.
    Fixed(f64),
    /// Estimated per kernel from the samples.
    Auto,
}

impl From<f64> for AccuracySpec {
    fn from(v: f64) -> Self {
        AccuracySpec::Fixed(v)
    }
}

/// ε for every kernel of a level-0 tiling, row-major over the tiling's kernels.
#[derive(Clone, Debug, PartialEq)]
pub struct KernelAccuracy {
    /// Kernels per row and per column.
    pub dims: [usize; 2],
    /// ε of each kernel, in metres, row-major.
    pub values: Vec<f64>,
}

impl KernelAccuracy {
    /// The same ε, `v` metres, for every kernel of `tiling`.
    pub fn constant(tiling: &Tiling, v: f64) -> Self {
        let dims = tiling.counts();
        KernelAccuracy {
            dims,
            values: vec![v; dims[0] * dims[1]],
        }
    }

    /// ε of the kernel at local position `k`.
    #[inline]
    pub fn at(&self, k: [u32; 2]) -> f64 {
        self.values[k[1] as usize * self.dims[0] + k[0] as usize]
    }

    /// The largest ε of the kernels that meet a rectangle of level-0 cells.
    pub fn max_over(&self, tiling: &Tiling, cells: &CellRect) -> f64 {
        let [a0, b0] = tiling.kernel_at(cells.c0, cells.r0);
        let [a1, b1] = tiling.kernel_at(
            cells.c1.saturating_sub(1).max(cells.c0),
            cells.r1.saturating_sub(1).max(cells.r0),
        );
        let mut m = 0.0f64;
        for b in b0..=b1 {
            for a in a0..=a1 {
                m = m.max(self.at([a, b]));
            }
        }
        m
    }

    /// The `q`-quantile of the kernels' ε (the nearest rank): what most of a survey achieves,
    /// where [`KernelAccuracy::max`] is what all of it does.
    pub fn quantile(&self, q: f64) -> f64 {
        if self.values.is_empty() {
            return 0.0;
        }
        let mut v = self.values.clone();
        v.sort_by(f64::total_cmp);
        let k = ((q.clamp(0.0, 1.0) * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
        v[k]
    }

    /// The survey's ε: the largest of its kernels', since ε bounds the error everywhere.
    pub fn max(&self) -> f64 {
        self.values.iter().copied().fold(0.0, f64::max)
    }
}

/// What the estimator found, for reports and charts.
#[derive(Clone, Debug, PartialEq)]
pub struct Estimate {
    /// The exponent of interpolation error against spacing, in [0.3, 2].
    pub alpha: f64,
    /// RMS error of the grid decimated by 2, at the samples it drops (d₂), in metres.
    pub rms2: f64,
    /// The same for the grid decimated by 4 (d₄).
    pub rms4: f64,
    /// ε of every kernel.
    pub kernels: KernelAccuracy,
}

/// Along row `r`: the difference between z(c, r) and the bilinear surface through the samples
/// of the grid decimated by `f`, for every c, or NaN where that surface is undefined or (c, r)
/// is one of its samples. `out` gets one figure a column.
fn decimation_errors(g: &Grid, f: usize, r: usize, out: &mut [f64]) {
    out.fill(f64::NAN);
    let j = r / f * f;
    if j + f >= g.rows {
        return;
    }
    let row = |k: usize| &g.samples[k * g.cols..(k + 1) * g.cols];
    let (here, above, below) = (row(r), row(j), row(j + f));
    let fy = (r - j) as f64 / f as f64;
    let on_row = r.is_multiple_of(f);
    for i in (0..g.cols).step_by(f) {
        if i + f >= g.cols {
            break;
        }
        let (z00, z10) = (above[i] as f64, above[i + f] as f64);
        let (z01, z11) = (below[i] as f64, below[i + f] as f64);
        for c in i..i + f {
            if on_row && c == i {
                continue;
            }
            let fx = (c - i) as f64 / f as f64;
            let top = z00 + (z10 - z00) * fx;
            let bottom = z01 + (z11 - z01) * fx;
            // Any void corner or sample makes it NaN.
            out[c] = (top + (bottom - top) * fy - here[c] as f64).abs();
        }
    }
}

/// Estimates ε for every kernel of `tiling` over level 0, with windows `margin` cells wider
/// than their kernels (the part of the grid each patch evaluates).
pub fn estimate(g: &Grid, tiling: &Tiling, margin: u32) -> Estimate {
    // Per row: sums of squares and counts for both factors, and the largest d₂ per column.
    let rows: Vec<(f64, u64, f64, u64, Vec<f32>)> = (0..g.rows)
        .into_par_iter()
        .map_init(
            || (vec![0.0; g.cols], vec![0.0; g.cols]),
            |(d2, d4), r| {
                let mut out = (0.0, 0u64, 0.0, 0u64, vec![f32::NAN; g.cols]);
                decimation_errors(g, 2, r, d2);
                decimation_errors(g, 4, r, d4);
                for c in 0..g.cols {
                    let d = d2[c];
                    if !d.is_nan() {
                        out.0 += d * d;
                        out.1 += 1;
                        out.4[c] = d as f32;
                    }
                    let d = d4[c];
                    if !d.is_nan() {
                        out.2 += d * d;
                        out.3 += 1;
                    }
                }
                out
            },
        )
        .collect();
    let (s2, n2, s4, n4) = rows.iter().fold((0.0, 0, 0.0, 0), |a, r| {
        (a.0 + r.0, a.1 + r.1, a.2 + r.2, a.3 + r.3)
    });
    let rms2 = if n2 > 0 { (s2 / n2 as f64).sqrt() } else { 0.0 };
    let rms4 = if n4 > 0 { (s4 / n4 as f64).sqrt() } else { 0.0 };
    let alpha = if rms2 > 0.0 && rms4 > 0.0 {
        (rms4 / rms2).log2().clamp(0.3, 2.0)
    } else {
        2.0
    };
    let scale = 1.0 / 2f64.powf(alpha);
    let dims = tiling.counts();
    let values: Vec<Option<f64>> = (0..dims[0] * dims[1])
        .into_par_iter()
        .map(|k| {
            let kernel = tiling.kernel([(k % dims[0]) as u32, (k / dims[0]) as u32]);
            let w = tiling.window(&kernel, margin);
            let mut worst: Option<f64> = None;
            for row in &rows[w.r0 as usize..=w.r1 as usize] {
                for &d in &row.4[w.c0 as usize..=w.c1 as usize] {
                    if !d.is_nan() {
                        worst = Some(worst.unwrap_or(0.0).max(d as f64));
                    }
                }
            }
            worst.map(|d| d * scale)
        })
        .collect();
    // A kernel too thin or too void to measure takes the largest estimate of its measured
    // neighbours (ε must bound the error, so an unknown one is not assumed small), or, with
    // none, the survey's median; a survey with nothing to measure, half its largest step
    // between neighbouring samples.
    let mut measured: Vec<f64> = values.iter().flatten().copied().collect();
    measured.sort_by(f64::total_cmp);
    let median = measured
        .get(measured.len() / 2)
        .copied()
        .unwrap_or_else(|| 0.5 * largest_step(g));
    let at = |a: i64, b: i64| -> Option<f64> {
        (a >= 0 && b >= 0 && (a as usize) < dims[0] && (b as usize) < dims[1])
            .then(|| values[b as usize * dims[0] + a as usize])
            .flatten()
    };
    let values = (0..dims[0] * dims[1])
        .map(|k| {
            values[k].unwrap_or_else(|| {
                let (a, b) = ((k % dims[0]) as i64, (k / dims[0]) as i64);
                let near = (-1..=1)
                    .flat_map(|db| (-1..=1).map(move |da| (a + da, b + db)))
                    .filter_map(|(x, y)| at(x, y))
                    .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))));
                near.unwrap_or(median)
            })
        })
        .collect();
    Estimate {
        alpha,
        rms2,
        rms4,
        kernels: KernelAccuracy { dims, values },
    }
}

/// The largest height difference between two valid samples side by side, or, with no two
/// side by side, the spread of the valid heights: a scale for ground the decimation cannot
/// measure.
fn largest_step(g: &Grid) -> f64 {
    let (mut step, mut lo, mut hi) = (0.0f64, f64::INFINITY, f64::NEG_INFINITY);
    let mut pairs = false;
    for r in 0..g.rows {
        for c in 0..g.cols {
            let z = g.at(c, r);
            if z.is_nan() {
                continue;
            }
            (lo, hi) = (lo.min(z as f64), hi.max(z as f64));
            for (dc, dr) in [(1, 0), (0, 1)] {
                if c + dc < g.cols && r + dr < g.rows && g.is_valid(c + dc, r + dr) {
                    pairs = true;
                    step = step.max((g.at(c + dc, r + dr) - z).abs() as f64);
                }
            }
        }
    }
    if pairs {
        step
    } else if hi >= lo {
        hi - lo
    } else {
        0.0
    }
}

/// How far one grid's surface is from another's samples: the largest and RMS difference
/// between `other`'s bilinear surface and every valid sample of `grid` where that surface is
/// defined, and how many samples that was.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Deviation {
    /// The largest difference, in metres.
    pub max_m: f64,
    /// The RMS difference, in metres.
    pub rms_m: f64,
    /// How many samples of `grid` were compared.
    pub samples: u64,
}

/// The deviation of `other` from `grid`'s samples; None where they share no ground.
pub fn deviation(grid: &Grid, other: &Grid) -> Option<Deviation> {
    deviation_across(grid, other, &other.world_bounds(), &Some)
}

/// [`deviation`] between grids of two planes: `to_other` carries a point of `grid`'s plane
/// to `other`'s (None where it has no image), and `bounds` bounds `other`'s samples in
/// `grid`'s plane.
pub fn deviation_across(
    grid: &Grid,
    other: &Grid,
    bounds: &patchwork_geom::Aabb,
    to_other: &(dyn Fn([f64; 2]) -> Option<[f64; 2]> + Sync),
) -> Option<Deviation> {
    // Only the samples of `grid` under `other`'s bounds can meet it.
    let (lo, hi) = grid.shape().grid_bounds(bounds);
    let range = |k: usize, n: usize| {
        let a = lo[k].floor().max(0.0);
        let z = hi[k].ceil().min(n as f64 - 1.0);
        (a <= z).then_some((a as usize, z as usize))
    };
    let (c0, c1) = range(0, grid.cols)?;
    let (r0, r1) = range(1, grid.rows)?;
    let (worst, sum, n) = (r0..=r1)
        .into_par_iter()
        .map(|r| {
            let mut acc = (0.0f64, 0.0f64, 0u64);
            for c in c0..=c1 {
                let z = grid.at(c, r);
                if z.is_nan() {
                    continue;
                }
                let p = grid.georef.to_world(c as f64, r as f64);
                if let Some(h) = to_other(p).and_then(|q| other.bilinear(q)) {
                    let d = (h - z as f64).abs();
                    acc = (acc.0.max(d), acc.1 + d * d, acc.2 + 1);
                }
            }
            acc
        })
        .reduce(
            || (0.0, 0.0, 0),
            |a, b| (a.0.max(b.0), a.1 + b.1, a.2 + b.2),
        );
    (n > 0).then(|| Deviation {
        max_m: worst,
        rms_m: (sum / n as f64).sqrt(),
        samples: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Georef;

    #[test]
    fn row_decimation_errors_are_the_per_sample_definition_bit_for_bit() {
        // The definition, one sample at a time.
        let one = |g: &Grid, f: usize, c: usize, r: usize| -> Option<f64> {
            if c.is_multiple_of(f) && r.is_multiple_of(f) {
                return None;
            }
            let (i, j) = (c / f * f, r / f * f);
            if i + f >= g.cols || j + f >= g.rows {
                return None;
            }
            let z = g.at(c, r) as f64;
            let (z00, z10) = (g.at(i, j) as f64, g.at(i + f, j) as f64);
            let (z01, z11) = (g.at(i, j + f) as f64, g.at(i + f, j + f) as f64);
            let fx = (c - i) as f64 / f as f64;
            let fy = (r - j) as f64 / f as f64;
            let top = z00 + (z10 - z00) * fx;
            let bottom = z01 + (z11 - z01) * fx;
            let d = (top + (bottom - top) * fy - z).abs();
            (!d.is_nan()).then_some(d)
        };
        let (cols, rows) = (23, 18);
        let samples: Vec<f32> = (0..cols * rows)
            .map(|k| {
                if k % 29 == 3 {
                    f32::NAN
                } else {
                    ((k as f32) * 0.731).sin() * 40.0 + (k % 7) as f32
                }
            })
            .collect();
        let g = Grid::new(
            cols,
            rows,
            samples,
            Georef::north_up([0.0, 0.0], [1.0, 1.0]),
        )
        .unwrap();
        let mut out = vec![0.0; cols];
        for f in [2, 4] {
            for r in 0..rows {
                decimation_errors(&g, f, r, &mut out);
                for (c, got) in out.iter().enumerate() {
                    match one(&g, f, c, r) {
                        Some(d) => assert_eq!(got.to_bits(), d.to_bits(), "f {f} at {c},{r}"),
                        None => assert!(got.is_nan(), "f {f} at {c},{r}: {got}"),
                    }
                }
            }
        }
    }

    fn grid(n: usize, f: impl Fn(f64, f64) -> f64) -> Grid {
        let s = (0..n * n)
            .map(|k| f((k % n) as f64, (k / n) as f64) as f32)
            .collect();
        Grid::new(n, n, s, Georef::north_up([0.0, 0.0], [1.0, 1.0])).unwrap()
    }

    #[test]
    fn a_grid_too_small_to_measure_is_not_taken_as_exact() {
        let g = Grid::new(
            2,
            6,
            vec![0.0, 4.0, 1.0, 5.0, 2.0, 6.0, 3.0, 9.0, 4.0, 8.0, 5.0, 7.0],
            Georef::north_up([0.0, 0.0], [1.0, 1.0]),
        )
        .unwrap();
        let e = estimate(&g, &Tiling::new(g.cells(), 28, [0, 0]), 2);
        // Nothing is decimated away, so half the largest step between neighbours: 6 m / 2.
        assert_eq!(e.kernels.max(), 3.0);
    }

    #[test]
    fn a_plane_is_exact_and_a_paraboloid_is_quadratic() {
        let plane = grid(60, |x, y| 3.0 * x - 2.0 * y + 7.0);
        let t = Tiling::new(plane.cells(), 28, [0, 0]);
        let e = estimate(&plane, &t, 2);
        assert!(e.kernels.max() < 1e-4, "{e:?}");
        let bowl = grid(60, |x, y| 0.05 * (x * x + y * y));
        let e = estimate(&bowl, &t, 2);
        assert!((e.alpha - 2.0).abs() < 0.05, "α = {}", e.alpha);
        // The bilinear error of a paraboloid over a unit cell is (a/4)(1/2·1/2)·2 at its centre.
        let truth = 0.05 * 0.25 * 2.0;
        for &v in &e.kernels.values {
            assert!((v - truth).abs() < 0.2 * truth, "{v} vs {truth}");
        }
    }
}
