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
//!
//! Beside its top, each box carries whether it is *exposed*: whether some of its valid kernel
//! is covered by no more accurate patch. Where a query asks for more accuracy than any survey
//! has, it falls back to the most accurate data at each point, and the exposed boxes are
//! exactly the patches that are that somewhere. Exposure is a pure function of the set of
//! patches too, recomputed for the same neighbourhood of a change as the tops.

use super::cover::covered_all;
use super::quadtree::{At, Entry, MsQuadtree, TreeStats};
use patchwork_geom::{Aabb, Affine, ORect};
use patchwork_model::edge::EdgePatch;
use patchwork_model::grid::Georef;
use patchwork_model::ids::{PatchId, SurveyId};
use patchwork_model::patch::CellRect;
use patchwork_model::place::{Frame, PlaneId, STORE_PLANE};
use patchwork_model::survey::SurveyMeta;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::cmp::Ordering;
use std::collections::{BTreeMap, HashSet};
use std::sync::Arc;

/// The settings of LOD space and of its quadtree.
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
            // Measured on the Copernicus + NASADEM pair (docs/SCALE.md): at 64 boxes a node a
            // box is stored 1.63 times, at 256 1.26 times (12 bytes a patch less), and a cut
            // takes as long; at 512, 1.16 times, and cuts take 15% longer.
            node_capacity: 256,
        }
    }
}

/// A patch as LOD space sees it: its kernel, its valid part, and its error.
///
/// Its shapes are in its own plane: the store's, or the CRS of a survey in another (see
/// [`patchwork_model::place`]). Coverage between patches of one plane is decided there, exactly
/// as ever; between planes, through the store's plane, on each patch's frame, with the shapes
/// grown or shrunk by the frames' bounds so that the answer stays conservative.
///
/// A box keeps its shapes as cells of its level's grid, which every box of the level shares,
/// and makes the world's rectangles from them when asked, with the grid's own arithmetic, so
/// that they are the rectangles the grid would give to the bit; 64-byte rectangles and their
/// bounds kept ready made a box of about 300 bytes. The cells of a survey's patch are read from
/// the patch, in its survey's list, which the box shares. The index keeps no box of a survey
/// in the store's plane: it makes one from the patch when asked ([`UnitBoxes`]).
#[derive(Clone, Debug, PartialEq)]
pub struct PatchBox {
    /// The patch the box stands for.
    pub id: PatchId,
    /// The unit the patch is inserted and retired with: its survey, or its edge patch's owner.
    pub survey: SurveyId,
    /// The patch's mipmap level; 0 for an edge patch.
    pub level: u8,
    /// Where the patch is in its survey's list of patches (0 for an edge patch): what finds
    /// the patch from its box. It fits in the box's padding.
    pub position: u32,
    /// Nominal kernel area in the store's plane, the first key of the global order.
    pub area: f64,
    /// Bottom of the box: the patch's error ε + δ.
    pub min_z: f64,
    /// The grid the cells are of.
    lattice: Arc<Lattice>,
    /// The kernel's cells, the window's, and the kernel's valid parts.
    cells: Cells,
    /// For a patch of another plane, where it lies in the store's.
    pub placed: Option<Box<Placed>>,
}

/// Where a box's cells are.
#[derive(Clone)]
enum Cells {
    /// A survey's patch: the one at the box's `position` in the survey's list. The survey's
    /// metadata rather than the list, whose pointer is twice as wide.
    Survey(Arc<SurveyMeta>),
    /// An edge patch's.
    Edge(Box<EdgeCells>),
}

/// The cells of an edge patch's box.
#[derive(Clone, Debug, PartialEq)]
struct EdgeCells {
    /// The kernel's cells.
    kernel: CellRect,
    /// The window's cells: where the patch can contribute to a blend.
    window: CellRect,
    /// The kernel's valid parts, as disjoint rectangles of grid coordinates (first column,
    /// first row, end column, end row), on whole or half cells: what greater patches must
    /// cover to cut the box. None where the valid part is the whole kernel.
    valid: Option<Box<[[f64; 4]]>>,
}

impl PartialEq for Cells {
    fn eq(&self, o: &Cells) -> bool {
        match (self, o) {
            (Cells::Survey(a), Cells::Survey(b)) => Arc::ptr_eq(a, b) || a.patches == b.patches,
            (Cells::Edge(a), Cells::Edge(b)) => a == b,
            _ => false,
        }
    }
}

impl std::fmt::Debug for Cells {
    // A survey's whole list would be printed for each of its boxes.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Cells::Survey(s) => write!(f, "Survey({}, {} patches)", s.id, s.patches.len()),
            Cells::Edge(e) => e.fmt(f),
        }
    }
}

/// A grid as boxes use it: its georeference with its axes worked out once for all the boxes
/// on it (each rectangle would otherwise take a sine and a cosine).
#[derive(Clone, Debug, PartialEq)]
pub struct Lattice {
    georef: Georef,
    axes: [[f64; 2]; 2],
}

impl Lattice {
    /// The lattice of a grid.
    pub fn of(g: &Georef) -> Arc<Lattice> {
        Arc::new(Lattice {
            georef: *g,
            axes: g.axes(),
        })
    }

    /// The world parallelogram spanned by grid coordinates (c0, r0, c1, r1).
    fn rect(&self, r: [f64; 4]) -> ORect {
        self.georef.grid_rect_on(self.axes, r)
    }

    /// The rectangle of a range of cells: [`Georef::cells_rect`]'s, to the bit, as the
    /// coordinates and their differences are integers f64 holds exactly.
    fn cells(&self, c: &CellRect) -> ORect {
        self.rect(grid_coords(c))
    }
}

/// A range of cells as grid coordinates: exact, as every u32 is an f64.
fn grid_coords(c: &CellRect) -> [f64; 4] {
    [c.c0 as f64, c.r0 as f64, c.c1 as f64, c.r1 as f64]
}

/// A patch of another plane in the store's: its shapes carried through its frame, each
/// within `rho` of the true image of the patch's own.
#[derive(Clone, Debug, PartialEq)]
pub struct Placed {
    /// The plane the patch's kernel, valid parts and window lie in.
    pub plane: PlaneId,
    /// The map from the patch's plane into the store's.
    pub frame: Affine,
    /// The frame's inverse: from the store's plane into the patch's.
    pub inverse: Affine,
    /// How far the frame may be from the true image anywhere in the window, store units.
    pub rho: f64,
    /// The kernel, carried into the store's plane.
    pub kernel: ORect,
    /// The valid parts, carried likewise.
    pub valid: Vec<ORect>,
    /// The window, carried likewise.
    pub window: ORect,
}

impl PatchBox {
    /// The box of the patch `position` in the list of the survey `s`, at the error the survey
    /// gives it (its own, or what raised claims made it), on a level whose lattice is
    /// `lattice` and whose kernels' nominal area is `area`; `framed` places a patch of another
    /// plane in the store's.
    fn of_patch(
        s: &Arc<SurveyMeta>,
        position: u32,
        (lattice, area): &(Arc<Lattice>, f64),
        framed: Option<(PlaneId, &Frame)>,
    ) -> Self {
        let p = &s.patches[position as usize];
        let b = PatchBox {
            id: p.id,
            survey: s.id,
            level: p.level,
            position,
            area: *area,
            min_z: s.error_at(position as usize),
            lattice: lattice.clone(),
            cells: Cells::Survey(s.clone()),
            placed: None,
        };
        match framed {
            Some(f) => Self::placed(b, f),
            None => b,
        }
    }

    /// The box of an edge patch. Its nominal area is a level-0 kernel's, whatever its tile's
    /// size: its samples are level 0's, so it is ordered with level-0 patches.
    fn edge(e: &EdgePatch, framed: Option<(PlaneId, &Frame)>) -> Self {
        let g = &e.georef;
        let whole = e.valid.len() == 1 && e.valid[0] == grid_coords(&e.kernel);
        let b = PatchBox {
            id: e.id,
            survey: e.owner,
            level: 0,
            position: 0,
            area: nominal_area(g, e.kernel_cells as f64),
            min_z: e.error,
            lattice: Lattice::of(g),
            cells: Cells::Edge(Box::new(EdgeCells {
                kernel: e.kernel,
                window: e.window,
                valid: (!whole).then(|| e.valid.clone().into_boxed_slice()),
            })),
            placed: None,
        };
        match framed {
            Some(f) => Self::placed(b, f),
            None => b,
        }
    }

    /// A box carried into the store's plane through the frame of its plane.
    fn placed(b: PatchBox, (plane, f): (PlaneId, &Frame)) -> Self {
        let inverse = f
            .map
            .inverse()
            .expect("a frame maps the plane onto the plane");
        let placed = Placed {
            plane,
            frame: f.map,
            inverse,
            rho: f.rho,
            kernel: b.kernel().mapped(&f.map),
            valid: b.valid().iter().map(|v| v.mapped(&f.map)).collect(),
            window: b.window().mapped(&f.map),
        };
        PatchBox {
            // In the store's units, so that patches of every plane order together.
            area: b.area * f.map.det().abs(),
            placed: Some(Box::new(placed)),
            ..b
        }
    }

    /// The plane the kernel, the valid parts and the window lie in: the store's, or for a
    /// patch of another plane, its own (kept with its placement, which only such a patch has).
    #[inline]
    pub fn plane(&self) -> PlaneId {
        self.placed.as_ref().map_or(STORE_PLANE, |p| p.plane)
    }

    /// The kernel's cells.
    #[inline]
    fn kernel_cells(&self) -> CellRect {
        match &self.cells {
            Cells::Survey(s) => s.kernel(&s.patches[self.position as usize]),
            Cells::Edge(e) => e.kernel,
        }
    }

    /// The kernel, in the patch's plane.
    pub fn kernel(&self) -> ORect {
        self.lattice.cells(&self.kernel_cells())
    }

    /// Where the patch can contribute to a blend, in the patch's plane.
    pub fn window(&self) -> ORect {
        let w = match &self.cells {
            Cells::Survey(s) => s.window(&s.patches[self.position as usize]),
            Cells::Edge(e) => e.window,
        };
        self.lattice.cells(&w)
    }

    /// The kernel's valid parts, as disjoint shapes in the patch's plane: what greater patches
    /// must cover to cut the box.
    pub fn valid(&self) -> Vec<ORect> {
        let mut out = Vec::new();
        self.valid_into(&mut out);
        out
    }

    /// [`PatchBox::valid`], added to `out`.
    pub fn valid_into(&self, out: &mut Vec<ORect>) {
        match &self.cells {
            Cells::Survey(s) => out.extend(
                s.valid(&s.patches[self.position as usize])
                    .iter()
                    .map(|c| self.lattice.cells(c)),
            ),
            Cells::Edge(e) => match &e.valid {
                None => out.push(self.kernel()),
                Some(v) => out.extend(v.iter().map(|r| self.lattice.rect(*r))),
            },
        }
    }

    /// Store-plane bounds of the kernel.
    pub fn aabb(&self) -> Aabb {
        match &self.placed {
            Some(p) => p.kernel.inflated(p.rho).aabb(),
            None => self.kernel().aabb(),
        }
    }

    /// Store-plane bounds of the window.
    pub fn window_aabb(&self) -> Aabb {
        self.reach().aabb()
    }

    /// How far this box's store-plane shapes may be from the truth.
    pub fn rho(&self) -> f64 {
        self.placed.as_ref().map_or(0.0, |p| p.rho)
    }

    /// The kernel in the store's plane (through the frame, for a patch of another plane).
    pub fn store_kernel(&self) -> ORect {
        self.placed
            .as_ref()
            .map_or_else(|| self.kernel(), |p| p.kernel)
    }

    /// Everywhere in the store's plane the patch can contribute to a blend: its window, grown
    /// by the frame's bound for a patch of another plane.
    pub fn reach(&self) -> ORect {
        match &self.placed {
            Some(p) => p.window.inflated(p.rho),
            None => self.window(),
        }
    }

    /// Whether two kernels may meet: exactly within one plane, through the store's plane
    /// (with both frames' bounds) between two.
    fn meets(&self, o: &PatchBox) -> bool {
        if self.plane() == o.plane() {
            return self.kernel().intersects(&o.kernel());
        }
        self.store_kernel()
            .inflated(self.rho() + o.rho())
            .intersects(&o.store_kernel())
    }

    /// This box's valid parts as seen from `t`'s plane, shrunk where they are known only to
    /// within a frame's bound, so that whatever they cover there they truly cover.
    fn seen_from(&self, t: &PatchBox, out: &mut Vec<ORect>) {
        if self.plane() == t.plane() {
            self.valid_into(out);
            return;
        }
        let shrink = self.rho() + t.rho();
        let own;
        let valid = match &self.placed {
            Some(p) => &p.valid,
            None => {
                own = self.valid();
                &own
            }
        };
        for v in valid {
            let Some(v) = v.deflated(shrink) else {
                continue;
            };
            out.push(match &t.placed {
                Some(p) => v.mapped(&p.inverse),
                None => v,
            });
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

    /// Whether this box is more accurate than `o`: a smaller error, or the same error and
    /// greater in the global order. A total order, so that of two equal patches one serves.
    pub fn more_accurate(&self, o: &PatchBox) -> bool {
        match self.min_z.total_cmp(&o.min_z) {
            Ordering::Less => true,
            Ordering::Greater => false,
            Ordering::Equal => self.order(o) == Ordering::Greater,
        }
    }
}

/// The boxes of a unit (a survey, or an edge patch's owner) as the index keeps them. The boxes
/// of a survey in the store's plane are not kept at all: each is made from its patch when it is
/// asked for, in a few multiplications, so that what the index holds for such a patch is its
/// state, its quadtree entries and its place in the map from ids. A box of 72 bytes in an `Arc`
/// of its own, with a map entry of its own, took about 150.
#[derive(Clone, Debug)]
pub struct UnitBoxes(Boxes);

#[derive(Clone)]
enum Boxes {
    /// A survey's patches in the store's plane, with each level's lattice and nominal kernel
    /// area.
    Survey {
        meta: Arc<SurveyMeta>,
        levels: Arc<[(Arc<Lattice>, f64)]>,
    },
    /// Boxes made once and kept: an edge patch's, and those of a survey of another plane,
    /// whose placement in the store's plane is worth working out once.
    Made(Arc<[PatchBox]>),
}

impl std::fmt::Debug for Boxes {
    // A survey's whole list would be printed.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Boxes::Survey { meta, .. } => {
                write!(f, "Survey({}, {} patches)", meta.id, meta.patches.len())
            }
            Boxes::Made(b) => write!(f, "Made({} boxes)", b.len()),
        }
    }
}

impl UnitBoxes {
    /// A survey's patches as LOD-space boxes, placed in the store's plane as the survey is.
    pub fn of_survey(s: &Arc<SurveyMeta>) -> UnitBoxes {
        let levels: Arc<[(Arc<Lattice>, f64)]> = s
            .shapes
            .iter()
            .map(|l| {
                let area = nominal_area(&l.georef, s.layout.kernel as f64);
                (Lattice::of(&l.georef), area)
            })
            .collect();
        let Some(pl) = &s.placement else {
            return UnitBoxes(Boxes::Survey {
                meta: s.clone(),
                levels,
            });
        };
        let boxes = s
            .patches
            .iter()
            .enumerate()
            .map(|(k, p)| {
                let framed = Some((pl.plane.id, &pl.frames[k]));
                PatchBox::of_patch(s, k as u32, &levels[p.level as usize], framed)
            })
            .collect();
        UnitBoxes(Boxes::Made(boxes))
    }

    /// An edge patch's box, in its lattice's plane, carried into the store's through
    /// `framed` for a lattice of another.
    pub fn edge(e: &EdgePatch, framed: Option<(PlaneId, &Frame)>) -> UnitBoxes {
        UnitBoxes(Boxes::Made(Arc::new([PatchBox::edge(e, framed)])))
    }

    /// The unit's boxes.
    pub fn len(&self) -> usize {
        match &self.0 {
            Boxes::Survey { meta, .. } => meta.patches.len(),
            Boxes::Made(b) => b.len(),
        }
    }

    /// Whether the unit has no box.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The id of the box at `k` in the unit's list.
    #[inline]
    pub fn id(&self, k: usize) -> PatchId {
        match &self.0 {
            Boxes::Survey { meta, .. } => meta.patches[k].id,
            Boxes::Made(b) => b[k].id,
        }
    }

    /// The bottom of the box at `k`: its patch's error.
    #[inline]
    pub fn min_z(&self, k: usize) -> f64 {
        match &self.0 {
            Boxes::Survey { meta, .. } => meta.error_at(k),
            Boxes::Made(b) => b[k].min_z,
        }
    }

    /// The box at `k` in the unit's list.
    #[inline]
    pub fn get(&self, k: usize) -> PatchBox {
        match &self.0 {
            Boxes::Survey { meta, levels } => {
                let level = meta.patches[k].level as usize;
                PatchBox::of_patch(meta, k as u32, &levels[level], None)
            }
            Boxes::Made(b) => b[k].clone(),
        }
    }

    /// Every box of the unit, in its list's order.
    pub fn boxes(&self) -> impl Iterator<Item = PatchBox> + '_ {
        (0..self.len()).map(|k| self.get(k))
    }
}

/// The area of a kernel of `side` × `side` cells of a grid: the first key of the global order.
fn nominal_area(g: &Georef, side: f64) -> f64 {
    let skew = if g.is_orthogonal() {
        1.0
    } else {
        let [u, v] = g.axes();
        (u[0] * v[1] - u[1] * v[0]).abs()
    };
    side * g.step[0] * side * g.step[1] * skew
}

/// A box's current z-span `[min_z, max_z)`; empty when the patch is cut to nothing.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Span {
    /// Bottom: the patch's error ε + δ, in metres.
    pub min_z: f64,
    /// Top, exclusive: where greater patches cover the valid kernel, or the top of LOD space.
    pub max_z: f64,
}

impl Span {
    /// Whether the span is non-empty: the patch is not cut to nothing.
    pub fn is_active(&self) -> bool {
        self.max_z > self.min_z
    }
}

/// What the index derives for a box from the set of patches, and what a store keeps of it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BoxState {
    /// The top of the box's z-span.
    pub top: f64,
    /// Whether part of its valid kernel is covered by no more accurate patch: there, it is
    /// the most accurate data there is, which a cut below its error falls back to.
    pub exposed: bool,
}

impl BoxState {
    /// The state of a box the index has not computed yet: empty, and nowhere the best.
    pub const EMPTY: BoxState = BoxState {
        top: f64::NEG_INFINITY,
        exposed: false,
    };

    fn same(&self, o: &BoxState) -> bool {
        self.top.total_cmp(&o.top) == Ordering::Equal && self.exposed == o.exposed
    }
}

/// The states of a unit's boxes, in patch id order.
pub type UnitStates = Vec<(PatchId, BoxState)>;

/// A unit in the index: its id, its boxes, and their states in the same order.
#[derive(Clone, Debug)]
struct Unit {
    id: SurveyId,
    boxes: UnitBoxes,
    states: States,
}

/// The states of a unit's boxes, by place: the tops, and whether each is exposed as a bit, 8
/// bytes a box where a [`BoxState`] takes 16. Both are shared with the snapshots that hold
/// them, and copied only where a box moves.
#[derive(Clone, Debug)]
struct States {
    tops: Arc<[f64]>,
    exposed: Arc<[u64]>,
}

impl States {
    fn new(states: &[BoxState]) -> Self {
        let mut exposed = vec![0u64; states.len().div_ceil(64)];
        for (k, st) in states.iter().enumerate() {
            exposed[k / 64] |= u64::from(st.exposed) << (k % 64);
        }
        States {
            tops: states.iter().map(|st| st.top).collect(),
            exposed: exposed.into(),
        }
    }

    #[inline]
    fn get(&self, k: usize) -> BoxState {
        BoxState {
            top: self.tops[k],
            exposed: self.exposed[k / 64] >> (k % 64) & 1 == 1,
        }
    }

    fn set(&mut self, k: usize, st: BoxState) {
        Arc::make_mut(&mut self.tops)[k] = st.top;
        let word = &mut Arc::make_mut(&mut self.exposed)[k / 64];
        *word = (*word & !(1 << (k % 64))) | u64::from(st.exposed) << (k % 64);
    }
}

/// What an insertion or retirement did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ChangeStats {
    /// Boxes added.
    pub patches: usize,
    /// Boxes whose state was recomputed.
    pub recomputed: usize,
    /// Boxes whose state changed, every added box among them, with their new state: what a
    /// store must write to persist the index.
    pub moved: Vec<(PatchId, BoxState)>,
    /// Boxes removed.
    pub removed: Vec<PatchId>,
    /// Every unit a box of which moved or went, in id order, with the states of all its boxes
    /// after the change (in id order), or None where the unit went: what a store that keeps
    /// states a unit at a time rewrites.
    pub units: Vec<(SurveyId, Option<UnitStates>)>,
}

/// LOD space: every patch's box and its state, by the unit it came with, and the
/// multiple-storage quadtree over their windows that cuts are answered from.
///
/// The index gives each unit a number, and the quadtree names a box by its unit's number and
/// its place in the unit's list ([`At`]): no map from patch ids to boxes is kept, and a cut
/// names each patch it takes by its unit and place too ([`Extracted`]).
///
/// [`Extracted`]: crate::query::Extracted
#[derive(Clone, Debug)]
pub struct LodIndex {
    cfg: IndexConfig,
    // Persistent maps: the copy of the index a commit makes shares every unit it leaves, and
    // a unit's states are copied only where a box of it moved.
    numbers: imbl::OrdMap<SurveyId, u32>,
    units: imbl::OrdMap<u32, Unit>,
    /// The numbers of units that went, given to the next ones, so that the numbers stay below
    /// the most units ever present at once.
    free: Vec<u32>,
    /// Boxes in the index.
    boxes: usize,
    tree: MsQuadtree,
}

impl LodIndex {
    /// An empty index.
    pub fn new(cfg: IndexConfig) -> Self {
        LodIndex {
            cfg,
            numbers: imbl::OrdMap::new(),
            units: imbl::OrdMap::new(),
            free: Vec::new(),
            boxes: 0,
            tree: MsQuadtree::new(cfg.node_capacity),
        }
    }

    /// The settings the index was made with.
    pub fn config(&self) -> &IndexConfig {
        &self.cfg
    }

    /// Boxes in the index, active or not.
    pub fn len(&self) -> usize {
        self.boxes
    }

    /// Whether the index holds no box.
    pub fn is_empty(&self) -> bool {
        self.boxes == 0
    }

    /// Whether the unit `s` (a survey, or an edge patch's owner) is present.
    pub fn contains_survey(&self, s: SurveyId) -> bool {
        self.numbers.contains_key(&s)
    }

    /// The units present, in no particular order.
    pub fn surveys(&self) -> impl Iterator<Item = SurveyId> + '_ {
        self.numbers.keys().copied()
    }

    fn unit(&self, s: SurveyId) -> Option<&Unit> {
        self.units.get(self.numbers.get(&s)?)
    }

    /// How many boxes a unit has; None when it is absent.
    pub fn unit_len(&self, s: SurveyId) -> Option<usize> {
        self.unit(s).map(|u| u.boxes.len())
    }

    fn find(&self, at: At) -> Option<(&Unit, usize)> {
        let u = self.units.get(&at.unit)?;
        let k = at.position as usize;
        (k < u.boxes.len()).then_some((u, k))
    }

    /// A box and its state; None when no such box is present.
    pub(crate) fn lookup(&self, at: At) -> Option<(PatchBox, BoxState)> {
        let (u, k) = self.find(at)?;
        Some((u.boxes.get(k), u.states.get(k)))
    }

    /// The box at `position` in the list of the unit `unit` (a survey's list of patches; 0 for
    /// an edge patch), and its current z-span; None when there is no such box.
    pub fn get(&self, unit: SurveyId, position: u32) -> Option<(PatchBox, Span)> {
        let u = self.unit(unit)?;
        let k = position as usize;
        (k < u.boxes.len()).then(|| {
            let b = u.boxes.get(k);
            let span = Span {
                min_z: b.min_z,
                max_z: u.states.get(k).top,
            };
            (b, span)
        })
    }

    /// The quadtree's shape: nodes, stored entries, depth.
    pub fn tree_stats(&self) -> TreeStats {
        self.tree.stats()
    }

    /// The square of the quadtree's root, which holds every window's bounds; None before the
    /// first box is added.
    pub fn bounds(&self) -> Option<Aabb> {
        self.tree.bounds()
    }

    pub(crate) fn tree(&self) -> &MsQuadtree {
        &self.tree
    }

    /// Every box and its state, in id order: two indexes over the same surveys give equal maps.
    pub fn state(&self) -> BTreeMap<PatchId, (Span, bool)> {
        self.units
            .values()
            .flat_map(|u| {
                (0..u.boxes.len()).map(move |k| {
                    let st = u.states.get(k);
                    let span = Span {
                        min_z: u.boxes.min_z(k),
                        max_z: st.top,
                    };
                    (u.boxes.id(k), (span, st.exposed))
                })
            })
            .collect()
    }

    /// Boxes not cut to nothing: those whose span is non-empty.
    pub fn active_count(&self) -> usize {
        self.units
            .values()
            .map(|u| {
                (0..u.boxes.len())
                    .filter(|&k| u.states.get(k).top > u.boxes.min_z(k))
                    .count()
            })
            .sum()
    }

    fn entry(at: At, b: &PatchBox, state: BoxState) -> Entry {
        Entry::new(at, state.top, b.min_z, state.exposed, &b.window_aabb())
    }

    /// Boxes whose window bounds meet `area`, each once, in id order (not in the order of
    /// their units' numbers, which depends on the order the units came in).
    pub(crate) fn boxes_in(&self, area: &Aabb) -> Vec<(At, PatchBox)> {
        let mut ats = Vec::new();
        self.tree.for_each_in(area, |e| ats.push(e.at()));
        ats.sort_unstable();
        ats.dedup();
        let mut out: Vec<(At, PatchBox)> = ats
            .into_iter()
            .filter_map(|at| self.find(at).map(|(u, k)| (at, u.boxes.get(k))))
            .collect();
        out.sort_unstable_by_key(|(_, b)| b.id);
        out
    }

    /// Boxes other than `p` whose kernels meet `p`'s and that `keep` accepts.
    fn neighbours(&self, p: &PatchBox, keep: impl Fn(&PatchBox) -> bool) -> Vec<(At, PatchBox)> {
        self.boxes_in(&p.aabb())
            .into_iter()
            .filter(|(_, q)| q.id != p.id && q.meets(p) && keep(q))
            .collect()
    }

    /// Algorithm 1, over every greater patch present among `near` (the patches whose kernels
    /// meet `p`'s). Candidates are taken in order of error (ties by id, so the answer never
    /// depends on iteration order); coverage is monotone in the set, so a binary search over
    /// the distinct errors finds the first that covers.
    fn ceiling_of(&self, p: &PatchBox, near: &[(At, PatchBox)]) -> f64 {
        let top = self.cfg.max_error;
        let mut cands: Vec<&PatchBox> = near
            .iter()
            .map(|(_, q)| q)
            .filter(|q| q.order(p) == Ordering::Greater)
            .collect();
        if cands.is_empty() {
            return top;
        }
        cands.sort_by(|a, b| a.min_z.total_cmp(&b.min_z).then(a.id.cmp(&b.id)));
        let valid = p.valid();
        let rects_upto = |n: usize| -> Vec<ORect> {
            let mut out = Vec::new();
            for q in &cands[..n] {
                q.seen_from(p, &mut out);
            }
            out
        };
        if !covered_all(&valid, &rects_upto(cands.len())) {
            return top;
        }
        // Ends of runs of equal error: the prefixes worth testing.
        let ends: Vec<usize> = (1..=cands.len())
            .filter(|&n| n == cands.len() || cands[n].min_z != cands[n - 1].min_z)
            .collect();
        let (mut lo, mut hi) = (0usize, ends.len() - 1);
        while lo < hi {
            let mid = (lo + hi) / 2;
            if covered_all(&valid, &rects_upto(ends[mid])) {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        let z = cands[ends[lo] - 1].min_z;
        // At or below the patch's own error the patch is redundant: its span is empty.
        z.min(top)
    }

    /// Whether some of `p`'s valid kernel is covered by no more accurate patch among `near`.
    /// Like the top, a pure function of the set of patches.
    fn exposed(&self, p: &PatchBox, near: &[(At, PatchBox)]) -> bool {
        let mut better: Vec<ORect> = Vec::new();
        for (_, q) in near.iter().filter(|(_, q)| q.more_accurate(p)) {
            q.seen_from(p, &mut better);
        }
        better.is_empty() || !covered_all(&p.valid(), &better)
    }

    fn derive(&self, p: &PatchBox) -> BoxState {
        let near = self.neighbours(p, |_| true);
        let top = self.ceiling_of(p, &near);
        // A box cut to nothing is covered by greater patches no less accurate than itself,
        // which are more accurate in the total order: it is exposed nowhere.
        let exposed = top > p.min_z && self.exposed(p, &near);
        BoxState { top, exposed }
    }

    /// Recomputes the state of the boxes `todo` against the current set and moves changed
    /// boxes in the tree. `fresh` boxes are reported whether or not their provisional state
    /// changed. Gives the count recomputed, and the boxes moved in id order with their units.
    fn recompute(
        &mut self,
        todo: Vec<At>,
        fresh: &HashSet<At>,
    ) -> (usize, Vec<(PatchId, BoxState, SurveyId)>) {
        let states: Vec<(At, PatchBox, BoxState)> = todo
            .par_iter()
            .filter_map(|&at| {
                let (b, _) = self.lookup(at)?;
                let state = self.derive(&b);
                Some((at, b, state))
            })
            .collect();
        let mut moved = Vec::new();
        for (at, b, state) in &states {
            let unit = self.units.get_mut(&at.unit).expect("present");
            let k = at.position as usize;
            let changed = !unit.states.get(k).same(state);
            if changed {
                // Copies the unit's states only where a snapshot still shares them.
                unit.states.set(k, *state);
                self.tree.remove(*at, &b.window_aabb());
                self.tree.insert(Self::entry(*at, b, *state));
            }
            if changed || fresh.contains(at) {
                moved.push((b.id, *state, unit.id));
            }
        }
        moved.sort_unstable_by_key(|m| m.0);
        (states.len(), moved)
    }

    /// Boxes already present whose state a change to `changed` can move: smaller ones that
    /// meet them (their tops) and less accurate ones that meet them (their exposure).
    fn touched_by(&self, changed: &[PatchBox]) -> Vec<At> {
        let set: HashSet<At> = changed
            .par_iter()
            .flat_map_iter(|b| {
                self.neighbours(b, |q| q.order(b) == Ordering::Less || b.more_accurate(q))
                    .into_iter()
                    .map(|(at, _)| at)
                    .collect::<Vec<_>>()
            })
            .collect();
        set.into_iter().collect()
    }

    /// Gives a unit a number and puts its boxes into the tree with `states`, and the unit into
    /// the index. Returns where its boxes are.
    fn put(&mut self, survey: SurveyId, boxes: UnitBoxes, states: Vec<BoxState>) -> Vec<At> {
        let number = self.free.pop().unwrap_or_else(|| {
            u32::try_from(self.units.len()).expect("fewer than 2³² units in an index")
        });
        let mut ats = Vec::with_capacity(boxes.len());
        for (k, b) in boxes.boxes().enumerate() {
            let at = At {
                unit: number,
                position: u32::try_from(k).expect("fewer than 2³² patches in a survey"),
            };
            self.tree.insert(Self::entry(at, &b, states[k]));
            ats.push(at);
        }
        self.boxes += boxes.len();
        self.numbers.insert(survey, number);
        let unit = Unit {
            id: survey,
            boxes,
            states: States::new(&states),
        };
        self.units.insert(number, unit);
        ats
    }

    /// Takes a unit out of the index and its boxes out of the tree, and frees its number.
    fn take(&mut self, survey: SurveyId) -> Option<Unit> {
        let number = self.numbers.remove(&survey)?;
        let unit = self.units.remove(&number).expect("a numbered unit");
        for (k, b) in unit.boxes.boxes().enumerate() {
            let at = At {
                unit: number,
                position: k as u32,
            };
            self.tree.remove(at, &b.window_aabb());
        }
        self.boxes -= unit.boxes.len();
        self.free.push(number);
        Some(unit)
    }

    /// Removes the patches of the units in `remove`, adds those of `insert`, and recomputes
    /// every box the change can touch, once (Algorithm 2 for all of them at once). Removing an
    /// absent unit or adding a present one changes nothing.
    pub fn apply(
        &mut self,
        remove: &[SurveyId],
        insert: Vec<(SurveyId, UnitBoxes)>,
    ) -> ChangeStats {
        let mut changed: Vec<PatchBox> = Vec::new();
        for s in remove {
            if let Some(unit) = self.take(*s) {
                changed.extend(unit.boxes.boxes());
            }
        }
        let mut removed: Vec<PatchId> = changed.iter().map(|b| b.id).collect();
        // What is new: each unit once, none already present.
        let mut seen = HashSet::new();
        let adding: Vec<(SurveyId, UnitBoxes)> = insert
            .into_iter()
            .filter(|(survey, _)| !self.numbers.contains_key(survey) && seen.insert(*survey))
            .collect();
        // The boxes already present that the new ones can move are found before the new ones
        // go into the tree, so that the search meets only those: the new boxes are all
        // recomputed anyway, and a survey alone in its area (the first of a store, or a tile
        // of a mosaic) had every box search through its own survey's thousands for nothing.
        changed.extend(adding.iter().flat_map(|(_, boxes)| boxes.boxes()));
        let mut todo = self.touched_by(&changed);
        drop(changed);
        let (mut fresh, mut fresh_ids) = (HashSet::new(), HashSet::new());
        for (survey, boxes) in adding {
            fresh_ids.extend((0..boxes.len()).map(|k| boxes.id(k)));
            // Provisionally empty; the recomputation below gives the real state.
            let states = vec![BoxState::EMPTY; boxes.len()];
            fresh.extend(self.put(survey, boxes, states));
        }
        // A box removed and added again in one change (same content) is simply recomputed.
        removed.retain(|id| !fresh_ids.contains(id));
        removed.sort_unstable();
        todo.extend(fresh.iter().copied());
        todo.sort_unstable();
        todo.dedup();
        let (recomputed, moved) = self.recompute(todo, &fresh);
        let mut units: Vec<SurveyId> = remove
            .iter()
            .copied()
            .chain(moved.iter().map(|m| m.2))
            .collect();
        units.sort_unstable();
        units.dedup();
        let units = units
            .into_iter()
            .map(|u| (u, self.unit_states(u)))
            .collect();
        ChangeStats {
            patches: fresh.len(),
            recomputed,
            moved: moved.into_iter().map(|(id, st, _)| (id, st)).collect(),
            removed,
            units,
        }
    }

    /// The states of a present unit's boxes, in id order.
    pub fn unit_states(&self, unit: SurveyId) -> Option<Vec<(PatchId, BoxState)>> {
        let u = self.unit(unit)?;
        let mut v: Vec<(PatchId, BoxState)> = (0..u.boxes.len())
            .map(|k| (u.boxes.id(k), u.states.get(k)))
            .collect();
        v.sort_unstable_by_key(|(id, _)| *id);
        Some(v)
    }

    /// Every unit with the states of its boxes, both in id order: the whole index as a store
    /// keeps it.
    pub fn all_unit_states(&self) -> Vec<(SurveyId, Vec<(PatchId, BoxState)>)> {
        let mut units: Vec<SurveyId> = self.numbers.keys().copied().collect();
        units.sort_unstable();
        units
            .into_iter()
            .filter_map(|u| Some((u, self.unit_states(u)?)))
            .collect()
    }

    /// Adds a survey's patches. Adding a survey that is already present changes nothing.
    pub fn insert_survey(&mut self, survey: SurveyId, boxes: UnitBoxes) -> ChangeStats {
        self.apply(&[], vec![(survey, boxes)])
    }

    /// Removes a survey's patches and restores every box they had cut. Returns None when the
    /// survey is not present.
    pub fn retire_survey(&mut self, survey: SurveyId) -> Option<ChangeStats> {
        self.contains_survey(survey)
            .then(|| self.apply(&[survey], Vec::new()))
    }

    /// Rebuilds an index from units whose boxes' states were computed before (by a store),
    /// each state in the order of its unit's boxes, without running the cutter.
    pub fn restore(
        cfg: IndexConfig,
        units: impl IntoIterator<Item = (SurveyId, UnitBoxes, Vec<BoxState>)>,
    ) -> Self {
        let mut ix = LodIndex::new(cfg);
        for (survey, boxes, states) in units {
            assert_eq!(boxes.len(), states.len(), "a state for every box");
            if !ix.contains_survey(survey) {
                ix.put(survey, boxes, states);
            }
        }
        ix.tree.shrink_to_fit();
        ix
    }

    /// Re-derives every box's state from scratch and checks the tree: what `verify` runs.
    pub fn check(&self) -> Result<(), String> {
        self.tree.check()?;
        let ats: Vec<At> = self
            .units
            .iter()
            .flat_map(|(&unit, u)| {
                (0..u.boxes.len() as u32).map(move |position| At { unit, position })
            })
            .collect();
        let bad: Vec<String> = ats
            .into_par_iter()
            .filter_map(|at| {
                let (b, st) = self.lookup(at)?;
                let want = self.derive(&b);
                (!want.same(&st)).then(|| {
                    format!(
                        "patch {}: top {} exposed {} should be {} {}",
                        b.id, st.top, st.exposed, want.top, want.exposed
                    )
                })
            })
            .collect();
        if let Some(first) = bad.first() {
            return Err(format!(
                "{} boxes have a wrong top or exposure; first: {first}",
                bad.len()
            ));
        }
        let mut seen = HashSet::new();
        self.tree.for_each_in(
            &self.tree.bounds().unwrap_or(Aabb::new(0.0, 0.0, 0.0, 0.0)),
            |e| {
                seen.insert(e.at());
            },
        );
        if seen.len() != self.boxes {
            return Err(format!(
                "the quadtree holds {} boxes, the index {}",
                seen.len(),
                self.boxes
            ));
        }
        Ok(())
    }
}
