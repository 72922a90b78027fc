//! The survey record as versions 4 to 8 wrote it (`s/`): a frozen copy of its top level, so
//! that the steps that write it (3 → 4) and read it (8 → 9) keep doing so whatever the record becomes. Its parts
//! (georeference, level, timings) are the current forms', unchanged since version 4; a change
//! to one of them freezes its version-8 form here first.

use crate::form::{AccuracySource, Georef, Level, Survey};
use crate::{IngestTimings, Status};
use serde::{Deserialize, Serialize};

/// A survey record of versions 4 to 8: what 3 → 4 writes and 8 → 9 reads.
#[derive(Serialize, Deserialize)]
pub struct SurveyV8 {
    pub(super) id: u64,
    pub(super) source: String,
    pub(super) content_id: String,
    pub(super) accuracy: f64,
    pub(super) accuracy_source: AccuracySource,
    pub(super) crs: Option<String>,
    pub(super) vertical_source: Option<String>,
    pub(super) vertical: Option<String>,
    pub(super) vertical_error_m: f64,
    pub(super) status: Status,
    pub(super) cols: u64,
    pub(super) rows: u64,
    pub(super) georef: Georef,
    pub(super) samples: u64,
    pub(super) levels: Vec<Level>,
    pub(super) tiling_offset: [i64; 2],
    pub(super) ingest: IngestTimings,
    pub(super) created_unix: u64,
}

impl SurveyV8 {
    /// The same record as version 9 writes it: nothing said of where it came from.
    pub fn now(self) -> Survey {
        Survey {
            id: self.id,
            source: self.source,
            content_id: self.content_id,
            accuracy: self.accuracy,
            accuracy_source: self.accuracy_source,
            crs: self.crs,
            vertical_source: self.vertical_source,
            vertical: self.vertical,
            vertical_error_m: self.vertical_error_m,
            status: self.status,
            cols: self.cols,
            rows: self.rows,
            georef: self.georef,
            samples: self.samples,
            levels: self.levels,
            tiling_offset: self.tiling_offset,
            ingest: self.ingest,
            created_unix: self.created_unix,
            about: Default::default(),
        }
    }
}
