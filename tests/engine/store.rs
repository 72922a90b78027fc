//! The store: what is committed comes back as the same terrain, retirements and replacements
//! persist, verify finds damage, old and newer schemas are handled, compaction gives space
//! back and survives a crash, and a store in use is refused.

use crate::common;

use common::*;
use patchwork::restore::{self, Opened};
use patchwork::store::{
    form, open_error, Change, Corruption, DiskSpace, FailedRecord, IngestTimings, Insertion,
    Packed, Retirement, SpaceGuard, Status, Store, StoreError, StoreOptions, SurveyRecord,
    SCHEMA_VERSION,
};
use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::ChangeStats;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::AccuracySource;
use patchwork_core::model::edge::EdgePatch;
use patchwork_core::model::evidence::PairEvidence;
use patchwork_core::model::ids::{PatchId, SurveyId};
use patchwork_core::model::survey::Survey;
use patchwork_core::resample::SampleGrid;
use patchwork_core::terrain::Terrain;

/// The migration steps an open runs from schema `from` to the current one, in order.
fn steps_from(from: u32) -> Vec<(u32, u32)> {
    (from..SCHEMA_VERSION).map(|v| (v, v + 1)).collect()
}

/// A box state as the store writes it: the top, then the exposure byte.
fn state_bytes(top: f64, exposed: bool) -> Vec<u8> {
    let mut b = top.to_le_bytes().to_vec();
    b.push(u8::from(exposed));
    b
}

/// Bytes a box takes in a unit's record (`b/<unit>`): its patch id, then its state.
const BOX_BYTES: usize = 17;

/// A unit's record with one box's state replaced (Some) or its entry dropped (None).
fn with_box(record: &[u8], id: PatchId, state: Option<Vec<u8>>) -> Vec<u8> {
    record
        .chunks_exact(BOX_BYTES)
        .flat_map(|e| {
            if e[..8] != id.0.to_le_bytes() {
                e.to_vec()
            } else {
                state.as_ref().map_or(Vec::new(), |s| [&e[..8], s].concat())
            }
        })
        .collect()
}

/// A unit's record as version 6 kept it: a `t/<patch>` key a box.
fn tops_v6(record: &[u8]) -> Vec<(String, Vec<u8>)> {
    record
        .chunks_exact(BOX_BYTES)
        .map(|e| {
            let id = PatchId(u64::from_le_bytes(e[..8].try_into().unwrap()));
            (format!("t/{id}"), e[8..].to_vec())
        })
        .collect()
}
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

fn open(dir: &Path) -> Opened {
    let o = restore::open(dir, LAYOUT, IndexConfig::default(), StoreOptions::default())
        .expect("store opens");
    assert!(o.warnings.is_empty(), "{:?}", o.warnings);
    o
}

/// The error a store that must not open gives.
fn refused(dir: &Path) -> StoreError {
    restore::open(dir, LAYOUT, IndexConfig::default(), StoreOptions::default())
        .err()
        .expect("refused")
}

/// A survey packed and committed, as the engine commits it.
fn commit_survey(
    store: &mut Store,
    s: &Survey,
    rec: &SurveyRecord,
    change: &ChangeStats,
    edges: &[Arc<EdgePatch>],
    pairs: &[Arc<PairEvidence>],
) -> Result<(), StoreError> {
    let packed = store.pack_survey(s)?;
    store.commit(Change {
        insert: Some(Insertion {
            survey: s,
            record: rec,
            change,
            pairs,
            packed,
        }),
        edges,
        ..Change::default()
    })
}

/// A survey retired, as the engine retires it.
fn commit_retire(
    store: &mut Store,
    id: SurveyId,
    change: &ChangeStats,
    edges: &[Arc<EdgePatch>],
    pin: bool,
) -> Result<(), StoreError> {
    store.commit(Change {
        retire: Some(Retirement { id, change, pin }),
        edges,
        ..Change::default()
    })
}

/// One survey replaced by another in one commit, as the engine replaces a changed file.
#[allow(clippy::too_many_arguments)]
fn commit_replace(
    store: &mut Store,
    old: SurveyId,
    retire_change: &ChangeStats,
    new: &Survey,
    rec: &SurveyRecord,
    insert_change: &ChangeStats,
    edges: &[Arc<EdgePatch>],
    pairs: &[Arc<PairEvidence>],
    packed: Packed,
) -> Result<(), StoreError> {
    store.commit(Change {
        retire: Some(Retirement {
            id: old,
            change: retire_change,
            pin: false,
        }),
        insert: Some(Insertion {
            survey: new,
            record: rec,
            change: insert_change,
            pairs,
            packed,
        }),
        edges,
    })
}

fn store_dir(tmp: &tempfile::TempDir) -> PathBuf {
    tmp.path().join("store")
}

/// What the daemon does: change a copy of the terrain, commit, and keep the copy only then.
fn ingest(store: &mut Store, t: &mut Terrain, s: &Arc<Survey>, source: &str) {
    let mut next = t.clone();
    let change = next.insert(s.clone());
    let rec = SurveyRecord::new(
        s,
        source,
        "",
        AccuracySource::Flag,
        IngestTimings::default(),
    );
    commit_survey(
        store,
        s,
        &rec,
        &change,
        &next.edges_of(&[&change]),
        &next.pairs_of(s.id),
    )
    .expect("commit");
    *t = next;
}

fn retire(store: &mut Store, t: &mut Terrain, id: SurveyId) {
    let mut next = t.clone();
    let change = next.retire(id).expect("present");
    commit_retire(store, id, &change, &next.edges_of(&[&change]), false).expect("retire");
    *t = next;
}

fn spec(cols: usize, rows: usize, origin: [f64; 2], seed: u64, accuracy: f64) -> Spec {
    Spec {
        cols,
        rows,
        origin,
        theta: 0.0,
        step: [1.0, 1.0],
        voids: vec![(cols as f64 * 0.3, rows as f64 * 0.6, 3.0)],
        accuracy,
        seed,
    }
}

/// Two overlapping surveys of one terrain, one of them rotated and finer.
fn pair() -> (Arc<Survey>, Arc<Survey>) {
    let a = spec(48, 40, [0.0, 0.0], 7, 0.0).survey().unwrap();
    let b = Spec {
        cols: 60,
        rows: 52,
        origin: [12.0, 6.0],
        theta: 0.4,
        step: [0.5, 0.5],
        voids: vec![(20.0, 20.0, 4.0)],
        accuracy: 1.0,
        seed: 7,
    }
    .survey()
    .unwrap();
    (a, b)
}

fn answers(t: &Terrain, roi: &Aabb) -> Vec<Vec<patchwork_core::index::query::Extracted>> {
    [0.0, 0.5, 2.0, 8.0, 40.0]
        .iter()
        .map(|&e| t.uniform(roi, e))
        .collect()
}

fn heights(t: &Terrain, roi: &Aabb) -> Vec<u32> {
    t.tile(roi, 33, 29, 1.0)
        .heights
        .iter()
        .map(|z| z.to_bits())
        .collect()
}

fn assert_same(a: &Terrain, b: &Terrain, roi: &Aabb) {
    assert_eq!(a.index().state(), b.index().state());
    assert_eq!(answers(a, roi), answers(b, roi));
    assert_eq!(heights(a, roi), heights(b, roi));
    let mut ia: Vec<_> = a.surveys().map(|s| s.id).collect();
    let mut ib: Vec<_> = b.surveys().map(|s| s.id).collect();
    ia.sort();
    ib.sort();
    assert_eq!(ia, ib);
}

fn assert_verified(store: &Store) {
    let r = restore::verify(store).unwrap();
    assert!(r.is_ok(), "{:#?}", r.problems);
}

#[test]
fn committed_surveys_come_back_as_the_same_terrain() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (a, b) = pair();
    let roi = bounds_of(&[a.clone(), b.clone()]);
    let mut t = Terrain::new(IndexConfig::default());
    {
        let Opened {
            mut store, terrain, ..
        } = open(&dir);
        assert_eq!(store.migrations_run(), &steps_from(0)[..]);
        assert_eq!(terrain.index().len(), 0);
        ingest(&mut store, &mut t, &a, "/data/a.tif");
        ingest(&mut store, &mut t, &b, "/data/b.tif");
        assert_eq!(store.crs().and_then(|c| c.epsg_code()), Some(32631));
        assert_verified(&store);
    }
    let Opened { store, terrain, .. } = open(&dir);
    assert!(store.migrations_run().is_empty());
    assert_same(&terrain, &t, &roi);
    assert_same(&terrain, &terrain_of(&[a.clone(), b.clone()]), &roi);
    terrain.index().check().unwrap();
    // The samples come back bit for bit, voids included, read from disk.
    for s in [&a, &b] {
        let back = terrain.survey(s.id).unwrap();
        assert_eq!(back.shapes.len(), s.levels.len());
        for (k, y) in s.levels.iter().enumerate() {
            let x = terrain.window(back, k, back.shapes[k].all()).unwrap();
            let bits = |g: &patchwork_core::model::grid::Grid| -> Vec<u32> {
                g.samples.iter().map(|z| z.to_bits()).collect()
            };
            assert_eq!(bits(&x.grid), bits(y));
            assert_eq!(x.grid.georef, y.georef);
            assert_eq!(back.shapes[k], y.shape());
        }
        // The patches as built; those served carry what the other survey says of them.
        let base = terrain.base(s.id).unwrap();
        assert_eq!(base.patches, s.patches);
        assert_eq!(base.edge_tiles, s.edge_tiles);
    }
    let recs = store.surveys().unwrap();
    assert_eq!(recs.len(), 2);
    let ra = recs.iter().find(|r| r.id == a.id).unwrap();
    assert_eq!(ra.source, "/data/a.tif");
    assert_eq!(ra.status, Status::Active);
    assert_eq!(ra.samples, a.levels[0].valid_count() as u64);
    assert!(ra.ingest.commit_ms > 0.0);
    assert_eq!(store.crs().and_then(|c| c.epsg_code()), Some(32631));
}

#[test]
fn a_retired_survey_stays_retired() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (a, b) = pair();
    let c = spec(30, 30, [20.0, 10.0], 7, 0.5).survey().unwrap();
    let roi = bounds_of(&[a.clone(), b.clone(), c.clone()]);
    let mut t = Terrain::new(IndexConfig::default());
    {
        let Opened { mut store, .. } = open(&dir);
        for (s, n) in [(&a, "a"), (&b, "b"), (&c, "c")] {
            ingest(&mut store, &mut t, s, n);
        }
        retire(&mut store, &mut t, b.id);
        assert!(matches!(
            commit_retire(&mut store, b.id, &Default::default(), &[], false),
            Err(StoreError::NotActive(_))
        ));
        assert_verified(&store);
    }
    let Opened { store, terrain, .. } = open(&dir);
    assert_same(&terrain, &t, &roi);
    assert_same(&terrain, &terrain_of(&[a.clone(), c.clone()]), &roi);
    let rb = store
        .surveys()
        .unwrap()
        .into_iter()
        .find(|r| r.id == b.id)
        .unwrap();
    assert_eq!(rb.status, Status::Retired);
    assert!(terrain.survey(b.id).is_none());
    assert_verified(&store);
}

#[test]
fn a_replacement_is_one_commit() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (a, b) = pair();
    // The same file rewritten with other heights.
    let a2 = spec(48, 40, [0.0, 0.0], 11, 0.0).survey().unwrap();
    assert_ne!(a.id, a2.id);
    let roi = bounds_of(&[a.clone(), b.clone()]);
    let mut t = Terrain::new(IndexConfig::default());
    {
        let Opened { mut store, .. } = open(&dir);
        ingest(&mut store, &mut t, &a, "a.tif");
        ingest(&mut store, &mut t, &b, "b.tif");
        let mut next = t.clone();
        let retired = next.retire(a.id).unwrap();
        let inserted = next.insert(a2.clone());
        let rec = SurveyRecord::new(
            &a2,
            "a.tif",
            "",
            AccuracySource::Flag,
            IngestTimings::default(),
        );
        let packed = store.pack_survey(&a2).unwrap();
        commit_replace(
            &mut store,
            a.id,
            &retired,
            &a2,
            &rec,
            &inserted,
            &next.edges_of(&[&retired, &inserted]),
            &next.pairs_of(a2.id),
            packed,
        )
        .unwrap();
        t = next;
        assert_verified(&store);
    }
    let Opened { store, terrain, .. } = open(&dir);
    assert_same(&terrain, &t, &roi);
    assert_same(&terrain, &terrain_of(&[b.clone(), a2.clone()]), &roi);
    let recs = store.surveys().unwrap();
    let status = |id| recs.iter().find(|r| r.id == id).unwrap().status;
    assert_eq!(status(a.id), Status::Retired);
    assert_eq!(status(a2.id), Status::Active);
}

#[test]
fn verify_finds_a_missing_chunk_a_missing_top_and_a_wrong_top() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (a, b) = pair();
    let mut t = Terrain::new(IndexConfig::default());
    let Opened { mut store, .. } = open(&dir);
    ingest(&mut store, &mut t, &a, "a");
    ingest(&mut store, &mut t, &b, "b");
    let r = restore::verify(&store).unwrap();
    assert!(r.is_ok(), "{:?}", r.problems);
    assert_eq!((r.active, r.retired), (2, 0));
    assert_eq!(r.patches, a.patches.len() + b.patches.len());
    // A state for every patch, the edge patches along the surveys' borders among them.
    assert_eq!(r.tops, t.index().len());
    assert!(r.tops > r.patches);

    let chunk = format!("c/{}/01/00000000", a.id);
    let saved = store.raw().remove(chunk.as_bytes()).unwrap().unwrap();
    let r = restore::verify(&store).unwrap();
    assert!(
        r.problems.iter().any(|p| p.contains("chunk 0 of level 1")),
        "{:?}",
        r.problems
    );
    store.raw().insert(chunk.as_bytes(), saved).unwrap();
    assert_verified(&store);

    let top = format!("b/{}", b.id);
    let saved = store.raw().get(top.as_bytes()).unwrap().unwrap();
    store
        .raw()
        .insert(top.as_bytes(), with_box(&saved, b.patches[3].id, None))
        .unwrap();
    let r = restore::verify(&store).unwrap();
    assert!(
        r.problems
            .iter()
            .any(|p| p.contains(&b.patches[3].id.to_string()) && p.contains("no top")),
        "{:?}",
        r.problems
    );

    // A top that is there but wrong: only re-deriving the index can tell.
    store
        .raw()
        .insert(
            top.as_bytes(),
            with_box(&saved, b.patches[3].id, Some(state_bytes(12345.0, false))),
        )
        .unwrap();
    let r = restore::verify(&store).unwrap();
    assert!(
        r.problems.iter().any(|p| p.contains("wrong top")),
        "{:?}",
        r.problems
    );
    store.raw().insert(top.as_bytes(), saved).unwrap();

    // A top of a patch that belongs to nothing.
    let stray = [
        0x0123_4567_89ab_cdef_u64.to_le_bytes().to_vec(),
        state_bytes(1.0, false),
    ]
    .concat();
    store.raw().insert(b"b/0123456789abcdef", stray).unwrap();
    let r = restore::verify(&store).unwrap();
    assert!(
        r.problems.iter().any(|p| p.contains("0123456789abcdef")),
        "{:?}",
        r.problems
    );
    store.raw().remove(b"b/0123456789abcdef").unwrap();

    // A damaged chunk fails its checksum.
    let chunk0 = format!("c/{}/00/00000000", a.id);
    let loc = store.raw().get(chunk0.as_bytes()).unwrap().unwrap();
    let loc = patchwork::store::pack::Loc::from_bytes(&loc).unwrap();
    let pack = dir.join(patchwork::store::pack::PACK_FILE);
    {
        use std::os::unix::fs::FileExt;
        let f = std::fs::OpenOptions::new()
            .write(true)
            .read(true)
            .open(&pack)
            .unwrap();
        let mut b = [0u8; 1];
        f.read_exact_at(&mut b, loc.offset + 20).unwrap();
        f.write_all_at(&[b[0] ^ 1], loc.offset + 20).unwrap();
    }
    let r = restore::verify(&store).unwrap();
    assert!(
        r.problems.iter().any(|p| p.contains("damaged")),
        "{:?}",
        r.problems
    );
    // Samples that changed under the same key, in a sound chunk.
    let g = &a.levels[0];
    let mut samples = g.samples.clone();
    samples[0] += 1.0;
    let bytes = patchwork::store::chunks::encode(&samples, g.cols);
    let loc = store.raw_pack().append(&[bytes]).unwrap()[0];
    store
        .raw()
        .insert(chunk0.as_bytes(), &loc.to_bytes()[..])
        .unwrap();
    let r = restore::verify(&store).unwrap();
    assert!(
        r.problems.iter().any(|p| p.contains("have changed")),
        "{:?}",
        r.problems
    );
}

#[test]
fn a_newer_schema_is_refused_naming_both_versions() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    {
        let Opened { store, .. } = open(&dir);
        store
            .raw()
            .insert(b"meta/schema", &99u32.to_le_bytes())
            .unwrap();
        store.raw().flush().unwrap();
    }
    let err = refused(&dir);
    assert!(
        matches!(err, StoreError::Newer { found: 99, supported } if supported == SCHEMA_VERSION)
    );
    let msg = err.to_string();
    assert!(
        msg.contains("99") && msg.contains(&SCHEMA_VERSION.to_string()),
        "{msg}"
    );
}

#[test]
fn a_directory_with_data_but_no_schema_is_not_adopted() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    {
        let db = sled::open(&dir).unwrap();
        db.insert(b"something", b"else").unwrap();
        db.flush().unwrap();
    }
    let err = refused(&dir);
    assert!(matches!(err, StoreError::Migration { from: 0, to: 1, .. }));
    assert!(err.to_string().contains("not a Patchwork store"), "{err}");
}

#[test]
fn settings_of_an_existing_store_win() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    drop(open(&dir));
    let other = patchwork_core::model::patch::PatchLayout {
        kernel: 16,
        margin: 2,
    };
    let cfg = IndexConfig {
        max_error: 500.0,
        node_capacity: 8,
    };
    let Opened { store, .. } = restore::open(&dir, other, cfg, StoreOptions::default()).unwrap();
    assert_eq!(store.layout(), LAYOUT);
    assert_eq!(store.index_config(), IndexConfig::default());
}

#[test]
fn a_store_keeps_the_recipe_it_was_made_with() {
    use patchwork_core::model::mipmap::Filter;
    use patchwork_core::model::patch::{Blend, PatchKind};
    use patchwork_core::model::survey::Recipe;
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let with = |mipmap, patches| StoreOptions {
        recipe: Recipe { mipmap, patches },
        ..StoreOptions::default()
    };
    let blending = |blend| StoreOptions {
        blend,
        ..with(Filter::Minimax, PatchKind::Bilinear)
    };
    let opened = |opts: StoreOptions| {
        restore::open(&dir, LAYOUT, IndexConfig::default(), opts)
            .unwrap()
            .store
    };
    let made = Recipe {
        mipmap: Filter::Decimate,
        patches: PatchKind::Bicubic,
    };
    let first = restore::open(
        &dir,
        LAYOUT,
        IndexConfig::default(),
        StoreOptions {
            blend: Blend::Accurate,
            ..with(Filter::Decimate, PatchKind::Bicubic)
        },
    )
    .unwrap();
    assert_eq!(first.store.recipe(), made);
    assert_eq!(first.store.blend(), Blend::Accurate);
    // The terrain an open restores blends as its store does.
    assert_eq!(first.terrain.blend(), Blend::Accurate);
    drop(first);
    let again = opened(blending(Blend::Formula1));
    assert_eq!(again.recipe(), made);
    assert_eq!(again.blend(), Blend::Accurate);
    drop(again);

    // A store from before the choices holds smooth, bilinear surveys, whatever a new store
    // would get.
    let old = tmp.path().join("old");
    let mut store = restore::open(
        &old,
        LAYOUT,
        IndexConfig::default(),
        with(Filter::Smooth, PatchKind::Bilinear),
    )
    .unwrap()
    .store;
    let mut t = Terrain::new(IndexConfig::default());
    ingest(&mut store, &mut t, &pair().0, "a");
    store.raw().remove("meta/mipmap").unwrap();
    store.raw().remove("meta/patches").unwrap();
    store.raw().remove("meta/blend").unwrap();
    drop(store);
    for _ in 0..2 {
        let o = restore::open(
            &old,
            LAYOUT,
            IndexConfig::default(),
            StoreOptions {
                blend: Blend::Accurate,
                ..with(Filter::Minimax, PatchKind::Bicubic)
            },
        )
        .unwrap();
        assert_eq!(
            o.store.recipe(),
            Recipe {
                mipmap: Filter::Smooth,
                patches: PatchKind::Bilinear
            }
        );
        // It served Formula 1's heights, and keeps serving them.
        assert_eq!(o.store.blend(), Blend::Formula1);
        assert_eq!(o.terrain.blend(), Blend::Formula1);
    }
}

#[test]
fn a_failed_commit_changes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (a, b) = pair();
    let mut t = Terrain::new(IndexConfig::default());
    let Opened { mut store, .. } = open(&dir);
    ingest(&mut store, &mut t, &a, "a");
    // Another CRS cannot join the store.
    let foreign = Arc::new(
        Survey::build(
            spec(30, 30, [5.0, 5.0], 3, 0.0).grid(),
            0.0,
            Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
            LAYOUT,
        )
        .unwrap(),
    );
    let mut next = t.clone();
    let change = next.insert(foreign.clone());
    let rec = SurveyRecord::new(
        &foreign,
        "f",
        "",
        AccuracySource::Flag,
        IngestTimings::default(),
    );
    let err = commit_survey(
        &mut store,
        &foreign,
        &rec,
        &change,
        &next.edges_of(&[&change]),
        &[],
    )
    .unwrap_err();
    // The engine places a survey in the store's CRS before committing it; one placed in
    // another (or in none) is refused.
    assert!(
        matches!(&err, StoreError::CrsMismatch { placed_in, store_crs, .. }
            if placed_in.contains("4326") && store_crs.contains("32631")),
        "{err}"
    );
    // Committing the same survey twice would overwrite its tops with nothing.
    let rec = SurveyRecord::new(&a, "a", "", AccuracySource::Flag, IngestTimings::default());
    let err = commit_survey(&mut store, &a, &rec, &Default::default(), &[], &[]).unwrap_err();
    assert!(matches!(err, StoreError::Duplicate(id) if id == a.id));
    // A record of another survey is refused.
    let rec = SurveyRecord::new(&a, "b", "", AccuracySource::Flag, IngestTimings::default());
    let mut nb = t.clone();
    let change = nb.insert(b.clone());
    assert!(matches!(
        commit_survey(&mut store, &b, &rec, &change, &nb.edges_of(&[&change]), &[]),
        Err(StoreError::Inconsistent { survey, .. }) if survey == b.id
    ));
    assert_eq!(store.surveys().unwrap().len(), 1);
    assert_verified(&store);
}

#[test]
fn failures_are_recorded_listed_and_cleared() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (a, _) = pair();
    let f = |source: &str| FailedRecord {
        source: source.into(),
        error: "not a GeoTIFF".into(),
        size: 1234,
        mtime_unix: 1_700_000_000,
        content_id: String::new(),
        at_unix: 1_700_000_100,
    };
    {
        let Opened { mut store, .. } = open(&dir);
        store.record_failure(&f("/in/b.tif"), 100).unwrap();
        store.record_failure(&f("/in/a.tif"), 100).unwrap();
        store.record_failure(&f("/in/c.tif"), 100).unwrap();
        store.clear_failure("/in/c.tif").unwrap();
        // Clearing what is not there is fine.
        store.clear_failure("/in/zzz.tif").unwrap();
    }
    let Opened { mut store, .. } = open(&dir);
    assert_eq!(
        store.failures().unwrap(),
        vec![f("/in/a.tif"), f("/in/b.tif")]
    );
    // A file that finally ingests loses its failure in the same commit.
    let mut t = Terrain::new(IndexConfig::default());
    ingest(&mut store, &mut t, &a, "/in/a.tif");
    assert_eq!(store.failures().unwrap(), vec![f("/in/b.tif")]);
    let r = restore::verify(&store).unwrap();
    assert!(r.is_ok() && r.failures == 1, "{r:?}");
}

#[test]
fn failure_records_are_one_a_path_and_bounded_and_can_be_forgotten() {
    let tmp = tempfile::tempdir().unwrap();
    let Opened { mut store, .. } = open(&store_dir(&tmp));
    let f = |source: &str, at_unix: u64| FailedRecord {
        source: source.into(),
        error: "not a GeoTIFF".into(),
        size: 1,
        mtime_unix: 1,
        content_id: String::new(),
        at_unix,
    };
    for i in 0..50 {
        store
            .record_failure(&f(&format!("/in/{i:02}.tif"), i), 10)
            .unwrap();
        // The same path again replaces its record.
        store
            .record_failure(&f(&format!("/in/{i:02}.tif"), i), 10)
            .unwrap();
    }
    let kept: Vec<String> = store
        .failures()
        .unwrap()
        .into_iter()
        .map(|r| r.source)
        .collect();
    let newest: Vec<String> = (40..50).map(|i| format!("/in/{i}.tif")).collect();
    assert_eq!(kept, newest, "the newest 10 stay");
    assert!(store.forget_failure("/in/45.tif").unwrap());
    assert!(!store.forget_failure("/in/45.tif").unwrap());
    assert_eq!(store.failures().unwrap().len(), 9);
    assert_verified(&store);
}

/// A disk whose free space a test sets.
struct FakeDisk(std::sync::atomic::AtomicU64);

impl DiskSpace for FakeDisk {
    fn available(&self, _: &Path) -> std::io::Result<u64> {
        Ok(self.0.load(std::sync::atomic::Ordering::SeqCst))
    }
}

#[test]
fn a_write_the_disk_has_no_room_for_is_refused_with_nothing_written() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let disk = Arc::new(FakeDisk(u64::MAX.into()));
    let guard = SpaceGuard {
        disk: disk.clone(),
        min_free: 64 << 20,
        reserve: 0,
    };
    let Opened { mut store, .. } =
        restore::open(&dir, LAYOUT, IndexConfig::default(), guard.clone()).unwrap();
    let (a, b) = (big(1), big(2));
    let mut t = Terrain::new(IndexConfig::default());
    ingest(&mut store, &mut t, &a, "/in/a.tif");
    let before = store.raw().iter().count();
    // Room for a small write (64 MiB kept free and 4 MiB for sled), not for a survey's
    // samples three times over.
    disk.0.store(68 << 20, std::sync::atomic::Ordering::SeqCst);
    let mut next = t.clone();
    let change = next.insert(b.clone());
    let rec = SurveyRecord::new(
        &b,
        "/in/b.tif",
        "",
        AccuracySource::Sidecar,
        Default::default(),
    );
    let e = commit_survey(
        &mut store,
        &b,
        &rec,
        &change,
        &next.edges_of(&[&change]),
        &next.pairs_of(b.id),
    )
    .unwrap_err();
    assert!(
        matches!(
            e,
            StoreError::Full {
                available_mb: 68,
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("nothing was written"), "{e}");
    assert_eq!(store.raw().iter().count(), before);
    assert!(store.writable().is_ok(), "a small write still fits");
    disk.0.store(10 << 20, std::sync::atomic::Ordering::SeqCst);
    assert!(store.writable().is_err());
    let f = FailedRecord {
        source: "/in/x.tif".into(),
        error: "bad".into(),
        size: 1,
        mtime_unix: 1,
        content_id: String::new(),
        at_unix: 1,
    };
    assert!(matches!(
        store.record_failure(&f, 10),
        Err(StoreError::Full { .. })
    ));
    // Space returns, and so do writes.
    disk.0.store(u64::MAX, std::sync::atomic::Ordering::SeqCst);
    commit_survey(
        &mut store,
        &b,
        &rec,
        &change,
        &next.edges_of(&[&change]),
        &next.pairs_of(b.id),
    )
    .unwrap();
    assert_verified(&store);
    // A compaction the disk has no room for gives the store back, open and as it was, rather
    // than closing it for the caller to open again; its partial copy is gone.
    disk.0.store(10 << 20, std::sync::atomic::Ordering::SeqCst);
    let live = next.index().state().into_keys().collect();
    let Err(failed) = restore::compact(store, &live) else {
        panic!("a compaction with no room for its copy went through");
    };
    assert!(
        matches!(failed.error, StoreError::Full { .. }),
        "{}",
        failed.error
    );
    let store = *failed.store.expect("the store, given back open");
    assert!(!Path::new(&format!("{}.compact", dir.display())).exists());
    disk.0.store(u64::MAX, std::sync::atomic::Ordering::SeqCst);
    assert!(store.writable().is_ok());
    assert_verified(&store);
    drop(store);
    // A store opens on a full disk, and says it cannot be written.
    disk.0.store(0, std::sync::atomic::Ordering::SeqCst);
    let Opened { store, terrain, .. } =
        restore::open(&dir, LAYOUT, IndexConfig::default(), guard).unwrap();
    assert_eq!(terrain.surveys().count(), 2);
    assert!(matches!(store.writable(), Err(StoreError::Full { .. })));
}

#[test]
fn a_pin_holds_the_content_of_a_survey_retired_by_hand_until_it_is_ingested_again() {
    let tmp = tempfile::tempdir().unwrap();
    let Opened { mut store, .. } = open(&store_dir(&tmp));
    let (a, _) = pair();
    let mut t = Terrain::new(IndexConfig::default());
    let change = t.insert(a.clone());
    let content = "c0".repeat(32);
    let rec = SurveyRecord::new(
        &a,
        "/in/a.tif",
        &content,
        AccuracySource::Flag,
        Default::default(),
    );
    commit_survey(
        &mut store,
        &a,
        &rec,
        &change,
        &t.edges_of(&[&change]),
        &t.pairs_of(a.id),
    )
    .unwrap();
    let change = t.retire(a.id).unwrap();
    commit_retire(&mut store, a.id, &change, &t.edges_of(&[&change]), true).unwrap();
    let pins = store.pins().unwrap();
    assert_eq!(pins.get("/in/a.tif"), Some(&content));
    assert_verified(&store);
    ingest(&mut store, &mut t, &a, "/in/a.tif");
    assert!(
        store.pins().unwrap().is_empty(),
        "ingesting the file again lifts the pin"
    );
}

fn big(k: u64) -> Arc<Survey> {
    let s = Spec {
        cols: 200,
        rows: 200,
        origin: [(k % 3) as f64 * 60.0, (k / 3) as f64 * 60.0],
        theta: 0.0,
        step: [1.0, 1.0],
        voids: vec![(50.0, 120.0, 6.0)],
        accuracy: 0.5 * k as f64,
        seed: k,
    };
    s.survey().unwrap()
}

/// A store of six 200×200 surveys, five of them retired, and the terrain it should load as.
fn retired_store(dir: &Path) -> (Vec<Arc<Survey>>, Terrain) {
    let surveys: Vec<Arc<Survey>> = (0..6).map(big).collect();
    let Opened { mut store, .. } = open(dir);
    let mut t = Terrain::new(IndexConfig::default());
    for (k, s) in surveys.iter().enumerate() {
        ingest(&mut store, &mut t, s, &format!("/in/{k}.tif"));
    }
    for s in &surveys[1..] {
        retire(&mut store, &mut t, s.id);
    }
    assert_verified(&store);
    (surveys, t)
}

#[test]
fn compaction_gives_space_back_and_keeps_the_answers() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (surveys, t) = retired_store(&dir);
    let roi = bounds_of(&surveys);
    let Opened { store, terrain, .. } = open(&dir);
    assert_same(&terrain, &t, &roi);
    let before = store.disk_bytes();
    let started = Instant::now();
    let live = terrain.index().state().into_keys().collect();
    let (Opened { store, terrain, .. }, rep) = restore::compact(store, &live).unwrap();
    eprintln!("compaction: {rep:?} in {:?}", started.elapsed());
    assert_eq!(rep.bytes_before, before);
    assert_eq!(rep.surveys_purged, 5);
    assert!(
        rep.bytes_after < rep.bytes_before,
        "{} → {}",
        rep.bytes_before,
        rep.bytes_after
    );
    assert_eq!(store.disk_bytes(), rep.bytes_after);
    assert_same(&terrain, &t, &roi);
    assert_verified(&store);
    for s in &surveys[1..] {
        let chunk = format!("c/{}/00/00000000", s.id);
        assert!(store.raw().get(chunk.as_bytes()).unwrap().is_none());
    }
    // Retired surveys are gone for good, records and all.
    assert_eq!(store.surveys().unwrap().len(), 1);
    assert!(!tmp.path().join("store.old").exists());
    assert!(!tmp.path().join("store.compact").exists());
    drop(store);
    // And what compaction wrote opens again.
    let Opened { store, terrain, .. } = open(&dir);
    assert_same(&terrain, &t, &roi);
    // Compacting a compact store changes nothing.
    let live = terrain.index().state().into_keys().collect();
    let (
        Opened {
            store: _store,
            terrain,
            ..
        },
        rep,
    ) = restore::compact(store, &live).unwrap();
    assert_eq!((rep.surveys_purged, rep.keys_removed), (0, 0));
    assert_same(&terrain, &t, &roi);
    // With nothing to remove, compaction never grows the store, however often it runs.
    let mut store = _store;
    for round in 0..3 {
        let files = dir_digest(&dir);
        let (opened, rep) = restore::compact(store, &live).unwrap();
        assert!(
            rep.bytes_after <= rep.bytes_before,
            "round {round}: {} → {} bytes, {rep:?}",
            rep.bytes_before,
            rep.bytes_after
        );
        // A compact store compacted again is left byte for byte as it was.
        assert!(!rep.swapped, "round {round}: {rep:?}");
        assert_eq!(dir_digest(&dir), files, "round {round}");
        assert_same(&opened.terrain, &t, &roi);
        store = opened.store;
    }
}

#[test]
fn open_recovers_from_a_crash_at_any_step_of_compaction() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (a, b) = pair();
    let mut t = Terrain::new(IndexConfig::default());
    {
        let Opened { mut store, .. } = open(&dir);
        ingest(&mut store, &mut t, &a, "a");
        ingest(&mut store, &mut t, &b, "b");
    }
    let roi = bounds_of(&[a.clone(), b.clone()]);
    let old = tmp.path().join("store.old");
    let compact = tmp.path().join("store.compact");
    let pristine = tmp.path().join("pristine");
    copy_dir(&dir, &pristine);
    let junk = |p: &Path| {
        std::fs::create_dir_all(p).unwrap();
        std::fs::write(p.join("db"), b"half a database").unwrap();
    };
    let check = |what: &str| {
        let Opened { store, terrain, .. } = open(&dir);
        assert_same(&terrain, &t, &roi);
        assert_verified(&store);
        assert!(!old.exists(), "{what}: .old left");
        assert!(!compact.exists(), "{what}: .compact left");
    };

    // During the copy: a partial `.compact` beside the store.
    junk(&compact);
    check("copy");
    // Between the renames, with and without the copy.
    std::fs::rename(&dir, &old).unwrap();
    junk(&compact);
    check("between renames");
    std::fs::rename(&dir, &old).unwrap();
    check("between renames, copy gone");
    // After both renames, before `.old` is deleted.
    copy_dir(&pristine, &old);
    check("after renames");
    // Only the copy: not ours to guess.
    std::fs::rename(&dir, &compact).unwrap();
    let err = refused(&dir);
    assert!(
        matches!(err, StoreError::Corrupt(Corruption::Swapped { .. })),
        "{err}"
    );
    std::fs::rename(&compact, &dir).unwrap();
    check("copy renamed back");
}

#[test]
fn a_store_in_use_is_refused_with_a_helpful_message() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let first = open(&dir);
    let err = refused(&dir);
    assert!(matches!(err, StoreError::Locked { .. }), "{err}");
    let msg = err.to_string();
    assert!(
        msg.contains("in use by another process") && msg.contains("is the daemon running?"),
        "{msg}"
    );
    assert!(msg.contains(&dir.display().to_string()), "{msg}");

    // Another process: this test binary again, running only the helper below.
    let out = std::process::Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "store::store_child_opens",
            "--nocapture",
            "--test-threads=1",
        ])
        .env("PATCHWORK_STORE_CHILD", &dir)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("child: locked"), "{text}");

    drop(first);
    drop(open(&dir));
}

/// The other process of the test above; does nothing when run on its own.
#[test]
fn store_child_opens() {
    let Some(dir) = std::env::var_os("PATCHWORK_STORE_CHILD") else {
        return;
    };
    match restore::open(
        Path::new(&dir),
        LAYOUT,
        IndexConfig::default(),
        StoreOptions::default(),
    ) {
        Err(StoreError::Locked { .. }) => println!("child: locked"),
        Err(e) => println!("child: other error {e}"),
        Ok(_) => println!("child: opened"),
    }
}

#[test]
fn sled_lock_errors_are_recognised() {
    let e = sled::Error::Io(std::io::Error::other(
        "could not acquire lock on \"/x/db\": Os { code: 11, kind: WouldBlock }",
    ));
    let err = open_error(e, Path::new("/x"));
    assert_eq!(
        err.to_string(),
        "the store at /x is in use by another process (is the daemon running?)"
    );
    let e = sled::Error::Io(std::io::Error::from(std::io::ErrorKind::WouldBlock));
    assert!(matches!(
        open_error(e, Path::new("/x")),
        StoreError::Locked { .. }
    ));
    let e = sled::Error::Io(std::io::Error::from(std::io::ErrorKind::PermissionDenied));
    assert!(matches!(
        open_error(e, Path::new("/x")),
        StoreError::Sled(_)
    ));
}

/// A version-1 georeference and level, field for field.
#[derive(serde::Serialize)]
struct GeorefV1 {
    origin: [f64; 2],
    theta: f64,
    step: [f64; 2],
}

#[derive(serde::Serialize)]
struct LevelV1 {
    cols: u64,
    rows: u64,
    georef: GeorefV1,
}

fn georef_v1(g: &patchwork_core::model::grid::Georef) -> GeorefV1 {
    GeorefV1 {
        origin: g.origin,
        theta: g.theta,
        step: g.step,
    }
}

/// A version-1 survey record, field for field, to write a store as version 1 wrote it.
#[derive(serde::Serialize)]
struct RecordV1 {
    id: SurveyId,
    source: String,
    content_id: String,
    accuracy: f64,
    crs: Option<u32>,
    status: patchwork::store::Status,
    cols: u64,
    rows: u64,
    georef: GeorefV1,
    samples: u64,
    levels: Vec<LevelV1>,
    ingest: IngestTimings,
    created_unix: u64,
}

#[test]
fn a_version_1_store_is_migrated_and_its_index_derived_again() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    // A version 1 store tiled every survey from its first sample: surveys on the lattice of
    // the origin are tiled so still.
    let a = spec(48, 40, [0.0, 0.0], 7, 0.0).survey().unwrap();
    let b = spec(40, 36, [0.0, 0.0], 9, 1.0).survey().unwrap();
    assert_eq!((a.tiling.offset, b.tiling.offset), ([0, 0], [0, 0]));
    let mut t = Terrain::new(IndexConfig::default());
    {
        let Opened { mut store, .. } = open(&dir);
        ingest(&mut store, &mut t, &a, "a");
        ingest(&mut store, &mut t, &b, "b");
        // Take it back to version 1: old records, tops without exposure and only for
        // surveys' patches, no overlaps.
        let db = store.raw();
        let survey_patches: std::collections::HashSet<String> = [&a, &b]
            .iter()
            .flat_map(|s| s.patches.iter().map(|p| format!("t/{}", p.id)))
            .collect();
        for kv in db.iter() {
            let (k, v) = kv.unwrap();
            let key = String::from_utf8_lossy(&k).to_string();
            if key.starts_with("s/") {
                let r: SurveyRecord =
                    bincode::serde::decode_from_slice(&v, bincode::config::standard())
                        .unwrap()
                        .0;
                let old = RecordV1 {
                    id: r.id,
                    source: r.source,
                    content_id: r.content_id,
                    accuracy: r.accuracy,
                    crs: r.crs.as_ref().and_then(|c| c.epsg_code()),
                    status: r.status,
                    cols: r.cols,
                    rows: r.rows,
                    georef: georef_v1(&r.georef),
                    samples: r.samples,
                    levels: r
                        .levels
                        .iter()
                        .map(|l| LevelV1 {
                            cols: l.cols,
                            rows: l.rows,
                            georef: georef_v1(&l.georef),
                        })
                        .collect(),
                    ingest: r.ingest,
                    created_unix: r.created_unix,
                };
                let bytes =
                    bincode::serde::encode_to_vec(&old, bincode::config::standard()).unwrap();
                db.insert(k, bytes).unwrap();
            } else if key.starts_with("b/") {
                db.remove(k).unwrap();
                for (top, state) in tops_v6(&v) {
                    if survey_patches.contains(&top) {
                        db.insert(top.as_bytes(), &state[..8]).unwrap();
                    }
                }
            } else if key.starts_with("o/") || key.starts_with("e/") || key.starts_with("c/") {
                db.remove(k).unwrap();
            } else if let Some(id) = key.strip_prefix("p/") {
                // Versions 1 and 2 kept the patches alone, in the database.
                let id: SurveyId = id.parse().unwrap();
                let p = store.load_patches(id).unwrap();
                let patches: &Vec<form::Patch> = &p.patches;
                let bytes =
                    bincode::serde::encode_to_vec(patches, bincode::config::standard()).unwrap();
                db.insert(k, bytes).unwrap();
            }
        }
        // Versions 1 and 2 kept each level as bands of 64 rows of raw f32.
        for s in [&a, &b] {
            for (level, g) in s.levels.iter().enumerate() {
                for (band, rows) in g.samples.chunks(64 * g.cols).enumerate() {
                    let bytes: Vec<u8> = rows.iter().flat_map(|z| z.to_le_bytes()).collect();
                    let key = format!("c/{}/{level:02}/{band:08}", s.id);
                    db.insert(key.as_bytes(), bytes).unwrap();
                }
            }
        }
        db.insert(b"meta/schema", &1u32.to_le_bytes()).unwrap();
        // Version 1 kept the store's CRS as an EPSG number.
        db.insert(b"meta/crs", &32631u32.to_le_bytes()).unwrap();
        db.flush().unwrap();
    }
    let Opened { store, terrain, .. } = open(&dir);
    assert_eq!(store.migrations_run(), &steps_from(1)[..]);
    let roi = bounds_of(&[a.clone(), b.clone()]);
    assert_same(&terrain, &t, &roi);
    assert_eq!(terrain.index().state(), t.index().state());
    let recs = store.surveys().unwrap();
    assert!(recs
        .iter()
        .all(|r| r.accuracy_source == AccuracySource::Unknown));
    assert_verified(&store);
    drop(store);
    drop(terrain);
    // The rebuild was written: the next open restores from the stored states.
    let Opened { store, terrain, .. } = open(&dir);
    assert!(store.migrations_run().is_empty());
    assert_eq!(terrain.index().state(), t.index().state());
}

#[test]
fn chunks_a_crash_left_past_the_commit_are_cut_at_open() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (a, b) = pair();
    let mut t = Terrain::new(IndexConfig::default());
    let committed;
    {
        let Opened { mut store, .. } = open(&dir);
        ingest(&mut store, &mut t, &a, "a");
        committed = store.raw_pack().len();
        // A commit that appended its chunks and died before its batch.
        store.raw_pack().append(&[vec![7u8; 5000]]).unwrap();
    }
    let pack = dir.join(patchwork::store::pack::PACK_FILE);
    assert_eq!(std::fs::metadata(&pack).unwrap().len(), committed + 5000);
    let Opened {
        mut store, terrain, ..
    } = open(&dir);
    assert_eq!(std::fs::metadata(&pack).unwrap().len(), committed);
    assert_verified(&store);
    let roi = bounds_of(std::slice::from_ref(&a));
    assert_same(&terrain, &t, &roi);
    // Later commits go where the cut tail was.
    let mut t2 = terrain.clone();
    ingest(&mut store, &mut t2, &b, "b");
    assert_verified(&store);
}

#[test]
fn a_version_6_store_keeps_its_box_states_a_unit_at_a_time() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    // A mosaic of four tiles with voids: units of both kinds, surveys and edge patches.
    let tiles: Vec<Arc<Survey>> = [[0.0, 0.0], [24.0, 0.0], [0.0, -20.0], [24.0, -20.0]]
        .iter()
        .enumerate()
        .map(|(k, &o)| spec(24, 20, o, 20 + k as u64, 0.5).survey().unwrap())
        .collect();
    let mut t = Terrain::new(IndexConfig::default());
    let records: Vec<(sled::IVec, sled::IVec)>;
    {
        let Opened { mut store, .. } = open(&dir);
        for (k, s) in tiles.iter().enumerate() {
            ingest(&mut store, &mut t, s, &format!("tile{k}"));
        }
        // Back to version 6: a `t/<patch>` key a box.
        let db = store.raw();
        records = db.scan_prefix("b/").map(Result::unwrap).collect();
        assert_eq!(records.len(), tiles.len() + t.edges().count());
        for (k, v) in &records {
            db.remove(k).unwrap();
            for (top, state) in tops_v6(v) {
                db.insert(top.as_bytes(), state).unwrap();
            }
        }
        db.insert(b"meta/schema", &6u32.to_le_bytes()).unwrap();
        db.flush().unwrap();
    }
    let Opened { store, terrain, .. } = open(&dir);
    assert_eq!(store.migrations_run(), &steps_from(6)[..]);
    let migrated: Vec<(sled::IVec, sled::IVec)> =
        store.raw().scan_prefix("b/").map(Result::unwrap).collect();
    assert_eq!(migrated, records);
    assert_eq!(store.raw().scan_prefix("t/").count(), 0);
    assert_eq!(terrain.index().state(), t.index().state());
    assert_verified(&store);
    drop(store);
    drop(terrain);

    // A state no record names leaves the store to a rebuild, which derives the same index.
    {
        let Opened { store, .. } = open(&dir);
        let db = store.raw();
        for (k, v) in db.scan_prefix("b/").map(Result::unwrap).collect::<Vec<_>>() {
            db.remove(&k).unwrap();
            for (top, state) in tops_v6(&v) {
                db.insert(top.as_bytes(), state).unwrap();
            }
        }
        db.insert(b"t/0123456789abcdef", state_bytes(1.0, false))
            .unwrap();
        db.insert(b"meta/schema", &6u32.to_le_bytes()).unwrap();
        db.flush().unwrap();
    }
    let Opened { store, terrain, .. } = open(&dir);
    assert_eq!(store.migrations_run(), &steps_from(6)[..]);
    assert_eq!(store.raw().scan_prefix("t/").count(), 0);
    assert_eq!(terrain.index().state(), t.index().state());
    assert_verified(&store);
}

#[test]
fn abutting_tiles_read_back_from_disk_answer_as_in_memory_whole_and_in_sub_tiles() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    // Four tiles of one lattice meeting at their edges, each with a void: the seams and the
    // void rims are edge patches, stored and read back rather than derived from samples.
    let tiles: Vec<Arc<Survey>> = [[0.0, 0.0], [24.0, 0.0], [0.0, -20.0], [24.0, -20.0]]
        .iter()
        .enumerate()
        .map(|(k, &o)| spec(24, 20, o, 20 + k as u64, 0.5).survey().unwrap())
        .collect();
    let roi = bounds_of(&tiles);
    let mut t = Terrain::new(IndexConfig::default());
    {
        let Opened { mut store, .. } = open(&dir);
        for (k, s) in tiles.iter().enumerate() {
            ingest(&mut store, &mut t, s, &format!("tile{k}"));
        }
        assert_verified(&store);
    }
    // The store stays open: it serves the samples.
    let Opened {
        store: _store,
        terrain,
        ..
    } = open(&dir);
    assert!(terrain.edges().count() > 0);
    assert_same(&terrain, &t, &roi);
    let [w, h] = [roi.width() / 2.0, roi.height() / 2.0];
    for (i, j) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
        let sub = Aabb {
            min: [roi.min[0] + i * w, roi.min[1] + j * h],
            max: [roi.min[0] + (i + 1.0) * w, roi.min[1] + (j + 1.0) * h],
        };
        assert_eq!(heights(&terrain, &sub), heights(&t, &sub));
    }
}

#[test]
fn a_survey_of_many_chunks_reads_back_as_in_memory_inside_chunks_and_across_their_seams() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    // 600 × 530 samples are 3 × 3 chunks: some patches read inside one chunk, in place, and
    // others across a seam between two or four, copied out. A finer, less accurate survey
    // overlaps it across its seams, so that both kinds meet where surveys blend.
    let s = spec(600, 530, [0.0, 0.0], 41, 0.0).survey().unwrap();
    let fine = Spec {
        step: [0.5, 0.5],
        ..spec(700, 600, [150.0, -100.0], 43, 1.5)
    }
    .survey()
    .unwrap();
    let roi = bounds_of(&[s.clone(), fine.clone()]);
    let mut t = Terrain::new(IndexConfig::default());
    {
        let Opened { mut store, .. } = open(&dir);
        ingest(&mut store, &mut t, &s, "big");
        ingest(&mut store, &mut t, &fine, "fine");
    }
    let Opened {
        store: _store,
        terrain,
        ..
    } = open(&dir);
    for e in [0.0, 2.0] {
        let ps = terrain.uniform(&roi, e);
        assert_eq!(ps, t.uniform(&roi, e));
        let grid = SampleGrid::uniform(&roi, 301, 277);
        let bits = |t: &Terrain| -> Vec<u32> {
            let h = t.resample(ps.clone(), &grid).heights;
            h.iter().map(|z| z.to_bits()).collect()
        };
        assert_eq!(bits(&terrain), bits(&t), "e = {e}");
    }
}

/// Opens a store that may hold damage: warnings are expected, not a failure.
fn open_damaged(dir: &Path) -> Opened {
    restore::open(dir, LAYOUT, IndexConfig::default(), StoreOptions::default())
        .expect("a damaged store still opens")
}

/// Flips the pack's byte at `at` in the store at `dir`, as a failing disk might.
fn flip_pack_byte(dir: &Path, at: u64) {
    let pack = dir.join(patchwork::store::pack::PACK_FILE);
    let mut bytes = std::fs::read(&pack).unwrap();
    bytes[at as usize] ^= 0x5a;
    std::fs::write(&pack, &bytes).unwrap();
}

/// The store of `a` then `b`, and where `b`'s bytes lie in the pack: after `a`'s, to the end.
fn store_of_two(dir: &Path) -> (Arc<Survey>, Arc<Survey>, Terrain, std::ops::Range<u64>) {
    let (a, b) = pair();
    let mut t = Terrain::new(IndexConfig::default());
    let Opened { mut store, .. } = open(dir);
    ingest(&mut store, &mut t, &a, "a");
    let a_end = store.raw_pack().len();
    ingest(&mut store, &mut t, &b, "b");
    let end = store.raw_pack().len();
    (a, b, t, a_end..end)
}

/// What a store whose survey `b` is damaged must be: `a` served as in a store that never had
/// `b`, `b` listed as damaged, the stored index the one without it, and nothing else wrong.
fn assert_quarantined(o: &Opened, a: &Arc<Survey>, b: &Arc<Survey>, at: &str) {
    let damaged = o.store.damaged();
    assert_eq!(
        damaged.keys().copied().collect::<Vec<_>>(),
        vec![b.id],
        "{at}: {:?}",
        o.warnings
    );
    assert!(
        o.warnings
            .iter()
            .any(|w| w.contains(&b.id.to_string()) && w.contains("damaged")),
        "{at}: {:?}",
        o.warnings
    );
    let roi = bounds_of(&[a.clone(), b.clone()]);
    assert_same(&o.terrain, &terrain_of(std::slice::from_ref(a)), &roi);
    let catalog = o.store.catalog().unwrap();
    assert_eq!(
        catalog.active().map(|r| r.id).collect::<Vec<_>>(),
        vec![a.id],
        "{at}"
    );
    let r = restore::verify(&o.store).unwrap();
    assert_eq!(r.damaged, 1, "{at}");
    // The survey's own damage is listed; the index of the rest is checked and sound.
    assert!(
        r.problems.iter().any(|p| p.contains("damaged")),
        "{at}: {:?}",
        r.problems
    );
    assert!(
        r.problems.iter().all(|p| p.contains(&b.id.to_string())),
        "{at}: {:?}",
        r.problems
    );
}

#[test]
fn a_damaged_survey_is_left_out_at_open_and_every_other_one_is_served() {
    let tmp = tempfile::tempdir().unwrap();
    let pristine = store_dir(&tmp);
    let (a, b, both, range) = store_of_two(&pristine);
    let roi = bounds_of(&[a.clone(), b.clone()]);
    let len = range.end - range.start;
    // The first byte (the patch list's header), bytes through the chunks, the last byte.
    let mut offsets: Vec<u64> = (0..12).map(|i| range.start + i * len / 12).collect();
    offsets.extend([range.start + 1, range.start + 7, range.end - 1]);
    for (n, at) in offsets.into_iter().enumerate() {
        let dir = tmp.path().join(format!("flip{n}"));
        copy_dir(&pristine, &dir);
        flip_pack_byte(&dir, at);
        let what = format!("byte {at} flipped");
        {
            let o = open_damaged(&dir);
            assert_quarantined(&o, &a, &b, &what);
        }
        // The next open restores the index it stored without the survey, as it was.
        let o = open_damaged(&dir);
        assert_quarantined(&o, &a, &b, &what);
        let Opened {
            mut store,
            mut terrain,
            ..
        } = o;
        if n % 2 == 0 {
            // Repair drops the survey for good; its file can then come back as new.
            let dropped = store.repair().unwrap();
            assert_eq!(dropped.len(), 1);
            assert_eq!((dropped[0].id, dropped[0].source.as_str()), (b.id, "b"));
            assert!(store.damaged().is_empty());
            assert_verified(&store);
            ingest(&mut store, &mut terrain, &b, "b");
        } else {
            // Ingesting its file again heals it in one commit that replaces the damaged one.
            let mut next = terrain.clone();
            let change = next.insert(b.clone());
            let rec =
                SurveyRecord::new(&b, "b", "", AccuracySource::Flag, IngestTimings::default());
            let packed = store.pack_survey(&b).unwrap();
            commit_replace(
                &mut store,
                b.id,
                &Default::default(),
                &b,
                &rec,
                &change,
                &next.edges_of(&[&change]),
                &next.pairs_of(b.id),
                packed,
            )
            .unwrap();
            terrain = next;
            assert!(store.damaged().is_empty());
        }
        assert_same(&terrain, &both, &roi);
        assert_verified(&store);
        drop(store);
        let o = open(&dir);
        assert_same(&o.terrain, &both, &roi);
        assert_verified(&o.store);
    }
}

/// An open reads back only the chunks committed since the one before it (the pack is
/// append-only): damage to a chunk an earlier open checked is left to `verify` and to the read
/// that meets it, which fails on its checksum rather than serve it; a survey found damaged is
/// read whole at every open, so it stays left out.
#[test]
fn an_open_reads_back_only_the_chunks_committed_since_the_last_one() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (_, b, _, range) = store_of_two(&dir);
    // The store was opened empty, then took both: the next open reads their chunks back,
    // and notes how far.
    let o = open(&dir);
    assert_eq!(
        o.store.raw_pack().checked_to(),
        Some(range.end),
        "the open noted what it checked"
    );
    assert_eq!(
        o.store.raw().get("meta/checked_to").unwrap(),
        None,
        "the open wrote its mark into the database"
    );
    drop(o);
    flip_pack_byte(&dir, (range.start + range.end) / 2);
    let o = open(&dir);
    assert!(
        o.store.damaged().is_empty(),
        "the open read old chunks again"
    );
    let r = restore::verify(&o.store).unwrap();
    assert!(
        r.problems.iter().any(|p| p.contains(&b.id.to_string())),
        "verify missed the damage: {:?}",
        r.problems
    );
    let points: Vec<[f64; 2]> = {
        let g = &b.levels[0];
        (0..g.rows)
            .step_by(3)
            .flat_map(|r| (0..g.cols).step_by(3).map(move |c| (c, r)))
            .map(|(c, r)| g.georef.to_world(c as f64, r as f64))
            .collect()
    };
    assert!(
        o.terrain.try_sample(&points, 0.0).is_err(),
        "a damaged chunk was served"
    );
}

/// The mark of how far opens checked the pack is a file beside it: one that is damaged or gone
/// makes the open read every chunk back again, and a store from before the file, which kept
/// the mark in its database, is read from there.
#[test]
fn a_damaged_or_missing_mark_makes_the_open_read_the_pack_again() {
    let tmp = tempfile::tempdir().unwrap();
    let pristine = store_dir(&tmp);
    let (_, b, _, range) = store_of_two(&pristine);
    drop(open(&pristine));
    let mark = pristine.join(patchwork::store::pack::CHECKED_FILE);
    let bytes = std::fs::read(&mark).unwrap();
    let damaged_after = |name: &str, change: &dyn Fn(&Path)| {
        let dir = tmp.path().join(name);
        copy_dir(&pristine, &dir);
        change(&dir);
        flip_pack_byte(&dir, (range.start + range.end) / 2);
        let o = restore::open(
            &dir,
            LAYOUT,
            IndexConfig::default(),
            StoreOptions::default(),
        )
        .expect("store opens");
        o.store.damaged().keys().copied().collect::<Vec<_>>()
    };
    let mark_of = |dir: &Path| dir.join(patchwork::store::pack::CHECKED_FILE);
    // The mark as it is: the old chunk's damage is left to verify.
    assert!(damaged_after("kept", &|_| {}).is_empty());
    // Any byte of the mark flipped: no mark, the open reads the pack whole.
    for at in [0, 3, 8, 15] {
        let found = damaged_after(&format!("flipped{at}"), &|d| {
            let mut m = bytes.clone();
            m[at] ^= 0x10;
            std::fs::write(mark_of(d), m).unwrap();
        });
        assert_eq!(
            found,
            vec![b.id],
            "a mark with byte {at} flipped was trusted"
        );
    }
    for (name, content) in [("empty", Vec::new()), ("short", bytes[..8].to_vec())] {
        let found = damaged_after(name, &|d| std::fs::write(mark_of(d), &content).unwrap());
        assert_eq!(found, vec![b.id], "a mark {name} was trusted");
    }
    assert_eq!(
        damaged_after("gone", &|d| std::fs::remove_file(mark_of(d)).unwrap()),
        vec![b.id],
        "the open trusted a mark that is gone"
    );
    // A store from before the file: the database's mark is read.
    let found = damaged_after("in_database", &|d| {
        std::fs::remove_file(mark_of(d)).unwrap();
        let db = sled::Config::new().path(d).open().unwrap();
        db.insert("meta/checked_to", &range.end.to_le_bytes()[..])
            .unwrap();
        db.flush().unwrap();
    });
    assert!(found.is_empty(), "the database's mark was not read");
}

#[test]
fn a_truncated_pack_loses_only_the_surveys_whose_bytes_are_gone() {
    let tmp = tempfile::tempdir().unwrap();
    let pristine = store_dir(&tmp);
    let (a, b, _, range) = store_of_two(&pristine);
    let mid = range.start + (range.end - range.start) / 2;
    for (n, cut) in [range.start, range.start + 3, mid, range.end - 1]
        .into_iter()
        .enumerate()
    {
        let dir = tmp.path().join(format!("cut{n}"));
        copy_dir(&pristine, &dir);
        let pack = dir.join(patchwork::store::pack::PACK_FILE);
        std::fs::OpenOptions::new()
            .write(true)
            .open(&pack)
            .unwrap()
            .set_len(cut)
            .unwrap();
        let o = open_damaged(&dir);
        assert!(
            o.warnings
                .iter()
                .any(|w| w.contains("fewer than were committed")),
            "{:?}",
            o.warnings
        );
        assert_quarantined(&o, &a, &b, &format!("cut at {cut}"));
        // New bytes go past the hole: no location of the lost survey ever holds them.
        let Opened {
            mut store,
            mut terrain,
            ..
        } = o;
        assert!(store.raw_pack().len() >= range.end);
        store.repair().unwrap();
        ingest(&mut store, &mut terrain, &b, "b");
        assert_verified(&store);
    }
    // With everything gone, both surveys are damaged and an empty terrain is served.
    let dir = tmp.path().join("empty");
    copy_dir(&pristine, &dir);
    std::fs::write(dir.join(patchwork::store::pack::PACK_FILE), b"").unwrap();
    let o = open_damaged(&dir);
    assert_eq!(o.store.damaged().len(), 2);
    assert_eq!(o.terrain.surveys().count(), 0);
}

#[test]
fn a_record_that_does_not_decode_is_damage_too() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (a, b, _, _) = store_of_two(&dir);
    {
        let o = open(&dir);
        o.store
            .raw()
            .insert(format!("s/{}", b.id).as_bytes(), &b"\xff\xff\xff"[..])
            .unwrap();
        o.store.raw().flush().unwrap();
    }
    let mut o = open_damaged(&dir);
    assert_eq!(
        o.store.damaged().keys().copied().collect::<Vec<_>>(),
        vec![b.id]
    );
    let roi = bounds_of(&[a.clone(), b.clone()]);
    assert_same(&o.terrain, &terrain_of(std::slice::from_ref(&a)), &roi);
    o.store.repair().unwrap();
    assert_verified(&o.store);
}

#[test]
fn a_version_5_store_keeps_its_failures_with_no_content_known() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (a, _) = pair();
    let mut t = Terrain::new(IndexConfig::default());
    {
        let Opened { mut store, .. } = open(&dir);
        ingest(&mut store, &mut t, &a, "a");
        // A failure as version 5 wrote it: source, error, size, mtime, time recorded.
        let old = (
            "/in/bad.tif".to_string(),
            "not a GeoTIFF".to_string(),
            1234u64,
            1_700_000_000u64,
            1_700_000_100u64,
        );
        let v = bincode::serde::encode_to_vec(&old, bincode::config::standard()).unwrap();
        store.raw().insert("f//in/bad.tif".as_bytes(), v).unwrap();
        store
            .raw()
            .insert("meta/schema".as_bytes(), &5u32.to_le_bytes()[..])
            .unwrap();
        store.raw().flush().unwrap();
    }
    let Opened { store, terrain, .. } = open(&dir);
    assert_eq!(store.migrations_run(), &steps_from(5)[..]);
    assert_eq!(
        store.failures().unwrap(),
        vec![FailedRecord {
            source: "/in/bad.tif".into(),
            error: "not a GeoTIFF".into(),
            size: 1234,
            mtime_unix: 1_700_000_000,
            at_unix: 1_700_000_100,
            content_id: String::new(),
        }]
    );
    assert_same(&terrain, &t, &bounds_of(std::slice::from_ref(&a)));
    assert_verified(&store);
}

#[test]
fn damaged_database_files_are_an_error_that_says_what_to_do_never_a_panic() {
    let tmp = tempfile::tempdir().unwrap();
    let pristine = store_dir(&tmp);
    let (a, _) = pair();
    {
        let Opened { mut store, .. } = open(&pristine);
        let mut t = Terrain::new(IndexConfig::default());
        ingest(&mut store, &mut t, &a, "a");
    }
    // sled writes a snapshot when a handle that wrote closes.
    {
        let db = sled::Config::new().path(&pristine).open().unwrap();
        db.insert("meta/x", "1").unwrap();
        db.remove("meta/x").unwrap();
        db.flush().unwrap();
    }
    let files: Vec<String> = std::fs::read_dir(&pristine)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    // The database file cut short: sled panics inside its recovery at some lengths.
    for (n, part) in [0.5, 0.25, 0.1, 0.75, 0.9].into_iter().enumerate() {
        let dir = tmp.path().join(format!("cut{n}"));
        copy_dir(&pristine, &dir);
        let db = dir.join("db");
        let len = std::fs::metadata(&db).unwrap().len();
        std::fs::OpenOptions::new()
            .write(true)
            .open(&db)
            .unwrap()
            .set_len((len as f64 * part) as u64)
            .unwrap();
        let opened = std::panic::catch_unwind(|| {
            restore::open(
                &dir,
                LAYOUT,
                IndexConfig::default(),
                StoreOptions::default(),
            )
            .map(|_| ())
        });
        match opened.expect("no panic") {
            // sled's log may still hold all that was committed.
            Ok(()) => {}
            Err(e) => {
                let msg = e.to_string();
                assert!(msg.contains("damaged") && msg.contains("backup"), "{msg}");
            }
        }
    }
    // A damaged snapshot: the message names the file to move away, and moving it works.
    let snap = files
        .iter()
        .find(|f| f.starts_with("snap."))
        .unwrap_or_else(|| panic!("{files:?}"));
    let dir = tmp.path().join("snap");
    copy_dir(&pristine, &dir);
    let p = dir.join(snap);
    let mut bytes = std::fs::read(&p).unwrap();
    for b in bytes.iter_mut().skip(8) {
        *b ^= 0xa5;
    }
    std::fs::write(&p, bytes).unwrap();
    let msg = refused(&dir).to_string();
    assert!(msg.contains(snap.as_str()) && msg.contains("move"), "{msg}");
    assert!(!msg.contains("offset None"), "{msg}");
    std::fs::remove_file(&p).unwrap();
    let Opened { store, terrain, .. } = open(&dir);
    assert_same(
        &terrain,
        &terrain_of(std::slice::from_ref(&a)),
        &bounds_of(std::slice::from_ref(&a)),
    );
    assert_verified(&store);
}

/// Verify says how far it has got: every survey record as it is checked, then every active
/// survey as the index is derived again, each count rising to its total.
#[test]
fn verify_says_how_far_it_has_got() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    let (surveys, _) = retired_store(&dir);
    let Opened { store, .. } = open(&dir);
    let seen = std::sync::Mutex::new(Vec::new());
    let report = restore::verify_with(&store, &|step, done, total| {
        seen.lock().unwrap().push((step, done, total))
    })
    .unwrap();
    assert!(report.is_ok(), "{:?}", report.problems);
    let seen = seen.into_inner().unwrap();
    let of = |step: &str| -> Vec<(u64, u64)> {
        seen.iter()
            .filter(|s| s.0 == step)
            .map(|s| (s.1, s.2))
            .collect()
    };
    let records = surveys.len() as u64;
    assert_eq!(
        of("surveys"),
        (0..records).map(|k| (k, records)).collect::<Vec<_>>()
    );
    assert_eq!(of("index"), vec![(0, 1)], "one survey is active");
    // The surveys are checked before the index is derived.
    assert_eq!(seen.last().unwrap().0, "index");
}

#[test]
fn a_version_7_store_measures_its_overlaps_again() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = store_dir(&tmp);
    // A real crop and a blurred copy of it: a pair whose evidence the step drops.
    let g = real_crop("srtm_n44e005_voids_crop.tif");
    let auto = |g| {
        Arc::new(
            Survey::build(
                g,
                patchwork_core::model::accuracy::AccuracySpec::Auto,
                Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
                LAYOUT,
            )
            .unwrap(),
        )
    };
    let (orig, copy) = (
        auto(g.clone()),
        auto(patchwork_core::model::coreg::blurred(&g, 2.0)),
    );
    let mut t = Terrain::new(IndexConfig::default());
    {
        let Opened { mut store, .. } = open(&dir);
        ingest(&mut store, &mut t, &orig, "orig");
        ingest(&mut store, &mut t, &copy, "copy");
        // Back to version 7: overlaps in a format this binary no longer reads.
        let db = store.raw();
        let keys: Vec<sled::IVec> = db.scan_prefix("o/").map(|kv| kv.unwrap().0).collect();
        assert_eq!(keys.len(), 2);
        for k in keys {
            db.insert(k, &b"an overlap of schema 7"[..]).unwrap();
        }
        db.insert(b"meta/schema", &7u32.to_le_bytes()).unwrap();
        db.flush().unwrap();
    }
    let Opened { store, terrain, .. } = open(&dir);
    assert_eq!(store.migrations_run(), &steps_from(7)[..]);
    let pairs: Vec<PairEvidence> = store
        .all_pairs()
        .unwrap()
        .iter()
        .map(|p| (**p).clone())
        .collect();
    let fresh: Vec<PairEvidence> = t.pairs().iter().map(|p| (**p).clone()).collect();
    assert_eq!(pairs, fresh);
    assert_eq!(terrain.index().state(), t.index().state());
    assert!(terrain.blame(orig.id, copy.id).is_some());
    assert_verified(&store);
}

/// A patch in memory keeps only its kernel's place in its level's tiling; the cells stored
/// beside it must be the ones that place gives, and the place must lie in the tiling. A
/// patch list that says otherwise (a kernel one cell short, a place past the end of its row)
/// leaves its survey damaged, as any other damage to it does, and every other survey served.
#[test]
fn a_stored_patch_whose_kernel_is_not_its_place_in_the_tiling_damages_its_survey() {
    let tmp = tempfile::tempdir().unwrap();
    let pristine = store_dir(&tmp);
    let (a, b, _, _) = store_of_two(&pristine);
    type Tamper = fn(&mut form::Patch);
    let tampers: [(&str, Tamper); 3] = [
        ("a kernel a cell short", |p| p.kernel.c1 -= 1),
        ("a place past its row", |p| p.index[0] += 1 << 20),
        ("a place one row down", |p| p.index[1] += 1),
    ];
    for (n, (what, tamper)) in tampers.into_iter().enumerate() {
        let dir = tmp.path().join(format!("tamper{n}"));
        copy_dir(&pristine, &dir);
        {
            let Opened { store, .. } = open(&dir);
            let mut stored = store.load_patches(b.id).unwrap();
            // The last level-0 patch: one row down from it is past its level's tiling.
            let k = stored.patches.iter().rposition(|p| p.level == 0).unwrap();
            tamper(&mut stored.patches[k]);
            let sealed =
                patchwork::store::chunks::seal(&patchwork::store::encode(&stored).unwrap());
            let loc = store.raw_pack().append(&[sealed]).unwrap()[0];
            let end = store.raw_pack().len();
            drop(store);
            let db = sled::open(&dir).unwrap();
            db.insert(patchwork::store::keys::patches(b.id), &loc.to_bytes()[..])
                .unwrap();
            db.insert(patchwork::store::keys::PACK_LEN, &end.to_le_bytes()[..])
                .unwrap();
            db.flush().unwrap();
        }
        let o = open_damaged(&dir);
        assert_quarantined(&o, &a, &b, what);
    }
}
