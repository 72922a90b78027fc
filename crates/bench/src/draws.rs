//! Degraded copies drawn at random beside their originals (`patchwork_testkit::degrade`):
//! the share of each original's samples it still serves at e = 0 within its own claim, per
//! draw (`draws.csv`), and per kind of operation, how many of the draws holding it fell under
//! 98% and the lowest share they left.

use crate::Fail;
use patchwork_testkit::degrade::{self, SCENES};
use patchwork_testkit::fixtures::real_crop_in_crs;
use std::fmt::Write as _;
use std::path::Path;

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
    Ok(())
}
