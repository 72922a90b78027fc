//! Does a union of parallelograms cover a parallelogram? Everything is carried into the
//! target's own frame, where it is the rectangle [0, size] and every other shape a
//! parallelogram. The answer is exact for shapes that share the target's orientation (their
//! sides along its axes there) and conservative otherwise: it may say "not covered" for a
//! region that is covered, never the reverse. The cutter and the query fallback rely on that
//! direction: a false "covered" would open a hole in the terrain.

use patchwork_geom::ORect;

/// Relative tolerance for edges that coincide up to floating-point noise. Far above the noise
/// of f64 coordinates, far below any cell of any grid.
const TOL: f64 = 1e-9;
/// Most regions examined per call before giving up (and answering "not covered").
const BUDGET: usize = 4096;
/// Deepest halving of a region where no aligned edge offers a better split.
const MAX_HALVINGS: u32 = 14;

#[derive(Clone, Copy)]
enum Shape {
    /// Axis-aligned in the target's frame: [x0, x1] × [y0, y1].
    Aligned([f64; 4]),
    /// Any other orientation, kept in the target's frame.
    Rotated(ORect),
}

/// A rectangle in the target's frame.
#[derive(Clone, Copy)]
struct Region {
    x0: f64,
    y0: f64,
    x1: f64,
    y1: f64,
}

impl Shape {
    fn overlaps(&self, r: &Region, tol: f64) -> bool {
        match self {
            Shape::Aligned([x0, y0, x1, y1]) => {
                *x0 < r.x1 - tol && *x1 > r.x0 + tol && *y0 < r.y1 - tol && *y1 > r.y0 + tol
            }
            Shape::Rotated(o) => {
                let reg = ORect {
                    origin: [r.x0 + tol, r.y0 + tol],
                    u: [1.0, 0.0],
                    v: [0.0, 1.0],
                    size: [
                        (r.x1 - r.x0 - 2.0 * tol).max(0.0),
                        (r.y1 - r.y0 - 2.0 * tol).max(0.0),
                    ],
                };
                o.intersects(&reg)
            }
        }
    }

    fn contains(&self, r: &Region, tol: f64) -> bool {
        match self {
            Shape::Aligned([x0, y0, x1, y1]) => {
                *x0 <= r.x0 + tol && *y0 <= r.y0 + tol && *x1 >= r.x1 - tol && *y1 >= r.y1 - tol
            }
            Shape::Rotated(o) => [[r.x0, r.y0], [r.x1, r.y0], [r.x1, r.y1], [r.x0, r.y1]]
                .iter()
                .all(|&p| {
                    let l = o.local(p);
                    l[0] >= -tol
                        && l[1] >= -tol
                        && l[0] <= o.size[0] + tol
                        && l[1] <= o.size[1] + tol
                }),
        }
    }
}

/// Whether every target rectangle is covered by the union of `by`.
pub fn covered_all(targets: &[ORect], by: &[ORect]) -> bool {
    targets.iter().all(|t| covered(t, by))
}

/// Whether the union of `by` covers `target`.
pub fn covered(target: &ORect, by: &[ORect]) -> bool {
    let tol = TOL * (target.size[0] + target.size[1]);
    let shapes: Vec<Shape> = by.iter().map(|q| to_frame(target, q)).collect();
    let root = Region {
        x0: 0.0,
        y0: 0.0,
        x1: target.size[0],
        y1: target.size[1],
    };
    let mut budget = BUDGET;
    let live: Vec<usize> = (0..shapes.len()).collect();
    cover(&root, &shapes, &live, tol, &mut budget, 0)
}

fn to_frame(target: &ORect, q: &ORect) -> Shape {
    let o = target.local(q.origin);
    let u = target.local_dir(q.u);
    let v = target.local_dir(q.v);
    // Grids that share an orientation (or differ by quarter turns) stay exact: both sides
    // along the target's axes. (One side along an axis says nothing of the other when either
    // grid is skewed.)
    let flat = |w: [f64; 2], k: usize| w[k].abs() < 1e-12;
    if (flat(u, 1) && flat(v, 0)) || (flat(u, 0) && flat(v, 1)) {
        let a = [o[0] + u[0] * q.size[0], o[1] + u[1] * q.size[0]];
        let b = [o[0] + v[0] * q.size[1], o[1] + v[1] * q.size[1]];
        let c = [a[0] + v[0] * q.size[1], a[1] + v[1] * q.size[1]];
        let xs = [o[0], a[0], b[0], c[0]];
        let ys = [o[1], a[1], b[1], c[1]];
        let min = |s: [f64; 4]| s.iter().cloned().fold(f64::INFINITY, f64::min);
        let max = |s: [f64; 4]| s.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        Shape::Aligned([min(xs), min(ys), max(xs), max(ys)])
    } else {
        Shape::Rotated(ORect {
            origin: o,
            u,
            v,
            size: q.size,
        })
    }
}

fn cover(
    r: &Region,
    shapes: &[Shape],
    live: &[usize],
    tol: f64,
    budget: &mut usize,
    halvings: u32,
) -> bool {
    let hits: Vec<usize> = live
        .iter()
        .copied()
        .filter(|&i| shapes[i].overlaps(r, tol))
        .collect();
    if hits.is_empty() {
        return false;
    }
    if hits.iter().any(|&i| shapes[i].contains(r, tol)) {
        return true;
    }
    if *budget == 0 {
        return false;
    }
    *budget -= 1;
    // Splitting along an aligned edge that crosses the region makes progress exactly; only
    // when none crosses do we halve, which is where the answer can turn conservative.
    let mid = [(r.x0 + r.x1) / 2.0, (r.y0 + r.y1) / 2.0];
    let mut best: Option<(usize, f64, f64)> = None;
    for &i in &hits {
        if let Shape::Aligned([x0, y0, x1, y1]) = shapes[i] {
            for (axis, e) in [(0, x0), (0, x1), (1, y0), (1, y1)] {
                let (lo, hi) = if axis == 0 {
                    (r.x0, r.x1)
                } else {
                    (r.y0, r.y1)
                };
                if e > lo + tol && e < hi - tol {
                    let d = (e - mid[axis]).abs() / (hi - lo);
                    if best.is_none_or(|b| d < b.2) {
                        best = Some((axis, e, d));
                    }
                }
            }
        }
    }
    let (axis, at, halvings) = match best {
        Some((axis, e, _)) => (axis, e, halvings),
        None if halvings < MAX_HALVINGS => {
            let axis = usize::from(r.y1 - r.y0 > r.x1 - r.x0);
            (axis, mid[axis], halvings + 1)
        }
        None => return false,
    };
    let (a, b) = if axis == 0 {
        (Region { x1: at, ..*r }, Region { x0: at, ..*r })
    } else {
        (Region { y1: at, ..*r }, Region { y0: at, ..*r })
    };
    cover(&a, shapes, &hits, tol, budget, halvings)
        && cover(&b, shapes, &hits, tol, budget, halvings)
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwork_geom::Aabb;

    fn r(x0: f64, y0: f64, x1: f64, y1: f64) -> ORect {
        ORect::from_aabb(&Aabb::new(x0, y0, x1, y1))
    }

    fn rotated(cx: f64, cy: f64, half: f64, theta: f64) -> ORect {
        let (s, c) = theta.sin_cos();
        let u = [c, s];
        let v = [-s, c];
        ORect {
            origin: [cx - half * (u[0] + v[0]), cy - half * (u[1] + v[1])],
            u,
            v,
            size: [2.0 * half, 2.0 * half],
        }
    }

    #[test]
    fn aligned_tilings_are_exact() {
        let t = r(0.0, 0.0, 10.0, 10.0);
        let quarters = [
            r(0.0, 0.0, 5.0, 5.0),
            r(5.0, 0.0, 10.0, 5.0),
            r(0.0, 5.0, 5.0, 10.0),
            r(5.0, 5.0, 10.0, 10.0),
        ];
        assert!(covered(&t, &quarters));
        assert!(!covered(&t, &quarters[..3]));
        // A gap one thousandth of the target wide is found.
        let gap = [r(0.0, 0.0, 4.99, 10.0), r(5.0, 0.0, 10.0, 10.0)];
        assert!(!covered(&t, &gap));
        // Ragged, overlapping pieces.
        let ragged = [
            r(-1.0, -1.0, 3.0, 11.0),
            r(2.0, -1.0, 7.5, 4.0),
            r(2.5, 3.0, 11.0, 11.0),
            r(7.0, -2.0, 12.0, 3.5),
        ];
        assert!(covered(&t, &ragged));
    }

    #[test]
    fn a_rotated_cover_is_found_and_a_rotated_gap_is_never_missed() {
        let t = r(0.0, 0.0, 1.0, 1.0);
        assert!(covered(&t, &[rotated(0.5, 0.5, 0.75, 0.4)]));
        assert!(!covered(&t, &[rotated(0.5, 0.5, 0.55, 0.4)]));
        // Two rotated halves that overlap generously are seen to cover.
        let left = rotated(0.2, 0.5, 0.6, 0.1);
        let right = rotated(0.8, 0.5, 0.6, 0.1);
        assert!(covered(&t, &[left, right]));
        // Pull them apart a little: a thin wedge of the target is uncovered.
        let left = rotated(0.05, 0.5, 0.5, 0.1);
        let right = rotated(1.0, 0.5, 0.5, 0.1);
        assert!(!covered(&t, &[left, right]));
    }

    #[test]
    fn coverage_never_claims_points_that_are_uncovered() {
        // Random rotated configurations: whenever coverage is claimed, dense point samples
        // of the target must all lie in some rectangle.
        let mut rnd = patchwork_geom::rng::uniform(12345);
        let t = r(0.0, 0.0, 1.0, 1.0);
        let mut claimed = 0;
        for _ in 0..300 {
            let n = 1 + (rnd() * 5.0) as usize;
            let by: Vec<ORect> = (0..n)
                .map(|_| {
                    rotated(
                        rnd() * 1.4 - 0.2,
                        rnd() * 1.4 - 0.2,
                        0.2 + rnd() * 0.6,
                        rnd() * 3.0,
                    )
                })
                .collect();
            if covered(&t, &by) {
                claimed += 1;
                for i in 0..60 {
                    for j in 0..60 {
                        let p = [(i as f64 + 0.5) / 60.0, (j as f64 + 0.5) / 60.0];
                        assert!(by.iter().any(|q| q.contains_point(p)), "hole at {p:?}");
                    }
                }
            }
        }
        assert!(
            claimed > 10,
            "only {claimed} covered configurations were exercised"
        );
    }
}
