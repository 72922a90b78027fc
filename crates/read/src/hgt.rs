//! SRTM `.hgt` reader: headerless big-endian i16 grids named after their south-west corner.

use std::io::{BufReader, Read};
use std::path::Path;

use super::{has_extension, Raster, RasterReader, ReadError, ReadLimits, Source};

/// SRTM's void marker.
pub const HGT_VOID: i16 = -32768;

/// Reads SRTM1 (3601 x 3601) and SRTM3 (1201 x 1201) `.hgt` tiles.
pub struct HgtReader;

impl RasterReader for HgtReader {
    fn accepts(&self, path: &Path, _head: &[u8]) -> bool {
        // The format has no magic bytes; the extension is all there is.
        has_extension(path, &["hgt"])
    }

    fn read(&self, src: &mut Source, limits: &ReadLimits) -> Result<Raster, ReadError> {
        read_hgt_from(src, limits)
    }
}

/// Lower-left corner (lat, lon) in whole degrees from a name like `N44E005.hgt` or
/// `s12w077.SRTMGL1.hgt`.
pub fn parse_hgt_name(path: &Path) -> Result<(i32, i32), ReadError> {
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
    let bad = || {
        ReadError::invalid(format!(
            "cannot place {name:?}: SRTM .hgt files must be named after their south-west \
             corner like N44E005.hgt or S12W077.hgt"
        ))
    };
    let b = name.as_bytes();
    if b.len() < 7 {
        return Err(bad());
    }
    let digits = |s: &[u8]| -> Option<i32> {
        s.iter().try_fold(0i32, |acc, &c| {
            c.is_ascii_digit().then(|| acc * 10 + i32::from(c - b'0'))
        })
    };
    let lat = digits(&b[1..3]).ok_or_else(bad)?;
    let lon = digits(&b[4..7]).ok_or_else(bad)?;
    let lat = match b[0].to_ascii_uppercase() {
        b'N' => lat,
        b'S' => -lat,
        _ => return Err(bad()),
    };
    let lon = match b[3].to_ascii_uppercase() {
        b'E' => lon,
        b'W' => -lon,
        _ => return Err(bad()),
    };
    // The tile spans lat..lat+1 and lon..lon+1, which must stay on the globe.
    if !(-90..90).contains(&lat) || !(-180..180).contains(&lon) {
        return Err(bad());
    }
    Ok((lat, lon))
}

/// Reads an SRTM tile, placed by its name.
pub fn read_hgt(path: &Path, limits: &ReadLimits) -> Result<Raster, ReadError> {
    parse_hgt_name(path)?;
    read_hgt_from(&mut Source::open(path, limits)?, limits)
}

/// [`read_hgt`] of an open file.
pub fn read_hgt_from(file: &mut Source, limits: &ReadLimits) -> Result<Raster, ReadError> {
    // Owned: the file is read below while its path names it in messages.
    let path = &file.path().to_path_buf();
    let (lat, lon) = parse_hgt_name(path)?;
    let len = file.len();
    let n: usize = match len {
        2_884_802 => 1201,
        25_934_402 => 3601,
        _ => {
            return Err(ReadError::invalid(format!(
                "{} is {len} bytes, which matches neither SRTM3 (1201 x 1201 samples, \
                 2884802 bytes) nor SRTM1 (3601 x 3601 samples, 25934402 bytes); the file \
                 may be truncated or not an .hgt tile",
                path.display()
            )));
        }
    };
    limits.check(n as u64, n as u64)?;

    let mut samples = Vec::with_capacity(n * n);
    let mut reader = BufReader::new(file);
    let mut row = vec![0u8; n * 2];
    for _ in 0..n {
        reader.read_exact(&mut row)?;
        samples.extend(row.chunks_exact(2).map(|b| {
            let v = i16::from_be_bytes([b[0], b[1]]);
            if v == HGT_VOID {
                f32::NAN
            } else {
                f32::from(v)
            }
        }));
    }

    // Samples sit exactly on the degree lines (PixelIsPoint); GDAL's corner-based transform
    // therefore starts half a step outside the tile.
    let step = 1.0 / (n - 1) as f64;
    let geotransform = [
        f64::from(lon) - 0.5 * step,
        step,
        0.0,
        f64::from(lat + 1) + 0.5 * step,
        0.0,
        -step,
    ];
    Ok(Raster {
        cols: n,
        rows: n,
        samples,
        geotransform,
        // SRTM's heights, and NASADEM's after it, are above the EGM96 geoid.
        crs: super::crs::FileCrs {
            crs: Some(patchwork_crs::Crs::wgs84()),
            unreadable: None,
            vertical: patchwork_crs::vertical::VerticalCrs::epsg(5773),
        },
        nodata: Some(f64::from(HGT_VOID)),
        acquired: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{assert_gt_close, data_file};

    #[test]
    fn names_parse_to_south_west_corner() {
        let p = |s: &str| parse_hgt_name(Path::new(s));
        assert_eq!(p("N44E005.hgt").unwrap(), (44, 5));
        assert_eq!(p("S12W077.hgt").unwrap(), (-12, -77));
        assert_eq!(p("/data/s01w180.SRTMGL1.hgt").unwrap(), (-1, -180));
        assert_eq!(p("N00E000.HGT").unwrap(), (0, 0));
        for bad in [
            "X44E005.hgt",
            "N4E005.hgt",
            "N44E05.hgt",
            "N44Q005.hgt",
            "N90E000.hgt",
            "N10E180.hgt",
            "dem.hgt",
        ] {
            let e = p(bad).unwrap_err();
            assert!(e.to_string().contains("N44E005"), "{bad}: {e}");
        }
    }

    #[test]
    fn real_srtm3_tile() {
        // The real tile around Mont Ventoux, rows 791..1191 and columns 135..535, the rest made
        // void (tests/data/make_fixtures.py).
        let r = read_hgt(&data_file("hgt/N44E005.hgt"), &ReadLimits::default()).unwrap();
        assert_eq!((r.cols, r.rows), (1201, 1201));
        assert_eq!(r.crs.epsg(), Some(4326));
        assert_eq!(r.crs.vertical.as_ref().map(|v| v.key()), Some("EPSG:5773"));
        assert_eq!(r.nodata, Some(-32768.0));
        assert_eq!(r.nodata_count(), 1_282_407);
        let s = 1.0 / 1200.0;
        assert_gt_close(
            r.geotransform,
            [5.0 - 0.5 * s, s, 0.0, 45.0 + 0.5 * s, 0.0, -s],
            1e-12,
        );
        // Mont Ventoux (1910 m, 44.174N 5.279E) is in this tile; the summit sample must be close.
        let (col, row) = (
            (0.279 * 1200.0_f64).round() as usize,
            ((45.0 - 44.174) * 1200.0_f64).round() as usize,
        );
        let mut best = f32::MIN;
        for r0 in row - 3..=row + 3 {
            for c0 in col - 3..=col + 3 {
                best = best.max(r.get(c0, r0));
            }
        }
        assert!(
            (1850.0..1950.0).contains(&best),
            "Ventoux summit area max {best}"
        );
    }

    #[test]
    fn bad_length_and_name_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let limits = ReadLimits::default();

        let short = dir.path().join("N44E005.hgt");
        std::fs::write(&short, vec![0u8; 2_884_800]).unwrap();
        let e = read_hgt(&short, &limits).unwrap_err();
        assert!(e.to_string().contains("2884800 bytes"), "{e}");

        let unnamed = dir.path().join("tile.hgt");
        std::fs::write(&unnamed, vec![0u8; 2_884_802]).unwrap();
        let e = read_hgt(&unnamed, &limits).unwrap_err();
        assert!(matches!(e, ReadError::Invalid { .. }), "{e}");

        let empty = dir.path().join("S12W077.hgt");
        std::fs::write(&empty, b"").unwrap();
        assert!(read_hgt(&empty, &limits)
            .unwrap_err()
            .to_string()
            .contains("empty"));

        let dir_named = dir.path().join("N10E010.hgt");
        std::fs::create_dir(&dir_named).unwrap();
        assert!(read_hgt(&dir_named, &limits)
            .unwrap_err()
            .to_string()
            .contains("directory"));
    }

    #[test]
    fn synthetic_southern_western_tile() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("S12W077.hgt");
        let mut bytes = vec![0u8; 2_884_802];
        bytes[0..2].copy_from_slice(&(-32768i16).to_be_bytes());
        bytes[2..4].copy_from_slice(&(-12i16).to_be_bytes());
        let last = bytes.len() - 2;
        bytes[last..].copy_from_slice(&4000i16.to_be_bytes());
        std::fs::write(&path, bytes).unwrap();
        let r = read_hgt(&path, &ReadLimits::default()).unwrap();
        assert!(r.get(0, 0).is_nan());
        assert_eq!(r.get(1, 0), -12.0);
        assert_eq!(r.get(1200, 1200), 4000.0);
        assert_eq!(r.nodata_count(), 1);
        let s = 1.0 / 1200.0;
        assert_gt_close(
            r.geotransform,
            [-77.0 - 0.5 * s, s, 0.0, -11.0 + 0.5 * s, 0.0, -s],
            1e-12,
        );
        // Sample (0,0) sits exactly on the north-west corner of the degree cell.
        let (x, y) = r.pixel_centre(0, 0);
        assert_gt_close(
            [x, y, 0.0, 0.0, 0.0, 0.0],
            [-77.0, -11.0, 0.0, 0.0, 0.0, 0.0],
            1e-12,
        );
    }
}
