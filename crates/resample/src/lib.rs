//! Resampling extracted patches into heights (§5): sample grids, resolved patches and their
//! surfaces, and the CPU implementation of Formula 1 and of the accurate blend ([`cpu`]). The
//! GPU's, which holds to this one, is the daemon's (it needs a device). Pure computation: it blends whatever
//! patches it is given, and imports neither the index nor anything above.

pub mod cpu;

use patchwork_crs::Reprojection;
use patchwork_geom::snap;
use patchwork_geom::{Aabb, ORect};
use patchwork_model::edge::{EdgeGrid, EdgePatch};
use patchwork_model::grid::{Georef, SampleRect, Window};
use patchwork_model::ids::PatchId;
use patchwork_model::patch::{Bicubic, Blend, CellRect, Patch, PatchKind};
use patchwork_model::spline::Spline;
use patchwork_model::survey::SurveyMeta;
use std::sync::Arc;

/// Where a tile is resampled: `Auto` takes the GPU when the daemon has one.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// The GPU where the daemon has one that serves, else the CPU.
    Auto,
    /// The CPU only.
    Cpu,
    /// The GPU only: an error where the daemon has none or it fails.
    Gpu,
}

/// Set when the caller of a long computation has given up (its deadline passed): the loops
/// that resample check it as they go and stop, so that abandoned work frees its thread.
#[derive(Clone, Debug, Default)]
pub struct Cancel(Arc<std::sync::atomic::AtomicBool>);

impl Cancel {
    /// Asks the work to stop; every clone sees it.
    pub fn cancel(&self) {
        self.0.store(true, std::sync::atomic::Ordering::Relaxed);
    }

    /// Whether [`Self::cancel`] has been called on this or any clone.
    #[inline]
    pub fn is_cancelled(&self) -> bool {
        self.0.load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// Output samples per block side when binning patches.
pub const BLOCK: usize = 16;

/// Where to sample: a `width × height` array of plane positions, row-major. A NaN position
/// (a view ray above the horizon) yields nodata.
///
/// A grid is kept in the form it was made in, so that a device can generate its points from
/// a few numbers where the CPU lists them: a north-up grid's axes, a view's rows (each an
/// evenly spaced line), or another CRS's north-up grid carried through a lattice; any other
/// grid lists its points.
#[derive(Clone, Debug)]
pub struct SampleGrid {
    /// Samples per row.
    pub width: usize,
    /// Rows of samples.
    pub height: usize,
    /// Every point, row-major, listed on first use by a grid of rows or a carried grid, and
    /// never by a north-up one: listing a 2048² tile's points took longer than blending most
    /// of it.
    list: std::sync::OnceLock<Vec<[f64; 2]>>,
    /// For a north-up tile, the x of each column and the y of each row: point (i, j) is
    /// (xs[i], ys[j]), which lets the CPU work out per column and per row what it would
    /// otherwise work out per sample.
    pub axes: Option<Axes>,
    /// For a grid of rows, each row's first point and step (point (i, j) is first + i·step),
    /// or None for a row without points.
    rows: Option<Arc<Vec<Row>>>,
    /// For a grid carried from another CRS, the grid there and the lattice that carries it.
    carry: Option<Arc<Carried>>,
}

/// A row of evenly spaced points: the first, and the step to the next. None for a row all
/// of whose points are NaN.
pub type Row = Option<[[f64; 2]; 2]>;

/// Point `i` of a row, `first + i·step`, computed so in f64: each coordinate moves one way
/// with `i`, so a run of a row's points is bounded by its ends.
#[inline]
pub fn row_point([p, q]: &[[f64; 2]; 2], i: usize) -> [f64; 2] {
    let i = i as f64;
    [p[0] + i * q[0], p[1] + i * q[1]]
}

/// A north-up grid of another CRS whose points are carried into the store's plane by a
/// lattice, point (i, j) to `by.at([own.xs[i], own.ys[j]])`.
pub struct Carried {
    /// The grid in its own CRS.
    pub own: Axes,
    /// From its CRS to the store's.
    pub by: Arc<Reprojection>,
}

impl std::fmt::Debug for Carried {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Carried")
            .field("width", &self.own.xs.len())
            .field("height", &self.own.ys.len())
            .field("from", &self.by.from().key())
            .finish()
    }
}

/// Closed intervals [min, max] along one axis.
pub type Intervals = Vec<[f64; 2]>;

/// The coordinates of a north-up tile's columns and rows.
#[derive(Clone, Debug)]
pub struct Axes {
    /// The x of each column.
    pub xs: Vec<f64>,
    /// The y of each row.
    pub ys: Vec<f64>,
}

impl Axes {
    /// The bounds of the grid's points; None where a coordinate is not finite.
    pub fn bounds(&self) -> Option<Aabb> {
        let span = |v: &[f64]| {
            v.iter()
                .fold([f64::INFINITY, f64::NEG_INFINITY], |[lo, hi], &x| {
                    [lo.min(x), hi.max(x)]
                })
        };
        let ([x0, x1], [y0, y1]) = (span(&self.xs), span(&self.ys));
        [x0, x1, y0, y1]
            .iter()
            .all(|v| v.is_finite())
            .then(|| Aabb::new(x0, y0, x1, y1))
    }
}

impl SampleGrid {
    fn of(width: usize, height: usize) -> Self {
        SampleGrid {
            width,
            height,
            list: std::sync::OnceLock::new(),
            axes: None,
            rows: None,
            carry: None,
        }
    }

    /// A north-up tile over `roi`, sample (i, j) at the centre of its pixel.
    pub fn uniform(roi: &Aabb, width: usize, height: usize) -> Self {
        let dx = roi.width() / width as f64;
        let dy = roi.height() / height as f64;
        let xs: Vec<f64> = (0..width)
            .map(|i| roi.min[0] + (i as f64 + 0.5) * dx)
            .collect();
        let ys: Vec<f64> = (0..height)
            .map(|j| roi.max[1] - (j as f64 + 0.5) * dy)
            .collect();
        Self::of_axes(xs, ys)
    }

    /// A north-up grid of any columns and rows: point (i, j) is (xs[i], ys[j]).
    pub fn of_axes(xs: Vec<f64>, ys: Vec<f64>) -> Self {
        Self::of(xs.len(), ys.len()).with_axes(Axes { xs, ys })
    }

    fn with_axes(mut self, a: Axes) -> Self {
        self.axes = Some(a);
        self
    }

    /// A grid of any points, row-major, `width × height` of them.
    pub fn of_points(width: usize, height: usize, points: Vec<[f64; 2]>) -> Self {
        assert_eq!(points.len(), width * height, "a point for every sample");
        let g = Self::of(width, height);
        g.list.set(points).expect("a new grid lists nothing");
        g
    }

    /// A grid of `width` points a row, each row evenly spaced: point (i, j) is
    /// `first + i·step` of `rows[j]`, computed so in f64, or NaN for a row that is None.
    pub fn of_rows(width: usize, rows: Vec<Row>) -> Self {
        Self::of(width, rows.len()).with_rows(rows)
    }

    fn with_rows(mut self, rows: Vec<Row>) -> Self {
        self.rows = Some(Arc::new(rows));
        self
    }

    /// The north-up grid `own` of another CRS, carried by `by` into the store's plane: point
    /// (i, j) is where [`Reprojection::map`] takes (xs[i], ys[j]).
    pub fn carried(own: Axes, by: Arc<Reprojection>) -> Self {
        Self::of(own.xs.len(), own.ys.len()).with_carry(Carried { own, by })
    }

    fn with_carry(mut self, c: Carried) -> Self {
        self.carry = Some(Arc::new(c));
        self
    }

    /// The same points without their form: resampled one point at a time, as any grid is.
    pub fn pointwise(self) -> Self {
        let list = self.points().collect();
        SampleGrid::of_points(self.width, self.height, list)
    }

    /// For a grid of rows, each row's first point and step.
    pub fn rows(&self) -> Option<&[Row]> {
        self.rows.as_deref().map(Vec::as_slice)
    }

    /// For a carried grid, the grid in its own CRS and the lattice that carries it.
    pub fn carry(&self) -> Option<&Carried> {
        self.carry.as_deref()
    }

    /// Every point, row-major, listed on first use for a grid that does not list them (a
    /// north-up grid's are its axes' products).
    pub fn list(&self) -> &[[f64; 2]] {
        self.list.get_or_init(|| {
            if let Some(c) = &self.carry {
                let pts: Vec<[f64; 2]> = c
                    .own
                    .ys
                    .iter()
                    .flat_map(|&y| c.own.xs.iter().map(move |&x| [x, y]))
                    .collect();
                return c.by.map(&pts);
            }
            (0..self.width * self.height)
                .map(|k| self.point(k))
                .collect()
        })
    }

    /// Sample k's position, row-major.
    #[inline]
    pub fn point(&self, k: usize) -> [f64; 2] {
        if let Some(a) = &self.axes {
            return [a.xs[k % self.width], a.ys[k / self.width]];
        }
        if let Some(rows) = &self.rows {
            return match &rows[k / self.width] {
                Some(row) => row_point(row, k % self.width),
                None => [f64::NAN; 2],
            };
        }
        self.list()[k]
    }

    /// Every sample's position, row-major.
    pub fn points(&self) -> impl ExactSizeIterator<Item = [f64; 2]> + '_ {
        (0..self.width * self.height).map(|k| self.point(k))
    }

    /// For a north-up grid whose axes each run one way, the x interval of each column of
    /// `side` × `side` squares of samples and the y interval of each row of them, from the
    /// first and last sample each spans: square (i, j) is their product. None for any other
    /// grid, whose squares' bounds come from their points.
    pub fn axis_bounds(&self, side: usize) -> Option<(Intervals, Intervals)> {
        let Axes { xs, ys } = self.axes.as_ref()?;
        let spans = |v: &[f64]| {
            v.chunks(side)
                .map(|c| {
                    let (a, b) = (c[0], c[c.len() - 1]);
                    [a.min(b), a.max(b)]
                })
                .collect()
        };
        // First and last bound a square only along an axis that runs one way.
        let monotone =
            |v: &[f64]| v.windows(2).all(|w| w[0] <= w[1]) || v.windows(2).all(|w| w[0] >= w[1]);
        if !(monotone(xs) && monotone(ys)) {
            return None;
        }
        Some((spans(xs), spans(ys)))
    }

    /// Bounds of each block's points, row-major over blocks; None for a block without any.
    pub fn block_bounds(&self) -> Vec<Option<Aabb>> {
        self.bounds_of(BLOCK)
    }

    /// Bounds of the points of each `side` × `side` square of samples, row-major; None for
    /// one without any.
    pub fn bounds_of(&self, side: usize) -> Vec<Option<Aabb>> {
        let bx = self.width.div_ceil(side);
        let by = self.height.div_ceil(side);
        if let Some((cols, rows)) = self.axis_bounds(side) {
            return (0..bx * by)
                .map(|b| {
                    let ([x0, x1], [y0, y1]) = (cols[b % bx], rows[b / bx]);
                    Some(Aabb::new(x0, y0, x1, y1))
                })
                .collect();
        }
        use rayon::prelude::*;
        (0..bx * by)
            .into_par_iter()
            .map(|b| {
                let (i0, j0) = ((b % bx) * side, (b / bx) * side);
                let mut acc: Option<Aabb> = None;
                for j in j0..(j0 + side).min(self.height) {
                    for i in i0..(i0 + side).min(self.width) {
                        let p = self.point(j * self.width + i);
                        if p[0].is_nan() {
                            continue;
                        }
                        let pb = Aabb { min: p, max: p };
                        acc = Some(acc.map_or(pb, |a| a.union(&pb)));
                    }
                }
                acc
            })
            .collect()
    }
}

/// What a patch evaluates.
#[derive(Clone, Debug)]
pub enum Surface {
    /// A mipmap level, bilinear on its valid cells, through a window that holds at least the
    /// patch's samples and one more ring where the level has it (see [`ResolvedPatch::reads`]).
    Bilinear(Window),
    /// The same, evaluating the patch's spline (fitted to its window's samples) wherever the
    /// bilinear surface is defined.
    Bicubic(Window, Arc<Spline>),
    /// An edge patch's filled samples (see [`patchwork_model::edge`]).
    Edge(Arc<EdgeGrid>),
}

impl Surface {
    /// The georeferencing of the level's (or the edge patch's) grid.
    pub fn georef(&self) -> &Georef {
        match self {
            Surface::Bilinear(w) | Surface::Bicubic(w, _) => &w.level.georef,
            Surface::Edge(e) => &e.georef,
        }
    }

    /// Cells along each axis.
    pub fn cells(&self) -> [usize; 2] {
        match self {
            Surface::Bilinear(w) | Surface::Bicubic(w, _) => w.level.cells(),
            Surface::Edge(e) => [e.cols - 1, e.rows - 1],
        }
    }
}

/// A patch's answer at a point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// The height.
    pub z: f64,
    /// Scales the patch's blend weight (1 but for edge patches).
    pub weight: f64,
    /// Whether the point lies in the valid part of the patch's kernel.
    pub covered: bool,
}

/// A patch ready to evaluate: its samples and everything per-sample work needs, computed
/// once per request.
#[derive(Clone, Debug)]
pub struct ResolvedPatch {
    /// Identifies the window's samples, so a device that already holds them need not upload
    /// them again.
    pub id: PatchId,
    /// What the patch evaluates.
    pub surface: Surface,
    /// The patch's kernel, in grid units of its level: the points it covers.
    pub kernel: CellRect,
    /// The window clipped to the level's grid, in grid units: a survey patch reaches no point
    /// outside it.
    pub window: CellRect,
    /// Centre of the unclipped window, in level grid units.
    pub centre: [f64; 2],
    /// 1 / the unclipped window's half-size: scales a grid offset from `centre` to the
    /// weight's t ∈ (−1, 1).
    pub inv_half: [f64; 2],
    /// What the weight is scaled by in the sums: Formula 1's `area_norm`, or 1 for the
    /// accurate blend.
    pub norm: f64,
    /// 1 / (dx·dy): the weight's unit volume, in world units, so that in Formula 1 smaller
    /// patches weigh more.
    pub area_norm: f64,
    /// 0 for the paper's tent, w(t) = 1 − |t|. For edge patches, half / margin: the weight is
    /// min(1, (1 − |t|)·flat), flat over the kernel and falling to 0 across the extension
    /// zone, so that the large tiles of edge patches weigh their kernel fully (and an f32
    /// evaluation of the weight keeps its precision there).
    pub flat: f64,
    /// The window's world bounds, clipped to the unclipped window's (beyond which the weight
    /// is 0): what [`cpu::bin`] tests blocks against, widened a little ([`Self::reach`]).
    pub window_aabb: Aabb,
    /// The patch's error: the fallback's tiers, and the accurate blend's order.
    pub error: f64,
    /// See [`patchwork_index::query::Extracted::fallback`].
    pub fallback: bool,
    /// Among the fallback patches of its set, the rank of its error (equal errors share one):
    /// at a point no cut patch covers, the fallback patches of the best rank covering it are
    /// blended, with any of better rank that reach it.
    pub rank: u32,
    /// The sides of its kernel (bit 0 the first column, 1 the first row, 2 the last column,
    /// 3 the last row) across which the accurate blend gives it no weight: for a level-0
    /// survey patch, those where a neighbouring kernel of its survey claims a larger ε than
    /// its own ([`closed_sides`]). Its extension zone there holds samples no better than that
    /// claim, and laid over a more accurate survey's kernel they would leak into an answer
    /// asked within the patch's own error. So beyond such a side it weighs 0, and its ramp
    /// runs inside its kernel, where its samples are as good as it claims
    /// ([`Self::inner_weight`]); where it holds a point it takes what the patches after it in
    /// its tier leave. Heights stay continuous, and its neighbour of the same samples answers
    /// beyond the edge.
    pub closed: u8,
    /// Weighed as the accurate blend weighs it ([`PatchSet::with_blend`]): 1 over its kernel,
    /// falling to 0 across the extension zone, with `norm` 1.
    pub accurate: bool,
    /// Which positions of a sample the patch reads: 0 for the grid's own (the store's
    /// plane), k for those [`PatchSet::planes`]`[k − 1]` carries them to, in the CRS of a
    /// survey of another plane.
    pub plane: u16,
    /// Where the level's sample (0, 0) lies, in the world (the GPU's shader places its
    /// samples from these, as the CPU does).
    pub origin: [f64; 2],
    /// The level's column and row axes, unit vectors in the world.
    pub axes: [[f64; 2]; 2],
    /// What a world offset is dotted with for grid coordinates ([`Georef::duals`]): the axes
    /// themselves but on a skewed grid; `u` gives columns, `v` rows.
    pub u: [f64; 2],
    /// See `u`.
    pub v: [f64; 2],
    /// Samples a world unit along the columns and along the rows.
    pub inv_step: [f64; 2],
}

impl ResolvedPatch {
    #[allow(clippy::too_many_arguments)]
    fn make(
        id: PatchId,
        surface: Surface,
        kernel: CellRect,
        window: CellRect,
        centre: [f64; 2],
        half: [f64; 2],
        error: f64,
        fallback: bool,
    ) -> Self {
        let g = *surface.georef();
        let [u, v] = g.axes();
        let [du, dv] = g.duals();
        let nominal = ORect {
            origin: g.to_world(centre[0] - half[0], centre[1] - half[1]),
            u,
            v,
            size: [2.0 * half[0] * g.step[0], 2.0 * half[1] * g.step[1]],
        };
        let w = g.cells_rect(&window);
        ResolvedPatch {
            id,
            kernel,
            window,
            centre,
            inv_half: [1.0 / half[0], 1.0 / half[1]],
            norm: 1.0 / (half[0] * g.step[0] * half[1] * g.step[1]),
            area_norm: 1.0 / (half[0] * g.step[0] * half[1] * g.step[1]),
            flat: 0.0,
            window_aabb: w.aabb().intersection(&nominal.aabb()).unwrap_or(w.aabb()),
            error,
            fallback,
            rank: 0,
            closed: 0,
            accurate: false,
            plane: 0,
            origin: g.origin,
            axes: [u, v],
            u: du,
            v: dv,
            inv_step: [1.0 / g.step[0], 1.0 / g.step[1]],
            surface,
        }
    }

    /// The samples of its level a survey patch reads: its window and one more cell on every
    /// side the level has (the rule for points on a cell edge may look at the cell beyond).
    pub fn reads(s: &SurveyMeta, p: &Patch) -> SampleRect {
        let w = s.window(p);
        let [cw, ch] = s.shapes[p.level as usize].cells();
        SampleRect {
            c0: w.c0.saturating_sub(1) as usize,
            r0: w.r0.saturating_sub(1) as usize,
            c1: (w.c1 as usize + 1).min(cw) + 1,
            r1: (w.r1 as usize + 1).min(ch) + 1,
        }
    }

    /// The patch at `k` in the list of the survey `s`, at the error the index takes it at, on
    /// its level, read through a window holding [`Self::reads`].
    pub fn new(level: Window, s: &SurveyMeta, k: usize, fallback: bool) -> Self {
        let p = &s.patches[k];
        let (kernel, window) = s.kernel_and_window(p);
        let surface = match s.kind {
            PatchKind::Bilinear => Surface::Bilinear(level),
            PatchKind::Bicubic => {
                let spline = Bicubic::spline_of(&window, |c, r| level.at(c, r));
                Surface::Bicubic(level, Arc::new(spline))
            }
        };
        let mut q = Self::make(
            p.id,
            surface,
            kernel,
            window,
            s.centre(p),
            s.half(),
            s.error_at(k),
            fallback,
        );
        q.closed = closed_sides(s, p);
        q
    }

    /// An edge patch, evaluating `grid`, its samples, with its flattened weight.
    pub fn edge(e: &EdgePatch, grid: Arc<EdgeGrid>, fallback: bool) -> Self {
        let mut p = Self::make(
            e.id,
            Surface::Edge(grid),
            e.kernel,
            e.window,
            e.centre,
            e.half,
            e.error,
            fallback,
        );
        p.flat = e.flat;
        p
    }

    /// The 1-D blend weight at t ∈ (−1, 1).
    #[inline]
    fn weight(&self, t: f64) -> f64 {
        if let Surface::Bicubic(..) = self.surface {
            return PatchKind::Bicubic.weight(t);
        }
        let w = 1.0 - t.abs();
        if self.flat > 0.0 {
            (w * self.flat).min(1.0)
        } else {
            w
        }
    }

    /// The 1-D weight along `axis` at grid coordinate `g`, where t is g's offset from the
    /// window's centre over its half-size: Formula 1's [`Self::weight`], or for the accurate
    /// blend 1 over the kernel and, outside it, a ramp from 1 at the kernel's edge on g's side
    /// to 0 at the unclipped window's. The ramp is s (a C0 join) for bilinear and edge patches
    /// and 6s⁵ − 15s⁴ + 10s³ (a C2 join at both ends) for bicubic ones, so the surface keeps
    /// the continuity its patches have. Exactly 1 on the kernel, so a point there that no
    /// more accurate patch reaches gets the patch's height to the bit; but across a closed
    /// side ([`Self::closed`]) the weight is 0 and the ramp runs inside the kernel instead
    /// ([`Self::inner_weight`]).
    #[inline(always)]
    fn axis_weight(&self, axis: usize, g: f64, t: f64) -> f64 {
        if !self.accurate {
            return self.weight(t);
        }
        let (k0, k1) = if axis == 0 {
            (self.kernel.c0 as f64, self.kernel.c1 as f64)
        } else {
            (self.kernel.r0 as f64, self.kernel.r1 as f64)
        };
        if g >= k0 && g <= k1 {
            let sides = (self.closed >> axis) & 0b101;
            if sides == 0 {
                return 1.0;
            }
            return self.inner_weight(axis, g, [k0, k1], sides);
        }
        let below = g < k0;
        if self.closed & (1 << (axis + if below { 0 } else { 2 })) != 0 {
            return 0.0;
        }
        let edge = if below { k0 } else { k1 };
        // The kernel's edge on g's side, as a t: the ramp runs from there to |t| = 1.
        let tk = (edge - self.centre[axis]).abs() * self.inv_half[axis];
        let s = ((1.0 - t.abs()) / (1.0 - tk)).clamp(0.0, 1.0);
        if s.is_nan() || s <= 0.0 {
            // Also a kernel that fills its window (no extension zone): NaN from 0 / 0.
            return 0.0;
        }
        let w = match self.surface {
            Surface::Bicubic(..) => s * s * s * (s * (6.0 * s - 15.0) + 10.0),
            _ => s,
        };
        // Off the kernel a patch never takes a whole point: the C2 ramp is so flat near the
        // kernel's edge that it rounds to 1 there, and the point would then end at a patch
        // that does not cover it, nodata where the next patch's kernel holds it.
        w.min(BELOW_ONE)
    }

    /// The accurate blend's weight inside the kernel along `axis`, at grid coordinate `g`,
    /// where `sides` (bit 0 the kernel's first line, bit 2 its last) are closed: a ramp from 0
    /// at a closed edge up to 1 a margin inside it (the extension zone's width on that side),
    /// shaped as the outer ramp is. The patches after it in the order thus take over before
    /// its edge, inside the kernel where its samples are within its claim, rather than after
    /// it where they are not; what they leave, the patch takes (`cpu::Over::hold`), as its
    /// neighbour of the same samples takes it beyond the edge. Below 1 wherever it ramps.
    #[inline]
    fn inner_weight(&self, axis: usize, g: f64, [k0, k1]: [f64; 2], sides: u8) -> f64 {
        let (c, half) = (self.centre[axis], 1.0 / self.inv_half[axis]);
        let mut s = 1.0f64;
        if sides & 1 != 0 {
            s = s.min((g - k0) / (half - (c - k0).abs()));
        }
        if sides & 4 != 0 {
            s = s.min((k1 - g) / (half - (k1 - c).abs()));
        }
        if s >= 1.0 {
            return 1.0;
        }
        let w = match self.surface {
            Surface::Bicubic(..) => s * s * s * (s * (6.0 * s - 15.0) + 10.0),
            _ => s,
        };
        w.clamp(0.0, BELOW_ONE)
    }

    /// Where the accurate blend puts the patch among those that reach a point: the cut's
    /// patches (0) before the fallback's, each fallback rank a tier of its own.
    #[inline]
    pub fn tier(&self) -> u32 {
        if self.fallback {
            1 + self.rank
        } else {
            0
        }
    }

    /// Grid coordinates of a world point. Coordinates within [`SNAP`](patchwork_geom::SNAP) of a grid line are
    /// put on it: a sample grid aligned with a level puts points on its lines, where validity
    /// changes, and rounding noise must not decide which side they fall on (nor may it differ
    /// between the CPU and the GPU).
    #[inline]
    pub fn to_grid(&self, p: [f64; 2]) -> [f64; 2] {
        let d = [p[0] - self.origin[0], p[1] - self.origin[1]];
        [
            snap((d[0] * self.u[0] + d[1] * self.u[1]) * self.inv_step[0]),
            snap((d[0] * self.v[0] + d[1] * self.v[1]) * self.inv_step[1]),
        ]
    }

    /// The bounds a block is binned against: the window's, widened by 10⁻⁸ of their size.
    /// A point within [`SNAP`](patchwork_geom::SNAP) of a window's edge is put on it, and a
    /// window is at least a cell wide, so every point the patch reaches lies inside, and a
    /// block's patches never depend on where the block begins.
    pub fn reach(&self) -> Aabb {
        let b = self.window_aabb;
        b.grown(1e-8 * b.width().max(b.height()))
    }

    /// Whether the patch's grid coordinate along x depends on x alone and along y on y alone
    /// (a north-up level of the store's plane), and it is a bilinear patch: what
    /// [`Self::along`] needs. A patch of another plane reads positions carried into it, which
    /// no tile's axes give.
    pub fn separable(&self) -> bool {
        self.plane == 0
            && matches!(self.surface, Surface::Bilinear(_))
            && self.u[1] == 0.0
            && self.v[0] == 0.0
    }

    /// For a [`Self::separable`] patch, everything [`Self::at`] works out from one coordinate:
    /// `axis` 0 for an x, 1 for a y. Computed as `at` computes it, term for term.
    #[inline]
    pub fn along(&self, axis: usize, x: f64) -> AxisHit {
        let Surface::Bilinear(level) = &self.surface else {
            unreachable!("only bilinear patches are separable")
        };
        let (w, k) = (&self.window, &self.kernel);
        let (dir, offset, cells, lo, hi, klo, khi) = if axis == 0 {
            (
                self.u[0],
                level.c0,
                level.grid.cols - 1,
                w.c0,
                w.c1,
                k.c0,
                k.c1,
            )
        } else {
            (
                self.v[1],
                level.r0,
                level.grid.rows - 1,
                w.r0,
                w.r1,
                k.r0,
                k.r1,
            )
        };
        let g = snap(((x - self.origin[axis]) * dir) * self.inv_step[axis]);
        let t = (g - self.centre[axis]) * self.inv_half[axis];
        // Window::bilinear_grid works in the window's own coordinates; Grid::locate then
        // finds the cell.
        let local = g - offset as f64;
        let located = local >= 0.0 && local <= cells as f64;
        let cell = if located {
            (local.floor() as usize).min(cells.max(1) - 1)
        } else {
            0
        };
        AxisHit {
            reaches: t.abs() < 1.0 && g >= lo as f64 && g <= hi as f64 && located,
            weight: self.axis_weight(axis, g, t),
            covered: g >= klo as f64 && g <= khi as f64,
            local,
            cell: cell as u32,
            frac: local - cell as f64,
        }
    }

    /// [`Self::at`] from the two halves [`Self::along`] gave for the point's x and y.
    #[inline(always)]
    pub fn at_axes(&self, x: &AxisHit, y: &AxisHit) -> Option<(f64, Hit)> {
        if !(x.reaches && y.reaches) {
            return None;
        }
        let Surface::Bilinear(level) = &self.surface else {
            unreachable!("only bilinear patches are separable")
        };
        let grid = &level.grid;
        let z = grid
            .bilinear_in_cell(x.cell as usize, y.cell as usize, [x.frac, y.frac])
            .or_else(|| grid.bilinear_grid([x.local, y.local]))?;
        let hit = Hit {
            z,
            weight: 1.0,
            covered: x.covered && y.covered,
        };
        Some((x.weight * y.weight * self.norm * hit.weight, hit))
    }

    /// The patch's blend weight and answer at a world point; None where it does not reach.
    #[inline]
    pub fn at(&self, p: [f64; 2]) -> Option<(f64, Hit)> {
        let g = self.to_grid(p);
        let tx = (g[0] - self.centre[0]) * self.inv_half[0];
        let ty = (g[1] - self.centre[1]) * self.inv_half[1];
        // A point with no position in the patch's plane (NaN) reaches nothing.
        if !(tx.abs() < 1.0 && ty.abs() < 1.0) {
            return None;
        }
        let hit = match &self.surface {
            Surface::Bilinear(level) => {
                if !self.window.contains_grid(g) {
                    return None;
                }
                Hit {
                    z: level.bilinear_grid(g)?,
                    weight: 1.0,
                    covered: self.kernel.contains_grid(g),
                }
            }
            Surface::Bicubic(level, spline) => {
                if !self.window.contains_grid(g) {
                    return None;
                }
                level.bilinear_grid(g)?;
                let w = &self.window;
                Hit {
                    z: spline.eval([g[0] - w.c0 as f64, g[1] - w.r0 as f64]),
                    weight: 1.0,
                    covered: self.kernel.contains_grid(g),
                }
            }
            Surface::Edge(e) => {
                let s = e.eval(g)?;
                Hit {
                    z: s.z,
                    weight: s.weight,
                    covered: self.kernel.contains_grid(g),
                }
            }
        };
        let w =
            self.axis_weight(0, g[0], tx) * self.axis_weight(1, g[1], ty) * self.norm * hit.weight;
        Some((w, hit))
    }
}

/// The sides of a survey patch's kernel across which the accurate blend does not reach
/// ([`ResolvedPatch::closed`]): for a level-0 patch, each side whose strip of the window
/// beyond the kernel meets a kernel of a larger ε than the patch's own. A coarser patch's
/// error already holds the largest ε under its whole window, so it reaches everywhere.
pub fn closed_sides(s: &SurveyMeta, p: &Patch) -> u8 {
    if p.level != 0 {
        return 0;
    }
    let (k, w) = s.kernel_and_window(p);
    let own = s.kernel_accuracy.at(s.kernel_index(p));
    // Most surveys claim one ε everywhere (`accuracy` is the largest): nothing to compare.
    if s.accuracy <= own {
        return 0;
    }
    let strips = [
        (w.c0 < k.c0).then_some(CellRect { c1: k.c0, ..w }),
        (w.r0 < k.r0).then_some(CellRect { r1: k.r0, ..w }),
        (w.c1 > k.c1).then_some(CellRect { c0: k.c1, ..w }),
        (w.r1 > k.r1).then_some(CellRect { r0: k.r1, ..w }),
    ];
    strips
        .iter()
        .enumerate()
        .fold(0, |m, (i, strip)| match strip {
            Some(r) if s.kernel_accuracy.max_over(&s.tiling, r) > own => m | 1 << i,
            _ => m,
        })
}

/// The largest f64 below 1: the most weight a patch has off its kernel.
const BELOW_ONE: f64 = 1.0 - f64::EPSILON / 2.0;

/// What a separable patch makes of one coordinate of a point (see [`ResolvedPatch::along`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct AxisHit {
    /// Inside the open weight support, the window and the level along this axis.
    pub reaches: bool,
    /// The 1-D blend weight at this coordinate.
    pub weight: f64,
    /// Inside the kernel along this axis.
    pub covered: bool,
    /// The coordinate in the window's grid, its cell and the fraction across it.
    pub local: f64,
    /// See `local`.
    pub cell: u32,
    /// See `local`.
    pub frac: f64,
}

/// The patches of one request, in a fixed order so that sums are reproducible.
#[derive(Clone, Default)]
pub struct PatchSet {
    /// The patches; indices into this are what [`cpu::bin`] lists.
    pub patches: Vec<ResolvedPatch>,
    /// Whether any patch is a fallback, so that blending must mind tiers.
    pub has_fallback: bool,
    /// How the patches are blended.
    pub blend: Blend,
    /// The maps from the store's plane to the planes of the set's surveys of other CRSs: a
    /// patch of plane k reads a sample's position carried by `planes[k − 1]`.
    pub planes: Vec<Arc<Reprojection>>,
}

impl std::fmt::Debug for PatchSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PatchSet")
            .field("patches", &self.patches.len())
            .field("has_fallback", &self.has_fallback)
            .field("blend", &self.blend)
            .field("planes", &self.planes.len())
            .finish()
    }
}

impl PatchSet {
    /// The set, with the fallback patches ranked by error, blended by Formula 1 until
    /// [`Self::with_blend`] says otherwise.
    pub fn new(mut patches: Vec<ResolvedPatch>) -> Self {
        let mut errors: Vec<f64> = patches
            .iter()
            .filter(|p| p.fallback)
            .map(|p| p.error)
            .collect();
        errors.sort_by(f64::total_cmp);
        errors.dedup();
        for p in patches.iter_mut().filter(|p| p.fallback) {
            p.rank = errors.partition_point(|&e| e < p.error) as u32;
        }
        PatchSet {
            has_fallback: !errors.is_empty(),
            patches,
            planes: Vec::new(),
            blend: Blend::Formula1,
        }
    }

    /// The set blended by `b`. For the accurate blend the patches are put in the order it
    /// lays them over one another: by tier (the cut's, then each fallback rank), then error,
    /// then id. Bins list patches in ascending index, so every bin, on the CPU and on the
    /// device, is then in that order, and a point stops at the first patch whose kernel holds
    /// it. The order compares two patches by their own tier, error and id alone, so a point
    /// gets the same answer from any set that holds the patches reaching it. Formula 1 keeps
    /// the set's order, whatever it is: its sums are the same in any order but for rounding.
    pub fn with_blend(mut self, b: Blend) -> Self {
        self.blend = b;
        let accurate = b == Blend::Accurate;
        for p in &mut self.patches {
            p.accurate = accurate;
            p.norm = if accurate { 1.0 } else { p.area_norm };
        }
        if accurate {
            self.patches.sort_by(|a, b| {
                (a.tier().cmp(&b.tier()))
                    .then(a.error.total_cmp(&b.error))
                    .then(a.id.cmp(&b.id))
            });
        }
        self
    }

    /// The set with patches of other planes: `planes[k − 1]` carries a sample to plane k.
    pub fn with_planes(mut self, planes: Vec<Arc<Reprojection>>) -> Self {
        self.planes = planes;
        self
    }

    /// Every sample's position in every other plane of the set, row-major, NaN where it has
    /// none: the lattice's answer for each point alone, so the same from any grid.
    pub fn positions(&self, grid: &SampleGrid) -> Vec<Vec<[f64; 2]>> {
        if self.planes.is_empty() {
            return Vec::new();
        }
        let points: Vec<[f64; 2]> = grid.points().collect();
        self.planes.iter().map(|r| r.map(&points)).collect()
    }
}
