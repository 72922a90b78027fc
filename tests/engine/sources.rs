//! Provenance: every height names what served it. Points over two overlapping surveys are
//! drawn at random (the seed is printed); each point's source must be a survey whose data
//! covers it, the more accurate one where both do, and carry what the survey's sidecar says;
//! asking for sources changes no height; a tile's shares add up to its samples; and a sidecar
//! edited afterwards is what the sources say from then on.

use crate::common;

use common::daemon::crop;
use common::seed;
use patchwork::config::Config;
use patchwork::engine::{Backend, Ctx, Cut, Engine, Origin, Outcome, SampleRequest, TileRequest};
use patchwork_core::geom::Aabb;
use patchwork_read::{read_raster, ReadLimits};
use std::path::{Path, PathBuf};

const COP_SIDECAR: &str = "title = \"Copernicus DEM GLO-30\"\n\
    license = \"Copernicus DEM licence\"\n\
    attribution = \"© DLR e.V. and © Airbus, provided under COPERNICUS by the EU and ESA\"\n\
    acquired = \"2011-01/2015-01\"\n";

/// The Copernicus crop with a sidecar saying where it came from, claimed at 3 m, and the
/// NASADEM crop of the same ground with none, at 8 m.
fn two_surveys(dir: &Path) -> (Engine, PathBuf, PathBuf) {
    let cop = dir.join("cop.tif");
    std::fs::copy(crop("copernicus_n34w119_crop.tif"), &cop).unwrap();
    std::fs::write(
        dir.join("cop.tif.toml"),
        format!("accuracy_m = 3.0\n{COP_SIDECAR}"),
    )
    .unwrap();
    let nas = dir.join("nas.tif");
    std::fs::copy(crop("nasadem_n34w119_crop.tif"), &nas).unwrap();
    std::fs::write(dir.join("nas.tif.toml"), "accuracy_m = 8.0\n").unwrap();
    let e = Engine::open(Config {
        data_dir: dir.join("data"),
        ingest_roots: vec![dir.to_path_buf()],
        crs: Some("EPSG:4326".into()),
        ..Config::default()
    })
    .unwrap();
    for f in [&cop, &nas] {
        let done = e.ingest(f, None, Origin::Request).unwrap();
        assert_eq!(done.outcome, Outcome::Inserted, "{}", done.error);
    }
    (e, cop, nas)
}

/// The bounds of a crop's samples, degrees.
fn bounds(name: &str) -> Aabb {
    let r = read_raster(&crop(name), &ReadLimits::default()).unwrap();
    let (x0, y0) = r.pixel_centre(0, 0);
    let (x1, y1) = r.pixel_centre(r.cols - 1, r.rows - 1);
    Aabb::new(x0.min(x1), y0.min(y1), x0.max(x1), y0.max(y1))
}

#[test]
fn every_height_names_the_survey_that_served_it_and_what_its_sidecar_says() {
    let tmp = tempfile::tempdir().unwrap();
    let (e, cop, nas) = two_surveys(tmp.path());
    let (cb, nb) = (
        bounds("copernicus_n34w119_crop.tif"),
        bounds("nasadem_n34w119_crop.tif"),
    );
    let all = cb.union(&nb);
    let seed = seed();
    let mut next = patchwork_core::geom::rng::uniform(seed);
    // Over both crops and a little beyond them.
    let pad = 0.01;
    let pts: Vec<[f64; 2]> = (0..2000)
        .map(|_| {
            let (u, v) = (next(), next());
            [
                all.min[0] - pad + u * (all.width() + 2.0 * pad),
                all.min[1] - pad + v * (all.height() + 2.0 * pad),
            ]
        })
        .collect();
    let (_, listing) = e.surveys();
    let id_of = |f: &Path| {
        listing
            .records
            .iter()
            .find(|r| Path::new(&r.source) == f)
            .unwrap()
            .id
    };
    let (cop_id, nas_id) = (id_of(&cop), id_of(&nas));
    let cop_record = listing.records.iter().find(|r| r.id == cop_id).unwrap();
    assert_eq!(
        cop_record.about.title.as_deref(),
        Some("Copernicus DEM GLO-30")
    );
    assert_eq!(
        cop_record.about.acquired.as_deref(),
        Some("2011-01/2015-01")
    );

    for error in [0.0, 5.0, 30.0] {
        let plain = SampleRequest::new(pts.clone(), None, error).unwrap();
        let without = e.sample(&plain, Ctx::default()).unwrap();
        let with = e
            .sample(&plain.clone().with_sources(true), Ctx::default())
            .unwrap();
        assert!(without.sources.is_empty());
        assert_eq!(with.sources.len(), pts.len());
        let (mut from_cop, mut from_nas) = (0, 0);
        for (k, p) in pts.iter().enumerate() {
            let (a, b) = (without.heights[k], with.heights[k]);
            assert_eq!(
                a.to_bits(),
                b.to_bits(),
                "e {error}: point {k} changed height"
            );
            let Some(s) = &with.sources[k] else {
                assert!(
                    a.is_nan(),
                    "e {error}: point {k} {p:?} has a height and no source"
                );
                continue;
            };
            assert!(
                !a.is_nan(),
                "e {error}: point {k} {p:?} has a source and no height"
            );
            // A survey serves only where its data can reach: its cells and a cell around.
            let near = |b: &Aabb| {
                let g = 2.0 / 3600.0 * 2f64.powi(s.level as i32);
                p[0] > b.min[0] - g
                    && p[0] < b.max[0] + g
                    && p[1] > b.min[1] - g
                    && p[1] < b.max[1] + g
            };
            if s.survey == cop_id {
                from_cop += 1;
                assert!(
                    near(&cb),
                    "e {error}: {p:?} served by Copernicus, outside it"
                );
                assert_eq!(s.about.title.as_deref(), Some("Copernicus DEM GLO-30"));
                assert_eq!(s.about.license.as_deref(), Some("Copernicus DEM licence"));
                assert!(s.file.ends_with("cop.tif"), "{}", s.file);
            } else {
                assert_eq!(s.survey, nas_id);
                from_nas += 1;
                assert!(near(&nb), "e {error}: {p:?} served by NASADEM, outside it");
                assert_eq!(s.about, Default::default());
            }
            // One arc-second cells, about 25 × 31 m here, doubled a level.
            let cell = 30.9 * 2f64.powi(s.level as i32);
            assert!(
                (s.cell_m - cell).abs() < 0.05 * cell,
                "e {error}: a level-{} cell of {} m",
                s.level,
                s.cell_m
            );
            assert!(s.error_m >= 0.0);
            // Where Copernicus has data, it is the more accurate and must serve at e = 0.
            let inner = |b: &Aabb| {
                let m = 4.0 / 3600.0;
                p[0] > b.min[0] + m
                    && p[0] < b.max[0] - m
                    && p[1] > b.min[1] + m
                    && p[1] < b.max[1] - m
            };
            if error == 0.0 && inner(&cb) {
                assert_eq!(s.survey, cop_id, "{p:?}: the less accurate survey served");
            }
        }
        println!("e {error}: {from_cop} points from Copernicus, {from_nas} from NASADEM");
        assert!(from_cop > 100 && from_nas > 100, "{from_cop} {from_nas}");
    }

    // A tile over both: each survey's share of the samples it served, adding up.
    let roi = Aabb::new(cb.min[0], nb.min[1], nb.max[0], cb.max[1]);
    let cut = Cut::new(None, roi, 5.0).unwrap();
    let req = TileRequest::new(cut, 200, 150, Backend::Cpu).unwrap();
    let (tile, _, _) = e.tile(&req, Ctx::default()).unwrap();
    let shares = e.tile_sources(&req, Ctx::default()).unwrap();
    let with_data = tile.heights.iter().filter(|h| !h.is_nan()).count() as u64;
    assert_eq!(shares.iter().map(|s| s.samples).sum::<u64>(), with_data);
    let total: f64 = shares.iter().map(|s| s.share).sum();
    assert!((total - 1.0).abs() < 1e-9, "{total}");
    assert_eq!(shares.len(), 2, "{shares:?}");
    assert!(shares.windows(2).all(|w| w[0].samples >= w[1].samples));

    // A sidecar edited afterwards: the samples are the same survey, what it says is new. Its
    // epoch stays (a new one is a new survey: tests/engine/change.rs).
    std::fs::write(
        tmp.path().join("cop.tif.toml"),
        "accuracy_m = 3.0\ntitle = \"GLO-30, tile N34 W119\"\nacquired = \"2011-01/2015-01\"\n",
    )
    .unwrap();
    let done = e.ingest(&cop, None, Origin::Request).unwrap();
    assert_eq!(done.survey, Some(cop_id), "{done:?}");
    let s = e
        .sample(
            &SampleRequest::new(vec![[cb.min[0] + 0.002, cb.max[1] - 0.002]], None, 0.0)
                .unwrap()
                .with_sources(true),
            Ctx::default(),
        )
        .unwrap();
    let about = &s.sources[0].as_ref().unwrap().about;
    assert_eq!(about.title.as_deref(), Some("GLO-30, tile N34 W119"));
    assert_eq!(about.license, None);
}

#[test]
fn a_sidecar_field_that_is_not_a_line_of_text_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let f = dir.join("cop.tif");
    std::fs::copy(crop("copernicus_n34w119_crop.tif"), &f).unwrap();
    std::fs::write(dir.join("cop.tif.toml"), "title = \"two\\nlines\"\n").unwrap();
    let e = Engine::open(Config {
        data_dir: dir.join("data"),
        ingest_roots: vec![dir.to_path_buf()],
        ..Config::default()
    })
    .unwrap();
    let done = e.ingest(&f, None, Origin::Request).unwrap();
    assert_eq!(done.outcome, Outcome::Failed);
    assert_eq!(done.reason, Some(patchwork::engine::Reason::Sidecar));
    assert!(done.error.contains("title"), "{}", done.error);
}
