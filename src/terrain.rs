//! The in-memory engine: surveys, the edge patches their lattices call for, their LOD index,
//! and the queries and tiles built on them. It does no I/O: the samples of stored surveys come
//! through a [`SampleSource`], and the store persists what it holds.

use crate::crs::Crs;
use crate::index::geom::Aabb;
use crate::index::lod::{BoxState, ChangeStats, IndexConfig, LodIndex, PatchBox};
use crate::index::query::{Extracted, ViewQuery};
use crate::model::accuracy::{self, Deviation};
use crate::model::edge::{self, EdgePatch, Member};
use crate::model::grid::{Grid, SampleRect, Window};
use crate::model::ids::{PatchId, SurveyId};
use crate::model::lattice::{tile_of, Lattice};
use crate::model::patch::Patch;
use crate::model::place::{
    self, Frame, PlaceError, Plane, PlaneId, Planes, Residuals, STORE_PLANE,
};
use crate::model::source::{SampleError, SampleSource};
use crate::model::survey::{Survey, SurveyMeta};
use crate::resample::{cpu, Cancel, PatchSet, ResolvedPatch, SampleGrid};
use rayon::prelude::*;
use std::collections::{BTreeSet, HashMap};
use std::sync::Arc;

/// Why a survey could not be inserted or retired.
#[derive(Clone, Debug, thiserror::Error, PartialEq)]
pub enum TerrainError {
    #[error(transparent)]
    Samples(#[from] SampleError),
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
    let m = 1e-3 * a.width().max(a.height());
    Some(Aabb::new(
        a.min[0] - m,
        a.min[1] - m,
        a.max[0] + m,
        a.max[1] + m,
    ))
}

/// What the reprojection can cost an edge patch's heights: as for a survey's patch (see
/// [`place::reprojection_error`]), with the largest slope of its own cells.
fn edge_reprojection_error(e: &EdgePatch, rho: f64) -> f64 {
    let g = &e.grid;
    let mut slope = 0.0f64;
    for r in 0..g.rows {
        for c in 0..g.cols {
            let z = g.heights[r * g.cols + c] as f64;
            if z.is_nan() {
                continue;
            }
            for (dc, dr) in [(1, 0), (0, 1)] {
                let (cc, rr) = (c + dc, r + dr);
                if cc < g.cols && rr < g.rows {
                    let w = g.heights[rr * g.cols + cc] as f64;
                    if !w.is_nan() {
                        slope = slope.max((w - z).abs());
                    }
                }
            }
        }
    }
    std::f64::consts::SQRT_2 * rho * g.georef.cells_per_unit() * slope
}

/// Heights resampled from a set of patches. NaN marks nodata.
#[derive(Clone, Debug)]
pub struct Tile {
    pub width: usize,
    pub height: usize,
    pub heights: Vec<f32>,
    /// The patches the heights were blended from, in id order.
    pub patches: Vec<Extracted>,
}

/// A patch of the terrain: a survey's, or an edge patch.
#[derive(Clone, Copy, Debug)]
pub enum PatchRef<'a> {
    Survey(&'a Arc<SurveyMeta>, &'a Patch),
    Edge(&'a Arc<EdgePatch>),
}

#[derive(Clone, Copy, Debug)]
enum Slot {
    Survey(SurveyId, u32),
    Edge(SurveyId),
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
#[derive(Clone, Debug)]
struct LatticeGroup {
    plane: PlaneId,
    lattice: Lattice,
    members: Vec<GroupMember>,
    tiles: HashMap<[i64; 2], SurveyId>,
}

impl LatticeGroup {
    /// The tiles a change to `m` (inserting or retiring it) can alter: its own edge tiles and
    /// the edge tiles of the other members within its reach.
    fn affected_by(&self, m: &GroupMember) -> Vec<[i64; 2]> {
        let [[x0, x1], [y0, y1]] = m.tile_range();
        let mut set: BTreeSet<[i64; 2]> = m.edge_tiles().iter().copied().collect();
        for o in &self.members {
            if o.survey.id == m.survey.id {
                continue;
            }
            let [[a0, a1], [b0, b1]] = o.tile_range();
            if a0 > x1 || x0 > a1 || b0 > y1 || y0 > b1 {
                continue;
            }
            set.extend(
                o.edge_tiles()
                    .iter()
                    .filter(|t| (x0..=x1).contains(&t[0]) && (y0..=y1).contains(&t[1])),
            );
        }
        set.into_iter().collect()
    }
}

#[derive(Clone, Debug)]
pub struct Terrain {
    /// The store's CRS and the planes of surveys in others, once the terrain has a CRS.
    planes: Option<Arc<Planes>>,
    index: LodIndex,
    surveys: HashMap<SurveyId, Arc<SurveyMeta>>,
    edges: HashMap<SurveyId, Arc<EdgePatch>>,
    lattices: Vec<LatticeGroup>,
    patches: HashMap<PatchId, Slot>,
    /// Samples held in memory: surveys inserted with them and not yet handed to a store.
    resident: HashMap<SurveyId, Arc<[Arc<Grid>]>>,
    /// Where the samples of every other survey are read.
    source: Option<Arc<dyn SampleSource>>,
}

/// Edge patches to take out of the index and to put in.
type EdgeDiff = (Vec<SurveyId>, Vec<Arc<EdgePatch>>);

impl Terrain {
    pub fn new(cfg: IndexConfig) -> Self {
        Terrain {
            planes: None,
            index: LodIndex::new(cfg),
            surveys: HashMap::new(),
            edges: HashMap::new(),
            lattices: Vec::new(),
            patches: HashMap::new(),
            resident: HashMap::new(),
            source: None,
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

    /// Reads the samples of surveys not in memory from `source`.
    pub fn set_source(&mut self, source: Arc<dyn SampleSource>) {
        self.source = Some(source);
    }

    /// Drops a survey's samples from memory once its store can serve them; a terrain without
    /// a source keeps them.
    pub fn page_out(&mut self, id: SurveyId) {
        if self.source.is_some() {
            self.resident.remove(&id);
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
        })?;
        source.window(s.id, level, &s.shapes[level], rect)
    }

    /// Rebuilds a terrain from what a store keeps: the surveys without their samples, the
    /// edge patches and the box states, without running the cutter or reading a sample.
    /// Returns the patches that had no stored state, restored as empty.
    ///
    /// Surveys of another CRS than `crs` get their patches' frames in its plane; their errors
    /// are as stored. One that cannot be placed (which a store never holds) is left out and
    /// named in the second list.
    pub fn restore(
        cfg: IndexConfig,
        crs: Option<&Crs>,
        surveys: Vec<Arc<SurveyMeta>>,
        edges: Vec<Arc<EdgePatch>>,
        states: &HashMap<PatchId, BoxState>,
        source: Arc<dyn SampleSource>,
    ) -> (Self, Vec<PatchId>) {
        let mut t = Terrain::with_crs(cfg, crs, None);
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
        let mut group_of_survey = HashMap::new();
        for s in surveys {
            let gi = t.group_of(&s);
            let m = GroupMember::new(s.clone(), &t.lattices[gi].lattice);
            t.lattices[gi].members.push(m);
            group_of_survey.insert(s.id, gi);
            t.register(s);
        }
        for e in edges {
            // An edge patch whose surveys are gone would be stale; the index derivation that
            // a missing state triggers puts the right ones back.
            let Some(&gi) = e.members.first().and_then(|m| group_of_survey.get(m)) else {
                continue;
            };
            t.register_edge(gi, e);
        }
        let mut missing = Vec::new();
        let mut state = |id: PatchId| {
            states.get(&id).copied().unwrap_or_else(|| {
                missing.push(id);
                BoxState::EMPTY
            })
        };
        let mut units: Vec<(SurveyId, Vec<(PatchBox, BoxState)>)> = Vec::new();
        for s in t.surveys.values() {
            let boxes = s.boxes().into_iter().map(|b| {
                let st = state(b.id);
                (b, st)
            });
            units.push((s.id, boxes.collect()));
        }
        let boxes: Vec<(SurveyId, PatchBox)> =
            t.edges.values().map(|e| (e.owner, t.edge_box(e))).collect();
        for (owner, b) in boxes {
            let st = state(b.id);
            units.push((owner, vec![(b, st)]));
        }
        missing.sort_unstable();
        t.index = LodIndex::restore(cfg, units);
        (t, missing)
    }

    fn register(&mut self, s: Arc<SurveyMeta>) {
        for (k, p) in s.patches.iter().enumerate() {
            self.patches.insert(p.id, Slot::Survey(s.id, k as u32));
        }
        self.surveys.insert(s.id, s);
    }

    fn register_edge(&mut self, gi: usize, e: Arc<EdgePatch>) {
        self.patches.insert(e.id, Slot::Edge(e.owner));
        self.lattices[gi].tiles.insert(e.tile, e.owner);
        self.edges.insert(e.owner, e);
    }

    fn unregister_edge(&mut self, gi: usize, owner: SurveyId) {
        if let Some(e) = self.edges.remove(&owner) {
            self.patches.remove(&e.id);
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
                self.lattices.push(LatticeGroup {
                    plane,
                    lattice: l,
                    members: Vec::new(),
                    tiles: HashMap::new(),
                });
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
        let all = self.lattices.iter().flat_map(|g| &g.members);
        for m in all.filter(|g| members.contains(&g.survey.id)) {
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
    fn edge_box(&self, e: &EdgePatch) -> PatchBox {
        let framed = self.edge_frame(e);
        PatchBox::edge(e, framed.as_ref().map(|(id, f)| (*id, f)))
    }

    fn edge_frame(&self, e: &EdgePatch) -> Option<(PlaneId, Frame)> {
        let (plane, rho) = self.edge_plane(&e.members)?;
        let frame = plane
            .frame(&e.grid.georef, &e.window, &rho)
            .unwrap_or(Frame {
                // Every edge patch lies within its surveys' samples, which all have images;
                // should the fit still fail, a frame that reaches everywhere keeps coverage
                // conservative.
                map: crate::index::geom::Affine {
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
        let Some(layout) = g.members.first().map(|m| m.survey.layout) else {
            return Ok((g.tiles.values().copied().collect(), Vec::new()));
        };
        let built: Vec<([i64; 2], Option<EdgePatch>)> = tiles
            .par_iter()
            .map(|&t| {
                // Each tile reads only the members' samples around it.
                let mut windows = Vec::new();
                for m in &g.members {
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
                Ok((t, edge::build(t, &members, &layout)))
            })
            .collect::<Result<_, SampleError>>()?;
        let mut gone = Vec::new();
        let mut come = Vec::new();
        for (t, mut e) in built {
            // An edge patch of another plane, like its surveys' patches, answers for where the
            // reprojection moves its points: its error grows as theirs do.
            if let Some(e) = e.as_mut() {
                if let Some((_, rho)) = self.edge_plane(&e.members) {
                    e.error += edge_reprojection_error(e, rho.to_native);
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

    pub fn index(&self) -> &LodIndex {
        &self.index
    }

    pub fn survey(&self, id: SurveyId) -> Option<&Arc<SurveyMeta>> {
        self.surveys.get(&id)
    }

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
        let mut out: Vec<Arc<EdgePatch>> = changes
            .iter()
            .flat_map(|c| c.moved.iter())
            .filter_map(|(id, _)| match self.patch(*id)? {
                PatchRef::Edge(e) => Some(e.clone()),
                PatchRef::Survey(..) => None,
            })
            .collect();
        out.sort_by_key(|e| e.id);
        out.dedup_by_key(|e| e.id);
        out
    }

    /// A patch of the terrain.
    pub fn patch(&self, id: PatchId) -> Option<PatchRef<'_>> {
        match self.patches.get(&id)? {
            Slot::Survey(sid, k) => {
                let s = self.surveys.get(sid)?;
                Some(PatchRef::Survey(s, &s.patches[*k as usize]))
            }
            Slot::Edge(owner) => self.edges.get(owner).map(PatchRef::Edge),
        }
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
        let meta = s.meta();
        let gi = self.group_of(&meta);
        let m = GroupMember::new(meta.clone(), &self.lattices[gi].lattice);
        let affected = self.lattices[gi].affected_by(&m);
        self.lattices[gi].members.push(m);
        self.resident.insert(s.id, s.levels.clone().into());
        let (gone, come) = match self.rebuild(gi, affected) {
            Ok(d) => d,
            Err(e) => {
                self.resident.remove(&s.id);
                self.lattices[gi].members.pop();
                if self.lattices[gi].members.is_empty() {
                    self.lattices.remove(gi);
                }
                return Err(e.into());
            }
        };
        let mut insert = vec![(s.id, meta.boxes())];
        insert.extend(come.iter().map(|e| (e.owner, vec![self.edge_box(e)])));
        let stats = self.index.apply(&gone, insert);
        self.register(meta);
        for o in gone {
            self.unregister_edge(gi, o);
        }
        for e in come {
            self.register_edge(gi, e);
        }
        Ok(stats)
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
        let Some(gi) = self
            .lattices
            .iter()
            .position(|g| g.members.iter().any(|m| m.survey.id == id))
        else {
            return Ok(None);
        };
        let pos = self.lattices[gi]
            .members
            .iter()
            .position(|m| m.survey.id == id)
            .expect("member");
        let affected = {
            let g = &self.lattices[gi];
            g.affected_by(&g.members[pos])
        };
        let member = self.lattices[gi].members.remove(pos);
        let (mut gone, come) = match self.rebuild(gi, affected) {
            Ok(d) => d,
            Err(e) => {
                self.lattices[gi].members.insert(pos, member);
                return Err(e);
            }
        };
        let s = self.surveys.remove(&id).expect("a member is a survey");
        for p in &s.patches {
            self.patches.remove(&p.id);
        }
        self.resident.remove(&id);
        let insert = come
            .iter()
            .map(|e| (e.owner, vec![self.edge_box(e)]))
            .collect();
        let edge_gone = gone.clone();
        gone.push(id);
        let stats = self.index.apply(&gone, insert);
        for o in edge_gone {
            self.unregister_edge(gi, o);
        }
        for e in come {
            self.register_edge(gi, e);
        }
        if self.lattices[gi].members.is_empty() {
            self.lattices.remove(gi);
        }
        Ok(Some(stats))
    }

    /// How `s` and every survey of the terrain that it overlaps disagree, measured at the
    /// samples of the finer of the two against the other's surface (see
    /// [`SurveyMeta::finer_than`]). Each of the two is read over the other's bounds, whichever
    /// came first, so the figure does not depend on the order of insertion.
    ///
    /// Surveys of two planes are compared through the store's: each sample of the finer is
    /// carried into the other's CRS by the maps that place them (exactly as a tile would
    /// evaluate the other there); surveys of one plane, in that plane.
    pub fn overlaps(&self, s: &Survey) -> Result<Vec<(SurveyId, Deviation)>, SampleError> {
        let mine_plane = self.placement_of(s);
        let mine = match &mine_plane {
            Some(p) => p.footprint,
            None => s.shapes[0].world_bounds(),
        };
        let mut out = Vec::new();
        for o in self.surveys.values() {
            if o.id == s.id {
                continue;
            }
            let theirs = o.footprint();
            if !mine.intersects(&theirs) {
                continue;
            }
            let (ps, po) = (
                mine_plane.as_ref().map(|p| p.plane.clone()),
                o.placement.as_ref().map(|p| p.plane.clone()),
            );
            let same = ps.as_ref().map(|p| p.id) == po.as_ref().map(|p| p.id);
            // Each one's bounds in the other's plane.
            let (theirs_here, mine_there) = if same {
                (o.shapes[0].world_bounds(), s.shapes[0].world_bounds())
            } else {
                let (Some(a), Some(b)) = (
                    native_bounds(ps.as_deref(), &theirs),
                    native_bounds(po.as_deref(), &mine),
                ) else {
                    continue;
                };
                (a, b)
            };
            let (Some(rs), Some(ro)) = (
                s.shapes[0].rect_over(&theirs_here),
                o.shapes[0].rect_over(&mine_there),
            ) else {
                continue;
            };
            let a = s.levels[0].window(rs.c0, rs.r0, rs.cols(), rs.rows());
            let b = self.samples(o, 0, ro)?;
            let s_finer = s.finer_than(o);
            let (fine, coarse) = if s_finer { (&a, &b) } else { (&b, &a) };
            let d = if same {
                accuracy::deviation(fine, coarse)
            } else {
                let (from, to) = if s_finer { (&ps, &po) } else { (&po, &ps) };
                let carry = |p: [f64; 2]| -> Option<[f64; 2]> {
                    let q = match from {
                        Some(f) => f.to_store.at(p)?,
                        None => p,
                    };
                    match to {
                        Some(t) => t.to_native.at(q),
                        None => Some(q),
                    }
                };
                let bounds = if s_finer { &theirs_here } else { &mine_there };
                accuracy::deviation_across(fine, coarse, bounds, &carry)
            };
            if let Some(d) = d {
                out.push((o.id, d));
            }
        }
        out.sort_by_key(|(id, _)| *id);
        Ok(out)
    }

    /// A survey's placement in the terrain's plane: its own, or worked out for one read back
    /// from a store (which keeps the errors but not the frames).
    fn placement_of(&self, s: &SurveyMeta) -> Option<Arc<place::Placement>> {
        if let Some(p) = &s.placement {
            return Some(p.clone());
        }
        s.placement_in(self.planes.as_ref()?).ok().flatten()
    }

    pub fn uniform(&self, roi: &Aabb, e: f64) -> Vec<Extracted> {
        self.index.uniform(roi, e)
    }

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
        let patches = ps
            .par_iter()
            .filter_map(|x| {
                let r = match self.patch(x.id)? {
                    PatchRef::Survey(s, p) => {
                        let level = p.level as usize;
                        let rect = ResolvedPatch::reads(p, &s.shapes[level]);
                        self.window(s, level, rect)
                            .map(|w| ResolvedPatch::new(w, p, s.kind, x.fallback))
                    }
                    PatchRef::Edge(e) => Ok(ResolvedPatch::edge(e, x.fallback)),
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
        Ok(
            PatchSet::new(patches)
                .with_planes(planes.iter().map(|p| p.to_native.clone()).collect()),
        )
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
        // A point that is nowhere (outside where its CRS reaches the store's) has no height.
        let finite: Vec<[f64; 2]> = points
            .iter()
            .copied()
            .filter(|p| p[0].is_finite() && p[1].is_finite())
            .collect();
        if finite.is_empty() {
            return Ok(Some(vec![f32::NAN; points.len()]));
        }
        let ps = self.uniform(&Aabb::of_points(&finite), e);
        let set = self.try_resolve(&ps)?;
        // Rows of points, so that they resample on every core and a cancel is seen between
        // rows; each point's height depends on the point alone. The last row is padded with
        // points that are nowhere.
        const ROW: usize = 1024;
        let width = points.len().min(ROW);
        let height = points.len().div_ceil(width);
        let mut padded = points.to_vec();
        padded.resize(width * height, [f64::NAN, f64::NAN]);
        let grid = SampleGrid::of_points(width, height, padded);
        Ok(cpu::resample_until(&set, &grid, cancel).map(|mut h| {
            h.truncate(points.len());
            h
        }))
    }

    /// A view-dependent sample grid of `width × height` screen pixels.
    pub fn view_tile(&self, v: &ViewQuery, width: usize, height: usize) -> Tile {
        let ps = self.view(v);
        self.resample(ps, &SampleGrid::view(v, width, height, v.look[2]))
    }
}
