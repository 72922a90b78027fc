//! Copies of a real survey of the kinds that misregistered products, resampled mosaics and old
//! digitised maps resemble: blurred, shifted, both, with noise, offset in height, and coarser.
//! Each knows how its content lies against the original's, so that what the store finds can
//! be checked against the truth. The bench charts what the store makes of each beside the
//! original; the tests hold the store to it.

use patchwork_core::model::coreg::blurred;
use patchwork_core::model::grid::Grid;

/// One copy of a grid, and where its content lies against the original's.
#[derive(Clone, Debug)]
pub struct Copy {
    /// What was done to make it, for messages.
    pub label: &'static str,
    /// The copy's samples and georeference.
    pub grid: Grid,
    /// How far the content moved, in the original's cells (columns right, rows down).
    pub shift_px: [f64; 2],
    /// Height added, metres.
    pub dz: f64,
}

/// The copies the store must not be fooled by, every one made from `g`:
/// Gaussian blurs of σ = 1, 2 and 3 cells; shifts of half a cell, of 2.5 and 1.5, and of 5
/// and −2 whole cells; a blur of 2 shifted by (3.5, 1.5); the same with noise of σ = 2 m; a
/// vertical offset of 30 m; and every second and every third sample.
pub fn standard(g: &Grid) -> Vec<Copy> {
    let plain = |label, grid| Copy {
        label,
        grid,
        shift_px: [0.0, 0.0],
        dz: 0.0,
    };
    let moved = |label, grid, shift_px| Copy {
        label,
        grid,
        shift_px,
        dz: 0.0,
    };
    vec![
        plain("blur σ1", blurred(g, 1.0)),
        plain("blur σ2", blurred(g, 2.0)),
        plain("blur σ3", blurred(g, 3.0)),
        moved("shift 0.5", shifted(g, [0.5, 0.0]), [0.5, 0.0]),
        moved("shift 2.5,1.5", shifted(g, [2.5, 1.5]), [2.5, 1.5]),
        moved("shift 5,-2", shifted(g, [5.0, -2.0]), [5.0, -2.0]),
        moved(
            "blur σ2 + shift 3.5,1.5",
            shifted(&blurred(g, 2.0), [3.5, 1.5]),
            [3.5, 1.5],
        ),
        moved(
            "blur σ2 + shift 3.5,1.5 + noise 2 m",
            noisy(&shifted(&blurred(g, 2.0), [3.5, 1.5]), 2.0, 5),
            [3.5, 1.5],
        ),
        Copy {
            label: "offset 30 m",
            grid: offset(g, 30.0),
            shift_px: [0.0, 0.0],
            dz: 30.0,
        },
        plain("every 2nd sample", g.decimated(2)),
        plain("every 3rd sample", g.decimated(3)),
    ]
}

/// The grid's content moved by `by` cells (columns right, rows down) on the same lattice:
/// each sample the original's surface at its position less `by`, bilinear, NaN where that
/// falls off the original's data. A whole-cell shift is an exact copy, moved.
pub fn shifted(g: &Grid, by: [f64; 2]) -> Grid {
    let mut out = vec![f32::NAN; g.samples.len()];
    for r in 0..g.rows {
        for c in 0..g.cols {
            if let Some(z) = g.bilinear_grid([c as f64 - by[0], r as f64 - by[1]]) {
                out[r * g.cols + c] = z as f32;
            }
        }
    }
    Grid::new(g.cols, g.rows, out, g.georef).expect("the shape of a grid")
}

/// Gaussian noise of standard deviation `sd` metres added to every valid sample,
/// reproducibly from `seed` (Box–Muller over a 64-bit LCG).
pub fn noisy(g: &Grid, sd: f64, seed: u64) -> Grid {
    let mut next = patchwork_core::geom::rng::uniform(seed);
    let samples = g
        .samples
        .iter()
        .map(|&z| {
            let (u1, u2) = (next().max(1e-12), next());
            z + (sd * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
        })
        .collect();
    Grid::new(g.cols, g.rows, samples, g.georef).expect("the shape of a grid")
}

/// Every valid height raised by `dz` metres.
pub fn offset(g: &Grid, dz: f64) -> Grid {
    let mut out = g.clone();
    for z in out.samples.iter_mut() {
        *z += dz as f32;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwork_core::model::grid::Georef;

    fn ramp() -> Grid {
        let s = (0..100).map(|k| (k % 10) as f32 * 2.0).collect();
        Grid::new(10, 10, s, Georef::north_up([0.0, 10.0], [1.0, 1.0])).unwrap()
    }

    #[test]
    fn a_shift_moves_the_content_and_leaves_voids_behind() {
        let g = ramp();
        let s = shifted(&g, [1.5, 0.0]);
        assert!(s.at(0, 3).is_nan() && s.at(1, 3).is_nan());
        // z = 2c, moved right by 1.5 cells: 2(c − 1.5).
        assert_eq!(s.at(4, 3), 5.0);
    }

    #[test]
    fn noise_and_offset_keep_voids() {
        let mut g = ramp();
        g.samples[5] = f32::NAN;
        assert!(noisy(&g, 2.0, 1).samples[5].is_nan());
        let o = offset(&g, 30.0);
        assert!(o.samples[5].is_nan() && o.samples[6] == g.samples[6] + 30.0);
    }
}
