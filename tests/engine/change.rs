//! Ground that changed, through the engine: an SRTM crop dated 2000 and a resurvey of it dated
//! 2024 in its sidecar, with a change drawn at random (the seed is printed) and fresh noise,
//! ingested in a random order. The resurvey serves the changed ground, `surveys` lists the
//! change with the survey that saw it last, and a sidecar whose `acquired` is no date, or
//! changes for samples already served, is refused with a clear error.

use crate::common;

use common::daemon::crop;
use common::seed;
use patchwork::config::Config;
use patchwork::engine::{conflicts_of, Engine, Later, Origin, Outcome, Reason};
use patchwork_read::write_tiff::write_geotiff_f32;
use patchwork_read::{read_raster, ReadLimits};
use patchwork_testkit::changes::{self, Kind};
use patchwork_testkit::copies::noisy;
use std::path::Path;

fn engine(dir: &Path) -> Engine {
    Engine::open(Config {
        data_dir: dir.join("data"),
        ingest_roots: vec![dir.to_path_buf()],
        crs: Some("EPSG:4326".into()),
        ..Config::default()
    })
    .unwrap()
}

#[test]
fn a_dated_resurvey_serves_the_ground_that_changed_and_the_listing_says_where() {
    let seed = seed();
    let mut next = patchwork_core::geom::rng::uniform(seed);
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let name = "srtm_n44e005_voids_crop.tif";
    let raster = read_raster(&crop(name), &ReadLimits::default()).unwrap();
    let crs = raster.crs.crs.clone();
    let g = raster.clone().into_grid().unwrap();
    let old = dir.join("ventoux_2000.tif");
    std::fs::copy(crop(name), &old).unwrap();
    std::fs::write(
        dir.join("ventoux_2000.tif.toml"),
        "acquired = \"2000-02-11/2000-02-22\"\n",
    )
    .unwrap();
    // A pit, a mound or a slide well past SRTM's claims (about 16 m here).
    let kind = [Kind::Pit, Kind::Mound, Kind::Slide][(next() * 3.0) as usize];
    let drawn = changes::apply(kind, &g, 40.0, &mut next);
    let after = noisy(&drawn.after, 0.5, seed);
    let new = dir.join("ventoux_2024.tif");
    write_geotiff_f32(
        &new,
        after.cols,
        after.rows,
        &after.samples,
        raster.geotransform,
        crs.as_ref(),
        Some(-32768.0),
    )
    .unwrap();
    std::fs::write(
        dir.join("ventoux_2024.tif.toml"),
        "acquired = \"2024-06\"\n",
    )
    .unwrap();
    let mut files = [old.clone(), new.clone()];
    if next() < 0.5 {
        files.swap(0, 1);
    }
    println!(
        "{}; ingested {:?} first",
        drawn.label,
        files[0].file_name().unwrap()
    );
    let e = engine(dir);
    for f in &files {
        let done = e.ingest(f, None, Origin::Request).unwrap();
        assert_eq!(done.outcome, Outcome::Inserted, "{}", done.error);
    }
    let t = e.snapshot();
    let ids: Vec<_> = t.surveys().map(|s| s.id).collect();
    assert_eq!(ids.len(), 2);
    let resurvey = t
        .surveys()
        .find(|s| s.epoch.is_some_and(|ep| ep.start > 1_500_000_000))
        .expect("the resurvey, dated 2024")
        .id;
    // The listing: the change, seen from the resurvey, which saw it last.
    let conflicts = conflicts_of(&t, resurvey);
    let changes: Vec<_> = conflicts.iter().flat_map(|c| c.changes.iter()).collect();
    assert!(!changes.is_empty(), "no change listed: {conflicts:?}");
    assert!(
        changes.iter().all(|c| c.later == Later::This),
        "{changes:?}"
    );
    let most = changes.iter().map(|c| c.most_m).fold(0.0, f64::max);
    let (gained, lost): (f64, f64) = changes
        .iter()
        .fold((0.0, 0.0), |a, c| (a.0 + c.gained_m3, a.1 + c.lost_m3));
    println!("listed: {changes:?}");
    assert!(most > 30.0, "largest change {most:.1} m");
    match kind {
        Kind::Pit => assert!(
            lost > 10.0 * gained,
            "a pit gained {gained} and lost {lost}"
        ),
        Kind::Mound => assert!(
            gained > 10.0 * lost,
            "a mound gained {gained} and lost {lost}"
        ),
        _ => assert!(
            gained > 0.0 && lost > 0.0,
            "a slide gained {gained} and lost {lost}"
        ),
    }
    // The samples changed by more than 40 m are served as resurveyed, at e = 0: at least
    // 80% of them in a draw.
    let mut pts = Vec::new();
    let mut want = Vec::new();
    for r in 0..g.rows {
        for c in 0..g.cols {
            let i = r * g.cols + c;
            if !g.samples[i].is_nan() && drawn.delta[i].abs() > 40.0 {
                pts.push(g.georef.to_world(c as f64, r as f64));
                want.push((drawn.after.samples[i], drawn.delta[i]));
            }
        }
    }
    assert!(pts.len() > 50, "{} changed samples", pts.len());
    let got = t.sample(&pts, 0.0);
    let served = got
        .iter()
        .zip(&want)
        .filter(|(h, (z, d))| (**h - z).abs() < 0.5 * d.abs())
        .count();
    println!(
        "{served} of {} changed samples served as resurveyed",
        pts.len()
    );
    // As the core's draws hold each draw (a slide of 81 m on Mont Ventoux kept 91%).
    assert!(served as f64 >= 0.8 * pts.len() as f64);

    // A new epoch for the same samples is refused, and the survey keeps serving.
    std::fs::write(dir.join("ventoux_2024.tif.toml"), "acquired = \"1999\"\n").unwrap();
    let done = e.ingest(&new, None, Origin::Request).unwrap();
    assert_eq!(done.outcome, Outcome::Failed);
    assert!(done.error.contains("retire"), "{}", done.error);
    assert_eq!(e.snapshot().surveys().count(), 2);
}

#[test]
fn a_sidecar_acquired_that_is_no_date_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let f = dir.join("cop.tif");
    std::fs::copy(crop("copernicus_n34w119_crop.tif"), &f).unwrap();
    std::fs::write(dir.join("cop.tif.toml"), "acquired = \"last spring\"\n").unwrap();
    let e = engine(dir);
    let done = e.ingest(&f, None, Origin::Request).unwrap();
    assert_eq!(done.outcome, Outcome::Failed);
    assert_eq!(done.reason, Some(Reason::Sidecar));
    assert!(done.error.contains("acquired"), "{}", done.error);
}
