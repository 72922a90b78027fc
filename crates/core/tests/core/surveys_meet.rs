//! Where surveys meet, on real terrain: a finer copy serves the small errors, a height does not
//! depend on the region that holds it, tiles of one mosaic join as one survey, no valid sample
//! is lost and no void is filled, and the edges of the input space have answers.

use crate::common;

use common::*;
use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::AccuracySpec::Auto;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::patch::Blend;
use patchwork_core::resample::{cpu, SampleGrid, BLOCK};
use patchwork_core::terrain::Terrain;

fn cop() -> Grid {
    real_crop("copernicus_n34w119_crop.tif")
}

/// The bounds of a rectangle of pixels of a north-up grid: columns [c0, c1), rows [r0, r1).
fn pixels(g: &Grid, c0: f64, r0: f64, c1: f64, r1: f64) -> Aabb {
    Aabb::of_points(&[
        g.georef.to_world(c0 - 0.5, r0 - 0.5),
        g.georef.to_world(c1 - 0.5, r1 - 0.5),
    ])
}

/// Largest |a − b| where both are data, less one f32 step of the height: two tiles compute
/// the same point from their own origins, so positions differ in the last bits and a height
/// may round to the next f32 (0.12 mm above 1,024 m). Panics where one is data and the other
/// is not.
fn max_diff(a: &[f32], b: &[f32], what: &str) -> f64 {
    a.iter()
        .zip(b)
        .enumerate()
        .map(|(i, (x, y))| {
            assert_eq!(x.is_nan(), y.is_nan(), "{what}: masks differ at sample {i}");
            if x.is_nan() {
                return 0.0;
            }
            let step = (f32::from_bits(x.abs().to_bits() + 1) - x.abs()) as f64;
            ((*x as f64 - *y as f64).abs() - step).max(0.0)
        })
        .fold(0.0, f64::max)
}

#[test]
fn a_finer_copy_of_the_same_ground_serves_the_small_errors() {
    // A 90 m copy of the 30 m crop, both with ε estimated from their own samples.
    let fine = survey_with(cop(), Auto);
    let coarse = survey_with(decimate(&cop(), 3), Auto);
    assert!(
        fine.accuracy < coarse.accuracy,
        "fine ε {} not below coarse ε {}",
        fine.accuracy,
        coarse.accuracy
    );
    let t = terrain_of(&[coarse.clone(), fine.clone()]);
    let g = &fine.levels[0];
    let roi = pixels(g, 40.0, 60.0, 250.0, 240.0);
    let grid = SampleGrid::uniform(&roi, 180, 150);
    for e in [0.0, 1.0, fine.accuracy] {
        let tile = t.tile(&roi, 180, 150, e);
        assert!(
            tile.patches.iter().all(|x| x.survey != coarse.id),
            "e = {e}: the coarse copy serves where the fine one is as good"
        );
        let worst = grid
            .points()
            .zip(&tile.heights)
            .filter_map(|(p, z)| Some((g.bilinear(p)? - *z as f64).abs()))
            .fold(0.0, f64::max);
        assert!(worst < 1e-3, "e = {e}: {worst} m off the fine survey");
    }
    // Past the coarse copy's error it takes over where it can, within the bound.
    let e = 2.0 * coarse.accuracy;
    let tile = t.tile(&roi, 180, 150, e);
    assert!(tile.patches.iter().any(|x| x.survey == coarse.id));
    for (p, z) in grid.points().zip(&tile.heights) {
        if let Some(h) = g.bilinear(p) {
            let hs = survey_heights(&[fine.clone(), coarse.clone()], p);
            let lo = hs.iter().cloned().fold(h, f64::min);
            let hi = hs.iter().cloned().fold(h, f64::max);
            assert!(*z as f64 >= lo - e - 1e-3 && *z as f64 <= hi + e + 1e-3);
        }
    }
}

#[test]
fn a_height_does_not_depend_on_the_region_that_holds_it() {
    // ε = 2 over the middle of the crop, overlapped by a coarser ε = 20 copy of all of it.
    let fine = survey_with(window(&cop(), 60, 50, 180, 200), 2.0);
    let coarse = survey_with(decimate(&cop(), 2), 20.0);
    let mut t = terrain_of(&[fine.clone(), coarse.clone()]);
    let g = &cop();
    let (w, h) = (120usize, 90usize);
    let (c0, r0, c1, r1) = (10.0, 20.0, 290.0, 290.0);
    let whole = pixels(g, c0, r0, c1, r1);
    // Sub-tiles share the whole tile's sample positions: split at pixel boundaries of the tile.
    let cuts_x = [0usize, 37, 80, w];
    let cuts_y = [0usize, 50, h];
    let dx = (c1 - c0) / w as f64;
    let dy = (r1 - r0) / h as f64;
    for (blend, e) in Blend::ALL
        .into_iter()
        .flat_map(|b| [0.0, 2.0, 10.0, 25.0].map(|e| (b, e)))
    {
        println!("{} blend, e = {e}", blend.name());
        t.set_blend(blend);
        let big = t.tile(&whole, w, h, e);
        for jy in 0..cuts_y.len() - 1 {
            for ix in 0..cuts_x.len() - 1 {
                let (a0, a1) = (cuts_x[ix], cuts_x[ix + 1]);
                let (b0, b1) = (cuts_y[jy], cuts_y[jy + 1]);
                let roi = pixels(
                    g,
                    c0 + a0 as f64 * dx,
                    r0 + b0 as f64 * dy,
                    c0 + a1 as f64 * dx,
                    r0 + b1 as f64 * dy,
                );
                let sub = t.tile(&roi, a1 - a0, b1 - b0, e);
                let want: Vec<f32> = (b0..b1)
                    .flat_map(|j| big.heights[j * w + a0..j * w + a1].to_vec())
                    .collect();
                let d = max_diff(&sub.heights, &want, &format!("e = {e}, sub-tile {ix},{jy}"));
                assert!(
                    d <= 1e-4,
                    "e = {e}: sub-tile {ix},{jy} is {d} m off the whole"
                );
            }
        }
        // Heights at the same points asked one by one are the tile's too.
        let grid = SampleGrid::uniform(&whole, w, h);
        let picks: Vec<usize> = (0..w * h).step_by(97).collect();
        let pts: Vec<[f64; 2]> = picks.iter().map(|&i| grid.point(i)).collect();
        let one_by_one = t.sample(&pts, e);
        let want: Vec<f32> = picks.iter().map(|&i| big.heights[i]).collect();
        assert!(max_diff(&one_by_one, &want, "points") <= 1e-4);
        // Wherever the ε = 2 survey has data, the answer is within the error asked of it; past
        // the coarse survey's ε, within the error of one of the two.
        let bound = e.max(2.0);
        let (mut worst, mut n) = (0.0f64, 0);
        for (p, z) in grid.points().zip(&big.heights) {
            let Some(hf) = fine.levels[0].bilinear(p) else {
                continue;
            };
            let off = if e < 20.0 {
                (hf - *z as f64).abs()
            } else {
                let hs = survey_heights(&[fine.clone(), coarse.clone()], p);
                let lo = hs.iter().cloned().fold(f64::INFINITY, f64::min);
                let hi = hs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                (lo - *z as f64).max(*z as f64 - hi).max(0.0)
            };
            worst = worst.max(off);
            n += 1;
        }
        assert!(n > 1000 && worst <= bound + 1e-3, "e = {e}: {worst} m off");
    }
}

#[test]
fn tiles_of_one_mosaic_join_as_one_survey() {
    let whole = cop();
    let half = 150;
    let pieces: Vec<_> = [(0, 0), (half, 0), (0, half), (half, half)]
        .iter()
        .map(|&(c, r)| survey_with(window(&whole, c, r, half, half), 1.0))
        .collect();
    let mut one = terrain_of(&[survey_with(whole.clone(), 1.0)]);
    let mut mosaic = terrain_of(&pieces);
    // Across the whole footprint, out to the outer pixel edges, at sizes that put samples on
    // and between the seams.
    let roi = pixels(&whole, 0.0, 0.0, 300.0, 300.0);
    for blend in Blend::ALL {
        one.set_blend(blend);
        mosaic.set_blend(blend);
        for (w, h) in [(300, 300), (347, 311), (600, 600)] {
            for e in [0.0, 1.0, 8.0] {
                let a = one.tile(&roi, w, h, e).heights;
                let b = mosaic.tile(&roi, w, h, e).heights;
                assert!(a.iter().all(|z| !z.is_nan()), "nodata in the whole survey");
                let what = format!("{} blend, {w}×{h}, e = {e}", blend.name());
                let d = max_diff(&a, &b, &what);
                // At e = 0 the seams are interpolated exactly as across the whole grid.
                let tol = if e <= 1.0 { 1e-3 } else { e };
                assert!(d <= tol, "{what}: mosaic {d} m off the whole survey");
            }
        }
    }
    // The seam between the pieces is served by edge patches made from both sides.
    assert!(
        mosaic.edges().any(|x| x.members.len() == 4),
        "no patch holds the corner of four"
    );
    // Order and retirement do not matter.
    let reversed: Vec<_> = pieces.iter().rev().cloned().collect();
    assert_eq!(
        mosaic.index().state(),
        terrain_of(&reversed).index().state()
    );
    let mut less = mosaic.clone();
    less.retire(pieces[1].id).unwrap();
    let never = terrain_of(&[pieces[0].clone(), pieces[2].clone(), pieces[3].clone()]);
    assert_eq!(less.index().state(), never.index().state());
}

/// A terrain that reads its samples from a store lets go of its edge patches' samples and
/// makes them again from their members' when a read needs them: to the bit those the patches
/// were built with, tiles to the bit, from any snapshot, one that a retirement has since
/// moved on from too. The mosaic is split at a random column and row.
#[test]
fn edge_patches_made_again_from_their_members_are_the_ones_built() {
    use patchwork_core::model::edge::EdgeGrid;
    use patchwork_core::model::source::MemorySource;
    use std::sync::Arc;
    let whole = cop();
    let mut draw = patchwork_core::geom::rng::uniform(seed());
    let (cols, rows) = (whole.cols, whole.rows);
    let cs = 40 + (draw() * (cols - 80) as f64) as usize;
    let rs = 40 + (draw() * (rows - 80) as f64) as usize;
    println!("split at column {cs} and row {rs}");
    let pieces: Vec<_> = [
        (0, 0, cs, rs),
        (cs, 0, cols - cs, rs),
        (0, rs, cs, rows - rs),
        (cs, rs, cols - cs, rows - rs),
    ]
    .iter()
    .map(|&(c, r, w, h)| survey_with(window(&whole, c, r, w, h), 1.0))
    .collect();
    let held = terrain_of(&pieces);
    assert!(held.edges().count() > 0 && held.edges().all(|e| e.grid.is_some()));
    let mut lean = held.clone();
    lean.set_source(Arc::new(MemorySource::of(
        pieces.iter().map(|s| s.as_ref()),
    )));
    for s in &pieces {
        lean.page_out(s.id);
    }
    assert!(lean.edges().all(|e| e.grid.is_none()));
    let same = |a: &EdgeGrid, b: &EdgeGrid| {
        let bits = |g: &EdgeGrid| {
            g.kept_heights()
                .iter()
                .map(|z| z.to_bits())
                .collect::<Vec<_>>()
        };
        a.kept() == b.kept()
            && bits(a) == bits(b)
            && a.kept_flags() == b.kept_flags()
            && a.slope.to_bits() == b.slope.to_bits()
            && a.georef == b.georef
    };
    let made_again = |t: &Terrain, of: &Terrain| {
        for e in of.edges() {
            let Some(x) = t.edge(e.owner).filter(|x| x.id == e.id) else {
                panic!("edge patch {} is not in the terrain", e.id);
            };
            let g = t.edge_grid(x).expect("the members' samples");
            assert!(
                same(&g, e.grid.as_ref().expect("built with its samples")),
                "edge patch {} made again is not the one built",
                e.id
            );
        }
    };
    made_again(&lean, &held);
    let roi = pixels(&whole, 0.0, 0.0, (cols - 1) as f64, (rows - 1) as f64);
    for e in [0.0, 2.0] {
        let (a, b) = (held.tile(&roi, 257, 263, e), lean.tile(&roi, 257, 263, e));
        assert!(
            a.heights
                .iter()
                .zip(&b.heights)
                .all(|(x, y)| x.to_bits() == y.to_bits()),
            "e = {e}: the tile differs"
        );
    }
    // A snapshot taken before a retirement still makes its own edge patches, with a cache
    // of its own so that nothing is found ready.
    let mut old = lean.clone();
    let gone = (draw() * 4.0) as usize % 4;
    lean.retire(pieces[gone].id).unwrap();
    assert!(
        old.edges()
            .any(|e| lean.edge(e.owner).is_none_or(|x| x.id != e.id)),
        "the retirement changed no edge patch"
    );
    old.set_edge_cache(1 << 20);
    made_again(&old, &held);
    // And the terrain after it makes those of a terrain that never had the piece.
    let rest: Vec<_> = (0..4)
        .filter(|&k| k != gone)
        .map(|k| pieces[k].clone())
        .collect();
    made_again(&lean, &terrain_of(&rest));
}

/// Checks a survey alone: every valid sample comes back exactly at e = 0, by point and by
/// tile; nothing is made up outside the pixels of valid samples; and a cell with three valid
/// corners is the plane through them. Returns how many valid samples are in no whole cell.
fn nothing_lost_nothing_invented(g: Grid) -> usize {
    let s = survey_with(g.clone(), Auto);
    let mut t = terrain_of(std::slice::from_ref(&s));
    let mut loose = 0;
    for blend in Blend::ALL {
        println!("{} blend", blend.name());
        t.set_blend(blend);
        loose = nothing_lost_nothing_invented_by(&g, &t);
    }
    loose
}

/// [`nothing_lost_nothing_invented`] of `g` with its terrain `t`, blended as `t` blends.
fn nothing_lost_nothing_invented_by(g: &Grid, t: &Terrain) -> usize {
    let mut pts = Vec::new();
    let mut want = Vec::new();
    let mut loose = 0;
    for r in 0..g.rows {
        for c in 0..g.cols {
            if !g.is_valid(c, r) {
                continue;
            }
            pts.push(g.georef.to_world(c as f64, r as f64));
            want.push(g.at(c, r));
            let in_cell = (r.saturating_sub(1)..=r.min(g.rows - 2))
                .any(|rr| (c.saturating_sub(1)..=c.min(g.cols - 2)).any(|cc| g.cell_valid(cc, rr)));
            if !in_cell {
                loose += 1;
                // A one-pixel tile centred on it.
                let p = pts.last().unwrap();
                let step = g.georef.step;
                let roi = Aabb::new(
                    p[0] - step[0] / 2.0,
                    p[1] - step[1] / 2.0,
                    p[0] + step[0] / 2.0,
                    p[1] + step[1] / 2.0,
                );
                let z = t.tile(&roi, 1, 1, 0.0).heights[0];
                assert!((z - g.at(c, r)).abs() < 1e-3, "1×1 tile at ({c}, {r}): {z}");
            }
        }
    }
    let got = t.sample(&pts, 0.0);
    for ((p, z), w) in pts.iter().zip(&got).zip(&want) {
        assert!(
            (z - w).abs() < 1e-3,
            "{z} instead of the sample {w} at {p:?}"
        );
    }
    // A tile at three samples per pixel: data exactly in the pixels of valid samples, and
    // the plane through three valid corners inside their triangle.
    let roi = pixel_bounds(g);
    let (w, h) = (3 * g.cols, 3 * g.rows);
    let tile = t.tile(&roi, w, h, 0.0);
    let grid = SampleGrid::uniform(&roi, w, h);
    let mut triangles = 0;
    for (p, z) in grid.points().zip(&tile.heights) {
        assert_eq!(
            pixel_valid(g, p),
            !z.is_nan(),
            "at {p:?}: {z} where the pixel is {}",
            if pixel_valid(g, p) { "data" } else { "void" }
        );
        let q = g.georef.to_grid(p);
        let (c, r) = (q[0].floor(), q[1].floor());
        if c < 0.0 || r < 0.0 || c as usize + 1 >= g.cols || r as usize + 1 >= g.rows {
            continue;
        }
        let (c, r) = (c as usize, r as usize);
        let (fx, fy) = (q[0] - c as f64, q[1] - r as f64);
        let v = [
            g.is_valid(c, r),
            g.is_valid(c + 1, r),
            g.is_valid(c, r + 1),
            g.is_valid(c + 1, r + 1),
        ];
        if v.iter().filter(|&&b| b).count() != 3 {
            continue;
        }
        // Barycentric weights of the valid triangle; inside it when all are ≥ 0.
        let zc = |dc: usize, dr: usize| g.at(c + dc, r + dr) as f64;
        let plane = match v.iter().position(|&b| !b).unwrap() {
            3 if fx + fy <= 1.0 => {
                Some(zc(0, 0) + (zc(1, 0) - zc(0, 0)) * fx + (zc(0, 1) - zc(0, 0)) * fy)
            }
            0 if fx + fy >= 1.0 => Some(
                zc(1, 1) + (zc(0, 1) - zc(1, 1)) * (1.0 - fx) + (zc(1, 0) - zc(1, 1)) * (1.0 - fy),
            ),
            1 if fy >= fx => {
                Some(zc(0, 0) + (zc(1, 1) - zc(0, 1)) * fx + (zc(0, 1) - zc(0, 0)) * fy)
            }
            2 if fx >= fy => {
                Some(zc(0, 0) + (zc(1, 0) - zc(0, 0)) * fx + (zc(1, 1) - zc(1, 0)) * fy)
            }
            _ => None,
        };
        if let Some(want) = plane {
            triangles += 1;
            assert!(
                (*z as f64 - want).abs() < 1e-3,
                "{z} off the valid triangle's {want} at {p:?}"
            );
        }
    }
    assert!(
        triangles > 0,
        "no point in a three-cornered cell was checked"
    );
    loose
}

#[test]
fn no_valid_sample_is_lost_and_no_void_is_filled() {
    let holes = real_crop("srtm_n44e005_big_hole_crop.tif");
    let voids = holes.samples.iter().filter(|z| z.is_nan()).count() as f64;
    assert!(voids / holes.samples.len() as f64 > 0.7);
    nothing_lost_nothing_invented(holes);
    // Scattered soundings: a quarter of the samples, most of them in no whole cell.
    let soundings = sparse(&cop(), 0.25, 11);
    let valid = soundings.valid_count();
    let loose = nothing_lost_nothing_invented(soundings);
    println!("soundings: {loose} of {valid} valid samples are in no whole cell");
    assert!(
        loose * 3 > valid,
        "only {loose} of {valid} samples are outside whole cells"
    );
}

#[test]
fn the_edges_of_the_input_space_have_answers() {
    let s = survey_with(cop(), Auto);
    let mut t = Terrain::new(IndexConfig::default());
    t.insert(s.clone());
    let roi = s.levels[0].world_bounds();
    let top = IndexConfig::default().max_error;
    for e in [top, 2.0 * top, 1e300] {
        let ps = t.uniform(&roi, e);
        assert!(!ps.is_empty(), "e = {e}: no patches");
        assert_eq!(ps, t.uniform(&roi, top), "e = {e} is not the coarsest cut");
        let tile = t.tile(&roi, 32, 32, e);
        assert!(tile.heights.iter().all(|z| !z.is_nan()), "e = {e}: nodata");
    }
    // One point, and points along a line, are answered like any others.
    let g = &s.levels[0];
    let one = [g.georef.to_world(100.0, 120.0)];
    assert!((t.sample(&one, 0.0)[0] - g.at(100, 120)).abs() < 1e-3);
    let column: Vec<[f64; 2]> = (0..20)
        .map(|r| g.georef.to_world(33.0, r as f64 * 7.0))
        .collect();
    let row: Vec<[f64; 2]> = (0..20)
        .map(|c| g.georef.to_world(c as f64 * 7.0, 33.0))
        .collect();
    for (k, z) in t.sample(&column, 0.0).iter().enumerate() {
        assert!((z - g.at(33, k * 7)).abs() < 1e-3);
    }
    for (k, z) in t.sample(&row, 0.0).iter().enumerate() {
        assert!((z - g.at(k * 7, 33)).abs() < 1e-3);
    }
}

#[test]
fn surveys_on_different_lattices_with_less_than_a_cell_between_them_leave_no_gap() {
    // The west half at 30 m, and the east half as a 90 m survey whose first sample is two fine
    // cells past the fine survey's last: 0.67 of its own cells, so their pixels meet.
    let whole = cop();
    let west = window(&whole, 0, 0, 150, 300);
    let east = decimate(&window(&whole, 151, 0, 149, 300), 3);
    for spec in [1.0, 5.0] {
        let w = survey_with(west.clone(), spec);
        let e = survey_with(east.clone(), 3.0 * spec);
        let mut t = terrain_of(&[w.clone(), e.clone()]);
        // A band across the join, finer than either survey, out to the outer pixel rows.
        let roi = pixels(&whole, 120.0, 0.0, 180.0, 298.0);
        for (blend, err) in Blend::ALL
            .into_iter()
            .flat_map(|b| [0.0, spec, 3.0 * spec, 50.0].map(|e| (b, e)))
        {
            t.set_blend(blend);
            let tile = t.tile(&roi, 240, 200, err);
            let grid = SampleGrid::uniform(&roi, 240, 200);
            // Each patch is within its error of its own survey, and the blend is convex.
            let bound = tile
                .patches
                .iter()
                .map(|x| x.span.min_z)
                .fold(0.0, f64::max);
            for (p, z) in grid.points().zip(&tile.heights) {
                assert!(!z.is_nan(), "a gap at {p:?}, e = {err}, {blend:?}");
                let hs = survey_heights(&[w.clone(), e.clone()], p);
                let lo = hs.iter().cloned().fold(f64::INFINITY, f64::min);
                let hi = hs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                assert!(
                    (*z as f64) >= lo - bound - 1e-3 && (*z as f64) <= hi + bound + 1e-3,
                    "{z} outside [{lo}, {hi}] ± {bound} at {p:?}, {blend:?}"
                );
            }
        }
    }
}

/// A finer copy with voids (edge patches), a coarser one of estimated accuracy (fallback tiers
/// below it) and a rotated one (resampled a point at a time inside a north-up tile).
fn every_kind_of_patch() -> Vec<std::sync::Arc<patchwork_core::model::survey::Survey>> {
    let g = cop();
    vec![
        survey_with(sparse(&window(&g, 20, 30, 200, 180), 0.9, 7), 1.0),
        survey_with(decimate(&g, 3), Auto),
        survey_with(turned(&window(&g, 120, 100, 120, 120), 17.0), 2.0),
    ]
}

/// Resamples tiles of odd sizes that start anywhere over `t`, at several errors, by rows and
/// columns and point by point, and fails on any height that differs by a bit. Returns the
/// heights compared and the blocks that one patch served alone.
fn by_rows_equals_by_points(t: &Terrain, b: Aabb, sizes: &[(usize, usize)]) -> (usize, usize) {
    let (w, h) = (b.width(), b.height());
    let rois = [
        b,
        Aabb::new(
            b.min[0] + 0.2 * w,
            b.min[1] + 0.3 * h,
            b.min[0] + 0.45 * w,
            b.min[1] + 0.5 * h,
        ),
        Aabb::new(
            b.min[0] + 0.31 * w,
            b.min[1] + 0.27 * h,
            b.min[0] + 0.93 * w,
            b.min[1] + 0.71 * h,
        ),
    ];
    let (mut compared, mut alone) = (0, 0);
    for roi in rois {
        for e in [0.0, 2.0, 10.0, 60.0] {
            for &(width, height) in sizes {
                let grid = SampleGrid::uniform(&roi, width, height);
                let ps = t.uniform(&roi, e);
                // Blocks one patch serves alone take the resampler's short path.
                alone += cpu::blocks_alone(&t.resolve(&ps), &grid).0;
                let fast = t.resample(ps.clone(), &grid).heights;
                let slow = t.resample(ps, &grid.clone().pointwise()).heights;
                for (k, (a, b)) in fast.iter().zip(&slow).enumerate() {
                    assert!(
                        a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()) || a == b,
                        "{roi:?} e = {e} {width}x{height} sample {k}: {a} by rows, {b} by points ({:?})",
                        t.blend()
                    );
                }
                compared += fast.iter().filter(|z| !z.is_nan()).count();
            }
        }
    }
    (compared, alone)
}

#[test]
fn a_north_up_tile_resampled_by_rows_and_columns_is_the_pointwise_one_to_the_bit() {
    // Every kind of patch at once: a finer copy with voids (edge patches), a coarser one of
    // estimated accuracy (fallback tiers below it), a rotated one (resampled a point at a
    // time inside the same tile), each at several errors.
    let surveys = every_kind_of_patch();
    let mut t = terrain_of(&surveys);
    for blend in Blend::ALL {
        t.set_blend(blend);
        let (compared, _) =
            by_rows_equals_by_points(&t, bounds_of(&surveys), &[(97, 61), (256, 256), (33, 190)]);
        assert!(
            compared > 300_000,
            "{blend:?}: only {compared} heights compared"
        );
    }
}

#[test]
fn blocks_that_one_patch_serves_alone_get_the_blend_to_the_bit() {
    // Two surveys of one ground side by side with an overlap, one with a hole, and a coarser
    // copy of estimated accuracy under both (fallback tiers of another resolution): most
    // blocks of a fine tile lie inside one kernel, and the short path must give what the
    // blend gives, at the voids, the kernels' edges, the margins and where the tiers meet.
    let g = cop();
    let mut holed = window(&g, 140, 60, 160, 200);
    for r in 80..95 {
        for c in 40..70 {
            holed.samples[r * holed.cols + c] = f32::NAN;
        }
    }
    let surveys = vec![
        survey_with(window(&g, 0, 0, 180, 240), 1.0),
        survey_with(holed, 2.0),
        survey_with(decimate(&window(&g, 0, 0, 300, 240), 2), Auto),
    ];
    let mut t = terrain_of(&surveys);
    for blend in Blend::ALL {
        t.set_blend(blend);
        let (compared, alone) =
            by_rows_equals_by_points(&t, bounds_of(&surveys), &[(300, 401), (512, 512)]);
        println!("{blend:?}: {alone} blocks served by one patch, {compared} heights compared");
        assert!(
            compared > 1_000_000,
            "{blend:?}: only {compared} heights compared"
        );
        assert!(
            alone > 1_000,
            "{blend:?}: only {alone} blocks served by one patch"
        );
    }
}

#[test]
fn each_block_is_binned_every_patch_whose_window_meets_it_and_no_other() {
    // Binning finds a north-up grid's blocks by bisection along its axes and any other
    // grid's by buckets; the plain test of every patch against every block is the reference.
    // Surveys of several levels, edge patches and a rotated survey, on north-up grids (their
    // axes either way round), in blocks and in the GPU's squares of 8 × 8 blocks, and on a
    // grid of scattered points with holes in it.
    let surveys = every_kind_of_patch();
    let t = terrain_of(&surveys);
    let b = bounds_of(&surveys);
    let inner = Aabb::new(
        b.min[0] + 0.31 * b.width(),
        b.min[1] + 0.27 * b.height(),
        b.min[0] + 0.93 * b.width(),
        b.min[1] + 0.71 * b.height(),
    );
    let mut seen = 0;
    for roi in [b, inner] {
        for e in [0.0, 10.0] {
            let set = t.resolve(&t.uniform(&roi, e));
            let uniform = SampleGrid::uniform(&roi, 97, 61);
            let scattered = SampleGrid::of_points(
                40,
                30,
                (0..1200)
                    .map(|k| {
                        let (i, j) = ((k * 7919) % 1200, (k * 104_729) % 1200);
                        if k % 13 == 0 {
                            [f64::NAN, f64::NAN]
                        } else {
                            [
                                roi.min[0] + roi.width() * i as f64 / 1200.0,
                                roi.min[1] + roi.height() * j as f64 / 1200.0,
                            ]
                        }
                    })
                    .collect(),
            );
            let axes = uniform.axes.clone().expect("a uniform grid has axes");
            let reversed = SampleGrid::of_axes(
                axes.xs.iter().rev().copied().collect(),
                axes.ys.iter().rev().copied().collect(),
            );
            // Columns that go back and forth bound no block by their ends.
            let mut xs = axes.xs.clone();
            xs.swap(3, 40);
            let zigzag = SampleGrid::of_axes(xs, axes.ys.clone());
            let squares = [BLOCK, 8 * BLOCK];
            for (grid, side) in [uniform, reversed, zigzag, scattered]
                .into_iter()
                .flat_map(|g| squares.map(|s| (g.clone(), s)))
            {
                let bins = cpu::bin_squares(&set.patches, &grid, side);
                let want: Vec<Vec<u32>> = grid
                    .bounds_of(side)
                    .iter()
                    .map(|bb| match bb {
                        Some(bb) => (0..set.patches.len() as u32)
                            .filter(|&k| set.patches[k as usize].reach().intersects(bb))
                            .collect(),
                        None => Vec::new(),
                    })
                    .collect();
                assert_eq!(bins, want, "{roi:?} e = {e}, squares of {side}");
                seen += bins.iter().map(Vec::len).sum::<usize>();
            }
        }
    }
    assert!(seen > 1000, "only {seen} patches binned");
}

/// The accurate blend's bound (docs/MODEL.md, "Resampling"): a height is a convex combination
/// of the patches laid over the point up to the first whose kernel holds it, so it lies within
/// that patch's error e* of the surveys there, where Formula 1 promises only the largest error
/// of every patch that reaches the point. Where the first patch that reaches a point holds it
/// in its kernel, the height is that patch's, to the bit. Scenes a fine survey nested in a
/// coarse copy and the Copernicus and NASADEM pair; regions and errors drawn at random.
#[test]
fn the_accurate_blend_keeps_the_bound_of_the_first_kernel_that_holds_a_point() {
    let seed = seed();
    let mut draw = patchwork_core::geom::rng::uniform(seed);
    let g = cop();
    let scenes = [
        (
            "nested",
            vec![
                survey_with(window(&g, 60, 50, 180, 200), 2.0),
                survey_with(decimate(&g, 2), 20.0),
            ],
        ),
        (
            "pair",
            vec![
                survey_with(g.clone(), Auto),
                survey_with(real_crop("nasadem_n34w119_crop.tif"), Auto),
            ],
        ),
    ];
    let (mut checked, mut exact, mut tighter) = (0usize, 0usize, 0usize);
    for (name, surveys) in &scenes {
        let mut t = terrain_of(surveys);
        t.set_blend(Blend::Accurate);
        let b = bounds_of(surveys);
        for _ in 0..6 {
            let (fw, fh) = (0.15 + 0.5 * draw(), 0.15 + 0.5 * draw());
            let (x0, y0) = (
                b.min[0] + (1.0 - fw) * draw() * b.width(),
                b.min[1] + (1.0 - fh) * draw() * b.height(),
            );
            let roi = Aabb::new(x0, y0, x0 + fw * b.width(), y0 + fh * b.height());
            let e = [0.0, 1.0, 3.0, 8.0, 20.0, 40.0][(draw() * 6.0) as usize];
            let grid = SampleGrid::uniform(&roi, 96, 80);
            let set = t.resolve(&t.uniform(&roi, e));
            let heights = cpu::resample(&set, &grid);
            for (k, h) in heights.iter().enumerate() {
                if h.is_nan() {
                    continue;
                }
                let p = grid.point(k);
                // The patches that reach p in the set's order, up to the first whose kernel
                // holds p (weight 1), less those of a tier worse than the first that covers it.
                let hits: Vec<_> = set
                    .patches
                    .iter()
                    .filter_map(|q| q.at(p).map(|(w, hit)| (q, w, hit)))
                    .collect();
                let mut counted = Vec::new();
                let mut stop = u32::MAX;
                for &(q, w, hit) in &hits {
                    if q.tier() > stop {
                        break;
                    }
                    counted.push((q, hit));
                    if hit.covered {
                        stop = stop.min(q.tier());
                    }
                    if w == 1.0 {
                        break;
                    }
                }
                let e_star = counted.iter().map(|(q, _)| q.error).fold(0.0, f64::max);
                let e_all = hits.iter().map(|(q, _, _)| q.error).fold(0.0, f64::max);
                if counted.len() == 1 && hits[0].1 == 1.0 {
                    assert_eq!(
                        h.to_bits(),
                        (counted[0].1.z as f32).to_bits(),
                        "{name}, seed {seed}: the first patch holds {p:?} but {h} is not its {}",
                        counted[0].1.z
                    );
                    exact += 1;
                }
                let hs = survey_heights(surveys, p);
                if hs.is_empty() {
                    continue;
                }
                let lo = hs.iter().cloned().fold(f64::INFINITY, f64::min);
                let hi = hs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                let z = *h as f64;
                assert!(
                    z >= lo - e_star - 1e-3 && z <= hi + e_star + 1e-3,
                    "{name}, seed {seed}, e = {e}: {z} outside [{lo}, {hi}] ± {e_star} at {p:?}"
                );
                checked += 1;
                tighter += usize::from(e_star < e_all);
            }
        }
    }
    println!(
        "{checked} heights within e* of the surveys, {exact} of them one patch's to the bit; \
         e* below Formula 1's bound at {tighter}"
    );
    assert!(
        checked > 20_000 && exact > checked / 4,
        "too few heights checked"
    );
}

/// Where a kernel's neighbour claims a larger ε, the accurate blend gives the patch no weight
/// beyond that side and ramps it down inside its kernel instead (`ResolvedPatch::closed`).
/// Heights must stay continuous across such an edge: on the Copernicus and NASADEM pair, whose
/// estimated claims differ from kernel to kernel, at points drawn at random along every closed
/// edge, just inside and just outside it.
#[test]
fn heights_stay_continuous_across_a_closed_side_of_a_kernel() {
    let seed = seed();
    let mut draw = patchwork_core::geom::rng::uniform(seed);
    let surveys = vec![
        survey_with(cop(), Auto),
        survey_with(real_crop("nasadem_n34w119_crop.tif"), Auto),
    ];
    let mut t = terrain_of(&surveys);
    t.set_blend(Blend::Accurate);
    let b = bounds_of(&surveys);
    let (mut edges, mut worst) = (0usize, 0.0f64);
    for e in [0.0, 2.0, 6.0, 15.0] {
        let set = t.resolve(&t.uniform(&b, e));
        let all: Vec<u32> = (0..set.patches.len() as u32).collect();
        for q in set.patches.iter().filter(|q| q.closed != 0) {
            let k = q.kernel;
            let world = |c: f64, r: f64| {
                let (du, dv) = (c / q.inv_step[0], r / q.inv_step[1]);
                [
                    q.origin[0] + du * q.axes[0][0] + dv * q.axes[1][0],
                    q.origin[1] + du * q.axes[0][1] + dv * q.axes[1][1],
                ]
            };
            for side in (0..4).filter(|s| q.closed & (1 << s) != 0) {
                edges += 1;
                // Across the side, 10⁻⁶ of a cell either way of it, somewhere along it.
                let mut along = |lo: u32, hi: u32| lo as f64 + draw() * (hi - lo) as f64;
                let (inside, outside) = match side {
                    0 => {
                        let r = along(k.r0, k.r1);
                        (world(k.c0 as f64 + 1e-6, r), world(k.c0 as f64 - 1e-6, r))
                    }
                    1 => {
                        let c = along(k.c0, k.c1);
                        (world(c, k.r0 as f64 + 1e-6), world(c, k.r0 as f64 - 1e-6))
                    }
                    2 => {
                        let r = along(k.r0, k.r1);
                        (world(k.c1 as f64 - 1e-6, r), world(k.c1 as f64 + 1e-6, r))
                    }
                    _ => {
                        let c = along(k.c0, k.c1);
                        (world(c, k.r1 as f64 - 1e-6), world(c, k.r1 as f64 + 1e-6))
                    }
                };
                let (hi, ho) = (
                    cpu::blend(&set, &all, inside),
                    cpu::blend(&set, &all, outside),
                );
                if hi.is_nan() || ho.is_nan() {
                    // A void's edge: no height to be continuous with.
                    continue;
                }
                let d = (hi as f64 - ho as f64).abs();
                assert!(
                    d < 1e-3,
                    "seed {seed}, e = {e}: {hi} inside and {ho} outside a closed side of patch \
                     {:?} at {inside:?}",
                    q.id
                );
                worst = worst.max(d);
            }
        }
    }
    println!("{edges} closed sides crossed; the largest step across one is {worst:.2e} m");
    assert!(edges > 100, "only {edges} closed sides in the pair");
}
