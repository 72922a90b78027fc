//! Formula 1 beside the accurate blend (paper §7.3, docs/MODEL.md "The accurate blend"), on the
//! mixed scenes and the pair: the same cut's patches blended both ways into one north-up tile.
//!
//! Scenes, each made from real surveys (the middle of the first file, and of the second for
//! the pair), each with the survey its errors are measured against, the most accurate one:
//!
//! - *copies*: the survey and a copy of every third sample, both with estimated ε; against
//!   the survey;
//! - *nested*: the middle third of the survey with ε = 2 m inside a half-resolution copy with
//!   ε = 20 m; against the ε = 2 survey, where it has data;
//! - *mosaic*: the survey cut into four abutting tiles, ε = 1 m; against the whole survey;
//! - *pair*: the first two files over the same ground (Copernicus and NASADEM), ε estimated and
//!   weighed against each other; against the one the store serves as the more accurate.
//!
//! For each error asked and each blend: the largest and RMS error against that survey; the
//! slope jump along rows (the second difference of heights over the spacing: the change of
//! slope, m/m, from one step to the next, where blending bends the surface); the patches blended per sample (those with a
//! positive weight in the sum, on every seventh sample); the share of 16² blocks one patch
//! serves whole; and the median time of the tile on the CPU, and on a GPU where one is found
//! (a software adapter only with PATCHWORK_ALLOW_EMULATED_GPU=1, named in the CSV).

use crate::{meet, Fail};
use patchwork_core::crs::Crs;
use patchwork_core::geom::Aabb;
use patchwork_core::model::accuracy::AccuracySpec;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::patch::Blend;
use patchwork_core::model::survey::Survey;
use patchwork_core::resample::{cpu, PatchSet, SampleGrid, BLOCK};
use patchwork_core::terrain::Terrain;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// One scene, error and blend.
#[derive(Clone, Debug)]
pub struct Row {
    /// `copies`, `nested`, `mosaic` or `pair`.
    pub scene: &'static str,
    /// The error asked, metres.
    pub error: f64,
    /// `formula1` or `accurate`.
    pub blend: &'static str,
    /// Patches of the cut.
    pub patches: usize,
    /// Largest |tile − the most accurate survey| where it has data, metres.
    pub max_err: f64,
    /// RMS of the same.
    pub rms_err: f64,
    /// Slope jump along rows (m/m from one step to the next): 99th percentile.
    pub jump_p99: f64,
    /// The largest.
    pub jump_max: f64,
    /// Patches blended per valid sample, mean.
    pub per_sample: f64,
    /// Share of the tile's blocks one patch serves whole.
    pub alone: f64,
    /// Median time of the tile on the CPU.
    pub cpu_ms: f64,
    /// On the GPU, where there is one (at e = 0, 10 and 50 m).
    pub gpu_ms: Option<f64>,
    /// Samples without a height.
    pub nodata: usize,
}

struct Scene {
    name: &'static str,
    terrain: Terrain,
    /// The survey errors are measured against.
    truth: Grid,
}

/// The middle `side` × `side` samples of a grid, or all of it where it is smaller.
fn middle(g: &Grid, side: usize) -> Grid {
    let (w, h) = (g.cols.min(side), g.rows.min(side));
    g.window((g.cols - w) / 2, (g.rows - h) / 2, w, h)
}

fn scenes(files: &[PathBuf], side: usize) -> Result<Vec<Scene>, Fail> {
    let read = |f: &Path| -> Result<(Grid, Option<Crs>), Fail> {
        let r = patchwork_read::read_raster(f, &Default::default())?;
        let crs = r.crs.crs.clone();
        Ok((r.into_grid()?, crs))
    };
    let first = files.first().ok_or("no survey to make the scenes of")?;
    let (whole, crs) = read(first)?;
    let g = middle(&whole, side);
    let mut out = vec![Scene {
        name: "copies",
        terrain: meet::terrain(&[
            meet::survey(g.clone(), AccuracySpec::Auto, crs.clone())?,
            meet::survey(g.decimated(3), AccuracySpec::Auto, crs.clone())?,
        ]),
        truth: g.clone(),
    }];
    let (w0, h0) = (g.cols / 3, g.rows / 3);
    let inner = g.window(w0, h0, w0, h0);
    out.push(Scene {
        name: "nested",
        terrain: meet::terrain(&[
            meet::survey(inner.clone(), AccuracySpec::Fixed(2.0), crs.clone())?,
            meet::survey(g.decimated(2), AccuracySpec::Fixed(20.0), crs.clone())?,
        ]),
        truth: inner,
    });
    let pieces = meet::quarters(&g)
        .into_iter()
        .map(|p| meet::survey(p, AccuracySpec::Fixed(1.0), crs.clone()))
        .collect::<Result<Vec<_>, _>>()?;
    out.push(Scene {
        name: "mosaic",
        terrain: meet::terrain(&pieces),
        truth: g.clone(),
    });
    if let Some(second) = files.get(1) {
        let (other, _) = read(second)?;
        // The same ground: the second file's samples within the first's middle, a cell more.
        let b = g.world_bounds();
        let (c0, r0) = {
            let p = other.georef.to_grid([b.min[0], b.max[1]]);
            (
                p[0].floor().max(0.0) as usize,
                p[1].floor().max(0.0) as usize,
            )
        };
        let (c1, r1) = {
            let p = other.georef.to_grid([b.max[0], b.min[1]]);
            (
                (p[0].ceil() as usize + 1).min(other.cols),
                (p[1].ceil() as usize + 1).min(other.rows),
            )
        };
        if c1 > c0 + 1 && r1 > r0 + 1 {
            let other = other.window(c0, r0, c1 - c0, r1 - r0);
            let a = meet::survey(g.clone(), AccuracySpec::Auto, crs.clone())?;
            let o = meet::survey(other.clone(), AccuracySpec::Auto, crs.clone())?;
            let t = meet::terrain(&[a.clone(), o.clone()]);
            // The more accurate of the two as the store serves them, once each has been
            // weighed against the other.
            let eps = |s: &Arc<Survey>| t.survey(s.id).map_or(f64::INFINITY, |m| m.accuracy);
            let truth = if eps(&a) <= eps(&o) { g.clone() } else { other };
            out.push(Scene {
                name: "pair",
                terrain: t,
                truth,
            });
        }
    }
    Ok(out)
}

/// The 99th percentile and the largest slope jump along rows, samples `step_m` apart: the
/// second difference over the spacing, the change of slope (m/m) from one step to the next.
fn jumps(h: &[f32], width: usize, step_m: f64) -> (f64, f64) {
    let mut j: Vec<f64> = h
        .chunks(width)
        .flat_map(|row| {
            row.windows(3).filter_map(|w| {
                let d = (w[2] as f64 - 2.0 * w[1] as f64 + w[0] as f64) / step_m;
                d.is_finite().then_some(d.abs())
            })
        })
        .collect();
    if j.is_empty() {
        return (0.0, 0.0);
    }
    j.sort_by(f64::total_cmp);
    (j[j.len() * 99 / 100], j[j.len() - 1])
}

/// Patches with a positive weight in the height of sample `k` (of the store's plane), as the
/// set's blend counts them.
fn blended_at(set: &PatchSet, bin: &[u32], p: [f64; 2]) -> usize {
    let hits: Vec<_> = bin
        .iter()
        .filter_map(|&k| {
            let q = &set.patches[k as usize];
            q.at(p).map(|(w, h)| (q, w, h))
        })
        .collect();
    match set.blend {
        Blend::Accurate => {
            let (mut rest, mut stop, mut n) = (1.0f64, u32::MAX, 0);
            for (q, w, h) in hits {
                if rest <= 0.0 || q.tier() > stop {
                    break;
                }
                let a = w * rest;
                rest -= a;
                n += usize::from(a > 0.0);
                if h.covered {
                    stop = stop.min(q.tier());
                }
            }
            n
        }
        Blend::Formula1 => {
            // The tiers up to the best that covers the point: the cut's alone where one of its
            // patches covers it, else the fallback ranks up to the best covering one with them.
            let covering = hits
                .iter()
                .filter(|(_, _, h)| h.covered)
                .map(|(q, _, _)| q.tier())
                .min()
                .unwrap_or(u32::MAX);
            hits.iter()
                .filter(|(q, w, _)| *w > 0.0 && q.tier() <= covering)
                .count()
        }
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Runs every scene at each error with both blends; writes `blend.csv` and the charts.
pub fn run(files: &[PathBuf], out: &Path, smoke: bool) -> Result<Vec<Row>, Fail> {
    std::fs::create_dir_all(out)?;
    let (side, tile, repeats) = if smoke {
        (300, 128, 1)
    } else {
        (1200, 1024, 9)
    };
    let errors = [0.0, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0];
    let allow = std::env::var("PATCHWORK_ALLOW_EMULATED_GPU").as_deref() == Ok("1");
    let mut gpu = patchwork_engine::gpu::GpuResampler::new(if allow {
        patchwork_engine::gpu::Emulated::Allow
    } else {
        patchwork_engine::gpu::Emulated::Refuse
    })
    .ok();
    let adapter = gpu.as_ref().map(|g| g.adapter().to_string());
    println!(
        "blend: GPU {}",
        adapter.as_deref().unwrap_or("none (CPU times only)")
    );
    let mut rows = Vec::new();
    for scene in scenes(files, side)? {
        let t = &scene.terrain;
        let g = &scene.truth;
        let b = scene.terrain.surveys().fold(None::<Aabb>, |a, s| {
            let w = s.shapes[0].world_bounds();
            Some(a.map_or(w, |a| a.union(&w)))
        });
        let b = b.ok_or("a scene without surveys")?;
        // The middle 60% of the scene, as the mixed scenes of the main bench take it.
        let roi = Aabb::new(
            b.min[0] + 0.2 * b.width(),
            b.min[1] + 0.2 * b.height(),
            b.max[0] - 0.2 * b.width(),
            b.max[1] - 0.2 * b.height(),
        );
        let grid = SampleGrid::uniform(&roi, tile, tile);
        let lat = 0.5 * (roi.min[1] + roi.max[1]);
        let geographic = g.georef.step[0] < 0.1;
        let step_m = roi.width() / tile as f64
            * if geographic {
                111_320.0 * lat.to_radians().cos()
            } else {
                1.0
            };
        for &e in &errors {
            let ps = t.uniform(&roi, e);
            let base = t.resolve(&ps);
            let sets = Blend::ALL.map(|b| base.clone().with_blend(b));
            // The two blends in turn, so that the machine's drift falls on both alike.
            let mut times = [Vec::new(), Vec::new()];
            let mut heights = [Vec::new(), Vec::new()];
            for _ in 0..repeats {
                for (k, set) in sets.iter().enumerate() {
                    let t0 = Instant::now();
                    heights[k] = cpu::resample(set, &grid);
                    times[k].push(t0.elapsed().as_secs_f64() * 1e3);
                }
            }
            // A GPU at a few errors only: a software one takes seconds a tile.
            let mut gpu_times = [Vec::new(), Vec::new()];
            if let Some(d) = gpu.as_mut().filter(|_| [0.0, 10.0, 50.0].contains(&e)) {
                for set in &sets {
                    d.resample(set, &grid)?;
                }
                for _ in 0..repeats.min(5) {
                    for (k, set) in sets.iter().enumerate() {
                        let t0 = Instant::now();
                        d.resample(set, &grid)?;
                        gpu_times[k].push(t0.elapsed().as_secs_f64() * 1e3);
                    }
                }
            }
            for (k, set) in sets.iter().enumerate() {
                let blend = set.blend;
                let heights = &heights[k];
                let gpu_ms = (!gpu_times[k].is_empty()).then(|| median(gpu_times[k].clone()));
                let (max_err, rms_err) = meet::against(g, &grid, heights);
                let (jump_p99, jump_max) = jumps(heights, tile, step_m);
                let bins = cpu::bin(&set.patches, &grid);
                let bx = tile.div_ceil(BLOCK);
                let (mut n, mut blended) = (0usize, 0usize);
                for k in (0..tile * tile).step_by(7) {
                    if heights[k].is_nan() {
                        continue;
                    }
                    let (i, j) = (k % tile, k / tile);
                    blended += blended_at(set, &bins[(j / BLOCK) * bx + i / BLOCK], grid.point(k));
                    n += 1;
                }
                let (alone, blocks) = cpu::blocks_alone(set, &grid);
                let row = Row {
                    scene: scene.name,
                    error: e,
                    blend: blend.name(),
                    patches: ps.len(),
                    max_err,
                    rms_err,
                    jump_p99,
                    jump_max,
                    per_sample: blended as f64 / n.max(1) as f64,
                    alone: alone as f64 / blocks.max(1) as f64,
                    cpu_ms: median(times[k].clone()),
                    gpu_ms,
                    nodata: heights.iter().filter(|z| z.is_nan()).count(),
                };
                println!(
                    "{:>6} e = {e:>4} {:>8}: {} patches, max {:.3} m RMS {:.3} m, jump p99 {:.5} max {:.4}, {:.2} patches a sample, {:.0}% of blocks alone, CPU {:.1} ms{}",
                    row.scene,
                    row.blend,
                    row.patches,
                    row.max_err,
                    row.rms_err,
                    row.jump_p99,
                    row.jump_max,
                    row.per_sample,
                    100.0 * row.alone,
                    row.cpu_ms,
                    row.gpu_ms.map_or(String::new(), |g| format!(", GPU {g:.1} ms"))
                );
                rows.push(row);
            }
        }
    }
    let mut f = std::fs::File::create(out.join("blend.csv"))?;
    writeln!(
        f,
        "scene,error_m,blend,patches,max_err_m,rms_err_m,jump_p99,jump_max,patches_per_sample,blocks_alone,cpu_ms,gpu_ms,gpu,nodata"
    )?;
    for r in &rows {
        writeln!(
            f,
            "{},{},{},{},{:.4},{:.4},{:.6},{:.5},{:.3},{:.4},{:.2},{},{},{}",
            r.scene,
            r.error,
            r.blend,
            r.patches,
            r.max_err,
            r.rms_err,
            r.jump_p99,
            r.jump_max,
            r.per_sample,
            r.alone,
            r.cpu_ms,
            r.gpu_ms.map_or(String::new(), |g| format!("{g:.2}")),
            adapter.as_deref().unwrap_or("").replace(',', ";"),
            r.nodata
        )?;
    }
    crate::charts::blend(out, &rows)?;
    Ok(rows)
}
