//! C2 patches (§4.1): the natural bicubic spline through a window's samples, and the
//! Bézier nets that bound its distance to another surface.
//!
//! A patch's spline is a uniform tensor-product cubic B-spline on the window's sample grid
//! that passes through every sample, with zero second derivative across the window's border
//! (the natural end condition). It depends on the window's samples alone, so a client holding
//! a patch's samples fits the very same surface; it is C2 inside the window, and Formula 1 with
//! the weight (1 − |t|)³(3|t| + 1) keeps the blend C2.
//!
//! A spline needs a height at every sample. A void sample is filled, for the fit only, from its
//! valid neighbours (rings of means growing inwards from the valid samples): the patch is still
//! only evaluated on valid cells, as a bilinear one is, and its δ is measured on them.

/// The B-spline coefficients of one window: `(cols + 2) × (rows + 2)` of them, row-major, for a
/// window of `cols × rows` samples. Coefficient (i, j) belongs to the knot at sample
/// (i − 1, j − 1).
#[derive(Clone, Debug, PartialEq)]
pub struct Spline {
    /// Samples per row of the window it was fitted to.
    pub cols: usize,
    /// Rows of samples of that window.
    pub rows: usize,
    /// The `(cols + 2) × (rows + 2)` coefficients, row-major.
    pub coef: Vec<f64>,
}

/// The uniform cubic B-spline basis at t ∈ [0, 1], for the coefficients of knots i−1 … i+2.
#[inline]
pub fn basis(t: f64) -> [f64; 4] {
    let s = 1.0 - t;
    let t2 = t * t;
    let t3 = t2 * t;
    [
        s * s * s / 6.0,
        (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
        (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
        t3 / 6.0,
    ]
}

/// The 1-D natural interpolating spline through `z` (n values), as n + 2 B-spline
/// coefficients, written to `out`. With the natural end conditions the end coefficients equal
/// the end values, and the interior ones solve c[i−1] + 4c[i] + c[i+1] = 6z[i]; `scratch`
/// holds the elimination's factors.
fn fit_line(z: &[f64], out: &mut [f64], scratch: &mut Vec<f64>) {
    let n = z.len();
    debug_assert_eq!(out.len(), n + 2);
    match n {
        0 => return,
        1 => {
            out.fill(z[0]);
            return;
        }
        _ => {}
    }
    let c = &mut out[1..=n];
    c[0] = z[0];
    c[n - 1] = z[n - 1];
    if n > 2 {
        // Thomas' algorithm on the interior, whose ends fold in the known c[0] and c[n−1].
        let m = n - 2;
        scratch.clear();
        scratch.resize(m, 0.0);
        let mut prev_c = 0.0;
        let mut prev_d = 0.0;
        for k in 0..m {
            let mut d = 6.0 * z[k + 1];
            if k == 0 {
                d -= c[0];
            }
            if k == m - 1 {
                d -= c[n - 1];
            }
            let denom = 4.0 - prev_c;
            let cc = 1.0 / denom;
            let dd = (d - prev_d) / denom;
            scratch[k] = cc;
            c[k + 1] = dd;
            prev_c = cc;
            prev_d = dd;
        }
        for k in (0..m.saturating_sub(1)).rev() {
            let next = c[k + 2];
            c[k + 1] -= scratch[k] * next;
        }
    }
    // Zero second derivative at the ends: c[−1] − 2c[0] + c[1] = 0.
    out[0] = 2.0 * out[1] - out[2];
    out[n + 1] = 2.0 * out[n] - out[n - 1];
}

/// Fills void (NaN) samples of a `cols × rows` block, in place, with the mean of their valid
/// 4-neighbours, ring by ring inwards from the valid samples; a block with no valid sample
/// becomes zeros.
fn fill_voids(z: &mut [f64], cols: usize, rows: usize) {
    let mut todo: Vec<usize> = (0..z.len()).filter(|&k| z[k].is_nan()).collect();
    while !todo.is_empty() {
        let mut next = Vec::new();
        let mut set = Vec::new();
        for &k in &todo {
            let (c, r) = (k % cols, k / cols);
            let mut sum = 0.0;
            let mut n = 0u32;
            let mut add = |v: f64| {
                if !v.is_nan() {
                    sum += v;
                    n += 1;
                }
            };
            if c > 0 {
                add(z[k - 1]);
            }
            if c + 1 < cols {
                add(z[k + 1]);
            }
            if r > 0 {
                add(z[k - cols]);
            }
            if r + 1 < rows {
                add(z[k + cols]);
            }
            if n > 0 {
                set.push((k, sum / n as f64));
            } else {
                next.push(k);
            }
        }
        if set.is_empty() {
            for k in next {
                z[k] = 0.0;
            }
            return;
        }
        // A ring is filled from the values before it, so the fill does not depend on the
        // order samples are visited in.
        for (k, v) in set {
            z[k] = v;
        }
        todo = next;
    }
}

impl Spline {
    /// The natural bicubic spline through the `cols × rows` samples `at(c, r)`, voids filled.
    pub fn fit(cols: usize, rows: usize, at: impl Fn(usize, usize) -> f32) -> Spline {
        let mut z: Vec<f64> = (0..rows)
            .flat_map(|r| (0..cols).map(move |c| (c, r)))
            .map(|(c, r)| at(c, r) as f64)
            .collect();
        fill_voids(&mut z, cols, rows);
        let (cc, cr) = (cols + 2, rows + 2);
        let mut scratch = Vec::new();
        // Along rows: each sample row gives a row of cols + 2 coefficients.
        let mut rowfit = vec![0.0; cc * rows];
        for r in 0..rows {
            fit_line(
                &z[r * cols..(r + 1) * cols],
                &mut rowfit[r * cc..(r + 1) * cc],
                &mut scratch,
            );
        }
        // Then down each coefficient column: the tensor product of the two 1-D fits.
        let mut coef = vec![0.0; cc * cr];
        let mut line = vec![0.0; rows];
        let mut out = vec![0.0; cr];
        for i in 0..cc {
            for r in 0..rows {
                line[r] = rowfit[r * cc + i];
            }
            fit_line(&line, &mut out, &mut scratch);
            for (j, &v) in out.iter().enumerate() {
                coef[j * cc + i] = v;
            }
        }
        Spline { cols, rows, coef }
    }

    /// Coefficient (i, j), knot (i − 1, j − 1).
    #[inline]
    fn c(&self, i: usize, j: usize) -> f64 {
        self.coef[j * (self.cols + 2) + i]
    }

    /// The cell holding coordinate x on an axis of n samples, and the fraction across it: the
    /// last line belongs to the cell before it.
    #[inline]
    fn locate(x: f64, n: usize) -> (usize, f64) {
        let cells = n.saturating_sub(1).max(1);
        let i = (x.floor().max(0.0) as usize).min(cells - 1);
        (i, x - i as f64)
    }

    /// The spline at window grid coordinates g ∈ [0, cols − 1] × [0, rows − 1].
    #[inline]
    pub fn eval(&self, g: [f64; 2]) -> f64 {
        let (i, tx) = Self::locate(g[0], self.cols);
        let (j, ty) = Self::locate(g[1], self.rows);
        let bx = basis(tx);
        let by = basis(ty);
        let mut z = 0.0;
        for (b, &wy) in by.iter().enumerate() {
            let row = &self.coef[(j + b) * (self.cols + 2) + i..][..4];
            z += wy * (row[0] * bx[0] + row[1] * bx[1] + row[2] * bx[2] + row[3] * bx[3]);
        }
        z
    }

    /// The Bézier net of cell (c, r) (between samples c, c + 1 and r, r + 1): the 4 × 4
    /// control heights, `[row][column]`, of the bicubic polynomial the spline is on that cell.
    /// The polynomial lies within their range (the convex hull property).
    pub fn bezier(&self, c: usize, r: usize) -> [[f64; 4]; 4] {
        let mut rows = [[0.0; 4]; 4];
        for (b, row) in rows.iter_mut().enumerate() {
            let d = [0, 1, 2, 3].map(|a| self.c(c + a, r + b));
            *row = to_bezier(d);
        }
        let mut net = [[0.0; 4]; 4];
        for m in 0..4 {
            let d = [rows[0][m], rows[1][m], rows[2][m], rows[3][m]];
            let q = to_bezier(d);
            for n in 0..4 {
                net[n][m] = q[n];
            }
        }
        net
    }
}

/// The Bézier control points of one uniform cubic B-spline segment.
#[inline]
fn to_bezier(d: [f64; 4]) -> [f64; 4] {
    [
        (d[0] + 4.0 * d[1] + d[2]) / 6.0,
        (2.0 * d[1] + d[2]) / 3.0,
        (d[1] + 2.0 * d[2]) / 3.0,
        (d[1] + 4.0 * d[2] + d[3]) / 6.0,
    ]
}

/// The matrices that take a cubic's Bézier control points on [0, 1] to its control points on
/// each of the `f` intervals [k/f, (k+1)/f]: row m of matrix k holds the weights of the
/// original points in the blossom at (a, …, a, b, …, b), m of them b.
pub fn subdivision(f: usize) -> Vec<[[f64; 4]; 4]> {
    (0..f)
        .map(|k| {
            let a = k as f64 / f as f64;
            let b = (k + 1) as f64 / f as f64;
            let mut s = [[0.0; 4]; 4];
            for (m, row) in s.iter_mut().enumerate() {
                let u = [0, 1, 2].map(|q| if q < 3 - m { a } else { b });
                // The blossom of Bernstein polynomial i: the sum over the ways of choosing
                // i of the three arguments to take u, the others 1 − u.
                for set in 0u32..8 {
                    let i = set.count_ones() as usize;
                    let w: f64 = (0..3)
                        .map(|q| {
                            if set & (1 << q) != 0 {
                                u[q]
                            } else {
                                1.0 - u[q]
                            }
                        })
                        .product();
                    row[i] += w;
                }
            }
            s
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn horner_bezier(p: [f64; 4], t: f64) -> f64 {
        let s = 1.0 - t;
        p[0] * s * s * s + 3.0 * p[1] * s * s * t + 3.0 * p[2] * s * t * t + p[3] * t * t * t
    }

    #[test]
    fn the_spline_interpolates_and_is_natural() {
        let (cols, rows) = (9, 7);
        let f = |c: usize, r: usize| ((c * 37 + r * 11) % 17) as f32 - 0.3 * r as f32;
        let s = Spline::fit(cols, rows, f);
        for r in 0..rows {
            for c in 0..cols {
                let z = s.eval([c as f64, r as f64]);
                assert!((z - f(c, r) as f64).abs() < 1e-9, "{c},{r}: {z}");
            }
        }
        // C2 across a cell line: second differences from both sides agree.
        let h = 1e-4;
        for x in [1.0, 2.0, 5.0] {
            let y = 2.3;
            let d2 = |x0: f64| {
                (s.eval([x0 + h, y]) - 2.0 * s.eval([x0, y]) + s.eval([x0 - h, y])) / (h * h)
            };
            assert!((d2(x - 2.0 * h) - d2(x + 2.0 * h)).abs() < 1e-2);
        }
        // Natural: zero second derivative across the first and last lines.
        let y = 3.4;
        let d2 = (s.eval([0.0, y]) - 2.0 * s.eval([h, y]) + s.eval([2.0 * h, y])) / (h * h);
        assert!(d2.abs() < 1e-2, "{d2}");
    }

    #[test]
    fn planes_are_reproduced_and_voids_filled() {
        let plane = |c: usize, r: usize| 3.0 * c as f32 - 2.0 * r as f32 + 100.0;
        let s = Spline::fit(6, 5, |c, r| {
            if (c, r) == (2, 2) {
                f32::NAN
            } else {
                plane(c, r)
            }
        });
        // The filled sample is the mean of its neighbours, which on a plane is the plane.
        for (x, y) in [(0.5, 0.5), (2.0, 2.0), (4.7, 3.9), (1.3, 2.6)] {
            let z = 3.0 * x - 2.0 * y + 100.0;
            assert!((s.eval([x, y]) - z).abs() < 1e-9);
        }
    }

    #[test]
    fn bezier_nets_and_subdivision_reproduce_the_spline() {
        let f = |c: usize, r: usize| (((c * 7919 + r * 104_729) % 1009) as f32 * 0.37).sin() * 50.0;
        let s = Spline::fit(8, 8, f);
        let subs = subdivision(4);
        for (c, r) in [(0, 0), (3, 5), (6, 6)] {
            let net = s.bezier(c, r);
            for k in 0..4 {
                for l in 0..4 {
                    // The sub-net of fine cell (k, l) of the cell, evaluated at its own
                    // (u, v), is the spline at the matching point.
                    let mut sub = [[0.0; 4]; 4];
                    for n in 0..4 {
                        for m in 0..4 {
                            let mut v = 0.0;
                            for y in 0..4 {
                                for x in 0..4 {
                                    v += subs[l][n][y] * subs[k][m][x] * net[y][x];
                                }
                            }
                            sub[n][m] = v;
                        }
                    }
                    for (u, v) in [(0.0, 0.0), (0.3, 0.8), (1.0, 0.5)] {
                        let rows = sub.map(|row| horner_bezier(row, u));
                        let got = horner_bezier(rows, v);
                        let g = [
                            c as f64 + (k as f64 + u) / 4.0,
                            r as f64 + (l as f64 + v) / 4.0,
                        ];
                        assert!((got - s.eval(g)).abs() < 1e-9, "{got} vs {}", s.eval(g));
                    }
                }
            }
        }
    }
}
