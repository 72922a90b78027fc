//! Copies degraded beyond the family the arbitration between surveys was first built on
//! (`patchwork_testkit::widened`), drawn at random at test time: the seed is printed, and
//! `PATCHWORK_SEED` replays it, `PATCHWORK_DRAWS` sets how many draws. Each copy lies on the
//! original's lattice, with no sidecar; the store must still serve the original at e = 0.
//! The kinds held back from development are reported apart.

use crate::common::*;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::AccuracySpec;
use patchwork_core::model::evidence::{Contradicted, Test};
use patchwork_core::model::grid::Grid;
use patchwork_core::model::survey::Survey;
use patchwork_core::terrain::Terrain;
use patchwork_testkit::degrade::SCENES;
use patchwork_testkit::widened::{self, served_within, Kind};
use std::sync::Arc;

fn draws(default: usize) -> usize {
    std::env::var("PATCHWORK_DRAWS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// What one draw found.
struct Draw {
    /// The line to print.
    line: String,
    /// The share of the original's samples served within 1 m.
    share: f64,
    /// Whether a held-back kind was drawn.
    held_back: bool,
    /// Whether the pair was left undetermined.
    undetermined: bool,
}

/// One draw: a crop, one copy of it made by `pick`'s kinds (one to `most` chained), both
/// inserted in a random order, and the share of the original served within 1 m.
fn one_draw(
    scenes: &[(&str, (Grid, Option<patchwork_core::crs::Crs>))],
    next: &mut impl FnMut() -> f64,
    pick: impl Fn(Kind) -> bool,
    most: usize,
) -> Draw {
    let (name, (g, crs)) = &scenes[(next() * scenes.len() as f64) as usize];
    let build = |g: Grid| {
        Arc::new(Survey::build(g, AccuracySpec::Auto, crs.clone(), Default::default()).unwrap())
    };
    let (label, copy, kinds) = widened::draw(g, next, pick, most, false);
    let original = build(g.clone());
    let mut both = [original.clone(), build(copy)];
    if next() < 0.5 {
        both.swap(0, 1);
    }
    let mut t = Terrain::new(IndexConfig::default());
    t.set_contradicted(Contradicted::Distrust);
    for s in &both {
        t.insert(s.clone());
    }
    let share = served_within(&t, g, 1.0);
    let original = Some(original.id);
    let undetermined = t.pairs().iter().all(|p| {
        t.verdict(p.finer, p.coarser)
            .is_none_or(|v| v.by.test == Test::Undetermined)
    });
    let verdicts: Vec<String> =
        t.pairs()
            .iter()
            .map(|p| {
                let mut v = format!("{:?}", t.verdict(p.finer, p.coarser).map(|v| v.by.test));
                if share < 0.9 {
                    // Why the pair let the copy serve.
                    v += &format!(
                    "; the original is the {}; predictions {:?}; claims {:?}; tie to the finer \
                     {:?}; line {:?}; transfer {:?}; bands {:?}",
                    if Some(p.finer) == original { "finer" } else { "coarser" },
                    p.degradation,
                    p.claims,
                    p.tie_to_finer(),
                    p.line,
                    p.transfer,
                    p.detail.as_ref().map(|d| d
                        .bands
                        .iter()
                        .map(|b| (b.reference_gain(), b.other_gain()))
                        .collect::<Vec<_>>()),
                );
                }
                v
            })
            .collect();
    Draw {
        line: format!(
            "{name}, {label}: {:.1}% within 1 m ({})",
            100.0 * share,
            verdicts.join(", ")
        ),
        share,
        held_back: kinds.iter().any(|k| k.held_back()),
        undetermined,
    }
}

/// Copies turned, stretched or sheared (bilinear or cubic): the pair is placed by an affine
/// map, after which the copy's resampling shows as a filter of the original. Pooled, the
/// original serves at least 98% of its samples within 1 m; in every draw at least 90%.
/// Shears are held back. Two or three resamplings chained, by a cubic, are a known limit
/// (docs/MODEL.md, "Coregistration").
#[test]
fn copies_turned_stretched_or_sheared_do_not_displace_their_original() {
    let seed = seed();
    let n = draws(10);
    let scenes: Vec<_> = SCENES.iter().map(|n| (*n, real_crop_in_crs(n))).collect();
    let mut next = uniform(seed);
    let placements = |k: Kind| matches!(k, Kind::Rotation | Kind::Stretch | Kind::Shear);
    let (mut all, mut held, mut low) = (Vec::new(), Vec::new(), Vec::new());
    for draw in 0..n {
        let Draw {
            line,
            share,
            held_back,
            ..
        } = one_draw(&scenes, &mut next, placements, 1);
        println!("draw {draw}: {line}");
        if held_back {
            held.push(share);
        } else {
            all.push(share);
        }
        if share < 0.9 {
            low.push(format!("draw {draw}: {line}"));
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    println!(
        "seed {seed}: pooled {:.1}% over {} draws; held back (shears) {:.1}% over {}",
        100.0 * mean(&all),
        all.len(),
        100.0 * mean(&held),
        held.len()
    );
    assert!(
        low.is_empty(),
        "seed {seed}: the original kept under 90% in:\n{}",
        low.join("\n")
    );
    let pooled = mean(&[all, held].concat());
    assert!(pooled >= 0.98, "seed {seed}: pooled {:.1}%", 100.0 * pooled);
}

/// The smallest turns the drawn family holds, found: a copy of the Rhine crop turned by
/// 0.1–0.115° either way with a cubic moves its corners by a fifth of a cell, and lowers the
/// NMAD of the differences by 0.1–4% only (the rest is the cubic's own), yet every part of the
/// overlap turns alike. The pair is placed with the turn, found to a quarter of itself, and
/// the original serves, whichever comes first. Left with its shift (the rule of a tenth), a
/// turn of 0.11° read as a symmetric misfit and the copy's lower claim served 57% of the
/// original's ground.
#[test]
fn a_copy_turned_by_a_tenth_of_a_degree_is_placed_with_its_turn() {
    let (g, crs) = real_crop_in_crs("real/rhine_deflate_strips.tif");
    let build = |g: Grid| {
        Arc::new(Survey::build(g, AccuracySpec::Auto, crs.clone(), Default::default()).unwrap())
    };
    let original = build(g.clone());
    for a in [0.1, 0.105, 0.11, 0.115, -0.1, -0.105, -0.11, -0.115] {
        let copy = build(patchwork_testkit::degrade::warped(
            &g,
            patchwork_testkit::degrade::rotation(a),
            true,
        ));
        for order in [[&original, &copy], [&copy, &original]] {
            let mut t = Terrain::new(IndexConfig::default());
            t.set_contradicted(Contradicted::Distrust);
            for s in order {
                t.insert(s.clone());
            }
            let pair = &t.pairs()[0];
            let c = pair.coreg.expect("coregistered");
            let (turned, scale) = c.placement().rotation_and_scale();
            // Seen from either side, the other lies turned by the angle one way or the other;
            // the fit reads a little short of it (0.084° for 0.1°).
            assert!(
                (turned.abs() - a.abs()).abs() < 0.25 * a.abs() && (scale - 1.0).abs() < 1e-3,
                "{a}°: turned {turned}°, scale {scale}: {c:?}"
            );
            let share = served_within(&t, &g, 1.0);
            assert!(
                share >= 0.99,
                "{a}°: the original serves {:.1}% ({:?}; the original is the finer: {}; \
                 predictions {:?}; claims {:?}; tie to the finer {:?}; transfer {:?}; bands {:?})",
                100.0 * share,
                t.verdict(pair.finer, pair.coarser).map(|v| v.by.test),
                pair.finer == original.id,
                pair.degradation,
                pair.claims,
                pair.tie_to_finer(),
                pair.transfer,
                pair.detail.as_ref().map(|d| d
                    .bands
                    .iter()
                    .map(|b| (b.reference_gain(), b.other_gain()))
                    .collect::<Vec<_>>()),
            );
        }
    }
}

/// Copies filtered (in the frequency domain, sharpened after a blur, ringing), trended,
/// striped, filled with fabricated ground or aliased, one to three chained, any kind with any
/// other, the placements included. Where the pair decides, it decides for the original: in
/// all but one decided draw in ten the original keeps at least 90% of its samples within 1 m
/// (every one is the goal; the known exception is below), and pooled over the rest at least
/// 98%. Some pairs are symmetric, and no rule on the two alone can tell
/// which is the original (a copy that is the original plus a plane is the original less a
/// plane, and stripes weaker than the ground's own relief at their wavelength are as much
/// in one as the other): those must be reported undetermined, and are counted apart.
/// Ringing, slanted stripes and a lossy codec's cosine blocks are held back, with shears.
#[test]
fn copies_filtered_striped_filled_or_aliased_do_not_displace_their_original() {
    let seed = seed();
    let n = draws(12);
    let scenes: Vec<_> = SCENES.iter().map(|n| (*n, real_crop_in_crs(n))).collect();
    let mut next = uniform(seed);
    let (mut decided, mut held, mut undecided, mut wrong) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for draw in 0..n {
        // Every other draw a kind alone, so that each is seen on its own as well as chained.
        let most = if draw % 2 == 0 { 1 } else { 3 };
        let d = one_draw(&scenes, &mut next, |_| true, most);
        println!("draw {draw}: {}", d.line);
        if d.undetermined {
            undecided.push(d.share);
        } else if d.held_back {
            held.push(d.share);
        } else {
            decided.push(d.share);
        }
        if d.share < 0.9 && !d.undetermined {
            wrong.push(format!("draw {draw}: {}", d.line));
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    println!(
        "seed {seed}: decided, pooled {:.1}% over {} draws; held back {:.1}% over {}; \
         undetermined {} draws, the original keeping {:.1}%; all {:.1}%",
        100.0 * mean(&decided),
        decided.len(),
        100.0 * mean(&held),
        held.len(),
        undecided.len(),
        100.0 * mean(&undecided),
        100.0 * mean(&[decided.clone(), held.clone(), undecided.clone()].concat()),
    );
    // A known limit, not yet met: a copy low-passed hard (a Butterworth at a sixth of the
    // Nyquist frequency, after a turn) beside rough ground of 1 km cells can read as noise in
    // the original: about one draw in 300. One draw in ten is the bound this test holds.
    if !wrong.is_empty() {
        println!(
            "seed {seed}: decided for the copy, the original keeping under 90%, in:\n{}",
            wrong.join("\n")
        );
    }
    assert!(
        wrong.len() <= n / 10,
        "seed {seed}: decided for the copy, the original keeping under 90%, in:\n{}",
        wrong.join("\n")
    );
    // Pooled over the decided draws but the one in ten allowed above.
    let kept: Vec<f64> = [decided, held]
        .concat()
        .into_iter()
        .filter(|&x| x >= 0.9)
        .collect();
    let pooled = mean(&kept);
    assert!(pooled >= 0.98, "seed {seed}: pooled {:.1}%", 100.0 * pooled);
}
