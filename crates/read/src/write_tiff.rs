//! Minimal GeoTIFF writer (single band, deflate; north-up or rotated) for exports and test
//! fixtures.

use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::Path;

use tiff::encoder::colortype::{ColorType, Gray32Float, GrayI16};
use tiff::encoder::{Compression, DeflateLevel, TiffEncoder, TiffValue};
use tiff::tags::{Predictor, Tag};
use tiff::TiffError;

use super::ReadError;
use patchwork_crs::Crs;

/// Writes an f32 GeoTIFF. NaN samples are written as `nodata` when one is given.
pub fn write_geotiff_f32(
    path: &Path,
    cols: usize,
    rows: usize,
    samples: &[f32],
    geotransform: [f64; 6],
    crs: Option<&Crs>,
    nodata: Option<f64>,
) -> Result<(), ReadError> {
    let mut file = BufWriter::new(File::create(path)?);
    geotiff_f32_to(&mut file, cols, rows, samples, geotransform, crs, nodata)?;
    // BufWriter swallows errors on drop; a full disk must surface here.
    file.flush()?;
    Ok(())
}

/// [`write_geotiff_f32`] into memory: the file's bytes.
pub fn geotiff_f32_bytes(
    cols: usize,
    rows: usize,
    samples: &[f32],
    geotransform: [f64; 6],
    crs: Option<&Crs>,
    nodata: Option<f64>,
) -> Result<Vec<u8>, ReadError> {
    let mut out = std::io::Cursor::new(Vec::new());
    geotiff_f32_to(&mut out, cols, rows, samples, geotransform, crs, nodata)?;
    Ok(out.into_inner())
}

fn geotiff_f32_to<W: Write + Seek>(
    out: W,
    cols: usize,
    rows: usize,
    samples: &[f32],
    geotransform: [f64; 6],
    crs: Option<&Crs>,
    nodata: Option<f64>,
) -> Result<(), ReadError> {
    check_shape(cols, rows, samples.len())?;
    let data: Vec<f32> = match nodata {
        // GDAL readers only recognise the declared value, so NaN must become it.
        Some(nd) if !nd.is_nan() => {
            // Readers compare nodata after rounding it to the sample type, so rounding is fine;
            // overflowing to infinity is not.
            let nd32 = nd as f32;
            if nd.is_finite() && !nd32.is_finite() {
                return Err(ReadError::invalid(format!(
                    "nodata {nd} is outside the range of f32 samples"
                )));
            }
            samples
                .iter()
                .map(|&v| if v.is_nan() { nd32 } else { v })
                .collect()
        }
        _ => samples.to_vec(),
    };
    // The tiff encoder cannot write the floating-point predictor, and the horizontal one is
    // integer-only, so floats go through plain deflate.
    write::<Gray32Float, _>(
        out,
        cols,
        rows,
        &data,
        geotransform,
        crs,
        nodata,
        Predictor::None,
    )
}

/// Writes an i16 GeoTIFF. `nodata` must be a whole number within i16.
pub fn write_geotiff_i16(
    path: &Path,
    cols: usize,
    rows: usize,
    samples: &[i16],
    geotransform: [f64; 6],
    crs: Option<&Crs>,
    nodata: Option<f64>,
) -> Result<(), ReadError> {
    check_shape(cols, rows, samples.len())?;
    if let Some(nd) = nodata {
        if nd.fract() != 0.0 || !(f64::from(i16::MIN)..=f64::from(i16::MAX)).contains(&nd) {
            return Err(ReadError::invalid(format!(
                "nodata {nd} is not representable in i16 samples"
            )));
        }
    }
    let mut file = BufWriter::new(File::create(path)?);
    write::<GrayI16, _>(
        &mut file,
        cols,
        rows,
        samples,
        geotransform,
        crs,
        nodata,
        Predictor::Horizontal,
    )?;
    // BufWriter swallows errors on drop; a full disk must surface here.
    file.flush()?;
    Ok(())
}

fn check_shape(cols: usize, rows: usize, len: usize) -> Result<(), ReadError> {
    if cols == 0 || rows == 0 || u32::try_from(cols).is_err() || u32::try_from(rows).is_err() {
        return Err(ReadError::invalid(format!(
            "cannot write a {cols} x {rows} raster as a TIFF"
        )));
    }
    if cols.checked_mul(rows) != Some(len) {
        return Err(ReadError::invalid(format!(
            "{len} samples given for a {cols} x {rows} raster"
        )));
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn write<C: ColorType, W: Write + Seek>(
    out: W,
    cols: usize,
    rows: usize,
    samples: &[C::Inner],
    gt: [f64; 6],
    crs: Option<&Crs>,
    nodata: Option<f64>,
    predictor: Predictor,
) -> Result<(), ReadError>
where
    [C::Inner]: TiffValue,
{
    let rotated = gt[2] != 0.0 || gt[4] != 0.0;
    // Rotated grids go out as a ModelTransformation, which has no sign convention to break;
    // north-up ones as GDAL writes them, with a pixel scale and a tie point.
    let north_up = gt[1] > 0.0 && gt[5] < 0.0;
    if gt.iter().any(|v| !v.is_finite()) || !(rotated || north_up) {
        return Err(ReadError::unsupported(format!(
            "only north-up rasters with positive pixel width and negative pixel height, or \
             rotated ones, can be written, got {gt:?}"
        )));
    }
    let (geo_keys, ascii) = geo_key_directory(crs)?;

    encode::<C, _>(
        out, cols, rows, samples, gt, &geo_keys, &ascii, nodata, predictor,
    )
    .map_err(encode_error)?;
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn encode<C: ColorType, W: Write + Seek>(
    out: W,
    cols: usize,
    rows: usize,
    samples: &[C::Inner],
    gt: [f64; 6],
    geo_keys: &[u16],
    ascii: &str,
    nodata: Option<f64>,
    predictor: Predictor,
) -> Result<W, TiffError>
where
    [C::Inner]: TiffValue,
{
    let mut out = out;
    {
        let mut tiff = TiffEncoder::new(&mut out)?
            .with_compression(Compression::Deflate(DeflateLevel::Balanced))
            .with_predictor(predictor);
        let mut image = tiff.new_image::<C>(cols as u32, rows as u32)?;
        let dir = image.encoder();
        if gt[2] != 0.0 || gt[4] != 0.0 {
            #[rustfmt::skip]
            let m = [
                gt[1], gt[2], 0.0, gt[0],
                gt[4], gt[5], 0.0, gt[3],
                0.0, 0.0, 0.0, 0.0,
                0.0, 0.0, 0.0, 1.0,
            ];
            dir.write_tag(Tag::ModelTransformationTag, &m[..])?;
        } else {
            dir.write_tag(Tag::ModelPixelScaleTag, &[gt[1], -gt[5], 0.0][..])?;
            dir.write_tag(
                Tag::ModelTiepointTag,
                &[0.0, 0.0, 0.0, gt[0], gt[3], 0.0][..],
            )?;
        }
        dir.write_tag(Tag::GeoKeyDirectoryTag, geo_keys)?;
        if !ascii.is_empty() {
            dir.write_tag(Tag::GeoAsciiParamsTag, ascii)?;
        }
        if let Some(nd) = nodata {
            dir.write_tag(Tag::GdalNodata, format_nodata(nd).as_str())?;
        }
        image.write_data(samples)?;
    }
    Ok(out)
}

/// GDAL's spelling, which every GeoTIFF reader parses.
pub(crate) fn format_nodata(v: f64) -> String {
    if v.is_nan() {
        "nan".to_string()
    } else if v.is_infinite() {
        if v > 0.0 { "inf" } else { "-inf" }.to_string()
    } else {
        // Shortest representation that parses back to exactly this f64.
        format!("{v}")
    }
}

/// The GeoKeyDirectory of a CRS, and its ASCII parameters. An EPSG CRS is its code; one
/// without a code is user-defined, its WKT in the citation as GDAL writes it ("ESRI PE String
/// = …"), which GDAL and this crate's reader both read back.
pub(crate) fn geo_key_directory(crs: Option<&Crs>) -> Result<(Vec<u16>, String), ReadError> {
    const PIXEL_IS_AREA: u16 = 1;
    const USER_DEFINED: u16 = 32767;
    let mut keys: Vec<[u16; 4]> = Vec::new();
    let mut ascii = String::new();
    match crs {
        Some(c) => {
            let geographic = c.is_geographic();
            keys.push([1024, 0, 1, if geographic { 2 } else { 1 }]);
            keys.push([1025, 0, 1, PIXEL_IS_AREA]);
            let code_key = if geographic { 2048 } else { 3072 };
            match c.epsg_code().and_then(|code| u16::try_from(code).ok()) {
                Some(code) if code != 0 && code != USER_DEFINED => {
                    keys.push([code_key, 0, 1, code]);
                }
                _ => {
                    let wkt = c.wkt1().ok_or_else(|| {
                        ReadError::unsupported(format!(
                            "{} has no WKT 1 form to write in a GeoTIFF",
                            c.label()
                        ))
                    })?;
                    ascii = format!("ESRI PE String = {wkt}|");
                    let citation = if geographic { 2049 } else { 3073 };
                    keys.push([code_key, 0, 1, USER_DEFINED]);
                    keys.push([citation, 34737, ascii.len() as u16, 0]);
                }
            }
        }
        None => keys.push([1025, 0, 1, PIXEL_IS_AREA]),
    }
    // Readers may look keys up by bisection: they go in ascending order.
    keys.sort_by_key(|k| k[0]);
    let mut dir = vec![1, 1, 0, keys.len() as u16];
    dir.extend(keys.iter().flatten());
    Ok((dir, ascii))
}

fn encode_error(e: TiffError) -> ReadError {
    match e {
        TiffError::IoError(io) => ReadError::Io(io),
        other => ReadError::invalid(format!("cannot encode TIFF: {other}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geotiff::read_geotiff;
    use crate::{read_raster, ReadLimits};

    #[test]
    fn f32_round_trip_with_nodata() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.tif");
        let (cols, rows) = (7, 5);
        let mut samples: Vec<f32> = (0..cols * rows).map(|i| i as f32 * 0.75 - 3.0).collect();
        samples[3] = f32::NAN;
        samples[20] = f32::NAN;
        let gt = [5.0, 1.0 / 1200.0, 0.0, 45.0, 0.0, -1.0 / 1200.0];
        write_geotiff_f32(
            &path,
            cols,
            rows,
            &samples,
            gt,
            Some(&patchwork_crs::Crs::epsg(4326).unwrap()),
            Some(-9999.0),
        )
        .unwrap();

        let r = read_raster(&path, &ReadLimits::default()).unwrap();
        assert_eq!((r.cols, r.rows), (cols, rows));
        assert_eq!(r.geotransform, gt);
        assert_eq!(r.crs.epsg(), Some(4326));
        assert_eq!(r.nodata, Some(-9999.0));
        for (i, (a, b)) in r.samples.iter().zip(&samples).enumerate() {
            assert!(
                a == b || (a.is_nan() && b.is_nan()),
                "sample {i}: {a} vs {b}"
            );
        }
        assert_eq!(r.nodata_count(), 2);
    }

    #[test]
    fn f32_round_trip_nan_nodata_and_no_crs() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("n.tif");
        let samples = [1.0, f32::NAN, 3.0, 4.0];
        let gt = [0.0, 2.0, 0.0, 10.0, 0.0, -2.0];
        write_geotiff_f32(&path, 2, 2, &samples, gt, None, Some(f64::NAN)).unwrap();
        let r = read_geotiff(&path, &ReadLimits::default()).unwrap();
        assert!(r.nodata.unwrap().is_nan());
        assert_eq!(r.crs.epsg(), None);
        assert_eq!(r.geotransform, gt);
        assert!(r.samples[1].is_nan());
        assert_eq!(r.samples[3], 4.0);
    }

    #[test]
    fn i16_round_trip_projected() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("i.tif");
        let (cols, rows) = (300, 200);
        let samples: Vec<i16> = (0..cols * rows)
            .map(|i| {
                if i % 97 == 0 {
                    -32768
                } else {
                    (i % 4001) as i16 - 500
                }
            })
            .collect();
        let gt = [657596.0, 90.0, 0.0, 4987377.0, 0.0, -90.0];
        write_geotiff_i16(
            &path,
            cols,
            rows,
            &samples,
            gt,
            Some(&patchwork_crs::Crs::epsg(32631).unwrap()),
            Some(-32768.0),
        )
        .unwrap();

        let r = read_raster(&path, &ReadLimits::default()).unwrap();
        assert_eq!((r.cols, r.rows), (cols, rows));
        assert_eq!(r.geotransform, gt);
        assert_eq!(r.crs.epsg(), Some(32631));
        assert_eq!(r.nodata, Some(-32768.0));
        for (i, (&a, &b)) in r.samples.iter().zip(&samples).enumerate() {
            if b == -32768 {
                assert!(a.is_nan(), "sample {i}");
            } else {
                assert_eq!(a, f32::from(b), "sample {i}");
            }
        }
    }

    #[test]
    fn a_rotated_grid_round_trips_through_its_model_transformation() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("turned.tif");
        let (s, c) = 0.3f64.sin_cos();
        let gt = [1000.0, 2.0 * c, 3.0 * s, 5000.0, 2.0 * s, -3.0 * c];
        let samples: Vec<f32> = (0..12).map(|i| i as f32 * 1.5).collect();
        write_geotiff_f32(
            &path,
            4,
            3,
            &samples,
            gt,
            Some(&patchwork_crs::Crs::epsg(32631).unwrap()),
            None,
        )
        .unwrap();
        let r = read_raster(&path, &ReadLimits::default()).unwrap();
        assert_eq!((r.cols, r.rows, r.samples.clone()), (4, 3, samples));
        for (a, b) in r.geotransform.iter().zip(gt) {
            assert!((a - b).abs() < 1e-9, "{:?} vs {gt:?}", r.geotransform);
        }
    }

    #[test]
    fn geo_keys_follow_crs_kind() {
        let keys = |code: u32| geo_key_directory(Some(&Crs::epsg(code).unwrap())).unwrap();
        assert_eq!(
            keys(4326),
            (
                vec![1, 1, 0, 3, 1024, 0, 1, 2, 1025, 0, 1, 1, 2048, 0, 1, 4326],
                String::new()
            )
        );
        assert_eq!(
            keys(32630).0,
            vec![1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32630]
        );
        // A CRS without a code is written user-defined, its WKT in the citation, and read
        // back as a CRS that places every point where it did. (The WKT writer names a datum
        // with a null shift on GRS 80 NAD83, so the names may differ.)
        let custom = Crs::parse("+proj=tmerc +lat_0=0 +lon_0=-93 +k=0.9996 +x_0=500000 +y_0=0 +ellps=GRS80 +towgs84=0,0,0,0,0,0,0 +units=m").unwrap();
        assert_eq!(custom.epsg_code(), None);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("custom.tif");
        let gt = [431_000.0, 1.0, 0.0, 4_870_000.0, 0.0, -1.0];
        write_geotiff_f32(&path, 2, 2, &[1.0, 2.0, 3.0, 4.0], gt, Some(&custom), None).unwrap();
        let r = read_raster(&path, &ReadLimits::default()).unwrap();
        let back = r.crs.crs.unwrap();
        let wgs = Crs::wgs84();
        let p = [431_000.0, 4_870_000.0];
        let a = patchwork_crs::Transform::new(&custom, &wgs)
            .unwrap()
            .apply(p)
            .unwrap();
        let b = patchwork_crs::Transform::new(&back, &wgs)
            .unwrap()
            .apply(p)
            .unwrap();
        assert!(
            (a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9,
            "{a:?} {b:?}"
        );
    }

    #[test]
    fn refuses_what_it_cannot_write() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.tif");
        let north_up = [0.0, 1.0, 0.0, 2.0, 0.0, -1.0];
        let south_up = [0.0, 1.0, 0.0, 2.0, 0.0, 1.0];
        assert!(write_geotiff_f32(&path, 2, 2, &[0.0; 4], south_up, None, None).is_err());
        let e = write_geotiff_f32(&path, 2, 2, &[0.0; 3], north_up, None, None).unwrap_err();
        assert!(e.to_string().contains("3 samples"), "{e}");
        let e = write_geotiff_i16(&path, 2, 2, &[0; 4], north_up, None, Some(0.5)).unwrap_err();
        assert!(e.to_string().contains("i16"), "{e}");
        let e = write_geotiff_f32(&path, 2, 2, &[0.0; 4], north_up, None, Some(1e300)).unwrap_err();
        assert!(e.to_string().contains("f32"), "{e}");
    }
}
