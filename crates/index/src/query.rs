//! Cuts through LOD space (§4.3): uniform, view-dependent, and any error field.

use super::lod::{LodIndex, PatchBox, Span};
use patchwork_geom::{Aabb, ORect};
use patchwork_model::ids::{PatchId, SurveyId};
use patchwork_model::place::PlaneId;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// A patch returned by a query.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Extracted {
    /// The patch.
    pub id: PatchId,
    /// The unit it came with: its survey, or its edge patch's owner.
    pub survey: SurveyId,
    /// Where it is in its unit's list: its place in its survey's list of patches, 0 for an
    /// edge patch. With `survey`, what finds the patch.
    pub position: u32,
    /// Its mipmap level.
    pub level: u8,
    /// Its box's z-span in LOD space, in metres.
    pub span: Span,
    /// Its kernel in the store's plane (through the frame, for a patch of another plane).
    pub kernel: ORect,
    /// Where in the store's plane it can contribute to a blend: [`PatchBox::reach`].
    pub window: ORect,
    /// The plane its grid is in (see [`PatchBox::plane`]).
    pub plane: PlaneId,
    /// Taken because no data is as accurate as the cut asks somewhere in its kernel, and it is
    /// the most accurate data there: blended only where nothing the cut asked for is.
    pub fallback: bool,
}

/// Where a cut falls short of its error: of the points that some patch's kernel holds, the
/// share that only fallback patches hold (no data there is as accurate as asked), and the
/// least and largest error of what serves those points (the best fallback patch at each).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shortfall {
    /// Share of the points with data that only fallback patches hold, in (0, 1].
    pub share: f64,
    /// Least error, in metres, of the best fallback patch at those points.
    pub min_error: f64,
    /// Largest such error.
    pub max_error: f64,
}

/// The [`Shortfall`] of a cut's patches over `points`; None where every point with data is
/// met.
///
/// Each point is tested against the patches whose kernel's bounds reach the cell of a coarse
/// grid it falls in, rather than against all of them: a cut of thousands of patches over a
/// tile's few thousand probes would otherwise cost tens of millions of tests, more than the
/// rest of a mesh's preparation.
pub fn shortfall(ps: &[Extracted], points: impl Iterator<Item = [f64; 2]>) -> Option<Shortfall> {
    if ps.iter().all(|x| !x.fallback) {
        return None;
    }
    let points: Vec<[f64; 2]> = points.collect();
    let bins = Bins::new(&points, ps);
    let (mut held, mut only) = (0usize, 0usize);
    let (mut least, mut most) = (f64::INFINITY, 0.0f64);
    for &p in &points {
        let near = bins.near(p);
        let inside = |x: &&Extracted| x.kernel.contains_point(p);
        if near
            .iter()
            .map(|&k| &ps[k as usize])
            .filter(|x| !x.fallback)
            .any(|x| inside(&x))
        {
            held += 1;
            continue;
        }
        // The most accurate of the fallback patches there is what serves the point.
        let best = near
            .iter()
            .map(|&k| &ps[k as usize])
            .filter(|x| x.fallback)
            .filter(inside)
            .map(|x| x.span.min_z)
            .fold(f64::INFINITY, f64::min);
        if best.is_finite() {
            held += 1;
            only += 1;
            least = least.min(best);
            most = most.max(best);
        }
    }
    (only > 0).then(|| Shortfall {
        share: only as f64 / held as f64,
        min_error: least,
        max_error: most,
    })
}

/// The patches of a cut binned by the cells of a grid over a set of points: every patch whose
/// kernel's bounds reach a cell is listed in it, so a point's cell lists every patch whose
/// kernel can hold the point (and maybe a few more).
///
/// The lists lie end to end in one vector, cell after cell (`starts` says where each begins):
/// a list of its own for each of a tile's 4,096 cells cost more in allocations than the
/// probes themselves.
struct Bins {
    origin: [f64; 2],
    cell: [f64; 2],
    n: [usize; 2],
    starts: Vec<u32>,
    listed: Vec<u32>,
}

impl Bins {
    fn new(points: &[[f64; 2]], ps: &[Extracted]) -> Bins {
        let b = Aabb::of_points(points);
        let side = (points.len() as f64).sqrt().ceil().clamp(1.0, 256.0) as usize;
        let n = [side, side];
        let cell = [
            (b.width() / side as f64).max(f64::MIN_POSITIVE),
            (b.height() / side as f64).max(f64::MIN_POSITIVE),
        ];
        let mut bins = Bins {
            origin: b.min,
            cell,
            n,
            starts: vec![0; side * side + 1],
            listed: Vec::new(),
        };
        if points.is_empty() {
            return bins;
        }
        // The cells each patch's kernel reaches, as ranges of columns and rows.
        let spans: Vec<Option<([usize; 2], [usize; 2])>> = ps
            .iter()
            .map(|x| {
                let a = x.kernel.aabb();
                let meets = a.max[0] >= b.min[0]
                    && a.min[0] <= b.max[0]
                    && a.max[1] >= b.min[1]
                    && a.min[1] <= b.max[1];
                meets.then(|| (bins.at(a.min), bins.at(a.max)))
            })
            .collect();
        // Counted, then placed: each cell's patches in ascending order, as pushed one by one.
        for ([i0, j0], [i1, j1]) in spans.iter().flatten() {
            for j in *j0..=*j1 {
                for i in *i0..=*i1 {
                    bins.starts[j * n[0] + i + 1] += 1;
                }
            }
        }
        for c in 0..side * side {
            bins.starts[c + 1] += bins.starts[c];
        }
        let mut next = bins.starts.clone();
        bins.listed = vec![0; bins.starts[side * side] as usize];
        for (k, span) in spans.iter().enumerate() {
            let Some(([i0, j0], [i1, j1])) = span else {
                continue;
            };
            for j in *j0..=*j1 {
                for i in *i0..=*i1 {
                    let at = &mut next[j * n[0] + i];
                    bins.listed[*at as usize] = k as u32;
                    *at += 1;
                }
            }
        }
        bins
    }

    /// The cell of a point, clamped to the grid. Monotone in each coordinate, so a point
    /// inside a box falls in a cell between those of the box's corners.
    fn at(&self, p: [f64; 2]) -> [usize; 2] {
        let idx = |a: usize| {
            let t = ((p[a] - self.origin[a]) / self.cell[a]).floor();
            if t.is_nan() {
                0
            } else {
                (t.max(0.0) as usize).min(self.n[a] - 1)
            }
        };
        [idx(0), idx(1)]
    }

    /// The patches listed in a point's cell.
    fn near(&self, p: [f64; 2]) -> &[u32] {
        let [i, j] = self.at(p);
        let c = j * self.n[0] + i;
        &self.listed[self.starts[c] as usize..self.starts[c + 1] as usize]
    }
}

impl Extracted {
    fn of(b: &PatchBox, span: Span, fallback: bool) -> Self {
        Extracted {
            id: b.id,
            survey: b.survey,
            position: b.position,
            level: b.level,
            span,
            kernel: b.store_kernel(),
            window: b.reach(),
            plane: b.plane(),
            fallback,
        }
    }
}

/// The error allowed at each point of the plane: the query surface in LOD space.
pub trait ErrorField: Sync {
    /// Lower and upper bounds of the allowed error over an area. Bounds may be loose, which
    /// costs minimality, never coverage.
    fn range(&self, area: &Aabb) -> (f64, f64);
}

/// The same error everywhere: a horizontal plane.
#[derive(Clone, Copy, Debug)]
pub struct Uniform(pub f64);

impl ErrorField for Uniform {
    fn range(&self, _: &Aabb) -> (f64, f64) {
        (self.0, self.0)
    }
}

/// A convex region of interest.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Roi {
    /// Counter-clockwise or clockwise vertices of a convex polygon.
    pub points: Vec<[f64; 2]>,
}

impl Roi {
    /// The ROI of an axis-aligned rectangle.
    pub fn rect(b: &Aabb) -> Self {
        Roi {
            points: b.corners().to_vec(),
        }
    }

    /// Bounds of the polygon.
    pub fn aabb(&self) -> Aabb {
        Aabb::of_points(&self.points)
    }

    /// Separating-axis test against a parallelogram; closed.
    pub fn intersects(&self, r: &ORect) -> bool {
        let n = self.points.len();
        let corners = r.corners();
        let proj = |pts: &[[f64; 2]], a: [f64; 2]| {
            pts.iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                    let d = p[0] * a[0] + p[1] * a[1];
                    (lo.min(d), hi.max(d))
                })
        };
        let mut axes: Vec<[f64; 2]> = r.normals().to_vec();
        for i in 0..n {
            let p = self.points[i];
            let q = self.points[(i + 1) % n];
            axes.push([q[1] - p[1], p[0] - q[0]]);
        }
        axes.iter().all(|&a| {
            let (a0, a1) = proj(&self.points, a);
            let (b0, b1) = proj(&corners, a);
            !(a1 < b0 || b1 < a0)
        })
    }

    /// Whether a point lies in the polygon, boundary included.
    pub fn contains_point(&self, p: [f64; 2]) -> bool {
        let n = self.points.len();
        let mut sign = 0.0f64;
        for i in 0..n {
            let a = self.points[i];
            let b = self.points[(i + 1) % n];
            let c = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]);
            if c != 0.0 {
                if sign != 0.0 && c.signum() != sign {
                    return false;
                }
                sign = c.signum();
            }
        }
        true
    }
}

impl LodIndex {
    /// The cut through LOD space along `field`: every patch that reaches into the ROI (its
    /// window meets it) and whose z-span meets the field there, and, where no data is as
    /// accurate as the field asks, the most accurate data there is (exposed boxes with an error
    /// above the field), marked as fallback. A patch is judged on its kernel, as in the paper;
    /// one whose window alone reaches the ROI, on its whole kernel. A uniform field is the
    /// same everywhere, so
    /// whether a patch is taken then does not depend on the ROI: a point gets the same patches
    /// from any ROI that holds it.
    pub fn cut(&self, roi: &Roi, field: &dyn ErrorField) -> Vec<Extracted> {
        let area = roi.aabb();
        let mut ats = Vec::new();
        self.tree()
            .cut(&area, |a| field.range(a), |e| ats.push(e.at()));
        ats.sort_unstable();
        ats.dedup();
        // On every core: a 1° cut of 16,000 patches took 10 ms on one.
        let mut out: Vec<Extracted> = ats
            .into_par_iter()
            .filter_map(|at| {
                let (b, state) = self.lookup(at)?;
                if !roi.intersects(&b.reach()) {
                    return None;
                }
                let span = Span {
                    min_z: b.min_z,
                    max_z: state.top,
                };
                // Judged on its kernel, within the ROI where the kernel reaches into it.
                let aabb = b.aabb();
                let (lo, hi) = field.range(&aabb.intersection(&area).unwrap_or(aabb));
                if span.is_active() && b.min_z <= hi && span.max_z > lo {
                    return Some(Extracted::of(&b, span, false));
                }
                (state.exposed && span.is_active() && b.min_z > lo)
                    .then(|| Extracted::of(&b, span, true))
            })
            .collect();
        // In id order, which does not depend on the order the surveys came in.
        out.sort_unstable_by_key(|x| x.id);
        out
    }

    /// The uniform cut at error `e` over a rectangle. Where no data is as accurate as `e`, the
    /// most accurate data there is comes back instead of a hole; each patch carries its own
    /// error. At or above the top of LOD space, the coarsest cut.
    pub fn uniform(&self, roi: &Aabb, e: f64) -> Vec<Extracted> {
        let top = self.config().max_error;
        let e = e.max(0.0).min(top - top.abs() * 1e-12);
        self.cut(&Roi::rect(roi), &Uniform(e))
    }

    /// The view-dependent cut: a skewed plane of constant screen error, clipped to the view's
    /// footprint on the plane.
    pub fn view(&self, view: &ViewQuery) -> Vec<Extracted> {
        let Some(bounds) = self.bounds() else {
            return Vec::new();
        };
        let field = view.field();
        let roi = view.footprint(&bounds);
        self.cut(&roi, &field)
    }
}

/// Metres per CRS unit along x and y near a point. Geographic CRSs use the WGS84 ellipsoid's
/// local scale, so that view distances come out in metres whatever the CRS.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metric {
    /// Metres per CRS unit along x and along y.
    pub scale: [f64; 2],
}

impl Metric {
    /// One metre per unit along both axes: a projected CRS in metres.
    pub const PROJECTED: Metric = Metric { scale: [1.0, 1.0] };

    /// The local scale at latitude `lat` degrees, for longitude/latitude coordinates.
    pub fn geographic(lat: f64) -> Metric {
        let p = lat.to_radians();
        let m_lat = 111_132.92 - 559.82 * (2.0 * p).cos() + 1.175 * (4.0 * p).cos()
            - 0.0023 * (6.0 * p).cos();
        let m_lon = 111_412.84 * p.cos() - 93.5 * (3.0 * p).cos() + 0.118 * (5.0 * p).cos();
        Metric {
            scale: [m_lon, m_lat],
        }
    }
}

/// A camera over the terrain: the view-dependent query of §4.3.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewQuery {
    /// Eye position: plane coordinates in CRS units, height in metres.
    pub eye: [f64; 3],
    /// A point the camera looks at, same units.
    pub look: [f64; 3],
    /// Horizontal field of view in degrees.
    pub fov_deg: f64,
    /// Viewport width in pixels.
    pub viewport_px: u32,
    /// Allowed screen error in pixels.
    pub pixel_error: f64,
    /// How the plane's CRS units convert to metres.
    pub metric: Metric,
}

/// The error field of a view: δ = δ_screen · distance / (d·λ), distance measured in the plane.
#[derive(Clone, Copy, Debug)]
pub struct ViewField {
    eye: [f64; 2],
    scale: [f64; 2],
    /// Metres of error allowed per metre of distance.
    slope: f64,
}

impl ViewField {
    /// The error allowed at a point, in metres: the slope times its distance from the eye in the
    /// plane.
    pub fn at(&self, p: [f64; 2]) -> f64 {
        let dx = (p[0] - self.eye[0]) * self.scale[0];
        let dy = (p[1] - self.eye[1]) * self.scale[1];
        self.slope * dx.hypot(dy)
    }
}

impl ErrorField for ViewField {
    fn range(&self, a: &Aabb) -> (f64, f64) {
        let near = [
            self.eye[0].clamp(a.min[0], a.max[0]),
            self.eye[1].clamp(a.min[1], a.max[1]),
        ];
        let far = a
            .corners()
            .iter()
            .map(|&c| self.at(c))
            .fold(0.0f64, f64::max);
        (self.at(near), far)
    }
}

impl ViewQuery {
    /// The points of a screen grid of `width × height` pixels projected from the eye onto the
    /// plane z = `ground` (§5, persistent grid mapping), dense near the viewer and sparse far
    /// away, as each row's first point and the step from one point to the next: None for a
    /// row whose rays miss the plane. A screen row's rays share their vertical component (the
    /// camera's right vector is level), so they meet the plane at one distance along the view
    /// and their points lie evenly on a line: a view grid is two points a row, not one a
    /// pixel.
    pub fn ground_rows(
        &self,
        width: usize,
        height: usize,
        ground: f64,
    ) -> Vec<Option<[[f64; 2]; 2]>> {
        let view = self;
        let s = view.metric.scale;
        let eye = [view.eye[0] * s[0], view.eye[1] * s[1], view.eye[2]];
        let look = [view.look[0] * s[0], view.look[1] * s[1], view.look[2]];
        let f = normalise([look[0] - eye[0], look[1] - eye[1], look[2] - eye[2]]);
        let right = {
            let r = [f[1], -f[0], 0.0];
            if r[0].hypot(r[1]) < 1e-9 {
                [1.0, 0.0, 0.0]
            } else {
                normalise(r)
            }
        };
        let up = cross(right, f);
        let t = (view.fov_deg.to_radians() / 2.0).tan();
        let aspect = height as f64 / width as f64;
        // Pixel i's ray is f + (x0 + i·dx)·right + y·up.
        let x0 = (1.0 / width as f64 - 1.0) * t;
        let dx = 2.0 * t / width as f64;
        (0..height)
            .map(|j| {
                let y = (1.0 - 2.0 * (j as f64 + 0.5) / height as f64) * t * aspect;
                let dz = f[2] + y * up[2];
                let k = (ground - eye[2]) / dz;
                (dz < -1e-12 && k > 0.0).then(|| {
                    let first = |a: usize| (eye[a] + k * (f[a] + y * up[a] + x0 * right[a])) / s[a];
                    let step = |a: usize| k * dx * right[a] / s[a];
                    [[first(0), first(1)], [step(0), step(1)]]
                })
            })
            .collect()
    }

    /// Checks that the view can be cut: finite eye and look, a field of view in (0°, 180°), a
    /// viewport at least a pixel wide and a finite, non-negative pixel error.
    pub fn validate(&self) -> Result<(), String> {
        if !(self
            .eye
            .iter()
            .chain(self.look.iter())
            .all(|v| v.is_finite()))
        {
            return Err("eye and look must be finite".into());
        }
        if !(self.fov_deg > 0.0 && self.fov_deg < 180.0) {
            return Err(format!(
                "fov must lie in (0, 180) degrees, got {}",
                self.fov_deg
            ));
        }
        if self.viewport_px == 0 {
            return Err("viewport must be at least one pixel wide".into());
        }
        if !(self.pixel_error.is_finite() && self.pixel_error >= 0.0) {
            return Err(format!("pixel error must be ≥ 0, got {}", self.pixel_error));
        }
        Ok(())
    }

    /// The view's error field: at distance d from the eye, the ground that `pixel_error`
    /// pixels span there, d · 2 tan(fov/2) · pixel_error / viewport_px.
    pub fn field(&self) -> ViewField {
        let half = (self.fov_deg.to_radians() / 2.0).tan();
        ViewField {
            eye: [self.eye[0], self.eye[1]],
            scale: self.metric.scale,
            slope: self.pixel_error * 2.0 * half / self.viewport_px as f64,
        }
    }

    /// The frustum's footprint on the plane, reaching as far as the data does: a triangle with
    /// its apex under the eye, or a square under a camera that looks straight down.
    pub fn footprint(&self, data: &Aabb) -> Roi {
        let s = self.metric.scale;
        let e = [self.eye[0] * s[0], self.eye[1] * s[1]];
        let d = [
            (self.look[0] - self.eye[0]) * s[0],
            (self.look[1] - self.eye[1]) * s[1],
        ];
        let height = (self.eye[2] - self.look[2]).abs().max(1.0);
        let half = self.fov_deg.to_radians() / 2.0;
        let horiz = d[0].hypot(d[1]);
        let back = |p: [f64; 2]| [p[0] / s[0], p[1] / s[1]];
        if horiz < 1e-3 * height {
            let r = height * half.tan() * std::f64::consts::SQRT_2;
            return Roi {
                points: vec![
                    back([e[0] - r, e[1] - r]),
                    back([e[0] + r, e[1] - r]),
                    back([e[0] + r, e[1] + r]),
                    back([e[0] - r, e[1] + r]),
                ],
            };
        }
        let reach = data
            .corners()
            .iter()
            .map(|c| (c[0] * s[0] - e[0]).hypot(c[1] * s[1] - e[1]))
            .fold(0.0f64, f64::max)
            .max(horiz)
            / half.cos();
        let dir = [d[0] / horiz, d[1] / horiz];
        let turn = |a: f64| {
            let (sn, cs) = a.sin_cos();
            [dir[0] * cs - dir[1] * sn, dir[0] * sn + dir[1] * cs]
        };
        let l = turn(half);
        let r = turn(-half);
        Roi {
            points: vec![
                back(e),
                back([e[0] + reach * r[0], e[1] + reach * r[1]]),
                back([e[0] + reach * l[0], e[1] + reach * l[1]]),
            ],
        }
    }
}

fn normalise(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
