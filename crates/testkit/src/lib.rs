//! Scenes the tests and the bench share, made from a real survey's grid: degraded copies of
//! it (blurred, shifted, noisy, offset) and the cases where methods break (a cliff, spikes,
//! voids, a rotation). Kept out of the daemon and of the core: they make test data, and serve
//! no request.

pub mod changes;
pub mod copies;
pub mod degrade;
pub mod fixtures;
pub mod s3;
pub mod widened;

use patchwork_core::geom::rng;
use patchwork_core::model::grid::Grid;

/// The four cases where a method breaks, from a crop `g` of a real survey: a 400 m cliff down
/// its middle, spikes and pits every 997 samples, holes of 1 to 12 samples across (one for every
/// 3,000 samples), and the crop turned 25°.
pub fn stability_cases(g: &Grid) -> Vec<(&'static str, Grid)> {
    let mut cliff = g.clone();
    for (k, z) in cliff.samples.iter_mut().enumerate() {
        if k % cliff.cols >= cliff.cols / 2 {
            *z += 400.0;
        }
    }
    let mut spikes = g.clone();
    for (k, z) in spikes.samples.iter_mut().enumerate() {
        match k % 997 {
            0 => *z += 1500.0,
            500 => *z -= 800.0,
            _ => {}
        }
    }
    // Holes of 1 to 12 samples across, one for every 3,000 samples.
    let mut voids = g.clone();
    let mut next = rng::uniform(44);
    for _ in 0..(g.cols * g.rows / 3000).max(1) {
        let (cx, cy) = (next() * g.cols as f64, next() * g.rows as f64);
        let r = 0.5 + next() * 5.5;
        for row in (cy - r).max(0.0) as usize..((cy + r).ceil() as usize).min(g.rows) {
            for col in (cx - r).max(0.0) as usize..((cx + r).ceil() as usize).min(g.cols) {
                if (col as f64 - cx).hypot(row as f64 - cy) <= r {
                    voids.samples[row * g.cols + col] = f32::NAN;
                }
            }
        }
    }
    vec![
        ("cliff", cliff),
        ("spikes", spikes),
        ("voids", voids),
        ("rotated", g.turned(25.0)),
    ]
}
