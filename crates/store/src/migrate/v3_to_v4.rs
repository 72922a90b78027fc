//! 3 → 4: surveys in any CRS. The store's CRS and every survey's become CRS keys ("EPSG:n",
//! or a definition) instead of EPSG numbers; records say what vertical CRS their heights are
//! in; georeferences may have a row axis of their own (skewed and mirrored grids).
//!
//! Records are rewritten from the frozen version-3 layout. Edge patches keep a
//! georeference too; they follow from the surveys, so the step drops them and marks the store
//! for a rebuild, which derives them, and every box state, again.

use super::v3::RecordV3;
use super::v8::SurveyV8;
use super::Ctx;
use crate::form::Level;
use crate::{decode, encode, keys};
use patchwork_core::crs::Crs;

pub(super) fn run(tree: &sled::Tree, _: &Ctx) -> Result<sled::Batch, String> {
    let mut b = sled::Batch::default();
    let crs = |code: u32| Crs::epsg(code).map_err(|e| e.to_string());
    if let Some(v) = tree.get(keys::CRS).map_err(|e| e.to_string())? {
        let code: [u8; 4] = v
            .as_ref()
            .try_into()
            .map_err(|_| format!("meta/crs holds {} bytes, not 4", v.len()))?;
        b.insert(keys::CRS, crs(u32::from_le_bytes(code))?.key().as_bytes());
    }
    let mut any = false;
    for kv in tree.scan_prefix(keys::SURVEY_PREFIX) {
        let (k, v) = kv.map_err(|e| e.to_string())?;
        any = true;
        let old: RecordV3 = decode(&v, &String::from_utf8_lossy(&k)).map_err(|e| e.to_string())?;
        // In the form of versions 4 to 8, which the later steps read.
        let rec = SurveyV8 {
            id: old.id.0,
            source: old.source,
            content_id: old.content_id,
            accuracy: old.accuracy,
            accuracy_source: old.accuracy_source,
            crs: old.crs.map(crs).transpose()?.map(|c| c.key().to_string()),
            vertical_source: None,
            vertical: None,
            vertical_error_m: 0.0,
            status: old.status,
            cols: old.cols,
            rows: old.rows,
            georef: (&old.georef.now()).into(),
            samples: old.samples,
            levels: old
                .levels
                .into_iter()
                .map(|l| Level {
                    cols: l.cols,
                    rows: l.rows,
                    georef: (&l.georef.now()).into(),
                })
                .collect(),
            tiling_offset: old.tiling_offset,
            ingest: old.ingest,
            created_unix: old.created_unix,
        };
        b.insert(k, encode(&rec).map_err(|e| e.to_string())?);
    }
    for kv in tree.scan_prefix(keys::EDGE_PREFIX) {
        let (k, _) = kv.map_err(|e| e.to_string())?;
        b.remove(k);
    }
    if any {
        b.insert(keys::REBUILD, &[1u8][..]);
    }
    Ok(b)
}
