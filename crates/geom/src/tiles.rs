//! The two tile pyramids web map clients ask for: Web Mercator XYZ (MapLibre's `raster-dem`,
//! rows from the north) and the geographic TMS of Cesium's quantized-mesh (two root tiles
//! side by side, rows from the south). Bounds, the tiles over a region, and the errors each
//! level is cut at; pure arithmetic.

use crate::Aabb;

/// Half the Web Mercator world's side, metres: π × the WGS 84 semi-major axis.
pub const MERCATOR_HALF: f64 = 20_037_508.342_789_244;

/// The deepest level either pyramid serves: 2^24 tiles a side is under a centimetre a pixel.
pub const MAX_LEVEL: u32 = 24;

/// Cesium's geometric error of a level-0 tile of its geographic tiling (two root tiles, a
/// 65-sample heightmap): `a · 2π · 0.25 / (65 · 2)`, metres. Level `l` has this over 2^l.
pub const CESIUM_LEVEL0_ERROR: f64 = 77_067.339_040_841_74;

/// The latitude Web Mercator stops at, degrees.
pub const MERCATOR_MAX_LAT: f64 = 85.051_128_779_806_59;

/// A rectangle of tiles of one level: columns `x0..=x1`, rows `y0..=y1`, in the pyramid's own
/// row order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileRange {
    /// The level.
    pub z: u32,
    /// The first column.
    pub x0: u32,
    /// The first row.
    pub y0: u32,
    /// The last column.
    pub x1: u32,
    /// The last row.
    pub y1: u32,
}

/// The Web Mercator pyramid, XYZ: 2^z × 2^z tiles, row 0 at the north.
pub mod mercator {
    use super::*;

    /// Whether tile (z, x, y) exists.
    pub fn valid(z: u32, x: u32, y: u32) -> bool {
        z <= MAX_LEVEL && x < (1 << z) && y < (1 << z)
    }

    /// Tile (z, x, y)'s bounds in EPSG:3857 metres.
    pub fn bounds(z: u32, x: u32, y: u32) -> Aabb {
        let side = 2.0 * MERCATOR_HALF / (1u64 << z) as f64;
        let xmin = -MERCATOR_HALF + x as f64 * side;
        let ymax = MERCATOR_HALF - y as f64 * side;
        Aabb::new(xmin, ymax - side, xmin + side, ymax)
    }

    /// Metres east and north of a longitude and latitude (degrees), on the sphere of the WGS 84
    /// semi-major axis; latitudes are clamped to the projection's.
    pub fn project(lon: f64, lat: f64) -> [f64; 2] {
        let lat = lat.clamp(-MERCATOR_MAX_LAT, MERCATOR_MAX_LAT);
        let x = lon / 180.0 * MERCATOR_HALF;
        let y = (std::f64::consts::FRAC_PI_4 + lat.to_radians() / 2.0)
            .tan()
            .ln()
            * (MERCATOR_HALF / std::f64::consts::PI);
        [x, y]
    }

    /// The longitude and latitude (degrees) of a point in EPSG:3857 metres.
    pub fn unproject(x: f64, y: f64) -> [f64; 2] {
        let lon = x / MERCATOR_HALF * 180.0;
        let lat = (2.0 * (y / MERCATOR_HALF * std::f64::consts::PI).exp().atan()
            - std::f64::consts::FRAC_PI_2)
            .to_degrees();
        [lon, lat]
    }

    /// Tile (z, x, y)'s bounds in longitude and latitude, degrees.
    pub fn lonlat_bounds(z: u32, x: u32, y: u32) -> Aabb {
        let b = bounds(z, x, y);
        let [w, s] = unproject(b.min[0], b.min[1]);
        let [e, n] = unproject(b.max[0], b.max[1]);
        Aabb::new(w, s, e, n)
    }

    /// The tiles of level `z` that a longitude-latitude rectangle (degrees) touches.
    pub fn over(z: u32, lonlat: &Aabb) -> TileRange {
        let n = (1u64 << z) as f64;
        let side = 2.0 * MERCATOR_HALF / n;
        let last = (1u32 << z) - 1;
        let [x0, y0] = project(lonlat.min[0], lonlat.min[1]);
        let [x1, y1] = project(lonlat.max[0], lonlat.max[1]);
        let col = |x: f64| (((x + MERCATOR_HALF) / side).floor().max(0.0) as u32).min(last);
        let row = |y: f64| (((MERCATOR_HALF - y) / side).floor().max(0.0) as u32).min(last);
        TileRange {
            z,
            x0: col(x0),
            x1: col(x1),
            y0: row(y1),
            y1: row(y0),
        }
    }

    /// The tiles of level `z` that lie wholly inside a longitude-latitude rectangle (degrees);
    /// None if no tile does.
    pub fn within(z: u32, lonlat: &Aabb) -> Option<TileRange> {
        inner(over(z, lonlat), lonlat, lonlat_bounds)
    }

    /// The vertical error a `size`-pixel tile of level `z` is cut at: half a pixel's side at
    /// the equator, metres. It depends on the level alone, not on the tile's latitude, so that
    /// neighbouring tiles of a level are cut alike and meet without a seam.
    pub fn error(z: u32, size: u32) -> f64 {
        0.5 * 2.0 * MERCATOR_HALF / (size as f64 * (1u64 << z) as f64)
    }
}

/// Cesium's geographic pyramid, TMS: 2^(z+1) × 2^z tiles of 180/2^z degrees, row 0 at the
/// south.
pub mod geographic {
    use super::*;

    /// Whether tile (z, x, y) exists.
    pub fn valid(z: u32, x: u32, y: u32) -> bool {
        z <= MAX_LEVEL && x < (2 << z) && y < (1 << z)
    }

    /// Tile (z, x, y)'s bounds, longitude and latitude in degrees.
    pub fn bounds(z: u32, x: u32, y: u32) -> Aabb {
        let side = 180.0 / (1u64 << z) as f64;
        let w = -180.0 + x as f64 * side;
        let s = -90.0 + y as f64 * side;
        Aabb::new(w, s, w + side, s + side)
    }

    /// The tiles of level `z` that a longitude-latitude rectangle touches.
    pub fn over(z: u32, lonlat: &Aabb) -> TileRange {
        let side = 180.0 / (1u64 << z) as f64;
        let (cols, rows) = ((2u32 << z) - 1, (1u32 << z) - 1);
        let col = |lon: f64| (((lon + 180.0) / side).floor().max(0.0) as u32).min(cols);
        let row = |lat: f64| (((lat + 90.0) / side).floor().max(0.0) as u32).min(rows);
        TileRange {
            z,
            x0: col(lonlat.min[0]),
            x1: col(lonlat.max[0]),
            y0: row(lonlat.min[1]),
            y1: row(lonlat.max[1]),
        }
    }

    /// The tiles of level `z` that lie wholly inside a longitude-latitude rectangle; None if
    /// no tile does.
    pub fn within(z: u32, lonlat: &Aabb) -> Option<TileRange> {
        inner(over(z, lonlat), lonlat, bounds)
    }

    /// Cesium's geometric error for level `z`, metres.
    pub fn geometric_error(z: u32) -> f64 {
        CESIUM_LEVEL0_ERROR / (1u64 << z) as f64
    }
}

/// The part of `r` (the tiles a rectangle touches) whose tiles lie wholly inside it: only its
/// first and last rows and columns can reach outside.
fn inner(r: TileRange, area: &Aabb, bounds: impl Fn(u32, u32, u32) -> Aabb) -> Option<TileRange> {
    let (mut x0, mut x1, mut y0, mut y1) = (r.x0 as i64, r.x1 as i64, r.y0 as i64, r.y1 as i64);
    let b = |x: i64, y: i64| bounds(r.z, x as u32, y as u32);
    if b(x0, r.y0 as i64).min[0] < area.min[0] {
        x0 += 1;
    }
    if b(x1, r.y0 as i64).max[0] > area.max[0] {
        x1 -= 1;
    }
    // Rows run north to south in one pyramid and south to north in the other: test both
    // sides of each end row.
    let out = |y: i64| {
        let t = b(r.x0 as i64, y);
        t.min[1] < area.min[1] || t.max[1] > area.max[1]
    };
    if out(y0) {
        y0 += 1;
    }
    if y1 >= y0 && out(y1) {
        y1 -= 1;
    }
    (x0 <= x1 && y0 <= y1).then_some(TileRange {
        z: r.z,
        x0: x0 as u32,
        y0: y0 as u32,
        x1: x1 as u32,
        y1: y1 as u32,
    })
}

/// The first level whose pixels (a tile's side over `samples`) are no larger than `cell`,
/// both in the pyramid's units at level 0's tile side `side0`: past it a client only
/// magnifies.
pub fn finest_level(side0: f64, samples: u32, cell: f64) -> u32 {
    let mut z = 0;
    while z < MAX_LEVEL && side0 / (1u64 << z) as f64 / samples as f64 > cell {
        z += 1;
    }
    z
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tiles_within_a_box_are_inside_it_and_their_neighbours_are_not() {
        let inside = |t: &Aabb, a: &Aabb| a.contains(t);
        let mut h = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            h ^= h << 13;
            h ^= h >> 7;
            h ^= h << 17;
            (h >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..200 {
            let (w, s) = (-180.0 + 300.0 * next(), -80.0 + 140.0 * next());
            let area = Aabb::new(w, s, w + 60.0 * next(), s + 20.0 * next());
            for z in [0, 3, 7, 12] {
                type Of = fn(u32, u32, u32) -> Aabb;
                let pyramids: [(Option<TileRange>, Of, u32, u32); 2] = [
                    (
                        mercator::within(z, &area),
                        mercator::lonlat_bounds,
                        1 << z,
                        1 << z,
                    ),
                    (
                        geographic::within(z, &area),
                        geographic::bounds,
                        2 << z,
                        1 << z,
                    ),
                ];
                for (r, bounds, cols, rows) in pyramids {
                    let Some(r) = r else { continue };
                    for (x, y) in [(r.x0, r.y0), (r.x1, r.y1), (r.x0, r.y1), (r.x1, r.y0)] {
                        assert!(inside(&bounds(z, x, y), &area), "{z}/{x}/{y} in {area:?}");
                    }
                    if r.x0 > 0 {
                        assert!(!inside(&bounds(z, r.x0 - 1, r.y0), &area));
                    }
                    if r.x1 + 1 < cols {
                        assert!(!inside(&bounds(z, r.x1 + 1, r.y0), &area));
                    }
                    if r.y0 > 0 {
                        assert!(!inside(&bounds(z, r.x0, r.y0 - 1), &area));
                    }
                    if r.y1 + 1 < rows {
                        assert!(!inside(&bounds(z, r.x0, r.y1 + 1), &area));
                    }
                }
            }
        }
    }

    #[test]
    fn mercator_tiles_tile_the_world_from_the_north() {
        let b = mercator::bounds(0, 0, 0);
        assert_eq!(
            b,
            Aabb::new(-MERCATOR_HALF, -MERCATOR_HALF, MERCATOR_HALF, MERCATOR_HALF)
        );
        let nw = mercator::bounds(1, 0, 0);
        assert_eq!(nw.min, [-MERCATOR_HALF, 0.0]);
        assert_eq!(nw.max, [0.0, MERCATOR_HALF]);
        // Los Angeles at z 11 is tile 351, 817 (as every XYZ map has it).
        let r = mercator::over(11, &Aabb::new(-118.25, 34.05, -118.25, 34.05));
        assert_eq!((r.x0, r.y0), (351, 817));
        assert!(mercator::valid(11, 351, 817) && !mercator::valid(11, 2048, 0));
        let [_, y] = mercator::project(0.0, MERCATOR_MAX_LAT);
        assert!((y - MERCATOR_HALF).abs() < 1e-3, "{y}");
        let [x, y] = mercator::project(-118.25, 34.05);
        let [lon, lat] = mercator::unproject(x, y);
        assert!((lon + 118.25).abs() < 1e-12 && (lat - 34.05).abs() < 1e-12);
    }

    #[test]
    fn geographic_tiles_have_two_roots_and_rows_from_the_south() {
        assert_eq!(
            geographic::bounds(0, 0, 0),
            Aabb::new(-180.0, -90.0, 0.0, 90.0)
        );
        assert_eq!(
            geographic::bounds(0, 1, 0),
            Aabb::new(0.0, -90.0, 180.0, 90.0)
        );
        assert!(geographic::valid(0, 1, 0) && !geographic::valid(0, 2, 0));
        let r = geographic::over(1, &Aabb::new(-119.0, 34.4, -118.8, 34.6));
        assert_eq!((r.x0, r.x1, r.y0, r.y1), (0, 0, 1, 1));
        let b = geographic::bounds(12, 1390, 2833);
        assert!(b.min[0] <= -118.9 && -118.9 <= b.max[0], "{b:?}");
        assert!(b.min[1] <= 34.5 && 34.5 <= b.max[1], "{b:?}");
        assert!((geographic::geometric_error(1) - 38_533.67).abs() < 0.01);
    }

    #[test]
    fn errors_halve_with_each_level() {
        assert!((mercator::error(0, 256) - 78_271.517).abs() < 1e-3);
        assert_eq!(mercator::error(3, 512), mercator::error(4, 256));
        // One arc-second cells: 256-pixel Web Mercator tiles reach them at level 13, and
        // Cesium's 180°-wide roots at level 12.
        assert_eq!(finest_level(360.0, 256, 1.0 / 3600.0), 13);
        assert_eq!(finest_level(180.0, 256, 1.0 / 3600.0), 12);
    }
}
