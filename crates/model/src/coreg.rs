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

/// How one survey lies against another.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Coregistration {
    /// `other(p + shift) ≈ reference(p) + dz`: where the other's content lies relative to the
    /// reference's, in the reference plane's units.
    pub shift: [f64; 2],
    /// The other's heights less the reference's, in metres.
    pub dz: f64,
    /// RMS of the differences as the surveys lie, in metres.
    pub rms_before: f64,
    /// RMS once shifted and offset.
    pub rms_after: f64,
    /// The normalised median absolute deviation of the differences once shifted: the spread
    /// that outliers do not inflate.
    pub nmad_after: f64,
    /// How many reference samples the figures once shifted and offset are over.
    pub samples: u64,
    /// Whether the shift is determined: enough samples, relief in every direction (the
    /// shift's standard error along the flattest direction under [`MOST_SHIFT_ERROR`]
    /// cells), and an overlap at least [`LEAST_WIDTH`] coarse cells wide. A thin, low-relief strip of coast is not: any shift fits it about as well, and
    /// the one found blames nobody.
    pub conditioned: bool,
}

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
            for i in 0..3 {
                for j in 0..3 {
                    n[i][j] += g[i] * g[j];
                }
                b[i] -= g[i] * d;
            }
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
    Some(Coregistration {
        shift: s,
        dz,
        rms_before,
        rms_after: rms(&after, dz),
        nmad_after,
        samples: after.len() as u64,
        conditioned,
    })
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

/// Residuals of one prediction, one list per width of [`SIGMAS`].
type Residuals = Vec<Vec<f64>>;

/// The residuals of `target`'s samples predicted by low-passes of `source`, one list per
/// width of [`SIGMAS`], each sample carried into the source's plane by `to_source` (the
/// coregistration already applied), with `dz` added to the prediction.
fn residuals(source: &Grid, target: &Grid, to_source: Carry, dz: f64) -> Residuals {
    let pts: Vec<([f64; 2], f64)> = (0..target.rows)
        .flat_map(|r| (0..target.cols).map(move |c| (c, r)))
        .filter_map(|(c, r)| {
            let z = target.at(c, r);
            (!z.is_nan()).then(|| (target.georef.to_world(c as f64, r as f64), z as f64))
        })
        .filter_map(|(p, z)| Some((to_source(p)?, z)))
        .collect();
    SIGMAS
        .iter()
        .map(|&sigma| {
            let b = blurred(source, sigma);
            // Only points whose filtered value is whole: 3σ inside the source's samples.
            let margin = 3.0 * sigma + 1.0;
            pts.iter()
                .filter_map(|&(q, z)| {
                    let g = b.georef.to_grid(q);
                    let inside = g[0] >= margin
                        && g[1] >= margin
                        && g[0] <= (b.cols - 1) as f64 - margin
                        && g[1] <= (b.rows - 1) as f64 - margin;
                    inside.then(|| Some(b.bilinear_grid(g)? + dz - z)).flatten()
                })
                .collect()
        })
        .collect()
}

/// The best prediction over [`SIGMAS`] from residuals gathered over several windows.
fn best_prediction(per_sigma: &[Vec<f64>]) -> Option<Prediction> {
    let mut best: Option<Prediction> = None;
    for (d, &sigma) in per_sigma.iter().zip(SIGMAS.iter()) {
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
    let s = c.shift;
    let back = |q: [f64; 2]| to_reference(q).map(|p| [p[0] - s[0], p[1] - s[1]]);
    let forth = |p: [f64; 2]| to_other([p[0] + s[0], p[1] + s[1]]);
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
                residuals(&wide, &b_inner, &back, c.dz),
                residuals(&b, a, &forth, -c.dz),
            ))
        })
        .collect();
    let pool = |pick: fn(&(Residuals, Residuals)) -> &Residuals| {
        let mut all = vec![Vec::new(); SIGMAS.len()];
        for w in &per_window {
            for (into, from) in all.iter_mut().zip(pick(w)) {
                into.extend_from_slice(from);
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
