//! LOD space: one box per patch, kept minimal and order-independent (paper §3.3).
//!
//! The top of a box is a pure function of the set of patches present: the lowest z at which
//! patches greater than it in the global order, and no less accurate than z, cover its valid
//! kernel. Algorithm 1 computes exactly that when it is given every greater patch, active or
//! not: a patch cut to nothing is covered by greater patches at least as accurate as itself,
//! so leaving it in the candidate set never changes the answer. Recomputing the top of every
//! patch a change can touch therefore gives the same index for the same set of surveys,
//! whatever the order of insertions and retirements, and retiring a survey restores every
//! patch it had cut.

use super::cover::covered_all;
use super::geom::{Aabb, ORect};
use super::quadtree::{Entry, MsQuadtree, TreeStats};
use crate::model::grid::Grid;
use crate::model::ids::{PatchId, SurveyId};
use crate::model::patch::Patch;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::cmp::Ordering;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Arc;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IndexConfig {
    /// The top of LOD space, in metres: boxes start this tall.
    pub max_error: f64,
    /// Boxes per quadtree node (t in §4.2).
    pub node_capacity: usize,
}

impl Default for IndexConfig {
    fn default() -> Self {
        IndexConfig {
            max_error: 10_000.0,
            node_capacity: 64,
        }
    }
}

/// A patch as LOD space sees it: its kernel, its valid part, and its error.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PatchBox {
    pub id: PatchId,
    pub survey: SurveyId,
    pub level: u8,
    /// Nominal kernel area, the first key of the global order.
    pub area: f64,
    /// Bottom of the box: the patch's error ε + δ.
    pub min_z: f64,
    pub kernel: ORect,
    pub valid: Vec<ORect>,
    pub window: ORect,
    /// Bounds of the kernel.
    pub aabb: Aabb,
}

impl PatchBox {
    pub fn new(p: &Patch, level: &Grid, kernel_cells: usize) -> Self {
        let g = &level.georef;
        let kernel = ORect::from_cells(g, &p.kernel);
        let side = kernel_cells as f64;
        PatchBox {
            id: p.id,
            survey: p.survey,
            level: p.level,
            area: side * g.step[0] * side * g.step[1],
            min_z: p.error,
            kernel,
            valid: p.valid.iter().map(|c| ORect::from_cells(g, c)).collect(),
            window: ORect::from_cells(g, &p.window),
            aabb: kernel.aabb(),
        }
    }

    /// The global order: smaller area first; at equal area the less accurate first; at equal
    /// area and error the id decides, so that identical-looking patches from two surveys do
    /// not both survive.
    pub fn order(&self, o: &PatchBox) -> Ordering {
        self.area
            .total_cmp(&o.area)
            .then(o.min_z.total_cmp(&self.min_z))
            .then(self.id.cmp(&o.id))
    }
}

/// A box's current z-span `[min_z, max_z)`; empty when the patch is cut to nothing.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Span {
    pub min_z: f64,
    pub max_z: f64,
}

impl Span {
    pub fn is_active(&self) -> bool {
        self.max_z > self.min_z
    }
}

#[derive(Clone, Debug)]
struct Slot {
    bx: Arc<PatchBox>,
    max_z: f64,
}

/// What an insertion or retirement did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ChangeStats {
    pub patches: usize,
    /// Boxes whose top was recomputed.
    pub recomputed: usize,
    /// Boxes whose top moved (the new ones included), with their new top: what a store must
    /// write beside the survey to persist the index.
    pub moved: Vec<(PatchId, f64)>,
}

#[derive(Clone, Debug)]
struct SurveyEntry {
    patches: Vec<PatchId>,
    /// The survey's best error: its accuracy ε, the error of its level-0 patches.
    floor: f64,
    /// Bounds of its kernels.
    bounds: Aabb,
}

#[derive(Clone, Debug)]
pub struct LodIndex {
    cfg: IndexConfig,
    slots: HashMap<PatchId, Slot>,
    surveys: HashMap<SurveyId, SurveyEntry>,
    tree: MsQuadtree,
}

impl LodIndex {
    pub fn new(cfg: IndexConfig) -> Self {
        LodIndex {
            cfg,
            slots: HashMap::new(),
            surveys: HashMap::new(),
            tree: MsQuadtree::new(cfg.node_capacity),
        }
    }

    pub fn config(&self) -> &IndexConfig {
        &self.cfg
    }

    pub fn len(&self) -> usize {
        self.slots.len()
    }

    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    pub fn contains_survey(&self, s: SurveyId) -> bool {
        self.surveys.contains_key(&s)
    }

    pub fn surveys(&self) -> impl Iterator<Item = SurveyId> + '_ {
        self.surveys.keys().copied()
    }

    pub fn survey_floor(&self, s: SurveyId) -> Option<f64> {
        self.surveys.get(&s).map(|e| e.floor)
    }

    pub fn survey_patches(&self, s: SurveyId) -> Option<&[PatchId]> {
        self.surveys.get(&s).map(|e| e.patches.as_slice())
    }

    /// Accuracies of the surveys whose bounds meet `area`.
    pub fn survey_floors_in(&self, area: &Aabb) -> Vec<f64> {
        self.surveys
            .values()
            .filter(|e| e.bounds.intersects(area))
            .map(|e| e.floor)
            .collect()
    }

    pub fn get(&self, id: PatchId) -> Option<(&Arc<PatchBox>, Span)> {
        self.slots.get(&id).map(|s| {
            (
                &s.bx,
                Span {
                    min_z: s.bx.min_z,
                    max_z: s.max_z,
                },
            )
        })
    }

    pub fn tree_stats(&self) -> TreeStats {
        self.tree.stats()
    }

    pub fn bounds(&self) -> Option<Aabb> {
        self.tree.bounds()
    }

    pub(crate) fn tree(&self) -> &MsQuadtree {
        &self.tree
    }

    /// Every box and its span, in id order: two indexes over the same surveys give equal maps.
    pub fn state(&self) -> BTreeMap<PatchId, Span> {
        self.slots
            .iter()
            .map(|(id, s)| {
                (
                    *id,
                    Span {
                        min_z: s.bx.min_z,
                        max_z: s.max_z,
                    },
                )
            })
            .collect()
    }

    pub fn active_count(&self) -> usize {
        self.slots.values().filter(|s| s.max_z > s.bx.min_z).count()
    }

    fn entry(slot: &Slot) -> Entry {
        Entry {
            id: slot.bx.id,
            ceiling: slot.max_z,
            floor: slot.bx.min_z,
            aabb: slot.bx.aabb,
        }
    }

    /// Boxes whose kernel bounds meet `area`, each once, in id order.
    pub(crate) fn boxes_in(&self, area: &Aabb) -> Vec<&Arc<PatchBox>> {
        let mut ids = Vec::new();
        self.tree.for_each_in(area, |e| ids.push(e.id));
        ids.sort_unstable();
        ids.dedup();
        ids.iter().map(|id| &self.slots[id].bx).collect()
    }

    /// Algorithm 1, over every greater patch present. Candidates are taken in order of error
    /// (ties by id, so the answer never depends on iteration order); coverage is monotone in
    /// the set, so a binary search over the distinct errors finds the first that covers.
    fn ceiling_of(&self, p: &PatchBox) -> f64 {
        let top = self.cfg.max_error;
        let mut cands: Vec<&Arc<PatchBox>> = self
            .boxes_in(&p.aabb)
            .into_iter()
            .filter(|q| q.order(p) == Ordering::Greater && q.kernel.intersects(&p.kernel))
            .collect();
        if cands.is_empty() {
            return top;
        }
        cands.sort_by(|a, b| a.min_z.total_cmp(&b.min_z).then(a.id.cmp(&b.id)));
        let rects_upto = |n: usize| -> Vec<ORect> {
            cands[..n]
                .iter()
                .flat_map(|q| q.valid.iter().copied())
                .collect()
        };
        if !covered_all(&p.valid, &rects_upto(cands.len())) {
            return top;
        }
        // Ends of runs of equal error: the prefixes worth testing.
        let ends: Vec<usize> = (1..=cands.len())
            .filter(|&n| n == cands.len() || cands[n].min_z != cands[n - 1].min_z)
            .collect();
        let (mut lo, mut hi) = (0usize, ends.len() - 1);
        while lo < hi {
            let mid = (lo + hi) / 2;
            if covered_all(&p.valid, &rects_upto(ends[mid])) {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        let z = cands[ends[lo] - 1].min_z;
        // At or below the patch's own error the patch is redundant: its span is empty.
        z.min(top)
    }

    /// Recomputes the tops of `ids` against the current set and moves changed boxes in the tree.
    fn recompute(&mut self, ids: Vec<PatchId>) -> (usize, Vec<(PatchId, f64)>) {
        let tops: Vec<(PatchId, f64)> = ids
            .par_iter()
            .filter_map(|id| self.slots.get(id).map(|s| (*id, self.ceiling_of(&s.bx))))
            .collect();
        let mut moved = Vec::new();
        for (id, top) in &tops {
            let slot = self.slots.get_mut(id).expect("present");
            if slot.max_z.total_cmp(top) != Ordering::Equal {
                let old = Self::entry(slot);
                slot.max_z = *top;
                let new = Self::entry(slot);
                self.tree.remove(old.id, &old.aabb);
                self.tree.insert(new);
                moved.push((*id, *top));
            }
        }
        (tops.len(), moved)
    }

    /// Patches already present that are smaller than one of `bigs` and meet it: the only ones
    /// whose top `bigs` can move.
    fn touched_by(&self, bigs: &[Arc<PatchBox>]) -> Vec<PatchId> {
        let set: HashSet<PatchId> = bigs
            .par_iter()
            .flat_map_iter(|b| {
                self.boxes_in(&b.aabb)
                    .into_iter()
                    .filter(|q| q.order(b) == Ordering::Less && q.kernel.intersects(&b.kernel))
                    .map(|q| q.id)
                    .collect::<Vec<_>>()
            })
            .collect();
        let mut v: Vec<PatchId> = set.into_iter().collect();
        v.sort_unstable();
        v
    }

    /// Adds a survey's patches (Algorithm 2 for all of them at once). Adding a survey that is
    /// already present changes nothing.
    pub fn insert_survey(&mut self, survey: SurveyId, boxes: Vec<PatchBox>) -> ChangeStats {
        if self.surveys.contains_key(&survey) {
            return ChangeStats::default();
        }
        let boxes: Vec<Arc<PatchBox>> = boxes
            .into_iter()
            .filter(|b| !self.slots.contains_key(&b.id))
            .map(Arc::new)
            .collect();
        let ids: Vec<PatchId> = boxes.iter().map(|b| b.id).collect();
        for b in &boxes {
            // Provisionally empty; the recomputation below gives the real top.
            let slot = Slot {
                bx: b.clone(),
                max_z: f64::NEG_INFINITY,
            };
            self.tree.insert(Self::entry(&slot));
            self.slots.insert(b.id, slot);
        }
        let floor = boxes.iter().map(|b| b.min_z).fold(f64::INFINITY, f64::min);
        let Some(bounds) = boxes.iter().map(|b| b.aabb).reduce(|a, b| a.union(&b)) else {
            return ChangeStats::default();
        };
        self.surveys.insert(
            survey,
            SurveyEntry {
                patches: ids.clone(),
                floor,
                bounds,
            },
        );
        let mut todo = self.touched_by(&boxes);
        todo.extend(ids.iter().copied());
        todo.sort_unstable();
        todo.dedup();
        let (recomputed, moved) = self.recompute(todo);
        ChangeStats {
            patches: ids.len(),
            recomputed,
            moved,
        }
    }

    /// Removes a survey's patches and restores every box they had cut. Returns None when the
    /// survey is not present.
    pub fn retire_survey(&mut self, survey: SurveyId) -> Option<ChangeStats> {
        let ids = self.surveys.remove(&survey)?.patches;
        let mut gone = Vec::with_capacity(ids.len());
        for id in &ids {
            if let Some(slot) = self.slots.remove(id) {
                self.tree.remove(*id, &slot.bx.aabb);
                gone.push(slot.bx);
            }
        }
        let todo = self.touched_by(&gone);
        let (recomputed, moved) = self.recompute(todo);
        Some(ChangeStats {
            patches: ids.len(),
            recomputed,
            moved,
        })
    }

    /// Rebuilds an index from boxes whose tops were computed before (by a store), without
    /// running the cutter. `check` tells whether the tops are still right.
    pub fn restore(
        cfg: IndexConfig,
        surveys: impl IntoIterator<Item = (SurveyId, Vec<(PatchBox, f64)>)>,
    ) -> Self {
        let mut ix = LodIndex::new(cfg);
        for (survey, boxes) in surveys {
            let Some(bounds) = boxes.iter().map(|(b, _)| b.aabb).reduce(|a, b| a.union(&b)) else {
                continue;
            };
            let floor = boxes
                .iter()
                .map(|(b, _)| b.min_z)
                .fold(f64::INFINITY, f64::min);
            let mut ids = Vec::with_capacity(boxes.len());
            for (b, max_z) in boxes {
                let slot = Slot {
                    bx: Arc::new(b),
                    max_z,
                };
                ix.tree.insert(Self::entry(&slot));
                ids.push(slot.bx.id);
                ix.slots.insert(slot.bx.id, slot);
            }
            ix.surveys.insert(
                survey,
                SurveyEntry {
                    patches: ids,
                    floor,
                    bounds,
                },
            );
        }
        ix
    }

    /// Re-derives every top from scratch and checks the tree: what `verify` runs.
    pub fn check(&self) -> Result<(), String> {
        self.tree.check()?;
        let bad: Vec<String> = self
            .slots
            .par_iter()
            .filter_map(|(id, s)| {
                let top = self.ceiling_of(&s.bx);
                (top.total_cmp(&s.max_z) != Ordering::Equal)
                    .then(|| format!("patch {id}: top {} should be {top}", s.max_z))
            })
            .collect();
        if let Some(first) = bad.first() {
            return Err(format!(
                "{} boxes have a wrong top; first: {first}",
                bad.len()
            ));
        }
        let mut seen = HashSet::new();
        self.tree.for_each_in(
            &self.tree.bounds().unwrap_or(Aabb::new(0.0, 0.0, 0.0, 0.0)),
            |e| {
                seen.insert(e.id);
            },
        );
        if seen.len() != self.slots.len() {
            return Err(format!(
                "the quadtree holds {} boxes, the index {}",
                seen.len(),
                self.slots.len()
            ));
        }
        Ok(())
    }
}
