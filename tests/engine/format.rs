//! The store's format, pinned by committed stores (`tests/data/stores/v<N>`, written by
//! `cargo run --example format_fixture`): one of every schema version from 8, the first
//! committed, on. Each must open (migrated to the current version where it is older), verify
//! clean and give back its surveys' samples as their files hold them; and every record of
//! the current version's must decode into its stored form (`patchwork_store::form`) and encode
//! back to its very bytes. A change to what the store writes that comes without a migration
//! and a new committed store fails here.

use crate::common;

use common::copy_dir;
use common::daemon::crop;
use patchwork::store::pack::{Loc, PackFile, PACK_FILE};
use patchwork::store::{
    chunks, decode, decode_state, encode, encode_state, form, keys, FailedRecord, Store,
    StoreOptions, StoredPatches, SurveyRecord, SCHEMA_VERSION,
};
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::ids::SurveyId;
use patchwork_core::model::patch::PatchLayout;
use patchwork_read::{read_raster, ReadLimits};
use serde::de::DeserializeOwned;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

fn stores() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/stores")
}

/// The schema versions with a committed store, oldest first.
fn committed() -> Vec<u32> {
    let mut v: Vec<u32> = std::fs::read_dir(stores())
        .expect("tests/data/stores")
        .filter_map(|e| {
            e.ok()?
                .file_name()
                .to_str()?
                .strip_prefix('v')?
                .parse()
                .ok()
        })
        .collect();
    v.sort();
    v
}

/// A copy of the committed store of version `v` to open: opening may migrate and writes.
fn copy_of(v: u32) -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("store");
    copy_dir(&stores().join(format!("v{v}")), &dir);
    (tmp, dir)
}

#[test]
fn the_current_schema_has_a_committed_store() {
    assert!(
        committed().contains(&SCHEMA_VERSION),
        "schema {SCHEMA_VERSION} has no committed store: write one with `cargo run --example \
         format_fixture -- tests/data/stores/v{SCHEMA_VERSION}` and commit it"
    );
}

/// Decodes `bytes` as a `T`, encodes it back and checks the bytes are the same.
fn same_bytes<T: Serialize + DeserializeOwned>(bytes: &[u8], what: &str) -> T {
    let v: T = decode(bytes, what).unwrap_or_else(|e| panic!("{what} no longer decodes: {e}"));
    assert_eq!(
        encode(&v).unwrap(),
        bytes,
        "{what} encodes differently now: a format change needs a migration"
    );
    v
}

#[test]
fn every_record_of_the_current_schema_decodes_and_encodes_back_to_its_bytes() {
    let (_tmp, dir) = copy_of(SCHEMA_VERSION);
    let db = sled::open(&dir).unwrap();
    let tree: &sled::Tree = &db;
    let u64_at =
        |k: &[u8]| u64::from_le_bytes(tree.get(k).unwrap().unwrap()[..8].try_into().unwrap());
    let pack = PackFile::open(&dir, u64_at(keys::PACK_LEN)).unwrap();
    assert!(dir.join(PACK_FILE).exists());
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    for kv in tree.iter() {
        let (k, v) = kv.unwrap();
        let key = String::from_utf8_lossy(&k).into_owned();
        let what = format!("the record at {key}");
        let kind = match key.split_once('/') {
            Some(("meta", name)) => format!("meta/{name}"),
            Some((prefix, _)) => format!("{prefix}/"),
            None => panic!("a key without a prefix: {key}"),
        };
        *seen.entry(kind.clone()).or_default() += 1;
        match kind.as_str() {
            "meta/schema" => {
                assert_eq!(
                    u32::from_le_bytes(v[..].try_into().unwrap()),
                    SCHEMA_VERSION
                )
            }
            "meta/layout" => {
                same_bytes::<form::Layout>(&v, &what);
            }
            "meta/index" => {
                same_bytes::<form::Index>(&v, &what);
            }
            "meta/crs" => {
                patchwork_core::crs::Crs::parse(std::str::from_utf8(&v).unwrap()).unwrap();
            }
            "meta/mipmap" | "meta/patches" | "meta/contradicted" | "meta/vertical_crs"
            | "meta/blend" => {
                assert!(std::str::from_utf8(&v).is_ok(), "{what}: not UTF-8");
            }
            "meta/pack_len" | "meta/checked_to" => assert_eq!(v.len(), 8),
            "meta/quarantined" => {
                same_bytes::<Vec<u64>>(&v, &what);
            }
            "s/" => {
                let r: form::Survey = same_bytes(&v, &what);
                assert_eq!(key, format!("s/{}", SurveyId(r.id)));
                // The record the daemon works with is made of it, and encodes as it.
                let record = SurveyRecord::try_from(r).unwrap();
                assert_eq!(encode(&record).unwrap(), v.to_vec(), "{what}");
            }
            "a/" => {
                same_bytes::<form::Accuracies>(&v, &what);
            }
            "e/" => {
                same_bytes::<form::Edge>(&v, &what);
            }
            "o/" => {
                same_bytes::<form::Pair>(&v, &what);
            }
            "f/" => {
                same_bytes::<FailedRecord>(&v, &what);
            }
            "r/" => assert!(std::str::from_utf8(&v).is_ok(), "{what}: not a hex id"),
            "b/" => {
                assert_eq!(v.len() % 17, 0, "{what}: not whole boxes");
                for b in v.chunks_exact(17) {
                    let s = decode_state(&b[8..], &what).unwrap();
                    assert_eq!(encode_state(&s), b[8..]);
                }
            }
            "c/" => {
                let loc = Loc::from_bytes(&v).unwrap_or_else(|| panic!("{what}: no location"));
                assert_eq!(loc.to_bytes(), v[..]);
            }
            "p/" => {
                let sealed = chunks::read_packed(tree, &pack, &k).unwrap();
                let bytes = chunks::unseal(&sealed, 1 << 30).unwrap();
                let p: StoredPatches = form::Patches::into(same_bytes(&bytes, &what));
                assert!(!p.patches.is_empty(), "{what}: no patches");
            }
            other => panic!(
                "{what}: a kind of record ({other}) this test does not know; pin its encoding here"
            ),
        }
    }
    println!("records of schema {SCHEMA_VERSION}: {seen:?}");
    // The committed store holds one of each kind the store writes outside an object store.
    for kind in [
        "s/",
        "p/",
        "c/",
        "a/",
        "e/",
        "o/",
        "f/",
        "b/",
        "r/",
        "meta/layout",
        "meta/index",
    ] {
        assert!(
            seen.contains_key(kind),
            "the committed store holds no {kind} record"
        );
    }
}

/// Every committed store opens as the current code opens it (migrating an older one), verifies
/// clean, and gives back its surveys' level-0 samples as their files hold them.
#[test]
fn every_committed_store_opens_verifies_and_gives_back_its_samples() {
    for v in committed() {
        let (_tmp, dir) = copy_of(v);
        let loaded = Store::open_with(
            &dir,
            PatchLayout::default(),
            IndexConfig::default(),
            StoreOptions::default(),
        )
        .unwrap_or_else(|e| panic!("the store of schema {v} no longer opens: {e}"));
        let ran = loaded.store.migrations_run().to_vec();
        let want: Vec<(u32, u32)> = (v..SCHEMA_VERSION).map(|n| (n, n + 1)).collect();
        assert_eq!(ran, want, "schema {v}: the migrations run");
        // Each survey's file, from its record as the migrations left it.
        let sources: BTreeMap<SurveyId, String> = loaded
            .store
            .raw()
            .scan_prefix(keys::SURVEY_PREFIX)
            .map(|kv| {
                let r: SurveyRecord = decode(&kv.unwrap().1, "a survey record").unwrap();
                (r.id, r.source)
            })
            .collect();
        let surveys = loaded.store.whole_surveys().unwrap();
        assert_eq!(surveys.len(), 3, "schema {v}: active surveys");
        for s in &surveys {
            let file = crop(
                Path::new(&sources[&s.meta.id])
                    .file_name()
                    .unwrap()
                    .to_str()
                    .unwrap(),
            );
            let r = read_raster(&file, &ReadLimits::default()).unwrap();
            let grid = r.into_grid().unwrap();
            let got = &s.levels[0];
            assert_eq!(
                (got.cols, got.rows),
                (grid.cols, grid.rows),
                "schema {v}: {file:?}"
            );
            let same = got
                .samples
                .iter()
                .zip(&grid.samples)
                .all(|(a, b)| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()));
            assert!(
                same,
                "schema {v}: the samples of {file:?} differ from the file's"
            );
        }
        let opened = patchwork::restore::restore(loaded).unwrap();
        assert!(
            opened.warnings.is_empty(),
            "schema {v}: {:?}",
            opened.warnings
        );
        let report = patchwork::restore::verify(&opened.store).unwrap();
        assert!(
            report.problems.is_empty(),
            "schema {v}: {:?}",
            report.problems
        );
        println!("schema {v}: {report:?}");
    }
}
