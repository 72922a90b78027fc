//! NOAA's GTX grids: the format of the geoid models PROJ ships (`egm96_15.gtx` in Debian's
//! `proj-data`, and the VDatum grids). A geoid grid is not a survey, so this reader is not
//! among the inbox's ([`crate::readers`]); [`read_geoid_grid`] reads a GTX or any raster the
//! inbox reads.
//!
//! The layout: a 40-byte big-endian header (the south-west node's latitude and longitude,
//! the steps in latitude and longitude, all `f64` degrees, then rows and columns as `i32`),
//! then `rows × cols` big-endian `f32` undulations in metres, the southernmost row first,
//! west to east. -88.8888 marks a node without a value. Longitudes may run over 0..360.

use std::io::Read;
use std::path::Path;

use super::{read_raster, Raster, ReadError, ReadLimits, Source};

/// Bytes of the header.
const HEADER: usize = 40;

/// The value VDatum writes where a grid has no undulation.
const NODATA: f32 = -88.8888;

/// A geoid grid: a GTX file (by its extension) or any raster [`read_raster`] reads.
pub fn read_geoid_grid(path: &Path, limits: &ReadLimits) -> Result<Raster, ReadError> {
    if super::has_extension(path, &["gtx"]) {
        read_gtx(path, limits)
    } else {
        read_raster(path, limits)
    }
}

/// Reads a GTX grid, north-up (row 0 northmost) in EPSG:4326, each node a sample at the centre
/// of its pixel as GDAL places it.
pub fn read_gtx(path: &Path, limits: &ReadLimits) -> Result<Raster, ReadError> {
    let mut src = Source::open(path, limits)?;
    let bad =
        |why: String| ReadError::invalid(format!("{} is not a GTX grid: {why}", path.display()));
    let mut head = [0u8; HEADER];
    src.read_exact(&mut head)
        .map_err(|_| bad(format!("it is shorter than the {HEADER}-byte header")))?;
    let f = |i: usize| f64::from_be_bytes(head[i..i + 8].try_into().expect("8 bytes"));
    let n = |i: usize| i32::from_be_bytes(head[i..i + 4].try_into().expect("4 bytes"));
    let (lat0, mut lon0, dlat, dlon) = (f(0), f(8), f(16), f(24));
    let (rows, cols) = (n(32), n(36));
    if !(rows >= 2 && cols >= 2) {
        return Err(bad(format!("{rows} rows and {cols} columns")));
    }
    let (rows, cols) = (rows as usize, cols as usize);
    let steps_ok = dlat.is_finite() && dlon.is_finite() && dlat > 0.0 && dlon > 0.0;
    let north = lat0 + (rows - 1) as f64 * dlat;
    // A grid may reach a node's rounding past the pole, no further.
    let on_earth = lat0 >= -90.0 - dlat / 2.0 && north <= 90.0 + dlat / 2.0;
    if !(steps_ok && lat0.is_finite() && lon0.is_finite() && on_earth) {
        return Err(bad(format!(
            "its nodes (from {lat0}° N, {lon0}° E, steps {dlat}° and {dlon}°, {rows} rows) \
             are not on the globe"
        )));
    }
    limits.check(cols as u64, rows as u64)?;
    let want = HEADER as u64 + 4 * rows as u64 * cols as u64;
    if src.len() != want {
        return Err(bad(format!(
            "it is {} bytes, and its header describes {want}",
            src.len()
        )));
    }
    // Grids over 0..360 are placed over -180..180 where they start east of the antimeridian.
    if lon0 >= 180.0 {
        lon0 -= 360.0;
    }
    let mut body = vec![0u8; 4 * rows * cols];
    src.read_exact(&mut body)?;
    let mut samples = vec![f32::NAN; rows * cols];
    for (r, row) in body.chunks_exact(4 * cols).enumerate() {
        // The file's first row is the southernmost; the raster's row 0 is the northmost.
        let out = &mut samples[(rows - 1 - r) * cols..(rows - r) * cols];
        for (o, b) in out.iter_mut().zip(row.chunks_exact(4)) {
            let v = f32::from_be_bytes([b[0], b[1], b[2], b[3]]);
            *o = if v == NODATA || !v.is_finite() {
                f32::NAN
            } else {
                v
            };
        }
    }
    Ok(Raster {
        cols,
        rows,
        samples,
        geotransform: [lon0 - dlon / 2.0, dlon, 0.0, north + dlat / 2.0, 0.0, -dlat],
        crs: super::crs::FileCrs {
            crs: Some(patchwork_crs::Crs::wgs84()),
            unreadable: None,
            vertical: None,
        },
        nodata: Some(f64::from(NODATA)),
        acquired: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A GTX file of `rows × cols` nodes from (lat0, lon0), value `v(row from south, col)`.
    fn gtx(
        path: &Path,
        lat0: f64,
        lon0: f64,
        step: f64,
        rows: i32,
        cols: i32,
        v: impl Fn(i32, i32) -> f32,
    ) {
        let mut b = Vec::new();
        for x in [lat0, lon0, step, step] {
            b.extend_from_slice(&x.to_be_bytes());
        }
        b.extend_from_slice(&rows.to_be_bytes());
        b.extend_from_slice(&cols.to_be_bytes());
        for r in 0..rows {
            for c in 0..cols {
                b.extend_from_slice(&v(r, c).to_be_bytes());
            }
        }
        std::fs::write(path, b).unwrap();
    }

    #[test]
    fn a_gtx_grid_reads_north_up_with_its_nodes_at_pixel_centres() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("geoid.gtx");
        gtx(&p, 43.0, 4.0, 0.5, 3, 4, |r, c| {
            if (r, c) == (0, 3) {
                NODATA
            } else {
                (10 * r + c) as f32
            }
        });
        let g = read_geoid_grid(&p, &ReadLimits::default()).unwrap();
        assert_eq!((g.cols, g.rows), (4, 3));
        // Row 0 is the northmost: the file's last row, at 44° N.
        assert_eq!(g.get(1, 0), 21.0);
        assert_eq!(g.get(0, 2), 0.0);
        assert!(g.get(3, 2).is_nan(), "-88.8888 is no value");
        assert_eq!(g.pixel_centre(0, 0), (4.0, 44.0));
        assert_eq!(g.pixel_centre(3, 2), (5.5, 43.0));
        assert_eq!(g.crs.epsg(), Some(4326));
        // A grid over 0..360 that starts east of the antimeridian is placed west of it.
        gtx(&p, -1.0, 359.0, 1.0, 2, 2, |_, _| 1.0);
        let g = read_gtx(&p, &ReadLimits::default()).unwrap();
        assert_eq!(g.pixel_centre(0, 1), (-1.0, -1.0));
    }

    #[test]
    fn a_damaged_gtx_grid_is_refused_saying_why() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.gtx");
        let refused = |p: &Path| read_gtx(p, &ReadLimits::default()).unwrap_err().to_string();
        std::fs::write(&p, [0u8; 12]).unwrap();
        assert!(refused(&p).contains("header"), "{}", refused(&p));
        gtx(&p, 43.0, 4.0, 0.5, 3, 4, |_, _| 0.0);
        let full = std::fs::read(&p).unwrap();
        std::fs::write(&p, &full[..full.len() - 4]).unwrap();
        assert!(
            refused(&p).contains("its header describes"),
            "{}",
            refused(&p)
        );
        gtx(&p, 89.0, 4.0, 1.0, 5, 4, |_, _| 0.0);
        assert!(refused(&p).contains("not on the globe"), "{}", refused(&p));
        gtx(&p, 43.0, 4.0, -0.5, 3, 4, |_, _| 0.0);
        assert!(refused(&p).contains("not on the globe"), "{}", refused(&p));
        gtx(&p, 43.0, 4.0, 0.5, 1, 4, |_, _| 0.0);
        assert!(refused(&p).contains("1 rows"), "{}", refused(&p));
    }
}
