//! A store whose chunks are on an object store (here a folder laid out as one): compaction
//! moves the live chunks into new segments and deletes the old ones once their grace period is
//! over, with the terrain unchanged; a store keeps the backend it was made with.

use patchwork::config::{BackendKind, Config, Storage};
use patchwork::engine::{Cut, Engine, Origin};
use patchwork_core::geom::Aabb;
use patchwork_core::resample::Backend;
use std::path::{Path, PathBuf};

fn crop(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

fn segments(folder: &Path) -> Vec<u64> {
    let mut out: Vec<u64> = std::fs::read_dir(folder.join("segments"))
        .unwrap()
        .filter_map(|e| {
            let name = e.unwrap().file_name().into_string().ok()?;
            name.strip_suffix(".seg")?.parse().ok()
        })
        .collect();
    out.sort_unstable();
    out
}

#[test]
fn compaction_on_an_object_store_moves_the_live_chunks_and_lets_the_old_segments_go() {
    let tmp = tempfile::tempdir().unwrap();
    let folder = tmp.path().join("objects");
    let cfg = Config {
        data_dir: tmp.path().join("data"),
        ingest_roots: vec![crop("")],
        storage: Storage {
            backend: BackendKind::Folder,
            folder: Some(folder.clone()),
            gc_grace_s: 0,
            ..Storage::default()
        },
        ..Config::default()
    };
    let roi = Aabb {
        min: [-118.99, 34.46],
        max: [-118.90, 34.53],
    };
    let heights = |e: &Engine| {
        e.tile(&Cut::Uniform { roi, error: 0.0 }, 64, 48, Backend::Cpu)
            .unwrap()
            .0
            .heights
            .iter()
            .map(|h| h.to_bits())
            .collect::<Vec<u32>>()
    };
    let e = Engine::open(cfg.clone()).unwrap();
    let mut ids = Vec::new();
    for f in ["copernicus_n34w119_crop.tif", "nasadem_n34w119_crop.tif"] {
        let done = e.ingest(&crop(f), None, Origin::Request).unwrap();
        assert!(done.error.is_empty(), "{f}: {}", done.error);
        ids.push(done.survey.unwrap());
    }
    assert!(!tmp.path().join("data/chunks.pack").exists());
    let before = segments(&folder);
    assert_eq!(before.len(), 2, "{before:?}");
    e.retire(&ids[1].to_string()).unwrap();
    let kept = heights(&e);
    assert!(kept.iter().any(|h| f32::from_bits(*h).is_finite()));

    let report = e.compact().unwrap();
    assert!(report.swapped && report.surveys_purged == 1, "{report:?}");
    // The live chunks are in a new segment past the old address space, and the old segments
    // are gone (the grace period is 0 here).
    let after = segments(&folder);
    assert_eq!(after.len(), 1, "{after:?}");
    assert!(after[0] > *before.last().unwrap());
    assert_eq!(heights(&e), kept);
    assert!(e.verify().unwrap().problems.is_empty());
    drop(e);

    let e = Engine::open(cfg.clone()).unwrap();
    assert_eq!(heights(&e), kept);
    assert!(e.verify().unwrap().problems.is_empty());
    drop(e);

    // The store keeps the backend it was made with.
    let local = Config {
        storage: Storage::default(),
        ..cfg
    };
    let refused = Engine::open(local).err().expect("refused").to_string();
    assert!(refused.contains("file://"), "{refused}");
}
