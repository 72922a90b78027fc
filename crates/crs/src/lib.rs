//! Coordinate reference systems: what a survey's or a request's coordinates mean, and how a
//! point is carried from one CRS to another. A leaf of the crate: it does no I/O and knows
//! nothing of grids or patches.
//!
//! Definitions and transforms come from `proj-core` and `proj-wkt` (EPSG codes, WKT 1 and 2,
//! PROJ strings, PROJJSON; PROJ's choice of operation between datums), chosen by measurement
//! over the other pure-Rust stack (docs/MODEL.md, "Coordinate reference systems"). This module
//! adds what the store needs on top: one canonical name per CRS, so that two files in the
//! same CRS share a plane whatever words their WKT used ([`Crs::key`]); and a fast,
//! bounded-error interpolation of a transform for the millions of points a tile asks for
//! ([`Reprojection`]).
//!
//! Coordinates are always easting (or longitude) first, as GeoTIFF, GDAL's traditional order
//! and every DEM format place them, whatever axis order a WKT declares.

mod lattice;
pub mod vertical;

pub use lattice::{Block as LatticeBlock, Reprojection, BLOCK_SIDE as LATTICE_SIDE};

use proj_core::{AxisOrder, CrsDef};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};
use thiserror::Error;

/// Why a CRS could not be read, or two CRSs could not be joined.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum CrsError {
    /// A text that names or defines no CRS this build can use.
    #[error("{what} is not a CRS this build can use: {why}")]
    Unreadable {
        /// What was given, as a message may repeat it: the text quoted when short, else its name.
        what: String,
        /// The reason, from the parser or from the checks after it.
        why: String,
    },
    /// Two CRSs between which no transformation could be set up.
    #[error("there is no transformation from {from} to {to}: {why}")]
    NoTransform {
        /// The source CRS's [`Crs::label`].
        from: String,
        /// The target CRS's [`Crs::label`].
        to: String,
        /// The reason the transform library gave.
        why: String,
    },
}

/// A horizontal CRS. Two values are equal when their [`Crs::key`]s are: the same EPSG code, or
/// the same canonical definition.
#[derive(Clone)]
pub struct Crs(Arc<Inner>);

struct Inner {
    key: String,
    epsg: Option<u32>,
    name: String,
    geographic: bool,
    /// Metres per unit of a projected CRS's coordinates; 0 for a geographic one.
    unit_m: f64,
}

impl Crs {
    /// Reads a CRS from any text that names or defines one: `EPSG:32631` (or `32631`), WKT 1
    /// or 2 (a `.prj`, a GeoTIFF citation), a PROJ string or PROJJSON. A definition that is an
    /// EPSG CRS (an ESRI `.prj` for a UTM zone, GeoTIFF keys of a user-defined projection) is
    /// given that code. Only the horizontal part of a compound CRS is kept.
    pub fn parse(text: &str) -> Result<Crs, CrsError> {
        let text = text.trim();
        if let Some(c) = cache()
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get(text)
        {
            return Ok(c.clone());
        }
        let crs = Self::read(text)?;
        let mut cache = cache()
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        // Bounded: texts come from files, and a few hundred distinct CRSs is already many.
        if cache.len() > 4096 {
            cache.clear();
        }
        cache.insert(text.to_string(), crs.clone());
        cache.insert(crs.key().to_string(), crs.clone());
        Ok(crs)
    }

    /// The CRS of an EPSG code.
    pub fn epsg(code: u32) -> Result<Crs, CrsError> {
        Self::parse(&format!("EPSG:{code}"))
    }

    /// Geographic WGS 84 (EPSG:4326), longitude first.
    pub fn wgs84() -> Crs {
        static WGS84: OnceLock<Crs> = OnceLock::new();
        WGS84
            .get_or_init(|| Crs::epsg(4326).expect("EPSG:4326 is in the registry"))
            .clone()
    }

    fn read(text: &str) -> Result<Crs, CrsError> {
        let what = describe(text);
        let bad = |why: String| CrsError::Unreadable {
            what: what.clone(),
            why,
        };
        if text.is_empty() {
            return Err(bad("it is empty".into()));
        }
        let parsed = proj_wkt::parse_crs(text).map_err(|e| bad(e.to_string()))?;
        let def = parsed
            .horizontal_crs()
            .ok_or_else(|| bad("it has no horizontal part".into()))?
            .with_axis_order(AxisOrder::EastNorth);
        if !(def.is_geographic() || def.is_projected()) {
            return Err(bad(
                "it is neither geographic nor projected (a geocentric CRS?)".into(),
            ));
        }
        let epsg = match def.epsg() {
            0 => identify(&def),
            c => Some(c),
        }
        // A definition that declares its own shift to WGS 84 is that definition, not the
        // registry's CRS of the same code, whose datum operation may differ.
        .filter(|_| !declares_shift(&def) || def.epsg() != 0);
        let key = match epsg {
            Some(c) => format!("EPSG:{c}"),
            None => proj_wkt::to_wkt2(&def).unwrap_or_else(|_| text.to_string()),
        };
        let name = match epsg.and_then(proj_core::lookup_epsg) {
            Some(r) if !r.name().is_empty() => r.name().to_string(),
            _ if !def.name().is_empty() => def.name().to_string(),
            _ => first_quoted(text).unwrap_or_default(),
        };
        let unit_m = def
            .as_projected()
            .map(|p| p.linear_unit_to_meter())
            .unwrap_or(0.0);
        // The key must be usable as a definition by itself: that is how it is stored.
        if epsg.is_none() {
            proj_wkt::parse_crs(&key).map_err(|e| bad(format!("its definition {e}")))?;
        }
        Ok(Crs(Arc::new(Inner {
            key,
            epsg,
            name,
            geographic: def.is_geographic(),
            unit_m,
        })))
    }

    /// `EPSG:n`, or the canonical WKT 2 of a definition no EPSG code matches: what the store
    /// records, what identifies the CRS, and a definition [`Crs::parse`] reads back.
    pub fn key(&self) -> &str {
        &self.0.key
    }

    /// The EPSG code, given or identified from an equivalent definition; None where no EPSG CRS
    /// matches.
    pub fn epsg_code(&self) -> Option<u32> {
        self.0.epsg
    }

    /// The CRS's name, as the registry or the definition gives it (may be empty).
    pub fn name(&self) -> &str {
        &self.0.name
    }

    /// Longitude and latitude in degrees.
    pub fn is_geographic(&self) -> bool {
        self.0.geographic
    }

    /// Metres per coordinate unit of a projected CRS; None for a geographic one.
    pub fn unit_m(&self) -> Option<f64> {
        (!self.0.geographic).then_some(self.0.unit_m)
    }

    /// How to name the CRS in a message: `EPSG:32631 (WGS 84 / UTM zone 31N)`, or its name
    /// for one without a code.
    pub fn label(&self) -> String {
        match (self.0.epsg, self.0.name.is_empty()) {
            (Some(c), false) => format!("EPSG:{c} ({})", self.0.name),
            (Some(c), true) => format!("EPSG:{c}"),
            (None, false) => format!("\"{}\"", self.0.name),
            (None, true) => "a CRS without a name or code".into(),
        }
    }

    /// Its definition as WKT 1, for a GeoTIFF citation or a `.prj`.
    pub fn wkt1(&self) -> Option<String> {
        proj_wkt::parse_crs(&self.0.key)
            .ok()
            .and_then(|d| proj_wkt::to_wkt(&d).ok())
    }
}

impl PartialEq for Crs {
    fn eq(&self, o: &Crs) -> bool {
        Arc::ptr_eq(&self.0, &o.0) || self.0.key == o.0.key
    }
}

impl Eq for Crs {}

impl std::hash::Hash for Crs {
    fn hash<H: std::hash::Hasher>(&self, h: &mut H) {
        self.0.key.hash(h)
    }
}

impl std::fmt::Debug for Crs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0.epsg {
            Some(c) => write!(f, "EPSG:{c}"),
            None => write!(f, "Crs({:?})", self.0.name),
        }
    }
}

impl std::fmt::Display for Crs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.label())
    }
}

impl serde::Serialize for Crs {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.key())
    }
}

impl<'de> serde::Deserialize<'de> for Crs {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Crs, D::Error> {
        let key = String::deserialize(d)?;
        Crs::parse(&key).map_err(serde::de::Error::custom)
    }
}

fn cache() -> &'static Mutex<HashMap<String, Crs>> {
    static CACHE: OnceLock<Mutex<HashMap<String, Crs>>> = OnceLock::new();
    CACHE.get_or_init(Default::default)
}

/// Whether a definition carries its own datum shift (a TOWGS84, a bound CRS).
fn declares_shift(def: &CrsDef) -> bool {
    def.datum().declares_shift()
}

/// The EPSG code of a definition that carries none, where the registry holds an equivalent
/// CRS on the same datum (the same projection and parameters, unit and axis order): the
/// smallest such code, so that the answer never depends on the order of a scan. Only a
/// definition whose datum the registry knows (by its code or name) is identified: many datums
/// share an ellipsoid and a null shift to WGS 84 (NAD83 and its realisations, ETRS89,
/// RGF93, ...), and their CRSs are equivalent for a transformation but not the same CRS. A
/// scan of the registry takes about 10 ms.
fn identify(def: &CrsDef) -> Option<u32> {
    let datum = def.datum().epsg();
    if datum == 0 {
        return None;
    }
    // EPSG numbers its geographic and projected CRSs below 32768, bar a few compound and
    // vertical ones that are not horizontal CRSs anyway.
    (1024..32768u32).find(|&code| {
        proj_core::lookup_epsg(code).is_some_and(|r| {
            (r.is_geographic() || r.is_projected())
                && r.datum().epsg() == datum
                && r.semantically_equivalent(def)
        })
    })
}

/// A CRS text fit to repeat in a message: its code, or its name, never the whole text.
fn describe(text: &str) -> String {
    if text.len() <= 40 && !text.contains('[') && !text.contains('{') {
        return format!("{text:?}");
    }
    match first_quoted(text) {
        Some(n) => format!("the CRS \"{n}\""),
        None => "the CRS given".into(),
    }
}

/// The first quoted string of a WKT or PROJJSON text, at most 80 characters of the usual
/// name characters: its name.
fn first_quoted(text: &str) -> Option<String> {
    let a = text.find('"')?;
    let b = text[a + 1..].find('"')?;
    let n = &text[a + 1..a + 1 + b];
    let fit = !n.is_empty()
        && n.len() <= 80
        && n.chars()
            .all(|c| c.is_alphanumeric() || " _-/.,:()+'".contains(c));
    fit.then(|| n.to_string())
}

/// The exact transformation between two CRSs, as PROJ would choose it; identity between
/// equal ones.
pub struct Transform {
    from: Crs,
    to: Crs,
    op: Option<proj_core::Transform>,
}

impl Transform {
    /// The transformation from `from` to `to`; the identity, with no operation looked up,
    /// where they are equal.
    pub fn new(from: &Crs, to: &Crs) -> Result<Transform, CrsError> {
        if from == to {
            return Ok(Transform {
                from: from.clone(),
                to: to.clone(),
                op: None,
            });
        }
        let op =
            proj_wkt::transform_from_crs_strings_horizontal(from.key(), to.key()).map_err(|e| {
                CrsError::NoTransform {
                    from: from.label(),
                    to: to.label(),
                    why: e.to_string(),
                }
            })?;
        Ok(Transform {
            from: from.clone(),
            to: to.clone(),
            op: Some(op),
        })
    }

    /// The source CRS.
    pub fn from(&self) -> &Crs {
        &self.from
    }

    /// The target CRS.
    pub fn to(&self) -> &Crs {
        &self.to
    }

    /// Whether the two CRSs are equal, so that [`Transform::apply`] returns every point unchanged.
    pub fn is_identity(&self) -> bool {
        self.op.is_none()
    }

    /// The point in the target CRS; None where the transformation is not defined (outside a
    /// projection's domain).
    #[inline]
    pub fn apply(&self, p: [f64; 2]) -> Option<[f64; 2]> {
        let Some(op) = &self.op else {
            return Some(p);
        };
        if !(p[0].is_finite() && p[1].is_finite()) {
            return None;
        }
        let (x, y) = op.convert((p[0], p[1])).ok()?;
        (x.is_finite() && y.is_finite()).then_some([x, y])
    }
}

/// Metres per degree of longitude and of latitude at latitude `lat` (degrees), on the WGS 84
/// ellipsoid: the local scale of a geographic CRS.
pub fn metres_per_degree(lat: f64) -> [f64; 2] {
    let p = lat.to_radians();
    let m_lat =
        111_132.92 - 559.82 * (2.0 * p).cos() + 1.175 * (4.0 * p).cos() - 0.0023 * (6.0 * p).cos();
    let m_lon = 111_412.84 * p.cos() - 93.5 * (3.0 * p).cos() + 0.118 * (5.0 * p).cos();
    [m_lon, m_lat]
}

#[cfg(test)]
mod tests {
    use super::*;

    const ESRI_UTM31: &str = r#"PROJCS["WGS_1984_UTM_Zone_31N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]],PRIMEM["Greenwich",0.0],UNIT["Degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],PARAMETER["False_Easting",500000.0],PARAMETER["False_Northing",0.0],PARAMETER["Central_Meridian",3.0],PARAMETER["Scale_Factor",0.9996],PARAMETER["Latitude_Of_Origin",0.0],UNIT["Meter",1.0]]"#;

    #[test]
    fn codes_wkt_and_proj_strings_of_one_crs_are_one_crs() {
        let a = Crs::parse("EPSG:32631").unwrap();
        let b = Crs::parse(ESRI_UTM31).unwrap();
        let c = Crs::parse("+proj=utm +zone=31 +datum=WGS84 +units=m +no_defs").unwrap();
        let d = Crs::parse("32631").unwrap();
        assert_eq!(a.key(), "EPSG:32631");
        assert!(a == b && b == c && c == d, "{a:?} {b:?} {c:?} {d:?}");
        assert_eq!(b.epsg_code(), Some(32631));
        assert_eq!(a.name(), "WGS 84 / UTM zone 31N");
        assert!(!a.is_geographic() && Crs::wgs84().is_geographic());
        assert_eq!(a.unit_m(), Some(1.0));
    }

    #[test]
    fn a_definition_without_a_code_keeps_a_key_that_reads_back() {
        // A transverse Mercator zone on GRS 80 with a zero shift to WGS 84: a datum of its
        // own, which no EPSG CRS has.
        let wkt = r#"PROJCS["unnamed",GEOGCS["GRS 1980(IUGG, 1980)",DATUM["unknown",SPHEROID["GRS80",6378137,298.257222101],TOWGS84[0,0,0,0,0,0,0]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],PARAMETER["central_meridian",-93],PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],PARAMETER["false_northing",0],UNIT["metre",1]]"#;
        let c = Crs::parse(wkt).unwrap();
        assert_eq!(c.epsg_code(), None);
        let again = Crs::parse(c.key()).unwrap();
        assert_eq!(c, again);
        // It transforms like the WGS 84 zone it all but is.
        let t = Transform::new(&c, &Crs::wgs84()).unwrap();
        let u = Transform::new(&Crs::epsg(32615).unwrap(), &Crs::wgs84()).unwrap();
        let p = [431_000.0, 4_870_000.0];
        let (a, b) = (t.apply(p).unwrap(), u.apply(p).unwrap());
        assert!(
            (a[0] - b[0]).abs() < 1e-6 && (a[1] - b[1]).abs() < 1e-6,
            "{a:?} {b:?}"
        );
    }

    #[test]
    fn what_is_not_a_crs_is_refused_by_name_not_quoted_at_large() {
        let e = Crs::parse("EPSG:999999").unwrap_err().to_string();
        assert!(e.contains("EPSG:999999"), "{e}");
        let long = format!("PROJCS[\"Bogus\",{}]", "x".repeat(5000));
        let e = Crs::parse(&long).unwrap_err().to_string();
        assert!(e.contains("Bogus") && e.len() < 400, "{e}");
        assert!(Crs::parse("").is_err());
    }

    #[test]
    fn transforms_follow_proj_on_a_known_point() {
        // pyproj 3.7 (PROJ 9.5): EPSG:4326 → EPSG:32631 of (5.0, 44.0).
        let t = Transform::new(&Crs::wgs84(), &Crs::epsg(32631).unwrap()).unwrap();
        let p = t.apply([5.0, 44.0]).unwrap();
        assert!((p[0] - 660_349.410_578_446_5).abs() < 1e-6, "{p:?}");
        assert!((p[1] - 4_873_817.333_440_361).abs() < 1e-6, "{p:?}");
        assert!(Transform::new(&Crs::wgs84(), &Crs::wgs84())
            .unwrap()
            .is_identity());
    }
}
