//! The staged tiles as an MBTiles 1.3 database (SQLite): tiles in TMS rows, identical tiles
//! stored once behind the `tiles` view (as mbutil and tippecanoe lay it out, and GDAL reads),
//! and the metadata the spec names, with the raster-DEM `encoding` and the heights' frame
//! beside it.

use super::{each_tile, io, ExportError, Image, Meta, Stage};
use rusqlite::{params, Connection};
use std::path::Path;

const SCHEMA: &str = "
    CREATE TABLE metadata (name TEXT, value TEXT);
    CREATE UNIQUE INDEX metadata_name ON metadata (name);
    CREATE TABLE map (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER, tile_id TEXT);
    CREATE UNIQUE INDEX map_index ON map (zoom_level, tile_column, tile_row);
    CREATE TABLE images (tile_id TEXT, tile_data BLOB);
    CREATE UNIQUE INDEX images_id ON images (tile_id);
    CREATE VIEW tiles AS
        SELECT map.zoom_level AS zoom_level, map.tile_column AS tile_column,
               map.tile_row AS tile_row, images.tile_data AS tile_data
        FROM map JOIN images ON images.tile_id = map.tile_id;
";

/// Writes the database to `path`; the number of distinct tile contents.
pub(super) fn write(path: &Path, stage: &mut Stage, meta: &Meta) -> Result<u64, ExportError> {
    let fail = |e: rusqlite::Error| ExportError::Archive {
        path: path.to_path_buf(),
        why: e.to_string(),
    };
    let mut db = Connection::open(path).map_err(fail)?;
    // One transaction, written at the end: the file is renamed into place only once whole,
    // so a journal would only slow it down.
    db.execute_batch("PRAGMA journal_mode = OFF; PRAGMA synchronous = OFF;")
        .map_err(fail)?;
    let tx = db.transaction().map_err(fail)?;
    tx.execute_batch(SCHEMA).map_err(fail)?;
    let mut distinct = 0u64;
    {
        let mut map = tx
            .prepare("INSERT INTO map VALUES (?1, ?2, ?3, ?4)")
            .map_err(fail)?;
        let mut image = tx
            .prepare("INSERT OR IGNORE INTO images VALUES (?1, ?2)")
            .map_err(fail)?;
        each_tile(
            stage,
            |id, _, bytes| {
                let (z, x, y) = {
                    let c = pmtiles::TileCoord::from(
                        pmtiles::TileId::new(id).map_err(|e| e.to_string())?,
                    );
                    (u32::from(c.z()), c.x(), c.y())
                };
                let key = blake3::hash(bytes).to_hex()[..32].to_string();
                distinct += image
                    .execute(params![key, bytes])
                    .map_err(|e| e.to_string())? as u64;
                // MBTiles rows count from the south (TMS).
                let row = (1u32 << z) - 1 - y;
                map.execute(params![z, x, row, key])
                    .map_err(|e| e.to_string())?;
                Ok(())
            },
            path,
        )?;
    }
    let [w, s, e, n] = meta.bounds;
    let tj = &meta.tilejson;
    let text = |k: &str| tj[k].as_str().unwrap_or("").to_string();
    let mut rows: Vec<(&str, String)> = vec![
        ("name", text("name")),
        ("description", text("description")),
        (
            "format",
            match meta.image {
                Image::Png => "png",
                Image::Webp => "webp",
            }
            .into(),
        ),
        ("type", "baselayer".into()),
        ("version", "1.3".into()),
        ("bounds", format!("{w},{s},{e},{n}")),
        (
            "center",
            format!(
                "{},{},{}",
                meta.center[0],
                meta.center[1],
                meta.zooms.1.min(10).max(meta.zooms.0)
            ),
        ),
        ("minzoom", meta.zooms.0.to_string()),
        ("maxzoom", meta.zooms.1.to_string()),
        ("attribution", text("attribution")),
        ("encoding", text("encoding")),
        ("tileSize", tj["tileSize"].to_string()),
    ];
    // What the spec has no row for (the heights' frame and vertical CRS) in its `json` row.
    rows.push((
        "json",
        serde_json::json!({
            "heights": tj["heights"],
            "vertical_crs": tj["vertical_crs"],
            "encoding": tj["encoding"],
        })
        .to_string(),
    ));
    for (k, v) in rows {
        tx.execute("INSERT INTO metadata VALUES (?1, ?2)", params![k, v])
            .map_err(fail)?;
    }
    tx.commit().map_err(fail)?;
    db.close().map_err(|(_, e)| fail(e))?;
    std::fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(io(path))?;
    Ok(distinct)
}
