//! Seed 001's estimator of a node's largest error (Kalem and Kourgli), beside the exact δ the
//! store measures: charted, not used. An underestimate would break the bound a patch's error
//! promises, so it can serve only where time matters more than the bound.
//!
//! The estimator localises a node's largest world-space error with a Haar decomposition of
//! the samples under it, then measures the error only there. Here a node is a patch window
//! (`patches.kernel` 28 cells and `margin` 2 at every level, as the store cuts them: 64² samples
//! of level 0 under a level-1 window, 1,024² under a level-5 one, the paper's node size). Under
//! a level-ℓ cell lie 2^ℓ × 2^ℓ samples of level 0, and the energy of the Haar detail
//! coefficients of every scale within that block is, by Parseval, the sum of the squared
//! departures of its samples from their mean: one pass over level 0 with summed-area tables
//! of z and z² gives it for every cell of every level. The estimate of a window is the largest
//! exact deviation (the store's own, [`Bilinear::max_deviation`]) over the share `q` of its cells
//! whose detail energy is highest; the exact δ is the largest over all of them.
//!
//! Reported for each survey, level and share: how many windows the estimate falls below δ,
//! by how much (metres, and as a share of δ), the paper's estimation error M/N_T (the share of
//! a window's samples whose deviation exceeds the estimate), and the time of the estimate for
//! every window of every level beside the store's exact pass over the same levels.

use crate::Fail;
use patchwork_core::model::grid::{Georef, Grid};
use patchwork_core::model::mipmap;
use patchwork_core::model::patch::{Bilinear, CellRect, PatchFunction, Tiling};
use patchwork_read::{read_raster, ReadLimits};
use rayon::prelude::*;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// The store's patch layout (config/patchwork.toml, `[patches]`).
const KERNEL: usize = 28;
const MARGIN: u32 = 2;
/// Shares of a window's cells whose error is measured.
const SHARES: [f64; 3] = [1.0 / 64.0, 1.0 / 16.0, 1.0 / 4.0];

/// One survey, level and share.
#[derive(Clone, Debug)]
pub struct Row {
    /// The survey's file name.
    pub survey: String,
    /// The mipmap level.
    pub level: usize,
    /// The share of a window's cells measured.
    pub share: f64,
    /// Windows of the level with data.
    pub windows: usize,
    /// Of those, where the estimate is below δ.
    pub under: usize,
    /// The largest shortfall δ − estimate, metres.
    pub shortfall_max_m: f64,
    /// The median shortfall over the windows underestimated, as a share of their δ.
    pub shortfall_median_rel: f64,
    /// The mean and largest M/N_T over the windows.
    pub mnt_mean: f64,
    /// See `mnt_mean`.
    pub mnt_max: f64,
    /// The estimate's time for every level's windows, ms (the same on each row of a survey
    /// and share).
    pub estimate_ms: f64,
    /// The store's exact δ for every level's windows, ms.
    pub exact_ms: f64,
}

/// Summed-area tables of level 0: valid samples, their sum and their sum of squares.
struct Sums {
    cols: usize,
    n: Vec<u32>,
    s: Vec<f64>,
    q: Vec<f64>,
}

impl Sums {
    fn of(g: &Grid) -> Sums {
        let (w, h) = (g.cols + 1, g.rows + 1);
        let (mut n, mut s, mut q) = (vec![0u32; w * h], vec![0.0; w * h], vec![0.0; w * h]);
        for j in 0..g.rows {
            let (mut rn, mut rs, mut rq) = (0u32, 0.0f64, 0.0f64);
            for i in 0..g.cols {
                let z = g.at(i, j);
                if !z.is_nan() {
                    let z = f64::from(z);
                    rn += 1;
                    rs += z;
                    rq += z * z;
                }
                let k = (j + 1) * w + i + 1;
                n[k] = n[k - w] + rn;
                s[k] = s[k - w] + rs;
                q[k] = q[k - w] + rq;
            }
        }
        Sums { cols: w, n, s, q }
    }

    /// The Haar detail energy of samples [i0, i1) × [j0, j1): Σ(z − mean)².
    fn energy(&self, i0: usize, j0: usize, i1: usize, j1: usize) -> f64 {
        let w = self.cols;
        let at = |v: &[f64]| v[j1 * w + i1] - v[j0 * w + i1] - v[j1 * w + i0] + v[j0 * w + i0];
        let n =
            self.n[j1 * w + i1] + self.n[j0 * w + i0] - self.n[j0 * w + i1] - self.n[j1 * w + i0];
        if n == 0 {
            return 0.0;
        }
        let (s, q) = (at(&self.s), at(&self.q));
        (q - s * s / f64::from(n)).max(0.0)
    }
}

/// The windows of level `lv`, as the store cuts them.
fn windows(levels: &[Arc<Grid>], lv: usize) -> Vec<CellRect> {
    let t = Tiling::new(levels[lv].cells(), KERNEL, [0, 0]);
    let [kx, ky] = t.counts();
    (0..ky as u32)
        .flat_map(|y| (0..kx as u32).map(move |x| [x, y]))
        .map(|k| t.window(&t.kernel(k), MARGIN))
        .collect()
}

fn cell(c: u32, r: u32) -> CellRect {
    CellRect {
        c0: c,
        r0: r,
        c1: c + 1,
        r1: r + 1,
    }
}

/// The estimates of every window of every level at share `q`, and δ of each cell measured.
fn estimate(levels: &[Arc<Grid>], q: f64) -> Vec<Vec<f64>> {
    let sums = Sums::of(&levels[0]);
    (1..levels.len())
        .map(|lv| {
            let g = &levels[lv];
            let f = 1usize << lv;
            let [cw, ch] = g.cells();
            let fine = &levels[0];
            let energy: Vec<f64> = (0..cw * ch)
                .into_par_iter()
                .map(|k| {
                    let (c, r) = (k % cw, k / cw);
                    if !g.cell_valid(c, r) {
                        return -1.0;
                    }
                    let (i0, j0) = ((c * f).min(fine.cols - 1), (r * f).min(fine.rows - 1));
                    let (i1, j1) = (
                        (c * f + f + 1).min(fine.cols),
                        (r * f + f + 1).min(fine.rows),
                    );
                    sums.energy(i0, j0, i1, j1)
                })
                .collect();
            // The cells each window chooses, measured once each.
            let wins = windows(levels, lv);
            let chosen: Vec<Vec<usize>> = wins
                .par_iter()
                .map(|w| {
                    let mut cells: Vec<usize> = (w.r0 as usize..w.r1 as usize)
                        .flat_map(|r| (w.c0 as usize..w.c1 as usize).map(move |c| r * cw + c))
                        .filter(|&k| energy[k] >= 0.0)
                        .collect();
                    let keep = ((cells.len() as f64 * q).ceil() as usize)
                        .max(1)
                        .min(cells.len());
                    if keep < cells.len() {
                        cells.select_nth_unstable_by(keep - 1, |a, b| {
                            energy[*b].total_cmp(&energy[*a])
                        });
                        cells.truncate(keep);
                    }
                    cells
                })
                .collect();
            let mut todo: Vec<usize> = chosen.iter().flatten().copied().collect();
            todo.sort_unstable();
            todo.dedup();
            let measured: Vec<f64> = todo
                .par_iter()
                .map(|&k| {
                    Bilinear.max_deviation(levels, lv, &cell((k % cw) as u32, (k / cw) as u32))
                })
                .collect();
            chosen
                .iter()
                .map(|cells| {
                    cells
                        .iter()
                        .map(|k| measured[todo.binary_search(k).expect("measured")])
                        .fold(0.0f64, f64::max)
                })
                .collect()
        })
        .collect()
}

/// Samples under window `w` of level `lv` whose deviation exceeds `t`, and all of them.
fn exceeding(levels: &[Arc<Grid>], lv: usize, w: &CellRect, t: f64) -> (u64, u64) {
    let (coarse, fine) = (&levels[lv], &levels[0]);
    let f = 1usize << lv;
    let inv = 1.0 / f as f64;
    let (mut m, mut n) = (0u64, 0u64);
    // Each sample once, though it lies on the edges of up to four cells.
    let (i_end, j_end) = (
        (w.c1 as usize * f).min(fine.cols - 1),
        (w.r1 as usize * f).min(fine.rows - 1),
    );
    for j in (w.r0 as usize * f)..=j_end {
        let r = (j / f).min(coarse.rows - 2);
        for i in (w.c0 as usize * f)..=i_end {
            let c = (i / f).min(coarse.cols - 2);
            let z = fine.at(i, j);
            if z.is_nan() || !coarse.cell_valid(c, r) {
                continue;
            }
            let (fx, fy) = ((i - c * f) as f64 * inv, (j - r * f) as f64 * inv);
            let z00 = f64::from(coarse.at(c, r));
            let z10 = f64::from(coarse.at(c + 1, r));
            let z01 = f64::from(coarse.at(c, r + 1));
            let z11 = f64::from(coarse.at(c + 1, r + 1));
            let a = z00 + (z01 - z00) * fy;
            let b = z10 + (z11 - z10) * fy;
            let d = (a + (b - a) * fx - f64::from(z)).abs();
            n += 1;
            if d > t {
                m += 1;
            }
        }
    }
    (m, n)
}

/// The estimator beside exact δ on each file; writes `wavelet.csv` and its charts to `out`.
pub fn run(files: &[PathBuf], out: &Path) -> Result<Vec<Row>, Fail> {
    std::fs::create_dir_all(out)?;
    let mut rows = Vec::new();
    for path in files {
        let name = path
            .file_name()
            .map_or("?".into(), |n| n.to_string_lossy().into_owned());
        let r = read_raster(path, &ReadLimits::default())?;
        let grid = Grid::new(
            r.cols,
            r.rows,
            r.samples,
            Georef::from_geotransform(r.geotransform)?,
        )?;
        let levels = mipmap::build(Arc::new(grid), KERNEL);
        let all: Vec<(usize, CellRect)> = (1..levels.len())
            .flat_map(|lv| windows(&levels, lv).into_iter().map(move |w| (lv, w)))
            .collect();
        // The store's exact pass, then each share's estimate: medians of 3.
        let time = |f: &mut dyn FnMut()| {
            let mut t: Vec<f64> = (0..3)
                .map(|_| {
                    let s = Instant::now();
                    f();
                    s.elapsed().as_secs_f64() * 1e3
                })
                .collect();
            t.sort_by(f64::total_cmp);
            t[1]
        };
        let mut exact = Vec::new();
        let exact_ms = time(&mut || exact = Bilinear.deviations(&levels, &all));
        for &q in &SHARES {
            let mut est = Vec::new();
            let estimate_ms = time(&mut || est = estimate(&levels, q));
            let mut k = 0;
            for (lv, level_est) in est.iter().enumerate().map(|(i, e)| (i + 1, e)) {
                let wins = windows(&levels, lv);
                let judged: Vec<(f64, f64, u64, u64)> = wins
                    .par_iter()
                    .zip(&exact[k..k + wins.len()])
                    .zip(level_est)
                    .map(|((w, &d), &e)| {
                        let (m, n) = exceeding(&levels, lv, w, e);
                        (d, e, m, n)
                    })
                    .collect();
                k += wins.len();
                let with_data: Vec<&(f64, f64, u64, u64)> =
                    judged.iter().filter(|j| j.3 > 0).collect();
                let under: Vec<&&(f64, f64, u64, u64)> =
                    with_data.iter().filter(|j| j.1 < j.0 - 1e-9).collect();
                let mut rel: Vec<f64> = under.iter().map(|j| (j.0 - j.1) / j.0).collect();
                rel.sort_by(f64::total_cmp);
                let mnt: Vec<f64> = with_data.iter().map(|j| j.2 as f64 / j.3 as f64).collect();
                rows.push(Row {
                    survey: name.clone(),
                    level: lv,
                    share: q,
                    windows: with_data.len(),
                    under: under.len(),
                    shortfall_max_m: under.iter().map(|j| j.0 - j.1).fold(0.0, f64::max),
                    shortfall_median_rel: rel.get(rel.len() / 2).copied().unwrap_or(0.0),
                    mnt_mean: mnt.iter().sum::<f64>() / mnt.len().max(1) as f64,
                    mnt_max: mnt.iter().copied().fold(0.0, f64::max),
                    estimate_ms,
                    exact_ms,
                });
            }
        }
        println!("wavelet estimator: {name} done");
    }
    let mut f = std::fs::File::create(out.join("wavelet.csv"))?;
    writeln!(
        f,
        "survey,level,share,windows,under,shortfall_max_m,shortfall_median_rel,mnt_mean,mnt_max,estimate_ms,exact_ms"
    )?;
    for r in &rows {
        writeln!(
            f,
            "{},{},{:.6},{},{},{:.4},{:.4},{:.6},{:.6},{:.1},{:.1}",
            r.survey,
            r.level,
            r.share,
            r.windows,
            r.under,
            r.shortfall_max_m,
            r.shortfall_median_rel,
            r.mnt_mean,
            r.mnt_max,
            r.estimate_ms,
            r.exact_ms
        )?;
    }
    crate::charts::wavelet(out, &rows)?;
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(cols: usize, rows: usize, f: impl Fn(usize, usize) -> f32) -> Grid {
        let samples = (0..rows)
            .flat_map(|j| (0..cols).map(move |i| (i, j)))
            .map(|(i, j)| f(i, j))
            .collect();
        Grid::new(
            cols,
            rows,
            samples,
            Georef::from_geotransform([0.0, 1.0, 0.0, 0.0, 0.0, -1.0]).unwrap(),
        )
        .unwrap()
    }

    #[test]
    fn a_blocks_haar_energy_is_its_squared_departure_from_its_mean() {
        let g = grid(9, 7, |i, j| {
            if (i, j) == (3, 2) {
                f32::NAN
            } else {
                (i * i + 3 * j) as f32 * 0.5
            }
        });
        let sums = Sums::of(&g);
        let block: Vec<f64> = (1..6)
            .flat_map(|j| (2..7).map(move |i| (i, j)))
            .map(|(i, j)| f64::from(g.at(i, j)))
            .filter(|z| !z.is_nan())
            .collect();
        let mean = block.iter().sum::<f64>() / block.len() as f64;
        let want: f64 = block.iter().map(|z| (z - mean).powi(2)).sum();
        assert!((sums.energy(2, 1, 7, 6) - want).abs() < 1e-6 * want.max(1.0));
    }

    #[test]
    fn estimates_never_exceed_the_exact_delta_and_reach_it_measuring_every_cell() {
        let g = grid(257, 257, |i, j| {
            let (x, y) = (i as f32 * 0.07, j as f32 * 0.05);
            (x.sin() * 40.0 + (y * 1.7).cos() * 25.0)
                + if (i * 31 + j * 17) % 97 == 0 {
                    30.0
                } else {
                    0.0
                }
        });
        let levels = mipmap::build(Arc::new(g), KERNEL);
        let all: Vec<(usize, CellRect)> = (1..levels.len())
            .flat_map(|lv| windows(&levels, lv).into_iter().map(move |w| (lv, w)))
            .collect();
        let exact = Bilinear.deviations(&levels, &all);
        for q in [1.0 / 16.0, 1.0] {
            let est: Vec<f64> = estimate(&levels, q).into_iter().flatten().collect();
            assert_eq!(est.len(), exact.len());
            for (e, d) in est.iter().zip(&exact) {
                assert!(*e <= d + 1e-9, "{e} > {d}");
                if q == 1.0 {
                    assert_eq!(e, d);
                }
            }
        }
    }
}
