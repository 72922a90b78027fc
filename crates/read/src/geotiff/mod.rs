//! GeoTIFF and Cloud Optimized GeoTIFF reader built on the pure-Rust `tiff` decoder.

use rayon::prelude::*;
use std::io::{Cursor, Read, Seek};
use std::panic::{self, AssertUnwindSafe};
use std::path::Path;

use tiff::decoder::ifd::Value;
use tiff::decoder::{ChunkType, Decoder, DecodingResult, Limits};
use tiff::tags::Tag;
use tiff::{TiffError, TiffFormatError};

use crate::crs::{by_name, crs_label, FileCrs, GeoTiffCrs};
use crate::{has_extension, Raster, RasterReader, ReadError, ReadLimits, Source};

mod geokeys;
mod ifd;
mod inflate;

use geokeys::*;
use ifd::*;
use inflate::*;
use patchwork_crs::vertical::VerticalCrs;
use patchwork_crs::Crs;

/// GeoTIFF's marker for a CRS described by parameters instead of a code.
pub(crate) const USER_DEFINED: u16 = 32767;

/// Reads single-band GeoTIFF and COG files (first, full-resolution image only).
pub struct GeoTiffReader;

impl RasterReader for GeoTiffReader {
    fn accepts(&self, path: &Path, head: &[u8]) -> bool {
        is_tiff_signature(head) || has_extension(path, &["tif", "tiff"])
    }

    fn read(&self, src: &mut Source, limits: &ReadLimits) -> Result<Raster, ReadError> {
        read_geotiff_from(src, limits)
    }
}

/// Classic TIFF or BigTIFF, either byte order.
pub fn is_tiff_signature(head: &[u8]) -> bool {
    matches!(
        head.get(..4),
        Some(b"II*\0" | b"MM\0*" | b"II+\0" | b"MM\0+")
    )
}

/// Reads the single band of the first (full-resolution) image of a GeoTIFF or COG.
pub fn read_geotiff(path: &Path, limits: &ReadLimits) -> Result<Raster, ReadError> {
    read_geotiff_from(&mut Source::open(path, limits)?, limits)
}

/// [`read_geotiff`] of an open file.
pub fn read_geotiff_from(file: &mut Source, limits: &ReadLimits) -> Result<Raster, ReadError> {
    let file_len = file.len();
    // The file is read whole so that its chunks can be decoded in parallel, each thread with
    // a decoder of its own over the same bytes. A file that could not be a raster within the
    // limit, even uncompressed with overviews (a third more) and masks, is refused before a
    // byte of it is read.
    if file_len > limits.max_bytes.saturating_mul(2).saturating_add(1 << 20) {
        return Err(ReadError::invalid(format!(
            "the file is {} MiB, more than twice what a raster may have (limits.max_ingest_mb = {})",
            file_len >> 20,
            limits.max_bytes >> 20
        )));
    }
    let mut bytes = Vec::with_capacity(file_len as usize);
    file.read_to_end(&mut bytes)?;
    let file_len = bytes.len() as u64;
    // The decoder is fed untrusted bytes and still has internal asserts; a panic there must
    // become an error for this one file, not take the whole import down.
    match panic::catch_unwind(AssertUnwindSafe(|| decode(&bytes, file_len, limits))) {
        Ok(result) => result,
        Err(payload) => {
            let msg = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown reason".to_string());
            Err(ReadError::invalid(format!(
                "malformed TIFF: the decoder failed on its contents ({msg})"
            )))
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum SampleKind {
    U8,
    U16,
    I16,
    I32,
    F32,
    F64,
}

impl SampleKind {
    fn bytes(self) -> u64 {
        match self {
            SampleKind::U8 => 1,
            SampleKind::U16 | SampleKind::I16 => 2,
            SampleKind::I32 | SampleKind::F32 => 4,
            SampleKind::F64 => 8,
        }
    }
}

fn decode(bytes: &[u8], file_len: u64, limits: &ReadLimits) -> Result<Raster, ReadError> {
    decode_with(bytes, file_len, limits, true)
}

/// [`decode`], with the decoding of deflated float chunks here (`own_inflate`) or left to the
/// TIFF decoder, which the tests hold the former to.
fn decode_with(
    bytes: &[u8],
    file_len: u64,
    limits: &ReadLimits,
    own_inflate: bool,
) -> Result<Raster, ReadError> {
    check_first_ifd(&mut Cursor::new(bytes), file_len)?;
    // Decoder::new loads the first IFD, which in a COG is the full-resolution image; the
    // overviews and masks chained after it are never visited.
    let mut dec = Decoder::new(Cursor::new(bytes)).map_err(tiff_error)?;
    let (width, height) = dec.dimensions().map_err(tiff_error)?;
    limits.check(u64::from(width), u64::from(height))?;
    let (cols, rows) = (width as usize, height as usize);

    let kind = sample_kind(&mut dec)?;
    let (geotransform, crs) = georeference(&mut dec)?;
    let nodata = gdal_nodata(&mut dec)?;
    let acquired = acquired(&mut dec);
    let chunks = chunk_layout_check(&mut dec, file_len)?;
    let expansion = codec_expansion(&mut dec)?;
    limits.check_fillable(
        u64::from(width),
        u64::from(height),
        chunks.present.saturating_mul(expansion) / kind.bytes(),
    )?;
    let inflate = (own_inflate && deflated_float_predictor(&mut dec, kind)?).then_some(bytes);

    // The decoder may then allocate a whole chunk's samples, and read a chunk's compressed
    // bytes, and no more: both have been bounded by what the file holds.
    let largest_chunk = largest_chunk_samples(&dec, cols, rows)? * kind.bytes();
    if largest_chunk > limits.max_bytes {
        return Err(ReadError::invalid(format!(
            "a chunk of the image needs {} MiB, more than the whole raster may have",
            largest_chunk >> 20
        )));
    }
    let mut tiff_limits = Limits::default();
    tiff_limits.decoding_buffer_size = usize::try_from(largest_chunk)
        .unwrap_or(usize::MAX)
        .max(tiff_limits.ifd_value_size);
    tiff_limits.intermediate_buffer_size = usize::try_from(file_len).unwrap_or(usize::MAX);
    let mut dec = dec.with_limits(tiff_limits.clone());
    let open = || {
        Decoder::new(Cursor::new(bytes))
            .map(|d| d.with_limits(tiff_limits.clone()))
            .map_err(tiff_error)
    };
    let samples = read_samples(
        &mut dec, &open, cols, rows, kind, nodata, &chunks, expansion, inflate,
    )?;
    Ok(Raster {
        cols,
        rows,
        samples,
        geotransform,
        crs,
        nodata,
        acquired,
    })
}

fn sample_kind<R: Read + Seek>(dec: &mut Decoder<R>) -> Result<SampleKind, ReadError> {
    let bands: u16 = dec
        .find_tag_unsigned(Tag::SamplesPerPixel)
        .map_err(tiff_error)?
        .unwrap_or(1);
    if bands != 1 {
        // Picking band 1 of a multi-band file would silently import e.g. the red channel of an
        // RGB picture as terrain; an explicit refusal is safer.
        return Err(ReadError::unsupported(format!(
            "the image has {bands} bands (SamplesPerPixel = {bands}); only single-band \
             elevation rasters are supported"
        )));
    }
    let bits: u16 = dec
        .find_tag_unsigned_vec::<u16>(Tag::BitsPerSample)
        .map_err(tiff_error)?
        .and_then(|v| v.first().copied())
        .unwrap_or(1);
    let format: u16 = dec
        .find_tag_unsigned_vec::<u16>(Tag::SampleFormat)
        .map_err(tiff_error)?
        .and_then(|v| v.first().copied())
        .unwrap_or(1);
    Ok(match (format, bits) {
        (1, 8) => SampleKind::U8,
        (1, 16) => SampleKind::U16,
        (2, 16) => SampleKind::I16,
        (2, 32) => SampleKind::I32,
        (3, 32) => SampleKind::F32,
        (3, 64) => SampleKind::F64,
        _ => {
            let name = match format {
                1 => "unsigned integer",
                2 => "signed integer",
                3 => "floating point",
                4 => "untyped",
                5 => "complex integer",
                6 => "complex floating point",
                _ => "unknown-format",
            };
            return Err(ReadError::unsupported(format!(
                "{bits}-bit {name} samples (SampleFormat {format}, BitsPerSample {bits}); \
                 supported sample types are u8, u16, i16, i32, f32 and f64"
            )));
        }
    })
}

/// The image's samples. Chunks are decoded in parallel, a band of chunk rows to a task, each
/// task with a decoder from `open` (the first IFD of the same bytes). With `inflate` (the
/// file's bytes), deflated f32 chunks with the floating-point predictor are decoded here
/// instead: see [`FloatInflater`].
#[allow(clippy::too_many_arguments)]
fn read_samples<'a, R: Read + Seek>(
    dec: &mut Decoder<R>,
    open: &(dyn Fn() -> Result<Decoder<Cursor<&'a [u8]>>, ReadError> + Sync),
    cols: usize,
    rows: usize,
    kind: SampleKind,
    nodata: Option<f64>,
    chunks: &Chunks,
    expansion: u64,
    inflate: Option<&[u8]>,
) -> Result<Vec<f32>, ReadError> {
    let counts = &chunks.counts;
    let chunk_type = dec.get_chunk_type();
    let count = match chunk_type {
        ChunkType::Strip => dec.strip_count(),
        ChunkType::Tile => dec.tile_count(),
    }
    .map_err(tiff_error)?;
    if count as usize != counts.len() {
        return Err(ReadError::invalid(format!(
            "the image needs {count} chunks but the file lists {}",
            counts.len()
        )));
    }
    let (cw, ch) = dec.chunk_dimensions();
    let (cw, ch) = (cw as usize, ch as usize);
    let across = match chunk_type {
        ChunkType::Strip => 1,
        ChunkType::Tile => cols.div_ceil(cw),
    };
    // GDAL fills sparse blocks with the nodata value, or 0 when there is none.
    let sparse_fill = if nodata.is_some() { f32::NAN } else { 0.0 };
    let convert = Converter::new(kind, nodata);

    // Where each chunk goes, and that it lies inside the image, before anything is decoded.
    let mut places = Vec::with_capacity(counts.len());
    for idx in 0..counts.len() {
        let x0 = (idx % across) * cw;
        let y0 = (idx / across).saturating_mul(ch);
        let (dw, dh) = dec.chunk_data_dimensions(idx as u32);
        let (dw, dh) = (dw as usize, dh as usize);
        if x0 + dw > cols || y0.saturating_add(dh) > rows || (dh > ch && ch > 0) {
            return Err(ReadError::invalid(format!(
                "chunk {idx} ({dw} x {dh} at {x0},{y0}) lies outside the {cols} x {rows} image"
            )));
        }
        places.push((x0, y0, dw, dh));
    }
    let mut out = vec![0f32; cols * rows];
    // A band is one row of chunks: `ch` image rows that no other band writes.
    let band_rows = ch.max(1);
    out.par_chunks_mut(cols * band_rows)
        .enumerate()
        .try_for_each(|(band, slab)| -> Result<(), ReadError> {
            let first = band * across;
            let last = (first + across).min(counts.len());
            if first >= last {
                return Ok(());
            }
            let mut dec = None;
            let mut inflater = None;
            for idx in first..last {
                let bytes = counts[idx];
                let (x0, y0, dw, dh) = places[idx];
                let r0 = y0 - band * band_rows;
                let rows_out = slab[r0 * cols..]
                    .chunks_mut(cols)
                    .take(dh)
                    .map(|row| &mut row[x0..x0 + dw]);
                if bytes == 0 {
                    rows_out.for_each(|row| row.fill(sparse_fill));
                    continue;
                }
                // The decoder allocates the whole chunk before it reads a byte of it: the
                // bytes the file holds for it must be able to fill that much.
                let (bw, bh) = match chunk_type {
                    ChunkType::Strip => (dw as u64, dh as u64),
                    ChunkType::Tile => (cw as u64, ch as u64),
                };
                let holds = bytes.saturating_mul(expansion);
                if bw * bh * kind.bytes() > holds {
                    return Err(ReadError::invalid(format!(
                        "chunk {idx} declares {bw} x {bh} samples, more than its bytes can hold"
                    )));
                }
                if let Some(file) = inflate {
                    let start = chunks.offsets[idx] as usize;
                    let data = &file[start..start + bytes as usize];
                    let f = inflater.get_or_insert_with(FloatInflater::new);
                    f.chunk(idx, data, bw as usize, dh, rows_out, |v| convert.float(v))?;
                    continue;
                }
                if dec.is_none() {
                    dec = Some(open()?);
                }
                let d = dec.as_mut().expect("opened");
                let chunk = d.read_chunk(idx as u32).map_err(tiff_error)?;
                convert.place(chunk, dw, dh, rows_out)?;
            }
            Ok(())
        })?;
    Ok(out)
}

/// Turns decoded samples into f32 with nodata and non-finite values as NaN. Nodata is compared
/// in the file's own sample type, as GDAL does (a f32 file's nodata is rounded to f32 first).
struct Converter {
    kind: SampleKind,
    nodata: Option<f64>,
}

impl Converter {
    fn new(kind: SampleKind, nodata: Option<f64>) -> Self {
        Converter { kind, nodata }
    }

    /// An f32 sample as a height: nodata and non-finite values are voids.
    #[inline]
    fn float(&self, v: f32) -> f32 {
        if !v.is_finite() || Some(v) == self.nodata.map(|v| v as f32) {
            f32::NAN
        } else {
            v
        }
    }

    fn int_nodata(&self) -> Option<i64> {
        self.nodata
            .filter(|v| v.is_finite() && v.fract() == 0.0)
            .map(|v| v as i64)
    }

    fn place<'a>(
        &self,
        chunk: DecodingResult,
        dw: usize,
        dh: usize,
        rows: impl Iterator<Item = &'a mut [f32]>,
    ) -> Result<(), ReadError> {
        let nd_int = self.int_nodata();
        let int = |v: i64| {
            if Some(v) == nd_int {
                f32::NAN
            } else {
                v as f32
            }
        };
        let nd64 = self.nodata;
        match (self.kind, chunk) {
            (SampleKind::U8, DecodingResult::U8(src)) => {
                copy(&src, dw, dh, rows, |v| int(v.into()))
            }
            (SampleKind::U16, DecodingResult::U16(src)) => {
                copy(&src, dw, dh, rows, |v| int(v.into()))
            }
            (SampleKind::I16, DecodingResult::I16(src)) => {
                copy(&src, dw, dh, rows, |v| int(v.into()))
            }
            (SampleKind::I32, DecodingResult::I32(src)) => {
                copy(&src, dw, dh, rows, |v| int(v.into()))
            }
            (SampleKind::F32, DecodingResult::F32(src)) => {
                copy(&src, dw, dh, rows, |v| self.float(v))
            }
            (SampleKind::F64, DecodingResult::F64(src)) => copy(&src, dw, dh, rows, |v| {
                let x = v as f32;
                if !x.is_finite() || Some(v) == nd64 {
                    f32::NAN
                } else {
                    x
                }
            }),
            (kind, _) => Err(ReadError::invalid(format!(
                "decoder returned samples of another type than the header's {kind:?}"
            ))),
        }
    }
}

fn copy<'a, T: Copy>(
    src: &[T],
    dw: usize,
    dh: usize,
    rows: impl Iterator<Item = &'a mut [f32]>,
    f: impl Fn(T) -> f32,
) -> Result<(), ReadError> {
    if src.len() < dw * dh {
        return Err(ReadError::invalid(format!(
            "a {dw} x {dh} chunk decoded to only {} samples",
            src.len()
        )));
    }
    for (dst, src_row) in rows.zip(src.chunks_exact(dw)) {
        for (d, &s) in dst.iter_mut().zip(src_row) {
            *d = f(s);
        }
    }
    Ok(())
}

fn tiff_error(e: TiffError) -> ReadError {
    match e {
        TiffError::IoError(io) => io_error(io),
        TiffError::FormatError(
            TiffFormatError::TiffSignatureNotFound | TiffFormatError::TiffSignatureInvalid,
        ) => ReadError::invalid(
            "not a TIFF file: it does not start with the TIFF signature (II*\\0 or MM\\0*)",
        ),
        TiffError::FormatError(f) => ReadError::invalid(format!("malformed TIFF: {f}")),
        TiffError::UnsupportedError(u) => ReadError::unsupported(format!("TIFF feature: {u}")),
        TiffError::LimitsExceeded => ReadError::invalid(
            "malformed TIFF: a tag or data chunk claims an implausibly large size",
        ),
        TiffError::IntSizeError => {
            ReadError::invalid("malformed TIFF: a size field overflows the platform's integers")
        }
        TiffError::UsageError(u) => ReadError::invalid(format!("malformed TIFF layout: {u}")),
    }
}

/// Inside the decoder, I/O errors other than end-of-file come from the decompressors and mean
/// the data is corrupt, which "I/O error" would misdescribe.
fn io_error(e: std::io::Error) -> ReadError {
    use std::io::ErrorKind;
    match e.kind() {
        ErrorKind::InvalidData | ErrorKind::InvalidInput | ErrorKind::Other => {
            ReadError::invalid(format!("corrupt compressed image data: {e}"))
        }
        _ => e.into(),
    }
}

#[cfg(test)]
mod tests;
