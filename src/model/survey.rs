//! A survey: one grid, its mipmap and its patches, ready for the index.

use super::accuracy::{self, AccuracySpec, KernelAccuracy};
use super::edge;
use super::grid::{Grid, Shape};
use super::ids::{hash64, SurveyId};
use super::lattice::Lattice;
use super::mipmap;
use super::mipmap::Filter;
use super::patch::{make_patches, Patch, PatchKind, PatchLayout, Tiling};
use crate::index::lod::PatchBox;
use std::sync::Arc;
use thiserror::Error;

#[derive(Debug, Error, PartialEq)]
pub enum SurveyError {
    #[error("the raster has no valid sample: every sample is nodata")]
    AllNodata,
    #[error("accuracy must be a finite number of metres ≥ 0, got {0}")]
    BadAccuracy(f64),
    #[error("the patch layout needs a kernel of at least one cell, got {0}")]
    BadLayout(usize),
}

/// How a store makes its surveys' coarser levels and their patches: chosen when the store is
/// made, and the same for every survey in it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Recipe {
    pub mipmap: Filter,
    pub patches: PatchKind,
}

/// What the index keeps of a survey: everything but its samples, which the store serves from
/// disk when a patch is read.
#[derive(Clone, Debug)]
pub struct SurveyMeta {
    pub id: SurveyId,
    /// ε, in metres: the largest over the survey's kernels.
    pub accuracy: f64,
    pub spec: AccuracySpec,
    /// EPSG code of the survey's horizontal CRS, where known.
    pub crs: Option<u32>,
    pub layout: PatchLayout,
    /// The function its patches evaluate.
    pub kind: PatchKind,
    /// How level 0 is cut into kernels.
    pub tiling: Tiling,
    /// ε of every level-0 kernel.
    pub kernel_accuracy: KernelAccuracy,
    /// The levels' sizes and georeferences, level 0 first.
    pub shapes: Vec<Shape>,
    pub patches: Vec<Patch>,
    /// The lattice tiles whose edge patches this survey's samples can reach (see
    /// [`edge::edge_tiles`]): found once from the samples, so that inserting or retiring a
    /// neighbour never has to read them all again.
    pub edge_tiles: Vec<[i64; 2]>,
}

/// A survey with its samples: what a reader's grid becomes before it is stored.
#[derive(Clone, Debug)]
pub struct Survey {
    pub meta: Arc<SurveyMeta>,
    /// Level 0 first.
    pub levels: Vec<Arc<Grid>>,
}

impl std::ops::Deref for Survey {
    type Target = SurveyMeta;
    fn deref(&self) -> &SurveyMeta {
        &self.meta
    }
}

impl SurveyMeta {
    /// ε at level-0 sample (c, r): the largest of the kernels it is a corner of.
    pub fn accuracy_at(&self, c: usize, r: usize) -> f64 {
        let [cw, ch] = self.shapes[0].cells();
        let cell = super::patch::CellRect {
            c0: (c as u32).saturating_sub(1),
            r0: (r as u32).saturating_sub(1),
            c1: (c as u32 + 1).min(cw as u32),
            r1: (r as u32 + 1).min(ch as u32),
        };
        self.kernel_accuracy.max_over(&self.tiling, &cell)
    }

    /// The patches as LOD-space boxes.
    pub fn boxes(&self) -> Vec<PatchBox> {
        self.patches
            .iter()
            .map(|p| PatchBox::new(p, &self.shapes[p.level as usize].georef, self.layout.kernel))
            .collect()
    }

    /// Area of one level-0 cell.
    pub fn cell_area(&self) -> f64 {
        let s = self.shapes[0].georef.step;
        s[0] * s[1]
    }

    /// Whether this survey's samples are the finer of two overlapping surveys': the smaller
    /// cell, at equal cells the smaller id. Overlaps are measured at the finer survey's samples,
    /// so that the figure is the same whichever was inserted first.
    pub fn finer_than(&self, o: &SurveyMeta) -> bool {
        self.cell_area()
            .total_cmp(&o.cell_area())
            .then(self.id.cmp(&o.id))
            .is_lt()
    }

    /// Samples in every level, the mipmap's storage cost.
    pub fn stored_samples(&self) -> usize {
        self.shapes.iter().map(|l| l.cols * l.rows).sum()
    }

    /// Where the survey's sample (0, 0) is on its lattice.
    pub fn lattice_index(&self) -> [i64; 2] {
        let g = &self.shapes[0].georef;
        Lattice::of(g).index_of(g)
    }
}

impl Survey {
    /// The id of a survey's content. Two files with the same samples, georeference, CRS and
    /// accuracy (or both with an estimated one) are the same survey.
    pub fn id_of(grid: &Grid, spec: AccuracySpec, crs: Option<u32>) -> SurveyId {
        let mut h = blake3::Hasher::new();
        h.update(b"patchwork.survey.v1");
        h.update(&(grid.cols as u64).to_le_bytes());
        h.update(&(grid.rows as u64).to_le_bytes());
        let g = &grid.georef;
        for v in [g.origin[0], g.origin[1], g.theta, g.step[0], g.step[1]] {
            h.update(&v.to_bits().to_le_bytes());
        }
        match spec {
            AccuracySpec::Fixed(a) => h.update(&a.to_bits().to_le_bytes()),
            // The estimate is a function of the samples, so the samples name it.
            AccuracySpec::Auto => h.update(b"auto.v1"),
        };
        h.update(&crs.unwrap_or(0).to_le_bytes());
        // One NaN bit pattern for every void, so that how a file spelled nodata does not matter.
        let mut buf = Vec::with_capacity(4 * 4096);
        for chunk in grid.samples.chunks(4096) {
            buf.clear();
            for &z in chunk {
                let z = if z.is_nan() { f32::NAN } else { z };
                buf.extend_from_slice(&z.to_bits().to_le_bytes());
            }
            h.update(&buf);
        }
        SurveyId(hash64(h))
    }

    /// The level-0 tiling of a grid: kernels on its lattice's canonical tiles.
    pub fn tiling_of(grid: &Grid, layout: &PatchLayout) -> Tiling {
        let lattice = Lattice::of(&grid.georef);
        Tiling::new(grid.cells(), layout.kernel, lattice.index_of(&grid.georef))
    }

    /// Builds the mipmap (with the default filter) and the patches with their errors.
    pub fn build(
        grid: Grid,
        spec: impl Into<AccuracySpec>,
        crs: Option<u32>,
        layout: PatchLayout,
    ) -> Result<Survey, SurveyError> {
        Self::build_with(grid, spec, crs, layout, Recipe::default())
    }

    /// [`Survey::build`] with the mipmap and patches `recipe` says. A store builds all its
    /// surveys with one recipe, chosen when it was made.
    pub fn build_with(
        grid: Grid,
        spec: impl Into<AccuracySpec>,
        crs: Option<u32>,
        layout: PatchLayout,
        recipe: Recipe,
    ) -> Result<Survey, SurveyError> {
        let spec = spec.into();
        if let AccuracySpec::Fixed(a) = spec {
            if !(a.is_finite() && a >= 0.0) {
                return Err(SurveyError::BadAccuracy(a));
            }
        }
        if layout.kernel == 0 {
            return Err(SurveyError::BadLayout(layout.kernel));
        }
        if grid.valid_count() == 0 {
            return Err(SurveyError::AllNodata);
        }
        let id = Self::id_of(&grid, spec, crs);
        let tiling = Self::tiling_of(&grid, &layout);
        let kernel_accuracy = match spec {
            AccuracySpec::Fixed(a) => KernelAccuracy::constant(&tiling, a),
            AccuracySpec::Auto => accuracy::estimate(&grid, &tiling, layout.margin as u32).kernels,
        };
        let levels = mipmap::build_with(Arc::new(grid), layout.kernel, recipe.mipmap);
        let func = recipe.patches.function();
        let patches = make_patches(id, &kernel_accuracy, &levels, &tiling, &layout, func);
        Ok(Self::restore(
            id,
            spec,
            crs,
            layout,
            recipe.patches,
            tiling,
            kernel_accuracy,
            levels,
            patches,
        ))
    }

    /// A survey from its parts: as [`Survey::build`] makes them, or as a store kept them.
    #[allow(clippy::too_many_arguments)]
    pub fn restore(
        id: SurveyId,
        spec: AccuracySpec,
        crs: Option<u32>,
        layout: PatchLayout,
        kind: PatchKind,
        tiling: Tiling,
        kernel_accuracy: KernelAccuracy,
        levels: Vec<Arc<Grid>>,
        patches: Vec<Patch>,
    ) -> Survey {
        let index = Lattice::of(&levels[0].georef).index_of(&levels[0].georef);
        let edge_tiles = edge::edge_tiles(&levels[0], index, &layout);
        Survey {
            meta: Arc::new(SurveyMeta {
                id,
                accuracy: kernel_accuracy.max(),
                spec,
                crs,
                layout,
                kind,
                tiling,
                kernel_accuracy,
                shapes: levels.iter().map(|g| g.shape()).collect(),
                patches,
                edge_tiles,
            }),
            levels,
        }
    }

    /// What the index keeps of the survey.
    pub fn meta(&self) -> Arc<SurveyMeta> {
        self.meta.clone()
    }
}
