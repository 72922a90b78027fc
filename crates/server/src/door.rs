//! API messages checked at the door: each request message becomes the engine's request type
//! (`TryFrom`), or is refused with the [`BadRequest`] that says what is wrong, before any work
//! starts. The gRPC handlers and the CLI's `--data-dir` mode both come through here.

use super::proto as pb;
use patchwork_core::mesh::{Border, Method};
use patchwork_engine::request::parse_crs;
use patchwork_engine::{
    Backend, BadRequest, Camera, Cut, Heights, MeshSpec, Metres, Region, SampleRequest, TileRequest,
};

/// Vertices a side of a mesh when the request does not say.
pub const MESH_SIZE: u32 = 257;

impl TryFrom<&pb::Rect> for Region {
    type Error = BadRequest;
    fn try_from(r: &pb::Rect) -> Result<Region, BadRequest> {
        Region::of(r.xmin, r.ymin, r.xmax, r.ymax)
    }
}

impl TryFrom<&pb::ViewCut> for Camera {
    type Error = BadRequest;
    fn try_from(v: &pb::ViewCut) -> Result<Camera, BadRequest> {
        Camera::new(
            [v.eye_x, v.eye_y, v.eye_z],
            [v.look_x, v.look_y, v.look_z],
            v.fov_deg,
            v.viewport_px,
            v.pixel_error,
        )
    }
}

/// A region a request must have.
pub fn region(r: &Option<pb::Rect>) -> Result<Region, BadRequest> {
    r.as_ref().ok_or(BadRequest::NoRegion)?.try_into()
}

/// A uniform cut over a region of the CRS a request names (`crs`, empty for the store's).
pub fn uniform(c: &pb::UniformCut, crs: &str) -> Result<Cut, BadRequest> {
    Ok(Cut::uniform(
        parse_crs(crs)?,
        region(&c.roi)?,
        Metres::error(c.error)?,
    ))
}

/// The one cut of a request: uniform or view; a view's is in the store's CRS.
fn cut(u: Option<&pb::UniformCut>, v: Option<&pb::ViewCut>, crs: &str) -> Result<Cut, BadRequest> {
    match (u, v) {
        (Some(u), None) => uniform(u, crs),
        (None, Some(_)) if !crs.trim().is_empty() => Err(BadRequest::ViewCrs),
        (None, Some(v)) => Ok(Cut::View(v.try_into()?)),
        _ => Err(BadRequest::Cut),
    }
}

/// The cut of a patch query.
pub fn patch_cut(r: &pb::PatchQuery) -> Result<Cut, BadRequest> {
    match &r.cut {
        Some(pb::patch_query::Cut::Uniform(u)) => cut(Some(u), None, &r.crs),
        Some(pb::patch_query::Cut::View(v)) => cut(None, Some(v), &r.crs),
        None => cut(None, None, &r.crs),
    }
}

/// A backend the wire names.
pub fn backend(b: i32) -> Result<Backend, BadRequest> {
    match pb::Backend::try_from(b) {
        Ok(pb::Backend::Auto) => Ok(Backend::Auto),
        Ok(pb::Backend::Cpu) => Ok(Backend::Cpu),
        Ok(pb::Backend::Gpu) => Ok(Backend::Gpu),
        Err(_) => Err(BadRequest::Choice {
            field: "backend",
            value: b,
            choices: "auto, cpu or gpu",
        }),
    }
}

/// A mesh border the wire names.
pub fn mesh_border(b: i32) -> Result<Border, BadRequest> {
    match pb::MeshBorder::try_from(b) {
        Ok(pb::MeshBorder::Shared) => Ok(Border::Shared),
        Ok(pb::MeshBorder::Adaptive) => Ok(Border::Adaptive),
        Err(_) => Err(BadRequest::Choice {
            field: "mesh border",
            value: b,
            choices: "shared or adaptive",
        }),
    }
}

/// A mesh method the wire names.
pub fn mesh_method(m: i32) -> Result<Method, BadRequest> {
    match pb::MeshMethod::try_from(m) {
        Ok(pb::MeshMethod::Rtin) => Ok(Method::Rtin),
        Ok(pb::MeshMethod::Quadtree) => Ok(Method::Quadtree),
        Err(_) => Err(BadRequest::Choice {
            field: "mesh method",
            value: m,
            choices: "rtin or quadtree",
        }),
    }
}

impl TryFrom<&pb::TileRequest> for TileRequest {
    type Error = BadRequest;
    fn try_from(r: &pb::TileRequest) -> Result<TileRequest, BadRequest> {
        let (u, v) = match &r.cut {
            Some(pb::tile_request::Cut::Uniform(u)) => (Some(u), None),
            Some(pb::tile_request::Cut::View(v)) => (None, Some(v)),
            None => (None, None),
        };
        let heights = Heights::parse(&r.heights)?;
        TileRequest::new(cut(u, v, &r.crs)?, r.width, r.height, backend(r.backend)?)
            .map(|t| t.with_heights(heights))
    }
}

impl TryFrom<&pb::SampleRequest> for SampleRequest {
    type Error = BadRequest;
    fn try_from(r: &pb::SampleRequest) -> Result<SampleRequest, BadRequest> {
        let points = r.points.iter().map(|p| [p.x, p.y]).collect();
        let heights = Heights::parse(&r.heights)?;
        SampleRequest::new(points, parse_crs(&r.crs)?, r.error)
            .map(|s| s.with_heights(heights).with_sources(r.sources))
    }
}

/// A mesh request: the mesh and the backend that resamples it.
pub struct MeshAsk {
    /// The mesh.
    pub spec: MeshSpec,
    /// The backend.
    pub backend: Backend,
}

impl TryFrom<&pb::MeshRequest> for MeshAsk {
    type Error = BadRequest;
    fn try_from(r: &pb::MeshRequest) -> Result<MeshAsk, BadRequest> {
        let u = r.cut.as_ref().ok_or(BadRequest::NoRegion)?;
        let cols = if r.size == 0 { MESH_SIZE } else { r.size } as usize;
        let spec = MeshSpec {
            roi: region(&u.roi)?,
            error: Metres::error(u.error)?,
            cols,
            rows: if r.rows == 0 { cols } else { r.rows as usize },
            mesh_error: Metres::new("mesh_error", r.mesh_error)?,
            skirt_m: Metres::new("skirt_m", r.skirt_m)?,
            border: mesh_border(r.border)?,
            method: mesh_method(r.method)?,
            hole_reach_m: Metres::new("hole_reach_m", r.hole_reach_m)?,
            crs: parse_crs(&r.crs)?,
            fill_voids: false,
            heights: Heights::parse(&r.heights)?,
            rim: false,
        };
        Ok(MeshAsk {
            spec,
            backend: backend(r.backend)?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn uniform_tile(width: u32, roi: pb::Rect, error: f64) -> pb::TileRequest {
        pb::TileRequest {
            width,
            height: 4,
            cut: Some(pb::tile_request::Cut::Uniform(pb::UniformCut {
                roi: Some(roi),
                error,
            })),
            ..Default::default()
        }
    }

    fn rect(xmin: f64, ymin: f64, xmax: f64, ymax: f64) -> pb::Rect {
        pb::Rect {
            xmin,
            ymin,
            xmax,
            ymax,
        }
    }

    #[test]
    fn a_bad_request_is_refused_with_its_kind() {
        let ok = rect(0.0, 0.0, 1.0, 1.0);
        assert!(TileRequest::try_from(&uniform_tile(4, ok, 1.0)).is_ok());
        let kind = |r: pb::TileRequest| TileRequest::try_from(&r).unwrap_err();
        assert!(matches!(
            kind(uniform_tile(0, ok, 1.0)),
            BadRequest::TileSize { .. }
        ));
        assert!(matches!(
            kind(uniform_tile(4, ok, -1.0)),
            BadRequest::Metres { what: "error", .. }
        ));
        assert!(matches!(
            kind(uniform_tile(4, rect(1.0, 0.0, 0.0, 1.0), 1.0)),
            BadRequest::Region(_)
        ));
        assert_eq!(kind(pb::TileRequest::default()), BadRequest::Cut);
        let mut r = uniform_tile(4, ok, 1.0);
        r.backend = 99;
        assert!(matches!(
            kind(r),
            BadRequest::Choice {
                field: "backend",
                ..
            }
        ));
        let mut r = uniform_tile(4, ok, 1.0);
        r.crs = "EPSG:not-a-code".into();
        assert!(matches!(kind(r), BadRequest::Crs(_)));
        let view = pb::TileRequest {
            width: 4,
            height: 4,
            crs: "EPSG:4326".into(),
            cut: Some(pb::tile_request::Cut::View(pb::ViewCut::default())),
            ..Default::default()
        };
        assert_eq!(kind(view), BadRequest::ViewCrs);
        let s = pb::SampleRequest {
            points: vec![pb::Point {
                x: 0.0,
                y: f64::NAN,
            }],
            ..Default::default()
        };
        assert!(matches!(
            SampleRequest::try_from(&s).unwrap_err(),
            BadRequest::Point { index: 0, .. }
        ));
        let m = pb::MeshRequest {
            cut: Some(pb::UniformCut {
                roi: Some(ok),
                error: 1.0,
            }),
            skirt_m: f64::INFINITY,
            ..Default::default()
        };
        assert!(matches!(
            MeshAsk::try_from(&m).err(),
            Some(BadRequest::Metres {
                what: "skirt_m",
                ..
            })
        ));
    }
}
