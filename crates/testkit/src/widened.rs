//! Degradations beyond [`crate::degrade`]'s family: placements beyond a shift (rotations,
//! stretches, shears), filters in the frequency domain (brick-wall and Butterworth
//! low-passes, whose brick wall rings), sharpening after a blur, vertical trends, periodic
//! artefacts, voids filled with fabricated smooth ground, and aliasing. Drawn alone or
//! chained with each other and with the old family's operations, every parameter from a seed.
//!
//! Some kinds are held back: never drawn while the arbitration between surveys was being
//! developed, only in the tests that report them apart ([`Kind::held_back`]). A method
//! judged only on the cases it was tuned to proves nothing.

use crate::degrade::{self, rotation, warped};
use patchwork_core::model::coreg::blurred as blurred_copy;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::lines::fft2;
use patchwork_core::terrain::Terrain;
use rustfft::num_complex::Complex;

/// One kind of degradation of the widened family.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// Turned by 0.1–2° about the grid's centre.
    Rotation,
    /// Stretched or shrunk by 0.2–2%, alike or apart along the axes.
    Stretch,
    /// Sheared by 0.2–1.5%. Held back.
    Shear,
    /// A Butterworth low-pass in the frequency domain, cut at 0.15–0.6 of the Nyquist
    /// frequency, of order 2–8.
    SpectralLowPass,
    /// A brick-wall low-pass in the frequency domain, which rings beside every cliff. Held
    /// back.
    Ringing,
    /// A Gaussian blur, then an unsharp mask that raises what is left of the fine relief.
    SharpenedBlur,
    /// A plane or a bowl added: metres over the grid.
    Trend,
    /// Stripes: a sinusoid along the rows or the columns, 0.5–5 m, 3–40 cells a period.
    Stripes,
    /// One to four discs of ground replaced by a smooth fabricated surface (a plane through
    /// each disc's rim, as a void filler makes).
    FabricatedFill,
    /// Every 2nd–4th sample kept with no low-pass first, brought back by the nearest.
    Aliasing,
    /// Stripes at an angle to both axes, a sensor's pattern rather than a scan line's. Held
    /// back.
    SlantedStripes,
    /// Compressed as a lossy codec does: each whole block of 8 × 8 cells by its cosine
    /// transform, the coefficients rounded to a step of 0.25–4 m at the mean that grows with
    /// the frequency, so that fine detail is lost block by block and the blocks' edges show.
    /// Held back.
    BlockCompression,
}

impl Kind {
    /// Every kind.
    pub const ALL: [Kind; 12] = [
        Kind::Rotation,
        Kind::Stretch,
        Kind::Shear,
        Kind::SpectralLowPass,
        Kind::Ringing,
        Kind::SharpenedBlur,
        Kind::Trend,
        Kind::Stripes,
        Kind::FabricatedFill,
        Kind::Aliasing,
        Kind::SlantedStripes,
        Kind::BlockCompression,
    ];

    /// Whether this kind was kept out of the development of the arbitration: the tests
    /// report these apart.
    pub fn held_back(self) -> bool {
        matches!(
            self,
            Kind::Shear | Kind::Ringing | Kind::SlantedStripes | Kind::BlockCompression
        )
    }

    /// A short name, for reports.
    pub fn name(self) -> &'static str {
        match self {
            Kind::Rotation => "rotation",
            Kind::Stretch => "stretch",
            Kind::Shear => "shear",
            Kind::SpectralLowPass => "spectral low-pass",
            Kind::Ringing => "brick-wall low-pass",
            Kind::SharpenedBlur => "sharpened blur",
            Kind::Trend => "trend",
            Kind::Stripes => "stripes",
            Kind::FabricatedFill => "fabricated fill",
            Kind::Aliasing => "aliasing",
            Kind::SlantedStripes => "slanted stripes",
            Kind::BlockCompression => "block compression",
        }
    }
}

fn between(next: &mut impl FnMut() -> f64, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * next()
}

fn sign(next: &mut impl FnMut() -> f64) -> f64 {
    if next() < 0.5 {
        -1.0
    } else {
        1.0
    }
}

/// One degradation of `kind`, its parameters drawn from `next`: a label and the copy.
pub fn apply(kind: Kind, g: &Grid, next: &mut impl FnMut() -> f64) -> (String, Grid) {
    let cubic = next() < 0.5;
    let how = if cubic { "cubic" } else { "bilinear" };
    match kind {
        Kind::Rotation => {
            let a = between(next, 0.1, 2.0) * sign(next);
            (
                format!("rotated {a:.2}° ({how})"),
                warped(g, rotation(a), cubic),
            )
        }
        Kind::Stretch => {
            let sx = 1.0 + between(next, 0.002, 0.02) * sign(next);
            let sy = if next() < 0.5 {
                sx
            } else {
                1.0 + between(next, 0.002, 0.02) * sign(next)
            };
            (
                format!("stretched {sx:.4} × {sy:.4} ({how})"),
                warped(g, [[sx, 0.0], [0.0, sy]], cubic),
            )
        }
        Kind::Shear => {
            let k = between(next, 0.002, 0.015) * sign(next);
            let m = if next() < 0.5 {
                [[1.0, k], [0.0, 1.0]]
            } else {
                [[1.0, 0.0], [k, 1.0]]
            };
            (format!("sheared {k:.4} ({how})"), warped(g, m, cubic))
        }
        Kind::SpectralLowPass => {
            let cut = between(next, 0.15, 0.6);
            let order = 2 + (next() * 7.0) as i32;
            (
                format!("Butterworth low-pass at {cut:.2} of Nyquist, order {order}"),
                spectral(g, |f| 1.0 / (1.0 + (f / cut).powi(2 * order)).sqrt()),
            )
        }
        Kind::Ringing => {
            let cut = between(next, 0.2, 0.7);
            (
                format!("brick-wall low-pass at {cut:.2} of Nyquist"),
                spectral(g, |f| if f <= cut { 1.0 } else { 0.0 }),
            )
        }
        Kind::SharpenedBlur => {
            let s = between(next, 0.7, 2.5);
            let amount = between(next, 0.5, 2.0);
            let b = blurred_copy(g, s);
            let bb = blurred_copy(&b, s);
            let mut out = b.clone();
            for ((z, &zb), &zbb) in out.samples.iter_mut().zip(&b.samples).zip(&bb.samples) {
                *z = if zbb.is_nan() {
                    zb
                } else {
                    zb + (amount * (zb as f64 - zbb as f64)) as f32
                };
            }
            (
                format!("gaussian σ {s:.2}, then sharpened ×{amount:.2}"),
                out,
            )
        }
        Kind::Trend => {
            let a = between(next, 0.5, 10.0) * sign(next);
            let angle = between(next, 0.0, std::f64::consts::TAU);
            let bowl = next() < 0.4;
            let (w, h) = (g.cols as f64, g.rows as f64);
            let mut out = g.clone();
            for r in 0..g.rows {
                for c in 0..g.cols {
                    let (u, v) = (c as f64 / w - 0.5, r as f64 / h - 0.5);
                    let t = if bowl {
                        a * 4.0 * (u * u + v * v)
                    } else {
                        a * (u * angle.cos() + v * angle.sin())
                    };
                    out.samples[r * g.cols + c] += t as f32;
                }
            }
            let what = if bowl { "bowl" } else { "plane" };
            (format!("{what} of {a:.1} m"), out)
        }
        Kind::Stripes | Kind::SlantedStripes => {
            let amp = between(next, 0.5, 5.0);
            let period = between(next, 3.0, 40.0);
            let angle = if kind == Kind::Stripes {
                if next() < 0.5 {
                    0.0
                } else {
                    90.0
                }
            } else {
                between(next, 15.0, 75.0)
            };
            let (s, c) = angle.to_radians().sin_cos();
            let mut out = g.clone();
            for r in 0..g.rows {
                for col in 0..g.cols {
                    let t = (col as f64 * c + r as f64 * s) / period;
                    out.samples[r * g.cols + col] +=
                        (amp * (std::f64::consts::TAU * t).sin()) as f32;
                }
            }
            (
                format!("stripes of {amp:.1} m every {period:.1} cells at {angle:.0}°"),
                out,
            )
        }
        Kind::FabricatedFill => {
            let n = 1 + (next() * 4.0) as usize;
            let mut out = g.clone();
            let mut radii = Vec::new();
            for _ in 0..n {
                let rad = between(next, 8.0, 0.15 * g.cols.min(g.rows) as f64).max(4.0);
                let cx = between(next, rad, g.cols as f64 - rad);
                let cy = between(next, rad, g.rows as f64 - rad);
                fill_disc(&mut out, [cx, cy], rad);
                radii.push(format!("{rad:.0}"));
            }
            (
                format!("{n} discs (radii {}) filled smooth", radii.join(", ")),
                out,
            )
        }
        Kind::Aliasing => {
            let k = 2 + (next() * 3.0) as usize;
            let mut out = g.clone();
            for r in 0..g.rows {
                for c in 0..g.cols {
                    let (rr, cc) = ((r + k / 2) / k * k, (c + k / 2) / k * k);
                    out.samples[r * g.cols + c] = g.at(cc.min(g.cols - 1), rr.min(g.rows - 1));
                }
            }
            (format!("every {k}th sample, nearest back up"), out)
        }
        Kind::BlockCompression => {
            let step = between(next, 0.25, 4.0);
            let growth = between(next, 0.5, 2.0);
            (
                format!("8 × 8 cosine blocks quantised by {step:.2} m, ×{growth:.2} a frequency"),
                block_compressed(g, step, growth),
            )
        }
    }
}

/// `g` with each whole 8 × 8 block of cells taken to its orthonormal cosine transform (DCT-II),
/// the coefficient of frequencies (u, v) rounded to a multiple of `step · (1 + growth · (u +
/// v))`, and taken back. Voids are filled with their block's mean for the transform and stay
/// voids; a block with no valid sample, and the partial blocks at the right and bottom
/// edges, are kept as they are.
pub fn block_compressed(g: &Grid, step: f64, growth: f64) -> Grid {
    const N: usize = 8;
    let basis: Vec<[f64; N]> = (0..N)
        .map(|k| {
            let a = if k == 0 {
                (1.0 / N as f64).sqrt()
            } else {
                (2.0 / N as f64).sqrt()
            };
            let mut row = [0.0; N];
            for (n, x) in row.iter_mut().enumerate() {
                *x = a
                    * (std::f64::consts::PI * (2 * n + 1) as f64 * k as f64 / (2 * N) as f64).cos();
            }
            row
        })
        .collect();
    let mut out = g.clone();
    for by in 0..g.rows / N {
        for bx in 0..g.cols / N {
            let at = |r: usize, c: usize| (by * N + r) * g.cols + bx * N + c;
            let valid: Vec<f64> = (0..N * N)
                .map(|i| g.samples[at(i / N, i % N)] as f64)
                .filter(|z| !z.is_nan())
                .collect();
            if valid.is_empty() {
                continue;
            }
            let mean = valid.iter().sum::<f64>() / valid.len() as f64;
            let mut x = [[0.0f64; N]; N];
            for (r, row) in x.iter_mut().enumerate() {
                for (c, v) in row.iter_mut().enumerate() {
                    let z = g.samples[at(r, c)] as f64;
                    *v = if z.is_nan() { mean } else { z };
                }
            }
            // Forward: X = B x Bᵀ, quantised, then back: x = Bᵀ X B.
            let mut f = [[0.0f64; N]; N];
            for u in 0..N {
                for v in 0..N {
                    let mut sum = 0.0;
                    for r in 0..N {
                        for c in 0..N {
                            sum += basis[u][r] * x[r][c] * basis[v][c];
                        }
                    }
                    let q = step * (1.0 + growth * (u + v) as f64);
                    f[u][v] = (sum / q).round() * q;
                }
            }
            for r in 0..N {
                for c in 0..N {
                    if g.samples[at(r, c)].is_nan() {
                        continue;
                    }
                    let mut sum = 0.0;
                    for u in 0..N {
                        for v in 0..N {
                            sum += basis[u][r] * f[u][v] * basis[v][c];
                        }
                    }
                    out.samples[at(r, c)] = sum as f32;
                }
            }
        }
    }
    out
}

/// Draws a copy of `g` from the widened family, from the kinds `pick` allows: one to `most`
/// operations, each a widened kind, or where `old_family`, one in four after the first, an
/// operation of [`degrade`]'s family. Returns the label, the copy and the kinds drawn.
pub fn draw(
    g: &Grid,
    next: &mut impl FnMut() -> f64,
    pick: impl Fn(Kind) -> bool,
    most: usize,
    old_family: bool,
) -> (String, Grid, Vec<Kind>) {
    let kinds: Vec<Kind> = Kind::ALL.into_iter().filter(|&k| pick(k)).collect();
    assert!(!kinds.is_empty(), "no kind to draw from");
    let mut out = g.clone();
    let mut labels = Vec::new();
    let mut drawn = Vec::new();
    for i in 0..1 + (next() * most as f64) as usize {
        if old_family && i > 0 && next() < 0.25 {
            let d = degrade::draw(&out, next);
            labels.push(d.label);
            out = d.grid;
            continue;
        }
        let k = kinds[(next() * kinds.len() as f64) as usize];
        let (l, grid) = apply(k, &out, next);
        labels.push(l);
        drawn.push(k);
        out = grid;
    }
    (labels.join(" + "), out, drawn)
}

/// `g` filtered in the frequency domain by `gain` of the frequency (radial, as a fraction of
/// the Nyquist frequency, 0 to √2): its voids are filled with the mean for the transform and
/// stay voids.
pub fn spectral(g: &Grid, gain: impl Fn(f64) -> f64) -> Grid {
    let (w, h) = (g.cols, g.rows);
    let valid: Vec<f64> = g
        .samples
        .iter()
        .filter(|z| !z.is_nan())
        .map(|&z| z as f64)
        .collect();
    let mean = valid.iter().sum::<f64>() / valid.len().max(1) as f64;
    let mut data: Vec<Complex<f64>> = g
        .samples
        .iter()
        .map(|&z| Complex::new(if z.is_nan() { 0.0 } else { z as f64 - mean }, 0.0))
        .collect();
    fft2(&mut data, w, h, false);
    let freq = |k: usize, n: usize| {
        let k = if k <= n / 2 {
            k as f64
        } else {
            k as f64 - n as f64
        };
        2.0 * k / n as f64
    };
    for r in 0..h {
        for c in 0..w {
            let f = freq(c, w).hypot(freq(r, h));
            data[r * w + c] *= gain(f);
        }
    }
    fft2(&mut data, w, h, true);
    let n = (w * h) as f64;
    let samples = g
        .samples
        .iter()
        .zip(&data)
        .map(|(&z, v)| {
            if z.is_nan() {
                f32::NAN
            } else {
                (v.re / n + mean) as f32
            }
        })
        .collect();
    Grid::new(w, h, samples, g.georef).expect("the same shape")
}

/// The disc of radius `rad` (cells) about `centre` replaced by the plane that fits its rim
/// (the samples within a cell outside it), as a void filler's interpolation makes.
fn fill_disc(g: &mut Grid, centre: [f64; 2], rad: f64) {
    let mut rim = Vec::new();
    let (c0, c1) = (
        (centre[0] - rad - 2.0).max(0.0) as usize,
        ((centre[0] + rad + 2.0) as usize).min(g.cols - 1),
    );
    let (r0, r1) = (
        (centre[1] - rad - 2.0).max(0.0) as usize,
        ((centre[1] + rad + 2.0) as usize).min(g.rows - 1),
    );
    for r in r0..=r1 {
        for c in c0..=c1 {
            let d = (c as f64 - centre[0]).hypot(r as f64 - centre[1]);
            let z = g.at(c, r);
            if d > rad && d <= rad + 1.5 && !z.is_nan() {
                rim.push([c as f64, r as f64, z as f64]);
            }
        }
    }
    if rim.len() < 3 {
        return;
    }
    // The least-squares plane z = a + b·x + c·y through the rim.
    let mut n = [[0.0f64; 3]; 3];
    let mut v = [0.0f64; 3];
    for p in &rim {
        let row = [1.0, p[0] - centre[0], p[1] - centre[1]];
        for i in 0..3 {
            for j in 0..3 {
                n[i][j] += row[i] * row[j];
            }
            v[i] += row[i] * p[2];
        }
    }
    let Some(x) = solve3(n, v) else {
        return;
    };
    for r in r0..=r1 {
        for c in c0..=c1 {
            let (dx, dy) = (c as f64 - centre[0], r as f64 - centre[1]);
            if dx.hypot(dy) <= rad && !g.at(c, r).is_nan() {
                g.samples[r * g.cols + c] = (x[0] + x[1] * dx + x[2] * dy) as f32;
            }
        }
    }
}

fn solve3(n: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(&n);
    if d.abs() < 1e-12 {
        return None;
    }
    let mut x = [0.0; 3];
    for (k, xk) in x.iter_mut().enumerate() {
        let mut m = n;
        for i in 0..3 {
            m[i][k] = b[i];
        }
        *xk = det(&m) / d;
    }
    Some(x)
}

/// The share of `g`'s valid samples that `t` serves at e = 0 within `tol` metres of them.
pub fn served_within(t: &Terrain, g: &Grid, tol: f64) -> f64 {
    let mut pts = Vec::new();
    let mut want = Vec::new();
    for r in 0..g.rows {
        for c in 0..g.cols {
            let z = g.at(c, r);
            if !z.is_nan() {
                pts.push(g.georef.to_world(c as f64, r as f64));
                want.push(z as f64);
            }
        }
    }
    let got = t.sample(&pts, 0.0);
    let ok = got
        .iter()
        .zip(&want)
        .filter(|(h, z)| !h.is_nan() && (**h as f64 - **z).abs() <= tol)
        .count();
    ok as f64 / want.len().max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwork_core::model::grid::Georef;

    /// Rough ground of 20 × 18 cells: two whole blocks across and two down, and partial ones.
    fn rough() -> Grid {
        let s = (0..20 * 18)
            .map(|k| {
                let (c, r) = ((k % 20) as f32, (k / 20) as f32);
                100.0 + 3.0 * c + (c * 1.7).sin() * 4.0 + (r * 2.3).cos() * 5.0
            })
            .collect();
        Grid::new(20, 18, s, Georef::north_up([0.0, 18.0], [1.0, 1.0])).unwrap()
    }

    #[test]
    fn block_compression_is_lossless_at_a_fine_step_and_keeps_voids_and_partial_blocks() {
        let mut g = rough();
        g.samples[3 * 20 + 4] = f32::NAN;
        let fine = block_compressed(&g, 1e-6, 1.0);
        for (a, b) in g.samples.iter().zip(&fine.samples) {
            assert!(a.is_nan() && b.is_nan() || (a - b).abs() < 1e-3, "{a} {b}");
        }
        let coarse = block_compressed(&g, 4.0, 1.0);
        assert!(coarse.samples[3 * 20 + 4].is_nan());
        // The 17th column on (a partial block) and the 17th row down are kept as they were.
        assert_eq!(coarse.at(17, 5), g.at(17, 5));
        assert_eq!(coarse.at(5, 16), g.at(5, 16));
        // A whole block loses detail but keeps its mean to within a sixteenth of the step
        // (the mean is the zero frequency's coefficient over 8).
        let mean = |g: &Grid| {
            let v: Vec<f64> = (8..16)
                .flat_map(|r| (8..16).map(move |c| (c, r)))
                .map(|(c, r)| g.at(c, r) as f64)
                .collect();
            v.iter().sum::<f64>() / v.len() as f64
        };
        assert!((mean(&coarse) - mean(&g)).abs() <= 4.0 / 16.0 + 1e-4);
        let changed = (8..16)
            .flat_map(|r| (8..16).map(move |c| (c, r)))
            .filter(|&(c, r)| (coarse.at(c, r) - g.at(c, r)).abs() > 0.01)
            .count();
        assert!(changed > 32, "only {changed} of 64 samples changed");
    }
}
