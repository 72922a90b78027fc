//! Surveys in a CRS other than the store's: how their plane lies in the store's plane.
//!
//! A survey keeps its own grid and samples, in its own CRS (its *plane*). Its surface in the
//! store's plane is its own surface seen through a map from the store's plane to its own: a
//! point of the store is carried into the survey's CRS ([`Plane::to_native`], the exact
//! transformation interpolated on a fixed lattice, see [`patchwork_crs::Reprojection`]) and
//! evaluated there. Everything about the survey is then as it is in its own CRS: kernels still
//! tile its grid with no gap or overlap, a sample still comes back as itself, and the height
//! at a store point depends on the point alone.
//!
//! What that map leaves approximate is counted. Its distance from the exact transformation,
//! ρ (measured over the survey's footprint), moves the point a survey is evaluated at by at
//! most ρ, so a height by at most ρ times the slope of the survey's reference surface: each
//! patch's error grows by ρ times the largest slope under its window ([`reprojection_error`]).
//!
//! The index needs the patches' kernels in the store's plane, where their images are curved.
//! Each patch gets an affine **frame** fitted to the images of its window's points, and a
//! bound on how far the frame lies from the true image anywhere in the window: the index
//! grows a shape by that bound where it must not miss a point, and shrinks it where it must
//! not claim one, so coverage between planes stays conservative (see `index::lod`).

use super::accuracy::KernelAccuracy;
use super::grid::{Georef, Grid, Shape};
use super::patch::{CellRect, Tiling};
use patchwork_crs::{Crs, CrsError, Reprojection};
use patchwork_geom::{Aabb, Affine};
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// Identifies a plane within a store: 0 for the store's own CRS, else a hash of the CRS.
pub type PlaneId = u64;

/// The store's own plane.
pub const STORE_PLANE: PlaneId = 0;

/// A CRS other than the store's, and the maps between its plane and the store's.
pub struct Plane {
    /// Its id within the store: a hash of the CRS.
    pub id: PlaneId,
    /// The CRS whose plane this is.
    pub crs: Crs,
    /// Store plane → this plane: where every height of its surveys is evaluated.
    pub to_native: Arc<Reprojection>,
    /// This plane → the store's: where its patches lie in the index.
    pub to_store: Reprojection,
}

impl std::fmt::Debug for Plane {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Plane({:?} in {:?})", self.crs, self.to_native.from())
    }
}

impl Plane {
    /// The plane of `native` in a store of `store`, with the maps both ways.
    pub fn new(store: &Crs, native: &Crs) -> Result<Plane, CrsError> {
        Ok(Plane {
            id: plane_id(native),
            crs: native.clone(),
            to_native: Arc::new(Reprojection::new(store, native)?),
            to_store: Reprojection::new(native, store)?,
        })
    }

    /// The store-plane bounds of a grid's samples, from its border's images; None when part
    /// of it has no image in the store's CRS.
    pub fn footprint(&self, shape: &Shape) -> Option<Aabb> {
        let [c, r] = [(shape.cols - 1) as f64, (shape.rows - 1) as f64];
        let n = 64;
        let mut pts = Vec::with_capacity(4 * n);
        for k in 0..n {
            let t = k as f64 / n as f64;
            pts.push([t * c, 0.0]);
            pts.push([c, t * r]);
            pts.push([c - t * c, r]);
            pts.push([0.0, r - t * r]);
        }
        let mut out = Vec::with_capacity(pts.len());
        for [gc, gr] in pts {
            out.push(self.to_store.at(shape.georef.to_world(gc, gr))?);
        }
        let b = Aabb::of_points(&out);
        // The border's images bound the images of the inside (the map is a homeomorphism);
        // between the border points a side bows out by at most what an affine fit of a
        // 1/64 of it leaves, far below this margin of a thousandth of the extent.
        Some(b.grown(1e-3 * b.width().max(b.height())))
    }

    /// The residuals of both lattices over a grid whose store-plane footprint is `bounds`:
    /// (to_native's, in this plane's units; to_store's, in the store's).
    pub fn residuals(&self, shape: &Shape, bounds: &Aabb) -> (f64, f64) {
        let native = shape.world_bounds();
        (
            self.to_native.residual(bounds.min, bounds.max),
            self.to_store.residual(native.min, native.max),
        )
    }

    /// The frame of a window of cells of a level georeferenced by `g`: the affine map from
    /// this plane to the store's that best fits the window's images, and how far from the
    /// surface's true image it may be anywhere in the window, in store units (`rho` adds the
    /// lattices' own residuals). None where part of the window has no image.
    pub fn frame(&self, g: &Georef, cells: &CellRect, rho: &Residuals) -> Option<Frame> {
        let (c0, r0) = (cells.c0 as f64, cells.r0 as f64);
        let (w, h) = (cells.cols().max(1) as f64, cells.rows().max(1) as f64);
        let centre = g.to_world(c0 + w / 2.0, r0 + h / 2.0);
        // 9 × 9 images of the window, the outer ring on its border.
        const N: usize = 9;
        let mut pts = Vec::with_capacity(N * N);
        for j in 0..N {
            for i in 0..N {
                let p = g.to_world(
                    c0 + w * i as f64 / (N - 1) as f64,
                    r0 + h * j as f64 / (N - 1) as f64,
                );
                let q = self.to_store.at(p)?;
                pts.push(([p[0] - centre[0], p[1] - centre[1]], q));
            }
        }
        let map = fit(&pts, centre)?;
        // How far the map is from the images at the 81 points; a smooth map's distance from
        // its affine fit is close to quadratic across the window, so its largest value between
        // points sampled every eighth of the window is within a few percent of the largest
        // at them, and a quarter more covers it.
        let fitted = pts
            .iter()
            .map(|(d, q)| {
                let a = map.apply([d[0] + centre[0], d[1] + centre[1]]);
                (a[0] - q[0]).hypot(a[1] - q[1])
            })
            .fold(0.0f64, f64::max);
        let scale = map.origin[0].abs().max(map.origin[1].abs());
        Some(Frame {
            rho: 1.25 * fitted
                + rho.to_store
                + rho.to_native * map.stretch()
                + 64.0 * f64::EPSILON * scale,
            map,
        })
    }
}

/// How far the two lattices of a plane are from the exact transformations over one survey.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Residuals {
    /// Of the map from the store's plane to the survey's, in the survey's CRS units: how far
    /// from its true place a point of the store is evaluated.
    pub to_native: f64,
    /// Of the map from the survey's plane to the store's, in the store's CRS units.
    pub to_store: f64,
}

/// Where a window of a survey of another plane lies in the store's plane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    /// Native world coordinates → store plane.
    pub map: Affine,
    /// A bound on the distance between `map` and the true image anywhere in the window, in
    /// store units.
    pub rho: f64,
}

/// The least-squares affine map through `(offset from centre, image)` pairs, as a map of
/// native world coordinates.
fn fit(pts: &[([f64; 2], [f64; 2])], centre: [f64; 2]) -> Option<Affine> {
    // Normal equations of q = o + A·d, with d the offset from the window's centre: the
    // offsets are symmetric, so the system is well conditioned whatever the coordinates.
    let n = pts.len() as f64;
    let (mut sx, mut sy, mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let mut rhs = [[0.0f64; 3]; 2];
    for (d, q) in pts {
        sx += d[0];
        sy += d[1];
        sxx += d[0] * d[0];
        sxy += d[0] * d[1];
        syy += d[1] * d[1];
        for k in 0..2 {
            rhs[k][0] += q[k];
            rhs[k][1] += q[k] * d[0];
            rhs[k][2] += q[k] * d[1];
        }
    }
    let m = [[n, sx, sy], [sx, sxx, sxy], [sy, sxy, syy]];
    let mut coef = [[0.0f64; 3]; 2];
    for k in 0..2 {
        coef[k] = solve3(m, rhs[k])?;
    }
    // q = o + a·d  with d = p − centre  ⇒  q = (o − a·centre) + a·p.
    let a = [[coef[0][1], coef[1][1]], [coef[0][2], coef[1][2]]];
    let o = [
        coef[0][0] - a[0][0] * centre[0] - a[1][0] * centre[1],
        coef[1][0] - a[0][1] * centre[0] - a[1][1] * centre[1],
    ];
    let map = Affine { origin: o, m: a };
    (map.det().is_finite() && map.det() != 0.0).then_some(map)
}

/// Cramer's rule on a 3 × 3 system.
fn solve3(m: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(m);
    if !(d.is_finite() && d != 0.0) {
        return None;
    }
    let mut out = [0.0; 3];
    for (c, o) in out.iter_mut().enumerate() {
        let mut mc = m;
        for r in 0..3 {
            mc[r][c] = b[r];
        }
        *o = det(mc) / d;
    }
    Some(out)
}

/// The plane id of a CRS other than the store's.
pub fn plane_id(crs: &Crs) -> PlaneId {
    let h = blake3::hash(crs.key().as_bytes());
    let id = u64::from_le_bytes(h.as_bytes()[..8].try_into().expect("8 bytes"));
    // 0 is the store's own plane.
    id.max(1)
}

/// The planes of one store's surveys, made once per CRS and shared, with their lattices'
/// caches, by every terrain and ingest of the store.
#[derive(Debug)]
pub struct Planes {
    store: Crs,
    planes: Mutex<HashMap<Crs, Arc<Plane>>>,
}

impl Planes {
    /// No planes yet, for a store in `store`.
    pub fn new(store: Crs) -> Planes {
        Planes {
            store,
            planes: Mutex::new(HashMap::new()),
        }
    }

    /// The store's own CRS.
    pub fn store_crs(&self) -> &Crs {
        &self.store
    }

    /// A plane made before, by its id.
    pub fn by_id(&self, id: PlaneId) -> Option<Arc<Plane>> {
        self.planes
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .values()
            .find(|p| p.id == id)
            .cloned()
    }

    /// The plane of a CRS; None for the store's own.
    pub fn get(&self, crs: &Crs) -> Result<Option<Arc<Plane>>, CrsError> {
        if *crs == self.store {
            return Ok(None);
        }
        let mut planes = self
            .planes
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(p) = planes.get(crs) {
            return Ok(Some(p.clone()));
        }
        let p = Arc::new(Plane::new(&self.store, crs)?);
        planes.insert(crs.clone(), p.clone());
        Ok(Some(p))
    }
}

/// The largest slope of the reference surface (the bilinear surface of level 0) in each
/// level-0 kernel, in metres per grid cell: the largest height change along a side of a
/// valid cell, taken along both axes. A point moved by δ cells along the grid moves the
/// surface by at most |δ| times the larger of the two, along each axis.
pub fn kernel_slopes(g: &Grid, tiling: &Tiling) -> KernelAccuracy {
    let [cw, ch] = g.cells();
    let dims = tiling.counts();
    let rows: Vec<Vec<f64>> = (0..ch)
        .into_par_iter()
        .map(|r| {
            let mut out = vec![0.0f64; dims[0]];
            for c in 0..cw {
                if !g.cell_valid(c, r) {
                    continue;
                }
                let (z00, z10) = (g.at(c, r) as f64, g.at(c + 1, r) as f64);
                let (z01, z11) = (g.at(c, r + 1) as f64, g.at(c + 1, r + 1) as f64);
                let s = (z10 - z00)
                    .abs()
                    .max((z11 - z01).abs())
                    .max((z01 - z00).abs())
                    .max((z11 - z10).abs());
                let k = tiling.kernel_at(c as u32, r as u32)[0] as usize;
                out[k] = out[k].max(s);
            }
            out
        })
        .collect();
    let mut values = vec![0.0f64; dims[0] * dims[1]];
    for (r, row) in rows.into_iter().enumerate() {
        let kr = tiling.kernel_at(0, r as u32)[1] as usize;
        for (k, s) in row.into_iter().enumerate() {
            let v = &mut values[kr * dims[0] + k];
            *v = v.max(s);
        }
    }
    KernelAccuracy { dims, values }
}

/// What a point's displacement by at most `rho` native units can do to a height of the
/// level-0 reference surface under `cells` (level-0 cells): `rho` in cells (the most a
/// displacement of that length moves grid coordinates) times the largest slope there, along
/// each axis.
pub fn reprojection_error(
    rho: f64,
    g0: &Georef,
    slopes: &KernelAccuracy,
    tiling0: &Tiling,
    cells: &CellRect,
) -> f64 {
    if rho == 0.0 {
        return 0.0;
    }
    // A displacement of at most ρ·(cells per unit) cells has components whose sum is at most
    // √2 times that, each cell of it costing at most the slope.
    std::f64::consts::SQRT_2 * rho * g0.cells_per_unit() * slopes.max_over(tiling0, cells)
}

/// Where a survey of another plane lies in the store's: its plane, the lattices' residuals
/// over it, and the frame of each of its patches.
#[derive(Debug)]
pub struct Placement {
    /// The survey's plane.
    pub plane: Arc<Plane>,
    /// The lattices' residuals over the survey.
    pub residuals: Residuals,
    /// The store-plane bounds of its samples.
    pub footprint: Aabb,
    /// The frame of each patch, in the order of the survey's patches.
    pub frames: Vec<Frame>,
}

/// Why a survey cannot be placed in the store's plane.
#[derive(Clone, Debug, thiserror::Error, PartialEq)]
pub enum PlaceError {
    /// The maps between the survey's plane and the store's could not be made.
    #[error(transparent)]
    Crs(#[from] CrsError),
    /// Part of the survey has no image in the store's CRS.
    #[error(
        "part of the survey lies where {from} cannot be carried into the store's {to}: \
         outside the area a projection is defined on"
    )]
    Outside {
        /// The survey's CRS, as its label.
        from: String,
        /// The store's CRS, as its label.
        to: String,
    },
    /// The survey was placed for a store of another CRS.
    #[error("the survey was placed in a store of {placed}, not in this one of {store}")]
    Elsewhere {
        /// The CRS of the store it was placed for, as its label.
        placed: String,
        /// This store's CRS, as its label.
        store: String,
    },
}

impl Placement {
    /// The placement of a grid whose levels are `shapes`, with patches whose windows are
    /// `windows` (level, cells), in `plane`.
    pub fn new(
        plane: Arc<Plane>,
        shapes: &[Shape],
        windows: impl IntoParallelIterator<Item = (usize, CellRect)>,
    ) -> Result<Placement, PlaceError> {
        let outside = || PlaceError::Outside {
            from: plane.crs.label(),
            to: plane.to_native.from().label(),
        };
        let footprint = plane.footprint(&shapes[0]).ok_or_else(outside)?;
        let (to_native, to_store) = plane.residuals(&shapes[0], &footprint);
        if !(to_native.is_finite() && to_store.is_finite()) {
            return Err(outside());
        }
        let residuals = Residuals {
            to_native,
            to_store,
        };
        let frames: Option<Vec<Frame>> = windows
            .into_par_iter()
            .map(|(level, w)| plane.frame(&shapes[level].georef, &w, &residuals))
            .collect();
        Ok(Placement {
            frames: frames.ok_or_else(outside)?,
            plane,
            residuals,
            footprint,
        })
    }
}
