//! The read path: cuts, tiles, meshes and points, from the published terrain and never the
//! writer. Requests are checked here (regions, errors, sizes against the limits) before any
//! work starts, and long work stops once its [`Cancel`] is set.

use super::request::{Camera, Ctx, Heights, Made, Metres, Region, SampleRequest, TileRequest};
use super::route::Used;
use super::sources::{self, Share, Source};
use super::{BadRequest, Engine, EngineError, HeightsError, TooLarge};
use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::{Crs, Reprojection};
use patchwork_core::geom::Aabb;
use patchwork_core::index::query::{Extracted, Metric, Shortfall, ViewQuery};
use patchwork_core::mesh;
use patchwork_core::model::geoid::Shift;
use patchwork_core::resample::{cpu, Backend, Cancel, SampleGrid};
use patchwork_core::sync::lock;
use patchwork_core::terrain::{tile_shortfall, view_grid, Terrain, Tile};
use patchwork_store::StoreError;
use std::sync::Arc;

/// A query's cut through LOD space, made of checked parts.
#[derive(Clone, Debug)]
pub enum Cut {
    /// Over a rectangle of the store's CRS.
    Uniform {
        /// The rectangle.
        roi: Region,
        /// The largest error allowed.
        error: Metres,
    },
    /// Over a rectangle of another CRS: a tile of it is resampled at its own sample
    /// positions, carried into the store's.
    UniformIn {
        /// The rectangle's CRS.
        crs: Crs,
        /// The rectangle.
        roi: Region,
        /// The largest error allowed.
        error: Metres,
    },
    /// Through a camera, in the store's CRS: the error allowed grows with the distance.
    View(Camera),
}

impl Cut {
    /// A uniform cut over `roi` of `crs` (None for the store's).
    pub fn uniform(crs: Option<Crs>, roi: Region, error: Metres) -> Cut {
        match crs {
            Some(crs) => Cut::UniformIn { crs, roi, error },
            None => Cut::Uniform { roi, error },
        }
    }

    /// A uniform cut over `roi` of `crs` (None for the store's) at `error` metres, or why
    /// not.
    pub fn new(crs: Option<Crs>, roi: Aabb, error: f64) -> Result<Cut, BadRequest> {
        Ok(Cut::uniform(crs, Region::new(roi)?, Metres::error(error)?))
    }

    /// The error a uniform cut is made at; None for a view's, which varies over it.
    pub fn error(&self) -> Option<f64> {
        match self {
            Cut::Uniform { error, .. } | Cut::UniformIn { error, .. } => Some(error.get()),
            Cut::View(_) => None,
        }
    }

    /// The same cut at another error; a view's is kept as it is.
    fn at_error(&self, e: Metres) -> Cut {
        let mut c = self.clone();
        if let Cut::Uniform { error, .. } | Cut::UniformIn { error, .. } = &mut c {
            *error = e;
        }
        c
    }

    /// The CRS the cut's region and a tile's positions are in; None for the store's.
    pub fn crs(&self) -> Option<&Crs> {
        match self {
            Cut::UniformIn { crs, .. } => Some(crs),
            _ => None,
        }
    }
}

/// Most vertices a row or column of a mesh: a 2049² grid resamples 4.2 M heights.
pub const MAX_MESH_SIZE: usize = 2049;

/// The most coarser cuts [`Engine::fill_voids`] asks: 8⁵ times the error is past every
/// survey's coarsest level.
pub const FILL_STEPS: usize = 5;

/// A mesh asked of a uniform cut.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshSpec {
    /// The tile the grid spans.
    pub roi: Region,
    /// The cut's error.
    pub error: Metres,
    /// Grid vertices a row: 2 to [`MAX_MESH_SIZE`].
    pub cols: usize,
    /// Rows of vertices: 2 to [`MAX_MESH_SIZE`].
    pub rows: usize,
    /// How far the triangles may depart from the resampled heights at the grid's vertices.
    pub mesh_error: Metres,
    /// Depth of the skirts under the border; 0 leaves them out.
    pub skirt_m: Metres,
    /// How the border's vertices are chosen.
    pub border: mesh::Border,
    /// The triangulation.
    pub method: mesh::Method,
    /// How far the surface may be drawn over a void from the nearest measured vertex,
    /// metres (seed 004's horizontal error); 0 keeps holes exact.
    pub hole_reach_m: Metres,
    /// The CRS of the ROI and of the vertices; None for the store's.
    pub crs: Option<Crs>,
    /// Whether void vertices are given heights (see [`Engine::fill_voids`], and 0 m where
    /// no survey is near) so that the mesh covers the whole tile, as a globe's terrain must.
    pub fill_voids: bool,
    /// What the vertices' heights are measured from.
    pub heights: Heights,
    /// Whether to resample a vertex more all round, beyond the tile's edges
    /// ([`MeshTile::rim`]), for normals that agree across them.
    pub rim: bool,
}

impl MeshSpec {
    /// The grid resampled for the mesh: its ROI and vertices each way, grown by a vertex
    /// all round with [`MeshSpec::rim`].
    fn resampled(&self) -> (Aabb, usize, usize) {
        let (roi, cols, rows) = (*self.roi.aabb(), self.cols, self.rows);
        if !self.rim {
            return (roi, cols, rows);
        }
        let dx = roi.width() / (cols - 1) as f64;
        let dy = roi.height() / (rows - 1) as f64;
        let grown = Aabb::new(
            roi.min[0] - dx,
            roi.min[1] - dy,
            roi.max[0] + dx,
            roi.max[1] + dy,
        );
        (grown, cols + 2, rows + 2)
    }
}

/// A mesh of a uniform cut and what it was made from.
#[derive(Clone, Debug)]
pub struct MeshTile {
    /// The triangles, their vertices in the spec's CRS.
    pub mesh: mesh::Mesh,
    /// The tile its grid spans.
    pub roi: Aabb,
    /// The patches blended, in id order.
    pub patches: Vec<Extracted>,
    /// The backend that resampled the grid.
    pub backend: Used,
    /// Where no data is as accurate as the cut asked.
    pub shortfall: Option<Shortfall>,
    /// With [`MeshSpec::fill_voids`], which grid vertices (row by row) had no data at the
    /// cut's error and were filled; empty when none were.
    pub voids: Vec<bool>,
    /// What the heights are measured from.
    pub frame: Frame,
    /// With [`MeshSpec::rim`], the heights of the grid with a vertex more all round,
    /// `(cols + 2) × (rows + 2)` row by row: the mesh's grid is its inside.
    pub rim: Option<Vec<f32>>,
}

/// What a reply's heights are measured from, and what carrying them there may have added.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Frame {
    /// The vertical CRS they are from; None where nothing says what the store's are from.
    pub vertical: Option<VerticalCrs>,
    /// The largest error the geoid grids' interpolation may have added to a height, metres
    /// (0 for heights left in the store's frame): add it to the cut's error.
    pub error_m: f64,
}

/// A tile resampled in bands: what it was blended from and what resampled it.
#[derive(Clone, Debug)]
pub struct Bands {
    /// The patches blended, in id order.
    pub patches: Vec<Extracted>,
    /// The backend that resampled.
    pub backend: Used,
    /// What the heights are measured from.
    pub frame: Frame,
}

/// Heights at points, and what they are measured from.
#[derive(Clone, Debug)]
pub struct Sampled {
    /// A height a point, NaN where there is no data.
    pub heights: Vec<f32>,
    /// What they are measured from.
    pub frame: Frame,
    /// Where asked, what served each height (None where there is none); else empty.
    pub sources: Vec<Option<Source>>,
}

/// What a tile is, told with each of its bands.
#[derive(Clone, Copy, Debug)]
pub struct TileHead<'a> {
    /// Samples a row of the tile.
    pub width: usize,
    /// Rows of the whole tile, not of one band.
    pub height: usize,
    /// The patches the heights are blended from, in id order.
    pub patches: &'a [Extracted],
    /// The backend that resampled.
    pub backend: Used,
    /// Where no data is as accurate as the cut asked.
    pub shortfall: Option<Shortfall>,
}

impl Engine {
    fn metric_at(&self, lat: f64) -> Metric {
        match self.crs() {
            Some(c) if c.is_geographic() => Metric::geographic(lat),
            _ => Metric::PROJECTED,
        }
    }

    /// The view query of a camera, with the store's metric.
    fn view_of(&self, c: &Camera) -> ViewQuery {
        c.query(self.metric_at(c.eye()[1]))
    }

    /// The map from a CRS to the store's, None for the store's own: one per CRS, kept, so
    /// that its lattice's nodes are worked out once for every request in it.
    pub fn to_store(&self, crs: &Crs) -> Result<Option<Arc<Reprojection>>, EngineError> {
        let Some(store) = self.crs() else {
            return Err(EngineError::NoCrs);
        };
        if *crs == store {
            return Ok(None);
        }
        let mut cache = lock(&self.request_crs);
        if let Some(r) = cache.get(crs).filter(|r| *r.to() == store) {
            return Ok(Some(r.clone()));
        }
        let r = Arc::new(Reprojection::new(crs, &store)?);
        // Clients name few CRSs; a bound keeps a client naming many from holding memory.
        if cache.len() >= 64 {
            cache.clear();
        }
        cache.insert(crs.clone(), r.clone());
        Ok(Some(r))
    }

    /// The bounds of the points of a rectangle's border carried into the store's plane, and
    /// the margin that holds the border between them (0 in the store's own CRS): a side bows
    /// between the points carried by far less than a thousandth of the extent.
    fn store_bounds(&self, crs: &Crs, roi: &Aabb) -> Result<(Aabb, f64), EngineError> {
        let Some(r) = self.to_store(crs)? else {
            return Ok((*roi, 0.0));
        };
        let n = 32;
        let mut pts = Vec::with_capacity(4 * n + 1);
        for k in 0..=n {
            let t = k as f64 / n as f64;
            let x = roi.min[0] + t * roi.width();
            let y = roi.min[1] + t * roi.height();
            pts.extend([
                [x, roi.min[1]],
                [x, roi.max[1]],
                [roi.min[0], y],
                [roi.max[0], y],
            ]);
        }
        let mapped: Option<Vec<[f64; 2]>> = pts.iter().map(|&p| r.at(p)).collect();
        let mapped = mapped.ok_or_else(|| EngineError::Unreachable {
            from: crs.label(),
            to: r.to().label(),
        })?;
        let b = Aabb::of_points(&mapped);
        Ok((b, 1e-3 * b.width().max(b.height())))
    }

    /// The patches of a cut, with the snapshot they came from.
    pub fn query(&self, cut: &Cut) -> Result<(Arc<Terrain>, Vec<Extracted>), EngineError> {
        let (t, ps) = self.patches_of(cut)?;
        self.within_max_patches(ps.len())?;
        Ok((t, ps))
    }

    /// [`Engine::query`] for a tile worth at most `most` patches: where the cut at the error
    /// asked holds more (a low zoom of a large store at a tiny error, whose samples would take
    /// seconds to decode for a few hundred thousand pixels), the error is raised fourfold until
    /// it holds no more, and the cut is returned with the error it was made at. At the top of
    /// LOD space a cut holds a patch or so a survey, so this ends.
    pub fn query_within(
        &self,
        cut: &Cut,
        most: u64,
    ) -> Result<(Cut, Arc<Terrain>, Vec<Extracted>), EngineError> {
        let top = self.cfg.index.max_error;
        let mut cut = cut.clone();
        loop {
            let (t, ps) = self.patches_of(&cut)?;
            match cut.error() {
                Some(e) if ps.len() as u64 > most && e < top => {
                    cut = cut.at_error(Metres::error((e * 4.0).clamp(0.01, top))?);
                }
                _ => {
                    self.within_max_patches(ps.len())?;
                    return Ok((cut, t, ps));
                }
            }
        }
    }

    fn within_max_patches(&self, n: usize) -> Result<(), EngineError> {
        let max = self.cfg.limits.max_patches;
        if n as u64 > max {
            return Err(TooLarge::Patches { n: n as u64, max }.into());
        }
        Ok(())
    }

    /// The patches of `cut`, however many.
    fn patches_of(&self, cut: &Cut) -> Result<(Arc<Terrain>, Vec<Extracted>), EngineError> {
        let t = self.snapshot();
        let ps = match cut {
            Cut::Uniform { roi, error } => {
                self.within_region(Some(roi.aabb()))?;
                t.uniform(roi.aabb(), error.get())
            }
            Cut::UniformIn { crs, roi, error } => {
                // A region is asked of the carried border itself, where a tile's samples lie;
                // the cut takes the margin for bowing sides too.
                let (b, m) = self.store_bounds(crs, roi.aabb())?;
                self.within_region(Some(&b))?;
                t.uniform(&b.grown(m), error.get())
            }
            Cut::View(c) => {
                self.within_region(None)?;
                t.view(&self.view_of(c))
            }
        };
        Ok((t, ps))
    }

    /// A resampled tile, the backend that resampled it, and what its heights are from.
    pub fn tile(&self, req: &TileRequest, ctx: Ctx) -> Result<(Tile, Used, Frame), EngineError> {
        let (mut heights, mut shortfall) = (Vec::new(), None);
        let rows = req.size.height() as usize;
        let bands = self.tile_bands(req, ctx, rows, &mut |head, _, band| {
            heights = band;
            shortfall = head.shortfall;
            true
        })?;
        let tile = Tile {
            width: req.size.width() as usize,
            height: req.size.height() as usize,
            heights,
            patches: bands.patches,
            shortfall,
        };
        Ok((tile, bands.backend, bands.frame))
    }

    /// How to carry the store's heights into `heights`: None where they stay as they are.
    fn shift_to(&self, heights: &Heights) -> Result<Option<Shift>, EngineError> {
        let Heights::In(to) = heights else {
            return Ok(None);
        };
        let Some(store) = self.vertical_crs() else {
            return Err(HeightsError::Unknown { asked: to.label() }.into());
        };
        if store.same_reference(to) {
            return Ok(None);
        }
        for v in [&store, to] {
            if !self.geoids.has(v) {
                return Err(HeightsError::NoGrid {
                    asked: to.label(),
                    store: store.label(),
                    missing: v.label(),
                    key: v.key().into(),
                    files: crate::geoids::known_files(v).join(" or "),
                }
                .into());
            }
        }
        let shift = self.geoids.shift(&store, to).map_err(HeightsError::Grid)?;
        Ok(Some(shift))
    }

    /// Carries `heights`, resampled at `grid`'s positions in `crs` (None: the store's) from
    /// the store's frame into the one asked: for a tile whose voids were filled first, which
    /// is resampled in the store's frame and converted after.
    pub fn carry_heights(
        &self,
        heights: &mut [f32],
        grid: &SampleGrid,
        crs: Option<&Crs>,
        to: &Heights,
    ) -> Result<Frame, EngineError> {
        let shift = self.shift_to(to)?;
        self.carry(shift, heights, grid, crs, to)
    }

    fn carry(
        &self,
        shift: Option<Shift>,
        heights: &mut [f32],
        grid: &SampleGrid,
        crs: Option<&Crs>,
        to: &Heights,
    ) -> Result<Frame, EngineError> {
        let mut frame = self.frame_of(to);
        if let (Some(s), Some(crs)) = (shift, crs.cloned().or_else(|| self.crs())) {
            let at: Vec<[f64; 2]> = grid.points().collect();
            frame.error_m = s.apply(heights, &at, &crs)?.error_m;
        }
        Ok(frame)
    }

    /// Whether the store's heights can be given as `heights`, or why not: for a client that
    /// would rather have them in the store's frame than none.
    pub fn can_give(&self, heights: &Heights) -> Result<(), EngineError> {
        self.shift_to(heights).map(|_| ())
    }

    /// The frame heights asked as `heights` are in, before any conversion's error.
    pub fn frame_of(&self, heights: &Heights) -> Frame {
        Frame {
            vertical: match heights {
                Heights::Store => self.vertical_crs(),
                Heights::In(v) => Some(v.clone()),
            },
            error_m: 0.0,
        }
    }

    /// A mesh of a uniform cut: the resampled heights at the corners of a `cols × rows` grid
    /// of vertices over the ROI (a tile over the ROI grown by half a cell, whose pixel
    /// centres fall on them), triangulated as `spec` says. A cut made already in `ctx` is
    /// [`Engine::query`] of [`Engine::mesh_cut`]`(spec)`.
    pub fn mesh(
        &self,
        spec: &MeshSpec,
        backend: Backend,
        ctx: Ctx,
    ) -> Result<MeshTile, EngineError> {
        let (roi, cols, rows) = (*spec.roi.aabb(), spec.cols, spec.rows);
        for (side, n) in [("columns", cols), ("rows", rows)] {
            if !(2..=MAX_MESH_SIZE).contains(&n) {
                return Err(BadRequest::MeshSize {
                    side,
                    got: n,
                    most: MAX_MESH_SIZE,
                }
                .into());
            }
        }
        let cancel = ctx.cancel.clone();
        let shift = self.shift_to(&spec.heights)?;
        // The grid resampled: the mesh's, or with a vertex more all round.
        let (groi, gcols, grows) = spec.resampled();
        let pixels = mesh::pixel_roi(&groi, gcols, grows);
        let req = TileRequest::new(Self::mesh_cut(spec)?, gcols as u32, grows as u32, backend)?;
        let (mut tile, used, _) = self.tile(&req, ctx)?;
        let grid = SampleGrid::uniform(&pixels, gcols, grows);
        let mut voids = Vec::new();
        if spec.fill_voids {
            voids = self.fill_voids(
                &mut tile.heights,
                &grid,
                spec.crs.as_ref(),
                spec.error.get(),
                &cancel,
            )?;
        }
        // Converted once the voids are filled (in the store's frame, as the surveys are),
        // and before a void far from any survey is put on the ellipsoid.
        let frame = self.carry(
            shift,
            &mut tile.heights,
            &grid,
            spec.crs.as_ref(),
            &spec.heights,
        )?;
        if spec.fill_voids {
            // Nothing near enough to fill from: no survey is there, and a globe shows its
            // ellipsoid.
            for h in tile.heights.iter_mut().filter(|h| h.is_nan()) {
                *h = 0.0;
            }
        }
        let rim = spec.rim.then(|| {
            // The mesh's grid is the inside of the one resampled.
            let inside = |v: &[f32]| -> Vec<f32> {
                (1..=rows)
                    .flat_map(|j| v[j * gcols + 1..j * gcols + 1 + cols].to_vec())
                    .collect()
            };
            let all = std::mem::take(&mut tile.heights);
            tile.heights = inside(&all);
            if !voids.is_empty() {
                voids = (1..=rows)
                    .flat_map(|j| voids[j * gcols + 1..j * gcols + 1 + cols].to_vec())
                    .collect();
            }
            all
        });
        let holes = if spec.hole_reach_m.get() > 0.0 {
            let mid = (roi.min[1] + roi.max[1]) / 2.0;
            let scale = match &spec.crs {
                Some(c) => match c.unit_m() {
                    Some(m) => [m, m],
                    None => Metric::geographic(mid).scale,
                },
                None => self.metric_at(mid).scale,
            };
            mesh::Holes::Reach {
                reach: spec.hole_reach_m.get(),
                cell: [
                    roi.width() / (cols - 1) as f64 * scale[0],
                    roi.height() / (rows - 1) as f64 * scale[1],
                ],
            }
        } else {
            mesh::Holes::Exact
        };
        let options = mesh::Options {
            max_error: spec.mesh_error.get(),
            border: spec.border,
            method: spec.method,
            holes,
        };
        let mut mesh = mesh::triangulate_until(&tile.heights, cols, rows, &options, &|| {
            cancel.is_cancelled()
        })
        .ok_or(EngineError::Cancelled)?;
        if spec.skirt_m.get() > 0.0 {
            mesh::add_skirts(&mut mesh, spec.skirt_m.get() as f32);
        }
        Ok(MeshTile {
            mesh,
            roi,
            patches: tile.patches,
            backend: used,
            shortfall: tile.shortfall,
            voids,
            frame,
            rim,
        })
    }

    /// The cut a mesh resamples: over the ROI grown by half a cell, whose pixel centres fall
    /// on the grid's vertices.
    pub fn mesh_cut(spec: &MeshSpec) -> Result<Cut, EngineError> {
        let (roi, cols, rows) = spec.resampled();
        let pixels = mesh::pixel_roi(&roi, cols, rows);
        Ok(Cut::uniform(
            spec.crs.clone(),
            Region::new(pixels)?,
            spec.error,
        ))
    }

    /// Fills the voids (NaN) of `heights`, a tile at `grid`'s positions (of `crs`, None for
    /// the store's) cut at error `e`, from ever coarser cuts at the same points: at 8, 64, …
    /// times `e` (1 m at least), up to [`FILL_STEPS`] of them, each void taking the first
    /// height it is given. A coarser level of a survey averages the samples around a void,
    /// so a hole no wider than its cells is bridged by the survey's own terrain. Each height
    /// is that of a point at an error, as any request gives it: a void is filled alike in
    /// every tile that holds it, so neighbouring tiles still meet. Voids that no coarser cut
    /// reaches stay NaN. Returns which samples were void at `e` (empty when none were).
    pub fn fill_voids(
        &self,
        heights: &mut [f32],
        grid: &SampleGrid,
        crs: Option<&Crs>,
        e: f64,
        cancel: &Cancel,
    ) -> Result<Vec<bool>, EngineError> {
        let mut todo: Vec<usize> = (0..heights.len())
            .filter(|&k| heights[k].is_nan())
            .collect();
        if todo.is_empty() {
            return Ok(Vec::new());
        }
        let voids = heights.iter().map(|h| h.is_nan()).collect();
        // The voids' positions in the store's plane, carried once as a tile's are (so that
        // each gets the height a request in `crs` gives there), and only those a survey can
        // reach: most voids of a tile at the data's edge are far from every survey.
        let own: Vec<[f64; 2]> = todo.iter().map(|&k| grid.point(k)).collect();
        let near = self.reach();
        let mut points = match crs.map(|c| self.to_store(c)).transpose()?.flatten() {
            Some(r) => r.map_where(&own, &near),
            None => own,
        };
        let mut kept = 0;
        for i in 0..todo.len() {
            if near(points[i]) {
                (todo[kept], points[kept]) = (todo[i], points[i]);
                kept += 1;
            }
        }
        todo.truncate(kept);
        points.truncate(kept);
        // A cut at the top of LOD space holds nothing: stop below it.
        let top = self.cfg.index.max_error / 2.0;
        let mut coarser = e.max(1.0);
        for _ in 0..FILL_STEPS {
            if todo.is_empty() || coarser >= top {
                break;
            }
            coarser = (coarser * 8.0).min(top);
            let found = self.sample_points(&points, None, coarser, cancel)?;
            let (mut left, mut at) = (Vec::new(), Vec::new());
            for ((&k, p), h) in todo.iter().zip(&points).zip(found) {
                if h.is_nan() {
                    left.push(k);
                    at.push(*p);
                } else {
                    heights[k] = h;
                }
            }
            (todo, points) = (left, at);
        }
        Ok(voids)
    }

    /// A resampled tile in bands of about `rows` rows, top first: `sink` gets what the tile
    /// is, each band's first row and its heights, and says whether to go on. On the CPU a band
    /// goes to `sink` as soon as it is done, so that it can be sent while the next is worked
    /// out. Returns the patches blended and the backend that ran.
    pub fn tile_bands(
        &self,
        req: &TileRequest,
        ctx: Ctx,
        rows: usize,
        sink: &mut dyn FnMut(&TileHead, usize, Vec<f32>) -> bool,
    ) -> Result<Bands, EngineError> {
        let (cut, backend, cancel) = (&req.cut, req.backend, &ctx.cancel);
        let shift = self.shift_to(&req.heights)?;
        let (width, height) = (req.size.width(), req.size.height());
        let n = req.size.samples();
        let max = self.cfg.limits.max_tile_samples;
        if n > max {
            return Err(TooLarge::TileSamples {
                width,
                height,
                n,
                max,
            }
            .into());
        }
        let (t, ps): Made = match ctx.made {
            Some(m) => m,
            None => self.query(cut)?,
        };
        let grid = self.grid_of(cut, width as usize, height as usize)?;
        // Heights asked from another vertical CRS are carried there band by band, at the
        // tile's own positions: a tile in another CRS than the store's has them in its own.
        let mut frame = self.frame_of(&req.heights);
        let mut failed = None;
        let placed = match (&shift, cut) {
            (None, _) => None,
            (Some(_), Cut::UniformIn { crs, roi, .. }) => Some((
                Some(SampleGrid::uniform(
                    roi.aabb(),
                    width as usize,
                    height as usize,
                )),
                crs.clone(),
            )),
            (Some(_), _) => self.crs().map(|c| (None, c)),
        };
        let outer = sink;
        let sink = &mut |head: &TileHead, j0: usize, mut band: Vec<f32>| -> bool {
            if let (Some(s), Some((own, crs))) = (&shift, &placed) {
                let at = own.as_ref().unwrap_or(&grid);
                let k0 = j0 * at.width;
                let points: Vec<[f64; 2]> = (k0..k0 + band.len()).map(|k| at.point(k)).collect();
                match s.apply(&mut band, &points, crs) {
                    Ok(c) => frame.error_m = frame.error_m.max(c.error_m),
                    Err(e) => {
                        failed = Some(e);
                        return false;
                    }
                }
            }
            outer(head, j0, band)
        };
        let done = self.resample(&t, &ps, &grid, backend, rows, cancel, sink);
        if let Some(e) = failed {
            return Err(HeightsError::Convert(e).into());
        }
        let backend = done?;
        Ok(Bands {
            patches: ps,
            backend,
            frame,
        })
    }

    /// The positions in the store's plane of a `width × height` tile of `cut`.
    fn grid_of(&self, cut: &Cut, width: usize, height: usize) -> Result<SampleGrid, EngineError> {
        Ok(match cut {
            Cut::Uniform { roi, .. } => SampleGrid::uniform(roi.aabb(), width, height),
            Cut::UniformIn { crs, roi, .. } => {
                // The tile's own positions, carried into the store's plane.
                let own = SampleGrid::uniform(roi.aabb(), width, height);
                match self.to_store(crs)? {
                    Some(r) => carried(&own, &r, self.reach()),
                    None => own,
                }
            }
            Cut::View(c) => view_grid(&self.view_of(c), width, height),
        })
    }

    /// [`Self::tile_bands`]'s work: `grid` resampled from the patches `ps` of `t`.
    #[allow(clippy::too_many_arguments)]
    fn resample(
        &self,
        t: &Terrain,
        ps: &[Extracted],
        grid: &SampleGrid,
        backend: Backend,
        rows: usize,
        cancel: &Cancel,
        sink: &mut dyn FnMut(&TileHead, usize, Vec<f32>) -> bool,
    ) -> Result<Used, EngineError> {
        let shortfall = tile_shortfall(ps, grid);
        let head = |backend| TileHead {
            width: grid.width,
            height: grid.height,
            patches: ps,
            backend,
            shortfall,
        };
        // The samples are read (from the pack, or the chunk cache) before the GPU is asked
        // for, so that the device's lock is never held across disk I/O.
        let set = t
            .try_resolve_until(ps, &|| cancel.is_cancelled())
            .map_err(StoreError::from)?
            .ok_or(EngineError::Cancelled)?;
        // `auto` goes to whichever backend is expected to finish the tile first.
        let router = &self.gpu.router;
        let samples = (grid.width * grid.height) as u64;
        let has_gpu = self.has_gpu();
        let backend = if backend == Backend::Auto && has_gpu && !router.prefers_gpu(samples) {
            Backend::Cpu
        } else {
            backend
        };
        let on_gpu = (backend != Backend::Cpu && has_gpu).then(|| router.start(Used::Gpu, samples));
        if let Some(heights) = self.gpu_heights(&set, grid, backend)? {
            if let Some(run) = on_gpu {
                run.finish();
            }
            let head = head(Used::Gpu);
            let rows = rows.max(1);
            if rows >= grid.height {
                if !sink(&head, 0, heights) {
                    return Err(EngineError::Cancelled);
                }
            } else {
                for (k, band) in heights.chunks(rows * grid.width).enumerate() {
                    if !sink(&head, k * rows, band.to_vec()) {
                        return Err(EngineError::Cancelled);
                    }
                }
            }
            return Ok(Used::Gpu);
        }
        drop(on_gpu);
        let head = head(Used::Cpu);
        let mut run = router.start(Used::Cpu, samples);
        cpu::resample_bands(&set, grid, rows, cancel, &mut |j0, band| {
            // Handing a band to a slow client is not the CPU's time.
            let t = std::time::Instant::now();
            let more = sink(&head, j0, band);
            run.pause(t.elapsed());
            more
        })
        .ok_or(EngineError::Cancelled)?;
        run.finish();
        Ok(Used::Cpu)
    }

    /// Heights at points of a CRS: the points are carried into the store's plane as a tile's
    /// positions are, so a point has the height any tile of that CRS holding it gives.
    pub fn sample(&self, req: &SampleRequest, ctx: Ctx) -> Result<Sampled, EngineError> {
        let shift = self.shift_to(&req.heights)?;
        let points = req.points.get();
        if points.len() as u64 > self.cfg.limits.max_points {
            return Err(TooLarge::Points {
                n: points.len() as u64,
                max: self.cfg.limits.max_points,
            }
            .into());
        }
        let (mut heights, sources) = if req.sources {
            // The terrain and the records of one commit, so that every patch's survey is
            // in the catalog.
            let (t, catalog) = self.published();
            let at = self.in_store(points, req.crs.as_ref())?;
            let (heights, served) = t
                .try_sample_sources_until(&at, req.error.get(), &ctx.cancel)
                .map_err(StoreError::from)?
                .ok_or(EngineError::Cancelled)?;
            let sources = served
                .iter()
                .map(|x| x.as_ref().map(|x| sources::source_of(&t, &catalog, x)))
                .collect();
            (heights, sources)
        } else {
            let h = self.sample_points(points, req.crs.as_ref(), req.error.get(), &ctx.cancel)?;
            (h, Vec::new())
        };
        let mut frame = self.frame_of(&req.heights);
        if let (Some(s), Some(crs)) = (&shift, req.crs.clone().or_else(|| self.crs())) {
            frame.error_m = s.apply(&mut heights, points, &crs)?.error_m;
        }
        Ok(Sampled {
            heights,
            frame,
            sources,
        })
    }

    /// The surveys that served a tile, each with the share of the tile's samples it served,
    /// most first: the tile `req` asks for, blended from the same cut.
    pub fn tile_sources(&self, req: &TileRequest, ctx: Ctx) -> Result<Vec<Share>, EngineError> {
        let (width, height) = (req.size.width() as usize, req.size.height() as usize);
        let (t, ps): Made = match ctx.made {
            Some(m) => m,
            None => self.query(&req.cut)?,
        };
        // Read after the cut: a record, once written, stays until its survey is forgotten.
        let catalog = self.catalog();
        let grid = self.grid_of(&req.cut, width, height)?;
        let served = t.try_sources(&ps, &grid).map_err(StoreError::from)?;
        Ok(sources::shares(&t, &catalog, &served))
    }

    /// Whether a point of the store's plane is where any survey can give a height (within
    /// one's [`super::write::changed_area`]): a point beyond all of them has none, at any
    /// error.
    fn reach(&self) -> impl Fn([f64; 2]) -> bool + Sync {
        let areas: Vec<Aabb> = self
            .snapshot()
            .surveys()
            .map(|s| super::write::changed_area(s))
            .collect();
        move |p| areas.iter().any(|a| a.contains_point(p))
    }

    /// Points of `crs` (None for the store's) in the store's plane, NaN where the map does
    /// not reach; on a replica of a region, refused if one lies beyond it.
    fn in_store<'a>(
        &self,
        points: &'a [[f64; 2]],
        crs: Option<&Crs>,
    ) -> Result<std::borrow::Cow<'a, [[f64; 2]]>, EngineError> {
        let at = match crs.map(|c| self.to_store(c)).transpose()?.flatten() {
            Some(r) => std::borrow::Cow::Owned(r.map_where(points, self.reach())),
            None => std::borrow::Cow::Borrowed(points),
        };
        if self.region().is_some() {
            let placed: Vec<[f64; 2]> = at
                .iter()
                .copied()
                .filter(|p| p[0].is_finite() && p[1].is_finite())
                .collect();
            if !placed.is_empty() {
                self.within_region(Some(&Aabb::of_points(&placed)))?;
            }
        }
        Ok(at)
    }

    /// Heights at points of `crs` (None for the store's) at error `e`, given up once
    /// `cancel` is set.
    fn sample_points(
        &self,
        points: &[[f64; 2]],
        crs: Option<&Crs>,
        e: f64,
        cancel: &Cancel,
    ) -> Result<Vec<f32>, EngineError> {
        let points = self.in_store(points, crs)?;
        self.snapshot()
            .try_sample_until(&points, e, cancel)
            .map_err(StoreError::from)?
            .ok_or(EngineError::Cancelled)
    }
}

/// A north-up grid's points carried into the store's plane by `r`. Where the map takes the
/// grid's columns to columns and its rows to rows (Web Mercator to longitude and latitude,
/// say), the carried grid keeps axes, and the resampler its pass by rows and columns, which
/// is several times faster than point by point: checked at the corners, the middle and
/// between, each point must be where its column and its row put it, within 10⁻⁹ of the grid's
/// extent (a micrometre on a kilometre's tile). Any other map is applied point by point.
///
/// Positions whose exact image no survey reaches (`near` false) may be left out as NaN: a
/// low zoom's tile spans continents the lattice would otherwise be built over.
fn carried(
    own: &SampleGrid,
    r: &Arc<Reprojection>,
    near: impl Fn([f64; 2]) -> bool + Sync,
) -> SampleGrid {
    if let Some(a) = &own.axes {
        let (w, h) = (a.xs.len(), a.ys.len());
        let (xm, ym) = (a.xs[w / 2], a.ys[h / 2]);
        let xs: Option<Vec<f64>> = a.xs.iter().map(|&x| r.at([x, ym]).map(|p| p[0])).collect();
        let ys: Option<Vec<f64>> = a.ys.iter().map(|&y| r.at([xm, y]).map(|p| p[1])).collect();
        if let (Some(xs), Some(ys)) = (xs, ys) {
            let span = |v: &[f64]| (v[0] - v[v.len() - 1]).abs();
            let tol = 1e-9 * span(&xs).max(span(&ys)).max(f64::MIN_POSITIVE);
            let probes = [0, w / 4, w / 2, 3 * w / 4, w - 1]
                .into_iter()
                .flat_map(|i| [0, h / 3, h / 2, 2 * h / 3, h - 1].map(|j| (i, j)));
            let separable = probes.into_iter().all(|(i, j)| {
                r.at([a.xs[i], a.ys[j]])
                    .is_some_and(|p| (p[0] - xs[i]).abs() <= tol && (p[1] - ys[j]).abs() <= tol)
            });
            if separable {
                return SampleGrid::of_axes(xs, ys);
            }
        }
    }
    if let Some(a) = &own.axes {
        if a.bounds().is_some_and(|b| r.gathers(b.min, b.max)) {
            // Kept as the lattice and the grid it carries: a device carries the points
            // itself, and the CPU lists them as `map` would.
            return SampleGrid::carried(a.clone(), r.clone());
        }
    }
    let pts: Vec<[f64; 2]> = own.points().collect();
    SampleGrid::of_points(own.width, own.height, r.map_where(&pts, near))
}
