//! Requests as the engine takes them. Each part is checked when it is made, by the door it
//! comes in at (a gRPC message, an HTTP query, the command line), so that malformed input is
//! refused with [`BadRequest`] before any work starts, and a request that reaches the engine
//! is well formed by construction: an error in metres is finite and not negative, a region
//! has area, a tile has samples, a camera looks somewhere. What depends on the store or the
//! settings (a CRS the store can be reached from, a tile within `limits.max_tile_samples`) is
//! checked by the engine, still before it works.
//!
//! Each operation has one entry, taking its checked request and a [`Ctx`]: how the caller
//! gives up on it (its deadline, or a client gone), and a cut it made already.

use crate::Cut;
use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::Crs;
use patchwork_core::geom::Aabb;
use patchwork_core::index::query::{Extracted, Metric, ViewQuery};
use patchwork_core::resample::{Backend, Cancel};
use patchwork_core::terrain::Terrain;
use std::sync::Arc;
use thiserror::Error;

/// A request refused at the door: what is wrong with it, for the client to fix. Always
/// [`Reason::InvalidRequest`](crate::Reason::InvalidRequest) on the wire.
#[non_exhaustive]
#[derive(Clone, Debug, Error, PartialEq)]
pub enum BadRequest {
    /// An error (or another length) that is not a finite number of metres ≥ 0.
    #[error("{what} must be a finite number of metres ≥ 0, got {got}")]
    Metres {
        /// The field: `error`, `mesh_error`, `accuracy`, …
        what: &'static str,
        /// What the request gave.
        got: f64,
    },
    /// A region without area, or with a bound that is not a number.
    #[error(
        "the region must have finite bounds with xmin < xmax and ymin < ymax, got [{}, {}, {}, {}]",
        .0[0], .0[1], .0[2], .0[3]
    )]
    Region([f64; 4]),
    /// A request that needs a region and has none.
    #[error("the request needs a region (roi)")]
    NoRegion,
    /// A tile without samples.
    #[error("tile width and height must be at least 1, got {width}×{height}")]
    TileSize {
        /// Samples a row asked for.
        width: u32,
        /// Rows asked for.
        height: u32,
    },
    /// A point with a coordinate that is not a number.
    #[error("points must be finite: point {index} is ({x}, {y})")]
    Point {
        /// Its place in the request.
        index: usize,
        /// Its coordinates.
        x: f64,
        /// Its coordinates.
        y: f64,
    },
    /// A CRS that cannot be parsed.
    #[error("crs: {0}")]
    Crs(String),
    /// A camera that cannot be looked through.
    #[error("{0}")]
    Camera(String),
    /// No cut, or two.
    #[error("give exactly one cut: uniform (roi + error) or view")]
    Cut,
    /// A view cut with a CRS of its own.
    #[error("a view cut is in the store's CRS: leave crs empty")]
    ViewCrs,
    /// A value of an enum the server does not know.
    #[error("unknown {field} {value}: use {choices}")]
    Choice {
        /// The field.
        field: &'static str,
        /// What the request gave.
        value: i32,
        /// What it may be.
        choices: &'static str,
    },
    /// A mesh grid with too few or too many vertices a side.
    #[error("a mesh has 2 to {most} {side}: got {got}")]
    MeshSize {
        /// `columns` or `rows`.
        side: &'static str,
        /// What the request gave.
        got: usize,
        /// The most allowed.
        most: usize,
    },
    /// A path or id that is empty, holds a NUL or is longer than a path may be.
    #[error("{what} must be a non-empty path of at most {most} bytes without NUL characters")]
    Path {
        /// The field.
        what: &'static str,
        /// The longest path allowed.
        most: usize,
    },
    /// A frame of heights that cannot be parsed.
    #[error(
        "heights must be \"store\", \"ellipsoid\" or a vertical CRS as \"EPSG:n\", got \
         {got:?}: {why}"
    )]
    Heights {
        /// What the request gave.
        got: String,
        /// Why it is not one.
        why: String,
    },
}

/// A length in metres: finite and not negative (an error, an accuracy, a skirt's depth).
#[derive(Clone, Copy, Debug, PartialEq, PartialOrd)]
pub struct Metres(f64);

impl Metres {
    /// Zero metres: the finest cut there is.
    pub const ZERO: Metres = Metres(0.0);

    /// `m` metres, or why not: `what` names the field in the refusal.
    pub fn new(what: &'static str, m: f64) -> Result<Metres, BadRequest> {
        if m.is_finite() && m >= 0.0 {
            Ok(Metres(m))
        } else {
            Err(BadRequest::Metres { what, got: m })
        }
    }

    /// An error of a cut in metres.
    pub fn error(m: f64) -> Result<Metres, BadRequest> {
        Metres::new("error", m)
    }

    /// The number of metres.
    pub fn get(self) -> f64 {
        self.0
    }
}

/// A rectangle of a CRS with area: finite bounds, xmin < xmax and ymin < ymax.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Region(Aabb);

impl Region {
    /// `b` as a region, or why not.
    pub fn new(b: Aabb) -> Result<Region, BadRequest> {
        let finite = b.min.iter().chain(b.max.iter()).all(|v| v.is_finite());
        if finite && b.is_valid() && b.width() > 0.0 && b.height() > 0.0 {
            Ok(Region(b))
        } else {
            Err(BadRequest::Region([b.min[0], b.min[1], b.max[0], b.max[1]]))
        }
    }

    /// The region from its bounds.
    pub fn of(xmin: f64, ymin: f64, xmax: f64, ymax: f64) -> Result<Region, BadRequest> {
        Region::new(Aabb::new(xmin, ymin, xmax, ymax))
    }

    /// Its bounds.
    pub fn aabb(&self) -> &Aabb {
        &self.0
    }
}

impl TryFrom<Aabb> for Region {
    type Error = BadRequest;
    fn try_from(b: Aabb) -> Result<Region, BadRequest> {
        Region::new(b)
    }
}

/// A tile's size in samples: at least one each way. The limit on samples is the engine's.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileSize {
    width: u32,
    height: u32,
}

impl TileSize {
    /// `width × height` samples, or why not.
    pub fn new(width: u32, height: u32) -> Result<TileSize, BadRequest> {
        if width == 0 || height == 0 {
            return Err(BadRequest::TileSize { width, height });
        }
        Ok(TileSize { width, height })
    }

    /// Samples a row.
    pub fn width(self) -> u32 {
        self.width
    }

    /// Rows.
    pub fn height(self) -> u32 {
        self.height
    }

    /// Samples in all.
    pub fn samples(self) -> u64 {
        self.width as u64 * self.height as u64
    }
}

/// A camera of a view-dependent cut, in the store's CRS: finite, looking somewhere, with a
/// field of view in (0°, 180°), a viewport and a screen error ≥ 0. The engine adds the store's
/// metric when it makes the cut.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    eye: [f64; 3],
    look: [f64; 3],
    fov_deg: f64,
    viewport_px: u32,
    pixel_error: f64,
}

impl Camera {
    /// A camera at `eye` looking at `look` (plane coordinates, heights in metres) with a
    /// horizontal field of view, a viewport width and the screen error allowed, or why not.
    pub fn new(
        eye: [f64; 3],
        look: [f64; 3],
        fov_deg: f64,
        viewport_px: u32,
        pixel_error: f64,
    ) -> Result<Camera, BadRequest> {
        let c = Camera {
            eye,
            look,
            fov_deg,
            viewport_px,
            pixel_error,
        };
        c.query(Metric::PROJECTED)
            .validate()
            .map_err(BadRequest::Camera)?;
        Ok(c)
    }

    /// The eye.
    pub fn eye(&self) -> [f64; 3] {
        self.eye
    }

    /// The view query of this camera over a plane with `metric`.
    pub fn query(&self, metric: Metric) -> ViewQuery {
        ViewQuery {
            eye: self.eye,
            look: self.look,
            fov_deg: self.fov_deg,
            viewport_px: self.viewport_px,
            pixel_error: self.pixel_error,
            metric,
        }
    }
}

/// Points to sample, all finite.
#[derive(Clone, Debug, PartialEq)]
pub struct Points(Vec<[f64; 2]>);

impl Points {
    /// The points, or the first that is not finite.
    pub fn new(points: Vec<[f64; 2]>) -> Result<Points, BadRequest> {
        match points
            .iter()
            .position(|p| !(p[0].is_finite() && p[1].is_finite()))
        {
            Some(index) => Err(BadRequest::Point {
                index,
                x: points[index][0],
                y: points[index][1],
            }),
            None => Ok(Points(points)),
        }
    }

    /// The points.
    pub fn get(&self) -> &[[f64; 2]] {
        &self.0
    }
}

/// A CRS a request names: None for an empty text (the store's own), or why it is not one.
pub fn parse_crs(text: &str) -> Result<Option<Crs>, BadRequest> {
    if text.trim().is_empty() {
        return Ok(None);
    }
    Crs::parse(text)
        .map(Some)
        .map_err(|e| BadRequest::Crs(e.to_string()))
}

/// What the heights of a reply are measured from. Heights are always in metres.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum Heights {
    /// As the store keeps them, from its vertical CRS (which TileJSON and layer.json name).
    #[default]
    Store,
    /// From a vertical CRS: the WGS 84 ellipsoid (what Cesium and GPS take), or a geoid's
    /// or levelling datum's, carried there through the geoid grids of both.
    In(VerticalCrs),
}

impl Heights {
    /// Heights above the WGS 84 ellipsoid.
    pub fn ellipsoid() -> Heights {
        Heights::In(VerticalCrs::ellipsoidal())
    }

    /// `store` (or nothing), `ellipsoid` (or `ellipsoidal`, `EPSG:4979`), or a vertical CRS
    /// of the registry as `EPSG:n`.
    pub fn parse(text: &str) -> Result<Heights, BadRequest> {
        let t = text.trim();
        if t.is_empty() || t.eq_ignore_ascii_case("store") {
            return Ok(Heights::Store);
        }
        if t.eq_ignore_ascii_case("ellipsoid") {
            return Ok(Heights::ellipsoid());
        }
        VerticalCrs::parse(t)
            .map(Heights::In)
            .map_err(|e| BadRequest::Heights {
                got: t.into(),
                why: e.to_string(),
            })
    }

    /// How a reply names it: `store`, `ellipsoidal` or `EPSG:n`.
    pub fn key(&self) -> &str {
        match self {
            Heights::Store => "store",
            Heights::In(v) => v.key(),
        }
    }
}

/// A cut already made: the snapshot it was made from, and its patches.
pub type Made = (Arc<Terrain>, Vec<Extracted>);

/// What surrounds a request: how the caller gives up on it, and what it made already.
#[derive(Clone, Debug, Default)]
pub struct Ctx {
    /// Set when the caller gives up: its deadline passed (the server sets it then), or it
    /// hung up. Long work checks it as it goes and stops.
    pub cancel: Cancel,
    /// The request's cut, made already by [`Engine::query`](crate::Engine::query) of the
    /// same cut: for a caller that looks at the patches first (to see whether it has the
    /// tile already). None makes it here.
    pub made: Option<Made>,
}

impl Ctx {
    /// A context given up once `cancel` is set.
    pub fn until(cancel: &Cancel) -> Ctx {
        Ctx {
            cancel: cancel.clone(),
            made: None,
        }
    }

    /// This context with the cut made already.
    pub fn with_cut(mut self, made: Made) -> Ctx {
        self.made = Some(made);
        self
    }
}

/// A resampled tile: a cut, its size, and the backend asked for.
#[derive(Clone, Debug)]
pub struct TileRequest {
    /// Where and how accurate.
    pub cut: Cut,
    /// Samples each way.
    pub size: TileSize,
    /// Which backend resamples: `Auto` lets the engine choose.
    pub backend: Backend,
    /// What the heights are measured from.
    pub heights: Heights,
}

impl TileRequest {
    /// A `width × height` tile of `cut`, or why not.
    pub fn new(
        cut: Cut,
        width: u32,
        height: u32,
        backend: Backend,
    ) -> Result<TileRequest, BadRequest> {
        Ok(TileRequest {
            cut,
            size: TileSize::new(width, height)?,
            backend,
            heights: Heights::Store,
        })
    }

    /// This request with its heights measured from `heights`.
    pub fn with_heights(mut self, heights: Heights) -> TileRequest {
        self.heights = heights;
        self
    }
}

/// Heights at points of a CRS, at an error.
#[derive(Clone, Debug)]
pub struct SampleRequest {
    /// The points.
    pub points: Points,
    /// Their CRS; None for the store's.
    pub crs: Option<Crs>,
    /// The error of the cut they are sampled from.
    pub error: Metres,
    /// What the heights are measured from.
    pub heights: Heights,
    /// Whether to say what served each height.
    pub sources: bool,
}

impl SampleRequest {
    /// Heights at `points` of `crs` (None for the store's) at `error` metres, or why not.
    pub fn new(
        points: Vec<[f64; 2]>,
        crs: Option<Crs>,
        error: f64,
    ) -> Result<SampleRequest, BadRequest> {
        Ok(SampleRequest {
            points: Points::new(points)?,
            crs,
            error: Metres::error(error)?,
            heights: Heights::Store,
            sources: false,
        })
    }

    /// This request with its heights measured from `heights`.
    pub fn with_heights(mut self, heights: Heights) -> SampleRequest {
        self.heights = heights;
        self
    }

    /// This request asking what served each height.
    pub fn with_sources(mut self, sources: bool) -> SampleRequest {
        self.sources = sources;
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_parts_are_refused_with_their_kind() {
        assert_eq!(
            Metres::error(-1.0),
            Err(BadRequest::Metres {
                what: "error",
                got: -1.0
            })
        );
        assert!(matches!(
            Metres::error(f64::NAN),
            Err(BadRequest::Metres { .. })
        ));
        assert_eq!(Metres::error(0.0).map(Metres::get), Ok(0.0));
        assert!(matches!(
            Region::of(1.0, 0.0, 1.0, 2.0),
            Err(BadRequest::Region(_))
        ));
        assert!(matches!(
            Region::of(0.0, 0.0, f64::INFINITY, 2.0),
            Err(BadRequest::Region(_))
        ));
        assert!(Region::of(0.0, 0.0, 1.0, 2.0).is_ok());
        assert_eq!(
            TileSize::new(0, 4),
            Err(BadRequest::TileSize {
                width: 0,
                height: 4
            })
        );
        assert_eq!(TileSize::new(3, 4).map(TileSize::samples), Ok(12));
        assert!(matches!(
            Points::new(vec![[0.0, 0.0], [f64::NAN, 1.0]]),
            Err(BadRequest::Point { index: 1, .. })
        ));
        assert!(matches!(
            Camera::new([0.0; 3], [1.0, 0.0, 0.0], 180.0, 100, 1.0),
            Err(BadRequest::Camera(_))
        ));
        assert!(matches!(parse_crs("EPSG:nope"), Err(BadRequest::Crs(_))));
        assert_eq!(parse_crs("  "), Ok(None));
        assert_eq!(Heights::parse(""), Ok(Heights::Store));
        assert_eq!(Heights::parse("ellipsoid").unwrap().key(), "ellipsoidal");
        assert_eq!(Heights::parse("EPSG:5773").unwrap().key(), "EPSG:5773");
        assert!(matches!(
            Heights::parse("EPSG:4326"),
            Err(BadRequest::Heights { .. })
        ));
    }
}
