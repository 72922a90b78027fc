//! Whether one survey is a linear filter of the other: the pair's transfer function, ring by
//! ring of the spectrum.
//!
//! A filter scales each frequency of its input by a gain and adds nothing: where its gain
//! falls, the copy holds less power than the original, and what it holds is still the
//! original's, so the two stay coherent (`|Sₐ_b|² / (Sₐ S_b)` near 1). Noise does the
//! opposite: a survey that is the other plus noise holds more power, and the other's share of
//! it is exactly their coherence, so where one holds half the power of the other because of
//! the other's noise, their coherence is a half too. The tests of detail cannot tell these
//! apart where a filter's gain is 1 or 0 within a band (a hard low-pass in the frequency
//! domain): the copy's band is then all shared, and the original's excess reads as noise.
//! Ring by ring they can:
//!
//! - **A coherent loss**: rings where one side holds at most [`LOSS`] of the other's power,
//!   and the two are more coherent than [`COHERENT`] and than twice that ratio. No amount of
//!   noise in the other makes that; a filter's slope does (a Butterworth's, a Gaussian's, a
//!   resampling's).
//! - **An edge**: one side's power falls [`EDGE`] times more than the other's within two
//!   rings (the window's main lobe), from ring [`FIRST_EDGE`] out, holding over [`LOSS`]² of
//!   the other's power before and under it after, while the other side has no such fall of
//!   [`SMOOTH`]. Ground's spectrum and any noise's are smooth: a power law as steep as
//!   ground's falls by at most 5 over two rings from the fourth out. Only a filter in the
//!   frequency domain cuts a spectrum off, and past its cut the copy holds nothing the
//!   coherence could measure.
//!
//! The spectra are Welch's: the mean over tiles of [`TILE`]² samples, overlapping by half, of
//! the samples the line's spectra take ([`lines::read`]), each tile less its own plane and
//! under a Hann window. Only tiles with no gap count, so a void's cliff is in neither. Each
//! ring's power is its bins' median (a stripe's few bins do not move it), and its coherence
//! is over the bins not standing 20 times over that median, which are lines, not filters.

use super::lines::{self, Samples};
use rustfft::num_complex::Complex;

/// The side of a tile, in samples: 32 rings, two of which a hard cut falls across.
pub const TILE: usize = 64;
/// Fewer whole tiles than this say nothing.
const LEAST_TILES: usize = 4;
/// The innermost ring counted: those inside are a trend's and the window's.
const FIRST_RING: usize = 2;
/// The innermost ring an edge may start at: a power law as steep as ground's (f⁻⁴ a bin)
/// falls by 5 from the fourth ring to the sixth, and a side whose noise flattens its
/// spectrum there would stand that far from the other.
pub const FIRST_EDGE: usize = 4;
/// A side holding at most this share of the other's power in a ring has lost some of it...
pub const LOSS: f64 = 0.5;
/// ... coherently, where their coherence there is over this, and over twice the share.
pub const COHERENT: f64 = 0.8;
/// Rings of coherent loss that make a filter (of the [`TILE`] / 2 there are).
pub const LEAST_LOSSY: u32 = 3;
/// A fall of a side's power over two rings, beyond the other's there, that is an edge: twice
/// the most a smooth spectrum falls past [`FIRST_EDGE`].
pub const EDGE: f64 = 10.0;
/// The most the other side's own edge may reach for the first side's to count: where both
/// fall off, neither spectrum is ground's.
pub const SMOOTH: f64 = 5.0;
/// A bin standing this many times over its ring's median is a line, not a filter's work.
const LINE: f64 = 20.0;

/// What the pair's spectra say of a filter between them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transfer {
    /// Rings where the reference lost power coherently, then the other.
    pub lossy: [u32; 2],
    /// The largest fall of the reference's power over two rings, beyond the other's, where
    /// it holds content below and lacks it past: 1 where it never falls faster; then the
    /// other's.
    pub edge: [f64; 2],
    /// How many tiles the spectra are over.
    pub tiles: u32,
}

impl Transfer {
    /// Which side is a filter of the other: Some(true) for the reference, Some(false) for
    /// the other. An edge where the other side's spectrum is smooth decides first; else
    /// [`LEAST_LOSSY`] rings of coherent loss where the other has none. None where neither
    /// holds, or both point at different sides.
    pub fn filtered(&self) -> Option<bool> {
        let by_edge = |i: usize| self.edge[i] >= EDGE && self.edge[1 - i] < SMOOTH;
        let by_loss = |i: usize| self.lossy[i] >= LEAST_LOSSY && self.lossy[1 - i] == 0;
        let side = |i: usize| by_edge(i) || (by_loss(i) && !by_edge(1 - i));
        match (side(0), side(1)) {
            (true, false) => Some(true),
            (false, true) => Some(false),
            _ => None,
        }
    }

    /// The figure the verdict stands on: the filtered side's edge where it has one, else its
    /// rings of coherent loss.
    pub fn statistic(&self) -> f64 {
        match self.filtered() {
            Some(r) => {
                let i = if r { 0 } else { 1 };
                if self.edge[i] >= EDGE {
                    self.edge[i]
                } else {
                    self.lossy[i] as f64
                }
            }
            None => 0.0,
        }
    }
}

/// The transfer between the two sides of `s`: over tiles of [`TILE`]², or where fewer than
/// [`LEAST_TILES`] of those hold no gap (a survey full of voids, a small overlap), of half
/// that side. None where neither has enough.
pub fn measure(s: &Samples) -> Option<Transfer> {
    over_tiles(s, TILE).or_else(|| over_tiles(s, TILE / 2))
}

fn over_tiles(s: &Samples, tile: usize) -> Option<Transfer> {
    let (nx, ny) = (s.nx, s.ny);
    if nx < tile || ny < tile {
        return None;
    }
    let half = tile / 2;
    let starts = |n: usize| (0..=(n - tile) / half).map(move |i| i * half);
    let bins = tile * tile;
    let mut pa = vec![0.0; bins];
    let mut pb = vec![0.0; bins];
    let mut cross = vec![Complex::new(0.0, 0.0); bins];
    let mut tiles = 0u32;
    let mut ta = vec![0.0; bins];
    let mut tb = vec![0.0; bins];
    for r0 in starts(ny) {
        'tile: for c0 in starts(nx) {
            for r in 0..tile {
                for c in 0..tile {
                    let i = (r0 + r) * nx + c0 + c;
                    let (a, b) = (s.reference[i], s.other[i]);
                    if a.is_nan() || b.is_nan() {
                        continue 'tile;
                    }
                    ta[r * tile + c] = a;
                    tb[r * tile + c] = b;
                }
            }
            let fa = lines::spectrum(&ta, tile, tile);
            let fb = lines::spectrum(&tb, tile, tile);
            for i in 0..bins {
                pa[i] += fa[i].norm_sqr();
                pb[i] += fb[i].norm_sqr();
                cross[i] += fa[i] * fb[i].conj();
            }
            tiles += 1;
        }
    }
    if (tiles as usize) < LEAST_TILES {
        return None;
    }
    // Each bin's ring, and each ring's bins.
    let signed = |i: usize| {
        if i <= tile / 2 {
            i as f64
        } else {
            i as f64 - tile as f64
        }
    };
    let rings = tile / 2;
    let mut by: Vec<Vec<usize>> = vec![Vec::new(); rings];
    for v in 0..tile {
        for u in 0..tile {
            let k = signed(u).hypot(signed(v)).round() as usize;
            if (FIRST_RING..rings).contains(&k) {
                by[k].push(v * tile + u);
            }
        }
    }
    let median = |p: &[f64], ring: &[usize]| {
        let mut x: Vec<f64> = ring.iter().map(|&i| p[i]).collect();
        if x.is_empty() {
            return 0.0;
        }
        let m = x.len() / 2;
        *x.select_nth_unstable_by(m, f64::total_cmp).1
    };
    let ma: Vec<f64> = by.iter().map(|r| median(&pa, r)).collect();
    let mb: Vec<f64> = by.iter().map(|r| median(&pb, r)).collect();
    // Each ring's coherence, over the bins that are no line's.
    let coherence: Vec<f64> = by
        .iter()
        .enumerate()
        .map(|(k, ring)| {
            let (mut sa, mut sb, mut c) = (0.0, 0.0, Complex::new(0.0, 0.0));
            for &i in ring {
                if pa[i] > LINE * ma[k] || pb[i] > LINE * mb[k] {
                    continue;
                }
                sa += pa[i];
                sb += pb[i];
                c += cross[i];
            }
            if sa > 0.0 && sb > 0.0 {
                c.norm_sqr() / (sa * sb)
            } else {
                0.0
            }
        })
        .collect();
    let side = |mx: &[f64], my: &[f64]| -> (u32, f64) {
        let mut lossy = 0;
        let mut edge: f64 = 1.0;
        for k in FIRST_RING..rings {
            if mx[k] <= 0.0 || my[k] <= 0.0 {
                continue;
            }
            let share = mx[k] / my[k];
            if share <= LOSS && coherence[k] >= COHERENT && coherence[k] >= 2.0 * share {
                lossy += 1;
            }
            if k + 2 < rings
                && k >= FIRST_EDGE
                && share >= LOSS * LOSS
                && mx[k + 2] > 0.0
                && my[k + 2] > 0.0
                && mx[k + 2] <= LOSS * LOSS * my[k + 2]
            {
                edge = edge.max((mx[k] / mx[k + 2]) / (my[k] / my[k + 2]).max(1.0));
            }
        }
        (lossy, edge)
    };
    let (la, ea) = side(&ma, &mb);
    let (lb, eb) = side(&mb, &ma);
    Some(Transfer {
        lossy: [la, lb],
        edge: [ea, eb],
        tiles,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::coreg::Placement;
    use crate::grid::Grid;
    use crate::lines::{fft2, tests::ground};

    /// `g` filtered in the frequency domain by `gain` of the radial frequency, as a fraction
    /// of the Nyquist frequency.
    fn filtered(g: &Grid, gain: impl Fn(f64) -> f64) -> Grid {
        let n = g.cols;
        let mut data: Vec<Complex<f64>> = g
            .samples
            .iter()
            .map(|&z| Complex::new(z as f64, 0.0))
            .collect();
        fft2(&mut data, n, n, false);
        let f = |i: usize| {
            2.0 * (if i <= n / 2 {
                i as f64
            } else {
                i as f64 - n as f64
            }) / n as f64
        };
        for v in 0..n {
            for u in 0..n {
                data[v * n + u] *= gain(f(u).hypot(f(v)));
            }
        }
        fft2(&mut data, n, n, true);
        let mut out = g.clone();
        for (z, d) in out.samples.iter_mut().zip(&data) {
            *z = (d.re / (n * n) as f64) as f32;
        }
        out
    }

    /// `g` plus white noise of `sigma`, from a seed.
    fn noisy(g: &Grid, sigma: f64, seed: u64) -> Grid {
        let mut x = seed.wrapping_mul(0x2545_f491_4f6c_dd1d) | 1;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut out = g.clone();
        for z in out.samples.iter_mut() {
            let (u1, u2) = (next().max(1e-12), next());
            *z += (sigma * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32;
        }
        out
    }

    fn transfer(a: &Grid, b: &Grid) -> Transfer {
        let same = |p: [f64; 2]| Some(p);
        let s = lines::read(
            a,
            b,
            &same,
            &Placement::shift([0.0, 0.0]),
            &a.world_bounds(),
            1.0,
        )
        .unwrap();
        measure(&s).unwrap()
    }

    /// A copy low-passed in the frequency domain, gently (a Butterworth of order 2), steeply
    /// (of order 8) or as a brick wall, is the filtered side, whichever side is the
    /// reference.
    #[test]
    fn a_low_pass_copy_is_the_filtered_side() {
        for seed in 1..4 {
            let g = ground(256, seed);
            for (what, cut, order) in [
                ("gentle", 0.3, 2),
                ("steep", 0.5, 8),
                ("brick wall", 0.4, 0),
            ] {
                let copy = filtered(&g, |f| {
                    if order == 0 {
                        if f <= cut {
                            1.0
                        } else {
                            0.0
                        }
                    } else {
                        1.0 / (1.0 + (f / cut).powi(2 * order)).sqrt()
                    }
                });
                let t = transfer(&g, &copy);
                assert_eq!(t.filtered(), Some(false), "{what}, seed {seed}: {t:?}");
                let t = transfer(&copy, &g);
                assert_eq!(t.filtered(), Some(true), "{what}, seed {seed}: {t:?}");
                if order == 0 {
                    assert!(t.edge[0] >= EDGE, "{what}, seed {seed}: {t:?}");
                }
            }
        }
    }

    /// Noise added to either side, or to both apart (two surveys of the same ground), makes
    /// no filter of the clean one, however much the noise holds of the finest rings.
    #[test]
    fn noise_is_no_filter() {
        for seed in 1..4 {
            let g = ground(256, seed);
            for sigma in [0.5, 2.0, 8.0] {
                let n = noisy(&g, sigma, seed);
                for (a, b) in [(&g, &n), (&n, &g)] {
                    let t = transfer(a, b);
                    assert_eq!(t.filtered(), None, "σ {sigma}, seed {seed}: {t:?}");
                }
                let m = noisy(&g, 0.5 * sigma, seed + 100);
                let t = transfer(&n, &m);
                assert_eq!(t.filtered(), None, "σ {sigma} and half, seed {seed}: {t:?}");
            }
        }
    }
}
