//! Plane geometry of LOD-space boxes: axis-aligned bounds and oriented rectangles.

use crate::model::grid::Georef;
use crate::model::patch::CellRect;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    pub min: [f64; 2],
    pub max: [f64; 2],
}

impl Aabb {
    pub fn new(xmin: f64, ymin: f64, xmax: f64, ymax: f64) -> Self {
        Aabb {
            min: [xmin, ymin],
            max: [xmax, ymax],
        }
    }

    pub fn of_points(ps: &[[f64; 2]]) -> Self {
        let mut b = Aabb {
            min: [f64::INFINITY; 2],
            max: [f64::NEG_INFINITY; 2],
        };
        for p in ps {
            b.min = [b.min[0].min(p[0]), b.min[1].min(p[1])];
            b.max = [b.max[0].max(p[0]), b.max[1].max(p[1])];
        }
        b
    }

    /// Closed intersection: touching boxes intersect.
    #[inline]
    pub fn intersects(&self, o: &Aabb) -> bool {
        self.min[0] <= o.max[0]
            && o.min[0] <= self.max[0]
            && self.min[1] <= o.max[1]
            && o.min[1] <= self.max[1]
    }

    #[inline]
    pub fn contains(&self, o: &Aabb) -> bool {
        self.min[0] <= o.min[0]
            && self.min[1] <= o.min[1]
            && o.max[0] <= self.max[0]
            && o.max[1] <= self.max[1]
    }

    #[inline]
    pub fn contains_point(&self, p: [f64; 2]) -> bool {
        p[0] >= self.min[0] && p[0] <= self.max[0] && p[1] >= self.min[1] && p[1] <= self.max[1]
    }

    pub fn union(&self, o: &Aabb) -> Aabb {
        Aabb {
            min: [self.min[0].min(o.min[0]), self.min[1].min(o.min[1])],
            max: [self.max[0].max(o.max[0]), self.max[1].max(o.max[1])],
        }
    }

    pub fn intersection(&self, o: &Aabb) -> Option<Aabb> {
        let b = Aabb {
            min: [self.min[0].max(o.min[0]), self.min[1].max(o.min[1])],
            max: [self.max[0].min(o.max[0]), self.max[1].min(o.max[1])],
        };
        (b.min[0] <= b.max[0] && b.min[1] <= b.max[1]).then_some(b)
    }

    pub fn width(&self) -> f64 {
        self.max[0] - self.min[0]
    }
    pub fn height(&self) -> f64 {
        self.max[1] - self.min[1]
    }
    pub fn corners(&self) -> [[f64; 2]; 4] {
        [
            self.min,
            [self.max[0], self.min[1]],
            self.max,
            [self.min[0], self.max[1]],
        ]
    }
    pub fn is_valid(&self) -> bool {
        self.min
            .iter()
            .chain(self.max.iter())
            .all(|v| v.is_finite())
            && self.min[0] <= self.max[0]
            && self.min[1] <= self.max[1]
    }
}

/// The rectangle `origin + a·u + b·v` for `a ∈ [0, size[0]]`, `b ∈ [0, size[1]]`, with `u` and
/// `v` perpendicular unit vectors: a kernel or window of a possibly rotated grid.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ORect {
    pub origin: [f64; 2],
    pub u: [f64; 2],
    pub v: [f64; 2],
    pub size: [f64; 2],
}

#[inline]
fn dot(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}

impl ORect {
    /// The world rectangle spanned by a range of cells (sample c0 to sample c1).
    pub fn from_cells(g: &Georef, c: &CellRect) -> ORect {
        let [u, v] = g.axes();
        ORect {
            origin: g.to_world(c.c0 as f64, c.r0 as f64),
            u,
            v,
            size: [c.cols() as f64 * g.step[0], c.rows() as f64 * g.step[1]],
        }
    }

    /// The world rectangle spanned by fractional grid coordinates (c0, r0, c1, r1).
    pub fn from_grid(g: &Georef, r: [f64; 4]) -> ORect {
        let [u, v] = g.axes();
        ORect {
            origin: g.to_world(r[0], r[1]),
            u,
            v,
            size: [(r[2] - r[0]) * g.step[0], (r[3] - r[1]) * g.step[1]],
        }
    }

    pub fn from_aabb(b: &Aabb) -> ORect {
        ORect {
            origin: b.min,
            u: [1.0, 0.0],
            v: [0.0, 1.0],
            size: [b.width(), b.height()],
        }
    }

    #[inline]
    pub fn at(&self, a: f64, b: f64) -> [f64; 2] {
        [
            self.origin[0] + a * self.u[0] + b * self.v[0],
            self.origin[1] + a * self.u[1] + b * self.v[1],
        ]
    }

    /// Coordinates of a world point in this rectangle's frame.
    #[inline]
    pub fn local(&self, p: [f64; 2]) -> [f64; 2] {
        let d = [p[0] - self.origin[0], p[1] - self.origin[1]];
        [dot(d, self.u), dot(d, self.v)]
    }

    pub fn corners(&self) -> [[f64; 2]; 4] {
        [
            self.at(0.0, 0.0),
            self.at(self.size[0], 0.0),
            self.at(self.size[0], self.size[1]),
            self.at(0.0, self.size[1]),
        ]
    }

    pub fn aabb(&self) -> Aabb {
        Aabb::of_points(&self.corners())
    }

    pub fn area(&self) -> f64 {
        self.size[0] * self.size[1]
    }

    pub fn centre(&self) -> [f64; 2] {
        self.at(self.size[0] / 2.0, self.size[1] / 2.0)
    }

    #[inline]
    pub fn contains_point(&self, p: [f64; 2]) -> bool {
        let l = self.local(p);
        l[0] >= 0.0 && l[1] >= 0.0 && l[0] <= self.size[0] && l[1] <= self.size[1]
    }

    /// Projection of this rectangle on a unit axis, as an interval.
    fn project(&self, axis: [f64; 2]) -> (f64, f64) {
        let o = dot(self.origin, axis);
        let a = self.size[0] * dot(self.u, axis);
        let b = self.size[1] * dot(self.v, axis);
        (o + a.min(0.0) + b.min(0.0), o + a.max(0.0) + b.max(0.0))
    }

    /// Separating-axis test; closed, so rectangles that only touch intersect.
    pub fn intersects(&self, o: &ORect) -> bool {
        for axis in [self.u, self.v, o.u, o.v] {
            let (a0, a1) = self.project(axis);
            let (b0, b1) = o.project(axis);
            if a1 < b0 || b1 < a0 {
                return false;
            }
        }
        true
    }

    pub fn intersects_aabb(&self, b: &Aabb) -> bool {
        self.intersects(&ORect::from_aabb(b))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotated_rectangles_separate_along_their_own_axes() {
        let (s, c) = (0.6f64, 0.8f64);
        let a = ORect {
            origin: [0.0, 0.0],
            u: [c, s],
            v: [-s, c],
            size: [1.0, 1.0],
        };
        // Inside a's axis-aligned bounds, but off its diagonal edge.
        let b = ORect::from_aabb(&Aabb::new(0.75, 0.0, 1.0, 0.1));
        assert!(a.aabb().intersects(&b.aabb()));
        assert!(!a.intersects(&b));
        let touching = ORect::from_aabb(&Aabb::new(0.8, 0.6, 2.0, 2.0));
        assert!(a.intersects(&touching));
    }
}
