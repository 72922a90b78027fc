//! The survey record as versions 2 and 3 wrote it: a frozen copy, so that the steps that
//! write it (1 → 2) and read it (2 → 3, 3 → 4) keep doing so whatever the record becomes.

use crate::{IngestTimings, Status};
use patchwork_core::model::accuracy::AccuracySource;
use patchwork_core::model::grid::Georef;
use patchwork_core::model::ids::SurveyId;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct GeorefV3 {
    pub origin: [f64; 2],
    pub theta: f64,
    pub step: [f64; 2],
}

impl GeorefV3 {
    pub fn now(&self) -> Georef {
        Georef {
            origin: self.origin,
            theta: self.theta,
            step: self.step,
            row_theta: None,
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LevelV3 {
    pub cols: u64,
    pub rows: u64,
    pub georef: GeorefV3,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RecordV3 {
    pub id: SurveyId,
    pub source: String,
    pub content_id: String,
    pub accuracy: f64,
    pub accuracy_source: AccuracySource,
    /// EPSG code.
    pub crs: Option<u32>,
    pub status: Status,
    pub cols: u64,
    pub rows: u64,
    pub georef: GeorefV3,
    pub samples: u64,
    pub levels: Vec<LevelV3>,
    pub tiling_offset: [i64; 2],
    pub ingest: IngestTimings,
    pub created_unix: u64,
}
