//! Two surveys of the same ground, compared as DEM analysts compare them: how one lies
//! against the other (coregistration: a horizontal shift and a vertical offset), and which
//! of the two is a degraded version of the other (blurred, decimated, resampled), which
//! decides whose accuracy claim a disagreement between them contradicts.
//!
//! # Coregistration
//!
//! The shift s and offset dz that make `other(p + s) = reference(p) + dz` best, over the
//! reference's samples in the overlap. The method is Nuth and Kääb's (2011): a shift s moves
//! the difference at a point by the slope along s, dh ≈ ∇h · s + dz, so the shift follows from
//! a fit of the differences against the terrain's slope and aspect. Nuth and Kääb fit it as
//! dh / tan α = a·cos(b − ψ) + c over slope α and aspect ψ; that is the same linear model as
//! dh = ∂h/∂x · sx + ∂h/∂y · sy + dz, which is solved here by least squares in that form,
//! iterated (each step re-evaluates `other` at the shifted points and its gradient there),
//! with differences beyond three NMADs left out as outliers (trees, buildings, voids filled).
//! The linearisation holds near the answer, so a search over whole-cell shifts (a robust
//! cross-correlation) first finds the basin. On real copies shifted by up to 5.4 cells the
//! fit alone, iterated from no shift, converged as well, and the search alone was off by the
//! fraction of a cell (docs/MODEL.md, "Overlaps"); the search is kept for shifts past the
//! fit's reach, at about 40 ms for 600² samples.
//!
//! # Degradation
//!
//! Blurring removes detail and cannot add it; decimating loses what lay between the samples.
//! So if `b` is a degraded copy of `a`, some low-pass of `a`, sampled where `b`'s samples are,
//! predicts `b` well, and no low-pass of `b` predicts `a`, whose detail `b` lacks. Both
//! predictions are tried over Gaussian filters of several widths, after the coregistration's
//! shift and offset; the smaller residual names the degraded one. Where neither predicts the
//! other better (the same content shifted or offset, or two independent surveys), it is
//! undecided.

use super::grid::Grid;
use patchwork_geom::Aabb;
use rayon::prelude::*;

/// Carries a point of one survey's plane into the other's; None where it has no image.
pub type Carry<'a> = &'a (dyn Fn([f64; 2]) -> Option<[f64; 2]> + Sync);

/// At most this many reference samples take part in a coregistration: spread evenly over the
/// overlap, they fix a shift to hundredths of a cell.
const MOST_POINTS: usize = 60_000;
/// Points for the whole-cell search, and its reach in cells of the coarser survey.
const SEARCH_POINTS: usize = 3_000;
const SEARCH_CELLS: i32 = 13;

/// Where the other's content lies against the reference's: the reference's point p is found
/// in the other at `p + shift + linear · (p − centre)`. A shift alone where `linear` is zero;
/// a rotation, a stretch or a shear about the overlap's centre besides (a copy turned by half
/// a degree is 5 cells off at the edge of a 1,200-cell overlap, which no shift mends).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placement {
    /// The point the linear part turns about: the middle of the overlap, in the reference's
    /// plane.
    pub centre: [f64; 2],
    /// The move at the centre, in the reference plane's units.
    pub shift: [f64; 2],
    /// The linear part beyond the identity, row-major: zero for a shift alone.
    pub linear: [[f64; 2]; 2],
}

impl Placement {
    /// A shift alone.
    pub fn shift(shift: [f64; 2]) -> Placement {
        Placement {
            centre: [0.0, 0.0],
            shift,
            linear: [[0.0; 2]; 2],
        }
    }

    /// Where the reference's point `p` is found in the other (in the reference's plane).
    #[inline]
    pub fn forth(&self, p: [f64; 2]) -> [f64; 2] {
        let d = [p[0] - self.centre[0], p[1] - self.centre[1]];
        let l = &self.linear;
        [
            p[0] + self.shift[0] + l[0][0] * d[0] + l[0][1] * d[1],
            p[1] + self.shift[1] + l[1][0] * d[0] + l[1][1] * d[1],
        ]
    }

    /// The reference's point that [`Self::forth`] takes to `q`.
    #[inline]
    pub fn back(&self, q: [f64; 2]) -> [f64; 2] {
        let l = &self.linear;
        let m = [[1.0 + l[0][0], l[0][1]], [l[1][0], 1.0 + l[1][1]]];
        let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
        let e = [
            q[0] - self.centre[0] - self.shift[0],
            q[1] - self.centre[1] - self.shift[1],
        ];
        [
            self.centre[0] + (m[1][1] * e[0] - m[0][1] * e[1]) / det,
            self.centre[1] + (m[0][0] * e[1] - m[1][0] * e[0]) / det,
        ]
    }

    /// The largest move over `bounds` (at one of its corners, the move being affine), in the
    /// reference plane's units.
    pub fn largest_move(&self, bounds: &Aabb) -> f64 {
        [
            bounds.min,
            [bounds.max[0], bounds.min[1]],
            [bounds.min[0], bounds.max[1]],
            bounds.max,
        ]
        .iter()
        .map(|&p| {
            let q = self.forth(p);
            (q[0] - p[0]).hypot(q[1] - p[1])
        })
        .fold(0.0, f64::max)
    }

    /// The rotation of the linear part, degrees anticlockwise, and its scale (the root of its
    /// determinant): what a listing reports of it.
    pub fn rotation_and_scale(&self) -> (f64, f64) {
        let l = &self.linear;
        let m = [[1.0 + l[0][0], l[0][1]], [l[1][0], 1.0 + l[1][1]]];
        let angle = (m[1][0] - m[0][1]).atan2(m[0][0] + m[1][1]).to_degrees();
        let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
        (angle, det.abs().sqrt())
    }
}

/// How one survey lies against another.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Coregistration {
    /// `other(p + shift) ≈ reference(p) + dz`: where the other's content lies relative to the
    /// reference's at the overlap's centre, in the reference plane's units.
    pub shift: [f64; 2],
    /// The other's heights less the reference's at the overlap's centre, in metres.
    pub dz: f64,
    /// The overlap's centre, in the reference's plane: what `linear` turns about and `tilt`
    /// is measured from.
    pub centre: [f64; 2],
    /// Half the overlap's width and height, in the reference plane's units: how far from the
    /// centre the placement reaches.
    pub half_extent: [f64; 2],
    /// The placement's linear part beyond the identity (see [`Placement`]): zero unless a
    /// rotation, stretch or shear fits the overlap markedly better than a shift alone.
    pub linear: [[f64; 2]; 2],
    /// The vertical difference's slope, metres per unit of the reference's plane, east and
    /// north: `other ≈ reference + dz + tilt · (p − centre)`. Zero with the shift alone.
    pub tilt: [f64; 2],
    /// RMS of the differences as the surveys lie, in metres.
    pub rms_before: f64,
    /// RMS once placed and offset.
    pub rms_after: f64,
    /// The normalised median absolute deviation of the differences once placed: the spread
    /// that outliers do not inflate.
    pub nmad_after: f64,
    /// How many reference samples the figures once placed and offset are over.
    pub samples: u64,
    /// Whether the shift is determined: enough samples, relief in every direction (the
    /// shift's standard error along the flattest direction under [`MOST_SHIFT_ERROR`]
    /// cells), and an overlap at least [`LEAST_WIDTH`] coarse cells wide. A thin, low-relief
    /// strip of coast is not: any shift fits it about as well, and the one found blames
    /// nobody.
    pub conditioned: bool,
}

impl Coregistration {
    /// Where the other's content lies.
    pub fn placement(&self) -> Placement {
        Placement {
            centre: self.centre,
            shift: self.shift,
            linear: self.linear,
        }
    }

    /// The largest move the placement makes over the overlap.
    pub fn largest_move(&self) -> f64 {
        let [c, e] = [self.centre, self.half_extent];
        self.placement().largest_move(&Aabb::new(
            c[0] - e[0],
            c[1] - e[1],
            c[0] + e[0],
            c[1] + e[1],
        ))
    }

    /// The largest vertical difference the offset and tilt make over the overlap: at its
    /// centre the offset, at a corner the offset and the tilt's reach.
    pub fn largest_rise(&self) -> f64 {
        let [e, n] = self.half_extent;
        self.dz.abs() + self.tilt[0].abs() * e + self.tilt[1].abs() * n
    }

    /// The other's height less the reference's at the reference's point `p`, once placed.
    pub fn dz_at(&self, p: [f64; 2]) -> f64 {
        self.dz + self.tilt[0] * (p[0] - self.centre[0]) + self.tilt[1] * (p[1] - self.centre[1])
    }

    /// The same figures with the surveys read as they lie (no placement, no tilt): what the
    /// tests of detail read where the placement is not determined.
    pub fn as_they_lie(&self) -> Coregistration {
        Coregistration {
            shift: [0.0, 0.0],
            linear: [[0.0; 2]; 2],
            tilt: [0.0, 0.0],
            ..*self
        }
    }
}

/// How much a rotation, stretch or shear (with a vertical tilt) must lower the spread of the
/// differences left by the best shift for it to be kept at once: by a tenth. Six more
/// parameters fit noise a little better whatever the truth; a copy turned by half a degree, or
/// stretched by half a percent, leaves a spread 2–10 times that of its shift's fit.
pub const AFFINE_GAIN: f64 = 0.9;

/// Where the spread falls by less, how consistently the overlap's parts must agree on a
/// placement that explains enough ([`AFFINE_EXPLAINS`]) for it to be kept: the F statistic of its six
/// more parameters, their covariance taken from the fits that leave out one block of
/// [`JACKKNIFE_BLOCKS`]² in turn, at least this. A copy turned by a tenth of a degree and
/// resampled by a cubic, over rough ground of 1 km cells, lowers the spread by 4% only (the
/// rest is the two interpolations' own difference), yet every part of it turns alike: F =
/// 1,536. Residuals correlated over many cells make a count of samples overstate the evidence
/// (a blur of σ 2–3 cells reads as F = 27–33 counted so); blocks do not, and the pairs of the
/// tests that no placement explains (blurs, noise, independent surveys, lattices apart)
/// mostly stay under 60.
pub const AFFINE_F: f64 = 100.0;

/// The least share of the differences' variance (over the samples the fit keeps, three NMADs
/// about the centre) that a placement kept by [`AFFINE_F`] must explain: 0.3. The NMAD does
/// not measure it: a turn's misfit lies on the steep ground, in the tails, and a copy turned by
/// −0.1° leaves the NMAD as it was (1.853 → 1.851 m) while its turn explains 52% of the
/// variance (turned +0.1°, 51%). A blur's differences fit a stretch or a shear consistently
/// where the ground is one shape throughout (a blurred hill is a shrunk one): smoothed copies
/// of the tests reach F = 100–146, explaining 6–17%.
pub const AFFINE_EXPLAINS: f64 = 0.3;

/// The blocks a side of the overlap is cut into for [`AFFINE_F`]'s covariance.
pub const JACKKNIFE_BLOCKS: usize = 6;

/// The fewest samples that determine a shift.
pub const LEAST_SAMPLES: u64 = 1000;
/// The narrowest overlap, in cells of the coarser survey, that determines a shift.
pub const LEAST_WIDTH: f64 = 8.0;
/// The largest standard error of a determined shift, in cells of the coarser survey.
pub const MOST_SHIFT_ERROR: f64 = 0.1;

/// Every `stride`-th valid sample of `g` inside `bounds`, by rows and columns: world position
/// and height.
fn samples_in(g: &Grid, bounds: &Aabb, most: usize) -> Vec<([f64; 2], f64)> {
    let Some(rect) = g.shape().rect_over(bounds) else {
        return Vec::new();
    };
    let n = rect.cols() * rect.rows();
    let stride = ((n as f64 / most as f64).sqrt().ceil() as usize).max(1);
    let mut out = Vec::new();
    for r in (rect.r0..rect.r1).step_by(stride) {
        for c in (rect.c0..rect.c1).step_by(stride) {
            let z = g.at(c, r);
            if z.is_nan() {
                continue;
            }
            let p = g.georef.to_world(c as f64, r as f64);
            if bounds.contains_point(p) {
                out.push((p, z as f64));
            }
        }
    }
    out
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let k = v.len() / 2;
    v.select_nth_unstable_by(k, f64::total_cmp);
    v[k]
}

/// The median and the normalised median absolute deviation.
fn robust(v: &[f64]) -> (f64, f64) {
    let m = median(v.to_vec());
    let mad = median(v.iter().map(|d| (d - m).abs()).collect());
    (m, 1.4826 * mad)
}

/// One side's step, in the reference plane's units: how far apart the other's samples are
/// seen from the reference (the larger of the two steps, so that a search step moves both by
/// at most a cell).
fn coarser_step(reference: &Grid, other: &Grid, carry: Carry, at: [f64; 2]) -> f64 {
    let own = reference.georef.step[0].min(reference.georef.step[1]);
    let (Some(a), Some(b)) = (carry(at), carry([at[0] + own, at[1]])) else {
        return own;
    };
    let seen = (b[0] - a[0]).hypot(b[1] - a[1]);
    let theirs = other.georef.step[0].min(other.georef.step[1]);
    if seen > 0.0 {
        own.max(own * theirs / seen)
    } else {
        own
    }
}

/// How a coregistration is found: the store's is [`Method::SearchThenFit`]; the others are
/// its halves, which the bench measures beside it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    /// Whole-cell shifts only, by the spread of the differences: a robust cross-correlation.
    Search,
    /// Nuth and Kääb's fit, iterated from no shift.
    Fit,
    /// The search, then the fit from where it lands: the store's method.
    SearchThenFit,
}

/// How `other` lies against `reference` over `bounds` (the overlap, in the reference's
/// plane); `carry` takes the reference's plane to the other's. None where they share too
/// little ground to say.
pub fn coregister(
    reference: &Grid,
    other: &Grid,
    carry: Carry,
    bounds: &Aabb,
) -> Option<Coregistration> {
    coregister_by(Method::SearchThenFit, reference, other, carry, bounds)
}

/// [`coregister`] by one `method`.
pub fn coregister_by(
    method: Method,
    reference: &Grid,
    other: &Grid,
    carry: Carry,
    bounds: &Aabb,
) -> Option<Coregistration> {
    let pts = samples_in(reference, bounds, MOST_POINTS);
    let at = |p: [f64; 2], s: [f64; 2]| -> Option<f64> {
        other.bilinear(carry([p[0] + s[0], p[1] + s[1]])?)
    };
    let diffs = |s: [f64; 2], pts: &[([f64; 2], f64)]| -> Vec<f64> {
        pts.par_iter()
            .filter_map(|&(p, z)| Some(at(p, s)? - z))
            .collect()
    };
    let before = diffs([0.0, 0.0], &pts);
    if before.len() < 64 {
        return None;
    }
    let rms = |v: &[f64], dz: f64| {
        (v.iter().map(|d| (d - dz) * (d - dz)).sum::<f64>() / v.len() as f64).sqrt()
    };
    let rms_before = rms(&before, 0.0);

    // The basin: whole-cell shifts of the coarser survey, on a few thousand points, by the
    // spread of the differences (which an offset does not change).
    let step = coarser_step(reference, other, carry, pts[pts.len() / 2].0);
    let few: Vec<([f64; 2], f64)> = pts
        .iter()
        .step_by((pts.len() / SEARCH_POINTS).max(1))
        .copied()
        .collect();
    let mut best = ([0.0, 0.0], f64::INFINITY);
    let reach = if method == Method::Fit {
        0
    } else {
        SEARCH_CELLS
    };
    for j in -reach..=reach {
        for i in -reach..=reach {
            let s = [i as f64 * step, j as f64 * step];
            let d = diffs(s, &few);
            // A shift that leaves most points without a partner is no answer.
            if d.len() * 2 < few.len() {
                continue;
            }
            let spread = robust(&d).1;
            if spread < best.1 {
                best = (s, spread);
            }
        }
    }
    let mut s = best.0;
    let mut dz = robust(&diffs(s, &pts)).0;
    // The slopes' second moments at the last step: how well the terrain fixes a shift.
    let mut slopes = [0.0f64; 3];

    // Nuth and Kääb's fit, iterated from there.
    let h = step * 0.5;
    let rounds = if method == Method::Search { 0 } else { 30 };
    for _ in 0..rounds {
        let rows: Vec<([f64; 3], f64)> = pts
            .par_iter()
            .filter_map(|&(p, z)| {
                let q = [p[0] + s[0], p[1] + s[1]];
                let here = other.bilinear(carry(q)?)?;
                let gx = (at(q, [h, 0.0])? - at(q, [-h, 0.0])?) / (2.0 * h);
                let gy = (at(q, [0.0, h])? - at(q, [0.0, -h])?) / (2.0 * h);
                Some(([gx, gy, -1.0], here - z - dz))
            })
            .collect();
        if rows.len() < 64 {
            return None;
        }
        let r: Vec<f64> = rows.iter().map(|x| x.1).collect();
        let (m, nmad) = robust(&r);
        let keep = 3.0 * nmad.max(1e-6);
        let mut n = [[0.0f64; 3]; 3];
        let mut b = [0.0f64; 3];
        for (g, d) in rows.iter().filter(|x| (x.1 - m).abs() <= keep) {
            add_row(&mut n, &mut b, g, *d);
        }
        let kept = rows
            .iter()
            .filter(|x| (x.1 - m).abs() <= keep)
            .count()
            .max(1) as f64;
        slopes = [n[0][0] / kept, n[0][1] / kept, n[1][1] / kept];
        let Some(x) = solve3(n, b) else {
            break;
        };
        s = [s[0] + x[0], s[1] + x[1]];
        dz += x[2];
        if x[0].hypot(x[1]) < 1e-3 * step && x[2].abs() < 1e-3 {
            break;
        }
        // A step past the search's reach means the fit has lost the basin.
        if s[0].abs().max(s[1].abs()) > (SEARCH_CELLS + 2) as f64 * step {
            s = best.0;
            break;
        }
    }
    let after = diffs(s, &pts);
    if after.len() < 64 {
        return None;
    }
    let (m, nmad_after) = robust(&after);
    // The offset as the robust centre of what is left, so that outliers do not pull it.
    let dz = m;
    // The flattest direction's RMS slope: the smaller eigenvalue of the slopes' moments.
    let [sxx, sxy, syy] = slopes;
    let flattest = (0.5 * (sxx + syy - ((sxx - syy).powi(2) + 4.0 * sxy * sxy).sqrt()))
        .max(0.0)
        .sqrt();
    let (w, h) = (bounds.max[0] - bounds.min[0], bounds.max[1] - bounds.min[1]);
    // The shift's standard error along the flattest direction, in coarse cells: the spread
    // left over the slope, over the root of the independent samples. Residuals are
    // correlated over a few cells, so a block of 3 × 3 coarse cells counts once.
    let independent = ((w * h) / (9.0 * step * step))
        .min(after.len() as f64)
        .max(1.0);
    let error_cells = nmad_after / (flattest * step * independent.sqrt());
    let conditioned = after.len() as u64 >= LEAST_SAMPLES
        && w.min(h) >= LEAST_WIDTH * step
        && error_cells <= MOST_SHIFT_ERROR;
    let centre = [
        0.5 * (bounds.min[0] + bounds.max[0]),
        0.5 * (bounds.min[1] + bounds.max[1]),
    ];
    let shifted = Coregistration {
        shift: s,
        dz,
        centre,
        half_extent: [0.5 * w, 0.5 * h],
        linear: [[0.0; 2]; 2],
        tilt: [0.0, 0.0],
        rms_before,
        rms_after: rms(&after, dz),
        nmad_after,
        samples: after.len() as u64,
        conditioned,
    };
    if method == Method::Search {
        return Some(shifted);
    }
    // A rotation, stretch or shear, and a tilt, fitted from the shift's answer; kept only
    // where it explains the differences markedly better.
    let radius = 0.5 * w.max(h);
    let placed = fit_affine(&pts, &at, step, radius, &shifted)?;
    let left: Vec<f64> = pts
        .par_iter()
        .filter_map(|&(p, z)| {
            let q = placed.placement().forth(p);
            Some(at(q, [0.0, 0.0])? - z - (placed.dz_at(p) - placed.dz))
        })
        .collect();
    if (left.len() as u64) < LEAST_SAMPLES.min(after.len() as u64) {
        return Some(shifted);
    }
    let (m, nmad) = robust(&left);
    // The jackknife reads the samples once more: only where the tenth does not settle it.
    let kept = nmad < AFFINE_GAIN * nmad_after || {
        let (f, share) = affine_f(&pts, &at, step, radius, bounds, &placed);
        share >= AFFINE_EXPLAINS && f >= AFFINE_F
    };
    if !kept {
        return Some(shifted);
    }
    Some(Coregistration {
        dz: m,
        rms_after: rms(&left, m),
        nmad_after: nmad,
        samples: left.len() as u64,
        ..placed
    })
}

/// The columns of the affine fit's rows (see [`affine_rows`]) beyond the shift and offset:
/// the linear part's four and the tilt's two.
const BEYOND_SHIFT: [usize; 6] = [2, 3, 4, 5, 7, 8];

/// Adds one row `g` with difference `d` to the normal equations `n x = b` of a least-squares
/// fit of the difference's change (`b` gathers −g d).
fn add_row<const N: usize>(n: &mut [[f64; N]; N], b: &mut [f64; N], g: &[f64; N], d: f64) {
    for i in 0..N {
        for j in 0..N {
            n[i][j] += g[i] * g[j];
        }
        b[i] -= g[i] * d;
    }
}

/// The F statistic of an affine placement's six parameters beyond the shift (its linear part
/// and tilt), by a block jackknife: the overlap cut into [`JACKKNIFE_BLOCKS`]² blocks, the
/// fit with each block left out is one Gauss–Newton step from `placed` (the normal equations
/// less that block's), and the spread of those fits is the parameters' covariance. Hotelling's
/// T² over it, scaled to F with 6 and K − 6 degrees of freedom for K blocks that hold
/// samples; NaN where too few blocks hold samples to say. With it, the share of the
/// differences' variance the six explain (see [`AFFINE_EXPLAINS`]).
fn affine_f(
    pts: &[([f64; 2], f64)],
    at: &(dyn Fn([f64; 2], [f64; 2]) -> Option<f64> + Sync),
    step: f64,
    radius: f64,
    bounds: &Aabb,
    placed: &Coregistration,
) -> (f64, f64) {
    const B: usize = JACKKNIFE_BLOCKS;
    let cell = |x: f64, lo: f64, hi: f64| {
        (((x - lo) / (hi - lo) * B as f64).floor().max(0.0) as usize).min(B - 1)
    };
    let rows: Vec<(usize, [f64; 9], f64)> = affine_rows(pts, at, step, radius, placed)
        .into_iter()
        .map(|(p, g, d)| {
            let block = cell(p[1], bounds.min[1], bounds.max[1]) * B
                + cell(p[0], bounds.min[0], bounds.max[0]);
            (block, g, d)
        })
        .collect();
    let r: Vec<f64> = rows.iter().map(|x| x.2).collect();
    let (m, nmad) = robust(&r);
    let keep = 3.0 * nmad.max(1e-6);
    let mut n = vec![[[0.0f64; 9]; 9]; B * B];
    let mut b = vec![[0.0f64; 9]; B * B];
    let mut count = vec![0usize; B * B];
    for (k, g, d) in rows.iter().filter(|x| (x.2 - m).abs() <= keep) {
        add_row(&mut n[*k], &mut b[*k], g, *d);
        count[*k] += 1;
    }
    let (mut all_n, mut all_b) = ([[0.0f64; 9]; 9], [0.0f64; 9]);
    for k in 0..B * B {
        for i in 0..9 {
            for j in 0..9 {
                all_n[i][j] += n[k][i][j];
            }
            all_b[i] += b[k][i];
        }
    }
    // A block with a handful of samples barely moves a fit and would shrink the spread.
    let least = rows.len() / (4 * B * B);
    // The six parameters as the fit scales them: the linear part and the tilt times the
    // radius.
    let theta = [
        placed.linear[0][0] * radius,
        placed.linear[0][1] * radius,
        placed.linear[1][0] * radius,
        placed.linear[1][1] * radius,
        placed.tilt[0] * radius,
        placed.tilt[1] * radius,
    ];
    // The share of the differences' variance (over the samples the fit kept) that the six
    // explain: the fit's residuals are orthogonal to its columns, so the variance left by the
    // shift alone is about the residuals' plus the six parameters' part.
    let (mut left, mut explained) = (0.0, 0.0);
    for (_, g, d) in rows.iter().filter(|x| (x.2 - m).abs() <= keep) {
        let c: f64 = BEYOND_SHIFT.iter().zip(theta).map(|(&j, t)| g[j] * t).sum();
        left += (d - m) * (d - m);
        explained += c * c;
    }
    let share = explained / (left + explained);
    let mut leave: Vec<[f64; 6]> = Vec::new();
    for k in (0..B * B).filter(|&k| count[k] > least.max(9)) {
        let mut nk = all_n;
        let mut bk = all_b;
        for i in 0..9 {
            for j in 0..9 {
                nk[i][j] -= n[k][i][j];
            }
            bk[i] -= b[k][i];
        }
        let Some(x) = solve(nk, bk) else { continue };
        let mut t = theta;
        for (i, at) in BEYOND_SHIFT.into_iter().enumerate() {
            t[i] += x[at];
        }
        leave.push(t);
    }
    let kk = leave.len();
    if kk < 12 {
        return (f64::NAN, share);
    }
    let mut mean = [0.0f64; 6];
    for t in &leave {
        for i in 0..6 {
            mean[i] += t[i] / kk as f64;
        }
    }
    let mut cov = [[0.0f64; 6]; 6];
    for t in &leave {
        for i in 0..6 {
            for j in 0..6 {
                cov[i][j] += (t[i] - mean[i]) * (t[j] - mean[j]) * (kk - 1) as f64 / kk as f64;
            }
        }
    }
    let Some(y) = solve(cov, theta) else {
        return (f64::NAN, share);
    };
    let t2: f64 = (0..6).map(|i| theta[i] * y[i]).sum();
    (t2 * (kk - 6) as f64 / (6.0 * (kk - 1) as f64), share)
}

/// The rows of the affine fit at placement `k`: for each sample p of the reference that the
/// other covers, p, the difference's derivatives by the nine unknowns (the shift, the linear
/// part, the offset and the tilt, d = p − centre scaled by `radius`), and the difference left.
fn affine_rows(
    pts: &[([f64; 2], f64)],
    at: &(dyn Fn([f64; 2], [f64; 2]) -> Option<f64> + Sync),
    step: f64,
    radius: f64,
    k: &Coregistration,
) -> Vec<([f64; 2], [f64; 9], f64)> {
    let h = step * 0.5;
    let place = k.placement();
    pts.par_iter()
        .filter_map(|&(p, z)| {
            let q = place.forth(p);
            let here = at(q, [0.0, 0.0])?;
            let gx = (at(q, [h, 0.0])? - at(q, [-h, 0.0])?) / (2.0 * h);
            let gy = (at(q, [0.0, h])? - at(q, [0.0, -h])?) / (2.0 * h);
            let (u, v) = ((p[0] - k.centre[0]) / radius, (p[1] - k.centre[1]) / radius);
            Some((
                p,
                [gx, gy, gx * u, gx * v, gy * u, gy * v, -1.0, -u, -v],
                here - z - k.dz_at(p),
            ))
        })
        .collect()
}

/// Nuth and Kääb's fit widened to an affine placement and a plane: the difference at the
/// reference's point p, with d = p − centre, moves by ∇h · (shift + L·d) − (dz + k·d) for a
/// change of the shift, the linear part L, the offset and the tilt k, nine unknowns solved
/// by least squares over the same samples, iterated from `start` (the shift's answer), with
/// differences beyond three NMADs left out. `radius` scales d to about one, so that the
/// normal equations stay balanced. None where the fit does not settle.
fn fit_affine(
    pts: &[([f64; 2], f64)],
    at: &(dyn Fn([f64; 2], [f64; 2]) -> Option<f64> + Sync),
    step: f64,
    radius: f64,
    start: &Coregistration,
) -> Option<Coregistration> {
    let mut k = *start;
    for _ in 0..30 {
        let rows: Vec<([f64; 9], f64)> = affine_rows(pts, at, step, radius, &k)
            .into_iter()
            .map(|(_, g, d)| (g, d))
            .collect();
        if rows.len() < 64 {
            return None;
        }
        let r: Vec<f64> = rows.iter().map(|x| x.1).collect();
        let (m, nmad) = robust(&r);
        let keep = 3.0 * nmad.max(1e-6);
        let mut n = [[0.0f64; 9]; 9];
        let mut b = [0.0f64; 9];
        for (g, d) in rows.iter().filter(|x| (x.1 - m).abs() <= keep) {
            add_row(&mut n, &mut b, g, *d);
        }
        let x = solve(n, b)?;
        k.shift = [k.shift[0] + x[0], k.shift[1] + x[1]];
        k.linear[0][0] += x[2] / radius;
        k.linear[0][1] += x[3] / radius;
        k.linear[1][0] += x[4] / radius;
        k.linear[1][1] += x[5] / radius;
        k.dz += x[6];
        k.tilt = [k.tilt[0] + x[7] / radius, k.tilt[1] + x[8] / radius];
        // Settled when nothing moves any point by a thousandth of a cell, or its height by
        // a millimetre.
        let moved = x[..6].iter().map(|v| v.abs()).fold(0.0, f64::max);
        let lifted = x[6..].iter().map(|v| v.abs()).fold(0.0, f64::max);
        if moved < 1e-3 * step && lifted < 1e-3 {
            break;
        }
        // A placement that moves the overlap's corners past the search's reach has lost the
        // basin, and one that folds the plane (a determinant near zero) is no copy's.
        let l = &k.linear;
        let det = (1.0 + l[0][0]) * (1.0 + l[1][1]) - l[0][1] * l[1][0];
        let far = (k.shift[0].abs() + k.shift[1].abs())
            + radius * l.iter().flatten().map(|v| v.abs()).sum::<f64>();
        if !(det > 0.5 && far <= 2.0 * (SEARCH_CELLS + 2) as f64 * step) {
            return None;
        }
    }
    Some(k)
}

/// The n × n system `m x = b` by Gaussian elimination with partial pivoting; None when
/// singular (or NaN).
pub(crate) fn solve<const N: usize>(mut m: [[f64; N]; N], mut b: [f64; N]) -> Option<[f64; N]> {
    let scale = m.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
    for col in 0..N {
        let pivot = (col..N).max_by(|&i, &j| m[i][col].abs().total_cmp(&m[j][col].abs()))?;
        if m[pivot][col].abs().partial_cmp(&(1e-12 * scale)) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        m.swap(col, pivot);
        b.swap(col, pivot);
        let (top, below) = m.split_at_mut(col + 1);
        let pivot_row = &top[col];
        for (i, row) in below.iter_mut().enumerate() {
            let f = row[col] / pivot_row[col];
            for (x, p) in row[col..].iter_mut().zip(&pivot_row[col..]) {
                *x -= f * p;
            }
            b[col + 1 + i] -= f * b[col];
        }
    }
    let mut x = [0.0; N];
    for row in (0..N).rev() {
        let s: f64 = (row + 1..N).map(|k| m[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / m[row][row];
    }
    Some(x)
}

/// The 3 × 3 system `n x = b` by Cramer's rule; None when singular.
fn solve3(n: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(&n);
    let scale = n.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
    // NaN fails the test too.
    if d.abs().partial_cmp(&(1e-12 * scale.powi(3))) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let mut x = [0.0; 3];
    for (k, xk) in x.iter_mut().enumerate() {
        let mut m = n;
        for i in 0..3 {
            m[i][k] = b[i];
        }
        *xk = det(&m) / d;
    }
    Some(x)
}

/// The filter widths tried, in cells of the filtered survey.
pub const SIGMAS: [f64; 8] = [0.0, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0];

/// How well one survey is predicted from a low-pass of the other: the residual's RMS and the
/// filter width that gives it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prediction {
    /// RMS of the residual about its median, in metres.
    pub rms: f64,
    /// The filter width that gives it, in cells of the filtered survey: one of [`SIGMAS`].
    pub sigma: f64,
}

/// Which of two surveys is a degraded version of the other.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Degradation {
    /// The other predicted from the reference.
    pub other_from_reference: Prediction,
    /// The reference predicted from the other.
    pub reference_from_other: Prediction,
}

/// The side a comparison finds degraded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Degraded {
    /// The reference is the degraded copy.
    Reference,
    /// The other is the degraded copy.
    Other,
    /// Neither predicts the other clearly better.
    Undecided,
}

/// How much better one prediction must be for its target to count as degraded. Blurred,
/// resampled and decimated copies of real crops measure 0–0.22 (docs/MODEL.md, "Overlaps");
/// a copy with white noise added measures 0.6–0.85 the wrong way round, since a low-pass of
/// the noisy one predicts the clean one better than the clean one predicts noise. Noise
/// raises the noisy copy's own estimate instead.
pub const DEGRADED_RATIO: f64 = 0.35;

impl Degradation {
    /// The degraded side: the one predicted from the other with a residual under
    /// [`DEGRADED_RATIO`] times that of the reverse prediction.
    pub fn degraded(&self) -> Degraded {
        let (a, b) = (self.other_from_reference.rms, self.reference_from_other.rms);
        if a < DEGRADED_RATIO * b {
            Degraded::Other
        } else if b < DEGRADED_RATIO * a {
            Degraded::Reference
        } else {
            Degraded::Undecided
        }
    }
}

/// A Gaussian low-pass of a grid, `sigma` cells wide, over its valid samples (each output a
/// weighted mean of the valid samples within 3σ, NaN where they weigh under half the full
/// kernel); σ = 0 is the grid itself.
pub fn blurred(g: &Grid, sigma: f64) -> Grid {
    if sigma <= 0.0 {
        return g.clone();
    }
    let radius = (3.0 * sigma).ceil() as isize;
    let w: Vec<f64> = (-radius..=radius)
        .map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f64 = w.iter().sum();
    let (cols, rows) = (g.cols as isize, g.rows as isize);
    // Rows first, carrying sums of weights so that voids renormalise.
    let pass = |src: &[(f64, f64)], along_rows: bool| -> Vec<(f64, f64)> {
        (0..rows)
            .into_par_iter()
            .flat_map_iter(|r| {
                let w = &w;
                (0..cols).map(move |c| {
                    let (mut s, mut ws) = (0.0, 0.0);
                    for (k, wk) in w.iter().enumerate() {
                        let d = k as isize - radius;
                        let (cc, rr) = if along_rows { (c + d, r) } else { (c, r + d) };
                        if cc < 0 || rr < 0 || cc >= cols || rr >= rows {
                            continue;
                        }
                        let (v, vw) = src[(rr * cols + cc) as usize];
                        s += wk * v;
                        ws += wk * vw;
                    }
                    (s, ws)
                })
            })
            .collect()
    };
    let start: Vec<(f64, f64)> = g
        .samples
        .iter()
        .map(|&z| {
            if z.is_nan() {
                (0.0, 0.0)
            } else {
                (z as f64, 1.0)
            }
        })
        .collect();
    let once = pass(&start, true);
    let twice = pass(&once, false);
    let samples = twice
        .iter()
        .map(|&(s, ws)| {
            if ws >= 0.5 * total * total {
                (s / ws) as f32
            } else {
                f32::NAN
            }
        })
        .collect();
    // The grid's own shape, whatever it is: a window one sample wide is still blurred along
    // its length, where the constructor would refuse it.
    Grid {
        cols: g.cols,
        rows: g.rows,
        samples,
        georef: g.georef,
    }
}

/// At most this many samples a side in the windows a degradation is measured on.
const DEGRADE_SIDE: usize = 256;

/// At most this many windows a side over an overlap.
const DEGRADE_WINDOWS: usize = 3;

/// Windows of at most `DEGRADE_SIDE`² samples of `g` spread evenly over `bounds`: up to
/// `DEGRADE_WINDOWS`² of them, so that the test sees the whole overlap and not one place.
fn windows_over(g: &Grid, bounds: &Aabb) -> Vec<Grid> {
    let Some(rect) = g.shape().rect_over(bounds) else {
        return Vec::new();
    };
    let (w, h) = (rect.cols().min(DEGRADE_SIDE), rect.rows().min(DEGRADE_SIDE));
    if w < 8 || h < 8 {
        return Vec::new();
    }
    let starts = |lo: usize, n: usize, side: usize| -> Vec<usize> {
        let count = n.div_ceil(side).min(DEGRADE_WINDOWS);
        (0..count)
            .map(|i| lo + i * (n - side) / (count - 1).max(1))
            .collect()
    };
    let mut out = Vec::new();
    for r0 in starts(rect.r0, rect.rows(), h) {
        for c0 in starts(rect.c0, rect.cols(), w) {
            out.push(g.window(c0, r0, w, h));
        }
    }
    out
}

/// Residuals of one prediction, per width of [`SIGMAS`]: read bilinearly, then by a cubic.
type Residuals = Vec<[Vec<f64>; 2]>;

/// The residuals of `target`'s samples predicted by low-passes of `source`, one list per
/// width of [`SIGMAS`], each sample carried into the source's plane by `to_source` (the
/// coregistration already applied), with `dz(p, q)` added to the prediction of the target's
/// point p carried to q.
fn residuals(
    source: &Grid,
    target: &Grid,
    to_source: Carry,
    dz: &dyn Fn([f64; 2], [f64; 2]) -> f64,
) -> Residuals {
    let pts: Vec<([f64; 2], f64)> = (0..target.rows)
        .flat_map(|r| (0..target.cols).map(move |c| (c, r)))
        .filter_map(|(c, r)| {
            let z = target.at(c, r);
            (!z.is_nan()).then(|| (target.georef.to_world(c as f64, r as f64), z as f64))
        })
        .filter_map(|(p, z)| {
            let q = to_source(p)?;
            Some((q, z - dz(p, q)))
        })
        .collect();
    SIGMAS
        .iter()
        .map(|&sigma| {
            let b = blurred(source, sigma);
            // Only points whose filtered value is whole: 3σ inside the source's samples.
            let margin = 3.0 * sigma + 1.0;
            // Read bilinearly and by a cubic: a copy resampled by a cubic is predicted from
            // its original by a cubic reading to the float's rounding, and the bilinear
            // reading's own smoothing would otherwise hide that (a copy stretched by 1.6% with
            // a cubic was predicted no better than its original, 1.1 m against 0.7).
            let read = |g: [f64; 2], cubic: bool| {
                if cubic {
                    b.cubic_grid(g)
                } else {
                    b.bilinear_grid(g)
                }
            };
            [false, true].map(|cubic| {
                pts.iter()
                    .filter_map(|&(q, z)| {
                        let g = b.georef.to_grid(q);
                        let inside = g[0] >= margin
                            && g[1] >= margin
                            && g[0] <= (b.cols - 1) as f64 - margin
                            && g[1] <= (b.rows - 1) as f64 - margin;
                        inside.then(|| Some(read(g, cubic)? - z)).flatten()
                    })
                    .collect()
            })
        })
        .collect()
}

/// The best prediction over [`SIGMAS`] and both readings, from residuals gathered over
/// several windows.
fn best_prediction(per_sigma: &[[Vec<f64>; 2]]) -> Option<Prediction> {
    let mut best: Option<Prediction> = None;
    for (d, &sigma) in per_sigma
        .iter()
        .zip(SIGMAS.iter())
        .flat_map(|(two, s)| two.iter().map(move |d| (d, s)))
    {
        if d.len() < 32 {
            continue;
        }
        let (m, _) = robust(d);
        let rms = (d.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / d.len() as f64).sqrt();
        if best.is_none_or(|b| rms < b.rms) {
            best = Some(Prediction { rms, sigma });
        }
    }
    best
}

/// Which of `reference` and `other` is the degraded one, over windows spread across their
/// overlap `bounds` (in the reference's plane), once `c` is applied. `to_other` and
/// `to_reference` carry points between the planes.
pub fn degradation(
    reference: &Grid,
    other: &Grid,
    to_other: Carry,
    to_reference: Carry,
    c: &Coregistration,
    bounds: &Aabb,
) -> Option<Degradation> {
    let place = c.placement();
    let back = |q: [f64; 2]| to_reference(q).map(|p| place.back(p));
    let forth = |p: [f64; 2]| to_other(place.forth(p));
    // Room for the widest filter around each window.
    let reach = (3.0 * SIGMAS[SIGMAS.len() - 1] + 2.0)
        * reference.georef.step[0].max(reference.georef.step[1]);
    let corners = |b: &Aabb, r: f64| {
        [
            [b.min[0] - r, b.min[1] - r],
            [b.max[0] + r, b.min[1] - r],
            [b.min[0] - r, b.max[1] + r],
            [b.max[0] + r, b.max[1] + r],
        ]
    };
    let per_window: Vec<(Residuals, Residuals)> = windows_over(reference, bounds)
        .par_iter()
        .filter_map(|a| {
            let wb = a.world_bounds();
            // The other's samples over the window and the filters' reach.
            let there: Vec<[f64; 2]> = corners(&wb, reach)
                .iter()
                .filter_map(|&p| forth(p))
                .collect();
            if there.len() < 4 {
                return None;
            }
            let rect = other.shape().rect_over(&Aabb::of_points(&there))?;
            let b = other.window(rect.c0, rect.r0, rect.cols(), rect.rows());
            // The reference a little wider, so that the other's samples over the window
            // have whole filtered values.
            let wide = Aabb::new(
                wb.min[0] - reach,
                wb.min[1] - reach,
                wb.max[0] + reach,
                wb.max[1] + reach,
            );
            let ra = reference.shape().rect_over(&wide)?;
            let wide = reference.window(ra.c0, ra.r0, ra.cols(), ra.rows());
            // The other's samples over the window only.
            let inner: Vec<[f64; 2]> = corners(&wb, 0.0).iter().filter_map(|&p| forth(p)).collect();
            let rb = other.shape().rect_over(&Aabb::of_points(&inner))?;
            let b_inner = other.window(rb.c0, rb.r0, rb.cols(), rb.rows());
            Some((
                // The offset where the reference's point is: the carried point in the first
                // prediction, the target's own in the second.
                residuals(&wide, &b_inner, &back, &|_, q| c.dz_at(q)),
                residuals(&b, a, &forth, &|p, _| -c.dz_at(p)),
            ))
        })
        .collect();
    let pool = |pick: fn(&(Residuals, Residuals)) -> &Residuals| {
        let mut all = vec![[Vec::new(), Vec::new()]; SIGMAS.len()];
        for w in &per_window {
            for (into, from) in all.iter_mut().zip(pick(w)) {
                into[0].extend_from_slice(&from[0]);
                into[1].extend_from_slice(&from[1]);
            }
        }
        all
    };
    Some(Degradation {
        other_from_reference: best_prediction(&pool(|w| &w.0))?,
        reference_from_other: best_prediction(&pool(|w| &w.1))?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Georef;

    #[test]
    fn a_window_one_sample_wide_is_blurred_along_its_length() {
        // The window of a survey over a narrow overlap may be one column wide, which a grid
        // built from samples could not be: blurring it keeps its shape (and, with half the
        // kernel's weight nowhere within it, leaves nothing measured).
        let samples: Vec<f32> = (0..17).map(|k| (k % 3) as f32).collect();
        let g = Grid {
            cols: 1,
            rows: 17,
            samples,
            georef: Georef::north_up([0.0, 0.0], [1.0, 1.0]),
        };
        let b = blurred(&g, 1.0);
        assert_eq!((b.cols, b.rows), (1, 17));
        assert!(b.samples.iter().all(|z| z.is_nan()), "{:?}", b.samples);
        let wide = Grid {
            cols: 7,
            ..g.clone()
        };
        let wide = Grid {
            samples: (0..7 * 17).map(|k| (k % 3) as f32).collect(),
            ..wide
        };
        let b = blurred(&wide, 1.0);
        assert_eq!((b.cols, b.rows), (7, 17));
        assert!(b.samples[3 * 7 + 3].is_finite());
    }
}
