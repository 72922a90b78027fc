//! Patches: windows of a mipmap level, each with a kernel that tiles the level, and the exact
//! error of the patch's surface against the survey's own samples.

use super::accuracy::KernelAccuracy;
use super::grid::Grid;
use super::ids::{PatchId, SurveyId};
use super::spline::{self, Spline};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// How a level is cut into patches, in whole cells so that windows align with samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PatchLayout {
    /// Kernel side in cells. Kernels of one level tile it without overlap.
    pub kernel: usize,
    /// Extension zone around the kernel, in cells, on every side.
    pub margin: usize,
}

impl Default for PatchLayout {
    /// The paper's 32-cell windows around 28-cell kernels (σ ≈ 0.9).
    fn default() -> Self {
        PatchLayout {
            kernel: 28,
            margin: 2,
        }
    }
}

/// A half-open range of cells `[c0, c1) × [r0, r1)`; as samples it spans `c0..=c1 × r0..=r1`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct CellRect {
    /// First cell column.
    pub c0: u32,
    /// First cell row.
    pub r0: u32,
    /// One past the last cell column.
    pub c1: u32,
    /// One past the last cell row.
    pub r1: u32,
}

impl CellRect {
    /// Columns of cells.
    pub fn cols(&self) -> u32 {
        self.c1 - self.c0
    }
    /// Rows of cells.
    pub fn rows(&self) -> u32 {
        self.r1 - self.r0
    }
    /// Whether it holds no cell.
    pub fn is_empty(&self) -> bool {
        self.c1 <= self.c0 || self.r1 <= self.r0
    }
    /// Whether fractional grid coordinates fall in the closed rectangle.
    #[inline]
    pub fn contains_grid(&self, g: [f64; 2]) -> bool {
        g[0] >= self.c0 as f64
            && g[0] <= self.c1 as f64
            && g[1] >= self.r0 as f64
            && g[1] <= self.r1 as f64
    }
}

/// One patch of one level. Samples are not copied: a bilinear patch is a window of its level.
#[derive(Clone, Debug, PartialEq)]
pub struct Patch {
    /// Derived from the survey, level and index.
    pub id: PatchId,
    /// Mipmap level; 0 is the survey's own samples.
    pub level: u8,
    /// Its kernel's place in its level's tiling of kernels, row-major: the index `[i, j]`
    /// its id was derived from is `[index % nx, index / nx]`, nx the tiling's kernels along a
    /// row. The kernel's cells, its window (the kernel grown by the margin, clipped to the
    /// level) and the window's centre are the tiling's to work out from it
    /// ([`SurveyMeta::kernel`], [`SurveyMeta::window`]): an index holds a patch for every
    /// 576 samples, and a patch keeps nothing that the tiling says.
    ///
    /// [`SurveyMeta::kernel`]: crate::survey::SurveyMeta::kernel
    /// [`SurveyMeta::window`]: crate::survey::SurveyMeta::window
    pub index: u32,
    /// The kernel's valid cells as disjoint rectangles ([`SurveyMeta::valid`]).
    ///
    /// [`SurveyMeta::valid`]: crate::survey::SurveyMeta::valid
    pub valid: ValidCells,
    /// ε + δ, with the survey's own claims: the bottom of the patch's box in LOD space unless
    /// other surveys' evidence raised those claims (then [`SurveyMeta::error_at`] says what it is).
    /// δ itself, the largest vertical distance to level 0 anywhere in the window, is the
    /// store's to keep ([`Survey::deltas`]): nothing the index does needs it apart.
    ///
    /// [`Survey::deltas`]: crate::survey::Survey::deltas
    /// [`SurveyMeta::error_at`]: crate::survey::SurveyMeta::error_at
    pub error: f64,
}

/// A kernel's valid cells as disjoint rectangles, held only where they are not the whole
/// kernel: nearly every patch's are, and a list of one rectangle is an allocation of its own
/// a patch (16 bytes, 32 with the allocator's). The list sits behind one more box, so that
/// what every patch holds is a thin pointer, 8 bytes where a slice's would be 16.
#[derive(Clone, Debug, PartialEq)]
pub struct ValidCells(Option<Box<Box<[CellRect]>>>);

impl ValidCells {
    /// The valid cells of `kernel`, `cells` being disjoint rectangles inside it.
    pub fn of(kernel: &CellRect, cells: Vec<CellRect>) -> ValidCells {
        let whole = cells.len() == 1 && cells[0] == *kernel;
        ValidCells((!whole).then(|| Box::new(cells.into_boxed_slice())))
    }

    /// The rectangles held: none where they are the whole kernel.
    pub fn held(&self) -> usize {
        self.0.as_ref().map_or(0, |c| c.len())
    }

    /// The rectangles where they are not the whole kernel.
    #[inline]
    pub fn parts(&self) -> Option<&[CellRect]> {
        self.0.as_deref().map(|b| &**b)
    }

    /// The rectangles, given the kernel they are of.
    #[inline]
    pub fn get<'a>(&'a self, kernel: &'a CellRect) -> &'a [CellRect] {
        match &self.0 {
            None => std::slice::from_ref(kernel),
            Some(cells) => cells,
        }
    }
}

/// Which function the patches of a store evaluate. A store makes all its surveys' patches of
/// one kind, chosen when it is made (`[patches] kind` in the config; `meta/patches` in the
/// store).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PatchKind {
    /// C0: bilinear on each cell, blended with the tent w(t) = 1 − |t|.
    #[default]
    Bilinear,
    /// C2: the natural bicubic spline through the window's samples, blended with
    /// w(t) = (1 − |t|)³(3|t| + 1).
    Bicubic,
}

impl PatchKind {
    /// Every patch kind.
    pub const ALL: [PatchKind; 2] = [PatchKind::Bilinear, PatchKind::Bicubic];

    /// The name in the config and the store, as serialised.
    pub fn name(self) -> &'static str {
        match self {
            PatchKind::Bilinear => "bilinear",
            PatchKind::Bicubic => "bicubic",
        }
    }

    /// The kind called `name`, if any.
    pub fn from_name(name: &str) -> Option<PatchKind> {
        PatchKind::ALL.into_iter().find(|k| k.name() == name)
    }

    /// The function that makes and measures patches of this kind.
    pub fn function(self) -> &'static dyn PatchFunction {
        match self {
            PatchKind::Bilinear => &Bilinear,
            PatchKind::Bicubic => &Bicubic,
        }
    }

    /// The 1-D blending weight on t ∈ [−1, 1], zero at ±1.
    #[inline]
    pub fn weight(self, t: f64) -> f64 {
        let a = t.abs().min(1.0);
        let w = 1.0 - a;
        match self {
            PatchKind::Bilinear => w,
            PatchKind::Bicubic => w * w * w * (3.0 * a + 1.0),
        }
    }
}

/// How the patches that reach a point are blended into its height. A store blends one way,
/// chosen when it is made (`[patches] blend` in the config; `meta/blend` in the store).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Blend {
    /// The paper's Formula 1: the weighted mean of every patch that reaches the point, each
    /// weighted by its kind's weight over its window divided by the window's area.
    Formula1,
    /// The paper's proposed blend (§7.3): patches in order of error, each weighing 1 over its
    /// kernel and falling to 0 across its extension zone, laid over one another, so that inside
    /// the most accurate kernel that holds a point that patch alone counts, and blending happens
    /// only where a more accurate patch's extension zone meets a less accurate kernel. The
    /// default: docs/BENCHMARKS.md, "The accurate blend beside Formula 1".
    #[default]
    Accurate,
}

impl Blend {
    /// Every blend.
    pub const ALL: [Blend; 2] = [Blend::Formula1, Blend::Accurate];

    /// The name in the config and the store, as serialised.
    pub fn name(self) -> &'static str {
        match self {
            Blend::Formula1 => "formula1",
            Blend::Accurate => "accurate",
        }
    }

    /// The blend called `name`, if any.
    pub fn from_name(name: &str) -> Option<Blend> {
        Blend::ALL.into_iter().find(|k| k.name() == name)
    }
}

/// The function a patch evaluates, and its δ: the largest distance from the *reference
/// surface*, the bilinear surface of the survey's level-0 samples on its valid cells (the
/// surface GDAL interpolates and edge patches continue), anywhere in the patch's window where
/// the patch is evaluated.
pub trait PatchFunction: Send + Sync {
    /// The patch's height at fractional level-grid coordinates inside its window, or None on void.
    fn eval(&self, level: &Grid, window: &CellRect, g: [f64; 2]) -> Option<f64>;
    /// The largest |patch − reference| over the window's valid cells, or a bound on it.
    fn max_deviation(&self, levels: &[Arc<Grid>], level: usize, window: &CellRect) -> f64;

    /// [`PatchFunction::max_deviation`] of many windows, as `(level, window)`.
    fn deviations(&self, levels: &[Arc<Grid>], windows: &[(usize, CellRect)]) -> Vec<f64> {
        windows
            .par_iter()
            .map(|(lv, w)| self.max_deviation(levels, *lv, w))
            .collect()
    }
}

/// C0 patches: bilinear interpolation of the window's samples, blended with w(t) = 1 − |t|.
#[derive(Clone, Copy, Debug, Default)]
pub struct Bilinear;

impl PatchFunction for Bilinear {
    #[inline]
    fn eval(&self, level: &Grid, window: &CellRect, g: [f64; 2]) -> Option<f64> {
        if !window.contains_grid(g) {
            return None;
        }
        level.bilinear_grid(g)
    }

    /// Exact for bilinear patches on aligned mipmaps: coarse cell edges are fine cell edges, so
    /// on every fine cell both surfaces are bilinear and so is their difference, whose extreme
    /// lies at a corner, that is at a level-0 sample. Checking every valid level-0 sample under
    /// every valid coarse cell of the window therefore finds the true maximum.
    fn max_deviation(&self, levels: &[Arc<Grid>], level: usize, window: &CellRect) -> f64 {
        if level == 0 {
            return 0.0;
        }
        let coarse = &levels[level];
        let fine = &levels[0];
        let f = 1usize << level;
        let inv = 1.0 / f as f64;
        let mut worst = 0.0f64;
        for r in window.r0 as usize..window.r1 as usize {
            let j0 = r * f;
            if j0 >= fine.rows {
                break;
            }
            let j1 = ((r + 1) * f).min(fine.rows - 1);
            for c in window.c0 as usize..window.c1 as usize {
                let i0 = c * f;
                if i0 >= fine.cols {
                    break;
                }
                if !coarse.cell_valid(c, r) {
                    continue;
                }
                let i1 = ((c + 1) * f).min(fine.cols - 1);
                let z00 = coarse.at(c, r) as f64;
                let z10 = coarse.at(c + 1, r) as f64;
                let z01 = coarse.at(c, r + 1) as f64;
                let z11 = coarse.at(c + 1, r + 1) as f64;
                for j in j0..=j1 {
                    let fy = (j - j0) as f64 * inv;
                    let a = z00 + (z01 - z00) * fy;
                    let b = z10 + (z11 - z10) * fy;
                    let row = &fine.samples[j * fine.cols + i0..=j * fine.cols + i1];
                    worst = worst.max(row_deviation(a, b, inv, row));
                }
            }
        }
        worst
    }

    /// A window's δ is the largest of its cells' own figures, and the windows of a level
    /// overlap by their extension zones: each cell's is computed once, by
    /// [`Bilinear::cell_deviations`].
    fn deviations(&self, levels: &[Arc<Grid>], windows: &[(usize, CellRect)]) -> Vec<f64> {
        let devs = self.cell_deviations(levels);
        windows
            .par_iter()
            .map(|&(lv, w)| {
                if lv == 0 {
                    return 0.0;
                }
                let cw = levels[lv].cells()[0];
                let d = &devs[lv];
                (w.r0 as usize..w.r1 as usize)
                    .flat_map(|r| d[r * cw + w.c0 as usize..r * cw + w.c1 as usize].iter())
                    .fold(0.0f64, |a, &b| a.max(b))
            })
            .collect()
    }
}

impl Bilinear {
    /// [`Bilinear::max_deviation`] of every single cell of every level: for each level, its
    /// cells row-major (none for level 0).
    ///
    /// All levels in one pass over level 0, a band of its rows to a task: each fine row is
    /// read once, while it is in cache, for every level, instead of once per level from
    /// memory; and the coarsest levels, a few cell rows each, no longer leave a core idle.
    /// Each (cell, fine row) pair is evaluated once, by [`row_deviation`] as in
    /// [`Bilinear::max_deviation`], and maxima do not depend on the order they are taken in:
    /// the result is that function's to the bit (tested).
    pub fn cell_deviations(&self, levels: &[Arc<Grid>]) -> Vec<Vec<f64>> {
        const BAND: usize = 64;
        let fine = &levels[0];
        let bands: Vec<Vec<(usize, Vec<f64>)>> = (0..fine.rows.div_ceil(BAND))
            .into_par_iter()
            .map(|b| {
                let rows = b * BAND..((b + 1) * BAND).min(fine.rows);
                (1..levels.len())
                    .map(|level| band_deviations(&levels[level], fine, level, rows.clone()))
                    .collect()
            })
            .collect();
        let mut out: Vec<Vec<f64>> = levels
            .iter()
            .enumerate()
            .map(|(lv, g)| {
                let [cw, ch] = g.cells();
                vec![0.0; if lv == 0 { 0 } else { cw * ch }]
            })
            .collect();
        for band in bands {
            for (lv, (first, part)) in band.into_iter().enumerate() {
                let dst = &mut out[lv + 1][first..first + part.len()];
                for (d, p) in dst.iter_mut().zip(part) {
                    *d = d.max(p);
                }
            }
        }
        out
    }
}

/// C2 patches (§4.1): the natural bicubic spline through the window's samples (see
/// [`crate::spline`]), evaluated on the window's valid cells.
#[derive(Clone, Copy, Debug, Default)]
pub struct Bicubic;

impl Bicubic {
    /// The patch's spline: fitted to its window's samples, `at(c, r)` in level coordinates;
    /// the spline's coordinates are relative to the window's first sample.
    pub fn spline_of(window: &CellRect, at: impl Fn(usize, usize) -> f32) -> Spline {
        let (c0, r0) = (window.c0 as usize, window.r0 as usize);
        Spline::fit(
            window.cols() as usize + 1,
            window.rows() as usize + 1,
            |c, r| at(c0 + c, r0 + r),
        )
    }

    fn spline(level: &Grid, window: &CellRect) -> Spline {
        Self::spline_of(window, |c, r| level.at(c, r))
    }
}

impl PatchFunction for Bicubic {
    /// Where the bilinear patch is defined (the same validity), the spline's height.
    fn eval(&self, level: &Grid, window: &CellRect, g: [f64; 2]) -> Option<f64> {
        Bilinear.eval(level, window, g)?;
        let s = Self::spline(level, window);
        Some(s.eval([g[0] - window.c0 as f64, g[1] - window.r0 as f64]))
    }

    /// A guaranteed bound, not a sample: on each level-0 cell under a valid cell of the window,
    /// both the spline and the reference are polynomials of degree 3 in each direction (the
    /// reference bilinear, degree-elevated), so their difference is one too, and lies within
    /// the range of its Bernstein coefficients. Those are the difference of the spline's
    /// Bézier net, subdivided down to the level-0 cell, and the reference's net. Where that
    /// range is well above the largest deviation already found, [`net_bound`] halves the cell
    /// until it is not: the bound is within 1% + 1 mm of the true maximum.
    fn max_deviation(&self, levels: &[Arc<Grid>], level: usize, window: &CellRect) -> f64 {
        let coarse = &levels[level];
        let fine = &levels[0];
        let spline = Self::spline(coarse, window);
        let f = 1usize << level;
        let subs = spline::subdivision(f);
        let third = [0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0];
        let mut worst = 0.0f64;
        // The largest deviation met exactly so far (at cell corners): cells whose bound is
        // not above it need no refining.
        let mut lower = 0.0f64;
        let mut diff = [[0.0f64; 4]; 4];
        // The net subdivided across, for each fine column of the cell: [k][row][m].
        let mut across = vec![[[0.0f64; 4]; 4]; f];
        for r in window.r0 as usize..window.r1 as usize {
            for c in window.c0 as usize..window.c1 as usize {
                if !coarse.cell_valid(c, r) {
                    continue;
                }
                let net = spline.bezier(c - window.c0 as usize, r - window.r0 as usize);
                for (k, sub) in subs.iter().enumerate() {
                    for (y, row) in net.iter().enumerate() {
                        for m in 0..4 {
                            across[k][y][m] = (0..4).map(|x| sub[m][x] * row[x]).sum();
                        }
                    }
                }
                for (l, sub_y) in subs.iter().enumerate() {
                    let j = r * f + l;
                    if j + 1 >= fine.rows {
                        break;
                    }
                    for (k, a) in across.iter().enumerate() {
                        let i = c * f + k;
                        if i + 1 >= fine.cols {
                            break;
                        }
                        let z00 = fine.at(i, j) as f64;
                        let z10 = fine.at(i + 1, j) as f64;
                        let z01 = fine.at(i, j + 1) as f64;
                        let z11 = fine.at(i + 1, j + 1) as f64;
                        for n in 0..4 {
                            let y = third[n];
                            let left = z00 + (z01 - z00) * y;
                            let right = z10 + (z11 - z10) * y;
                            for m in 0..4 {
                                let q: f64 = (0..4).map(|yy| sub_y[n][yy] * a[yy][m]).sum();
                                diff[n][m] = q - (left + (right - left) * third[m]);
                            }
                        }
                        worst = worst.max(net_bound(&diff, &mut lower, REFINE_DEPTH));
                    }
                }
            }
        }
        worst
    }
}

/// How many times [`net_bound`] may halve a cell: 4⁻⁸ of a cell is far below any survey's
/// resolution, and the bound's excess shrinks fourfold each time.
const REFINE_DEPTH: u32 = 8;

/// An upper bound on |p| over the unit square, for the bicubic polynomial p with Bernstein
/// coefficients `net`, tight to 1% + 1 mm of the larger of its true maximum and `lower`.
/// `lower` is raised to every exact value met (the corners): a part whose coefficients do not
/// rise above it cannot hold the maximum, and is not refined.
fn net_bound(net: &[[f64; 4]; 4], lower: &mut f64, depth: u32) -> f64 {
    let corners = net[0][0]
        .abs()
        .max(net[0][3].abs())
        .max(net[3][0].abs().max(net[3][3].abs()));
    // A void corner (which erosion rules out) gives NaN, which never wins a comparison.
    if corners > *lower {
        *lower = corners;
    }
    let hull = net.iter().flatten().fold(0.0f64, |a, &b| a.max(b.abs()));
    if hull.is_nan() || depth == 0 || hull <= *lower * 1.01 + 1e-3 {
        return if hull.is_nan() { 0.0 } else { hull };
    }
    let halves = |p: [f64; 4]| -> ([f64; 4], [f64; 4]) {
        let a = [
            (p[0] + p[1]) / 2.0,
            (p[1] + p[2]) / 2.0,
            (p[2] + p[3]) / 2.0,
        ];
        let b = [(a[0] + a[1]) / 2.0, (a[1] + a[2]) / 2.0];
        let mid = (b[0] + b[1]) / 2.0;
        ([p[0], a[0], b[0], mid], [mid, b[1], a[2], p[3]])
    };
    // Split each row across, then each column of each half down.
    let mut across = [[[0.0f64; 4]; 4]; 2];
    for (n, row) in net.iter().enumerate() {
        let (l, r) = halves(*row);
        across[0][n] = l;
        across[1][n] = r;
    }
    let mut worst = 0.0f64;
    for half in &across {
        let mut quarters = [[[0.0f64; 4]; 4]; 2];
        for m in 0..4 {
            let (top, bottom) = halves([half[0][m], half[1][m], half[2][m], half[3][m]]);
            for n in 0..4 {
                quarters[0][n][m] = top[n];
                quarters[1][n][m] = bottom[n];
            }
        }
        for q in &quarters {
            worst = worst.max(net_bound(q, lower, depth - 1));
        }
    }
    worst
}

/// One row of coarse cells, for [`band_deviations`]: each cell's left corners and their
/// differences down the cell, as `max_deviation` computes them, or None for a cell it skips
/// (a void corner, or no fine samples under it).
#[derive(Default)]
struct CellRow {
    r: Option<usize>,
    cells: Vec<Option<[f64; 4]>>,
}

impl CellRow {
    fn load(&mut self, coarse: &Grid, r: usize, f: usize, fine_cols: usize) {
        let [cw, _] = coarse.cells();
        self.r = Some(r);
        self.cells.clear();
        self.cells.extend((0..cw).map(|c| {
            if c * f >= fine_cols || !coarse.cell_valid(c, r) {
                return None;
            }
            let z00 = coarse.at(c, r) as f64;
            let z10 = coarse.at(c + 1, r) as f64;
            let z01 = coarse.at(c, r + 1) as f64;
            let z11 = coarse.at(c + 1, r + 1) as f64;
            Some([z00, z01 - z00, z10, z11 - z10])
        }));
    }
}

/// The largest deviation of each cell of `coarse` (level `level`) over the fine rows `rows`,
/// for the cell rows those rows meet: the index of the first cell and the cells' figures,
/// row-major. Fine row j lies in cell row j >> level and, where it starts that row, also on
/// the bottom edge of the row above.
fn band_deviations(
    coarse: &Grid,
    fine: &Grid,
    level: usize,
    rows: std::ops::Range<usize>,
) -> (usize, Vec<f64>) {
    let f = 1usize << level;
    let inv = 1.0 / f as f64;
    let [cw, ch] = coarse.cells();
    let first_row = if rows.start.is_multiple_of(f) && rows.start > 0 {
        rows.start / f - 1
    } else {
        rows.start / f
    };
    let last_row = ((rows.end - 1) / f).min(ch.saturating_sub(1));
    if ch == 0 || first_row > last_row {
        return (0, Vec::new());
    }
    let mut part = vec![0.0f64; (last_row - first_row + 1) * cw];
    // The cell rows in use, so that a cell's corners are read and checked once for all of
    // its fine rows rather than once for each.
    let (mut cur, mut prev) = (CellRow::default(), CellRow::default());
    for j in rows {
        let fine_row = &fine.samples[j * fine.cols..(j + 1) * fine.cols];
        let top = j / f;
        let above = (j.is_multiple_of(f) && j > 0).then(|| top - 1);
        for r in [above, Some(top)].into_iter().flatten() {
            if r >= ch {
                continue;
            }
            if cur.r != Some(r) {
                std::mem::swap(&mut cur, &mut prev);
                if cur.r != Some(r) {
                    cur.load(coarse, r, f, fine.cols);
                }
            }
            let fy = (j - r * f) as f64 * inv;
            let out = &mut part[(r - first_row) * cw..(r - first_row + 1) * cw];
            for (c, (worst, cell)) in out.iter_mut().zip(&cur.cells).enumerate() {
                let Some([z00, dz0, z10, dz1]) = *cell else {
                    continue;
                };
                let i0 = c * f;
                let i1 = ((c + 1) * f).min(fine.cols - 1);
                let (a, b) = (z00 + dz0 * fy, z10 + dz1 * fy);
                *worst = worst.max(row_deviation(a, b, inv, &fine_row[i0..=i1]));
            }
        }
    }
    (first_row * cw, part)
}

/// The largest |a + (b − a)·k/f − z_k| over one row of fine samples, voids skipped.
///
/// This is the inner loop of every δ, run about ten times per level-0 sample at ingest, so
/// it keeps four running maxima: one alone would chain every sample through the latency of
/// a max. A void gives NaN, which `e > w` never selects. The arithmetic is the plain formula's,
/// term for term, so the result is the same to the bit.
#[inline]
fn row_deviation(a: f64, b: f64, inv: f64, row: &[f32]) -> f64 {
    let s = b - a;
    let at = |k: usize, z: f32| (a + s * (k as f64 * inv) - z as f64).abs();
    let keep = |w: f64, e: f64| if e > w { e } else { w };
    let mut w = [0.0f64; 4];
    let mut quads = row.chunks_exact(4);
    for (q, z) in quads.by_ref().enumerate() {
        for l in 0..4 {
            w[l] = keep(w[l], at(4 * q + l, z[l]));
        }
    }
    let done = row.len() - quads.remainder().len();
    for (l, &z) in quads.remainder().iter().enumerate() {
        w[l] = keep(w[l], at(done + l, z));
    }
    w[0].max(w[1]).max(w[2].max(w[3]))
}

/// The kernel's valid cells, merged into rectangles: row runs that repeat on the next row grow
/// downwards instead of starting a new rectangle.
fn valid_rects(level: &Grid, kernel: &CellRect) -> Vec<CellRect> {
    let mut done = Vec::new();
    let mut open: Vec<CellRect> = Vec::new();
    for r in kernel.r0..kernel.r1 {
        let mut runs = Vec::new();
        let mut c = kernel.c0;
        while c < kernel.c1 {
            if level.cell_valid(c as usize, r as usize) {
                let start = c;
                while c < kernel.c1 && level.cell_valid(c as usize, r as usize) {
                    c += 1;
                }
                runs.push((start, c));
            } else {
                c += 1;
            }
        }
        let mut next = Vec::with_capacity(runs.len());
        for (c0, c1) in runs {
            match open.iter().position(|o| o.c0 == c0 && o.c1 == c1) {
                Some(k) => {
                    let mut o = open.swap_remove(k);
                    o.r1 = r + 1;
                    next.push(o);
                }
                None => next.push(CellRect {
                    c0,
                    r0: r,
                    c1,
                    r1: r + 1,
                }),
            }
        }
        done.append(&mut open);
        open = next;
    }
    done.append(&mut open);
    done.sort_by_key(|c| (c.r0, c.c0));
    done
}

/// How one level's cells are cut into kernels of `kernel × kernel` cells. Kernel boundaries
/// fall where `offset + c` is a multiple of `kernel`: level 0 takes its offset from the
/// canonical index of its lattice, so that surveys of one lattice cut it into the same tiles
/// (their patches then weigh a shared point alike), and coarser levels start at their own
/// first sample.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Tiling {
    /// Cells of the level along each axis.
    pub cells: [usize; 2],
    /// Kernel side, in cells.
    pub kernel: u32,
    /// Shifts the kernels: their boundaries fall where `offset + c` is a multiple of `kernel`.
    pub offset: [i64; 2],
}

impl Tiling {
    /// Cuts `cells` into kernels of `kernel` cells, shifted by `offset`.
    pub fn new(cells: [usize; 2], kernel: usize, offset: [i64; 2]) -> Self {
        Tiling {
            cells,
            kernel: kernel as u32,
            offset,
        }
    }

    /// The tile of the first kernel along each axis, in lattice tile numbers.
    pub fn first_tile(&self) -> [i64; 2] {
        self.offset
            .map(|o| crate::lattice::tile_of(o, self.kernel as usize))
    }

    /// Kernels along each axis.
    pub fn counts(&self) -> [usize; 2] {
        let k = self.kernel as i64;
        let f = self.first_tile();
        [0, 1].map(|a| {
            let last = (self.offset[a] + self.cells[a].max(1) as i64 - 1).div_euclid(k);
            (last - f[a] + 1) as usize
        })
    }

    /// The cells of the kernel at local position `k`, clipped to the level.
    pub fn kernel(&self, k: [u32; 2]) -> CellRect {
        let (c0, c1) = self.span(0, k[0]);
        let (r0, r1) = self.span(1, k[1]);
        CellRect { c0, r0, c1, r1 }
    }

    fn span(&self, axis: usize, k: u32) -> (u32, u32) {
        let kk = self.kernel as i64;
        let start = (self.first_tile()[axis] + k as i64) * kk - self.offset[axis];
        let lo = start.max(0) as u32;
        let hi = (start + kk).min(self.cells[axis] as i64) as u32;
        (lo, hi)
    }

    /// The local position of the kernel holding cell (c, r).
    #[inline]
    pub fn kernel_at(&self, c: u32, r: u32) -> [u32; 2] {
        let k = self.kernel as i64;
        let f = self.first_tile();
        [
            ((self.offset[0] + c as i64).div_euclid(k) - f[0]) as u32,
            ((self.offset[1] + r as i64).div_euclid(k) - f[1]) as u32,
        ]
    }

    /// Centre of the unclipped kernel at local position `k`, in level grid units.
    pub fn centre(&self, k: [u32; 2]) -> [f64; 2] {
        let kk = self.kernel as i64;
        let f = self.first_tile();
        [0, 1].map(|a| ((f[a] + k[a] as i64) * kk - self.offset[a]) as f64 + kk as f64 / 2.0)
    }

    /// A kernel grown by `margin` cells on every side, clipped to the level.
    pub fn window(&self, kernel: &CellRect, margin: u32) -> CellRect {
        CellRect {
            c0: kernel.c0.saturating_sub(margin),
            r0: kernel.r0.saturating_sub(margin),
            c1: (kernel.c1 + margin).min(self.cells[0] as u32),
            r1: (kernel.r1 + margin).min(self.cells[1] as u32),
        }
    }
}

/// The part of a patch's error that the survey's claims make: for a level-0 patch its
/// kernel's ε (in its extension zone it blends with patches of the same samples); for a
/// coarser one, which departs from those samples, the largest ε of the level-0 kernels under
/// its whole window. Its δ and whatever a placement adds come on top.
pub fn claimed_error(
    accuracy: &KernelAccuracy,
    tiling0: &Tiling,
    level: u8,
    kernel: &CellRect,
    window: &CellRect,
) -> f64 {
    if level == 0 {
        let k = tiling0.kernel_at(kernel.c0, kernel.r0);
        return accuracy.at(k);
    }
    let f = 1u32 << level;
    let [cw, ch] = tiling0.cells;
    let under = CellRect {
        c0: window.c0 * f,
        r0: window.r0 * f,
        c1: (window.c1 * f).min(cw as u32),
        r1: (window.r1 * f).min(ch as u32),
    };
    accuracy.max_over(tiling0, &under)
}

/// Cuts every level into patches and measures each patch's error, in parallel: the patches,
/// and each one's δ.
///
/// `tiling0` cuts level 0; coarser levels are cut from their first sample. A level-0 patch's
/// error is its kernel's ε; a coarser patch's is the largest ε of the level-0 kernels under its
/// window plus its own δ. A patch whose kernel
/// has no valid cell is not made: its window may hold data, but no point needs it for
/// coverage, so the cutter would only ever discard it.
pub fn make_patches(
    survey: SurveyId,
    accuracy: &KernelAccuracy,
    levels: &[Arc<Grid>],
    tiling0: &Tiling,
    layout: &PatchLayout,
    func: &dyn PatchFunction,
) -> (Vec<Patch>, Vec<f64>) {
    let m = layout.margin as u32;
    let tilings: Vec<Tiling> = levels
        .iter()
        .enumerate()
        .map(|(lv, g)| {
            if lv == 0 {
                *tiling0
            } else {
                Tiling::new(g.cells(), layout.kernel, [0, 0])
            }
        })
        .collect();
    let mut slots = Vec::new();
    for (lv, t) in tilings.iter().enumerate() {
        let [nx, ny] = t.counts();
        for pj in 0..ny as u32 {
            for pi in 0..nx as u32 {
                slots.push((lv, pi, pj));
            }
        }
    }
    let (mut patches, windows): (Vec<Patch>, Vec<(usize, CellRect)>) = slots
        .into_par_iter()
        .filter_map(|(lv, pi, pj)| {
            let g = &levels[lv];
            let t = &tilings[lv];
            let kernel = t.kernel([pi, pj]);
            if kernel.is_empty() {
                return None;
            }
            let valid = valid_rects(g, &kernel);
            if valid.is_empty() {
                return None;
            }
            let window = t.window(&kernel, m);
            let eps = claimed_error(accuracy, tiling0, lv as u8, &kernel, &window);
            let p = Patch {
                id: PatchId::derive(survey, lv as u8, [pi, pj]),
                level: lv as u8,
                index: pj * t.counts()[0] as u32 + pi,
                valid: ValidCells::of(&kernel, valid),
                error: eps,
            };
            Some((p, (lv, window)))
        })
        .unzip();
    let deltas: Vec<f64> = func
        .deviations(levels, &windows)
        .into_iter()
        // Rounding δ up by a few ulps keeps the bound a bound after f32 storage downstream.
        .map(|d| {
            if d > 0.0 {
                d * (1.0 + 1e-9) + 1e-6
            } else {
                0.0
            }
        })
        .collect();
    for (p, delta) in patches.iter_mut().zip(&deltas) {
        p.error += delta;
    }
    (patches, deltas)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Georef;
    use crate::mipmap;

    fn grid(cols: usize, rows: usize, f: impl Fn(usize, usize) -> f32) -> Arc<Grid> {
        let s = (0..rows)
            .flat_map(|r| (0..cols).map(move |c| (c, r)))
            .map(|(c, r)| f(c, r))
            .collect();
        Arc::new(Grid::new(cols, rows, s, Georef::north_up([0.0, 0.0], [1.0, 1.0])).unwrap())
    }

    #[test]
    fn kernels_tile_each_level_exactly_once() {
        let g = grid(100, 61, |c, r| ((c * 7 + r * 3) % 11) as f32);
        let levels = mipmap::build(g, 28);
        let t0 = Tiling::new(levels[0].cells(), 28, [-5, 17]);
        let (patches, _) = make_patches(
            SurveyId(1),
            &KernelAccuracy::constant(&t0, 0.0),
            &levels,
            &t0,
            &PatchLayout::default(),
            &Bilinear,
        );
        for (lv, level) in levels.iter().enumerate() {
            let [cw, ch] = level.cells();
            let mut seen = vec![0u8; cw * ch];
            // A patch keeps its kernel's place in the tiling, row-major: it gives back the
            // index its id was made with, and the kernel.
            let t = if lv == 0 {
                t0
            } else {
                Tiling::new(level.cells(), 28, [0, 0])
            };
            let nx = t.counts()[0] as u32;
            for p in patches.iter().filter(|p| p.level as usize == lv) {
                let index = [p.index % nx, p.index / nx];
                let kernel = t.kernel(index);
                assert_eq!(t.kernel_at(kernel.c0, kernel.r0), index, "level {lv}");
                assert_eq!(PatchId::derive(SurveyId(1), p.level, index), p.id);
                for r in kernel.r0..kernel.r1 {
                    for c in kernel.c0..kernel.c1 {
                        seen[r as usize * cw + c as usize] += 1;
                    }
                }
            }
            assert!(seen.iter().all(|&n| n == 1), "level {lv}");
        }
    }

    #[test]
    fn delta_is_exact_on_a_single_spike() {
        // One spike in a flat field: the coarse level smooths it, and δ must be the full
        // distance between the spike and the coarse surface at that sample.
        let g = grid(9, 9, |c, r| if (c, r) == (3, 3) { 10.0 } else { 0.0 });
        let levels = vec![g.clone(), Arc::new(mipmap::downsample(&g))];
        let w = CellRect {
            c0: 0,
            r0: 0,
            c1: 4,
            r1: 4,
        };
        let d = Bilinear.max_deviation(&levels, 1, &w);
        let coarse_at_spike = levels[1].bilinear_grid([1.5, 1.5]).unwrap();
        let mut expect = (10.0 - coarse_at_spike).abs();
        for r in 0..9 {
            for c in 0..9 {
                let z = g.at(c, r) as f64;
                let p = levels[1]
                    .bilinear_grid([c as f64 / 2.0, r as f64 / 2.0])
                    .unwrap();
                expect = expect.max((z - p).abs());
            }
        }
        assert!((d - expect).abs() < 1e-9, "{d} vs {expect}");
        // And it bounds the difference at arbitrary points, not only at samples.
        for k in 0..400 {
            let x = (k % 20) as f64 * 0.4;
            let y = (k / 20) as f64 * 0.4;
            let a = g.bilinear_grid([x, y]).unwrap();
            let b = levels[1].bilinear_grid([x / 2.0, y / 2.0]).unwrap();
            assert!((a - b).abs() <= d + 1e-9);
        }
    }

    #[test]
    fn cell_deviations_are_the_plain_formula_to_the_bit() {
        // Rough heights with voids, on sizes that leave partial cells at the far edges.
        for (cols, rows) in [(37, 29), (64, 65), (9, 130), (300, 270)] {
            let g = grid(cols, rows, |c, r| {
                let h = (c * 7919 + r * 104_729) % 1009;
                if h % 53 == 0 {
                    f32::NAN
                } else {
                    (h as f32 * 0.37).sin() * 300.0 + h as f32 * 0.013
                }
            });
            let mut levels = vec![g];
            while levels.last().unwrap().cols > 2 && levels.last().unwrap().rows > 2 {
                levels.push(Arc::new(mipmap::downsample(levels.last().unwrap())));
            }
            let all = Bilinear.cell_deviations(&levels);
            for lv in 1..levels.len() {
                let (coarse, fine) = (&levels[lv], &levels[0]);
                let f = 1usize << lv;
                let [cw, ch] = coarse.cells();
                let got = &all[lv];
                for r in 0..ch {
                    for c in 0..cw {
                        let mut worst = 0.0f64;
                        if coarse.cell_valid(c, r) && r * f < fine.rows && c * f < fine.cols {
                            for j in r * f..=((r + 1) * f).min(fine.rows - 1) {
                                for i in c * f..=((c + 1) * f).min(fine.cols - 1) {
                                    let (fx, fy) = (
                                        (i - c * f) as f64 / f as f64,
                                        (j - r * f) as f64 / f as f64,
                                    );
                                    let a = coarse.at(c, r) as f64
                                        + (coarse.at(c, r + 1) as f64 - coarse.at(c, r) as f64)
                                            * fy;
                                    let b = coarse.at(c + 1, r) as f64
                                        + (coarse.at(c + 1, r + 1) as f64
                                            - coarse.at(c + 1, r) as f64)
                                            * fy;
                                    let z = fine.at(i, j);
                                    if !z.is_nan() {
                                        worst = worst.max((a + (b - a) * fx - z as f64).abs());
                                    }
                                }
                            }
                        }
                        assert_eq!(
                            got[r * cw + c].to_bits(),
                            worst.to_bits(),
                            "{cols}x{rows} level {lv} cell {c},{r}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn the_bicubic_bound_holds_everywhere_and_is_near_tight() {
        // Rough heights with voids and a cliff, so that the spline overshoots.
        let g = grid(120, 100, |c, r| {
            let h = (c * 7919 + r * 104_729) % 1009;
            if (40..44).contains(&c) && (30..37).contains(&r) {
                f32::NAN
            } else {
                (h as f32 * 0.37).sin() * 20.0 + if c > 70 { 300.0 } else { 0.0 }
            }
        });
        let levels = mipmap::build(g.clone(), 8);
        let mut next = patchwork_geom::rng::uniform(99);
        for lv in 0..levels.len().min(3) {
            let coarse = &levels[lv];
            let f = (1usize << lv) as f64;
            let [cw, ch] = coarse.cells();
            for (c0, r0) in [(0u32, 0u32), (3, 5), (cw as u32 / 2, ch as u32 / 3)] {
                let w = CellRect {
                    c0,
                    r0,
                    c1: (c0 + 12).min(cw as u32),
                    r1: (r0 + 12).min(ch as u32),
                };
                let bound = Bicubic.max_deviation(&levels, lv, &w);
                let spline = Bicubic::spline(coarse, &w);
                let mut seen = 0.0f64;
                // Random points, and every level-0 sample, where a maximum often lies.
                let fine_steps =
                    (w.cols() as usize * (1 << lv) + 1) * (w.rows() as usize * (1 << lv) + 1);
                for k in 0..4000 + fine_steps {
                    let (gx, gy) = if k < 4000 {
                        (
                            w.c0 as f64 + next() * w.cols() as f64,
                            w.r0 as f64 + next() * w.rows() as f64,
                        )
                    } else {
                        let i = k - 4000;
                        let across = w.cols() as usize * (1 << lv) + 1;
                        (
                            w.c0 as f64 + (i % across) as f64 / f,
                            w.r0 as f64 + (i / across) as f64 / f,
                        )
                    };
                    let (cx, cy) = (
                        (gx as usize).min(w.c1 as usize - 1),
                        (gy as usize).min(w.r1 as usize - 1),
                    );
                    if !coarse.cell_valid(cx, cy) {
                        continue;
                    }
                    let z = spline.eval([gx - w.c0 as f64, gy - w.r0 as f64]);
                    let reference = g.bilinear_grid([gx * f, gy * f]).unwrap();
                    seen = seen.max((z - reference).abs());
                }
                assert!(seen <= bound + 1e-9, "level {lv}: {seen} > {bound}");
                assert!(seen >= 0.9 * bound - 2e-3, "level {lv}: {seen} ≪ {bound}");
            }
        }
    }

    #[test]
    fn valid_rects_cover_exactly_the_valid_cells() {
        let g = grid(30, 30, |c, r| {
            if (5..9).contains(&c) && (4..20).contains(&r) || (c + r) % 13 == 0 {
                f32::NAN
            } else {
                1.0
            }
        });
        let k = CellRect {
            c0: 0,
            r0: 0,
            c1: 29,
            r1: 29,
        };
        let rects = valid_rects(&g, &k);
        for r in 0..29 {
            for c in 0..29 {
                let n = rects
                    .iter()
                    .filter(|q| (q.c0..q.c1).contains(&c) && (q.r0..q.r1).contains(&r))
                    .count();
                assert_eq!(n, usize::from(g.cell_valid(c as usize, r as usize)));
            }
        }
    }
}
