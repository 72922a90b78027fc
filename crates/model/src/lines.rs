//! A periodic artefact: a line in one survey's spectrum that the other's lacks.
//!
//! Stripes from a scanner's lines, a sensor's pattern or a mosaic's seams add a sinusoid to
//! the ground, and the pair's differences then gather at one frequency. Neither the tests of
//! prediction nor those of detail see it: a filter of either side explains the other about
//! as well (one notched, the other not), and a stripe longer than the bands of detail reach,
//! or one that dwarfs the ground's own relief there, leaves every band undecided.
//!
//! What decides it is the shape of each side's spectrum where the differences gather. Natural
//! ground has a smooth spectrum (about a power law of the frequency, with no isolated lines),
//! and a filter can take a band away but cannot add one. So at the line's frequency the side
//! whose spectrum stands out from its own neighbourhood, above it (a line added) or below it
//! (a notch cut), is the one that was altered, and the other, smooth there, is the original.
//! Where both stand out (ground that is itself periodic: dunes, terraces, rows of a field),
//! or neither, the test says nothing.
//!
//! The neighbourhood is the ring of the spectrum at the same radius: its median power, which
//! a line's few bins do not move. The spectra are of each side's samples over the largest
//! rectangle at the overlap's middle (at most [`MOST_SIDE`] samples a side, at about the coarser survey's
//! cell), each less its own least-squares plane and tapered by a Hann window, so that a trend
//! or the window's edges spread no power over the rings.

use super::coreg::{Carry, Placement};
use super::detail::block_mean;
use super::grid::{Georef, Grid};
use patchwork_geom::Aabb;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;

/// The largest side of the rectangle analysed, in samples: a stripe 40 cells long then
/// shows as a line 12 bins out, clear of the trend's lowest bins.
pub const MOST_SIDE: usize = 512;
/// The least side: under it the rings hold too few bins for a median.
const LEAST_SIDE: usize = 48;
/// The least bins a ring's median is taken over, beside the line's own.
const LEAST_RING: usize = 32;
/// Rings nearer the centre than this, in bins, are a trend's or the window's: never a line.
const LEAST_RADIUS: f64 = 3.0;
/// A line of the differences must hold at least this share of their power (past the lowest
/// bins): a copy blurred and striped differs from its original by its stripes and by what
/// the blur took, stripes 4 m high beside a cut at a fifth of the Nyquist frequency holding
/// 15% ...
pub const LEAST_SHARE: f64 = 0.05;
/// ... and stand this many times above its ring's mean.
pub const LEAST_LINE: f64 = 20.0;
/// A side that holds the line's content and stands out from its ring at least this many
/// times, and this many times more than the other stands out from its own, had it added
/// (nine bins of a smooth spectrum scatter about their ring's mean by a factor under 2); the
/// other must not fall under its inverse (a notch in ground periodic in both).
pub const ALTERED: f64 = 5.0;

/// The strongest line of a pair's differences, and how each side's spectrum stands there.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Line {
    /// Its wavelength, in the reference plane's units.
    pub period: f64,
    /// The direction its crests advance in, degrees anticlockwise from the reference plane's
    /// x axis, in [0, 180).
    pub angle: f64,
    /// Its share of the differences' power past the lowest rings.
    pub share: f64,
    /// How many times the differences' power there stands above its ring's median.
    pub strength: f64,
    /// The same for the reference's spectrum, then the other's: over 1 where it holds a line,
    /// under 1 where it lacks what its ring holds.
    pub prominence: [f64; 2],
    /// The power of the reference's spectrum there, then the other's, over the differences':
    /// the side that holds the line's content has the more.
    pub held: [f64; 2],
}

impl Line {
    /// Which side was altered: Some(true) for the reference, Some(false) for the other. The
    /// side that holds the line's content had it added where it stands out from its ring,
    /// and from the other's standing in its own, by [`ALTERED`] times, and the other is not
    /// cut away there. None where the differences hold no clear line, or the spectra do not
    /// tell: ground that stands out at that frequency in both (a ridge's direction, dunes)
    /// holds weak stripes as much in one side as in the other.
    ///
    /// A notch (a line cut from one side) is not decided: the holder smooth there and the
    /// other far under its ring is also what weak stripes on rough ground look like where the
    /// ground happens to be faint at their frequency, and on drawn copies that rule blamed an
    /// original.
    pub fn altered(&self) -> Option<bool> {
        if self.share < LEAST_SHARE || self.strength < LEAST_LINE {
            return None;
        }
        // The side that holds the line's content, and how each stands against its ring.
        let reference = self.held[0] >= self.held[1];
        let [r, o] = self.prominence;
        let (holder, other) = if reference { (r, o) } else { (o, r) };
        (holder >= ALTERED * other.max(1.0) && other >= 1.0 / ALTERED).then_some(reference)
    }

    /// How far the altered side stands out from its ring, as a factor of 1 or more.
    pub fn standing(&self) -> f64 {
        let f = |p: f64| if p >= 1.0 { p } else { 1.0 / p };
        f(self.prominence[0]).max(f(self.prominence[1]))
    }
}

/// Both sides' samples over the rectangle at the overlap's middle, as the spectra take them:
/// the reference's block means at about the coarser survey's cell, and the other read at
/// the same points through the placement. NaN where either has no sample.
pub struct Samples {
    /// The reference's samples, row-major.
    pub reference: Vec<f64>,
    /// The other's, at the same points.
    pub other: Vec<f64>,
    /// Columns.
    pub nx: usize,
    /// Rows.
    pub ny: usize,
    /// Where the samples lie.
    pub georef: Georef,
}

/// The samples of `reference` and of `other` (read at `to_other(place.forth(p))` for the
/// reference's point p) over the largest rectangle at the middle of `bounds`, with `cell` the
/// coarser survey's cell in the reference plane's units. None where the overlap is too small,
/// or holds samples of both over less than half the rectangle.
pub fn read(
    reference: &Grid,
    other: &Grid,
    to_other: Carry,
    place: &Placement,
    bounds: &Aabb,
    cell: f64,
) -> Option<Samples> {
    let rect = reference.shape().rect_over(bounds)?;
    let own = reference.georef.step[0].max(reference.georef.step[1]);
    // At about the coarser survey's cell: the finer's detail past it is not in the other.
    let k = (cell / own).round().max(1.0) as usize;
    let (nx, ny) = (
        (rect.cols() / k).min(MOST_SIDE),
        (rect.rows() / k).min(MOST_SIDE),
    );
    if nx.min(ny) < LEAST_SIDE {
        return None;
    }
    // The rectangle at the overlap's middle.
    let (c0, r0) = (
        rect.c0 + (rect.cols() - nx * k) / 2,
        rect.r0 + (rect.rows() - ny * k) / 2,
    );
    let a = block_mean(&reference.window(c0, r0, nx * k, ny * k), k);
    let mut za = vec![f64::NAN; nx * ny];
    let mut zb = vec![f64::NAN; nx * ny];
    for r in 0..ny {
        for c in 0..nx {
            let z = a.at(c, r);
            let p = a.georef.to_world(c as f64, r as f64);
            if z.is_nan() || !bounds.contains_point(p) {
                continue;
            }
            let Some(h) = to_other(place.forth(p)).and_then(|q| other.bilinear(q)) else {
                continue;
            };
            za[r * nx + c] = z as f64;
            zb[r * nx + c] = h;
        }
    }
    let valid = za.iter().filter(|z| !z.is_nan()).count();
    if 2 * valid < nx * ny {
        return None;
    }
    Some(Samples {
        reference: za,
        other: zb,
        nx,
        ny,
        georef: a.georef,
    })
}

/// The strongest line of the differences of two sides' samples ([`read`]).
pub fn line(s: &Samples) -> Option<Line> {
    let (za, zb, nx, ny) = (&s.reference, &s.other, s.nx, s.ny);
    let fa = spectrum(za, nx, ny);
    let fb = spectrum(zb, nx, ny);
    let power = |f: &[Complex<f64>]| f.iter().map(|z| z.norm_sqr()).collect::<Vec<f64>>();
    let fd: Vec<Complex<f64>> = fb.iter().zip(&fa).map(|(b, a)| b - a).collect();
    let (pa, pb, pd) = (power(&fa), power(&fb), power(&fd));
    // Signed bins, then each bin's ring: its frequency's radius, in bins of the longer side.
    let signed = |i: usize, n: usize| {
        if i <= n / 2 {
            i as f64
        } else {
            i as f64 - n as f64
        }
    };
    let long = nx.max(ny);
    let ring = |u: usize, v: usize| {
        let (fx, fy) = (signed(u, nx) / nx as f64, signed(v, ny) / ny as f64);
        (fx.hypot(fy) * long as f64).round() as usize
    };
    let rings = long / 2 + 1;
    // The line: the strongest bin of the differences past the lowest bins.
    let mut total = 0.0;
    let mut best = (0.0, 0usize, 0usize);
    for v in 0..ny {
        for u in 0..nx {
            if signed(u, nx).hypot(signed(v, ny)) < LEAST_RADIUS || ring(u, v) >= rings {
                continue;
            }
            let p = pd[v * nx + u];
            total += p;
            if p > best.0 {
                best = (p, u, v);
            }
        }
    }
    if total <= 0.0 {
        return None;
    }
    let (_, u, v) = best;
    // Whether a bin lies in the line's lobe or its twin's, two bins each way: no part of
    // the neighbourhood it is measured against.
    let near = |a: usize, b: usize| {
        let d = |x: usize, y: i64, n: usize| {
            let e = (x as i64 - y).rem_euclid(n as i64);
            e.min(n as i64 - e)
        };
        let (su, sv) = (u as i64, v as i64);
        (d(a, su, nx) <= 2 && d(b, sv, ny) <= 2) || (d(a, -su, nx) <= 2 && d(b, -sv, ny) <= 2)
    };
    let medians = |p: &[f64]| -> Vec<f64> {
        let mut by: Vec<Vec<f64>> = vec![Vec::new(); rings];
        for b in 0..ny {
            for a in 0..nx {
                let r = ring(a, b);
                if r < rings && !near(a, b) {
                    by[r].push(p[b * nx + a]);
                }
            }
        }
        // Rings of a long, narrow rectangle hold few bins: each is widened by its
        // neighbours until it holds enough for a median.
        (0..rings)
            .map(|r| {
                let mut w = 0;
                let mut x: Vec<f64> = by[r].clone();
                while x.len() < LEAST_RING && w < rings {
                    w += 1;
                    if r >= w {
                        x.extend(&by[r - w]);
                    }
                    if r + w < rings {
                        x.extend(&by[r + w]);
                    }
                }
                if x.is_empty() {
                    return 0.0;
                }
                // A bin's power about its mean is exponential, whose median is ln 2 of the
                // mean: the median over ln 2 is the mean, which the line does not move.
                let m = x.len() / 2;
                *x.select_nth_unstable_by(m, f64::total_cmp).1 / std::f64::consts::LN_2
            })
            .collect()
    };
    let (ma, mb, md) = (medians(&pa), medians(&pb), medians(&pd));
    // A line's power spreads over the Hann window's main lobe, ±1 bin each way: summed there,
    // against its rings' means over the same bins.
    let lobe = |p: &[f64], m: &[f64]| -> (f64, f64) {
        let (mut s, mut e) = (0.0, 0.0);
        for dv in -1i64..=1 {
            for du in -1i64..=1 {
                let uu = (u as i64 + du).rem_euclid(nx as i64) as usize;
                let vv = (v as i64 + dv).rem_euclid(ny as i64) as usize;
                s += p[vv * nx + uu];
                e += m[ring(uu, vv).min(rings - 1)];
            }
        }
        (s, e)
    };
    let stand = |p: &[f64], m: &[f64]| {
        let (s, e) = lobe(p, m);
        if e > 0.0 {
            s / e
        } else if s > 0.0 {
            f64::INFINITY
        } else {
            1.0
        }
    };
    // The line's power in the differences; both halves of the spectrum hold it (the samples
    // are real).
    let line_power = lobe(&pd, &md).0;
    let share = 2.0 * line_power / total;
    // Cycles per plane unit along the columns and down the rows; the rows run clockwise
    // from the columns.
    let step = s.georef.step;
    let (fx, fy) = (
        signed(u, nx) / (nx as f64 * step[0]),
        signed(v, ny) / (ny as f64 * step[1]),
    );
    let held = |p: &[f64]| {
        if line_power > 0.0 {
            lobe(p, &md).0 / line_power
        } else {
            1.0
        }
    };
    Some(Line {
        period: 1.0 / fx.hypot(fy),
        angle: (s.georef.theta.to_degrees() - fy.atan2(fx).to_degrees()).rem_euclid(180.0),
        share: share.min(1.0),
        strength: stand(&pd, &md),
        prominence: [stand(&pa, &ma), stand(&pb, &mb)],
        held: [held(&pa), held(&pb)],
    })
}

/// The 2-D spectrum of an nx × ny field (NaN where there is no sample), less its own
/// least-squares plane and tapered by a Hann window; gaps count as the plane.
pub(crate) fn spectrum(z: &[f64], nx: usize, ny: usize) -> Vec<Complex<f64>> {
    let plane = fit_plane(z, nx, ny);
    let hann = |n: usize| -> Vec<f64> {
        (0..n)
            .map(|i| 0.5 - 0.5 * (std::f64::consts::TAU * i as f64 / (n - 1) as f64).cos())
            .collect()
    };
    let (hx, hy) = (hann(nx), hann(ny));
    let mut data: Vec<Complex<f64>> = (0..nx * ny)
        .map(|i| {
            let (c, r) = (i % nx, i / nx);
            let v = z[i];
            let d = if v.is_nan() {
                0.0
            } else {
                v - (plane[0] + plane[1] * c as f64 + plane[2] * r as f64)
            };
            Complex::new(d * hx[c] * hy[r], 0.0)
        })
        .collect();
    fft2(&mut data, nx, ny, false);
    data
}

/// The 2-D discrete Fourier transform of an nx × ny field, row-major, in place: along the
/// rows, then down the columns. Unnormalised both ways: an inverse after a forward gives the
/// field times nx · ny.
pub fn fft2(data: &mut [Complex<f64>], nx: usize, ny: usize, inverse: bool) {
    let mut planner = FftPlanner::new();
    let mut plan = |n| {
        if inverse {
            planner.plan_fft_inverse(n)
        } else {
            planner.plan_fft_forward(n)
        }
    };
    let (along, down) = (plan(nx), plan(ny));
    for row in data.chunks_exact_mut(nx) {
        along.process(row);
    }
    let mut col = vec![Complex::new(0.0, 0.0); ny];
    for c in 0..nx {
        for r in 0..ny {
            col[r] = data[r * nx + c];
        }
        down.process(&mut col);
        for r in 0..ny {
            data[r * nx + c] = col[r];
        }
    }
}

/// The least-squares plane `a + b·c + d·r` through the valid samples.
fn fit_plane(z: &[f64], nx: usize, ny: usize) -> [f64; 3] {
    let mut m = [[0.0f64; 3]; 3];
    let mut y = [0.0f64; 3];
    for (i, &v) in z.iter().enumerate() {
        if v.is_nan() {
            continue;
        }
        // Centred, so that the sums stay well conditioned.
        let x = [
            1.0,
            (i % nx) as f64 - nx as f64 / 2.0,
            (i / nx) as f64 - ny as f64 / 2.0,
        ];
        for a in 0..3 {
            y[a] += x[a] * v;
            for b in 0..3 {
                m[a][b] += x[a] * x[b];
            }
        }
    }
    let Some(s) = super::coreg::solve(m, y) else {
        return [0.0; 3];
    };
    let (hx, hy) = (nx as f64 / 2.0, ny as f64 / 2.0);
    [s[0] - s[1] * hx - s[2] * hy, s[1], s[2]]
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::grid::Georef;

    /// Rough ground of a power-law spectrum (power as f⁻³, random in each bin, as real
    /// relief's is), from a seed.
    pub(crate) fn ground(n: usize, seed: u64) -> Grid {
        let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        let mut next = move || {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((x >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let freq = |i: usize| {
            if i <= n / 2 {
                i as f64
            } else {
                i as f64 - n as f64
            }
        };
        let mut data: Vec<Complex<f64>> = (0..n * n)
            .map(|i| {
                let f = freq(i % n).hypot(freq(i / n)).max(1.0);
                // A Gaussian draw of each part, scaled to the spectrum's amplitude.
                let (u1, u2) = (next(), next());
                let rad = (-2.0 * u1.ln()).sqrt();
                let t = std::f64::consts::TAU * u2;
                Complex::new(rad * t.cos(), rad * t.sin()) * f.powf(-1.5) * 400.0
            })
            .collect();
        fft2(&mut data, n, n, true);
        let samples = data.iter().map(|z| (z.re / n as f64) as f32).collect();
        Grid::new(
            n,
            n,
            samples,
            Georef {
                origin: [0.0, 0.0],
                theta: 0.0,
                step: [1.0, 1.0],
                row_theta: None,
            },
        )
        .unwrap()
    }

    fn striped(g: &Grid, amp: f64, period: f64, angle: f64) -> Grid {
        let (s, c) = angle.to_radians().sin_cos();
        let mut out = g.clone();
        for r in 0..g.rows {
            for col in 0..g.cols {
                let t = (col as f64 * c + r as f64 * s) / period;
                out.samples[r * g.cols + col] += (amp * (std::f64::consts::TAU * t).sin()) as f32;
            }
        }
        out
    }

    fn line(a: &Grid, b: &Grid) -> Line {
        let same = |p: [f64; 2]| Some(p);
        let bounds = a.world_bounds();
        let s = read(a, b, &same, &Placement::shift([0.0, 0.0]), &bounds, 1.0).unwrap();
        super::line(&s).unwrap()
    }

    /// Stripes of any direction and period are found in the side that holds them, whichever
    /// side is the reference, and their period and direction are measured.
    #[test]
    fn stripes_are_found_in_the_side_that_holds_them() {
        for (seed, period, angle) in [(1, 5.0, 0.0), (2, 17.0, 90.0), (3, 31.0, 33.0)] {
            let g = ground(200, seed);
            let s = striped(&g, 2.0, period, angle);
            let l = line(&g, &s);
            println!("{l:?}");
            assert_eq!(l.altered(), Some(false), "{l:?}");
            assert!((l.period - period).abs() < 0.1 * period, "{l:?}");
            // The stripes' angle is from the columns toward the rows, which run clockwise.
            let da = (l.angle + angle).rem_euclid(180.0);
            assert!(da.min(180.0 - da) < 10.0, "{l:?}");
            assert_eq!(line(&s, &g).altered(), Some(true));
        }
    }

    /// Noise added, a copy shifted by a cell, and ground that is itself periodic in both
    /// hold no line that either side alone stands out in.
    #[test]
    fn noise_shifts_and_periodic_ground_hold_no_line() {
        let g = ground(200, 7);
        let mut x = 9u64;
        let noise: Vec<f32> = (0..g.samples.len())
            .map(|_| {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
                ((x >> 40) as f64 / (1u64 << 24) as f64 - 0.5) as f32
            })
            .collect();
        let mut noisy = g.clone();
        for (z, e) in noisy.samples.iter_mut().zip(&noise) {
            *z += e;
        }
        assert_eq!(line(&g, &noisy).altered(), None);
        let shifted = g.window(1, 0, 199, 200);
        let mut moved = g.window(0, 0, 199, 200);
        moved.samples.clone_from(&shifted.samples);
        assert_eq!(line(&g.window(0, 0, 199, 200), &moved).altered(), None);
        // Dunes in both, one copy noisy.
        let dunes = striped(&g, 3.0, 12.0, 20.0);
        let mut noisy_dunes = dunes.clone();
        for (z, e) in noisy_dunes.samples.iter_mut().zip(&noise) {
            *z += e;
        }
        assert_eq!(line(&dunes, &noisy_dunes).altered(), None);
    }
}
