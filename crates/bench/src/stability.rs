//! Where methods break, as a figure: a 400 m cliff, spikes and pits, a survey riddled with
//! voids and a rotated survey, each made from a crop of the bench's first survey, alone and
//! exact, under every recipe of [`variants::RECIPES`]. At random valid points the blend is
//! compared with the survey's own surface; the bound it must keep is e, or where no patch of
//! the cut meets e, the error of the fallback patches blended there (a bicubic patch
//! overshoots at a cliff or a spike even at level 0).
//!
//! `real_terrain::every_recipe_keeps_the_bound_at_cliffs_spikes_voids_and_rotations` holds the
//! same bound on the committed crops; this measures it on the bench's survey.

use super::variants;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::AccuracySpec;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::survey::{Recipe, Survey};
use patchwork_core::resample::cpu;
use patchwork_core::terrain::Terrain;
use std::fmt::Write as _;
use std::path::Path;
use std::sync::Arc;

use crate::Fail;

/// The errors asked for.
pub const ERRORS: [f64; 3] = [2.0, 10.0, 50.0];

/// One case under one recipe at one error.
#[derive(Clone, Debug)]
pub struct StabilityRow {
    /// The case: `cliff`, `spikes`, `voids` or `rotated`.
    pub case: &'static str,
    /// The mipmap filter and patch kind.
    pub recipe: Recipe,
    /// The requested error e, metres.
    pub error: f64,
    /// Patches of the cut.
    pub patches: usize,
    /// Fallback patches among them.
    pub fallback: usize,
    /// The largest deviation from the survey's own surface at the points.
    pub measured: f64,
    /// The largest bound that applied at them.
    pub bound: f64,
}

/// The four cases, from a crop `g` of a real survey.
pub use patchwork_testkit::stability_cases as cases;

/// Every case under every recipe at every error, `points` random valid points each.
pub fn run(
    g: &Grid,
    crs: Option<patchwork_core::crs::Crs>,
    points: usize,
) -> Result<Vec<StabilityRow>, Fail> {
    let mut rows = Vec::new();
    for (case, grid) in cases(g) {
        let cells: Vec<(usize, usize)> = {
            let [cw, ch] = grid.cells();
            (0..ch)
                .flat_map(|r| (0..cw).map(move |c| (c, r)))
                .filter(|&(c, r)| grid.cell_valid(c, r))
                .collect()
        };
        for recipe in variants::RECIPES {
            let s = Arc::new(Survey::build_with(
                grid.clone(),
                AccuracySpec::Fixed(0.0),
                crs.clone(),
                PatchLayout::default(),
                recipe,
            )?);
            let mut t = Terrain::new(IndexConfig::default());
            t.insert(s.clone());
            let roi = s.levels[0].world_bounds();
            let mut next = patchwork_core::geom::rng::uniform(7);
            for e in ERRORS {
                let ps = t.uniform(&roi, e);
                let set = t.resolve(&ps);
                let all: Vec<u32> = (0..set.patches.len() as u32).collect();
                let (mut measured, mut bound) = (0.0f64, 0.0f64);
                for _ in 0..points {
                    let k = ((next() * cells.len() as f64) as usize).min(cells.len() - 1);
                    let (c, r) = cells[k];
                    let p = grid.georef.to_world(c as f64 + next(), r as f64 + next());
                    let (Some(truth), h) = (grid.bilinear(p), cpu::blend(&set, &all, p)) else {
                        continue;
                    };
                    if h.is_nan() {
                        return Err(
                            format!("{case}, {recipe:?}, e = {e}: no height at {p:?}").into()
                        );
                    }
                    let fallback = set
                        .patches
                        .iter()
                        .filter(|q| q.fallback && q.at(p).is_some())
                        .map(|q| q.error)
                        .fold(0.0, f64::max);
                    measured = measured.max((h as f64 - truth).abs());
                    bound = bound.max(e.max(fallback));
                }
                println!(
                    "{case:>7} {:>8} {:>8} e = {e:>4}: {:>4} patches, largest deviation {measured:.2} m, bound {bound:.2} m",
                    recipe.mipmap.name(),
                    recipe.patches.name(),
                    ps.len()
                );
                rows.push(StabilityRow {
                    case,
                    recipe,
                    error: e,
                    patches: ps.len(),
                    fallback: ps.iter().filter(|x| x.fallback).count(),
                    measured,
                    bound,
                });
            }
        }
    }
    Ok(rows)
}

/// Writes the rows to `stability.csv` under `out`.
pub fn write_csv(out: &Path, rows: &[StabilityRow]) -> std::io::Result<()> {
    let mut s =
        String::from("case,filter,kind,error_m,patches,fallback_patches,measured_max_m,bound_m\n");
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{:.4},{:.4}",
            r.case,
            r.recipe.mipmap.name(),
            r.recipe.patches.name(),
            r.error,
            r.patches,
            r.fallback,
            r.measured,
            r.bound
        );
    }
    std::fs::write(out.join("stability.csv"), s)
}
