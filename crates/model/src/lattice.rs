//! Sample lattices: which surveys sample the same points of the plane.
//!
//! Tiled products (SRTM and Copernicus cells, the tiles of a lidar campaign) put their samples
//! on one lattice: same orientation, same spacing, and origins a whole number of steps apart.
//! Where such tiles meet, the cell between the last sample of one and the first of the next
//! belongs to neither, and only the union of their samples can interpolate across it. This
//! module names the lattice of a grid and gives every lattice point a canonical integer index,
//! the same whichever survey of the lattice it is computed from, so that patches of different
//! surveys can be laid out on one tiling.

use super::grid::Georef;

/// Relative tolerance on steps and angles for two grids to share a lattice: far above the
/// noise of georeferences written as decimal degrees or metres, far below any real difference.
const STEP_TOL: f64 = 1e-9;
/// Tolerance on the phase, in cells.
const PHASE_TOL: f64 = 1e-6;

/// The lattice a grid's samples lie on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lattice {
    /// Angle of the column axis, as in [`Georef::theta`].
    pub theta: f64,
    /// The row axis's own angle, for skewed or mirrored grids (see [`Georef::row_theta`]).
    pub row_theta: Option<f64>,
    /// Spacing along each axis, as in [`Georef::step`].
    pub step: [f64; 2],
    /// Where the lattice sits along each axis, as a fraction of a step in [10⁻⁶, 1 − 10⁻⁶], or
    /// 0.
    phase: [f64; 2],
}

impl Lattice {
    /// The lattice a georeference's samples lie on.
    pub fn of(g: &Georef) -> Lattice {
        let p = axis_coords(g, g.origin);
        let phase = p.map(|x| {
            let f = x - x.floor();
            // A phase within the tolerance of a whole step is 0 exactly, so that two grids of
            // one lattice whose noise falls on either side of it get the same indices.
            if !(PHASE_TOL..=1.0 - PHASE_TOL).contains(&f) {
                0.0
            } else {
                f
            }
        });
        Lattice {
            theta: g.theta,
            row_theta: g.row_theta,
            step: g.step,
            phase,
        }
    }

    /// Whether two lattices have the same points.
    pub fn same(&self, o: &Lattice) -> bool {
        let close = |a: f64, b: f64| (a - b).abs() <= STEP_TOL * a.abs().max(b.abs());
        let angle = (self.theta - o.theta).rem_euclid(std::f64::consts::TAU);
        let angle_ok = angle <= STEP_TOL || std::f64::consts::TAU - angle <= STEP_TOL;
        let rows_ok = match (self.row_theta, o.row_theta) {
            (None, None) => true,
            (Some(a), Some(b)) => {
                let d = (a - b).rem_euclid(std::f64::consts::TAU);
                d <= STEP_TOL || std::f64::consts::TAU - d <= STEP_TOL
            }
            _ => false,
        };
        angle_ok
            && rows_ok
            && close(self.step[0], o.step[0])
            && close(self.step[1], o.step[1])
            && (0..2).all(|k| {
                let d = (self.phase[k] - o.phase[k]).abs();
                d <= PHASE_TOL || (1.0 - d) <= PHASE_TOL
            })
    }

    /// The canonical index of grid `g`'s sample (0, 0) on this lattice, which `g` must lie on.
    /// Sample (c, r) of `g` is lattice point `index + (c, r)`.
    pub fn index_of(&self, g: &Georef) -> [i64; 2] {
        let p = axis_coords(g, g.origin);
        [
            (p[0] - self.phase[0]).round() as i64,
            (p[1] - self.phase[1]).round() as i64,
        ]
    }
}

/// A point's coordinates along the grid's column and row axes, in steps, from the plane's
/// origin.
fn axis_coords(g: &Georef, p: [f64; 2]) -> [f64; 2] {
    g.coords(p)
}

/// The tile of `kernel` lattice cells that holds lattice index `i`, for any sign of `i`.
#[inline]
pub fn tile_of(i: i64, kernel: usize) -> i64 {
    i.div_euclid(kernel as i64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn neighbouring_tiles_share_a_lattice_and_agree_on_indices() {
        let step = 1.0 / 3600.0;
        let a = Georef::north_up([-119.0 + 0.5 * step, 35.0 - 0.5 * step], [step, step]);
        // The cell to the east, and a crop of it 17 samples in.
        let b = Georef::north_up([-118.0 + 0.5 * step, 35.0 - 0.5 * step], [step, step]);
        let c = Georef::north_up(b.to_world(17.0, 5.0), [step, step]);
        let la = Lattice::of(&a);
        assert!(la.same(&Lattice::of(&b)) && la.same(&Lattice::of(&c)));
        let ia = la.index_of(&a);
        let ib = la.index_of(&b);
        let ic = Lattice::of(&c).index_of(&c);
        assert_eq!(ib[0] - ia[0], 3600);
        assert_eq!(ib[1], ia[1]);
        assert_eq!([ic[0] - ib[0], ic[1] - ib[1]], [17, 5]);
        // Half a step off, or another spacing, is another lattice.
        let d = Georef::north_up(a.to_world(0.5, 0.0), [step, step]);
        assert!(!la.same(&Lattice::of(&d)));
        let e = Georef::north_up(a.origin, [3.0 * step, 3.0 * step]);
        assert!(!la.same(&Lattice::of(&e)));
    }

    #[test]
    fn a_phase_next_to_zero_is_one_phase() {
        let a = Georef::north_up([1e-12, 0.0], [1.0, 1.0]);
        let b = Georef::north_up([-1e-12 + 5.0, 3.0], [1.0, 1.0]);
        let (la, lb) = (Lattice::of(&a), Lattice::of(&b));
        assert!(la.same(&lb));
        // Rows run south, so a point 3 units north is 3 rows before.
        assert_eq!(la.index_of(&b), [5, -3]);
        assert_eq!(tile_of(-1, 28), -1);
        assert_eq!(tile_of(27, 28), 0);
    }
}
