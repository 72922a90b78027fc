//! The in-memory engine: surveys, the edge patches their lattices call for, their LOD index,
//! and the queries and tiles built on them. It does no I/O: the samples of stored surveys come
//! through a [`SampleSource`], and the store persists what it holds.

use patchwork_crs::Crs;
use patchwork_geom::Aabb;
use patchwork_index::lod::{BoxState, ChangeStats, IndexConfig, LodIndex, UnitBoxes};
use patchwork_index::quadtree::{At, Entry, MsQuadtree};
use patchwork_index::query::{shortfall, Extracted, Shortfall, ViewQuery};
use patchwork_model::edge::{self, EdgeGrid, EdgePatch, Member};
use patchwork_model::evidence::{self, Blame, Contradicted, PairEvidence};
use patchwork_model::grid::{Grid, SampleRect, Window};
use patchwork_model::ids::{PatchId, SurveyId};
use patchwork_model::lattice::{tile_of, Lattice};
use patchwork_model::patch::{Blend, Patch, PatchLayout};
use patchwork_model::place::{
    self, Frame, PlaceError, Plane, PlaneId, Planes, Residuals, STORE_PLANE,
};
use patchwork_model::source::{SampleError, SampleSource};
use patchwork_model::survey::{Survey, SurveyMeta};
use patchwork_resample::{cpu, Cancel, PatchSet, ResolvedPatch, SampleGrid, BLOCK};
use rayon::prelude::*;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;

/// Why a survey could not be inserted or retired.
#[derive(Clone, Debug, thiserror::Error, PartialEq)]
pub enum TerrainError {
    /// The samples of the survey or of a neighbour could not be read.
    #[error(transparent)]
    Samples(#[from] SampleError),
    /// The survey could not be placed in the terrain's CRS.
    #[error(transparent)]
    Place(#[from] PlaceError),
}

/// The bounds, in a plane, of a rectangle of the store's plane: its border carried there
/// (the store's plane itself for None), a thousandth of its extent wider.
fn native_bounds(plane: Option<&Plane>, b: &Aabb) -> Option<Aabb> {
    let Some(plane) = plane else {
        return Some(*b);
    };
    let n = 32;
    let mut pts = Vec::with_capacity(4 * n);
    for k in 0..n {
        let t = k as f64 / n as f64;
        let (x, y) = (b.min[0] + t * b.width(), b.min[1] + t * b.height());
        for p in [
            [x, b.min[1]],
            [b.max[0], y],
            [b.max[0] - t * b.width(), b.max[1]],
            [b.min[0], b.max[1] - t * b.height()],
        ] {
            pts.push(plane.to_native.at(p)?);
        }
    }
    let a = Aabb::of_points(&pts);
    Some(a.grown(1e-3 * a.width().max(a.height())))
}

/// What the reprojection can cost the heights of an edge patch whose samples are `g`: as for
/// a survey's patch (see [`place::reprojection_error`]), with the largest slope of its own
/// cells.
fn edge_reprojection_error(g: &EdgeGrid, rho: f64) -> f64 {
    std::f64::consts::SQRT_2 * rho * g.georef.cells_per_unit() * g.slope
}

/// An edge patch as a terrain that can read its members' samples keeps it: without its own.
fn bare(e: Arc<EdgePatch>) -> Arc<EdgePatch> {
    if e.grid.is_some() {
        Arc::new(e.without_grid())
    } else {
        e
    }
}

/// The edge patches' samples a terrain made again from their members', by patch id, bounded
/// in bytes. An edge patch's id names what it holds, so every snapshot of the terrain shares
/// the one cache.
#[derive(Clone)]
struct EdgeGrids(Arc<quick_cache::sync::Cache<PatchId, Arc<EdgeGrid>, GridBytes>>);

#[derive(Clone)]
struct GridBytes;

impl quick_cache::Weighter<PatchId, Arc<EdgeGrid>> for GridBytes {
    fn weight(&self, _: &PatchId, g: &Arc<EdgeGrid>) -> u64 {
        (g.heap_bytes() + std::mem::size_of::<EdgeGrid>()) as u64
    }
}

impl EdgeGrids {
    /// A cache of at most `bytes` of samples: a grid is about 10 kB.
    fn new(bytes: u64) -> Self {
        let items = (bytes / 10_000).max(16) as usize;
        EdgeGrids(Arc::new(quick_cache::sync::Cache::with_weighter(
            items, bytes, GridBytes,
        )))
    }
}

impl std::fmt::Debug for EdgeGrids {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EdgeGrids")
            .field("bytes", &self.0.weight())
            .field("grids", &self.0.len())
            .finish()
    }
}

/// What a terrain keeps of the edge patches' samples it makes again, unless told otherwise
/// (see [`Terrain::set_edge_cache`]).
const EDGE_CACHE_BYTES: u64 = 16 << 20;

/// The key of a pair: its surveys' ids, smaller first.
fn pair_key(a: SurveyId, b: SurveyId) -> (SurveyId, SurveyId) {
    if a < b {
        (a, b)
    } else {
        (b, a)
    }
}

/// What a survey's claims are raised to where others contradict them: (row-major kernel
/// index, least ε), ascending, as [`SurveyMeta::with_raised_claims`] takes it.
type Raise = Arc<[(u32, f32)]>;

/// Whether `raise` gives the survey `base` other claims than `now`, the survey as a terrain
/// holds it. A survey's errors follow from its kernels' claims, so that equal claims make the
/// same survey: no list of the raises in force is kept beside it.
fn claims_differ(base: &Arc<SurveyMeta>, raise: &[(u32, f32)], now: &Arc<SurveyMeta>) -> bool {
    if raise.is_empty() {
        return !Arc::ptr_eq(base, now)
            && base.kernel_accuracy.values != now.kernel_accuracy.values;
    }
    let mut want = base.kernel_accuracy.values.clone();
    for &(k, v) in raise {
        let e = &mut want[k as usize];
        *e = e.max(v as f64);
    }
    want != now.kernel_accuracy.values
}

/// A survey as the index takes it: its claims raised by `raise` (the survey itself when none
/// are).
fn effective(base: &Arc<SurveyMeta>, raise: &[(u32, f32)]) -> Arc<SurveyMeta> {
    if raise.is_empty() {
        base.clone()
    } else {
        Arc::new(base.with_raised_claims(raise))
    }
}

/// Heights resampled from a set of patches. NaN marks nodata.
#[derive(Clone, Debug)]
pub struct Tile {
    /// Samples per row.
    pub width: usize,
    /// Rows of samples.
    pub height: usize,
    /// `width × height` heights, row-major, in the order of the grid's points.
    pub heights: Vec<f32>,
    /// The patches the heights were blended from, in id order.
    pub patches: Vec<Extracted>,
    /// Where no data is as accurate as the cut asked (see [`tile_shortfall`]).
    pub shortfall: Option<Shortfall>,
}

/// The sample grid of a view: a screen of `width × height` pixels projected onto the plane
/// of the point looked at (§5, persistent grid mapping).
pub fn view_grid(v: &ViewQuery, width: usize, height: usize) -> SampleGrid {
    SampleGrid::of_rows(width, v.ground_rows(width, height, v.look[2]))
}

/// The [`Shortfall`] of a tile's patches over its grid, measured at no more than 64 × 64 of
/// its points: a share to the percent, at a cost that does not grow with the tile.
pub fn tile_shortfall(patches: &[Extracted], grid: &SampleGrid) -> Option<Shortfall> {
    let (si, sj) = (
        grid.width.div_ceil(64).max(1),
        grid.height.div_ceil(64).max(1),
    );
    let points = (0..grid.height)
        .step_by(sj)
        .flat_map(|j| (0..grid.width).step_by(si).map(move |i| j * grid.width + i))
        .map(|k| grid.point(k))
        .filter(|p| !p[0].is_nan());
    shortfall(patches, points)
}

/// A patch of the terrain: a survey's, or an edge patch.
#[derive(Clone, Copy, Debug)]
pub enum PatchRef<'a> {
    /// A patch of a survey, with the survey (as the index takes it).
    Survey(&'a Arc<SurveyMeta>, &'a Patch),
    /// An edge patch.
    Edge(&'a Arc<EdgePatch>),
}

/// A survey on a lattice, with the tiles whose edge patches it can affect.
#[derive(Clone, Debug)]
struct GroupMember {
    survey: Arc<SurveyMeta>,
    index: [i64; 2],
}

impl GroupMember {
    fn new(survey: Arc<SurveyMeta>, lattice: &Lattice) -> Self {
        let index = lattice.index_of(&survey.shapes[0].georef);
        GroupMember { survey, index }
    }

    fn edge_tiles(&self) -> &[[i64; 2]] {
        &self.survey.edge_tiles
    }

    /// The tiles whose edge patches can read this survey's samples, as inclusive ranges.
    fn tile_range(&self) -> [[i64; 2]; 2] {
        let l = &self.survey.layout;
        let side = edge::tile_side(l);
        let reach = l.margin as i64 + 1;
        let g = &self.survey.shapes[0];
        let span = |a: usize, n: usize| {
            [
                tile_of(self.index[a] - reach, side) - 1,
                tile_of(self.index[a] + n as i64 - 1 + reach, side),
            ]
        };
        [span(0, g.cols), span(1, g.rows)]
    }

    /// The level-0 samples of the member that a tile's edge patch reads, if any.
    fn reads(&self, tile: [i64; 2]) -> Option<SampleRect> {
        let [[i0, j0], [i1, j1]] = edge::tile_reads(tile, &self.survey.layout);
        let g = &self.survey.shapes[0];
        let c0 = (i0 - self.index[0]).max(0);
        let r0 = (j0 - self.index[1]).max(0);
        let c1 = (i1 - self.index[0] + 1).min(g.cols as i64);
        let r1 = (j1 - self.index[1] + 1).min(g.rows as i64);
        (c0 < c1 && r0 < r1).then_some(SampleRect {
            c0: c0 as usize,
            r0: r0 as usize,
            c1: c1 as usize,
            r1: r1 as usize,
        })
    }
}

/// The surveys that share one lattice of one plane, and the edge patch of each of its tiles
/// that has one.
///
/// A national programme puts thousands of abutting tiles on one lattice, so nothing here is
/// looked up by going through the members: `near` finds those a tile's edge patch can read,
/// and the maps are persistent (`imbl`), so that the copy of the terrain a commit makes shares
/// all but what the commit changes.
#[derive(Clone, Debug)]
struct LatticeGroup {
    plane: PlaneId,
    lattice: Lattice,
    /// The members, by id.
    members: imbl::OrdMap<SurveyId, GroupMember>,
    /// The members' [`GroupMember::tile_range`]s, each an entry under its survey's id: what
    /// finds the members whose samples a tile's edge patch can read. A map from every tile to
    /// the set of its members held 15 bytes a patch of a survey of 3,601² samples.
    near: MsQuadtree,
    tiles: imbl::OrdMap<[i64; 2], SurveyId>,
}

impl LatticeGroup {
    fn new(plane: PlaneId, lattice: Lattice) -> Self {
        LatticeGroup {
            plane,
            lattice,
            members: imbl::OrdMap::new(),
            near: MsQuadtree::new(RANGES_PER_NODE),
            tiles: imbl::OrdMap::new(),
        }
    }

    /// A member's [`GroupMember::tile_range`] as bounds in tile numbers, corners included.
    fn range_box(m: &GroupMember) -> Aabb {
        let [[x0, x1], [y0, y1]] = m.tile_range();
        Aabb::new(x0 as f64, y0 as f64, x1 as f64, y1 as f64)
    }

    /// The members whose tile ranges meet `b` (tile numbers, corners included), by id; the
    /// tree's answer, a superset where f32 rounded the ranges, is refined on the ranges.
    fn members_in(&self, b: &Aabb) -> BTreeSet<SurveyId> {
        let mut ids = BTreeSet::new();
        self.near.for_each_in(b, |e| {
            ids.insert(survey_of(e.at()));
        });
        ids.retain(|id| {
            self.members.get(id).is_some_and(|m| {
                let [[x0, x1], [y0, y1]] = m.tile_range();
                x0 as f64 <= b.max[0]
                    && b.min[0] <= x1 as f64
                    && y0 as f64 <= b.max[1]
                    && b.min[1] <= y1 as f64
            })
        });
        ids
    }

    fn add(&mut self, m: GroupMember) {
        let id = m.survey.id;
        let entry = Entry::new(survey_at(id), 1.0, 0.0, false, &Self::range_box(&m));
        self.near.insert(entry);
        self.members.insert(id, m);
    }

    fn remove(&mut self, id: SurveyId) -> Option<GroupMember> {
        let m = self.members.remove(&id)?;
        self.near.remove(survey_at(id), &Self::range_box(&m));
        Some(m)
    }

    /// The members whose samples tile `t`'s edge patch can read, by id.
    fn near(&self, t: [i64; 2]) -> Vec<&GroupMember> {
        let at = Aabb::new(t[0] as f64, t[1] as f64, t[0] as f64, t[1] as f64);
        self.members_in(&at)
            .into_iter()
            .filter_map(|id| self.members.get(&id))
            .collect()
    }

    /// The tiles a change to `m` (inserting or retiring it) can alter: its own edge tiles and
    /// the edge tiles of the other members within its reach (those whose tile ranges meet
    /// its own).
    fn affected_by(&self, m: &GroupMember) -> Vec<[i64; 2]> {
        let [[x0, x1], [y0, y1]] = m.tile_range();
        let mut set: BTreeSet<[i64; 2]> = m.edge_tiles().iter().copied().collect();
        let others = self.members_in(&Self::range_box(m));
        for o in others
            .iter()
            .filter(|&&id| id != m.survey.id)
            .filter_map(|id| self.members.get(id))
        {
            set.extend(
                o.edge_tiles()
                    .iter()
                    .filter(|t| (x0..=x1).contains(&t[0]) && (y0..=y1).contains(&t[1])),
            );
        }
        set.into_iter().collect()
    }
}

/// The in-memory terrain: its surveys, the edge patches their lattices call for, the evidence
/// of their overlaps and the LOD index over all their patches, which queries cut and tiles
/// resample.
#[derive(Clone, Debug)]
pub struct Terrain {
    /// The store's CRS and the planes of surveys in others, once the terrain has a CRS.
    planes: Option<Arc<Planes>>,
    index: LodIndex,
    // The maps are persistent (`imbl`): the copy of the terrain a commit makes shares all
    // that the commit leaves, so that it costs the change and not the store's size.
    surveys: imbl::OrdMap<SurveyId, Arc<SurveyMeta>>,
    edges: imbl::OrdMap<SurveyId, Arc<EdgePatch>>,
    lattices: Vec<LatticeGroup>,
    /// Samples held in memory: surveys inserted with them and not yet handed to a store.
    resident: imbl::OrdMap<SurveyId, Arc<[Arc<Grid>]>>,
    /// Where the samples of every other survey are read.
    source: Option<Arc<dyn SampleSource>>,
    /// The samples of edge patches held without them, made again from their members'.
    edge_grids: EdgeGrids,
    /// The surveys as built, with their own claims; `surveys` holds them as the index takes
    /// them, their claims raised where other surveys' evidence finds them false.
    bases: imbl::OrdMap<SurveyId, Arc<SurveyMeta>>,
    /// The footprints of `bases`, each an entry under its survey's id: what finds the surveys
    /// a new one overlaps without going through them all.
    footprints: MsQuadtree,
    /// What each overlapping pair of surveys says of the other, by (smaller id, larger id).
    pairs: imbl::OrdMap<(SurveyId, SurveyId), Arc<PairEvidence>>,
    /// The surveys each survey has a pair with.
    neighbours: imbl::OrdMap<SurveyId, BTreeSet<SurveyId>>,
    contradicted: Contradicted,
    /// How resolved patches are blended (see [`PatchSet::with_blend`]).
    blend: Blend,
}

/// The surveys a terrain restored for `region` keeps: those whose footprints meet the region
/// grown by the largest window, `w`, so that every patch whose window reaches a point of the
/// region is kept. A survey's windows lie within its footprint, so `w` is bounded by the
/// largest footprint's side; an edge patch lies within its members' samples, so its window is
/// bounded by the side of their footprints' union, and every member of an edge patch that
/// reaches the region lies within `w` of it, which keeps the plane its heights are read in.
pub fn reaching(
    region: &Aabb,
    surveys: &[Arc<SurveyMeta>],
    edges: &[Arc<EdgePatch>],
) -> BTreeSet<SurveyId> {
    let side = |b: &Aabb| b.width().max(b.height());
    let footprints: HashMap<SurveyId, Aabb> =
        surveys.iter().map(|s| (s.id, s.footprint())).collect();
    let mut w = footprints.values().map(side).fold(0.0, f64::max);
    for e in edges {
        let union = e
            .members
            .iter()
            .filter_map(|m| footprints.get(m))
            .copied()
            .reduce(|a, b| a.union(&b));
        w = w.max(union.as_ref().map_or(0.0, side));
    }
    let grown = region.grown(w);
    footprints
        .into_iter()
        .filter(|(_, f)| f.intersects(&grown))
        .map(|(id, _)| id)
        .collect()
}

/// How a tree of surveys ([`Terrain::footprints`], a lattice group's members) names a survey:
/// its id's two halves, low first.
fn survey_at(id: SurveyId) -> At {
    At {
        unit: id.0 as u32,
        position: (id.0 >> 32) as u32,
    }
}

/// The survey a tree of surveys names by `at` (see [`survey_at`]).
fn survey_of(at: At) -> SurveyId {
    SurveyId(u64::from(at.unit) | (u64::from(at.position) << 32))
}

/// Tile ranges a node of a lattice group's tree holds before it splits. The ranges of a
/// mosaic's tiles overlap their neighbours' by their reach, so that nodes of a few ranges
/// split down to single tiles and store each range dozens of times: at 16 a node, 10,000
/// abutting 36² grids held 1.5 kB a survey in it; at 256, 0.13 kB.
const RANGES_PER_NODE: usize = 256;

/// Footprints a node of [`Terrain::footprints`] holds before it splits.
const FOOTPRINTS_PER_NODE: usize = 16;

/// Edge patches to take out of the index and to put in.
type EdgeDiff = (Vec<SurveyId>, Vec<Arc<EdgePatch>>);

impl Terrain {
    /// An empty terrain without a CRS: it takes its store's, or its first survey's.
    pub fn new(cfg: IndexConfig) -> Self {
        Terrain {
            planes: None,
            index: LodIndex::new(cfg),
            surveys: imbl::OrdMap::new(),
            edges: imbl::OrdMap::new(),
            lattices: Vec::new(),
            resident: imbl::OrdMap::new(),
            source: None,
            edge_grids: EdgeGrids::new(EDGE_CACHE_BYTES),
            bases: imbl::OrdMap::new(),
            footprints: MsQuadtree::new(FOOTPRINTS_PER_NODE),
            pairs: imbl::OrdMap::new(),
            neighbours: imbl::OrdMap::new(),
            contradicted: Contradicted::default(),
            blend: Blend::default(),
        }
    }

    /// A terrain in the plane of `crs`, with the planes of surveys in other CRSs shared with
    /// `planes` where given (their lattices keep caches worth keeping).
    pub fn with_crs(cfg: IndexConfig, crs: Option<&Crs>, planes: Option<Arc<Planes>>) -> Self {
        let mut t = Terrain::new(cfg);
        t.planes = match (planes, crs) {
            (Some(p), Some(c)) if p.store_crs() == c => Some(p),
            (_, Some(c)) => Some(Arc::new(Planes::new(c.clone()))),
            (_, None) => None,
        };
        t
    }

    /// Gives a terrain without a CRS yet its store's.
    ///
    /// # Panics
    /// For a terrain that has one already: a store's CRS never changes.
    pub fn set_crs(&mut self, crs: Crs) {
        assert!(self.planes.is_none(), "a terrain's CRS is set once");
        self.planes = Some(Arc::new(Planes::new(crs)));
    }

    /// The terrain's CRS: its store's, once it has one.
    pub fn crs(&self) -> Option<&Crs> {
        self.planes.as_ref().map(|p| p.store_crs())
    }

    /// The planes of the terrain's CRS, for surveys in others.
    pub fn planes(&self) -> Option<&Arc<Planes>> {
        self.planes.as_ref()
    }

    /// A survey as this terrain holds it: placed in its CRS (see [`Survey::placed`]). A
    /// terrain without a CRS yet takes the survey's.
    pub fn place(&mut self, s: &Survey) -> Result<Survey, PlaceError> {
        if self.planes.is_none() {
            if let Some(c) = s.placed_for() {
                self.planes = Some(Arc::new(Planes::new(c)));
            }
        }
        match &self.planes {
            Some(p) => s.placed(p),
            None => Ok(s.clone()),
        }
    }

    /// The CRS of a plane of the terrain's; None for the store's own.
    pub fn plane_crs(&self, id: PlaneId) -> Option<Crs> {
        if id == STORE_PLANE {
            return None;
        }
        self.planes.as_ref()?.by_id(id).map(|p| p.crs.clone())
    }

    /// Reads the samples of surveys not in memory from `source`, and lets go of the edge
    /// patches' samples, which it can then make again from their members' when a read needs
    /// them (see [`Terrain::edge_grid`]).
    pub fn set_source(&mut self, source: Arc<dyn SampleSource>) {
        self.source = Some(source);
        self.edges = self
            .edges
            .iter()
            .map(|(owner, e)| (*owner, bare(e.clone())))
            .collect();
    }

    /// Keeps at most `bytes` of the edge patches' samples made again, for every snapshot of
    /// the terrain from here on.
    pub fn set_edge_cache(&mut self, bytes: u64) {
        self.edge_grids = EdgeGrids::new(bytes);
    }

    /// The samples of an edge patch of the terrain: its own where it holds them, else made
    /// again from its members' samples as the terrain has them, which is what built it (the
    /// patch's id, which names what it holds, is checked), and kept in a cache shared by
    /// every snapshot.
    pub fn edge_grid(&self, e: &EdgePatch) -> Result<Arc<EdgeGrid>, SampleError> {
        if let Some(g) = &e.grid {
            return Ok(g.clone());
        }
        if let Some(g) = self.edge_grids.0.get(&e.id) {
            return Ok(g);
        }
        let gone = |why: &str| SampleError {
            survey: e.owner,
            reason: format!("edge patch {}: {why}", e.id),
            unavailable: false,
        };
        let g = self
            .lattices
            .iter()
            .find(|g| g.tiles.get(&e.tile) == Some(&e.owner))
            .ok_or_else(|| gone("not a patch of this terrain"))?;
        let layout = g
            .members
            .values()
            .next()
            .map(|m| m.survey.layout)
            .ok_or_else(|| gone("its lattice has no survey"))?;
        let built = self
            .build_tile(g, &layout, e.tile)?
            .filter(|b| b.owner == e.owner)
            .ok_or_else(|| gone("its surveys make another patch"))?;
        let grid = built.grid.ok_or_else(|| gone("built without samples"))?;
        self.edge_grids.0.insert(e.id, grid.clone());
        Ok(grid)
    }

    /// The edge patch that tile `t` of the group calls for, from its members' samples, with
    /// its samples and the error its members' claims give it; None where it calls for none.
    fn build_tile(
        &self,
        g: &LatticeGroup,
        layout: &PatchLayout,
        t: [i64; 2],
    ) -> Result<Option<EdgePatch>, SampleError> {
        // Each tile reads only the members' samples around it.
        let mut windows = Vec::new();
        for m in g.near(t) {
            if let Some(rect) = m.reads(t) {
                windows.push((m, self.window(&m.survey, 0, rect)?));
            }
        }
        let members: Vec<Member> = windows
            .iter()
            .map(|(m, w)| Member {
                survey: &m.survey,
                index: m.index,
                samples: w,
            })
            .collect();
        Ok(edge::build(t, &members, layout))
    }

    /// Drops a survey's samples from memory once its store can serve them; a terrain without
    /// a source keeps them.
    pub fn page_out(&mut self, id: SurveyId) {
        if self.source.is_some() {
            self.resident.remove(&id);
        }
    }

    /// Lets go of the samples of the edge patches that `changes` brought, once the store holds
    /// them: the terrain makes them again from their members' when a read needs them. A
    /// terrain without a source keeps them.
    pub fn page_out_edges(&mut self, changes: &[&ChangeStats]) {
        if self.source.is_none() {
            return;
        }
        let held: Vec<Arc<EdgePatch>> = self
            .moved_edges(changes)
            .filter(|e| e.grid.is_some())
            .cloned()
            .collect();
        for e in held {
            self.edges.insert(e.owner, bare(e));
        }
    }

    /// Samples `rect` of a level of a survey of the terrain, exactly, as a grid georeferenced
    /// where they lie.
    pub fn samples(
        &self,
        s: &SurveyMeta,
        level: usize,
        rect: SampleRect,
    ) -> Result<Grid, SampleError> {
        let w = self.window(s, level, rect)?;
        if (w.c0, w.r0, w.grid.cols, w.grid.rows) == (rect.c0, rect.r0, rect.cols(), rect.rows()) {
            // Read for this call alone: no copy.
            return Ok(Arc::unwrap_or_clone(w.grid));
        }
        Ok(w.grid
            .window(rect.c0 - w.c0, rect.r0 - w.r0, rect.cols(), rect.rows()))
    }

    /// Samples `rect` of a level of a survey of the terrain, through a window in the level's
    /// coordinates. A survey held in memory answers with its whole level.
    pub fn window(
        &self,
        s: &SurveyMeta,
        level: usize,
        rect: SampleRect,
    ) -> Result<Window, SampleError> {
        if let Some(levels) = self.resident.get(&s.id) {
            return Ok(Window::whole(levels[level].clone()));
        }
        let source = self.source.as_ref().ok_or_else(|| SampleError {
            survey: s.id,
            reason: "the terrain holds neither its samples nor a store to read them from".into(),
            unavailable: false,
        })?;
        source.window(s.id, level, &s.shapes[level], rect)
    }

    /// Rebuilds a terrain from what a store keeps: the surveys without their samples, the
    /// edge patches and the box states, without running the cutter or reading a sample.
    /// Returns the patches that had no stored state, restored as empty.
    ///
    /// Surveys of another CRS than `crs` get their patches' frames in its plane; their errors
    /// are as stored, raised where the stored `pairs` find their claims false under
    /// `contradicted`.
    ///
    /// With a `region` (of the store's plane), only the part of the terrain that answers
    /// inside it is kept (see [`reaching`]): every point of the region gets the same patches,
    /// with the same errors and states, and so the same height, as from the whole terrain.
    #[allow(clippy::too_many_arguments)]
    pub fn restore(
        cfg: IndexConfig,
        crs: Option<&Crs>,
        contradicted: Contradicted,
        surveys: Vec<Arc<SurveyMeta>>,
        pairs: Vec<Arc<PairEvidence>>,
        edges: Vec<Arc<EdgePatch>>,
        states: &HashMap<PatchId, BoxState>,
        source: Arc<dyn SampleSource>,
        region: Option<&Aabb>,
    ) -> (Self, Vec<PatchId>) {
        let mut t = Terrain::with_crs(cfg, crs, None);
        t.contradicted = contradicted;
        t.source = Some(source);
        let surveys: Vec<Arc<SurveyMeta>> = surveys
            .into_par_iter()
            .map(|s| match (&t.planes, s.placement.is_none()) {
                (Some(planes), true) => match s.placement_in(planes) {
                    Ok(Some(p)) => {
                        let mut m = (*s).clone();
                        m.placement = Some(p);
                        Arc::new(m)
                    }
                    _ => s,
                },
                _ => s,
            })
            .collect();
        let kept = region.map(|r| reaching(r, &surveys, &edges));
        // Every survey is a base while the raises are worked out, whatever the region: a kept
        // survey's raise depends on the claims of those it overlaps, and theirs on their own
        // pairs. What the region does not need is let go afterwards.
        for s in &surveys {
            t.set_base(s.clone());
        }
        for p in pairs {
            // A pair whose surveys are not both here would be stale.
            if t.bases.contains_key(&p.finer) && t.bases.contains_key(&p.coarser) {
                t.add_pair(p);
            }
        }
        let mut group_of_survey = HashMap::new();
        for base in surveys {
            if kept.as_ref().is_some_and(|k| !k.contains(&base.id)) {
                continue;
            }
            let r = t.raise_of(&base);
            let s = effective(&base, &r);
            let gi = t.group_of(&s);
            let m = GroupMember::new(s.clone(), &t.lattices[gi].lattice);
            t.lattices[gi].add(m);
            group_of_survey.insert(s.id, gi);
            t.register(s);
        }
        for e in edges {
            // An edge patch whose surveys are gone would be stale; the index derivation that
            // a missing state triggers puts the right ones back.
            let Some(&gi) = e.members.first().and_then(|m| group_of_survey.get(m)) else {
                continue;
            };
            // A restored terrain reads its samples from the store: its edge patches' too.
            t.register_edge(gi, bare(e));
        }
        if let Some(kept) = &kept {
            t.keep_evidence_of(kept);
        }
        let mut missing = Vec::new();
        let mut state = |id: PatchId| {
            states.get(&id).copied().unwrap_or_else(|| {
                missing.push(id);
                BoxState::EMPTY
            })
        };
        let mut units: Vec<(SurveyId, UnitBoxes, Vec<BoxState>)> = Vec::new();
        for s in t.surveys.values() {
            let boxes = UnitBoxes::of_survey(s);
            let states = (0..boxes.len()).map(|k| state(boxes.id(k))).collect();
            units.push((s.id, boxes, states));
        }
        let edges: Vec<(SurveyId, UnitBoxes)> =
            t.edges.values().map(|e| (e.owner, t.edge_box(e))).collect();
        for (owner, boxes) in edges {
            let states = vec![state(boxes.id(0))];
            units.push((owner, boxes, states));
        }
        missing.sort_unstable();
        t.index = LodIndex::restore(cfg, units);
        (t, missing)
    }

    /// Lets go of the bases and pairs that say nothing of the surveys `kept`: a pair is kept
    /// where one of its surveys is kept or has a pair with one (what a kept survey's evidence
    /// is judged by), and a base where a kept pair or survey names it.
    fn keep_evidence_of(&mut self, kept: &BTreeSet<SurveyId>) {
        let mut near = kept.clone();
        for id in kept {
            near.extend(self.neighbours.get(id).into_iter().flatten().copied());
        }
        let stale: Vec<(SurveyId, SurveyId)> = self
            .pairs
            .keys()
            .filter(|(a, b)| !near.contains(a) && !near.contains(b))
            .copied()
            .collect();
        for (a, b) in stale {
            self.pairs.remove(&(a, b));
            for (x, y) in [(a, b), (b, a)] {
                if let Some(set) = self.neighbours.get_mut(&x) {
                    set.remove(&y);
                    if set.is_empty() {
                        self.neighbours.remove(&x);
                    }
                }
            }
        }
        let gone: Vec<SurveyId> = self
            .bases
            .keys()
            .filter(|id| !kept.contains(id) && !self.neighbours.contains_key(id))
            .copied()
            .collect();
        for id in gone {
            self.drop_base(id);
        }
    }

    fn register(&mut self, s: Arc<SurveyMeta>) {
        self.surveys.insert(s.id, s);
    }

    fn register_edge(&mut self, gi: usize, e: Arc<EdgePatch>) {
        self.lattices[gi].tiles.insert(e.tile, e.owner);
        self.edges.insert(e.owner, e);
    }

    fn unregister_edge(&mut self, gi: usize, owner: SurveyId) {
        if let Some(e) = self.edges.remove(&owner) {
            if self.lattices[gi].tiles.get(&e.tile) == Some(&owner) {
                self.lattices[gi].tiles.remove(&e.tile);
            }
        }
    }

    /// The lattice group a survey belongs to, made if it is the first on its lattice: one
    /// lattice of one plane (the same numbers in two CRSs are two lattices).
    fn group_of(&mut self, s: &SurveyMeta) -> usize {
        let l = Lattice::of(&s.shapes[0].georef);
        let plane = s.plane_id();
        match self
            .lattices
            .iter()
            .position(|g| g.plane == plane && g.lattice.same(&l))
        {
            Some(i) => i,
            None => {
                self.lattices.push(LatticeGroup::new(plane, l));
                self.lattices.len() - 1
            }
        }
    }

    /// The plane, and its residuals over the members an edge patch reads, of a group of
    /// another plane; None for the store's.
    fn edge_plane(&self, members: &[SurveyId]) -> Option<(Arc<Plane>, Residuals)> {
        let mut out: Option<(Arc<Plane>, Residuals)> = None;
        // The groups' members, not the registered surveys: an insertion builds its edge
        // patches before it registers the survey.
        let found = members
            .iter()
            .filter_map(|id| self.lattices.iter().find_map(|g| g.members.get(id)));
        for m in found {
            let Some(p) = m.survey.placement.clone() else {
                continue;
            };
            let r = out.get_or_insert_with(|| (p.plane.clone(), Residuals::default()));
            r.1.to_native = r.1.to_native.max(p.residuals.to_native);
            r.1.to_store = r.1.to_store.max(p.residuals.to_store);
        }
        out
    }

    /// An edge patch as LOD space sees it: in its lattice's plane, framed in the store's
    /// for a lattice of another CRS.
    fn edge_box(&self, e: &EdgePatch) -> UnitBoxes {
        let framed = self.edge_frame(e);
        UnitBoxes::edge(e, framed.as_ref().map(|(id, f)| (*id, f)))
    }

    fn edge_frame(&self, e: &EdgePatch) -> Option<(PlaneId, Frame)> {
        let (plane, rho) = self.edge_plane(&e.members)?;
        let frame = plane.frame(&e.georef, &e.window, &rho).unwrap_or(Frame {
            // Every edge patch lies within its surveys' samples, which all have images;
            // should the fit still fail, a frame that reaches everywhere keeps coverage
            // conservative.
            map: patchwork_geom::Affine {
                origin: [0.0; 2],
                m: [[1.0, 0.0], [0.0, 1.0]],
            },
            rho: f64::INFINITY,
        });
        Some((plane.id, frame))
    }

    /// The edge patches of `tiles` as the group's members now call for, against those there:
    /// the owners that go and the patches that come.
    fn rebuild(&self, gi: usize, tiles: Vec<[i64; 2]>) -> Result<EdgeDiff, SampleError> {
        let g = &self.lattices[gi];
        let Some(layout) = g.members.values().next().map(|m| m.survey.layout) else {
            return Ok((g.tiles.values().copied().collect(), Vec::new()));
        };
        let built: Vec<([i64; 2], Option<EdgePatch>)> = tiles
            .par_iter()
            .map(|&t| Ok((t, self.build_tile(g, &layout, t)?)))
            .collect::<Result<_, SampleError>>()?;
        let mut gone = Vec::new();
        let mut come = Vec::new();
        for (t, mut e) in built {
            // An edge patch of another plane, like its surveys' patches, answers for where the
            // reprojection moves its points: its error grows as theirs do.
            if let Some(e) = e.as_mut() {
                if let (Some((_, rho)), Some(g)) = (self.edge_plane(&e.members), e.grid.clone()) {
                    e.error += edge_reprojection_error(&g, rho.to_native);
                }
            }
            let old = g.tiles.get(&t).copied();
            let new = e.as_ref().map(|e| e.owner);
            if old == new {
                continue;
            }
            gone.extend(old);
            come.extend(e.map(Arc::new));
        }
        Ok((gone, come))
    }

    /// The LOD index over every patch, survey and edge.
    pub fn index(&self) -> &LodIndex {
        &self.index
    }

    /// A survey as the index takes it: its claims raised where others find them false (see
    /// [`Terrain::base`] for the survey as built).
    pub fn survey(&self, id: SurveyId) -> Option<&Arc<SurveyMeta>> {
        self.surveys.get(&id)
    }

    /// Every survey as the index takes it (see [`Terrain::survey`]), in no particular order.
    pub fn surveys(&self) -> impl Iterator<Item = &Arc<SurveyMeta>> {
        self.surveys.values()
    }

    /// The edge patches, in no particular order.
    pub fn edges(&self) -> impl Iterator<Item = &Arc<EdgePatch>> {
        self.edges.values()
    }

    /// The edge patches this terrain holds among the boxes the changes moved: what a store
    /// writes of them besides their tops.
    pub fn edges_of(&self, changes: &[&ChangeStats]) -> Vec<Arc<EdgePatch>> {
        let mut out: Vec<Arc<EdgePatch>> = self.moved_edges(changes).cloned().collect();
        out.sort_by_key(|e| e.id);
        out.dedup_by_key(|e| e.id);
        out
    }

    /// The edge patches held among the boxes the changes moved. An edge patch is a unit of its
    /// own, so it moved where its unit is listed with states.
    fn moved_edges<'a>(
        &'a self,
        changes: &'a [&ChangeStats],
    ) -> impl Iterator<Item = &'a Arc<EdgePatch>> + 'a {
        changes
            .iter()
            .flat_map(|c| c.units.iter())
            .filter(|(_, states)| states.is_some())
            .filter_map(|(owner, _)| self.edges.get(owner))
    }

    /// The patch a cut took: the one at its place in its unit's list.
    pub fn patch(&self, x: &Extracted) -> Option<PatchRef<'_>> {
        if let Some(e) = self.edges.get(&x.survey).filter(|e| e.id == x.id) {
            return Some(PatchRef::Edge(e));
        }
        let s = self.surveys.get(&x.survey)?;
        let p = s
            .patches
            .get(x.position as usize)
            .filter(|p| p.id == x.id)?;
        Some(PatchRef::Survey(s, p))
    }

    /// The edge patch whose unit is `owner`.
    pub fn edge(&self, owner: SurveyId) -> Option<&Arc<EdgePatch>> {
        self.edges.get(&owner)
    }

    /// Adds a survey, with the edge patches it changes; adding one already present changes
    /// nothing. The survey's samples stay in memory until [`Terrain::page_out`].
    ///
    /// # Panics
    /// When a neighbour's samples cannot be read, which only a terrain with a source can
    /// meet: such a terrain calls [`Terrain::try_insert`].
    pub fn insert(&mut self, s: Arc<Survey>) -> ChangeStats {
        self.try_insert(&s)
            .expect("samples held in memory, and a survey that can be placed")
    }

    /// Adds a survey, reading its neighbours' samples where edge patches need them. On an
    /// error the terrain is as it was.
    ///
    /// A survey not yet placed in the terrain's CRS is placed first (see [`Terrain::place`]);
    /// a caller that commits the survey elsewhere too places it itself, and inserts that.
    pub fn try_insert(&mut self, s: &Survey) -> Result<ChangeStats, TerrainError> {
        if self.surveys.contains_key(&s.id) {
            return Ok(ChangeStats::default());
        }
        let placed_here = s.placed_in.is_some()
            && s.placed_in.as_ref() == self.crs()
            && (s.placement.is_some() || s.crs.as_ref() == self.crs());
        let placed;
        let s = if placed_here {
            s
        } else {
            placed = self.place(s)?;
            &placed
        };
        let base = s.meta();
        self.resident.insert(s.id, s.levels.clone().into());
        // What it and every survey it overlaps say of each other's claims.
        let pairs = match self.compare_with_all(&base) {
            Ok(p) => p,
            Err(e) => {
                self.resident.remove(&s.id);
                return Err(e.into());
            }
        };
        for p in pairs {
            self.add_pair(Arc::new(p));
        }
        // Its own claims are evidence in its neighbours' pairs.
        self.set_base(base.clone());
        let around = self.within_reach(s.id, self.neighbours.get(&s.id).cloned());
        let result = self.change(Some(base.clone()), None, around);
        if result.is_err() {
            self.resident.remove(&s.id);
            self.drop_base(s.id);
            self.drop_pairs(s.id);
        }
        result.map_err(TerrainError::from)
    }

    /// Removes a survey and the edge patches it changes; the terrain becomes the one that
    /// never had it.
    ///
    /// # Panics
    /// As [`Terrain::insert`]; a terrain with a source calls [`Terrain::try_retire`].
    pub fn retire(&mut self, id: SurveyId) -> Option<ChangeStats> {
        self.try_retire(id).expect("samples held in memory")
    }

    /// Removes a survey, reading its neighbours' samples where edge patches need them; None
    /// when it is not there. On an error the terrain is as it was.
    pub fn try_retire(&mut self, id: SurveyId) -> Result<Option<ChangeStats>, SampleError> {
        if !self.surveys.contains_key(&id) {
            return Ok(None);
        }
        let (dropped, around) = self.drop_pairs(id);
        let around = self.within_reach(id, Some(around));
        match self.change(None, Some(id), around) {
            Ok(stats) => Ok(Some(stats)),
            Err(e) => {
                for p in dropped {
                    self.add_pair(p);
                }
                Err(e)
            }
        }
    }

    /// Inserts `add` or retires `remove`, with everything that follows: the claims of the
    /// surveys `around` it (those it overlaps, whose pairs with it, and with each other through
    /// it as a third, came or went), the edge patches of every lattice tile any of them
    /// touches, and the index, in one change. The pairs are already as they will be. On an
    /// error the terrain is as it was, but for the pairs.
    fn change(
        &mut self,
        add: Option<Arc<SurveyMeta>>,
        remove: Option<SurveyId>,
        around: BTreeSet<SurveyId>,
    ) -> Result<ChangeStats, SampleError> {
        let reclaimed: Vec<(SurveyId, Raise)> = around
            .into_iter()
            .filter_map(|o| {
                let base = &self.bases[&o];
                let r = self.raise_of(base);
                let now = self.surveys.get(&o)?;
                claims_differ(base, &r, now).then_some((o, r))
            })
            .collect();
        let added = add.map(|base| {
            let r = self.raise_of(&base);
            let eff = effective(&base, &r);
            (base, r, eff)
        });
        // The lattice groups as they will be, with the tiles to build again; the groups as
        // they were, to put back on an error.
        let mut saved: HashMap<usize, LatticeGroup> = HashMap::new();
        let mut tiles: HashMap<usize, BTreeSet<[i64; 2]>> = HashMap::new();
        let mut new_metas: Vec<(SurveyId, Arc<SurveyMeta>)> = Vec::new();
        for (o, r) in &reclaimed {
            let eff = effective(&self.bases[o], r);
            let gi = self.group_index(*o).expect("a survey is a member");
            saved.entry(gi).or_insert_with(|| self.lattices[gi].clone());
            let g = &mut self.lattices[gi];
            // A raise changes a member's claims, not where it lies: its tiles stay.
            let m = g.members.get_mut(o).expect("member");
            m.survey = eff.clone();
            let m = m.clone();
            tiles.entry(gi).or_default().extend(g.affected_by(&m));
            new_metas.push((*o, eff));
        }
        let mut new_group = None;
        if let Some((_, _, eff)) = &added {
            let gi = self.group_of(eff);
            if gi == self.lattices.len() - 1 && self.lattices[gi].members.is_empty() {
                new_group = Some(gi);
            }
            saved.entry(gi).or_insert_with(|| self.lattices[gi].clone());
            let m = GroupMember::new(eff.clone(), &self.lattices[gi].lattice);
            let g = &mut self.lattices[gi];
            tiles.entry(gi).or_default().extend(g.affected_by(&m));
            g.add(m);
        }
        if let Some(id) = remove {
            let gi = self.group_index(id).expect("a survey is a member");
            saved.entry(gi).or_insert_with(|| self.lattices[gi].clone());
            let g = &mut self.lattices[gi];
            let m = g.remove(id).expect("member");
            tiles.entry(gi).or_default().extend(g.affected_by(&m));
        }
        // Every touched group's edge patches, built again.
        let mut diffs: Vec<(usize, EdgeDiff)> = Vec::new();
        let mut order: Vec<usize> = tiles.keys().copied().collect();
        order.sort_unstable();
        for gi in order {
            let t: Vec<[i64; 2]> = tiles[&gi].iter().copied().collect();
            match self.rebuild(gi, t) {
                Ok(d) => diffs.push((gi, d)),
                Err(e) => {
                    for (gi, g) in saved {
                        self.lattices[gi] = g;
                    }
                    if let Some(gi) = new_group {
                        self.lattices.remove(gi);
                    }
                    return Err(e);
                }
            }
        }
        // One change of the index: the survey in or out, the surveys whose claims moved out
        // and in again, and the edge patches.
        let mut gone: Vec<SurveyId> = remove.into_iter().collect();
        let mut insert: Vec<(SurveyId, UnitBoxes)> = Vec::new();
        if let Some((_, _, eff)) = &added {
            insert.push((eff.id, UnitBoxes::of_survey(eff)));
        }
        for (o, eff) in &new_metas {
            gone.push(*o);
            insert.push((*o, UnitBoxes::of_survey(eff)));
        }
        for (_, (g, c)) in &diffs {
            gone.extend(g.iter().copied());
            insert.extend(c.iter().map(|e| (e.owner, self.edge_box(e))));
        }
        let stats = self.index.apply(&gone, insert);
        // The terrain's own records.
        if let Some(id) = remove {
            self.surveys.remove(&id).expect("a survey");
            self.drop_base(id);
            self.resident.remove(&id);
        }
        if let Some((base, _, eff)) = added {
            self.set_base(base);
            self.register(eff);
        }
        for (_, eff) in new_metas {
            self.register(eff);
        }
        for (gi, (g, c)) in diffs {
            for o in g {
                self.unregister_edge(gi, o);
            }
            for e in c {
                self.register_edge(gi, e);
            }
        }
        // A group left without members goes (after its edge patches, which index it).
        self.lattices.retain(|g| !g.members.is_empty());
        Ok(stats)
    }

    /// Keeps a survey as built, and its footprint.
    fn set_base(&mut self, s: Arc<SurveyMeta>) {
        if let Some(old) = self.bases.insert(s.id, s.clone()) {
            self.footprints.remove(survey_at(old.id), &old.footprint());
        }
        self.footprints
            .insert(Entry::new(survey_at(s.id), 1.0, 0.0, false, &s.footprint()));
    }

    /// Forgets a survey as built, and its footprint.
    fn drop_base(&mut self, id: SurveyId) {
        if let Some(old) = self.bases.remove(&id) {
            self.footprints.remove(survey_at(old.id), &old.footprint());
        }
    }

    /// The group a survey is a member of.
    fn group_index(&self, id: SurveyId) -> Option<usize> {
        self.lattices
            .iter()
            .position(|g| g.members.contains_key(&id))
    }

    fn add_pair(&mut self, p: Arc<PairEvidence>) {
        let (a, b) = (p.finer, p.coarser);
        self.neighbours.entry(a).or_default().insert(b);
        self.neighbours.entry(b).or_default().insert(a);
        self.pairs.insert(pair_key(a, b), p);
    }

    /// Takes a survey's pairs out: them, and the surveys it had them with.
    fn drop_pairs(&mut self, id: SurveyId) -> (Vec<Arc<PairEvidence>>, BTreeSet<SurveyId>) {
        let Some(ns) = self.neighbours.remove(&id) else {
            return (Vec::new(), BTreeSet::new());
        };
        let mut out = Vec::new();
        for n in &ns {
            if let Some(set) = self.neighbours.get_mut(n) {
                set.remove(&id);
                if set.is_empty() {
                    self.neighbours.remove(n);
                }
            }
            out.extend(self.pairs.remove(&pair_key(id, *n)));
        }
        (out, ns)
    }

    /// Every overlapping pair's evidence, in key order.
    pub fn pairs(&self) -> Vec<Arc<PairEvidence>> {
        let mut v: Vec<(&(SurveyId, SurveyId), &Arc<PairEvidence>)> = self.pairs.iter().collect();
        v.sort_by_key(|(k, _)| **k);
        v.into_iter().map(|(_, p)| p.clone()).collect()
    }

    /// The evidence of every pair a survey is in, by the other survey's id.
    pub fn pairs_of(&self, id: SurveyId) -> Vec<Arc<PairEvidence>> {
        self.neighbours
            .get(&id)
            .into_iter()
            .flatten()
            .filter_map(|n| self.pairs.get(&pair_key(id, *n)).cloned())
            .collect()
    }

    /// Which claim of the pair of `a` and `b` is false, where they contradict each other.
    pub fn blame(&self, a: SurveyId, b: SurveyId) -> Option<Blame> {
        self.verdict(a, b)?.blame
    }

    /// What the pair of `a` and `b` decides, and by which test; None where they are no pair.
    pub fn verdict(&self, a: SurveyId, b: SurveyId) -> Option<evidence::Verdict> {
        let p = self.pairs.get(&pair_key(a, b))?;
        Some(self.verdict_of(p))
    }

    fn blame_pair(&self, p: &PairEvidence) -> Option<Blame> {
        self.verdict_of(p).blame
    }

    fn verdict_of(&self, p: &PairEvidence) -> evidence::Verdict {
        let (f, c) = (p.finer, p.coarser);
        let empty = BTreeSet::new();
        let nf = self.neighbours.get(&f).unwrap_or(&empty);
        let nc = self.neighbours.get(&c).unwrap_or(&empty);
        // A degraded copy of another survey lies where that one lies, and does not vote.
        let thirds = nf
            .intersection(nc)
            .filter(|t| !self.a_copy(**t))
            .filter_map(|t| {
                Some((
                    &**self.pairs.get(&pair_key(f, *t))?,
                    &**self.pairs.get(&pair_key(c, *t))?,
                ))
            });
        evidence::blame(p, thirds)
    }

    /// The surveys whose claims a change at `id` can move, given those it has (or had) pairs
    /// with, `near`. A survey's claims follow from its pairs' verdicts (which the pairs of the
    /// thirds that overlap both enter), from whether its partners are discredited (their
    /// verdicts), and, for one derived from a partner, from the partner's contested claims
    /// (whose partners' discredit enters, and so their verdicts): four overlaps away at most.
    fn within_reach(&self, id: SurveyId, near: Option<BTreeSet<SurveyId>>) -> BTreeSet<SurveyId> {
        let mut out = near.unwrap_or_default();
        let mut ring = out.clone();
        for _ in 0..3 {
            let next: BTreeSet<SurveyId> = ring
                .iter()
                .flat_map(|n| self.neighbours.get(n).into_iter().flatten().copied())
                .filter(|n| !out.contains(n))
                .collect();
            out.extend(next.iter().copied());
            ring = next;
        }
        out.remove(&id);
        out
    }

    /// Whether some pair of the survey finds it alone the false one: a degraded or misplaced
    /// version of another survey carries nothing of its own, so where it disagrees with a third
    /// its claim is no evidence against that third's.
    fn discredited(&self, id: SurveyId) -> bool {
        self.pairs_of(id).iter().any(|p| self.alone(p, id))
    }

    /// Whether some pair of the survey finds it, by itself, a lesser copy of the other.
    fn a_copy(&self, id: SurveyId) -> bool {
        self.pairs_of(id).iter().any(|p| {
            matches!(
                (p.finding(), p.finer == id),
                (Some((Blame::Finer, _)), true) | (Some((Blame::Coarser, _)), false)
            )
        })
    }

    /// Whether `id` loses the tie of a pair that nothing decides and whose claims contradict
    /// each other: it is then held, over the overlap, to what the winner's claim allows.
    fn loses_tie(&self, p: &PairEvidence, id: SurveyId) -> bool {
        self.blame_pair(p) == Some(Blame::Both)
            && p.tie_to_finer()
                .is_some_and(|finer| finer != (p.finer == id))
    }

    /// Whether the pair finds `id` alone the false one.
    fn alone(&self, p: &PairEvidence, id: SurveyId) -> bool {
        matches!(
            (self.blame_pair(p), p.finer == id),
            (Some(Blame::Finer), true) | (Some(Blame::Coarser), false)
        )
    }

    /// What the pairs that cannot tell which claim is false raise a survey's claims to, each
    /// kernel to the largest the other survey's claim allows there, by kernel. A survey
    /// discredited elsewhere is no evidence against this one.
    fn contested(&self, id: SurveyId) -> BTreeMap<u32, f32> {
        let mut raise = BTreeMap::new();
        for p in self.pairs_of(id) {
            if self.blame_pair(&p) == Some(Blame::Both) && !self.discredited(p.other(id)) {
                // Ground that changed between dated surveys is no contradiction of either.
                let changed = self.dated_change(&p, id);
                for &(k, v) in p.against(id) {
                    if changed.contains_key(&k) {
                        continue;
                    }
                    let e = raise.entry(k).or_insert(0.0f32);
                    *e = e.max(v);
                }
            }
        }
        raise
    }

    /// The raise of a survey's claims that its pairs call for: the contested claims' (see
    /// [`Terrain::contested`]), and where a pair finds it alone the false one (a degraded or
    /// misplaced version of the other), over the whole overlap the other's claim there, as
    /// contested, plus how far it departs from the other. None under a `keep` policy.
    fn raise_of(&self, base: &SurveyMeta) -> Raise {
        if self.contradicted == Contradicted::Keep {
            return Arc::from([]);
        }
        let id = base.id;
        let mut raise = self.contested(id);
        let own = &base.kernel_accuracy;
        for p in self.pairs_of(id) {
            let changed = self.dated_change(&p, id);
            if !changed.is_empty() && self.later(&p) == Some(p.other(id)) {
                // The ground this survey saw there is gone: the later survey serves, and this
                // one is held, for the present, to how far the ground moved plus the later's
                // claim over the change.
                let later = &self.bases[&p.other(id)].kernel_accuracy;
                let theirs = self
                    .dated_change(&p, p.other(id))
                    .keys()
                    .map(|&k| later.values[k as usize])
                    .fold(0.0, f64::max);
                for (&k, &d) in &changed {
                    let need = d as f64 + theirs;
                    if need > own.values[k as usize] * (1.0 + 1e-9) + 1e-9 {
                        let e = raise.entry(k).or_insert(0.0);
                        *e = e.max(need as f32);
                    }
                }
            }
            // A survey found false, or one that loses the tie of a pair nothing decides, is
            // held over the whole overlap: where the two agree within their claims the
            // loser's own estimate (which smoothness flatters) would otherwise still win.
            if !self.alone(&p, id) && !self.loses_tie(&p, id) {
                continue;
            }
            let other = p.other(id);
            let theirs = &self.bases[&other].kernel_accuracy;
            let contested = self.contested(other);
            // A coarser survey's evidence never makes a finer one worse than its own claim.
            let capped = p.finer == id && p.cell_ratio() >= 2.0;
            for (k, ko, d) in p.departs(id).iter() {
                // Where it saw the ground after the change, it departs by the change, not
                // by an error.
                if changed.contains_key(&k) {
                    continue;
                }
                let claim =
                    theirs.values[ko as usize].max(contested.get(&ko).map_or(0.0, |&v| v as f64));
                let need = if capped {
                    (d as f64 + claim).min(claim)
                } else {
                    d as f64 + claim
                };
                if need > own.values[k as usize] * (1.0 + 1e-9) + 1e-9 {
                    let e = raise.entry(k).or_insert(0.0);
                    *e = e.max(need as f32);
                }
            }
        }
        raise.into_iter().collect()
    }

    /// Which survey of the pair saw the ground last: the one whose epoch lies wholly after
    /// the other's. None where either epoch is unknown or the two overlap: an unknown epoch
    /// gives no precedence.
    pub fn later(&self, p: &PairEvidence) -> Option<SurveyId> {
        let (ef, ec) = (
            self.bases.get(&p.finer)?.epoch?,
            self.bases.get(&p.coarser)?.epoch?,
        );
        if ef.after(&ec) {
            Some(p.finer)
        } else if ec.after(&ef) {
            Some(p.coarser)
        } else {
            None
        }
    }

    /// The kernels of `id` that the pair's changes cover, with the largest change in each,
    /// where the pair's epochs say which saw the ground last; none otherwise.
    fn dated_change(&self, p: &PairEvidence, id: SurveyId) -> BTreeMap<u32, f32> {
        let mut out = BTreeMap::new();
        if p.changes.is_empty() || self.later(p).is_none() {
            return out;
        }
        for c in &p.changes {
            let ks = if id == p.finer {
                &c.finer_kernels
            } else {
                &c.coarser_kernels
            };
            for &(k, d) in ks {
                let e = out.entry(k).or_insert(0.0f32);
                *e = e.max(d);
            }
        }
        out
    }

    /// The survey as built, with the claims it makes itself.
    pub fn base(&self, id: SurveyId) -> Option<&Arc<SurveyMeta>> {
        self.bases.get(&id)
    }

    /// How a terrain treats claims that other surveys contradict.
    pub fn set_contradicted(&mut self, c: Contradicted) {
        assert!(
            self.surveys.is_empty(),
            "a terrain's policy is set before its surveys"
        );
        self.contradicted = c;
    }

    /// How the terrain treats claims that other surveys contradict.
    pub fn contradicted(&self) -> Contradicted {
        self.contradicted
    }

    /// Sets how the patches this terrain resolves are blended: its store's choice.
    pub fn set_blend(&mut self, b: Blend) {
        self.blend = b;
    }

    /// How the patches this terrain resolves are blended.
    pub fn blend(&self) -> Blend {
        self.blend
    }

    /// What `s` and every survey of the terrain it overlaps say of each other (see
    /// [`evidence::compare`]), measured at the samples of the finer of the two against the
    /// other's surface (see [`SurveyMeta::finer_than`]), each read over the other's bounds, so
    /// that the figures do not depend on the order of insertion. Its samples are read as any
    /// survey's are: a survey being inserted holds them in memory.
    ///
    /// Surveys of two planes are compared through the store's: each sample of the finer is
    /// carried into the other's CRS by the maps that place them (exactly as a tile would
    /// evaluate the other there); surveys of one plane, in that plane.
    fn compare_with_all(&self, s: &Arc<SurveyMeta>) -> Result<Vec<PairEvidence>, SampleError> {
        let mut near = BTreeSet::new();
        self.footprints.for_each_in(&s.footprint(), |e| {
            near.insert(survey_of(e.at()));
        });
        let others: Vec<&Arc<SurveyMeta>> = near
            .iter()
            .filter_map(|id| self.bases.get(id))
            .filter(|o| o.id != s.id && s.footprint().intersects(&o.footprint()))
            .collect();
        debug_assert_eq!(
            others.iter().map(|o| o.id).collect::<Vec<_>>(),
            {
                let mut all: Vec<SurveyId> = self
                    .bases
                    .values()
                    .filter(|o| o.id != s.id && s.footprint().intersects(&o.footprint()))
                    .map(|o| o.id)
                    .collect();
                all.sort_unstable();
                all
            },
            "the footprint index misses an overlapping survey"
        );
        let mut out = Vec::new();
        for o in others {
            let (fine, coarse) = if s.finer_than(o) { (s, o) } else { (o, s) };
            if let Some(p) = self.compare_pair(fine, coarse)? {
                out.push(p);
            }
        }
        Ok(out)
    }

    /// [`evidence::compare`] of two surveys of the terrain, `fine` the finer.
    fn compare_pair(
        &self,
        fine: &SurveyMeta,
        coarse: &SurveyMeta,
    ) -> Result<Option<PairEvidence>, SampleError> {
        let (pf, pc) = (self.placement_of(fine), self.placement_of(coarse));
        let (ff, fc) = (
            pf.as_ref()
                .map_or(fine.shapes[0].world_bounds(), |p| p.footprint),
            pc.as_ref()
                .map_or(coarse.shapes[0].world_bounds(), |p| p.footprint),
        );
        if !ff.intersects(&fc) {
            return Ok(None);
        }
        let (plf, plc) = (
            pf.as_ref().map(|p| p.plane.clone()),
            pc.as_ref().map(|p| p.plane.clone()),
        );
        let same = plf.as_ref().map(|p| p.id) == plc.as_ref().map(|p| p.id);
        // Each one's bounds in the other's plane.
        let (coarse_in_fine, fine_in_coarse) = if same {
            (
                coarse.shapes[0].world_bounds(),
                fine.shapes[0].world_bounds(),
            )
        } else {
            let (Some(a), Some(b)) = (
                native_bounds(plf.as_deref(), &fc),
                native_bounds(plc.as_deref(), &ff),
            ) else {
                return Ok(None);
            };
            (a, b)
        };
        let (Some(rf), Some(rc)) = (
            fine.shapes[0].rect_over(&coarse_in_fine),
            coarse.shapes[0].rect_over(&fine_in_coarse),
        ) else {
            return Ok(None);
        };
        let a = self.samples(fine, 0, rf)?;
        let b = self.samples(coarse, 0, rc)?;
        let through = |from: &Option<Arc<Plane>>, to: &Option<Arc<Plane>>, p: [f64; 2]| {
            let q = match from {
                Some(f) => f.to_store.at(p)?,
                None => p,
            };
            match to {
                Some(t) => t.to_native.at(q),
                None => Some(q),
            }
        };
        let to_coarse = |p: [f64; 2]| -> Option<[f64; 2]> {
            if same {
                Some(p)
            } else {
                through(&plf, &plc, p)
            }
        };
        let to_fine = |p: [f64; 2]| -> Option<[f64; 2]> {
            if same {
                Some(p)
            } else {
                through(&plc, &plf, p)
            }
        };
        let base_f = self.bases.get(&fine.id).map_or(fine, |b| b);
        let base_c = self.bases.get(&coarse.id).map_or(coarse, |b| b);
        let sf = evidence::Side {
            id: fine.id,
            grid: &a,
            offset: [rf.c0, rf.r0],
            tiling: &base_f.tiling,
            accuracy: &base_f.kernel_accuracy,
        };
        let sc = evidence::Side {
            id: coarse.id,
            grid: &b,
            offset: [rc.c0, rc.r0],
            tiling: &base_c.tiling,
            accuracy: &base_c.kernel_accuracy,
        };
        Ok(evidence::compare(
            &sf,
            &sc,
            &to_coarse,
            &to_fine,
            &coarse_in_fine,
            fine.metres_per_unit(),
        ))
    }

    /// A survey's placement in the terrain's plane: its own, or worked out for one read back
    /// from a store (which keeps the errors but not the frames).
    fn placement_of(&self, s: &SurveyMeta) -> Option<Arc<place::Placement>> {
        if let Some(p) = &s.placement {
            return Some(p.clone());
        }
        s.placement_in(self.planes.as_ref()?).ok().flatten()
    }

    /// The uniform cut at error `e` over `roi` (see [`LodIndex::uniform`]).
    pub fn uniform(&self, roi: &Aabb, e: f64) -> Vec<Extracted> {
        self.index.uniform(roi, e)
    }

    /// The view-dependent cut of `v` (see [`LodIndex::view`]).
    pub fn view(&self, v: &ViewQuery) -> Vec<Extracted> {
        self.index.view(v)
    }

    /// The samples and geometry of extracted patches, ready to blend.
    ///
    /// # Panics
    /// As [`Terrain::insert`]; a terrain with a source calls [`Terrain::try_resolve`].
    pub fn resolve(&self, ps: &[Extracted]) -> PatchSet {
        self.try_resolve(ps).expect("samples held in memory")
    }

    /// The samples and geometry of extracted patches, read where they are not in memory.
    ///
    /// Patches of surveys in other CRSs read each sample's position in their own plane: the
    /// set carries the maps there, one per plane, numbered in plane-id order.
    pub fn try_resolve(&self, ps: &[Extracted]) -> Result<PatchSet, SampleError> {
        Ok(self.try_resolve_until(ps, &|| false)?.unwrap_or_default())
    }

    /// [`Terrain::try_resolve`], given up (None) once `cancelled` says so: it is asked before
    /// each patch's samples are read, which for a large cut is most of the time it takes.
    pub fn try_resolve_until(
        &self,
        ps: &[Extracted],
        cancelled: &(dyn Fn() -> bool + Sync),
    ) -> Result<Option<PatchSet>, SampleError> {
        let gave_up = std::sync::atomic::AtomicBool::new(false);
        let mut ids: Vec<PlaneId> = ps
            .iter()
            .map(|x| x.plane)
            .filter(|&p| p != STORE_PLANE)
            .collect();
        ids.sort_unstable();
        ids.dedup();
        let planes: Vec<Arc<Plane>> = ids
            .iter()
            .filter_map(|&id| self.planes.as_ref()?.by_id(id))
            .collect();
        let index_of = |id: PlaneId| -> u16 {
            match id {
                STORE_PLANE => 0,
                id => 1 + planes.iter().position(|p| p.id == id).unwrap_or(0) as u16,
            }
        };
        self.prefetch(ps)?;
        let patches = ps
            .par_iter()
            .filter_map(|x| {
                if gave_up.load(std::sync::atomic::Ordering::Relaxed) || cancelled() {
                    gave_up.store(true, std::sync::atomic::Ordering::Relaxed);
                    return None;
                }
                let r = match self.patch(x)? {
                    PatchRef::Survey(s, p) => {
                        let level = p.level as usize;
                        let rect = ResolvedPatch::reads(s, p);
                        self.window(s, level, rect)
                            .map(|w| ResolvedPatch::new(w, s, x.position as usize, x.fallback))
                    }
                    PatchRef::Edge(e) => self
                        .edge_grid(e)
                        .map(|g| ResolvedPatch::edge(e, g, x.fallback)),
                };
                Some(r.map(|mut r| {
                    if x.plane != STORE_PLANE {
                        r.plane = index_of(x.plane);
                        // Its reach in the store's plane, where samples are binned.
                        r.window_aabb = x.window.aabb();
                    }
                    r
                }))
            })
            .collect::<Result<Vec<_>, _>>()?;
        if gave_up.into_inner() {
            return Ok(None);
        }
        Ok(Some(
            PatchSet::new(patches)
                .with_planes(planes.iter().map(|p| p.to_native.clone()).collect())
                .with_blend(self.blend),
        ))
    }

    /// Asks the store for the samples of every survey patch of `ps` at once, which an object
    /// store answers with a few merged requests where a read a patch would make one each.
    fn prefetch(&self, ps: &[Extracted]) -> Result<(), SampleError> {
        let Some(source) = self.source.as_ref() else {
            return Ok(());
        };
        let wants: Vec<(SurveyId, usize, patchwork_model::grid::Shape, SampleRect)> = ps
            .iter()
            .filter_map(|x| match self.patch(x)? {
                PatchRef::Survey(s, p) if !self.resident.contains_key(&s.id) => {
                    let level = p.level as usize;
                    let shape = s.shapes[level];
                    Some((s.id, level, shape, ResolvedPatch::reads(s, p)))
                }
                _ => None,
            })
            .collect();
        if wants.len() > 1 {
            source.prefetch(&wants)?;
        }
        Ok(())
    }

    /// Resamples patches at the points of a grid on the CPU.
    pub fn resample(&self, patches: Vec<Extracted>, grid: &SampleGrid) -> Tile {
        self.try_resample(patches, grid)
            .expect("samples held in memory")
    }

    /// Resamples patches at the points of a grid on the CPU, reading samples as needed.
    pub fn try_resample(
        &self,
        patches: Vec<Extracted>,
        grid: &SampleGrid,
    ) -> Result<Tile, SampleError> {
        let set = self.try_resolve(&patches)?;
        Ok(Tile {
            width: grid.width,
            height: grid.height,
            heights: cpu::resample(&set, grid),
            shortfall: tile_shortfall(&patches, grid),
            patches,
        })
    }

    /// A north-up `width × height` tile over `roi` at error `e`.
    pub fn tile(&self, roi: &Aabb, width: usize, height: usize, e: f64) -> Tile {
        let ps = self.uniform(roi, e);
        self.resample(ps, &SampleGrid::uniform(roi, width, height))
    }

    /// Heights at points, at error `e`: what tiles holding the same points give there.
    pub fn sample(&self, points: &[[f64; 2]], e: f64) -> Vec<f32> {
        self.try_sample(points, e).expect("samples held in memory")
    }

    /// Heights at points, at error `e`, reading samples as needed.
    pub fn try_sample(&self, points: &[[f64; 2]], e: f64) -> Result<Vec<f32>, SampleError> {
        Ok(self
            .try_sample_until(points, e, &Cancel::default())?
            .expect("never cancelled"))
    }

    /// [`Terrain::try_sample`], given up (None) once `cancel` is set.
    pub fn try_sample_until(
        &self,
        points: &[[f64; 2]],
        e: f64,
        cancel: &Cancel,
    ) -> Result<Option<Vec<f32>>, SampleError> {
        let Some((_, set, grid, slots)) = self.point_set(points, e)? else {
            return Ok(Some(vec![f32::NAN; points.len()]));
        };
        Ok(cpu::resample_until(&set, &grid, cancel).map(|h| unsort(&h, &slots)))
    }

    /// [`Terrain::try_sample_until`], with what served each point: the patch of the cut that
    /// weighs most in its height ([`cpu::resample_serving`]), None where it has none.
    #[allow(clippy::type_complexity)]
    pub fn try_sample_sources_until(
        &self,
        points: &[[f64; 2]],
        e: f64,
        cancel: &Cancel,
    ) -> Result<Option<(Vec<f32>, Vec<Option<Extracted>>)>, SampleError> {
        let Some((ps, set, grid, slots)) = self.point_set(points, e)? else {
            return Ok(Some((
                vec![f32::NAN; points.len()],
                vec![None; points.len()],
            )));
        };
        let Some((heights, served)) = cpu::resample_serving(&set, &grid, cancel) else {
            return Ok(None);
        };
        let served = self.patches_served(&ps, &set, &grid, served);
        Ok(Some((unsort(&heights, &slots), unsort(&served, &slots))))
    }

    /// What served each sample of `grid` from the patches `ps`: the patch that weighs most
    /// in its height ([`cpu::resample_serving`]), None where it has none.
    pub fn try_sources(
        &self,
        ps: &[Extracted],
        grid: &SampleGrid,
    ) -> Result<Vec<Option<Extracted>>, SampleError> {
        let set = self.try_resolve(ps)?;
        let (_, served) =
            cpu::resample_serving(&set, grid, &Cancel::default()).expect("never cancelled");
        Ok(self.patches_served(ps, &set, grid, served))
    }

    /// What [`cpu::resample_serving`] found served each sample of `grid`, an index into
    /// `set` (resolved from `ps`), as the patch of `ps` (by id: the set holds those of the cut
    /// that could be read and reach a point). An edge patch, which
    /// stitches the samples of several surveys across their seam, is told as the member
    /// whose footprint holds the point, the most accurate where several do (the nearest
    /// where none does): its `survey` is that member's id, not the patch's owner.
    fn patches_served(
        &self,
        ps: &[Extracted],
        set: &PatchSet,
        grid: &SampleGrid,
        served: Vec<Option<u32>>,
    ) -> Vec<Option<Extracted>> {
        let by_id: std::collections::HashMap<_, &Extracted> =
            ps.iter().map(|x| (x.id, x)).collect();
        served
            .into_iter()
            .enumerate()
            .map(|(at, k)| {
                let id = set.patches[k? as usize].id;
                let mut x = (*by_id.get(&id)?).clone();
                if let Some(e) = self.edges.get(&x.survey) {
                    let p = grid.point(at);
                    // How far the point lies outside a member's footprint: 0 inside.
                    let off = |s: &SurveyMeta| {
                        let f = s.footprint();
                        let d = |lo: f64, v: f64, hi: f64| (lo - v).max(v - hi).max(0.0);
                        d(f.min[0], p[0], f.max[0]).hypot(d(f.min[1], p[1], f.max[1]))
                    };
                    x.survey = e
                        .members
                        .iter()
                        .filter_map(|m| self.surveys.get(m))
                        .min_by(|a, b| {
                            off(a)
                                .total_cmp(&off(b))
                                .then(a.accuracy.total_cmp(&b.accuracy))
                                .then(a.id.cmp(&b.id))
                        })
                        .map(|s| s.id)?;
                }
                Some(x)
            })
            .collect()
    }

    /// The patches points are sampled from at error `e`, resolved; the points as a grid; and
    /// where each point went in it (its sample's index). Each point's height depends on the point alone, so they
    /// may be laid out in any order: in Z order, [`BLOCK`] to a row, so that each block of
    /// the resampler (`BLOCK` × `BLOCK` samples, binned together) holds points close to each
    /// other and visits only the patches near them, whereas scattered points in the order
    /// given would each visit every patch of the cut. The rows resample on every core and a
    /// cancel is seen between them; the last is padded with points that are nowhere. None
    /// where no point is anywhere (outside where its CRS reaches the store's).
    #[allow(clippy::type_complexity)]
    fn point_set(
        &self,
        points: &[[f64; 2]],
        e: f64,
    ) -> Result<Option<(Vec<Extracted>, PatchSet, SampleGrid, Vec<usize>)>, SampleError> {
        let finite: Vec<[f64; 2]> = points
            .iter()
            .copied()
            .filter(|p| p[0].is_finite() && p[1].is_finite())
            .collect();
        if finite.is_empty() {
            return Ok(None);
        }
        let bounds = Aabb::of_points(&finite);
        let ps = self.uniform(&bounds, e);
        let mut set = self.try_resolve(&ps)?;
        // Only the patches that reach a point are blended: scattered points leave most of the
        // cut over their bounds unused, and a block of the resampler visits every patch
        // binned with it. A patch reaches exactly where it is binned (its `reach`).
        let near = Bucketed::new(&finite, &bounds);
        set.patches.retain(|p| near.any_in(&p.reach()));
        let order = z_order(points, &bounds);
        // `BLOCK` points in the first row of each band of `BLOCK` rows, the others nowhere:
        // a block then bins only the patches near its few points (nowhere costs a test).
        let width = points.len().min(BLOCK);
        let bands = points.len().div_ceil(width);
        let height = (bands - 1) * BLOCK + 1;
        let mut laid = vec![[f64::NAN, f64::NAN]; width * height];
        let mut slots = vec![0; points.len()];
        for (i, &k) in order.iter().enumerate() {
            let at = (i / width) * BLOCK * width + i % width;
            laid[at] = points[k];
            slots[k] = at;
        }
        Ok(Some((
            ps,
            set,
            SampleGrid::of_points(width, height, laid),
            slots,
        )))
    }

    /// A view-dependent sample grid of `width × height` screen pixels.
    pub fn view_tile(&self, v: &ViewQuery, width: usize, height: usize) -> Tile {
        let ps = self.view(v);
        self.resample(ps, &view_grid(v, width, height))
    }
}

/// The indices of `points` in Z (Morton) order over `bounds`, points that are nowhere last.
fn z_order(points: &[[f64; 2]], bounds: &Aabb) -> Vec<usize> {
    let span = [
        bounds.width().max(f64::MIN_POSITIVE),
        bounds.height().max(f64::MIN_POSITIVE),
    ];
    let key = |p: &[f64; 2]| -> u64 {
        if !(p[0].is_finite() && p[1].is_finite()) {
            return u64::MAX;
        }
        let q = |v: f64, lo: f64, s: f64| (((v - lo) / s).clamp(0.0, 1.0) * 65535.0) as u32;
        let (x, y) = (
            q(p[0], bounds.min[0], span[0]),
            q(p[1], bounds.min[1], span[1]),
        );
        (0..16).fold(0u64, |k, b| {
            k | (((x >> b) & 1) as u64) << (2 * b) | (((y >> b) & 1) as u64) << (2 * b + 1)
        })
    };
    let keys: Vec<u64> = points.iter().map(key).collect();
    let mut order: Vec<usize> = (0..points.len()).collect();
    order.sort_by_key(|&k| (keys[k], k));
    order
}

/// Values of a layout back in the points' own order: point k's is at `slots[k]`.
fn unsort<T: Clone>(laid: &[T], slots: &[usize]) -> Vec<T> {
    slots.iter().map(|&at| laid[at].clone()).collect()
}

/// Points bucketed on a grid over their bounds, to ask whether any lies in a rectangle.
struct Bucketed<'a> {
    points: &'a [[f64; 2]],
    bounds: Aabb,
    n: usize,
    /// Point indices by bucket, row-major, laid end to end: bucket b holds
    /// `entries[offsets[b]..offsets[b + 1]]`.
    offsets: Vec<u32>,
    entries: Vec<u32>,
}

impl<'a> Bucketed<'a> {
    fn new(points: &'a [[f64; 2]], bounds: &Aabb) -> Self {
        // About four points a bucket.
        let n = ((points.len() as f64 / 4.0).sqrt().ceil() as usize).clamp(1, 1024);
        let mut b = Bucketed {
            points,
            bounds: *bounds,
            n,
            offsets: vec![0; n * n + 1],
            entries: vec![0; points.len()],
        };
        let cells: Vec<usize> = points.iter().map(|p| b.cell(*p)).collect();
        for &c in &cells {
            b.offsets[c + 1] += 1;
        }
        for k in 0..n * n {
            b.offsets[k + 1] += b.offsets[k];
        }
        let mut fill = b.offsets.clone();
        for (i, &c) in cells.iter().enumerate() {
            b.entries[fill[c] as usize] = i as u32;
            fill[c] += 1;
        }
        b
    }

    fn index(&self, v: f64, axis: usize) -> usize {
        let span = (self.bounds.max[axis] - self.bounds.min[axis]).max(f64::MIN_POSITIVE);
        let t = ((v - self.bounds.min[axis]) / span * self.n as f64).floor();
        t.clamp(0.0, (self.n - 1) as f64) as usize
    }

    fn cell(&self, p: [f64; 2]) -> usize {
        self.index(p[1], 1) * self.n + self.index(p[0], 0)
    }

    /// Whether a point lies in `r` (bounds included).
    fn any_in(&self, r: &Aabb) -> bool {
        if !r.intersects(&self.bounds) {
            return false;
        }
        let (c0, c1) = (self.index(r.min[0], 0), self.index(r.max[0], 0));
        let (r0, r1) = (self.index(r.min[1], 1), self.index(r.max[1], 1));
        (r0..=r1).any(|row| {
            (c0..=c1).any(|col| {
                let b = row * self.n + col;
                self.entries[self.offsets[b] as usize..self.offsets[b + 1] as usize]
                    .iter()
                    .any(|&i| r.contains_point(self.points[i as usize]))
            })
        })
    }
}
