//! The in-memory engine: surveys, the edge patches their lattices call for, their LOD index,
//! and the queries and tiles built on them. It does no I/O; the store persists what it holds
//! and the server calls into it.

use crate::index::geom::Aabb;
use crate::index::lod::{BoxState, ChangeStats, IndexConfig, LodIndex, PatchBox};
use crate::index::query::{Extracted, ViewQuery};
use crate::model::edge::{self, EdgePatch, Member};
use crate::model::ids::{PatchId, SurveyId};
use crate::model::lattice::{tile_of, Lattice};
use crate::model::patch::Patch;
use crate::model::survey::Survey;
use crate::resample::{cpu, PatchSet, ResolvedPatch, SampleGrid};
use rayon::prelude::*;
use std::collections::{BTreeSet, HashMap};
use std::sync::Arc;

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
    Survey(&'a Arc<Survey>, &'a Patch),
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
    survey: Arc<Survey>,
    index: [i64; 2],
    edge_tiles: Arc<Vec<[i64; 2]>>,
}

impl GroupMember {
    fn new(survey: Arc<Survey>, lattice: &Lattice) -> Self {
        let index = lattice.index_of(&survey.levels[0].georef);
        let edge_tiles = Arc::new(edge::edge_tiles(
            &Member {
                survey: &survey,
                index,
            },
            &survey.layout,
        ));
        GroupMember {
            survey,
            index,
            edge_tiles,
        }
    }

    fn as_member(&self) -> Member<'_> {
        Member {
            survey: &self.survey,
            index: self.index,
        }
    }

    /// The tiles whose edge patches can read this survey's samples, as inclusive ranges.
    fn tile_range(&self) -> [[i64; 2]; 2] {
        let l = &self.survey.layout;
        let side = edge::tile_side(l);
        let reach = l.margin as i64 + 1;
        let g = &self.survey.levels[0];
        let span = |a: usize, n: usize| {
            [
                tile_of(self.index[a] - reach, side) - 1,
                tile_of(self.index[a] + n as i64 - 1 + reach, side),
            ]
        };
        [span(0, g.cols), span(1, g.rows)]
    }
}

/// The surveys that share one lattice, and the edge patch of each of its tiles that has one.
#[derive(Clone, Debug)]
struct LatticeGroup {
    lattice: Lattice,
    members: Vec<GroupMember>,
    tiles: HashMap<[i64; 2], SurveyId>,
}

impl LatticeGroup {
    /// The tiles a change to `m` (inserting or retiring it) can alter: its own edge tiles and
    /// the edge tiles of the other members within its reach.
    fn affected_by(&self, m: &GroupMember) -> Vec<[i64; 2]> {
        let [[x0, x1], [y0, y1]] = m.tile_range();
        let mut set: BTreeSet<[i64; 2]> = m.edge_tiles.iter().copied().collect();
        for o in &self.members {
            if o.survey.id == m.survey.id {
                continue;
            }
            let [[a0, a1], [b0, b1]] = o.tile_range();
            if a0 > x1 || x0 > a1 || b0 > y1 || y0 > b1 {
                continue;
            }
            set.extend(
                o.edge_tiles
                    .iter()
                    .filter(|t| (x0..=x1).contains(&t[0]) && (y0..=y1).contains(&t[1])),
            );
        }
        set.into_iter().collect()
    }
}

#[derive(Clone, Debug)]
pub struct Terrain {
    index: LodIndex,
    surveys: HashMap<SurveyId, Arc<Survey>>,
    edges: HashMap<SurveyId, Arc<EdgePatch>>,
    lattices: Vec<LatticeGroup>,
    patches: HashMap<PatchId, Slot>,
}

/// Edge patches to take out of the index and to put in.
type EdgeDiff = (Vec<SurveyId>, Vec<Arc<EdgePatch>>);

impl Terrain {
    pub fn new(cfg: IndexConfig) -> Self {
        Terrain {
            index: LodIndex::new(cfg),
            surveys: HashMap::new(),
            edges: HashMap::new(),
            lattices: Vec::new(),
            patches: HashMap::new(),
        }
    }

    /// Rebuilds a terrain from surveys and the box states stored with them, without running
    /// the cutter: the edge patches are derived again from the surveys, their states read
    /// like the others. Returns the patches that had no stored state, restored as empty.
    pub fn restore(
        cfg: IndexConfig,
        surveys: Vec<Arc<Survey>>,
        states: &HashMap<PatchId, BoxState>,
    ) -> (Self, Vec<PatchId>) {
        let mut t = Terrain::new(cfg);
        for s in surveys {
            let gi = t.group_of(&s);
            let m = GroupMember::new(s.clone(), &t.lattices[gi].lattice);
            t.lattices[gi].members.push(m);
            t.register(s);
        }
        for gi in 0..t.lattices.len() {
            let tiles: BTreeSet<[i64; 2]> = t.lattices[gi]
                .members
                .iter()
                .flat_map(|m| m.edge_tiles.iter().copied())
                .collect();
            let (_, add) = t.rebuild(gi, tiles.into_iter().collect());
            for e in add {
                t.register_edge(gi, e);
            }
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
        for e in t.edges.values() {
            let b = PatchBox::edge(e);
            let st = state(b.id);
            units.push((e.owner, vec![(b, st)]));
        }
        missing.sort_unstable();
        t.index = LodIndex::restore(cfg, units);
        (t, missing)
    }

    fn register(&mut self, s: Arc<Survey>) {
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

    /// The lattice group a survey belongs to, made if it is the first on its lattice.
    fn group_of(&mut self, s: &Survey) -> usize {
        let l = Lattice::of(&s.levels[0].georef);
        match self.lattices.iter().position(|g| g.lattice.same(&l)) {
            Some(i) => i,
            None => {
                self.lattices.push(LatticeGroup {
                    lattice: l,
                    members: Vec::new(),
                    tiles: HashMap::new(),
                });
                self.lattices.len() - 1
            }
        }
    }

    /// The edge patches of `tiles` as the group's members now call for, against those there:
    /// the owners that go and the patches that come.
    fn rebuild(&self, gi: usize, tiles: Vec<[i64; 2]>) -> EdgeDiff {
        let g = &self.lattices[gi];
        let members: Vec<Member> = g.members.iter().map(|m| m.as_member()).collect();
        let Some(layout) = g.members.first().map(|m| m.survey.layout) else {
            return (g.tiles.values().copied().collect(), Vec::new());
        };
        let built: Vec<([i64; 2], Option<EdgePatch>)> = tiles
            .par_iter()
            .map(|&t| (t, edge::build(t, &members, &layout)))
            .collect();
        let mut gone = Vec::new();
        let mut come = Vec::new();
        for (t, e) in built {
            let old = g.tiles.get(&t).copied();
            let new = e.as_ref().map(|e| e.owner);
            if old == new {
                continue;
            }
            gone.extend(old);
            come.extend(e.map(Arc::new));
        }
        (gone, come)
    }

    pub fn index(&self) -> &LodIndex {
        &self.index
    }

    pub fn survey(&self, id: SurveyId) -> Option<&Arc<Survey>> {
        self.surveys.get(&id)
    }

    pub fn surveys(&self) -> impl Iterator<Item = &Arc<Survey>> {
        self.surveys.values()
    }

    /// The edge patches, in no particular order.
    pub fn edges(&self) -> impl Iterator<Item = &Arc<EdgePatch>> {
        self.edges.values()
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
    /// nothing.
    pub fn insert(&mut self, s: Arc<Survey>) -> ChangeStats {
        if self.surveys.contains_key(&s.id) {
            return ChangeStats::default();
        }
        let gi = self.group_of(&s);
        let m = GroupMember::new(s.clone(), &self.lattices[gi].lattice);
        let affected = self.lattices[gi].affected_by(&m);
        self.lattices[gi].members.push(m);
        let (gone, come) = self.rebuild(gi, affected);
        let mut insert = vec![(s.id, s.boxes())];
        insert.extend(come.iter().map(|e| (e.owner, vec![PatchBox::edge(e)])));
        let stats = self.index.apply(&gone, insert);
        self.register(s);
        for o in gone {
            self.unregister_edge(gi, o);
        }
        for e in come {
            self.register_edge(gi, e);
        }
        stats
    }

    /// Removes a survey and the edge patches it changes; the terrain becomes the one that
    /// never had it.
    pub fn retire(&mut self, id: SurveyId) -> Option<ChangeStats> {
        let s = self.surveys.remove(&id)?;
        for p in &s.patches {
            self.patches.remove(&p.id);
        }
        let gi = self
            .lattices
            .iter()
            .position(|g| g.members.iter().any(|m| m.survey.id == id))
            .expect("every survey is on a lattice");
        let pos = self.lattices[gi]
            .members
            .iter()
            .position(|m| m.survey.id == id)
            .expect("member");
        let affected = {
            let g = &self.lattices[gi];
            g.affected_by(&g.members[pos])
        };
        self.lattices[gi].members.remove(pos);
        let (mut gone, come) = self.rebuild(gi, affected);
        let insert = come
            .iter()
            .map(|e| (e.owner, vec![PatchBox::edge(e)]))
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
        Some(stats)
    }

    pub fn uniform(&self, roi: &Aabb, e: f64) -> Vec<Extracted> {
        self.index.uniform(roi, e)
    }

    pub fn view(&self, v: &ViewQuery) -> Vec<Extracted> {
        self.index.view(v)
    }

    /// The samples and geometry of extracted patches, ready to blend.
    pub fn resolve(&self, ps: &[Extracted]) -> PatchSet {
        PatchSet::new(
            ps.iter()
                .filter_map(|x| {
                    Some(match self.patch(x.id)? {
                        PatchRef::Survey(s, p) => {
                            ResolvedPatch::new(s.levels[p.level as usize].clone(), p, x.fallback)
                        }
                        PatchRef::Edge(e) => ResolvedPatch::edge(e, x.fallback),
                    })
                })
                .collect(),
        )
    }

    /// Resamples patches at the points of a grid on the CPU.
    pub fn resample(&self, patches: Vec<Extracted>, grid: &SampleGrid) -> Tile {
        let set = self.resolve(&patches);
        Tile {
            width: grid.width,
            height: grid.height,
            heights: cpu::resample(&set, grid),
            patches,
        }
    }

    /// A north-up `width × height` tile over `roi` at error `e`.
    pub fn tile(&self, roi: &Aabb, width: usize, height: usize, e: f64) -> Tile {
        let ps = self.uniform(roi, e);
        self.resample(ps, &SampleGrid::uniform(roi, width, height))
    }

    /// Heights at points, at error `e`: what tiles holding the same points give there.
    pub fn sample(&self, points: &[[f64; 2]], e: f64) -> Vec<f32> {
        if points.is_empty() {
            return Vec::new();
        }
        let ps = self.uniform(&Aabb::of_points(points), e);
        let grid = SampleGrid {
            width: points.len(),
            height: 1,
            points: points.to_vec(),
        };
        self.resample(ps, &grid).heights
    }

    /// A view-dependent sample grid of `width × height` screen pixels.
    pub fn view_tile(&self, v: &ViewQuery, width: usize, height: usize) -> Tile {
        let ps = self.view(v);
        self.resample(ps, &SampleGrid::view(v, width, height, v.look[2]))
    }
}
