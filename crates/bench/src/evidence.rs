//! Accuracy that copies cannot fake: every kind of copy of [`super::copies::standard`] beside
//! its original (and, where one is given, a third survey of the same ground), in a store that
//! keeps claims as made ("before") and in one that distrusts those the overlap contradicts
//! ("after"). For each: the shift each coregistration method finds, the verdict, the estimated
//! and served ε of original and copy, and the served tile's error against the original.

use super::copies::{self, Copy};
use patchwork_core::crs::Crs;
use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::AccuracySpec;
use patchwork_core::model::coreg::{self, Method};
use patchwork_core::model::evidence::Contradicted;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::survey::Survey;
use patchwork_core::terrain::Terrain;
use std::fmt::Write as _;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use crate::Fail;

/// The errors tiles are asked at.
pub const ERRORS: [f64; 2] = [0.0, 10.0];

/// One coregistration method on one copy: the shift found less the truth, in cells, the
/// offset found less the truth, in metres, and the time it took.
#[derive(Clone, Debug)]
pub struct Found {
    /// The method's name.
    pub method: &'static str,
    /// Distance of the shift found from the true one, cells.
    pub shift_error_px: f64,
    /// The offset found less the true one, metres.
    pub dz_error_m: f64,
    /// Time the method took, milliseconds.
    pub ms: f64,
}

/// One tile over the original at one error, before and after.
#[derive(Clone, Copy, Debug)]
pub struct TileError {
    /// The requested error e, metres.
    pub error: f64,
    /// RMS difference from the original with claims kept as made, metres.
    pub before_rms: f64,
    /// Largest difference from the original with claims kept as made, metres.
    pub before_max: f64,
    /// RMS difference from the original with contradicted claims distrusted, metres.
    pub after_rms: f64,
    /// Largest difference from the original with contradicted claims distrusted, metres.
    pub after_max: f64,
    /// The store without the copy, distrusting: what the copy should leave as it is.
    pub without_rms: f64,
    /// Largest difference from the original in the store without the copy, metres.
    pub without_max: f64,
}

/// One copy beside its original, with claims kept and distrusted.
#[derive(Clone, Debug)]
pub struct Case {
    /// The original's file name, and whether a third survey is in the store.
    pub scene: String,
    /// The copy's label.
    pub copy: &'static str,
    /// What each coregistration method finds.
    pub found: Vec<Found>,
    /// Whose claim the store distrusts: "copy", "original" or "both"; "none" where no pair
    /// finds a claim false.
    pub verdict: &'static str,
    /// Median kernel ε, metres: the original's and the copy's as estimated, then as served.
    pub orig_claimed: f64,
    /// The original's median kernel ε as served, metres.
    pub orig_served: f64,
    /// The copy's median kernel ε as estimated, metres.
    pub copy_claimed: f64,
    /// The copy's median kernel ε as served, metres.
    pub copy_served: f64,
    /// A tile over the original at each of [`ERRORS`].
    pub tiles: Vec<TileError>,
}

/// Every copy of each scene's original: (name, original, a third survey of the same ground).
pub fn run(scenes: &[(String, Grid, Option<Grid>)], crs: Option<Crs>) -> Result<Vec<Case>, Fail> {
    let mut out = Vec::new();
    for (name, g, third) in scenes {
        let survey = |g: &Grid| -> Result<Arc<Survey>, Fail> {
            Ok(Arc::new(Survey::build(
                g.clone(),
                AccuracySpec::Auto,
                crs.clone(),
                PatchLayout::default(),
            )?))
        };
        let orig = survey(g)?;
        let mut base = vec![orig.clone()];
        if let Some(t) = third {
            base.push(survey(t)?);
        }
        let scene = if third.is_some() {
            format!("{name} with a third survey")
        } else {
            name.clone()
        };
        let mut without = Terrain::new(IndexConfig::default());
        for s in &base {
            without.insert(s.clone());
        }
        for c in copies::standard(g) {
            let copy = survey(&c.grid)?;
            out.push(case(&scene, g, &orig, &base, &without, &c, &copy)?);
        }
    }
    Ok(out)
}

fn case(
    scene: &str,
    g: &Grid,
    orig: &Arc<Survey>,
    base: &[Arc<Survey>],
    without: &Terrain,
    c: &Copy,
    copy: &Arc<Survey>,
) -> Result<Case, Fail> {
    let terrain = |policy| -> Terrain {
        let mut t = Terrain::new(IndexConfig::default());
        t.set_contradicted(policy);
        for s in base.iter().chain([copy]) {
            t.insert(s.clone());
        }
        t
    };
    let (before, after) = (terrain(Contradicted::Keep), terrain(Contradicted::Distrust));
    // The methods as the store runs them: the finer survey is the reference.
    let (reference, other, sign) = if copy.finer_than(orig) {
        (&c.grid, g, -1.0)
    } else {
        (g, &c.grid, 1.0)
    };
    let bounds = g
        .world_bounds()
        .intersection(&c.grid.world_bounds())
        .ok_or("a copy off its original")?;
    let step = g.georef.step;
    let mut found = Vec::new();
    for (method, m) in [
        ("search", Method::Search),
        ("Nuth-Kääb", Method::Fit),
        ("search + Nuth-Kääb", Method::SearchThenFit),
    ] {
        let t0 = Instant::now();
        let k = coreg::coregister_by(m, reference, other, &|p| Some(p), &bounds)
            .ok_or("no coregistration")?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        // Where the copy's content lies against the original's, in the original's cells.
        let px = [sign * k.shift[0] / step[0], -sign * k.shift[1] / step[1]];
        found.push(Found {
            method,
            shift_error_px: (px[0] - c.shift_px[0]).hypot(px[1] - c.shift_px[1]),
            dz_error_m: sign * k.dz - c.dz,
            ms,
        });
    }
    let verdict = match patchwork_engine::conflicts_of(&after, copy.id)
        .iter()
        .find(|k| k.survey == orig.id)
        .map(|k| k.distrusted)
    {
        Some(patchwork_engine::Distrusted::This) => "copy",
        Some(patchwork_engine::Distrusted::Other) => "original",
        Some(patchwork_engine::Distrusted::Both) => "both",
        None => "none",
    };
    let median = |t: &Terrain, s: &Survey, served: bool| {
        let m = if served { t.survey(s.id) } else { t.base(s.id) };
        m.map_or(f64::NAN, |m| m.kernel_accuracy.quantile(0.5))
    };
    let roi = g.world_bounds();
    let tiles = ERRORS
        .iter()
        .map(|&e| {
            let (br, bm) = off_original(&before, g, &roi, e);
            let (ar, am) = off_original(&after, g, &roi, e);
            let (wr, wm) = off_original(without, g, &roi, e);
            TileError {
                error: e,
                before_rms: br,
                before_max: bm,
                after_rms: ar,
                after_max: am,
                without_rms: wr,
                without_max: wm,
            }
        })
        .collect();
    Ok(Case {
        scene: scene.to_string(),
        copy: c.label,
        found,
        verdict,
        orig_claimed: median(&after, orig, false),
        orig_served: median(&after, orig, true),
        copy_claimed: median(&after, copy, false),
        copy_served: median(&after, copy, true),
        tiles,
    })
}

/// RMS and largest difference of a 256² tile of `t` from `g`'s own surface, where `g` has
/// data.
fn off_original(t: &Terrain, g: &Grid, roi: &Aabb, e: f64) -> (f64, f64) {
    let n = 256;
    let tile = t.tile(roi, n, n, e);
    let (mut ss, mut max, mut k) = (0.0, 0.0f64, 0usize);
    for j in 0..n {
        for i in 0..n {
            let p = [
                roi.min[0] + (i as f64 + 0.5) * roi.width() / n as f64,
                roi.max[1] - (j as f64 + 0.5) * roi.height() / n as f64,
            ];
            let (Some(zo), z) = (g.bilinear(p), tile.heights[j * n + i] as f64) else {
                continue;
            };
            if z.is_nan() {
                continue;
            }
            ss += (z - zo) * (z - zo);
            max = max.max((z - zo).abs());
            k += 1;
        }
    }
    ((ss / k.max(1) as f64).sqrt(), max)
}

/// Writes `copies.csv` and `coreg.csv` under `out`.
pub fn write_csv(out: &Path, cases: &[Case]) -> std::io::Result<()> {
    let mut s = String::from(
        "scene,copy,verdict,original_eps_median_m,original_served_median_m,copy_eps_median_m,copy_served_median_m,error_m,before_rms_m,before_max_m,after_rms_m,after_max_m,without_rms_m,without_max_m\n",
    );
    for c in cases {
        for t in &c.tiles {
            let _ = writeln!(
                s,
                "{},\"{}\",{},{:.3},{:.3},{:.3},{:.3},{},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3}",
                c.scene,
                c.copy,
                c.verdict,
                c.orig_claimed,
                c.orig_served,
                c.copy_claimed,
                c.copy_served,
                t.error,
                t.before_rms,
                t.before_max,
                t.after_rms,
                t.after_max,
                t.without_rms,
                t.without_max
            );
        }
    }
    std::fs::write(out.join("copies.csv"), s)?;
    let mut s = String::from("scene,copy,method,shift_error_px,dz_error_m,ms\n");
    for c in cases {
        for f in &c.found {
            let _ = writeln!(
                s,
                "{},\"{}\",{},{:.4},{:.3},{:.1}",
                c.scene, c.copy, f.method, f.shift_error_px, f.dz_error_m, f.ms
            );
        }
    }
    std::fs::write(out.join("coreg.csv"), s)
}

/// The cases as the bench prints them.
pub fn print(cases: &[Case]) {
    for c in cases {
        let t = c.tiles.last().expect("tiles");
        let f: Vec<String> = c
            .found
            .iter()
            .map(|f| format!("{} {:.2} px", f.method, f.shift_error_px))
            .collect();
        println!(
            "{}, {}: distrusted {}; ε median original {:.2} → {:.2} m, copy {:.2} → {:.2} m; tile at e = {} off the original {:.2} m RMS ({:.1} max) before, {:.2} ({:.1}) after, {:.2} ({:.1}) without the copy; shift off by {}",
            c.scene,
            c.copy,
            c.verdict,
            c.orig_claimed,
            c.orig_served,
            c.copy_claimed,
            c.copy_served,
            t.error,
            t.before_rms,
            t.before_max,
            t.after_rms,
            t.after_max,
            t.without_rms,
            t.without_max,
            f.join(", ")
        );
    }
}
