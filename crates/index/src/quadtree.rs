//! The multiple-storage quadtree of §4.2.
//!
//! Every node keeps at most `capacity` entries, sorted by z-ceiling (highest first), and every
//! entry stored below a node has a ceiling no higher than any entry stored at it. That is what
//! lets a cut at z stop descending as soon as it meets a ceiling ≤ z. An entry may be stored in
//! several nodes (one per branch it overlaps), never in a node and one of its descendants.
//!
//! Ties in ceiling are broken by where the box is in its index ([`At`]), so the content of
//! every node is a function of the set of entries alone, whatever the order of insertions and
//! removals. (The numbers an index gives its units depend on the order they came in, so two
//! indexes over the same surveys may store their trees differently; their cuts are the same.)

use patchwork_geom::Aabb;
use std::cmp::Ordering;
use std::sync::Arc;

/// Below this depth nodes stop splitting and simply grow; it only matters when more than
/// `capacity` boxes pile up on one spot.
const MAX_DEPTH: u32 = 40;

/// Where a box is in its index: its unit's number and its place in the unit's list. What an
/// entry names its box by, in two 32-bit numbers, so that the index keeps no map from patch ids
/// to boxes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct At {
    /// The number the index gave the box's unit.
    pub unit: u32,
    /// The box's place in its unit's list.
    pub position: u32,
}

/// The bit of [`Entry`]'s floor that says the box is exposed: its sign bit.
const EXPOSED: u32 = 1 << 31;

/// A box as the quadtree stores it: its z-span, whether it is exposed, and its window's bounds.
///
/// The span and the bounds are kept in f32, rounded outwards (the ceiling up, the floor down,
/// the bounds grown), so that what the tree answers is a superset of what the exact values
/// would give, which callers refine on the boxes themselves; 32 bytes an entry where f64 took
/// 64, and an entry is stored 1.6 times a box. Rounding is monotone, so the tree's ordering
/// invariant over the rounded ceilings keeps every cut's early stop conservative.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Entry {
    at: At,
    ceiling: f32,
    /// The floor's bits, never negative, with [`EXPOSED`] in the sign bit: the flag alone
    /// would round the entry up from 32 bytes to 36.
    floor: u32,
    bounds: [f32; 4],
}

/// The greatest f32 no greater than `x`.
fn down(x: f64) -> f32 {
    let f = x as f32;
    if f as f64 > x {
        f.next_down()
    } else {
        f
    }
}

/// The least f32 no less than `x`.
fn up(x: f64) -> f32 {
    let f = x as f32;
    if (f as f64) < x {
        f.next_up()
    } else {
        f
    }
}

/// Bounds as the tree keeps them: grown to f32.
fn stored_bounds(b: &Aabb) -> [f32; 4] {
    [down(b.min[0]), down(b.min[1]), up(b.max[0]), up(b.max[1])]
}

impl Entry {
    /// The entry of a box whose z-span is `[floor, ceiling)` and whose window's bounds are
    /// `aabb`.
    ///
    /// A box's floor is its patch's error, never negative; were one negative (or not a
    /// number), the entry would keep 0, which only makes the tree answer more.
    pub fn new(at: At, ceiling: f64, floor: f64, exposed: bool, aabb: &Aabb) -> Self {
        Entry {
            at,
            ceiling: up(ceiling),
            // Never below +0.0 (`max` takes it over a NaN too), so that the sign bit is free.
            floor: down(floor).max(0.0).to_bits() | if exposed { EXPOSED } else { 0 },
            bounds: stored_bounds(aabb),
        }
    }

    /// The box the entry stands for.
    #[inline]
    pub fn at(&self) -> At {
        self.at
    }

    /// Whether the box is the most accurate data somewhere (see `lod`).
    #[inline]
    pub fn exposed(&self) -> bool {
        self.floor & EXPOSED != 0
    }

    /// Top of the box's z-span (exclusive), rounded up.
    pub fn ceiling(&self) -> f64 {
        self.ceiling as f64
    }

    /// Bottom of the box's z-span, rounded down.
    pub fn floor(&self) -> f64 {
        f64::from(f32::from_bits(self.floor & !EXPOSED))
    }

    /// Bounds of the box's window, grown to what f32 holds.
    pub fn aabb(&self) -> Aabb {
        let b = self.bounds.map(f64::from);
        Aabb::new(b[0], b[1], b[2], b[3])
    }

    /// Whether the box's z-span `[floor, ceiling)`, as rounded, is non-empty.
    pub fn is_active(&self) -> bool {
        f64::from(self.ceiling) > self.floor()
    }
}

/// Storage order: higher ceilings first, then lower ids.
#[inline]
fn order(a: &Entry, b: &Entry) -> Ordering {
    b.ceiling.total_cmp(&a.ceiling).then(a.at.cmp(&b.at))
}

/// A node. Its children sit behind an `Arc`, so that a copy of the tree (one a commit makes of
/// the terrain it publishes) shares every subtree until it is written: a write copies only the
/// nodes on its way down (`Arc::make_mut`), and a commit costs what it changes rather than the
/// size of the tree.
#[derive(Clone, Debug)]
struct Node {
    bounds: Aabb,
    entries: Vec<Entry>,
    children: Option<Arc<[Node; 4]>>,
}

impl Node {
    fn new(bounds: Aabb) -> Self {
        Node {
            bounds,
            entries: Vec::new(),
            children: None,
        }
    }

    fn split(&mut self) -> &mut [Node; 4] {
        let b = self.bounds;
        let ch = self.children.get_or_insert_with(|| {
            let mx = (b.min[0] + b.max[0]) / 2.0;
            let my = (b.min[1] + b.max[1]) / 2.0;
            Arc::new([
                Node::new(Aabb::new(b.min[0], b.min[1], mx, my)),
                Node::new(Aabb::new(mx, b.min[1], b.max[0], my)),
                Node::new(Aabb::new(b.min[0], my, mx, b.max[1])),
                Node::new(Aabb::new(mx, my, b.max[0], b.max[1])),
            ])
        });
        Arc::make_mut(ch)
    }

    fn put_sorted(&mut self, e: Entry) {
        let at = self
            .entries
            .binary_search_by(|x| order(x, &e))
            .unwrap_or_else(|i| i);
        self.entries.insert(at, e);
    }

    fn insert(&mut self, e: Entry, cap: usize, depth: u32) {
        if !self.bounds.intersects(&e.aabb()) {
            return;
        }
        // A node that is not full has nothing below it (removal refills), so it takes the entry.
        if self.entries.len() < cap || depth >= MAX_DEPTH {
            self.put_sorted(e);
            return;
        }
        let last = *self.entries.last().expect("node is full");
        let down = if order(&e, &last) == Ordering::Less {
            self.entries.pop();
            self.put_sorted(e);
            last
        } else {
            e
        };
        for c in self.split().iter_mut() {
            c.insert(down, cap, depth + 1);
        }
    }

    fn remove(&mut self, at: At, aabb: &Aabb, cap: usize) -> bool {
        if !self.bounds.intersects(aabb) {
            return false;
        }
        if let Some(pos) = self.entries.iter().position(|x| x.at() == at) {
            self.entries.remove(pos);
            self.refill(cap);
            return true;
        }
        let mut found = false;
        if let Some(ch) = self.children.as_mut() {
            // Only the children the box reaches are copied out of a shared subtree.
            if ch.iter().any(|c| c.bounds.intersects(aabb)) {
                for c in Arc::make_mut(ch).iter_mut() {
                    found |= c.remove(at, aabb, cap);
                }
            }
        }
        found
    }

    /// Pulls the best entries of the children up until the node is full again or its subtree
    /// is empty, so that "not full" keeps meaning "nothing below".
    fn refill(&mut self, cap: usize) {
        while self.entries.len() < cap {
            let Some(ch) = self.children.as_mut() else {
                return;
            };
            let best = ch
                .iter()
                .filter_map(|c| c.entries.first())
                .min_by(|a, b| order(a, b))
                .copied();
            let Some(best) = best else {
                self.children = None;
                return;
            };
            for c in Arc::make_mut(ch).iter_mut() {
                c.remove(best.at(), &best.aabb(), cap);
            }
            self.entries.push(best);
        }
    }

    fn for_each_in<'a>(&'a self, area: &Aabb, f: &mut impl FnMut(&'a Entry)) {
        if !self.bounds.intersects(area) {
            return;
        }
        for e in &self.entries {
            if e.aabb().intersects(area) {
                f(e);
            }
        }
        if let Some(ch) = &self.children {
            for c in ch.iter() {
                c.for_each_in(area, f);
            }
        }
    }

    fn cut<'a>(
        &'a self,
        area: &Aabb,
        range: &impl Fn(&Aabb) -> (f64, f64),
        f: &mut impl FnMut(&'a Entry),
    ) {
        let Some(part) = self.bounds.intersection(area) else {
            return;
        };
        let (lo, hi) = range(&part);
        for e in &self.entries {
            if e.ceiling() <= lo {
                // Every later entry, and everything below this node, is finer than needed.
                return;
            }
            if (e.floor() <= hi || e.exposed()) && e.aabb().intersects(area) {
                f(e);
            }
        }
        if let Some(ch) = &self.children {
            for c in ch.iter() {
                c.cut(area, range, f);
            }
        }
    }

    fn shrink_to_fit(&mut self) {
        self.entries.shrink_to_fit();
        if let Some(ch) = self.children.as_mut() {
            for c in Arc::make_mut(ch).iter_mut() {
                c.shrink_to_fit();
            }
        }
    }

    fn stats(&self, depth: u32, s: &mut TreeStats) {
        s.nodes += 1;
        s.stored += self.entries.len();
        s.depth = s.depth.max(depth);
        if let Some(ch) = &self.children {
            for c in ch.iter() {
                c.stats(depth + 1, s);
            }
        }
    }
}

/// The shape of a quadtree, for reports and checks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TreeStats {
    /// Nodes in the tree.
    pub nodes: usize,
    /// Stored entries, counting an entry once per node that holds it.
    pub stored: usize,
    /// Depth of the deepest node; the root's is 0.
    pub depth: u32,
}

/// The multiple-storage quadtree over entries' bounds: no entry below a node has a higher
/// ceiling than one at it, so that a cut stops descending at the first ceiling below it.
#[derive(Clone, Debug)]
pub struct MsQuadtree {
    root: Option<Node>,
    capacity: usize,
}

impl MsQuadtree {
    /// An empty tree whose nodes keep at most `capacity` entries (at least 1) before they split.
    pub fn new(capacity: usize) -> Self {
        MsQuadtree {
            root: None,
            capacity: capacity.max(1),
        }
    }

    /// The root's square, which holds every entry inserted so far; None before the first. It only
    /// ever grows.
    pub fn bounds(&self) -> Option<Aabb> {
        self.root.as_ref().map(|r| r.bounds)
    }

    /// Grows the root by doubling it towards `b` until it holds `b`. The root's place (and so
    /// the tree's shape) may depend on which data came first; what it stores never does.
    fn ensure_root(&mut self, b: &Aabb) {
        let root = self.root.get_or_insert_with(|| {
            let side = b.width().max(b.height()).max(1e-9);
            let side = 2f64.powi(side.log2().ceil() as i32);
            Node::new(Aabb::new(
                b.min[0],
                b.min[1],
                b.min[0] + side,
                b.min[1] + side,
            ))
        });
        while !root.bounds.contains(b) {
            let old_bounds = root.bounds;
            let old = std::mem::replace(root, Node::new(old_bounds));
            let side = old_bounds.width();
            let x = if b.min[0] < old_bounds.min[0] {
                old_bounds.min[0] - side
            } else {
                old_bounds.min[0]
            };
            let y = if b.min[1] < old_bounds.min[1] {
                old_bounds.min[1] - side
            } else {
                old_bounds.min[1]
            };
            *root = Node::new(Aabb::new(x, y, x + 2.0 * side, y + 2.0 * side));
            let cap = self.capacity;
            let ch = root.split();
            // The old root keeps its exact bounds: recomputed midpoints may differ in the last bit.
            let k = usize::from(old_bounds.min[0] > x) + 2 * usize::from(old_bounds.min[1] > y);
            ch[k] = old;
            root.refill(cap);
        }
    }

    /// Stores an entry, first growing the root until it holds the entry's bounds.
    pub fn insert(&mut self, e: Entry) {
        self.ensure_root(&e.aabb());
        let cap = self.capacity;
        if let Some(r) = self.root.as_mut() {
            r.insert(e, cap, 0);
        }
    }

    /// Removes the entry of the box `at`; `aabb` must be the bounds it was stored with (exact,
    /// or as the entry rounded them). False when no such entry is stored.
    pub fn remove(&mut self, at: At, aabb: &Aabb) -> bool {
        let cap = self.capacity;
        let b = stored_bounds(aabb).map(f64::from);
        let aabb = Aabb::new(b[0], b[1], b[2], b[3]);
        self.root.as_mut().is_some_and(|r| r.remove(at, &aabb, cap))
    }

    /// Every stored entry whose bounds meet `area`, possibly more than once.
    pub fn for_each_in<'a>(&'a self, area: &Aabb, mut f: impl FnMut(&'a Entry)) {
        if let Some(r) = &self.root {
            r.for_each_in(area, &mut f);
        }
    }

    /// Entries over `area` whose z-span meets the query surface, where `range` bounds the
    /// surface's z over a region, and exposed entries above it (a query's fallback below the
    /// data's accuracy). Possibly more than once; callers refine and deduplicate.
    pub fn cut<'a>(
        &'a self,
        area: &Aabb,
        range: impl Fn(&Aabb) -> (f64, f64),
        mut f: impl FnMut(&'a Entry),
    ) {
        if let Some(r) = &self.root {
            r.cut(area, &range, &mut f);
        }
    }

    /// Gives back what the nodes' lists hold beyond their entries. The lists grow by doubling,
    /// so a tree built by insertions holds room for about a third more entries than it has
    /// in its leaves. Meant for a tree just built: a subtree shared with a copy is copied.
    pub fn shrink_to_fit(&mut self) {
        if let Some(r) = self.root.as_mut() {
            r.shrink_to_fit();
        }
    }

    /// Counts the nodes, the stored entries and the depth.
    pub fn stats(&self) -> TreeStats {
        let mut s = TreeStats::default();
        if let Some(r) = &self.root {
            r.stats(0, &mut s);
        }
        s
    }

    /// Checks the storage invariant everywhere; used by verification and tests.
    pub fn check(&self) -> Result<(), String> {
        fn walk(n: &Node, cap: usize, above: Option<&Entry>, depth: u32) -> Result<(), String> {
            if n.entries
                .windows(2)
                .any(|w| order(&w[0], &w[1]) != Ordering::Less)
            {
                return Err(format!("node {:?} is not sorted", n.bounds));
            }
            if depth < MAX_DEPTH && n.entries.len() > cap {
                return Err(format!(
                    "node {:?} holds {} > {cap}",
                    n.bounds,
                    n.entries.len()
                ));
            }
            if let (Some(a), Some(first)) = (above, n.entries.first()) {
                if order(first, a) == Ordering::Less {
                    return Err(format!(
                        "node {:?} holds {:?} above its parent's last",
                        n.bounds,
                        first.at()
                    ));
                }
            }
            if let Some(e) = n.entries.iter().find(|e| !n.bounds.intersects(&e.aabb())) {
                return Err(format!("node {:?} holds {:?} outside it", n.bounds, e.at()));
            }
            if let Some(ch) = &n.children {
                if n.entries.len() < cap && ch.iter().any(|c| !c.entries.is_empty()) {
                    return Err(format!(
                        "node {:?} is not full but has entries below",
                        n.bounds
                    ));
                }
                let last = n.entries.last().or(above);
                for c in ch.iter() {
                    walk(c, cap, last, depth + 1)?;
                }
            }
            Ok(())
        }
        match &self.root {
            Some(r) => walk(r, self.capacity, None, 0),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An entry whose values f32 holds exactly, so that the tree's answers are exact too.
    fn entry(id: u32, x: f64, y: f64, s: f64, ceiling: f64) -> Entry {
        let (x, y, s) = (x as f32 as f64, y as f32 as f64, s as f32 as f64);
        Entry::new(
            At {
                unit: id,
                position: 0,
            },
            ceiling,
            0.0,
            false,
            &Aabb::new(x, y, x + s, y + s),
        )
    }

    #[test]
    fn rounding_keeps_every_value_inside_what_is_stored() {
        for x in [
            0.1,
            -0.1,
            1e-30,
            -118.999_999_9,
            4_123_456.789,
            1e300,
            f64::NEG_INFINITY,
        ] {
            assert!(f64::from(down(x)) <= x && x <= f64::from(up(x)), "{x}");
        }
        let b = Aabb::new(-118.3, 34.1, -118.2, 34.2);
        let e = Entry::new(At::default(), 5.3, 2.1, false, &b);
        assert!(e.aabb().contains(&b));
        assert!(e.ceiling() >= 5.3 && e.floor() <= 2.1);
    }

    #[test]
    fn invariant_holds_through_inserts_removals_and_growth() {
        let mut t = MsQuadtree::new(4);
        let mut all = Vec::new();
        let mut seed = 7u64;
        let mut rnd = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        for i in 0..400 {
            let e = entry(
                i,
                rnd() * 100.0 - 20.0,
                rnd() * 100.0,
                0.5 + rnd() * 10.0,
                (rnd() * 8.0).floor(),
            );
            t.insert(e);
            all.push(e);
            t.check().unwrap();
        }
        for e in all.iter().step_by(3) {
            assert!(t.remove(e.at(), &e.aabb()));
            t.check().unwrap();
        }
        let kept: Vec<_> = all
            .iter()
            .enumerate()
            .filter(|(i, _)| i % 3 != 0)
            .map(|(_, e)| *e)
            .collect();
        for z in [0.5, 2.5, 7.5] {
            let area = Aabb::new(10.0, 10.0, 40.0, 60.0);
            let mut got: Vec<u32> = Vec::new();
            t.cut(&area, |_| (z, z), |e| got.push(e.at().unit));
            got.sort();
            got.dedup();
            let mut want: Vec<u32> = kept
                .iter()
                .filter(|e| e.ceiling() > z && e.floor() <= z && e.aabb().intersects(&area))
                .map(|e| e.at().unit)
                .collect();
            want.sort();
            assert_eq!(got, want, "z = {z}");
        }
    }
}
