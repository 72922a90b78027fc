//! A survey: one grid, its mipmap and its patches, ready for the index.

use super::grid::Grid;
use super::ids::{hash64, SurveyId};
use super::mipmap;
use super::patch::{make_patches, Bilinear, Patch, PatchLayout};
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

#[derive(Clone, Debug)]
pub struct Survey {
    pub id: SurveyId,
    /// ε, in metres.
    pub accuracy: f64,
    /// EPSG code of the survey's horizontal CRS, where known.
    pub crs: Option<u32>,
    pub layout: PatchLayout,
    /// Level 0 first.
    pub levels: Vec<Arc<Grid>>,
    pub patches: Vec<Patch>,
}

impl Survey {
    /// The id of a survey's content. Two files with the same samples, georeference, CRS and
    /// accuracy are the same survey.
    pub fn id_of(grid: &Grid, accuracy: f64, crs: Option<u32>) -> SurveyId {
        let mut h = blake3::Hasher::new();
        h.update(b"patchwork.survey.v1");
        h.update(&(grid.cols as u64).to_le_bytes());
        h.update(&(grid.rows as u64).to_le_bytes());
        let g = &grid.georef;
        for v in [
            g.origin[0],
            g.origin[1],
            g.theta,
            g.step[0],
            g.step[1],
            accuracy,
        ] {
            h.update(&v.to_bits().to_le_bytes());
        }
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

    /// Builds the mipmap and the patches with their errors.
    pub fn build(
        grid: Grid,
        accuracy: f64,
        crs: Option<u32>,
        layout: PatchLayout,
    ) -> Result<Survey, SurveyError> {
        if !(accuracy.is_finite() && accuracy >= 0.0) {
            return Err(SurveyError::BadAccuracy(accuracy));
        }
        if layout.kernel == 0 {
            return Err(SurveyError::BadLayout(layout.kernel));
        }
        if grid.valid_count() == 0 {
            return Err(SurveyError::AllNodata);
        }
        let id = Self::id_of(&grid, accuracy, crs);
        let levels = mipmap::build(Arc::new(grid), layout.kernel);
        let patches = make_patches(id, accuracy, &levels, &layout, &Bilinear);
        Ok(Survey {
            id,
            accuracy,
            crs,
            layout,
            levels,
            patches,
        })
    }

    /// The patches as LOD-space boxes.
    pub fn boxes(&self) -> Vec<PatchBox> {
        self.patches
            .iter()
            .map(|p| PatchBox::new(p, &self.levels[p.level as usize], self.layout.kernel))
            .collect()
    }

    /// Samples in every level, the mipmap's storage cost.
    pub fn stored_samples(&self) -> usize {
        self.levels.iter().map(|l| l.samples.len()).sum()
    }
}
