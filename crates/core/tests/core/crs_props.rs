//! Property tests of the invariants on random surveys of several CRSs in one store: a store
//! in a transverse Mercator plane of its own (a CRS without an EPSG code), with surveys in it,
//! in UTM 31N (turned by the meridians' convergence there), in geographic WGS 84 (degrees)
//! and in Web Mercator (scaled by 1.4), rotated, skewed, voided, of any accuracy. Each samples
//! one made-up landscape at the store-plane positions of its own samples.

use crate::common;

use common::{config, landscape, LAYOUT};
use patchwork_core::crs::{Crs, Transform};
use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::AccuracySpec;
use patchwork_core::model::grid::{Georef, Grid};
use patchwork_core::model::survey::Survey;
use patchwork_core::terrain::Terrain;
use proptest::prelude::*;
use std::sync::Arc;

/// The store's CRS: a transverse Mercator plane centred on 45° N, 5° E.
const STORE: &str =
    "+proj=tmerc +lat_0=45 +lon_0=5 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs";

fn store() -> Crs {
    Crs::parse(STORE).unwrap()
}

/// A survey's CRS: the store's, UTM 31N, geographic WGS 84 or Web Mercator; and what a metre
/// of the store is in its units there, along x and y.
fn crs_of(k: usize) -> (Crs, [f64; 2]) {
    match k {
        0 => (store(), [1.0, 1.0]),
        1 => (Crs::epsg(32631).unwrap(), [1.0, 1.0]),
        2 => (
            Crs::wgs84(),
            [
                1.0 / (111_320.0 * 45f64.to_radians().cos()),
                1.0 / 111_132.0,
            ],
        ),
        _ => (Crs::epsg(3857).unwrap(), [1.414, 1.414]),
    }
}

#[derive(Clone, Debug)]
struct Spec {
    crs: usize,
    cols: usize,
    rows: usize,
    /// In the store's plane, metres.
    origin: [f64; 2],
    theta: f64,
    /// The row axis's own angle, for a skewed grid.
    skew: Option<f64>,
    /// Metres.
    step: [f64; 2],
    voids: Vec<(f64, f64, f64)>,
    accuracy: f64,
}

impl Spec {
    fn crs(&self) -> Crs {
        crs_of(self.crs).0
    }

    /// The grid in its own CRS, sampling the landscape where its samples lie in the store's.
    fn grid(&self) -> Grid {
        let (crs, unit) = crs_of(self.crs);
        let to = Transform::new(&store(), &crs).unwrap();
        let back = Transform::new(&crs, &store()).unwrap();
        let g = Georef {
            origin: to.apply(self.origin).unwrap(),
            theta: self.theta,
            step: [self.step[0] * unit[0], self.step[1] * unit[1]],
            row_theta: self.skew.map(|s| self.theta + s),
        };
        let mut s = Vec::with_capacity(self.cols * self.rows);
        for r in 0..self.rows {
            for c in 0..self.cols {
                let void = self.voids.iter().any(|&(vc, vr, rad)| {
                    (c as f64 - vc).powi(2) + (r as f64 - vr).powi(2) <= rad * rad
                });
                let p = back.apply(g.to_world(c as f64, r as f64)).unwrap();
                s.push(if void {
                    f32::NAN
                } else {
                    landscape(p[0], p[1], 7)
                });
            }
        }
        Grid::new(self.cols, self.rows, s, g).unwrap()
    }

    fn survey(&self) -> Option<Arc<Survey>> {
        let spec = if self.accuracy < 0.0 {
            AccuracySpec::Auto
        } else {
            self.accuracy.into()
        };
        Survey::build(self.grid(), spec, Some(self.crs()), LAYOUT)
            .ok()
            .map(Arc::new)
    }
}

fn any_spec() -> impl Strategy<Value = Spec> {
    (
        0usize..4,
        12usize..36,
        12usize..36,
        (-10.0f64..10.0, -10.0f64..10.0),
        prop_oneof![Just(0.0), 0.0f64..std::f64::consts::TAU],
        prop_oneof![Just(None), Just(None), (-0.6f64..0.6).prop_map(Some)],
        (0.5f64..2.5, 0.5f64..2.5),
        prop::collection::vec((0.0f64..36.0, 0.0f64..36.0, 1.0f64..5.0), 0..3),
        prop_oneof![Just(0.0), Just(0.5), Just(3.0), Just(-1.0)],
    )
        .prop_map(
            |(crs, cols, rows, origin, theta, skew, step, voids, accuracy)| Spec {
                crs,
                cols,
                rows,
                origin: [origin.0, origin.1],
                theta,
                skew,
                step: [step.0, step.1],
                voids,
                accuracy,
            },
        )
}

fn build(specs: &[Spec]) -> Vec<(Spec, Arc<Survey>)> {
    let mut out: Vec<(Spec, Arc<Survey>)> = specs
        .iter()
        .filter_map(|s| Some((s.clone(), s.survey()?)))
        .collect();
    out.sort_by_key(|(_, s)| s.id);
    out.dedup_by_key(|(_, s)| s.id);
    out
}

fn terrain(surveys: &[(Spec, Arc<Survey>)]) -> Terrain {
    let mut t = Terrain::with_crs(IndexConfig::default(), Some(&store()), None);
    for (_, s) in surveys {
        t.insert(s.clone());
    }
    t
}

fn bounds(t: &Terrain, surveys: &[(Spec, Arc<Survey>)]) -> Aabb {
    surveys
        .iter()
        .map(|(_, s)| t.survey(s.id).unwrap().footprint())
        .reduce(|a, b| a.union(&b))
        .unwrap()
}

/// Where a store point lies in a survey's own plane, as the terrain evaluates it there.
fn native(t: &Terrain, s: &Survey, p: [f64; 2]) -> Option<[f64; 2]> {
    let planes = t.planes().unwrap();
    match planes.get(s.crs.as_ref().unwrap()).unwrap() {
        Some(plane) => plane.to_native.at(p),
        None => Some(p),
    }
}

/// A random point of a valid level-0 cell of a survey, in the store's plane.
fn valid_point(s: &Survey, a: f64, b: f64, c: f64) -> Option<[f64; 2]> {
    let q = common::valid_point(s, a, b, c)?;
    Transform::new(s.crs.as_ref().unwrap(), &store())
        .unwrap()
        .apply(q)
}

proptest! {
    #![proptest_config(config(48))]

    #[test]
    fn across_crss_order_and_retirement_do_not_matter(
        specs in prop::collection::vec(any_spec(), 2..5),
        perm in any::<u64>(),
        victim in any::<prop::sample::Index>(),
    ) {
        let surveys = build(&specs);
        prop_assume!(surveys.len() >= 2);
        let forward = terrain(&surveys);
        let mut order = surveys.clone();
        for i in (1..order.len()).rev() {
            order.swap(i, (perm as usize >> (i % 16)) % (i + 1));
        }
        let shuffled = terrain(&order);
        prop_assert_eq!(forward.index().state(), shuffled.index().state());
        let v = victim.get(&surveys).1.clone();
        let mut retired = shuffled.clone();
        prop_assert!(retired.retire(v.id).is_some());
        let without: Vec<_> = surveys.iter().filter(|(_, s)| s.id != v.id).cloned().collect();
        prop_assert_eq!(retired.index().state(), terrain(&without).index().state());
        retired.index().check().map_err(TestCaseError::fail)?;
        // The same heights from either order, to the bit.
        let roi = bounds(&forward, &surveys);
        for e in [0.0, 2.0, 20.0] {
            let a: Vec<u32> = forward.tile(&roi, 24, 20, e).heights.iter().map(|z| z.to_bits()).collect();
            let b: Vec<u32> = shuffled.tile(&roi, 24, 20, e).heights.iter().map(|z| z.to_bits()).collect();
            prop_assert_eq!(a, b, "e = {}", e);
        }
    }

    #[test]
    fn across_crss_every_valid_point_has_a_height_within_the_error(
        specs in prop::collection::vec(any_spec(), 1..4),
        e in prop_oneof![Just(0.0), 0.0f64..40.0],
        picks in prop::collection::vec((any::<prop::sample::Index>(), 0.0f64..1.0, 0.0f64..1.0, 0.0f64..1.0), 20),
    ) {
        let surveys = build(&specs);
        prop_assume!(!surveys.is_empty());
        let t = terrain(&surveys);
        let ps = t.uniform(&bounds(&t, &surveys), e);
        for (si, a, b, c) in picks {
            let s = &si.get(&surveys).1;
            let Some(p) = valid_point(s, a, b, c) else { continue };
            let h = t.sample(&[p], e)[0] as f64;
            prop_assert!(!h.is_nan(), "nothing at a valid point {:?} of {:?}, e = {}", p, s.crs, e);
            // Within the error of the patches that serve there, of the surveys' own heights
            // at the point: each survey's bilinear surface where the terrain evaluates it.
            let best = ps.iter().map(|x| x.span.min_z).fold(f64::INFINITY, f64::min);
            let bound = ps.iter().map(|x| x.span.min_z).fold(e, f64::max).max(best);
            let heights: Vec<f64> = surveys
                .iter()
                .filter_map(|(_, o)| {
                    let q = native(&t, o, p)?;
                    o.levels[0].bilinear(q)
                })
                .collect();
            prop_assume!(!heights.is_empty());
            let lo = heights.iter().cloned().fold(f64::INFINITY, f64::min);
            let hi = heights.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            prop_assert!(h >= lo - bound - 1e-3 && h <= hi + bound + 1e-3,
                "at {:?}: {} outside [{}, {}] ± {}", p, h, lo, hi, bound);
        }
    }

    #[test]
    fn across_crss_a_height_does_not_depend_on_the_tile(
        specs in prop::collection::vec(any_spec(), 1..4),
        e in prop_oneof![Just(0.0), 0.0f64..30.0],
        split in (1usize..23, 1usize..19),
    ) {
        let surveys = build(&specs);
        prop_assume!(!surveys.is_empty());
        let t = terrain(&surveys);
        let roi = bounds(&t, &surveys);
        let (w, h) = (24usize, 20usize);
        let big = t.tile(&roi, w, h, e).heights;
        let (dx, dy) = (roi.width() / w as f64, roi.height() / h as f64);
        let (sx, sy) = split;
        let sub_roi = Aabb::new(roi.min[0] + sx as f64 * dx, roi.min[1], roi.max[0], roi.max[1] - sy as f64 * dy);
        let sub = t.tile(&sub_roi, w - sx, h - sy, e).heights;
        for j in sy..h {
            for i in sx..w {
                let (x, y) = (big[j * w + i], sub[(j - sy) * (w - sx) + (i - sx)]);
                prop_assert_eq!(x.is_nan(), y.is_nan(), "mask at ({}, {})", i, j);
                if !x.is_nan() {
                    let step = f32::from_bits(x.abs().to_bits() + 1) - x.abs();
                    prop_assert!((x - y).abs() <= 1e-4f32.max(step), "{} vs {} at ({}, {})", x, y, i, j);
                }
            }
        }
    }

    #[test]
    fn a_survey_of_another_crs_alone_gives_back_its_samples(
        spec in any_spec(),
    ) {
        let spec = Spec { accuracy: 0.0, voids: Vec::new(), ..spec };
        let Some(s) = spec.survey() else { return Ok(()) };
        let t = terrain(&[(spec.clone(), s.clone())]);
        let g = &s.levels[0];
        let to_store = Transform::new(s.crs.as_ref().unwrap(), &store()).unwrap();
        let pts: Vec<[f64; 2]> = (0..g.rows)
            .flat_map(|r| (0..g.cols).map(move |c| (c, r)))
            .map(|(c, r)| to_store.apply(g.georef.to_world(c as f64, r as f64)).unwrap())
            .collect();
        let hs = t.sample(&pts, 0.0);
        for (k, h) in hs.iter().enumerate() {
            let z = g.samples[k];
            prop_assert!((h - z).abs() <= 1e-3, "sample {} of {:?}: {} for {}", k, s.crs, h, z);
        }
    }
}
