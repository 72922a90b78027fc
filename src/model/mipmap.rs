//! Nodata-aware mipmaps that stay aligned with the original samples.
//!
//! Level k+1 keeps every other sample position of level k and filters it with the separable
//! [1 2 1]/4 kernel. Keeping coarse samples on fine sample positions means every coarse grid
//! line is also a fine grid line, so the difference between a coarse patch and the original
//! surface is bilinear on each original cell; that is what lets the patch error δ be exact
//! rather than estimated (see `patch::Bilinear`).
//!
//! Voids erode: a coarse sample is valid only when every fine sample under its filter is. So
//! every valid coarse cell lies over valid original cells, a coarse patch never invents heights
//! inside a hole, and its δ bounds it everywhere it is evaluated. At the grid's edge the filter
//! is renormalised over the samples that exist.

use super::grid::Grid;
use rayon::prelude::*;
use std::sync::Arc;

/// Halves the resolution. Coarse samples never lie beyond the fine grid, so no coarse cell
/// reaches past the survey's edge: with an odd number of fine cells, the last one is left to
/// the finer level.
pub fn downsample(fine: &Grid) -> Grid {
    let cols = (fine.cols - 1) / 2 + 1;
    let rows = (fine.rows - 1) / 2 + 1;
    const W: [f64; 3] = [0.25, 0.5, 0.25];
    let mut samples = vec![f32::NAN; cols * rows];
    samples
        .par_chunks_mut(cols)
        .enumerate()
        .for_each(|(j, out_row)| {
            for (i, out) in out_row.iter_mut().enumerate() {
                let (mut sum, mut wsum) = (0.0f64, 0.0f64);
                for (dj, wj) in W.iter().enumerate() {
                    let Some(r) = (2 * j + dj).checked_sub(1).filter(|&r| r < fine.rows) else {
                        continue;
                    };
                    let row = &fine.samples[r * fine.cols..(r + 1) * fine.cols];
                    for (di, wi) in W.iter().enumerate() {
                        let Some(c) = (2 * i + di).checked_sub(1).filter(|&c| c < fine.cols) else {
                            continue;
                        };
                        // A NaN here makes the sum NaN: the coarse sample is void.
                        sum += wi * wj * row[c] as f64;
                        wsum += wi * wj;
                    }
                }
                *out = (sum / wsum) as f32;
            }
        });
    Grid {
        cols,
        rows,
        samples,
        georef: fine.georef.coarsened(2.0),
    }
}

/// All levels of a grid, level 0 first, down to the first level that one kernel of
/// `kernel_cells` cells covers whole.
pub fn build(level0: Arc<Grid>, kernel_cells: usize) -> Vec<Arc<Grid>> {
    let mut levels = vec![level0];
    loop {
        let last = levels.last().expect("level 0 is present");
        let [cw, ch] = last.cells();
        if cw <= kernel_cells && ch <= kernel_cells {
            break;
        }
        let next = Arc::new(downsample(last));
        levels.push(next);
    }
    levels
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::grid::Georef;

    fn grid(cols: usize, rows: usize, f: impl Fn(usize, usize) -> f32) -> Grid {
        let s = (0..rows)
            .flat_map(|r| (0..cols).map(move |c| (c, r)))
            .map(|(c, r)| f(c, r))
            .collect();
        Grid::new(cols, rows, s, Georef::north_up([10.0, 20.0], [2.0, 3.0])).unwrap()
    }

    #[test]
    fn coarse_samples_sit_on_fine_samples() {
        let g = grid(9, 6, |c, r| (c + 10 * r) as f32);
        let d = downsample(&g);
        assert_eq!((d.cols, d.rows), (5, 3));
        for j in 0..d.rows {
            for i in 0..d.cols {
                let p = d.georef.to_world(i as f64, j as f64);
                let q = g.georef.to_world(2.0 * i as f64, 2.0 * j as f64);
                assert!((p[0] - q[0]).abs() < 1e-12 && (p[1] - q[1]).abs() < 1e-12);
            }
        }
        // A linear ramp survives the symmetric filter unchanged away from the border.
        assert!((d.at(2, 1) - g.at(4, 2)).abs() < 1e-5);
    }

    #[test]
    fn voids_erode_and_never_enter_the_average() {
        let g = grid(7, 7, |c, r| if c == 1 && r == 1 { f32::NAN } else { 7.0 });
        let d = downsample(&g);
        // Coarse samples 0 and 1 on each axis see fine sample 1 through the filter.
        for j in 0..d.rows {
            for i in 0..d.cols {
                assert_eq!(d.at(i, j).is_nan(), i < 2 && j < 2, "({i}, {j})");
                assert!(d.at(i, j).is_nan() || d.at(i, j) == 7.0);
            }
        }
        // Every valid coarse cell lies over valid fine cells only.
        for r in 0..d.rows - 1 {
            for c in 0..d.cols - 1 {
                if d.cell_valid(c, r) {
                    for fr in 2 * r..2 * r + 2 {
                        for fc in 2 * c..2 * c + 2 {
                            assert!(g.cell_valid(fc, fr));
                        }
                    }
                }
            }
        }
        let all_void = grid(4, 4, |_, _| f32::NAN);
        assert!(downsample(&all_void).samples.iter().all(|z| z.is_nan()));
    }

    #[test]
    fn pyramid_stops_when_one_kernel_covers() {
        let g = Arc::new(grid(200, 90, |c, r| (c * r) as f32));
        let levels = build(g, 28);
        let last = levels.last().unwrap();
        assert!(last.cells()[0] <= 28 && last.cells()[1] <= 28);
        let before = &levels[levels.len() - 2];
        assert!(before.cells()[0] > 28 || before.cells()[1] > 28);
    }
}
