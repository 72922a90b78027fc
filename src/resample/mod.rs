//! Resampling extracted patches into heights (§5): sample grids, resolved patches, and the
//! CPU and GPU implementations.

pub mod cpu;
pub mod gpu;

use crate::index::geom::Aabb;
use crate::index::query::ViewQuery;
use crate::model::grid::Grid;
use crate::model::ids::PatchId;
use crate::model::patch::{CellRect, Patch};
use std::sync::Arc;

/// Output samples per block side when binning patches.
pub const BLOCK: usize = 16;

/// Where to sample: a `width × height` array of plane positions, row-major. A NaN position
/// (a view ray above the horizon) yields nodata.
#[derive(Clone, Debug)]
pub struct SampleGrid {
    pub width: usize,
    pub height: usize,
    pub points: Vec<[f64; 2]>,
}

impl SampleGrid {
    /// A north-up tile over `roi`, sample (i, j) at the centre of its pixel.
    pub fn uniform(roi: &Aabb, width: usize, height: usize) -> Self {
        let dx = roi.width() / width as f64;
        let dy = roi.height() / height as f64;
        let points = (0..height)
            .flat_map(|j| {
                (0..width).map(move |i| {
                    [
                        roi.min[0] + (i as f64 + 0.5) * dx,
                        roi.max[1] - (j as f64 + 0.5) * dy,
                    ]
                })
            })
            .collect();
        SampleGrid {
            width,
            height,
            points,
        }
    }

    /// A screen grid of `width × height` pixels projected from the eye onto the plane
    /// z = `ground`: dense near the viewer, sparse far away (§5, persistent grid mapping).
    pub fn view(view: &ViewQuery, width: usize, height: usize, ground: f64) -> Self {
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
        let mut points = Vec::with_capacity(width * height);
        for j in 0..height {
            for i in 0..width {
                let x = (2.0 * (i as f64 + 0.5) / width as f64 - 1.0) * t;
                let y = (1.0 - 2.0 * (j as f64 + 0.5) / height as f64) * t * aspect;
                let d = [
                    f[0] + x * right[0] + y * up[0],
                    f[1] + x * right[1] + y * up[1],
                    f[2] + x * right[2] + y * up[2],
                ];
                let k = (ground - eye[2]) / d[2];
                points.push(if d[2] < -1e-12 && k > 0.0 {
                    [(eye[0] + k * d[0]) / s[0], (eye[1] + k * d[1]) / s[1]]
                } else {
                    [f64::NAN, f64::NAN]
                });
            }
        }
        SampleGrid {
            width,
            height,
            points,
        }
    }

    /// Bounds of each block's points, row-major over blocks; None for a block without any.
    pub fn block_bounds(&self) -> Vec<Option<Aabb>> {
        let bx = self.width.div_ceil(BLOCK);
        let by = self.height.div_ceil(BLOCK);
        (0..bx * by)
            .map(|b| {
                let (i0, j0) = ((b % bx) * BLOCK, (b / bx) * BLOCK);
                let mut acc: Option<Aabb> = None;
                for j in j0..(j0 + BLOCK).min(self.height) {
                    for i in i0..(i0 + BLOCK).min(self.width) {
                        let p = self.points[j * self.width + i];
                        if p[0].is_nan() {
                            continue;
                        }
                        let pb = Aabb { min: p, max: p };
                        acc = Some(acc.map_or(pb, |a| a.union(&pb)));
                    }
                }
                acc
            })
            .collect()
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

/// A patch ready to evaluate: its level grid and everything per-sample work needs, computed
/// once per request.
#[derive(Clone, Debug)]
pub struct ResolvedPatch {
    /// Identifies the window's samples, so a device that already holds them need not upload
    /// them again.
    pub id: PatchId,
    pub level: Arc<Grid>,
    pub kernel: CellRect,
    pub window: CellRect,
    pub centre: [f64; 2],
    pub inv_half: [f64; 2],
    /// 1 / (dx·dy): the weight's unit volume, in world units.
    pub norm: f64,
    pub window_aabb: Aabb,
    origin: [f64; 2],
    u: [f64; 2],
    v: [f64; 2],
    inv_step: [f64; 2],
}

impl ResolvedPatch {
    pub fn new(level: Arc<Grid>, p: &Patch) -> Self {
        let g = level.georef;
        let [u, v] = g.axes();
        let nominal = crate::index::geom::ORect {
            origin: g.to_world(p.centre[0] - p.half[0], p.centre[1] - p.half[1]),
            u,
            v,
            size: [2.0 * p.half[0] * g.step[0], 2.0 * p.half[1] * g.step[1]],
        };
        let window = crate::index::geom::ORect::from_cells(&g, &p.window);
        ResolvedPatch {
            id: p.id,
            kernel: p.kernel,
            window: p.window,
            centre: p.centre,
            inv_half: [1.0 / p.half[0], 1.0 / p.half[1]],
            norm: 1.0 / (p.half[0] * g.step[0] * p.half[1] * g.step[1]),
            window_aabb: window
                .aabb()
                .intersection(&nominal.aabb())
                .unwrap_or(window.aabb()),
            origin: g.origin,
            u,
            v,
            inv_step: [1.0 / g.step[0], 1.0 / g.step[1]],
            level,
        }
    }

    /// Level grid coordinates of a world point. Coordinates within [`SNAP`] of a grid line are
    /// put on it: a sample grid aligned with a level puts points on its lines, where validity
    /// changes, and rounding noise must not decide which side they fall on (nor may it differ
    /// between the CPU and the GPU).
    #[inline]
    pub fn to_grid(&self, p: [f64; 2]) -> [f64; 2] {
        let d = [p[0] - self.origin[0], p[1] - self.origin[1]];
        [
            snap((d[0] * self.u[0] + d[1] * self.u[1]) * self.inv_step[0]),
            snap((d[0] * self.v[0] + d[1] * self.v[1]) * self.inv_step[1]),
        ]
    }
}

/// How close to a grid line, in cells, a sample counts as on it.
pub const SNAP: f64 = 1e-9;

#[inline]
fn snap(x: f64) -> f64 {
    let n = x.round();
    if (x - n).abs() < SNAP {
        n
    } else {
        x
    }
}

/// The patches of one request, in a fixed order so that sums are reproducible.
#[derive(Clone, Debug, Default)]
pub struct PatchSet {
    pub patches: Vec<ResolvedPatch>,
}
