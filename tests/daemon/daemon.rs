//! The daemon end to end: the real binary on a free loopback port, real files dropped into a
//! temporary inbox, the real CLI talking to it.

use crate::common;

use common::daemon::*;
use patchwork_read::write_tiff::write_geotiff_f32;
use serde_json::Value;
use std::path::Path;
use std::time::Duration;

fn answers(d: &Daemon) -> Vec<Value> {
    let mut out = Vec::new();
    for roi in [
        "-119,34.5,-118.9,34.6",
        "-118.98,34.52,-118.95,34.55",
        "5.2,44.9,5.4,45.0",
    ] {
        for e in ["0", "3", "20"] {
            out.push(d.json(&["query", "--roi", roi, "--error", e, "--json"]));
        }
    }
    out
}

#[test]
fn any_drop_order_and_restarts_give_identical_answers() {
    let tmp = tempfile::tempdir().unwrap();
    let files = [
        "copernicus_n34w119_crop.tif",
        "nasadem_n34w119_crop.tif",
        "srtm_n44e005_voids_crop.tif",
    ];

    let mut a = Daemon::start(&tmp.path().join("a"));
    for f in files {
        drop_by_rename(&crop(f), &a.inbox(), f);
    }
    a.wait("three surveys in a", |s| count(s, "active") == 3);

    let b = Daemon::start(&tmp.path().join("b"));
    copy_slowly(&crop(files[2]), &b.inbox().join(files[2]));
    copy_slowly(&crop(files[1]), &b.inbox().join(files[1]));
    std::fs::copy(crop(files[0]), b.inbox().join(files[0])).unwrap();
    let sb = b.wait("three surveys in b", |s| count(s, "active") == 3);
    assert_eq!(
        count(&sb, "failed"),
        0,
        "a half-copied file was taken: {sb:#?}"
    );

    let reference = answers(&a);
    assert!(reference
        .iter()
        .any(|v| !v["patches"].as_array().unwrap().is_empty()));
    assert_eq!(reference, answers(&b));

    // A clean restart and a kill -9 both keep everything.
    a.stop();
    let a = Daemon::start(&tmp.path().join("a"));
    assert_eq!(reference, answers(&a));
    let mut a = a;
    a.kill9();
    let a = Daemon::start(&tmp.path().join("a"));
    assert_eq!(reference, answers(&a));
    assert_eq!(count(&a.surveys(), "active"), 3);
}

#[test]
fn replacing_and_deleting_a_file_retire_the_right_survey() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "area.tif");
    drop_by_rename(
        &crop("srtm_n44e005_voids_crop.tif"),
        &d.inbox(),
        "other.tif",
    );
    let s = d.wait("two surveys", |s| count(s, "active") == 2);
    let first = s
        .iter()
        .find(|v| v["source"].as_str().unwrap().ends_with("area.tif"))
        .unwrap()["id"]
        .clone();

    // New content under the same name: the old survey retires, the new one is active.
    drop_by_rename(&crop("nasadem_n34w119_crop.tif"), &d.inbox(), "area.tif");
    let s = d.wait("the replacement", |s| {
        count(s, "retired") == 1 && count(s, "active") == 2
    });
    let retired = s.iter().find(|v| v["status"] == "retired").unwrap();
    assert_eq!(retired["id"], first);
    let now = s
        .iter()
        .find(|v| v["status"] == "active" && v["source"].as_str().unwrap().ends_with("area.tif"))
        .unwrap();
    assert_ne!(now["id"], first);

    // Deleting the file retires what it held, and only that.
    std::fs::remove_file(d.inbox().join("area.tif")).unwrap();
    let s = d.wait("the deletion", |s| count(s, "retired") == 2);
    let active: Vec<_> = s.iter().filter(|v| v["status"] == "active").collect();
    assert_eq!(active.len(), 1);
    assert!(active[0]["source"].as_str().unwrap().ends_with("other.tif"));
    let v = d.json(&["stats", "--json"]);
    assert_eq!(v["surveys"], 1);
}

/// A little-endian TIFF header with the given size and sample type and no pixel data.
fn bare_tiff(width: u32, height: u32, bits: u16, format: u16) -> Vec<u8> {
    let entries: Vec<(u16, u16, u32)> = vec![
        (256, 4, width),
        (257, 4, height),
        (258, 3, bits as u32),
        (259, 3, 1),
        (262, 3, 1),
        (273, 4, 0),
        (277, 3, 1),
        (278, 4, height),
        (279, 4, 0),
        (339, 3, format as u32),
    ];
    let mut b = b"II*\0".to_vec();
    b.extend_from_slice(&8u32.to_le_bytes());
    b.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    for (tag, ty, v) in entries {
        b.extend_from_slice(&tag.to_le_bytes());
        b.extend_from_slice(&ty.to_le_bytes());
        b.extend_from_slice(&1u32.to_le_bytes());
        if ty == 3 {
            b.extend_from_slice(&(v as u16).to_le_bytes());
            b.extend_from_slice(&[0, 0]);
        } else {
            b.extend_from_slice(&v.to_le_bytes());
        }
    }
    b.extend_from_slice(&0u32.to_le_bytes());
    b
}

fn small_geotiff(path: &Path, samples: &[f32], epsg: u32) {
    let n = (samples.len() as f64).sqrt() as usize;
    let gt = [500_000.0, 30.0, 0.0, 4_900_000.0, 0.0, -30.0];
    let crs = patchwork_core::crs::Crs::epsg(epsg).unwrap();
    write_geotiff_f32(path, n, n, samples, gt, Some(&crs), Some(-9999.0)).unwrap();
}

#[test]
fn bad_files_are_reported_and_the_daemon_keeps_serving() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "good.tif");
    d.wait("the good file", |s| count(s, "active") == 1);
    let before = answers(&d);

    let inbox = d.inbox();
    let stage = tmp.path().join("stage");
    std::fs::create_dir_all(&stage).unwrap();
    let good = std::fs::read(crop("copernicus_n34w119_crop.tif")).unwrap();
    std::fs::write(stage.join("empty.tif"), b"").unwrap();
    std::fs::write(stage.join("truncated.tif"), &good[..good.len() / 2]).unwrap();
    std::fs::write(
        stage.join("garbage.tif"),
        (0..5000u32)
            .map(|i| (i * 7919 % 251) as u8)
            .collect::<Vec<_>>(),
    )
    .unwrap();
    std::fs::write(
        stage.join("huge.tif"),
        bare_tiff(1_000_000, 1_000_000, 16, 2),
    )
    .unwrap();
    std::fs::write(stage.join("u64.tif"), bare_tiff(64, 64, 64, 1)).unwrap();
    small_geotiff(&stage.join("allvoid.tif"), &[f32::NAN; 64 * 64], 4326);
    small_geotiff(
        &stage.join("nonfinite.tif"),
        &[f32::NAN, f32::INFINITY, f32::NEG_INFINITY, f32::NAN].repeat(16 * 16),
        4326,
    );
    // Not a bad file: a survey in another CRS than the store's is taken as it is.
    small_geotiff(
        &stage.join("utm.tif"),
        &(0..64 * 64).map(|i| i as f32).collect::<Vec<_>>(),
        32631,
    );
    // Good samples under sidecars that cannot be right: an accuracy past the top of LOD
    // space, and a CRS that contradicts the file's own.
    std::fs::write(stage.join("inaccurate.tif"), &good).unwrap();
    std::fs::write(inbox.join("inaccurate.tif.toml"), "accuracy_m = 1e308\n").unwrap();
    std::fs::write(stage.join("mislabelled.tif"), &good).unwrap();
    std::fs::write(inbox.join("mislabelled.tif.toml"), "crs = \"EPSG:32630\"\n").unwrap();
    for f in std::fs::read_dir(&stage).unwrap().flatten() {
        std::fs::rename(f.path(), inbox.join(f.file_name())).unwrap();
    }
    std::fs::create_dir(inbox.join("folder.tif")).unwrap();
    std::os::unix::fs::symlink(tmp.path().join("nowhere.tif"), inbox.join("dangling.tif")).unwrap();
    // A link out of the inbox, to a good file, gets the same message as one that leads
    // nowhere: the inbox is no window onto the rest of the disk.
    std::os::unix::fs::symlink(
        crop("copernicus_n34w119_crop.tif"),
        inbox.join("outside.tif"),
    )
    .unwrap();

    let expect = [
        ("empty.tif", "empty"),
        ("truncated.tif", "truncated"),
        ("garbage.tif", "TIFF"),
        ("huge.tif", "1000000"),
        ("u64.tif", "64-bit"),
        ("allvoid.tif", "nodata"),
        ("nonfinite.tif", "nodata"),
        ("folder.tif", "directory"),
        ("dangling.tif", "symlinks followed"),
        ("outside.tif", "symlinks followed"),
        ("inaccurate.tif", "refused"),
        ("mislabelled.tif", "EPSG:32630"),
    ];
    let s = d.wait("every bad file to be reported", |s| {
        count(s, "failed") == expect.len() && count(s, "active") == 2
    });
    for (name, needle) in expect {
        let rec = s
            .iter()
            .find(|v| v["source"].as_str().unwrap().ends_with(name))
            .unwrap_or_else(|| panic!("{name} not listed: {s:#?}"));
        assert_eq!(rec["status"], "failed", "{name}");
        let msg = rec["error"].as_str().unwrap();
        assert!(
            msg.to_lowercase().contains(&needle.to_lowercase()),
            "{name}: {msg:?} does not mention {needle:?}"
        );
    }
    let utm = s
        .iter()
        .find(|v| v["source"].as_str().unwrap().ends_with("utm.tif"))
        .unwrap();
    assert_eq!(utm["status"], "active", "{utm:#}");
    assert_eq!(utm["crs"], "EPSG:32631");
    let mislabelled = s
        .iter()
        .find(|v| v["source"].as_str().unwrap().ends_with("mislabelled.tif"))
        .unwrap();
    assert!(mislabelled["error"].as_str().unwrap().contains("EPSG:4326"));
    // Nothing stored was touched, and the daemon still answers.
    assert_eq!(before, answers(&d));
    assert!(d.cli(&["verify"]).status.success());
    // A failed file is not retried until it changes; when it does, it is.
    d.settle_inbox();
    assert_eq!(count(&d.surveys(), "failed"), expect.len());
    std::fs::remove_file(inbox.join("empty.tif")).unwrap();
    drop_by_rename(&crop("nasadem_n34w119_crop.tif"), &inbox, "empty.tif");
    d.wait("the repaired file", |s| {
        count(s, "active") == 3 && count(s, "failed") == expect.len() - 1
    });
}

/// A survey the size of a full 1″ cell (3600², 26 MB), so that its ingest is under way when a
/// kill lands: the real NASADEM crop, mirrored across it so that the ground stays continuous.
fn big_survey(dir: &Path) -> std::path::PathBuf {
    let r = patchwork_read::read_raster(
        &crop("nasadem_n34w119_crop.tif"),
        &patchwork_read::ReadLimits::default(),
    )
    .unwrap();
    let n = 3600;
    let mirror = |i: usize, len: usize| {
        let k = i % (2 * len);
        if k < len {
            k
        } else {
            2 * len - 1 - k
        }
    };
    let samples: Vec<i16> = (0..n * n)
        .map(|k| r.get(mirror(k % n, r.cols), mirror(k / n, r.rows)) as i16)
        .collect();
    let path = dir.join("big_source.tif");
    patchwork_read::write_tiff::write_geotiff_i16(
        &path,
        n,
        n,
        &samples,
        r.geotransform,
        r.crs.crs.as_ref(),
        None,
    )
    .unwrap();
    path
}

#[test]
fn kill_9_during_ingest_loses_nothing_and_the_inbox_catches_up() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("store");
    std::fs::create_dir_all(root.join("inbox")).unwrap();
    let big = big_survey(tmp.path());
    let mut seed = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64;
    let mut rnd = move || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 33) % 1000
    };
    let names = ["big.tif", "c1.tif", "c2.tif"];
    for round in 0..4 {
        // Each round brings new files, so that ingestion is under way when the kill lands.
        let mut d = Daemon::start(&root);
        let dir = d.inbox();
        match round % 2 {
            0 => {
                let _ = std::fs::remove_file(dir.join(names[1]));
                drop_by_rename(&big, &dir, names[0]);
                drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &dir, names[1]);
            }
            _ => {
                let _ = std::fs::remove_file(dir.join(names[0]));
                drop_by_rename(&crop("srtm_n44e005_voids_crop.tif"), &dir, names[2]);
                drop_by_rename(&big, &dir, names[0]);
            }
        }
        std::thread::sleep(Duration::from_millis(100 + 2 * rnd()));
        d.kill9();

        // The store opens and verifies; every survey in it is whole.
        let d = Daemon::start(&root);
        let v = d.cli(&["verify"]);
        assert!(
            v.status.success(),
            "round {round}: {}{}",
            String::from_utf8_lossy(&v.stdout),
            String::from_utf8_lossy(&v.stderr)
        );
        // And what the kill interrupted is ingested again from the inbox.
        let present: Vec<_> = names.iter().filter(|n| dir.join(n).exists()).collect();
        let s = d.wait("the inbox to be caught up", |s| {
            present.iter().all(|n| {
                s.iter()
                    .any(|v| v["status"] == "active" && v["source"].as_str().unwrap().ends_with(*n))
            })
        });
        assert_eq!(count(&s, "failed"), 0, "round {round}: {s:#?}");
        assert!(d.cli(&["verify"]).status.success());
    }
}

#[test]
fn compaction_shrinks_the_store_and_keeps_every_answer() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    for f in [
        "copernicus_n34w119_crop.tif",
        "nasadem_n34w119_crop.tif",
        "srtm_n44e005_voids_crop.tif",
    ] {
        drop_by_rename(&crop(f), &d.inbox(), f);
    }
    d.wait("three surveys", |s| count(s, "active") == 3);
    for f in ["copernicus_n34w119_crop.tif", "srtm_n44e005_voids_crop.tif"] {
        let source = d.inbox().canonicalize().unwrap().join(f);
        let out = d.cli(&["retire", source.to_str().unwrap()]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let before = answers(&d);
    let size = |d: &Daemon| d.json(&["stats", "--json"])["disk_bytes"].as_u64().unwrap();
    let bytes_before = size(&d);
    let out = d.cli(&["compact"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let bytes_after = size(&d);
    assert!(
        bytes_after < bytes_before,
        "{bytes_before} → {bytes_after} bytes"
    );
    assert_eq!(before, answers(&d));
    assert!(d.cli(&["verify"]).status.success());
    println!("compaction: {bytes_before} → {bytes_after} bytes");
}

#[test]
fn a_copy_under_another_name_keeps_the_survey_when_the_first_goes() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(
        &crop("copernicus_n34w119_crop.tif"),
        &d.inbox(),
        "first.tif",
    );
    let s = d.wait("the first copy", |s| count(s, "active") == 1);
    let id = s[0]["id"].clone();
    drop_by_rename(
        &crop("copernicus_n34w119_crop.tif"),
        &d.inbox(),
        "second.tif",
    );
    d.settle_inbox();
    // Identical content is one survey.
    assert_eq!(count(&d.surveys(), "active"), 1);
    std::fs::remove_file(d.inbox().join("first.tif")).unwrap();
    let s = d.wait("the copy to take over", |s| {
        s.iter().any(|v| {
            v["status"] == "active" && v["source"].as_str().unwrap().ends_with("second.tif")
        })
    });
    let active: Vec<_> = s.iter().filter(|v| v["status"] == "active").collect();
    assert_eq!(active.len(), 1);
    assert_eq!(active[0]["id"], id);
    assert!(d.cli(&["verify"]).status.success());
}

#[test]
fn the_api_serves_views_points_and_change_events_and_says_what_is_wrong() {
    use patchwork::serve::proto::{self as pb, terrain_client::TerrainClient};
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let url = format!("http://127.0.0.1:{}", d.port);
        let mut t = TerrainClient::connect(url)
            .await
            .unwrap()
            .max_decoding_message_size(1 << 30);
        let mut events = t
            .subscribe(pb::SubscribeRequest {})
            .await
            .unwrap()
            .into_inner();

        drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "a.tif");
        let e = tokio::time::timeout(Duration::from_secs(30), events.message())
            .await
            .unwrap()
            .unwrap()
            .unwrap();
        assert_eq!(e.outcome(), pb::Outcome::Inserted);
        assert!(e.source.ends_with("a.tif"));

        // Heights at points are the survey's own at e = 0, and nodata off the data.
        let grid =
            patchwork_read::read_raster(&crop("copernicus_n34w119_crop.tif"), &Default::default())
                .unwrap()
                .into_grid()
                .unwrap();
        let pts: Vec<[f64; 2]> = (0..50)
            .map(|k| {
                grid.georef
                    .to_world(3.7 + 5.3 * k as f64, 250.2 - 4.1 * k as f64)
            })
            .chain([[0.0, 0.0]])
            .collect();
        let req = pb::SampleRequest {
            crs: String::new(),
            points: pts.iter().map(|p| pb::Point { x: p[0], y: p[1] }).collect(),
            error: 0.0,
            ..Default::default()
        };
        let s = t.sample_heights(req).await.unwrap().into_inner();
        for (p, (z, v)) in pts.iter().zip(s.heights.iter().zip(&s.valid)) {
            match grid.bilinear(*p) {
                Some(h) => assert!(
                    *v == 1 && (*z as f64 - h).abs() < 1e-3,
                    "{z} vs {h} at {p:?}"
                ),
                None => assert_eq!(*v, 0),
            }
        }
        // This crop names no vertical CRS: its heights are the store's, which say nothing of
        // their frame, and cannot be carried above the ellipsoid; a frame that is not a
        // vertical CRS is refused at the door.
        assert_eq!(s.vertical_crs, "");
        assert_eq!(s.frame_error_m, 0.0);
        for (heights, code) in [
            ("ellipsoid", tonic::Code::InvalidArgument),
            ("EPSG:4326", tonic::Code::InvalidArgument),
        ] {
            let req = pb::SampleRequest {
                points: vec![pb::Point {
                    x: pts[0][0],
                    y: pts[0][1],
                }],
                heights: heights.into(),
                ..Default::default()
            };
            let e = t.sample_heights(req).await.unwrap_err();
            assert_eq!(e.code(), code, "{heights}: {e:?}");
            let reason = patchwork::serve::status::reason_of(&e);
            let want = if heights == "ellipsoid" {
                "GEOID"
            } else {
                "INVALID_REQUEST"
            };
            assert_eq!(reason.map(|r| r.as_str()), Some(want), "{heights}: {e:?}");
        }

        // One point, and points sharing an x or a y, are answered like any others.
        let along: Vec<[f64; 2]> = (0..12)
            .map(|k| grid.georef.to_world(40.0, 10.0 + 20.0 * k as f64))
            .chain((0..12).map(|k| grid.georef.to_world(10.0 + 20.0 * k as f64, 40.0)))
            .collect();
        for pts in [&along[..1], &along[..12], &along[12..]] {
            let req = pb::SampleRequest {
                crs: String::new(),
                points: pts.iter().map(|p| pb::Point { x: p[0], y: p[1] }).collect(),
                error: 0.0,
                ..Default::default()
            };
            let s = t.sample_heights(req).await.unwrap().into_inner();
            for (p, z) in pts.iter().zip(&s.heights) {
                let h = grid.bilinear(*p).unwrap();
                assert!((*z as f64 - h).abs() < 1e-3, "{z} vs {h} at {p:?}");
            }
        }

        // At or past the top of LOD space, the coarsest cut.
        let b = grid.world_bounds();
        let coarsest = |e: f64| pb::PatchQuery {
            crs: String::new(),
            cut: Some(pb::patch_query::Cut::Uniform(pb::UniformCut {
                roi: Some(pb::Rect {
                    xmin: b.min[0],
                    ymin: b.min[1],
                    xmax: b.max[0],
                    ymax: b.max[1],
                }),
                error: e,
            })),
            batch_size: 0,
        };
        for e in [10_000.0, 1e12] {
            let mut st = t.query_patches(coarsest(e)).await.unwrap().into_inner();
            let mut n = 0;
            while let Some(batch) = st.message().await.unwrap() {
                n += batch.patches.len();
            }
            assert!(n > 0, "e = {e}: no patches");
        }

        // A survey that disagrees with the first by far more than both accuracies: a copy of
        // part of it with a 60 m mound, given ε = 1 m by its sidecar.
        let (c0, r0, n) = (50usize, 50usize, 100usize);
        let mut mound = Vec::with_capacity(n * n);
        for r in r0..r0 + n {
            for c in c0..c0 + n {
                let lift = if (20..40).contains(&(c - c0)) && (20..40).contains(&(r - r0)) {
                    60.0
                } else {
                    0.0
                };
                mound.push(grid.at(c, r) + lift);
            }
        }
        let stage = tmp.path().join("mound.tif");
        let o = grid.georef.to_world(c0 as f64 - 0.5, r0 as f64 - 0.5);
        let st = grid.georef.step;
        write_geotiff_f32(
            &stage,
            n,
            n,
            &mound,
            [o[0], st[0], 0.0, o[1], 0.0, -st[1]],
            Some(&patchwork_core::crs::Crs::epsg(4326).unwrap()),
            None,
        )
        .unwrap();
        std::fs::write(d.inbox().join("mound.tif.toml"), "accuracy_m = 1.0\n").unwrap();
        std::fs::rename(&stage, d.inbox().join("mound.tif")).unwrap();
        let first = e.survey;
        let e = tokio::time::timeout(Duration::from_secs(30), events.message())
            .await
            .unwrap()
            .unwrap()
            .unwrap();
        assert_eq!(e.outcome(), pb::Outcome::Inserted);
        assert_eq!(e.conflicts.len(), 1, "{e:?}");
        assert_eq!(e.conflicts[0].survey, format!("{first:016x}"));
        assert!((e.conflicts[0].max_m - 60.0).abs() < 1.0, "{e:?}");
        let list = d.surveys();
        let of = |name: &str| {
            list.iter()
                .find(|v| v["source"].as_str().unwrap().ends_with(name))
                .unwrap()
                .clone()
        };
        let (a, m) = (of("a.tif"), of("mound.tif"));
        assert_eq!(a["accuracy_source"], "estimated");
        assert_eq!(m["accuracy_source"], "sidecar");
        // The claim is kept as given, and where the two contradict each other (neither is
        // a blurred or shifted version of the other, and no third survey says which is
        // right) both are trusted no more than the evidence allows: the excess of their
        // difference over their claims split evenly between them.
        assert_eq!(m["claimed_accuracy_m"], 1.0);
        let raised = m["accuracy_m"].as_f64().unwrap();
        assert!(raised > 20.0 && raised < 61.0, "{m}");
        assert_eq!(m["conflicts"][0]["decided_by"], "undetermined", "{m}");
        assert!(m["accuracy_median_m"].as_f64().unwrap() <= raised, "{m}");
        assert_eq!(m["conflicts"][0]["distrusted"], "both", "{m}");
        assert_eq!(a["conflicts"][0]["survey"], m["id"]);
        assert_eq!(m["conflicts"][0]["survey"], a["id"]);
        let rms = m["conflicts"][0]["rms_m"].as_f64().unwrap();
        assert!(rms > 1.0 && rms < 60.0, "{m}");

        // A view cut streams patches, fewer at a coarser pixel error.
        let view = |px: f64| pb::PatchQuery {
            crs: String::new(),
            cut: Some(pb::patch_query::Cut::View(pb::ViewCut {
                eye_x: -119.0,
                eye_y: 34.45,
                eye_z: 2000.0,
                look_x: -118.92,
                look_y: 34.54,
                look_z: 500.0,
                fov_deg: 60.0,
                viewport_px: 1024,
                pixel_error: px,
                ..Default::default()
            })),
            batch_size: 16,
        };
        let mut counts = Vec::new();
        for px in [1.0, 8.0] {
            let mut st = t.query_patches(view(px)).await.unwrap().into_inner();
            let mut n = 0;
            while let Some(b) = st.message().await.unwrap() {
                assert!(b.patches.len() <= 16);
                for p in &b.patches {
                    let width = match p.encoding() {
                        pb::SampleEncoding::F32 => 4,
                        pb::SampleEncoding::I16 => 2,
                    };
                    assert_eq!(p.data.len() as u32, width * p.cols * p.rows);
                }
                n += b.patches.len();
            }
            counts.push(n);
        }
        assert!(counts[0] > counts[1] && counts[1] > 0, "{counts:?}");

        // Wrong requests say what to change.
        let tile = |w: u32, roi: pb::Rect, backend: pb::Backend| pb::TileRequest {
            crs: String::new(),
            cut: Some(pb::tile_request::Cut::Uniform(pb::UniformCut {
                roi: Some(roi),
                error: 1.0,
            })),
            width: w,
            height: w,
            backend: backend as i32,
            ..Default::default()
        };
        let roi = pb::Rect {
            xmin: -119.0,
            ymin: 34.46,
            xmax: -118.95,
            ymax: 34.5,
        };
        let big = t
            .resample_tile(tile(8192, roi, pb::Backend::Cpu))
            .await
            .unwrap_err();
        assert_eq!(big.code(), tonic::Code::ResourceExhausted);
        assert!(big.message().contains("smaller tile"), "{}", big.message());
        let flipped = pb::Rect {
            xmin: 1.0,
            ymin: 0.0,
            xmax: 0.0,
            ymax: 1.0,
        };
        let bad = t
            .resample_tile(tile(64, flipped, pb::Backend::Cpu))
            .await
            .unwrap_err();
        assert_eq!(bad.code(), tonic::Code::InvalidArgument);
        assert!(bad.message().contains("xmin < xmax"), "{}", bad.message());
        // The kinds, in the statuses' google.rpc.ErrorInfo.
        use patchwork::engine::Reason;
        use patchwork::serve::status::reason_of;
        assert_eq!(reason_of(&bad), Some(Reason::InvalidRequest));
        assert_eq!(reason_of(&big), Some(Reason::TooLarge));
        let none = t
            .resample_tile(pb::TileRequest {
                crs: String::new(),
                cut: None,
                width: 8,
                height: 8,
                backend: 0,
                ..Default::default()
            })
            .await
            .unwrap_err();
        assert_eq!(none.code(), tonic::Code::InvalidArgument);
        let ok = t
            .resample_tile(tile(64, roi, pb::Backend::Auto))
            .await
            .unwrap()
            .into_inner();
        assert_eq!(ok.heights.len(), 64 * 64);
        assert!(ok.valid.contains(&1));
    });
    // The view form of the CLI.
    let v = d.json(&[
        "query",
        "--eye",
        "-119,34.45,2000",
        "--look",
        "-118.92,34.54,500",
        "--pixel-error",
        "2",
        "--json",
    ]);
    assert!(!v["patches"].as_array().unwrap().is_empty());
}

#[test]
fn the_daemon_starts_quietly_and_takes_no_software_gpu_unless_allowed() {
    // No runtime directory and no display, as on a server: Mesa's Vulkan layers used to
    // complain on stderr at every start. Every line now is the daemon's own log.
    let tmp = tempfile::tempdir().unwrap();
    let mut d = Daemon::start_with(
        tmp.path(),
        Setup {
            env: vec![("PATCHWORK_ALLOW_EMULATED_GPU".into(), "false".into())],
            unset: vec![
                "XDG_RUNTIME_DIR".into(),
                "WAYLAND_DISPLAY".into(),
                "DISPLAY".into(),
            ],
            ..Setup::default()
        },
    );
    let backend = d.json(&["stats", "--json"])["backend"]
        .as_str()
        .unwrap()
        .to_string();
    // A refused software driver is not even loaded: the probe runs in a child process.
    let maps = std::fs::read_to_string(format!("/proc/{}/maps", d.pid().unwrap())).unwrap();
    if backend == "cpu" {
        for lib in ["libvulkan_lvp", "libLLVM", "libGLX_mesa"] {
            assert!(
                !maps.contains(lib),
                "{lib} is mapped in a daemon that resamples on the CPU"
            );
        }
    }
    d.stop();
    let log = d.log();
    for line in log.lines() {
        assert!(
            line.contains(" INFO ") || line.contains(" WARN "),
            "a line that is not the daemon's log: {line:?}\n{log}"
        );
    }
    let probe: Vec<&str> = log.lines().filter(|l| l.contains("GPU")).collect();
    assert_eq!(probe.len(), 1, "one line from the GPU probe: {log}");
    if backend.starts_with("gpu") {
        // A real GPU is there; it is taken whatever the switch says.
        assert!(probe[0].contains("resampling on the GPU"), "{log}");
    } else {
        assert_eq!(backend, "cpu");
        assert!(probe[0].contains("resampling on the CPU"), "{log}");
    }
}

#[test]
fn daemon_tiles_on_the_gpu_match_the_cpu_and_gpu_without_a_device_is_refused() {
    use patchwork::serve::proto::{self as pb, terrain_client::TerrainClient};
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "a.tif");
    d.wait("the survey", |s| count(s, "active") == 1);
    let backend = d.json(&["stats", "--json"])["backend"]
        .as_str()
        .unwrap()
        .to_string();
    let required = std::env::var("PATCHWORK_REQUIRE_GPU").as_deref() == Ok("1");
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let mut t = TerrainClient::connect(format!("http://127.0.0.1:{}", d.port))
            .await
            .unwrap();
        let tile = |b: pb::Backend, e: f64| {
            let mut r = crop_tile(300, 200);
            r.backend = b as i32;
            if let Some(pb::tile_request::Cut::Uniform(u)) = &mut r.cut {
                u.error = e;
            }
            r
        };
        if !backend.starts_with("gpu") {
            assert!(
                !required,
                "PATCHWORK_REQUIRE_GPU=1 but the daemon resamples on {backend}"
            );
            println!("GPU path NOT exercised: the daemon has no GPU device ({backend})");
            let err = t
                .resample_tile(tile(pb::Backend::Gpu, 0.0))
                .await
                .unwrap_err();
            assert_eq!(err.code(), tonic::Code::FailedPrecondition);
            assert!(err.message().contains("no GPU device"), "{}", err.message());
            assert_eq!(
                patchwork::serve::status::reason_of(&err),
                Some(patchwork::engine::Reason::Unavailable)
            );
            return;
        }
        for e in [0.0, 5.0, 30.0] {
            let g = t
                .resample_tile(tile(pb::Backend::Gpu, e))
                .await
                .unwrap()
                .into_inner();
            let c = t
                .resample_tile(tile(pb::Backend::Cpu, e))
                .await
                .unwrap()
                .into_inner();
            assert_eq!((g.backend.as_str(), c.backend.as_str()), ("gpu", "cpu"));
            assert_eq!(g.valid, c.valid, "e = {e}: masks differ");
            let worst = g
                .heights
                .iter()
                .zip(&c.heights)
                .filter(|(a, _)| !a.is_nan())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(worst <= 1e-3, "e = {e}: GPU and CPU differ by {worst} m");
            println!("daemon on {backend}: e = {e} m, max |GPU − CPU| = {worst} m");
        }
    });
}

#[test]
fn tiles_come_as_bands_of_bytes_that_any_client_can_take_and_small_ones_at_once() {
    use patchwork::serve::proto::terrain_client::TerrainClient;
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "a.tif");
    d.wait("the survey", |s| count(s, "active") == 1);
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        // gRPC's default receive limit of 4 MB, as any client starts with.
        let mut t = TerrainClient::connect(format!("http://127.0.0.1:{}", d.port))
            .await
            .unwrap();
        let tile = crop_tile;
        // 2400 × 1800 heights are 17 MB: more than the limit as one message, not as bands.
        let (w, h) = (2400usize, 1800usize);
        let mut s = t
            .tile_bands(tile(w as u32, h as u32))
            .await
            .unwrap()
            .into_inner();
        let mut heights = Vec::new();
        let mut bands = 0;
        while let Some(b) = s.message().await.unwrap() {
            assert_eq!((b.width as usize, b.height as usize), (w, h));
            assert_eq!(b.row as usize, heights.len() / w, "bands come in row order");
            assert!(
                b.heights.len() <= 1 << 20,
                "a band of {} bytes",
                b.heights.len()
            );
            assert_eq!(b.heights.len(), 4 * w * b.rows as usize);
            assert_eq!(
                b.backend.is_empty(),
                bands > 0,
                "the first band says what ran"
            );
            heights.extend(
                b.heights
                    .chunks_exact(4)
                    .map(|q| f32::from_le_bytes(q.try_into().unwrap())),
            );
            bands += 1;
        }
        assert_eq!(heights.len(), w * h);
        assert!(bands >= 17, "{bands} bands");
        // A request refused before its first band is refused as the call's status.
        assert_eq!(
            t.tile_bands(tile(0, 16)).await.unwrap_err().code(),
            tonic::Code::InvalidArgument
        );
        // The same heights as the one-message tile, which needs a raised limit.
        let mut big = TerrainClient::connect(format!("http://127.0.0.1:{}", d.port))
            .await
            .unwrap()
            .max_decoding_message_size(64 << 20);
        let whole = big
            .resample_tile(tile(w as u32, h as u32))
            .await
            .unwrap()
            .into_inner();
        assert!(heights.iter().any(|z| !z.is_nan()));
        assert!(heights
            .iter()
            .zip(&whole.heights)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert_eq!(
            t.resample_tile(tile(w as u32, h as u32))
                .await
                .unwrap_err()
                .code(),
            tonic::Code::OutOfRange,
            "one message is over the default limit"
        );
        // A small tile answers at once: replies no longer wait out a delayed ACK (40 ms
        // each). The bound sits halfway to that wait, not near a quiet machine's 1-2 ms,
        // so that a loaded machine passes and the delayed ACK alone fails.
        let mut ms = Vec::new();
        for _ in 0..21 {
            let t0 = std::time::Instant::now();
            t.resample_tile(tile(16, 16)).await.unwrap();
            ms.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        ms.sort_by(f64::total_cmp);
        assert!(ms[10] < 20.0, "a 16² tile takes {:.1} ms (median)", ms[10]);
    });
}

#[test]
fn the_cli_asks_for_points_tiles_cuts_and_meshes_in_any_crs() {
    use patchwork_core::crs::{Crs, Transform};
    let tmp = tempfile::tempdir().unwrap();
    let setup = Setup {
        env: vec![("PATCHWORK_CRS".into(), "EPSG:4326".into())],
        ..Setup::default()
    };
    let d = Daemon::start_with(tmp.path(), setup);
    drop_by_rename(&crop("real/ventoux_geographic.tif"), &d.inbox(), "geo.tif");
    drop_by_rename(&crop("real/ventoux_utm31.tif"), &d.inbox(), "utm.tif");
    let surveys = d.wait("both surveys", |s| count(s, "active") == 2);
    let mut crss: Vec<&str> = surveys.iter().map(|s| s["crs"].as_str().unwrap()).collect();
    crss.sort();
    assert_eq!(crss, ["EPSG:32631", "EPSG:4326"]);
    assert!(surveys.iter().all(|s| s["vertical_crs"].is_string()));
    assert_eq!(d.json(&["stats", "--json"])["crs"], "EPSG:4326");

    // Points asked in UTM are the same ground as asked in degrees.
    let utm = Crs::epsg(32631).unwrap();
    let to_utm = Transform::new(&Crs::wgs84(), &utm).unwrap();
    let lonlat = [[5.25, 44.15], [5.30, 44.18], [5.36, 44.20]];
    let xy: Vec<[f64; 2]> = lonlat.iter().map(|&p| to_utm.apply(p).unwrap()).collect();
    let list = |ps: &[[f64; 2]]| {
        ps.iter()
            .map(|p| format!("{},{}", p[0], p[1]))
            .collect::<Vec<_>>()
            .join(",")
    };
    let heights = |v: &Value| -> Vec<f64> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|p| p["height"].as_f64().expect("a height"))
            .collect()
    };
    let geo = heights(&d.json(&["sample", "--points", &list(&lonlat), "--json"]));
    let (points, crs) = (list(&xy), "--crs=EPSG:32631");
    let by_utm = heights(&d.json(&["sample", "--points", &points, crs, "--json"]));
    for (a, b) in geo.iter().zip(&by_utm) {
        assert!(
            (a - b).abs() < 1e-3,
            "{geo:?} asked in degrees, {by_utm:?} in UTM"
        );
    }
    let line = d.json(&[
        "sample",
        "--line",
        "5.25,44.15,5.36,44.20",
        "--count",
        "5",
        "--json",
    ]);
    assert_eq!(line.as_array().unwrap().len(), 5);
    assert!((heights(&line)[0] - geo[0]).abs() < 1e-3);

    // A UTM cut, and a UTM tile: a GeoTIFF in UTM whose pixels are the store's heights there.
    let (x0, y0) = (xy[0][0] - 3000.0, xy[0][1] - 2000.0);
    let roi = format!("{x0},{y0},{},{}", x0 + 6400.0, y0 + 4800.0);
    let cut = d.json(&["query", "--roi", &roi, "--error", "0", crs, "--json"]);
    assert!(!cut["patches"].as_array().unwrap().is_empty());
    let out = tmp.path().join("utm.tif");
    let args = [
        "tile", "--roi", &roi, "--size", "64x48", "--error", "0", crs, "--out",
    ];
    let done = d.cli(&[&args[..], &[out.to_str().unwrap()]].concat());
    assert!(
        done.status.success(),
        "{}",
        String::from_utf8_lossy(&done.stderr)
    );
    // No estimated accuracy is 0 m: the reply says so, and what served instead.
    let said = String::from_utf8_lossy(&done.stdout);
    assert!(
        said.contains("no data as accurate as 0 m over 100% of the tile: served the most accurate there, errors "),
        "{said}"
    );
    let r = patchwork_read::read_raster(&out, &Default::default()).unwrap();
    assert_eq!(r.crs.crs.as_ref(), Some(&utm));
    assert_eq!((r.cols, r.rows), (64, 48));
    let gt = r.geotransform;
    assert!(
        (gt[0] - x0).abs() < 1e-6 && (gt[1] - 100.0).abs() < 1e-9 && (gt[5] + 100.0).abs() < 1e-9
    );
    let centres: Vec<[f64; 2]> = [(3, 5), (40, 20), (60, 44)]
        .iter()
        .map(|&(c, r)| {
            [
                gt[0] + (c as f64 + 0.5) * 100.0,
                gt[3] - (r as f64 + 0.5) * 100.0,
            ]
        })
        .collect();
    let at = heights(&d.json(&["sample", "--points", &list(&centres), crs, "--json"]));
    for ((&(c, row), want), p) in [(3, 5), (40, 20), (60, 44)].iter().zip(&at).zip(&centres) {
        let got = r.samples[row * 64 + c] as f64;
        assert!(
            (got - want).abs() < 1e-3,
            "pixel ({c}, {row}) at {p:?}: {got} in the tile, {want} sampled"
        );
    }

    // A mesh in UTM as glTF; a quantized-mesh tile must be asked in degrees.
    let glb = tmp.path().join("utm.glb");
    let mesh = [
        "mesh", "--roi", &roi, "--error", "5", "--size", "33", crs, "--out",
    ];
    let done = d.cli(&[&mesh[..], &[glb.to_str().unwrap()]].concat());
    assert!(
        done.status.success(),
        "{}",
        String::from_utf8_lossy(&done.stderr)
    );
    assert_eq!(&std::fs::read(&glb).unwrap()[..4], b"glTF");
    let terrain = tmp.path().join("utm.terrain");
    let done = d.cli(&[&mesh[..], &[terrain.to_str().unwrap()]].concat());
    assert!(!done.status.success());
    let e = String::from_utf8_lossy(&done.stderr);
    assert!(e.contains("--crs EPSG:4326"), "{e}");
}

#[test]
fn a_sidecar_added_edited_or_removed_beside_a_file_ingests_it_again() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    let side = d.inbox().join("a.tif.toml");
    // The file's survey as served: its earlier ones are listed as retired.
    let of = |s: &[Value]| -> Option<Value> {
        s.iter()
            .find(|v| v["source"].as_str().unwrap().ends_with("a.tif") && v["status"] != "retired")
            .cloned()
    };
    // A sidecar that cannot be right: the file fails on it.
    std::fs::write(&side, "accuracy_m = 1e308\n").unwrap();
    drop_by_rename(&crop("srtm_n44e005_voids_crop.tif"), &d.inbox(), "a.tif");
    d.wait("the file to fail on its sidecar", |s| {
        count(s, "failed") == 1
    });
    // Mended beside the failed file, the file is taken under it.
    std::fs::write(&side, "accuracy_m = 3.0\n").unwrap();
    let s = d.wait("the file under its mended sidecar", |s| {
        of(s).is_some_and(|v| v["status"] == "active" && v["claimed_accuracy_m"] == 3.0)
    });
    assert_eq!(of(&s).unwrap()["accuracy_source"], "sidecar");
    assert_eq!(count(&s, "failed"), 0, "{s:#?}");
    // Edited, the survey is taken again with the new claim, replacing the old one.
    std::fs::write(&side, "accuracy_m = 5.0\n").unwrap();
    let s = d.wait("the file under its edited sidecar", |s| {
        of(s).is_some_and(|v| v["status"] == "active" && v["claimed_accuracy_m"] == 5.0)
    });
    assert_eq!(count(&s, "active"), 1, "{s:#?}");
    // Removed, its accuracy is what a file without one gets again.
    std::fs::remove_file(&side).unwrap();
    let s = d.wait("the file with its sidecar gone", |s| {
        of(s).is_some_and(|v| v["status"] == "active" && v["accuracy_source"] != "sidecar")
    });
    assert_eq!(count(&s, "active"), 1, "{s:#?}");
}

#[test]
fn a_store_without_a_configured_crs_is_geographic_whatever_arrives_first() {
    // A UTM survey alone, first: the store is still in EPSG:4326, as it would be had the
    // geographic copy of the same ground come first.
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(&crop("real/ventoux_utm31.tif"), &d.inbox(), "utm.tif");
    let s = d.wait("the UTM survey", |s| count(s, "active") == 1);
    assert_eq!(s[0]["crs"], "EPSG:32631");
    assert_eq!(d.json(&["stats", "--json"])["crs"], "EPSG:4326");
    drop_by_rename(&crop("real/ventoux_geographic.tif"), &d.inbox(), "geo.tif");
    d.wait("both surveys", |s| count(s, "active") == 2);
    assert_eq!(d.json(&["stats", "--json"])["crs"], "EPSG:4326");
}

/// A store opened in the CLI's own process (`--data-dir`) resamples on the GPU as the daemon
/// does: `--backend gpu` opens the device (a software one where allowed), and is refused,
/// saying so, only where there is none.
#[test]
fn direct_mode_opens_the_gpu_for_a_tile() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let cli = |args: &[&str]| {
        std::process::Command::new(BIN)
            .args(args)
            .arg(format!("--data-dir={}", data.display()))
            .env("PATCHWORK_ALLOW_EMULATED_GPU", "1")
            .env("PATCHWORK_CRS", "EPSG:4326")
            .output()
            .unwrap()
    };
    let crop = crop("copernicus_n34w119_crop.tif");
    let o = cli(&["ingest", crop.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let tile = |backend: &str| {
        let out = tmp.path().join(format!("{backend}.tif"));
        let o = cli(&[
            "tile",
            "--roi=-119.0,34.46,-118.92,34.54",
            "--size=200x200",
            "--error=0",
            &format!("--backend={backend}"),
            &format!("--out={}", out.display()),
        ]);
        (o, out)
    };
    let (cpu, cpu_file) = tile("cpu");
    assert!(
        cpu.status.success(),
        "{}",
        String::from_utf8_lossy(&cpu.stderr)
    );
    let (gpu, gpu_file) = tile("gpu");
    let said = String::from_utf8_lossy(&gpu.stdout).into_owned();
    let err = String::from_utf8_lossy(&gpu.stderr).into_owned();
    let required = std::env::var("PATCHWORK_REQUIRE_GPU").as_deref() == Ok("1");
    if !gpu.status.success() {
        assert!(!required, "PATCHWORK_REQUIRE_GPU=1 but: {err}");
        assert!(err.contains("no GPU device"), "{err}");
        println!("GPU path NOT exercised: {err}");
        return;
    }
    assert!(said.contains("gpu"), "{said}");
    // The same heights as the CPU's, within the GPU's tolerance.
    let read = |p: &Path| {
        patchwork_read::read_raster(p, &Default::default())
            .unwrap()
            .into_grid()
            .unwrap()
    };
    let (a, b) = (read(&cpu_file), read(&gpu_file));
    let worst = a
        .samples
        .iter()
        .zip(&b.samples)
        .map(|(x, y)| {
            assert_eq!(x.is_nan(), y.is_nan());
            if x.is_nan() {
                0.0
            } else {
                (x - y).abs()
            }
        })
        .fold(0.0f32, f32::max);
    assert!(worst <= 1e-3, "{worst}");
    println!("direct mode: {said}");
}
