//! Times the store on the full Copernicus + NASADEM N34W119 pair: commit of each survey, reopen,
//! verify, retire and compaction.
//!
//! cargo run --release -p patchwork-bench --example store_timing -- [DATA_DIR] [STORE_DIR]
//!
//! DATA_DIR defaults to ../shared/data; STORE_DIR to a temporary directory, removed at the end.

use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::survey::Survey;
use patchwork_core::terrain::Terrain;
use patchwork_engine::restore::{self, Opened};
use patchwork_read::file_content_id;
use patchwork_read::{read_raster, ReadLimits};
use patchwork_store::{
    Change, IngestTimings, Insertion, Retirement, Store, StoreOptions, SurveyRecord,
};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn mib(b: u64) -> f64 {
    b as f64 / (1 << 20) as f64
}

fn ingest(store: &mut Store, terrain: &mut Terrain, path: &Path) -> Arc<Survey> {
    let t = Instant::now();
    let grid = read_raster(path, &ReadLimits::default())
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .into_grid()
        .unwrap();
    let read_ms = ms(t);
    let t = Instant::now();
    let s = Arc::new(
        Survey::build(
            grid,
            0.0,
            Some(patchwork_core::crs::Crs::epsg(4326).unwrap()),
            store.layout(),
        )
        .unwrap(),
    );
    let build_ms = ms(t);
    let t = Instant::now();
    let mut next = terrain.clone();
    let change = next.insert(s.clone());
    let index_ms = ms(t);
    let content = file_content_id(path, None).unwrap();
    let rec = SurveyRecord::new(
        &s,
        path.display().to_string(),
        content,
        patchwork_core::model::accuracy::AccuracySource::Flag,
        IngestTimings {
            read_ms,
            build_ms,
            index_ms,
            commit_ms: 0.0,
        },
    );
    let t = Instant::now();
    let packed = store.pack_survey(&s).unwrap();
    store
        .commit(Change {
            insert: Some(Insertion {
                survey: &s,
                record: &rec,
                change: &change,
                pairs: &next.pairs_of(s.id),
                packed,
            }),
            edges: &next.edges_of(&[&change]),
            ..Change::default()
        })
        .unwrap();
    let commit_ms = ms(t);
    *terrain = next;
    println!(
        "{}: {}×{}, {} levels, {} patches, {} tops moved; read {read_ms:.0} ms, build \
         {build_ms:.0} ms, index {index_ms:.0} ms, commit {commit_ms:.0} ms",
        path.file_name().unwrap().to_string_lossy(),
        s.levels[0].cols,
        s.levels[0].rows,
        s.levels.len(),
        s.patches.len(),
        change.moved.len(),
    );
    s
}

fn main() {
    let mut args = std::env::args_os().skip(1);
    let data = args
        .next()
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("../shared/data"));
    let tmp = tempfile_dir();
    let dir = args.next().map(PathBuf::from).unwrap_or(tmp.join("store"));
    let (layout, cfg) = (PatchLayout::default(), IndexConfig::default());

    let Opened { mut store, .. } =
        restore::open(&dir, layout, cfg, StoreOptions::default()).unwrap();
    let mut terrain = Terrain::new(cfg);
    let cop = ingest(
        &mut store,
        &mut terrain,
        &data.join("Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif"),
    );
    ingest(
        &mut store,
        &mut terrain,
        &data.join("NASADEM_HGT_n34w119.tif"),
    );
    let input: u64 = [
        "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif",
        "NASADEM_HGT_n34w119.tif",
    ]
    .iter()
    .map(|f| std::fs::metadata(data.join(f)).unwrap().len())
    .sum();
    let pack = store.raw_pack().len();
    println!(
        "store: {:.1} MiB on disk ({:.2}× the input files' {:.1} MiB): chunk pack {:.1} MiB, \
         database {:.1} MiB",
        mib(store.disk_bytes()),
        store.disk_bytes() as f64 / input as f64,
        mib(input),
        mib(pack),
        mib(store.disk_bytes() - pack),
    );
    let live = terrain.index().state().into_keys().collect();
    let (Opened { store, .. }, rep) = restore::compact(store, &live).unwrap();
    println!(
        "compact with nothing retired: {:.1} → {:.1} MiB ({:.2}× the input)",
        mib(rep.bytes_before),
        mib(rep.bytes_after),
        rep.bytes_after as f64 / input as f64
    );
    drop(store);

    let t = Instant::now();
    let Opened {
        mut store,
        terrain: back,
        ..
    } = restore::open(&dir, layout, cfg, StoreOptions::default()).unwrap();
    println!(
        "reopen: {:.0} ms, {} boxes, same index: {}",
        ms(t),
        back.index().len(),
        back.index().state() == terrain.index().state()
    );

    let t = Instant::now();
    let rep = restore::verify(&store).unwrap();
    println!(
        "verify: {:.0} ms, {} problems{}",
        ms(t),
        rep.problems.len(),
        rep.problems
            .first()
            .map(|p| format!(" (first: {p})"))
            .unwrap_or_default()
    );

    let t = Instant::now();
    let mut next = back.clone();
    let change = next.retire(cop.id).unwrap();
    let index_ms = ms(t);
    let t = Instant::now();
    store
        .commit(Change {
            retire: Some(Retirement {
                id: cop.id,
                change: &change,
                pin: false,
            }),
            edges: &next.edges_of(&[&change]),
            ..Change::default()
        })
        .unwrap();
    println!(
        "retire Copernicus: index {index_ms:.0} ms, commit {:.0} ms, {} tops moved",
        ms(t),
        change.moved.len()
    );

    let t = Instant::now();
    let live = terrain.index().state().into_keys().collect();
    let (Opened { store, .. }, rep) = restore::compact(store, &live).unwrap();
    println!(
        "compact: {:.0} ms (reopen included), {:.1} → {:.1} MiB",
        ms(t),
        mib(rep.bytes_before),
        mib(rep.bytes_after)
    );
    drop(store);
    let _ = std::fs::remove_dir_all(&tmp);
}

fn tempfile_dir() -> PathBuf {
    let d = std::env::temp_dir().join(format!("patchwork-store-timing-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}
