//! GeoTIFF and Cloud Optimized GeoTIFF reader built on the pure-Rust `tiff` decoder.

use rayon::prelude::*;
use std::io::{Cursor, Read, Seek};
use std::panic::{self, AssertUnwindSafe};
use std::path::Path;

use tiff::decoder::ifd::Value;
use tiff::decoder::{ChunkType, Decoder, DecodingResult, Limits};
use tiff::tags::Tag;
use tiff::{TiffError, TiffFormatError};

use super::crs::{by_name, crs_label, FileCrs, GeoTiffCrs};
use super::{has_extension, Raster, RasterReader, ReadError, ReadLimits, Source};
use patchwork_crs::vertical::VerticalCrs;
use patchwork_crs::Crs;

const GEO_KEY_MODEL_TYPE: u16 = 1024;
const GEO_KEY_RASTER_TYPE: u16 = 1025;
const GEO_KEY_GEOGRAPHIC_TYPE: u16 = 2048;
const GEO_KEY_PROJECTED_CS_TYPE: u16 = 3072;
const RASTER_PIXEL_IS_POINT: u16 = 2;
const MODEL_TYPE_PROJECTED: u16 = 1;
const MODEL_TYPE_GEOGRAPHIC: u16 = 2;
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

/// Bytes of one value of each TIFF field type; 0 for types the decoder does not know.
fn type_bytes(t: u16) -> u64 {
    match t {
        1 | 2 | 6 | 7 => 1,
        3 | 8 => 2,
        4 | 9 | 11 | 13 => 4,
        5 | 10 | 12 | 16 | 17 | 18 => 8,
        _ => 0,
    }
}

/// Checks that the first IFD and every value it points to lie inside the file. The decoder
/// allocates room for a tag's values before it reads them, so a few bytes that claim a tag
/// of millions of values would otherwise cost that much memory.
fn check_first_ifd<R: Read + Seek>(r: &mut R, file_len: u64) -> Result<(), ReadError> {
    use std::io::SeekFrom;
    let mut head = [0u8; 16];
    r.seek(SeekFrom::Start(0))?;
    let n = r.by_ref().take(16).read(&mut head)?;
    if n < 8 {
        return Err(ReadError::invalid(
            "not a TIFF file: it is shorter than a TIFF header",
        ));
    }
    let big_endian = match &head[..2] {
        b"II" => false,
        b"MM" => true,
        // The decoder names a bad signature itself.
        _ => return Ok(()),
    };
    let u16_at = |b: &[u8]| {
        let a = [b[0], b[1]];
        if big_endian {
            u16::from_be_bytes(a)
        } else {
            u16::from_le_bytes(a)
        }
    };
    let u32_at = |b: &[u8]| {
        let a = [b[0], b[1], b[2], b[3]];
        u64::from(if big_endian {
            u32::from_be_bytes(a)
        } else {
            u32::from_le_bytes(a)
        })
    };
    let u64_at = |b: &[u8]| {
        let a: [u8; 8] = b[..8].try_into().expect("8 bytes");
        if big_endian {
            u64::from_be_bytes(a)
        } else {
            u64::from_le_bytes(a)
        }
    };
    // Data a header points to past the end is what a cut-off download looks like; a hostile
    // header gets the same answer.
    //
    // (bytes of the entry count, of an entry, of a value held in the entry itself)
    let (ifd, count_len, entry_len, inline) = match u16_at(&head[2..]) {
        42 => (u32_at(&head[4..]), 2u64, 12u64, 4u64),
        43 if n >= 16 => (u64_at(&head[8..]), 8, 20, 8),
        _ => return Ok(()),
    };
    if ifd.checked_add(count_len).is_none_or(|end| end > file_len) {
        return Err(ReadError::Truncated);
    }
    r.seek(SeekFrom::Start(ifd))?;
    let mut buf = [0u8; 20];
    r.read_exact(&mut buf[..count_len as usize])?;
    let entries = if count_len == 2 {
        u64::from(u16_at(&buf))
    } else {
        u64_at(&buf)
    };
    let end = entries
        .checked_mul(entry_len)
        .and_then(|b| b.checked_add(ifd + count_len));
    if end.is_none_or(|end| end > file_len) {
        return Err(ReadError::Truncated);
    }
    for _ in 0..entries {
        let e = &mut buf[..entry_len as usize];
        r.read_exact(e)?;
        let ty = u16_at(&e[2..]);
        let (count, offset) = if entry_len == 12 {
            (u32_at(&e[4..]), u32_at(&e[8..]))
        } else {
            (u64_at(&e[4..]), u64_at(&e[12..]))
        };
        let bytes = count.saturating_mul(type_bytes(ty));
        if bytes > inline && offset.checked_add(bytes).is_none_or(|end| end > file_len) {
            return Err(ReadError::Truncated);
        }
    }
    r.seek(SeekFrom::Start(0))?;
    Ok(())
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

/// Geotransform (GDAL convention, PixelIsArea) and CRS from the GeoTIFF tags.
fn georeference<R: Read + Seek>(dec: &mut Decoder<R>) -> Result<([f64; 6], FileCrs), ReadError> {
    let keys = match dec.find_tag(Tag::GeoKeyDirectoryTag).map_err(tiff_error)? {
        Some(v) => v.into_u16_vec().map_err(|_| {
            ReadError::invalid("GeoKeyDirectory tag (34735) does not hold SHORT values")
        })?,
        None => Vec::new(),
    };
    // Parameters stored outside the directory; a bad one only costs the CRS's name.
    let doubles = f64_tag(dec, Tag::GeoDoubleParamsTag, "GeoDoubleParams")
        .ok()
        .flatten()
        .unwrap_or_default();
    let ascii = match dec.find_tag(Tag::GeoAsciiParamsTag) {
        Ok(Some(Value::Ascii(t))) => t,
        _ => String::new(),
    };
    let keys = GeoKeys::parse(&keys, &doubles, &ascii);

    let transform = f64_tag(dec, Tag::ModelTransformationTag, "ModelTransformation")?;
    let scale = f64_tag(dec, Tag::ModelPixelScaleTag, "ModelPixelScale")?;
    let tiepoint = f64_tag(dec, Tag::ModelTiepointTag, "ModelTiepoint")?;

    // Same precedence as GDAL: a pixel scale with a tiepoint wins over a transformation matrix.
    let usable_scale = scale.filter(|s| s.len() >= 2 && s[0] != 0.0 && s[1] != 0.0);
    let mut gt = match (usable_scale, tiepoint, transform) {
        (Some(s), Some(t), _) if t.len() >= 6 => [
            t[3] - t[0] * s[0],
            s[0],
            0.0,
            t[4] + t[1] * s[1],
            0.0,
            -s[1],
        ],
        (_, _, Some(m)) => {
            if m.len() < 16 {
                return Err(ReadError::invalid(format!(
                    "ModelTransformation tag (34264) has {} values instead of 16",
                    m.len()
                )));
            }
            [m[3], m[0], m[1], m[7], m[4], m[5]]
        }
        (None, Some(t), None) if t.len() > 6 => {
            return Err(ReadError::unsupported(format!(
                "the image is georeferenced only by {} ground control points, not by a \
                 regular grid; warp it first (e.g. gdalwarp)",
                t.len() / 6
            )));
        }
        _ => {
            return Err(ReadError::unsupported(
                "the TIFF has no usable georeferencing (neither ModelPixelScale + ModelTiepoint nor \
                 ModelTransformation tags): it is a plain image, not a GeoTIFF",
            ));
        }
    };

    if keys.get(GEO_KEY_RASTER_TYPE) == Some(RASTER_PIXEL_IS_POINT) {
        // The tiepoint names the centre of pixel (0,0); GDAL moves the origin to its corner.
        gt[0] -= 0.5 * (gt[1] + gt[2]);
        gt[3] -= 0.5 * (gt[4] + gt[5]);
    }
    let det = gt[1] * gt[5] - gt[2] * gt[4];
    if gt.iter().any(|v| !v.is_finite()) || det == 0.0 || !det.is_finite() {
        return Err(ReadError::invalid(format!(
            "georeferencing gives a degenerate or non-finite pixel grid: {gt:?}"
        )));
    }
    Ok((gt, keys.crs()))
}

fn f64_tag<R: Read + Seek>(
    dec: &mut Decoder<R>,
    tag: Tag,
    name: &str,
) -> Result<Option<Vec<f64>>, ReadError> {
    let Some(value) = dec.find_tag(tag).map_err(tiff_error)? else {
        return Ok(None);
    };
    // The GeoTIFF spec says DOUBLE, but being lenient about FLOAT or integer writers costs nothing.
    fn scalar(v: Value) -> Option<f64> {
        match v {
            Value::Double(x) => Some(x),
            Value::Float(x) => Some(f64::from(x)),
            other => other.into_i64().ok().map(|x| x as f64),
        }
    }
    let values = match value {
        Value::List(items) => items.into_iter().map(scalar).collect::<Option<Vec<_>>>(),
        single => scalar(single).map(|x| vec![x]),
    };
    values
        .map(Some)
        .ok_or_else(|| ReadError::invalid(format!("{name} tag does not hold numbers")))
}

/// The GeoKeyDirectory: SHORT keys stored inline, and the DOUBLE and ASCII ones stored in
/// their parameter tags.
struct GeoKeys {
    short: Vec<(u16, u16)>,
    double: Vec<(u16, Vec<f64>)>,
    ascii: Vec<(u16, String)>,
}

const GEO_KEY_CITATION: u16 = 1026;
const GEO_KEY_GEOG_CITATION: u16 = 2049;
const GEO_KEY_GEODETIC_DATUM: u16 = 2050;
const GEO_KEY_ELLIPSOID: u16 = 2056;
const GEO_KEY_SEMI_MAJOR: u16 = 2057;
const GEO_KEY_SEMI_MINOR: u16 = 2058;
const GEO_KEY_INV_FLATTENING: u16 = 2059;
const GEO_KEY_TOWGS84: u16 = 2062;
const GEO_KEY_PCS_CITATION: u16 = 3073;
const GEO_KEY_PROJECTION: u16 = 3074;
const GEO_KEY_COORD_TRANS: u16 = 3075;
const GEO_KEY_LINEAR_UNITS: u16 = 3076;
const GEO_KEY_VERTICAL_CS_TYPE: u16 = 4096;

impl GeoKeys {
    fn parse(raw: &[u16], doubles: &[f64], ascii: &str) -> GeoKeys {
        // Header: version, revision, minor revision, key count; then 4 SHORTs per key.
        // A short or inconsistent directory keeps what is complete rather than failing the
        // whole file, since the pixel grid itself does not depend on it.
        let count = raw.get(3).copied().unwrap_or(0) as usize;
        let mut keys = GeoKeys {
            short: Vec::new(),
            double: Vec::new(),
            ascii: Vec::new(),
        };
        for k in raw.get(4..).unwrap_or(&[]).chunks_exact(4).take(count) {
            let (id, loc, n, at) = (k[0], k[1], k[2] as usize, k[3] as usize);
            match loc {
                0 => keys.short.push((id, k[3])),
                34736 => {
                    if let Some(v) = doubles.get(at..at + n).filter(|_| n >= 1) {
                        keys.double.push((id, v.to_vec()));
                    }
                }
                34737 => {
                    if let Some(t) = ascii.get(at..at + n) {
                        let t = t.trim_end_matches(['|', '\0']).trim().to_string();
                        keys.ascii.push((id, t));
                    }
                }
                _ => {}
            }
        }
        keys
    }

    fn get(&self, id: u16) -> Option<u16> {
        self.short.iter().find(|(k, _)| *k == id).map(|(_, v)| *v)
    }

    fn double(&self, id: u16) -> Option<f64> {
        self.doubles(id).map(|v| v[0])
    }

    fn doubles(&self, id: u16) -> Option<Vec<f64>> {
        self.double
            .iter()
            .find(|(k, _)| *k == id)
            .map(|(_, v)| v.clone())
    }

    fn text(&self, id: u16) -> Option<&str> {
        self.ascii
            .iter()
            .find(|(k, _)| *k == id)
            .map(|(_, v)| v.as_str())
            .filter(|t| !t.is_empty())
    }

    fn epsg(&self) -> Option<u32> {
        let code = |id| {
            self.get(id)
                .filter(|&v| v != 0 && v != USER_DEFINED)
                .map(u32::from)
        };
        let projected = code(GEO_KEY_PROJECTED_CS_TYPE);
        let geographic = code(GEO_KEY_GEOGRAPHIC_TYPE);
        // Projected files usually also carry the base geographic CRS; the model type says which
        // one the coordinates are in.
        match self.get(GEO_KEY_MODEL_TYPE) {
            Some(MODEL_TYPE_PROJECTED) => projected,
            Some(MODEL_TYPE_GEOGRAPHIC) => geographic,
            Some(_) => None,
            None => projected.or(geographic),
        }
    }

    /// The CRS the keys describe: an EPSG code; a WKT GDAL wrote into a citation; a
    /// user-defined CRS built from its parameters (GeoTIFF's projection codes and
    /// transformation parameters, through [`GeoTiffCrs`]); or an EPSG CRS a citation names.
    /// What none of those reads is named, from its citation.
    fn crs(&self) -> FileCrs {
        let vertical = self
            .get(GEO_KEY_VERTICAL_CS_TYPE)
            .filter(|&v| v != 0 && v != USER_DEFINED)
            .and_then(|v| VerticalCrs::epsg(u32::from(v)));
        let found = |crs: Crs| FileCrs {
            crs: Some(crs),
            unreadable: None,
            vertical: vertical.clone(),
        };
        if let Some(c) = self.epsg() {
            return match Crs::epsg(c) {
                Ok(crs) => found(crs),
                Err(e) => FileCrs {
                    crs: None,
                    unreadable: Some(e.to_string()),
                    vertical,
                },
            };
        }
        let citation = [
            GEO_KEY_PCS_CITATION,
            GEO_KEY_CITATION,
            GEO_KEY_GEOG_CITATION,
        ]
        .iter()
        .find_map(|&k| self.text(k));
        let model = self.get(GEO_KEY_MODEL_TYPE);
        let projected = model == Some(MODEL_TYPE_PROJECTED)
            || (model.is_none() && self.get(GEO_KEY_PROJECTED_CS_TYPE).is_some());
        if model.is_none() && !projected && self.get(GEO_KEY_GEOGRAPHIC_TYPE).is_none() {
            return FileCrs::default();
        }
        // GDAL writes a whole WKT into the citation when it has nothing better.
        if let Some(w) = citation.and_then(|c| {
            ["PROJCS[", "GEOGCS[", "PROJCRS[", "GEOGCRS[", "COMPD_CS["]
                .iter()
                .filter_map(|k| c.find(k))
                .min()
                .map(|i| &c[i..])
        }) {
            let f = FileCrs::of_text(w);
            if f.crs.is_some() {
                return FileCrs {
                    vertical: f.vertical.or(vertical),
                    ..f
                };
            }
        }
        let param_keys = [
            3078u16, 3079, 3080, 3081, 3082, 3083, 3084, 3085, 3086, 3087, 3088, 3089, 3092, 3095,
        ];
        let user = GeoTiffCrs {
            geographic: self.get(GEO_KEY_GEOGRAPHIC_TYPE),
            datum: self.get(GEO_KEY_GEODETIC_DATUM),
            ellipsoid: self.get(GEO_KEY_ELLIPSOID),
            semi_major: self.double(GEO_KEY_SEMI_MAJOR),
            inv_flattening: self.double(GEO_KEY_INV_FLATTENING),
            semi_minor: self.double(GEO_KEY_SEMI_MINOR),
            towgs84: self
                .doubles(GEO_KEY_TOWGS84)
                .filter(|t| t.len() == 3 || t.len() == 7),
            projection: self.get(GEO_KEY_PROJECTION),
            transform: self.get(GEO_KEY_COORD_TRANS),
            params: param_keys
                .iter()
                .filter_map(|&k| self.double(k).map(|v| (k, v)))
                .collect(),
            linear_units: self.get(GEO_KEY_LINEAR_UNITS),
            name: citation.unwrap_or("user-defined"),
        };
        if let Some(crs) = user.wkt(projected).and_then(|w| Crs::parse(&w).ok()) {
            return found(crs);
        }
        if let Some(crs) = citation.and_then(by_name) {
            return found(crs);
        }
        FileCrs {
            crs: None,
            unreadable: Some(match citation {
                Some(c) => crs_label(c),
                None if projected => "a user-defined projected CRS".into(),
                None => "a user-defined geographic CRS".into(),
            }),
            vertical,
        }
    }
}

fn gdal_nodata<R: Read + Seek>(dec: &mut Decoder<R>) -> Result<Option<f64>, ReadError> {
    let Some(value) = dec.find_tag(Tag::GdalNodata).map_err(tiff_error)? else {
        return Ok(None);
    };
    let Value::Ascii(text) = value else {
        return Err(ReadError::invalid(
            "GDAL_NODATA tag (42113) is not an ASCII string",
        ));
    };
    let text = text.trim_matches(|c: char| c == '\0' || c.is_whitespace());
    if text.is_empty() {
        return Ok(None);
    }
    text.parse::<f64>().map(Some).map_err(|_| {
        ReadError::invalid(format!(
            "GDAL_NODATA tag (42113) holds {text:?}, which is not a number"
        ))
    })
}

/// The most bytes one byte of compressed data can decode to, for each compression the
/// decoder knows; the bound a header's claims are held to before anything is allocated.
/// PackBits turns 2 bytes into 128; an LZW code (9 to 12 bits) expands to at most 4096 bytes;
/// deflate's ratio is at most 1032:1; a zstd RLE block turns 4 bytes into 128 KiB.
fn codec_expansion<R: Read + Seek>(dec: &mut Decoder<R>) -> Result<u64, ReadError> {
    let code: u16 = dec
        .find_tag_unsigned(Tag::Compression)
        .map_err(tiff_error)?
        .unwrap_or(1);
    Ok(match code {
        1 => 1,
        32773 => 64,
        5 => 4096,
        8 | 32946 => 1032,
        // zstd, and codecs the decoder will refuse anyway.
        _ => 32768,
    })
}

/// Checks every chunk lies inside the file, so a cut-off download reports `Truncated` up front
/// instead of a decompressor error halfway through. Returns the bytes each chunk holds (0 for
/// sparse chunks: GDAL's SPARSE_OK writes offset 0 / byte count 0 for blocks that hold only
/// nodata), and the bytes of image data in the file: the union of the chunks, since many
/// chunks may point at the same bytes.
fn chunk_layout_check<R: Read + Seek>(
    dec: &mut Decoder<R>,
    file_len: u64,
) -> Result<Chunks, ReadError> {
    let (offsets_tag, counts_tag) = match dec.get_chunk_type() {
        ChunkType::Strip => (Tag::StripOffsets, Tag::StripByteCounts),
        ChunkType::Tile => (Tag::TileOffsets, Tag::TileByteCounts),
    };
    let offsets = dec
        .find_tag_unsigned_vec::<u64>(offsets_tag)
        .map_err(tiff_error)?
        .unwrap_or_default();
    let counts = dec
        .find_tag_unsigned_vec::<u64>(counts_tag)
        .map_err(tiff_error)?
        .unwrap_or_default();
    if offsets.len() != counts.len() {
        return Err(ReadError::invalid(format!(
            "{} chunk offsets but {} chunk byte counts",
            offsets.len(),
            counts.len()
        )));
    }
    let mut ranges = Vec::with_capacity(offsets.len());
    for (&offset, &count) in offsets.iter().zip(&counts) {
        if count > 0 {
            let end = offset.checked_add(count).filter(|&end| end <= file_len);
            ranges.push((offset, end.ok_or(ReadError::Truncated)?));
        }
    }
    ranges.sort_unstable();
    let (mut present, mut reached) = (0u64, 0u64);
    for (start, end) in ranges {
        present += end.saturating_sub(start.max(reached));
        reached = reached.max(end);
    }
    Ok(Chunks {
        offsets,
        counts,
        present,
    })
}

/// Where a file's chunks lie, each inside the file.
struct Chunks {
    offsets: Vec<u64>,
    /// Bytes of each chunk; 0 for a sparse one.
    counts: Vec<u64>,
    /// Bytes of image data, counted once where chunks share them.
    present: u64,
}

fn largest_chunk_samples<R: Read + Seek>(
    dec: &Decoder<R>,
    cols: usize,
    rows: usize,
) -> Result<u64, ReadError> {
    let (cw, ch) = dec.chunk_dimensions();
    let (cw, ch) = (u64::from(cw), u64::from(ch));
    match dec.get_chunk_type() {
        ChunkType::Strip => Ok(cols as u64 * ch.min(rows as u64)),
        ChunkType::Tile => {
            // Tiles wider than the image are legal, but a tile many times the image's size
            // is a corrupt or hostile header. The decoder fills whole tiles, padding included.
            let most = (cols as u64).max(4096) * (rows as u64).max(4096);
            if cw.checked_mul(ch).is_none_or(|n| n > most) {
                return Err(ReadError::invalid(format!(
                    "implausible tile size {cw} x {ch}"
                )));
            }
            Ok(cw * ch)
        }
    }
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

/// Whether the image is f32 samples, deflated, with the floating-point predictor: how
/// Copernicus and most float COGs are written, and the one layout decoded here rather than
/// by the TIFF decoder. Its predictor undoes each row through a fresh copy of the row, byte by
/// byte with a bounds check on each; on a 3600² tile that was a tenth of the CPU time of a
/// whole ingest.
fn deflated_float_predictor<R: Read + Seek>(
    dec: &mut Decoder<R>,
    kind: SampleKind,
) -> Result<bool, ReadError> {
    let tag = |dec: &mut Decoder<R>, t: Tag| -> Result<Option<u16>, ReadError> {
        dec.find_tag_unsigned(t).map_err(tiff_error)
    };
    Ok(kind == SampleKind::F32
        && matches!(tag(dec, Tag::Compression)?, Some(8 | 32946))
        && tag(dec, Tag::Predictor)? == Some(3))
}

/// Decodes deflated f32 chunks written with the floating-point predictor (TIFF Technical Note
/// 3): each row of a chunk is the bytes of its samples split into four planes, most
/// significant first whatever the file's byte order, then differenced byte by byte along the
/// row. Buffers are kept from one chunk to the next.
struct FloatInflater {
    inflater: flate2::Decompress,
    inflated: Vec<u8>,
}

impl FloatInflater {
    fn new() -> Self {
        FloatInflater {
            inflater: flate2::Decompress::new(true),
            inflated: Vec::new(),
        }
    }

    /// Decodes chunk `idx` of `width` samples a row (the padding of edge tiles included) and
    /// places its first `dh` rows through `height` into `rows`, as many samples of each as
    /// the row given for it holds.
    #[allow(clippy::too_many_arguments)]
    fn chunk<'a>(
        &mut self,
        idx: usize,
        data: &[u8],
        width: usize,
        dh: usize,
        rows: impl Iterator<Item = &'a mut [f32]>,
        height: impl Fn(f32) -> f32,
    ) -> Result<(), ReadError> {
        let need = width * 4 * dh;
        self.inflated.clear();
        self.inflated.resize(need, 0);
        // TIFF deflate is a zlib stream. A chunk may hold more rows than the image has left
        // (the padding rows of a bottom tile), which are never needed: decoding stops at
        // `need` bytes.
        let z = &mut self.inflater;
        z.reset(true);
        let status = z.decompress(data, &mut self.inflated, flate2::FlushDecompress::Finish);
        let corrupt = |why: String| {
            ReadError::invalid(format!("corrupt compressed image data: chunk {idx} {why}"))
        };
        match status {
            Ok(_) if z.total_out() as usize == need => {}
            Ok(_) => {
                return Err(corrupt(format!(
                    "decodes to {} of its {need} bytes",
                    z.total_out()
                )))
            }
            Err(e) => return Err(corrupt(e.to_string())),
        }
        for (dst, row) in rows.zip(self.inflated.chunks_exact_mut(width * 4)) {
            let mut acc = 0u8;
            for b in row.iter_mut() {
                acc = acc.wrapping_add(*b);
                *b = acc;
            }
            let (p0, rest) = row.split_at(width);
            let (p1, rest) = rest.split_at(width);
            let (p2, p3) = rest.split_at(width);
            for (i, d) in dst.iter_mut().enumerate() {
                *d = height(f32::from_bits(u32::from_be_bytes([
                    p0[i], p1[i], p2[i], p3[i],
                ])));
            }
        }
        Ok(())
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
mod tests {
    use super::*;
    use crate::test_support::{assert_close, assert_gt_close, data_file};
    use crate::write_tiff::{write_geotiff_f32, write_geotiff_i16};
    use std::path::PathBuf;

    const ARCSEC: f64 = 1.0 / 3600.0;

    fn read(path: &Path) -> Result<Raster, ReadError> {
        read_geotiff(path, &ReadLimits::default())
    }

    fn real(name: &str) -> Raster {
        read(&data_file(name)).unwrap_or_else(|e| panic!("reading {name}: {e}"))
    }

    // The files below are crops of real surveys that GDAL wrote in the encoding of the file
    // each was cut from (tests/data/make_fixtures.py, which printed the figures asserted here).

    /// Cut at column 0, row 1650 of the N34 W119 cell, whose tiepoint is on whole degrees.
    fn n34w119_crop_geotransform() -> [f64; 6] {
        // PixelIsPoint: GDAL reports the half-pixel shift.
        [
            -119.0 - 0.5 * ARCSEC,
            ARCSEC,
            0.0,
            35.0 + 0.5 * ARCSEC - 1650.0 * ARCSEC,
            0.0,
            -ARCSEC,
        ]
    }

    #[test]
    fn copernicus_cog_tiled_deflate_float_predictor() {
        let r = real("copernicus_cog.tif");
        assert_eq!((r.cols, r.rows), (300, 300));
        assert_eq!(r.crs.epsg(), Some(4326));
        assert_eq!(r.nodata, None);
        assert_gt_close(r.geotransform, n34w119_crop_geotransform(), 1e-12);
        assert_close(r.geotransform[0], -119.000138889, 1e-9, "origin x");
        assert_close(r.geotransform[3], 34.541805556, 1e-9, "origin y");
        assert_eq!(r.nodata_count(), 0);
        let (min, max) = min_max(&r.samples);
        assert_close(min as f64, 190.89943, 1e-4, "min");
        assert_close(max as f64, 1910.6836, 1e-4, "max");
    }

    #[test]
    fn copernicus_tiles_line_up_with_nasadem() {
        // Two independent surveys of the same ground: if any of the 128² tiles were decoded
        // into the wrong place, that tile's typical difference would be hundreds of metres
        // instead of ~0.
        let cop = real("copernicus_cog.tif");
        let nasa = real("nasadem_strips.tif");
        for ty in 0..3 {
            for tx in 0..3 {
                let mut diffs = Vec::new();
                for row in ty * 128..((ty + 1) * 128).min(300) {
                    for col in tx * 128..((tx + 1) * 128).min(300) {
                        let d = cop.get(col, row) - nasa.get(col, row);
                        if d.is_finite() {
                            diffs.push(d.abs());
                        }
                    }
                }
                let mid = diffs.len() / 2;
                let median = *diffs.select_nth_unstable_by(mid, f32::total_cmp).1;
                assert!(median < 5.0, "tile ({tx},{ty}) median |diff| {median} m");
            }
        }
    }

    #[test]
    fn nasadem_i16_pixel_is_point() {
        let r = real("nasadem_strips.tif");
        assert_eq!((r.cols, r.rows), (300, 300));
        assert_eq!(r.crs.epsg(), Some(4326));
        assert_eq!(r.nodata, Some(-32768.0));
        assert_gt_close(r.geotransform, n34w119_crop_geotransform(), 1e-12);
        assert_eq!(r.nodata_count(), 0, "NASADEM is void-filled");
    }

    #[test]
    fn srtm_utm_projected_epsg_and_voids() {
        let r = real("srtm_utm.tif");
        assert_eq!((r.cols, r.rows), (200, 240));
        assert_eq!(r.crs.epsg(), Some(32631));
        assert_eq!(r.nodata, Some(-32768.0));
        assert_eq!(r.nodata_count(), 3456);
        // PixelIsPoint, 90 m, cut 300 columns in.
        assert_gt_close(
            r.geotransform,
            [
                657641.6582899829 - 45.0 + 300.0 * 90.0,
                90.0,
                0.0,
                4987332.008210683 + 45.0,
                0.0,
                -90.0,
            ],
            1e-6,
        );
    }

    #[test]
    fn philondenx_nodata_zero_and_nan() {
        let r = real("philondenx_zero_nan.tif");
        assert_eq!((r.cols, r.rows), (512, 64));
        assert_eq!(r.crs.epsg(), Some(32630));
        assert_eq!(r.nodata, Some(0.0));
        // 10,124 samples equal to the declared nodata 0 plus one NaN.
        assert_eq!(r.nodata_count(), 10_125);
        assert!(r.get(8, 6).is_nan());
        assert_gt_close(
            r.geotransform,
            [708157.0, 1.0, 0.0, 4827432.0, 0.0, -1.0],
            1e-9,
        );
    }

    #[test]
    fn rhine_deflate_strips_nodata() {
        let r = real("rhine_deflate_strips.tif");
        assert_eq!((r.cols, r.rows), (200, 150));
        assert_eq!(r.crs.epsg(), Some(4326));
        assert_eq!(r.nodata, Some(-9999.0));
        // Part of the rectangle lies outside the basin.
        assert_eq!(r.nodata_count(), 5321);
        assert_gt_close(
            r.geotransform,
            [
                8.566666666495166,
                0.008333333333325754,
                0.0,
                49.50833333330509,
                0.0,
                -0.008333333333339965,
            ],
            1e-9,
        );
    }

    #[test]
    fn lidar_uncompressed_tiles_with_padding() {
        // 200 x 200 in 128 x 128 tiles: the last tile column and row are partly padding.
        let r = real("lidar_tiles_padded.tif");
        assert_eq!((r.cols, r.rows), (200, 200));
        assert_eq!(r.crs.epsg(), Some(26915));
        assert_eq!(r.nodata_count(), 0);
        let (min, max) = min_max(&r.samples);
        assert_close(min as f64, 379.65933, 1e-4, "min");
        assert_close(max as f64, 402.0443, 1e-4, "max");
        // Neighbours across the tile seam at column 128 must be as smooth as inside a tile.
        let seam = (0..200)
            .map(|row| (r.get(128, row) - r.get(127, row)).abs())
            .fold(0f32, f32::max);
        assert!(seam < 1.0, "tile seam jump {seam}");
    }

    #[test]
    fn big_hole_file_has_its_declared_nodata() {
        let r = real("srtm_big_hole.tif");
        assert_eq!((r.cols, r.rows), (200, 200));
        assert_eq!(r.crs.epsg(), Some(4326));
        // The file really declares -32678 (sic), and its holes hold that value.
        assert_eq!(r.nodata, Some(-32678.0));
        assert_eq!(r.nodata_count(), 30_368);
    }

    fn min_max(v: &[f32]) -> (f32, f32) {
        v.iter()
            .filter(|x| x.is_finite())
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &x| {
                (lo.min(x), hi.max(x))
            })
    }

    // ---- hand-built TIFFs -------------------------------------------------------------------

    enum Val {
        Short(Vec<u16>),
        Long(Vec<u32>),
        Double(Vec<f64>),
        Ascii(&'static str),
    }

    /// Builds a little-endian classic TIFF holding `chunks` as strips (or tiles when the tags
    /// say so); offset/byte-count tags are added here. Lets tests produce layouts, compressions
    /// and broken headers that the `tiff` encoder cannot write.
    fn build_tiff(tags: Vec<(u16, Val)>, chunks: &[Vec<u8>], tiled: bool) -> Vec<u8> {
        let mut out = b"II*\0\0\0\0\0".to_vec();
        let mut offsets = Vec::new();
        for c in chunks {
            offsets.push(out.len() as u32);
            out.extend_from_slice(c);
        }
        let (off_tag, cnt_tag) = if tiled { (324, 325) } else { (273, 279) };
        let mut tags = tags;
        if !chunks.is_empty() {
            tags.push((off_tag, Val::Long(offsets)));
            tags.push((
                cnt_tag,
                Val::Long(chunks.iter().map(|c| c.len() as u32).collect()),
            ));
        }
        tags.sort_by_key(|t| t.0);
        let encoded: Vec<(u16, u16, u32, Vec<u8>)> = tags
            .into_iter()
            .map(|(tag, v)| match v {
                Val::Short(x) => (
                    tag,
                    3,
                    x.len() as u32,
                    x.iter().flat_map(|s| s.to_le_bytes()).collect(),
                ),
                Val::Long(x) => (
                    tag,
                    4,
                    x.len() as u32,
                    x.iter().flat_map(|s| s.to_le_bytes()).collect(),
                ),
                Val::Double(x) => (
                    tag,
                    12,
                    x.len() as u32,
                    x.iter().flat_map(|s| s.to_le_bytes()).collect(),
                ),
                Val::Ascii(s) => {
                    let mut b = s.as_bytes().to_vec();
                    b.push(0);
                    (tag, 2, b.len() as u32, b)
                }
            })
            .collect();
        let mut value_at = Vec::new();
        for (_, _, _, bytes) in &encoded {
            if bytes.len() > 4 {
                if out.len() % 2 == 1 {
                    out.push(0);
                }
                value_at.push(out.len() as u32);
                out.extend_from_slice(bytes);
            } else {
                value_at.push(0);
            }
        }
        if out.len() % 2 == 1 {
            out.push(0);
        }
        let ifd = out.len() as u32;
        out[4..8].copy_from_slice(&ifd.to_le_bytes());
        out.extend_from_slice(&(encoded.len() as u16).to_le_bytes());
        for ((tag, ty, count, bytes), at) in encoded.iter().zip(value_at) {
            out.extend_from_slice(&tag.to_le_bytes());
            out.extend_from_slice(&ty.to_le_bytes());
            out.extend_from_slice(&count.to_le_bytes());
            if bytes.len() > 4 {
                out.extend_from_slice(&at.to_le_bytes());
            } else {
                let mut inline = [0u8; 4];
                inline[..bytes.len()].copy_from_slice(bytes);
                out.extend_from_slice(&inline);
            }
        }
        out.extend_from_slice(&0u32.to_le_bytes());
        out
    }

    fn geo_tags(origin: (f64, f64), step: f64, epsg: u16) -> Vec<(u16, Val)> {
        vec![
            (33550, Val::Double(vec![step, step, 0.0])),
            (
                33922,
                Val::Double(vec![0.0, 0.0, 0.0, origin.0, origin.1, 0.0]),
            ),
            (
                34735,
                Val::Short(vec![
                    1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, epsg,
                ]),
            ),
        ]
    }

    fn image_tags(w: u32, h: u32, bits: u16, format: u16) -> Vec<(u16, Val)> {
        vec![
            (256, Val::Long(vec![w])),
            (257, Val::Long(vec![h])),
            (258, Val::Short(vec![bits])),
            (262, Val::Short(vec![1])),
            (277, Val::Short(vec![1])),
            (339, Val::Short(vec![format])),
        ]
    }

    /// A zstd frame made of raw (stored) blocks: valid zstd without needing a compressor.
    fn zstd_stored(data: &[u8]) -> Vec<u8> {
        let mut out = vec![0x28, 0xB5, 0x2F, 0xFD];
        // Frame header: single segment, 4-byte content size, no checksum, no dictionary.
        out.push(0b1010_0000);
        out.extend_from_slice(&(data.len() as u32).to_le_bytes());
        let blocks: Vec<&[u8]> = data.chunks(100_000).collect();
        for (i, b) in blocks.iter().enumerate() {
            let last = u32::from(i + 1 == blocks.len());
            let header = ((b.len() as u32) << 3) | last;
            out.extend_from_slice(&header.to_le_bytes()[..3]);
            out.extend_from_slice(b);
        }
        out
    }

    /// TIFF floating-point predictor (3) for one row of f32 samples: byte planes, MSB first,
    /// then byte-wise horizontal differencing.
    fn float_predict_row(row: &[f32]) -> Vec<u8> {
        let n = row.len();
        let mut planes = vec![0u8; n * 4];
        for (i, v) in row.iter().enumerate() {
            for (b, byte) in v.to_be_bytes().iter().enumerate() {
                planes[b * n + i] = *byte;
            }
        }
        for i in (1..planes.len()).rev() {
            planes[i] = planes[i].wrapping_sub(planes[i - 1]);
        }
        planes
    }

    fn write_temp(dir: &tempfile::TempDir, name: &str, bytes: &[u8]) -> PathBuf {
        let p = dir.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }

    #[test]
    fn tiled_zstd_float_predictor_with_padding_and_sparse_tile() {
        // 20 x 18 image in 16 x 16 tiles: 2 x 2 tiles, right and bottom ones padded.
        let (w, h, t) = (20usize, 18usize, 16usize);
        let value = |c: usize, r: usize| (r * 100 + c) as f32 + 0.25;
        let mut tiles = Vec::new();
        for ty in 0..2 {
            for tx in 0..2 {
                if (tx, ty) == (1, 1) {
                    tiles.push(Vec::new()); // sparse: offset/bytes 0
                    continue;
                }
                let mut raw = Vec::new();
                for r in 0..t {
                    let row: Vec<f32> = (0..t).map(|c| value(tx * t + c, ty * t + r)).collect();
                    raw.extend(float_predict_row(&row));
                }
                tiles.push(zstd_stored(&raw));
            }
        }
        let mut tags = image_tags(w as u32, h as u32, 32, 3);
        tags.extend(geo_tags((500000.0, 4000000.0), 2.0, 32631));
        tags.extend([
            (259, Val::Short(vec![50000])),
            (317, Val::Short(vec![3])),
            (322, Val::Long(vec![t as u32])),
            (323, Val::Long(vec![t as u32])),
            (42113, Val::Ascii("-9999")),
        ]);
        let mut bytes = build_tiff(tags, &tiles, true);
        // build_tiff gave the sparse tile a real offset; GDAL writes 0 for both.
        let pos = find_sparse_offset(&bytes, &tiles);
        bytes[pos..pos + 4].copy_from_slice(&0u32.to_le_bytes());

        let dir = tempfile::tempdir().unwrap();
        let r = read(&write_temp(&dir, "zstd.tif", &bytes)).unwrap();
        assert_eq!((r.cols, r.rows, r.crs.epsg()), (20, 18, Some(32631)));
        assert_eq!(r.geotransform, [500000.0, 2.0, 0.0, 4000000.0, 0.0, -2.0]);
        for row in 0..h {
            for col in 0..w {
                let got = r.get(col, row);
                if col >= t && row >= t {
                    assert!(got.is_nan(), "sparse tile sample ({col},{row}) = {got}");
                } else {
                    assert_eq!(got, value(col, row), "sample ({col},{row})");
                }
            }
        }
    }

    #[test]
    fn deflated_float_predictor_chunks_decode_as_the_tiff_decoder_does() {
        use std::io::Write;
        // Real heights (the Copernicus crop) with a void, infinities and the nodata value
        // written in, as deflated chunks with the floating-point predictor: 16² tiles with
        // padding on the right and bottom, a sparse tile, and strips of 7 rows.
        let crop = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/data/copernicus_n34w119_crop.tif");
        let real = read(&crop).unwrap();
        let (w, h) = (45usize, 37usize);
        let value = |c: usize, r: usize| match (c, r) {
            (3, 4) => f32::NAN,
            (10, 2) => f32::INFINITY,
            (11, 30) => f32::NEG_INFINITY,
            (20, 20) => -9999.0,
            _ => real.get(c * 5, r * 7),
        };
        let zlib = |raw: &[u8]| {
            let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
            z.write_all(raw).unwrap();
            z.finish().unwrap()
        };
        let t = 16usize;
        let mut tiles = Vec::new();
        for ty in 0..h.div_ceil(t) {
            for tx in 0..w.div_ceil(t) {
                if (tx, ty) == (2, 0) {
                    tiles.push(Vec::new());
                    continue;
                }
                let mut raw = Vec::new();
                for r in 0..t {
                    let row: Vec<f32> = (0..t)
                        .map(|c| {
                            let (c, r) = (tx * t + c, ty * t + r);
                            if c < w && r < h {
                                value(c, r)
                            } else {
                                1.5
                            }
                        })
                        .collect();
                    raw.extend(float_predict_row(&row));
                }
                tiles.push(zlib(&raw));
            }
        }
        let strip_rows = 7usize;
        let strips: Vec<Vec<u8>> = (0..h.div_ceil(strip_rows))
            .map(|s| {
                let mut raw = Vec::new();
                for r in s * strip_rows..((s + 1) * strip_rows).min(h) {
                    let row: Vec<f32> = (0..w).map(|c| value(c, r)).collect();
                    raw.extend(float_predict_row(&row));
                }
                zlib(&raw)
            })
            .collect();
        let tags = |layout: Vec<(u16, Val)>| {
            let mut tags = image_tags(w as u32, h as u32, 32, 3);
            tags.extend(geo_tags((500000.0, 4000000.0), 30.0, 32611));
            tags.extend([
                (259, Val::Short(vec![8])),
                (317, Val::Short(vec![3])),
                (42113, Val::Ascii("-9999")),
            ]);
            tags.extend(layout);
            tags
        };
        let mut tiled = build_tiff(
            tags(vec![
                (322, Val::Long(vec![t as u32])),
                (323, Val::Long(vec![t as u32])),
            ]),
            &tiles,
            true,
        );
        let pos = find_sparse_offset_at(&tiled, 2);
        tiled[pos..pos + 4].copy_from_slice(&0u32.to_le_bytes());
        let stripped = build_tiff(
            tags(vec![(278, Val::Long(vec![strip_rows as u32]))]),
            &strips,
            false,
        );
        for bytes in [tiled, stripped] {
            let n = bytes.len() as u64;
            let ours = decode_with(&bytes, n, &ReadLimits::default(), true).unwrap();
            let theirs = decode_with(&bytes, n, &ReadLimits::default(), false).unwrap();
            let bits = |r: &Raster| r.samples.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&ours), bits(&theirs));
            assert_eq!(ours.get(0, 0), value(0, 0));
            assert_eq!(ours.get(44, 36), value(44, 36));
            for (c, r) in [(3, 4), (10, 2), (11, 30), (20, 20)] {
                assert!(ours.get(c, r).is_nan(), "({c},{r}) is a void");
            }
        }
        // A chunk that inflates to less than its rows is corrupt, and says which chunk.
        let mut short = tiles.clone();
        short[0] = zlib(&[0u8; 100]);
        let bytes = build_tiff(
            tags(vec![
                (322, Val::Long(vec![t as u32])),
                (323, Val::Long(vec![t as u32])),
            ]),
            &short,
            true,
        );
        let e = decode_with(&bytes, bytes.len() as u64, &ReadLimits::default(), true)
            .unwrap_err()
            .to_string();
        assert!(e.contains("corrupt") && e.contains("chunk 0"), "{e}");
    }

    /// Position of the last TileOffsets entry, which belongs to the sparse tile in the test above.
    fn find_sparse_offset(bytes: &[u8], tiles: &[Vec<u8>]) -> usize {
        find_sparse_offset_at(bytes, tiles.len() - 1)
    }

    /// Position of TileOffsets entry `k`.
    fn find_sparse_offset_at(bytes: &[u8], k: usize) -> usize {
        let ifd = u32::from_le_bytes(bytes[4..8].try_into().unwrap()) as usize;
        let n = u16::from_le_bytes(bytes[ifd..ifd + 2].try_into().unwrap()) as usize;
        for i in 0..n {
            let e = ifd + 2 + i * 12;
            if u16::from_le_bytes(bytes[e..e + 2].try_into().unwrap()) == 324 {
                let at = u32::from_le_bytes(bytes[e + 8..e + 12].try_into().unwrap()) as usize;
                return at + 4 * k;
            }
        }
        panic!("no TileOffsets");
    }

    #[test]
    fn zstd_horizontal_predictor_i16_strips_pixel_is_point_transform() {
        let (w, h) = (5usize, 3usize);
        let values: Vec<i16> = (0..(w * h) as i16).map(|i| i * 37 - 200).collect();
        let mut strips = Vec::new();
        for row in values.chunks(w) {
            let mut raw = Vec::new();
            let mut prev = 0i16;
            for &v in row {
                raw.extend_from_slice(&v.wrapping_sub(prev).to_le_bytes());
                prev = v;
            }
            strips.push(zstd_stored(&raw));
        }
        let mut tags = image_tags(w as u32, h as u32, 16, 2);
        tags.extend([
            (259, Val::Short(vec![50000])),
            (278, Val::Long(vec![1])),
            (317, Val::Short(vec![2])),
            // Rotated ModelTransformation, PixelIsPoint, geographic.
            (
                34264,
                Val::Double(vec![
                    0.5, 0.1, 0.0, 10.0, //
                    0.2, -0.5, 0.0, 50.0, //
                    0.0, 0.0, 0.0, 0.0, //
                    0.0, 0.0, 0.0, 1.0,
                ]),
            ),
            (
                34735,
                Val::Short(vec![
                    1, 1, 0, 3, 1024, 0, 1, 2, 1025, 0, 1, 2, 2048, 0, 1, 4326,
                ]),
            ),
        ]);
        let dir = tempfile::tempdir().unwrap();
        let r = read(&write_temp(
            &dir,
            "pred2.tif",
            &build_tiff(tags, &strips, false),
        ))
        .unwrap();
        let expect: Vec<f32> = values.iter().map(|&v| f32::from(v)).collect();
        assert_eq!(r.samples, expect);
        assert_eq!(r.crs.epsg(), Some(4326));
        // GDAL: origin -= half a pixel along both pixel axes.
        assert_gt_close(
            r.geotransform,
            [
                10.0 - 0.5 * (0.5 + 0.1),
                0.5,
                0.1,
                50.0 - 0.5 * (0.2 - 0.5),
                0.2,
                -0.5,
            ],
            1e-12,
        );
    }

    #[test]
    fn encoder_compressions_round_trip() {
        use tiff::encoder::{colortype, Compression, DeflateLevel, TiffEncoder};
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (33u32, 21u32);
        let data: Vec<f32> = (0..w * h).map(|i| (i as f32).sin() * 1000.0).collect();
        for (name, comp) in [
            ("none", Compression::Uncompressed),
            ("lzw", Compression::Lzw),
            ("packbits", Compression::Packbits),
            ("deflate", Compression::Deflate(DeflateLevel::Best)),
        ] {
            let path = dir.path().join(format!("{name}.tif"));
            let file = std::fs::File::create(&path).unwrap();
            let mut enc = TiffEncoder::new(file).unwrap().with_compression(comp);
            let mut img = enc.new_image::<colortype::Gray32Float>(w, h).unwrap();
            img.rows_per_strip(4).unwrap();
            img.encoder()
                .write_tag(Tag::ModelPixelScaleTag, &[1.0f64, 1.0, 0.0][..])
                .unwrap();
            img.encoder()
                .write_tag(
                    Tag::ModelTiepointTag,
                    &[0.0f64, 0.0, 0.0, 0.0, 21.0, 0.0][..],
                )
                .unwrap();
            img.write_data(&data).unwrap();
            let r = read(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(r.samples, data, "{name}");
            assert_eq!(r.crs.epsg(), None, "{name}");
        }
    }

    // ---- bad input --------------------------------------------------------------------------

    fn expect_err(path: &Path) -> ReadError {
        match read(path) {
            Ok(r) => panic!("{} read without error: {r:?}", path.display()),
            Err(e) => {
                let msg = e.to_string();
                assert!(msg.len() > 20, "unhelpful message {msg:?}");
                e
            }
        }
    }

    #[test]
    fn empty_file_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let e = expect_err(&write_temp(&dir, "empty.tif", b""));
        assert!(e.to_string().contains("empty"), "{e}");
    }

    #[test]
    fn garbage_named_tif_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let garbage: Vec<u8> = (0..4096u32)
            .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
            .collect();
        let e = expect_err(&write_temp(&dir, "garbage.tif", &garbage));
        assert!(e.to_string().contains("not a TIFF"), "{e}");
        let e = expect_err(&write_temp(&dir, "short.tif", b"II*"));
        assert!(
            matches!(e, ReadError::Truncated | ReadError::Invalid { .. }),
            "{e}"
        );
    }

    #[test]
    fn directory_named_tif_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let sub = dir.path().join("x.tif");
        std::fs::create_dir(&sub).unwrap();
        let e = expect_err(&sub);
        assert!(e.to_string().contains("directory"), "{e}");
    }

    #[test]
    fn truncated_real_files_report_truncation() {
        let dir = tempfile::tempdir().unwrap();
        for name in [
            "copernicus_cog.tif",
            "nasadem_strips.tif",
            "rhine_deflate_strips.tif",
        ] {
            let bytes = std::fs::read(data_file(name)).unwrap();
            let cut = write_temp(&dir, name, &bytes[..bytes.len() / 2]);
            let e = expect_err(&cut);
            assert!(matches!(e, ReadError::Truncated), "{name}: {e}");
            assert!(e.to_string().contains("truncated"), "{e}");
        }
        // Cut inside the header itself.
        let bytes = std::fs::read(data_file("rhine_deflate_strips.tif")).unwrap();
        expect_err(&write_temp(&dir, "head.tif", &bytes[..100]));
    }

    #[test]
    fn user_defined_utm_projections_get_their_epsg_code_or_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let tiff = |name: &str, keys: Vec<u16>, doubles: Vec<f64>, ascii: &'static str| {
            let mut tags = image_tags(2, 2, 32, 3);
            tags.push((278, Val::Long(vec![2])));
            tags.push((33550, Val::Double(vec![30.0, 30.0, 0.0])));
            tags.push((
                33922,
                Val::Double(vec![0.0, 0.0, 0.0, 500_000.0, 4_000_000.0, 0.0]),
            ));
            let mut dir_keys = vec![1, 1, 0, (keys.len() / 4) as u16];
            dir_keys.extend(keys);
            tags.push((34735, Val::Short(dir_keys)));
            if !doubles.is_empty() {
                tags.push((34736, Val::Double(doubles)));
            }
            if !ascii.is_empty() {
                tags.push((34737, Val::Ascii(ascii)));
            }
            let strip: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0]
                .iter()
                .flat_map(|v| v.to_le_bytes())
                .collect();
            read(&write_temp(&dir, name, &build_tiff(tags, &[strip], false))).unwrap()
        };
        // ProjectedCSType user-defined, ProjectionGeoKey = UTM zone 31 north, on WGS 84.
        let r = tiff(
            "code.tif",
            vec![
                1024, 0, 1, 1, 2048, 0, 1, 4326, 3072, 0, 1, 32767, 3074, 0, 1, 16031,
            ],
            vec![],
            "",
        );
        assert_eq!((r.crs.epsg(), r.crs.unreadable), (Some(32631), None));
        // Transverse Mercator given by its parameters: UTM 31N.
        let r = tiff(
            "params.tif",
            vec![
                1024, 0, 1, 1, 2048, 0, 1, 4326, 3072, 0, 1, 32767, 3075, 0, 1, 1, 3080, 34736, 1,
                0, 3081, 34736, 1, 1, 3082, 34736, 1, 2, 3083, 34736, 1, 3, 3092, 34736, 1, 4,
            ],
            vec![3.0, 0.0, 500_000.0, 0.0, 0.9996],
            "",
        );
        assert_eq!(r.crs.epsg(), Some(32631));
        // Only a citation, as GDAL writes for a WKT it cannot encode: UTM 33S on WGS 84.
        let r = tiff(
            "cited.tif",
            vec![1024, 0, 1, 1, 1026, 34737, 22, 0, 3072, 0, 1, 32767],
            vec![],
            "WGS 84 / UTM zone 33S|",
        );
        assert_eq!(r.crs.epsg(), Some(32733));
        // A projection we do not know is named, not reported as missing.
        let r = tiff(
            "lambert.tif",
            vec![
                1024, 0, 1, 1, 1026, 34737, 19, 0, 3072, 0, 1, 32767, 3075, 0, 1, 8,
            ],
            vec![],
            "RGF93 / Lambert-93|",
        );
        assert_eq!(r.crs.epsg(), None);
        assert_eq!(r.crs.unreadable.as_deref(), Some("RGF93 / Lambert-93"));
    }

    #[test]
    fn huge_header_is_refused_before_allocating() {
        let dir = tempfile::tempdir().unwrap();
        let mut tags = image_tags(1_000_000, 1_000_000, 32, 3);
        tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
        tags.push((278, Val::Long(vec![1_000_000])));
        // One strip whose data is missing entirely.
        let bytes = build_tiff(tags, &[vec![0u8; 16]], false);
        let e = expect_err(&write_temp(&dir, "huge.tif", &bytes));
        assert!(
            matches!(
                e,
                ReadError::TooLarge {
                    cols: 1_000_000,
                    rows: 1_000_000,
                    ..
                }
            ),
            "{e}"
        );

        // The same claim with no strip or tile tags at all.
        let bytes = build_tiff(image_tags(1_000_000, 1_000_000, 32, 3), &[], false);
        let e = expect_err(&write_temp(&dir, "huge_nodata.tif", &bytes));
        assert!(matches!(e, ReadError::Invalid { .. }), "{e}");

        // Tighter caller limits apply too.
        let small = write_temp(&dir, "small.tif", &small_geotiff_bytes(&dir));
        let e = read_geotiff(
            &small,
            &ReadLimits {
                max_bytes: 40,
                roots: None,
            },
        )
        .unwrap_err();
        assert!(matches!(e, ReadError::TooLarge { .. }), "{e}");
    }

    #[test]
    fn a_few_bytes_claiming_a_huge_raster_are_refused_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let raster = |w: u32, compression: u16| {
            let mut tags = image_tags(w, w, 32, 3);
            tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
            tags.push((259, Val::Short(vec![compression])));
            tags.push((278, Val::Long(vec![w])));
            tags
        };
        // One sparse strip: StripOffsets = 0, StripByteCounts = 0.
        let mut tags = raster(20_000, 1);
        tags.push((273, Val::Long(vec![0])));
        tags.push((279, Val::Long(vec![0])));
        let bytes = build_tiff(tags, &[], false);
        assert!(bytes.len() < 300, "{} bytes", bytes.len());
        let t0 = std::time::Instant::now();
        let e = expect_err(&write_temp(&dir, "sparse.tif", &bytes));
        assert!(t0.elapsed().as_millis() < 100, "took {:?}", t0.elapsed());
        assert!(e.to_string().contains("can fill at most 0"), "{e}");
        // A compressed strip can only expand so far: 16 bytes of zstd fill 128 Ki samples.
        let bytes = build_tiff(raster(20_000, 50000), &[vec![0u8; 16]], false);
        let e = expect_err(&write_temp(&dir, "zstd.tif", &bytes));
        assert!(e.to_string().contains("can fill at most 131072"), "{e}");
        // Many strips that point at the same bytes hold those bytes once: 2,000 strips of a
        // row each, all at the one 8 KB row at offset 8 (the offsets array itself, the first
        // value written there), cannot fill 2000 × 2000 samples.
        let mut tags = image_tags(2000, 2000, 32, 3);
        tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
        tags.push((278, Val::Long(vec![1])));
        tags.push((273, Val::Long(vec![8; 2000])));
        tags.push((279, Val::Long(vec![8000; 2000])));
        let bytes = build_tiff(tags, &[], false);
        assert!(bytes.len() < 20_000);
        let e = expect_err(&write_temp(&dir, "overlap.tif", &bytes));
        assert!(e.to_string().contains("can fill at most"), "{e}");
        // A raster small enough to cost nothing is still read, sparse or not.
        let mut tags = raster(64, 1);
        tags.push((273, Val::Long(vec![0])));
        tags.push((279, Val::Long(vec![0])));
        let r = read(&write_temp(
            &dir,
            "small.tif",
            &build_tiff(tags, &[], false),
        ))
        .unwrap();
        assert_eq!((r.cols, r.rows), (64, 64));
    }

    #[test]
    fn unsupported_sample_types_and_bands_are_named() {
        use tiff::encoder::{colortype, TiffEncoder};
        let dir = tempfile::tempdir().unwrap();

        let rgb = dir.path().join("rgb.tif");
        TiffEncoder::new(std::fs::File::create(&rgb).unwrap())
            .unwrap()
            .write_image::<colortype::RGB8>(4, 4, &[7u8; 48])
            .unwrap();
        let e = expect_err(&rgb);
        assert!(matches!(e, ReadError::Unsupported { .. }), "{e}");
        assert!(e.to_string().contains("3 bands"), "{e}");

        let u64_path = dir.path().join("u64.tif");
        TiffEncoder::new(std::fs::File::create(&u64_path).unwrap())
            .unwrap()
            .write_image::<colortype::Gray64>(4, 4, &[7u64; 16])
            .unwrap();
        let e = expect_err(&u64_path);
        assert!(e.to_string().contains("64-bit unsigned integer"), "{e}");

        // Hand-made complex float file; the decoder itself cannot represent it.
        let mut tags = image_tags(2, 2, 64, 6);
        tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
        let bytes = build_tiff(tags, &[vec![0u8; 32]], false);
        let e = expect_err(&write_temp(&dir, "complex.tif", &bytes));
        assert!(e.to_string().contains("complex floating point"), "{e}");
    }

    #[test]
    fn plain_tiff_without_georeference_is_refused() {
        use tiff::encoder::{colortype, TiffEncoder};
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plain.tif");
        TiffEncoder::new(std::fs::File::create(&path).unwrap())
            .unwrap()
            .write_image::<colortype::GrayI16>(3, 3, &[1i16; 9])
            .unwrap();
        let e = expect_err(&path);
        assert!(e.to_string().contains("no usable georeferencing"), "{e}");
    }

    #[test]
    fn bad_nodata_tag_is_reported() {
        let mut tags = image_tags(2, 1, 16, 2);
        tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
        tags.push((42113, Val::Ascii("none")));
        let dir = tempfile::tempdir().unwrap();
        let bytes = build_tiff(tags, &[vec![1, 0, 2, 0]], false);
        let e = expect_err(&write_temp(&dir, "nd.tif", &bytes));
        assert!(e.to_string().contains("GDAL_NODATA"), "{e}");
    }

    #[test]
    fn infinities_become_nan_and_nodata_whitespace_is_trimmed() {
        let mut tags = image_tags(4, 1, 32, 3);
        tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
        tags.push((42113, Val::Ascii(" -3.4028234663852886e+38 \n")));
        let data: Vec<u8> = [f32::INFINITY, f32::NEG_INFINITY, f32::MIN, 12.5]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let dir = tempfile::tempdir().unwrap();
        let r = read(&write_temp(
            &dir,
            "inf.tif",
            &build_tiff(tags, &[data], false),
        ))
        .unwrap();
        assert_eq!(r.nodata, Some(f64::from(f32::MIN)));
        assert!(r.samples[..3].iter().all(|v| v.is_nan()), "{:?}", r.samples);
        assert_eq!(r.samples[3], 12.5);
    }

    fn small_geotiff_bytes(dir: &tempfile::TempDir) -> Vec<u8> {
        let path = dir.path().join("seed.tif");
        let samples: Vec<f32> = (0..64).map(|i| i as f32 * 1.5).collect();
        write_geotiff_f32(
            &path,
            8,
            8,
            &samples,
            [600000.0, 30.0, 0.0, 5000000.0, 0.0, -30.0],
            Some(&patchwork_crs::Crs::epsg(32631).unwrap()),
            Some(-9999.0),
        )
        .unwrap();
        std::fs::read(path).unwrap()
    }

    #[test]
    fn corrupted_bytes_never_panic_out() {
        // Deterministic mutation fuzzing of a valid file: every outcome must be Ok or Err.
        let dir = tempfile::tempdir().unwrap();
        let seed = small_geotiff_bytes(&dir);
        let i16_path = dir.path().join("seed16.tif");
        write_geotiff_i16(
            &i16_path,
            4,
            4,
            &[5i16; 16],
            [0.0, 1.0, 0.0, 4.0, 0.0, -1.0],
            Some(&patchwork_crs::Crs::epsg(4326).unwrap()),
            None,
        )
        .unwrap();
        let seeds = [seed, std::fs::read(&i16_path).unwrap()];
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let path = dir.path().join("fuzz.tif");
        for i in 0..400 {
            let mut bytes = seeds[i % 2].clone();
            for _ in 0..1 + next() % 4 {
                let pos = (next() % bytes.len() as u64) as usize;
                bytes[pos] = next() as u8;
            }
            if next() % 5 == 0 {
                let keep = (next() % bytes.len() as u64) as usize;
                bytes.truncate(keep.max(1));
            }
            std::fs::write(&path, &bytes).unwrap();
            let _ = read(&path);
        }
    }
}
