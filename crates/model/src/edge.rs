//! Edge patches: the surface where no single survey has a whole cell.
//!
//! A survey's own patches interpolate its *valid cells*, cells whose four corners hold data.
//! That leaves out three kinds of ground that a user of the data expects answered:
//!
//! - the outer half pixel of every survey, which a GDAL raster covers (pixel-is-area);
//! - valid samples with a void beside them: the edges of holes, isolated samples, cells with
//!   three valid corners;
//! - the cell between two tiles of one mosaic, whose corners come from different files.
//!
//! Edge patches serve exactly those cells. They are built per tile of a *lattice* (see
//! [`super::lattice`]) from the union of the samples every survey on that lattice has there,
//! so a seam between tiles is interpolated across as GDAL does on a mosaic, and they follow
//! seed 004's void vertices:
//!
//! - a void corner gets a height from its valid neighbours (the mean of its valid
//!   4-neighbours, else of its valid diagonal ones), so heights never jump across a cell edge;
//! - a cell with four valid corners (a seam) is bilinear; any other cell is split into two
//!   triangles, along the diagonal that keeps a cell's three valid corners in one triangle, so
//!   that triangle is the plane through them;
//! - a point is data when its nearest sample is (the pixel it falls in): nothing is made up
//!   more than half a pixel from a valid sample, and an edge patch says nothing outside its
//!   surveys' pixels, so it never pulls another survey's data towards its own;
//! - in Formula 1 the patch's weight is scaled by a ramp that is 1 half a pixel inside the
//!   data and falls to 0 at the pixel edge (twice the distance to the nearest void pixel), so
//!   that where the pixels of two surveys overlap the blend passes smoothly from one to the
//!   other.
//!
//! An edge patch's error is the largest ε of the samples it uses, plus, in a cell with a void
//! corner, the largest height change over one cell at its valid corners: what the ground can
//! do within the cell the patch extrapolates into (seed 004's horizontal error, in metres).
//!
//! Which edge patches exist, and what they hold, is a function of the set of surveys on a
//! lattice, so order independence and exact retirement carry over: the terrain recomputes the
//! tiles a change can touch and swaps the patches that changed.

use super::grid::{Georef, Grid, Shape, Window};
use super::ids::{hash64, PatchId, SurveyId};
use super::lattice::tile_of;
use super::patch::{CellRect, PatchLayout};
use super::survey::SurveyMeta;
use patchwork_geom::on_line;
use std::sync::Arc;

/// Kernels per side of an edge patch's tile. Edge cells are thin (a survey's outer ring, the
/// rims of its holes), so a tile of several kernels holds few of them, and its grid is cut
/// down to where they are; fewer, larger edge patches keep a cut's patch count near what the
/// surveys' own patches need.
pub const EDGE_TILE: usize = 4;

/// The side, in lattice cells, of the tiles edge patches are cut on.
pub fn tile_side(layout: &PatchLayout) -> usize {
    layout.kernel * EDGE_TILE
}

/// The sample holds data (it is not a filled void).
pub const VALID: u8 = 1;
/// The cell whose top-left corner this sample is belongs to the edge patch.
pub const EDGE_CELL: u8 = 2;

/// The samples an edge patch evaluates: the corners of its edge cells on its window of the
/// lattice, voids filled where a valid sample is near, with a flag byte each.
///
/// Only an edge cell's four corners are ever read, and edge cells are thin (a seam between
/// abutting tiles is one cell wide), so the grid keeps those samples and a bit a sample saying
/// which they are: on a mosaic's tile a tenth of the window's samples, and a fifth of the
/// memory the whole window took.
#[derive(Clone, Debug, PartialEq)]
pub struct EdgeGrid {
    /// Samples per row of the window.
    pub cols: usize,
    /// Rows of samples.
    pub rows: usize,
    /// A bit a sample of the window, row-major, 64 to a word: whether the grid keeps it.
    kept: Vec<u64>,
    /// How many samples the words before each block of [`RANK_BLOCK`] words of `kept` keep.
    rank: Vec<u32>,
    /// The kept samples' heights, in row-major order: filled at void corners; NaN where
    /// nothing is near.
    heights: Vec<f32>,
    /// The kept samples' [`VALID`] and [`EDGE_CELL`] bits.
    flags: Vec<u8>,
    /// The largest height change between 4-neighbours of the whole window as it was built,
    /// filled voids included, in metres: what a reprojection's horizontal error moves a
    /// height by at most, a cell of it at a time.
    pub slope: f64,
    /// The georeference of the member with the smallest id, moved to the grid's sample (0, 0).
    pub georef: Georef,
}

/// Words of an edge grid's kept bits a count of the samples before them covers: a lookup
/// counts the bits of at most this many more words, and the counts take an eighth of what one
/// a word would.
const RANK_BLOCK: usize = 8;

/// Why the parts of an edge grid do not make one.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BadEdgeGrid(pub String);

impl std::fmt::Display for BadEdgeGrid {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "edge grid: {}", self.0)
    }
}

impl std::error::Error for BadEdgeGrid {}

impl EdgeGrid {
    /// The grid of a whole window of `cols × rows` samples: it keeps the corners of the cells
    /// whose top-left sample has [`EDGE_CELL`], and the window's slope.
    pub fn from_dense(
        cols: usize,
        rows: usize,
        heights: &[f32],
        flags: &[u8],
        georef: Georef,
    ) -> EdgeGrid {
        let n = cols * rows;
        assert!(
            heights.len() == n && flags.len() == n,
            "a dense edge grid's sizes"
        );
        let mut kept = vec![0u64; n.div_ceil(64)];
        let mut keep = |i: usize| kept[i / 64] |= 1 << (i % 64);
        for r in 0..rows.saturating_sub(1) {
            for c in 0..cols.saturating_sub(1) {
                let i = r * cols + c;
                if flags[i] & EDGE_CELL != 0 {
                    for k in [i, i + 1, i + cols, i + cols + 1] {
                        keep(k);
                    }
                }
            }
        }
        let bit = |i: usize| kept[i / 64] >> (i % 64) & 1 != 0;
        let heights_kept = (0..n).filter(|&i| bit(i)).map(|i| heights[i]).collect();
        let flags_kept = (0..n).filter(|&i| bit(i)).map(|i| flags[i]).collect();
        let slope = dense_slope(cols, rows, heights);
        Self::from_parts(cols, rows, kept, heights_kept, flags_kept, slope, georef)
            .expect("the parts just kept agree")
    }

    /// A grid from its stored parts, checked to agree.
    pub fn from_parts(
        cols: usize,
        rows: usize,
        kept: Vec<u64>,
        heights: Vec<f32>,
        flags: Vec<u8>,
        slope: f64,
        georef: Georef,
    ) -> Result<EdgeGrid, BadEdgeGrid> {
        let n = cols
            .checked_mul(rows)
            .filter(|_| cols >= 2 && rows >= 2)
            .ok_or_else(|| BadEdgeGrid(format!("a window of {cols} × {rows} samples")))?;
        if kept.len() != n.div_ceil(64) {
            return Err(BadEdgeGrid(format!(
                "{} words of kept bits for {n} samples",
                kept.len()
            )));
        }
        if n % 64 != 0 && kept[n / 64] >> (n % 64) != 0 {
            return Err(BadEdgeGrid("kept bits beyond the window".into()));
        }
        let mut rank = Vec::with_capacity(kept.len().div_ceil(RANK_BLOCK));
        let mut total = 0u32;
        for block in kept.chunks(RANK_BLOCK) {
            rank.push(total);
            total += block.iter().map(|w| w.count_ones()).sum::<u32>();
        }
        if heights.len() != total as usize || flags.len() != total as usize {
            return Err(BadEdgeGrid(format!(
                "{total} kept samples but {} heights and {} flags",
                heights.len(),
                flags.len()
            )));
        }
        if !slope.is_finite() || slope < 0.0 {
            return Err(BadEdgeGrid(format!("a slope of {slope}")));
        }
        Ok(EdgeGrid {
            cols,
            rows,
            kept,
            rank,
            heights,
            flags,
            slope,
            georef,
        })
    }

    /// The bits saying which samples are kept, 64 to a word, row-major.
    pub fn kept(&self) -> &[u64] {
        &self.kept
    }

    /// The kept samples' heights, row-major.
    pub fn kept_heights(&self) -> &[f32] {
        &self.heights
    }

    /// The kept samples' flags, row-major.
    pub fn kept_flags(&self) -> &[u8] {
        &self.flags
    }

    /// The bytes the grid holds on the heap.
    pub fn heap_bytes(&self) -> usize {
        self.kept.capacity() * 8
            + self.rank.capacity() * 4
            + self.heights.capacity() * 4
            + self.flags.capacity()
    }

    /// Where sample (c, r) is among the kept ones, if it is kept.
    #[inline]
    fn slot(&self, c: usize, r: usize) -> Option<usize> {
        let i = r * self.cols + c;
        let (w, b) = (i / 64, i % 64);
        let word = self.kept[w];
        if word >> b & 1 == 0 {
            return None;
        }
        let first = w - w % RANK_BLOCK;
        let before: u32 = self.kept[first..w].iter().map(|w| w.count_ones()).sum();
        Some(
            self.rank[w / RANK_BLOCK] as usize
                + before as usize
                + (word & ((1u64 << b) - 1)).count_ones() as usize,
        )
    }

    /// Sample (c, r)'s height and flags: NaN and 0 where it is not kept.
    #[inline]
    pub fn sample(&self, c: usize, r: usize) -> (f32, u8) {
        match self.slot(c, r) {
            Some(k) => (self.heights[k], self.flags[k]),
            None => (f32::NAN, 0),
        }
    }

    /// The whole window, row-major: heights (NaN where not kept) and flags (0 there), as a
    /// client or the GPU reads it.
    pub fn dense(&self) -> (Vec<f32>, Vec<u8>) {
        let n = self.cols * self.rows;
        let mut heights = vec![f32::NAN; n];
        let mut flags = vec![0u8; n];
        let mut k = 0;
        for (w, &word) in self.kept.iter().enumerate() {
            let mut bits = word;
            while bits != 0 {
                let i = w * 64 + bits.trailing_zeros() as usize;
                heights[i] = self.heights[k];
                flags[i] = self.flags[k];
                k += 1;
                bits &= bits - 1;
            }
        }
        (heights, flags)
    }

    #[inline]
    fn is_edge(&self, c: usize, r: usize) -> bool {
        self.sample(c, r).1 & EDGE_CELL != 0
    }

    /// The surface at fractional grid coordinates, or None outside every edge cell and outside
    /// the pixels of valid samples. A point on a line between cells takes the first edge cell
    /// holding it, in the same order as [`Grid::bilinear_grid`]; the surface is continuous
    /// there, so the choice only matters to rounding.
    pub fn eval(&self, g: [f64; 2]) -> Option<EdgeSample> {
        let (cw, ch) = (self.cols - 1, self.rows - 1);
        if !(g[0] >= 0.0 && g[1] >= 0.0 && g[0] <= cw as f64 && g[1] <= ch as f64) {
            return None;
        }
        let c = (g[0].floor() as usize).min(cw - 1);
        let r = (g[1].floor() as usize).min(ch - 1);
        let f = [g[0] - c as f64, g[1] - r as f64];
        if self.is_edge(c, r) {
            return self.in_cell(c, r, f);
        }
        let left = f[0] == 0.0 && c > 0;
        let up = f[1] == 0.0 && r > 0;
        if up && self.is_edge(c, r - 1) {
            return self.in_cell(c, r - 1, [f[0], 1.0]);
        }
        if left {
            if self.is_edge(c - 1, r) {
                return self.in_cell(c - 1, r, [1.0, f[1]]);
            }
            if up && self.is_edge(c - 1, r - 1) {
                return self.in_cell(c - 1, r - 1, [1.0, 1.0]);
            }
        }
        None
    }

    fn in_cell(&self, c: usize, r: usize, f: [f64; 2]) -> Option<EdgeSample> {
        // An edge cell's corners are all kept.
        let s = [(c, r), (c + 1, r), (c, r + 1), (c + 1, r + 1)].map(|(c, r)| self.sample(c, r));
        let v = s.map(|(_, flag)| flag & VALID != 0);
        if !nearest_valid(v, f) {
            return None;
        }
        let z = s.map(|(z, _)| z as f64);
        Some(EdgeSample {
            z: cell_surface(z, v, f),
            weight: ramp(v, f).max(MIN_WEIGHT),
        })
    }
}

/// An edge patch's answer at a point of data.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EdgeSample {
    /// The height, in metres.
    pub z: f64,
    /// Scales the patch's blend weight: 1 half a pixel inside the data, towards 0 at its edge.
    pub weight: f64,
}

/// The smallest weight a point of data gets, so that a point on the very edge of the pixels,
/// where the ramp is 0, is still answered.
pub const MIN_WEIGHT: f64 = 1e-6;

/// The largest height change between 4-neighbours of a window of `cols × rows` samples, NaN
/// ones left out.
fn dense_slope(cols: usize, rows: usize, heights: &[f32]) -> f64 {
    let mut slope = 0.0f64;
    for r in 0..rows {
        for c in 0..cols {
            let z = heights[r * cols + c] as f64;
            if z.is_nan() {
                continue;
            }
            for (dc, dr) in [(1, 0), (0, 1)] {
                let (cc, rr) = (c + dc, r + dr);
                if cc < cols && rr < rows {
                    let w = heights[rr * cols + cc] as f64;
                    if !w.is_nan() {
                        slope = slope.max((w - z).abs());
                    }
                }
            }
        }
    }
    slope
}

/// Twice the distance from a point to the nearest void corner's pixel (the larger of the
/// distances along the two axes, as for a square), at most 1. Only the cell's own corners
/// have pixels within half a cell of it.
#[inline]
pub fn ramp(v: [bool; 4], f: [f64; 2]) -> f64 {
    let mut r = 1.0f64;
    for (k, &valid) in v.iter().enumerate() {
        if valid {
            continue;
        }
        let s = [(k & 1) as f64, (k >> 1) as f64];
        let dx = ((f[0] - s[0]).abs() - 0.5).max(0.0);
        let dy = ((f[1] - s[1]).abs() - 0.5).max(0.0);
        r = r.min(2.0 * dx.max(dy));
    }
    r
}

#[inline]
fn bilinear(z: [f64; 4], f: [f64; 2]) -> f64 {
    let top = z[0] + (z[1] - z[0]) * f[0];
    let bottom = z[2] + (z[3] - z[2]) * f[0];
    top + (bottom - top) * f[1]
}

/// The height in one cell with corners z = (00, 10, 01, 11): bilinear when all four are valid,
/// else linear on two triangles (see the module notes for the diagonal).
#[inline]
pub fn cell_surface(z: [f64; 4], v: [bool; 4], f: [f64; 2]) -> f64 {
    if v.iter().all(|&b| b) {
        return bilinear(z, f);
    }
    if anti_diagonal(v) {
        // Triangles (00, 10, 01) and (11, 01, 10).
        if f[0] + f[1] <= 1.0 {
            z[0] + (z[1] - z[0]) * f[0] + (z[2] - z[0]) * f[1]
        } else {
            z[3] + (z[2] - z[3]) * (1.0 - f[0]) + (z[1] - z[3]) * (1.0 - f[1])
        }
    } else if f[0] >= f[1] {
        // Triangles (00, 10, 11) and (00, 11, 01).
        z[0] + (z[1] - z[0]) * f[0] + (z[3] - z[1]) * f[1]
    } else {
        z[0] + (z[3] - z[2]) * f[0] + (z[2] - z[0]) * f[1]
    }
}

/// Whether a cell splits along the diagonal from 10 to 01: when 00 or 11 is the one void
/// corner, or the valid corners are exactly 10 and 01.
#[inline]
pub fn anti_diagonal(v: [bool; 4]) -> bool {
    let n = v.iter().filter(|&&b| b).count();
    (n == 3 && (!v[0] || !v[3])) || (n == 2 && v[1] && v[2])
}

/// Whether the pixel a point falls in is valid: the corner nearest to it, or either of two
/// (or any of four) when it lies on the line halfway between them.
#[inline]
pub fn nearest_valid(v: [bool; 4], f: [f64; 2]) -> bool {
    let side = |x: f64| -> (bool, bool) {
        let d = x - 0.5;
        if on_line(d) {
            (true, true)
        } else {
            (d < 0.0, d > 0.0)
        }
    };
    let (x0, x1) = side(f[0]);
    let (y0, y1) = side(f[1]);
    (x0 && y0 && v[0]) || (x1 && y0 && v[1]) || (x0 && y1 && v[2]) || (x1 && y1 && v[3])
}

/// One edge patch: a tile of a lattice where some cell has data at a corner but no survey of
/// the lattice has the whole cell.
#[derive(Clone, Debug, PartialEq)]
pub struct EdgePatch {
    /// The unit the index inserts and retires; derived from the tile and the surveys used.
    pub owner: SurveyId,
    /// The patch's id, derived from `owner`.
    pub id: PatchId,
    /// The lattice tile, in the lattice's canonical tile numbers of [`tile_side`] cells.
    pub tile: [i64; 2],
    /// The surveys of the lattice whose samples reach the tile, in id order.
    pub members: Vec<SurveyId>,
    /// The tile's cells that the grid holds, in grid cells.
    pub kernel: CellRect,
    /// The kernel and its extension zone, cut to the edge cells: the whole grid.
    pub window: CellRect,
    /// The level-0 kernel side, in cells: edge patches are ordered with level-0 patches.
    pub kernel_cells: u32,
    /// The slope of the blend weight, flat over the kernel: half / margin (see
    /// `ResolvedPatch::flat`).
    pub flat: f64,
    /// Centre of the uncut window (the tile and its extension zone), in grid units; the blend
    /// weight uses it and `half`, as in [`super::patch::Patch`].
    pub centre: [f64; 2],
    /// Half the uncut window's side, in cells.
    pub half: [f64; 2],
    /// Where the kernel holds data, as rectangles of grid coordinates (c0, r0, c1, r1) whose
    /// edges fall on whole or half cells.
    pub valid: Vec<[f64; 4]>,
    /// ε of the samples used plus, in a cell with a void corner, the largest height change over
    /// one cell at its valid corners, in metres (see the module docs).
    pub error: f64,
    /// Where the grid's sample (0, 0) is and its cells' size: held whether or not the grid is.
    pub georef: Georef,
    /// The samples the patch evaluates, or None where a terrain let them go: they are a
    /// function of the members' samples, which it reads again when they are needed (see
    /// `Terrain::edge_grid`), so that a store of thousands of abutting tiles does not hold its
    /// edge patches' samples in memory beside the surveys' own in the store.
    pub grid: Option<Arc<EdgeGrid>>,
}

impl EdgePatch {
    /// The patch without its samples.
    pub fn without_grid(&self) -> EdgePatch {
        EdgePatch {
            grid: None,
            ..self.clone()
        }
    }

    /// The patch with `grid` as its samples.
    pub fn with_grid(&self, grid: Arc<EdgeGrid>) -> EdgePatch {
        EdgePatch {
            grid: Some(grid),
            ..self.clone()
        }
    }
}

/// A survey on a lattice: where its sample (0, 0) is on the lattice, and its level-0 samples
/// around the tiles being built.
#[derive(Clone, Copy)]
pub struct Member<'a> {
    /// The survey's metadata.
    pub survey: &'a SurveyMeta,
    /// Lattice index of the survey's sample (0, 0).
    pub index: [i64; 2],
    /// The survey's level-0 samples around the tiles being built.
    pub samples: &'a Window,
}

impl Member<'_> {
    fn shape(&self) -> &Shape {
        &self.survey.shapes[0]
    }

    /// Grid coordinates of lattice point (i, j), if the survey has that sample.
    #[inline]
    fn local(&self, i: i64, j: i64) -> Option<(usize, usize)> {
        let (c, r) = (i - self.index[0], j - self.index[1]);
        let g = self.shape();
        (c >= 0 && r >= 0 && (c as usize) < g.cols && (r as usize) < g.rows)
            .then_some((c as usize, r as usize))
    }

    /// Whether the survey's samples meet the lattice rectangle [i0, i1] × [j0, j1].
    fn meets(&self, i0: i64, j0: i64, i1: i64, j1: i64) -> bool {
        let g = self.shape();
        let (a0, b0) = (self.index[0], self.index[1]);
        let (a1, b1) = (a0 + g.cols as i64 - 1, b0 + g.rows as i64 - 1);
        a0 <= i1 && i0 <= a1 && b0 <= j1 && j0 <= b1
    }
}

/// The level-0 samples a tile's edge patch reads, as a lattice rectangle: the window one ring
/// wider, inclusive.
pub fn tile_reads(tile: [i64; 2], layout: &PatchLayout) -> [[i64; 2]; 2] {
    let k = tile_side(layout) as i64;
    let m = layout.margin as i64;
    let (i0, j0) = (tile[0] * k - m, tile[1] * k - m);
    let n = k + 2 * m + 1;
    [[i0 - 1, j0 - 1], [i0 + n, j0 + n]]
}

/// The tiles of the lattice whose edge patches a survey can affect: those whose samples, one
/// ring wider than the window, reach a valid sample of the survey with a void or the grid's
/// end among its eight neighbours. Every cell an edge patch serves has such a corner. `index`
/// is where the grid's sample (0, 0) is on its lattice.
pub fn edge_tiles(g: &Grid, index: [i64; 2], layout: &PatchLayout) -> Vec<[i64; 2]> {
    use rayon::prelude::*;
    let side = tile_side(layout);
    let k = side as i64;
    let reach = layout.margin as i64 + 1;
    let valid = |c: i64, r: i64| {
        c >= 0
            && r >= 0
            && (c as usize) < g.cols
            && (r as usize) < g.rows
            && g.is_valid(c as usize, r as usize)
    };
    let mut tiles: Vec<[i64; 2]> = (0..g.rows as i64)
        .into_par_iter()
        .flat_map_iter(|r| {
            let mut out = Vec::new();
            for c in 0..g.cols as i64 {
                if !valid(c, r) {
                    continue;
                }
                let border = (-1..=1).any(|dr| (-1..=1).any(|dc| !valid(c + dc, r + dr)));
                if !border {
                    continue;
                }
                let (i, j) = (index[0] + c, index[1] + r);
                for tj in tile_of(j - reach, side) - 1..=tile_of(j + reach, side) {
                    for ti in tile_of(i - reach, side) - 1..=tile_of(i + reach, side) {
                        if tile_reaches(ti, i, k, reach) && tile_reaches(tj, j, k, reach) {
                            out.push([ti, tj]);
                        }
                    }
                }
            }
            out.sort_unstable();
            out.dedup();
            out
        })
        .collect();
    tiles.sort_unstable();
    tiles.dedup();
    tiles
}

/// Whether tile `t`'s samples, `reach` wider than its cells, include lattice index `i`.
#[inline]
fn tile_reaches(t: i64, i: i64, k: i64, reach: i64) -> bool {
    t * k - reach <= i && i <= (t + 1) * k + reach
}

/// The edge patch of one lattice tile, from the surveys of the lattice; None when no cell of
/// the tile needs one.
pub fn build(tile: [i64; 2], members: &[Member], layout: &PatchLayout) -> Option<EdgePatch> {
    let k = tile_side(layout) as i64;
    let m = layout.margin as i64;
    // The window's first sample, and the samples one ring wider (for fills and slopes).
    let (i0, j0) = (tile[0] * k - m, tile[1] * k - m);
    let n = (k + 2 * m + 1) as usize;
    let ext = n + 2;
    let mut used: Vec<&Member> = members
        .iter()
        .filter(|mb| mb.meets(i0 - 1, j0 - 1, i0 + n as i64, j0 + n as i64))
        .collect();
    if used.is_empty() {
        return None;
    }
    used.sort_by_key(|mb| mb.survey.id);

    // The union: at each lattice point the most accurate survey's sample (ties by id).
    let mut z = vec![f32::NAN; ext * ext];
    let mut eps = vec![f64::INFINITY; ext * ext];
    for b in 0..ext {
        for a in 0..ext {
            let (i, j) = (i0 - 1 + a as i64, j0 - 1 + b as i64);
            for mb in &used {
                let Some((c, r)) = mb.local(i, j) else {
                    continue;
                };
                let h = mb.samples.at(c, r);
                if h.is_nan() {
                    continue;
                }
                let e = mb.survey.accuracy_at(c, r);
                // Members are in id order, so a strict comparison keeps the smaller id on ties.
                if e < eps[b * ext + a] {
                    eps[b * ext + a] = e;
                    z[b * ext + a] = h;
                }
            }
        }
    }
    let ok = |a: isize, b: isize| !z[((b + 1) as usize) * ext + (a + 1) as usize].is_nan();
    let at = |a: isize, b: isize| z[((b + 1) as usize) * ext + (a + 1) as usize] as f64;

    // Cells a single survey has whole are its own patches' business.
    let cells = n - 1;
    let mut edge = vec![false; cells * cells];
    let (km, kk) = (m as usize, (m + k) as usize);
    let mut any_in_kernel = false;
    // Bounds of the edge cells: the grid is cut down to them.
    let (mut a_lo, mut b_lo, mut a_hi, mut b_hi) = (usize::MAX, usize::MAX, 0, 0);
    for b in 0..cells {
        for a in 0..cells {
            let corner = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .iter()
                .any(|&(da, db)| ok((a + da) as isize, (b + db) as isize));
            if !corner {
                continue;
            }
            let (i, j) = (i0 + a as i64, j0 + b as i64);
            let whole = used.iter().any(|mb| {
                mb.local(i, j).is_some_and(|(c, r)| {
                    c + 1 < mb.shape().cols
                        && r + 1 < mb.shape().rows
                        && mb.samples.cell_valid(c, r)
                })
            });
            if !whole {
                edge[b * cells + a] = true;
                any_in_kernel |= (km..kk).contains(&a) && (km..kk).contains(&b);
                (a_lo, b_lo) = (a_lo.min(a), b_lo.min(b));
                (a_hi, b_hi) = (a_hi.max(a + 1), b_hi.max(b + 1));
            }
        }
    }
    if !any_in_kernel {
        return None;
    }

    // The error: ε of the samples used, plus a cell's height change where a corner is void.
    let slope = |a: usize, b: usize| -> f64 {
        let (ai, bi) = (a as isize, b as isize);
        let h = at(ai, bi);
        [(-1, 0), (1, 0), (0, -1), (0, 1)]
            .iter()
            .filter(|&&(da, db)| ok(ai + da, bi + db))
            .map(|&(da, db)| (at(ai + da, bi + db) - h).abs())
            .fold(0.0, f64::max)
    };
    let mut error = 0.0f64;
    for b in b_lo..b_hi {
        for a in a_lo..a_hi {
            if !edge[b * cells + a] {
                continue;
            }
            let valid: Vec<(usize, usize)> = [(a, b), (a + 1, b), (a, b + 1), (a + 1, b + 1)]
                .into_iter()
                .filter(|&(ca, cb)| ok(ca as isize, cb as isize))
                .collect();
            let e = valid
                .iter()
                .map(|&(ca, cb)| eps[(cb + 1) * ext + ca + 1])
                .fold(0.0, f64::max);
            let x = if valid.len() == 4 {
                0.0
            } else {
                valid
                    .iter()
                    .map(|&(ca, cb)| slope(ca, cb))
                    .fold(0.0, f64::max)
            };
            error = error.max(e + x);
        }
    }

    // The grid: the samples of the edge cells, voids filled from their valid neighbours.
    let (cols, rows) = (a_hi - a_lo + 1, b_hi - b_lo + 1);
    let mut heights = vec![f32::NAN; cols * rows];
    let mut flags = vec![0u8; cols * rows];
    for y in 0..rows {
        for x in 0..cols {
            let (ai, bi) = ((a_lo + x) as isize, (b_lo + y) as isize);
            let k2 = y * cols + x;
            if ok(ai, bi) {
                heights[k2] = at(ai, bi) as f32;
                flags[k2] |= VALID;
            } else {
                let mean = |ns: &[(isize, isize)]| {
                    let vals: Vec<f64> = ns
                        .iter()
                        .filter(|&&(da, db)| ok(ai + da, bi + db))
                        .map(|&(da, db)| at(ai + da, bi + db))
                        .collect();
                    (!vals.is_empty()).then(|| vals.iter().sum::<f64>() / vals.len() as f64)
                };
                if let Some(v) = mean(&[(-1, 0), (1, 0), (0, -1), (0, 1)])
                    .or_else(|| mean(&[(-1, -1), (1, -1), (-1, 1), (1, 1)]))
                {
                    heights[k2] = v as f32;
                }
            }
            let (a, b) = (a_lo + x, b_lo + y);
            if a < a_hi && b < b_hi && edge[b * cells + a] {
                flags[k2] |= EDGE_CELL;
            }
        }
    }

    // The kernel, in grid cells, and where it is data: the quarter of each edge cell nearest
    // a valid corner.
    let clip = |v: usize, lo: usize, hi: usize| (v.clamp(lo, hi) - lo) as u32;
    let kernel = CellRect {
        c0: clip(km, a_lo, a_hi),
        r0: clip(km, b_lo, b_hi),
        c1: clip(kk, a_lo, a_hi),
        r1: clip(kk, b_lo, b_hi),
    };
    let (qa, qb) = (kernel.c0 as usize + a_lo, kernel.r0 as usize + b_lo);
    let half_valid = |ha: usize, hb: usize| {
        let (a, b) = (qa + ha / 2, qb + hb / 2);
        edge[b * cells + a] && ok((a + ha % 2) as isize, (b + hb % 2) as isize)
    };
    let valid = half_rects(
        2 * kernel.cols() as usize,
        2 * kernel.rows() as usize,
        half_valid,
    )
    .into_iter()
    .map(|[a0, b0, a1, b1]| {
        [
            kernel.c0 as f64 + a0 as f64 / 2.0,
            kernel.r0 as f64 + b0 as f64 / 2.0,
            kernel.c0 as f64 + a1 as f64 / 2.0,
            kernel.r0 as f64 + b1 as f64 / 2.0,
        ]
    })
    .collect();

    // Positions come from the survey with the smallest id, so they never depend on order.
    let first = used[0];
    let origin = first.survey.shapes[0].georef.to_world(
        (i0 + a_lo as i64 - first.index[0]) as f64,
        (j0 + b_lo as i64 - first.index[1]) as f64,
    );
    let georef = Georef {
        origin,
        ..first.survey.shapes[0].georef
    };
    let ids: Vec<SurveyId> = used.iter().map(|mb| mb.survey.id).collect();
    let owner = owner_id(tile, k, &ids, error, &heights);
    Some(EdgePatch {
        owner,
        id: PatchId::derive(owner, 0, [0, 0]),
        tile,
        members: ids,
        kernel,
        window: CellRect {
            c0: 0,
            r0: 0,
            c1: (cols - 1) as u32,
            r1: (rows - 1) as u32,
        },
        kernel_cells: layout.kernel as u32,
        flat: (k as f64 / 2.0 + km as f64) / km as f64,
        centre: [
            km as f64 + k as f64 / 2.0 - a_lo as f64,
            km as f64 + k as f64 / 2.0 - b_lo as f64,
        ],
        half: [k as f64 / 2.0 + km as f64; 2],
        valid,
        error,
        georef,
        grid: Some(Arc::new(EdgeGrid::from_dense(
            cols, rows, &heights, &flags, georef,
        ))),
    })
}

/// The id of a tile's edge patch: its tile, the surveys it was made from, and what it holds.
/// The members' claims (which other surveys' evidence can raise) decide whose sample it
/// takes where they overlap and its error, so the same members can make another patch.
fn owner_id(
    tile: [i64; 2],
    side: i64,
    members: &[SurveyId],
    error: f64,
    heights: &[f32],
) -> SurveyId {
    let mut h = blake3::Hasher::new();
    h.update(b"patchwork.edge.v2");
    h.update(&side.to_le_bytes());
    h.update(&tile[0].to_le_bytes());
    h.update(&tile[1].to_le_bytes());
    for m in members {
        h.update(&m.0.to_le_bytes());
    }
    h.update(&error.to_bits().to_le_bytes());
    for z in heights {
        h.update(&z.to_bits().to_le_bytes());
    }
    SurveyId(hash64(h))
}

/// The true cells of a `cols × rows` boolean grid as disjoint rectangles [a0, b0, a1, b1):
/// row runs that repeat on the next row grow downwards.
fn half_rects(cols: usize, rows: usize, on: impl Fn(usize, usize) -> bool) -> Vec<[usize; 4]> {
    let mut done = Vec::new();
    let mut open: Vec<[usize; 4]> = Vec::new();
    for b in 0..rows {
        let mut runs = Vec::new();
        let mut a = 0;
        while a < cols {
            if on(a, b) {
                let s = a;
                while a < cols && on(a, b) {
                    a += 1;
                }
                runs.push((s, a));
            } else {
                a += 1;
            }
        }
        let mut next = Vec::with_capacity(runs.len());
        for (a0, a1) in runs {
            match open.iter().position(|o| o[0] == a0 && o[2] == a1) {
                Some(p) => {
                    let mut o = open.swap_remove(p);
                    o[3] = b + 1;
                    next.push(o);
                }
                None => next.push([a0, b, a1, b + 1]),
            }
        }
        done.append(&mut open);
        open = next;
    }
    done.append(&mut open);
    done.sort_by_key(|r| (r[1], r[0]));
    done
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn three_valid_corners_make_the_plane_through_them() {
        let z = [1.0, 3.0, 5.0, 99.0];
        let v = [true, true, true, false];
        // Plane z = 1 + 2x + 4y on the triangle (00, 10, 01), whatever the filled corner holds.
        for &(x, y) in &[(0.1, 0.2), (0.5, 0.5), (0.0, 1.0), (0.3, 0.6)] {
            let want = 1.0 + 2.0 * x + 4.0 * y;
            assert!((cell_surface(z, v, [x, y]) - want).abs() < 1e-12);
        }
        // The void corner's quarter is not data; the three others are.
        assert!(!nearest_valid(v, [0.75, 0.75]));
        assert!(nearest_valid(v, [0.75, 0.25]) && nearest_valid(v, [0.25, 0.75]));
        assert!(
            nearest_valid(v, [0.5, 0.75]),
            "the halfway line belongs to both pixels"
        );
        // The weight ramps from 1 at the samples to 0 at the void pixel's edge, continuously.
        assert_eq!(ramp(v, [0.0, 0.0]), 1.0);
        assert!((ramp(v, [0.4, 0.3]) - 0.4).abs() < 1e-12);
        assert!((ramp(v, [0.6, 0.3]) - 0.4).abs() < 1e-12);
        assert_eq!(ramp(v, [0.5, 0.5]), 0.0);
        // With 00 void the cell splits the other way, and (10, 01, 11) is the plane.
        let v = [false, true, true, true];
        assert!(anti_diagonal(v));
        let z = [-50.0, 3.0, 5.0, 7.0];
        let want = 1.0 + 2.0 * 0.7 + 4.0 * 0.6;
        assert!((cell_surface(z, v, [0.7, 0.6]) - want).abs() < 1e-12);
    }

    #[test]
    fn a_grid_keeps_its_edge_cells_corners_and_the_whole_windows_slope() {
        let (cols, rows) = (70, 9);
        let georef = Georef::north_up([0.0, 0.0], [1.0, -1.0]);
        let heights: Vec<f32> = (0..cols * rows).map(|i| (i * 7 % 13) as f32).collect();
        let mut flags = vec![VALID; cols * rows];
        // Edge cells along a seam at column 40 and one cell at the far corner.
        for r in 0..rows - 1 {
            flags[r * cols + 40] |= EDGE_CELL;
        }
        flags[(rows - 2) * cols + cols - 2] |= EDGE_CELL;
        let g = EdgeGrid::from_dense(cols, rows, &heights, &flags, georef);
        let (h, f) = g.dense();
        let mut kept = 0;
        for r in 0..rows {
            for c in 0..cols {
                let corner = [(0, 0), (1, 0), (0, 1), (1, 1)].iter().any(|&(dc, dr)| {
                    c >= dc
                        && r >= dr
                        && c - dc < cols - 1
                        && r - dr < rows - 1
                        && flags[(r - dr) * cols + c - dc] & EDGE_CELL != 0
                });
                let i = r * cols + c;
                if corner {
                    kept += 1;
                    assert_eq!((h[i], f[i]), (heights[i], flags[i]), "({c}, {r})");
                } else {
                    assert!(h[i].is_nan() && f[i] == 0, "({c}, {r}) is not kept");
                }
            }
        }
        assert_eq!(g.kept_heights().len(), kept);
        // The slope is the whole window's, samples left out included.
        assert_eq!(g.slope, dense_slope(cols, rows, &heights));
        // Heights 7i mod 13: neighbours along a row differ by 7 or 6, down a column by 9 or 4.
        assert_eq!(g.slope, 9.0);
        // Parts that disagree are refused.
        let bad = |kept: Vec<u64>, n: usize| {
            EdgeGrid::from_parts(cols, rows, kept, vec![0.0; n], vec![0; n], 1.0, georef)
        };
        assert!(bad(g.kept().to_vec(), kept).is_ok());
        assert!(bad(g.kept().to_vec(), kept + 1).is_err());
        assert!(bad(g.kept()[1..].to_vec(), kept).is_err());
        let mut beyond = g.kept().to_vec();
        *beyond.last_mut().unwrap() |= 1 << 63;
        assert!(bad(beyond, kept + 1).is_err());
    }

    #[test]
    fn half_rects_cover_exactly() {
        let on = |a: usize, b: usize| !(a + 2 * b).is_multiple_of(5) && a < 7;
        let rects = half_rects(9, 9, on);
        for b in 0..9 {
            for a in 0..9 {
                let n = rects
                    .iter()
                    .filter(|r| (r[0]..r[2]).contains(&a) && (r[1]..r[3]).contains(&b))
                    .count();
                assert_eq!(n, usize::from(on(a, b)), "({a}, {b})");
            }
        }
    }
}
