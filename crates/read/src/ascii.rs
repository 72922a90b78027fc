//! ESRI ASCII grid (`.asc`, also called AAIGrid) reader with optional `.prj` sidecar.

use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use super::{has_extension, Raster, RasterReader, ReadError, ReadLimits, Source};

/// Reads ESRI ASCII grids.
pub struct AsciiGridReader;

impl RasterReader for AsciiGridReader {
    fn accepts(&self, path: &Path, head: &[u8]) -> bool {
        let text = String::from_utf8_lossy(head);
        let starts_with_ncols = text
            .trim_start()
            .get(..5)
            .is_some_and(|s| s.eq_ignore_ascii_case("ncols"));
        has_extension(path, &["asc"]) || starts_with_ncols
    }

    fn read(&self, src: &mut Source, limits: &ReadLimits) -> Result<Raster, ReadError> {
        read_ascii_grid_from(src, limits)
    }
}

/// Whitespace-separated tokens read straight from the file, so a multi-gigabyte grid never
/// sits in memory as text and a binary file cannot make us buffer an endless "line".
struct Tokens<R> {
    reader: R,
    token: Vec<u8>,
}

const MAX_TOKEN: usize = 256;

impl<R: BufRead> Tokens<R> {
    fn next(&mut self) -> Result<Option<&str>, ReadError> {
        self.token.clear();
        loop {
            let buf = self.reader.fill_buf()?;
            if buf.is_empty() {
                break;
            }
            let mut used = 0;
            let mut done = false;
            for &b in buf {
                used += 1;
                if b.is_ascii_whitespace() {
                    if !self.token.is_empty() {
                        done = true;
                        break;
                    }
                } else {
                    self.token.push(b);
                    if self.token.len() > MAX_TOKEN {
                        return Err(ReadError::invalid(
                            "not an ASCII grid: found a word of more than 256 characters",
                        ));
                    }
                }
            }
            self.reader.consume(used);
            if done {
                break;
            }
        }
        if self.token.is_empty() {
            return Ok(None);
        }
        std::str::from_utf8(&self.token)
            .map(Some)
            .map_err(|_| ReadError::invalid("not an ASCII grid: the file contains binary data"))
    }
}

/// The header keys of an ESRI ASCII grid (lowercase).
const HEADER_KEYS: [&str; 13] = [
    "ncols",
    "nrows",
    "xllcorner",
    "xllcenter",
    "xllcentre",
    "yllcorner",
    "yllcenter",
    "yllcentre",
    "cellsize",
    "dx",
    "dy",
    "nodata_value",
    "nodata",
];

#[derive(Default)]
struct Header {
    ncols: Option<u64>,
    nrows: Option<u64>,
    /// (value, true when it names the centre of the lower-left cell rather than its corner)
    xll: Option<(f64, bool)>,
    yll: Option<(f64, bool)>,
    dx: Option<f64>,
    dy: Option<f64>,
    nodata: Option<f64>,
}

/// Reads an ESRI ASCII grid, and the `.prj` beside it if there is one.
pub fn read_ascii_grid(path: &Path, limits: &ReadLimits) -> Result<Raster, ReadError> {
    read_ascii_grid_from(&mut Source::open(path, limits)?, limits)
}

/// [`read_ascii_grid`] of an open file.
pub fn read_ascii_grid_from(file: &mut Source, limits: &ReadLimits) -> Result<Raster, ReadError> {
    // Owned: the file is read below while its path names it in messages.
    let path = &file.path().to_path_buf();
    let file_len = file.len();
    let mut tokens = Tokens {
        reader: BufReader::new(file),
        token: Vec::new(),
    };

    let mut h = Header::default();
    // Header lines are "key value"; the first token that is not a key is the first sample.
    // Nothing read from the file is echoed in an error: a file that is not a grid may hold
    // anything.
    let mut words = 0;
    let first_value: Option<String> = loop {
        let Some(tok) = tokens.next()? else {
            break None;
        };
        words += 1;
        let key = tok.to_ascii_lowercase();
        let is_key = key.starts_with(|c: char| c.is_ascii_alphabetic())
            && !matches!(key.as_str(), "nan" | "inf" | "infinity");
        if !is_key {
            break Some(tok.to_string());
        }
        let Some(key) = HEADER_KEYS.iter().copied().find(|k| *k == key) else {
            return Err(ReadError::invalid(format!(
                "not an ASCII grid: word {words} of the header is none of the keys {}",
                HEADER_KEYS.join(", ")
            )));
        };
        let value = tokens
            .next()?
            .ok_or_else(|| ReadError::invalid(format!("ASCII grid header {key} has no value")))?
            .to_string();
        words += 1;
        let num = || {
            value
                .parse::<f64>()
                .map_err(|_| ReadError::invalid(format!("ASCII grid header {key} is not a number")))
        };
        let count = || {
            value.parse::<u64>().ok().filter(|&n| n > 0).ok_or_else(|| {
                ReadError::invalid(format!(
                    "ASCII grid header {key} is not a positive whole number"
                ))
            })
        };
        match key {
            "ncols" => h.ncols = Some(count()?),
            "nrows" => h.nrows = Some(count()?),
            "xllcorner" => h.xll = Some((num()?, false)),
            "xllcenter" | "xllcentre" => h.xll = Some((num()?, true)),
            "yllcorner" => h.yll = Some((num()?, false)),
            "yllcenter" | "yllcentre" => h.yll = Some((num()?, true)),
            "cellsize" => {
                let v = num()?;
                h.dx = Some(v);
                h.dy = Some(v);
            }
            "dx" => h.dx = Some(num()?),
            "dy" => h.dy = Some(num()?),
            _ => h.nodata = Some(num()?),
        }
    };

    let missing = |what: &str| ReadError::invalid(format!("ASCII grid header lacks {what}"));
    let cols = h.ncols.ok_or_else(|| missing("ncols"))?;
    let rows = h.nrows.ok_or_else(|| missing("nrows"))?;
    let (xll, x_centre) = h.xll.ok_or_else(|| missing("xllcorner or xllcenter"))?;
    let (yll, y_centre) = h.yll.ok_or_else(|| missing("yllcorner or yllcenter"))?;
    let dx = h.dx.ok_or_else(|| missing("cellsize (or dx)"))?;
    let dy = h.dy.ok_or_else(|| missing("cellsize (or dy)"))?;
    if !(dx > 0.0 && dy > 0.0 && dx.is_finite() && dy.is_finite()) {
        return Err(ReadError::invalid(format!(
            "ASCII grid cell size must be positive, got {dx} x {dy}"
        )));
    }
    limits.check(cols, rows)?;
    // Every sample takes at least a character and a separator.
    limits.check_fillable(cols, rows, file_len.div_ceil(2))?;
    let (cols, rows) = (cols as usize, rows as usize);

    let x0 = if x_centre { xll - 0.5 * dx } else { xll };
    let y_bottom = if y_centre { yll - 0.5 * dy } else { yll };
    let geotransform = [x0, dx, 0.0, y_bottom + rows as f64 * dy, 0.0, -dy];

    // Compared as f32, the precision the samples are kept in, so "-9999" matches "-9999.0".
    let nodata32 = h.nodata.map(|v| v as f32);
    let total = cols * rows;
    let mut samples = Vec::with_capacity(total);
    if let Some(first) = first_value {
        samples.push(parse_sample(&first, 0, nodata32)?);
    }
    while samples.len() < total {
        match tokens.next()? {
            Some(tok) => samples.push(parse_sample(tok, samples.len(), nodata32)?),
            None => return Err(ReadError::Truncated),
        }
    }
    if tokens.next()?.is_some() {
        return Err(ReadError::invalid(format!(
            "ASCII grid has more values than ncols x nrows = {cols} x {rows}"
        )));
    }

    let crs = sidecar_crs(path, limits)?;
    Ok(Raster {
        cols,
        rows,
        samples,
        geotransform,
        crs,
        nodata: h.nodata,
        acquired: None,
    })
}

fn parse_sample(tok: &str, index: usize, nodata: Option<f32>) -> Result<f32, ReadError> {
    let v: f32 = tok.parse().map_err(|_| {
        ReadError::invalid(format!("ASCII grid sample {} is not a number", index + 1))
    })?;
    Ok(if !v.is_finite() || Some(v) == nodata {
        f32::NAN
    } else {
        v
    })
}

/// Extensions of the projection file beside a grid, which the reader opens.
pub const PRJ_EXTENSIONS: [&str; 2] = ["prj", "PRJ"];

/// The CRS of the `.prj` next to the grid, if there is one.
fn sidecar_crs(path: &Path, limits: &ReadLimits) -> Result<super::crs::FileCrs, ReadError> {
    for ext in PRJ_EXTENSIONS {
        let prj = path.with_extension(ext);
        // No entry at all is no projection file; anything else is opened like the grid.
        if prj.symlink_metadata().is_err() {
            continue;
        }
        let file = super::open_regular_file(&prj, limits)?;
        let mut text = String::new();
        // A projection file is a few kilobytes; anything far larger is not one.
        file.take(1 << 20)
            .read_to_string(&mut text)
            .map_err(|_| ReadError::invalid(format!("{} is not a text file", prj.display())))?;
        return Ok(super::crs::FileCrs::of_text(&text));
    }
    Ok(super::crs::FileCrs::default())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &tempfile::TempDir, name: &str, text: &str) -> std::path::PathBuf {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn read(path: &Path) -> Result<Raster, ReadError> {
        read_ascii_grid(path, &ReadLimits::default())
    }

    #[test]
    fn a_real_grid_written_by_gdal_reads_with_its_prj() {
        // Mont Ventoux from SRTM3, as GDAL's AAIGrid driver writes it: corner registration,
        // a cellsize of nine digits, and an ESRI .prj beside it.
        let r = read(&crate::test_support::data_file("ventoux.asc")).unwrap();
        assert_eq!((r.cols, r.rows), (120, 100));
        assert_eq!(r.crs.epsg(), Some(4326));
        assert_eq!(r.nodata, Some(-32768.0));
        assert_eq!(r.nodata_count(), 0);
        crate::test_support::assert_gt_close(
            r.geotransform,
            [
                5.195416666667,
                0.000833333333,
                0.0,
                44.132916666667 + 100.0 * 0.000833333333,
                0.0,
                -0.000833333333,
            ],
            1e-12,
        );
        let max = r.samples.iter().cloned().fold(f32::MIN, f32::max);
        assert_eq!(max, 1898.0, "the summit sample");
    }

    #[test]
    fn corner_header_values_and_nodata() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(
            &dir,
            "g.asc",
            "NCOLS 3\nNROWS 2\nXLLCORNER 100.0\nYLLCORNER 200\nCELLSIZE 10\nNODATA_value -9999\n\
             1 2.5 -9999.0\n4 nan 6e1\n",
        );
        let r = read(&p).unwrap();
        assert_eq!((r.cols, r.rows), (3, 2));
        assert_eq!(r.geotransform, [100.0, 10.0, 0.0, 220.0, 0.0, -10.0]);
        assert_eq!(r.nodata, Some(-9999.0));
        assert_eq!(r.crs.epsg(), None);
        assert_eq!(r.get(0, 0), 1.0);
        assert_eq!(r.get(1, 0), 2.5);
        assert!(r.get(2, 0).is_nan());
        assert!(r.get(1, 1).is_nan());
        assert_eq!(r.get(2, 1), 60.0);
    }

    #[test]
    fn centre_header_dx_dy_and_lowercase() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(
            &dir,
            "c.asc",
            "ncols 2\r\nnrows 2\r\nxllcenter 0.5\r\nyllcenter 10.25\r\ndx 1\r\ndy 0.5\r\n1 2\r\n3 4",
        );
        let r = read(&p).unwrap();
        // Lower-left cell centre (0.5, 10.25): outer corner (0, 10); top edge 10 + 2 * 0.5.
        assert_eq!(r.geotransform, [0.0, 1.0, 0.0, 11.0, 0.0, -0.5]);
        assert_eq!(r.samples, vec![1.0, 2.0, 3.0, 4.0]);
        assert_eq!(r.nodata, None);
    }

    #[test]
    fn prj_sidecar_gives_epsg() {
        let dir = tempfile::tempdir().unwrap();
        let grid = "ncols 1\nnrows 1\nxllcorner 0\nyllcorner 0\ncellsize 1\n5\n";
        let cases = [
            (
                "wgs",
                r#"GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]]"#,
                Some(4326),
            ),
            (
                "esri",
                r#"GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]],PRIMEM["Greenwich",0.0],UNIT["Degree",0.0174532925199433]]"#,
                Some(4326),
            ),
            (
                "utm",
                r#"PROJCS["WGS 84 / UTM zone 31N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563,AUTHORITY["EPSG","7030"]],AUTHORITY["EPSG","6326"]],AUTHORITY["EPSG","4326"]],PROJECTION["Transverse_Mercator"],UNIT["metre",1,AUTHORITY["EPSG","9001"]],AUTHORITY["EPSG","32631"]]"#,
                Some(32631),
            ),
            (
                "utm_noauth",
                r#"PROJCS["UTM 31 on WGS 84",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],AUTHORITY["EPSG","4326"]],PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],PARAMETER["central_meridian",3],PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],PARAMETER["false_northing",0],UNIT["metre",1]]"#,
                // No code of its own: its datum and parameters make it WGS 84 / UTM 31N.
                Some(32631),
            ),
            (
                "lambert",
                r#"GEOGCS["RGF93",DATUM["Reseau_Geodesique_Francais_1993",SPHEROID["GRS 1980",6378137,298.257222101]]]"#,
                // Its datum named, and nothing else to tell it apart: RGF93 v1, geographic.
                Some(4171),
            ),
            (
                "wkt2",
                r#"PROJCRS["ETRS89 / UTM zone 32N",BASEGEOGCRS["ETRS89",ID["EPSG",4258]],ID["EPSG",25832]]"#,
                Some(25832),
            ),
        ];
        for (name, wkt, want) in cases {
            let p = write(&dir, &format!("{name}.asc"), grid);
            write(&dir, &format!("{name}.prj"), wkt);
            let r = read(&p).unwrap();
            assert_eq!(r.crs.epsg(), want, "{name}");
            // What cannot be read is named, so that the error can say what was found.
            assert_eq!(r.crs.unreadable.is_some(), r.crs.crs.is_none(), "{name}");
        }
    }

    #[test]
    fn bad_grids_are_refused_with_reasons() {
        let dir = tempfile::tempdir().unwrap();
        let cases = [
            (
                "short.asc",
                "ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2 3\n",
                "truncated",
            ),
            (
                "long.asc",
                "ncols 1\nnrows 1\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2\n",
                "more values",
            ),
            (
                "nocell.asc",
                "ncols 1\nnrows 1\nxllcorner 0\nyllcorner 0\n1\n",
                "cellsize",
            ),
            (
                "badnum.asc",
                "ncols 1\nnrows 1\nxllcorner 0\nyllcorner 0\ncellsize 1\n1,5\n",
                "not a number",
            ),
            (
                "badkey.asc",
                "ncols 1\nnrows 1\nfoo 3\n",
                "word 5 of the header",
            ),
            (
                "claims.asc",
                "ncols 2000\nnrows 2000\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2 3\n",
                "can fill at most",
            ),
            (
                "zero.asc",
                "ncols 0\nnrows 1\nxllcorner 0\nyllcorner 0\ncellsize 1\n",
                "positive",
            ),
            (
                "neg.asc",
                "ncols 1\nnrows 1\nxllcorner 0\nyllcorner 0\ncellsize -1\n1\n",
                "positive",
            ),
            (
                "huge.asc",
                "ncols 1000000\nnrows 1000000\nxllcorner 0\nyllcorner 0\ncellsize 1\n1\n",
                "too large",
            ),
            ("empty.asc", "", "empty"),
        ];
        for (name, text, needle) in cases {
            let e = read(&write(&dir, name, text)).unwrap_err();
            assert!(e.to_string().contains(needle), "{name}: {e}");
        }
        let binary = dir.path().join("bin.asc");
        std::fs::write(&binary, [0xffu8; 5000]).unwrap();
        assert!(read(&binary).is_err());
    }

    #[test]
    fn errors_never_echo_what_the_file_holds() {
        let dir = tempfile::tempdir().unwrap();
        for text in [
            "secret hunter2\n",
            "ncols secret\n",
            "ncols 1\nnrows 1\nxllcorner 0\nyllcorner 0\ncellsize secret\n",
            "ncols 1\nnrows 1\nxllcorner 0\nyllcorner 0\ncellsize 1\nsecret\n",
            "ncols 2\nnrows 1\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 secret\n",
            "secret",
        ] {
            let e = read(&write(&dir, "x.asc", text)).unwrap_err().to_string();
            assert!(
                !e.contains("secret") && !e.contains("hunter2"),
                "{text:?}: {e}"
            );
        }
    }

    #[test]
    fn accepts_by_extension_or_header() {
        let r = AsciiGridReader;
        assert!(r.accepts(Path::new("a.ASC"), b""));
        assert!(r.accepts(Path::new("a.txt"), b"  NCOLS 4\n"));
        assert!(!r.accepts(Path::new("a.txt"), b"hello"));
    }
}
