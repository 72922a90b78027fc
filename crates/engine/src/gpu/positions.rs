//! Sample positions the device makes itself, so that none crosses the bus: a view's from its
//! rows (two points a row: each row of a view is an evenly spaced line on the ground), a grid
//! of another CRS from its axes carried through the CRS's lattice, and every sample's
//! position in the plane of each survey of another CRS through that plane's lattice.
//!
//! A lattice's nodes ([`Reprojection::block`], 16 × 16 a block) are uploaded once and kept on
//! the device beside the patches, each node as its offset from an anchor node of its block,
//! in two f32s: exact to 2⁻⁴⁸ of the block's size, where the node's own coordinates (millions
//! of metres) in two f32s would keep only 2⁻⁴⁸ of *those*. A request sends each block's
//! anchor relative to the plane's origin, and its lattices' descriptions: some hundred bytes
//! where the positions took 16 a sample and plane.
//!
//! *Why it is the CPU's answer.* The shader evaluates the same tensor Catmull-Rom sum as
//! [`Reprojection::at`], term for term (offsets from the cell's first node, weighted, summed
//! by rows), in double-f32 arithmetic (about 44 bits each step): relative to the request's
//! origin, every term is bounded by the tile's extent E in the target plane, so a position
//! errs by ~10⁻¹³·E. For a plane whose level cells are c across that is ~10⁻¹³·E/c cells,
//! under 10⁻⁹ for tiles under 10⁴ cells, the bound the sample positions of a north-up grid
//! keep (see `mod.rs`). The cell of the lattice a point falls in may differ from the CPU's
//! where a position is within rounding of a node line; the cubic is continuous there (at
//! either side's fraction 0 or 1 it is the node itself), so the answer is the same to that
//! rounding. Where any of a point's 16 nodes has no image the point has none, on both.

use super::{split, VOID};
use bytemuck::{Pod, Zeroable};
use patchwork_core::crs::{LatticeBlock, Reprojection, LATTICE_SIDE};
use patchwork_core::geom::Aabb;
use patchwork_core::resample::{row_point, Axes, Carried, PatchSet, Row, SampleGrid};
use std::hash::{Hash, Hasher};
use std::sync::Arc;

/// `Params::source`: the positions are made from a north-up grid's axes.
pub(super) const SOURCE_AXES: u32 = 1;
/// `Params::source`: from a view's rows.
pub(super) const SOURCE_ROWS: u32 = 2;
/// `BlockRef::slot` of a block none of whose nodes has an image.
pub(super) const NO_SLOT: u32 = u32::MAX;
/// Bytes of one block of nodes on the device: 16² nodes of 16 bytes.
pub(super) const BLOCK_BYTES: u64 = (LATTICE_SIDE * LATTICE_SIDE * 16) as u64;
/// The most blocks one lattice of a request may read: 4 MiB of nodes, some 500 km or 4°
/// square at the lattices' spacing, far more than any tile a device resamples. A wider
/// request (a continent at zoom 2) lists its positions on the CPU, as it did before.
const MOST_BLOCKS: i64 = 1024;

/// A lattice as one request reads it: `struct Lattice` in `resample.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(super) struct GpuLattice {
    g_hi: [f32; 2],
    g_lo: [f32; 2],
    inv_h_hi: f32,
    inv_h_lo: f32,
    table: u32,
    width: u32,
    height: u32,
    _pad: u32,
    first: [i32; 2],
}

/// One block of a request's lattice: `struct BlockRef` in `resample.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(super) struct BlockRef {
    anchor_hi: [f32; 2],
    anchor_lo: [f32; 2],
    pub(super) slot: u32,
    _pad: [u32; 3],
}

/// A block of nodes a request reads: found on the device by `key`, or uploaded as offsets
/// from `anchor` (its first node with an image; NaN for a block without any).
pub(super) struct NodeBlock {
    pub(super) key: (u64, [i64; 2]),
    pub(super) nodes: Arc<LatticeBlock>,
    pub(super) anchor: [f64; 2],
}

impl NodeBlock {
    /// The nodes as the shader reads them: offsets from the anchor, (x hi, y hi, x lo, y lo),
    /// x hi VOID where a node has no image.
    pub(super) fn pack(&self, out: &mut Vec<[f32; 4]>) {
        out.extend(self.nodes.iter().map(|n| {
            if n[0].is_finite() && n[1].is_finite() {
                let [xh, xl] = split(n[0] - self.anchor[0]);
                let [yh, yl] = split(n[1] - self.anchor[1]);
                [xh, yh, xl, yl]
            } else {
                [VOID, 0.0, 0.0, 0.0]
            }
        }));
    }
}

/// What the device makes a request's positions from.
pub(super) struct Generated {
    /// [`SOURCE_AXES`] or [`SOURCE_ROWS`].
    pub(super) kind: u32,
    /// The axes (as `points` lays them out) or two entries a row.
    pub(super) source: Vec<[f32; 4]>,
    /// Whether lattice 0 carries the source into the store's plane.
    pub(super) carry: bool,
    /// The carrying lattice (if any), then one a plane of the set.
    pub(super) lattices: Vec<GpuLattice>,
    /// Their blocks, each lattice's row-major, and the nodes behind each.
    pub(super) refs: Vec<BlockRef>,
    pub(super) blocks: Vec<NodeBlock>,
}

/// How a request's positions are made on the device: the origin they are relative to in the
/// store's plane and in each other plane, the bounds of each square of `side`² samples for
/// binning (None where the grid's axes bin it), and what the device needs.
pub(super) struct Plan {
    pub(super) origin: [f64; 2],
    pub(super) plane_origins: Vec<[f64; 2]>,
    pub(super) squares: Option<Vec<Option<Aabb>>>,
    pub(super) generated: Generated,
}

/// The plan for a grid of axes (running one way), rows or a carried grid, with the set's
/// planes; None where the device cannot make the positions (a lattice spanning more than
/// [`MOST_BLOCKS`], a carried grid whose squares' edges leave the lattice, a grid without a
/// valid point), and the CPU lists them.
pub(super) fn plan(set: &PatchSet, grid: &SampleGrid, side: usize) -> Option<Plan> {
    let mut g = Generated {
        kind: SOURCE_AXES,
        source: Vec::new(),
        carry: false,
        lattices: Vec::new(),
        refs: Vec::new(),
        blocks: Vec::new(),
    };
    let (origin, squares, bounds) = if let Some(a) = &grid.axes {
        let origin = [a.xs[0], a.ys[0]];
        g.source = axes_source(a, origin);
        (origin, None, a.bounds()?)
    } else if let Some(rows) = grid.rows() {
        let origin = rows.iter().flatten().next()?[0];
        g.kind = SOURCE_ROWS;
        g.source = rows_source(rows, origin);
        let squares = row_squares(rows, grid.width, side);
        let bounds = union(&squares)?;
        (origin, Some(squares), bounds)
    } else if let Some(c) = grid.carry() {
        let (squares, origin) = carried_squares(c, side)?;
        let own = [c.own.xs[0], c.own.ys[0]];
        g.source = axes_source(&c.own, own);
        let own_bounds = c.own.bounds()?;
        lattice(&c.by, &own_bounds, own, origin, &mut g)?;
        g.carry = true;
        let bounds = union(&squares)?;
        (origin, Some(squares), bounds)
    } else {
        return None;
    };
    if !(origin[0].is_finite() && origin[1].is_finite()) {
        return None;
    }
    let mut plane_origins = Vec::with_capacity(set.planes.len());
    for r in &set.planes {
        let o = r.at(origin)?;
        lattice(r, &bounds, origin, o, &mut g)?;
        plane_origins.push(o);
    }
    Some(Plan {
        origin,
        plane_origins,
        squares,
        generated: g,
    })
}

/// A north-up grid's axes relative to `origin`, as `points` lays them out: each column's x
/// as (x hi, 0, x lo, 0), then each row's y as (0, y hi, 0, y lo).
pub(super) fn axes_source(a: &Axes, origin: [f64; 2]) -> Vec<[f32; 4]> {
    let mut out = Vec::with_capacity(a.xs.len() + a.ys.len());
    out.extend(a.xs.iter().map(|&x| {
        let [xh, xl] = split(x - origin[0]);
        [xh, 0.0, xl, 0.0]
    }));
    out.extend(a.ys.iter().map(|&y| {
        let [yh, yl] = split(y - origin[1]);
        [0.0, yh, 0.0, yl]
    }));
    out
}

/// Two entries a row: its first point relative to `origin`, and its step.
fn rows_source(rows: &[Row], origin: [f64; 2]) -> Vec<[f32; 4]> {
    let mut out = Vec::with_capacity(2 * rows.len());
    for row in rows {
        match row {
            Some([p, q]) => {
                let ([xh, xl], [yh, yl]) = (split(p[0] - origin[0]), split(p[1] - origin[1]));
                out.push([xh, yh, xl, yl]);
                let ([xh, xl], [yh, yl]) = (split(q[0]), split(q[1]));
                out.push([xh, yh, xl, yl]);
            }
            None => out.extend([[VOID, 0.0, 0.0, 0.0], [0.0; 4]]),
        }
    }
    out
}

/// The bounds of each square of `side`² samples of a grid of rows: a square's are bounded by
/// its rows' first and last points within it ([`row_point`]).
fn row_squares(rows: &[Row], width: usize, side: usize) -> Vec<Option<Aabb>> {
    let sx = width.div_ceil(side);
    let mut out: Vec<Option<Aabb>> = vec![None; sx * rows.len().div_ceil(side)];
    for (j, row) in rows.iter().enumerate() {
        let Some(row) = row else { continue };
        let at = |i: usize| row_point(row, i);
        for s in 0..sx {
            let (a, b) = (at(s * side), at(((s + 1) * side).min(width) - 1));
            if a.iter().chain(&b).any(|v| !v.is_finite()) {
                continue;
            }
            let seg = Aabb::of_points(&[a, b]);
            let sq = &mut out[(j / side) * sx + s];
            *sq = Some(sq.map_or(seg, |o| o.union(&seg)));
        }
    }
    out
}

/// The bounds of each square of `side`² samples of a carried grid, from the images of the
/// samples on the squares' edges, and the image of sample (0, 0): None where any of those has
/// no image. The lattice's map is a C¹ interpolant within 10⁻⁶ m of a projection, one to one
/// at the scale of a square, so a square's image is bounded by its edges'; between two edge
/// samples the image of the edge strays from the chord by ⅛·curvature·step², far below the
/// millionth of the square's size each bound is widened by.
fn carried_squares(c: &Carried, side: usize) -> Option<(Vec<Option<Aabb>>, [f64; 2])> {
    let (w, h) = (c.own.xs.len(), c.own.ys.len());
    let edge = |k: usize, n: usize| k.is_multiple_of(side) || k % side == side - 1 || k == n - 1;
    let mut at: Vec<(usize, usize)> = Vec::new();
    for j in 0..h {
        if edge(j, h) {
            at.extend((0..w).map(|i| (i, j)));
        } else {
            at.extend((0..w).filter(|&i| edge(i, w)).map(|i| (i, j)));
        }
    }
    let pts: Vec<[f64; 2]> = at
        .iter()
        .map(|&(i, j)| [c.own.xs[i], c.own.ys[j]])
        .collect();
    let images = c.by.map(&pts);
    let sx = w.div_ceil(side);
    let mut out: Vec<Option<Aabb>> = vec![None; sx * h.div_ceil(side)];
    for (&(i, j), q) in at.iter().zip(&images) {
        if !(q[0].is_finite() && q[1].is_finite()) {
            return None;
        }
        let pb = Aabb { min: *q, max: *q };
        let sq = &mut out[(j / side) * sx + i / side];
        *sq = Some(sq.map_or(pb, |o| o.union(&pb)));
    }
    for b in out.iter_mut().flatten() {
        let d = 1e-6 * b.width().max(b.height()) + 1e-12 * b.max[0].abs().max(b.max[1].abs());
        *b = b.grown(d);
    }
    Some((out, images[0]))
}

fn union(squares: &[Option<Aabb>]) -> Option<Aabb> {
    squares.iter().flatten().copied().reduce(|a, b| a.union(&b))
}

/// A lattice's identity on the device: its CRSs and spacing.
fn lattice_key(r: &Reprojection) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    r.from().key().hash(&mut h);
    r.to().key().hash(&mut h);
    r.spacing().to_bits().hash(&mut h);
    h.finish()
}

/// Adds lattice `r` as read by positions within `bounds` relative to `from` (in its source
/// CRS) and carried to positions relative to `to`: its description, and its blocks from two
/// nodes before the bounds' first to three after their last (the stencil's reach, and a
/// node more for a cell the device's rounding puts one over). None where that is more than
/// [`MOST_BLOCKS`].
fn lattice(
    r: &Reprojection,
    bounds: &Aabb,
    from: [f64; 2],
    to: [f64; 2],
    g: &mut Generated,
) -> Option<()> {
    let h = r.spacing();
    let side = LATTICE_SIDE as i64;
    let node = |v: f64| (v / h).floor() as i64;
    let lo = [node(bounds.min[0]) - 2, node(bounds.min[1]) - 2];
    let hi = [node(bounds.max[0]) + 3, node(bounds.max[1]) + 3];
    let b0 = lo.map(|v| v.div_euclid(side));
    let b1 = hi.map(|v| v.div_euclid(side));
    let (w, ht) = (b1[0] - b0[0] + 1, b1[1] - b0[1] + 1);
    if w * ht > MOST_BLOCKS {
        return None;
    }
    let gs = [from[0] / h, from[1] / h];
    let gi = gs.map(f64::floor);
    let [gxh, gxl] = split(gs[0] - gi[0]);
    let [gyh, gyl] = split(gs[1] - gi[1]);
    let [ihh, ihl] = split(1.0 / h);
    g.lattices.push(GpuLattice {
        g_hi: [gxh, gyh],
        g_lo: [gxl, gyl],
        inv_h_hi: ihh,
        inv_h_lo: ihl,
        table: g.refs.len() as u32,
        width: w as u32,
        height: ht as u32,
        _pad: 0,
        first: [
            (gi[0] as i64 - b0[0] * side) as i32,
            (gi[1] as i64 - b0[1] * side) as i32,
        ],
    });
    let key = lattice_key(r);
    for by in b0[1]..=b1[1] {
        for bx in b0[0]..=b1[0] {
            let nodes = r.block([bx, by]);
            let anchor = nodes
                .iter()
                .find(|n| n[0].is_finite() && n[1].is_finite())
                .copied()
                .unwrap_or([f64::NAN; 2]);
            let ([xh, xl], [yh, yl]) = if anchor[0].is_finite() {
                (split(anchor[0] - to[0]), split(anchor[1] - to[1]))
            } else {
                ([0.0; 2], [0.0; 2])
            };
            g.refs.push(BlockRef {
                anchor_hi: [xh, yh],
                anchor_lo: [xl, yl],
                slot: NO_SLOT,
                _pad: [0; 3],
            });
            g.blocks.push(NodeBlock {
                key: (key, [bx, by]),
                nodes,
                anchor,
            });
        }
    }
    Some(())
}
