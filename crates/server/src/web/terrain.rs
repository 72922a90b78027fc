//! Cesium's quantized-mesh terrain: a tile of the geographic TMS pyramid is the cut at half
//! Cesium's geometric error for its level, resampled on a 257² grid over the tile, its voids
//! filled (the water mask says where), and meshed by RTIN within the other half, keeping
//! every border vertex: neighbours of one level share their edges' vertices and heights.

use super::pyramid::{Pyramid, TERRAIN_GRID};
use super::{Produced, Web};
use patchwork_core::geom::tiles::geographic;
use patchwork_core::mesh::{self, encode, Border, Method};
use patchwork_core::resample::Cancel;
use patchwork_engine::{
    Backend, Ctx, Cut, Engine, EngineError, Heights, Made, MeshSpec, Metres, Region,
};
use serde_json::json;

/// The extensions a client asked for in its `Accept` header.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Asked {
    /// Octahedron-encoded vertex normals, for lighting.
    pub normals: bool,
    /// The water mask: where the tile had no data.
    pub watermask: bool,
    /// Which tiles of the levels below exist.
    pub metadata: bool,
}

impl Asked {
    /// Reads `application/vnd.quantized-mesh;extensions=octvertexnormals-watermask-metadata`
    /// (Cesium's spelling; `vertexnormals`, the older one, counts as normals too).
    pub fn from_accept(accept: &str) -> Asked {
        let mut a = Asked::default();
        for part in accept.split([',', ';']) {
            if let Some(list) = part.trim().strip_prefix("extensions=") {
                for e in list.split('-') {
                    match e.trim() {
                        "octvertexnormals" | "vertexnormals" => a.normals = true,
                        "watermask" => a.watermask = true,
                        "metadata" => a.metadata = true,
                        _ => {}
                    }
                }
            }
        }
        a
    }
}

/// Levels of availability a tile's metadata tells of below it (layer.json's
/// `metadataAvailability`).
pub(super) const METADATA_LEVELS: u32 = 10;

/// How Cesium's geometric error for a level is spent: half on the cut, half on the mesh.
/// Either half alone is a vertical error no larger than what Cesium allows the tile, and the
/// two add up to it.
pub fn errors(z: u32) -> (f64, f64) {
    let g = geographic::geometric_error(z);
    (g / 2.0, g / 2.0)
}

/// A quantized-mesh tile asked for.
#[derive(Clone, Debug)]
pub struct Tile {
    /// The zoom level.
    pub z: u32,
    /// The column, from the west.
    pub x: u32,
    /// The row, from the south (TMS).
    pub y: u32,
    /// The extensions.
    pub asked: Asked,
    /// What the heights are measured from; None for Cesium's own, the ellipsoid's, where
    /// the store's heights can be carried there.
    pub heights: Option<Heights>,
}

/// The quantized-mesh tile `tile`: its ETag from the cut, then its bytes unless the client
/// has them. A tile with no data under it is the ellipsoid, all water.
///
/// Cesium places vertices above the WGS 84 ellipsoid, so that is what a tile's heights are
/// measured from unless the client asks otherwise. A store whose heights cannot be carried
/// there (nothing says what they are from, or a geoid grid is missing) serves them as they
/// are, with a `Warning` header saying why, rather than no terrain at all.
pub fn tile(
    engine: &Engine,
    web: &Web,
    tile: &Tile,
    if_none_match: Option<&str>,
    cancel: &Cancel,
) -> Result<Produced, EngineError> {
    let Tile { z, x, y, asked, .. } = *tile;
    let (heights, warning) = match &tile.heights {
        Some(h) => (h.clone(), None),
        None => match engine.can_give(&Heights::ellipsoid()) {
            Ok(()) => (Heights::ellipsoid(), None),
            Err(e) => (
                Heights::Store,
                Some(format!(
                    "heights are the store's, not above the ellipsoid: {e}"
                )),
            ),
        },
    };
    engine.can_give(&heights)?;
    let roi = geographic::bounds(z, x, y);
    let (cut_error, mesh_error) = errors(z);
    let n = TERRAIN_GRID;
    let crs = web.unless_store(engine, &web.geographic);
    let spec = MeshSpec {
        roi: Region::new(roi)?,
        error: Metres::error(cut_error)?,
        cols: n,
        rows: n,
        mesh_error: Metres::new("mesh_error", mesh_error)?,
        skirt_m: Metres::ZERO,
        border: Border::Shared,
        method: Method::Rtin,
        hole_reach_m: Metres::ZERO,
        crs,
        fill_voids: true,
        heights: heights.clone(),
        // Normals from the surface across the tile's edges, where Cesium shades with them.
        rim: asked.normals,
    };
    let (t, ps) = match engine.crs() {
        Some(_) => match engine.query(&Engine::mesh_cut(&spec)?) {
            Err(EngineError::Unreachable { .. }) => part_cut(engine, web, &spec)?,
            done => done?,
        },
        // A store with no survey yet has nothing anywhere.
        None => (engine.snapshot(), Vec::new()),
    };
    let pyramid = web.pyramid(engine);
    // The metadata tells of levels as deep as the finest survey anywhere goes.
    let depth = if asked.metadata {
        pyramid.terrain_max
    } else {
        0
    };
    let what = format!("terrain/{z}/{x}/{y}/{asked:?}/{depth}/{}", heights.key());
    let near = pyramid.near(&roi);
    let etag = web.etag(&what, &ps, &near);
    let made = web.produce(
        etag,
        if_none_match,
        "application/vnd.quantized-mesh",
        || {
            // Nothing in the cut may still leave voids a survey just beyond the tile fills.
            let (mesh, voids, rim) = if ps.is_empty() && near.is_empty() {
                // No data under the tile: the ellipsoid, all water.
                let flat = mesh::triangulate(
                    &vec![0.0; n * n],
                    n,
                    n,
                    &mesh::Options {
                        max_error: mesh_error,
                        ..Default::default()
                    },
                );
                (flat, vec![true; n * n], None)
            } else {
                let m = engine.mesh(&spec, Backend::Auto, Ctx::until(cancel).with_cut((t, ps)))?;
                (m.mesh, m.voids, m.rim)
            };
            let ext = encode::Extensions {
                normals: asked.normals,
                rim,
                watermask: asked.watermask.then(|| watermask(&voids, n)),
                metadata: asked.metadata.then(|| metadata(&pyramid, z, x, y)),
            };
            Ok(encode::quantized_mesh(&mesh, &roi, &ext))
        },
    )?;
    Ok(Produced { warning, ..made })
}

/// The cut of the part of a tile where the surveys can reach, for a projected store whose
/// CRS reaches only part of it (a UTM zone's, of a root tile): the rest is nodata, and the
/// globe shows the ellipsoid there, as it would anyway.
fn part_cut(engine: &Engine, web: &Web, spec: &MeshSpec) -> Result<Made, EngineError> {
    let tile = Engine::mesh_cut(spec)?;
    let Cut::UniformIn { roi, .. } = &tile else {
        return engine.query(&tile);
    };
    match web.pyramid(engine).reach_within(roi.aabb()) {
        Some(w) => engine.query(&Cut::uniform(spec.crs.clone(), Region::new(w)?, spec.error)),
        None => Ok((engine.snapshot(), Vec::new())),
    }
}

/// The water mask of a tile whose grid (`n` = 257 vertices a side) had no data at the
/// vertices `voids` marks (empty: none): one byte for a tile all land or all water, else
/// 256 × 256, each pixel the cell between four vertices, water where two or more of them are
/// void.
pub fn watermask(voids: &[bool], n: usize) -> Vec<u8> {
    if voids.is_empty() || voids.iter().all(|v| !v) {
        return vec![0];
    }
    if voids.iter().all(|v| *v) {
        return vec![255];
    }
    let cells = n - 1;
    let mut m = vec![0u8; cells * cells];
    for j in 0..cells {
        for i in 0..cells {
            let k = j * n + i;
            let wet = [voids[k], voids[k + 1], voids[k + n], voids[k + n + 1]]
                .iter()
                .filter(|v| **v)
                .count();
            if wet >= 2 {
                m[j * cells + i] = 255;
            }
        }
    }
    m
}

/// The metadata extension: which tiles under this one exist, level by level from the next
/// one down, as layer.json's `available` says.
fn metadata(p: &Pyramid, z: u32, x: u32, y: u32) -> String {
    let available = p.terrain_available();
    let mut levels = Vec::new();
    for dz in 1..=METADATA_LEVELS {
        let Some(level) = available.get((z + dz) as usize) else {
            break;
        };
        let (cx0, cx1) = (x << dz, ((x + 1) << dz) - 1);
        let (cy0, cy1) = (y << dz, ((y + 1) << dz) - 1);
        let ranges: Vec<_> = level
            .iter()
            .filter(|r| r.x0 <= cx1 && cx0 <= r.x1 && r.y0 <= cy1 && cy0 <= r.y1)
            .map(|r| {
                json!({
                    "startX": r.x0.max(cx0), "startY": r.y0.max(cy0),
                    "endX": r.x1.min(cx1), "endY": r.y1.min(cy1),
                })
            })
            .collect();
        levels.push(ranges);
    }
    json!({ "available": levels }).to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cesiums_accept_header_names_the_extensions() {
        let a = Asked::from_accept(
            "application/vnd.quantized-mesh;extensions=octvertexnormals-watermask-metadata,*/*;q=0.01",
        );
        assert_eq!(
            a,
            Asked {
                normals: true,
                watermask: true,
                metadata: true
            }
        );
        assert_eq!(
            Asked::from_accept("application/octet-stream"),
            Asked::default()
        );
        let w = Asked::from_accept("application/vnd.quantized-mesh;extensions=watermask");
        assert!(w.watermask && !w.normals);
    }

    #[test]
    fn the_water_mask_is_one_byte_unless_the_tile_is_mixed() {
        let n = 257;
        assert_eq!(watermask(&[], n), vec![0]);
        assert_eq!(watermask(&vec![true; n * n], n), vec![255]);
        let mut v = vec![false; n * n];
        // The westmost column of vertices void: the westmost cells have two void corners.
        for r in 0..n {
            v[r * n] = true;
        }
        let m = watermask(&v, n);
        assert_eq!(m.len(), 256 * 256);
        assert!(m
            .chunks(256)
            .all(|row| row[0] == 255 && row[1..].iter().all(|b| *b == 0)));
    }

    #[test]
    fn the_error_split_adds_up_to_cesiums() {
        let (a, b) = errors(12);
        assert!((a + b - geographic::geometric_error(12)).abs() < 1e-9);
    }
}
