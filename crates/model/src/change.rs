//! Where the ground changed between two surveys.
//!
//! Two surveys of the same ground, once one is placed on the other (see [`super::coreg`]),
//! differ by their errors: by no more than both claims together anywhere, and by about their
//! spread over most of the overlap. A difference beyond both (the level of detection) that is
//! also coherent, a patch of ground several cells across rather than a sample at a cliff or a
//! spike, is change: a quarry, a tip, a slide, an eruption. The geomorphic change literature
//! draws the same line (a level of detection from both surveys' errors, then a minimum
//! coherent area); here the errors are the surveys' own claims, kernel by kernel.
//!
//! A change is not an error of either survey: where the surveys' epochs say which saw the
//! ground last, that one serves there (see `Terrain`'s raises), and neither's claim is
//! contested by it. Where they do not, the change is listed and the claims are read as any
//! contradiction is.

use patchwork_geom::Aabb;

/// A coherent region where two surveys differ by more than their level of detection. Heights
/// are the coarser survey's less the finer's (as placed), measured at the finer's samples.
#[derive(Clone, Debug, PartialEq)]
pub struct Change {
    /// Its extent, in the finer survey's plane.
    pub bounds: Aabb,
    /// How many of the finer survey's samples it holds.
    pub samples: u64,
    /// Its area, square metres.
    pub area_m2: f64,
    /// The volume where the coarser survey lies above the finer, cubic metres.
    pub above_m3: f64,
    /// The volume where it lies below, cubic metres (positive).
    pub below_m3: f64,
    /// The largest difference, metres (positive).
    pub most_m: f64,
    /// The finer survey's level-0 kernels that hold it, each with the largest |difference|
    /// there, ascending by kernel.
    pub finer_kernels: Vec<(u32, f32)>,
    /// The same for the coarser survey's kernels.
    pub coarser_kernels: Vec<(u32, f32)>,
}

/// The least level of detection as a multiple of the pair's robust spread once placed: at 3
/// NMADs, one sample in 370 of pure noise passes, and the opening below removes them.
pub const SPREAD_FACTOR: f64 = 3.0;

/// The coherent regions of the samples a grid of `cols` × `rows` marks in `beyond` (those
/// past the level of detection): the mark opened by a square of half side `w` samples (so
/// that no stripe narrower than the square survives: a cliff's line, a row of spikes), then
/// split into 8-connected regions of at least `least` samples. Each region is its samples'
/// indices, row-major, ascending; the regions in the order of their first sample.
pub fn regions(
    beyond: &[bool],
    cols: usize,
    rows: usize,
    w: usize,
    least: usize,
) -> Vec<Vec<usize>> {
    assert_eq!(beyond.len(), cols * rows);
    let eroded = morph(beyond, cols, rows, w, true);
    let opened: Vec<bool> = morph(&eroded, cols, rows, w, false)
        .iter()
        .zip(beyond)
        .map(|(a, b)| *a && *b)
        .collect();
    let mut seen = vec![false; opened.len()];
    let mut out = Vec::new();
    let mut stack = Vec::new();
    for start in 0..opened.len() {
        if !opened[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut region = Vec::new();
        while let Some(i) = stack.pop() {
            region.push(i);
            let (c, r) = ((i % cols) as isize, (i / cols) as isize);
            for dr in -1..=1isize {
                for dc in -1..=1isize {
                    let (cc, rr) = (c + dc, r + dr);
                    if cc < 0 || rr < 0 || cc >= cols as isize || rr >= rows as isize {
                        continue;
                    }
                    let j = rr as usize * cols + cc as usize;
                    if opened[j] && !seen[j] {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        if region.len() >= least {
            region.sort_unstable();
            out.push(region);
        }
    }
    out
}

/// Erosion (`erode`) or dilation of a mask by a square of half side `w`, as two passes of a
/// line of `2w + 1`. Outside the grid counts as unmarked for an erosion: a region at the
/// overlap's edge must be `2w + 1` samples deep inside it.
fn morph(m: &[bool], cols: usize, rows: usize, w: usize, erode: bool) -> Vec<bool> {
    let line = |get: &dyn Fn(usize) -> bool, n: usize, out: &mut dyn FnMut(usize, bool)| {
        // Counts of marks in a sliding window.
        let mut count = 0usize;
        let at = |i: isize| i >= 0 && (i as usize) < n && get(i as usize);
        for i in -(w as isize)..=(w as isize) {
            count += at(i) as usize;
        }
        for i in 0..n {
            let full = 2 * w + 1;
            out(i, if erode { count == full } else { count > 0 });
            let (drop, add) = (i as isize - w as isize, i as isize + w as isize + 1);
            count -= at(drop) as usize;
            count += at(add) as usize;
        }
    };
    let mut a = vec![false; m.len()];
    for r in 0..rows {
        let row = &m[r * cols..(r + 1) * cols];
        let dst = &mut a[r * cols..(r + 1) * cols];
        line(&|i| row[i], cols, &mut |i, v| dst[i] = v);
    }
    let mut b = vec![false; m.len()];
    for c in 0..cols {
        line(&|i| a[i * cols + c], rows, &mut |i, v| b[i * cols + c] = v);
    }
    b
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mask(cols: usize, rows: usize, f: impl Fn(usize, usize) -> bool) -> Vec<bool> {
        (0..rows)
            .flat_map(|r| (0..cols).map(move |c| (c, r)))
            .map(|(c, r)| f(c, r))
            .collect()
    }

    #[test]
    fn a_disc_is_one_region_and_lines_and_specks_are_none() {
        let (cols, rows) = (60, 50);
        let m = mask(cols, rows, |c, r| {
            let disc = (c as f64 - 20.0).hypot(r as f64 - 20.0) <= 6.0;
            // A cliff's line two samples wide, a diagonal one, and scattered specks.
            let line = c == 45 || c == 46;
            let diagonal = c + 3 == r && c > 30;
            let speck = (c * 7 + r * 13) % 97 == 0;
            disc || line || diagonal || speck
        });
        let found = regions(&m, cols, rows, 1, 9);
        assert_eq!(
            found.len(),
            1,
            "{:?}",
            found.iter().map(Vec::len).collect::<Vec<_>>()
        );
        let disc = found[0].len();
        // The opening keeps all of a disc but its sharpest rim.
        assert!((100..=113).contains(&disc), "{disc}");
        // A wider square leaves the two-wide line out too, and the disc in.
        assert_eq!(regions(&m, cols, rows, 2, 9).len(), 1);
    }

    #[test]
    fn two_regions_apart_stay_apart_and_small_ones_are_dropped() {
        let (cols, rows) = (40, 20);
        let m = mask(cols, rows, |c, r| {
            (2..8).contains(&c) && (2..8).contains(&r)
                || (20..35).contains(&c) && (5..15).contains(&r)
                || (12..15).contains(&c) && (12..15).contains(&r)
        });
        let found = regions(&m, cols, rows, 1, 10);
        assert_eq!(
            found.iter().map(Vec::len).collect::<Vec<_>>(),
            vec![36, 150]
        );
    }
}
