//! Where a GeoTIFF lies: its model tiepoint, pixel scale or transformation, and the
//! GeoKeyDirectory (a CRS by code, or by the parameters GDAL writes for one without), the
//! vertical CRS, and GDAL's nodata tag.

use super::*;

pub(super) const GEO_KEY_MODEL_TYPE: u16 = 1024;
pub(super) const GEO_KEY_RASTER_TYPE: u16 = 1025;
pub(super) const GEO_KEY_GEOGRAPHIC_TYPE: u16 = 2048;
pub(super) const GEO_KEY_PROJECTED_CS_TYPE: u16 = 3072;
pub(super) const RASTER_PIXEL_IS_POINT: u16 = 2;
pub(super) const MODEL_TYPE_PROJECTED: u16 = 1;
pub(super) const MODEL_TYPE_GEOGRAPHIC: u16 = 2;
/// Geotransform (GDAL convention, PixelIsArea) and CRS from the GeoTIFF tags.
pub(super) fn georeference<R: Read + Seek>(
    dec: &mut Decoder<R>,
) -> Result<([f64; 6], FileCrs), ReadError> {
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

pub(super) fn f64_tag<R: Read + Seek>(
    dec: &mut Decoder<R>,
    tag: Tag,
    name: &str,
) -> Result<Option<Vec<f64>>, ReadError> {
    let Some(value) = dec.find_tag(tag).map_err(tiff_error)? else {
        return Ok(None);
    };
    // The GeoTIFF spec says DOUBLE, but being lenient about FLOAT or integer writers costs nothing.
    pub(super) fn scalar(v: Value) -> Option<f64> {
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
pub(super) struct GeoKeys {
    pub(super) short: Vec<(u16, u16)>,
    pub(super) double: Vec<(u16, Vec<f64>)>,
    pub(super) ascii: Vec<(u16, String)>,
}

pub(super) const GEO_KEY_CITATION: u16 = 1026;
pub(super) const GEO_KEY_GEOG_CITATION: u16 = 2049;
pub(super) const GEO_KEY_GEODETIC_DATUM: u16 = 2050;
pub(super) const GEO_KEY_ELLIPSOID: u16 = 2056;
pub(super) const GEO_KEY_SEMI_MAJOR: u16 = 2057;
pub(super) const GEO_KEY_SEMI_MINOR: u16 = 2058;
pub(super) const GEO_KEY_INV_FLATTENING: u16 = 2059;
pub(super) const GEO_KEY_TOWGS84: u16 = 2062;
pub(super) const GEO_KEY_PCS_CITATION: u16 = 3073;
pub(super) const GEO_KEY_PROJECTION: u16 = 3074;
pub(super) const GEO_KEY_COORD_TRANS: u16 = 3075;
pub(super) const GEO_KEY_LINEAR_UNITS: u16 = 3076;
pub(super) const GEO_KEY_VERTICAL_CS_TYPE: u16 = 4096;

impl GeoKeys {
    pub(super) fn parse(raw: &[u16], doubles: &[f64], ascii: &str) -> GeoKeys {
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

    pub(super) fn get(&self, id: u16) -> Option<u16> {
        self.short.iter().find(|(k, _)| *k == id).map(|(_, v)| *v)
    }

    pub(super) fn double(&self, id: u16) -> Option<f64> {
        self.doubles(id).map(|v| v[0])
    }

    pub(super) fn doubles(&self, id: u16) -> Option<Vec<f64>> {
        self.double
            .iter()
            .find(|(k, _)| *k == id)
            .map(|(_, v)| v.clone())
    }

    pub(super) fn text(&self, id: u16) -> Option<&str> {
        self.ascii
            .iter()
            .find(|(k, _)| *k == id)
            .map(|(_, v)| v.as_str())
            .filter(|t| !t.is_empty())
    }

    pub(super) fn epsg(&self) -> Option<u32> {
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
    pub(super) fn crs(&self) -> FileCrs {
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

pub(super) fn gdal_nodata<R: Read + Seek>(dec: &mut Decoder<R>) -> Result<Option<f64>, ReadError> {
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

/// When the file says its survey was acquired: the first GDAL metadata item (tag 42112) whose
/// name speaks of acquisition (`ACQUISITION_DATE`, `DATE_ACQUIRED`, `ACQUISITION_START_TIME`,
/// ...) or of a survey's or capture's date, else TIFF's `DateTime` (306, which many writers
/// set to when the file was made: the weaker word, so the later asked). Only a value that
/// reads as a date counts; a file's metadata is no promise, so one that does not is passed
/// over rather than refused.
pub(super) fn acquired<R: Read + Seek>(dec: &mut Decoder<R>) -> Option<String> {
    let dated = |v: &str| {
        let v = v.trim_matches(|c: char| c == '\0' || c.is_whitespace());
        patchwork_model::epoch::Epoch::parse(v)
            .is_ok()
            .then(|| v.to_string())
    };
    let ascii = |dec: &mut Decoder<R>, tag| match dec.find_tag(tag) {
        Ok(Some(Value::Ascii(t))) => Some(t),
        _ => None,
    };
    if let Some(xml) = ascii(dec, Tag::Unknown(42112)) {
        let found = gdal_items(&xml).find_map(|(name, value)| {
            let n = name.to_ascii_uppercase();
            let speaks = n.contains("ACQUI")
                || ["SURVEY", "CAPTURE", "COLLECT"]
                    .iter()
                    .any(|w| n.contains(w) && (n.contains("DATE") || n.contains("TIME")));
            speaks.then(|| dated(&value)).flatten()
        });
        if found.is_some() {
            return found;
        }
    }
    ascii(dec, Tag::DateTime).and_then(|t| dated(&t))
}

/// The (name, value) of each `<Item name="...">value</Item>` of GDAL's metadata XML, the
/// entities of the value decoded.
fn gdal_items(xml: &str) -> impl Iterator<Item = (String, String)> + '_ {
    xml.split("<Item").skip(1).filter_map(|item| {
        let (head, rest) = item.split_once('>')?;
        let name = head.split("name=\"").nth(1)?.split('"').next()?;
        let value = rest.split("</Item>").next()?;
        let value = value
            .replace("&lt;", "<")
            .replace("&gt;", ">")
            .replace("&quot;", "\"")
            .replace("&apos;", "'")
            .replace("&amp;", "&");
        Some((name.to_string(), value))
    })
}
