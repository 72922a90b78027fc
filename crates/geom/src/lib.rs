//! Plane geometry at the bottom of the layers: axis-aligned bounds, oriented rectangles
//! (the parallelograms of rotated, skewed and mirrored grids), affine maps, the one rule by
//! which a coordinate counts as on a grid line, and the reproducible random numbers the tests
//! and the bench spread points with. Pure computation, no I/O, and no other crate of the
//! workspace below it.

use serde::{Deserialize, Serialize};

pub mod rng;
mod snap;
pub mod tiles;

pub use snap::{on_line, snap, SNAP};

/// An axis-aligned bounding box, closed: `min` and `max` are its corners of least and greatest
/// coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    /// The corner of least x and least y.
    pub min: [f64; 2],
    /// The corner of greatest x and greatest y.
    pub max: [f64; 2],
}

impl Aabb {
    /// The box from `(xmin, ymin)` to `(xmax, ymax)`, taken as given: see [`Aabb::is_valid`].
    pub fn new(xmin: f64, ymin: f64, xmax: f64, ymax: f64) -> Self {
        Aabb {
            min: [xmin, ymin],
            max: [xmax, ymax],
        }
    }

    /// The least box holding every point. For no points it is empty, with infinite corners that
    /// [`Aabb::is_valid`] rejects and that [`Aabb::union`] leaves out.
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

    /// Whether `o` lies wholly in this box; closed, so a shared side still counts.
    #[inline]
    pub fn contains(&self, o: &Aabb) -> bool {
        self.min[0] <= o.min[0]
            && self.min[1] <= o.min[1]
            && o.max[0] <= self.max[0]
            && o.max[1] <= self.max[1]
    }

    /// Whether the point lies in the box, boundary included.
    #[inline]
    pub fn contains_point(&self, p: [f64; 2]) -> bool {
        p[0] >= self.min[0] && p[0] <= self.max[0] && p[1] >= self.min[1] && p[1] <= self.max[1]
    }

    /// The box grown by `d` on every side.
    pub fn grown(&self, d: f64) -> Aabb {
        Aabb::new(
            self.min[0] - d,
            self.min[1] - d,
            self.max[0] + d,
            self.max[1] + d,
        )
    }

    /// The least box holding both.
    pub fn union(&self, o: &Aabb) -> Aabb {
        Aabb {
            min: [self.min[0].min(o.min[0]), self.min[1].min(o.min[1])],
            max: [self.max[0].max(o.max[0]), self.max[1].max(o.max[1])],
        }
    }

    /// The part the two boxes share; None when they are apart. Closed, like
    /// [`Aabb::intersects`]: boxes that only touch share a box of zero width or height.
    pub fn intersection(&self, o: &Aabb) -> Option<Aabb> {
        let b = Aabb {
            min: [self.min[0].max(o.min[0]), self.min[1].max(o.min[1])],
            max: [self.max[0].min(o.max[0]), self.max[1].min(o.max[1])],
        };
        (b.min[0] <= b.max[0] && b.min[1] <= b.max[1]).then_some(b)
    }

    /// Extent along x.
    pub fn width(&self) -> f64 {
        self.max[0] - self.min[0]
    }
    /// Extent along y.
    pub fn height(&self) -> f64 {
        self.max[1] - self.min[1]
    }
    /// The four corners in turn round the box: `min` first, then along x.
    pub fn corners(&self) -> [[f64; 2]; 4] {
        [
            self.min,
            [self.max[0], self.min[1]],
            self.max,
            [self.min[0], self.max[1]],
        ]
    }
    /// Whether both corners are finite and `min` lies nowhere beyond `max`. A box of zero width or
    /// height is valid.
    pub fn is_valid(&self) -> bool {
        self.min
            .iter()
            .chain(self.max.iter())
            .all(|v| v.is_finite())
            && self.min[0] <= self.max[0]
            && self.min[1] <= self.max[1]
    }
}

/// The parallelogram `origin + a·u + b·v` for `a ∈ [0, size[0]]`, `b ∈ [0, size[1]]`: a kernel
/// or window of a grid, rotated, skewed or mirrored, or such a shape carried into another
/// plane. `u` and `v` are independent unit vectors; for every grid that is not skewed they
/// are perpendicular, and the shape is a rectangle.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ORect {
    /// The corner at `a = b = 0`.
    pub origin: [f64; 2],
    /// Unit vector along the first side, the `a` axis.
    pub u: [f64; 2],
    /// Unit vector along the second side, the `b` axis.
    pub v: [f64; 2],
    /// Lengths of the sides along `u` and `v`, in the plane's units.
    pub size: [f64; 2],
}

#[inline]
fn dot(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}

#[inline]
fn cross(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[1] - a[1] * b[0]
}

/// Whether a vector is a unit vector to rounding.
#[inline]
fn unit(a: [f64; 2]) -> bool {
    (dot(a, a) - 1.0).abs() < 1e-12
}

/// An affine map of the plane: `p ↦ origin + p[0]·m[0] + p[1]·m[1]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Affine {
    /// The image of the point (0, 0).
    pub origin: [f64; 2],
    /// The images of the unit vectors along x and along y.
    pub m: [[f64; 2]; 2],
}

impl Affine {
    /// The image of a point.
    #[inline]
    pub fn apply(&self, p: [f64; 2]) -> [f64; 2] {
        [
            self.origin[0] + p[0] * self.m[0][0] + p[1] * self.m[1][0],
            self.origin[1] + p[0] * self.m[0][1] + p[1] * self.m[1][1],
        ]
    }

    /// The image of a vector: the linear part alone.
    #[inline]
    pub fn apply_vec(&self, w: [f64; 2]) -> [f64; 2] {
        [
            w[0] * self.m[0][0] + w[1] * self.m[1][0],
            w[0] * self.m[0][1] + w[1] * self.m[1][1],
        ]
    }

    /// Determinant of the linear part: the factor by which the map scales areas, negative where it
    /// mirrors and zero where it flattens the plane.
    pub fn det(&self) -> f64 {
        cross(self.m[0], self.m[1])
    }

    /// The inverse map; None for a map that flattens the plane.
    pub fn inverse(&self) -> Option<Affine> {
        let det = self.det();
        if !(det.is_finite() && det != 0.0) {
            return None;
        }
        let [a, b] = self.m;
        let m = [[b[1] / det, -a[1] / det], [-b[0] / det, a[0] / det]];
        let inv = Affine {
            origin: [0.0; 2],
            m,
        };
        let o = inv.apply_vec(self.origin);
        Some(Affine {
            origin: [-o[0], -o[1]],
            m,
        })
    }

    /// The largest factor by which the map stretches a length: its spectral norm.
    pub fn stretch(&self) -> f64 {
        let [a, b] = self.m;
        let (p, q, r) = (dot(a, a), dot(a, b), dot(b, b));
        (0.5 * (p + r + ((p - r) * (p - r) + 4.0 * q * q).sqrt())).sqrt()
    }
}

impl ORect {
    /// The box as a shape: axes along x and y, origin at `min`.
    pub fn from_aabb(b: &Aabb) -> ORect {
        ORect {
            origin: b.min,
            u: [1.0, 0.0],
            v: [0.0, 1.0],
            size: [b.width(), b.height()],
        }
    }

    /// Whether the shape is a rectangle: perpendicular unit axes, so that a point's
    /// coordinates in its frame are dot products.
    #[inline]
    pub fn is_rect(&self) -> bool {
        dot(self.u, self.v).abs() < 1e-15 && unit(self.u) && unit(self.v)
    }

    /// The world point `origin + a·u + b·v`.
    #[inline]
    pub fn at(&self, a: f64, b: f64) -> [f64; 2] {
        [
            self.origin[0] + a * self.u[0] + b * self.v[0],
            self.origin[1] + a * self.u[1] + b * self.v[1],
        ]
    }

    /// Coordinates of a world point in this shape's frame: the (a, b) of `origin + a·u + b·v`.
    #[inline]
    pub fn local(&self, p: [f64; 2]) -> [f64; 2] {
        self.local_dir([p[0] - self.origin[0], p[1] - self.origin[1]])
    }

    /// Coordinates of a world vector in this shape's frame.
    #[inline]
    pub fn local_dir(&self, d: [f64; 2]) -> [f64; 2] {
        if self.is_rect() {
            return [dot(d, self.u), dot(d, self.v)];
        }
        let det = cross(self.u, self.v);
        [cross(d, self.v) / det, cross(self.u, d) / det]
    }

    /// The four corners in turn round the shape: `origin` first, then along `u`.
    pub fn corners(&self) -> [[f64; 2]; 4] {
        [
            self.at(0.0, 0.0),
            self.at(self.size[0], 0.0),
            self.at(self.size[0], self.size[1]),
            self.at(0.0, self.size[1]),
        ]
    }

    /// The least axis-aligned box holding the shape.
    pub fn aabb(&self) -> Aabb {
        Aabb::of_points(&self.corners())
    }

    /// The area: the product of the sides and the sine of the angle between `u` and `v`.
    pub fn area(&self) -> f64 {
        if self.is_rect() {
            return self.size[0] * self.size[1];
        }
        self.size[0] * self.size[1] * cross(self.u, self.v).abs()
    }

    /// The point halfway along both sides, where the diagonals cross.
    pub fn centre(&self) -> [f64; 2] {
        self.at(self.size[0] / 2.0, self.size[1] / 2.0)
    }

    /// Whether a world point lies in the shape, boundary included.
    #[inline]
    pub fn contains_point(&self, p: [f64; 2]) -> bool {
        let l = self.local(p);
        l[0] >= 0.0 && l[1] >= 0.0 && l[0] <= self.size[0] && l[1] <= self.size[1]
    }

    /// How far along `a` and along `b` the sides move when each moves `d` along its normal.
    fn offsets(&self, d: f64) -> [f64; 2] {
        if self.is_rect() {
            return [d, d];
        }
        let c = cross(self.u, self.v).abs();
        [d / c, d / c]
    }

    /// The shape with every side moved `d` outwards: it holds every point within `d` of it.
    pub fn inflated(&self, d: f64) -> ORect {
        if d <= 0.0 {
            return *self;
        }
        let [da, db] = self.offsets(d);
        ORect {
            origin: self.at(-da, -db),
            size: [self.size[0] + 2.0 * da, self.size[1] + 2.0 * db],
            ..*self
        }
    }

    /// The shape with every side moved `d` inwards: the points whose every point within `d`
    /// is in the shape. None when nothing is left.
    pub fn deflated(&self, d: f64) -> Option<ORect> {
        if d <= 0.0 {
            return Some(*self);
        }
        let [da, db] = self.offsets(d);
        let size = [self.size[0] - 2.0 * da, self.size[1] - 2.0 * db];
        (size[0] > 0.0 && size[1] > 0.0).then(|| ORect {
            origin: self.at(da, db),
            size,
            ..*self
        })
    }

    /// The image of the shape under an affine map, itself a parallelogram.
    pub fn mapped(&self, f: &Affine) -> ORect {
        let (a, b) = (f.apply_vec(self.u), f.apply_vec(self.v));
        let (la, lb) = (dot(a, a).sqrt(), dot(b, b).sqrt());
        ORect {
            origin: f.apply(self.origin),
            u: [a[0] / la, a[1] / la],
            v: [b[0] / lb, b[1] / lb],
            size: [self.size[0] * la, self.size[1] * lb],
        }
    }

    /// Projection of this shape on an axis, as an interval.
    fn project(&self, axis: [f64; 2]) -> (f64, f64) {
        let o = dot(self.origin, axis);
        let a = self.size[0] * dot(self.u, axis);
        let b = self.size[1] * dot(self.v, axis);
        (o + a.min(0.0) + b.min(0.0), o + a.max(0.0) + b.max(0.0))
    }

    /// The directions across this shape's sides: its axes for a rectangle, the normals of its
    /// sides otherwise.
    pub fn normals(&self) -> [[f64; 2]; 2] {
        if self.is_rect() {
            return [self.u, self.v];
        }
        [[-self.u[1], self.u[0]], [-self.v[1], self.v[0]]]
    }

    /// Separating-axis test; closed, so shapes that only touch intersect.
    pub fn intersects(&self, o: &ORect) -> bool {
        let [a, b] = self.normals();
        let [c, d] = o.normals();
        for axis in [a, b, c, d] {
            let (a0, a1) = self.project(axis);
            let (b0, b1) = o.project(axis);
            if a1 < b0 || b1 < a0 {
                return false;
            }
        }
        true
    }

    /// [`ORect::intersects`] with an axis-aligned box; closed as well.
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

    #[test]
    fn skewed_shapes_find_their_points_and_grow_and_shrink_by_distance() {
        // Sheared: the b axis leans 30° from the a axis.
        let (s, c) = (30f64.to_radians().sin(), 30f64.to_radians().cos());
        let p = ORect {
            origin: [1.0, 2.0],
            u: [1.0, 0.0],
            v: [s, c],
            size: [4.0, 2.0],
        };
        assert!(!p.is_rect());
        let q = p.at(1.5, 0.5);
        let l = p.local(q);
        assert!((l[0] - 1.5).abs() < 1e-12 && (l[1] - 0.5).abs() < 1e-12);
        assert!((p.area() - 8.0 * c).abs() < 1e-12);
        // Every point within d of the shape is in the inflated one, and every point of the
        // deflated one has its whole d-disc inside.
        let d = 0.1;
        let (big, small) = (p.inflated(d), p.deflated(d).unwrap());
        let mut next = crate::rng::uniform(3);
        for _ in 0..4000 {
            let x = [next() * 8.0 - 1.0, next() * 6.0];
            let inside = p.contains_point(x);
            let near = inside
                || (0..32).any(|k| {
                    let t = k as f64 * std::f64::consts::TAU / 32.0;
                    p.contains_point([x[0] + d * t.cos(), x[1] + d * t.sin()])
                });
            if near {
                assert!(big.contains_point(x), "{x:?}");
            }
            if small.contains_point(x) {
                assert!((0..32).all(|k| {
                    let t = k as f64 * std::f64::consts::TAU / 32.0;
                    p.contains_point([x[0] + d * t.cos(), x[1] + d * t.sin()])
                }));
            }
        }
        assert!(p.deflated(1.0).is_none());
        // An affine map carries it to a parallelogram holding exactly the images.
        let f = Affine {
            origin: [10.0, -3.0],
            m: [[2.0, 0.5], [-0.3, 1.5]],
        };
        let img = p.mapped(&f);
        let inv = f.inverse().unwrap();
        for (a, b) in [(0.0, 0.0), (4.0, 2.0), (1.0, 1.7)] {
            let w = f.apply(p.at(a, b));
            let l = img.local(w);
            assert!((l[0] / img.size[0] - a / 4.0).abs() < 1e-12);
            assert!((l[1] / img.size[1] - b / 2.0).abs() < 1e-12);
            let back = inv.apply(w);
            let want = p.at(a, b);
            assert!((back[0] - want[0]).abs() < 1e-12 && (back[1] - want[1]).abs() < 1e-12);
        }
    }
}
