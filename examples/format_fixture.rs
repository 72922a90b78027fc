//! Writes a small store of the current schema version for the format tests
//! (`tests/engine/format.rs`), which open it, decode every record in it and encode each back,
//! so that a change to what the store writes without a migration fails them. Run it once
//! for each new schema version, into a folder of its own, and commit the result:
//!
//! cargo run --example format_fixture -- tests/data/stores/v<N>
//!
//! The store holds every kind of record: the overlapping Copernicus and NASADEM crops (the
//! pair's evidence), an SRTM crop of Mont Ventoux with voids (edge patches) whose accuracy is
//! estimated (its kernels' accuracies), a file that is not a DEM (a failure), and a survey
//! retired by hand while its file stays in the inbox (its content id, pinned). From version
//! 9 the Copernicus crop has a sidecar saying where it came from (its record's `about`).
//! From version 11 each pair carries the regions where the ground changed between its surveys.

use patchwork::config::Config;
use patchwork::engine::{Engine, Origin};
use std::path::{Path, PathBuf};

fn main() {
    let out = PathBuf::from(
        std::env::args()
            .nth(1)
            .expect("usage: format_fixture OUT_DIR (tests/data/stores/v<N>)"),
    );
    assert!(!out.exists(), "{} exists already", out.display());
    let crops = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    let tmp = tempfile::tempdir().expect("a temporary folder");
    let inbox = tmp.path().join("in");
    std::fs::create_dir(&inbox).expect("inbox");
    let bad = inbox.join("not_a_dem.tif");
    std::fs::write(&bad, b"this is not a GeoTIFF").expect("bad file");
    let data = tmp.path().join("store");
    // With a sidecar that says where it came from.
    let copernicus = inbox.join("copernicus_n34w119_crop.tif");
    std::fs::copy(crops.join("copernicus_n34w119_crop.tif"), &copernicus).expect("copied");
    std::fs::write(
        inbox.join("copernicus_n34w119_crop.tif.toml"),
        "title = \"Copernicus DEM GLO-30, N34 W119\"\n\
         license = \"Copernicus DEM licence\"\n\
         attribution = \"© DLR e.V. 2010-2014 and © Airbus Defence and Space GmbH 2014-2018 \
         provided under COPERNICUS by the European Union and ESA\"\n\
         acquired = \"2011-01/2015-01\"\n",
    )
    .expect("sidecar");
    // Retired by hand while its file stays in the inbox: pinned there.
    let pinned = inbox.join("srtm_n44e005_big_hole_crop.tif");
    std::fs::copy(crops.join("srtm_n44e005_big_hole_crop.tif"), &pinned).expect("copied");
    let cfg = Config {
        data_dir: data.clone(),
        inbox: vec![inbox.clone()],
        ingest_roots: vec![crops.clone(), inbox.clone()],
        crs: Some("EPSG:4326".into()),
        ..Config::default()
    };
    {
        let e = Engine::open(cfg).expect("engine");
        for (file, accuracy) in [
            (crops.join("srtm_n44e005_voids_crop.tif"), None),
            (copernicus.clone(), Some(3.0)),
            (crops.join("nasadem_n34w119_crop.tif"), Some(8.0)),
            (pinned.clone(), Some(5.0)),
        ] {
            let done = e.ingest(&file, accuracy, Origin::Inbox).expect("ingested");
            assert!(done.error.is_empty(), "{file:?}: {}", done.error);
        }
        let failed = e.ingest(&bad, None, Origin::Inbox).expect("tried");
        assert!(!failed.error.is_empty(), "a text file ingested");
        e.retire(&patchwork::paths::source_name(&pinned))
            .expect("retired by hand");
        let report = e.verify().expect("verified");
        println!("{report:?}");
    }
    copy_dir(&data, &out);
    println!("wrote {}", out.display());
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("output folder");
    for entry in std::fs::read_dir(from).expect("store folder") {
        let entry = entry.expect("entry");
        let target = to.join(entry.file_name());
        if entry.file_type().expect("type").is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), &target).expect("copied");
        }
    }
}
