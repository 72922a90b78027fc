//! Surveys, terrains and brute-force oracles the tests share: synthetic surveys over a made-up
//! landscape, the real crops committed under `tests/data/`, and oracles that decide coverage,
//! minimality and error point by point, independently of the index's own geometry.

use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::{IndexConfig, PatchBox};
use patchwork_core::index::query::Extracted;
use patchwork_core::model::grid::{Georef, Grid};
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::survey::Survey;
use patchwork_core::resample::cpu;
use patchwork_core::terrain::{PatchRef, Terrain};
use std::cmp::Ordering;
use std::sync::Arc;

/// Small kernels, so that grids of a few dozen samples still have several levels.
pub const LAYOUT: PatchLayout = PatchLayout {
    kernel: 8,
    margin: 1,
};

/// A made-up landscape in world coordinates, so that overlapping surveys sample one terrain:
/// rolling hills, a ridge, and a 40 m cliff along a slanted line.
pub fn landscape(x: f64, y: f64, seed: u64) -> f32 {
    let s = (seed % 97) as f64 * 0.37;
    let hills = 30.0 * (x / 7.0 + s).sin() * (y / 5.0 - s).cos() + 8.0 * (x / 2.3 + y / 3.1).sin();
    let ridge = 25.0 * (-((x - y * 0.5 - 10.0) / 4.0).powi(2)).exp();
    let cliff = if x + 0.3 * y > 20.0 + s { 40.0 } else { 0.0 };
    (200.0 + hills + ridge + cliff) as f32
}

/// A synthetic survey: a rotated grid of a smooth random landscape with disc-shaped voids.
#[derive(Clone, Debug)]
pub struct Spec {
    /// Samples a row.
    pub cols: usize,
    /// Rows of samples.
    pub rows: usize,
    /// Where sample (0, 0) lies, in the world.
    pub origin: [f64; 2],
    /// The grid's rotation, in radians.
    pub theta: f64,
    /// Its cell size along the columns and the rows.
    pub step: [f64; 2],
    /// Voids as discs (centre col, centre row, radius in cells).
    pub voids: Vec<(f64, f64, f64)>,
    /// ε in metres; a negative value asks for it to be estimated from the samples.
    pub accuracy: f64,
    /// Draws the landscape.
    pub seed: u64,
}

impl Spec {
    /// The grid the spec describes.
    pub fn grid(&self) -> Grid {
        let g = Georef {
            origin: self.origin,
            theta: self.theta,
            step: self.step,
            row_theta: None,
        };
        let mut s = Vec::with_capacity(self.cols * self.rows);
        for r in 0..self.rows {
            for c in 0..self.cols {
                let void = self.voids.iter().any(|&(vc, vr, rad)| {
                    (c as f64 - vc).powi(2) + (r as f64 - vr).powi(2) <= rad * rad
                });
                let p = g.to_world(c as f64, r as f64);
                s.push(if void {
                    f32::NAN
                } else {
                    landscape(p[0], p[1], self.seed)
                });
            }
        }
        Grid::new(self.cols, self.rows, s, g).unwrap()
    }

    /// Its survey in UTM zone 31N; None where it cannot be built (every sample void).
    pub fn survey(&self) -> Option<Arc<Survey>> {
        let spec = if self.accuracy < 0.0 {
            patchwork_core::model::accuracy::AccuracySpec::Auto
        } else {
            self.accuracy.into()
        };
        Survey::build(
            self.grid(),
            spec,
            Some(patchwork_core::crs::Crs::epsg(32631).unwrap()),
            LAYOUT,
        )
        .ok()
        .map(Arc::new)
    }
}

/// A terrain of these surveys, inserted in order.
pub fn terrain_of(surveys: &[Arc<Survey>]) -> Terrain {
    let mut t = Terrain::new(IndexConfig::default());
    for s in surveys {
        t.insert(s.clone());
    }
    t
}

/// The bounds of the surveys' level-0 grids together.
pub fn bounds_of(surveys: &[Arc<Survey>]) -> Aabb {
    surveys
        .iter()
        .map(|s| s.levels[0].world_bounds())
        .reduce(|a, b| a.union(&b))
        .expect("at least one survey")
}

/// Whether a world point lies in the valid part of an extracted patch's kernel, decided from
/// the patch's own grid (not from the index's rectangles).
pub fn in_valid_kernel(t: &Terrain, x: &Extracted, p: [f64; 2]) -> bool {
    let tol = 1e-7;
    match t.patch(x).expect("extracted patches resolve") {
        PatchRef::Survey(s, patch) => {
            let g = s.shapes[patch.level as usize].georef.to_grid(p);
            s.valid(patch).iter().any(|r| {
                g[0] >= r.c0 as f64 - tol
                    && g[0] <= r.c1 as f64 + tol
                    && g[1] >= r.r0 as f64 - tol
                    && g[1] <= r.r1 as f64 + tol
            })
        }
        PatchRef::Edge(e) => {
            let g = e.georef.to_grid(p);
            let k = e.kernel;
            let inside = g[0] >= k.c0 as f64 - tol
                && g[0] <= k.c1 as f64 + tol
                && g[1] >= k.r0 as f64 - tol
                && g[1] <= k.r1 as f64 + tol;
            inside
                && t.edge_grid(e)
                    .expect("an edge patch's samples")
                    .eval(g)
                    .is_some()
        }
    }
}

/// A uniformly random point inside a valid level-0 cell of the survey, from two numbers in [0, 1).
pub fn valid_point(s: &Survey, a: f64, b: f64, c: f64) -> Option<[f64; 2]> {
    let g = &s.levels[0];
    let [cw, ch] = g.cells();
    let cells: Vec<(usize, usize)> = (0..ch)
        .flat_map(|r| (0..cw).map(move |c| (c, r)))
        .filter(|&(c, r)| g.cell_valid(c, r))
        .collect();
    if cells.is_empty() {
        return None;
    }
    let (cc, rr) = cells[((a * cells.len() as f64) as usize).min(cells.len() - 1)];
    Some(g.georef.to_world(cc as f64 + b, rr as f64 + c))
}

/// The outer edges of a grid's pixels: half a cell beyond its outer samples, as GDAL sees a
/// north-up raster.
pub fn pixel_bounds(g: &Grid) -> Aabb {
    let c = g.cols as f64 - 0.5;
    let r = g.rows as f64 - 0.5;
    Aabb::of_points(&[
        g.georef.to_world(-0.5, -0.5),
        g.georef.to_world(c, -0.5),
        g.georef.to_world(-0.5, r),
        g.georef.to_world(c, r),
    ])
}

/// Whether a point lies in a valid sample's pixel: within half a cell of it along both axes
/// (on a pixel edge, either pixel counts). Decided from the samples alone.
pub fn pixel_valid(g: &Grid, p: [f64; 2]) -> bool {
    let q = g.georef.to_grid(p);
    let tol = 1e-9;
    let around = |x: f64, n: usize| -> Vec<usize> {
        let lo = (x - 0.5 - tol).ceil().max(0.0);
        let hi = (x + 0.5 + tol).floor().min(n as f64 - 1.0);
        if lo > hi {
            return Vec::new();
        }
        (lo as usize..=hi as usize).collect()
    };
    around(q[0], g.cols)
        .iter()
        .any(|&c| around(q[1], g.rows).iter().any(|&r| g.is_valid(c, r)))
}

/// The lowest and highest valid sample within a cell and a half of a point: the range any
/// interpolation near it may take.
pub fn neighbourhood_range(g: &Grid, p: [f64; 2]) -> (f64, f64) {
    let q = g.georef.to_grid(p);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let span = |x: f64, n: usize| {
        let a = (x - 1.5).floor().max(0.0) as usize;
        let b = ((x + 1.5).ceil().max(0.0) as usize).min(n - 1);
        a..=b
    };
    for r in span(q[1], g.rows) {
        for c in span(q[0], g.cols) {
            if g.is_valid(c, r) {
                let z = g.at(c, r) as f64;
                lo = lo.min(z);
                hi = hi.max(z);
            }
        }
    }
    (lo, hi)
}

/// Formula 1 over every extracted patch at one point.
pub fn blended(t: &Terrain, ps: &[Extracted], p: [f64; 2]) -> f32 {
    let set = t.resolve(ps);
    let all: Vec<u32> = (0..set.patches.len() as u32).collect();
    cpu::blend(&set, &all, p)
}

/// Heights of every survey with valid data at p: its bilinear height in a whole cell, or in
/// a valid pixel without one (a border, the edge of a void) the range of the samples near.
pub fn survey_heights(surveys: &[Arc<Survey>], p: [f64; 2]) -> Vec<f64> {
    surveys
        .iter()
        .flat_map(|s| {
            let g = &s.levels[0];
            match g.bilinear(p) {
                Some(h) => vec![h],
                None if pixel_valid(g, p) => {
                    let (lo, hi) = neighbourhood_range(g, p);
                    vec![lo, hi]
                }
                None => Vec::new(),
            }
        })
        .collect()
}

/// Patches whose valid kernel is entirely covered by valid kernels of extracted patches that
/// are greater in the global order. Decided by point sampling at the centres of a lattice
/// fine enough (`cell / 8`) that every piece of the arrangement holds a sample when all grids
/// share one orientation and their edges sit on a quarter-cell lattice.
pub fn redundant(t: &Terrain, ps: &[Extracted], lattice: f64) -> Vec<String> {
    let boxes: Vec<(Extracted, PatchBox)> = ps
        .iter()
        .map(|x| (x.clone(), t.index().get(x.survey, x.position).unwrap().0))
        .collect();
    let mut bad = Vec::new();
    for (x, b) in &boxes {
        let greater: Vec<&Extracted> = boxes
            .iter()
            .filter(|(_, q)| q.order(b) == Ordering::Greater && q.kernel().intersects(&b.kernel()))
            .map(|(y, _)| y)
            .collect();
        let mut needed = false;
        'rects: for r in &b.valid() {
            let a = r.aabb();
            let nx = (a.width() / lattice).round() as usize;
            let ny = (a.height() / lattice).round() as usize;
            for j in 0..ny {
                for i in 0..nx {
                    let p = [
                        a.min[0] + (i as f64 + 0.5) * lattice,
                        a.min[1] + (j as f64 + 0.5) * lattice,
                    ];
                    if !greater.iter().any(|y| in_valid_kernel(t, y, p)) {
                        needed = true;
                        break 'rects;
                    }
                }
            }
        }
        if !needed {
            bad.push(format!(
                "{} (level {}, error {})",
                x.id, x.level, x.span.min_z
            ));
        }
    }
    bad
}

/// Fallback patches with no point of their valid kernel outside every more accurate
/// extracted patch: nowhere the best data, so the fallback had no reason to take them.
/// Decided by point sampling, as [`redundant`].
pub fn needless_fallback(
    t: &Terrain,
    all: &[Extracted],
    fallback: &[Extracted],
    lattice: f64,
) -> Vec<String> {
    let boxes: Vec<(Extracted, PatchBox)> = all
        .iter()
        .map(|x| (x.clone(), t.index().get(x.survey, x.position).unwrap().0))
        .collect();
    let mut bad = Vec::new();
    for x in fallback {
        let b = t.index().get(x.survey, x.position).unwrap().0;
        let better: Vec<&Extracted> = boxes
            .iter()
            .filter(|(_, q)| q.more_accurate(&b) && q.kernel().intersects(&b.kernel()))
            .map(|(y, _)| y)
            .collect();
        let needed = b.valid().iter().any(|r| {
            let a = r.aabb();
            let nx = (a.width() / lattice).round().max(1.0) as usize;
            let ny = (a.height() / lattice).round().max(1.0) as usize;
            (0..ny).any(|j| {
                (0..nx).any(|i| {
                    let p = [
                        a.min[0] + (i as f64 + 0.5) * a.width() / nx as f64,
                        a.min[1] + (j as f64 + 0.5) * a.height() / ny as f64,
                    ];
                    !better.iter().any(|y| in_valid_kernel(t, y, p))
                })
            })
        });
        if !needed {
            bad.push(format!("{} (error {})", x.id, x.span.min_z));
        }
    }
    bad
}

/// One of the real-terrain crops committed under `tests/data/`, as a grid.
pub fn real_crop(name: &str) -> Grid {
    let path = data_dir().join(name);
    patchwork_read::read_raster(&path, &Default::default())
        .unwrap_or_else(|e| panic!("{name}: {e}"))
        .into_grid()
        .unwrap()
}

pub use patchwork_core::geom::rng::uniform;

/// One of the committed crops as a grid with its file's CRS.
pub fn real_crop_in_crs(name: &str) -> (Grid, Option<patchwork_core::crs::Crs>) {
    let path = data_dir().join(name);
    let r = patchwork_read::read_raster(&path, &Default::default())
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    let crs = r.crs.crs.clone();
    (r.into_grid().unwrap(), crs)
}

/// One of the committed crops as a survey of its own CRS (the file's), its accuracy
/// estimated, with the default patch layout.
pub fn crop_survey(name: &str) -> Arc<Survey> {
    let (grid, crs) = real_crop_in_crs(name);
    Arc::new(
        Survey::build(
            grid,
            patchwork_core::model::accuracy::AccuracySpec::Auto,
            crs,
            PatchLayout::default(),
        )
        .unwrap(),
    )
}

/// A window of a grid, georeferenced where it lies.
pub fn window(g: &Grid, c0: usize, r0: usize, cols: usize, rows: usize) -> Grid {
    g.window(c0, r0, cols, rows)
}

/// Every `k`-th sample of a grid from the first: a coarser survey of the same ground.
pub fn decimate(g: &Grid, k: usize) -> Grid {
    g.decimated(k)
}

/// A grid with only a `keep` fraction of its samples left, chosen by a seeded hash: scattered
/// soundings rather than whole cells.
pub fn sparse(g: &Grid, keep: f64, seed: u64) -> Grid {
    let mut out = g.clone();
    for (k, z) in out.samples.iter_mut().enumerate() {
        let mut h = (k as u64 ^ seed).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        h ^= h >> 29;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 32;
        if (h >> 11) as f64 / (1u64 << 53) as f64 >= keep {
            *z = f32::NAN;
        }
    }
    out
}

/// A survey of a grid with the given ε (a number, or `AccuracySpec::Auto`), EPSG:4326.
pub fn survey_with(
    g: Grid,
    spec: impl Into<patchwork_core::model::accuracy::AccuracySpec>,
) -> Arc<Survey> {
    Arc::new(
        Survey::build(
            g,
            spec,
            Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
            PatchLayout::default(),
        )
        .unwrap(),
    )
}

/// The same samples turned by `degrees` about the grid's centre: a rotated grid over the
/// original.
pub fn turned(grid: &Grid, degrees: f64) -> Grid {
    grid.turned(degrees)
}

/// A real crop as a survey: exact (ε = 0), EPSG:4326, the default patch layout.
pub fn real_survey(g: Grid) -> Arc<Survey> {
    real_survey_of(g, patchwork_core::model::patch::PatchKind::Bilinear)
}

/// [`real_survey`] with patches of `kind`.
pub fn real_survey_of(g: Grid, kind: patchwork_core::model::patch::PatchKind) -> Arc<Survey> {
    let recipe = patchwork_core::model::survey::Recipe {
        patches: kind,
        ..Default::default()
    };
    Arc::new(
        Survey::build_with(
            g,
            0.0,
            Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
            PatchLayout::default(),
            recipe,
        )
        .unwrap(),
    )
}

/// The folder of the real-terrain crops the tests read (`tests/data/` of the workspace).
pub fn data_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data")
}

/// The seed of a test's random draws: `PATCHWORK_SEED` where set (it replays a run), else the
/// clock's. Printed, so that a failure can be replayed.
pub fn seed() -> u64 {
    let seed = std::env::var("PATCHWORK_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(1, |d| d.as_nanos() as u64)
        });
    println!("seed {seed} (PATCHWORK_SEED={seed} replays it)");
    seed
}
