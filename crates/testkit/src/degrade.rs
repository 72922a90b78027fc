//! Degraded copies of a real survey drawn at random: the cases an arbitration between
//! overlapping surveys must not be tuned to. A copy is one to three operations chained, each
//! with its parameters drawn: Gaussian, box, median and B-spline smoothing filters,
//! resampling down by 1.5–4× (bilinear or cubic, kept coarse or brought back up to the
//! original lattice), shifts of up to 12 cells with fractions, vertical offsets, noise and
//! quantisation. Every draw follows from a seed, which a failing test prints.

use super::copies::{noisy, offset, shifted};
use patchwork_core::crs::Crs;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::AccuracySpec;
use patchwork_core::model::coreg::blurred;
use patchwork_core::model::evidence::Contradicted;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::ids::SurveyId;
use patchwork_core::model::survey::Survey;
use patchwork_core::terrain::Terrain;
use std::sync::Arc;

/// The committed crops copies are drawn from: five DEMs of four origins (Copernicus,
/// NASADEM and SRTM radar, two lidar surveys) and a basin-scale grid.
pub const SCENES: [&str; 6] = [
    "copernicus_n34w119_crop.tif",
    "nasadem_n34w119_crop.tif",
    "srtm_n44e005_voids_crop.tif",
    "real/philondenx_zero_nan.tif",
    "real/lidar_tiles_padded.tif",
    "real/rhine_deflate_strips.tif",
];

/// A drawn copy: what was done, in words, and the result.
#[derive(Clone, Debug)]
pub struct Drawn {
    /// The operations, in the order applied.
    pub label: String,
    /// The degraded samples.
    pub grid: Grid,
}

/// Draws a copy of `g` from `next` (uniform in [0, 1)). A vertical offset or a
/// quantisation alone leaves a copy with the original's content, which nothing in the pair
/// can tell from it (the store reports both as distrusted there, and a third survey decides);
/// so a chain is drawn again until it holds an operation that changes the content: a filter,
/// a resampling, noise or a shift.
pub fn draw(g: &Grid, next: &mut impl FnMut() -> f64) -> Drawn {
    let mut out = g.clone();
    let mut label = Vec::new();
    let mut changes = false;
    while !changes {
        out = g.clone();
        label.clear();
        for _ in 0..1 + (next() * 3.0) as usize {
            let (l, grid, kind) = one(&out, next);
            changes |= kind;
            label.push(l);
            out = grid;
        }
    }
    Drawn {
        label: label.join(" + "),
        grid: out,
    }
}

fn between(next: &mut impl FnMut() -> f64, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * next()
}

/// One operation, drawn, and whether it changes the content (anything but an offset or a
/// quantisation).
fn one(g: &Grid, next: &mut impl FnMut() -> f64) -> (String, Grid, bool) {
    let k = (next() * 9.0) as usize;
    let (label, grid) = one_of(k, g, next);
    (label, grid, k != 6 && k != 8)
}

fn one_of(k: usize, g: &Grid, next: &mut impl FnMut() -> f64) -> (String, Grid) {
    match k {
        0 => {
            let s = between(next, 0.5, 3.0);
            (format!("gaussian σ {s:.2}"), blurred(g, s))
        }
        1 => {
            let w = [3, 5, 7][(next() * 3.0) as usize];
            (format!("box {w}×{w}"), boxed(g, w))
        }
        2 => {
            let w = [3, 5][(next() * 2.0) as usize];
            (format!("median {w}×{w}"), median(g, w))
        }
        3 => {
            let f = between(next, 1.5, 4.0);
            let cubic = next() < 0.5;
            let back = next() < 0.5;
            let how = if cubic { "cubic" } else { "bilinear" };
            let down = resampled(g, f, cubic);
            if back {
                (
                    format!("{how} down {f:.2}× and up"),
                    resampled_onto(&down, g, cubic),
                )
            } else {
                (format!("{how} down {f:.2}×"), down)
            }
        }
        4 => {
            let w = [2, 3, 4][(next() * 3.0) as usize];
            (format!("B-spline smoothing {w}"), spline(g, w))
        }
        5 => {
            let (d, a) = (
                between(next, 0.0, 12.0),
                between(next, 0.0, std::f64::consts::TAU),
            );
            let by = [d * a.cos(), d * a.sin()];
            (format!("shift {:.2},{:.2}", by[0], by[1]), shifted(g, by))
        }
        6 => {
            let dz = between(next, 1.0, 50.0) * if next() < 0.5 { -1.0 } else { 1.0 };
            (format!("offset {dz:.1} m"), offset(g, dz))
        }
        7 => {
            let sd = between(next, 0.5, 5.0);
            let seed = (next() * u32::MAX as f64) as u64;
            (format!("noise {sd:.2} m"), noisy(g, sd, seed))
        }
        _ => {
            let q = [1.0, 2.0, 5.0, 10.0][(next() * 4.0) as usize];
            (format!("quantised to {q} m"), quantised(g, q))
        }
    }
}

/// A square moving average `w` samples wide (odd) over the valid samples, NaN where fewer
/// than half are valid.
pub fn boxed(g: &Grid, w: usize) -> Grid {
    let r = (w / 2) as isize;
    filter(
        g,
        |vals| (2 * vals.len() >= w * w).then(|| vals.iter().sum::<f64>() / vals.len() as f64),
        r,
    )
}

/// A square median `w` samples wide over the valid samples.
pub fn median(g: &Grid, w: usize) -> Grid {
    let r = (w / 2) as isize;
    filter(
        g,
        |vals| {
            if 2 * vals.len() < w * w {
                return None;
            }
            let mut v = vals.to_vec();
            v.sort_by(f64::total_cmp);
            Some(v[v.len() / 2])
        },
        r,
    )
}

fn filter(g: &Grid, f: impl Fn(&[f64]) -> Option<f64>, r: isize) -> Grid {
    let (cols, rows) = (g.cols as isize, g.rows as isize);
    let mut out = Vec::with_capacity(g.samples.len());
    let mut vals = Vec::new();
    for y in 0..rows {
        for x in 0..cols {
            if g.at(x as usize, y as usize).is_nan() {
                out.push(f32::NAN);
                continue;
            }
            vals.clear();
            for yy in (y - r).max(0)..=(y + r).min(rows - 1) {
                for xx in (x - r).max(0)..=(x + r).min(cols - 1) {
                    let z = g.at(xx as usize, yy as usize);
                    if !z.is_nan() {
                        vals.push(z as f64);
                    }
                }
            }
            out.push(f(&vals).map_or(f32::NAN, |v| v as f32));
        }
    }
    Grid::new(g.cols, g.rows, out, g.georef).expect("the same shape")
}

/// A cubic B-spline smoother: the `w`-wide box filter four times over (its kernel is the
/// cubic B-spline of width 4w, what a smoothing spline's equivalent kernel approaches).
pub fn spline(g: &Grid, w: usize) -> Grid {
    let mut out = g.clone();
    for _ in 0..4 {
        out = boxed_even(&out, w);
    }
    out
}

/// A box of any width, centred (an even one averages the half-samples at its ends).
fn boxed_even(g: &Grid, w: usize) -> Grid {
    if w % 2 == 1 {
        return boxed(g, w);
    }
    // An even box is the mean of the odd boxes either side of it.
    let (a, b) = (boxed(g, w - 1), boxed(g, w + 1));
    let samples = a
        .samples
        .iter()
        .zip(&b.samples)
        .map(|(x, y)| 0.5 * (x + y))
        .collect();
    Grid::new(g.cols, g.rows, samples, g.georef).expect("the same shape")
}

/// Catmull–Rom weights for a fraction t.
fn cubic_weights(t: f64) -> [f64; 4] {
    let (t2, t3) = (t * t, t * t * t);
    [
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    ]
}

/// The grid's surface at fractional grid coordinates: bilinear, or cubic (NaN where any of
/// the 16 samples is missing or off the grid).
fn interpolate(g: &Grid, x: f64, y: f64, cubic: bool) -> f32 {
    if !cubic {
        return g.bilinear_grid([x, y]).map_or(f32::NAN, |v| v as f32);
    }
    let (x0, y0) = (x.floor() as isize, y.floor() as isize);
    let (wx, wy) = (cubic_weights(x - x0 as f64), cubic_weights(y - y0 as f64));
    let mut s = 0.0;
    for (j, wyj) in wy.iter().enumerate() {
        for (i, wxi) in wx.iter().enumerate() {
            let (c, r) = (x0 - 1 + i as isize, y0 - 1 + j as isize);
            if c < 0 || r < 0 || c >= g.cols as isize || r >= g.rows as isize {
                return f32::NAN;
            }
            let z = g.at(c as usize, r as usize);
            if z.is_nan() {
                return f32::NAN;
            }
            s += wxi * wyj * z as f64;
        }
    }
    s as f32
}

/// The grid resampled onto a lattice `f` times coarser from the same first sample, each
/// sample interpolated where it falls (no prefilter: what a point resampler does).
pub fn resampled(g: &Grid, f: f64, cubic: bool) -> Grid {
    let cols = ((g.cols - 1) as f64 / f).floor() as usize + 1;
    let rows = ((g.rows - 1) as f64 / f).floor() as usize + 1;
    let mut out = Vec::with_capacity(cols * rows);
    for r in 0..rows {
        for c in 0..cols {
            out.push(interpolate(g, c as f64 * f, r as f64 * f, cubic));
        }
    }
    Grid::new(cols, rows, out, g.georef.coarsened(f)).expect("a coarser shape")
}

/// `g` interpolated at every sample of `onto`'s lattice.
pub fn resampled_onto(g: &Grid, onto: &Grid, cubic: bool) -> Grid {
    let mut out = Vec::with_capacity(onto.samples.len());
    for r in 0..onto.rows {
        for c in 0..onto.cols {
            let p = onto.georef.to_world(c as f64, r as f64);
            let q = g.georef.to_grid(p);
            out.push(interpolate(g, q[0], q[1], cubic));
        }
    }
    Grid::new(onto.cols, onto.rows, out, onto.georef).expect("the same shape")
}

/// `g` placed by an affine map about its centre, on its own lattice: the copy's sample at
/// grid position p is `g` read at `centre + m · (p − centre)` (a rotation, a stretch or a
/// shear, or any mix), interpolated as a resampler does; NaN where that falls outside.
pub fn warped(g: &Grid, m: [[f64; 2]; 2], cubic: bool) -> Grid {
    let centre = [(g.cols - 1) as f64 / 2.0, (g.rows - 1) as f64 / 2.0];
    let mut out = Vec::with_capacity(g.samples.len());
    for r in 0..g.rows {
        for c in 0..g.cols {
            let d = [c as f64 - centre[0], r as f64 - centre[1]];
            let x = centre[0] + m[0][0] * d[0] + m[0][1] * d[1];
            let y = centre[1] + m[1][0] * d[0] + m[1][1] * d[1];
            out.push(interpolate(g, x, y, cubic));
        }
    }
    Grid::new(g.cols, g.rows, out, g.georef).expect("the same shape")
}

/// A rotation by `degrees` (anticlockwise in grid terms), as [`warped`] takes it.
pub fn rotation(degrees: f64) -> [[f64; 2]; 2] {
    let (s, c) = degrees.to_radians().sin_cos();
    [[c, -s], [s, c]]
}

/// Every height rounded to a multiple of `q` metres.
pub fn quantised(g: &Grid, q: f64) -> Grid {
    let mut out = g.clone();
    for z in out.samples.iter_mut() {
        *z = ((*z as f64 / q).round() * q) as f32;
    }
    out
}

/// The share of `orig`'s valid samples (of `g`, its grid) that `t` serves at e = 0 within the
/// original's own claim there (the largest of the kernels around the sample), and how many
/// samples that is over.
pub fn served_within_claim(t: &Terrain, orig: &Survey, g: &Grid) -> (f64, usize) {
    let base = t.base(orig.id).expect("the original is in the terrain");
    let (tiling, acc) = (&base.tiling, &base.kernel_accuracy);
    let [cw, ch] = tiling.cells;
    let claim = |c: usize, r: usize| -> f64 {
        let mut e: f64 = 0.0;
        for rr in [r.saturating_sub(1), r.min(ch - 1)] {
            for cc in [c.saturating_sub(1), c.min(cw - 1)] {
                let k = tiling.kernel_at(cc as u32, rr as u32);
                e = e.max(acc.values[k[1] as usize * acc.dims[0] + k[0] as usize]);
            }
        }
        e
    };
    let mut pts = Vec::new();
    let mut want = Vec::new();
    for r in 0..g.rows {
        for c in 0..g.cols {
            let z = g.at(c, r);
            if !z.is_nan() {
                pts.push(g.georef.to_world(c as f64, r as f64));
                want.push((z as f64, claim(c, r)));
            }
        }
    }
    let got = t.sample(&pts, 0.0);
    let ok = got
        .iter()
        .zip(&want)
        .filter(|(h, (z, e))| !h.is_nan() && (**h as f64 - z).abs() <= e + 1e-3)
        .count();
    (ok as f64 / want.len().max(1) as f64, want.len())
}

/// One draw: an original, its copies, the terrain of all of them inserted in a random order,
/// and how the original fares.
pub struct Scene {
    /// The copies' operations, one label a copy.
    /// Each copy's operations, as [`Drawn::label`].
    pub labels: Vec<String>,
    /// The original first, then the copies, in the order they were inserted.
    pub surveys: Vec<Arc<Survey>>,
    /// The original's id.
    pub original: SurveyId,
    /// The terrain of the original and its copies.
    pub terrain: Terrain,
    /// The share of the original's samples served within its own claim at e = 0.
    pub share: f64,
    /// The original's valid samples that share is of.
    pub samples: usize,
}

/// Draws one to three copies of `g` (a survey in `crs`), inserts them with the original in a
/// random order (the store distrusting contradicted claims), and measures what the original
/// keeps.
pub fn scene(g: &Grid, crs: Option<Crs>, next: &mut impl FnMut() -> f64) -> Scene {
    let build = |g: Grid| {
        Arc::new(Survey::build(g, AccuracySpec::Auto, crs.clone(), Default::default()).unwrap())
    };
    let orig = build(g.clone());
    let mut all = vec![orig.clone()];
    let mut labels = Vec::new();
    for _ in 0..1 + (next() * 3.0) as usize {
        let d = draw(g, next);
        labels.push(d.label);
        all.push(build(d.grid));
    }
    for i in (1..all.len()).rev() {
        let j = (next() * (i + 1) as f64) as usize;
        all.swap(i, j);
    }
    let mut t = Terrain::new(IndexConfig::default());
    t.set_contradicted(Contradicted::Distrust);
    for s in &all {
        t.insert(s.clone());
    }
    let (share, samples) = served_within_claim(&t, &orig, g);
    Scene {
        labels,
        surveys: all,
        original: orig.id,
        terrain: t,
        share,
        samples,
    }
}

impl Scene {
    /// Every pair's verdict and the claims before and after, for a failure message.
    pub fn explain(&self) -> String {
        let name = |id| self.surveys.iter().position(|s| s.id == id).unwrap();
        let t = &self.terrain;
        let mut out = Vec::new();
        for p in t.pairs() {
            let (f, c) = (p.finer, p.coarser);
            out.push(format!(
                "    #{} vs #{}: {:?}, ε medians {:.2} → {:.2} and {:.2} → {:.2}, coreg {:?}",
                name(f),
                name(c),
                t.verdict(f, c).unwrap(),
                t.base(f).unwrap().kernel_accuracy.quantile(0.5),
                t.survey(f).unwrap().kernel_accuracy.quantile(0.5),
                t.base(c).unwrap().kernel_accuracy.quantile(0.5),
                t.survey(c).unwrap().kernel_accuracy.quantile(0.5),
                p.coreg.map(|k| (k.shift, k.conditioned)),
            ));
        }
        out.push(format!("    the original is #{}", name(self.original)));
        out.join("\n")
    }
}
