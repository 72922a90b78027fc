//! What two overlapping surveys say of each other's accuracy claims.
//!
//! A claim ε is a bound: the survey's surface is within ε of the ground. Two surveys of the
//! same ground with claims ε₁ and ε₂ can then differ by at most ε₁ + ε₂ anywhere; where they
//! differ by more, at least one claim is false. Which one is decided from what cannot be
//! faked (see [`super::coreg`]): a survey that a low-pass of the other predicts, and that
//! predicts the other no better, is a degraded copy, and its claim is the false one. Where the
//! pair cannot tell, surveys that overlap both can: one that lies where a third survey lies,
//! against one shifted or offset from both, is right. Where nothing tells, neither claim is
//! trusted beyond what the other allows.
//!
//! The false claim is raised, kernel by kernel, to what the evidence shows. Where nothing tells
//! the two apart, each is raised only where they contradict each other, to the least that the
//! other's claim allows: the difference less the other's ε. Where one is found to be the
//! degraded or misplaced one, it carries nothing the other does not, so its claim can be no
//! better than the other's (as raised by the first rule) plus how far it departs from it, over
//! the whole overlap; it never displaces the other there.
//! Every figure here is a function of the
//! pair (measured at the finer survey's samples, whichever came first) or of the set of pairs,
//! so the accuracies that follow, and the index built on them, do not depend on the order the
//! surveys arrived in, and retiring a survey takes its evidence with it.

use super::accuracy::{Deviation, KernelAccuracy};
use super::coreg::{self, Carry, Coregistration, Degradation, Degraded};
use super::grid::Grid;
use super::ids::SurveyId;
use super::patch::Tiling;
use patchwork_geom::Aabb;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// How two overlapping surveys compare, and where their claims contradict each other.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairEvidence {
    /// The survey whose samples the figures are measured at: the finer.
    pub finer: SurveyId,
    /// The other survey, whose surface is evaluated at those samples.
    pub coarser: SurveyId,
    /// How far the coarser's surface lies from the finer's samples.
    pub deviation: Deviation,
    /// How the coarser lies against the finer, the finer as reference; None where they share too
    /// little ground to say.
    pub coreg: Option<Coregistration>,
    /// Which of the two is a degraded copy of the other; None where that cannot be measured.
    pub degradation: Option<Degradation>,
    /// The coarser survey's cell, in the finer's plane units: a shift under half of it is
    /// registration noise.
    pub cell: f64,
    /// Metres per unit of the finer's plane, east and north, for shifts in metres.
    pub metres_per_unit: [f64; 2],
    /// The finer survey's kernels whose claim the coarser's contradicts, with the least ε the
    /// coarser's claim allows there (row-major kernel indices, ascending).
    pub against_finer: Vec<(u32, f32)>,
    /// The same for the coarser survey's kernels, against the finer's claim.
    pub against_coarser: Vec<(u32, f32)>,
    /// How far the finer survey departs from the coarser, kernel by kernel: (own kernel, the
    /// other's kernel, largest difference), ascending. Were it derived from the other, its
    /// claim there could be no better than that difference plus the other's.
    pub departs_finer: Vec<(u32, u32, f32)>,
    /// The same for the coarser survey, by its kernel and the finer's.
    pub departs_coarser: Vec<(u32, u32, f32)>,
}

/// One side of a pair, as the comparison needs it: a window of its level 0 with where the
/// window starts, and its claims.
pub struct Side<'a> {
    /// The survey.
    pub id: SurveyId,
    /// A window of its level 0.
    pub grid: &'a Grid,
    /// Level-0 position of the window's first sample.
    pub offset: [usize; 2],
    /// Its level-0 kernel tiling.
    pub tiling: &'a Tiling,
    /// Its ε per level-0 kernel.
    pub accuracy: &'a KernelAccuracy,
}

impl Side<'_> {
    /// The kernels of the level-0 cells that have window sample (c, r) as a corner.
    fn kernels_at(&self, c: usize, r: usize) -> impl Iterator<Item = u32> + '_ {
        let [cw, ch] = self.tiling.cells;
        let (gc, gr) = (self.offset[0] + c, self.offset[1] + r);
        let cs = [gc.saturating_sub(1), gc.min(cw.saturating_sub(1))];
        let rs = [gr.saturating_sub(1), gr.min(ch.saturating_sub(1))];
        let dims = self.accuracy.dims;
        rs.into_iter()
            .flat_map(move |r| cs.into_iter().map(move |c| (c, r)))
            .map(move |(c, r)| {
                let k = self.tiling.kernel_at(c as u32, r as u32);
                k[1] * dims[0] as u32 + k[0]
            })
    }

    /// The kernel of the level-0 cell that holds fractional window coordinates `g`.
    fn kernel_of(&self, g: [f64; 2]) -> u32 {
        let [cw, ch] = self.tiling.cells;
        let c = (self.offset[0] as f64 + g[0])
            .floor()
            .clamp(0.0, (cw.max(1) - 1) as f64);
        let r = (self.offset[1] as f64 + g[1])
            .floor()
            .clamp(0.0, (ch.max(1) - 1) as f64);
        let k = self.tiling.kernel_at(c as u32, r as u32);
        k[1] * self.accuracy.dims[0] as u32 + k[0]
    }

    fn claim(&self, k: u32) -> f64 {
        self.accuracy.values[k as usize]
    }
}

/// Compares two surveys where they overlap. `finer` is measured against `coarser`'s surface;
/// `to_coarser` and `to_finer` carry points between their planes, and `bounds` is the
/// coarser's footprint in the finer's plane. None where they share no measured ground.
pub fn compare(
    finer: &Side,
    coarser: &Side,
    to_coarser: Carry,
    to_finer: Carry,
    bounds: &Aabb,
    metres_per_unit: [f64; 2],
) -> Option<PairEvidence> {
    let (f, c) = (finer.grid, coarser.grid);
    // Every valid sample of the finer against the coarser's surface.
    let (worst, sum, n, [against_f, against_c], [departs_f, departs_c]) = (0..f.rows)
        .into_par_iter()
        .map(|r| {
            let mut acc: Acc = Default::default();
            for col in 0..f.cols {
                let z = f.at(col, r);
                if z.is_nan() {
                    continue;
                }
                let p = f.georef.to_world(col as f64, r as f64);
                if !bounds.contains_point(p) {
                    continue;
                }
                let Some(q) = to_coarser(p) else { continue };
                let g = c.georef.to_grid(q);
                let Some(h) = c.bilinear_grid(g) else {
                    continue;
                };
                let d = (h - z as f64).abs();
                acc.0 = acc.0.max(d);
                acc.1 += d * d;
                acc.2 += 1;
                let kc = coarser.kernel_of(g);
                let (ef, ec) = (finer.claim_at(col, r), coarser.claim(kc));
                // What the other's claim leaves for this one, and what it could claim were it
                // derived from the other, where either is more than it claims.
                let ([af, ac], [df, dc]) = (&mut acc.3, &mut acc.4);
                for k in finer.kernels_at(col, r) {
                    raise(af, k, finer.claim(k), d - ec);
                    keep_max(df, (k, kc), d);
                    keep_max(dc, (kc, k), d);
                }
                raise(ac, kc, ec, d - ef);
            }
            acc
        })
        // Gathered in row order, so that the sums are the same bits on every run.
        .collect::<Vec<Acc>>()
        .into_iter()
        .fold(Acc::default(), |mut a, b| {
            a.0 = a.0.max(b.0);
            a.1 += b.1;
            a.2 += b.2;
            for (into, from) in a.3.iter_mut().zip(b.3) {
                for (k, v) in from {
                    keep_max(into, k, v as f64);
                }
            }
            for (into, from) in a.4.iter_mut().zip(b.4) {
                for (k, v) in from {
                    keep_max(into, k, v as f64);
                }
            }
            a
        });
    if n == 0 {
        return None;
    }
    let sorted = |m: HashMap<u32, f32>| {
        let mut v: Vec<(u32, f32)> = m.into_iter().collect();
        v.sort_unstable_by_key(|e| e.0);
        v
    };
    let coreg = coreg::coregister(f, c, to_coarser, bounds);
    let degradation = coreg
        .as_ref()
        .and_then(|k| coreg::degradation(f, c, to_coarser, to_finer, k, bounds));
    Some(PairEvidence {
        finer: finer.id,
        coarser: coarser.id,
        deviation: Deviation {
            max_m: worst,
            rms_m: (sum / n as f64).sqrt(),
            samples: n,
        },
        coreg,
        degradation,
        cell: seen_step(c, to_finer),
        metres_per_unit,
        against_finer: sorted(against_f),
        against_coarser: sorted(against_c),
        departs_finer: departures(departs_f),
        departs_coarser: departures(departs_c),
    })
}

/// What a comparison gathers: the largest and the sum of squares of the differences and their
/// count; per kernel, the least ε the other's claim allows where it is more than claimed, of
/// the finer and of the coarser; per pair of kernels, the largest difference, of each.
type Acc = (
    f64,
    f64,
    u64,
    [HashMap<u32, f32>; 2],
    [HashMap<(u32, u32), f32>; 2],
);

/// Keeps `need` for kernel `k` where it is above the kernel's own claim (with a hair of slack
/// for rounding).
fn raise(m: &mut HashMap<u32, f32>, k: u32, own: f64, need: f64) {
    if need > own * (1.0 + 1e-9) + 1e-9 {
        keep_max(m, k, need);
    }
}

fn keep_max<K: std::hash::Hash + Eq>(m: &mut HashMap<K, f32>, k: K, v: f64) {
    let e = m.entry(k).or_insert(0.0);
    *e = e.max(v as f32);
}

fn departures(m: HashMap<(u32, u32), f32>) -> Vec<(u32, u32, f32)> {
    let mut v: Vec<(u32, u32, f32)> = m.into_iter().map(|((a, b), d)| (a, b, d)).collect();
    v.sort_unstable_by_key(|e| (e.0, e.1));
    v
}

impl Side<'_> {
    /// The largest claim of the kernels that have window sample (c, r) as a corner: what the
    /// survey claims at that sample.
    fn claim_at(&self, c: usize, r: usize) -> f64 {
        self.kernels_at(c, r)
            .map(|k| self.claim(k))
            .fold(0.0, f64::max)
    }
}

/// The larger step of grid `g`, seen in another plane at the grid's middle.
fn seen_step(g: &Grid, to_other: Carry) -> f64 {
    let (c, r) = (g.cols as f64 / 2.0, g.rows as f64 / 2.0);
    let at = |dc: f64, dr: f64| to_other(g.georef.to_world(c + dc, r + dr));
    let own = g.georef.step[0].max(g.georef.step[1]);
    let (Some(o), Some(x), Some(y)) = (at(0.0, 0.0), at(1.0, 0.0), at(0.0, 1.0)) else {
        return own;
    };
    (x[0] - o[0])
        .hypot(x[1] - o[1])
        .max((y[0] - o[0]).hypot(y[1] - o[1]))
}

/// What a store does with a claim that another survey's evidence finds false.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Contradicted {
    /// Raise it to what the evidence shows, so that it stops displacing the survey that
    /// contradicts it.
    #[default]
    Distrust,
    /// Keep it as claimed, and only report the contradiction.
    Keep,
}

impl Contradicted {
    /// The name in the config and the store, as serialised.
    pub fn name(self) -> &'static str {
        match self {
            Contradicted::Distrust => "distrust",
            Contradicted::Keep => "keep",
        }
    }

    /// The policy called `s`, if any.
    pub fn from_name(s: &str) -> Option<Self> {
        match s {
            "distrust" => Some(Contradicted::Distrust),
            "keep" => Some(Contradicted::Keep),
            _ => None,
        }
    }
}

/// Which side of a pair a claim is false on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Blame {
    /// The finer survey's claim is the false one.
    Finer,
    /// The coarser survey's claim is the false one.
    Coarser,
    /// Nothing tells which: each claim is raised only where the two contradict each other.
    Both,
}

impl PairEvidence {
    /// Whether some claim of either contradicts the other's.
    pub fn contradicted(&self) -> bool {
        !(self.against_finer.is_empty() && self.against_coarser.is_empty())
    }

    /// Whether one survey lies shifted or offset from the other: by half the coarser cell or
    /// more, or by more height than the spread of their differences once aligned explains.
    pub fn misregistered(&self) -> bool {
        self.coreg.as_ref().is_some_and(|c| {
            c.shift[0].hypot(c.shift[1]) >= 0.5 * self.cell
                || c.dz.abs() > (3.0 * c.nmad_after).max(1.0)
        })
    }

    /// Which one the pair alone finds degraded: the comparison of predictions (see
    /// [`Degradation::degraded`]), undecided where both predict the other to within a
    /// hundredth of their differences (the same content, shifted or offset).
    pub fn degraded(&self) -> Degraded {
        let (Some(d), Some(c)) = (&self.degradation, &self.coreg) else {
            return Degraded::Undecided;
        };
        let worse = d.other_from_reference.rms.max(d.reference_from_other.rms);
        if worse <= 0.01 * c.rms_before + 0.01 {
            return Degraded::Undecided;
        }
        d.degraded()
    }

    /// The shift of the coarser against the finer, in metres east and north, and its height
    /// above it.
    pub fn shift_m(&self) -> Option<[f64; 3]> {
        self.coreg.as_ref().map(|c| {
            [
                c.shift[0] * self.metres_per_unit[0],
                c.shift[1] * self.metres_per_unit[1],
                c.dz,
            ]
        })
    }

    /// The other survey of the pair.
    pub fn other(&self, id: SurveyId) -> SurveyId {
        if id == self.finer {
            self.coarser
        } else {
            self.finer
        }
    }

    /// The kernels of `id`'s that the pair contradicts, with the least ε allowed there.
    pub fn against(&self, id: SurveyId) -> &[(u32, f32)] {
        if id == self.finer {
            &self.against_finer
        } else {
            &self.against_coarser
        }
    }

    /// How far `id` departs from the other, by its kernel and the other's.
    pub fn departs(&self, id: SurveyId) -> &[(u32, u32, f32)] {
        if id == self.finer {
            &self.departs_finer
        } else {
            &self.departs_coarser
        }
    }
}

/// Which claim of a pair is false, given the pairs each of its surveys makes with every survey
/// that overlaps both: `thirds` yields, for each such survey, its pair with the finer and its
/// pair with the coarser. A degraded copy is blamed whether or not its claims contradict the
/// other's, since it must not displace what it was made from; otherwise None for a pair that
/// contradicts nothing.
pub fn blame<'a>(
    pair: &PairEvidence,
    thirds: impl Iterator<Item = (&'a PairEvidence, &'a PairEvidence)>,
) -> Option<Blame> {
    match pair.degraded() {
        Degraded::Other => return Some(Blame::Coarser),
        Degraded::Reference => return Some(Blame::Finer),
        Degraded::Undecided => {}
    }
    if !pair.contradicted() {
        return None;
    }
    // Two surveys of one content, one moved: whichever lies where the others lie is right.
    if !pair.misregistered() {
        return Some(Blame::Both);
    }
    let (mut finer_off, mut coarser_off) = (0, 0);
    for (with_finer, with_coarser) in thirds {
        match (with_finer.misregistered(), with_coarser.misregistered()) {
            (false, true) => coarser_off += 1,
            (true, false) => finer_off += 1,
            _ => {}
        }
    }
    Some(match coarser_off.cmp(&finer_off) {
        std::cmp::Ordering::Greater => Blame::Coarser,
        std::cmp::Ordering::Less => Blame::Finer,
        std::cmp::Ordering::Equal => Blame::Both,
    })
}
