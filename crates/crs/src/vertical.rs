//! Vertical CRSs: what a survey's heights are measured from (a geoid model such as EGM96 or
//! EGM2008, a national levelling datum such as NAVD88, or the ellipsoid), and how heights are
//! carried from one to another through geoid grids.
//!
//! A gravity-related height H and the ellipsoidal height h of the same point differ by the
//! geoid undulation N of that datum's geoid model there: h = H + N. Going from datum A to
//! datum B is then H_B = H_A + N_A − N_B, with N of the ellipsoid itself 0. Each N comes from
//! a grid of undulations over longitude and latitude (the GeoTIFFs PROJ distributes, such as
//! `us_nga_egm96_15.tif`), interpolated bilinearly; what that interpolation can miss is
//! estimated from the grid's own curvature and counted in the survey's ε.

use super::CrsError;
use std::sync::Arc;

/// A vertical CRS: the registry's, by EPSG code, or heights above the WGS 84 ellipsoid.
#[derive(Clone)]
pub struct VerticalCrs(Arc<Inner>);

struct Inner {
    key: String,
    name: String,
    /// Metres per unit of its heights.
    unit_m: f64,
    /// The vertical datum's EPSG code, for gravity-related heights; None for ellipsoidal ones.
    datum: Option<u32>,
    ellipsoidal: bool,
}

/// What names heights above the ellipsoid in a sidecar or the config.
pub const ELLIPSOIDAL: &str = "ellipsoidal";

impl VerticalCrs {
    /// `EPSG:5773` (or `5773`) for a vertical CRS of the registry, or `ellipsoidal` for heights
    /// above the WGS 84 ellipsoid (EPSG:4979's).
    pub fn parse(text: &str) -> Result<VerticalCrs, CrsError> {
        let t = text.trim();
        let bad = |why: &str| CrsError::Unreadable {
            what: format!("{t:?}"),
            why: why.into(),
        };
        if t.eq_ignore_ascii_case(ELLIPSOIDAL) || t.eq_ignore_ascii_case("EPSG:4979") {
            return Ok(Self::ellipsoidal());
        }
        let digits = t
            .strip_prefix("EPSG:")
            .or_else(|| t.strip_prefix("epsg:"))
            .unwrap_or(t);
        let code: u32 = digits.parse().map_err(|_| {
            bad("a vertical CRS is named by its EPSG code (\"EPSG:5773\") or as \"ellipsoidal\"")
        })?;
        Self::epsg(code).ok_or_else(|| bad("the registry has no vertical CRS of that code"))
    }

    /// The registry's vertical CRS of an EPSG code.
    pub fn epsg(code: u32) -> Option<VerticalCrs> {
        let d = proj_core::lookup_vertical_epsg(code)?;
        Some(Self::from_def(&d))
    }

    fn from_def(d: &proj_core::VerticalCrsDef) -> VerticalCrs {
        let ellipsoidal = matches!(
            d.kind(),
            proj_core::VerticalCrsKind::EllipsoidalHeight { .. }
        );
        if ellipsoidal {
            return Self::ellipsoidal();
        }
        VerticalCrs(Arc::new(Inner {
            key: format!("EPSG:{}", d.epsg()),
            name: d.name().to_string(),
            unit_m: d.linear_unit_to_meter(),
            datum: d.vertical_datum_epsg(),
            ellipsoidal: false,
        }))
    }

    /// Heights above the WGS 84 ellipsoid, in metres.
    pub fn ellipsoidal() -> VerticalCrs {
        VerticalCrs(Arc::new(Inner {
            key: ELLIPSOIDAL.into(),
            name: "ellipsoidal height".into(),
            unit_m: 1.0,
            datum: None,
            ellipsoidal: true,
        }))
    }

    /// The vertical part of a compound CRS definition (a WKT `COMPD_CS` or `COMPOUNDCRS`, or
    /// `EPSG:h+v`), if it has one the registry knows.
    pub fn of_compound(text: &str) -> Option<VerticalCrs> {
        let def = proj_wkt::parse_crs(text).ok()?;
        let v = def.vertical_crs()?;
        match v.epsg() {
            0 => Some(Self::from_def(v)),
            code => Self::epsg(code).or_else(|| Some(Self::from_def(v))),
        }
    }

    /// `EPSG:n`, or `ellipsoidal`: what the store records, and a text [`Self::parse`] reads.
    pub fn key(&self) -> &str {
        &self.0.key
    }

    /// The CRS's name, as the registry gives it.
    pub fn name(&self) -> &str {
        &self.0.name
    }

    /// Metres per unit of its heights (0.3048… for a CRS in feet).
    pub fn unit_m(&self) -> f64 {
        self.0.unit_m
    }

    /// Whether heights are above the WGS 84 ellipsoid rather than a geoid or levelling datum.
    pub fn is_ellipsoidal(&self) -> bool {
        self.0.ellipsoidal
    }

    /// Whether heights in both are measured from the same surface, whatever their units.
    pub fn same_reference(&self, o: &VerticalCrs) -> bool {
        match (self.0.ellipsoidal, o.0.ellipsoidal) {
            (true, true) => true,
            (false, false) => match (self.0.datum, o.0.datum) {
                (Some(a), Some(b)) => a == b,
                _ => self.0.key == o.0.key,
            },
            _ => false,
        }
    }

    /// How to name it in a message: `EPSG:5773 (EGM96 height)`.
    pub fn label(&self) -> String {
        if self.0.ellipsoidal {
            return "ellipsoidal heights (WGS 84)".into();
        }
        format!("{} ({})", self.0.key, self.0.name)
    }
}

impl PartialEq for VerticalCrs {
    fn eq(&self, o: &VerticalCrs) -> bool {
        self.0.key == o.0.key
    }
}

impl Eq for VerticalCrs {}

impl std::hash::Hash for VerticalCrs {
    fn hash<H: std::hash::Hasher>(&self, h: &mut H) {
        self.0.key.hash(h)
    }
}

impl std::fmt::Debug for VerticalCrs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0.key)
    }
}

impl std::fmt::Display for VerticalCrs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.label())
    }
}

impl serde::Serialize for VerticalCrs {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.key())
    }
}

impl<'de> serde::Deserialize<'de> for VerticalCrs {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<VerticalCrs, D::Error> {
        let key = String::deserialize(d)?;
        VerticalCrs::parse(&key).map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn registry_codes_and_the_ellipsoid_are_named_and_compared() {
        let egm96 = VerticalCrs::parse("EPSG:5773").unwrap();
        assert_eq!(egm96.name(), "EGM96 height");
        let egm08 = VerticalCrs::parse("3855").unwrap();
        assert!(!egm96.same_reference(&egm08));
        assert!(egm96.same_reference(&VerticalCrs::epsg(5773).unwrap()));
        let e = VerticalCrs::parse("ellipsoidal").unwrap();
        assert!(e.is_ellipsoidal() && !e.same_reference(&egm96));
        // NAVD88 in metres and in US feet: the same surface, other units.
        let (m, ft) = (
            VerticalCrs::parse("EPSG:5703").unwrap(),
            VerticalCrs::parse("EPSG:6360").unwrap(),
        );
        assert!(m.same_reference(&ft));
        assert!(
            (ft.unit_m() - 1200.0 / 3937.0).abs() < 1e-12,
            "{}",
            ft.unit_m()
        );
        assert!(VerticalCrs::parse("EPSG:4326").is_err());
        assert!(VerticalCrs::parse("mean sea level").is_err());
    }
}
