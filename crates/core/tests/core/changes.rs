//! Ground that changed between two dated surveys (`patchwork_testkit::changes`), drawn at
//! random at test time: the seed is printed, `PATCHWORK_SEED` replays it and
//! `PATCHWORK_DRAWS` sets how many draws. Each draw takes a real crop as the ground of 2000,
//! changes it, and resurveys the changed ground in 2024 on another lattice or the same, with
//! noise; both are inserted in a random order. The later survey must serve the changed
//! ground, and unchanged ground must stay within both surveys' claims; the other order gives
//! the same heights, and retiring either survey gives the store that never had it.

use crate::common::*;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::AccuracySpec;
use patchwork_core::model::epoch::Epoch;
use patchwork_core::model::evidence::Contradicted;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::survey::Survey;
use patchwork_core::terrain::Terrain;
use patchwork_testkit::changes::{self, Kind};
use patchwork_testkit::degrade::SCENES;
use std::sync::Arc;

fn draws(default: usize) -> usize {
    std::env::var("PATCHWORK_DRAWS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// What one draw measured.
struct Measured {
    line: String,
    /// Changed samples (beyond both claims), and how many the later survey served.
    changed: (usize, usize),
    /// Unchanged samples, and how many were served within both claims of the ground.
    unchanged: (usize, usize),
    held_back: bool,
}

fn one_draw(
    scenes: &[(&str, (Grid, Option<patchwork_core::crs::Crs>))],
    next: &mut impl FnMut() -> f64,
    seed: u64,
) -> Measured {
    let (name, (g, crs)) = &scenes[(next() * scenes.len() as f64) as usize];
    let kind = Kind::ALL[(next() * Kind::ALL.len() as f64) as usize];
    let build = |g: Grid, when: &str| {
        Arc::new(
            Survey::build(g, AccuracySpec::Auto, crs.clone(), Default::default())
                .unwrap()
                .with_epoch(Some(Epoch::parse(when).unwrap())),
        )
    };
    let before = build(g.clone(), "2000-02-11/2000-02-22");
    // Changes at least as high as twice the ground's median claim (a resurvey's is about
    // the same): the level of detection of most of the pair.
    let drawn = changes::apply(kind, g, 2.0 * median_claim(&before), next);
    let (how, resurveyed) = changes::resurvey(&drawn.after, next, seed);
    let after = build(resurveyed, "2024-05");
    // The level of detection at a point: both surveys' claims there.
    let lod = |p: [f64; 2]| claim_at(&before, p) + claim_at(&after, p);
    let mut both = [before.clone(), after.clone()];
    if next() < 0.5 {
        both.swap(0, 1);
    }
    let terrain = |order: &[Arc<Survey>]| {
        let mut t = Terrain::new(IndexConfig::default());
        t.set_contradicted(Contradicted::Distrust);
        for s in order {
            t.insert(s.clone());
        }
        t
    };
    let t = terrain(&both);
    // Where a coarser resurvey's interpolation mixes changed and unchanged ground, neither
    // counts: two of its cells around every changed sample.
    let margin = (after.levels[0].georef.step[0] / g.georef.step[0] * 2.0).ceil() as isize;
    let near_change = |c: usize, r: usize| {
        (-margin..=margin).any(|dr| {
            (-margin..=margin).any(|dc| {
                let (cc, rr) = (c as isize + dc, r as isize + dr);
                cc >= 0
                    && rr >= 0
                    && (cc as usize) < g.cols
                    && (rr as usize) < g.rows
                    && drawn.delta[rr as usize * g.cols + cc as usize] != 0.0
            })
        })
    };
    let (mut pts, mut which) = (Vec::new(), Vec::new());
    for r in 0..g.rows {
        for c in 0..g.cols {
            let i = r * g.cols + c;
            if g.samples[i].is_nan() {
                continue;
            }
            let d = drawn.delta[i] as f64;
            let p = g.georef.to_world(c as f64, r as f64);
            // Changed: beyond twice the level of detection, where a change is found whatever
            // the noise (a sample just past it is found about half the time).
            let class = if d.abs() > 2.0 * lod(p) {
                Some(true)
            } else if !near_change(c, r) {
                Some(false)
            } else {
                None
            };
            if let Some(changed) = class {
                pts.push(p);
                which.push((i, changed));
            }
        }
    }
    let got = t.sample(&pts, 0.0);
    let (mut changed, mut unchanged) = ((0, 0), (0, 0));
    for ((h, &(i, is_changed)), &p) in got.iter().zip(&which).zip(&pts) {
        let h = *h as f64;
        if is_changed {
            changed.0 += 1;
            let d = drawn.delta[i] as f64;
            let now = drawn.after.samples[i] as f64;
            changed.1 += (!h.is_nan() && (h - now).abs() < 0.5 * d.abs()) as usize;
        } else {
            unchanged.0 += 1;
            let z = g.samples[i] as f64;
            unchanged.1 += (!h.is_nan() && (h - z).abs() <= lod(p)) as usize;
        }
    }
    // The other order gives the same heights, to the bit.
    both.swap(0, 1);
    let again = terrain(&both).sample(&pts, 0.0);
    assert!(
        got.iter()
            .zip(&again)
            .all(|(a, b)| a.to_bits() == b.to_bits()),
        "{name}, {}: the order of insertion changed heights",
        drawn.label
    );
    // Retiring either gives the store that never had it.
    for gone in [&before, &after] {
        let mut retired = t.clone();
        assert!(retired.retire(gone.id).is_some());
        let kept: Vec<_> = both.iter().filter(|s| s.id != gone.id).cloned().collect();
        assert_eq!(
            retired.index().state(),
            terrain(&kept).index().state(),
            "{name}, {}: retiring a survey left a trace",
            drawn.label
        );
    }
    let found: Vec<String> = t
        .pairs()
        .iter()
        .map(|p| {
            format!(
                "{} region(s), {:.0} m² in all, later {:?}",
                p.changes.len(),
                p.changes.iter().map(|c| c.area_m2).sum::<f64>(),
                t.later(p).map(|l| if l == after.id {
                    "resurvey"
                } else {
                    "original"
                })
            )
        })
        .collect();
    let share = |(n, ok): (usize, usize)| 100.0 * ok as f64 / n.max(1) as f64;
    Measured {
        line: format!(
            "{name}, {} ({how}): changed {:.1}% of {} served as resurveyed, unchanged {:.1}% of \
             {} within both claims (medians {:.2} and {:.2} m) [{}]",
            drawn.label,
            share(changed),
            changed.0,
            share(unchanged),
            unchanged.0,
            median_claim(&before),
            median_claim(&after),
            found.join("; ")
        ),
        changed,
        unchanged,
        held_back: kind.held_back(),
    }
}

/// A survey's claim at `p`: its level-0 kernel's there (the nearest, outside it).
fn claim_at(s: &Survey, p: [f64; 2]) -> f64 {
    let g = &s.levels[0];
    let q = g.georef.to_grid(p);
    let [cw, ch] = s.tiling.cells;
    let c = q[0].floor().clamp(0.0, (cw.max(1) - 1) as f64) as u32;
    let r = q[1].floor().clamp(0.0, (ch.max(1) - 1) as f64) as u32;
    let k = s.tiling.kernel_at(c, r);
    s.kernel_accuracy.values[(k[1] as usize) * s.kernel_accuracy.dims[0] + k[0] as usize]
}

fn median_claim(s: &Survey) -> f64 {
    let mut v = s.kernel_accuracy.values.clone();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Pits, mounds, slides, coasts cut back and platforms levelled, resurveyed later on another
/// lattice or the same with noise: the later survey serves at least 95% of the changed
/// samples (beyond twice both claims) pooled, and 75% in every draw that changed 64 or more
/// (a platform cut and filled over steep ground, resurveyed on a moved lattice, has kept
/// 80%), and the unchanged ground at least 99% within both claims. Trenches are held back and reported apart.
#[test]
fn changed_ground_is_served_by_the_survey_that_saw_it_last() {
    let seed = seed();
    let n = draws(8);
    let scenes: Vec<_> = SCENES.iter().map(|n| (*n, real_crop_in_crs(n))).collect();
    let mut next = uniform(seed);
    let (mut pooled, mut held, mut calm) = ((0, 0), (0, 0), (0, 0));
    let mut low = Vec::new();
    for draw in 0..n {
        let m = one_draw(&scenes, &mut next, seed ^ draw as u64);
        println!("draw {draw}: {}", m.line);
        let into = if m.held_back { &mut held } else { &mut pooled };
        into.0 += m.changed.0;
        into.1 += m.changed.1;
        calm.0 += m.unchanged.0;
        calm.1 += m.unchanged.1;
        // A draw whose change leaves fewer samples than a few coherent regions' least size
        // counts in the pool only.
        if m.changed.0 >= 64 && (m.changed.1 as f64) < 0.75 * m.changed.0 as f64 {
            low.push(format!("draw {draw}: {}", m.line));
        }
        if (m.unchanged.1 as f64) < 0.99 * m.unchanged.0 as f64 {
            low.push(format!("draw {draw} (unchanged ground): {}", m.line));
        }
    }
    let share = |(n, ok): (usize, usize)| 100.0 * ok as f64 / n.max(1) as f64;
    println!(
        "seed {seed}: changed ground served as resurveyed {:.1}% of {}; held back (trenches) \
         {:.1}% of {}; unchanged within both claims {:.2}% of {}",
        share(pooled),
        pooled.0,
        share(held),
        held.0,
        share(calm),
        calm.0
    );
    assert!(
        low.is_empty(),
        "seed {seed}: short of the mark in:\n{}",
        low.join("\n")
    );
    assert!(
        pooled.1 as f64 >= 0.95 * pooled.0 as f64,
        "seed {seed}: pooled {:.1}%",
        share(pooled)
    );
}
