//! The restricted quadtree of seed 002: square nodes, each drawn as a fan of eight triangles
//! around its centre through its corners and the midpoints of its sides, split while that fan
//! departs from the grid by more than the error; neighbours kept within one level of each
//! other; and where a node meets a coarser one, the midpoint of the shared side *omitted* from
//! its fan, so that both draw that side as one edge and no T-junction is left.
//!
//! Every error is exact (the fans' triangles against every grid vertex inside them, as in
//! [`super::rtin_with`]), measured on the triangles actually drawn: a node whose omissions
//! take it past the error is split, or, at the finest nodes, its coarser neighbour is.

use super::{split_error, Border, Builder, Field, Mesh, Tri, STOP_EVERY};

/// A node: its north-west grid vertex and its side in cells (a power of two, 2 at least, so
/// that it has a centre vertex).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
struct Node {
    x: i64,
    y: i64,
    span: i64,
}

/// The sides, in the order a fan walks them: north, east, south, west.
const SIDES: usize = 4;

impl Node {
    fn children(self) -> [Node; 4] {
        let h = self.span / 2;
        [(0, 0), (h, 0), (0, h), (h, h)].map(|(dx, dy)| Node {
            x: self.x + dx,
            y: self.y + dy,
            span: h,
        })
    }

    /// A cell just across each side, or None past the tile's border (`last` = size − 1).
    fn across(self, last: i64) -> [Option<[i64; 2]>; SIDES] {
        let (x, y, s) = (self.x, self.y, self.span);
        [
            (y > 0).then_some([x, y - 1]),
            (x + s < last).then_some([x + s, y]),
            (y + s < last).then_some([x, y + s]),
            (x > 0).then_some([x - 1, y]),
        ]
    }

    /// The fan's triangles, the midpoints of the sides in `omit` left out.
    fn fan(self, omit: [bool; SIDES]) -> Vec<Tri> {
        let (x, y, s, h) = (self.x, self.y, self.span, self.span / 2);
        let centre = [x + h, y + h];
        let corners = [[x, y], [x + s, y], [x + s, y + s], [x, y + s]];
        let mids = [[x + h, y], [x + s, y + h], [x + h, y + s], [x, y + h]];
        let mut ring = Vec::with_capacity(8);
        for side in 0..SIDES {
            ring.push(corners[side]);
            if !omit[side] {
                ring.push(mids[side]);
            }
        }
        (0..ring.len())
            .map(|k| Tri {
                a: ring[k],
                b: ring[(k + 1) % ring.len()],
                c: centre,
            })
            .collect()
    }

    fn error(self, f: &Field, omit: [bool; SIDES]) -> f64 {
        self.fan(omit)
            .iter()
            .map(|t| split_error(f, t))
            .fold(0.0, f64::max)
    }

    /// Whether the node's square holds a vertex of the tile's border.
    fn on_border(self, f: &Field) -> bool {
        let (lc, lr) = (f.cols as i64 - 1, f.rows as i64 - 1);
        let (x1, y1) = (self.x + self.span, self.y + self.span);
        let meets = |lo: i64, hi: i64, line: i64| lo <= line && line <= hi;
        let (in_x, in_y) = (self.x <= lc, self.y <= lr);
        (in_y && (meets(self.x, x1, 0) || meets(self.x, x1, lc)))
            || (in_x && (meets(self.y, y1, 0) || meets(self.y, y1, lr)))
    }
}

/// The leaves, as the level of the leaf that holds each block of 2 × 2 cells (the finest
/// node): the leaf holding a cell is found in one look, which the restriction makes millions
/// of.
struct Tree<'a> {
    /// log₂ of the span of the leaf holding each block, row-major.
    level: Vec<u8>,
    /// Blocks a side.
    blocks: usize,
    field: &'a Field,
    max_error: f64,
    border: Border,
}

impl Tree<'_> {
    /// Makes `n` a leaf, or splits it and its children while their whole fans depart from
    /// the grid by more than the error (or a shared border wants them finest).
    fn refine(&mut self, n: Node) {
        let mut stack = vec![n];
        while let Some(n) = stack.pop() {
            let split = n.span > 2
                && ((self.border == Border::Shared && n.on_border(self.field))
                    || n.error(self.field, [false; SIDES]) > self.max_error);
            if split {
                stack.extend(n.children());
            } else {
                self.set_leaf(n);
            }
        }
    }

    fn set_leaf(&mut self, n: Node) {
        let level = n.span.trailing_zeros() as u8;
        let (bx, by, bs) = (
            (n.x / 2) as usize,
            (n.y / 2) as usize,
            (n.span / 2) as usize,
        );
        for row in by..by + bs {
            let start = row * self.blocks + bx;
            self.level[start..start + bs].fill(level);
        }
    }

    /// The leaf holding cell `c`: nodes lie at multiples of their span.
    fn leaf_at(&self, c: [i64; 2]) -> Node {
        let k = (c[1] / 2) as usize * self.blocks + (c[0] / 2) as usize;
        let span = 1i64 << self.level[k];
        Node {
            x: c[0] - c[0] % span,
            y: c[1] - c[1] % span,
            span,
        }
    }

    fn is_leaf(&self, n: Node) -> bool {
        self.leaf_at([n.x, n.y]) == n
    }

    /// Every leaf, north-west corners in row order.
    fn leaves(&self) -> Vec<Node> {
        let mut out = Vec::new();
        for by in 0..self.blocks {
            for bx in 0..self.blocks {
                let span = 1usize << self.level[by * self.blocks + bx];
                let (x, y) = (2 * bx, 2 * by);
                if x % span == 0 && y % span == 0 {
                    out.push(Node {
                        x: x as i64,
                        y: y as i64,
                        span: span as i64,
                    });
                }
            }
        }
        out
    }

    /// Splits a leaf whose neighbours need it finer: its children are refined in turn, since
    /// a finer fan is not always closer to the grid than the one it replaces.
    fn split(&mut self, n: Node) {
        for c in n.children() {
            self.refine(c);
        }
    }

    /// Each side's neighbour where it is coarser: the sides to omit.
    fn omitted(&self, n: Node, last: i64) -> ([bool; SIDES], [Option<Node>; SIDES]) {
        let mut omit = [false; SIDES];
        let mut coarser = [None; SIDES];
        for (side, c) in n.across(last).into_iter().enumerate() {
            if let Some(c) = c {
                let m = self.leaf_at(c);
                if m.span > n.span {
                    omit[side] = true;
                    coarser[side] = Some(m);
                }
            }
        }
        (omit, coarser)
    }
}

/// The restricted-quadtree mesh of the field within `max_error` at every measured grid
/// vertex. A shared border keeps every border vertex (its nodes are split to the finest).
pub(super) fn mesh(
    field: &Field,
    max_error: f64,
    border: Border,
    stop: &(dyn Fn() -> bool + Sync),
) -> Option<Mesh> {
    let last = field.side as i64 - 1;
    let root = Node {
        x: 0,
        y: 0,
        span: last,
    };
    let blocks = (field.side - 1) / 2;
    let mut tree = Tree {
        level: vec![0; blocks * blocks],
        blocks,
        field,
        max_error,
        border,
    };
    tree.refine(root);
    loop {
        // Restrict: no leaf more than one level coarser than a neighbour.
        let mut changed = false;
        if stop() {
            return None;
        }
        for (k, n) in tree.leaves().into_iter().enumerate() {
            if k.is_multiple_of(STOP_EVERY) && stop() {
                return None;
            }
            for c in n.across(last).into_iter().flatten() {
                let m = tree.leaf_at(c);
                if m.span > 2 * n.span {
                    tree.split(m);
                    changed = true;
                }
            }
        }
        if changed {
            continue;
        }
        // The fans as drawn, with the omitted midpoints: too far from the grid, and the node
        // is split, or at the finest its coarser neighbours are.
        for n in tree.leaves() {
            if !tree.is_leaf(n) {
                continue;
            }
            let (omit, coarser) = tree.omitted(n, last);
            if !omit.iter().any(|&o| o) {
                continue;
            }
            // Only the triangles over omitted sides differ from the fan the refinement
            // measured; a void under one (even its own) must not be drawn over either.
            let drawn = n
                .fan(omit)
                .iter()
                .filter(|t| is_omitted_side(n, t))
                .map(|t| split_error(field, t))
                .fold(0.0, f64::max);
            if drawn <= max_error {
                continue;
            }
            if n.span > 2 {
                tree.split(n);
            } else {
                for m in coarser.into_iter().flatten() {
                    if tree.is_leaf(m) {
                        tree.split(m);
                    }
                }
            }
            changed = true;
        }
        if !changed {
            break;
        }
    }
    let mut out = Builder::new(field);
    for n in tree.leaves() {
        let (omit, _) = tree.omitted(n, last);
        for t in n.fan(omit) {
            out.push(&t);
        }
    }
    Some(out.finish())
}

/// Whether a fan triangle spans a whole side of its node (its side's midpoint omitted).
fn is_omitted_side(n: Node, t: &Tri) -> bool {
    (t.a[0] - t.b[0]).abs() + (t.a[1] - t.b[1]).abs() == n.span
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tests::{conforming, doubled_area};
    use crate::{edges, fit, triangulate, Holes, Method, Options};

    fn mesh(h: &[f32], size: usize, max_error: f64, border: Border) -> Mesh {
        let o = Options {
            max_error,
            border,
            method: Method::Quadtree,
            holes: Holes::Exact,
        };
        triangulate(h, size, size, &o)
    }

    fn rough(size: usize) -> Vec<f32> {
        let mut next = patchwork_geom::rng::uniform(5);
        (0..size * size)
            .map(|k| {
                let (x, y) = ((k % size) as f32, (k / size) as f32);
                (x * 0.2).sin() * 40.0 + (y * 0.11).cos() * 25.0 + next() as f32 * 2.0
            })
            .collect()
    }

    #[test]
    fn the_quadtree_keeps_the_error_without_t_junctions() {
        let size = 65;
        let h = rough(size);
        for e in [0.5, 3.0, 15.0, 60.0] {
            let m = mesh(&h, size, e, Border::Adaptive);
            assert!(m.max_deviation <= e, "e = {e}: {}", m.max_deviation);
            assert!(conforming(&m), "e = {e}: a T-junction");
            // Twice the tile's area in cells: the triangles cover it once.
            assert_eq!(doubled_area(&m), 2 * (size as i64 - 1).pow(2), "e = {e}");
        }
        let coarse = mesh(&h, size, 60.0, Border::Adaptive);
        let fine = mesh(&h, size, 0.5, Border::Adaptive);
        assert!(coarse.triangles.len() * 4 < fine.triangles.len());
        let shared = mesh(&h, size, 60.0, Border::Shared);
        assert!(edges(&shared).iter().all(|e| e.len() == size));
        assert!(conforming(&shared));
    }

    #[test]
    fn nodes_split_for_their_neighbours_still_keep_the_error() {
        // Ridges and valleys of every scale: a random walk in both directions.
        for seed in 1..4 {
            let size = 129;
            let mut next = patchwork_geom::rng::uniform(seed);
            let mut h = vec![0.0f32; size * size];
            for y in 0..size {
                for x in 0..size {
                    let left = if x > 0 { h[y * size + x - 1] } else { 0.0 };
                    let up = if y > 0 { h[(y - 1) * size + x] } else { left };
                    h[y * size + x] = 0.5 * (left + up) + (next() as f32 - 0.5) * 12.0;
                }
            }
            for e in [2.0, 10.0, 40.0] {
                let m = mesh(&h, size, e, Border::Adaptive);
                assert!(
                    m.max_deviation <= e,
                    "seed {seed}, e = {e}: {}",
                    m.max_deviation
                );
                assert!(conforming(&m));
            }
        }
    }

    #[test]
    fn the_quadtree_leaves_voids_open() {
        let size = 33;
        let mut h = rough(size);
        for y in 9..13 {
            for x in 4..19 {
                h[y * size + x] = f32::NAN;
            }
        }
        let m = mesh(&h, size, 1e9, Border::Adaptive);
        let field = Field::new(&h, size, size, Holes::Exact);
        for t in &m.triangles {
            for v in t {
                assert!(!m.heights[*v as usize].is_nan());
            }
            let p = t.map(|v| m.grid[v as usize].map(i64::from));
            let tri = Tri {
                a: p[0],
                b: p[1],
                c: p[2],
            };
            assert!(
                fit(&field, &tri).is_some_and(|f| f.error.is_finite()),
                "a triangle over a void"
            );
        }
        assert!(!m.triangles.is_empty());
    }
}
