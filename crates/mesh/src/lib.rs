//! Triangle meshes of a resampled tile, for renderers: a right-triangulated irregular network
//! (RTIN, the triangle bintree of seed 003, the method martini uses) or a restricted quadtree
//! (seed 002), each with an exact error; void vertices that keep holes open, or a hole border
//! simplified within a horizontal distance (seed 004); and skirts that hide the cracks
//! between tiles of different errors (seed 002). Pure computation, no I/O; [`encode`] writes
//! the formats.
//!
//! A tile is `cols × rows` heights, row 0 at the top (north), NaN where void. Both methods
//! work on a square of 2ⁿ + 1 vertices a side; a tile of any other size is padded to the
//! smallest that holds it with vertices *outside* the tile, which nothing is drawn over and
//! which a triangle holding a measured vertex must be split away from, as seed 004 pads its
//! rectangles with void vertices. Triangles over nothing that may be drawn are dropped whole.
//!
//! A triangle is a right isosceles triangle of grid vertices, split at the midpoint of its
//! hypotenuse. Its *error* is the largest vertical distance between its plane and the heights
//! at every measured grid vertex inside it or on its edges, exactly; a triangle holding both
//! a vertex that may be drawn over and one that may not has an infinite one. The error kept
//! for a midpoint is the largest of the two triangles that share that hypotenuse and of their
//! descendants, so that two triangles that share a hypotenuse always split together: the mesh
//! has no T-junction inside the tile.

pub mod encode;
pub mod quadtree;

use patchwork_geom::Aabb;
use rayon::prelude::*;
use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::sync::atomic::{AtomicU64, Ordering};

/// How the grid is triangulated.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Method {
    /// The right-triangulated irregular network (seed 003).
    #[default]
    Rtin,
    /// The restricted quadtree with omitted edge vertices ([`quadtree`]).
    Quadtree,
}

impl Method {
    /// The method's name in lower case: `rtin` or `quadtree`.
    pub fn name(self) -> &'static str {
        match self {
            Method::Rtin => "rtin",
            Method::Quadtree => "quadtree",
        }
    }
}

/// What a mesh keeps on the tile's border.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Border {
    /// Every grid vertex on the border is a mesh vertex, so two tiles of one grid spacing
    /// that share a side share all its vertices: tiles of one error fit without a crack.
    #[default]
    Shared,
    /// The border is simplified like the inside: fewest triangles, but a neighbour's border
    /// vertices differ, and only skirts hide the T-junctions.
    Adaptive,
}

/// How a mesh meets the tile's voids.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Holes {
    /// No triangle holds a void vertex: holes keep their border at full resolution.
    #[default]
    Exact,
    /// Seed 004's horizontal error: a void vertex within `reach` of a measured one (along
    /// steps to the eight neighbours, never shorter than the straight line, in the units of
    /// `cell`, one grid cell's width and height) may be drawn over, its height filled in from
    /// its neighbours. Holes narrower than twice the reach close, and a wider hole's border
    /// may move into it by the reach at most. Every measured vertex stays within the vertical
    /// error; only voids are drawn over, so nothing measured is lost.
    Reach {
        /// How far a void vertex may lie from a measured one, in the units of `cell`.
        reach: f64,
        /// One grid cell's width and height (metres, in the daemon's meshes).
        cell: [f64; 2],
    },
}

/// What a mesh is asked to be.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Options {
    /// How far the triangles may depart from the measured heights at the grid's vertices.
    pub max_error: f64,
    /// What the mesh keeps on the tile's border.
    pub border: Border,
    /// How the grid is triangulated.
    pub method: Method,
    /// How the mesh meets the tile's voids.
    pub holes: Holes,
}

/// The mesh of `heights` (`cols × rows`, row 0 north) as `options` say.
///
/// # Panics
/// If `cols` or `rows` is below 2 or `heights` does not hold `cols × rows` values.
pub fn triangulate(heights: &[f32], cols: usize, rows: usize, options: &Options) -> Mesh {
    triangulate_until(heights, cols, rows, options, &|| false)
        .expect("never stopped, so always made")
}

/// [`triangulate`], given up (None) soon after `stop` says so: it is asked now and then, from
/// any thread.
pub fn triangulate_until(
    heights: &[f32],
    cols: usize,
    rows: usize,
    options: &Options,
    stop: &(dyn Fn() -> bool + Sync),
) -> Option<Mesh> {
    let field = Field::new(heights, cols, rows, options.holes);
    match options.method {
        Method::Rtin => rtin(&field, options.max_error, options.border, stop),
        Method::Quadtree => quadtree::mesh(&field, options.max_error, options.border, stop),
    }
}

/// A mesh of one tile in grid coordinates.
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    /// The tile's grid: vertices a row and rows.
    pub cols: usize,
    /// See `cols`.
    pub rows: usize,
    /// Each vertex's grid position (column, row); a skirt vertex shares its top's position.
    pub grid: Vec<[u32; 2]>,
    /// Each vertex's height, metres.
    pub heights: Vec<f32>,
    /// Counter-clockwise seen from above with north up (x east, y north).
    pub triangles: Vec<[u32; 3]>,
    /// Vertices from here on are skirt vertices, and triangles from `skirt_triangles` on are
    /// skirt triangles.
    pub skirt_vertices: usize,
    /// See `skirt_vertices`.
    pub skirt_triangles: usize,
    /// The largest distance from the measured grid heights to the surface triangles.
    pub max_deviation: f64,
    /// The farthest a void vertex under the surface lies from a measured one, in the units
    /// of [`Holes::Reach`]'s cell (0 when holes are exact).
    pub max_reach: f64,
}

/// The heights a mesh is made from, on the square grid of 2ⁿ + 1 vertices that holds the
/// tile.
pub(crate) struct Field {
    /// Vertices a side.
    side: usize,
    cols: usize,
    rows: usize,
    /// Heights, row-major over `side²`: measured, filled in over a void within reach, or
    /// NaN where nothing may be drawn (voids out of reach, and outside the tile).
    z: Vec<f32>,
    /// 0 at a measured vertex, the distance to the nearest measured one at a filled void,
    /// infinite where `z` is NaN.
    reach: Vec<f32>,
}

impl Field {
    fn new(heights: &[f32], cols: usize, rows: usize, holes: Holes) -> Field {
        assert!(
            cols >= 2 && rows >= 2,
            "a mesh grid is 2 vertices a side at least"
        );
        assert_eq!(heights.len(), cols * rows);
        let side = (cols.max(rows) - 1).next_power_of_two().max(2) + 1;
        let mut z = vec![f32::NAN; side * side];
        let mut reach = vec![f32::INFINITY; side * side];
        for (r, row) in heights.chunks_exact(cols).enumerate() {
            for (c, &h) in row.iter().enumerate() {
                if !h.is_nan() {
                    z[r * side + c] = h;
                    reach[r * side + c] = 0.0;
                }
            }
        }
        let mut f = Field {
            side,
            cols,
            rows,
            z,
            reach,
        };
        if let Holes::Reach { reach, cell } = holes {
            f.fill(reach, cell);
        }
        f
    }

    /// Fills every void vertex within `limit` of a measured one, nearest first (Dijkstra
    /// over the eight neighbours, whose path is never shorter than the straight line, so a
    /// vertex filled is truly within the limit), each with the mean of its neighbours filled
    /// or measured before it: seed 004's heights for void vertices from their neighbours.
    fn fill(&mut self, limit: f64, cell: [f64; 2]) {
        // NaN or nothing: no reach.
        if limit.is_nan() || limit <= 0.0 {
            return;
        }
        let (side, cols, rows) = (self.side as i64, self.cols as i64, self.rows as i64);
        let diagonal = cell[0].hypot(cell[1]);
        let steps = [
            (-1, -1, diagonal),
            (0, -1, cell[1]),
            (1, -1, diagonal),
            (-1, 0, cell[0]),
            (1, 0, cell[0]),
            (-1, 1, diagonal),
            (0, 1, cell[1]),
            (1, 1, diagonal),
        ];
        let inside = |c: i64, r: i64| c >= 0 && r >= 0 && c < cols && r < rows;
        let void =
            |reach: &[f32], c: i64, r: i64| inside(c, r) && reach[(r * side + c) as usize] != 0.0;
        // Distances as their bits: positive floats order like their bit patterns.
        let mut best = vec![f64::INFINITY; self.reach.len()];
        let mut heap = BinaryHeap::new();
        for r in 0..rows {
            for c in 0..cols {
                let k = (r * side + c) as usize;
                if self.reach[k] == 0.0
                    && steps
                        .iter()
                        .any(|&(dc, dr, _)| void(&self.reach, c + dc, r + dr))
                {
                    best[k] = 0.0;
                    heap.push(Reverse((0u64, k)));
                }
            }
        }
        while let Some(Reverse((bits, k))) = heap.pop() {
            let d = f64::from_bits(bits);
            if d > best[k] {
                continue;
            }
            let (c, r) = ((k as i64) % side, (k as i64) / side);
            if d > 0.0 {
                let (mut sum, mut n) = (0.0f64, 0u32);
                for &(dc, dr, _) in &steps {
                    let (c2, r2) = (c + dc, r + dr);
                    if inside(c2, r2) {
                        let z = self.z[(r2 * side + c2) as usize];
                        if !z.is_nan() {
                            sum += z as f64;
                            n += 1;
                        }
                    }
                }
                // The vertex it was reached from is measured or filled: n ≥ 1.
                self.z[k] = (sum / n as f64) as f32;
                self.reach[k] = d as f32;
            }
            for &(dc, dr, w) in &steps {
                let (c2, r2) = (c + dc, r + dr);
                if !void(&self.reach, c2, r2) {
                    continue;
                }
                let q = (r2 * side + c2) as usize;
                let nd = d + w;
                if nd <= limit && nd < best[q] {
                    best[q] = nd;
                    heap.push(Reverse((nd.to_bits(), q)));
                }
            }
        }
    }

    fn at(&self, p: [i64; 2]) -> usize {
        p[1] as usize * self.side + p[0] as usize
    }

    /// Whether grid vertex `p` lies on the tile's border.
    fn on_border(&self, p: [i64; 2]) -> bool {
        let (lc, lr) = (self.cols as i64 - 1, self.rows as i64 - 1);
        ((p[0] == 0 || p[0] == lc) && p[1] <= lr) || ((p[1] == 0 || p[1] == lr) && p[0] <= lc)
    }
}

/// How a triangle fits the field, when it holds a vertex that may be drawn over.
#[derive(Clone, Copy, Debug)]
struct Fit {
    /// The largest |plane − height| over its measured vertices; infinite if it also holds a
    /// vertex nothing may be drawn over.
    error: f64,
    /// The farthest filled void vertex in it from a measured one.
    reach: f64,
}

/// A triangle: hypotenuse a–b, right angle at c.
#[derive(Clone, Copy, Debug)]
struct Tri {
    a: [i64; 2],
    b: [i64; 2],
    c: [i64; 2],
}

impl Tri {
    fn mid(&self) -> [i64; 2] {
        [(self.a[0] + self.b[0]) / 2, (self.a[1] + self.b[1]) / 2]
    }

    /// Legs of one cell: no grid vertex is at the hypotenuse's midpoint.
    fn is_leaf(&self) -> bool {
        (self.a[0] - self.c[0]).abs() + (self.a[1] - self.c[1]).abs() <= 1
    }

    fn children(&self) -> [Tri; 2] {
        let m = self.mid();
        [
            Tri {
                a: self.c,
                b: self.a,
                c: m,
            },
            Tri {
                a: self.b,
                b: self.c,
                c: m,
            },
        ]
    }
}

impl Mesh {
    /// The surface's height at every grid vertex of the tile, row-major, from the surface
    /// triangle that holds it (skirts left out); NaN where none does.
    pub fn surface_at_vertices(&self) -> Vec<f64> {
        let mut out = vec![f64::NAN; self.cols * self.rows];
        for t in &self.triangles[..self.skirt_triangles] {
            let p = t.map(|v| self.grid[v as usize].map(|c| c as f64));
            let z = t.map(|v| self.heights[v as usize] as f64);
            let area = (p[1][0] - p[0][0]) * (p[2][1] - p[0][1])
                - (p[1][1] - p[0][1]) * (p[2][0] - p[0][0]);
            let lo = [0, 1].map(|k| p.iter().map(|q| q[k]).fold(f64::MAX, f64::min) as usize);
            let hi = [0, 1].map(|k| p.iter().map(|q| q[k]).fold(0.0, f64::max) as usize);
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    let q = [x as f64, y as f64];
                    let w = |a: [f64; 2], b: [f64; 2]| {
                        ((b[0] - a[0]) * (q[1] - a[1]) - (b[1] - a[1]) * (q[0] - a[0])) / area
                    };
                    let (wa, wb, wc) = (w(p[1], p[2]), w(p[2], p[0]), w(p[0], p[1]));
                    if wa >= -1e-12 && wb >= -1e-12 && wc >= -1e-12 {
                        out[y * self.cols + x] = wa * z[0] + wb * z[1] + wc * z[2];
                    }
                }
            }
        }
        out
    }
}

/// The tile whose `cols × rows` pixel centres are the corners of a mesh grid over `roi`:
/// the ROI grown by half a grid cell on every side.
pub fn pixel_roi(roi: &Aabb, cols: usize, rows: usize) -> Aabb {
    let hx = roi.width() / (cols - 1) as f64 / 2.0;
    let hy = roi.height() / (rows - 1) as f64 / 2.0;
    Aabb::new(
        roi.min[0] - hx,
        roi.min[1] - hy,
        roi.max[0] + hx,
        roi.max[1] + hy,
    )
}

/// The two root triangles of a grid of `side` vertices a side.
fn roots(side: usize) -> [Tri; 2] {
    let m = side as i64 - 1;
    [
        Tri {
            a: [0, 0],
            b: [m, m],
            c: [m, 0],
        },
        Tri {
            a: [m, m],
            b: [0, 0],
            c: [0, m],
        },
    ]
}

/// How triangle `t` fits the field: None if nothing may be drawn over any of its vertices.
/// Row by row: each edge bounds a row's run of columns, found exactly in integers, and the
/// plane is evaluated from its gradient along the run.
fn fit(f: &Field, t: &Tri) -> Option<Fit> {
    let at = |p: [i64; 2]| f.z[f.at(p)] as f64;
    let (za, zb, zc) = (at(t.a), at(t.b), at(t.c));
    let [a, b, c] = [t.a, t.b, t.c];
    let area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
    let sign = area.signum();
    // Each edge p → q as A·x + B·y + C ≥ 0 on the inside.
    let edge = |p: [i64; 2], q: [i64; 2]| {
        let (ea, eb) = (-(q[1] - p[1]) * sign, (q[0] - p[0]) * sign);
        (ea, eb, -(ea * p[0] + eb * p[1]))
    };
    let edges = [edge(b, c), edge(c, a), edge(a, b)];
    // The plane's gradient, from the two legs (NaN if a corner is blocked: then so is the
    // triangle, and its plane is never used).
    let inv = 1.0 / area as f64;
    let (ux, uy, uz) = ((b[0] - a[0]) as f64, (b[1] - a[1]) as f64, zb - za);
    let (vx, vy, vz) = ((c[0] - a[0]) as f64, (c[1] - a[1]) as f64, zc - za);
    let gx = (uz * vy - vz * uy) * inv;
    let gy = (vz * ux - uz * vx) * inv;
    let (y0, y1) = (a[1].min(b[1]).min(c[1]), a[1].max(b[1]).max(c[1]));
    let (x0, x1) = (a[0].min(b[0]).min(c[0]), a[0].max(b[0]).max(c[0]));
    if x0 >= f.cols as i64 || y0 >= f.rows as i64 {
        // Wholly in the padding: not worth a look at its vertices.
        return None;
    }
    let (mut worst, mut far) = (0.0f64, 0.0f32);
    let (mut drawable, mut blocked) = (false, false);
    for y in y0..=y1 {
        let (mut lo, mut hi) = (x0, x1);
        for &(ea, eb, ec) in &edges {
            let rest = eb * y + ec;
            match ea.signum() {
                1 => lo = lo.max((-rest).div_euclid(ea) + i64::from((-rest).rem_euclid(ea) != 0)),
                -1 => hi = hi.min(rest.div_euclid(-ea)),
                _ if rest < 0 => hi = lo - 1,
                _ => {}
            }
        }
        if lo > hi {
            continue;
        }
        let start = y as usize * f.side + lo as usize;
        let n = (hi - lo) as usize + 1;
        let (zs, rs) = (&f.z[start..start + n], &f.reach[start..start + n]);
        let base = za + (lo - a[0]) as f64 * gx + (y - a[1]) as f64 * gy;
        for (k, (&z, &r)) in zs.iter().zip(rs).enumerate() {
            if r == 0.0 {
                drawable = true;
                worst = worst.max((base + k as f64 * gx - z as f64).abs());
            } else if r.is_finite() {
                drawable = true;
                far = far.max(r);
            } else {
                blocked = true;
            }
        }
        if drawable && blocked {
            break;
        }
    }
    drawable.then_some(Fit {
        error: if blocked { f64::INFINITY } else { worst },
        reach: far as f64,
    })
}

/// The error a triangle asks to be split by: none when it holds nothing to draw.
fn split_error(f: &Field, t: &Tri) -> f64 {
    fit(f, t).map_or(0.0, |fit| fit.error)
}

/// How many triangles are measured between two looks at whether to stop.
const STOP_EVERY: usize = 1 << 16;

/// Triangles at this depth split a level of the RTIN into tasks run in parallel: 512 of them.
const TASK_DEPTH: usize = 8;

/// The error kept for every midpoint vertex, computed from the smallest triangles up. With a
/// shared border, a midpoint on the tile's border gets an infinite one, so that every border
/// vertex is kept and the triangles above split down to it.
fn midpoint_errors(
    f: &Field,
    border: Border,
    stop: &(dyn Fn() -> bool + Sync),
) -> Option<Vec<f64>> {
    let side = f.side;
    // Errors are ≥ 0 (or infinite), whose bits order like the numbers: the two triangles
    // sharing a midpoint may be measured on two threads, and the larger is kept.
    let errors: Vec<AtomicU64> = (0..side * side).map(|_| AtomicU64::new(0)).collect();
    let error_at = |p: [i64; 2]| f64::from_bits(errors[f.at(p)].load(Ordering::Relaxed));
    // The levels that have a midpoint vertex: the roots (legs of 2ⁿ cells) down to the one
    // above the leaves (half cells); two levels halve the legs.
    let levels = 2 * (side - 1).trailing_zeros() as usize;
    // Deepest level first, so that a parent reads its children's midpoints once both
    // triangles sharing each have written them (each level finishes before the next
    // starts). A level's triangles are found by descending from the roots rather than kept:
    // the finest levels hold millions.
    for depth in (0..levels).rev() {
        let top = depth.min(TASK_DEPTH);
        let mut tasks = Vec::with_capacity(2 << top);
        let mut stack: Vec<(Tri, usize)> = roots(side).map(|t| (t, 0)).to_vec();
        while let Some((t, d)) = stack.pop() {
            if d < top {
                stack.extend(t.children().map(|c| (c, d + 1)));
            } else {
                tasks.push(t);
            }
        }
        tasks.into_par_iter().try_for_each(|t| {
            if stop() {
                return None;
            }
            let mut stack = vec![(t, top)];
            let mut seen = 0usize;
            while let Some((t, d)) = stack.pop() {
                if d < depth {
                    stack.extend(t.children().map(|c| (c, d + 1)));
                    continue;
                }
                seen += 1;
                if seen.is_multiple_of(STOP_EVERY) && stop() {
                    return None;
                }
                let mut e = split_error(f, &t);
                let m = t.mid();
                if border == Border::Shared && f.on_border(m) {
                    e = f64::INFINITY;
                }
                let [l, r] = t.children();
                if !l.is_leaf() {
                    e = e.max(error_at(l.mid())).max(error_at(r.mid()));
                }
                errors[f.at(m)].fetch_max(e.to_bits(), Ordering::Relaxed);
            }
            Some(())
        })?;
    }
    Some(
        errors
            .into_iter()
            .map(|e| f64::from_bits(e.into_inner()))
            .collect(),
    )
}

/// The RTIN mesh of the field within `max_error` at every measured grid vertex.
fn rtin(
    f: &Field,
    max_error: f64,
    border: Border,
    stop: &(dyn Fn() -> bool + Sync),
) -> Option<Mesh> {
    let errors = midpoint_errors(f, border, stop)?;
    let mut out = Builder::new(f);
    let mut stack: Vec<Tri> = roots(f.side).to_vec();
    while let Some(t) = stack.pop() {
        if !t.is_leaf() && errors[f.at(t.mid())] > max_error {
            let [l, r] = t.children();
            stack.push(r);
            stack.push(l);
            continue;
        }
        out.push(&t);
    }
    Some(out.finish())
}

/// A mesh being put together: each grid vertex once, triangles turned counter-clockwise.
struct Builder<'a> {
    field: &'a Field,
    index: Vec<u32>,
    mesh: Mesh,
}

impl<'a> Builder<'a> {
    fn new(field: &'a Field) -> Self {
        Builder {
            field,
            index: vec![u32::MAX; field.side * field.side],
            mesh: Mesh {
                cols: field.cols,
                rows: field.rows,
                grid: Vec::new(),
                heights: Vec::new(),
                triangles: Vec::new(),
                skirt_vertices: 0,
                skirt_triangles: 0,
                max_deviation: 0.0,
                max_reach: 0.0,
            },
        }
    }

    /// Adds a triangle, unless it holds nothing measured or a vertex that may not be drawn
    /// over: the hole stays open.
    fn push(&mut self, t: &Tri) {
        let f = self.field;
        let Some(fit) = fit(f, t).filter(|fit| fit.error.is_finite()) else {
            return;
        };
        let m = &mut self.mesh;
        m.max_deviation = m.max_deviation.max(fit.error);
        m.max_reach = m.max_reach.max(fit.reach);
        let mut ids = [t.a, t.b, t.c].map(|p| {
            let k = f.at(p);
            if self.index[k] == u32::MAX {
                self.index[k] = m.grid.len() as u32;
                m.grid.push([p[0] as u32, p[1] as u32]);
                m.heights.push(f.z[k]);
            }
            self.index[k]
        });
        // Rows run south, so counter-clockwise in the world is clockwise on the grid.
        let [a, b, c] = [t.a, t.b, t.c];
        let cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        if cross > 0 {
            ids.swap(1, 2);
        }
        m.triangles.push(ids);
    }

    fn finish(mut self) -> Mesh {
        self.mesh.skirt_vertices = self.mesh.grid.len();
        self.mesh.skirt_triangles = self.mesh.triangles.len();
        self.mesh
    }
}

/// The mesh's vertices on each side of the tile, west, south, east and north, in order along
/// the side (skirt vertices excluded).
pub fn edges(mesh: &Mesh) -> [Vec<u32>; 4] {
    let (lc, lr) = (mesh.cols as u32 - 1, mesh.rows as u32 - 1);
    let on = |pick: &dyn Fn([u32; 2]) -> Option<u32>| {
        let mut v: Vec<(u32, u32)> = mesh.grid[..mesh.skirt_vertices]
            .iter()
            .enumerate()
            .filter_map(|(i, &g)| pick(g).map(|along| (along, i as u32)))
            .collect();
        v.sort_unstable();
        v.into_iter().map(|(_, i)| i).collect::<Vec<u32>>()
    };
    [
        on(&|g| (g[0] == 0).then_some(g[1])),
        on(&|g| (g[1] == lr).then_some(g[0])),
        on(&|g| (g[0] == lc).then_some(g[1])),
        on(&|g| (g[1] == 0).then_some(g[0])),
    ]
}

/// Adds a skirt `depth` metres deep under every edge of the mesh that lies on the tile's
/// border: a wall down from the edge, facing out, so that the cracks between this tile and a
/// neighbour of another error (whose border vertices and heights differ) are hidden while
/// both heights are within `depth` of each other (seed 002).
pub fn add_skirts(mesh: &mut Mesh, depth: f32) {
    let (lc, lr) = (mesh.cols as u32 - 1, mesh.rows as u32 - 1);
    let border = |a: [u32; 2], b: [u32; 2]| {
        (a[0] == b[0] && (a[0] == 0 || a[0] == lc)) || (a[1] == b[1] && (a[1] == 0 || a[1] == lr))
    };
    let mut below = vec![u32::MAX; mesh.skirt_vertices];
    let surface = mesh.triangles[..mesh.skirt_triangles].to_vec();
    for t in surface {
        for k in 0..3 {
            // Counter-clockwise from above, an edge a → b of a border triangle has the
            // outside on its right: the wall a, b, b', a' faces out.
            let (a, b) = (t[k], t[(k + 1) % 3]);
            if !border(mesh.grid[a as usize], mesh.grid[b as usize]) {
                continue;
            }
            let [a2, b2] = [a, b].map(|v| {
                if below[v as usize] == u32::MAX {
                    below[v as usize] = mesh.grid.len() as u32;
                    mesh.grid.push(mesh.grid[v as usize]);
                    mesh.heights.push(mesh.heights[v as usize] - depth);
                }
                below[v as usize]
            });
            mesh.triangles.push([a, a2, b]);
            mesh.triangles.push([b, a2, b2]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rtin_with(h: &[f32], size: usize, max_error: f64, border: Border) -> Mesh {
        let o = Options {
            max_error,
            border,
            ..Options::default()
        };
        triangulate(h, size, size, &o)
    }

    fn adaptive(h: &[f32], size: usize, max_error: f64) -> Mesh {
        rtin_with(h, size, max_error, Border::Adaptive)
    }

    fn rough(size: usize) -> Vec<f32> {
        rough_rect(size, size)
    }

    fn rough_rect(cols: usize, rows: usize) -> Vec<f32> {
        let mut next = patchwork_geom::rng::uniform(3);
        (0..cols * rows)
            .map(|k| {
                let (x, y) = ((k % cols) as f32, (k / cols) as f32);
                (x * 0.3).sin() * 40.0 + (y * 0.17).cos() * 25.0 + next() as f32 * 3.0
            })
            .collect()
    }

    #[test]
    fn the_mesh_keeps_the_error_and_covers_the_tile() {
        let size = 65;
        let h = rough(size);
        for e in [0.5, 2.0, 10.0, 50.0] {
            let m = adaptive(&h, size, e);
            let got = m.surface_at_vertices();
            let mut worst = 0.0f64;
            for (g, z) in got.iter().zip(&h) {
                assert!(!g.is_nan(), "e = {e}: a grid vertex outside every triangle");
                worst = worst.max((g - *z as f64).abs());
            }
            assert!(worst <= e + 1e-9, "e = {e}: {worst}");
            assert!(
                (worst - m.max_deviation).abs() < 1e-6,
                "{worst} vs {}",
                m.max_deviation
            );
            // Two triangles per cell at most, and far fewer when e allows.
            assert!(m.triangles.len() <= 2 * (size - 1) * (size - 1));
        }
        let fine = adaptive(&h, size, 0.0);
        let coarse = adaptive(&h, size, 50.0);
        assert!(coarse.triangles.len() * 4 < fine.triangles.len());
        // Counter-clockwise from above: with rows running south, every triangle's grid
        // cross product is negative.
        for t in &coarse.triangles {
            let p = t.map(|v| coarse.grid[v as usize].map(|c| c as i64));
            let cross = (p[1][0] - p[0][0]) * (p[2][1] - p[0][1])
                - (p[1][1] - p[0][1]) * (p[2][0] - p[0][0]);
            assert!(cross < 0);
        }
    }

    #[test]
    fn no_triangle_spans_a_void_and_the_rest_is_meshed() {
        let size = 33;
        let mut h = rough(size);
        for y in 10..14 {
            for x in 5..20 {
                h[y * size + x] = f32::NAN;
            }
        }
        let m = adaptive(&h, size, 1e9);
        let got = m.surface_at_vertices();
        for y in 0..size {
            for x in 0..size {
                let void = h[y * size + x].is_nan();
                assert_eq!(got[y * size + x].is_nan(), void, "({x}, {y})");
            }
        }
        // A cell with four valid corners is always meshed: nothing but voids is lost.
        for t in &m.triangles {
            for v in t {
                assert!(!m.heights[*v as usize].is_nan());
            }
        }
    }

    #[test]
    fn shared_hypotenuses_split_together() {
        // Every edge of the mesh inside the tile is shared by exactly two triangles; on the
        // border by one. A T-junction would leave an edge used once inside the tile.
        let size = 65;
        let h = rough(size);
        for e in [0.5, 5.0, 30.0] {
            let m = adaptive(&h, size, e);
            let mut uses = std::collections::HashMap::new();
            for t in &m.triangles {
                for k in 0..3 {
                    let (a, b) = (t[k], t[(k + 1) % 3]);
                    *uses.entry((a.min(b), a.max(b))).or_insert(0) += 1;
                }
            }
            let last = size as u32 - 1;
            for ((a, b), n) in uses {
                let (p, q) = (m.grid[a as usize], m.grid[b as usize]);
                let on_border = (p[0] == q[0] && (p[0] == 0 || p[0] == last))
                    || (p[1] == q[1] && (p[1] == 0 || p[1] == last));
                assert_eq!(n, if on_border { 1 } else { 2 }, "{p:?}–{q:?} at e = {e}");
            }
        }
    }

    #[test]
    fn a_shared_border_keeps_every_border_vertex() {
        let size = 33;
        let h = rough(size);
        let m = rtin_with(&h, size, 1e9, Border::Shared);
        assert!(edges(&m).iter().all(|e| e.len() == size));
        let loose = adaptive(&h, size, 1e9);
        assert!(edges(&loose).iter().all(|e| e.len() == 2));
        assert_eq!(loose.triangles.len(), 2);
    }

    #[test]
    fn skirts_hang_from_every_border_edge() {
        let size = 17;
        let h = rough(size);
        let mut m = adaptive(&h, size, 5.0);
        let border_edges: usize = edges(&m).iter().map(|e| e.len() - 1).sum();
        let before = m.triangles.len();
        add_skirts(&mut m, 12.0);
        assert_eq!(m.triangles.len() - before, 2 * border_edges);
        for v in m.skirt_vertices..m.grid.len() {
            let top = m.grid[..m.skirt_vertices]
                .iter()
                .position(|g| *g == m.grid[v])
                .unwrap();
            assert_eq!(m.heights[v], m.heights[top] - 12.0);
        }
    }

    /// Twice the area the surface triangles cover, in cells.
    pub(super) fn doubled_area(m: &Mesh) -> i64 {
        m.triangles[..m.skirt_triangles]
            .iter()
            .map(|t| {
                let p = t.map(|v| m.grid[v as usize].map(i64::from));
                ((p[1][0] - p[0][0]) * (p[2][1] - p[0][1])
                    - (p[1][1] - p[0][1]) * (p[2][0] - p[0][0]))
                    .abs()
            })
            .sum()
    }

    /// Every edge inside the tile is shared by two triangles, every border edge by one: no
    /// T-junction, no overlap.
    pub(super) fn conforming(m: &Mesh) -> bool {
        let mut uses = std::collections::HashMap::new();
        for t in &m.triangles[..m.skirt_triangles] {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *uses.entry((a.min(b), a.max(b))).or_insert(0) += 1;
            }
        }
        let (lc, lr) = (m.cols as u32 - 1, m.rows as u32 - 1);
        uses.into_iter().all(|((a, b), n)| {
            let (p, q) = (m.grid[a as usize], m.grid[b as usize]);
            let border = (p[0] == q[0] && (p[0] == 0 || p[0] == lc))
                || (p[1] == q[1] && (p[1] == 0 || p[1] == lr));
            n == if border { 1 } else { 2 }
        })
    }

    #[test]
    fn grids_of_any_size_are_meshed_whole_and_only_inside() {
        for (cols, rows) in [(2, 2), (50, 37), (3, 40), (100, 100), (65, 33)] {
            let h = rough_rect(cols, rows);
            for method in [Method::Rtin, Method::Quadtree] {
                for (e, border) in [
                    (0.0, Border::Adaptive),
                    (3.0, Border::Shared),
                    (1e9, Border::Adaptive),
                ] {
                    let o = Options {
                        max_error: e,
                        border,
                        method,
                        holes: Holes::Exact,
                    };
                    let what = format!("{cols} × {rows} {method:?} e = {e} {border:?}");
                    let m = triangulate(&h, cols, rows, &o);
                    assert!(
                        m.grid
                            .iter()
                            .all(|g| (g[0] as usize) < cols && (g[1] as usize) < rows),
                        "{what}"
                    );
                    let got = m.surface_at_vertices();
                    let mut worst = 0.0f64;
                    for (g, z) in got.iter().zip(&h) {
                        assert!(!g.is_nan(), "{what}: a vertex left out");
                        worst = worst.max((g - *z as f64).abs());
                    }
                    assert!(
                        worst <= e + 1e-6 && worst <= m.max_deviation + 1e-6,
                        "{what}: {worst}"
                    );
                    assert!(conforming(&m), "{what}: a T-junction");
                    assert_eq!(
                        doubled_area(&m),
                        2 * (cols as i64 - 1) * (rows as i64 - 1),
                        "{what}: covered once"
                    );
                    if border == Border::Shared {
                        let [w, s, e, n] = edges(&m).map(|e| e.len());
                        assert_eq!([w, s, e, n], [rows, cols, rows, cols], "{what}");
                    }
                }
            }
        }
    }

    /// A plane with a 3 × 3 void and a 20 × 20 one in a corner.
    fn plane_with_holes(size: usize) -> Vec<f32> {
        let mut h: Vec<f32> = (0..size * size)
            .map(|k| 2.0 * (k % size) as f32 + 3.0 * (k / size) as f32)
            .collect();
        for y in 40..43 {
            for x in 40..43 {
                h[y * size + x] = f32::NAN;
            }
        }
        for y in 0..20 {
            for x in 0..20 {
                h[y * size + x] = f32::NAN;
            }
        }
        h
    }

    #[test]
    fn a_reach_closes_narrow_holes_and_draws_no_farther_into_wide_ones() {
        let size = 65;
        let h = plane_with_holes(size);
        let mesh = |reach: f64, method: Method| {
            let holes = if reach > 0.0 {
                Holes::Reach {
                    reach,
                    cell: [1.0, 1.0],
                }
            } else {
                Holes::Exact
            };
            let o = Options {
                max_error: 0.01,
                border: Border::Adaptive,
                method,
                holes,
            };
            triangulate(&h, size, size, &o)
        };
        for method in [Method::Rtin, Method::Quadtree] {
            let exact = mesh(0.0, method);
            let near = mesh(2.5, method);
            let what = format!("{method:?}");
            assert_eq!(exact.max_reach, 0.0);
            assert!(
                near.max_reach > 0.0 && near.max_reach <= 2.5,
                "{what}: {}",
                near.max_reach
            );
            // A reach of a few cells lets triangles cross the big hole's border.
            let wide = mesh(16.0, method);
            assert!(wide.triangles.len() < exact.triangles.len(), "{what}");
            let (ge, gn) = (exact.surface_at_vertices(), near.surface_at_vertices());
            for y in 0..size {
                for x in 0..size {
                    let k = y * size + x;
                    if !h[k].is_nan() {
                        // Measured heights: within the error in both.
                        for g in [ge[k], gn[k]] {
                            assert!((g - h[k] as f64).abs() <= 0.01 + 1e-9, "{what} ({x}, {y})");
                        }
                        continue;
                    }
                    // Voids: open when exact; drawn over with a reach only within it of
                    // data: the small hole closes, the corner one keeps its far part.
                    assert!(
                        ge[k].is_nan(),
                        "{what}: exact holes drawn over at ({x}, {y})"
                    );
                    let d = if x < 20 && y < 20 {
                        (20 - x.max(y)) as f64
                    } else {
                        1.0
                    };
                    if d > 2.5 {
                        assert!(
                            gn[k].is_nan(),
                            "{what}: ({x}, {y}) drawn {d} cells from data"
                        );
                    }
                    if x >= 40 && y >= 40 {
                        assert!(
                            !gn[k].is_nan(),
                            "{what}: the 3 × 3 hole stays open at ({x}, {y})"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn a_mesh_is_given_up_when_asked() {
        let size = 513;
        let h = rough(size);
        for method in [Method::Rtin, Method::Quadtree] {
            let o = Options {
                max_error: 1.0,
                method,
                ..Options::default()
            };
            let looks = std::sync::atomic::AtomicUsize::new(0);
            let stop = || {
                looks.fetch_add(1, Ordering::Relaxed);
                true
            };
            assert!(
                triangulate_until(&h, size, size, &o, &stop).is_none(),
                "{method:?}"
            );
            // Once for each task started before the first said to stop, at most.
            let n = looks.load(Ordering::Relaxed);
            assert!(
                n >= 1 && n <= rayon::current_num_threads(),
                "{method:?}: {n}"
            );
            let never = triangulate_until(&h, size, size, &o, &|| false);
            assert_eq!(never, Some(triangulate(&h, size, size, &o)), "{method:?}");
        }
    }
}
