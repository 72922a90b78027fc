//! Which of two surveys of the same ground carries the detail they share, scale by scale.
//!
//! A survey's own accuracy estimate rewards smoothness: a blurred copy looks six times more
//! accurate than its original. So the pair is judged on what neither can fake. Both surfaces
//! are split into bands of scale (differences of Gaussian low-passes, σ from half the coarser
//! survey's cell to four cells: only scales both resolve, the finer one low-passed to the
//! coarser's first), and in each band three figures are kept over the whole overlap: the
//! energy of each (the mean square of its band, each on its own samples) and the energy they
//! share (the mean product of the two bands at the finer's samples, once the coregistration
//! has aligned them).
//!
//! A filter scales a band's shared detail by its gain h and removes the rest; noise adds
//! energy that the other does not share. With `a = s + nₐ` and `b = h·s + n_b`, the shared
//! energy is `C = h·S` and `E_b = h²S + N_b`, so `E_b / C = h + N_b / (h·S)` is at least the
//! gain: where it is well under 1, `b` lacks detail that `a` has, whatever noise either holds
//! (noise in `a` cannot lower it). That is the test of a blur, a resampling or a smoothing, and
//! it does not reward smoothness: it is the smoother one that falls under 1. Noise shows the
//! other way round: the noisy one's band holds energy the other does not share (`E / C − 1`,
//! its excess), while the clean one's excess stays near 0. Independent surveys of the same
//! ground each have an excess of their own, and neither falls under 1.
//!
//! Every figure is a mean over samples spread over the whole overlap (at most 16 windows of
//! 256² samples of the finer, once it is low-passed), so one patch of cloud or sea does not
//! decide it.

use super::coreg::{blurred, Carry, Placement};
use super::grid::{Georef, Grid};
use patchwork_geom::Aabb;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;

/// Band edges, in cells of the coarser survey: band i lies between the low-passes of σ =
/// `EDGES[i]` and `EDGES[i + 1]`.
pub const EDGES: [f64; 4] = [0.5, 1.0, 2.0, 4.0];
/// The side of a window's core, in (low-passed) samples of the finer survey.
const CORE: usize = 256;
/// At most this many windows over an overlap.
const MOST_WINDOWS: usize = 16;
/// A band with fewer samples of either survey says nothing.
pub const LEAST_SAMPLES: u64 = 400;
/// A band whose shared energy is under this fraction of the geometric mean of the two
/// energies (a coherence under 0.3²... of 0.09 in energy) holds too little common content.
pub const LEAST_COHERENCE: f64 = 0.3;
/// Under this `E / C` a survey lacks detail the other has: its gain at that scale is at most
/// this. On five real DEMs a Gaussian blur of one cell measures 0.50–0.76 at the finest band,
/// a 3 × 3 box 0.69–0.81, a B-spline smoothing 0.44–0.73; a blur of half a cell 0.75–0.90
/// (harmless within the original's error); independent surveys of the same ground
/// (Copernicus and NASADEM) 0.95, and a copy moved by whole cells 0.98–1.0.
pub const LACKS_BELOW: f64 = 0.85;
/// Over this excess a survey adds detail the other does not share, where all of the other's
/// is shared (its `E / C` within [`SHARED`]).
pub const NOISY_ABOVE: f64 = 1.0;
/// The `E / C` of a survey whose detail is all in the other: a clean original beside a
/// noisy copy of it measures 1.00 ± 0.05.
pub const SHARED: [f64; 2] = [0.95, 1.1];

/// One band's figures.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Band {
    /// The band's finer edge, σ in the reference plane's units.
    pub sigma: f64,
    /// Mean square of the reference's band.
    pub energy_reference: f64,
    /// Mean square of the other's band, at the same points.
    pub energy_other: f64,
    /// Mean product of the two: the energy they share.
    pub shared: f64,
    /// How many points the means are over.
    pub samples: u64,
}

impl Band {
    /// Whether the band says anything: enough samples, and enough shared content.
    pub fn informative(&self) -> bool {
        self.samples >= LEAST_SAMPLES
            && self.shared > 0.0
            && self.shared >= LEAST_COHERENCE * (self.energy_reference * self.energy_other).sqrt()
    }

    /// `E / C` of the reference: an upper bound on its gain against the other.
    pub fn reference_gain(&self) -> f64 {
        self.energy_reference / self.shared
    }

    /// `E / C` of the other.
    pub fn other_gain(&self) -> f64 {
        self.energy_other / self.shared
    }
}

/// The bands of a pair, finest first.
#[derive(Clone, Debug, PartialEq)]
pub struct Detail {
    /// One per band both surveys resolve.
    pub bands: Vec<Band>,
}

/// What the bands find.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Finding {
    /// The reference lacks detail the other has: its gain `E / C` at band `band`.
    ReferenceLacks {
        /// The band's index.
        band: usize,
        /// Its `E / C`.
        gain: f64,
    },
    /// The other lacks detail the reference has.
    OtherLacks {
        /// The band's index.
        band: usize,
        /// Its `E / C`.
        gain: f64,
    },
    /// The reference adds detail the other does not share: its excess `E / C − 1`.
    ReferenceNoisy {
        /// The band's index.
        band: usize,
        /// The excess.
        excess: f64,
    },
    /// The other adds detail the reference does not share.
    OtherNoisy {
        /// The band's index.
        band: usize,
        /// The excess.
        excess: f64,
    },
    /// Nothing clear: neither lacks nor adds detail beyond the thresholds, or no band says.
    Undecided,
}

impl Detail {
    /// The verdict: the lowest gain among informative bands under [`LACKS_BELOW`] (a lack of
    /// shared detail cannot come from noise, so it is looked for first), else the largest
    /// excess over [`NOISY_ABOVE`] where the other's detail is all shared. A blur raises the
    /// original's excess as much as noise would, but it also lowers the copy's `E / C` under
    /// 1, which noise in the original cannot; so the excess counts only beside an `E / C`
    /// near 1.
    pub fn finding(&self) -> Finding {
        let useful = || {
            self.bands
                .iter()
                .enumerate()
                .filter(|(_, b)| b.informative())
        };
        let lowest = useful()
            .flat_map(|(i, b)| [(i, b.reference_gain(), true), (i, b.other_gain(), false)])
            .min_by(|x, y| x.1.total_cmp(&y.1));
        if let Some((band, gain, reference)) = lowest {
            if gain < LACKS_BELOW {
                return if reference {
                    Finding::ReferenceLacks { band, gain }
                } else {
                    Finding::OtherLacks { band, gain }
                };
            }
        }
        // Not the finest band: reading between samples damps it, and a nonlinear filter (a
        // median) removes detail there without damping what it keeps, which looks the same.
        // The clean side must look clean in every band that says anything, not only in the
        // one where the other's excess is largest: a smoothed side beside a noisy-looking one
        // shows `E / C` under 1 somewhere (its gain), and a band where it happens to come
        // near 1 proves nothing.
        let clean = |reference: bool| {
            useful().filter(|(i, _)| *i > 0).all(|(_, b)| {
                let g = if reference {
                    b.reference_gain()
                } else {
                    b.other_gain()
                };
                (SHARED[0]..=SHARED[1]).contains(&g)
            })
        };
        let (reference_clean, other_clean) = (clean(true), clean(false));
        let noisiest = useful()
            .filter(|(i, _)| *i > 0)
            .flat_map(|(i, b)| {
                let (r, o) = (b.reference_gain() - 1.0, b.other_gain() - 1.0);
                [(i, r, other_clean, true), (i, o, reference_clean, false)]
            })
            .filter(|&(_, e, other_clean, _)| e > NOISY_ABOVE && other_clean)
            .max_by(|x, y| x.1.total_cmp(&y.1));
        match noisiest {
            Some((band, excess, _, true)) => Finding::ReferenceNoisy { band, excess },
            Some((band, excess, _, false)) => Finding::OtherNoisy { band, excess },
            None => Finding::Undecided,
        }
    }

    /// How much more shared detail the reference lacks than the other: the sum over
    /// informative bands of `ln min(E / C, 1)` of the other less the reference's. Positive
    /// where the reference lacks more; 0 where neither lacks any (noise, or independent
    /// surveys).
    pub fn lack(&self) -> f64 {
        self.bands
            .iter()
            .filter(|b| b.informative())
            .map(|b| b.other_gain().min(1.0).ln() - b.reference_gain().min(1.0).ln())
            .sum()
    }

    /// The other's excess `E / C − 1` less the reference's, at the finest informative band
    /// past the first (see [`Detail::finding`] for why not the first): positive where the
    /// other holds more detail the reference does not share.
    pub fn excess(&self) -> Option<f64> {
        let b = self.bands.iter().skip(1).find(|b| b.informative())?;
        Some(b.other_gain() - b.reference_gain())
    }
}

/// A grid low-passed and thinned by `k`: each output sample the mean of the valid samples of a
/// k × k block (NaN where fewer than half are), placed at the block's centre. Keeps the
/// analysis of a fine survey against a much coarser one to the coarser one's scale, at a
/// cost in proportion to the samples.
pub fn block_mean(g: &Grid, k: usize) -> Grid {
    if k <= 1 {
        return g.clone();
    }
    let (cols, rows) = (g.cols / k, g.rows / k);
    let samples: Vec<f32> = (0..rows)
        .into_par_iter()
        .flat_map_iter(|r| {
            (0..cols).map(move |c| {
                let (mut s, mut n) = (0.0f64, 0usize);
                for rr in r * k..(r + 1) * k {
                    for cc in c * k..(c + 1) * k {
                        let z = g.at(cc, rr);
                        if !z.is_nan() {
                            s += z as f64;
                            n += 1;
                        }
                    }
                }
                if 2 * n >= k * k {
                    (s / n as f64) as f32
                } else {
                    f32::NAN
                }
            })
        })
        .collect();
    let half = (k as f64 - 1.0) / 2.0;
    let georef = Georef {
        origin: g.georef.to_world(half, half),
        step: [g.georef.step[0] * k as f64, g.georef.step[1] * k as f64],
        ..g.georef
    };
    Grid::new(cols, rows, samples, georef).expect("a shape from a grid's")
}

/// The band-passes of a grid, σ given in its own cells: `out[i] = L(σᵢ) − L(σᵢ₊₁)`.
fn bands_of(g: &Grid, sigmas: &[f64]) -> Vec<Grid> {
    let lows: Vec<Grid> = sigmas.iter().map(|&s| blurred(g, s)).collect();
    lows.windows(2)
        .map(|w| {
            let samples = w[0]
                .samples
                .iter()
                .zip(&w[1].samples)
                .map(|(a, b)| a - b)
                .collect();
            Grid::new(g.cols, g.rows, samples, g.georef).expect("the same shape")
        })
        .collect()
}

/// Sums of one band over windows.
#[derive(Clone, Copy, Default)]
struct Sums {
    ea: f64,
    eb: f64,
    cross: f64,
    n: u64,
}

/// The bands of `reference` (the finer survey's window over the overlap) and `other` (the
/// coarser's), over `bounds` in the reference's plane, with `other`'s content found at
/// `to_other(place.forth(p))` for the reference's point p. `cell` is the coarser survey's cell in
/// the reference plane's units. None where the overlap is too small for any band.
pub fn measure(
    reference: &Grid,
    other: &Grid,
    to_other: Carry,
    to_reference: Carry,
    place: &Placement,
    bounds: &Aabb,
    cell: f64,
) -> Option<Detail> {
    let rect = reference.shape().rect_over(bounds)?;
    let own = reference.georef.step[0].max(reference.georef.step[1]);
    // The finer one low-passed and thinned to about half the coarser's cell, so that the
    // finest band (σ half a coarse cell) still spans a sample or more.
    let k = ((cell / own) / 2.0).floor().max(1.0) as usize;
    // The overlap's samples, copied only where they are not the whole grid already (the
    // caller reads the overlap alone) or where they are thinned.
    let whole =
        if (rect.c0, rect.r0, rect.cols(), rect.rows()) == (0, 0, reference.cols, reference.rows) {
            Cow::Borrowed(reference)
        } else {
            Cow::Owned(reference.window(rect.c0, rect.r0, rect.cols(), rect.rows()))
        };
    if whole.cols / k < 2 || whole.rows / k < 2 {
        // Thinned to less than a cell: no detail to measure.
        return None;
    }
    let a = if k > 1 {
        Cow::Owned(block_mean(&whole, k))
    } else {
        whole
    };
    let step_a = own * k as f64;
    // Sigmas in the reference's plane units, then in each grid's cells. The other's are in
    // its own plane; its cell there stands for `cell` here.
    let sig: Vec<f64> = EDGES.iter().map(|e| e * cell).collect();
    let sig_a: Vec<f64> = sig.iter().map(|s| s / step_a).collect();
    let sig_b: Vec<f64> = EDGES.to_vec();
    let margin = (3.0 * sig_a[sig_a.len() - 1]).ceil() as usize + 1;
    let side = CORE + 2 * margin;
    if a.cols < 2 * margin + 8 || a.rows < 2 * margin + 8 {
        return None;
    }
    // Windows over the whole overlap: all of it when it is small, else a lattice of windows
    // spread evenly.
    let starts = |n: usize| -> Vec<usize> {
        if n <= side {
            return vec![0];
        }
        let count = n.div_ceil(side);
        let take = count.min(4);
        (0..take)
            .map(|i| (i * (n - side)) / (take - 1).max(1))
            .collect()
    };
    let mut windows = Vec::new();
    for &r0 in &starts(a.rows) {
        for &c0 in &starts(a.cols) {
            windows.push((c0, r0));
        }
    }
    windows.truncate(MOST_WINDOWS);
    let nb = EDGES.len() - 1;
    let per_window: Vec<Vec<Sums>> = windows
        .par_iter()
        .filter_map(|&(c0, r0)| {
            let (w, h) = (side.min(a.cols - c0), side.min(a.rows - r0));
            let wa = a.window(c0, r0, w, h);
            let ba = bands_of(&wa, &sig_a);
            // The other's samples over the window and its filters' reach, where it lies.
            let wb = wa.world_bounds();
            let reach = 3.0 * sig[sig.len() - 1] + 2.0 * cell;
            let corners: Vec<[f64; 2]> = [
                [wb.min[0] - reach, wb.min[1] - reach],
                [wb.max[0] + reach, wb.min[1] - reach],
                [wb.min[0] - reach, wb.max[1] + reach],
                [wb.max[0] + reach, wb.max[1] + reach],
            ]
            .iter()
            .filter_map(|&p| to_other(place.forth(p)))
            .collect();
            if corners.len() < 4 {
                return None;
            }
            let rb = other.shape().rect_over(&Aabb::of_points(&corners))?;
            let gb = other.window(rb.c0, rb.r0, rb.cols(), rb.rows());
            let bb = bands_of(&gb, &sig_b);
            // Both surfaces are read at the same points, half-way between the two lattices
            // (where one lattice is a fraction δ of a cell off the other, the reference's
            // nodes moved by δ / 2): bilinear reading then damps both alike, and neither
            // looks smoother for being the one read between its samples.
            let centre = wa.georef.to_world(w as f64 / 2.0, h as f64 / 2.0);
            let half = to_other(place.forth(centre))
                .and_then(|q| {
                    let g = gb.georef.to_grid(q);
                    let node = gb.georef.to_world(g[0].round(), g[1].round());
                    let p = to_reference(node)?;
                    let ga = wa.georef.to_grid(place.back(p));
                    Some([(ga[0] - ga[0].round()) / 2.0, (ga[1] - ga[1].round()) / 2.0])
                })
                .unwrap_or([0.0, 0.0]);
            let mut out = vec![Sums::default(); nb];
            for (i, s) in out.iter_mut().enumerate() {
                // Only points whose widest filter lies inside the window.
                let m = (3.0 * sig_a[i + 1]).ceil() as usize + 1;
                if w <= 2 * m || h <= 2 * m {
                    continue;
                }
                for r in m..h - m {
                    for c in m..w - m {
                        let g = [c as f64 + half[0], r as f64 + half[1]];
                        let Some(za) = ba[i].bilinear_grid(g) else {
                            continue;
                        };
                        let p = wa.georef.to_world(g[0], g[1]);
                        if !bounds.contains_point(p) {
                            continue;
                        }
                        let Some(q) = to_other(place.forth(p)) else {
                            continue;
                        };
                        let Some(zb) = bb[i].bilinear(q) else {
                            continue;
                        };
                        s.ea += za * za;
                        s.eb += zb * zb;
                        s.cross += za * zb;
                        s.n += 1;
                    }
                }
            }
            Some(out)
        })
        .collect();
    let mut total = vec![Sums::default(); nb];
    for w in &per_window {
        for (t, s) in total.iter_mut().zip(w) {
            t.ea += s.ea;
            t.eb += s.eb;
            t.cross += s.cross;
            t.n += s.n;
        }
    }
    let bands: Vec<Band> = total
        .iter()
        .enumerate()
        .filter(|(_, s)| s.n > 0)
        .map(|(i, s)| Band {
            sigma: sig[i],
            energy_reference: s.ea / s.n as f64,
            energy_other: s.eb / s.n as f64,
            shared: s.cross / s.n as f64,
            samples: s.n,
        })
        .collect();
    (!bands.is_empty()).then_some(Detail { bands })
}
