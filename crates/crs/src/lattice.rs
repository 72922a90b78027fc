//! A transformation sampled on a lattice and interpolated: what a tile's millions of points go
//! through, at a few tens of nanoseconds each instead of the exact transformation's few
//! hundred, with an error that is measured and small enough to count.
//!
//! The lattice is fixed in the source CRS (nodes at whole multiples of the spacing), so the
//! position a point maps to depends on the point alone, never on the tile or request that
//! holds it: a height at a point stays one answer. Between nodes the map is the tensor
//! Catmull-Rom cubic through the 4 × 4 nodes around the point, exact at the nodes, C¹, and
//! within about 10⁻⁶ m of the exact transformation at a spacing of 1/64° or 1 km for UTM,
//! Web Mercator, LAEA, polar stereographic and Swiss oblique Mercator (docs/MODEL.md,
//! "Coordinate reference systems"). [`Reprojection::residual`] measures the difference over
//! a region, and callers count it: a patch's error grows by it times the ground's slope.

use super::{Crs, CrsError, Transform};
use rayon::prelude::*;
use std::sync::Arc;

/// Nodes per side of a cached block.
const SIDE: usize = 16;
/// Nodes per side of a block, as [`Reprojection::block`] gives them.
pub const BLOCK_SIDE: usize = SIDE;
/// Blocks kept per reprojection: 8,192 of 4 KiB, 32 MiB at most, covering some 2 × 10⁶ km²
/// at the default spacing.
const BLOCKS: usize = 8192;
/// A lattice spanning more nodes than this is not gathered for one batch; its points go one
/// at a time.
const MOST_GATHERED: usize = 1 << 22;

/// The images of a block's nodes, row-major: node (i, j) of block (bx, by) is lattice node
/// (16·bx + i, 16·by + j), at (that node × the spacing) in the source CRS. NaN where the
/// exact transformation has no image.
pub type Block = [[f64; 2]; SIDE * SIDE];

/// A transformation from one CRS to another, interpolated on a lattice.
pub struct Reprojection {
    exact: Transform,
    /// Node spacing, in the source CRS's units.
    h: f64,
    blocks: quick_cache::sync::Cache<[i64; 2], Arc<Block>>,
    /// This reprojection's own number, never reused: what a thread's recent blocks are keyed
    /// by, so that a block of one that was dropped is never taken for another's.
    id: u64,
}

/// Blocks a thread keeps at hand, newest first: the four a cell's nodes can straddle, and as
/// many again for a second reprojection used in the same loop.
const RECENT_BLOCKS: usize = 8;

type Recent = [Option<((u64, [i64; 2]), Arc<Block>)>; RECENT_BLOCKS];

thread_local! {
    static RECENT: std::cell::RefCell<Recent> = const { std::cell::RefCell::new([const { None }; RECENT_BLOCKS]) };
}

static NEXT_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

impl Reprojection {
    /// The lattice of about a kilometre: 1/64° in a geographic source CRS, 1,024 m in a
    /// projected one.
    pub fn new(from: &Crs, to: &Crs) -> Result<Reprojection, CrsError> {
        let h = match from.unit_m() {
            None => 1.0 / 64.0,
            Some(m) => 1024.0 / m,
        };
        Ok(Reprojection {
            exact: Transform::new(from, to)?,
            h,
            blocks: quick_cache::sync::Cache::new(BLOCKS),
            id: NEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
        })
    }

    /// The source CRS.
    pub fn from(&self) -> &Crs {
        self.exact.from()
    }

    /// The target CRS.
    pub fn to(&self) -> &Crs {
        self.exact.to()
    }

    /// Whether the transformation is the identity: then no lattice is built and points pass
    /// unchanged.
    pub fn is_identity(&self) -> bool {
        self.exact.is_identity()
    }

    /// The exact transformation the lattice samples.
    pub fn exact(&self) -> &Transform {
        &self.exact
    }

    /// The node spacing, in the source CRS's units: node (i, j) is at (i·h, j·h).
    pub fn spacing(&self) -> f64 {
        self.h
    }

    /// Whether [`Self::map`] gathers the nodes around a batch of points within `[min, max]`
    /// at once (and so whether a device may be handed them): a batch spanning more goes
    /// point by point.
    pub fn gathers(&self, min: [f64; 2], max: [f64; 2]) -> bool {
        let spanned = ((max[0] - min[0]) / self.h + 4.0) * ((max[1] - min[1]) / self.h + 4.0);
        spanned.is_finite() && spanned <= MOST_GATHERED as f64
    }

    /// The images of block `b`'s nodes (see [`Block`]), worked out once and cached: what
    /// [`Self::at`] interpolates, for a device that interpolates them itself.
    pub fn block(&self, b: [i64; 2]) -> Arc<Block> {
        let make = || -> Result<Arc<Block>, std::convert::Infallible> {
            let mut out = Box::new([[f64::NAN; 2]; SIDE * SIDE]);
            for (k, node) in out.iter_mut().enumerate() {
                let i = b[0] * SIDE as i64 + (k % SIDE) as i64;
                let j = b[1] * SIDE as i64 + (k / SIDE) as i64;
                if let Some(q) = self.exact.apply([i as f64 * self.h, j as f64 * self.h]) {
                    *node = q;
                }
            }
            Ok(Arc::from(out))
        };
        match self.blocks.get_or_insert_with(&b, make) {
            Ok(b) => b,
            Err(never) => match never {},
        }
    }

    /// Calls `f` with block `b`, from this thread's few most recent blocks when it is among
    /// them. `at` runs once per point, millions of times for a tile or a coregistration, and
    /// a lookup in the shared cache (a shard's lock and the block's reference count, both
    /// atomics that every thread mapping the same region writes) cost it more than the
    /// interpolation itself: 70% of the time of a comparison between surveys of two CRSs.
    #[inline]
    fn with_block<R>(&self, b: [i64; 2], f: impl FnOnce(&Block) -> R) -> R {
        let key = (self.id, b);
        let mut f = Some(f);
        // A hit reads the block through this thread's slot, without touching its reference
        // count, which the other threads' slots and the shared cache also hold.
        let hit = RECENT.with(|r| {
            let r = r.borrow();
            let (_, block) = r.iter().flatten().find(|(k, _)| *k == key)?;
            f.take().map(|f| f(block))
        });
        if let Some(out) = hit {
            return out;
        }
        let block = self.block(b);
        RECENT.with(|r| {
            let mut r = r.borrow_mut();
            r.rotate_right(1);
            r[0] = Some((key, block.clone()));
        });
        (f.take().expect("called once"))(&block)
    }

    /// The 4 × 4 nodes around lattice cell (i, j), from node (i − 1, j − 1), row-major: in
    /// one block for 13 cells of 16 along each axis, in two or four for the others.
    #[inline]
    fn stencil(&self, i: i64, j: i64) -> [[f64; 2]; 16] {
        let s = SIDE as i64;
        let mut out = [[f64::NAN; 2]; 16];
        let (i0, j0) = (i - 1, j - 1);
        let (bx0, by0) = (i0.div_euclid(s), j0.div_euclid(s));
        let (bx1, by1) = ((i0 + 3).div_euclid(s), (j0 + 3).div_euclid(s));
        for by in by0..=by1 {
            for bx in bx0..=bx1 {
                self.with_block([bx, by], |block| {
                    for b in 0..4 {
                        let j = j0 + b;
                        if j.div_euclid(s) != by {
                            continue;
                        }
                        for a in 0..4 {
                            let i = i0 + a;
                            if i.div_euclid(s) == bx {
                                out[(b * 4 + a) as usize] =
                                    block[(j.rem_euclid(s) * s + i.rem_euclid(s)) as usize];
                            }
                        }
                    }
                });
            }
        }
        out
    }

    /// Which lattice cell holds a point, and where in it.
    #[inline]
    fn locate(&self, p: [f64; 2]) -> Option<([i64; 2], [f64; 2])> {
        if !(p[0].is_finite() && p[1].is_finite()) {
            return None;
        }
        let (x, y) = (p[0] / self.h, p[1] / self.h);
        let (i, j) = (x.floor(), y.floor());
        if i.abs() > 1e15 || j.abs() > 1e15 {
            return None;
        }
        Some(([i as i64, j as i64], [x - i, y - j]))
    }

    /// The interpolated image of a point; None where the lattice around it is not defined.
    pub fn at(&self, p: [f64; 2]) -> Option<[f64; 2]> {
        if self.exact.is_identity() {
            return Some(p);
        }
        let ([i, j], f) = self.locate(p)?;
        let nodes = self.stencil(i, j);
        let q = interpolate(f, |a, b| nodes[(b * 4 + a) as usize]);
        (q[0].is_finite() && q[1].is_finite()).then_some(q)
    }

    /// [`Self::at`] of every point, NaN where it is None: the same values, with the nodes
    /// gathered once for the batch.
    pub fn map(&self, points: &[[f64; 2]]) -> Vec<[f64; 2]> {
        if self.exact.is_identity() {
            return points.to_vec();
        }
        let none = [f64::NAN; 2];
        let cells: Vec<Option<([i64; 2], [f64; 2])>> =
            points.par_iter().map(|&p| self.locate(p)).collect();
        let (mut lo, mut hi) = ([i64::MAX; 2], [i64::MIN; 2]);
        for (c, _) in cells.iter().flatten() {
            for k in 0..2 {
                lo[k] = lo[k].min(c[k] - 1);
                hi[k] = hi[k].max(c[k] + 2);
            }
        }
        if lo[0] > hi[0] {
            return vec![none; points.len()];
        }
        let w = (hi[0] - lo[0] + 1) as usize;
        let h = (hi[1] - lo[1] + 1) as usize;
        if w.saturating_mul(h) > MOST_GATHERED {
            return points
                .par_iter()
                .map(|&p| self.at(p).unwrap_or(none))
                .collect();
        }
        // Gathered block by block: a lookup a block rather than one a node (see `at`). The
        // batch's blocks are held until copied: at most the nodes the batch gathers, as many
        // as `grid` holds, beside the cache's own.
        let mut grid = vec![[f64::NAN; 2]; w * h];
        let s = SIDE as i64;
        let (b0, b1) = (
            [lo[0].div_euclid(s), lo[1].div_euclid(s)],
            [hi[0].div_euclid(s), hi[1].div_euclid(s)],
        );
        let blocks: Vec<[i64; 2]> = (b0[1]..=b1[1])
            .flat_map(|by| (b0[0]..=b1[0]).map(move |bx| [bx, by]))
            .collect();
        let made: Vec<Arc<Block>> = blocks.par_iter().map(|&b| self.block(b)).collect();
        for (b, block) in blocks.iter().zip(&made) {
            for jj in 0..s {
                let j = b[1] * s + jj;
                if j < lo[1] || j > hi[1] {
                    continue;
                }
                for ii in 0..s {
                    let i = b[0] * s + ii;
                    if i >= lo[0] && i <= hi[0] {
                        grid[(j - lo[1]) as usize * w + (i - lo[0]) as usize] =
                            block[(jj * s + ii) as usize];
                    }
                }
            }
        }
        cells
            .par_iter()
            .map(|c| {
                let Some(([i, j], f)) = *c else {
                    return none;
                };
                let (a0, b0) = ((i - 1 - lo[0]) as usize, (j - 1 - lo[1]) as usize);
                let q = interpolate(f, |a, b| grid[(b0 + b as usize) * w + a0 + a as usize]);
                if q[0].is_finite() && q[1].is_finite() {
                    q
                } else {
                    none
                }
            })
            .collect()
    }

    /// [`Self::map`] of the points whose exact image `keep` takes, NaN for the others, where
    /// the batch spreads wider than the lattice gathers at once (a world-wide tile over a
    /// store of one region, say): carried one at a time, each of its points would build blocks
    /// of nodes for itself, most of them far from anything `keep` wants, which took seconds
    /// and hundreds of megabytes for one 512² tile. A point kept gets the position
    /// [`Self::map`] gives it, so a height at a point still does not depend on the batch; a
    /// narrower batch is mapped whole, as by [`Self::map`].
    pub fn map_where(
        &self,
        points: &[[f64; 2]],
        keep: impl Fn([f64; 2]) -> bool + Sync,
    ) -> Vec<[f64; 2]> {
        if self.exact.is_identity() || self.nodes_spanned(points) <= MOST_GATHERED as f64 {
            return self.map(points);
        }
        let kept: Vec<usize> = (0..points.len())
            .into_par_iter()
            .filter(|&k| self.exact.apply(points[k]).is_some_and(&keep))
            .collect();
        let chosen: Vec<[f64; 2]> = kept.iter().map(|&k| points[k]).collect();
        let mut out = vec![[f64::NAN; 2]; points.len()];
        for (&k, q) in kept.iter().zip(self.map(&chosen)) {
            out[k] = q;
        }
        out
    }

    /// How many lattice nodes the bounding box of the finite points among `points` spans.
    fn nodes_spanned(&self, points: &[[f64; 2]]) -> f64 {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in points
            .iter()
            .filter(|p| p[0].is_finite() && p[1].is_finite())
        {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        if lo[0] > hi[0] {
            return 0.0;
        }
        ((hi[0] - lo[0]) / self.h + 4.0) * ((hi[1] - lo[1]) / self.h + 4.0)
    }

    /// A bound on how far [`Self::at`] lies from the exact transformation anywhere in the
    /// source rectangle `[min, max]`, in the target CRS's units: twice the largest difference
    /// at nine points of every lattice cell there, plus the rounding of coordinates of that
    /// size. 0 for an identity. The points are where the error peaks: Catmull-Rom is exact
    /// for quadratics, and the cubic term of a smooth map leaves an error shaped like
    /// t(1 − t)(1 − 2t) along each axis, largest at t = ½ ± 1/√12 and zero halfway; the
    /// quartic term's peaks halfway.
    pub fn residual(&self, min: [f64; 2], max: [f64; 2]) -> f64 {
        if self.exact.is_identity() {
            return 0.0;
        }
        let (Some(([i0, j0], _)), Some(([i1, j1], _))) = (self.locate(min), self.locate(max))
        else {
            return f64::INFINITY;
        };
        let (worst, size) = (j0..=j1)
            .into_par_iter()
            .map(|j| {
                let mut acc = (0.0f64, 0.0f64);
                for i in i0..=i1 {
                    for (fx, fy) in PROBES.iter().flat_map(|&a| PROBES.map(|b| (a, b))) {
                        let p = [(i as f64 + fx) * self.h, (j as f64 + fy) * self.h];
                        let (Some(a), Some(e)) = (self.at(p), self.exact.apply(p)) else {
                            continue;
                        };
                        acc.0 = acc.0.max((a[0] - e[0]).hypot(a[1] - e[1]));
                        acc.1 = acc.1.max(e[0].abs().max(e[1].abs()));
                    }
                }
                acc
            })
            .reduce(|| (0.0, 0.0), |a, b| (a.0.max(b.0), a.1.max(b.1)));
        2.0 * worst + 8.0 * f64::EPSILON * size
    }
}

/// Where along a lattice cell [`Reprojection::residual`] looks: ½ and ½ ± 1/√12.
const PROBES: [f64; 3] = [0.211_324_865_405_187_1, 0.5, 0.788_675_134_594_812_9];

/// The Catmull-Rom weights of the four nodes around a point a fraction `t` of the way
/// between the middle two.
#[inline]
fn weights(t: f64) -> [f64; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    [
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
}

/// The tensor Catmull-Rom cubic at fractions `f` of the cell whose first corner is node
/// (1, 1) of the 4 × 4 nodes `node(a, b)`. Summed as offsets from that corner, so that
/// coordinates of millions of units keep their last millimetre's digits; a point on a node
/// gets the node exactly.
#[inline]
fn interpolate(f: [f64; 2], node: impl Fn(i64, i64) -> [f64; 2]) -> [f64; 2] {
    let base = node(1, 1);
    let (wx, wy) = (weights(f[0]), weights(f[1]));
    let mut out = [0.0f64; 2];
    for (b, &wb) in wy.iter().enumerate() {
        let mut row = [0.0f64; 2];
        for (a, &wa) in wx.iter().enumerate() {
            let n = node(a as i64, b as i64);
            row[0] += wa * (n[0] - base[0]);
            row[1] += wa * (n[1] - base[1]);
        }
        out[0] += wb * row[0];
        out[1] += wb * row[1];
    }
    [base[0] + out[0], base[1] + out[1]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lattice_is_within_its_residual_of_the_exact_transform_and_batches_agree() {
        for (from, to, min, max) in [
            (4326, 32631, [4.9, 43.9], [6.1, 44.6]),
            (
                32631,
                4326,
                [600_000.0, 4_860_000.0],
                [700_000.0, 4_950_000.0],
            ),
            (4326, 3857, [-119.1, 33.9], [-117.9, 35.1]),
        ] {
            let r = Reprojection::new(&Crs::epsg(from).unwrap(), &Crs::epsg(to).unwrap()).unwrap();
            let rho = r.residual(min, max);
            let unit = if to == 4326 { 111_000.0 } else { 1.0 };
            assert!(rho * unit < 1e-4, "{from}→{to}: {rho}");
            let mut next = patchwork_geom::rng::uniform(from as u64);
            let pts: Vec<[f64; 2]> = (0..3000)
                .map(|_| {
                    [
                        min[0] + next() * (max[0] - min[0]),
                        min[1] + next() * (max[1] - min[1]),
                    ]
                })
                .collect();
            let batch = r.map(&pts);
            for (p, b) in pts.iter().zip(&batch) {
                let a = r.at(*p).unwrap();
                assert_eq!(
                    a.map(f64::to_bits),
                    b.map(f64::to_bits),
                    "one answer per point"
                );
                let e = r.exact().apply(*p).unwrap();
                assert!(
                    (a[0] - e[0]).hypot(a[1] - e[1]) <= rho,
                    "{from}→{to} at {p:?}"
                );
            }
            // Nodes are exact.
            let node = [r.h * (min[0] / r.h).ceil(), r.h * (min[1] / r.h).ceil()];
            assert_eq!(r.at(node), r.exact().apply(node));
        }
    }

    /// A world-wide batch (a 512² Web Mercator tile at zoom 0) over a store of one region:
    /// the points near it get what `map` gives them, bit for bit, and the rest are left out.
    #[test]
    fn a_wide_batch_carries_only_what_is_kept_and_carries_it_as_map_does() {
        let r = Reprojection::new(&Crs::epsg(3857).unwrap(), &Crs::wgs84()).unwrap();
        let half = 20_037_508.342_789_244;
        let n = 512;
        let pts: Vec<[f64; 2]> = (0..n * n)
            .map(|k| {
                let (i, j) = ((k % n) as f64 + 0.5, (k / n) as f64 + 0.5);
                [
                    -half + i * 2.0 * half / n as f64,
                    half - j * 2.0 * half / n as f64,
                ]
            })
            .collect();
        let region =
            |q: [f64; 2]| (-119.5..=-117.5).contains(&q[0]) && (33.5..=35.5).contains(&q[1]);
        let out = r.map_where(&pts, region);
        let kept: Vec<usize> = (0..pts.len()).filter(|&k| !out[k][0].is_nan()).collect();
        assert!(!kept.is_empty() && kept.len() < 20, "{} kept", kept.len());
        for k in 0..pts.len() {
            if region(r.exact().apply(pts[k]).unwrap()) {
                assert_eq!(
                    out[k].map(f64::to_bits),
                    r.at(pts[k]).unwrap().map(f64::to_bits),
                    "one answer per point"
                );
            } else {
                assert!(out[k][0].is_nan());
            }
        }
        // A batch the lattice gathers at once is mapped whole.
        let near = &pts[kept[0]..kept[0] + 1];
        assert_eq!(r.map_where(near, |_| false), r.map(near));
    }
}
