//! 1 → 2: survey records say where their accuracy came from and how level 0 is tiled, box
//! states carry exposure, and overlaps between surveys are kept.
//!
//! Records are rewritten field by field from a frozen copy of the version-1 layout. Exposure
//! and overlaps cannot be computed from the tree alone, so the step marks the store for a
//! rebuild: the next open derives the whole index again from the surveys (with the edge
//! patches version 2 adds) and writes every box state and overlap in one batch.

use super::v3::{GeorefV3, LevelV3, RecordV3};
use super::Ctx;
use crate::form::AccuracySource;
use crate::{decode, encode, keys, IngestTimings, Status};
use serde::Deserialize;

#[derive(Deserialize)]
struct GeorefV1 {
    origin: [f64; 2],
    theta: f64,
    step: [f64; 2],
}

#[derive(Deserialize)]
struct LevelV1 {
    cols: u64,
    rows: u64,
    georef: GeorefV1,
}

#[derive(Deserialize)]
enum StatusV1 {
    Active,
    Retired,
}

#[derive(Deserialize)]
struct TimingsV1 {
    read_ms: f64,
    build_ms: f64,
    index_ms: f64,
    commit_ms: f64,
}

#[derive(Deserialize)]
struct RecordV1 {
    id: patchwork_core::model::ids::SurveyId,
    source: String,
    content_id: String,
    accuracy: f64,
    crs: Option<u32>,
    status: StatusV1,
    cols: u64,
    rows: u64,
    georef: GeorefV1,
    samples: u64,
    levels: Vec<LevelV1>,
    ingest: TimingsV1,
    created_unix: u64,
}

fn georef(g: GeorefV1) -> GeorefV3 {
    GeorefV3 {
        origin: g.origin,
        theta: g.theta,
        step: g.step,
    }
}

pub(super) fn run(tree: &sled::Tree, _: &Ctx) -> Result<sled::Batch, String> {
    let mut b = sled::Batch::default();
    let mut any = false;
    for kv in tree.scan_prefix(keys::SURVEY_PREFIX) {
        any = true;
        let (k, v) = kv.map_err(|e| e.to_string())?;
        let old: RecordV1 = decode(&v, &String::from_utf8_lossy(&k)).map_err(|e| e.to_string())?;
        let rec = RecordV3 {
            id: old.id,
            source: old.source,
            content_id: old.content_id,
            accuracy: old.accuracy,
            accuracy_source: AccuracySource::Unknown,
            crs: old.crs,
            status: match old.status {
                StatusV1::Active => Status::Active,
                StatusV1::Retired => Status::Retired,
            },
            cols: old.cols,
            rows: old.rows,
            georef: georef(old.georef),
            samples: old.samples,
            levels: old
                .levels
                .into_iter()
                .map(|l| LevelV3 {
                    cols: l.cols,
                    rows: l.rows,
                    georef: georef(l.georef),
                })
                .collect(),
            // Version 1 cut every level from its first sample.
            tiling_offset: [0, 0],
            ingest: IngestTimings {
                read_ms: old.ingest.read_ms,
                build_ms: old.ingest.build_ms,
                index_ms: old.ingest.index_ms,
                commit_ms: old.ingest.commit_ms,
            },
            created_unix: old.created_unix,
        };
        b.insert(k, encode(&rec).map_err(|e| e.to_string())?);
    }
    if any {
        b.insert(keys::REBUILD, &[1u8]);
    }
    Ok(b)
}
