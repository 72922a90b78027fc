//! Naming a CRS by its EPSG code when a file describes it by parameters instead: WKT in a
//! `.prj` without an authority, or a GeoTIFF whose projection is "user-defined".
//!
//! Only what DEM files commonly carry is recognised: geographic WGS 84, NAD83 and ETRS89, UTM
//! zones on those datums, and Web Mercator. Anything else is reported by name, so that the user
//! can say which code it is in a sidecar.

/// A geodetic datum with EPSG codes of its own.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Datum {
    Wgs84,
    Nad83,
    Etrs89,
}

impl Datum {
    /// The geographic CRS of the datum.
    pub fn geographic(self) -> u32 {
        match self {
            Datum::Wgs84 => 4326,
            Datum::Nad83 => 4269,
            Datum::Etrs89 => 4258,
        }
    }

    /// The UTM zone's projected CRS on this datum, where EPSG defines one.
    pub fn utm(self, zone: u32, north: bool) -> Option<u32> {
        if !(1..=60).contains(&zone) {
            return None;
        }
        match (self, north) {
            (Datum::Wgs84, true) => Some(32600 + zone),
            (Datum::Wgs84, false) => Some(32700 + zone),
            // NAD83 zones 1–23 and ETRS89 zones 28–38 are the ones EPSG numbers this way.
            (Datum::Nad83, true) if zone <= 23 => Some(26900 + zone),
            (Datum::Etrs89, true) if (28..=38).contains(&zone) => Some(25800 + zone),
            _ => None,
        }
    }

    /// The datum a name or citation mentions, if one of ours. A TOWGS84[...] node names the
    /// transformation to WGS 84, not the datum, so it is left out.
    pub fn in_text(text: &str) -> Option<Datum> {
        let t = squash(&without_towgs84(text));
        if t.contains("nad83") || t.contains("northamericandatum1983") {
            Some(Datum::Nad83)
        } else if t.contains("etrs89")
            || t.contains("etrs1989")
            || t.contains("europeanterrestrial")
        {
            Some(Datum::Etrs89)
        } else if t.contains("wgs84")
            || t.contains("wgs1984")
            || t.contains("worldgeodeticsystem1984")
        {
            Some(Datum::Wgs84)
        } else {
            None
        }
    }
}

/// The text with every TOWGS84[...] node removed.
fn without_towgs84(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let upper = text.to_ascii_uppercase();
    let mut i = 0;
    while let Some(k) = upper[i..].find("TOWGS84[") {
        out.push_str(&text[i..i + k]);
        let rest = i + k;
        i = upper[rest..].find(']').map_or(text.len(), |e| rest + e + 1);
    }
    out.push_str(&text[i..]);
    out
}

/// Lower-case letters and digits only: "WGS_1984_UTM_Zone_31N" and "WGS 84 / UTM zone 31N"
/// compare alike.
fn squash(s: &str) -> String {
    s.chars()
        .filter(|c| c.is_ascii_alphanumeric())
        .map(|c| c.to_ascii_lowercase())
        .collect()
}

/// A UTM zone and hemisphere named in text: "UTM zone 31N", "UTM_Zone_31N",
/// "UTM Zone 31, Northern Hemisphere", "utm31s".
pub fn utm_in_text(text: &str) -> Option<(u32, bool)> {
    let t = squash(text);
    let at = t.find("utm")?;
    let rest = t[at + 3..].strip_prefix("zone").unwrap_or(&t[at + 3..]);
    let digits: String = rest.chars().take_while(|c| c.is_ascii_digit()).collect();
    let zone: u32 = digits.parse().ok()?;
    let after = &rest[digits.len()..];
    let north = if after.starts_with("northern") || after.starts_with('n') {
        true
    } else if after.starts_with("southern") || after.starts_with('s') {
        false
    } else {
        return None;
    };
    (1..=60).contains(&zone).then_some((zone, north))
}

/// The UTM zone a Transverse Mercator with these parameters is, if it is one.
pub fn utm_from_parameters(
    central_meridian: f64,
    scale: f64,
    false_easting: f64,
    false_northing: f64,
    latitude_of_origin: f64,
) -> Option<(u32, bool)> {
    let zone = ((central_meridian + 183.0) / 6.0).round();
    let standard = (scale - 0.9996).abs() < 1e-9
        && (false_easting - 500_000.0).abs() < 1e-6
        && latitude_of_origin.abs() < 1e-9
        && (central_meridian - (6.0 * zone - 183.0)).abs() < 1e-9
        && (1.0..=60.0).contains(&zone);
    if !standard {
        return None;
    }
    if false_northing.abs() < 1e-6 {
        Some((zone as u32, true))
    } else if (false_northing - 10_000_000.0).abs() < 1e-6 {
        Some((zone as u32, false))
    } else {
        None
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

/// The EPSG code of a WKT CRS: its own AUTHORITY (or WKT2 ID), else what its name or its
/// parameters identify. Otherwise the error names the CRS the WKT describes.
pub fn epsg_from_wkt(wkt: &str) -> Result<u32, String> {
    if let Some(code) = top_level_authority(wkt) {
        return Ok(code);
    }
    let upper = wkt.to_ascii_uppercase();
    let projected = upper.contains("PROJCS[") || upper.contains("PROJCRS[");
    let name = first_quoted(wkt).unwrap_or_else(|| "a CRS without a name".into());
    let datum = Datum::in_text(wkt);
    if !projected {
        let geographic = upper.contains("GEOGCS[") || upper.contains("GEOGCRS[");
        return match datum {
            Some(d) if geographic => Ok(d.geographic()),
            _ => Err(name),
        };
    }
    let sq = squash(&name);
    if sq.contains("webmercator")
        || sq.contains("pseudomercator")
        || sq.contains("popularvisualisation")
    {
        return Ok(3857);
    }
    let utm = utm_in_text(&name).or_else(|| {
        let p = |keys: &[&str]| parameter(wkt, keys);
        let tm = squash(wkt).contains("transversemercator");
        if !tm {
            return None;
        }
        utm_from_parameters(
            p(&[
                "central_meridian",
                "longitude_of_center",
                "longitude of natural origin",
            ])?,
            p(&["scale_factor", "scale factor at natural origin"])?,
            p(&["false_easting", "false easting"])?,
            p(&["false_northing", "false northing"])?,
            p(&["latitude_of_origin", "latitude of natural origin"]).unwrap_or(0.0),
        )
    });
    match (datum, utm) {
        (Some(d), Some((zone, north))) => d.utm(zone, north).ok_or(name),
        _ => Err(name),
    }
}

/// AUTHORITY["EPSG",..] (or ID["EPSG",..]) attached to the outermost node. Nested authorities
/// (datum, base CRS, units) describe parts, not the CRS itself, and are ignored.
fn top_level_authority(wkt: &str) -> Option<u32> {
    let bytes = wkt.as_bytes();
    let mut depth = 0usize;
    let mut in_quote = false;
    for i in 0..bytes.len() {
        match bytes[i] {
            b'"' => in_quote = !in_quote,
            b'[' | b'(' if !in_quote => depth += 1,
            b']' | b')' if !in_quote => depth = depth.saturating_sub(1),
            _ if !in_quote && depth == 1 => {
                // Compared as bytes: `i` may fall inside a multi-byte character. A match is
                // ASCII, so the text after it starts on a character boundary.
                let rest = &bytes[i..];
                let keyword_start = i == 0 || matches!(bytes[i - 1], b',' | b'[' | b'(' | b' ');
                for kw in ["AUTHORITY[", "ID["] {
                    if keyword_start
                        && rest.len() >= kw.len()
                        && rest[..kw.len()].eq_ignore_ascii_case(kw.as_bytes())
                    {
                        if let Some(code) = parse_authority(&wkt[i + kw.len()..]) {
                            return Some(code);
                        }
                    }
                }
            }
            _ => {}
        }
    }
    None
}

/// `"EPSG","32631"]` or `"EPSG",32631]` → 32631.
fn parse_authority(args: &str) -> Option<u32> {
    let end = args.find([']', ')'])?;
    let mut parts = args[..end].split(',');
    let name = parts.next()?.trim().trim_matches('"');
    if !name.eq_ignore_ascii_case("EPSG") {
        return None;
    }
    parts.next()?.trim().trim_matches('"').parse().ok()
}

fn first_quoted(wkt: &str) -> Option<String> {
    let a = wkt.find('"')?;
    let b = wkt[a + 1..].find('"')?;
    Some(wkt[a + 1..a + 1 + b].to_string())
}

/// The value of PARAMETER["name", value] for the first of `names` present (case and
/// punctuation aside).
fn parameter(wkt: &str, names: &[&str]) -> Option<f64> {
    let upper = wkt.to_ascii_uppercase();
    let mut from = 0;
    while let Some(k) = upper[from..].find("PARAMETER[") {
        let start = from + k + "PARAMETER[".len();
        let end = start + wkt[start..].find([']', ')'])?;
        let mut parts = wkt[start..end].splitn(2, ',');
        let name = squash(parts.next()?);
        if names.iter().any(|n| squash(n) == name) {
            return parts.next()?.trim().parse().ok();
        }
        from = end;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_that_is_not_ascii_is_no_problem() {
        // Found by fuzzing: a two-byte character where a keyword could start.
        let wkt = "PROJCS[\"x\",\u{77e},AUTHORITY[\"EPSG\",\"32631\"]]";
        assert_eq!(epsg_from_wkt(wkt), Ok(32631));
        assert!(epsg_from_wkt("PROJCS[\"é\",ÿÿÿ,é]").is_err());
    }

    #[test]
    fn esri_and_ogc_utm_without_authority_resolve() {
        let esri = r#"PROJCS["WGS_1984_UTM_Zone_31N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]],PRIMEM["Greenwich",0.0],UNIT["Degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],PARAMETER["False_Easting",500000.0],PARAMETER["False_Northing",0.0],PARAMETER["Central_Meridian",3.0],PARAMETER["Scale_Factor",0.9996],PARAMETER["Latitude_Of_Origin",0.0],UNIT["Meter",1.0]]"#;
        assert_eq!(epsg_from_wkt(esri), Ok(32631));
        // Named only by its parameters.
        let unnamed = esri.replace("WGS_1984_UTM_Zone_31N", "custom");
        assert_eq!(epsg_from_wkt(&unnamed), Ok(32631));
        let south = esri
            .replace("WGS_1984_UTM_Zone_31N", "x")
            .replace("\"False_Northing\",0.0", "\"False_Northing\",10000000.0");
        assert_eq!(epsg_from_wkt(&south), Ok(32731));
        let nad = r#"PROJCS["NAD83 / UTM zone 15N",GEOGCS["NAD83",DATUM["North_American_Datum_1983",SPHEROID["GRS 1980",6378137,298.257222101]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],UNIT["metre",1]]"#;
        assert_eq!(epsg_from_wkt(nad), Ok(26915));
        let with_id = r#"PROJCS["x",GEOGCS["WGS 84"],AUTHORITY["EPSG","32630"]]"#;
        assert_eq!(epsg_from_wkt(with_id), Ok(32630));
        let geo = r#"GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]]]"#;
        assert_eq!(epsg_from_wkt(geo), Ok(4326));
        // A datum of its own with a transformation to WGS 84 is not WGS 84.
        let ed50 = r#"PROJCS["ED50 / UTM zone 31N",GEOGCS["ED50",DATUM["European_Datum_1950",SPHEROID["International 1924",6378388,297],TOWGS84[-87,-98,-121,0,0,0,0]]],PROJECTION["Transverse_Mercator"]]"#;
        assert_eq!(epsg_from_wkt(ed50), Err("ED50 / UTM zone 31N".to_string()));
    }

    #[test]
    fn an_unknown_projection_is_named() {
        let lcc = r#"PROJCS["Lambert_Conformal_Conic_Custom",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]]],PROJECTION["Lambert_Conformal_Conic"],PARAMETER["Central_Meridian",3.0]]"#;
        assert_eq!(
            epsg_from_wkt(lcc),
            Err("Lambert_Conformal_Conic_Custom".to_string())
        );
        assert_eq!(
            utm_in_text("UTM Zone 31, Northern Hemisphere"),
            Some((31, true))
        );
        assert_eq!(utm_in_text("WGS 84 / UTM zone 33S"), Some((33, false)));
        assert_eq!(utm_in_text("no zone here"), None);
    }
}
