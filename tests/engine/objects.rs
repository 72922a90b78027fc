//! A store whose chunks are on an object store (here a folder laid out as one): compaction
//! moves the live chunks into new segments and deletes the old ones once their grace period is
//! over, with the terrain unchanged; a store keeps the backend it was made with.

use patchwork::config::{BackendKind, Config, Storage};
use patchwork::engine::{Ctx, Cut, Engine, EngineError, Origin, TileRequest};
use patchwork::store::StoreError;
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

/// A store in `root/data` whose chunks are in the folder `root/objects`, with `storage`'s
/// other settings; it ingests the crops.
fn on_folder(root: &Path, storage: Storage) -> Config {
    Config {
        data_dir: root.join("data"),
        ingest_roots: vec![crop("")],
        storage: Storage {
            backend: BackendKind::Folder,
            folder: Some(root.join("objects")),
            ..storage
        },
        ..Config::default()
    }
}

#[test]
fn compaction_on_an_object_store_moves_the_live_chunks_and_lets_the_old_segments_go() {
    let tmp = tempfile::tempdir().unwrap();
    let folder = tmp.path().join("objects");
    let cfg = on_folder(
        tmp.path(),
        Storage {
            gc_grace_s: 0,
            ..Storage::default()
        },
    );
    let roi = Aabb {
        min: [-118.99, 34.46],
        max: [-118.90, 34.53],
    };
    let heights = |e: &Engine| {
        e.tile(
            &TileRequest::new(Cut::new(None, roi, 0.0).unwrap(), 64, 48, Backend::Cpu).unwrap(),
            Ctx::default(),
        )
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
    // With nothing left to drop, a compaction leaves the store and the bucket as they are,
    // rather than upload every live chunk again.
    let report = e.compact().unwrap();
    assert!(!report.swapped && report.keys_removed == 0, "{report:?}");
    assert_eq!(segments(&folder), after);
    assert_eq!(heights(&e), kept);
    drop(e);

    // The store keeps the backend it was made with.
    let local = Config {
        storage: Storage::default(),
        ..cfg
    };
    let refused = Engine::open(local).err().expect("refused").to_string();
    assert!(refused.contains("file://"), "{refused}");
}

/// What a server answers for the crops' region: the patch set of a uniform cut at two
/// errors, each patch as (id, survey, level, top), and a tile's heights, bit for bit.
type Answers = (Vec<(u64, String, u8, u64)>, Vec<u32>);

fn answers(e: &Engine) -> Answers {
    let roi = Aabb {
        min: [-118.99, 34.46],
        max: [-118.90, 34.53],
    };
    let mut patches = Vec::new();
    for error in [0.0, 8.0] {
        let (_, ps) = e.query(&Cut::new(None, roi, error).unwrap()).unwrap();
        patches.extend(ps.iter().map(|p| {
            (
                p.id.0,
                p.survey.to_string(),
                p.level,
                p.span.max_z.to_bits(),
            )
        }));
    }
    let heights = e
        .tile(
            &TileRequest::new(Cut::new(None, roi, 0.0).unwrap(), 64, 48, Backend::Cpu).unwrap(),
            Ctx::default(),
        )
        .unwrap()
        .0
        .heights
        .iter()
        .map(|h| h.to_bits())
        .collect();
    (patches, heights)
}

/// One round for each replica, then each answers as the writer does and stands at its commit.
fn converged(writer: &Engine, replicas: &[&Engine]) {
    let want = answers(writer);
    let commit = writer
        .replication()
        .commit
        .expect("the writer keeps a journal");
    for (i, r) in replicas.iter().enumerate() {
        r.round().unwrap();
        let f = r.replication().following.expect("a replica");
        assert_eq!((f.applied, f.published), (commit, commit), "replica {i}");
        assert_eq!(r.replication().commit, Some(commit));
        assert!(
            answers(r) == want,
            "replica {i} answers otherwise at commit {commit}"
        );
        assert!(r.verify().unwrap().problems.is_empty(), "replica {i}");
    }
}

#[test]
fn replicas_follow_the_writer_through_inserts_a_replacement_a_retirement_and_a_compaction() {
    let tmp = tempfile::tempdir().unwrap();
    let folder = tmp.path().join("objects");
    let inbox = tmp.path().join("inbox");
    std::fs::create_dir_all(&inbox).unwrap();
    let storage = Storage {
        backend: BackendKind::Folder,
        folder: Some(folder.clone()),
        gc_grace_s: 0,
        // A snapshot every second commit, so that the logs before the older of the two newest
        // snapshots are deleted along the way.
        snapshot_every: 2,
        ..Storage::default()
    };
    let writer_cfg = Config {
        data_dir: tmp.path().join("writer"),
        ingest_roots: vec![crop(""), inbox.clone()],
        storage: storage.clone(),
        ..Config::default()
    };
    let replica_cfg = |name: &str| {
        let mut storage = storage.clone();
        storage
            .set_follow(&format!("file://{}", folder.display()))
            .unwrap();
        Config {
            data_dir: tmp.path().join(name),
            storage,
            ..Config::default()
        }
    };
    let w = Engine::open(writer_cfg).unwrap();
    let a = Engine::open(replica_cfg("a")).unwrap();
    converged(&w, &[&a]);

    let mut ids = Vec::new();
    for f in ["copernicus_n34w119_crop.tif", "nasadem_n34w119_crop.tif"] {
        let done = w.ingest(&crop(f), None, Origin::Request).unwrap();
        assert!(done.error.is_empty(), "{f}: {}", done.error);
        ids.push(done.survey.unwrap());
    }
    // The third survey comes through a file that then changes: the new content replaces it.
    let changing = inbox.join("changing.tif");
    std::fs::copy(crop("srtm_n44e005_voids_crop.tif"), &changing).unwrap();
    w.ingest(&changing, None, Origin::Request).unwrap();
    let b = Engine::open(replica_cfg("b")).unwrap();
    converged(&w, &[&a, &b]);

    std::fs::copy(crop("nasadem_n34w119_crop.tif"), &changing).unwrap();
    let replaced = w.ingest(&changing, Some(3.0), Origin::Request).unwrap();
    assert!(replaced.error.is_empty(), "{}", replaced.error);
    w.retire(&ids[0].to_string()).unwrap();
    converged(&w, &[&a, &b]);

    // A replica refuses writes, naming the writer that holds the lease.
    let Err(refused) = a.ingest(&crop("copernicus_n34w119_crop.tif"), None, Origin::Request) else {
        panic!("a replica took an ingest");
    };
    assert_eq!(refused.reason(), patchwork::engine::Reason::ReadOnlyReplica);
    let refused = refused.to_string();
    assert!(
        refused.contains("read replica") && refused.contains(&std::process::id().to_string()),
        "{refused}"
    );
    assert!(a.retire(&ids[1].to_string()).is_err());

    // Compaction rewrites the writer's database: its log sends the replicas to its snapshot.
    // (The retired survey and the one replaced go.)
    let report = w.compact().unwrap();
    assert!(report.swapped && report.surveys_purged == 2, "{report:?}");
    converged(&w, &[&a, &b]);
    // A replica that starts now starts from the newest snapshot; the logs before the older of
    // the two kept are gone.
    let logs = std::fs::read_dir(folder.join("log")).unwrap().count();
    let snapshots = std::fs::read_dir(folder.join("snapshots")).unwrap().count();
    assert!(
        snapshots <= 2 && logs <= 4,
        "{snapshots} snapshots, {logs} logs"
    );
    let c = Engine::open(replica_cfg("c")).unwrap();
    converged(&w, &[&a, &b, &c]);
    drop(c);

    // A replica restarted goes on from its own database.
    drop(a);
    w.retire(&ids[1].to_string()).unwrap();
    let a = Engine::open(replica_cfg("a")).unwrap();
    converged(&w, &[&a, &b]);

    // A writer's directory is not a replica's to fill.
    drop(w);
    let mut taken = replica_cfg("writer");
    taken.data_dir = tmp.path().join("writer");
    let e = Engine::open(taken).err().expect("refused");
    assert!(
        matches!(
            &e,
            EngineError::Store(StoreError::NotAReplica { holds, .. })
                if holds == "holds a store of its own"
        ),
        "{e}"
    );
}

/// On a folder, as on S3, the writer renews its lease and writes on past the lease's first
/// term, and a lease that a writer left behind (killed, or stopped once its lease had run out)
/// is taken over once it runs out: the folder gives the conditional PUT both need.
#[test]
fn a_writer_on_a_folder_renews_its_lease_and_one_left_behind_is_taken_over() {
    let tmp = tempfile::tempdir().unwrap();
    let folder = tmp.path().join("objects");
    let cfg = on_folder(
        tmp.path(),
        Storage {
            lease_s: 1,
            ..Storage::default()
        },
    );
    let ingest = |e: &Engine, f: &str| {
        let done = e.ingest(&crop(f), None, Origin::Request).unwrap();
        assert!(done.error.is_empty(), "{f}: {}", done.error);
    };
    let e = Engine::open(cfg.clone()).unwrap();
    ingest(&e, "copernicus_n34w119_crop.tif");
    // Three terms of the lease later.
    std::thread::sleep(std::time::Duration::from_millis(3000));
    ingest(&e, "nasadem_n34w119_crop.tif");
    drop(e);
    // A writer on another host that stopped without giving the lease back.
    let now_ms = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64;
    let left = format!(
        r#"{{"holder":"another-host:1:0","expires_ms":{}}}"#,
        now_ms + 1500
    );
    std::fs::write(folder.join("lease"), left).unwrap();
    let refused = Engine::open(cfg.clone())
        .err()
        .expect("refused")
        .to_string();
    assert!(refused.contains("another-host"), "{refused}");
    std::thread::sleep(std::time::Duration::from_millis(2000));
    let e = Engine::open(cfg).expect("the lease that ran out is taken over");
    assert_eq!(e.stats().surveys, 2);
    assert!(e.verify().unwrap().problems.is_empty());
}
