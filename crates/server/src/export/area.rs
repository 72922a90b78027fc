//! Which tiles an export holds: those of each zoom that touch its area, a rectangle or
//! polygons in longitude and latitude (the surveys' own footprints by default).

use patchwork_core::geom::tiles::mercator;
use patchwork_core::geom::Aabb;

/// An export's area, in degrees of longitude and latitude.
#[derive(Clone, Debug, PartialEq)]
pub enum Area {
    /// A rectangle.
    Bounds(Aabb),
    /// Polygons, each its outer ring then its holes; a tile is in the area where it
    /// touches any polygon's interior.
    Polygons(Vec<Vec<Vec<[f64; 2]>>>),
}

impl Area {
    /// The rectangle that holds the area; None where it holds nothing.
    pub fn bounds(&self) -> Option<Aabb> {
        match self {
            Area::Bounds(b) => Some(*b),
            Area::Polygons(ps) => {
                let outer: Vec<[f64; 2]> = ps
                    .iter()
                    .filter_map(|p| p.first())
                    .flatten()
                    .copied()
                    .collect();
                (!outer.is_empty()).then(|| Aabb::of_points(&outer))
            }
        }
    }

    /// Whether the area touches the rectangle `r`.
    pub fn touches(&self, r: &Aabb) -> bool {
        match self {
            Area::Bounds(b) => b.intersects(r),
            Area::Polygons(ps) => ps.iter().any(|p| polygon_touches(p, r)),
        }
    }

    /// Every tile of zoom `z` over the rectangle `within` (degrees), row by row, each with
    /// whether the area touches it.
    pub fn tiles(&self, z: u32, within: &Aabb) -> Vec<(u32, u32, bool)> {
        let range = mercator::over(z, within);
        let mut out = Vec::new();
        for y in range.y0..=range.y1 {
            for x in range.x0..=range.x1 {
                out.push((x, y, self.touches(&mercator::lonlat_bounds(z, x, y))));
            }
        }
        out
    }

    /// The polygons of a GeoJSON text: a Polygon, a MultiPolygon, a Feature of one, or a
    /// FeatureCollection of them (features of other geometries are an error, not skipped: an
    /// export that quietly leaves part of what was asked for is worse than none).
    pub fn from_geojson(text: &str) -> Result<Area, String> {
        let v: serde_json::Value =
            serde_json::from_str(text).map_err(|e| format!("not JSON: {e}"))?;
        let mut out = Vec::new();
        collect(&v, &mut out)?;
        if out.is_empty() {
            return Err("it holds no polygon".into());
        }
        Ok(Area::Polygons(out))
    }
}

fn collect(v: &serde_json::Value, out: &mut Vec<Vec<Vec<[f64; 2]>>>) -> Result<(), String> {
    let kind = v["type"].as_str().unwrap_or("");
    match kind {
        "FeatureCollection" => {
            for f in v["features"]
                .as_array()
                .ok_or("a FeatureCollection without features")?
            {
                collect(f, out)?;
            }
        }
        "Feature" => collect(&v["geometry"], out)?,
        "Polygon" => out.push(polygon(&v["coordinates"])?),
        "MultiPolygon" => {
            for p in v["coordinates"]
                .as_array()
                .ok_or("a MultiPolygon without coordinates")?
            {
                out.push(polygon(p)?);
            }
        }
        other => return Err(format!("a {other:?} is not an area: give polygons")),
    }
    Ok(())
}

fn polygon(v: &serde_json::Value) -> Result<Vec<Vec<[f64; 2]>>, String> {
    let rings = v
        .as_array()
        .ok_or("a polygon's coordinates are not rings")?;
    let mut out = Vec::with_capacity(rings.len());
    for ring in rings {
        let mut r = Vec::new();
        for p in ring.as_array().ok_or("a ring is not a list of positions")? {
            let (Some(lon), Some(lat)) = (p[0].as_f64(), p[1].as_f64()) else {
                return Err(format!("{p} is not a position"));
            };
            if !(-180.0..=180.0).contains(&lon) || !(-90.0..=90.0).contains(&lat) {
                return Err(format!("{p} is not a longitude and latitude in degrees"));
            }
            r.push([lon, lat]);
        }
        if r.len() < 4 {
            return Err("a ring has fewer than four positions".into());
        }
        out.push(r);
    }
    if out.is_empty() {
        return Err("a polygon without rings".into());
    }
    Ok(out)
}

/// Whether polygon `p` (outer ring, then holes) touches rectangle `r`: some edge crosses
/// it, or it lies wholly inside the polygon, or the polygon wholly inside it.
fn polygon_touches(p: &[Vec<[f64; 2]>], r: &Aabb) -> bool {
    let crosses = p
        .iter()
        .flat_map(|ring| ring.windows(2))
        .any(|e| segment_touches(e[0], e[1], r));
    if crosses {
        return true;
    }
    // No edge meets the rectangle: it is wholly inside the polygon or wholly outside, and so
    // is its centre; or the whole polygon is inside it, and so is its first vertex.
    let c = [(r.min[0] + r.max[0]) / 2.0, (r.min[1] + r.max[1]) / 2.0];
    let inside = |q: [f64; 2], ring: &[[f64; 2]]| {
        let mut odd = false;
        for e in ring.windows(2) {
            let (a, b) = (e[0], e[1]);
            if (a[1] > q[1]) != (b[1] > q[1])
                && q[0] < a[0] + (q[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0])
            {
                odd = !odd;
            }
        }
        odd
    };
    let in_polygon = inside(c, &p[0]) && !p[1..].iter().any(|h| inside(c, h));
    in_polygon || p[0].first().is_some_and(|&q| r.contains_point(q))
}

/// Whether segment a–b meets rectangle `r` (Liang–Barsky clipping).
fn segment_touches(a: [f64; 2], b: [f64; 2], r: &Aabb) -> bool {
    let d = [b[0] - a[0], b[1] - a[1]];
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for k in 0..2 {
        for (p, q) in [(-d[k], a[k] - r.min[k]), (d[k], r.max[k] - a[k])] {
            if p == 0.0 {
                if q < 0.0 {
                    return false;
                }
            } else {
                let t = q / p;
                if p < 0.0 {
                    t0 = t0.max(t);
                } else {
                    t1 = t1.min(t);
                }
            }
        }
    }
    t0 <= t1
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square(w: f64, s: f64, e: f64, n: f64) -> Vec<[f64; 2]> {
        vec![[w, s], [e, s], [e, n], [w, n], [w, s]]
    }

    #[test]
    fn polygons_touch_what_they_overlap_and_not_what_their_holes_hold() {
        let p = vec![square(0.0, 0.0, 10.0, 10.0), square(4.0, 4.0, 6.0, 6.0)];
        let a = Area::Polygons(vec![p]);
        // Crossing an edge, wholly inside, holding the whole polygon, in the hole, outside.
        assert!(a.touches(&Aabb::new(-1.0, -1.0, 1.0, 1.0)));
        assert!(a.touches(&Aabb::new(1.0, 1.0, 2.0, 2.0)));
        assert!(a.touches(&Aabb::new(-5.0, -5.0, 15.0, 15.0)));
        assert!(!a.touches(&Aabb::new(4.5, 4.5, 5.5, 5.5)));
        assert!(!a.touches(&Aabb::new(11.0, 11.0, 12.0, 12.0)));
        // A diagonal triangle does not touch the corner its bounding box holds.
        let t = Area::Polygons(vec![vec![vec![
            [0.0, 0.0],
            [10.0, 0.0],
            [0.0, 10.0],
            [0.0, 0.0],
        ]]]);
        assert!(!t.touches(&Aabb::new(8.0, 8.0, 9.0, 9.0)));
        assert!(t.touches(&Aabb::new(1.0, 1.0, 2.0, 2.0)));
    }

    #[test]
    fn geojson_areas_are_read_and_bad_ones_refused() {
        let fc = r#"{"type":"FeatureCollection","features":[
            {"type":"Feature","properties":{},"geometry":{"type":"Polygon",
             "coordinates":[[[5,44],[6,44],[6,45],[5,45],[5,44]]]}}]}"#;
        let a = Area::from_geojson(fc).unwrap();
        assert_eq!(a.bounds(), Some(Aabb::new(5.0, 44.0, 6.0, 45.0)));
        // Zoom 8 tiles are 1.4° wide: the degree touches two to four columns and rows.
        let n = a
            .tiles(8, &a.bounds().unwrap())
            .iter()
            .filter(|t| t.2)
            .count();
        assert!((2..=16).contains(&n), "{n}");
        assert!(Area::from_geojson(r#"{"type":"Point","coordinates":[1,2]}"#).is_err());
        assert!(Area::from_geojson(
            r#"{"type":"Polygon","coordinates":[[[500,1],[2,2],[1,1],[500,1]]]}"#
        )
        .is_err());
        assert!(Area::from_geojson("nonsense").is_err());
    }
}
