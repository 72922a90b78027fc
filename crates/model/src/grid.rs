//! Regularly sampled grids in the plane: the common currency between readers, mipmaps and patches.

use super::patch::CellRect;
use patchwork_geom::ORect;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Where a grid's samples sit in its CRS's plane.
///
/// Sample `(col, row)` sits at `origin + col·sx·u + row·sy·v`, with `u = (cos θ, sin θ)` and,
/// for every north-up or rotated raster, `v = (sin θ, −cos θ)`: the column axis turned
/// clockwise by 90°. At θ = 0 this is a north-up raster: columns run east, rows run south,
/// exactly as GDAL places pixel centres. A skewed or mirrored geotransform has a row axis of
/// its own, `v = (sin ψ, −cos ψ)` with ψ = `row_theta` (ψ = θ + π for rows that run north).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Georef {
    /// Position of sample (0, 0), the centre of the first pixel for PixelIsArea rasters.
    pub origin: [f64; 2],
    /// Angle of the column axis from the x axis, counter-clockwise, in radians.
    pub theta: f64,
    /// Spacing between columns (sX) and between rows (sY), both positive, in CRS units.
    pub step: [f64; 2],
    /// The row axis's angle ψ where the row axis is not the column axis turned clockwise by
    /// 90° (skewed or mirrored grids); None for every other grid.
    pub row_theta: Option<f64>,
}

/// Why a georeference cannot place a grid.
#[derive(Debug, Error, PartialEq)]
pub enum GeorefError {
    /// A sample spacing is not positive and finite.
    #[error("sample spacing must be positive and finite, got {0:?}")]
    BadStep([f64; 2]),
    /// The column and row axes are parallel, so the grid would lie on a line.
    #[error("the geotransform's column and row axes are parallel: it maps the grid onto a line")]
    Degenerate,
    /// A value is NaN or infinite.
    #[error("the georeference has non-finite values")]
    NotFinite,
}

impl Georef {
    /// A north-up georeference (θ = 0): columns run east, rows run south.
    pub fn north_up(origin: [f64; 2], step: [f64; 2]) -> Self {
        Georef {
            origin,
            theta: 0.0,
            step,
            row_theta: None,
        }
    }

    /// Builds the georeference from a GDAL geotransform, whose origin is the outer corner of
    /// pixel (0, 0). Any affine transform that does not flatten the grid is taken: rotated,
    /// skewed or mirrored.
    pub fn from_geotransform(gt: [f64; 6]) -> Result<Self, GeorefError> {
        if gt.iter().any(|v| !v.is_finite()) {
            return Err(GeorefError::NotFinite);
        }
        let (cx, cy) = (gt[1], gt[4]);
        let (rx, ry) = (gt[2], gt[5]);
        let sx = cx.hypot(cy);
        let sy = rx.hypot(ry);
        if sx <= 0.0 || sy <= 0.0 {
            return Err(GeorefError::BadStep([sx, sy]));
        }
        if (cx * ry - cy * rx).abs() <= 1e-12 * sx * sy {
            return Err(GeorefError::Degenerate);
        }
        let theta = cy.atan2(cx);
        let (s, c) = theta.sin_cos();
        // The row axis of a north-up or rotated raster is the column axis turned clockwise by
        // 90°; any other is kept as an angle of its own.
        let tol = 1e-9 * sy;
        let row_theta =
            ((rx - sy * s).abs() > tol || (ry + sy * c).abs() > tol).then(|| rx.atan2(-ry));
        let origin = [gt[0] + 0.5 * (cx + rx), gt[3] + 0.5 * (cy + ry)];
        Ok(Georef {
            origin,
            theta,
            step: [sx, sy],
            row_theta,
        })
    }

    /// The GDAL geotransform of this georeference (pixel corner origin).
    pub fn geotransform(&self) -> [f64; 6] {
        let [u, v] = self.axes();
        let (cx, cy) = (u[0] * self.step[0], u[1] * self.step[0]);
        let (rx, ry) = (v[0] * self.step[1], v[1] * self.step[1]);
        [
            self.origin[0] - 0.5 * (cx + rx),
            cx,
            rx,
            self.origin[1] - 0.5 * (cy + ry),
            cy,
            ry,
        ]
    }

    /// Unit vectors of the column and row axes.
    #[inline]
    pub fn axes(&self) -> [[f64; 2]; 2] {
        // North-up grids, nearly all of them, without the sine and cosine: placing every
        // sample of an overlap spent a tenth of a comparison's time in them. The same bits:
        // sin 0 = 0 and cos 0 = 1 exactly (a θ of −0 takes the long way, for its signed zeros).
        if self.theta.to_bits() == 0 && self.row_theta.is_none() {
            return [[1.0, 0.0], [0.0, -1.0]];
        }
        let (s, c) = self.theta.sin_cos();
        let v = match self.row_theta {
            None => [s, -c],
            Some(psi) => {
                let (s, c) = psi.sin_cos();
                [s, -c]
            }
        };
        [[c, s], v]
    }

    /// Whether the axes are perpendicular, so that a point's grid coordinates are its
    /// projections on them: every grid but a skewed one.
    #[inline]
    pub fn is_orthogonal(&self) -> bool {
        self.row_theta.is_none() || {
            let [u, v] = self.axes();
            u[0] * v[0] + u[1] * v[1] == 0.0
        }
    }

    /// The vectors whose dot products with an offset from the origin, divided by the steps,
    /// give its grid coordinates: the axes themselves when they are perpendicular, else the
    /// rows of the inverse of the axes' matrix.
    #[inline]
    pub fn duals(&self) -> [[f64; 2]; 2] {
        let [u, v] = self.axes();
        if self.row_theta.is_none() || u[0] * v[0] + u[1] * v[1] == 0.0 {
            return [u, v];
        }
        let det = u[0] * v[1] - u[1] * v[0];
        [[v[1] / det, -v[0] / det], [-u[1] / det, u[0] / det]]
    }

    /// World position of fractional grid coordinates.
    #[inline]
    pub fn to_world(&self, col: f64, row: f64) -> [f64; 2] {
        self.to_world_on(self.axes(), col, row)
    }

    /// [`Georef::to_world`] with the grid's [`Georef::axes`] worked out already, for callers
    /// that place many points or rectangles of one grid.
    #[inline]
    pub fn to_world_on(&self, axes: [[f64; 2]; 2], col: f64, row: f64) -> [f64; 2] {
        let [u, v] = axes;
        let a = col * self.step[0];
        let b = row * self.step[1];
        [
            self.origin[0] + a * u[0] + b * v[0],
            self.origin[1] + a * u[1] + b * v[1],
        ]
    }

    /// Fractional grid coordinates of a world position.
    #[inline]
    pub fn to_grid(&self, p: [f64; 2]) -> [f64; 2] {
        self.coords([p[0] - self.origin[0], p[1] - self.origin[1]])
    }

    /// Grid coordinates of an offset `d` from the origin.
    #[inline]
    pub fn coords(&self, d: [f64; 2]) -> [f64; 2] {
        let [u, v] = self.duals();
        [
            (d[0] * u[0] + d[1] * u[1]) / self.step[0],
            (d[0] * v[0] + d[1] * v[1]) / self.step[1],
        ]
    }

    /// The georeference of a grid whose sample (i, j) sits at this grid's (i·f, j·f).
    pub fn coarsened(&self, factor: f64) -> Georef {
        Georef {
            step: [self.step[0] * factor, self.step[1] * factor],
            ..*self
        }
    }

    /// The largest distance in grid cells that a world offset of length 1 can move a point:
    /// 1 / (the smaller step) for perpendicular axes, more for skewed ones.
    pub fn cells_per_unit(&self) -> f64 {
        let [u, v] = self.duals();
        let a = [u[0] / self.step[0], u[1] / self.step[0]];
        let b = [v[0] / self.step[1], v[1] / self.step[1]];
        // The spectral norm of the 2 × 2 matrix with rows a and b.
        let (p, q, r) = (
            a[0] * a[0] + a[1] * a[1],
            a[0] * b[0] + a[1] * b[1],
            b[0] * b[0] + b[1] * b[1],
        );
        (0.5 * (p + r + ((p - r) * (p - r) + 4.0 * q * q).sqrt())).sqrt()
    }

    /// Checks that every value is finite, the steps positive and the axes not parallel.
    pub fn validate(&self) -> Result<(), GeorefError> {
        let row = self.row_theta.unwrap_or(0.0);
        if !(self.origin.iter().all(|v| v.is_finite()) && self.theta.is_finite() && row.is_finite())
        {
            return Err(GeorefError::NotFinite);
        }
        if !(self.step.iter().all(|s| s.is_finite() && *s > 0.0)) {
            return Err(GeorefError::BadStep(self.step));
        }
        let [u, v] = self.axes();
        if (u[0] * v[1] - u[1] * v[0]).abs() <= 1e-12 {
            return Err(GeorefError::Degenerate);
        }
        Ok(())
    }
}

/// A grid of heights. Nodata is NaN: it is the validity mask, so no void value can leak into
/// arithmetic without showing up as NaN.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Grid {
    /// Samples per row.
    pub cols: usize,
    /// Rows of samples.
    pub rows: usize,
    /// Row-major heights in metres, NaN where there is no data.
    pub samples: Vec<f32>,
    /// Where the samples sit in the plane.
    pub georef: Georef,
}

/// Why samples and a georeference do not make a grid.
#[derive(Debug, Error, PartialEq)]
pub enum GridError {
    /// Fewer than 2 × 2 samples: no cell.
    #[error("a grid needs at least 2×2 samples, got {cols}×{rows}")]
    TooSmall {
        /// Samples per row.
        cols: usize,
        /// Rows of samples.
        rows: usize,
    },
    /// The number of samples is not `cols × rows`.
    #[error("{cols}×{rows} samples expected, {got} given")]
    WrongLength {
        /// Samples per row.
        cols: usize,
        /// Rows of samples.
        rows: usize,
        /// Samples given.
        got: usize,
    },
    /// The georeference cannot place the grid.
    #[error(transparent)]
    Georef(#[from] GeorefError),
}

impl Grid {
    /// Builds a grid, turning ±inf into nodata: an infinite height is never a measurement.
    pub fn new(
        cols: usize,
        rows: usize,
        mut samples: Vec<f32>,
        georef: Georef,
    ) -> Result<Self, GridError> {
        if cols < 2 || rows < 2 {
            return Err(GridError::TooSmall { cols, rows });
        }
        if samples.len() != cols * rows {
            return Err(GridError::WrongLength {
                cols,
                rows,
                got: samples.len(),
            });
        }
        georef.validate()?;
        for s in samples.iter_mut() {
            if !s.is_finite() {
                *s = f32::NAN;
            }
        }
        Ok(Grid {
            cols,
            rows,
            samples,
            georef,
        })
    }

    /// Height of sample (col, row), in metres; NaN where there is no data.
    #[inline]
    pub fn at(&self, col: usize, row: usize) -> f32 {
        self.samples[row * self.cols + col]
    }

    /// Whether sample (col, row) holds data.
    #[inline]
    pub fn is_valid(&self, col: usize, row: usize) -> bool {
        !self.at(col, row).is_nan()
    }

    /// Number of cells along each axis.
    #[inline]
    pub fn cells(&self) -> [usize; 2] {
        [self.cols - 1, self.rows - 1]
    }

    /// A cell is valid when all four of its corners are: only then is the bilinear surface
    /// defined over it without inventing heights.
    #[inline]
    pub fn cell_valid(&self, c: usize, r: usize) -> bool {
        let i = r * self.cols + c;
        !(self.samples[i].is_nan()
            || self.samples[i + 1].is_nan()
            || self.samples[i + self.cols].is_nan()
            || self.samples[i + self.cols + 1].is_nan())
    }

    /// Number of samples that hold data.
    pub fn valid_count(&self) -> usize {
        self.samples.iter().filter(|s| !s.is_nan()).count()
    }

    /// The cell holding fractional coordinates, and the position inside it, or None outside
    /// the grid. Points on the last row or column belong to the cell before them.
    #[inline]
    pub fn locate(&self, g: [f64; 2]) -> Option<([usize; 2], [f64; 2])> {
        let [cw, ch] = self.cells();
        if !(g[0] >= 0.0 && g[1] >= 0.0 && g[0] <= cw as f64 && g[1] <= ch as f64) {
            return None;
        }
        let c = (g[0].floor() as usize).min(cw - 1);
        let r = (g[1].floor() as usize).min(ch - 1);
        Some(([c, r], [g[0] - c as f64, g[1] - r as f64]))
    }

    /// Bilinear height at fractional grid coordinates; None outside the grid or on a cell with
    /// a void corner.
    #[inline]
    pub fn bilinear_grid(&self, g: [f64; 2]) -> Option<f64> {
        let ([c, r], f) = self.locate(g)?;
        if let Some(z) = self.bilinear_in_cell(c, r, f) {
            return Some(z);
        }
        // A point on an edge shared with a valid cell belongs to that cell's closed surface.
        let left = f[0] == 0.0 && c > 0;
        let up = f[1] == 0.0 && r > 0;
        let right = f[0] == 1.0 && c + 2 < self.cols;
        let down = f[1] == 1.0 && r + 2 < self.rows;
        let cs: &[(isize, f64)] = match (left, right) {
            (true, _) => &[(0, f[0]), (-1, 1.0)],
            (_, true) => &[(0, f[0]), (1, 0.0)],
            _ => &[(0, f[0])],
        };
        let rs: &[(isize, f64)] = match (up, down) {
            (true, _) => &[(0, f[1]), (-1, 1.0)],
            (_, true) => &[(0, f[1]), (1, 0.0)],
            _ => &[(0, f[1])],
        };
        for &(dc, fc) in cs {
            for &(dr, fr) in rs {
                if dc == 0 && dr == 0 {
                    continue;
                }
                let (cc, rr) = ((c as isize + dc) as usize, (r as isize + dr) as usize);
                if let Some(z) = self.bilinear_in_cell(cc, rr, [fc, fr]) {
                    return Some(z);
                }
            }
        }
        None
    }

    /// Catmull-Rom cubic height at fractional grid coordinates, through the 4 × 4 samples
    /// around the point; None where any of them is void or outside the grid.
    pub fn cubic_grid(&self, g: [f64; 2]) -> Option<f64> {
        if !(g[0].is_finite() && g[1].is_finite()) {
            return None;
        }
        let (c0, r0) = (g[0].floor(), g[1].floor());
        let (fx, fy) = (g[0] - c0, g[1] - r0);
        let (c0, r0) = (c0 as isize - 1, r0 as isize - 1);
        if c0 < 0 || r0 < 0 || c0 + 3 >= self.cols as isize || r0 + 3 >= self.rows as isize {
            return None;
        }
        let w = |t: f64| {
            let (t2, t3) = (t * t, t * t * t);
            [
                0.5 * (-t3 + 2.0 * t2 - t),
                0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
                0.5 * (-3.0 * t3 + 4.0 * t2 + t),
                0.5 * (t3 - t2),
            ]
        };
        let (wx, wy) = (w(fx), w(fy));
        let mut out = 0.0;
        for (j, wj) in wy.iter().enumerate() {
            let row = (r0 as usize + j) * self.cols + c0 as usize;
            let mut s = 0.0;
            for (i, wi) in wx.iter().enumerate() {
                let z = self.samples[row + i];
                if z.is_nan() {
                    return None;
                }
                s += wi * z as f64;
            }
            out += wj * s;
        }
        Some(out)
    }

    /// Bilinear height at position `f` ∈ [0, 1]² inside cell (c, r); None where a corner is void.
    #[inline]
    pub fn bilinear_in_cell(&self, c: usize, r: usize, f: [f64; 2]) -> Option<f64> {
        let i = r * self.cols + c;
        let z00 = self.samples[i] as f64;
        let z10 = self.samples[i + 1] as f64;
        let z01 = self.samples[i + self.cols] as f64;
        let z11 = self.samples[i + self.cols + 1] as f64;
        let top = z00 + (z10 - z00) * f[0];
        let bottom = z01 + (z11 - z01) * f[0];
        let z = top + (bottom - top) * f[1];
        // NaN corners propagate, so one check covers all four.
        (!z.is_nan()).then_some(z)
    }

    /// Bilinear height at a world position.
    #[inline]
    pub fn bilinear(&self, p: [f64; 2]) -> Option<f64> {
        self.bilinear_grid(self.georef.to_grid(p))
    }

    /// The samples `[c0, c0 + cols) × [r0, r0 + rows)`, georeferenced where they lie.
    pub fn window(&self, c0: usize, r0: usize, cols: usize, rows: usize) -> Grid {
        assert!(
            c0 + cols <= self.cols && r0 + rows <= self.rows,
            "window outside the grid"
        );
        let mut samples = Vec::with_capacity(cols * rows);
        for r in r0..r0 + rows {
            samples.extend_from_slice(&self.samples[r * self.cols + c0..r * self.cols + c0 + cols]);
        }
        Grid {
            cols,
            rows,
            samples,
            georef: Georef {
                origin: self.georef.to_world(c0 as f64, r0 as f64),
                ..self.georef
            },
        }
    }

    /// Every `k`-th sample from the first, along both axes: a coarser survey of the same
    /// ground, with no filtering.
    pub fn decimated(&self, k: usize) -> Grid {
        let cols = (self.cols - 1) / k + 1;
        let rows = (self.rows - 1) / k + 1;
        let mut samples = Vec::with_capacity(cols * rows);
        for r in 0..rows {
            samples.extend((0..cols).map(|c| self.at(c * k, r * k)));
        }
        Grid {
            cols,
            rows,
            samples,
            georef: self.georef.coarsened(k as f64),
        }
    }

    /// The same samples on a lattice turned by `degrees` about the grid's centre: a rotated
    /// survey over the same ground.
    pub fn turned(&self, degrees: f64) -> Grid {
        let mid = [(self.cols - 1) as f64 / 2.0, (self.rows - 1) as f64 / 2.0];
        let centre = self.georef.to_world(mid[0], mid[1]);
        let g = Georef {
            theta: degrees.to_radians(),
            ..self.georef
        };
        let off = g.to_world(mid[0], mid[1]);
        let mut out = self.clone();
        out.georef = Georef {
            origin: [
                g.origin[0] + centre[0] - off[0],
                g.origin[1] + centre[1] - off[1],
            ],
            ..g
        };
        out
    }

    /// Axis-aligned world bounds of the sample positions.
    pub fn world_bounds(&self) -> patchwork_geom::Aabb {
        self.shape().world_bounds()
    }

    /// The grid's size and place, without its samples.
    pub fn shape(&self) -> Shape {
        Shape {
            cols: self.cols,
            rows: self.rows,
            georef: self.georef,
        }
    }
}

/// A grid's size and place without its samples: what stays in memory of a level whose
/// samples live on disk.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Shape {
    /// Samples per row.
    pub cols: usize,
    /// Rows of samples.
    pub rows: usize,
    /// Where the samples sit in the plane.
    pub georef: Georef,
}

impl Shape {
    /// Cells along each axis.
    pub fn cells(&self) -> [usize; 2] {
        [self.cols - 1, self.rows - 1]
    }

    /// Axis-aligned world bounds of the sample positions.
    pub fn world_bounds(&self) -> patchwork_geom::Aabb {
        let c = (self.cols - 1) as f64;
        let r = (self.rows - 1) as f64;
        patchwork_geom::Aabb::of_points(&[
            self.georef.to_world(0.0, 0.0),
            self.georef.to_world(c, 0.0),
            self.georef.to_world(0.0, r),
            self.georef.to_world(c, r),
        ])
    }

    /// The smallest and largest fractional grid coordinates of a world rectangle's corners.
    pub fn grid_bounds(&self, b: &patchwork_geom::Aabb) -> ([f64; 2], [f64; 2]) {
        let corners = b.corners().map(|p| self.georef.to_grid(p));
        let lo = |k: usize| corners.iter().map(|g| g[k]).fold(f64::INFINITY, f64::min);
        let hi = |k: usize| {
            corners
                .iter()
                .map(|g| g[k])
                .fold(f64::NEG_INFINITY, f64::max)
        };
        ([lo(0), lo(1)], [hi(0), hi(1)])
    }

    /// The samples whose cells meet a world rectangle, one ring wider, clipped to the grid;
    /// None when they miss it.
    pub fn rect_over(&self, b: &patchwork_geom::Aabb) -> Option<SampleRect> {
        let (lo, hi) = self.grid_bounds(b);
        let c0 = (lo[0].floor() - 1.0).max(0.0);
        let r0 = (lo[1].floor() - 1.0).max(0.0);
        let c1 = (hi[0].ceil() + 1.0).min((self.cols - 1) as f64);
        let r1 = (hi[1].ceil() + 1.0).min((self.rows - 1) as f64);
        (c0 <= c1 && r0 <= r1).then(|| SampleRect {
            c0: c0 as usize,
            r0: r0 as usize,
            c1: c1 as usize + 1,
            r1: r1 as usize + 1,
        })
    }

    /// The whole grid as a rectangle of samples.
    pub fn all(&self) -> SampleRect {
        SampleRect {
            c0: 0,
            r0: 0,
            c1: self.cols,
            r1: self.rows,
        }
    }
}

/// A half-open rectangle of samples `[c0, c1) × [r0, r1)` of a grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct SampleRect {
    /// First column.
    pub c0: usize,
    /// First row.
    pub r0: usize,
    /// One past the last column.
    pub c1: usize,
    /// One past the last row.
    pub r1: usize,
}

impl SampleRect {
    /// Columns of samples.
    pub fn cols(&self) -> usize {
        self.c1 - self.c0
    }
    /// Rows of samples.
    pub fn rows(&self) -> usize {
        self.r1 - self.r0
    }
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.cols() * self.rows()
    }
    /// Whether it holds no sample.
    pub fn is_empty(&self) -> bool {
        self.c1 <= self.c0 || self.r1 <= self.r0
    }
}

/// Samples of a rectangle of a larger grid (a level), indexed in the level's coordinates:
/// sample (c, r) of the level is sample (c − c0, r − r0) of `grid`. Subtracting whole numbers
/// from grid coordinates is exact, so a window answers exactly as its level does wherever it
/// holds the samples the answer reads.
#[derive(Clone, Debug)]
pub struct Window {
    /// The rectangle's samples, as a grid of their own.
    pub grid: std::sync::Arc<Grid>,
    /// Level column of the window's first sample.
    pub c0: usize,
    /// Level row of the window's first sample.
    pub r0: usize,
    /// The level's own shape.
    pub level: Shape,
}

impl Window {
    /// A whole level as its own window.
    pub fn whole(g: std::sync::Arc<Grid>) -> Window {
        Window {
            level: g.shape(),
            grid: g,
            c0: 0,
            r0: 0,
        }
    }

    /// The samples of `rect` of a level whose shape is `level`.
    pub fn of(grid: std::sync::Arc<Grid>, rect: SampleRect, level: Shape) -> Window {
        debug_assert_eq!((grid.cols, grid.rows), (rect.cols(), rect.rows()));
        Window {
            grid,
            c0: rect.c0,
            r0: rect.r0,
            level,
        }
    }

    /// Level sample (c, r), which the window must hold.
    #[inline]
    pub fn at(&self, c: usize, r: usize) -> f32 {
        self.grid.at(c - self.c0, r - self.r0)
    }

    /// Whether level cell (c, r), which the window must hold, has four valid corners.
    #[inline]
    pub fn cell_valid(&self, c: usize, r: usize) -> bool {
        self.grid.cell_valid(c - self.c0, r - self.r0)
    }

    /// The bilinear height at fractional level coordinates, read from the window's samples.
    #[inline]
    pub fn bilinear_grid(&self, g: [f64; 2]) -> Option<f64> {
        self.grid
            .bilinear_grid([g[0] - self.c0 as f64, g[1] - self.r0 as f64])
    }
}

impl Georef {
    /// The world parallelogram spanned by a range of cells (sample c0 to sample c1).
    pub fn cells_rect(&self, c: &CellRect) -> ORect {
        let [u, v] = self.axes();
        ORect {
            origin: self.to_world(c.c0 as f64, c.r0 as f64),
            u,
            v,
            size: [
                c.cols() as f64 * self.step[0],
                c.rows() as f64 * self.step[1],
            ],
        }
    }

    /// The world parallelogram spanned by fractional grid coordinates (c0, r0, c1, r1).
    pub fn grid_rect(&self, r: [f64; 4]) -> ORect {
        self.grid_rect_on(self.axes(), r)
    }

    /// [`Georef::grid_rect`] with the grid's [`Georef::axes`] worked out already.
    pub fn grid_rect_on(&self, axes: [[f64; 2]; 2], r: [f64; 4]) -> ORect {
        let [u, v] = axes;
        ORect {
            origin: self.to_world_on(axes, r[0], r[1]),
            u,
            v,
            size: [(r[2] - r[0]) * self.step[0], (r[3] - r[1]) * self.step[1]],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn geotransform_round_trip_follows_gdal_pixel_centres() {
        let gt = [-119.0, 1.0 / 3600.0, 0.0, 35.0, 0.0, -1.0 / 3600.0];
        let g = Georef::from_geotransform(gt).unwrap();
        // GDAL: the centre of pixel (0, 0) is half a pixel in from the corner.
        assert!((g.origin[0] - (-119.0 + 0.5 / 3600.0)).abs() < 1e-12);
        assert!((g.origin[1] - (35.0 - 0.5 / 3600.0)).abs() < 1e-12);
        let back = g.geotransform();
        for (a, b) in gt.iter().zip(back.iter()) {
            assert!((a - b).abs() < 1e-12, "{gt:?} vs {back:?}");
        }
    }

    #[test]
    fn rotated_geotransform_round_trips() {
        let th: f64 = 0.3;
        let (s, c) = th.sin_cos();
        let gt = [1000.0, 2.0 * c, 3.0 * s, 5000.0, 2.0 * s, -3.0 * c];
        let g = Georef::from_geotransform(gt).unwrap();
        assert!((g.theta - th).abs() < 1e-12);
        assert!((g.step[0] - 2.0).abs() < 1e-12 && (g.step[1] - 3.0).abs() < 1e-12);
        let p = g.to_world(7.25, 3.5);
        let q = g.to_grid(p);
        assert!((q[0] - 7.25).abs() < 1e-9 && (q[1] - 3.5).abs() < 1e-9);
    }

    #[test]
    fn skewed_and_mirrored_transforms_round_trip_and_flat_ones_are_refused() {
        for gt in [
            // Rows that run north.
            [0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            // A shear: rows lean east by a third of a cell.
            [500.0, 2.0, 0.7, 900.0, 0.0, -2.0],
            // Rotated and sheared, with unequal steps.
            [10.0, 3.0, 1.0, 20.0, 0.5, -2.5],
        ] {
            let g = Georef::from_geotransform(gt).unwrap();
            assert!(g.row_theta.is_some(), "{gt:?}");
            let back = g.geotransform();
            for (a, b) in gt.iter().zip(back.iter()) {
                assert!((a - b).abs() < 1e-9, "{gt:?} vs {back:?}");
            }
            for (c, r) in [(0.0, 0.0), (7.25, 3.5), (-2.0, 11.0)] {
                let p = g.to_world(c, r);
                // GDAL's own arithmetic for the centre of pixel (c, r).
                let q = [
                    gt[0] + (c + 0.5) * gt[1] + (r + 0.5) * gt[2],
                    gt[3] + (c + 0.5) * gt[4] + (r + 0.5) * gt[5],
                ];
                assert!((p[0] - q[0]).abs() < 1e-9 && (p[1] - q[1]).abs() < 1e-9);
                let back = g.to_grid(p);
                assert!((back[0] - c).abs() < 1e-9 && (back[1] - r).abs() < 1e-9);
            }
        }
        let flat = [0.0, 1.0, 2.0, 0.0, 1.0, 2.0];
        assert_eq!(
            Georef::from_geotransform(flat),
            Err(GeorefError::Degenerate)
        );
        // A north-up raster keeps no row angle of its own.
        let up = [0.0, 1.0, 0.0, 0.0, 0.0, -1.0];
        assert_eq!(Georef::from_geotransform(up).unwrap().row_theta, None);
    }

    #[test]
    fn bilinear_is_exact_on_samples_and_void_aware() {
        let g = Georef::north_up([0.0, 10.0], [1.0, 1.0]);
        let mut s = vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0];
        let grid = Grid::new(3, 3, s.clone(), g).unwrap();
        assert_eq!(grid.bilinear([1.0, 9.0]), Some(4.0));
        assert_eq!(grid.bilinear([2.0, 8.0]), Some(8.0));
        assert_eq!(grid.bilinear([0.5, 9.5]), Some(2.0));
        assert_eq!(grid.bilinear([2.01, 8.0]), None);
        s[0] = f32::NAN;
        let grid = Grid::new(3, 3, s, g).unwrap();
        assert_eq!(grid.bilinear([0.5, 9.5]), None);
        assert_eq!(grid.bilinear([1.5, 8.5]), Some(6.0));
        // The shared edge of a void cell and a valid one takes the valid cell's surface.
        assert_eq!(grid.bilinear([1.0, 9.0]), Some(4.0));
    }

    #[test]
    fn infinities_become_nodata() {
        let g = Georef::north_up([0.0, 0.0], [1.0, 1.0]);
        let grid = Grid::new(2, 2, vec![f32::INFINITY, 1.0, 2.0, f32::NEG_INFINITY], g).unwrap();
        assert_eq!(grid.valid_count(), 2);
    }
}
