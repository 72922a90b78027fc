//! A survey: one grid, its mipmap and its patches, ready for the index.

use super::accuracy::{self, AccuracySpec, KernelAccuracy};
use super::edge;
use super::epoch::Epoch;
use super::grid::{Grid, Shape};
use super::ids::{hash64, PatchId, SurveyId};
use super::lattice::Lattice;
use super::mipmap;
use super::mipmap::Filter;
use super::patch::{make_patches, CellRect, Patch, PatchKind, PatchLayout, Tiling};
use super::place::{self, PlaceError, Placement, PlaneId, Planes, STORE_PLANE};
use patchwork_crs::vertical::VerticalCrs;
use patchwork_crs::Crs;
use patchwork_geom::Aabb;
use std::sync::Arc;
use thiserror::Error;

/// Why a grid cannot be built into a survey.
#[derive(Debug, Error, PartialEq)]
pub enum SurveyError {
    /// Every sample is nodata.
    #[error("the raster has no valid sample: every sample is nodata")]
    AllNodata,
    /// A fixed ε that is negative or not finite.
    #[error("accuracy must be a finite number of metres ≥ 0, got {0}")]
    BadAccuracy(f64),
    /// A patch layout whose kernel has no cell.
    #[error("the patch layout needs a kernel of at least one cell, got {0}")]
    BadLayout(usize),
}

/// How a store makes its surveys' coarser levels and their patches: chosen when the store is
/// made, and the same for every survey in it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Recipe {
    /// How coarser levels' samples are made.
    pub mipmap: Filter,
    /// The function the patches evaluate.
    pub patches: PatchKind,
}

/// What the index keeps of a survey: everything but its samples, which the store serves from
/// disk when a patch is read.
#[derive(Clone, Debug)]
pub struct SurveyMeta {
    /// Derived from its content (see [`Survey::id_of`]).
    pub id: SurveyId,
    /// ε, in metres: the largest over the survey's kernels.
    pub accuracy: f64,
    /// How its ε was decided: given, or estimated from its samples.
    pub spec: AccuracySpec,
    /// The survey's horizontal CRS, where known: its plane.
    pub crs: Option<Crs>,
    /// What its heights are measured from, where known: the store's vertical CRS, once
    /// heights in another were converted to it.
    pub vertical: Option<VerticalCrs>,
    /// Where it lies in the store's plane, for a survey in another CRS; None in the store's
    /// own (see [`Survey::placed`]).
    pub placement: Option<Arc<Placement>>,
    /// The CRS of the store its patches' errors were made for, once placed in one (see
    /// [`Survey::placed`]); None for a survey just built.
    pub placed_in: Option<Crs>,
    /// How its levels are cut into patches.
    pub layout: PatchLayout,
    /// The function its patches evaluate.
    pub kind: PatchKind,
    /// How level 0 is cut into kernels.
    pub tiling: Tiling,
    /// ε of every level-0 kernel.
    pub kernel_accuracy: KernelAccuracy,
    /// The levels' sizes and georeferences, level 0 first.
    pub shapes: Vec<Shape>,
    /// Its patches, of every level, with the errors the survey's own claims give them. A
    /// survey whose claims other surveys' evidence raised shares this list with the survey as
    /// it came (see [`SurveyMeta::with_raised_claims`]), so that an overlap does not hold every
    /// patch of it twice; [`SurveyMeta::error_at`] is a patch's error as the index takes it.
    pub patches: Arc<[Patch]>,
    /// The errors that raised claims changed: none for a survey as it came.
    pub raised: Option<Raised>,
    /// The lattice tiles whose edge patches this survey's samples can reach (see
    /// [`edge::edge_tiles`]): found once from the samples, so that inserting or retiring a
    /// neighbour never has to read them all again.
    pub edge_tiles: Vec<[i64; 2]>,
    /// When it was acquired, where known: where it and an overlapping survey disagree by
    /// change (see [`crate::change`]), the one acquired wholly after the other serves.
    pub epoch: Option<Epoch>,
}

/// The errors of a survey's patches that raised claims changed (see
/// [`SurveyMeta::with_raised_claims`]).
#[derive(Clone, Debug, PartialEq)]
pub enum Raised {
    /// Those that changed, by patch id, ascending: where few did.
    Some(Arc<[(PatchId, f64)]>),
    /// Every patch's, by its place in the list: where most changed, 8 bytes a patch where
    /// the list by id takes 16 for each patch in it.
    All(Arc<[f64]>),
}

/// A patch's valid cells ([`SurveyMeta::valid`]): its whole kernel, or the rectangles it
/// keeps where they are not.
#[derive(Clone, Copy, Debug)]
pub enum Valid<'a> {
    /// The whole kernel.
    Whole(CellRect),
    /// Disjoint rectangles inside it.
    Parts(&'a [CellRect]),
}

impl std::ops::Deref for Valid<'_> {
    type Target = [CellRect];
    #[inline]
    fn deref(&self) -> &[CellRect] {
        match self {
            Valid::Whole(k) => std::slice::from_ref(k),
            Valid::Parts(v) => v,
        }
    }
}

/// A survey with its samples: what a reader's grid becomes before it is stored.
#[derive(Clone, Debug)]
pub struct Survey {
    /// What the index keeps of it.
    pub meta: Arc<SurveyMeta>,
    /// Level 0 first.
    pub levels: Vec<Arc<Grid>>,
    /// Each patch's δ, the largest vertical distance to level 0 anywhere in its window (0 for
    /// level 0), in the order of `meta.patches`: what the store keeps beside each patch, and
    /// the index never needs apart from the error it is part of (8 bytes a patch less held).
    pub deltas: Arc<[f64]>,
}

impl std::ops::Deref for Survey {
    type Target = SurveyMeta;
    fn deref(&self) -> &SurveyMeta {
        &self.meta
    }
}

impl SurveyMeta {
    /// ε at level-0 sample (c, r): the largest of the kernels it is a corner of.
    pub fn accuracy_at(&self, c: usize, r: usize) -> f64 {
        let [cw, ch] = self.shapes[0].cells();
        let cell = super::patch::CellRect {
            c0: (c as u32).saturating_sub(1),
            r0: (r as u32).saturating_sub(1),
            c1: (c as u32 + 1).min(cw as u32),
            r1: (r as u32 + 1).min(ch as u32),
        };
        self.kernel_accuracy.max_over(&self.tiling, &cell)
    }

    /// How level `level` is cut into kernels: level 0 as the survey's lattice says, coarser
    /// levels from their first sample.
    pub fn level_tiling(&self, level: usize) -> Tiling {
        if level == 0 {
            self.tiling
        } else {
            Tiling::new(self.shapes[level].cells(), self.layout.kernel, [0, 0])
        }
    }

    /// Centre of the unclipped window of `p`, one of the survey's patches, in its level's
    /// grid units. The blending weight uses it and [`SurveyMeta::half`], so that a kernel edge
    /// lying on the grid border still gets a positive weight. Worked out when asked rather
    /// than kept with each patch: an index holds a patch for every 576 samples.
    pub fn centre(&self, p: &Patch) -> [f64; 2] {
        let t = self.level_tiling(p.level as usize);
        t.centre(Self::place(&t, p))
    }

    /// The place of `p`, one of the survey's patches, in its level's tiling of kernels: the
    /// index its id was derived from.
    #[inline]
    pub fn kernel_index(&self, p: &Patch) -> [u32; 2] {
        Self::place(&self.level_tiling(p.level as usize), p)
    }

    /// `p`'s place in `t`, its level's tiling, from its row-major index.
    #[inline]
    fn place(t: &Tiling, p: &Patch) -> [u32; 2] {
        let nx = t.counts()[0].max(1) as u32;
        [p.index % nx, p.index / nx]
    }

    /// The kernel of `p`, one of the survey's patches: its cells, clipped to its level.
    #[inline]
    pub fn kernel(&self, p: &Patch) -> CellRect {
        let t = self.level_tiling(p.level as usize);
        t.kernel(Self::place(&t, p))
    }

    /// The window of `p`, one of the survey's patches: its kernel grown by the layout's
    /// margin, clipped to its level's grid.
    #[inline]
    pub fn window(&self, p: &Patch) -> CellRect {
        let t = self.level_tiling(p.level as usize);
        t.window(&t.kernel(Self::place(&t, p)), self.layout.margin as u32)
    }

    /// The kernel of `p` and its window at once, for the callers that need both.
    #[inline]
    pub fn kernel_and_window(&self, p: &Patch) -> (CellRect, CellRect) {
        let t = self.level_tiling(p.level as usize);
        let k = t.kernel(Self::place(&t, p));
        (k, t.window(&k, self.layout.margin as u32))
    }

    /// The valid cells of `p`'s kernel as disjoint rectangles: where it covers a point.
    #[inline]
    pub fn valid<'a>(&self, p: &'a Patch) -> Valid<'a> {
        match p.valid.parts() {
            None => Valid::Whole(self.kernel(p)),
            Some(v) => Valid::Parts(v),
        }
    }

    /// Half the unclipped window's side along each axis, in cells: half a kernel and a
    /// margin, the same for every patch.
    pub fn half(&self) -> [f64; 2] {
        let h = self.layout.kernel as f64 / 2.0 + self.layout.margin as f64;
        [h, h]
    }

    /// The error of the patch at `k` in the survey's list, as the index takes it: its own,
    /// or what raised claims made it.
    #[inline]
    pub fn error_at(&self, k: usize) -> f64 {
        let p = &self.patches[k];
        match &self.raised {
            None => p.error,
            Some(Raised::All(e)) => e[k],
            Some(Raised::Some(r)) => r
                .binary_search_by_key(&p.id, |&(id, _)| id)
                .map_or(p.error, |i| r[i].1),
        }
    }

    /// The survey with its claims raised where other surveys' evidence contradicts them
    /// (see [`super::evidence`]): each kernel listed (row-major index, least ε) to at least
    /// that ε, and every patch's error by what that adds to the part its claims make. The
    /// patches themselves are shared; the errors raised are listed beside them.
    pub fn with_raised_claims(&self, raise: &[(u32, f32)]) -> SurveyMeta {
        let mut m = self.clone();
        for &(k, v) in raise {
            let e = &mut m.kernel_accuracy.values[k as usize];
            *e = e.max(v as f64);
        }
        m.accuracy = m.kernel_accuracy.max();
        let errors: Vec<f64> = (0..self.patches.len())
            .map(|k| {
                let p = &self.patches[k];
                let (kernel, window) = self.kernel_and_window(p);
                let claim = |a: &KernelAccuracy| {
                    super::patch::claimed_error(a, &self.tiling, p.level, &kernel, &window)
                };
                let (before, after) = (claim(&self.kernel_accuracy), claim(&m.kernel_accuracy));
                let own = self.error_at(k);
                if after > before {
                    own + (after - before)
                } else {
                    own
                }
            })
            .collect();
        let changed: Vec<usize> = (0..errors.len())
            .filter(|&k| errors[k] != self.patches[k].error)
            .collect();
        m.raised = if changed.is_empty() {
            None
        } else if 2 * changed.len() > errors.len() {
            Some(Raised::All(errors.into()))
        } else {
            let mut some: Vec<(PatchId, f64)> = changed
                .into_iter()
                .map(|k| (self.patches[k].id, errors[k]))
                .collect();
            some.sort_unstable_by_key(|&(id, _)| id);
            Some(Raised::Some(some.into()))
        };
        m
    }

    /// The CRS of the store the survey is placed in, or would be by default: the store it
    /// was placed for, else its own.
    pub fn placed_for(&self) -> Option<Crs> {
        self.placed_in.clone().or_else(|| self.crs.clone())
    }

    /// The plane the survey's grid is in: the store's, or its own CRS's.
    pub fn plane_id(&self) -> PlaneId {
        self.placement.as_ref().map_or(STORE_PLANE, |p| p.plane.id)
    }

    /// The store-plane bounds of the survey's samples.
    pub fn footprint(&self) -> Aabb {
        match &self.placement {
            Some(p) => p.footprint,
            None => self.shapes[0].world_bounds(),
        }
    }

    /// Where its patches lie in the store's plane, for a survey of another CRS whose patches
    /// (and their errors) are as a store of this CRS keeps them. None for the store's own.
    pub fn placement_in(&self, planes: &Planes) -> Result<Option<Arc<Placement>>, PlaceError> {
        let Some(crs) = &self.crs else {
            return Ok(None);
        };
        let Some(plane) = planes.get(crs)? else {
            return Ok(None);
        };
        let windows: Vec<(usize, CellRect)> = self
            .patches
            .iter()
            .map(|p| (p.level as usize, self.window(p)))
            .collect();
        Placement::new(plane, &self.shapes, windows).map(|p| Some(Arc::new(p)))
    }

    /// Metres per unit of the survey's own CRS along x and y, at its middle: its linear unit
    /// for a projected CRS, the ellipsoid's local scale for a geographic one (1 without a
    /// CRS).
    pub fn metres_per_unit(&self) -> [f64; 2] {
        match &self.crs {
            Some(c) if c.is_geographic() => {
                let g = &self.shapes[0];
                let mid = g.georef.to_world(g.cols as f64 / 2.0, g.rows as f64 / 2.0);
                patchwork_crs::metres_per_degree(mid[1])
            }
            Some(c) => [c.unit_m().unwrap_or(1.0); 2],
            None => [1.0, 1.0],
        }
    }

    /// Area of one level-0 cell on the ground, in square metres (so that surveys of two CRSs
    /// compare).
    pub fn cell_area(&self) -> f64 {
        let s = self.shapes[0].georef.step;
        let m = self.metres_per_unit();
        s[0] * m[0] * s[1] * m[1]
    }

    /// Whether this survey's samples are the finer of two overlapping surveys': the smaller
    /// cell, at equal cells the smaller id. Overlaps are measured at the finer survey's samples,
    /// so that the figure is the same whichever was inserted first.
    pub fn finer_than(&self, o: &SurveyMeta) -> bool {
        self.cell_area()
            .total_cmp(&o.cell_area())
            .then(self.id.cmp(&o.id))
            .is_lt()
    }

    /// Samples in every level, the mipmap's storage cost.
    pub fn stored_samples(&self) -> usize {
        self.shapes.iter().map(|l| l.cols * l.rows).sum()
    }

    /// Where the survey's sample (0, 0) is on its lattice.
    pub fn lattice_index(&self) -> [i64; 2] {
        let g = &self.shapes[0].georef;
        Lattice::of(g).index_of(g)
    }
}

impl Survey {
    /// The id of a survey's content. Two files with the same samples, georeference, CRS and
    /// accuracy (or both with an estimated one) are the same survey.
    pub fn id_of(grid: &Grid, spec: AccuracySpec, crs: Option<&Crs>) -> SurveyId {
        let mut h = blake3::Hasher::new();
        h.update(b"patchwork.survey.v1");
        h.update(&(grid.cols as u64).to_le_bytes());
        h.update(&(grid.rows as u64).to_le_bytes());
        let g = &grid.georef;
        for v in [g.origin[0], g.origin[1], g.theta, g.step[0], g.step[1]] {
            h.update(&v.to_bits().to_le_bytes());
        }
        // Only a skewed or mirrored grid has a row angle of its own, and only it hashes one:
        // every other survey keeps the id it always had.
        if let Some(psi) = g.row_theta {
            h.update(b"row_theta");
            h.update(&psi.to_bits().to_le_bytes());
        }
        match spec {
            AccuracySpec::Fixed(a) => h.update(&a.to_bits().to_le_bytes()),
            // The estimate is a function of the samples, so the samples name it.
            AccuracySpec::Auto => h.update(b"auto.v1"),
        };
        // An EPSG CRS hashes its code, as every survey always has; a definition without one,
        // its canonical text.
        match crs.map(|c| (c.epsg_code(), c)) {
            None => h.update(&0u32.to_le_bytes()),
            Some((Some(code), _)) => h.update(&code.to_le_bytes()),
            Some((None, c)) => {
                h.update(&0u32.to_le_bytes());
                h.update(b"crs");
                h.update(c.key().as_bytes())
            }
        };
        // One NaN bit pattern for every void, so that how a file spelled nodata does not matter.
        let mut buf = Vec::with_capacity(4 * 4096);
        for chunk in grid.samples.chunks(4096) {
            buf.clear();
            for &z in chunk {
                let z = if z.is_nan() { f32::NAN } else { z };
                buf.extend_from_slice(&z.to_bits().to_le_bytes());
            }
            h.update(&buf);
        }
        SurveyId(hash64(h))
    }

    /// The level-0 tiling of a grid: kernels on its lattice's canonical tiles.
    pub fn tiling_of(grid: &Grid, layout: &PatchLayout) -> Tiling {
        let lattice = Lattice::of(&grid.georef);
        Tiling::new(grid.cells(), layout.kernel, lattice.index_of(&grid.georef))
    }

    /// Builds the mipmap (with the default filter) and the patches with their errors.
    pub fn build(
        grid: Grid,
        spec: impl Into<AccuracySpec>,
        crs: Option<Crs>,
        layout: PatchLayout,
    ) -> Result<Survey, SurveyError> {
        Self::build_with(grid, spec, crs, layout, Recipe::default())
    }

    /// [`Survey::build`] with the mipmap and patches `recipe` says. A store builds all its
    /// surveys with one recipe, chosen when it was made.
    pub fn build_with(
        grid: Grid,
        spec: impl Into<AccuracySpec>,
        crs: Option<Crs>,
        layout: PatchLayout,
        recipe: Recipe,
    ) -> Result<Survey, SurveyError> {
        Self::build_adding(grid, spec, crs, layout, recipe, 0.0)
    }

    /// [`Survey::build_with`], with `extra` metres added to an estimated ε everywhere: what a
    /// conversion of the heights between vertical CRSs may have added to their error. (A
    /// fixed ε comes with it added already, so that the survey's id hashes what its record
    /// keeps.)
    pub fn build_adding(
        grid: Grid,
        spec: impl Into<AccuracySpec>,
        crs: Option<Crs>,
        layout: PatchLayout,
        recipe: Recipe,
        extra: f64,
    ) -> Result<Survey, SurveyError> {
        let spec = spec.into();
        if let AccuracySpec::Fixed(a) = spec {
            if !(a.is_finite() && a >= 0.0) {
                return Err(SurveyError::BadAccuracy(a));
            }
        }
        if layout.kernel == 0 {
            return Err(SurveyError::BadLayout(layout.kernel));
        }
        if grid.valid_count() == 0 {
            return Err(SurveyError::AllNodata);
        }
        let tiling = Self::tiling_of(&grid, &layout);
        let grid = Arc::new(grid);
        // The content hash and the accuracy estimate read level 0 as the mipmap does, and
        // neither needs the other: side by side they fill the cores that the mipmap's
        // coarsest levels leave idle.
        let ((id, kernel_accuracy), levels) = rayon::join(
            || {
                let id = Self::id_of(&grid, spec, crs.as_ref());
                let kernels = match spec {
                    AccuracySpec::Fixed(a) => KernelAccuracy::constant(&tiling, a),
                    AccuracySpec::Auto => {
                        let mut k =
                            accuracy::estimate(&grid, &tiling, layout.margin as u32).kernels;
                        if extra > 0.0 {
                            k.values.iter_mut().for_each(|v| *v += extra);
                        }
                        k
                    }
                };
                (id, kernels)
            },
            || mipmap::build_with(grid.clone(), layout.kernel, recipe.mipmap),
        );
        let func = recipe.patches.function();
        let (patches, deltas) = make_patches(id, &kernel_accuracy, &levels, &tiling, &layout, func);
        Ok(Self::restore(
            id,
            spec,
            crs,
            layout,
            recipe.patches,
            tiling,
            kernel_accuracy,
            levels,
            patches,
            deltas,
        ))
    }

    /// A survey from its parts: as [`Survey::build`] makes them, or as a store kept them.
    #[allow(clippy::too_many_arguments)]
    pub fn restore(
        id: SurveyId,
        spec: AccuracySpec,
        crs: Option<Crs>,
        layout: PatchLayout,
        kind: PatchKind,
        tiling: Tiling,
        kernel_accuracy: KernelAccuracy,
        levels: Vec<Arc<Grid>>,
        patches: Vec<Patch>,
        deltas: Vec<f64>,
    ) -> Survey {
        assert_eq!(patches.len(), deltas.len(), "a δ for every patch");
        let index = Lattice::of(&levels[0].georef).index_of(&levels[0].georef);
        let edge_tiles = edge::edge_tiles(&levels[0], index, &layout);
        Survey {
            meta: Arc::new(SurveyMeta {
                id,
                accuracy: kernel_accuracy.max(),
                spec,
                crs,
                vertical: None,
                placement: None,
                placed_in: None,
                layout,
                kind,
                tiling,
                kernel_accuracy,
                shapes: levels.iter().map(|g| g.shape()).collect(),
                patches: patches.into(),
                raised: None,
                edge_tiles,
                epoch: None,
            }),
            levels,
            deltas: deltas.into(),
        }
    }

    /// The survey acquired over `epoch` (None where unknown): what decides, where it and an
    /// overlapping survey saw different ground, which one serves there.
    pub fn with_epoch(mut self, epoch: Option<Epoch>) -> Survey {
        Arc::make_mut(&mut self.meta).epoch = epoch;
        self
    }

    /// What the index keeps of the survey.
    pub fn meta(&self) -> Arc<SurveyMeta> {
        self.meta.clone()
    }

    /// The survey as a store of the planes' CRS keeps it: in the store's own CRS unchanged;
    /// in another, placed in the store's plane, every patch's error grown by what the
    /// reprojection can cost there (see [`crate::place`]).
    ///
    /// A survey already placed in a store of that CRS (one read back from it) keeps its
    /// errors, and gets its patches' frames; one placed for another store is refused.
    pub fn placed(&self, planes: &Planes) -> Result<Survey, PlaceError> {
        let store = planes.store_crs();
        let keep = match &self.placed_in {
            Some(c) if c == store => true,
            Some(c) => {
                return Err(PlaceError::Elsewhere {
                    placed: c.label(),
                    store: store.label(),
                })
            }
            None => false,
        };
        let placement = match (&self.placement, keep) {
            (Some(p), true) => Some(p.clone()),
            _ => self.placement_in(planes)?,
        };
        let mut meta = (*self.meta).clone();
        meta.placed_in = Some(store.clone());
        let Some(placement) = placement else {
            meta.placement = None;
            return Ok(Survey {
                meta: Arc::new(meta),
                levels: self.levels.clone(),
                deltas: self.deltas.clone(),
            });
        };
        if keep {
            meta.placement = Some(placement);
            return Ok(Survey {
                meta: Arc::new(meta),
                levels: self.levels.clone(),
                deltas: self.deltas.clone(),
            });
        }
        let rho = placement.residuals.to_native;
        let g0 = &self.shapes[0].georef;
        let slopes = place::kernel_slopes(&self.levels[0], &self.tiling);
        let [cw, ch] = self.shapes[0].cells();
        // A survey is placed as it came, before any evidence raises its claims.
        debug_assert!(
            meta.raised.is_none(),
            "a survey placed after its claims were raised"
        );
        let mut patches = meta.patches.to_vec();
        for p in patches.iter_mut() {
            let f = 1u32 << p.level;
            let w = meta.window(p);
            let under = CellRect {
                c0: w.c0 * f,
                r0: w.r0 * f,
                c1: (w.c1 * f).min(cw as u32),
                r1: (w.r1 * f).min(ch as u32),
            };
            p.error += place::reprojection_error(rho, g0, &slopes, &self.tiling, &under);
        }
        meta.patches = patches.into();
        meta.placement = Some(placement);
        Ok(Survey {
            meta: Arc::new(meta),
            levels: self.levels.clone(),
            deltas: self.deltas.clone(),
        })
    }
}
