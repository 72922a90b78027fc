//! 2 → 3: samples in square compressed chunks, patches stored with the edge tiles their
//! survey reaches, and edge patches stored rather than derived at every open.
//!
//! Version 2 kept each level in sled as bands of 64 rows of raw little-endian `f32`, and
//! derived the edge patches from every sample at open, so an open read the whole store. The
//! step reads each survey's bands, writes its levels again to the chunk pack as
//! [`chunks::CHUNK`]² chunks in the chunk codec (the pack is synced before the batch that
//! points at it), and stores its patches beside the edge tiles found from its level 0. Edge patches
//! follow from the set of surveys, not from the tree alone, so the step marks the store for a
//! rebuild, which writes them with every box state.

use super::v3::RecordV3;
use super::Ctx;
use crate::{chunks, decode, encode, form, keys, StoredPatches};
use patchwork_core::model::edge;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::lattice::Lattice;

/// Version 2's rows per band.
const BAND_ROWS: usize = 64;

pub(super) fn run(tree: &sled::Tree, ctx: &Ctx) -> Result<sled::Batch, String> {
    let mut batch = sled::Batch::default();
    let layout: patchwork_core::model::patch::PatchLayout = match tree.get(keys::LAYOUT) {
        Ok(Some(v)) => decode(&v, "meta/layout").map_err(|e| e.to_string())?,
        Ok(None) => ctx.layout,
        Err(e) => return Err(e.to_string()),
    };
    // Every version-2 chunk key goes; the new chunks of the same survey and level are written
    // after, so where a number is reused the new chunk is what the batch leaves.
    for kv in tree.scan_prefix(keys::CHUNK_PREFIX) {
        let (k, _) = kv.map_err(|e| e.to_string())?;
        batch.remove(k);
    }
    let mut any = false;
    for kv in tree.scan_prefix(keys::SURVEY_PREFIX) {
        let (k, v) = kv.map_err(|e| e.to_string())?;
        let Some(id) = keys::parse_survey(&k) else {
            continue;
        };
        any = true;
        let rec: RecordV3 = decode(&v, "survey record").map_err(|e| e.to_string())?;
        let mut level0 = None;
        for (level, h) in rec.levels.iter().enumerate() {
            let (cols, rows) = (h.cols as usize, h.rows as usize);
            let mut samples = Vec::with_capacity(cols * rows);
            for band in 0..rows.div_ceil(BAND_ROWS) {
                let want = 4 * cols * BAND_ROWS.min(rows - band * BAND_ROWS);
                let v = tree
                    .get(keys::chunk(id, level, band))
                    .map_err(|e| e.to_string())?
                    .ok_or_else(|| {
                        format!("band {band} of level {level} of survey {id} is missing")
                    })?;
                if v.len() != want {
                    return Err(format!(
                        "band {band} of level {level} of survey {id} holds {} bytes, not {want}",
                        v.len()
                    ));
                }
                samples.extend(
                    v.chunks_exact(4)
                        .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes"))),
                );
            }
            let g = Grid::new(cols, rows, samples, h.georef.now())
                .map_err(|e| format!("level {level} of survey {id}: {e}"))?;
            let (ks, bytes): (Vec<usize>, Vec<Vec<u8>>) =
                chunks::encode_level(&g).into_iter().unzip();
            let locs = ctx
                .pack
                .append(&bytes)
                .map_err(|e| format!("writing the chunk pack: {e}"))?;
            for (k, loc) in ks.into_iter().zip(locs) {
                batch.insert(keys::chunk(id, level, k), &loc.to_bytes()[..]);
            }
            if level == 0 {
                level0 = Some(g);
            }
        }
        let Some(g) = level0 else {
            return Err(format!("survey {id} has no levels"));
        };
        if let Some(v) = tree.get(keys::patches(id)).map_err(|e| e.to_string())? {
            let patches: Vec<form::Patch> = decode(&v, "patches").map_err(|e| e.to_string())?;
            let index = Lattice::of(&g.georef).index_of(&g.georef);
            let stored = StoredPatches {
                patches,
                edge_tiles: edge::edge_tiles(&g, index, &layout),
            };
            let sealed = chunks::seal(&encode(&stored).map_err(|e| e.to_string())?);
            let loc = ctx
                .pack
                .append(&[sealed])
                .map_err(|e| format!("writing the chunk pack: {e}"))?[0];
            batch.insert(keys::patches(id), &loc.to_bytes()[..]);
        }
    }
    if any {
        batch.insert(keys::REBUILD, &[1u8][..]);
    }
    // The pack was empty at version 2 (an open cuts it back to the committed length, none).
    batch.insert(keys::PACK_LEN, &ctx.pack.len().to_le_bytes()[..]);
    Ok(batch)
}
