//! A tile's mesh in standard formats: Wavefront OBJ, binary glTF 2.0 (.glb) and Cesium's
//! quantized-mesh-1.0 (.terrain) with its edge indices and the extensions Cesium asks for:
//! oct-encoded vertex normals, the water mask and metadata.
//!
//! Positions are in the tile's CRS and heights in metres (glTF's in metres throughout). The tile spans `roi`: grid vertex
//! (c, r) lies at x = xmin + c·(xmax − xmin)/(cols − 1), y = ymax − r·(ymax − ymin)/(rows − 1).

use super::{edges, Mesh};
use patchwork_geom::Aabb;
use std::fmt::Write as _;

/// A vertex's position in the store's CRS and its height.
fn position(m: &Mesh, roi: &Aabb, v: usize) -> [f64; 3] {
    let [c, r] = m.grid[v];
    [
        roi.min[0] + c as f64 * roi.width() / (m.cols - 1) as f64,
        roi.max[1] - r as f64 * roi.height() / (m.rows - 1) as f64,
        m.heights[v] as f64,
    ]
}

/// Wavefront OBJ: `v x y z` in the CRS (z up, metres), then 1-based `f` faces, skirts
/// included.
pub fn obj(m: &Mesh, roi: &Aabb) -> String {
    let mut s = String::with_capacity(m.grid.len() * 40 + m.triangles.len() * 24);
    let _ = writeln!(
        s,
        "# patchwork mesh: {} vertices, {} triangles ({} of skirt), max deviation {:.4} m",
        m.grid.len(),
        m.triangles.len(),
        m.triangles.len() - m.skirt_triangles,
        m.max_deviation
    );
    for v in 0..m.grid.len() {
        let [x, y, z] = position(m, roi, v);
        let _ = writeln!(s, "v {x:.9} {y:.9} {z:.3}");
    }
    for t in &m.triangles {
        let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s
}

/// Binary glTF 2.0, skirts included. glTF is y-up and in metres, its positions f32.
///
/// In a projected CRS a vertex is (x − xmin, height, ymin − y) and the node's translation
/// (f64) puts the tile's south-west corner back, so the CRS position is exact to f32 relative
/// to the tile, not to the CRS's origin. In longitude and latitude (`lonlat`) degrees are no
/// unit for glTF: a vertex is (east, up, −north) in metres, in the plane tangent to the WGS 84
/// ellipsoid under the tile's centre (the local east-north-up frame, so the earth's curvature
/// shows as it is), and the node's `extras` name that centre.
pub fn glb(m: &Mesh, roi: &Aabb, lonlat: bool) -> Vec<u8> {
    let centre = [
        (roi.min[0] + roi.max[0]) / 2.0,
        (roi.min[1] + roi.max[1]) / 2.0,
    ];
    let enu = Enu::at(centre[0], centre[1]);
    let mut positions = Vec::with_capacity(m.grid.len() * 12);
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for v in 0..m.grid.len() {
        let [x, y, z] = position(m, roi, v);
        let p = if lonlat {
            let [e, n, u] = enu.of(ecef(x, y, z));
            [e as f32, u as f32, -n as f32]
        } else {
            [(x - roi.min[0]) as f32, z as f32, (roi.min[1] - y) as f32]
        };
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
        positions.extend(p.iter().flat_map(|c| c.to_le_bytes()));
    }
    let node = if lonlat {
        format!(
            r#"{{"mesh":0,"extras":{{"frame":"east-north-up","origin_lon_lat_height":[{:?},{:?},0.0]}}}}"#,
            centre[0], centre[1]
        )
    } else {
        format!(
            r#"{{"mesh":0,"translation":[{:?},0.0,{:?}]}}"#,
            roi.min[0], -roi.min[1]
        )
    };
    let indices: Vec<u8> = m
        .triangles
        .iter()
        .flatten()
        .flat_map(|i| i.to_le_bytes())
        .collect();
    let json = format!(
        concat!(
            r#"{{"asset":{{"version":"2.0","generator":"patchwork"}},"scene":0,"scenes":[{{"nodes":[0]}}],"#,
            r#""nodes":[{node}],"#,
            r#""meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1,"mode":4}}]}}],"#,
            r#""buffers":[{{"byteLength":{len}}}],"#,
            r#""bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":{p},"target":34962}},"#,
            r#"{{"buffer":0,"byteOffset":{p},"byteLength":{i},"target":34963}}],"#,
            r#""accessors":[{{"bufferView":0,"componentType":5126,"count":{n},"type":"VEC3","min":{lo:?},"max":{hi:?}}},"#,
            r#"{{"bufferView":1,"componentType":5125,"count":{t},"type":"SCALAR"}}]}}"#
        ),
        node = node,
        len = positions.len() + indices.len(),
        p = positions.len(),
        i = indices.len(),
        n = m.grid.len(),
        lo = lo,
        hi = hi,
        t = m.triangles.len() * 3,
    );
    let mut json = json.into_bytes();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let mut bin = positions;
    bin.extend(indices);
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((json.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(json);
    out.extend((bin.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(bin);
    out
}

/// WGS84's semi-axes, metres.
const WGS84: [f64; 3] = [6_378_137.0, 6_378_137.0, 6_356_752.314_245_179];

/// Earth-centred, earth-fixed coordinates of a longitude, latitude (degrees) and height.
pub fn ecef(lon: f64, lat: f64, h: f64) -> [f64; 3] {
    let (lon, lat) = (lon.to_radians(), lat.to_radians());
    let e2 = 1.0 - (WGS84[2] * WGS84[2]) / (WGS84[0] * WGS84[0]);
    let n = WGS84[0] / (1.0 - e2 * lat.sin().powi(2)).sqrt();
    [
        (n + h) * lat.cos() * lon.cos(),
        (n + h) * lat.cos() * lon.sin(),
        (n * (1.0 - e2) + h) * lat.sin(),
    ]
}

/// The east-north-up frame tangent to the WGS 84 ellipsoid at a longitude and latitude.
struct Enu {
    origin: [f64; 3],
    /// The east, north and up unit vectors, in earth-fixed coordinates.
    axes: [[f64; 3]; 3],
}

impl Enu {
    fn at(lon: f64, lat: f64) -> Enu {
        let (sl, cl) = lon.to_radians().sin_cos();
        let (sp, cp) = lat.to_radians().sin_cos();
        Enu {
            origin: ecef(lon, lat, 0.0),
            axes: [
                [-sl, cl, 0.0],
                [-sp * cl, -sp * sl, cp],
                [cp * cl, cp * sl, sp],
            ],
        }
    }

    /// An earth-fixed point's east, north and up metres from the origin.
    fn of(&self, p: [f64; 3]) -> [f64; 3] {
        let d = sub(p, self.origin);
        self.axes.map(|a| dot(a, d))
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

fn zigzag(v: i32) -> u16 {
    ((v << 1) ^ (v >> 31)) as u16
}

/// A unit vector as two bytes (Cesium's `AttributeCompression.octEncode`).
fn oct(n: [f64; 3]) -> [u8; 2] {
    let l1 = n[0].abs() + n[1].abs() + n[2].abs();
    let (mut x, mut y) = (n[0] / l1, n[1] / l1);
    if n[2] < 0.0 {
        let sign = |v: f64| if v < 0.0 { -1.0 } else { 1.0 };
        (x, y) = ((1.0 - y.abs()) * sign(x), (1.0 - x.abs()) * sign(y));
    }
    let byte = |v: f64| ((v.clamp(-1.0, 1.0) * 0.5 + 0.5) * 255.0).round() as u8;
    [byte(x), byte(y)]
}

/// Cesium's horizon occlusion point: in the ellipsoid-scaled frame, along the direction of
/// `centre`, the nearest point from which every vertex lies at or above the horizon.
fn occlusion_point(centre: [f64; 3], points: &[[f64; 3]]) -> [f64; 3] {
    let scaled = |p: [f64; 3]| [p[0] / WGS84[0], p[1] / WGS84[1], p[2] / WGS84[2]];
    let c = scaled(centre);
    let dir = {
        let l = norm(c);
        [c[0] / l, c[1] / l, c[2] / l]
    };
    let mut worst = 0.0f64;
    for &p in points {
        let q = scaled(p);
        let mag2 = dot(q, q);
        let mag = mag2.sqrt();
        let d = [q[0] / mag, q[1] / mag, q[2] / mag];
        let (mag2, mag) = (mag2.max(1.0), mag.max(1.0));
        let cos_a = dot(d, dir);
        let sin_a = norm(cross(d, dir));
        let cos_b = 1.0 / mag;
        let sin_b = (mag2 - 1.0).sqrt() * cos_b;
        worst = worst.max(1.0 / (cos_a * cos_b - sin_a * sin_b));
    }
    [dir[0] * worst, dir[1] * worst, dir[2] * worst]
}

/// The extensions of a quantized-mesh tile, each sent only to a client that asked for it
/// (Cesium names them in its `Accept` header).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Extensions {
    /// Oct-encoded vertex normals (extension 1): from the surface around each vertex where
    /// `rim` gives it, else area-weighted over the tile's faces.
    pub normals: bool,
    /// The heights of the mesh's grid with one more vertex all round, beyond the tile's
    /// edges, `(cols + 2) × (rows + 2)` row by row: each vertex's normal is then the
    /// surface's there, across the edge as inside, so that two tiles sharing an edge give its
    /// vertices the same normal and shading shows no seam along it.
    pub rim: Option<Vec<f32>>,
    /// The water mask (extension 2): one byte for a tile all land (0) or all water (255), or
    /// 256 × 256 bytes, north row first and west to east.
    pub watermask: Option<Vec<u8>>,
    /// Metadata (extension 4): a JSON object, such as the availability of the tiles under
    /// this one.
    pub metadata: Option<String>,
}

/// Cesium's quantized-mesh-1.0 of the surface (skirts left out: a client adds its own from
/// the edge indices), with the extensions asked for. `roi` is in longitude and latitude,
/// degrees.
pub fn quantized_mesh(m: &Mesh, roi: &Aabb, ext: &Extensions) -> Vec<u8> {
    // Vertices in order of first use, as the high-water-mark index coding needs.
    let mut order = Vec::with_capacity(m.skirt_vertices);
    let mut new_id = vec![u32::MAX; m.skirt_vertices];
    let triangles: Vec<[u32; 3]> = m.triangles[..m.skirt_triangles]
        .iter()
        .map(|t| {
            t.map(|v| {
                if new_id[v as usize] == u32::MAX {
                    new_id[v as usize] = order.len() as u32;
                    order.push(v as usize);
                }
                new_id[v as usize]
            })
        })
        .collect();
    let n = order.len();
    let lonlat: Vec<[f64; 3]> = order.iter().map(|&v| position(m, roi, v)).collect();
    let world: Vec<[f64; 3]> = lonlat.iter().map(|p| ecef(p[0], p[1], p[2])).collect();
    let (hmin, hmax) = lonlat
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            (a.min(p[2]), b.max(p[2]))
        });
    let (hmin, hmax) = if n == 0 { (0.0, 0.0) } else { (hmin, hmax) };
    let c = [
        0.5 * (roi.min[0] + roi.max[0]),
        0.5 * (roi.min[1] + roi.max[1]),
    ];
    let centre = ecef(c[0], c[1], 0.5 * (hmin + hmax));
    let radius = world
        .iter()
        .map(|p| norm(sub(*p, centre)))
        .fold(0.0, f64::max);
    let horizon = occlusion_point(centre, &world);

    let mut out = Vec::new();
    let f64s = |out: &mut Vec<u8>, v: &[f64]| out.extend(v.iter().flat_map(|x| x.to_le_bytes()));
    f64s(&mut out, &centre);
    out.extend((hmin as f32).to_le_bytes());
    out.extend((hmax as f32).to_le_bytes());
    f64s(&mut out, &centre);
    f64s(&mut out, &[radius]);
    f64s(&mut out, &horizon);

    out.extend((n as u32).to_le_bytes());
    let span = |v: f64, lo: f64, hi: f64| {
        if hi > lo {
            ((v - lo) / (hi - lo) * 32767.0).round() as i32
        } else {
            0
        }
    };
    let u: Vec<i32> = lonlat
        .iter()
        .map(|p| span(p[0], roi.min[0], roi.max[0]))
        .collect();
    let v: Vec<i32> = lonlat
        .iter()
        .map(|p| span(p[1], roi.min[1], roi.max[1]))
        .collect();
    let h: Vec<i32> = lonlat.iter().map(|p| span(p[2], hmin, hmax)).collect();
    for values in [&u, &v, &h] {
        let mut prev = 0;
        for &x in values.iter() {
            out.extend(zigzag(x - prev).to_le_bytes());
            prev = x;
        }
    }
    let wide = n > 65_536;
    let index = |out: &mut Vec<u8>, i: u32| {
        if wide {
            out.extend(i.to_le_bytes());
        } else {
            out.extend((i as u16).to_le_bytes());
        }
    };
    let align = if wide { 4 } else { 2 };
    while out.len() % align != 0 {
        out.push(0);
    }
    out.extend((triangles.len() as u32).to_le_bytes());
    let mut highest = 0u32;
    for &i in triangles.iter().flatten() {
        index(&mut out, highest - i);
        if i == highest {
            highest += 1;
        }
    }
    for side in edges(m) {
        out.extend((side.len() as u32).to_le_bytes());
        for i in side {
            index(&mut out, new_id[i as usize]);
        }
    }
    if ext.normals {
        match &ext.rim {
            Some(rim) if rim.len() == (m.cols + 2) * (m.rows + 2) => {
                let data: Vec<u8> = order
                    .iter()
                    .flat_map(|&v| oct(rim_normal(m, roi, rim, m.grid[v])))
                    .collect();
                extension(&mut out, 1, &data);
            }
            _ => normals(&mut out, &triangles, &world),
        }
    }
    if let Some(mask) = &ext.watermask {
        extension(&mut out, 2, mask);
    }
    if let Some(json) = &ext.metadata {
        let mut data = Vec::with_capacity(4 + json.len());
        data.extend((json.len() as u32).to_le_bytes());
        data.extend(json.as_bytes());
        extension(&mut out, 4, &data);
    }
    out
}

/// One extension: its id, its length and its bytes.
fn extension(out: &mut Vec<u8>, id: u8, data: &[u8]) {
    out.push(id);
    out.extend((data.len() as u32).to_le_bytes());
    out.extend(data);
}

/// The unit normal, earth-fixed, of the surface at grid vertex `g` of `m`: across the
/// vertices on either side of it east–west and north–south in `rim` (the grid with a vertex
/// more all round), so that a vertex on the tile's edge has the normal its neighbour tile
/// gives it too.
fn rim_normal(m: &Mesh, roi: &Aabb, rim: &[f32], g: [u32; 2]) -> [f64; 3] {
    let w = m.cols + 2;
    let dx = roi.width() / (m.cols - 1) as f64;
    let dy = roi.height() / (m.rows - 1) as f64;
    // Rim vertex (i, j) is grid vertex (i − 1, j − 1).
    let at = |i: usize, j: usize| {
        let lon = roi.min[0] + (i as f64 - 1.0) * dx;
        let lat = roi.max[1] - (j as f64 - 1.0) * dy;
        ecef(lon, lat, rim[j * w + i] as f64)
    };
    let (i, j) = (g[0] as usize + 1, g[1] as usize + 1);
    let east = sub(at(i + 1, j), at(i - 1, j));
    let north = sub(at(i, j - 1), at(i, j + 1));
    let n = cross(east, north);
    let l = norm(n);
    let p = at(i, j);
    if l > 0.0 && n.iter().all(|v| v.is_finite()) {
        [n[0] / l, n[1] / l, n[2] / l]
    } else {
        let l = norm(p);
        [p[0] / l, p[1] / l, p[2] / l]
    }
}

/// The normals extension: vertex normals in the earth-fixed frame, area-weighted over the
/// faces.
fn normals(out: &mut Vec<u8>, triangles: &[[u32; 3]], world: &[[f64; 3]]) {
    let n = world.len();
    let mut normals = vec![[0.0f64; 3]; n];
    for t in triangles {
        let [a, b, c] = t.map(|i| world[i as usize]);
        let f = cross(sub(b, a), sub(c, a));
        for &i in t {
            for k in 0..3 {
                normals[i as usize][k] += f[k];
            }
        }
    }
    let mut data = Vec::with_capacity(2 * n);
    for (nv, p) in normals.iter().zip(world) {
        let l = norm(*nv);
        let unit = if l > 0.0 {
            [nv[0] / l, nv[1] / l, nv[2] / l]
        } else {
            let l = norm(*p);
            [p[0] / l, p[1] / l, p[2] / l]
        };
        data.extend(oct(unit));
    }
    extension(out, 1, &data);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ecef_matches_known_points() {
        let p = ecef(0.0, 0.0, 0.0);
        assert!((p[0] - 6_378_137.0).abs() < 1e-6 && p[1].abs() < 1e-6 && p[2].abs() < 1e-6);
        let pole = ecef(0.0, 90.0, 0.0);
        assert!((pole[2] - 6_356_752.314_245).abs() < 1e-3);
    }

    #[test]
    fn the_tangent_frame_is_metres_east_north_and_up() {
        let f = Enu::at(5.0, 44.0);
        let up = f.of(ecef(5.0, 44.0, 100.0));
        assert!(up[0].abs() < 1e-9 && up[1].abs() < 1e-9 && (up[2] - 100.0).abs() < 1e-9);
        // A thousandth of a degree north is about 111 m north, and drops below the plane by
        // the curvature, d²/2R.
        let n = f.of(ecef(5.0, 44.001, 0.0));
        assert!(n[0].abs() < 1e-6 && (n[1] - 111.1).abs() < 0.1, "{n:?}");
        assert!((n[2] + n[1] * n[1] / (2.0 * 6.37e6)).abs() < 1e-4, "{n:?}");
        let e = f.of(ecef(5.001, 44.0, 0.0));
        assert!((e[0] - 80.2).abs() < 0.05 && e[1].abs() < 1e-3, "{e:?}");
    }

    #[test]
    fn oct_encoding_round_trips_axes() {
        assert_eq!(oct([0.0, 0.0, 1.0]), [128, 128]);
        assert_eq!(oct([1.0, 0.0, 0.0]), [255, 128]);
        assert_eq!(oct([0.0, -1.0, 0.0]), [128, 0]);
    }

    #[test]
    fn zigzag_is_cesiums() {
        assert_eq!([0, -1, 1, -2, 2].map(zigzag), [0, 1, 2, 3, 4]);
    }
}
