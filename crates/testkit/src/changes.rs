//! Ground that changed between two surveys: pits and quarries, mounds and tips, a slope's mass
//! moved downhill, a retreating coast, a levelled platform, and (held back from development)
//! a trench. Each is drawn on a grid from a seed and returns the changed ground with the
//! change itself, sample by sample, so that a test knows which samples changed and by how
//! much. Resurveys of the changed ground are made on other lattices, with noise.

use crate::copies::noisy;
use crate::degrade::resampled_onto;
use patchwork_core::model::grid::Grid;

/// One kind of change.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A quarry: steep walls to a floor 15–60 m down.
    Pit,
    /// A tip: steep sides up to a top 10–40 m above the ground.
    Mound,
    /// A slide: a disc of slope lowered 10–30 m and the same volume laid down downhill.
    Slide,
    /// A coast or a bank cut back: a long band lowered 10–40 m, its floor flat.
    Coast,
    /// A platform levelled: a disc cut and filled to its mean height.
    Platform,
    /// A trench 4–8 samples wide and 8–25 m deep across the ground. Held back.
    Trench,
}

impl Kind {
    /// Every kind.
    pub const ALL: [Kind; 6] = [
        Kind::Pit,
        Kind::Mound,
        Kind::Slide,
        Kind::Coast,
        Kind::Platform,
        Kind::Trench,
    ];

    /// Whether the kind was kept out of development.
    pub fn held_back(self) -> bool {
        matches!(self, Kind::Trench)
    }

    /// Its name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Kind::Pit => "pit",
            Kind::Mound => "mound",
            Kind::Slide => "slide",
            Kind::Coast => "coast",
            Kind::Platform => "platform",
            Kind::Trench => "trench",
        }
    }
}

/// A change drawn on a grid.
pub struct Changed {
    /// What was done, in words.
    pub label: String,
    /// The ground after the change, on the grid's lattice (voids as they were).
    pub after: Grid,
    /// The change at each sample, metres (after less before; 0 where unchanged).
    pub delta: Vec<f32>,
}

/// Draws one change of `kind` on `g`, from `next` (uniform in [0, 1)), somewhere in its middle
/// half. Its height is drawn from the kind's range, and at least 1.5–2.5 times `least` (the
/// surveys' level of detection, so that a rough DEM's change is not all below it).
pub fn apply(kind: Kind, g: &Grid, least: f64, next: &mut impl FnMut() -> f64) -> Changed {
    let sized = |lo: f64, span: f64, next: &mut dyn FnMut() -> f64| {
        (lo + span * next()).max(least * (1.5 + next()))
    };
    let (cols, rows) = (g.cols as f64, g.rows as f64);
    let small = cols.min(rows);
    let centre = [cols * (0.3 + 0.4 * next()), rows * (0.3 + 0.4 * next())];
    let radius = (small * (0.05 + 0.07 * next())).max(7.0);
    let at = |c: usize, r: usize| [c as f64 - centre[0], r as f64 - centre[1]];
    // A wall's profile: 1 inside, falling to 0 over the outer fifth.
    let wall = |rho: f64| ((1.0 - rho) / 0.2).clamp(0.0, 1.0);
    let mut delta = vec![0f32; g.samples.len()];
    let label;
    match kind {
        Kind::Pit | Kind::Mound => {
            let (sign, h) = if kind == Kind::Pit {
                (-1.0, sized(15.0, 45.0, next))
            } else {
                (1.0, sized(10.0, 30.0, next))
            };
            for r in 0..g.rows {
                for c in 0..g.cols {
                    let d = at(c, r);
                    delta[r * g.cols + c] = (sign * h * wall(d[0].hypot(d[1]) / radius)) as f32;
                }
            }
            label = format!("{} {h:.0} m, radius {radius:.0} samples", kind.name());
        }
        Kind::Slide => {
            // Downhill at the centre, from the grid's own slope there.
            let (c0, r0) = (centre[0] as usize, centre[1] as usize);
            let z = |c: usize, r: usize| g.at(c.min(g.cols - 1), r.min(g.rows - 1)) as f64;
            let (gx, gy) = (
                z(c0 + 2, r0) - z(c0.saturating_sub(2), r0),
                z(c0, r0 + 2) - z(c0, r0.saturating_sub(2)),
            );
            let n = gx.hypot(gy);
            let down = if n.is_finite() && n > 0.0 {
                [-gx / n, -gy / n]
            } else {
                [1.0, 0.0]
            };
            let h = sized(10.0, 20.0, next);
            let run = 1.8 * radius;
            for r in 0..g.rows {
                for c in 0..g.cols {
                    let d = at(c, r);
                    let scar = wall(d[0].hypot(d[1]) / radius);
                    let e = [d[0] - run * down[0], d[1] - run * down[1]];
                    let toe = wall(e[0].hypot(e[1]) / radius);
                    delta[r * g.cols + c] = (h * (toe - scar)) as f32;
                }
            }
            label = format!("slide {h:.0} m over {run:.0} samples, radius {radius:.0}");
        }
        Kind::Coast | Kind::Trench => {
            let angle = std::f64::consts::PI * next();
            let dir = [angle.cos(), angle.sin()];
            let (half_width, h, half_length) = if kind == Kind::Coast {
                (radius * 0.6, sized(10.0, 30.0, next), small * 0.3)
            } else {
                (2.0 + 2.0 * next(), sized(8.0, 17.0, next), small * 0.35)
            };
            for r in 0..g.rows {
                for c in 0..g.cols {
                    let d = at(c, r);
                    let along = d[0] * dir[0] + d[1] * dir[1];
                    let across = -d[0] * dir[1] + d[1] * dir[0];
                    let off = across.abs() / half_width;
                    let beyond = ((along.abs() - half_length) / half_width).max(0.0);
                    delta[r * g.cols + c] = (-h * wall(off.hypot(beyond))) as f32;
                }
            }
            label = format!(
                "{} {h:.0} m deep, {:.0} samples wide, {:.0} long",
                kind.name(),
                2.0 * half_width,
                2.0 * half_length
            );
        }
        Kind::Platform => {
            let inside = |c: usize, r: usize| {
                let d = at(c, r);
                d[0].hypot(d[1]) <= radius
            };
            let (mut sum, mut n) = (0.0, 0usize);
            for r in 0..g.rows {
                for c in 0..g.cols {
                    let z = g.at(c, r);
                    if inside(c, r) && !z.is_nan() {
                        sum += z as f64;
                        n += 1;
                    }
                }
            }
            let level = sum / n.max(1) as f64;
            for r in 0..g.rows {
                for c in 0..g.cols {
                    let z = g.at(c, r) as f64;
                    if inside(c, r) && !z.is_nan() {
                        delta[r * g.cols + c] = (level - z) as f32;
                    }
                }
            }
            label = format!("platform levelled at {level:.0} m, radius {radius:.0} samples");
        }
    }
    let samples = g
        .samples
        .iter()
        .zip(&delta)
        .map(|(z, d)| if z.is_nan() { *z } else { z + d })
        .collect();
    let after = Grid::new(g.cols, g.rows, samples, g.georef).expect("the same shape");
    Changed {
        label,
        after,
        delta,
    }
}

/// A resurvey of `after` (on `g`'s lattice): on the same lattice, on one 1.5 or 2 times
/// coarser, or on one moved by a fraction of a cell; with 0.2–1 m of fresh noise. Returns the
/// label and the grid.
pub fn resurvey(after: &Grid, next: &mut impl FnMut() -> f64, seed: u64) -> (String, Grid) {
    let sd = 0.2 + 0.8 * next();
    let pick = next();
    let (label, grid) = if pick < 0.4 {
        ("the same lattice".to_string(), after.clone())
    } else if pick < 0.7 {
        let f = if next() < 0.5 { 1.5 } else { 2.0 };
        let mut georef = after.georef.coarsened(f);
        let (cols, rows) = (
            ((after.cols - 1) as f64 / f) as usize + 1,
            ((after.rows - 1) as f64 / f) as usize + 1,
        );
        georef.origin = after.georef.to_world(0.25, 0.25);
        let onto = Grid::new(cols, rows, vec![0.0; cols * rows], georef).expect("a shape");
        (
            format!("a lattice {f}× coarser"),
            resampled_onto(after, &onto, false),
        )
    } else {
        let (dx, dy) = (0.2 + 0.6 * next(), 0.2 + 0.6 * next());
        let mut georef = after.georef;
        georef.origin = after.georef.to_world(dx, dy);
        let onto = Grid::new(
            after.cols - 1,
            after.rows - 1,
            vec![0.0; (after.cols - 1) * (after.rows - 1)],
            georef,
        )
        .expect("a shape");
        (
            format!("a lattice moved by ({dx:.2}, {dy:.2}) cells"),
            resampled_onto(after, &onto, true),
        )
    };
    (format!("{label}, noise {sd:.2} m"), noisy(&grid, sd, seed))
}
