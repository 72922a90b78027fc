//! Formula 1 on the CPU: every output sample is the weighted mean of the patches whose window
//! holds it, with weights W = w(tx)·w(ty) / (dx·dy) so that smaller, more accurate patches
//! count more. A sample no valid kernel holds is nodata.
//!
//! Where a cut falls back below the data's accuracy, patches come in tiers: the cut's own
//! patches, then the fallback patches ranked by error. At a point some cut patch covers, only
//! the cut's patches blend; elsewhere the best-ranked fallback patch that covers the point
//! sets the tier, and the fallback patches of that rank or better blend with the cut's
//! patches that reach the point (which are more accurate still). A point's height then depends
//! only on the point and the patches that reach it, never on the ROI, and it is within the
//! error of the most accurate data that covers it.

//!
//! The accurate blend ([`Blend::Accurate`]) lays the patches that reach a point over one
//! another in the set's order (tier, error, id): each takes its weight ω (1 over its kernel)
//! of what the better ones left, so the first whose kernel holds the point ends the sum, and
//! the same tiers hold. Every path below forms its sums in that order, term for term.

use super::{AxisHit, Cancel, Hit, PatchSet, ResolvedPatch, SampleGrid, Surface, BLOCK};
use patchwork_model::patch::Blend;
use rayon::prelude::*;

/// Patch indices per block of output samples, so each sample visits only patches near it:
/// those whose window meets the block's bounds, in ascending order.
pub fn bin(patches: &[ResolvedPatch], grid: &SampleGrid) -> Vec<Vec<u32>> {
    bin_squares(patches, grid, BLOCK)
}

/// [`bin`] for squares of `side` × `side` samples.
pub fn bin_squares(patches: &[ResolvedPatch], grid: &SampleGrid, side: usize) -> Vec<Vec<u32>> {
    if let Some((cols, rows)) = grid.axis_bounds(side) {
        if let Some(bins) = bin_axes(patches, &cols, &rows) {
            return bins;
        }
    }
    bin_boxes(patches, &grid.bounds_of(side))
}

/// [`bin_boxes`] for the boxes of a north-up grid, box (i, j) the product of the x interval
/// `cols[i]` and the y interval `rows[j]`, row-major. None where the intervals do not run one
/// way along each list (see [`Flat::of_axes`]).
pub fn bin_axes(
    patches: &[ResolvedPatch],
    cols: &[[f64; 2]],
    rows: &[[f64; 2]],
) -> Option<Vec<Vec<u32>>> {
    let windows: Vec<patchwork_geom::Aabb> = patches.iter().map(ResolvedPatch::reach).collect();
    let flat = Flat::of_axes(&windows, cols, rows)?;
    Some(
        flat.offsets
            .windows(2)
            .map(|w| flat.entries[w[0] as usize..w[1] as usize].to_vec())
            .collect(),
    )
}

/// Bins laid end to end: bin b holds `entries[offsets[b]..offsets[b + 1]]`, the form a GPU
/// takes them in.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Flat {
    /// Where each bin starts in `entries`, and after the last where it ends.
    pub offsets: Vec<u32>,
    /// Patch indices, ascending within a bin.
    pub entries: Vec<u32>,
}

impl Flat {
    /// [`bin_axes`] of patches whose windows' bounds are `windows`, end to end. Where the
    /// intervals' ends run one way along each list (as
    /// monotone axes make them), each patch finds the boxes its window meets by bisection,
    /// rather than each box looking for its patches; bins are counted, then filled, in the
    /// patches' order.
    pub fn of_axes(
        windows: &[patchwork_geom::Aabb],
        cols: &[[f64; 2]],
        rows: &[[f64; 2]],
    ) -> Option<Flat> {
        // The indices of the intervals that meet [a, b]: a run of them, found by bisection.
        type Span = fn(&[[f64; 2]], f64, f64) -> std::ops::Range<usize>;
        fn rising(v: &[[f64; 2]], a: f64, b: f64) -> std::ops::Range<usize> {
            v.partition_point(|c| c[1] < a)..v.partition_point(|c| c[0] <= b)
        }
        fn falling(v: &[[f64; 2]], a: f64, b: f64) -> std::ops::Range<usize> {
            v.partition_point(|c| c[0] > b)..v.partition_point(|c| c[1] >= a)
        }
        let order = |v: &[[f64; 2]]| -> Option<Span> {
            let pairs = || v.windows(2);
            if pairs().all(|w| w[0][0] <= w[1][0] && w[0][1] <= w[1][1]) {
                Some(rising)
            } else if pairs().all(|w| w[0][0] >= w[1][0] && w[0][1] >= w[1][1]) {
                Some(falling)
            } else {
                None
            }
        };
        let (x_span, y_span) = (order(cols)?, order(rows)?);
        let spans: Vec<_> = windows
            .iter()
            .map(|a| {
                (
                    x_span(cols, a.min[0], a.max[0]),
                    y_span(rows, a.min[1], a.max[1]),
                )
            })
            .collect();
        let w = cols.len();
        let mut offsets = vec![0u32; w * rows.len() + 1];
        for (xs, ys) in &spans {
            for j in ys.clone() {
                for i in xs.clone() {
                    offsets[j * w + i + 1] += 1;
                }
            }
        }
        for b in 1..offsets.len() {
            offsets[b] += offsets[b - 1];
        }
        let mut next = offsets.clone();
        let mut entries = vec![0u32; *offsets.last().expect("one offset at least") as usize];
        for (k, (xs, ys)) in spans.into_iter().enumerate() {
            for j in ys {
                for i in xs.clone() {
                    let at = &mut next[j * w + i];
                    entries[*at as usize] = k as u32;
                    *at += 1;
                }
            }
        }
        Some(Flat { offsets, entries })
    }

    /// Bins given one by one.
    pub fn of(bins: &[Vec<u32>]) -> Flat {
        let mut f = Flat {
            offsets: Vec::with_capacity(bins.len() + 1),
            entries: Vec::with_capacity(bins.iter().map(Vec::len).sum()),
        };
        f.offsets.push(0);
        for b in bins {
            f.entries.extend_from_slice(b);
            f.offsets.push(f.entries.len() as u32);
        }
        f
    }
}

/// Patch indices per box, those whose window meets it, in ascending order: [`bin`] for boxes
/// of any size (the GPU bins blocks of blocks, and each block picks its own from those).
pub fn bin_boxes(
    patches: &[ResolvedPatch],
    blocks: &[Option<patchwork_geom::Aabb>],
) -> Vec<Vec<u32>> {
    // Testing every patch against every block cost a 2048² tile of 15,000 patches 0.5 s:
    // buckets narrow each block's test to the patches near it.
    let buckets = Buckets::new(patches);
    blocks
        .par_iter()
        .map(|b| match b {
            Some(b) => {
                let mut near = buckets.near(b);
                near.retain(|&k| patches[k as usize].reach().intersects(b));
                near
            }
            None => Vec::new(),
        })
        .collect()
}

/// Patch indices on a uniform grid of cells over the patches' windows.
struct Buckets {
    min: [f64; 2],
    /// Cells per world unit, along each axis.
    scale: [f64; 2],
    side: usize,
    cells: Vec<Vec<u32>>,
}

impl Buckets {
    fn new(patches: &[ResolvedPatch]) -> Self {
        let side = ((patches.len() as f64).sqrt().ceil() as usize).clamp(1, 256);
        let bounds = patches
            .iter()
            .map(ResolvedPatch::reach)
            .reduce(|a, b| a.union(&b));
        let mut b = Buckets {
            min: [0.0; 2],
            scale: [0.0; 2],
            side,
            cells: vec![Vec::new(); side * side],
        };
        let Some(bounds) = bounds else {
            return b;
        };
        b.min = bounds.min;
        // A zero-wide extent puts everything in the first cell along that axis.
        let per = |w: f64| if w > 0.0 { side as f64 / w } else { 0.0 };
        b.scale = [per(bounds.width()), per(bounds.height())];
        for (k, p) in patches.iter().enumerate() {
            let ([i0, i1], [j0, j1]) = b.span(&p.reach());
            for j in j0..=j1 {
                for i in i0..=i1 {
                    b.cells[j * side + i].push(k as u32);
                }
            }
        }
        b
    }

    /// The first and last cell along x and along y that a box reaches, clamped to the grid.
    fn span(&self, a: &patchwork_geom::Aabb) -> ([usize; 2], [usize; 2]) {
        let cell = |v: f64, axis: usize| {
            let c = ((v - self.min[axis]) * self.scale[axis]).floor();
            c.clamp(0.0, (self.side - 1) as f64) as usize
        };
        (
            [cell(a.min[0], 0), cell(a.max[0], 0)],
            [cell(a.min[1], 1), cell(a.max[1], 1)],
        )
    }

    /// Every patch in a cell the box reaches, ascending and each once: a superset of those
    /// whose window meets it, since a cell holds every patch whose window reaches the cell.
    fn near(&self, a: &patchwork_geom::Aabb) -> Vec<u32> {
        let ([i0, i1], [j0, j1]) = self.span(a);
        let mut out = Vec::new();
        for j in j0..=j1 {
            for i in i0..=i1 {
                out.extend_from_slice(&self.cells[j * self.side + i]);
            }
        }
        out.sort_unstable();
        out.dedup();
        out
    }
}

/// Heights at every point of the grid, NaN where no valid kernel reaches.
pub fn resample(set: &PatchSet, grid: &SampleGrid) -> Vec<f32> {
    resample_until(set, grid, &Cancel::default()).expect("never cancelled")
}

/// [`resample`], checking `cancel` before every row; None once it is set.
pub fn resample_until(set: &PatchSet, grid: &SampleGrid, cancel: &Cancel) -> Option<Vec<f32>> {
    let mut out = Vec::new();
    resample_bands(set, grid, grid.height, cancel, &mut |_, band| {
        out = band;
        true
    })?;
    Some(out)
}

/// [`resample`] in bands of `rows` rows (rounded up to whole blocks), top first: `sink` gets
/// each band's first row and heights as soon as they are done, so that a caller can send one
/// while the next is worked out. None once `cancel` is set or `sink` says stop.
pub fn resample_bands(
    set: &PatchSet,
    grid: &SampleGrid,
    rows: usize,
    cancel: &Cancel,
    sink: &mut dyn FnMut(usize, Vec<f32>) -> bool,
) -> Option<()> {
    let rows = rows.max(1).div_ceil(BLOCK) * BLOCK;
    // Columns out of order go point by point: the pass by columns finds a patch's columns
    // by bisection.
    let pointwise;
    let grid = match &grid.axes {
        Some(a) if !a.xs.windows(2).all(|w| w[0] <= w[1]) => {
            pointwise = grid.clone().pointwise();
            &pointwise
        }
        _ => grid,
    };
    let bins = bin(&set.patches, grid);
    // Where each sample lies in the planes of surveys of other CRSs, once for the tile.
    let planes = set.positions(grid);
    // A north-up tile: what a patch makes of a column's x is worked out once for the tile,
    // and of a row's y once for the row, where a point at a time works both out for every
    // patch at every sample. The answer is the same, term for term (tested).
    let columns = columns_of(set, grid);
    for j0 in (0..grid.height).step_by(rows) {
        let mut out = vec![f32::NAN; grid.width * (grid.height - j0).min(rows)];
        match (&grid.axes, &columns) {
            (Some(axes), Some(columns)) => {
                by_axes(set, axes, columns, &bins, &planes, j0, &mut out, cancel)
            }
            _ => by_points(set, grid, &bins, &planes, j0, &mut out, cancel),
        }
        if cancel.is_cancelled() || !sink(j0, out) {
            return None;
        }
    }
    Some(())
}

/// For a north-up tile, what each separable patch makes of its columns.
fn columns_of(set: &PatchSet, grid: &SampleGrid) -> Option<Vec<Option<Columns>>> {
    grid.axes.as_ref().map(|axes| {
        set.patches
            .par_iter()
            .map(|p| p.separable().then(|| Columns::new(p, &axes.xs)))
            .collect()
    })
}

/// The rows from `j0` (the first of a block) that `out` holds, one point at a time.
fn by_points(
    set: &PatchSet,
    grid: &SampleGrid,
    bins: &[Vec<u32>],
    planes: &[Vec<[f64; 2]>],
    j0: usize,
    out: &mut [f32],
    cancel: &Cancel,
) {
    let bx = grid.width.div_ceil(BLOCK);
    // Listed here, once, rather than by whichever thread first needs it.
    let list = grid.list();
    out.par_chunks_mut(grid.width)
        .enumerate()
        .for_each(|(dj, row)| {
            if cancel.is_cancelled() {
                return;
            }
            let j = j0 + dj;
            let pts = &list[j * grid.width..(j + 1) * grid.width];
            let mut tiers = Vec::with_capacity(8);
            for (i, (o, &p)) in row.iter_mut().zip(pts).enumerate() {
                if p[0].is_nan() {
                    continue;
                }
                let bin = &bins[(j / BLOCK) * bx + i / BLOCK];
                let at = j * grid.width + i;
                *o = blend_by(set, bin, &mut tiers, |k| {
                    let q = &set.patches[k];
                    q.at(in_plane(q, p, planes, at))
                });
            }
        });
}

/// A sample's position in a patch's plane: `p` itself in the store's, else where `planes`
/// carried sample `at` of the grid.
#[inline(always)]
fn in_plane(q: &ResolvedPatch, p: [f64; 2], planes: &[Vec<[f64; 2]>], at: usize) -> [f64; 2] {
    match q.plane {
        0 => p,
        k => planes[k as usize - 1][at],
    }
}

/// The rows from `j0` (the first of a block) that `out` holds, of a north-up tile.
#[allow(clippy::too_many_arguments)]
fn by_axes(
    set: &PatchSet,
    axes: &super::Axes,
    columns: &[Option<Columns>],
    bins: &[Vec<u32>],
    planes: &[Vec<[f64; 2]>],
    j0: usize,
    out: &mut [f32],
    cancel: &Cancel,
) {
    let width = axes.xs.len();
    let bx = width.div_ceil(BLOCK);
    out.par_chunks_mut(width * BLOCK)
        .enumerate()
        .for_each(|(db, band)| {
            if cancel.is_cancelled() {
                return;
            }
            let b = j0 / BLOCK + db;
            // The patches of this band of blocks, and where each one's row half is kept.
            let bins = &bins[b * bx..((b + 1) * bx).min(bins.len())];
            let mut near: Vec<u32> = bins.iter().flatten().copied().collect();
            near.sort_unstable();
            near.dedup();
            let mut slot = vec![u32::MAX; set.patches.len()];
            for (n, &k) in near.iter().enumerate() {
                slot[k as usize] = n as u32;
            }
            let mut rows = vec![AxisHit::default(); near.len()];
            let (mut live, mut ranks, mut sums) = (Vec::new(), Vec::new(), Vec::new());
            let mut tiers = Vec::with_capacity(8);
            // The blocks that one patch serves alone, their columns laid out once for all
            // the band's rows.
            let alone: Vec<Option<Alone>> = bins
                .iter()
                .enumerate()
                .map(|(ib, bin)| Alone::of(set, columns, bin, ib * BLOCK, width))
                .collect();
            for (dj, row) in band.chunks_mut(width).enumerate() {
                if cancel.is_cancelled() {
                    return;
                }
                let row_j = b * BLOCK + dj;
                let y = axes.ys[row_j];
                for (h, &k) in rows.iter_mut().zip(&near) {
                    if columns[k as usize].is_some() {
                        *h = set.patches[k as usize].along(1, y);
                    }
                }
                for (ib, (cells, bin)) in row.chunks_mut(BLOCK).zip(bins).enumerate() {
                    if let Some(one) = &alone[ib] {
                        let left =
                            one.fill(&set.patches[one.k], &rows[slot[one.k] as usize], cells);
                        if let Some(left) = left {
                            // The samples the patch does not serve alone (off its kernel, or
                            // over a void), each blended as a point is.
                            let i0 = ib * BLOCK;
                            for d in (0..cells.len()).filter(|d| left & (1 << d) != 0) {
                                let i = i0 + d;
                                cells[d] = blend_by(set, bin, &mut tiers, |k| {
                                    let p = &set.patches[k];
                                    match &columns[k] {
                                        Some(c) => p.at_axes(&c.at(i), &rows[slot[k] as usize]),
                                        None => {
                                            let at = row_j * width + i;
                                            p.at(in_plane(p, [axes.xs[i], y], planes, at))
                                        }
                                    }
                                });
                            }
                            continue;
                        }
                    }
                    // The block's patches that can reach this row, in the bin's order: the
                    // others answer None at every sample of it.
                    live.clear();
                    live.extend(bin.iter().copied().filter(|&k| {
                        columns[k as usize].is_none() || rows[slot[k as usize] as usize].reaches
                    }));
                    // A patch at a time across the block's samples, each sample's sums taken
                    // in the bin's order as blend_by takes them: the same sums, with the
                    // patch's lookups made once for the block rather than once per sample.
                    // Fallback patches sum by rank, the block's ranks in ascending order.
                    ranks.clear();
                    ranks.extend(
                        live.iter()
                            .map(|&k| &set.patches[k as usize])
                            .filter(|p| p.fallback)
                            .map(|p| p.rank),
                    );
                    ranks.sort_unstable();
                    ranks.dedup();
                    let i0 = ib * BLOCK;
                    if set.blend == Blend::Accurate {
                        // A patch at a time in the set's order, each sample laid over as
                        // `over_by` lays it; the block stops at the first patch no sample
                        // of it can take any more.
                        let mut over = [Over::default(); BLOCK];
                        let over = &mut over[..cells.len()];
                        for &k in &live {
                            let p = &set.patches[k as usize];
                            let (tier, holds) = (p.tier(), p.closed != 0);
                            if !over.iter().any(|o| o.open(tier)) {
                                break;
                            }
                            let samples = over.iter_mut().zip(i0..i0 + cells.len());
                            match &columns[k as usize] {
                                Some(c) => {
                                    let yh = &rows[slot[k as usize] as usize];
                                    for (o, i) in samples.filter(|(o, _)| o.open(tier)) {
                                        if let Some((w, h)) = p.at_axes(&c.at(i), yh) {
                                            o.add(tier, w, h.z, h.covered, holds);
                                        }
                                    }
                                }
                                None => {
                                    for (o, i) in samples.filter(|(o, _)| o.open(tier)) {
                                        let at = row_j * width + i;
                                        let q = in_plane(p, [axes.xs[i], y], planes, at);
                                        if let Some((w, h)) = p.at(q) {
                                            o.add(tier, w, h.z, h.covered, holds);
                                        }
                                    }
                                }
                            }
                        }
                        for (c, o) in cells.iter_mut().zip(over.iter()) {
                            *c = o.height();
                        }
                        continue;
                    }
                    let add = |k: u32, sums: &mut [Tier; BLOCK]| {
                        let p = &set.patches[k as usize];
                        let sums = sums.iter_mut().zip(i0..i0 + cells.len());
                        match &columns[k as usize] {
                            Some(c) => {
                                let yh = &rows[slot[k as usize] as usize];
                                for (t, i) in sums {
                                    if let Some((w, h)) = p.at_axes(&c.at(i), yh) {
                                        t.add(w, h.z, h.covered);
                                    }
                                }
                            }
                            None => {
                                for (t, i) in sums {
                                    let at = row_j * width + i;
                                    let q = in_plane(p, [axes.xs[i], y], planes, at);
                                    if let Some((w, h)) = p.at(q) {
                                        t.add(w, h.z, h.covered);
                                    }
                                }
                            }
                        }
                    };
                    if ranks.is_empty() {
                        let mut cut = [Tier::default(); BLOCK];
                        for &k in &live {
                            add(k, &mut cut);
                        }
                        for (o, t) in cells.iter_mut().zip(&cut) {
                            *o = t.height();
                        }
                        continue;
                    }
                    sums.clear();
                    sums.resize(ranks.len() + 1, [Tier::default(); BLOCK]);
                    for &k in &live {
                        let p = &set.patches[k as usize];
                        let tier = if p.fallback {
                            1 + ranks.partition_point(|&r| r < p.rank)
                        } else {
                            0
                        };
                        add(k, &mut sums[tier]);
                    }
                    let (cut, ranked) = sums.split_first().expect("the cut's sums");
                    for (di, o) in cells.iter_mut().enumerate() {
                        *o = settle(cut[di], ranks.iter().zip(ranked).map(|(&r, t)| (r, &t[di])));
                    }
                }
            }
        });
}

/// A block that one patch serves alone, with what the patch makes of the block's columns
/// laid out by column, so that a row of the block is one short loop over the level's samples.
///
/// Formula 1 at a point that patch k covers gives k's height alone when k is the only patch
/// of the cut in the block, or when the block has no patch of the cut and k is its one
/// fallback patch of the best rank: the other fallback patches are of worse rank, and a
/// point covered by a better tier never adds a worse one. The sums are then w·z and w,
/// divided as the blend divides them, so the height is the blend's to the bit.
///
/// The accurate blend gives k's height alone wherever k's kernel holds the point with a
/// weight of exactly 1 (all of it but the ramps inside closed sides) and k is first of the
/// block's patches in the set's order: it takes the whole point, w = 1 and
/// (0 + 1·z) / (0 + 1) = z as `Over` forms it.
struct Alone {
    /// The patch.
    k: usize,
    /// Per column: the cell, the fraction across it and the weight along x.
    cell: [u32; BLOCK],
    frac: [f64; BLOCK],
    weight: [f64; BLOCK],
    /// The columns in the patch's kernel and window (for the accurate blend, at weight 1), a
    /// bit each.
    inside: u16,
    /// Columns in use: the block's, fewer at the tile's right edge.
    n: usize,
}

impl Alone {
    /// The block's one patch, if it has one as above that is separable and whose kernel and
    /// window hold all but [`LEFT_MOST`] columns of the block at most.
    fn of(
        set: &PatchSet,
        columns: &[Option<Columns>],
        bin: &[u32],
        i0: usize,
        width: usize,
    ) -> Option<Alone> {
        let k = alone_in(set, bin)?;
        let c = columns[k].as_ref()?;
        let n = (i0 + BLOCK).min(width) - i0;
        let mut one = Alone {
            k,
            cell: [0; BLOCK],
            frac: [0.0; BLOCK],
            weight: [0.0; BLOCK],
            inside: 0,
            n,
        };
        // In the accurate blend a patch takes a whole point only where its weight is 1: not
        // on the ramp inside a closed side of its kernel.
        let p = &set.patches[k];
        for d in 0..n {
            let h = c.at(i0 + d);
            if h.reaches && h.covered && (!p.accurate || h.weight == 1.0) {
                (one.cell[d], one.frac[d], one.weight[d]) = (h.cell, h.frac, h.weight);
                one.inside |= 1 << d;
            }
        }
        // A sample left to the blend costs it a point's lookups of every patch, several
        // times what the block's own loop costs a sample: with more than a few left, the
        // block's loop is the faster.
        (one.inside.count_ones() as usize + LEFT_MOST >= n).then_some(one)
    }

    /// Whether the patch serves every column of the block.
    fn whole(&self) -> bool {
        self.inside == ((1u32 << self.n) - 1) as u16
    }

    /// One row of the block into `out`, `y` what the patch makes of the row's y. None where
    /// the row lies off the patch's kernel, or for the accurate blend on its ramp inside a
    /// closed side: the whole row is the blend's to make. Otherwise the samples it left for
    /// the blend, a bit each: those off the kernel, or over a void.
    #[inline]
    fn fill(&self, p: &ResolvedPatch, y: &AxisHit, out: &mut [f32]) -> Option<u16> {
        let Surface::Bilinear(level) = &p.surface else {
            unreachable!("only bilinear patches are separable")
        };
        if !(y.reaches && y.covered) || (p.accurate && y.weight != 1.0) {
            return None;
        }
        let g = &level.grid;
        let r = y.cell as usize * g.cols;
        let (top, bottom) = (
            &g.samples[r..r + g.cols],
            &g.samples[r + g.cols..r + 2 * g.cols],
        );
        let (fy, wy) = (y.frac, y.weight);
        let mut left = !self.inside & (((1u32 << self.n) - 1) as u16);
        for (d, o) in out[..self.n].iter_mut().enumerate() {
            if self.inside & (1 << d) == 0 {
                continue;
            }
            let c = self.cell[d] as usize;
            let fx = self.frac[d];
            let (z00, z10) = (top[c] as f64, top[c + 1] as f64);
            let (z01, z11) = (bottom[c] as f64, bottom[c + 1] as f64);
            let upper = z00 + (z10 - z00) * fx;
            let lower = z01 + (z11 - z01) * fx;
            let z = upper + (lower - upper) * fy;
            // The weight as `ResolvedPatch::at_axes` makes it (its last factor is 1 for a
            // bilinear patch), and the sums from zero as a tier takes them.
            let w = self.weight[d] * wy * p.norm;
            if z.is_nan() || w <= 0.0 || w.is_nan() {
                left |= 1 << d;
            }
            *o = ((0.0 + w * z) / (0.0 + w)) as f32;
        }
        Some(left)
    }
}

/// Most columns of a block that [`Alone`] leaves to the blend of each point.
const LEFT_MOST: usize = 4;

/// The patch that serves a block alone wherever it covers it (see [`Alone`]): the bin's one
/// patch of the cut, or with none, its one fallback patch of the best rank.
fn alone_in(set: &PatchSet, bin: &[u32]) -> Option<usize> {
    if set.blend == Blend::Accurate {
        return bin.first().map(|&k| k as usize);
    }
    let mut cut = bin.iter().filter(|&&k| !set.patches[k as usize].fallback);
    if let Some(&k) = cut.next() {
        return cut.next().is_none().then_some(k as usize);
    }
    let best = bin.iter().map(|&k| set.patches[k as usize].rank).min()?;
    let mut of_best = bin
        .iter()
        .filter(|&&k| set.patches[k as usize].rank == best);
    let k = *of_best.next()?;
    of_best.next().is_none().then_some(k as usize)
}

/// How many of a tile's blocks one patch serves whole (it covers every column of the block,
/// so that the resampler's short path takes each row it covers), and how many blocks it has.
pub fn blocks_alone(set: &PatchSet, grid: &SampleGrid) -> (usize, usize) {
    let bins = bin(&set.patches, grid);
    let Some(columns) = columns_of(set, grid) else {
        return (0, bins.len());
    };
    let bx = grid.width.div_ceil(BLOCK);
    let alone = bins
        .iter()
        .enumerate()
        .filter(|(b, bin)| {
            Alone::of(set, &columns, bin, (b % bx) * BLOCK, grid.width).is_some_and(|a| a.whole())
        })
        .count();
    (alone, bins.len())
}

/// What one separable patch makes of the columns of a tile it may reach: the columns whose x
/// lies within a column's width of its window, each with its [`AxisHit`].
struct Columns {
    first: usize,
    hits: Vec<AxisHit>,
}

impl Columns {
    fn new(p: &ResolvedPatch, xs: &[f64]) -> Self {
        // Binning already takes a patch only where its window's bounds meet a block; a
        // column's width of slack more keeps every x whose rounding could still reach.
        let pad = if xs.len() > 1 {
            (xs[1] - xs[0]).abs()
        } else {
            f64::INFINITY
        };
        let (lo, hi) = (p.window_aabb.min[0] - pad, p.window_aabb.max[0] + pad);
        let first = xs.partition_point(|&x| x < lo);
        let last = xs.partition_point(|&x| x <= hi);
        Columns {
            first,
            hits: xs[first..last.max(first)]
                .iter()
                .map(|&x| p.along(0, x))
                .collect(),
        }
    }

    #[inline(always)]
    fn at(&self, i: usize) -> AxisHit {
        i.checked_sub(self.first)
            .and_then(|k| self.hits.get(k))
            .copied()
            .unwrap_or_default()
    }
}

/// Sums of one tier at one point.
#[derive(Clone, Copy, Default)]
struct Tier {
    sum: f64,
    wsum: f64,
    covered: bool,
    /// Some patch of it reaches the point.
    present: bool,
}

impl Tier {
    #[inline]
    fn add(&mut self, w: f64, z: f64, covered: bool) {
        self.sum += w * z;
        self.wsum += w;
        self.covered |= covered;
        self.present = true;
    }

    #[inline]
    fn merge(&mut self, o: &Tier) {
        self.sum += o.sum;
        self.wsum += o.wsum;
        self.covered |= o.covered;
    }

    fn height(&self) -> f32 {
        if self.covered && self.wsum > 0.0 {
            (self.sum / self.wsum) as f32
        } else {
            f32::NAN
        }
    }
}

/// The accurate blend's sums at one point: patches laid over one another in the set's order,
/// each taking its weight's share of what the better ones left (`rest`).
#[derive(Clone, Copy)]
struct Over {
    /// Σ a·z and Σ a, a the share each patch took.
    sum: f64,
    asum: f64,
    /// What is left for the patches after: 1 − Σ a.
    rest: f64,
    /// The tier of the first patch whose kernel holds the point, u32::MAX until one does:
    /// worse tiers no longer count, as in Formula 1's tiers.
    stop: u32,
    /// The height of the first patch with a closed side ([`ResolvedPatch::closed`]) whose
    /// kernel holds the point: on the ramp inside that side it weighs less than 1, and it
    /// takes what its tier leaves, where its neighbour of the same samples would beyond
    /// the edge. NaN until one does (a height is never NaN).
    hold: f64,
}

impl Default for Over {
    fn default() -> Self {
        Over {
            sum: 0.0,
            asum: 0.0,
            rest: 1.0,
            stop: u32::MAX,
            hold: f64::NAN,
        }
    }
}

impl Over {
    /// Whether a patch of `tier` can still add anything. Patches come in ascending tier, and
    /// `rest` only falls, so once this is false it is false for every later patch.
    #[inline(always)]
    fn open(&self, tier: u32) -> bool {
        self.rest > 0.0 && tier <= self.stop
    }

    /// Lays a patch of weight `w` and height `z` under those before it; its share. `holds`:
    /// the patch has a closed side, so where it covers the point it takes what its tier
    /// leaves ([`Self::hold`]).
    #[inline(always)]
    fn add(&mut self, tier: u32, w: f64, z: f64, covered: bool, holds: bool) -> f64 {
        let a = w * self.rest;
        self.sum += a * z;
        self.asum += a;
        self.rest -= a;
        if covered {
            self.stop = self.stop.min(tier);
            if holds && self.hold.is_nan() {
                self.hold = z;
            }
        }
        a
    }

    fn height(&self) -> f32 {
        let (mut sum, mut asum) = (self.sum, self.asum);
        if self.rest > 0.0 && !self.hold.is_nan() {
            sum += self.rest * self.hold;
            asum += self.rest;
        }
        if self.stop != u32::MAX && asum > 0.0 {
            (sum / asum) as f32
        } else {
            f32::NAN
        }
    }
}

/// The accurate blend at one point, where `at(k)` is patch k's weight and answer there; with
/// the index of the patch that took the largest share, the first of equals.
#[inline(always)]
fn over_by(
    set: &PatchSet,
    bin: &[u32],
    at: impl Fn(usize) -> Option<(f64, Hit)>,
) -> (f32, Option<u32>) {
    let mut o = Over::default();
    let mut most = (0.0, None);
    // The patch that takes what its tier leaves, and its own share.
    let mut holder = None;
    for &k in bin {
        let q = &set.patches[k as usize];
        let tier = q.tier();
        if !o.open(tier) {
            break;
        }
        if let Some((w, h)) = at(k as usize) {
            let holds = q.closed != 0;
            let first = o.hold.is_nan();
            let a = o.add(tier, w, h.z, h.covered, holds);
            if first && !o.hold.is_nan() {
                holder = Some((k, a));
            }
            if a > most.0 {
                most = (a, Some(k));
            }
        }
    }
    if let Some((k, a)) = holder {
        if a + o.rest > most.0 {
            most = (a + o.rest, Some(k));
        }
    }
    let z = o.height();
    (z, if z.is_nan() { None } else { most.1 })
}

/// [`resample_until`] of `grid`, and for each sample the patch that weighs most in its height:
/// of the patches [`blend_by`] counts there (the cut's where one of them covers it, else the
/// cut's and the fallback ranks up to the best that covers it), the one of the largest
/// weight; None where the height is nodata. What a client asking "where does this height come
/// from" is told. The heights are those of [`resample_until`], bit for bit: each sample's
/// patches are asked once, in bin order, and their answers blended by the same [`blend_by`].
/// For the accurate blend, the patch that took the largest share ([`over_by`]). None once
/// `cancel` is set.
pub fn resample_serving(
    set: &PatchSet,
    grid: &SampleGrid,
    cancel: &Cancel,
) -> Option<(Vec<f32>, Vec<Option<u32>>)> {
    let bins = bin(&set.patches, grid);
    let planes = set.positions(grid);
    let bx = grid.width.div_ceil(BLOCK);
    let list = grid.list();
    type Scratch = (Vec<Option<(f64, Hit)>>, Vec<(u32, Tier)>);
    let out: Vec<(f32, Option<u32>)> = (0..grid.width * grid.height)
        .into_par_iter()
        .map_init(
            || -> Scratch { (Vec::new(), Vec::with_capacity(8)) },
            |(answers, tiers), at| {
                let p = list[at];
                if p[0].is_nan() || cancel.is_cancelled() {
                    return (f32::NAN, None);
                }
                let (i, j) = (at % grid.width, at / grid.width);
                let bin = &bins[(j / BLOCK) * bx + i / BLOCK];
                if set.blend == Blend::Accurate {
                    return over_by(set, bin, |k| {
                        let q = &set.patches[k];
                        q.at(in_plane(q, p, &planes, at))
                    });
                }
                answers.clear();
                answers.extend(bin.iter().map(|&k| {
                    let q = &set.patches[k as usize];
                    q.at(in_plane(q, p, &planes, at))
                }));
                // `blend_by` asks each patch of the bin once, in order.
                let next = std::cell::Cell::new(0);
                let z = blend_by(set, bin, tiers, |_| {
                    let n = next.get();
                    next.set(n + 1);
                    answers[n]
                });
                if z.is_nan() {
                    return (z, None);
                }
                let hits = || {
                    bin.iter().zip(answers.iter()).filter_map(|(&k, a)| {
                        let (w, h) = (*a)?;
                        let q = &set.patches[k as usize];
                        Some((k, w, h.covered, q.fallback.then_some(q.rank)))
                    })
                };
                let cut_covers = hits().any(|h| h.3.is_none() && h.2);
                let best = if cut_covers {
                    None
                } else {
                    hits().filter(|h| h.2).filter_map(|h| h.3).min()
                };
                let served = hits()
                    .filter(|h| match (h.3, best) {
                        (None, _) => true,
                        (Some(r), Some(b)) => r <= b,
                        (Some(_), None) => false,
                    })
                    .filter(|h| h.1 > 0.0)
                    .max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0)))
                    .map(|h| h.0);
                (z, served)
            },
        )
        .collect();
    if cancel.is_cancelled() {
        return None;
    }
    Some(out.into_iter().unzip())
}

/// The set's blend at one point of the store's plane.
pub fn blend(set: &PatchSet, bin: &[u32], p: [f64; 2]) -> f32 {
    let planes: Vec<Vec<[f64; 2]>> = set
        .planes
        .iter()
        .map(|r| vec![r.at(p).unwrap_or([f64::NAN; 2])])
        .collect();
    blend_by(set, bin, &mut Vec::new(), |k| {
        let q = &set.patches[k];
        q.at(in_plane(q, p, &planes, 0))
    })
}

/// The set's blend at one point (Formula 1, or [`over_by`]), where `at(k)` is patch k's weight
/// and answer there, with `tiers`
/// as scratch space for the fallback ranks that reach it. Always inlined: `at` is the inner
/// loop of every tile, and called through a function it cost a third of a tile's time.
#[inline(always)]
fn blend_by(
    set: &PatchSet,
    bin: &[u32],
    tiers: &mut Vec<(u32, Tier)>,
    at: impl Fn(usize) -> Option<(f64, Hit)>,
) -> f32 {
    if set.blend == Blend::Accurate {
        return over_by(set, bin, at).0;
    }
    let mut cut = Tier::default();
    if !set.has_fallback {
        for &k in bin {
            if let Some((w, h)) = at(k as usize) {
                cut.add(w, h.z, h.covered);
            }
        }
        return cut.height();
    }
    tiers.clear();
    for &k in bin {
        let q = &set.patches[k as usize];
        let Some((w, h)) = at(k as usize) else {
            continue;
        };
        if !q.fallback {
            cut.add(w, h.z, h.covered);
            continue;
        }
        match tiers.iter_mut().find(|t| t.0 == q.rank) {
            Some(t) => t.1.add(w, h.z, h.covered),
            None => {
                let mut t = Tier::default();
                t.add(w, h.z, h.covered);
                tiers.push((q.rank, t));
            }
        }
    }
    tiers.sort_unstable_by_key(|t| t.0);
    settle(cut, tiers.iter().map(|(r, t)| (*r, t)))
}

/// A point's height from the sums of the cut's patches and of each fallback rank's, ranks in
/// ascending order. Where the cut's patches cover the point they alone count; elsewhere the
/// best rank that covers it, and every better one that reaches it, are added to them in rank
/// order, so that every path adds them in the same order.
#[inline]
fn settle<'a>(mut cut: Tier, ranked: impl Iterator<Item = (u32, &'a Tier)> + Clone) -> f32 {
    if cut.covered {
        return cut.height();
    }
    let Some(best) = ranked
        .clone()
        .filter(|(_, t)| t.covered)
        .map(|(r, _)| r)
        .min()
    else {
        return f32::NAN;
    };
    for (_, t) in ranked.filter(|(r, t)| t.present && *r <= best) {
        cut.merge(t);
    }
    cut.height()
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwork_geom::Aabb;

    #[test]
    fn a_cancelled_resampling_stops_and_says_so() {
        let roi = Aabb {
            min: [0.0, 0.0],
            max: [1.0, 1.0],
        };
        let grid = SampleGrid::uniform(&roi, 64, 64);
        let set = PatchSet::default();
        assert_eq!(
            resample_until(&set, &grid, &Cancel::default()).map(|h| h.len()),
            Some(64 * 64)
        );
        let cancel = Cancel::default();
        cancel.cancel();
        assert!(resample_until(&set, &grid, &cancel).is_none());
    }
}
