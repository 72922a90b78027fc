//! The CRS a file describes, as [`patchwork_crs`] reads it: a WKT (a `.prj`, a GeoTIFF
//! citation), or GeoTIFF keys, whether they name an EPSG code or give a user-defined
//! projection by its parameters. What cannot be read is named, so that the error can say what
//! the file held.

use patchwork_crs::vertical::VerticalCrs;
use patchwork_crs::Crs;

/// What a file says of its CRS.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FileCrs {
    /// The horizontal CRS, where the file names one that can be read.
    pub crs: Option<Crs>,
    /// A CRS the file describes that could not be read, by name (for the error).
    pub unreadable: Option<String>,
    /// The vertical CRS, where the file names one.
    pub vertical: Option<VerticalCrs>,
}

impl FileCrs {
    /// The horizontal CRS's EPSG code, where it has one.
    pub fn epsg(&self) -> Option<u32> {
        self.crs.as_ref().and_then(|c| c.epsg_code())
    }

    /// The CRS of a WKT text (or any other definition [`Crs::parse`] reads).
    ///
    /// A WKT too incomplete to define a CRS (no projection parameters, say) that bears the
    /// exact name of an EPSG CRS is that CRS, as GDAL would take it.
    pub fn of_text(text: &str) -> FileCrs {
        match Crs::parse(text) {
            Ok(c) => FileCrs {
                crs: Some(c),
                unreadable: None,
                vertical: VerticalCrs::of_compound(text),
            },
            Err(e) => match first_name(text).and_then(by_name) {
                Some(c) => FileCrs {
                    crs: Some(c),
                    unreadable: None,
                    vertical: None,
                },
                None => FileCrs {
                    crs: None,
                    unreadable: Some(e.to_string()),
                    vertical: None,
                },
            },
        }
    }
}

/// A CRS name fit to repeat in a message: one that looks like a name (at most 80 letters,
/// digits, spaces and `_-/.,:()+'`), else a description. Files are not quoted at large.
pub fn crs_label(name: &str) -> String {
    let looks_like_a_name = !name.is_empty()
        && name.len() <= 80
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || " _-/.,:()+'".contains(c));
    if looks_like_a_name {
        name.to_string()
    } else {
        "a CRS without a readable name".to_string()
    }
}

/// The name of a WKT's outermost node: its first quoted string.
fn first_name(text: &str) -> Option<&str> {
    let a = text.find('"')?;
    let b = text[a + 1..].find('"')?;
    Some(&text[a + 1..a + 1 + b])
}

/// The EPSG CRS whose registry name is `name` (case and runs of spaces aside), as a GeoTIFF
/// citation such as "WGS 84 / UTM zone 33S" names one.
pub fn by_name(name: &str) -> Option<Crs> {
    let norm = |s: &str| {
        s.split_whitespace()
            .collect::<Vec<_>>()
            .join(" ")
            .to_ascii_lowercase()
    };
    let want = norm(name);
    if want.is_empty() || want.len() > 120 {
        return None;
    }
    (1024..32768u32)
        .find(|&c| {
            proj_core::lookup_epsg(c)
                .is_some_and(|d| (d.is_projected() || d.is_geographic()) && norm(d.name()) == want)
        })
        .and_then(|c| Crs::epsg(c).ok())
}

/// The parts of a user-defined GeoTIFF CRS, as its keys give them (GeoTIFF 1.1, §7).
#[derive(Clone, Debug, Default)]
pub struct GeoTiffCrs<'a> {
    /// GeographicTypeGeoKey, GeogGeodeticDatumGeoKey and GeogEllipsoidGeoKey, where codes.
    pub geographic: Option<u16>,
    /// See `geographic`.
    pub datum: Option<u16>,
    /// See `geographic`.
    pub ellipsoid: Option<u16>,
    /// GeogSemiMajorAxisGeoKey and GeogInvFlatteningGeoKey (or GeogSemiMinorAxisGeoKey).
    pub semi_major: Option<f64>,
    /// See `semi_major`.
    pub inv_flattening: Option<f64>,
    /// See `semi_major`.
    pub semi_minor: Option<f64>,
    /// GeogTOWGS84GeoKey: 3 or 7 Helmert parameters.
    pub towgs84: Option<Vec<f64>>,
    /// ProjectionGeoKey (a code of a standard projection, such as 16031 for UTM zone 31N).
    pub projection: Option<u16>,
    /// ProjCoordTransGeoKey and the parameters, by key.
    pub transform: Option<u16>,
    /// See `transform`.
    pub params: Vec<(u16, f64)>,
    /// ProjLinearUnitsGeoKey.
    pub linear_units: Option<u16>,
    /// GTCitationGeoKey (or the geographic citation): the CRS's name, for messages.
    pub name: &'a str,
}

// Projection parameter keys.
const STD_PARALLEL1: u16 = 3078;
const STD_PARALLEL2: u16 = 3079;
const NAT_ORIGIN_LONG: u16 = 3080;
const NAT_ORIGIN_LAT: u16 = 3081;
const FALSE_EASTING: u16 = 3082;
const FALSE_NORTHING: u16 = 3083;
const FALSE_ORIGIN_LONG: u16 = 3084;
const FALSE_ORIGIN_LAT: u16 = 3085;
const FALSE_ORIGIN_EASTING: u16 = 3086;
const FALSE_ORIGIN_NORTHING: u16 = 3087;
const CENTER_LONG: u16 = 3088;
const CENTER_LAT: u16 = 3089;
const SCALE_AT_NAT_ORIGIN: u16 = 3092;
const STRAIGHT_VERT_POLE_LONG: u16 = 3095;

impl GeoTiffCrs<'_> {
    /// The geographic part as WKT 1: the registry's CRS where a code names it (its datum
    /// code names its geographic CRS, 2000 below it, for EPSG's datums), else one built from
    /// the ellipsoid's figures and any shift to WGS 84.
    fn geogcs(&self) -> Option<String> {
        let code = self
            .geographic
            .filter(|&c| c != 0 && c != super::geotiff::USER_DEFINED)
            .map(u32::from)
            .or_else(|| {
                self.datum
                    .filter(|&d| (6000..7000).contains(&d))
                    .map(|d| u32::from(d) - 2000)
            });
        if let Some(code) = code {
            if let Some(w) = proj_core::lookup_epsg(code)
                .filter(|d| d.is_geographic())
                .and_then(|d| proj_wkt::to_wkt(&d).ok())
            {
                // A declared shift overrides the registry's choice, as GDAL reads it.
                return Some(match &self.towgs84 {
                    Some(t) => with_towgs84(&w, t),
                    None => w,
                });
            }
        }
        let (a, rf) = match self.ellipsoid {
            Some(7030) => (6_378_137.0, 298.257_223_563),
            Some(7019) => (6_378_137.0, 298.257_222_101),
            Some(7022) => (6_378_388.0, 297.0),
            Some(7004) => (6_377_397.155, 299.152_812_8),
            _ => {
                let a = self.semi_major?;
                let rf = self.inv_flattening.or_else(|| {
                    let b = self.semi_minor?;
                    (a > b).then(|| a / (a - b))
                })?;
                (a, rf)
            }
        };
        let shift = self
            .towgs84
            .as_ref()
            .map(|t| format!(",TOWGS84[{}]", join(t)))
            .unwrap_or_default();
        Some(format!(
            "GEOGCS[\"unknown\",DATUM[\"unknown\",SPHEROID[\"unknown\",{a},{rf}]{shift}],\
             PRIMEM[\"Greenwich\",0],UNIT[\"degree\",0.0174532925199433]]"
        ))
    }

    /// The CRS, as WKT 1 built from the keys; None when they do not define one.
    pub fn wkt(&self, projected: bool) -> Option<String> {
        let geog = self.geogcs()?;
        if !projected {
            return Some(geog);
        }
        let p = |k: u16| self.params.iter().find(|(id, _)| *id == k).map(|(_, v)| *v);
        let unit = match self.linear_units {
            None | Some(9001) => "UNIT[\"metre\",1]".to_string(),
            Some(9002) => "UNIT[\"foot\",0.3048]".into(),
            Some(9003) => "UNIT[\"US survey foot\",0.304800609601219]".into(),
            Some(_) => return None,
        };
        let (method, params): (&str, Vec<(&str, f64)>) = match (self.projection, self.transform) {
            // EPSG's UTM projection codes: 16001–16060 north, 16101–16160 south.
            (Some(c @ 16001..=16060), _) | (Some(c @ 16101..=16160), _) => {
                let south = c > 16100;
                let zone = f64::from(c - if south { 16100 } else { 16000 });
                (
                    "Transverse_Mercator",
                    vec![
                        ("latitude_of_origin", 0.0),
                        ("central_meridian", 6.0 * zone - 183.0),
                        ("scale_factor", 0.9996),
                        ("false_easting", 500_000.0),
                        ("false_northing", if south { 10_000_000.0 } else { 0.0 }),
                    ],
                )
            }
            (_, Some(1)) => (
                "Transverse_Mercator",
                vec![
                    ("latitude_of_origin", p(NAT_ORIGIN_LAT).unwrap_or(0.0)),
                    ("central_meridian", p(NAT_ORIGIN_LONG)?),
                    ("scale_factor", p(SCALE_AT_NAT_ORIGIN)?),
                    ("false_easting", p(FALSE_EASTING).unwrap_or(0.0)),
                    ("false_northing", p(FALSE_NORTHING).unwrap_or(0.0)),
                ],
            ),
            (_, Some(7)) => (
                "Mercator_1SP",
                vec![
                    ("central_meridian", p(NAT_ORIGIN_LONG).unwrap_or(0.0)),
                    ("scale_factor", p(SCALE_AT_NAT_ORIGIN).unwrap_or(1.0)),
                    ("false_easting", p(FALSE_EASTING).unwrap_or(0.0)),
                    ("false_northing", p(FALSE_NORTHING).unwrap_or(0.0)),
                ],
            ),
            (_, Some(8)) => (
                "Lambert_Conformal_Conic_2SP",
                vec![
                    ("standard_parallel_1", p(STD_PARALLEL1)?),
                    ("standard_parallel_2", p(STD_PARALLEL2)?),
                    ("latitude_of_origin", p(FALSE_ORIGIN_LAT)?),
                    ("central_meridian", p(FALSE_ORIGIN_LONG)?),
                    ("false_easting", p(FALSE_ORIGIN_EASTING).unwrap_or(0.0)),
                    ("false_northing", p(FALSE_ORIGIN_NORTHING).unwrap_or(0.0)),
                ],
            ),
            (_, Some(9)) => (
                "Lambert_Conformal_Conic_1SP",
                vec![
                    ("latitude_of_origin", p(NAT_ORIGIN_LAT)?),
                    ("central_meridian", p(NAT_ORIGIN_LONG)?),
                    ("scale_factor", p(SCALE_AT_NAT_ORIGIN).unwrap_or(1.0)),
                    ("false_easting", p(FALSE_EASTING).unwrap_or(0.0)),
                    ("false_northing", p(FALSE_NORTHING).unwrap_or(0.0)),
                ],
            ),
            (_, Some(10)) => (
                "Lambert_Azimuthal_Equal_Area",
                vec![
                    ("latitude_of_center", p(CENTER_LAT)?),
                    ("longitude_of_center", p(CENTER_LONG)?),
                    ("false_easting", p(FALSE_EASTING).unwrap_or(0.0)),
                    ("false_northing", p(FALSE_NORTHING).unwrap_or(0.0)),
                ],
            ),
            (_, Some(11)) => (
                "Albers_Conic_Equal_Area",
                vec![
                    ("standard_parallel_1", p(STD_PARALLEL1)?),
                    ("standard_parallel_2", p(STD_PARALLEL2)?),
                    ("latitude_of_center", p(NAT_ORIGIN_LAT)?),
                    ("longitude_of_center", p(NAT_ORIGIN_LONG)?),
                    ("false_easting", p(FALSE_EASTING).unwrap_or(0.0)),
                    ("false_northing", p(FALSE_NORTHING).unwrap_or(0.0)),
                ],
            ),
            (_, Some(15)) => (
                "Polar_Stereographic",
                vec![
                    ("latitude_of_origin", p(NAT_ORIGIN_LAT)?),
                    ("central_meridian", p(STRAIGHT_VERT_POLE_LONG)?),
                    ("scale_factor", p(SCALE_AT_NAT_ORIGIN).unwrap_or(1.0)),
                    ("false_easting", p(FALSE_EASTING).unwrap_or(0.0)),
                    ("false_northing", p(FALSE_NORTHING).unwrap_or(0.0)),
                ],
            ),
            (_, Some(16)) => (
                "Oblique_Stereographic",
                vec![
                    ("latitude_of_origin", p(NAT_ORIGIN_LAT)?),
                    ("central_meridian", p(NAT_ORIGIN_LONG)?),
                    ("scale_factor", p(SCALE_AT_NAT_ORIGIN).unwrap_or(1.0)),
                    ("false_easting", p(FALSE_EASTING).unwrap_or(0.0)),
                    ("false_northing", p(FALSE_NORTHING).unwrap_or(0.0)),
                ],
            ),
            _ => return None,
        };
        let params: String = params
            .iter()
            .map(|(k, v)| format!(",PARAMETER[\"{k}\",{v}]"))
            .collect();
        let name = crs_label(self.name).replace('"', "");
        Some(format!(
            "PROJCS[\"{name}\",{geog},PROJECTION[\"{method}\"]{params},{unit}]"
        ))
    }
}

fn join(v: &[f64]) -> String {
    v.iter()
        .map(|x| x.to_string())
        .collect::<Vec<_>>()
        .join(",")
}

/// A WKT 1 GEOGCS with a TOWGS84 node put in its DATUM (replacing any there).
fn with_towgs84(geogcs: &str, t: &[f64]) -> String {
    let Some(d) = geogcs.find("DATUM[") else {
        return geogcs.to_string();
    };
    // The DATUM node ends where its brackets balance.
    let mut depth = 0usize;
    let mut end = None;
    for (i, ch) in geogcs[d..].char_indices() {
        match ch {
            '[' => depth += 1,
            ']' => {
                depth -= 1;
                if depth == 0 {
                    end = Some(d + i);
                    break;
                }
            }
            _ => {}
        }
    }
    let Some(end) = end else {
        return geogcs.to_string();
    };
    format!("{},TOWGS84[{}]{}", &geogcs[..end], join(t), &geogcs[end..])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn esri_ogc_and_cited_crss_are_read_by_the_library() {
        let esri = r#"PROJCS["WGS_1984_UTM_Zone_31N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]],PRIMEM["Greenwich",0.0],UNIT["Degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],PARAMETER["False_Easting",500000.0],PARAMETER["False_Northing",0.0],PARAMETER["Central_Meridian",3.0],PARAMETER["Scale_Factor",0.9996],PARAMETER["Latitude_Of_Origin",0.0],UNIT["Meter",1.0]]"#;
        let f = FileCrs::of_text(esri);
        assert_eq!(f.crs.and_then(|c| c.epsg_code()), Some(32631));
        let lcc = r#"PROJCS["RGF93_Lambert_93",GEOGCS["GCS_RGF_1993",DATUM["D_RGF_1993",SPHEROID["GRS_1980",6378137.0,298.257222101]],PRIMEM["Greenwich",0.0],UNIT["Degree",0.0174532925199433]],PROJECTION["Lambert_Conformal_Conic"],PARAMETER["False_Easting",700000.0],PARAMETER["False_Northing",6600000.0],PARAMETER["Central_Meridian",3.0],PARAMETER["Standard_Parallel_1",49.0],PARAMETER["Standard_Parallel_2",44.0],PARAMETER["Latitude_Of_Origin",46.5],UNIT["Meter",1.0]]"#;
        assert_eq!(
            FileCrs::of_text(lcc).crs.and_then(|c| c.epsg_code()),
            Some(2154)
        );
        assert_eq!(
            by_name("WGS 84 / UTM zone 33S").and_then(|c| c.epsg_code()),
            Some(32733)
        );
        assert!(by_name("no such CRS").is_none());
        // A compound CRS gives its vertical part too.
        let compound = format!(
            "COMPD_CS[\"x\",{esri},VERT_CS[\"EGM96 height\",VERT_DATUM[\"EGM96 geoid\",2005,AUTHORITY[\"EPSG\",\"5171\"]],UNIT[\"metre\",1],AUTHORITY[\"EPSG\",\"5773\"]]]"
        );
        let f = FileCrs::of_text(&compound);
        assert_eq!(f.crs.and_then(|c| c.epsg_code()), Some(32631));
        assert_eq!(
            f.vertical.map(|v| v.key().to_string()).as_deref(),
            Some("EPSG:5773")
        );
        let bad = FileCrs::of_text("PROJCS[\"Mystery\",PROJECTION[\"Nowhere\"]]");
        assert!(bad.crs.is_none() && bad.unreadable.unwrap().contains("Mystery"));
    }

    #[test]
    fn user_defined_geotiff_projections_are_built_from_their_parameters() {
        let k = GeoTiffCrs {
            datum: Some(6171),
            transform: Some(8),
            params: vec![
                (STD_PARALLEL1, 49.0),
                (STD_PARALLEL2, 44.0),
                (FALSE_ORIGIN_LAT, 46.5),
                (FALSE_ORIGIN_LONG, 3.0),
                (FALSE_ORIGIN_EASTING, 700_000.0),
                (FALSE_ORIGIN_NORTHING, 6_600_000.0),
            ],
            name: "Lambert-93",
            ..Default::default()
        };
        let c = Crs::parse(&k.wkt(true).unwrap()).unwrap();
        assert_eq!(c.epsg_code(), Some(2154), "{:?}", k.wkt(true));
        // UTM by its projection code on GRS 80 with a zero shift: a CRS of its own, that
        // transforms like the WGS 84 zone.
        let k = GeoTiffCrs {
            ellipsoid: Some(7019),
            towgs84: Some(vec![0.0; 7]),
            projection: Some(16015),
            ..Default::default()
        };
        let c = Crs::parse(&k.wkt(true).unwrap()).unwrap();
        let t = patchwork_crs::Transform::new(&c, &Crs::epsg(32615).unwrap()).unwrap();
        let p = t.apply([431_000.0, 4_870_000.0]).unwrap();
        assert!((p[0] - 431_000.0).abs() < 1e-3 && (p[1] - 4_870_000.0).abs() < 1e-3);
    }
}
