//! The in-memory engine: surveys, their LOD index, and the queries and tiles built on them.
//! It does no I/O; the store persists what it holds and the server calls into it.

use crate::index::geom::Aabb;
use crate::index::lod::{ChangeStats, IndexConfig, LodIndex};
use crate::index::query::{Extracted, ViewQuery};
use crate::model::ids::{PatchId, SurveyId};
use crate::model::patch::{Bilinear, Patch};
use crate::model::survey::Survey;
use crate::resample::{cpu, PatchSet, ResolvedPatch, SampleGrid};
use std::collections::HashMap;
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

#[derive(Clone, Debug)]
pub struct Terrain {
    index: LodIndex,
    surveys: HashMap<SurveyId, Arc<Survey>>,
    patches: HashMap<PatchId, (SurveyId, u32)>,
}

impl Terrain {
    pub fn new(cfg: IndexConfig) -> Self {
        Terrain {
            index: LodIndex::new(cfg),
            surveys: HashMap::new(),
            patches: HashMap::new(),
        }
    }

    /// Rebuilds a terrain from surveys and the box tops stored with them.
    pub fn restore(cfg: IndexConfig, surveys: Vec<(Arc<Survey>, HashMap<PatchId, f64>)>) -> Self {
        let index = LodIndex::restore(
            cfg,
            surveys.iter().map(|(s, tops)| {
                let boxes = s
                    .boxes()
                    .into_iter()
                    .map(|b| {
                        let top = tops.get(&b.id).copied().unwrap_or(f64::NEG_INFINITY);
                        (b, top)
                    })
                    .collect();
                (s.id, boxes)
            }),
        );
        let mut t = Terrain {
            index,
            surveys: HashMap::new(),
            patches: HashMap::new(),
        };
        for (s, _) in surveys {
            t.register(s);
        }
        t
    }

    fn register(&mut self, s: Arc<Survey>) {
        for (k, p) in s.patches.iter().enumerate() {
            self.patches.insert(p.id, (s.id, k as u32));
        }
        self.surveys.insert(s.id, s);
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

    /// A patch and the survey it belongs to.
    pub fn patch(&self, id: PatchId) -> Option<(&Arc<Survey>, &Patch)> {
        let (sid, k) = self.patches.get(&id)?;
        let s = self.surveys.get(sid)?;
        Some((s, &s.patches[*k as usize]))
    }

    /// Adds a survey; adding one already present changes nothing.
    pub fn insert(&mut self, s: Arc<Survey>) -> ChangeStats {
        if self.surveys.contains_key(&s.id) {
            return ChangeStats::default();
        }
        let stats = self.index.insert_survey(s.id, s.boxes());
        self.register(s);
        stats
    }

    /// Removes a survey; the index becomes the one that never had it.
    pub fn retire(&mut self, id: SurveyId) -> Option<ChangeStats> {
        let s = self.surveys.remove(&id)?;
        for p in &s.patches {
            self.patches.remove(&p.id);
        }
        self.index.retire_survey(id)
    }

    pub fn uniform(&self, roi: &Aabb, e: f64) -> Vec<Extracted> {
        self.index.uniform(roi, e)
    }

    pub fn view(&self, v: &ViewQuery) -> Vec<Extracted> {
        self.index.view(v)
    }

    /// The samples and geometry of extracted patches, ready to blend.
    pub fn resolve(&self, ps: &[Extracted]) -> PatchSet {
        PatchSet {
            patches: ps
                .iter()
                .filter_map(|x| {
                    let (s, p) = self.patch(x.id)?;
                    Some(ResolvedPatch::new(s.levels[p.level as usize].clone(), p))
                })
                .collect(),
        }
    }

    /// Resamples patches at the points of a grid on the CPU.
    pub fn resample(&self, patches: Vec<Extracted>, grid: &SampleGrid) -> Tile {
        let set = self.resolve(&patches);
        Tile {
            width: grid.width,
            height: grid.height,
            heights: cpu::resample(&set, grid, &Bilinear),
            patches,
        }
    }

    /// A north-up `width × height` tile over `roi` at error `e`.
    pub fn tile(&self, roi: &Aabb, width: usize, height: usize, e: f64) -> Tile {
        let ps = self.uniform(roi, e);
        self.resample(ps, &SampleGrid::uniform(roi, width, height))
    }

    /// A view-dependent sample grid of `width × height` screen pixels.
    pub fn view_tile(&self, v: &ViewQuery, width: usize, height: usize) -> Tile {
        let ps = self.view(v);
        self.resample(ps, &SampleGrid::view(v, width, height, v.look[2]))
    }
}
