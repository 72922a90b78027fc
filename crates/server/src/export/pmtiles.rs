//! The staged tiles as a PMTiles v3 archive, through the `pmtiles` crate's writer: tiles in
//! Hilbert order, identical tiles stored once and runs of them as one directory entry, and the metadata MapLibre's and the pmtiles
//! packages' readers look for, `encoding` among it.

use super::{each_tile, io, ExportError, Image, Meta, Stage};
use pmtiles::{PmTilesWriter, TileType};
use std::fs::File;
use std::path::Path;

/// Writes the archive to `path`; the number of distinct tile contents.
pub(super) fn write(path: &Path, stage: &mut Stage, meta: &Meta) -> Result<u64, ExportError> {
    let file = File::create(path).map_err(io(path))?;
    let tile_type = match meta.image {
        Image::Png => TileType::Png,
        Image::Webp => TileType::Webp,
    };
    let [w, s, e, n] = meta.bounds;
    let fail = |e: pmtiles::PmtError| ExportError::Archive {
        path: path.to_path_buf(),
        why: e.to_string(),
    };
    // Tiles alike (a sea, a plain at a coarse zoom, the nodata beyond a survey) are stored
    // once, found by a hash of their bytes that also counts them.
    let mut w = PmTilesWriter::new(tile_type)
        .min_zoom(meta.zooms.0 as u8)
        .max_zoom(meta.zooms.1 as u8)
        .bounds(w, s, e, n)
        .center(meta.center[0], meta.center[1])
        .center_zoom(meta.zooms.1.min(10).max(meta.zooms.0) as u8)
        .metadata(meta.tilejson.to_string())
        .dedup_by_key::<[u8; 16]>()
        .create(file)
        .map_err(fail)?;
    let mut distinct = std::collections::HashSet::new();
    each_tile(
        stage,
        |id, _, bytes| {
            let key: [u8; 16] = blake3::hash(bytes).as_bytes()[..16]
                .try_into()
                .expect("16 bytes");
            distinct.insert(key);
            let coord =
                pmtiles::TileCoord::from(pmtiles::TileId::new(id).map_err(|e| e.to_string())?);
            w.add_tile(coord, bytes, Some(key))
                .map_err(|e| e.to_string())
        },
        path,
    )?;
    w.finalize().map_err(fail)?;
    // The writer's file is closed by now; its bytes must be on disk before the rename.
    File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(io(path))?;
    Ok(distinct.len() as u64)
}
