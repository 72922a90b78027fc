//! The recipes side by side: for each survey alone and each [`Filter`] and [`PatchKind`], the uniform
//! cut over the whole survey at every error, counted in patches and in samples shipped (the
//! samples of the patches' windows) beside the survey's own valid samples, with the cut's and
//! a tile's time and the tile's measured error.
//!
//! The surveys are taken as exact (ε = 0), so that e is the largest deviation from the
//! samples' own surface: the measure martini's and delatin's maximum error use
//! (bench/mesh_compare.py puts them beside these figures).

use super::{errors, reference, timed};
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::AccuracySpec;
use patchwork_core::model::mipmap::Filter;
use patchwork_core::model::patch::{PatchKind, PatchLayout};
use patchwork_core::model::survey::{Recipe, Survey};
use patchwork_core::resample::SampleGrid;
use patchwork_core::terrain::{PatchRef, Terrain};
use std::fmt::Write as _;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

/// One recipe on one file at one error.
#[derive(Clone, Debug)]
pub struct VariantRow {
    /// The file's name.
    pub dataset: String,
    /// The mipmap filter and patch kind.
    pub recipe: Recipe,
    /// The requested error e, metres.
    pub error: f64,
    /// Patches of the cut.
    pub patches: usize,
    /// Patches from level 1 or coarser.
    pub coarse: usize,
    /// Samples shipped: those of the patches' windows.
    pub samples: usize,
    /// The survey's valid level-0 samples.
    pub raw: usize,
    /// Time the survey took to build under the recipe, seconds.
    pub build_s: f64,
    /// Median time of the cut over three runs, milliseconds.
    pub query_ms: f64,
    /// Time of resampling the cut into a tile over the whole survey, milliseconds.
    pub resample_ms: f64,
    /// Of a tile over the whole survey, against the survey's own surface.
    pub max_err: f64,
}

/// What is compared: every filter with bilinear patches, and bicubic patches on the smooth
/// and the minimax mipmaps.
pub const RECIPES: [Recipe; 5] = [
    Recipe {
        mipmap: Filter::Smooth,
        patches: PatchKind::Bilinear,
    },
    Recipe {
        mipmap: Filter::Decimate,
        patches: PatchKind::Bilinear,
    },
    Recipe {
        mipmap: Filter::Minimax,
        patches: PatchKind::Bilinear,
    },
    Recipe {
        mipmap: Filter::Smooth,
        patches: PatchKind::Bicubic,
    },
    Recipe {
        mipmap: Filter::Minimax,
        patches: PatchKind::Bicubic,
    },
];

/// Every recipe on every file, each file a terrain of its own.
pub fn run(
    files: &[std::path::PathBuf],
    errors_used: &[f64],
    tile: usize,
) -> Result<Vec<VariantRow>, Box<dyn std::error::Error>> {
    let mut rows = Vec::new();
    for f in files {
        let name = f
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let raster = patchwork_read::read_raster(f, &Default::default())?;
        let crs = raster.crs.crs.clone();
        let grid = raster.into_grid()?;
        let raw = grid.valid_count();
        for recipe in RECIPES {
            let t0 = Instant::now();
            let s = Survey::build_with(
                grid.clone(),
                AccuracySpec::Fixed(0.0),
                crs.clone(),
                PatchLayout::default(),
                recipe,
            )?;
            let build_s = t0.elapsed().as_secs_f64();
            let bounds = s.levels[0].world_bounds();
            let mut t = Terrain::new(IndexConfig::default());
            t.insert(Arc::new(s));
            let sample_grid = SampleGrid::uniform(&bounds, tile, tile);
            let (lo, hi) = reference(&t, &sample_grid);
            for &e in errors_used {
                let (query_ms, ps) = timed(3, || t.uniform(&bounds, e));
                let (mut coarse, mut samples) = (0, 0);
                for x in &ps {
                    coarse += usize::from(x.level > 0);
                    samples += match t.patch(x) {
                        Some(PatchRef::Survey(s, p)) => {
                            let w = s.window(p);
                            (w.cols() as usize + 1) * (w.rows() as usize + 1)
                        }
                        Some(PatchRef::Edge(e)) => {
                            t.edge_grid(e).map_or(0, |g| g.kept_heights().len())
                        }
                        None => 0,
                    };
                }
                let (resample_ms, out) = timed(1, || t.resample(ps.clone(), &sample_grid));
                let max_err = errors(&out.heights, &lo, &hi)
                    .into_iter()
                    .fold(0.0, f64::max);
                println!(
                    "{name} {:>8} {:>8} e = {e:>5} m: {} patches ({coarse} coarse), {samples} samples ({:.2}× raw), query {query_ms:.2} ms, max error {max_err:.2} m",
                    recipe.mipmap.name(),
                    recipe.patches.name(),
                    ps.len(),
                    samples as f64 / raw as f64
                );
                rows.push(VariantRow {
                    dataset: name.clone(),
                    recipe,
                    error: e,
                    patches: ps.len(),
                    coarse,
                    samples,
                    raw,
                    build_s,
                    query_ms,
                    resample_ms,
                    max_err,
                });
            }
        }
    }
    Ok(rows)
}

/// Writes the rows to `variants.csv` under `out`.
pub fn write_csv(out: &Path, rows: &[VariantRow]) -> std::io::Result<()> {
    let mut s = String::from(
        "dataset,filter,kind,error_m,patches,coarse_patches,samples,raw_samples,build_s,query_ms,resample_ms,max_error_m\n",
    );
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{:.3},{:.3},{:.2},{:.4}",
            r.dataset,
            r.recipe.mipmap.name(),
            r.recipe.patches.name(),
            r.error,
            r.patches,
            r.coarse,
            r.samples,
            r.raw,
            r.build_s,
            r.query_ms,
            r.resample_ms,
            r.max_err
        );
    }
    std::fs::write(out.join("variants.csv"), s)
}
