//! Where surveys meet: the bench's mixed-survey scenes and the check of the accuracy estimator.
//!
//! Every scene is made from one real survey, so that its own samples are the truth:
//!
//! - *copies*: the survey and a copy of every third sample, both with estimated ε; the tile's
//!   error against the finer survey, against e;
//! - *nested*: the middle of the survey with ε = 2 m inside a half-resolution copy with
//!   ε = 20 m; the error against the ε = 2 survey where it has data, and the largest
//!   difference between a tile and the sub-tiles that share its samples;
//! - *mosaic*: the survey cut into four abutting tiles; nodata in the tile over them and the
//!   largest difference from the whole survey at e = 0;
//! - *estimator*: copies decimated by 2, 3, 4 and 8, each kernel's estimated ε beside the
//!   largest deviation of the copy from the original over that kernel.

use patchwork_core::crs::Crs;
use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::{self, AccuracySpec};
use patchwork_core::model::grid::Grid;
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::survey::Survey;
use patchwork_core::resample::SampleGrid;
use patchwork_core::terrain::Terrain;
use rayon::prelude::*;
use std::fmt::Write as _;
use std::path::Path;
use std::sync::Arc;

use crate::Fail;

/// One tile of a mixed scene at one error.
#[derive(Clone, Debug)]
pub struct MixedRow {
    /// The scene: `copies` or `nested`.
    pub scene: &'static str,
    /// The requested error e, metres.
    pub error: f64,
    /// Patches of the tile.
    pub patches: usize,
    /// Patches of the finer survey among them.
    pub finer: usize,
    /// Largest |tile − the finer survey's surface| where it has data, metres.
    pub max_err: f64,
    /// RMS of |tile − the finer survey's surface| where it has data, metres.
    pub rms_err: f64,
    /// Largest |tile − sub-tile| at shared samples (nested scene only).
    pub split_diff: f64,
    /// Samples of the tile without a height.
    pub nodata: usize,
}

/// One kernel of one decimated copy.
#[derive(Clone, Debug)]
pub struct EstimateRow {
    /// The copy's decimation factor.
    pub factor: usize,
    /// The kernel's estimated ε, metres.
    pub estimated: f64,
    /// Largest |copy − original| at the original's samples in the kernel, metres.
    pub measured: f64,
}

/// One decimated copy as a whole: its estimated ε beside its measured deviation.
#[derive(Clone, Debug)]
pub struct CopyRow {
    /// The decimation factor.
    pub factor: usize,
    /// The survey's ε: the largest of its kernels'.
    pub estimated: f64,
    /// Largest deviation of the copy from the original, metres.
    pub measured_max: f64,
    /// RMS deviation of the copy from the original, metres.
    pub measured_rms: f64,
}

/// What the scenes measure, as [`run`] returns it.
pub struct Scenes {
    /// Tiles of the copies and nested scenes (`mixed.csv`).
    pub mixed: Vec<MixedRow>,
    /// Every kernel of every decimated copy (`estimator.csv`).
    pub estimator: Vec<EstimateRow>,
    /// Every decimated copy as a whole.
    pub copies: Vec<CopyRow>,
    /// ε of the finer survey and of its 90 m copy in the copies scene (their largest kernels').
    pub copies_accuracy: (f64, f64),
    /// Largest |mosaic − whole| at e = 0, and samples of data in the whole that are nodata in
    /// the mosaic.
    pub mosaic: (f64, usize),
}

pub(crate) fn survey(g: Grid, spec: AccuracySpec, crs: Option<Crs>) -> Result<Arc<Survey>, Fail> {
    Ok(Arc::new(Survey::build(
        g,
        spec,
        crs,
        PatchLayout::default(),
    )?))
}

pub(crate) fn terrain(surveys: &[Arc<Survey>]) -> Terrain {
    let mut t = Terrain::new(IndexConfig::default());
    for s in surveys {
        t.insert(s.clone());
    }
    t
}

/// A grid cut into four abutting tiles: the mosaic scene's surveys.
pub(crate) fn quarters(g: &Grid) -> [Grid; 4] {
    let (hw, hh) = (g.cols / 2, g.rows / 2);
    [
        g.window(0, 0, hw, hh),
        g.window(hw, 0, g.cols - hw, hh),
        g.window(0, hh, hw, g.rows - hh),
        g.window(hw, hh, g.cols - hw, g.rows - hh),
    ]
}

/// The bounds of pixels [c0, c1) × [r0, r1) of a north-up grid.
fn pixels(g: &Grid, c0: f64, r0: f64, c1: f64, r1: f64) -> Aabb {
    Aabb::of_points(&[
        g.georef.to_world(c0 - 0.5, r0 - 0.5),
        g.georef.to_world(c1 - 0.5, r1 - 0.5),
    ])
}

/// Max and RMS of |tile − the grid's surface| where the grid has a whole cell.
pub(crate) fn against(g: &Grid, grid: &SampleGrid, heights: &[f32]) -> (f64, f64) {
    let (worst, sum, n) = grid
        .points()
        .zip(heights)
        .filter_map(|(p, z)| Some((g.bilinear(p)? - *z as f64).abs()))
        .fold((0.0f64, 0.0f64, 0usize), |(w, s, n), d| {
            (w.max(d), s + d * d, n + 1)
        });
    (worst, (sum / n.max(1) as f64).sqrt())
}

/// Runs the scenes on `g` (north-up). `side` is the tile size, `errors` the errors tried.
pub fn run(g: &Grid, crs: Option<Crs>, side: usize, errors: &[f64]) -> Result<Scenes, Fail> {
    let mut mixed = Vec::new();
    let (c, r) = (g.cols as f64, g.rows as f64);
    let roi = pixels(g, 0.2 * c, 0.2 * r, 0.8 * c, 0.8 * r);
    let grid = SampleGrid::uniform(&roi, side, side);

    let fine = survey(g.clone(), AccuracySpec::Auto, crs.clone())?;
    let coarse = survey(g.decimated(3), AccuracySpec::Auto, crs.clone())?;
    let copies_accuracy = (fine.accuracy, coarse.accuracy);
    let t = terrain(&[fine.clone(), coarse]);
    for &e in errors {
        let tile = t.tile(&roi, side, side, e);
        let (max_err, rms_err) = against(g, &grid, &tile.heights);
        mixed.push(MixedRow {
            scene: "copies",
            error: e,
            patches: tile.patches.len(),
            finer: tile.patches.iter().filter(|x| x.survey == fine.id).count(),
            max_err,
            rms_err,
            split_diff: 0.0,
            nodata: tile.heights.iter().filter(|z| z.is_nan()).count(),
        });
    }

    let (w0, h0) = (g.cols / 3, g.rows / 3);
    let middle = g.window(w0, h0, w0, h0);
    let nested_fine = survey(middle.clone(), AccuracySpec::Fixed(2.0), crs.clone())?;
    let t = terrain(&[
        nested_fine.clone(),
        survey(g.decimated(2), AccuracySpec::Fixed(20.0), crs.clone())?,
    ]);
    for &e in errors {
        let tile = t.tile(&roi, side, side, e);
        let (max_err, rms_err) = against(&middle, &grid, &tile.heights);
        // Four sub-tiles split at a third of the tile, sharing its sample positions.
        let cut = side / 3;
        let (dx, dy) = (roi.width() / side as f64, roi.height() / side as f64);
        let mut split_diff = 0.0f64;
        for (a0, a1) in [(0, cut), (cut, side)] {
            for (b0, b1) in [(0, cut), (cut, side)] {
                let sub = Aabb::new(
                    roi.min[0] + a0 as f64 * dx,
                    roi.max[1] - b1 as f64 * dy,
                    roi.min[0] + a1 as f64 * dx,
                    roi.max[1] - b0 as f64 * dy,
                );
                let s = t.tile(&sub, a1 - a0, b1 - b0, e).heights;
                for j in b0..b1 {
                    for i in a0..a1 {
                        let (x, y) = (tile.heights[j * side + i], s[(j - b0) * (a1 - a0) + i - a0]);
                        let d = if x.is_nan() != y.is_nan() {
                            f64::INFINITY
                        } else if x.is_nan() {
                            0.0
                        } else {
                            (x as f64 - y as f64).abs()
                        };
                        split_diff = split_diff.max(d);
                    }
                }
            }
        }
        mixed.push(MixedRow {
            scene: "nested",
            error: e,
            patches: tile.patches.len(),
            finer: tile
                .patches
                .iter()
                .filter(|x| x.survey == nested_fine.id)
                .count(),
            max_err,
            rms_err,
            split_diff,
            nodata: tile.heights.iter().filter(|z| z.is_nan()).count(),
        });
    }

    let pieces: Vec<Arc<Survey>> = quarters(g)
        .into_iter()
        .map(|p| survey(p, AccuracySpec::Fixed(1.0), crs.clone()))
        .collect::<Result<_, _>>()?;
    let whole = terrain(&[survey(g.clone(), AccuracySpec::Fixed(1.0), crs.clone())?]);
    let mosaic = terrain(&pieces);
    let all = pixels(g, 0.0, 0.0, c, r);
    let a = whole.tile(&all, side, side, 0.0).heights;
    let b = mosaic.tile(&all, side, side, 0.0).heights;
    // Nodata where the whole survey has data: seams the mosaic leaves open.
    let nodata = a
        .iter()
        .zip(&b)
        .filter(|(x, y)| !x.is_nan() && y.is_nan())
        .count();
    let diff = a
        .iter()
        .zip(&b)
        .filter(|(x, y)| !x.is_nan() && !y.is_nan())
        .map(|(x, y)| (*x as f64 - *y as f64).abs())
        .fold(0.0, f64::max);

    let (estimator, copies) = estimator(g);
    Ok(Scenes {
        mixed,
        estimator,
        copies,
        copies_accuracy,
        mosaic: (diff, nodata),
    })
}

/// Copies decimated by 2, 3, 4 and 8: each kernel's estimate beside the largest deviation of
/// the copy from the original's samples within it.
fn estimator(g: &Grid) -> (Vec<EstimateRow>, Vec<CopyRow>) {
    let layout = PatchLayout::default();
    let mut rows = Vec::new();
    let mut copies = Vec::new();
    for k in [2usize, 3, 4, 8] {
        let copy = g.decimated(k);
        let tiling = Survey::tiling_of(&copy, &layout);
        let est = accuracy::estimate(&copy, &tiling, layout.margin as u32);
        let dims = tiling.counts();
        // Per kernel of the copy, the largest |copy − original| at the original's samples.
        let measured: Vec<f64> = (0..g.rows)
            .into_par_iter()
            .fold(
                || vec![0.0f64; dims[0] * dims[1]],
                |mut acc, r| {
                    for c in 0..g.cols {
                        let z = g.at(c, r);
                        if z.is_nan() {
                            continue;
                        }
                        let q = [c as f64 / k as f64, r as f64 / k as f64];
                        let Some(h) = copy.bilinear_grid(q) else {
                            continue;
                        };
                        let [cw, ch] = copy.cells();
                        let cell = [
                            (q[0].floor() as usize).min(cw - 1) as u32,
                            (q[1].floor() as usize).min(ch - 1) as u32,
                        ];
                        let [a, b] = tiling.kernel_at(cell[0], cell[1]);
                        let i = b as usize * dims[0] + a as usize;
                        acc[i] = acc[i].max((h - z as f64).abs());
                    }
                    acc
                },
            )
            .reduce(
                || vec![0.0f64; dims[0] * dims[1]],
                |a, b| a.iter().zip(&b).map(|(x, y)| x.max(*y)).collect(),
            );
        for (i, m) in measured.iter().enumerate() {
            if *m > 0.0 {
                rows.push(EstimateRow {
                    factor: k,
                    estimated: est.kernels.values[i],
                    measured: *m,
                });
            }
        }
        let dev = accuracy::deviation(g, &copy);
        copies.push(CopyRow {
            factor: k,
            estimated: est.kernels.max(),
            measured_max: dev.map_or(0.0, |d| d.max_m),
            measured_rms: dev.map_or(0.0, |d| d.rms_m),
        });
    }
    (rows, copies)
}

/// Writes `mixed.csv` and `estimator.csv` under `out`.
pub fn write_csv(out: &Path, s: &Scenes) -> std::io::Result<()> {
    let mut text = String::from(
        "scene,error_m,patches,finer_patches,max_error_m,rms_error_m,split_diff_m,nodata\n",
    );
    for m in &s.mixed {
        let _ = writeln!(
            text,
            "{},{},{},{},{:.4},{:.4},{:.6},{}",
            m.scene, m.error, m.patches, m.finer, m.max_err, m.rms_err, m.split_diff, m.nodata
        );
    }
    let _ = writeln!(
        text,
        "# copies: the finer survey's ε {:.2} m, its 90 m copy's {:.2} m (largest kernel)",
        s.copies_accuracy.0, s.copies_accuracy.1
    );
    let _ = writeln!(
        text,
        "# mosaic of four tiles at e = 0: largest difference from the whole survey {:.6} m, {} samples nodata where the whole has data",
        s.mosaic.0, s.mosaic.1
    );
    std::fs::write(out.join("mixed.csv"), text)?;
    let mut text = String::from("factor,estimated_m,measured_max_m\n");
    for e in &s.estimator {
        let _ = writeln!(text, "{},{:.4},{:.4}", e.factor, e.estimated, e.measured);
    }
    for c in &s.copies {
        let _ = writeln!(
            text,
            "# copy decimated by {}: estimated ε {:.3} m; measured max {:.3} m, RMS {:.3} m",
            c.factor, c.estimated, c.measured_max, c.measured_rms
        );
    }
    std::fs::write(out.join("estimator.csv"), text)
}
