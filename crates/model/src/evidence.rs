//! What two overlapping surveys say of each other's accuracy claims.
//!
//! A claim ε is a bound: the survey's surface is within ε of the ground. Two surveys of the
//! same ground with claims ε₁ and ε₂ can then differ by at most ε₁ + ε₂ anywhere; where they
//! differ by more, at least one claim is false. Which one is decided from what cannot be
//! faked, never from the surveys' own estimates, which smoothness flatters: a survey that a
//! low-pass of the other predicts, and that predicts the other no better (see
//! [`super::coreg`]), or whose bands lack detail the other has (see [`super::detail`]), is a
//! lesser copy, and its claim is the false one. Where the pair cannot tell, surveys that
//! overlap both can: one that lies where a third survey lies, against one shifted or offset
//! from both, is right. Where nothing tells, the pair is undetermined.
//!
//! The false claim is raised, kernel by kernel, to what the evidence shows. Where the pair is
//! undetermined, each is raised only where they contradict each other, by half the excess of
//! their difference over their claims (the least raise of both that makes them agree), and the
//! pair's tie (the finer cells, then the more shared detail; see
//! [`PairEvidence::tie_to_finer`]) holds the loser as a copy of the winner would be held. A
//! survey found to be the lesser or misplaced one carries nothing the other does not, so its
//! claim can be no better than the other's (as raised by the first rule) plus how far it
//! departs from it, over the whole overlap; it never displaces the other there. A coarser
//! survey testifies against a much finer one only at its own scale, and never for more than
//! its own claim.
//!
//! Every figure here is a function of the pair (measured at the finer survey's samples,
//! whichever came first) or of the set of pairs, so the accuracies that follow, and the index
//! built on them, do not depend on the order the surveys arrived in, and retiring a survey
//! takes its evidence with it.

use super::accuracy::{Deviation, KernelAccuracy};
use super::change::{self, Change};
use super::coreg::{self, Carry, Coregistration, Degradation, Degraded};
use super::detail::{self, Detail, Finding};
use super::grid::Grid;
use super::ids::SurveyId;
use super::lines::{self, Line};
use super::patch::Tiling;
use super::transfer::{self, Transfer};
use patchwork_geom::Aabb;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// How two overlapping surveys compare, and where their claims contradict each other.
#[derive(Clone, Debug, PartialEq)]
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
    /// Which of the two is a degraded copy of the other, by predicting each from low-passes
    /// of the other; None where that cannot be measured.
    pub degradation: Option<Degradation>,
    /// The detail each holds and shares, band by band; None where the overlap is too small.
    pub detail: Option<Detail>,
    /// The strongest line of their differences' spectrum, and how each side's spectrum
    /// stands there (see [`super::lines`]); None where the overlap is too small.
    pub line: Option<Line>,
    /// Whether either is a filter of the other, ring by ring of their spectra (see
    /// [`super::transfer`]); None where the overlap holds too few whole tiles.
    pub transfer: Option<Transfer>,
    /// The finer survey's cell, in its plane's units.
    pub finer_cell: f64,
    /// The median claim of each, the finer's then the coarser's, over the samples compared.
    pub claims: (f64, f64),
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
    pub departs_finer: Departures,
    /// The same for the coarser survey, by its kernel and the finer's.
    pub departs_coarser: Departures,
    /// Where the ground changed between the two (see [`super::change`]): coherent regions
    /// where, placed, they differ by more than both claims and their spread allow.
    pub changes: Vec<Change>,
}

/// How far one survey of a pair departs from the other, kernel by kernel: entries of (own
/// kernel, the other's kernel, largest difference), packed. Every two kernels of an overlap
/// that meet have an entry, about 3.4 a patch where two surveys cover the same ground, and as
/// a list of 12-byte tuples they were the index's largest part after the patches themselves.
/// Listed in order, kernel numbers climb in small steps, so an entry keeps each as the
/// difference from the last (zigzag, then 7 bits a byte) and the f32 whole: about 6 bytes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Departures {
    len: u32,
    bytes: Box<[u8]>,
}

impl Departures {
    /// The entries `e`, in their order.
    pub fn new(e: &[(u32, u32, f32)]) -> Self {
        let mut bytes = Vec::with_capacity(e.len() * 7);
        let (mut k0, mut o0) = (0u32, 0u32);
        for &(k, o, d) in e {
            put_varint(&mut bytes, zigzag(k as i64 - k0 as i64));
            put_varint(&mut bytes, zigzag(o as i64 - o0 as i64));
            bytes.extend_from_slice(&d.to_le_bytes());
            (k0, o0) = (k, o);
        }
        Departures {
            len: u32::try_from(e.len()).expect("fewer than 2³² kernel pairs"),
            bytes: bytes.into_boxed_slice(),
        }
    }

    /// How many entries.
    pub fn len(&self) -> usize {
        self.len as usize
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The entries, in their order.
    pub fn iter(&self) -> impl Iterator<Item = (u32, u32, f32)> + '_ {
        let mut at = 0;
        let (mut k, mut o) = (0i64, 0i64);
        (0..self.len).map(move |_| {
            k += unzigzag(take_varint(&self.bytes, &mut at));
            o += unzigzag(take_varint(&self.bytes, &mut at));
            let d = f32::from_le_bytes(self.bytes[at..at + 4].try_into().expect("4 bytes"));
            at += 4;
            (k as u32, o as u32, d)
        })
    }

    /// The entries as a list.
    pub fn to_vec(&self) -> Vec<(u32, u32, f32)> {
        self.iter().collect()
    }
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

fn unzigzag(v: u64) -> i64 {
    (v >> 1) as i64 ^ -((v & 1) as i64)
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push(v as u8 | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn take_varint(b: &[u8], at: &mut usize) -> u64 {
    let (mut v, mut shift) = (0u64, 0);
    loop {
        let byte = b[*at];
        *at += 1;
        v |= u64::from(byte & 0x7f) << shift;
        if byte < 0x80 {
            return v;
        }
        shift += 7;
    }
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
    let cell = seen_step(c, to_finer);
    let finer_cell = f.georef.step[0].max(f.georef.step[1]);
    // A coarser survey testifies against a finer one only at the scale it resolves: against
    // the finer low-passed to half its cell, and never for more than its own claim.
    let ratio = cell / finer_cell;
    let seen_coarse = (ratio >= COARSER).then(|| coreg::blurred(f, 0.5 * ratio));
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
                // Where the two differ by more than their claims allow, the excess is split
                // evenly: the least raise of both that makes them agree, and one that does
                // not favour the side that claims less (smoothness flatters a claim).
                let seen = match &seen_coarse {
                    Some(lp) => {
                        let zl = lp.at(col, r);
                        (!zl.is_nan()).then(|| (h - zl as f64).abs())
                    }
                    None => Some(d),
                };
                for k in finer.kernels_at(col, r) {
                    let own = finer.claim(k);
                    if let Some(dl) = seen {
                        let mut need = 0.5 * (dl + ef - ec);
                        if seen_coarse.is_some() {
                            need = need.min(ec);
                        }
                        raise(af, k, own, need);
                    }
                    keep_max(df, (k, kc), d);
                    keep_max(dc, (kc, k), d);
                }
                raise(ac, kc, ec, 0.5 * (d + ec - ef));
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
    // The tests of detail run on the surveys aligned where the alignment is determined, and
    // as they lie where it is not.
    let aligned = coreg.map(|k| if k.conditioned { k } else { k.as_they_lie() });
    let degradation = aligned
        .as_ref()
        .and_then(|k| coreg::degradation(f, c, to_coarser, to_finer, k, bounds));
    let detail = aligned
        .as_ref()
        .and_then(|k| detail::measure(f, c, to_coarser, to_finer, &k.placement(), bounds, cell));
    let samples = aligned
        .as_ref()
        .and_then(|k| lines::read(f, c, to_coarser, &k.placement(), bounds, cell));
    let line = samples.as_ref().and_then(lines::line);
    let transfer = samples.as_ref().and_then(transfer::measure);
    let changes = changes(
        finer,
        coarser,
        to_coarser,
        bounds,
        aligned.as_ref(),
        seen_coarse.as_ref(),
        metres_per_unit,
        ratio,
    );
    let departs_finer = departures(departs_f);
    let departs_coarser = departures(departs_c);
    // Each one's median claim over the kernels compared.
    let median_claim = |side: &Side, d: &[(u32, u32, f32)]| {
        let mut ks: Vec<u32> = d.iter().map(|e| e.0).collect();
        ks.dedup();
        let mut v: Vec<f64> = ks.iter().map(|&k| side.claim(k)).collect();
        if v.is_empty() {
            return 0.0;
        }
        let m = v.len() / 2;
        *v.select_nth_unstable_by(m, f64::total_cmp).1
    };
    let claims = (
        median_claim(finer, &departs_finer),
        median_claim(coarser, &departs_coarser),
    );
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
        detail,
        line,
        transfer,
        finer_cell,
        cell,
        metres_per_unit,
        against_finer: sorted(against_f),
        against_coarser: sorted(against_c),
        claims,
        departs_finer: Departures::new(&departs_finer),
        departs_coarser: Departures::new(&departs_coarser),
        changes,
    })
}

/// The coherent regions where the coarser, placed on the finer by `placed` (as they lie where
/// that is None), differs from the finer's samples (low-passed to the coarser's scale as
/// `seen_coarse`, where it is much coarser) by more than the level of detection: both claims
/// there, and at least [`change::SPREAD_FACTOR`] times the pair's spread once placed.
#[allow(clippy::too_many_arguments)]
fn changes(
    finer: &Side,
    coarser: &Side,
    to_coarser: Carry,
    bounds: &Aabb,
    placed: Option<&Coregistration>,
    seen_coarse: Option<&Grid>,
    metres_per_unit: [f64; 2],
    ratio: f64,
) -> Vec<Change> {
    let (f, c) = (finer.grid, coarser.grid);
    let place = placed.map_or(coreg::Placement::shift([0.0, 0.0]), |k| k.placement());
    let floor = placed.map_or(0.0, |k| change::SPREAD_FACTOR * k.nmad_after);
    // The difference at a finer sample, and the coarser's kernel there.
    let diff = |col: usize, r: usize| -> Option<(f64, u32)> {
        let z = match seen_coarse {
            Some(lp) => lp.at(col, r),
            None => f.at(col, r),
        };
        if z.is_nan() || f.at(col, r).is_nan() {
            return None;
        }
        let p = f.georef.to_world(col as f64, r as f64);
        if !bounds.contains_point(p) {
            return None;
        }
        let g = c.georef.to_grid(to_coarser(place.forth(p))?);
        let h = c.bilinear_grid(g)?;
        let dz = placed.map_or(0.0, |k| k.dz_at(p));
        Some((h - z as f64 - dz, coarser.kernel_of(g)))
    };
    let beyond: Vec<bool> = (0..f.rows)
        .into_par_iter()
        .flat_map_iter(|r| {
            let diff = &diff;
            (0..f.cols).map(move |col| {
                diff(col, r).is_some_and(|(d, kc)| {
                    let lod = (finer.claim_at(col, r) + coarser.claim(kc)).max(floor);
                    d.abs() > lod
                })
            })
        })
        .collect();
    if !beyond.contains(&true) {
        return Vec::new();
    }
    // The opening's square: a cell of the coarser survey at least, so that a cliff's line
    // of its interpolation errors is no change.
    let w = ((0.5 * ratio).ceil() as usize).max(1);
    let least = (4.0 * ratio * ratio).ceil().max(16.0) as usize;
    let cell_m2 = f.georef.step[0] * metres_per_unit[0] * f.georef.step[1] * metres_per_unit[1];
    change::regions(&beyond, f.cols, f.rows, w, least)
        .into_iter()
        .map(|region| {
            let mut out = Change {
                bounds: Aabb::new(f64::MAX, f64::MAX, f64::MIN, f64::MIN),
                samples: region.len() as u64,
                area_m2: region.len() as f64 * cell_m2,
                above_m3: 0.0,
                below_m3: 0.0,
                most_m: 0.0,
                finer_kernels: Vec::new(),
                coarser_kernels: Vec::new(),
            };
            let (mut fk, mut ck) = (HashMap::new(), HashMap::new());
            for i in region {
                let (col, r) = (i % f.cols, i / f.cols);
                let Some((d, kc)) = diff(col, r) else {
                    continue;
                };
                let p = f.georef.to_world(col as f64, r as f64);
                out.bounds.min = [out.bounds.min[0].min(p[0]), out.bounds.min[1].min(p[1])];
                out.bounds.max = [out.bounds.max[0].max(p[0]), out.bounds.max[1].max(p[1])];
                if d > 0.0 {
                    out.above_m3 += d * cell_m2;
                } else {
                    out.below_m3 -= d * cell_m2;
                }
                out.most_m = out.most_m.max(d.abs());
                for k in finer.kernels_at(col, r) {
                    keep_max(&mut fk, k, d.abs());
                }
                keep_max(&mut ck, kc, d.abs());
            }
            let sorted = |m: HashMap<u32, f32>| {
                let mut v: Vec<(u32, f32)> = m.into_iter().collect();
                v.sort_unstable_by_key(|e| e.0);
                v
            };
            out.finer_kernels = sorted(fk);
            out.coarser_kernels = sorted(ck);
            out
        })
        .collect()
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

    /// Whether one survey lies shifted, turned, stretched, offset or tilted from the other:
    /// somewhere in the overlap by half the coarser cell or more, or by more height than the
    /// spread of their differences once aligned explains.
    pub fn misregistered(&self) -> bool {
        self.coreg.as_ref().is_some_and(|c| {
            c.conditioned
                && (c.largest_move() >= 0.5 * self.cell
                    || c.largest_rise() > (3.0 * c.nmad_after).max(1.0))
        })
    }

    /// Which one the comparison of predictions finds degraded (see
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

    /// Which one the pair alone finds the lesser copy, by the first test that decides: the
    /// predictions (a low-pass of one predicts the other, and not the other way round), the
    /// bands' shared detail (one lacks detail the other has, which noise cannot fake), the
    /// transfer between them (one a filter of the other, ring by ring of their spectra),
    /// added noise (one holds detail the other does not share, while all of the other's is
    /// shared), or a line in the spectrum of their differences that one side holds, or lacks,
    /// where the other's is smooth. None where no test decides.
    pub fn finding(&self) -> Option<(Blame, Decided)> {
        if let Some(d) = &self.degradation {
            let ratio = |a: f64, b: f64| if b > 0.0 { a / b } else { 1.0 };
            let (a, b) = (d.other_from_reference.rms, d.reference_from_other.rms);
            match self.degraded() {
                Degraded::Other if self.may_be_degraded(false) => {
                    return Some((Blame::Coarser, Decided::new(Test::Prediction, ratio(a, b))))
                }
                Degraded::Reference if self.may_be_degraded(true) => {
                    return Some((Blame::Finer, Decided::new(Test::Prediction, ratio(b, a))))
                }
                _ => {}
            }
        }
        let found = self
            .detail
            .as_ref()
            .map_or(Finding::Undecided, |d| d.finding());
        match found {
            Finding::ReferenceLacks { gain, .. } => {
                return Some((Blame::Finer, Decided::new(Test::Detail, gain)))
            }
            Finding::OtherLacks { gain, .. } => {
                return Some((Blame::Coarser, Decided::new(Test::Detail, gain)))
            }
            _ => {}
        }
        // The reference blamed where `reference`, else the other.
        let blame = |reference: bool| {
            if reference {
                Blame::Finer
            } else {
                Blame::Coarser
            }
        };
        // Before noise: a hard low-pass leaves its copy's bands all shared, and the
        // original's excess over them reads as noise; ring by ring it is a filter.
        if let Some(t) = &self.transfer {
            if let Some(reference) = t.filtered() {
                return Some((
                    blame(reference),
                    Decided::new(Test::Transfer, t.statistic()),
                ));
            }
        }
        let by_detail = match found {
            Finding::ReferenceNoisy { excess, .. } => {
                Some((Blame::Finer, Decided::new(Test::Noise, excess)))
            }
            Finding::OtherNoisy { excess, .. } => {
                Some((Blame::Coarser, Decided::new(Test::Noise, excess)))
            }
            _ => None,
        };
        by_detail.or_else(|| {
            let l = self.line.as_ref()?;
            Some((blame(l.altered()?), Decided::new(Test::Line, l.standing())))
        })
    }

    /// Whether the side the predictions find degraded (the finer where `finer`) may be.
    /// Noise turns the predictions round (a low-pass of a noisy copy predicts the clean
    /// original, which cannot predict noise). Its mark at the finest band is a clean side
    /// whose detail is all shared (`E / C` within 2% of 1) beside one holding detail the
    /// other does not share (over 1.1), or beside one whose `E / C` is over twice its own
    /// (and 2); where the band shares too little to say, a side with over twice the other's
    /// energy. A blurred or resampled copy lacks shared detail or holds aliases of its own,
    /// and is not taken for the clean side.
    fn may_be_degraded(&self, finer: bool) -> bool {
        let Some(b) = self.detail.as_ref().and_then(|d| d.bands.first()) else {
            return true;
        };
        let pick = |r: f64, o: f64| if finer { (r, o) } else { (o, r) };
        if b.informative() {
            // A side whose band holds more than twice the unshared energy of this one's (and
            // of a clean one's) is not cleaner: junk a filter left round voids and edges, as
            // a transform's ringing, turns the predictions round as noise does.
            let (mine, theirs) = pick(b.reference_gain(), b.other_gain());
            !(((0.98..=1.02).contains(&mine) && theirs > 1.1) || theirs > 2.0 * mine.max(1.0))
        } else {
            let (mine, theirs) = pick(b.energy_reference, b.energy_other);
            theirs <= 2.0 * mine
        }
    }

    /// The cell of the coarser over the cell of the finer.
    pub fn cell_ratio(&self) -> f64 {
        if self.finer_cell > 0.0 {
            self.cell / self.finer_cell
        } else {
            1.0
        }
    }

    /// Who takes a pair that nothing decides: the finer cells, then the one a low-pass of the
    /// other predicts less well (by half), then the one whose bands lack less of the detail
    /// the two share, then the one that adds less detail the other does not share. The
    /// predictions come before the bands because they read each side both bilinearly and by
    /// a cubic, where the bands read the other side bilinearly alone: placed by a fraction of
    /// a cell, that reading smooths it, and a copy turned by 0.1° with a cubic, taken as the
    /// reference, made its original seem to lack 6% of the finest shared detail while the
    /// original predicted it 2.7 times better than the reverse. Never the smoother
    /// by its own estimate, which smoothness flatters. Some(true) where the finer survey
    /// takes it; None where nothing tells them apart (the same content moved or offset),
    /// and the claims, raised alike, decide. Where the two hold the same detail, the one
    /// claiming less over the overlap takes it.
    pub fn tie_to_finer(&self) -> Option<bool> {
        if self.cell_ratio() >= COARSER_TIE {
            return Some(true);
        }
        let detail = self.detail.as_ref();
        if let Some(d) = &self.degradation {
            let (a, b) = (d.other_from_reference.rms, d.reference_from_other.rms);
            if a < 0.5 * b && self.may_be_degraded(false) {
                return Some(true);
            }
            if b < 0.5 * a && self.may_be_degraded(true) {
                return Some(false);
            }
        }
        if let Some(lack) = detail.map(|d| d.lack()) {
            if lack.abs() > LEAN {
                return Some(lack < 0.0);
            }
        }
        if let Some(x) = detail.and_then(|d| d.excess()) {
            if x.abs() > 0.1 {
                return Some(x > 0.0);
            }
        }
        // The two hold the same detail: the lower claim over the overlap, which no longer
        // flatters one for being smoother.
        match self.claims.0.total_cmp(&self.claims.1) {
            std::cmp::Ordering::Less => Some(true),
            std::cmp::Ordering::Greater => Some(false),
            std::cmp::Ordering::Equal => None,
        }
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
    pub fn departs(&self, id: SurveyId) -> &Departures {
        if id == self.finer {
            &self.departs_finer
        } else {
            &self.departs_coarser
        }
    }
}

/// How far apart two surveys' cells must be for the coarser's evidence to be taken at its
/// own scale.
const COARSER: f64 = 2.0;
/// How far apart their cells must be for a pair nothing decides to go to the finer outright.
const COARSER_TIE: f64 = 1.25;
/// The least lack of shared detail (the sum of `ln E / C` under 1) that leans a tie: the
/// figure of two copies of one content moved by whole cells is within ±0.01.
const LEAN: f64 = 0.02;

/// The test that decided a pair.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Test {
    /// A low-pass of one predicts the other, and not the other way round; the statistic is
    /// the ratio of the two predictions' residuals (under [`coreg::DEGRADED_RATIO`]).
    Prediction,
    /// One lacks detail the other has: the statistic is its band's `E / C`, an upper bound
    /// on its gain there (under [`detail::LACKS_BELOW`]).
    Detail,
    /// One adds detail the other does not share: the statistic is its band's excess
    /// `E / C − 1` (over [`detail::NOISY_ABOVE`]).
    Noise,
    /// One holds a line in its spectrum (stripes) or a notch that the other, smooth there,
    /// lacks: the statistic is how many times it stands out from its ring (over
    /// [`lines::ALTERED`]).
    Line,
    /// One is a filter of the other: it lost power coherently over several rings of their
    /// spectra, or its spectrum falls off an edge where the other's is smooth; the statistic
    /// is the edge's fall, else the rings of coherent loss (see [`super::transfer`]).
    Transfer,
    /// Surveys overlapping both lie where one lies: the statistic is the margin of votes.
    Consensus,
    /// Nothing decides: the statistic is 0, and the pair's tie goes as
    /// [`PairEvidence::tie_to_finer`] says.
    Undetermined,
}

impl Test {
    /// The name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Test::Prediction => "prediction",
            Test::Detail => "detail",
            Test::Noise => "noise",
            Test::Line => "line",
            Test::Transfer => "transfer",
            Test::Consensus => "consensus",
            Test::Undetermined => "undetermined",
        }
    }
}

/// A decision with the figure it rests on and how far that figure is past its threshold,
/// from 0 (at it) to 1.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Decided {
    /// The test.
    pub test: Test,
    /// Its statistic.
    pub statistic: f64,
    /// How clear the decision is: 0 at the threshold, 1 as clear as it gets.
    pub confidence: f64,
}

impl Decided {
    fn new(test: Test, statistic: f64) -> Self {
        let confidence = match test {
            Test::Prediction => 1.0 - statistic / coreg::DEGRADED_RATIO,
            Test::Detail => 1.0 - statistic / detail::LACKS_BELOW,
            Test::Noise => 1.0 - detail::NOISY_ABOVE / statistic,
            Test::Line => 1.0 - lines::ALTERED.ln() / statistic.ln(),
            // Rings of loss over the least that count; an edge (20 or more) is near 1.
            Test::Transfer => 1.0 - transfer::LEAST_LOSSY as f64 / statistic,
            Test::Consensus => statistic,
            Test::Undetermined => 0.0,
        };
        Decided {
            test,
            statistic,
            confidence: confidence.clamp(0.0, 1.0),
        }
    }
}

/// What a pair's evidence decides: whose claim is false, if any, and by which test.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Verdict {
    /// Whose claim is false; None for a pair that contradicts nothing and holds no copy.
    pub blame: Option<Blame>,
    /// How it was decided.
    pub by: Decided,
}

/// Which claim of a pair is false, given the pairs each of its surveys makes with every survey
/// that overlaps both: `thirds` yields, for each such survey, its pair with the finer and its
/// pair with the coarser. A lesser copy (see [`PairEvidence::finding`]) is blamed whether or
/// not its claims contradict the other's, since it must not displace what it was made from;
/// otherwise there is no blame for a pair that contradicts nothing.
pub fn blame<'a>(
    pair: &PairEvidence,
    thirds: impl Iterator<Item = (&'a PairEvidence, &'a PairEvidence)>,
) -> Verdict {
    if let Some((blame, by)) = pair.finding() {
        return Verdict {
            blame: Some(blame),
            by,
        };
    }
    let undetermined = |blame| Verdict {
        blame,
        by: Decided::new(Test::Undetermined, 0.0),
    };
    if !pair.contradicted() {
        return undetermined(None);
    }
    // Two surveys of one content, one moved: whichever lies where the others lie is right.
    if !pair.misregistered() {
        return undetermined(Some(Blame::Both));
    }
    let (mut finer_off, mut coarser_off) = (0, 0);
    for (with_finer, with_coarser) in thirds {
        match (with_finer.misregistered(), with_coarser.misregistered()) {
            (false, true) => coarser_off += 1,
            (true, false) => finer_off += 1,
            _ => {}
        }
    }
    let margin = |a: i32, b: i32| (a - b) as f64 / (a + b) as f64;
    match coarser_off.cmp(&finer_off) {
        std::cmp::Ordering::Greater => Verdict {
            blame: Some(Blame::Coarser),
            by: Decided::new(Test::Consensus, margin(coarser_off, finer_off)),
        },
        std::cmp::Ordering::Less => Verdict {
            blame: Some(Blame::Finer),
            by: Decided::new(Test::Consensus, margin(finer_off, coarser_off)),
        },
        std::cmp::Ordering::Equal => undetermined(Some(Blame::Both)),
    }
}

#[cfg(test)]
mod departures_tests {
    use super::Departures;

    /// Lists of every shape come back as they went in: steps up and down, far jumps, the ends
    /// of u32, and differences of every kind of f32 (the bits kept, NaN included).
    #[test]
    fn departures_come_back_as_they_went_in() {
        // As the workspace's other random tests draw theirs (testkit's `seed`, which this
        // crate sits below): PATCHWORK_SEED replays a run.
        let seed = std::env::var("PATCHWORK_SEED")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| {
                std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(1, |d| d.as_nanos() as u64)
            });
        println!("seed {seed} (PATCHWORK_SEED={seed} replays it)");
        let mut x = seed;
        let mut next = move || {
            // splitmix64
            x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = x;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        };
        for case in 0..200 {
            let n = (next() % 300) as usize;
            let mut e: Vec<(u32, u32, f32)> = Vec::with_capacity(n);
            let (mut k, mut o) = (0u32, 0u32);
            for _ in 0..n {
                match next() % 4 {
                    0 => (k, o) = (next() as u32, next() as u32),
                    1 => (k, o) = (u32::MAX - (next() % 3) as u32, (next() % 3) as u32),
                    _ => {
                        k = k.wrapping_add((next() % 3) as u32);
                        o = o.wrapping_add((next() % 300) as u32).wrapping_sub(150);
                    }
                }
                e.push((k, o, f32::from_bits(next() as u32)));
            }
            let d = Departures::new(&e);
            assert_eq!(d.len(), n, "case {case}");
            let back = d.to_vec();
            let bits = |v: &[(u32, u32, f32)]| -> Vec<(u32, u32, u32)> {
                v.iter().map(|&(a, b, c)| (a, b, c.to_bits())).collect()
            };
            assert_eq!(bits(&back), bits(&e), "case {case}");
        }
    }

    /// An ascending list of a real overlap's shape, kernels meeting in twos and threes, packs
    /// into about half of what the tuples took.
    #[test]
    fn a_list_in_order_packs_into_about_half() {
        let dims = 150u32;
        let mut e = Vec::new();
        for k in 0..dims * dims {
            let (c, r) = (k % dims, k / dims);
            for (dc, dr) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                if c + dc < dims && r + dr < dims {
                    e.push((k, (r + dr) * dims + c + dc, 0.5 + (k % 7) as f32));
                }
            }
        }
        let d = Departures::new(&e);
        let per = d.bytes.len() as f64 / e.len() as f64;
        assert!(per <= 7.0, "{per} bytes an entry");
        assert_eq!(d.to_vec(), e);
    }
}
