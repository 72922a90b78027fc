//! Cloud-optimized GeoTIFF: a float32 raster in 512² tiles with its overviews, laid out as
//! GDAL's COG driver lays it out, so that a reader fetches the header and every directory in
//! one range request and then only the tiles it needs:
//!
//! - the header, then GDAL's "ghost" structural metadata saying the layout (readers that know
//!   it skip probing);
//! - every IFD, full resolution first then each overview, coarsest last, with their arrays;
//! - the tiles' bytes, coarsest overview first, each level's row by row.
//!
//! Tiles are deflated with the floating-point predictor (TIFF Technical Note 3: each row's
//! bytes regrouped by significance, then differenced), as GDAL writes float DEMs: about half
//! the bytes of plain deflate. The `tiff` crate writes neither tiles nor that predictor, so
//! the file is written here; GDAL and rio-cogeo validate it in `tests/daemon/exports.rs`.

use super::write_tiff::{format_nodata, geo_key_directory};
use super::ReadError;
use patchwork_crs::Crs;
use rayon::prelude::*;
use std::io::Write;
use std::path::Path;

/// Pixels on a tile's side, GDAL's COG default.
pub const BLOCK: usize = 512;

/// One level of the pyramid: `width × height` samples, row-major, NaN where there is no data.
pub struct Level {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// The samples.
    pub samples: Vec<f32>,
}

impl Level {
    /// The next coarser level: each sample the mean of the valid ones among the 2 × 2 it
    /// covers (GDAL's `average` resampling), NaN where none is.
    pub fn halved(&self) -> Level {
        let (w, h) = (self.width.div_ceil(2), self.height.div_ceil(2));
        let mut samples = vec![f32::NAN; w * h];
        samples.par_chunks_mut(w).enumerate().for_each(|(j, row)| {
            for (i, out) in row.iter_mut().enumerate() {
                let (mut sum, mut n) = (0.0f64, 0u32);
                for (di, dj) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (x, y) = (2 * i + di, 2 * j + dj);
                    if x < self.width && y < self.height {
                        let v = self.samples[y * self.width + x];
                        if !v.is_nan() {
                            sum += f64::from(v);
                            n += 1;
                        }
                    }
                }
                if n > 0 {
                    *out = (sum / f64::from(n)) as f32;
                }
            }
        });
        Level {
            width: w,
            height: h,
            samples,
        }
    }
}

/// The overviews of `full`, each half the one before, until one fits in a tile.
pub fn pyramid(full: Level) -> Vec<Level> {
    let mut levels = vec![full];
    while let Some(last) = levels.last() {
        if last.width <= BLOCK && last.height <= BLOCK {
            break;
        }
        let next = last.halved();
        levels.push(next);
    }
    levels
}

/// Writes `levels` (full resolution first, as [`pyramid`] gives them) to `path` as a COG with
/// geotransform `gt` (north-up) of the full level, in `crs`, voids as `nodata`.
pub fn write_cog_f32(
    path: &Path,
    levels: &[Level],
    gt: [f64; 6],
    crs: Option<&Crs>,
    nodata: f64,
) -> Result<(), ReadError> {
    let bytes = cog_f32_bytes(levels, gt, crs, nodata)?;
    let mut f = std::fs::File::create(path)?;
    f.write_all(&bytes)?;
    f.sync_all()?;
    Ok(())
}

/// Tag types.
const SHORT: u16 = 3;
const LONG: u16 = 4;
const ASCII: u16 = 2;
const DOUBLE: u16 = 12;

/// A tag's value as it is stored.
enum Value {
    Short(Vec<u16>),
    Long(Vec<u32>),
    Ascii(String),
    Double(Vec<f64>),
}

impl Value {
    fn kind(&self) -> u16 {
        match self {
            Value::Short(_) => SHORT,
            Value::Long(_) => LONG,
            Value::Ascii(_) => ASCII,
            Value::Double(_) => DOUBLE,
        }
    }

    fn count(&self) -> u32 {
        match self {
            Value::Short(v) => v.len() as u32,
            Value::Long(v) => v.len() as u32,
            // With its NUL.
            Value::Ascii(s) => s.len() as u32 + 1,
            Value::Double(v) => v.len() as u32,
        }
    }

    fn bytes(&self) -> Vec<u8> {
        match self {
            Value::Short(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            Value::Long(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            Value::Ascii(s) => s.bytes().chain([0]).collect(),
            Value::Double(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        }
    }
}

/// The tags of one level's IFD, sorted, with its tile offsets and byte counts to fill in.
fn tags(
    level: &Level,
    overview: bool,
    tiles: usize,
    geo: Option<&[(u16, Value)]>,
) -> Vec<(u16, Value)> {
    let mut t = Vec::new();
    if overview {
        // NewSubfileType: a reduced-resolution version of the image.
        t.push((254, Value::Long(vec![1])));
    }
    t.extend([
        (256, Value::Long(vec![level.width as u32])),
        (257, Value::Long(vec![level.height as u32])),
        (258, Value::Short(vec![32])),
        // Adobe deflate.
        (259, Value::Short(vec![8])),
        // Min-is-black.
        (262, Value::Short(vec![1])),
        (277, Value::Short(vec![1])),
        (284, Value::Short(vec![1])),
        // The floating-point predictor.
        (317, Value::Short(vec![3])),
        (322, Value::Short(vec![BLOCK as u16])),
        (323, Value::Short(vec![BLOCK as u16])),
        (324, Value::Long(vec![0; tiles])),
        (325, Value::Long(vec![0; tiles])),
        // IEEE floating point.
        (339, Value::Short(vec![3])),
    ]);
    if let Some(g) = geo {
        for (k, v) in g {
            let v = match v {
                Value::Short(x) => Value::Short(x.clone()),
                Value::Long(x) => Value::Long(x.clone()),
                Value::Ascii(x) => Value::Ascii(x.clone()),
                Value::Double(x) => Value::Double(x.clone()),
            };
            t.push((*k, v));
        }
    }
    t.sort_by_key(|(k, _)| *k);
    t
}

/// Bytes an IFD of `tags` takes with the values that do not fit in its entries, word-aligned.
fn ifd_len(tags: &[(u16, Value)]) -> usize {
    let outside: usize = tags
        .iter()
        .map(|(_, v)| v.bytes().len())
        .filter(|&n| n > 4)
        .map(|n| n + (n & 1))
        .sum();
    2 + 12 * tags.len() + 4 + outside
}

/// The deflated tiles of a level, row by row, each padded to a whole tile with NaN.
fn tiles_of(level: &Level, nodata: f32) -> Vec<Vec<u8>> {
    let across = level.width.div_ceil(BLOCK);
    let down = level.height.div_ceil(BLOCK);
    (0..across * down)
        .into_par_iter()
        .map(|t| {
            let (tx, ty) = (t % across, t / across);
            let mut raw = Vec::with_capacity(BLOCK * BLOCK * 4);
            let mut row = vec![0u8; BLOCK * 4];
            for j in 0..BLOCK {
                let y = ty * BLOCK + j;
                // Bytes of most significance first, as the predictor regroups them.
                for i in 0..BLOCK {
                    let x = tx * BLOCK + i;
                    let v = if x < level.width && y < level.height {
                        level.samples[y * level.width + x]
                    } else {
                        f32::NAN
                    };
                    let v = if v.is_nan() { nodata } else { v };
                    let be = v.to_be_bytes();
                    for (k, b) in be.iter().enumerate() {
                        row[k * BLOCK + i] = *b;
                    }
                }
                // Then differenced along the row.
                for k in (1..row.len()).rev() {
                    row[k] = row[k].wrapping_sub(row[k - 1]);
                }
                raw.extend_from_slice(&row);
            }
            let mut z = flate2::write::ZlibEncoder::new(
                Vec::with_capacity(raw.len() / 3),
                flate2::Compression::new(6),
            );
            z.write_all(&raw).expect("deflating into memory");
            z.finish().expect("deflating into memory")
        })
        .collect()
}

/// [`write_cog_f32`] into memory.
pub fn cog_f32_bytes(
    levels: &[Level],
    gt: [f64; 6],
    crs: Option<&Crs>,
    nodata: f64,
) -> Result<Vec<u8>, ReadError> {
    if levels.is_empty() {
        return Err(ReadError::invalid("a COG needs at least one level"));
    }
    if gt[2] != 0.0 || gt[4] != 0.0 || gt[1] <= 0.0 || gt[5] >= 0.0 {
        return Err(ReadError::unsupported(format!(
            "a COG is written north-up, got the geotransform {gt:?}"
        )));
    }
    for l in levels {
        if l.width == 0 || l.height == 0 || l.samples.len() != l.width * l.height {
            return Err(ReadError::invalid(format!(
                "{} samples for a {} x {} level",
                l.samples.len(),
                l.width,
                l.height
            )));
        }
    }
    let nd32 = nodata as f32;
    if !nd32.is_finite() {
        return Err(ReadError::invalid(format!(
            "nodata {nodata} is not a finite f32"
        )));
    }
    let (keys, ascii) = geo_key_directory(crs)?;
    let mut geo = vec![
        (33550, Value::Double(vec![gt[1], -gt[5], 0.0])),
        (33922, Value::Double(vec![0.0, 0.0, 0.0, gt[0], gt[3], 0.0])),
        (34735, Value::Short(keys)),
        (42113, Value::Ascii(format_nodata(nodata))),
    ];
    if !ascii.is_empty() {
        geo.push((34737, Value::Ascii(ascii)));
    }
    let data: Vec<Vec<Vec<u8>>> = levels.iter().map(|l| tiles_of(l, nd32)).collect();
    let ifds: Vec<Vec<(u16, Value)>> = levels
        .iter()
        .enumerate()
        .map(|(k, l)| tags(l, k > 0, data[k].len(), (k == 0).then_some(&geo[..])))
        .collect();

    // GDAL's structural metadata: the layout, so that its reader need not probe for it.
    let body = "LAYOUT=IFDS_BEFORE_DATA\nBLOCK_ORDER=ROW_MAJOR\nKNOWN_INCOMPATIBLE_EDITION=NO\n";
    let ghost = format!(
        "GDAL_STRUCTURAL_METADATA_SIZE={:06} bytes\n{body}",
        body.len()
    );
    let first_ifd = 8 + ghost.len() + (ghost.len() & 1);
    let mut ifd_at = Vec::with_capacity(ifds.len());
    let mut at = first_ifd;
    for t in &ifds {
        ifd_at.push(at);
        at += ifd_len(t);
    }
    // The tiles, coarsest level first.
    let mut tile_at: Vec<Vec<(u32, u32)>> = vec![Vec::new(); levels.len()];
    for k in (0..levels.len()).rev() {
        for d in &data[k] {
            let off = u32::try_from(at).map_err(|_| too_big())?;
            tile_at[k].push((off, d.len() as u32));
            at += d.len();
        }
    }
    u32::try_from(at).map_err(|_| too_big())?;

    let mut out = Vec::with_capacity(at);
    out.extend_from_slice(b"II");
    out.extend_from_slice(&42u16.to_le_bytes());
    out.extend_from_slice(&(first_ifd as u32).to_le_bytes());
    out.extend_from_slice(ghost.as_bytes());
    if ghost.len() & 1 == 1 {
        out.push(0);
    }
    for (k, mut t) in ifds.into_iter().enumerate() {
        for (tag, v) in t.iter_mut() {
            match tag {
                324 => *v = Value::Long(tile_at[k].iter().map(|p| p.0).collect()),
                325 => *v = Value::Long(tile_at[k].iter().map(|p| p.1).collect()),
                _ => {}
            }
        }
        debug_assert_eq!(out.len(), ifd_at[k]);
        let start = ifd_at[k];
        let mut extra = start + 2 + 12 * t.len() + 4;
        let mut entries = Vec::new();
        let mut outside = Vec::new();
        entries.extend_from_slice(&(t.len() as u16).to_le_bytes());
        for (tag, v) in &t {
            let b = v.bytes();
            entries.extend_from_slice(&tag.to_le_bytes());
            entries.extend_from_slice(&v.kind().to_le_bytes());
            entries.extend_from_slice(&v.count().to_le_bytes());
            if b.len() <= 4 {
                let mut word = [0u8; 4];
                word[..b.len()].copy_from_slice(&b);
                entries.extend_from_slice(&word);
            } else {
                entries.extend_from_slice(&(extra as u32).to_le_bytes());
                extra += b.len() + (b.len() & 1);
                outside.extend_from_slice(&b);
                if b.len() & 1 == 1 {
                    outside.push(0);
                }
            }
        }
        let next = ifd_at.get(k + 1).copied().unwrap_or(0) as u32;
        entries.extend_from_slice(&next.to_le_bytes());
        out.extend_from_slice(&entries);
        out.extend_from_slice(&outside);
    }
    for k in (0..levels.len()).rev() {
        for d in &data[k] {
            out.extend_from_slice(d);
        }
    }
    debug_assert_eq!(out.len(), at);
    Ok(out)
}

fn too_big() -> ReadError {
    ReadError::unsupported(
        "the COG would pass 4 GiB, more than a classic TIFF addresses: export a smaller \
         region or a coarser resolution",
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{read_raster, ReadLimits};

    #[test]
    fn a_cog_reads_back_sample_for_sample_with_its_overviews_halved() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.tif");
        let (w, h) = (1100, 700);
        let mut samples: Vec<f32> = (0..w * h)
            .map(|k| ((k % w) as f32 * 0.37).sin() * 300.0 + (k / w) as f32 * 0.25 - 50.0)
            .collect();
        samples[5] = f32::NAN;
        samples[w * 600 + 1000] = f32::NAN;
        let levels = pyramid(Level {
            width: w,
            height: h,
            samples: samples.clone(),
        });
        // 1100 → 550 → 275: the last fits in a tile.
        assert_eq!(
            levels.iter().map(|l| l.width).collect::<Vec<_>>(),
            [1100, 550, 275]
        );
        let gt = [5.0, 1.0 / 3600.0, 0.0, 45.0, 0.0, -1.0 / 3600.0];
        write_cog_f32(&path, &levels, gt, Some(&Crs::epsg(4326).unwrap()), -9999.0).unwrap();
        let r = read_raster(&path, &ReadLimits::default()).unwrap();
        assert_eq!((r.cols, r.rows), (w, h));
        assert_eq!(r.geotransform, gt);
        assert_eq!(r.crs.epsg(), Some(4326));
        for (k, (a, b)) in r.samples.iter().zip(&samples).enumerate() {
            assert!(a == b || (a.is_nan() && b.is_nan()), "{k}: {a} vs {b}");
        }
        // An overview sample is the mean of the valid ones below it.
        let o = &levels[1];
        let hole = (samples[4] + samples[w + 4] + samples[w + 5]) / 3.0;
        assert!((o.samples[2] - hole).abs() < 1e-4);
        let m = (samples[0] + samples[1] + samples[w] + samples[w + 1]) / 4.0;
        assert!((o.samples[0] - m).abs() < 1e-4);
    }
}
