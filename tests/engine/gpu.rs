//! The GPU resampler against the CPU one: the same nodata mask and heights within 1 mm (two
//! f32 steps of the height, which is 2 mm above 8,192 m), plus 2·10⁻⁵ of the spread of the
//! heights blended at the point (see `src/resample/gpu.rs`: where the weight ramp at a survey's
//! edge blends surveys hundreds of metres apart, the f32 weight's rounding shows), on synthetic
//! rotated grids with voids, on the committed real crops, where surveys meet, and with surveys
//! of other CRSs read through the store-to-survey lattice, for uniform
//! and view-dependent sample grids, each with Formula 1 and with the accurate blend.
//!
//! Without a GPU adapter these tests say so and pass, unless PATCHWORK_REQUIRE_GPU=1 (as CI
//! sets it, with a software Vulkan driver installed), where they fail.

use crate::common;

use common::*;
use patchwork::gpu::{Emulated, GpuResampler};
use patchwork_core::geom::Aabb;
use patchwork_core::index::query::{Metric, ViewQuery};
use patchwork_core::model::patch::Blend;
use patchwork_core::model::survey::Survey;
use patchwork_core::resample::{cpu, PatchSet, SampleGrid};
use patchwork_core::terrain::Terrain;
use std::sync::Arc;

const TOLERANCE: f64 = 1e-3;

fn gpu() -> Option<GpuResampler> {
    match GpuResampler::new(Emulated::Allow) {
        Ok(g) => {
            println!("GPU adapter: {}", g.adapter());
            Some(g)
        }
        Err(e) => {
            if std::env::var("PATCHWORK_REQUIRE_GPU").as_deref() == Ok("1") {
                panic!("PATCHWORK_REQUIRE_GPU=1 but there is no usable GPU: {e}");
            }
            println!("GPU path NOT exercised: no adapter ({e})");
            None
        }
    }
}

/// Resamples on both, with each blend, and checks the masks are identical; returns the
/// largest difference.
fn compare(
    g: &mut GpuResampler,
    t: &Terrain,
    ps: Vec<patchwork_core::index::query::Extracted>,
    grid: &SampleGrid,
    what: &str,
) -> f64 {
    let set = t.resolve(&ps);
    let f1 = set.clone().with_blend(Blend::Formula1);
    let f1 = compare_set(g, f1, grid, &format!("{what}, formula1"));
    let accurate = set.with_blend(Blend::Accurate);
    f1.max(compare_set(g, accurate, grid, &format!("{what}, accurate")))
}

/// [`compare`] of one set.
fn compare_set(g: &mut GpuResampler, set: PatchSet, grid: &SampleGrid, what: &str) -> f64 {
    let want = cpu::resample(&set, grid);
    let got = g
        .resample(&set, grid)
        .unwrap_or_else(|e| panic!("{what}: {e}"));
    let bins = cpu::bin(&set.patches, grid);
    let bx = grid.width.div_ceil(patchwork_core::resample::BLOCK);
    let positions = set.positions(grid);
    // The spread of the heights the patches reaching a point give there, each patch read at
    // the point's position in its own plane.
    let spread = |k: usize| {
        let at = |plane: u16| match plane {
            0 => grid.point(k),
            n => positions[n as usize - 1][k],
        };
        let bin = &bins[(k / grid.width / patchwork_core::resample::BLOCK) * bx
            + (k % grid.width) / patchwork_core::resample::BLOCK];
        let zs = bin.iter().filter_map(|&i| {
            let p = &set.patches[i as usize];
            p.at(at(p.plane)).map(|(_, h)| h.z)
        });
        let (lo, hi) = zs.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), z| {
            (a.min(z), b.max(z))
        });
        (hi - lo).max(0.0)
    };
    assert_eq!(got.len(), want.len());
    let mut worst = 0.0f64;
    let mut valid = 0;
    for (k, (a, b)) in got.iter().zip(&want).enumerate() {
        assert_eq!(
            a.is_nan(),
            b.is_nan(),
            "{what}: mask differs at sample {k} ({:?}): gpu {a}, cpu {b}",
            grid.point(k)
        );
        if !a.is_nan() {
            valid += 1;
            let d = (*a as f64 - *b as f64).abs();
            let step = (f32::from_bits(b.abs().to_bits() + 1) - b.abs()) as f64;
            let tol = TOLERANCE.max(2.0 * step);
            assert!(
                d <= tol || d <= tol + 2e-5 * spread(k),
                "{what}: the GPU is {d} m off the CPU at sample {k} (height {b}, spread {})",
                spread(k)
            );
            worst = worst.max(d);
        }
    }
    println!(
        "{what}: {} patches, {valid} of {} samples valid, max |gpu − cpu| = {:.3e} m",
        set.patches.len(),
        want.len(),
        worst
    );
    worst
}

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.next()
    }
}

fn random_spec(rng: &mut Rng, seed: u64) -> Spec {
    let cols = rng.range(12.0, 70.0) as usize;
    let rows = rng.range(12.0, 70.0) as usize;
    let voids = (0..(rng.next() * 4.0) as usize)
        .map(|_| {
            (
                rng.range(0.0, cols as f64),
                rng.range(0.0, rows as f64),
                rng.range(0.5, 6.0),
            )
        })
        .collect();
    // Quarter turns and arbitrary angles, so rotated grids meet north-up ones.
    let theta = if rng.next() < 0.3 {
        0.0
    } else {
        rng.range(0.0, std::f64::consts::TAU)
    };
    Spec {
        cols,
        rows,
        origin: [rng.range(-10.0, 10.0), rng.range(-10.0, 10.0)],
        theta,
        step: [rng.range(0.4, 1.5), rng.range(0.4, 1.5)],
        voids,
        accuracy: [0.0, 0.5, 2.0][(rng.next() * 3.0) as usize],
        seed,
    }
}

#[test]
fn gpu_matches_cpu_on_random_synthetic_sets() {
    let Some(mut g) = gpu() else { return };
    let mut rng = Rng(2024);
    let mut worst = 0.0f64;
    for case in 0..12 {
        let surveys: Vec<Arc<Survey>> = (0..1 + (rng.next() * 4.0) as usize)
            .filter_map(|_| random_spec(&mut rng, 7).survey())
            .collect();
        if surveys.is_empty() {
            continue;
        }
        let t = terrain_of(&surveys);
        let roi = bounds_of(&surveys);
        for e in [0.0, 1.0, 5.0, 30.0] {
            // Sizes that are not multiples of the block, so partial blocks are exercised.
            let (w, h) = (37 + case * 7, 53 + case * 3);
            let grid = SampleGrid::uniform(&roi, w, h);
            let what = format!("synthetic case {case}, {} surveys, e = {e}", surveys.len());
            worst = worst.max(compare(&mut g, &t, t.uniform(&roi, e), &grid, &what));
        }
        let c = [
            0.5 * (roi.min[0] + roi.max[0]),
            0.5 * (roi.min[1] + roi.max[1]),
        ];
        let v = ViewQuery {
            eye: [roi.min[0] - 5.0, roi.min[1] - 5.0, 320.0],
            look: [c[0], c[1], 200.0],
            fov_deg: 70.0,
            viewport_px: 300,
            pixel_error: 1.0,
            metric: Metric::PROJECTED,
        };
        let grid = patchwork_core::terrain::view_grid(&v, 90, 70);
        let what = format!("synthetic case {case}, view");
        worst = worst.max(compare(&mut g, &t, t.view(&v), &grid, &what));
    }
    println!("synthetic sets: max |gpu − cpu| = {worst:.3e} m");
}

#[test]
fn gpu_matches_cpu_on_the_real_crops() {
    let Some(mut g) = gpu() else { return };
    let cop = real_crop("copernicus_n34w119_crop.tif");
    let surveys = vec![
        real_survey(turned(&cop, 25.0)),
        real_survey(cop),
        real_survey(real_crop("nasadem_n34w119_crop.tif")),
        real_survey(real_crop("srtm_n44e005_voids_crop.tif")),
    ];
    let t = terrain_of(&surveys);
    let mut worst = 0.0f64;
    for s in &surveys {
        let roi = s.levels[0].world_bounds();
        for (e, size) in [(0.0, 256), (2.0, 200), (5.0, 256), (20.0, 128), (100.0, 64)] {
            let grid = SampleGrid::uniform(&roi, size, size);
            let what = format!("survey {} at e = {e}, {size}²", s.id);
            worst = worst.max(compare(&mut g, &t, t.uniform(&roi, e), &grid, &what));
        }
    }
    // The three over N34W119 at full resolution onto a small tile: one bin holds hundreds
    // of patches, from which the device picks each block's few.
    let all = bounds_of(&surveys[..3]);
    let grid = SampleGrid::uniform(&all, 100, 90);
    let ps = t.uniform(&all, 0.0);
    let set = t.resolve(&ps);
    let largest = patchwork::gpu::prepare(&set, &grid).largest_bin();
    assert!(largest > 256, "a bin of only {largest} patches");
    // Estimated claims differ from kernel to kernel: patches whose accurate blend stops at a
    // side of their kernel (`ResolvedPatch::closed`) are among them.
    let closed = set.patches.iter().filter(|p| p.closed != 0).count();
    assert!(closed > 10, "only {closed} patches with a closed side");
    let what = format!("the N34W119 three at e = 0, 100×90, a bin of {largest} patches");
    worst = worst.max(compare(&mut g, &t, ps.clone(), &grid, &what));
    // Columns that go back and forth: no block is bounded by its first and last column.
    let axes = grid.axes.clone().expect("a uniform grid has axes");
    let mut xs = axes.xs.clone();
    xs.swap(5, 70);
    let zigzag = SampleGrid::of_axes(xs, axes.ys);
    worst = worst.max(compare(&mut g, &t, ps, &zigzag, "columns out of order"));
    // A view over the N34W119 pair from a corner, looking across it.
    let pair = [surveys[1].clone(), surveys[2].clone()];
    let b: Aabb = bounds_of(&pair);
    let eye = [b.min[0] + 0.1 * b.width(), b.min[1] + 0.1 * b.height()];
    for px in [0.5, 2.0, 8.0] {
        let v = ViewQuery {
            eye: [eye[0], eye[1], 2500.0],
            look: [b.max[0], b.max[1], 800.0],
            fov_deg: 60.0,
            viewport_px: 800,
            pixel_error: px,
            metric: Metric::geographic(eye[1]),
        };
        let grid = patchwork_core::terrain::view_grid(&v, 240, 160);
        let what = format!("view at {px} px");
        worst = worst.max(compare(&mut g, &t, t.view(&v), &grid, &what));
    }
    println!("real crops: max |gpu − cpu| = {worst:.3e} m");
}

#[test]
fn gpu_matches_cpu_with_bicubic_patches() {
    use patchwork_core::model::patch::PatchKind;
    let Some(mut g) = gpu() else { return };
    let cop = real_crop("copernicus_n34w119_crop.tif");
    let surveys = vec![
        real_survey_of(turned(&cop, 25.0), PatchKind::Bicubic),
        real_survey_of(cop, PatchKind::Bicubic),
        real_survey_of(real_crop("srtm_n44e005_voids_crop.tif"), PatchKind::Bicubic),
    ];
    let t = terrain_of(&surveys);
    let mut worst = 0.0f64;
    for s in &surveys {
        let roi = s.levels[0].world_bounds();
        for (e, size) in [(0.0, 256), (5.0, 200), (20.0, 128), (100.0, 64)] {
            let grid = SampleGrid::uniform(&roi, size, size);
            let what = format!("bicubic survey {} at e = {e}, {size}²", s.id);
            worst = worst.max(compare(&mut g, &t, t.uniform(&roi, e), &grid, &what));
        }
    }
    println!("bicubic crops: max |gpu − cpu| = {worst:.3e} m");
}

#[test]
fn gpu_keeps_a_millimetre_near_nine_kilometres() {
    let Some(mut g) = gpu() else { return };
    // The Copernicus crop lifted so its peaks sit just under 9,000 m, where an f32 height
    // has a spacing of 0.98 mm.
    let mut cop = real_crop("copernicus_n34w119_crop.tif");
    let top = cop.samples.iter().cloned().fold(f32::MIN, f32::max);
    let lift = 8999.0 - top as f64;
    for z in cop.samples.iter_mut() {
        *z = (*z as f64 + lift) as f32;
    }
    let surveys = vec![real_survey(turned(&cop, 25.0)), real_survey(cop)];
    let t = terrain_of(&surveys);
    let roi = bounds_of(&surveys);
    let mut worst = 0.0f64;
    for e in [0.0, 10.0, 50.0] {
        let grid = SampleGrid::uniform(&roi, 300, 300);
        let what = format!("lifted by {lift:.0} m, e = {e}");
        worst = worst.max(compare(&mut g, &t, t.uniform(&roi, e), &grid, &what));
    }
    println!("near 9 km: max |gpu − cpu| = {worst:.3e} m");
}

#[test]
fn gpu_uploads_shared_patches_once_and_survives_eviction() {
    let Some(mut g) = gpu() else { return };
    let cop = real_crop("copernicus_n34w119_crop.tif");
    let s = real_survey(cop);
    let t = terrain_of(std::slice::from_ref(&s));
    let roi = s.levels[0].world_bounds();
    let ps = t.uniform(&roi, 0.0);
    let set = t.resolve(&ps);
    let grid = SampleGrid::uniform(&roi, 128, 128);
    let (a, first) = g.resample_timed(&set, &grid).unwrap();
    assert_eq!(first.uploaded_patches, set.patches.len());
    let (b, again) = g.resample_timed(&set, &grid).unwrap();
    assert_eq!(again.uploaded_patches, 0, "{again:?}");
    assert_eq!(again.cached_patches, set.patches.len());
    assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
    // Warm, a north-up grid sends its axes and the bins, not a point a sample: a 2048² tile
    // uploads under 1 MB (64 MB of points before) and reads back 4 bytes a sample. The
    // patches' records stay on the device: a patch costs what the request adds to it (32
    // bytes) and its entries in the bins of 128² samples, not its 144-byte record.
    let big = SampleGrid::uniform(&roi, 2048, 2048);
    let want = cpu::resample(&set, &big);
    g.resample_timed(&set, &big).unwrap();
    let (got, warm) = g.resample_timed(&set, &big).unwrap();
    println!("warm 2048²: {warm:?}");
    assert_eq!(warm.uploaded_patches, 0);
    assert!(warm.uploaded_bytes <= 1 << 20, "{warm:?}");
    let prep = patchwork::gpu::prepare(&set, &big);
    let (bins, entries) = prep.bins();
    let params = 64;
    let axes = 2 * 2048 * 16;
    assert_eq!(
        warm.uploaded_bytes as usize,
        params + axes + 32 * set.patches.len() + 4 * (bins + 1 + entries),
        "{warm:?}"
    );
    assert_eq!(warm.read_bytes, 2048 * 2048 * 4);
    assert!(got
        .iter()
        .zip(&want)
        .all(|(a, b)| a.is_nan() == b.is_nan() && (a.is_nan() || (a - b).abs() <= 1e-3)));
    // Half the tile shares its patches with the whole one.
    let half = Aabb {
        min: roi.min,
        max: [0.5 * (roi.min[0] + roi.max[0]), roi.max[1]],
    };
    let (_, part) = g
        .resample_timed(
            &t.resolve(&t.uniform(&half, 0.0)),
            &SampleGrid::uniform(&half, 64, 128),
        )
        .unwrap();
    assert_eq!(part.uploaded_patches, 0, "{part:?}");

    // An arena too small for two requests empties itself between them and stays right.
    let mut small = GpuResampler::with_budget(64 << 10, Emulated::Allow).unwrap();
    let coarse = t.resolve(&t.uniform(&roi, 50.0));
    for (set, what) in [(&set, "fine"), (&coarse, "coarse"), (&set, "fine again")] {
        let want = cpu::resample(set, &grid);
        let (got, tm) = small.resample_timed(set, &grid).unwrap();
        let worst = got
            .iter()
            .zip(&want)
            .map(|(a, b)| {
                assert_eq!(a.is_nan(), b.is_nan());
                if a.is_nan() {
                    0.0
                } else {
                    (*a as f64 - *b as f64).abs()
                }
            })
            .fold(0.0, f64::max);
        assert!(worst <= TOLERANCE, "{what}: {worst}");
        println!("small arena, {what}: {tm:?}");
    }
}

#[test]
fn requests_in_flight_together_each_get_their_own_heights() {
    // Threads share one device as a daemon's requests do: each holds it only to submit, and
    // waits for its heights and reads them back while others submit. Every request gets
    // what it gets alone, bit for bit, whatever else was queued beside it.
    let Some(g) = gpu() else { return };
    let cop = real_crop("copernicus_n34w119_crop.tif");
    let s = real_survey(cop);
    let t = terrain_of(std::slice::from_ref(&s));
    let roi = s.levels[0].world_bounds();
    let cases: Vec<(PatchSet, SampleGrid)> = [(0.0, 96), (5.0, 64), (20.0, 80), (2.0, 48)]
        .into_iter()
        .map(|(e, n)| {
            (
                t.resolve(&t.uniform(&roi, e)),
                SampleGrid::uniform(&roi, n, n + 7),
            )
        })
        .collect();
    let g = std::sync::Mutex::new(g);
    let alone: Vec<Vec<f32>> = cases
        .iter()
        .map(|(set, grid)| g.lock().unwrap().resample(set, grid).unwrap())
        .collect();
    std::thread::scope(|scope| {
        for worker in 0..4 {
            let (g, cases, alone) = (&g, &cases, &alone);
            scope.spawn(move || {
                for round in 0..6 {
                    let k = (worker + round) % cases.len();
                    let (set, grid) = &cases[k];
                    let prep = patchwork::gpu::prepare(set, grid);
                    let submitted = g.lock().unwrap().submit(set, prep).unwrap();
                    let (got, _) = submitted.wait().unwrap();
                    assert!(
                        got.iter()
                            .zip(&alone[k])
                            .all(|(a, b)| a.to_bits() == b.to_bits()),
                        "case {k} differs when other requests are in flight"
                    );
                }
            });
        }
    });
}

#[test]
fn gpu_matches_cpu_where_surveys_meet() {
    let Some(mut g) = gpu() else { return };
    let cop = real_crop("copernicus_n34w119_crop.tif");
    let mut worst = 0.0f64;
    let mut check = |t: &Terrain, roi: &Aabb, w: usize, h: usize, e: f64, what: &str| {
        let grid = SampleGrid::uniform(roi, w, h);
        let what = format!("{what}, {w}×{h}, e = {e}");
        worst = worst.max(compare(&mut g, t, t.uniform(roi, e), &grid, &what));
    };
    // Four tiles of one mosaic: seams interpolated across by edge patches.
    let pieces: Vec<_> = [(0, 0), (150, 0), (0, 150), (150, 150)]
        .iter()
        .map(|&(c, r)| survey_with(window(&cop, c, r, 150, 150), 1.0))
        .collect();
    let mosaic = terrain_of(&pieces);
    let all = pixel_bounds(&cop);
    for (w, h) in [(347, 311), (600, 600)] {
        check(&mosaic, &all, w, h, 0.0, "mosaic");
    }
    // Samples on the pixel edges and corners, where the pixel test ties.
    let step = cop.georef.step;
    let corners = Aabb::new(
        all.min[0] + step[0] / 2.0,
        all.min[1] + step[1] / 2.0,
        all.max[0] + step[0] / 2.0,
        all.max[1] + step[1] / 2.0,
    );
    check(&mosaic, &corners, 300, 300, 0.0, "mosaic at pixel corners");
    // Three quarters void, and scattered soundings: triangles, fills and the pixel test.
    for (name, grid) in [
        ("big hole", real_crop("srtm_n44e005_big_hole_crop.tif")),
        ("soundings", sparse(&cop, 0.25, 11)),
    ] {
        let s = survey_with(
            grid.clone(),
            patchwork_core::model::accuracy::AccuracySpec::Auto,
        );
        let t = terrain_of(std::slice::from_ref(&s));
        let roi = pixel_bounds(&grid);
        for e in [0.0, 20.0] {
            check(&t, &roi, 2 * grid.cols + 1, 2 * grid.rows + 3, e, name);
        }
    }
    // An ε = 2 survey inside an ε = 20 one: fallback tiers below 20 m.
    let fine = survey_with(window(&cop, 60, 50, 180, 200), 2.0);
    let coarse = survey_with(decimate(&cop, 2), 20.0);
    let t = terrain_of(&[fine, coarse]);
    for e in [0.0, 2.0, 10.0, 25.0] {
        check(&t, &all, 256, 256, e, "ε 2 in ε 20");
    }
    println!("where surveys meet: max |gpu − cpu| = {worst:.3e} m");
}

#[test]
fn gpu_matches_cpu_across_crss() {
    use patchwork_core::crs::{Crs, Reprojection};
    use patchwork_core::index::lod::IndexConfig;
    let Some(mut g) = gpu() else { return };
    // Mont Ventoux in geographic WGS 84 and in UTM 31N, each in a store of the other's CRS
    // and of its own: every patch of the other survey reads positions carried to its plane.
    let geo = crop_survey("real/ventoux_geographic.tif");
    let utm = crop_survey("real/ventoux_utm31.tif");
    let mut worst = 0.0f64;
    for store in [Crs::wgs84(), Crs::epsg(32631).unwrap()] {
        let mut t = Terrain::with_crs(IndexConfig::default(), Some(&store), None);
        t.insert(geo.clone());
        t.insert(utm.clone());
        let both = t
            .survey(geo.id)
            .unwrap()
            .footprint()
            .intersection(&t.survey(utm.id).unwrap().footprint())
            .expect("the surveys overlap");
        for (e, size) in [(0.0, 256), (3.0, 200), (10.0, 128), (50.0, 64)] {
            let grid = SampleGrid::uniform(&both, size, size);
            let what = format!("Ventoux pair in {} at e = {e}, {size}²", store.key());
            worst = worst.max(compare(&mut g, &t, t.uniform(&both, e), &grid, &what));
        }
        // Only the other CRS's survey: all of the tile through the lattice.
        let mut alone = Terrain::with_crs(IndexConfig::default(), Some(&store), None);
        let other = if store.is_geographic() { &utm } else { &geo };
        alone.insert(other.clone());
        let roi = alone.survey(other.id).unwrap().footprint();
        let grid = SampleGrid::uniform(&roi, 300, 300);
        let what = format!("survey {} alone in {}", other.id, store.key());
        worst = worst.max(compare(
            &mut g,
            &alone,
            alone.uniform(&roi, 0.0),
            &grid,
            &what,
        ));
        // A view across the pair, its metric the store's.
        let metric = if store.is_geographic() {
            Metric::geographic((both.min[1] + both.max[1]) / 2.0)
        } else {
            Metric::PROJECTED
        };
        let v = ViewQuery {
            eye: [both.min[0], both.min[1], 2500.0],
            look: [both.max[0], both.max[1], 1200.0],
            fov_deg: 60.0,
            viewport_px: 800,
            pixel_error: 2.0,
            metric,
        };
        let grid = patchwork_core::terrain::view_grid(&v, 240, 160);
        let what = format!("view across the pair in {}", store.key());
        worst = worst.max(compare(&mut g, &t, t.view(&v), &grid, &what));
        // Made on the device: the view's rows and the other plane's lattice, not a
        // position a sample and plane.
        let set = t.resolve(&t.view(&v));
        assert!(!patchwork::gpu::prepare(&set, &grid).listed());
        let (_, warm) = g.resample_timed(&set, &grid).unwrap();
        let listed = 16 * 2 * grid.width * grid.height;
        println!("{what}, warm: {warm:?}, where listed positions took {listed} bytes");
        assert!(warm.uploaded_bytes as usize * 10 < listed, "{warm:?}");

        // A north-up tile in the other survey's CRS: carried into the store's plane by a
        // lattice on the device, and from there into the other plane by another.
        let other_crs = if store.is_geographic() {
            Crs::epsg(32631).unwrap()
        } else {
            Crs::wgs84()
        };
        let to_store = Arc::new(Reprojection::new(&other_crs, &store).unwrap());
        let back = Reprojection::new(&store, &other_crs).unwrap();
        let (a, b) = (
            back.exact().apply(both.min).unwrap(),
            back.exact().apply(both.max).unwrap(),
        );
        let own = Aabb::new(
            a[0].min(b[0]),
            a[1].min(b[1]),
            a[0].max(b[0]),
            a[1].max(b[1]),
        );
        let axes = SampleGrid::uniform(&own, 230, 190).axes.unwrap();
        let grid = SampleGrid::carried(axes, to_store);
        let stored = Aabb::of_points(grid.list());
        let ps = t.uniform(&stored, 2.0);
        let set = t.resolve(&ps);
        assert!(!patchwork::gpu::prepare(&set, &grid).listed());
        let what = format!(
            "a tile in {} over the pair in {}",
            other_crs.key(),
            store.key()
        );
        worst = worst.max(compare(&mut g, &t, ps, &grid, &what));
    }
    println!("across CRSs: max |gpu − cpu| = {worst:.3e} m");
}

#[test]
fn a_software_adapter_is_taken_only_when_allowed() {
    let Some(g) = gpu() else {
        return;
    };
    match GpuResampler::new(Emulated::Refuse) {
        Ok(real) => {
            // A real GPU is preferred to a software one in any case.
            assert!(!real.is_emulated(), "{}", real.adapter());
            assert_eq!(real.adapter(), g.adapter());
        }
        Err(e) => {
            assert!(g.is_emulated(), "{} refused: {e}", g.adapter());
            let e = e.to_string();
            assert!(
                e.contains("software") && e.contains("allow_emulated_gpu"),
                "the refusal says what was found and how to allow it: {e}"
            );
        }
    }
}
