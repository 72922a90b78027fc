//! Samples on disk: square chunks of a level, compressed losslessly, checksummed, and read
//! back through a bounded cache of decoded chunks.
//!
//! A chunk is `CHUNK × CHUNK` samples of one level (less at the level's right and bottom
//! edges), so a patch's window (33² samples by default) touches at most four of them and a
//! tile decodes about the area it covers. Chunks are numbered row-major over the level.
//!
//! Encoding, chosen by measurement (docs/BENCHMARKS.md, "Store size"):
//! - heights that are all whole numbers (16-bit sources: SRTM, NASADEM, most .hgt) are
//!   delta-coded along rows as integers, zigzagged, split into byte planes and zstd-compressed;
//! - any other heights go through the float predictor GeoTIFF uses (byte planes, most
//!   significant first, then byte differences along the row) and zstd at level 1;
//! - where neither is smaller than the raw samples, the raw samples are kept.
//!
//! Every chunk starts with a one-byte codec and the first four bytes of the BLAKE3 hash of
//! its payload, checked on every read: a damaged chunk is an error, never wrong heights.

use super::pack::{ChunkStore, Loc};
use patchwork_core::model::grid::{Grid, SampleRect, Shape, Window};
use patchwork_core::model::ids::SurveyId;
use patchwork_core::model::source::{check_rect, SampleError, SampleSource};
use patchwork_core::sync::{read, write};
use rayon::prelude::*;
use std::sync::Arc;

/// Samples per chunk side.
pub const CHUNK: usize = 256;

/// zstd's level: on the predicted planes level 1 is within 2% of level 3 and 6% of level 19
/// in size, at two thirds of level 3's time, and encoding is a tenth of an ingest's work (see
/// docs/BENCHMARKS.md, "The store").
const ZSTD_LEVEL: i32 = 1;

const RAW: u8 = 0;
const FLOAT: u8 = 1;
const INT: u8 = 2;
/// Not samples: a record kept in the pack (a survey's patches), zstd-compressed.
const SEALED: u8 = 3;
const HEADER: usize = 5;
/// Stands for a void in the integer codec: far outside any height a reader accepts.
const INT_VOID: i32 = i32::MIN;
/// Integers beyond this are not heights; their deltas could overflow.
const INT_LIMIT: f32 = (1 << 30) as f32;

/// The chunks of a level: how many along each axis.
pub fn chunk_counts(shape: &Shape) -> [usize; 2] {
    [shape.cols.div_ceil(CHUNK), shape.rows.div_ceil(CHUNK)]
}

/// The samples chunk `k` of a level holds.
pub fn chunk_rect(shape: &Shape, k: usize) -> SampleRect {
    let [nx, _] = chunk_counts(shape);
    let (tx, ty) = (k % nx, k / nx);
    SampleRect {
        c0: tx * CHUNK,
        r0: ty * CHUNK,
        c1: ((tx + 1) * CHUNK).min(shape.cols),
        r1: ((ty + 1) * CHUNK).min(shape.rows),
    }
}

/// The chunks of a level, with their encoded bytes, in parallel.
pub fn encode_level(g: &Grid) -> Vec<(usize, Vec<u8>)> {
    let shape = g.shape();
    let [nx, ny] = chunk_counts(&shape);
    (0..nx * ny)
        .into_par_iter()
        .map(|k| {
            let r = chunk_rect(&shape, k);
            let mut samples = Vec::with_capacity(r.len());
            for row in r.r0..r.r1 {
                samples.extend_from_slice(&g.samples[row * g.cols + r.c0..row * g.cols + r.c1]);
            }
            (k, encode(&samples, r.cols()))
        })
        .collect()
}

fn checksum(payload: &[u8]) -> [u8; 4] {
    let h = blake3::hash(payload);
    h.as_bytes()[..4].try_into().expect("4 bytes")
}

/// Whether a chunk's or a sealed record's bytes still match the checksum in their header: what
/// an open checks of every chunk without decoding one.
pub fn intact(bytes: &[u8]) -> Result<(), String> {
    if bytes.len() < HEADER {
        return Err(format!(
            "{} bytes, shorter than a chunk header",
            bytes.len()
        ));
    }
    if checksum(&bytes[HEADER..]) != bytes[1..HEADER] {
        return Err("the checksum does not match: the chunk is damaged".into());
    }
    Ok(())
}

fn with_header(codec: u8, payload: Vec<u8>) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER + payload.len());
    out.push(codec);
    out.extend_from_slice(&checksum(&payload));
    out.extend_from_slice(&payload);
    out
}

/// Whether every height is void or a whole number whose float is exactly that integer.
fn all_integers(samples: &[f32]) -> bool {
    samples.iter().all(|&z| {
        z.is_nan() || (z.abs() < INT_LIMIT && (z as i32) as f32 == z && z.to_bits() != 0x8000_0000)
    })
}

/// Splits 4-byte words into four planes, `order` giving the byte of each word per plane.
fn planes(words: impl ExactSizeIterator<Item = [u8; 4]>, out: &mut Vec<u8>) {
    let n = words.len();
    let start = out.len();
    out.resize(start + 4 * n, 0);
    let (p0, rest) = out[start..].split_at_mut(n);
    let (p1, rest) = rest.split_at_mut(n);
    let (p2, p3) = rest.split_at_mut(n);
    for (i, w) in words.enumerate() {
        p0[i] = w[0];
        p1[i] = w[1];
        p2[i] = w[2];
        p3[i] = w[3];
    }
}

fn unplanes(bytes: &[u8], n: usize) -> impl Iterator<Item = [u8; 4]> + '_ {
    let (p0, rest) = bytes.split_at(n);
    let (p1, rest) = rest.split_at(n);
    let (p2, p3) = rest.split_at(n);
    (0..n).map(move |i| [p0[i], p1[i], p2[i], p3[i]])
}

/// Encodes a chunk of `cols`-wide rows.
pub fn encode(samples: &[f32], cols: usize) -> Vec<u8> {
    encode_at(samples, cols, ZSTD_LEVEL)
}

/// [`encode`] at another zstd level: for measuring the choice.
#[doc(hidden)]
pub fn encode_at(samples: &[f32], cols: usize, level: i32) -> Vec<u8> {
    let raw_len = 4 * samples.len();
    let mut pre = Vec::with_capacity(raw_len);
    let codec = if all_integers(samples) {
        for row in samples.chunks(cols) {
            let mut prev = 0i32;
            let words = row.iter().map(|&z| {
                let x = if z.is_nan() { INT_VOID } else { z as i32 };
                let d = x.wrapping_sub(prev);
                prev = x;
                (((d << 1) ^ (d >> 31)) as u32).to_le_bytes()
            });
            planes(words, &mut pre);
        }
        INT
    } else {
        for row in samples.chunks(cols) {
            let start = pre.len();
            planes(row.iter().map(|z| z.to_bits().to_be_bytes()), &mut pre);
            // Byte differences along the row's planes, last to first so each uses the original.
            let r = &mut pre[start..];
            for i in (1..r.len()).rev() {
                r[i] = r[i].wrapping_sub(r[i - 1]);
            }
        }
        FLOAT
    };
    match zstd::bulk::compress(&pre, level) {
        Ok(z) if z.len() < raw_len => with_header(codec, z),
        _ => {
            let raw: Vec<u8> = samples.iter().flat_map(|z| z.to_le_bytes()).collect();
            with_header(RAW, raw)
        }
    }
}

/// A record's bytes as the pack keeps them: compressed, with the chunk header's checksum.
pub fn seal(bytes: &[u8]) -> Vec<u8> {
    let z = zstd::bulk::compress(bytes, ZSTD_LEVEL).expect("compressing in memory");
    with_header(SEALED, z)
}

/// A record's bytes back from [`seal`]; at most `limit` bytes are accepted.
pub fn unseal(bytes: &[u8], limit: usize) -> Result<Vec<u8>, String> {
    if bytes.len() < HEADER || bytes[0] != SEALED {
        return Err("not a sealed record".into());
    }
    if checksum(&bytes[HEADER..]) != bytes[1..HEADER] {
        return Err("the checksum does not match: the record is damaged".into());
    }
    // zstd writes the content's size in the frame, so the buffer is made that size: made the
    // size of the limit, every record read would take a gibibyte of address space.
    let payload = &bytes[HEADER..];
    let size = match zstd::zstd_safe::get_frame_content_size(payload) {
        Ok(Some(n)) if n <= limit as u64 => n as usize,
        Ok(Some(n)) => return Err(format!("{n} bytes, more than a record may hold ({limit})")),
        _ => limit,
    };
    zstd::bulk::decompress(payload, size).map_err(|e| format!("zstd: {e}"))
}

/// Decodes a chunk of `n` samples in `cols`-wide rows.
pub fn decode(bytes: &[u8], n: usize, cols: usize) -> Result<Vec<f32>, String> {
    if bytes.len() < HEADER {
        return Err(format!(
            "{} bytes, shorter than a chunk header",
            bytes.len()
        ));
    }
    let (codec, sum, payload) = (bytes[0], &bytes[1..HEADER], &bytes[HEADER..]);
    if checksum(payload) != sum {
        return Err("the checksum does not match: the chunk is damaged".into());
    }
    let unpack = |p: &[u8]| -> Result<Vec<u8>, String> {
        let b = zstd::bulk::decompress(p, 4 * n).map_err(|e| format!("zstd: {e}"))?;
        if b.len() != 4 * n {
            return Err(format!("{} bytes decoded, {} expected", b.len(), 4 * n));
        }
        Ok(b)
    };
    match codec {
        RAW if payload.len() == 4 * n => Ok(payload
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")))
            .collect()),
        RAW => Err(format!("{} raw bytes, {} expected", payload.len(), 4 * n)),
        INT => {
            let b = unpack(payload)?;
            let mut out = Vec::with_capacity(n);
            let mut at = 0;
            while at < n {
                let w = cols.min(n - at);
                let mut prev = 0i32;
                for word in unplanes(&b[4 * at..4 * (at + w)], w) {
                    let u = u32::from_le_bytes(word);
                    let d = ((u >> 1) as i32) ^ -((u & 1) as i32);
                    prev = prev.wrapping_add(d);
                    out.push(if prev == INT_VOID {
                        f32::NAN
                    } else {
                        prev as f32
                    });
                }
                at += w;
            }
            Ok(out)
        }
        FLOAT => {
            let mut b = unpack(payload)?;
            let mut out = Vec::with_capacity(n);
            let mut at = 0;
            while at < n {
                let w = cols.min(n - at);
                let r = &mut b[4 * at..4 * (at + w)];
                for i in 1..r.len() {
                    r[i] = r[i].wrapping_add(r[i - 1]);
                }
                out.extend(unplanes(r, w).map(|word| f32::from_bits(u32::from_be_bytes(word))));
                at += w;
            }
            Ok(out)
        }
        c => Err(format!("unknown chunk codec {c}")),
    }
}

/// A decoded chunk in the cache, georeferenced where it lies: a patch whose samples lie in one
/// chunk reads them in place. Copying every patch's window cost a tile of 16,000 patches
/// 290 MB of copies, a third of its time.
type Chunk = Arc<Grid>;

/// Which chunk: survey, level, number.
type ChunkKey = (u64, u8, u32);

#[derive(Clone)]
struct Bytes;

impl quick_cache::Weighter<ChunkKey, Chunk> for Bytes {
    fn weight(&self, _: &ChunkKey, v: &Chunk) -> u64 {
        4 * v.samples.len() as u64 + 64
    }
}

/// Reads chunks from the store through a cache of decoded ones, bounded in bytes.
///
/// Terrains published to readers hold it; the store closes it when it closes, so that a
/// snapshot still in a reader's hands never keeps the database open (and its directory
/// locked) after the store is gone. Reads after that fail, cached chunks aside.
pub struct ChunkReader {
    /// Chunk locations, and the pack that holds the bytes.
    open: std::sync::RwLock<Option<(sled::Tree, Arc<dyn ChunkStore>)>>,
    cache: quick_cache::sync::Cache<ChunkKey, Chunk, Bytes>,
}

impl std::fmt::Debug for ChunkReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ChunkReader")
            .field("cached_bytes", &self.cache.weight())
            .finish()
    }
}

/// How the cache is doing.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheStats {
    /// Bytes the cached chunks take, as the cache weighs them: 4 a sample and 64 a chunk.
    pub bytes: u64,
    /// The most bytes the cache holds.
    pub capacity: u64,
    /// Decoded chunks in the cache.
    pub chunks: usize,
    /// Reads the cache answered since the reader was made.
    pub hits: u64,
    /// Reads that had to go to the pack since the reader was made.
    pub misses: u64,
}

impl ChunkReader {
    /// A reader of the chunks whose locations are in `tree` and whose bytes are in `pack`,
    /// caching at most `capacity_bytes` of decoded samples.
    pub fn new(tree: sled::Tree, pack: Arc<dyn ChunkStore>, capacity_bytes: u64) -> Self {
        let items = (capacity_bytes / (4 * (CHUNK * CHUNK) as u64)).max(16) as usize;
        ChunkReader {
            open: std::sync::RwLock::new(Some((tree, pack))),
            cache: quick_cache::sync::Cache::with_weighter(items, capacity_bytes, Bytes),
        }
    }

    /// Lets go of the database: later reads of chunks not in the cache fail.
    pub fn close(&self) {
        *write(&self.open) = None;
    }

    /// The cache's size and hit counts now.
    pub fn stats(&self) -> CacheStats {
        CacheStats {
            bytes: self.cache.weight(),
            capacity: self.cache.capacity(),
            chunks: self.cache.len(),
            hits: self.cache.hits(),
            misses: self.cache.misses(),
        }
    }

    /// Fetches together the chunks `wants` needs that the cache lacks, when the pack is remote
    /// (see [`SampleSource::prefetch`]): a cold 512² tile on S3 needs about fifty, which one
    /// by one are fifty GETs. A local pack reads a chunk in microseconds, and is left alone.
    fn fetch_missing(
        &self,
        wants: &[(SurveyId, usize, Shape, SampleRect)],
    ) -> Result<(), SampleError> {
        let open = read(&self.open);
        let Some((tree, pack)) = open.as_ref() else {
            return Ok(());
        };
        if pack.local() {
            return Ok(());
        }
        let mut seen = std::collections::HashSet::new();
        let mut todo: Vec<(ChunkKey, SurveyId, usize, Shape, usize, Loc)> = Vec::new();
        for &(survey, level, shape, rect) in wants {
            if check_rect(survey, &rect, shape.cols, shape.rows).is_err() {
                continue;
            }
            for k in chunks_reached(&shape, &rect) {
                let key = (survey.0, level as u8, k as u32);
                if self.cache.contains_key(&key) || !seen.insert(key) {
                    continue;
                }
                // A chunk whose location is missing or bad is left to the read to report.
                let chunk = super::keys::chunk(survey, level, k);
                if let Ok(loc) = location(tree, pack.as_ref(), &chunk) {
                    todo.push((key, survey, level, shape, k, loc));
                }
            }
        }
        if todo.len() < 2 {
            return Ok(());
        }
        let locs: Vec<Loc> = todo.iter().map(|t| t.5).collect();
        let got = pack.read_many(&locs);
        let unreachable = todo.iter().zip(&got).find_map(|(t, r)| match r {
            Err(e) if super::objects::is_unreachable(e) => Some((t.1, t.2, t.4, e.to_string())),
            _ => None,
        });
        if let Some((survey, level, k, e)) = unreachable {
            return Err(SampleError {
                survey,
                reason: format!("chunk {k} of level {level}: reading the pack: {e}"),
                unavailable: true,
            });
        }
        todo.into_par_iter()
            .zip(got)
            .for_each(|((key, _, _, shape, k, _), bytes)| {
                let r = chunk_rect(&shape, k);
                // What fails to arrive or to decode (its checksum checked as on every read) is
                // read again, and reported, by the read that needs it.
                if let Some(samples) = bytes.ok().and_then(|b| decode(&b, r.len(), r.cols()).ok()) {
                    self.cache
                        .insert(key, Arc::new(placed(&shape, &r, samples)));
                }
            });
        Ok(())
    }

    fn chunk(
        &self,
        survey: SurveyId,
        level: usize,
        shape: &Shape,
        k: usize,
    ) -> Result<Chunk, SampleError> {
        let key = (survey.0, level as u8, k as u32);
        self.cache.get_or_insert_with(&key, || {
            let fail = |reason: String| SampleError {
                survey,
                reason,
                unavailable: false,
            };
            let r = chunk_rect(shape, k);
            let open = read(&self.open);
            let (tree, pack) = open
                .as_ref()
                .ok_or_else(|| fail("the store is closed".into()))?;
            let bytes = located(tree, pack.as_ref(), &super::keys::chunk(survey, level, k))
                .map_err(|e| fail(format!("chunk {k} of level {level}: {e}")))?
                .map_err(|e| SampleError {
                    unavailable: super::objects::is_unreachable(&e),
                    ..fail(format!("chunk {k} of level {level}: reading the pack: {e}"))
                })?;
            let samples = decode(&bytes, r.len(), r.cols())
                .map_err(|e| fail(format!("chunk {k} of level {level}: {e}")))?;
            Ok(Arc::new(placed(shape, &r, samples)))
        })
    }
}

/// The chunks of a level shaped `shape` that `rect` (not empty) reaches, by index.
fn chunks_reached(shape: &Shape, rect: &SampleRect) -> impl Iterator<Item = usize> {
    let [nx, _] = chunk_counts(shape);
    let (cols, rows) = (
        rect.c0 / CHUNK..=(rect.c1 - 1) / CHUNK,
        rect.r0 / CHUNK..=(rect.r1 - 1) / CHUNK,
    );
    rows.flat_map(move |ty| cols.clone().map(move |tx| ty * nx + tx))
}

/// A chunk's bytes: its location from the database, then the bytes from the pack.
pub fn read_chunk(
    tree: &sled::Tree,
    pack: &dyn ChunkStore,
    survey: SurveyId,
    level: usize,
    k: usize,
) -> Result<Vec<u8>, String> {
    read_packed(tree, pack, &super::keys::chunk(survey, level, k))
}

/// The bytes the pack holds for `key`, whose value in the database is their location.
pub fn read_packed(
    tree: &sled::Tree,
    pack: &dyn ChunkStore,
    key: &[u8],
) -> Result<Vec<u8>, String> {
    located(tree, pack, key)?.map_err(|e| format!("reading the pack: {e}"))
}

/// The bytes at the location the database holds for `key`: Err when the location is missing
/// or bad, Ok(Err) when the pack could not give its bytes.
fn located(
    tree: &sled::Tree,
    pack: &dyn ChunkStore,
    key: &[u8],
) -> Result<std::io::Result<Vec<u8>>, String> {
    Ok(pack.read(location(tree, pack, key)?))
}

/// The location the database holds for `key`, checked to lie within the pack.
fn location(tree: &sled::Tree, pack: &dyn ChunkStore, key: &[u8]) -> Result<Loc, String> {
    let v = tree
        .get(key)
        .map_err(|e| e.to_string())?
        .ok_or("it is missing")?;
    let loc = Loc::from_bytes(&v).ok_or_else(|| format!("its location is {} bytes", v.len()))?;
    if loc.end() > pack.len() {
        return Err(format!(
            "it lies at {}..{}, past the {} bytes of the pack",
            loc.offset,
            loc.end(),
            pack.len()
        ));
    }
    Ok(loc)
}

/// `rect`'s samples of a level shaped `shape`, georeferenced where they lie in it.
fn placed(shape: &Shape, rect: &SampleRect, samples: Vec<f32>) -> Grid {
    Grid {
        cols: rect.cols(),
        rows: rect.rows(),
        samples,
        georef: patchwork_core::model::grid::Georef {
            origin: shape.georef.to_world(rect.c0 as f64, rect.r0 as f64),
            ..shape.georef
        },
    }
}

impl SampleSource for ChunkReader {
    fn prefetch(&self, wants: &[(SurveyId, usize, Shape, SampleRect)]) -> Result<(), SampleError> {
        self.fetch_missing(wants)
    }

    fn read(
        &self,
        survey: SurveyId,
        level: usize,
        shape: &Shape,
        rect: SampleRect,
    ) -> Result<Grid, SampleError> {
        check_rect(survey, &rect, shape.cols, shape.rows)?;
        let mut samples = vec![f32::NAN; rect.len()];
        for k in chunks_reached(shape, &rect) {
            let cr = chunk_rect(shape, k);
            let chunk = self.chunk(survey, level, shape, k)?;
            let (c0, c1) = (rect.c0.max(cr.c0), rect.c1.min(cr.c1));
            for r in rect.r0.max(cr.r0)..rect.r1.min(cr.r1) {
                let from = (r - cr.r0) * cr.cols() + (c0 - cr.c0);
                let to = (r - rect.r0) * rect.cols() + (c0 - rect.c0);
                samples[to..to + (c1 - c0)].copy_from_slice(&chunk.samples[from..from + (c1 - c0)]);
            }
        }
        Ok(placed(shape, &rect, samples))
    }

    fn window(
        &self,
        survey: SurveyId,
        level: usize,
        shape: &Shape,
        rect: SampleRect,
    ) -> Result<Window, SampleError> {
        check_rect(survey, &rect, shape.cols, shape.rows)?;
        let [nx, _] = chunk_counts(shape);
        let (tx, ty) = (rect.c0 / CHUNK, rect.r0 / CHUNK);
        if (rect.c1 - 1) / CHUNK != tx || (rect.r1 - 1) / CHUNK != ty {
            let grid = Arc::new(self.read(survey, level, shape, rect)?);
            return Ok(Window::of(grid, rect, *shape));
        }
        let k = ty * nx + tx;
        Ok(Window::of(
            self.chunk(survey, level, shape, k)?,
            chunk_rect(shape, k),
            *shape,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(samples: &[f32], cols: usize) -> u8 {
        let b = encode(samples, cols);
        let back = decode(&b, samples.len(), cols).unwrap();
        for (a, z) in samples.iter().zip(&back) {
            assert!(
                a.to_bits() == z.to_bits() || (a.is_nan() && z.is_nan()),
                "{a} came back as {z}"
            );
        }
        b[0]
    }

    #[test]
    fn every_codec_gives_back_the_exact_samples() {
        let ints: Vec<f32> = (0..600)
            .map(|i| {
                if i % 37 == 0 {
                    f32::NAN
                } else {
                    (i % 50) as f32 - 20.0
                }
            })
            .collect();
        assert_eq!(round_trip(&ints, 30), INT);
        let floats: Vec<f32> = (0..600)
            .map(|i| {
                if i % 41 == 0 {
                    f32::NAN
                } else {
                    (i as f32 * 0.37).sin() * 812.25
                }
            })
            .collect();
        assert_eq!(round_trip(&floats, 30), FLOAT);
        // -0 is not the integer 0 bit for bit, and extreme values overflow deltas.
        let odd = [
            -0.0f32,
            1.0,
            2.0,
            3.0e9,
            -3.0e9,
            f32::MIN_POSITIVE,
            7.0,
            8.0,
        ];
        assert_ne!(round_trip(&odd, 4), INT);
        // Noise does not compress: it is kept raw.
        let mut x = 0x1234_5678u32;
        let noise: Vec<f32> = (0..256)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                f32::from_bits(x & 0x7f7f_ffff)
            })
            .collect();
        assert_eq!(round_trip(&noise, 16), RAW);
    }

    #[test]
    fn reads_assemble_windows_across_chunks_and_the_cache_stays_within_its_bound() {
        use crate::pack::PackFile;
        use patchwork_core::model::grid::Georef;
        let tmp = tempfile::tempdir().unwrap();
        let db = sled::Config::new()
            .path(tmp.path().join("db"))
            .open()
            .unwrap();
        let pack = Arc::new(PackFile::open(tmp.path(), 0).unwrap());
        // 600 × 520 samples: 3 × 3 chunks, the last row and column of them partial.
        let (cols, rows) = (600, 520);
        let samples: Vec<f32> = (0..cols * rows)
            .map(|i| {
                if i % 97 == 0 {
                    f32::NAN
                } else {
                    (i % 1013) as f32 * 0.25
                }
            })
            .collect();
        let g = Grid::new(
            cols,
            rows,
            samples,
            Georef::north_up([0.0, 0.0], [1.0, 1.0]),
        )
        .unwrap();
        let id = SurveyId(42);
        let (ks, bytes): (Vec<usize>, Vec<Vec<u8>>) = encode_level(&g).into_iter().unzip();
        assert_eq!(ks.len(), 9);
        for (k, loc) in ks.into_iter().zip(pack.append(&bytes).unwrap()) {
            db.insert(super::super::keys::chunk(id, 0, k), &loc.to_bytes()[..])
                .unwrap();
        }
        // Room for two decoded chunks.
        let one = 4 * (CHUNK * CHUNK) as u64 + 64;
        let reader = ChunkReader::new((*db).clone(), pack, 2 * one);
        let shape = g.shape();
        // A window across four chunks comes back exactly.
        let rect = SampleRect {
            c0: 250,
            r0: 240,
            c1: 270,
            r1: 300,
        };
        let w = reader.read(id, 0, &shape, rect).unwrap();
        let want = g.window(250, 240, 20, 60);
        assert!(w
            .samples
            .iter()
            .zip(&want.samples)
            .all(|(a, b)| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())));
        assert_eq!(w.georef, want.georef);
        // The whole level, then again: the cache never holds more than its bound.
        for _ in 0..2 {
            let all = reader.read(id, 0, &shape, shape.all()).unwrap();
            assert_eq!(all.samples.len(), cols * rows);
            let st = reader.stats();
            assert!(st.bytes <= st.capacity, "{st:?}");
        }
        let st = reader.stats();
        assert!(st.misses >= 9 + 4, "{st:?}");
        // Past the store's closing, only what is cached can still be read.
        reader.close();
        assert!(reader.read(id, 0, &shape, shape.all()).is_err());
    }

    #[test]
    fn a_damaged_chunk_is_an_error() {
        let s: Vec<f32> = (0..100).map(|i| i as f32 * 0.5).collect();
        let mut b = encode(&s, 10);
        let last = b.len() - 1;
        b[last] ^= 1;
        assert!(decode(&b, 100, 10).unwrap_err().contains("checksum"));
        assert!(decode(&b[..3], 100, 10).is_err());
    }
}
