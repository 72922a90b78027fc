//! Triangle meshes of a resampled tile, for renderers: a right-triangulated irregular network
//! (RTIN, the triangle bintree of seed 003, the method martini uses) with an exact error, void
//! vertices that keep holes open (seed 004), and skirts that hide the cracks between tiles of
//! different errors (seed 002). Pure computation, no I/O; [`encode`] writes the formats.
//!
//! The grid is `size × size` heights, `size` = 2ⁿ + 1, row 0 at the top (north), NaN where
//! void. A triangle is a right isosceles triangle of grid vertices, split at the midpoint of
//! its hypotenuse. Its *error* is the largest vertical distance between its plane and the grid
//! heights at every grid vertex inside it or on its edges, exactly; a triangle holding a void
//! vertex has an infinite one. The error kept for a midpoint is the largest of the two
//! triangles that share that hypotenuse and of their descendants, so that two triangles that
//! share a hypotenuse always split together: the mesh has no T-junction inside the tile.

pub mod encode;
pub mod quadtree;

use crate::index::geom::Aabb;

/// How the grid is triangulated.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Method {
    /// The right-triangulated irregular network ([`rtin_with`]).
    #[default]
    Rtin,
    /// The restricted quadtree with omitted edge vertices ([`quadtree::mesh`]).
    Quadtree,
}

impl Method {
    pub fn name(self) -> &'static str {
        match self {
            Method::Rtin => "rtin",
            Method::Quadtree => "quadtree",
        }
    }
}

/// The mesh of `heights` by `method`: within `max_error` of them at every grid vertex, no
/// triangle over a void, the border kept as `border` says.
pub fn triangulate(
    heights: &[f32],
    size: usize,
    max_error: f64,
    border: Border,
    method: Method,
) -> Mesh {
    match method {
        Method::Rtin => rtin_with(heights, size, max_error, border),
        Method::Quadtree => quadtree::mesh(heights, size, max_error, border),
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

/// A mesh of one tile in grid coordinates.
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    /// Grid vertices per side.
    pub size: usize,
    /// Each vertex's grid position (column, row); a skirt vertex shares its top's position.
    pub grid: Vec<[u32; 2]>,
    /// Each vertex's height, metres.
    pub heights: Vec<f32>,
    /// Counter-clockwise seen from above with north up (x east, y north).
    pub triangles: Vec<[u32; 3]>,
    /// Vertices from here on are skirt vertices, and triangles from `skirt_triangles` on are
    /// skirt triangles.
    pub skirt_vertices: usize,
    pub skirt_triangles: usize,
    /// The largest distance from the grid heights over the surface triangles.
    pub max_deviation: f64,
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
    /// The surface's height at every grid vertex, row-major, from the surface triangle that
    /// holds it (skirts left out); NaN where none does.
    pub fn surface_at_vertices(&self) -> Vec<f64> {
        let s = self.size;
        let mut out = vec![f64::NAN; s * s];
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
                        out[y * s + x] = wa * z[0] + wb * z[1] + wc * z[2];
                    }
                }
            }
        }
        out
    }
}

/// The tile whose `size × size` pixel centres are the corners of a mesh grid over `roi`: the
/// ROI grown by half a grid cell on every side.
pub fn pixel_roi(roi: &Aabb, size: usize) -> Aabb {
    let n = (size - 1) as f64;
    let (hx, hy) = (roi.width() / n / 2.0, roi.height() / n / 2.0);
    Aabb::new(
        roi.min[0] - hx,
        roi.min[1] - hy,
        roi.max[0] + hx,
        roi.max[1] + hy,
    )
}

/// Whether `size` is 2ⁿ + 1 with n ≥ 1.
pub fn valid_size(size: usize) -> bool {
    size >= 3 && (size - 1).is_power_of_two()
}

/// The two root triangles of a grid of `size` vertices a side.
fn roots(size: usize) -> [Tri; 2] {
    let m = size as i64 - 1;
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

/// The largest |plane − height| over the grid vertices in a triangle (edges included), or
/// infinity if one is void. Row by row: each edge bounds a row's run of columns, found exactly
/// in integers, and the plane is evaluated from its gradient along the run.
fn triangle_error(h: &[f32], size: usize, t: &Tri) -> f64 {
    let at = |p: [i64; 2]| h[p[1] as usize * size + p[0] as usize] as f64;
    let (za, zb, zc) = (at(t.a), at(t.b), at(t.c));
    if za.is_nan() || zb.is_nan() || zc.is_nan() {
        return f64::INFINITY;
    }
    let [a, b, c] = [t.a, t.b, t.c];
    let area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
    let sign = area.signum();
    // Each edge p → q as A·x + B·y + C ≥ 0 on the inside.
    let edge = |p: [i64; 2], q: [i64; 2]| {
        let (ea, eb) = (-(q[1] - p[1]) * sign, (q[0] - p[0]) * sign);
        (ea, eb, -(ea * p[0] + eb * p[1]))
    };
    let edges = [edge(b, c), edge(c, a), edge(a, b)];
    // The plane's gradient, from the two legs.
    let inv = 1.0 / area as f64;
    let (ux, uy, uz) = ((b[0] - a[0]) as f64, (b[1] - a[1]) as f64, zb - za);
    let (vx, vy, vz) = ((c[0] - a[0]) as f64, (c[1] - a[1]) as f64, zc - za);
    let gx = (uz * vy - vz * uy) * inv;
    let gy = (vz * ux - uz * vx) * inv;
    let (y0, y1) = (a[1].min(b[1]).min(c[1]), a[1].max(b[1]).max(c[1]));
    let (x0, x1) = (a[0].min(b[0]).min(c[0]), a[0].max(b[0]).max(c[0]));
    let mut worst = 0.0f64;
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
        let row = &h[y as usize * size..][lo as usize..=hi as usize];
        let base = za + (lo - a[0]) as f64 * gx + (y - a[1]) as f64 * gy;
        for (k, &z) in row.iter().enumerate() {
            let d = (base + k as f64 * gx - z as f64).abs();
            // NaN (a void vertex) fails every comparison: caught below.
            if d > worst {
                worst = d;
            } else if d.is_nan() {
                return f64::INFINITY;
            }
        }
    }
    worst
}

/// The error kept for every midpoint vertex, computed from the smallest triangles up. With a
/// shared border, a midpoint on the border gets an infinite one, so that every border vertex
/// is kept and the triangles above split down to it.
fn midpoint_errors(h: &[f32], size: usize, border: Border) -> Vec<f64> {
    let mut errors = vec![0.0f64; size * size];
    // The levels that have a midpoint vertex: the roots (legs of 2ⁿ cells) down to the one
    // above the leaves (half cells); two levels halve the legs.
    let levels = 2 * (size - 1).trailing_zeros() as usize;
    let key = |p: [i64; 2]| p[1] as usize * size + p[0] as usize;
    let last = size as i64 - 1;
    // Deepest level first, so that a parent reads its children's midpoints once both
    // triangles sharing each have written them. A level's triangles are found by descending
    // from the roots rather than kept: the finest levels hold millions.
    let mut stack = Vec::with_capacity(2 * levels + 2);
    for depth in (0..levels).rev() {
        stack.extend(roots(size).map(|t| (t, 0usize)));
        while let Some((t, d)) = stack.pop() {
            if d < depth {
                stack.extend(t.children().map(|c| (c, d + 1)));
                continue;
            }
            let mut e = triangle_error(h, size, &t);
            let m = t.mid();
            if border == Border::Shared && (m[0] == 0 || m[1] == 0 || m[0] == last || m[1] == last)
            {
                e = f64::INFINITY;
            }
            let [l, r] = t.children();
            if !l.is_leaf() {
                e = e.max(errors[key(l.mid())]).max(errors[key(r.mid())]);
            }
            let m = key(m);
            errors[m] = errors[m].max(e);
        }
    }
    errors
}

/// The RTIN mesh of `heights` (`size × size`, row 0 north) within `max_error` of them at every
/// grid vertex, without triangles over voids, its border simplified like the rest.
///
/// # Panics
/// If `size` is not 2ⁿ + 1 or `heights` does not hold `size²` values.
pub fn rtin(heights: &[f32], size: usize, max_error: f64) -> Mesh {
    rtin_with(heights, size, max_error, Border::Adaptive)
}

/// [`rtin`], keeping the border as `border` says.
pub fn rtin_with(heights: &[f32], size: usize, max_error: f64, border: Border) -> Mesh {
    assert!(valid_size(size), "a mesh grid is 2^n + 1 vertices a side");
    assert_eq!(heights.len(), size * size);
    let errors = midpoint_errors(heights, size, border);
    let key = |p: [i64; 2]| p[1] as usize * size + p[0] as usize;
    let mut out = Builder::new(heights, size);
    let mut stack: Vec<Tri> = roots(size).to_vec();
    while let Some(t) = stack.pop() {
        if !t.is_leaf() && errors[key(t.mid())] > max_error {
            let [l, r] = t.children();
            stack.push(r);
            stack.push(l);
            continue;
        }
        out.push(&t);
    }
    out.finish()
}

/// A mesh being put together: each grid vertex once, triangles turned counter-clockwise.
struct Builder<'a> {
    heights: &'a [f32],
    index: Vec<u32>,
    mesh: Mesh,
}

impl<'a> Builder<'a> {
    fn new(heights: &'a [f32], size: usize) -> Self {
        Builder {
            heights,
            index: vec![u32::MAX; size * size],
            mesh: Mesh {
                size,
                grid: Vec::new(),
                heights: Vec::new(),
                triangles: Vec::new(),
                skirt_vertices: 0,
                skirt_triangles: 0,
                max_deviation: 0.0,
            },
        }
    }

    /// Adds a triangle, unless it holds a void vertex: the hole stays open.
    fn push(&mut self, t: &Tri) {
        let size = self.mesh.size;
        let e = triangle_error(self.heights, size, t);
        if !e.is_finite() {
            return;
        }
        let m = &mut self.mesh;
        m.max_deviation = m.max_deviation.max(e);
        let mut ids = [t.a, t.b, t.c].map(|p| {
            let k = p[1] as usize * size + p[0] as usize;
            if self.index[k] == u32::MAX {
                self.index[k] = m.grid.len() as u32;
                m.grid.push([p[0] as u32, p[1] as u32]);
                m.heights.push(self.heights[k]);
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
    let last = mesh.size as u32 - 1;
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
        on(&|g| (g[1] == last).then_some(g[0])),
        on(&|g| (g[0] == last).then_some(g[1])),
        on(&|g| (g[1] == 0).then_some(g[0])),
    ]
}

/// Adds a skirt `depth` metres deep under every edge of the mesh that lies on the tile's
/// border: a wall down from the edge, facing out, so that the cracks between this tile and a
/// neighbour of another error (whose border vertices and heights differ) are hidden while
/// both heights are within `depth` of each other (seed 002).
pub fn add_skirts(mesh: &mut Mesh, depth: f32) {
    let last = mesh.size as u32 - 1;
    let border = |a: [u32; 2], b: [u32; 2]| {
        (a[0] == b[0] && (a[0] == 0 || a[0] == last))
            || (a[1] == b[1] && (a[1] == 0 || a[1] == last))
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

    fn rough(size: usize) -> Vec<f32> {
        let mut next = crate::rng::uniform(3);
        (0..size * size)
            .map(|k| {
                let (x, y) = ((k % size) as f32, (k / size) as f32);
                (x * 0.3).sin() * 40.0 + (y * 0.17).cos() * 25.0 + next() as f32 * 3.0
            })
            .collect()
    }

    #[test]
    fn the_mesh_keeps_the_error_and_covers_the_tile() {
        let size = 65;
        let h = rough(size);
        for e in [0.5, 2.0, 10.0, 50.0] {
            let m = rtin(&h, size, e);
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
        let fine = rtin(&h, size, 0.0);
        let coarse = rtin(&h, size, 50.0);
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
        let m = rtin(&h, size, 1e9);
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
            let m = rtin(&h, size, e);
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
        let loose = rtin(&h, size, 1e9);
        assert!(edges(&loose).iter().all(|e| e.len() == 2));
        assert_eq!(loose.triangles.len(), 2);
    }

    #[test]
    fn skirts_hang_from_every_border_edge() {
        let size = 17;
        let h = rough(size);
        let mut m = rtin(&h, size, 5.0);
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
}
