//! The survey record as versions 2 and 3 wrote it: a frozen copy, so that the steps that
//! write it (1 → 2) and read it (2 → 3, 3 → 4) keep doing so whatever the record becomes.

use crate::form::AccuracySource;
use crate::{IngestTimings, Status};
use patchwork_core::model::grid::Georef;
use patchwork_core::model::ids::SurveyId;
use serde::{Deserialize, Serialize};

/// A georeference as versions 2 and 3 wrote it: a rotation, and no row axis of its own.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct GeorefV3 {
    /// Position of sample (0, 0).
    pub origin: [f64; 2],
    /// Angle of the column axis from the x axis, counter-clockwise, in radians.
    pub theta: f64,
    /// Spacing between columns and between rows, in CRS units.
    pub step: [f64; 2],
}

impl GeorefV3 {
    /// The same georeference as a [`Georef`] is now: its row axis the column axis turned.
    pub fn now(&self) -> Georef {
        Georef {
            origin: self.origin,
            theta: self.theta,
            step: self.step,
            row_theta: None,
        }
    }
}

/// A level's header as versions 2 and 3 wrote it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LevelV3 {
    /// Samples in a row.
    pub cols: u64,
    /// Rows of samples.
    pub rows: u64,
    /// Where the level's samples are.
    pub georef: GeorefV3,
}

/// A survey record as versions 2 and 3 wrote it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RecordV3 {
    /// The survey's id.
    pub id: SurveyId,
    /// The file it was read from.
    pub source: String,
    /// Hex blake3 of the file's bytes; empty when unknown.
    pub content_id: String,
    /// ε in metres.
    pub accuracy: f64,
    /// Where ε came from.
    pub accuracy_source: AccuracySource,
    /// EPSG code.
    pub crs: Option<u32>,
    /// Whether it is in the terrain or retired.
    pub status: Status,
    /// Level 0's samples in a row.
    pub cols: u64,
    /// Level 0's rows of samples.
    pub rows: u64,
    /// Level 0's georeference.
    pub georef: GeorefV3,
    /// Valid level-0 samples.
    pub samples: u64,
    /// Level 0 first.
    pub levels: Vec<LevelV3>,
    /// Where level 0's kernel boundaries fall.
    pub tiling_offset: [i64; 2],
    /// Where the time of its ingestion went.
    pub ingest: IngestTimings,
    /// When the record was made, in Unix seconds.
    pub created_unix: u64,
}
