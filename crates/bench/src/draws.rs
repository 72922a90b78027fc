//! Degraded copies drawn at random beside their originals (`patchwork_testkit::degrade`):
//! the share of each original's samples it still serves at e = 0 within its own claim, per
//! draw (`draws.csv`), and per kind of operation, how many of the draws holding it fell under
//! 98% and the lowest share they left. Then copies of the widened family
//! (`patchwork_testkit::widened`), each kind in turn, with the share of the original served
//! within 1 m (`widened.csv`), and changed ground resurveyed later
//! (`patchwork_testkit::changes`), each kind in turn, with the share of the changed samples
//! the later survey serves (`changes.csv`).

use crate::Fail;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::AccuracySpec;
use patchwork_core::model::epoch::Epoch;
use patchwork_core::model::evidence::Contradicted;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::survey::Survey;
use patchwork_core::terrain::Terrain;
use patchwork_testkit::changes;
use patchwork_testkit::degrade::{self, SCENES};
use patchwork_testkit::fixtures::real_crop_in_crs;
use patchwork_testkit::widened;
use std::fmt::Write as _;
use std::path::Path;
use std::sync::Arc;

/// The kinds of operation, as their labels begin.
const KINDS: [&str; 10] = [
    "gaussian",
    "box",
    "median",
    "bilinear",
    "cubic",
    "B-spline",
    "shift",
    "offset",
    "noise",
    "quantised",
];

/// Runs `n` draws from `seed` and writes `draws.csv` under `out`.
pub fn run(out: &Path, n: usize, seed: u64) -> Result<(), Fail> {
    std::fs::create_dir_all(out)?;
    println!("{n} draws, seed {seed}");
    let scenes: Vec<_> = SCENES.iter().map(|s| (*s, real_crop_in_crs(s))).collect();
    let mut next = patchwork_core::geom::rng::uniform(seed);
    let mut csv = String::from("draw,scene,copies,share,samples\n");
    let mut rows: Vec<(String, Vec<String>, f64)> = Vec::new();
    for k in 0..n {
        let (name, (g, crs)) = &scenes[(next() * scenes.len() as f64) as usize];
        let s = degrade::scene(g, crs.clone(), &mut next);
        writeln!(
            csv,
            "{k},{name},\"{}\",{:.5},{}",
            s.labels.join("; "),
            s.share,
            s.samples
        )
        .expect("a string");
        if s.share < 0.98 {
            println!(
                "draw {k}: {name} [{}]: {:.2}%",
                s.labels.join("; "),
                100.0 * s.share
            );
        }
        rows.push((name.to_string(), s.labels, s.share));
    }
    std::fs::write(out.join("draws.csv"), csv)?;
    let shares: Vec<(String, f64)> = rows.iter().map(|r| (r.0.clone(), r.2)).collect();
    crate::charts::draws(out, &shares)?;
    let held = rows.iter().filter(|r| r.2 >= 0.98).count();
    println!(
        "the original kept 98% of its samples within its claim in {held} of {n} draws ({:.1}%)",
        100.0 * held as f64 / n as f64
    );
    println!("| operation | draws with it | under 98% | lowest share |");
    println!("|---|---|---|---|");
    for kind in KINDS {
        let with: Vec<&(String, Vec<String>, f64)> = rows
            .iter()
            .filter(|r| {
                r.1.iter()
                    .any(|l| l.split(" + ").any(|op| op.starts_with(kind)))
            })
            .collect();
        let under = with.iter().filter(|r| r.2 < 0.98).count();
        let lowest = with.iter().map(|r| r.2).fold(1.0f64, f64::min);
        println!(
            "| {kind} | {} | {under} | {:.1}% |",
            with.len(),
            100.0 * lowest
        );
    }
    println!("| scene | draws | under 98% |");
    println!("|---|---|---|");
    for scene in SCENES {
        let of: Vec<_> = rows.iter().filter(|r| r.0 == scene).collect();
        let under = of.iter().filter(|r| r.2 < 0.98).count();
        println!("| {scene} | {} | {under} |", of.len());
    }
    widened_draws(out, n, &scenes, &mut next)?;
    changed_draws(out, n, &scenes, &mut next)?;
    Ok(())
}

type Scenes<'a> = [(&'a str, (Grid, Option<patchwork_core::crs::Crs>))];

fn terrain(surveys: &[Arc<Survey>]) -> Terrain {
    let mut t = Terrain::new(IndexConfig::default());
    t.set_contradicted(Contradicted::Distrust);
    for s in surveys {
        t.insert(s.clone());
    }
    t
}

/// Prints a table of shares by kind, and charts them, a series a kind.
fn by_kind(out: &Path, file: &str, what: &str, rows: &[(String, f64)]) -> Result<(), Fail> {
    let mut kinds: Vec<&str> = rows.iter().map(|r| r.0.as_str()).collect();
    kinds.dedup();
    kinds.sort_unstable();
    kinds.dedup();
    println!("| kind | draws | pooled | lowest | under 90% |");
    println!("|---|---|---|---|---|");
    for k in kinds {
        let of: Vec<f64> = rows.iter().filter(|r| r.0 == k).map(|r| r.1).collect();
        let pooled = of.iter().sum::<f64>() / of.len().max(1) as f64;
        let lowest = of.iter().copied().fold(1.0f64, f64::min);
        let under = of.iter().filter(|&&s| s < 0.9).count();
        println!(
            "| {k} | {} | {:.1}% | {:.1}% | {under} |",
            of.len(),
            100.0 * pooled,
            100.0 * lowest
        );
    }
    crate::charts::draws_by(out, file, what, rows)
}

/// `n` copies of the widened family, the kinds in turn, each beside its original in a random
/// order: the share of the original's samples served within 1 m at e = 0.
fn widened_draws(
    out: &Path,
    n: usize,
    scenes: &Scenes,
    next: &mut impl FnMut() -> f64,
) -> Result<(), Fail> {
    println!("{n} copies of the widened family (held back: shear, ringing, slanted stripes, block compression)");
    let mut csv = String::from("draw,scene,kind,copy,share\n");
    let mut rows = Vec::new();
    for k in 0..n {
        let kind = widened::Kind::ALL[k % widened::Kind::ALL.len()];
        let (name, (g, crs)) = &scenes[(next() * scenes.len() as f64) as usize];
        let (label, copy) = widened::apply(kind, g, next);
        let build = |g: Grid| {
            Arc::new(
                Survey::build(g, AccuracySpec::Auto, crs.clone(), Default::default())
                    .expect("a survey"),
            )
        };
        let mut both = [build(g.clone()), build(copy)];
        if next() < 0.5 {
            both.swap(0, 1);
        }
        let share = widened::served_within(&terrain(&both), g, 1.0);
        writeln!(csv, "{k},{name},{},\"{label}\",{share:.5}", kind.name()).expect("a string");
        rows.push((kind.name().to_string(), share));
    }
    std::fs::write(out.join("widened.csv"), csv)?;
    by_kind(
        out,
        "widened",
        "copies of the widened family: the original's samples served within 1 m",
        &rows,
    )
}

/// `n` changes, the kinds in turn, each resurveyed later (dated 2024 against 2000): the share
/// of the changed samples (beyond both claims) the later survey serves at e = 0.
fn changed_draws(
    out: &Path,
    n: usize,
    scenes: &Scenes,
    next: &mut impl FnMut() -> f64,
) -> Result<(), Fail> {
    println!("{n} changes resurveyed later (held back: trench)");
    let mut csv = String::from("draw,scene,kind,change,resurvey,changed,share\n");
    let mut rows = Vec::new();
    for k in 0..n {
        let kind = changes::Kind::ALL[k % changes::Kind::ALL.len()];
        let (name, (g, crs)) = &scenes[(next() * scenes.len() as f64) as usize];
        let build = |g: Grid, when: &str| {
            Arc::new(
                Survey::build(g, AccuracySpec::Auto, crs.clone(), Default::default())
                    .expect("a survey")
                    .with_epoch(Some(Epoch::parse(when).expect("a date"))),
            )
        };
        let median = |s: &Survey| {
            let mut v = s.kernel_accuracy.values.clone();
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let before = build(g.clone(), "2000");
        let drawn = changes::apply(kind, g, 2.0 * median(&before), next);
        let (how, resurveyed) = changes::resurvey(&drawn.after, next, k as u64);
        let after = build(resurveyed, "2024");
        // Beyond both median claims: the level of detection over most of the pair.
        let lod = median(&before) + median(&after);
        let mut both = [before.clone(), after.clone()];
        if next() < 0.5 {
            both.swap(0, 1);
        }
        let t = terrain(&both);
        let (mut pts, mut want) = (Vec::new(), Vec::new());
        for (i, d) in drawn.delta.iter().enumerate() {
            if !g.samples[i].is_nan() && (*d as f64).abs() > lod {
                pts.push(g.georef.to_world((i % g.cols) as f64, (i / g.cols) as f64));
                want.push((drawn.after.samples[i], *d));
            }
        }
        if pts.is_empty() {
            continue;
        }
        let got = t.sample(&pts, 0.0);
        let ok = got
            .iter()
            .zip(&want)
            .filter(|(h, (z, d))| (**h - z).abs() < 0.5 * d.abs())
            .count();
        let share = ok as f64 / pts.len() as f64;
        writeln!(
            csv,
            "{k},{name},{},\"{}\",\"{how}\",{},{share:.5}",
            kind.name(),
            drawn.label,
            pts.len()
        )
        .expect("a string");
        rows.push((kind.name().to_string(), share));
    }
    std::fs::write(out.join("changes.csv"), csv)?;
    by_kind(
        out,
        "changes",
        "changes resurveyed later: the changed samples the later survey serves",
        &rows,
    )
}
