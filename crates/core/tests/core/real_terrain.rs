//! The model's invariants on real terrain: the overlapping Copernicus and NASADEM pair, an SRTM
//! tile with voids, and a real crop turned into a rotated grid.

use crate::common;

use common::*;
use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::source::MemorySource;
use patchwork_core::model::survey::Survey;
use patchwork_core::terrain::Terrain;
use std::sync::Arc;

struct Real {
    cop: Arc<Survey>,
    nasa: Arc<Survey>,
    srtm: Arc<Survey>,
    rotated: Arc<Survey>,
}

fn real() -> Real {
    let cop = real_crop("copernicus_n34w119_crop.tif");
    let rotated = real_survey(turned(&cop, 25.0));
    Real {
        cop: real_survey(cop),
        nasa: real_survey(real_crop("nasadem_n34w119_crop.tif")),
        srtm: real_survey(real_crop("srtm_n44e005_voids_crop.tif")),
        rotated,
    }
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
}

#[test]
fn the_pair_and_the_rotated_crop_give_one_index_in_any_order() {
    let r = real();
    let all = [
        r.cop.clone(),
        r.nasa.clone(),
        r.rotated.clone(),
        r.srtm.clone(),
    ];
    let a = terrain_of(&all);
    let b = terrain_of(&[
        r.srtm.clone(),
        r.rotated.clone(),
        r.nasa.clone(),
        r.cop.clone(),
    ]);
    assert_eq!(a.index().state(), b.index().state());
    a.index().check().unwrap();

    // insert(A, B, C) then retire(B) equals insert(A, C).
    let mut c = terrain_of(&[r.cop.clone(), r.nasa.clone(), r.rotated.clone()]);
    c.retire(r.nasa.id).unwrap();
    let d = terrain_of(&[r.rotated.clone(), r.cop.clone()]);
    assert_eq!(c.index().state(), d.index().state());
    let roi = bounds_of(&[r.cop.clone(), r.nasa.clone()]);
    for e in [0.0, 2.0, 10.0, 50.0] {
        assert_eq!(c.uniform(&roi, e), d.uniform(&roi, e), "e = {e}");
    }
    c.index().check().unwrap();
}

#[test]
fn real_terrain_is_covered_and_within_the_error_everywhere() {
    let r = real();
    let surveys = vec![
        r.cop.clone(),
        r.nasa.clone(),
        r.rotated.clone(),
        r.srtm.clone(),
    ];
    let t = terrain_of(&surveys);
    let mut rng = Rng(42);
    for e in [0.0, 0.5, 2.0, 5.0, 20.0, 50.0] {
        for s in &surveys {
            let roi = s.levels[0].world_bounds();
            let ps = t.uniform(&roi, e);
            assert!(ps.iter().all(|x| (x.span.min_z <= e) != x.fallback));
            let set = t.resolve(&ps);
            let all: Vec<u32> = (0..set.patches.len() as u32).collect();
            let mut worst = 0.0f64;
            for _ in 0..400 {
                let p = valid_point(s, rng.next(), rng.next(), rng.next()).unwrap();
                if !roi.contains_point(p) {
                    continue;
                }
                assert!(
                    ps.iter().any(|x| in_valid_kernel(&t, x, p)),
                    "hole at {p:?}, e = {e}"
                );
                let h = patchwork_core::resample::cpu::blend(&set, &all, p) as f64;
                let hs = survey_heights(&surveys, p);
                let lo = hs.iter().cloned().fold(f64::INFINITY, f64::min);
                let hi = hs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                assert!(
                    h >= lo - e - 1e-3 && h <= hi + e + 1e-3,
                    "{h} outside [{lo}, {hi}] ± {e} at {p:?}"
                );
                worst = worst.max((lo - h).max(h - hi));
            }
            println!("e = {e:>4}: {} patches over survey {}, worst excess over the survey hull {worst:.3} m", ps.len(), s.id);
        }
    }
}

#[test]
fn cuts_through_the_aligned_pair_are_minimal() {
    let r = real();
    let pair = vec![r.cop.clone(), r.nasa.clone()];
    let t = terrain_of(&pair);
    let roi = bounds_of(&pair);
    let lattice = r.cop.levels[0].georef.step[0] / 8.0;
    for e in [0.0, 1.0, 5.0, 20.0, 100.0] {
        let ps = t.uniform(&roi, e);
        let bad = redundant(&t, &ps, lattice);
        assert!(bad.is_empty(), "e = {e}: {bad:?}");
        // Where both surveys overlap, level-0 patches tie in area and error and the id picks
        // one, so the pair costs fewer patches than the two alone (each with the claims the
        // other leaves it: both claim to be exact, and they differ by up to 98 m). Coarser kernels of the two
        // crops do not line up, so there both may be needed.
        let alone: usize = pair
            .iter()
            .map(|s| terrain_of(&[as_served(&t, s)]).uniform(&roi, e).len())
            .sum();
        assert!(
            ps.len() <= alone,
            "e = {e}: {} patches for the pair, {alone} apart",
            ps.len()
        );
        if e == 0.0 {
            assert!(
                ps.len() < alone,
                "{} patches for the pair, {alone} apart",
                ps.len()
            );
        }
    }
}

#[test]
fn voids_stay_nodata_and_valid_samples_get_heights() {
    let r = real();
    let t = terrain_of(std::slice::from_ref(&r.srtm));
    let g = &r.srtm.levels[0];
    // Half a pixel beyond the outer samples: the raster's own footprint.
    let roi = pixel_bounds(g);
    for e in [0.0, 20.0, 100.0] {
        let tile = t.tile(&roi, 256, 256, e);
        let grid = patchwork_core::resample::SampleGrid::uniform(&roi, 256, 256);
        let (mut void, mut valid, mut edge) = (0, 0, 0);
        for (p, z) in grid.points().zip(&tile.heights) {
            match (g.bilinear(p), pixel_valid(g, p)) {
                (Some(h), _) => {
                    valid += 1;
                    assert!(!z.is_nan(), "nodata at a valid point {p:?}, e = {e}");
                    assert!(
                        (*z as f64 - h).abs() <= e + 1e-3,
                        "{z} vs {h} at {p:?}, e = {e}"
                    );
                }
                (None, true) => {
                    // In a pixel of data but no whole cell: a border or the edge of a void.
                    edge += 1;
                    assert!(!z.is_nan(), "nodata in a valid pixel at {p:?}, e = {e}");
                    let (lo, hi) = neighbourhood_range(g, p);
                    assert!(
                        *z as f64 >= lo - e - 1e-3 && *z as f64 <= hi + e + 1e-3,
                        "{z} outside the nearby samples [{lo}, {hi}] at {p:?}, e = {e}"
                    );
                }
                (None, false) => {
                    void += 1;
                    assert!(
                        z.is_nan(),
                        "a made-up height {z} in a void at {p:?}, e = {e}"
                    );
                }
            }
        }
        assert!(
            void > 500 && valid > 50_000 && edge > 500,
            "void {void}, valid {valid}, edge {edge}"
        );
    }
}

#[test]
fn a_query_below_every_accuracy_returns_the_best_data_without_holes() {
    let cop = real_crop("copernicus_n34w119_crop.tif");
    let rough = Arc::new(
        Survey::build(
            cop,
            4.0,
            Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
            PatchLayout::default(),
        )
        .unwrap(),
    );
    let fine = real_survey(real_crop("nasadem_n34w119_crop.tif"));
    let mut t = Terrain::new(IndexConfig::default());
    t.insert(rough.clone());
    t.insert(fine.clone());
    let roi: Aabb = rough.levels[0].world_bounds();
    let ps = t.uniform(&roi, 1.0);
    let mut rng = Rng(7);
    let (mut by_fine, mut with_fine) = (0, 0);
    for _ in 0..500 {
        let p = valid_point(&rough, rng.next(), rng.next(), rng.next()).unwrap();
        assert!(
            ps.iter().any(|x| in_valid_kernel(&t, x, p)),
            "hole at {p:?}"
        );
        let covering: Vec<_> = ps.iter().filter(|x| in_valid_kernel(&t, x, p)).collect();
        // Where the survey that claims to be exact has data, the most accurate data serves
        // the point: its own where its claim stands, or the rough survey's where the two
        // disagree by more than 4 m (there the rough one, holding more of the detail the two
        // share, takes the tie, and the exact one is held above it).
        if fine.levels[0].bilinear(p).is_some() {
            let best = [fine.id, rough.id]
                .iter()
                .filter_map(|&id| level0_error(&t, id, p))
                .fold(f64::INFINITY, f64::min);
            let served = covering
                .iter()
                .map(|x| x.span.min_z)
                .fold(f64::INFINITY, f64::min);
            assert!(
                served <= best + 1e-9,
                "{served} served where {best} is held, at {p:?}"
            );
            by_fine += covering.iter().any(|x| x.survey == fine.id) as usize;
            with_fine += 1;
        } else {
            assert!(covering.iter().all(|x| x.span.min_z >= 4.0));
        }
    }
    println!("the exact survey serves {by_fine} of {with_fine} points where it has data");
    // Nothing in the pair says which is false: undetermined, the tie to the rough one.
    let v = t.verdict(fine.id, rough.id).unwrap();
    assert_eq!(
        v.by.test,
        patchwork_core::model::evidence::Test::Undetermined
    );
    let pair = &t.pairs_of(fine.id)[0];
    assert_eq!(pair.tie_to_finer() == Some(true), pair.finer == rough.id);
    // Each serves where its claim is the lower.
    assert!(
        by_fine > 0 && by_fine < with_fine,
        "{by_fine} of {with_fine}"
    );
}

/// A survey with the claims a terrain serves it with, as a survey of its own.
fn as_served(t: &Terrain, s: &Arc<Survey>) -> Arc<Survey> {
    Arc::new(Survey {
        meta: t.survey(s.id).unwrap().clone(),
        levels: s.levels.clone(),
        deltas: s.deltas.clone(),
    })
}

/// The error of the level-0 patch of a survey, as the terrain serves it, whose valid cells
/// hold `p`.
fn level0_error(t: &Terrain, id: patchwork_core::model::ids::SurveyId, p: [f64; 2]) -> Option<f64> {
    let s = t.survey(id)?;
    let g = s.shapes[0].georef.to_grid(p);
    (0..s.patches.len())
        .filter(|&k| s.patches[k].level == 0)
        .find(|&k| {
            s.valid(&s.patches[k]).iter().any(|r| {
                g[0] >= r.c0 as f64
                    && g[0] <= r.c1 as f64
                    && g[1] >= r.r0 as f64
                    && g[1] <= r.r1 as f64
            })
        })
        .map(|k| s.error_at(k))
}

/// A terrain of `all`, inserted in order, and the box states a store would hold after it:
/// the moved states of each change written, the removed ones dropped.
fn inserted_with_states(
    all: &[Arc<Survey>],
) -> (
    Terrain,
    std::collections::HashMap<
        patchwork_core::model::ids::PatchId,
        patchwork_core::index::lod::BoxState,
    >,
) {
    let mut t = Terrain::new(IndexConfig::default());
    let mut states = std::collections::HashMap::new();
    for s in all {
        let change = t.insert(s.clone());
        for id in &change.removed {
            states.remove(id);
        }
        states.extend(change.moved);
    }
    (t, states)
}

#[test]
fn an_index_restored_from_stored_tops_is_the_same_index() {
    let r = real();
    let all = [r.cop.clone(), r.nasa.clone(), r.rotated.clone()];
    let (t, states) = inserted_with_states(&all);
    // What a store keeps: the surveys without samples (with their own claims), what each
    // overlapping pair says of the other, the edge patches, the states; the samples come
    // through a source.
    let metas = all.iter().map(|s| s.meta()).collect();
    let edges = t.edges().cloned().collect();
    let source = Arc::new(MemorySource::of(all.iter().map(|s| s.as_ref())));
    let (restored, missing) = Terrain::restore(
        IndexConfig::default(),
        t.crs(),
        t.contradicted(),
        metas,
        t.pairs(),
        edges,
        &states,
        source,
        None,
    );
    assert!(
        missing.is_empty(),
        "{} patches without a state",
        missing.len()
    );
    assert_eq!(states.len(), t.index().len(), "stale states were written");
    assert_eq!(restored.index().state(), t.index().state());
    restored.index().check().unwrap();
    let roi = bounds_of(&all);
    assert_eq!(restored.uniform(&roi, 3.0), t.uniform(&roi, 3.0));
    // And it reads the same samples, through windows, as the terrain that holds them.
    let a = restored.tile(&roi, 96, 96, 3.0);
    let b = t.tile(&roi, 96, 96, 3.0);
    assert!(a
        .heights
        .iter()
        .zip(&b.heights)
        .all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan())));
}

#[test]
fn view_cuts_cover_the_footprint_and_coarsen_with_distance() {
    use patchwork_core::index::query::{Metric, ViewQuery};
    let r = real();
    let pair = vec![r.cop.clone(), r.nasa.clone()];
    let t = terrain_of(&pair);
    let b = bounds_of(&pair);
    let eye_xy = [b.min[0] + 0.1 * b.width(), b.min[1] + 0.1 * b.height()];
    let view = |px: f64| ViewQuery {
        eye: [eye_xy[0], eye_xy[1], 2500.0],
        look: [b.max[0], b.max[1], 800.0],
        fov_deg: 60.0,
        viewport_px: 800,
        pixel_error: px,
        metric: Metric::geographic(eye_xy[1]),
    };
    let (mut first, mut last) = (0, usize::MAX / 2);
    for px in [0.5, 1.0, 3.0, 10.0] {
        let v = view(px);
        let ps = t.view(&v);
        // Where no patch meets the error (the two claim to be exact and differ, so their
        // claims are raised there), the best data serves, a level-0 patch of either; at a
        // coarser error part of such a region may be met by one survey's coarser patch with
        // the other's level-0 patches around it, which can cost a patch or two more.
        assert!(
            ps.len() <= last + last / 50,
            "{px} px: {} patches, more than at a finer error ({last})",
            ps.len()
        );
        first = first.max(ps.len());
        last = ps.len();
        // Every patch meets the screen error somewhere on its kernel: its error is at most
        // the allowed error at the kernel's far corner. Fallback patches are the best data
        // where nothing meets it.
        let field = v.field();
        for x in ps.iter().filter(|x| !x.fallback) {
            let far = x
                .kernel
                .corners()
                .iter()
                .map(|&c| field.at(c))
                .fold(0.0f64, f64::max);
            assert!(
                x.span.min_z <= far + 1e-9,
                "{px} px: error {} beyond {far}",
                x.span.min_z
            );
        }
        let footprint = v.footprint(&t.index().bounds().unwrap());
        let tile = t.view_tile(&v, 200, 150);
        let grid = patchwork_core::terrain::view_grid(&v, 200, 150);
        let mut checked = 0;
        for (p, z) in grid.points().zip(&tile.heights) {
            if p[0].is_nan() || !footprint.contains_point(p) {
                continue;
            }
            let hs = survey_heights(&pair, p);
            if hs.is_empty() {
                assert!(z.is_nan(), "a height outside the data at {p:?}");
                continue;
            }
            assert!(
                ps.iter().any(|x| in_valid_kernel(&t, x, p)),
                "hole at {p:?}"
            );
            let lo = hs.iter().cloned().fold(f64::INFINITY, f64::min);
            let hi = hs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            // Within the errors of the patches blended there, which the cut bounds by the
            // field over each patch's kernel.
            let allowed = ps
                .iter()
                .filter(|x| x.window.contains_point(p))
                .map(|x| x.span.min_z)
                .fold(0.0f64, f64::max);
            let h = *z as f64;
            assert!(
                h >= lo - allowed - 1e-3 && h <= hi + allowed + 1e-3,
                "{h} vs [{lo}, {hi}] ± {allowed}"
            );
            checked += 1;
        }
        assert!(checked > 1000, "{px} px: only {checked} samples on data");
        println!("{px} px: {} patches, {checked} samples checked", ps.len());
    }
    assert!(
        last * 4 < first * 3,
        "{first} patches at most, {last} at 10 px"
    );
}

#[test]
fn estimated_accuracies_and_edge_patches_do_not_depend_on_order() {
    // Copernicus and NASADEM share a lattice, so their borders make edge patches together.
    let auto = |n: &str| {
        Arc::new(
            Survey::build(
                real_crop(n),
                patchwork_core::model::accuracy::AccuracySpec::Auto,
                Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
                PatchLayout::default(),
            )
            .unwrap(),
        )
    };
    let c = auto("copernicus_n34w119_crop.tif");
    let n = auto("nasadem_n34w119_crop.tif");
    let s = auto("srtm_n44e005_voids_crop.tif");
    let a = terrain_of(&[c.clone(), n.clone(), s.clone()]);
    let b = terrain_of(&[s.clone(), n.clone(), c.clone()]);
    assert_eq!(a.index().state(), b.index().state());
    let edges = |t: &Terrain| {
        let mut v: Vec<_> = t.edges().map(|e| e.owner).collect();
        v.sort();
        v
    };
    assert_eq!(edges(&a), edges(&b));
    assert!(
        a.edges().any(|e| e.members.len() == 2),
        "no shared edge patch"
    );
    a.index().check().unwrap();
    // Retiring one gives the terrain that never had it, edge patches included.
    let mut r = a.clone();
    r.retire(n.id).unwrap();
    let never = terrain_of(&[s.clone(), c.clone()]);
    assert_eq!(r.index().state(), never.index().state());
    assert_eq!(edges(&r), edges(&never));
}

/// Where methods break, for every mipmap filter and patch kind: a 400 m cliff, spikes and pits,
/// a survey full of voids and a rotated survey, each alone and exact. At random valid points of
/// each, the blended height stays within e of the survey's own surface (the bilinear surface
/// of its samples), or where no patch is that good (a bicubic patch overshoots at a cliff or a
/// spike even at level 0) within the error of the worst fallback patch blended there. The
/// largest deviation measured is printed beside e.
#[test]
fn every_recipe_keeps_the_bound_at_cliffs_spikes_voids_and_rotations() {
    use patchwork_core::model::mipmap::Filter;
    use patchwork_core::model::patch::PatchKind;
    use patchwork_core::model::survey::Recipe;
    // The bench's cases (a 400 m cliff, spikes and pits every 997 samples, the crop turned
    // 25°), with the SRTM crop's real voids for its synthetic ones.
    let cop = real_crop("copernicus_n34w119_crop.tif");
    let cases: Vec<(&str, _)> = patchwork_testkit::stability_cases(&cop)
        .into_iter()
        .map(|(name, g)| match name {
            "voids" => (name, real_crop("srtm_n44e005_voids_crop.tif")),
            _ => (name, g),
        })
        .collect();
    let mut rng = Rng(7);
    for (name, grid) in &cases {
        let recipes = PatchKind::ALL
            .into_iter()
            .flat_map(|patches| Filter::ALL.map(|mipmap| Recipe { mipmap, patches }));
        for recipe in recipes {
            let s = Arc::new(
                Survey::build_with(
                    grid.clone(),
                    0.0,
                    Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
                    PatchLayout::default(),
                    recipe,
                )
                .unwrap(),
            );
            let t = terrain_of(std::slice::from_ref(&s));
            let roi = s.levels[0].world_bounds();
            for e in [2.0, 10.0, 50.0] {
                let ps = t.uniform(&roi, e);
                let set = t.resolve(&ps);
                let all: Vec<u32> = (0..set.patches.len() as u32).collect();
                let (mut worst, mut worst_bound) = (0.0f64, 0.0f64);
                for _ in 0..600 {
                    let p = valid_point(&s, rng.next(), rng.next(), rng.next()).unwrap();
                    let h = patchwork_core::resample::cpu::blend(&set, &all, p) as f64;
                    assert!(
                        !h.is_nan(),
                        "{name}, {recipe:?}, e = {e}: no height at {p:?}"
                    );
                    let fallback = set
                        .patches
                        .iter()
                        .filter(|q| q.fallback && q.at(p).is_some())
                        .map(|q| q.error)
                        .fold(0.0, f64::max);
                    let bound = e.max(fallback);
                    let hs = survey_heights(std::slice::from_ref(&s), p);
                    let lo = hs.iter().cloned().fold(f64::INFINITY, f64::min);
                    let hi = hs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                    let off = (lo - h).max(h - hi).max(0.0);
                    assert!(
                        off <= bound + 1e-3,
                        "{name}, {recipe:?}, e = {e}: {h} is {off} m outside [{lo}, {hi}] at {p:?}"
                    );
                    worst = worst.max(off);
                    worst_bound = worst_bound.max(bound);
                }
                println!(
                    "{name:>7} {:>8} {:>8} e = {e:>4}: {:>4} patches ({} fallback), largest deviation {worst:.2} m (bound {worst_bound:.2} m)",
                    recipe.mipmap.name(),
                    recipe.patches.name(),
                    ps.len(),
                    ps.iter().filter(|x| x.fallback).count(),
                );
            }
        }
    }
}

/// A terrain restored for a region (a replica's) answers every point of the region as the whole
/// one does, to the bit: a lattice of abutting tiles (edge patches across their seams), an
/// overlapping survey on the same lattice, a copy offset by 30 m that claims 1 m (a pair whose
/// evidence raises claims) and a rotated crop, with regions drawn at random (seed printed).
#[test]
fn a_terrain_restored_for_a_region_answers_inside_it_as_the_whole_one() {
    use patchwork_core::model::patch::Blend;
    let whole = real_crop("copernicus_n34w119_crop.tif");
    let side = 30;
    let mut all: Vec<Arc<Survey>> = Vec::new();
    for r in (0..whole.rows - side + 1).step_by(side) {
        for c in (0..whole.cols - side + 1).step_by(side) {
            all.push(survey_with(window(&whole, c, r, side, side), 1.0));
        }
    }
    let nasa = real_crop("nasadem_n34w119_crop.tif");
    all.push(survey_with(window(&nasa, 20, 120, 50, 40), 4.0));
    let mut false_copy = window(&whole, 140, 30, 40, 40);
    for z in false_copy.samples.iter_mut() {
        *z += 30.0;
    }
    all.push(survey_with(false_copy, 1.0));
    all.push(real_survey(turned(&window(&whole, 170, 170, 40, 40), 25.0)));
    let (t, states) = inserted_with_states(&all);
    assert!(t.pairs().len() >= 2, "the scene has no overlapping pairs");
    assert!(
        t.edges().any(|e| e.members.len() >= 2),
        "no edge patch across a seam"
    );
    let roi = bounds_of(&all);
    let seed = seed();
    let mut rng = Rng(seed);
    println!("seed {seed}");
    let metas: Vec<_> = all.iter().map(|s| s.meta()).collect();
    let edges: Vec<_> = t.edges().cloned().collect();
    let source = Arc::new(MemorySource::of(all.iter().map(|s| s.as_ref())));
    for round in 0..4 {
        // A region a sixth to a half of the scene's side, anywhere in it.
        let (w, h) = (
            roi.width() * (0.17 + 0.33 * rng.next()),
            roi.height() * (0.17 + 0.33 * rng.next()),
        );
        let x = roi.min[0] + (roi.width() - w) * rng.next();
        let y = roi.min[1] + (roi.height() - h) * rng.next();
        let region = Aabb::new(x, y, x + w, y + h);
        let (mut part, missing) = Terrain::restore(
            IndexConfig::default(),
            t.crs(),
            t.contradicted(),
            metas.clone(),
            t.pairs(),
            edges.clone(),
            &states,
            source.clone(),
            Some(&region),
        );
        // (The index's own check derives each box's state from the boxes beside it, which a
        // region's terrain holds only in part: its states are the whole store's, as stored.)
        assert!(missing.is_empty());
        println!(
            "round {round}: region {region:?} keeps {} of {} boxes",
            part.index().len(),
            t.index().len()
        );
        let mut whole_t = t.clone();
        for blend in Blend::ALL {
            part.set_blend(blend);
            whole_t.set_blend(blend);
            for e in [0.0, 2.0, 9.0] {
                let (cols, rows) = (
                    40 + (rng.next() * 90.0) as usize,
                    40 + (rng.next() * 90.0) as usize,
                );
                let a = part.tile(&region, cols, rows, e).heights;
                let b = whole_t.tile(&region, cols, rows, e).heights;
                let same = a
                    .iter()
                    .zip(&b)
                    .filter(|(x, y)| x.to_bits() == y.to_bits())
                    .count();
                assert_eq!(
                    same,
                    a.len(),
                    "round {round}, {} blend, e = {e}: {} of {} heights differ",
                    blend.name(),
                    a.len() - same,
                    a.len()
                );
            }
        }
    }
    // A region far smaller than the scene keeps less than the whole of it.
    let corner = Aabb::new(roi.min[0], roi.min[1], roi.min[0] + 1e-6, roi.min[1] + 1e-6);
    let (part, _) = Terrain::restore(
        IndexConfig::default(),
        t.crs(),
        t.contradicted(),
        metas,
        t.pairs(),
        edges,
        &states,
        source,
        Some(&corner),
    );
    assert!(
        part.index().len() < t.index().len(),
        "a corner's terrain holds all {} boxes",
        t.index().len()
    );
}
