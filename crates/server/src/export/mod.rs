//! One-file exports of the web pyramid, for hosting without a server: PMTiles (what a CDN
//! or an object store serves to MapLibre through the pmtiles protocol) and MBTiles (what older
//! tile stacks and offline apps read). Each tile is made by the same code, with the same
//! parameters, as the HTTP server's `/tiles/{z}/{x}/{y}.png|webp` ([`raster::tile`]), so an
//! archive holds byte for byte what the server would send.
//!
//! An export is resumable. Tiles are kept as they are made in a folder beside the archive
//! (`OUT.part`): their bytes appended to one file, then a record of each (its tile id, where
//! its bytes are, and its ETag) appended to another once the bytes are durable, every second
//! (and when the export stops). A rerun with the same options reads the records back, drops whatever a crash left
//! past the last whole record, and asks for each kept tile again with its ETag: where the
//! data under the tile is unchanged the tile is kept without being made, and where a survey
//! came or went since, it is made afresh. The archive is written last, to a temporary name
//! renamed into place, so that `OUT` is either absent or whole.
//!
//! Tiles are resampled on the CPU, whose arithmetic gives the same bytes on every run: a
//! tile kept from a run before is then the tile this run would make. A GPU's float32
//! rounding differs in the last bits of a few heights, so a daemon resampling on a GPU
//! serves tiles that may differ from the archive's by a terrarium step at a few pixels.

mod area;
pub mod cog;
mod mbtiles;
mod pmtiles;

pub use area::Area;

use crate::web::{raster, Encoding, Web};
use axum::body::Bytes;
use patchwork_core::geom::tiles::mercator;
use patchwork_core::geom::Aabb;
use patchwork_core::resample::Cancel;
use patchwork_engine::{EngineError, Heights};
use rayon::prelude::*;
use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// The file an export writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Container {
    /// PMTiles v3: one file of Hilbert-ordered tiles and a directory, read by HTTP ranges.
    Pmtiles,
    /// MBTiles 1.3: an SQLite database of tiles (rows in TMS order) and metadata.
    Mbtiles,
}

/// The image each tile is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Image {
    /// PNG, as `/tiles/{z}/{x}/{y}.png`.
    Png,
    /// Lossless WebP, as `/tiles/{z}/{x}/{y}.webp`.
    Webp,
}

/// What to export.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The file.
    pub container: Container,
    /// How heights are coded in a tile's colours.
    pub encoding: Encoding,
    /// The image each tile is.
    pub image: Image,
    /// Pixels on a side: 256 or 512.
    pub size: u32,
    /// The first and last zoom.
    pub zooms: (u32, u32),
    /// Where; the surveys' footprints where None.
    pub area: Option<Area>,
    /// The cut's error, metres; where None, each zoom's own as the HTTP server's default
    /// (half a pixel at the equator).
    pub error: Option<f64>,
    /// What the heights are measured from.
    pub heights: Heights,
}

impl Plan {
    /// What a staged tile was made for: a rerun with other options starts afresh.
    fn key(&self) -> String {
        format!(
            "patchwork export 1 {}\n{:?} {:?} {:?} {} {:?} {:?} {:?} {}\n",
            env!("CARGO_PKG_VERSION"),
            self.container,
            self.encoding,
            self.image,
            self.size,
            self.zooms,
            self.area,
            self.error,
            self.heights.key()
        )
    }

    fn format(&self) -> raster::Format {
        match self.image {
            Image::Png => raster::Format::Png(self.encoding),
            Image::Webp => raster::Format::Webp(self.encoding),
        }
    }
}

/// Why an export stopped. Whatever it made is kept for the next run.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ExportError {
    /// The options cannot make an export.
    #[error("{0}")]
    Options(String),
    /// A tile could not be made.
    #[error("tile {z}/{x}/{y}: {source}")]
    Tile {
        /// Its zoom.
        z: u32,
        /// Its column.
        x: u32,
        /// Its row.
        y: u32,
        /// What failed (boxed: the engine's errors are large, and this one is rare).
        source: Box<EngineError>,
    },
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        source: std::io::Error,
    },
    /// The archive could not be written.
    #[error("writing {path}: {why}")]
    Archive {
        /// The archive.
        path: PathBuf,
        /// What failed.
        why: String,
    },
    /// Stopped when asked.
    #[error("stopped; what was made is kept, and a rerun goes on from there")]
    Cancelled,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ExportError + '_ {
    move |source| ExportError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// How far an export has come.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Progress {
    /// Tiles of the plan.
    pub total: u64,
    /// Tiles done: made now, or kept from a run before.
    pub done: u64,
    /// Of those, kept from a run before.
    pub kept: u64,
    /// Bytes of the tiles done.
    pub bytes: u64,
}

/// What an export wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct Summary {
    /// The tiles and their bytes.
    pub progress: Progress,
    /// Distinct tile contents in the archive (PMTiles stores each once).
    pub distinct: u64,
    /// The archive's bytes.
    pub file_bytes: u64,
    /// The coarsest error any tile was made at, where one was made coarser than asked
    /// (`limits.max_web_tile_patches`), as `X-Patchwork-Error` says of a tile.
    pub coarsened: Option<f64>,
    /// Why the heights are not what the archive says, where the server would say so.
    pub warning: Option<String>,
}

/// How often the tiles made are made durable: a crash loses at most this much work, and the
/// syncs cost nothing beside it.
const SYNC_EVERY: std::time::Duration = std::time::Duration::from_secs(1);

/// Writes `plan` to `out`, telling `progress` after each batch; `cancel` stops it between
/// tiles, keeping what was made.
pub fn export(
    web: &Web,
    plan: &Plan,
    out: &Path,
    cancel: &Cancel,
    progress: &mut dyn FnMut(Progress),
) -> Result<Summary, ExportError> {
    let engine = web.engine().clone();
    let (z0, z1) = plan.zooms;
    if z0 > z1 || z1 > 24 {
        return Err(ExportError::Options(format!(
            "zooms {z0}-{z1}: give A-B with A ≤ B ≤ 24"
        )));
    }
    if !matches!(plan.size, 256 | 512) {
        return Err(ExportError::Options(format!(
            "size must be 256 or 512, got {}",
            plan.size
        )));
    }
    // Refused before any work where the heights cannot be given as asked.
    engine
        .can_give(&plan.heights)
        .map_err(|e| ExportError::Options(e.to_string()))?;
    let pyramid = web.pyramid(&engine);
    let area = match &plan.area {
        Some(a) => a.clone(),
        None if pyramid.footprints.is_empty() => {
            return Err(ExportError::Options(
                "the store holds no survey: nothing to export".into(),
            ))
        }
        None => Area::Polygons(
            pyramid
                .footprints
                .iter()
                .map(|f| vec![f.ring.clone()])
                .collect(),
        ),
    };
    // Every tile of the rectangle the archive's header names, at every zoom: a web map asks
    // for any tile inside a source's bounds, and MapLibre (5.24) stalls on a raster-DEM tile
    // an archive lacks. Those that touch the area are made; the others are the tile the
    // server gives where there is no data, stored once.
    let Some(bounds) = meta_bounds(&area, &pyramid) else {
        return Err(ExportError::Options(
            "the area holds none of the store's surveys: nothing to export".into(),
        ));
    };
    let mut tiles: Vec<(u64, u32, u32, u32, bool)> = Vec::new();
    for z in z0..=z1 {
        for (x, y, inside) in area.tiles(z, &bounds) {
            tiles.push((tile_id(z, x, y), z, x, y, inside));
        }
    }
    let void = Bytes::from(raster::void_image(
        plan.encoding,
        plan.image == Image::Webp,
        plan.size,
    ));
    // In the archive's order, so that tiles near each other on the map are near in the file.
    tiles.sort_unstable();
    let mut stage = Stage::open(&stage_path(out), &plan.key())?;
    let mut p = Progress {
        total: tiles.len() as u64,
        ..Progress::default()
    };
    progress(p);
    let mut coarsened: Option<f64> = None;
    let mut warning = None;
    let mut synced = std::time::Instant::now();
    // Batches of a few tiles a thread: enough to keep every core busy, few enough that the
    // progress moves and a stop is quick.
    for batch in tiles.chunks(rayon::current_num_threads() * 32) {
        if cancel.is_cancelled() {
            stage.sync()?;
            return Err(ExportError::Cancelled);
        }
        let made: Result<Vec<_>, _> = batch
            .par_iter()
            .map(|&(id, z, x, y, inside)| {
                if !inside {
                    let kept = stage.tiles.get(&id).is_some_and(|s| s.etag == VOID);
                    return Ok((id, Made::void((!kept).then(|| void.clone()))));
                }
                let size = plan.size;
                let r = raster::Request {
                    z,
                    x,
                    y,
                    size,
                    format: plan.format(),
                    error: plan.error.unwrap_or_else(|| mercator::error(z, size)),
                    heights: plan.heights.clone(),
                };
                let had = stage.tiles.get(&id).map(|s| quote(&s.etag));
                raster::tile(&engine, web, &r, had.as_deref(), cancel)
                    .map(|t| (id, Made::from(t)))
                    .map_err(|source| match source {
                        EngineError::Cancelled => ExportError::Cancelled,
                        source => ExportError::Tile {
                            z,
                            x,
                            y,
                            source: Box::new(source),
                        },
                    })
            })
            .collect();
        let made = match made {
            Ok(m) => m,
            Err(e) => {
                // What the batches before made is kept for the next run.
                stage.sync()?;
                return Err(e);
            }
        };
        for (id, t) in made {
            if let Some(e) = t.error {
                coarsened = Some(coarsened.map_or(e, |c: f64| c.max(e)));
            }
            if warning.is_none() {
                warning = t.warning.clone();
            }
            match &t.body {
                Some(body) => stage.add(id, t.etag, body)?,
                None => p.kept += 1,
            }
            p.done += 1;
            p.bytes += stage.tiles.get(&id).map_or(0, |s| s.len as u64);
        }
        if synced.elapsed() >= SYNC_EVERY {
            stage.sync()?;
            synced = std::time::Instant::now();
        }
        progress(p);
    }
    stage.sync()?;
    // Only this plan's tiles go in: a stage carried on after a survey went may hold tiles of
    // a rectangle that has since shrunk.
    let planned: std::collections::HashSet<u64> = tiles.iter().map(|t| t.0).collect();
    stage.tiles.retain(|id, _| planned.contains(id));
    let meta = Meta::of(web, plan, &area, &engine);
    let tmp = out.with_file_name(format!(
        ".{}.tmp",
        out.file_name()
            .map_or("export".into(), |n| n.to_string_lossy())
    ));
    let _ = std::fs::remove_file(&tmp);
    let distinct = match plan.container {
        Container::Pmtiles => pmtiles::write(&tmp, &mut stage, &meta)?,
        Container::Mbtiles => mbtiles::write(&tmp, &mut stage, &meta)?,
    };
    std::fs::rename(&tmp, out).map_err(io(out))?;
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        // The rename itself is durable only once the folder is.
        let _ = File::open(dir).and_then(|d| d.sync_all());
    }
    let file_bytes = std::fs::metadata(out).map_err(io(out))?.len();
    stage.remove()?;
    Ok(Summary {
        progress: p,
        distinct,
        file_bytes,
        coarsened,
        warning,
    })
}

/// The stage's ETag of a tile outside the area: no tile the server makes has it.
const VOID: [u8; 16] = [0; 16];

/// A tile made, or found unchanged.
struct Made {
    etag: [u8; 16],
    body: Option<Bytes>,
    error: Option<f64>,
    warning: Option<String>,
}

impl Made {
    /// A tile outside the area: `body`, or None where the stage has it already.
    fn void(body: Option<Bytes>) -> Made {
        Made {
            etag: VOID,
            body,
            error: None,
            warning: None,
        }
    }
}

impl From<crate::web::Produced> for Made {
    fn from(p: crate::web::Produced) -> Made {
        Made {
            etag: p.etag,
            body: p.body,
            error: p.error,
            warning: p.warning,
        }
    }
}

/// The rectangle an export's header names: the area's, within the surveys' union; None where
/// they do not meet.
fn meta_bounds(area: &Area, pyramid: &crate::web::pyramid::Pyramid) -> Option<Aabb> {
    let a = area.bounds()?;
    let b = match pyramid.bounds {
        Some(p) => a.intersection(&p)?,
        None => a,
    };
    let lat = patchwork_core::geom::tiles::MERCATOR_MAX_LAT;
    let (s, n) = (b.min[1].max(-lat), b.max[1].min(lat));
    // Wholly poleward of Web Mercator's reach: no tile holds it.
    (s < n).then(|| Aabb::new(b.min[0], s, b.max[0], n))
}

/// The PMTiles id of tile (z, x, y): its place on the Hilbert curve of its zoom, after every
/// tile of the zooms above it.
pub fn tile_id(z: u32, x: u32, y: u32) -> u64 {
    ::pmtiles::TileId::from(
        ::pmtiles::TileCoord::new(z as u8, x, y).expect("a tile of zoom 0 to 24"),
    )
    .value()
}

fn quote(etag: &[u8; 16]) -> String {
    crate::web::quote_etag(etag)
}

/// Where an export into `out` keeps its tiles until the archive is written.
pub fn stage_path(out: &Path) -> PathBuf {
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push(".part");
    out.with_file_name(name)
}

/// What the archive says of itself beside its tiles.
pub(crate) struct Meta {
    pub zooms: (u32, u32),
    /// West, south, east, north, degrees.
    pub bounds: [f64; 4],
    pub center: [f64; 2],
    pub image: Image,
    /// The TileJSON the HTTP server gives for these tiles, less its URLs: the encoding, the
    /// heights' frame, the attribution of the surveys in the area.
    pub tilejson: serde_json::Value,
}

impl Meta {
    fn of(web: &Web, plan: &Plan, area: &Area, engine: &patchwork_engine::Engine) -> Meta {
        let pyramid = web.pyramid(engine);
        let b = meta_bounds(area, &pyramid).unwrap_or(Aabb::new(-180.0, -85.0, 180.0, 85.0));
        let bounds = [b.min[0], b.min[1], b.max[0], b.max[1]];
        let center = [(bounds[0] + bounds[2]) / 2.0, (bounds[1] + bounds[3]) / 2.0];
        let mut tilejson = pyramid.tilejson(
            String::new(),
            plan.size,
            plan.encoding.name(),
            Some(&b),
            &plan.heights,
        );
        let o = tilejson.as_object_mut().expect("TileJSON is an object");
        o.remove("tiles");
        o.insert("minzoom".into(), plan.zooms.0.into());
        o.insert("maxzoom".into(), plan.zooms.1.into());
        o.insert("bounds".into(), serde_json::json!(bounds));
        o.insert(
            "center".into(),
            serde_json::json!([center[0], center[1], plan.zooms.1.min(10).max(plan.zooms.0)]),
        );
        o.insert("type".into(), "baselayer".into());
        o.insert(
            "format".into(),
            match plan.image {
                Image::Png => "png",
                Image::Webp => "webp",
            }
            .into(),
        );
        Meta {
            zooms: plan.zooms,
            bounds,
            center,
            image: plan.image,
            tilejson,
        }
    }
}

/// One staged tile.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Staged {
    pub offset: u64,
    pub len: u32,
    pub etag: [u8; 16],
}

/// Bytes of a staged tile's record: id, offset, length, ETag.
const RECORD: usize = 8 + 8 + 4 + 16;

/// The tiles made so far, in `OUT.part/`: `plan` (the options they were made for), `tiles`
/// (their bytes, appended) and `index` (a record a tile, appended once its bytes are
/// durable; a later record of a tile replaces an earlier one).
pub(crate) struct Stage {
    dir: PathBuf,
    data: File,
    index: File,
    end: u64,
    pub tiles: HashMap<u64, Staged>,
    records: Vec<u8>,
}

impl Stage {
    fn open(dir: &Path, key: &str) -> Result<Stage, ExportError> {
        let plan = dir.join("plan");
        match std::fs::read_to_string(&plan) {
            Ok(k) if k == key => {}
            Ok(_) => {
                // Tiles of other options are no use to these.
                tracing::info!(stage = %dir.display(), "a partial export of other options is dropped");
                std::fs::remove_dir_all(dir).map_err(io(dir))?;
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                let _ = std::fs::remove_dir_all(dir);
            }
            Err(e) => return Err(io(&plan)(e)),
        }
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        if !plan.exists() {
            std::fs::write(&plan, key).map_err(io(&plan))?;
        }
        let open = |name: &str| {
            let p = dir.join(name);
            OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .open(&p)
                .map_err(io(&p))
        };
        let (mut data, mut index) = (open("tiles")?, open("index")?);
        let data_len = data.metadata().map_err(io(dir))?.len();
        let mut raw = Vec::new();
        index.read_to_end(&mut raw).map_err(io(dir))?;
        let mut tiles = HashMap::new();
        let mut end = 0u64;
        let mut whole = 0;
        for r in raw.chunks_exact(RECORD) {
            let id = u64::from_le_bytes(r[0..8].try_into().expect("8 bytes"));
            let offset = u64::from_le_bytes(r[8..16].try_into().expect("8 bytes"));
            let len = u32::from_le_bytes(r[16..20].try_into().expect("4 bytes"));
            let etag: [u8; 16] = r[20..36].try_into().expect("16 bytes");
            if offset + len as u64 > data_len {
                // Written before its bytes were durable: not the case when records are
                // appended after a sync, but a record must never point past the data.
                break;
            }
            end = end.max(offset + len as u64);
            tiles.insert(id, Staged { offset, len, etag });
            whole += RECORD;
        }
        // A crash may leave a part of a record, or bytes of tiles never recorded: both go.
        index.set_len(whole as u64).map_err(io(dir))?;
        data.set_len(end).map_err(io(dir))?;
        data.seek(SeekFrom::Start(end)).map_err(io(dir))?;
        index.seek(SeekFrom::Start(whole as u64)).map_err(io(dir))?;
        Ok(Stage {
            dir: dir.to_path_buf(),
            data,
            index,
            end,
            tiles,
            records: Vec::new(),
        })
    }

    fn add(&mut self, id: u64, etag: [u8; 16], body: &[u8]) -> Result<(), ExportError> {
        self.data.write_all(body).map_err(io(&self.dir))?;
        let s = Staged {
            offset: self.end,
            len: body.len() as u32,
            etag,
        };
        self.end += body.len() as u64;
        self.records.extend(id.to_le_bytes());
        self.records.extend(s.offset.to_le_bytes());
        self.records.extend(s.len.to_le_bytes());
        self.records.extend(etag);
        self.tiles.insert(id, s);
        Ok(())
    }

    /// Makes the tiles added so far durable: their bytes, then their records.
    fn sync(&mut self) -> Result<(), ExportError> {
        if self.records.is_empty() {
            return Ok(());
        }
        self.data.sync_data().map_err(io(&self.dir))?;
        self.index.write_all(&self.records).map_err(io(&self.dir))?;
        self.index.sync_data().map_err(io(&self.dir))?;
        self.records.clear();
        Ok(())
    }

    /// The staged tiles by id, in id order.
    pub fn sorted(&self) -> Vec<(u64, Staged)> {
        let mut v: Vec<(u64, Staged)> = self.tiles.iter().map(|(k, v)| (*k, *v)).collect();
        v.sort_unstable_by_key(|t| t.0);
        v
    }

    /// The bytes of a staged tile.
    pub fn read(&mut self, s: &Staged, buf: &mut Vec<u8>) -> Result<(), ExportError> {
        buf.resize(s.len as usize, 0);
        self.data
            .seek(SeekFrom::Start(s.offset))
            .and_then(|_| self.data.read_exact(buf))
            .map_err(io(&self.dir))
    }

    fn remove(self) -> Result<(), ExportError> {
        let dir = self.dir.clone();
        drop(self);
        std::fs::remove_dir_all(&dir).map_err(io(&dir))
    }
}

/// The tiles of a staged export in the archive's order with their bytes, for the writers.
pub(crate) fn each_tile(
    stage: &mut Stage,
    mut f: impl FnMut(u64, [u8; 16], &[u8]) -> Result<(), String>,
    out: &Path,
) -> Result<(), ExportError> {
    let mut buf = Vec::new();
    for (id, s) in stage.sorted() {
        stage.read(&s, &mut buf)?;
        f(id, s.etag, &buf).map_err(|why| ExportError::Archive {
            path: out.to_path_buf(),
            why,
        })?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stage_keeps_whole_records_and_drops_what_a_crash_left_half_written() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("out.pmtiles.part");
        let mut s = Stage::open(&p, "plan a").unwrap();
        s.add(1, [1; 16], b"one").unwrap();
        s.add(2, [2; 16], b"two!").unwrap();
        s.sync().unwrap();
        // Bytes of a tile whose record was never written, then half a record.
        s.add(3, [3; 16], b"three").unwrap();
        drop(s);
        let mut index = OpenOptions::new()
            .append(true)
            .open(p.join("index"))
            .unwrap();
        index.write_all(&[7; RECORD / 2]).unwrap();
        drop(index);

        let mut s = Stage::open(&p, "plan a").unwrap();
        assert_eq!(s.tiles.len(), 2);
        let mut buf = Vec::new();
        let two = s.tiles[&2];
        s.read(&two, &mut buf).unwrap();
        assert_eq!(buf, b"two!");
        assert_eq!(std::fs::metadata(p.join("tiles")).unwrap().len(), 7);
        assert_eq!(
            std::fs::metadata(p.join("index")).unwrap().len(),
            2 * RECORD as u64
        );
        // A tile made again is appended, and its later record wins.
        s.add(1, [9; 16], b"uno").unwrap();
        s.sync().unwrap();
        drop(s);
        let mut s = Stage::open(&p, "plan a").unwrap();
        let one = s.tiles[&1];
        assert_eq!(one.etag, [9; 16]);
        s.read(&one, &mut buf).unwrap();
        assert_eq!(buf, b"uno");
        drop(s);
        // Tiles of other options are no use.
        assert!(Stage::open(&p, "plan b").unwrap().tiles.is_empty());
    }

    #[test]
    fn tile_ids_follow_the_pmtiles_spec() {
        // The spec's examples: zoom 0 is 0, zoom 1 starts at 1, zoom 2 at 5.
        assert_eq!(tile_id(0, 0, 0), 0);
        assert_eq!(tile_id(1, 0, 0), 1);
        assert_eq!(tile_id(1, 0, 1), 2);
        assert_eq!(tile_id(2, 0, 0), 5);
    }
}
