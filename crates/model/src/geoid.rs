//! Heights carried between vertical CRSs: a survey whose heights are measured from another
//! geoid (or from the ellipsoid) than the store's is converted, sample by sample, before it
//! is modelled (see [`patchwork_crs::vertical`] for the relation H_B = H_A + N_A − N_B).
//!
//! A geoid model is a grid of undulations N over longitude and latitude, interpolated
//! bilinearly as PROJ does. Between its nodes the true N departs from that by about
//! h²/8 · |N''| along each axis: the largest second difference of the grid around the cells a
//! survey uses, an eighth of it per axis, is what the conversion can miss, and it is added to
//! the survey's ε.

use super::grid::Grid;
use patchwork_crs::vertical::VerticalCrs;
use patchwork_crs::{Crs, Reprojection};
use rayon::prelude::*;
use std::sync::Arc;

/// A geoid model: undulations in metres over a geographic grid.
#[derive(Debug)]
pub struct Geoid {
    /// The vertical CRS whose heights it relates to the ellipsoid.
    pub vertical: VerticalCrs,
    /// Undulations N, in metres; NaN where the model has none.
    pub grid: Grid,
    /// The grid's CRS: geographic.
    pub crs: Crs,
    /// Where the grid came from, for messages.
    pub source: String,
}

/// Why a geoid model cannot be made or used.
#[derive(Clone, Debug, thiserror::Error, PartialEq)]
pub enum GeoidError {
    /// The grid's CRS is not geographic.
    #[error("the geoid grid {grid} is in {crs}, not a geographic CRS")]
    NotGeographic {
        /// Where the grid came from.
        grid: String,
        /// The grid's CRS, as its label.
        crs: String,
    },
    /// A sample of the survey lies where the model has no undulation.
    #[error(
        "the survey reaches where the geoid grid {grid} has no undulation: it does not \
         cover the survey"
    )]
    Uncovered {
        /// Where the grid came from.
        grid: String,
    },
    /// The survey's positions could not be carried into the geoid's CRS.
    #[error(transparent)]
    Crs(#[from] patchwork_crs::CrsError),
}

impl Geoid {
    /// A geoid model from its grid of undulations, which must be in a geographic CRS.
    pub fn new(
        vertical: VerticalCrs,
        grid: Grid,
        crs: Crs,
        source: String,
    ) -> Result<Geoid, GeoidError> {
        if !crs.is_geographic() {
            return Err(GeoidError::NotGeographic {
                grid: source,
                crs: crs.label(),
            });
        }
        Ok(Geoid {
            vertical,
            grid,
            crs,
            source,
        })
    }

    /// N at a longitude and latitude, and what bilinear interpolation can miss there: an
    /// eighth of the largest second difference of the grid along each axis at the corners of
    /// the cell, summed over both axes.
    pub fn at(&self, lonlat: [f64; 2]) -> Option<(f64, f64)> {
        let g = &self.grid;
        let mut q = g.georef.to_grid(lonlat);
        // A global grid whose columns span 360° takes any longitude.
        let span = g.georef.step[0] * (g.cols - 1) as f64;
        if span >= 359.999 && (q[0] < 0.0 || q[0] > (g.cols - 1) as f64) {
            let per = 360.0 / g.georef.step[0];
            q[0] = q[0].rem_euclid(per);
        }
        let n = g.bilinear_grid(q)?;
        let ([c, r], _) = g.locate(q)?;
        let second = |c: usize, r: usize| -> f64 {
            let at = |c: isize, r: isize| -> Option<f64> {
                (c >= 0 && r >= 0 && (c as usize) < g.cols && (r as usize) < g.rows)
                    .then(|| g.at(c as usize, r as usize) as f64)
                    .filter(|v| !v.is_nan())
            };
            let (ci, ri) = (c as isize, r as isize);
            let mid = at(ci, ri).unwrap_or(0.0);
            let dx = match (at(ci - 1, ri), at(ci + 1, ri)) {
                (Some(a), Some(b)) => (a - 2.0 * mid + b).abs(),
                _ => 0.0,
            };
            let dy = match (at(ci, ri - 1), at(ci, ri + 1)) {
                (Some(a), Some(b)) => (a - 2.0 * mid + b).abs(),
                _ => 0.0,
            };
            (dx + dy) / 8.0
        };
        let e = [(c, r), (c + 1, r), (c, r + 1), (c + 1, r + 1)]
            .iter()
            .map(|&(a, b)| second(a, b))
            .fold(0.0f64, f64::max);
        Some((n, e))
    }
}

/// What a conversion did: the largest error it may add to a height.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Converted {
    /// The largest interpolation error the geoids may add to a height, in metres.
    pub error_m: f64,
}

/// Heights in metres carried from one vertical CRS to another: H_to = H_from + N_from − N_to,
/// with N of an ellipsoidal CRS 0 and that of a gravity-related one from its geoid model.
#[derive(Clone, Debug)]
pub struct Shift {
    /// The CRS heights are in.
    pub from: VerticalCrs,
    /// The CRS they are carried to.
    pub to: VerticalCrs,
    /// The model of `from`, None when it is ellipsoidal or the same surface as `to`.
    pub geoid_from: Option<Arc<Geoid>>,
    /// The model of `to`, None when it is ellipsoidal or the same surface as `from`.
    pub geoid_to: Option<Arc<Geoid>>,
}

impl Shift {
    /// Whether it leaves every height as it is: both CRSs measure from the same surface.
    pub fn is_identity(&self) -> bool {
        self.from.same_reference(&self.to)
    }

    /// Carries `heights` (metres; NaN stays NaN) at `positions` of `crs` from `from` to `to`,
    /// in place. Returns the largest interpolation error the geoids may add to one of them.
    pub fn apply(
        &self,
        heights: &mut [f32],
        positions: &[[f64; 2]],
        crs: &Crs,
    ) -> Result<Converted, GeoidError> {
        assert_eq!(heights.len(), positions.len(), "a position a height");
        if self.is_identity() {
            return Ok(Converted { error_m: 0.0 });
        }
        // Every geoid is geographic; one lattice from the positions' CRS to each geoid's
        // carries them there (its error, a few micrometres, is nothing beside a geoid's).
        let undulation = |geoid: Option<&Arc<Geoid>>| -> Result<Vec<(f64, f64)>, GeoidError> {
            let Some(geoid) = geoid else {
                return Ok(vec![(0.0, 0.0); positions.len()]);
            };
            let to_geo = Reprojection::new(crs, &geoid.crs)?;
            let lonlat = to_geo.map(positions);
            let uncovered = || GeoidError::Uncovered {
                grid: geoid.source.clone(),
            };
            lonlat
                .par_iter()
                .zip(&*heights)
                .map(|(p, z)| {
                    if z.is_nan() {
                        return Ok((0.0, 0.0));
                    }
                    geoid.at(*p).ok_or_else(uncovered)
                })
                .collect()
        };
        let (nf, nt) = (
            undulation(self.geoid_from.as_ref())?,
            undulation(self.geoid_to.as_ref())?,
        );
        let error_m = heights
            .par_iter_mut()
            .zip(nf.par_iter().zip(&nt))
            .map(|(z, (a, b))| {
                if z.is_nan() {
                    return 0.0;
                }
                *z = (*z as f64 + a.0 - b.0) as f32;
                a.1 + b.1
            })
            .reduce(|| 0.0, f64::max);
        Ok(Converted { error_m })
    }
}

/// Converts heights from `from` to `to` in place, for a grid in `crs`: H_to = H_from·unit +
/// N_from − N_to, with N of an ellipsoidal CRS 0 and `geoid(v)` the model of a
/// gravity-related one. Returns the largest interpolation error the geoids may add.
pub fn convert(
    grid: &mut Grid,
    crs: &Crs,
    from: &VerticalCrs,
    to: &VerticalCrs,
    geoid_from: Option<&Arc<Geoid>>,
    geoid_to: Option<&Arc<Geoid>>,
) -> Result<Converted, GeoidError> {
    let unit = from.unit_m();
    if unit != 1.0 {
        grid.samples.par_iter_mut().for_each(|z| {
            *z = (*z as f64 * unit) as f32;
        });
    }
    let shift = Shift {
        from: from.clone(),
        to: to.clone(),
        geoid_from: geoid_from.cloned(),
        geoid_to: geoid_to.cloned(),
    };
    if shift.is_identity() {
        return Ok(Converted { error_m: 0.0 });
    }
    let g = grid.georef;
    let cols = grid.cols;
    let positions: Vec<[f64; 2]> = (0..grid.rows)
        .into_par_iter()
        .flat_map_iter(|r| (0..cols).map(move |c| g.to_world(c as f64, r as f64)))
        .collect();
    shift.apply(&mut grid.samples, &positions, crs)
}
