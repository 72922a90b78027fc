//! The index's memory, counted by the allocator rather than read off the resident set: the
//! heap a store's open holds once it serves, per patch, with the chunk and page caches made
//! too small to matter. The scale bench's figure (resident memory after a restart less an
//! empty daemon's) also counts sled's page cache and the allocator's slack.
//!
//! cargo run --release -p patchwork-bench --example index_memory -- [FILE ...]
//!
//! The files default to the Copernicus N34W119 tile in ../shared/data. With
//! `INDEX_MEMORY_KEEP=DIR` the store is made in DIR and kept (`INDEX_MEMORY_INGEST_ONLY=1`
//! stops there, before any open); `INDEX_MEMORY_OPEN=DIR` then only opens it, and with
//! `INDEX_MEMORY_EXIT=1` too exits as soon as it is open. `INDEX_MEMORY_NODE_CAPACITY=N` makes
//! a store whose quadtree nodes keep N boxes, and `INDEX_MEMORY_CUTS=1` times 400 uniform cuts
//! of a fixed draw on the store opened.

use patchwork_core::index::lod::IndexConfig;
use patchwork_engine::config::Config;
use patchwork_engine::{Engine, Origin};
use std::alloc::{GlobalAlloc, Layout, System};
use std::path::PathBuf;
use std::sync::atomic::{AtomicIsize, Ordering::Relaxed};

/// Bytes allocated and not yet freed, by every thread.
static LIVE: AtomicIsize = AtomicIsize::new(0);

struct Counting;

// SAFETY: every call is passed to the system allocator unchanged; the counter only watches.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(l) };
        if !p.is_null() {
            LIVE.fetch_add(l.size() as isize, Relaxed);
        }
        p
    }

    unsafe fn alloc_zeroed(&self, l: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(l) };
        if !p.is_null() {
            LIVE.fetch_add(l.size() as isize, Relaxed);
        }
        p
    }

    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) };
        LIVE.fetch_sub(l.size() as isize, Relaxed);
    }

    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        let q = unsafe { System.realloc(p, l, new) };
        if !q.is_null() {
            LIVE.fetch_add(new as isize - l.size() as isize, Relaxed);
        }
        q
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Set in the child that opens the store, so that nothing the ingest left behind is freed
/// while the open is counted.
const OPEN: &str = "INDEX_MEMORY_OPEN";

fn config(store: PathBuf, roots: Vec<PathBuf>) -> Config {
    Config {
        data_dir: store,
        ingest_roots: roots,
        // One MiB of decoded chunks and a quarter of it for sled's pages: what is left is the
        // index.
        cache_mb: 1,
        index: IndexConfig {
            // INDEX_MEMORY_NODE_CAPACITY=N makes a store whose quadtree nodes keep N boxes.
            node_capacity: std::env::var("INDEX_MEMORY_NODE_CAPACITY")
                .ok()
                .and_then(|v| v.parse().ok())
                .unwrap_or(IndexConfig::default().node_capacity),
            ..IndexConfig::default()
        },
        ..Config::default()
    }
}

fn main() {
    if let Ok(store) = std::env::var(OPEN) {
        return measure(PathBuf::from(store));
    }
    let files: Vec<PathBuf> = {
        let given: Vec<PathBuf> = std::env::args().skip(1).map(PathBuf::from).collect();
        if given.is_empty() {
            vec!["../shared/data/Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif".into()]
        } else {
            given
        }
    };
    let tmp = tempfile::tempdir().expect("temporary directory");
    // INDEX_MEMORY_KEEP=DIR ingests into DIR and keeps it, for a heap profiler's open of it.
    let store = match std::env::var_os("INDEX_MEMORY_KEEP") {
        Some(dir) => PathBuf::from(dir),
        None => tmp.path().join("store"),
    };
    let roots = files
        .iter()
        .filter_map(|f| f.parent().map(|p| p.to_path_buf()))
        .collect();
    {
        let engine = Engine::open(config(store.clone(), roots)).expect("open the store");
        for f in &files {
            let done = engine.ingest(f, None, Origin::Request).expect("ingest");
            assert!(done.error.is_empty(), "{}: {}", f.display(), done.error);
        }
    }
    // INDEX_MEMORY_INGEST_ONLY=1 leaves the store as the ingest left it, for a profiler's
    // first open of it.
    if std::env::var_os("INDEX_MEMORY_INGEST_ONLY").is_some() {
        return;
    }
    // An empty store's open first: what a daemon holds whatever it serves.
    let me = std::env::current_exe().expect("this program");
    let run = |store: &std::path::Path| -> i64 {
        let out = std::process::Command::new(&me)
            .env(OPEN, store)
            .output()
            .expect("run the open");
        assert!(out.status.success(), "the open failed");
        let text = String::from_utf8_lossy(&out.stdout).to_string();
        print!("{text}");
        text.lines()
            .find_map(|l| l.strip_prefix("held "))
            .and_then(|v| v.trim().parse().ok())
            .expect("the child says what it holds")
    };
    let empty = run(&tmp.path().join("empty"));
    let full = run(&store);
    let patches: usize = std::fs::read_to_string(store.with_file_name("patches"))
        .ok()
        .and_then(|v| v.trim().parse().ok())
        .expect("the child says how many patches");
    println!(
        "the index: {:.1} MiB beyond an empty store's open, {:.0} bytes a patch",
        (full - empty) as f64 / (1 << 20) as f64,
        (full - empty) as f64 / patches.max(1) as f64
    );
}

/// Opens the store at `store` and prints what the open holds.
fn measure(store: PathBuf) {
    let store_dir = store.clone();
    let before = LIVE.load(Relaxed);
    let engine = Engine::open(config(store, Vec::new())).expect("open the store");
    // The open's first start of the database, which its load read through, is let go by
    // sled's own threads, a moment after the open drops it.
    std::thread::sleep(std::time::Duration::from_secs(2));
    let held = LIVE.load(Relaxed) - before;
    println!("held {held}");
    if std::env::var_os("INDEX_MEMORY_EXIT").is_some() {
        std::process::exit(0);
    }
    let terrain = engine.snapshot();
    let catalog = engine.catalog();
    let index = terrain.index();
    let patches = index.len().max(1);
    if index.is_empty() {
        return;
    }
    // Beside the store, for the parent.
    let at = store_dir.with_file_name("patches");
    std::fs::write(at, index.len().to_string()).expect("write the count");
    let samples: usize = terrain
        .surveys()
        .map(|s| s.shapes[0].cols * s.shapes[0].rows)
        .sum();
    println!(
        "{} patches, {} samples a patch; the open holds {:.1} MiB: {:.0} bytes a patch",
        index.len(),
        samples / patches,
        held as f64 / (1 << 20) as f64,
        held as f64 / patches as f64
    );
    let tree = index.tree_stats();
    println!(
        "by size alone: a patch {} B, a quadtree entry {} B ({:.2} stored a patch, {:.3} nodes a patch); \
         a box, made when asked, {} B",
        std::mem::size_of::<patchwork_core::model::patch::Patch>(),
        std::mem::size_of::<patchwork_core::index::quadtree::Entry>(),
        tree.stored as f64 / patches as f64,
        tree.nodes as f64 / patches as f64,
        std::mem::size_of::<patchwork_core::index::lod::PatchBox>(),
    );
    // What the parts hold by their sizes: the surveys' metadata and the edge patches' samples.
    let (mut surveys, mut meta, mut valid, mut accuracy) = (0usize, 0usize, 0usize, 0usize);
    for m in terrain.surveys() {
        surveys += 1;
        meta += std::mem::size_of::<patchwork_core::model::survey::SurveyMeta>()
            + m.shapes.len() * std::mem::size_of::<patchwork_core::model::grid::Shape>()
            + m.patches.len() * std::mem::size_of::<patchwork_core::model::patch::Patch>()
            + m.edge_tiles.len() * 16;
        valid += m.patches.iter().map(|p| p.valid.held() * 16).sum::<usize>();
        accuracy += m.kernel_accuracy.values.len() * 8;
    }
    let (mut edges, mut edge_bytes) = (0usize, 0usize);
    for e in terrain.edges() {
        edges += 1;
        edge_bytes += std::mem::size_of::<patchwork_core::model::edge::EdgePatch>()
            + e.members.len() * 8
            + e.valid.len() * 32
            + e.grid.as_ref().map_or(0, |g| g.heap_bytes());
    }
    let per = |b: usize| b as f64 / surveys.max(1) as f64;
    println!(
        "by sizes, a survey: its metadata and patches {:.0} B, their valid lists {:.0} B, its \
         kernels' ε {:.0} B; {edges} edge patches, their samples and flags {:.0} B a survey",
        per(meta),
        per(valid),
        per(accuracy),
        per(edge_bytes)
    );
    // What the quadtree's shape costs a cut: 400 uniform cuts over squares of a hundredth to a
    // tenth of the data's side, at errors from 0 to 30 m, drawn from a fixed seed so that two
    // builds cut the same; the median and the 90th percentile.
    if let Some(b) = index
        .bounds()
        .filter(|_| std::env::var_os("INDEX_MEMORY_CUTS").is_some())
    {
        let data = terrain
            .surveys()
            .map(|s| s.footprint())
            .reduce(|a, b| a.union(&b));
        let data = data.unwrap_or(b);
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut draw = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut ms, mut got) = (Vec::new(), 0usize);
        for _ in 0..400 {
            let side = data.width().min(data.height()) * (0.01 + 0.09 * draw());
            let x = data.min[0] + (data.width() - side) * draw();
            let y = data.min[1] + (data.height() - side) * draw();
            let e = 30.0 * draw();
            let roi = patchwork_core::geom::Aabb::new(x, y, x + side, y + side);
            let t0 = std::time::Instant::now();
            got += index.uniform(&roi, e).len();
            ms.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        ms.sort_by(f64::total_cmp);
        println!(
            "400 uniform cuts: {:.3} ms (median), {:.3} ms (90th percentile), {} patches each",
            ms[200],
            ms[360],
            got / 400
        );
    }
    // What an edge patch held without its samples costs the first read that needs them:
    // made again from its members' samples, read from the store through cold caches. A copy
    // of the terrain with a cache of its own makes them, so that nothing stays.
    {
        let mut probe = (*terrain).clone();
        probe.set_edge_cache(1 << 20);
        let mut ms: Vec<f64> = probe
            .edges()
            .filter(|e| e.grid.is_none())
            .map(|e| {
                let t0 = std::time::Instant::now();
                probe.edge_grid(e).expect("the members' samples");
                t0.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        if !ms.is_empty() {
            ms.sort_by(f64::total_cmp);
            println!(
                "{} edge patches held without their samples: each made again in {:.2} ms \
                 (median), {:.2} ms (90th percentile)",
                ms.len(),
                ms[ms.len() / 2],
                ms[ms.len() * 9 / 10]
            );
        }
    }
    // What the terrain alone holds: the engine (its database, caches and tasks) dropped, the
    // published terrain kept.
    drop(engine);
    let with_catalog = LIVE.load(Relaxed) - before;
    drop(catalog);
    let terrain_only = LIVE.load(Relaxed) - before;
    println!(
        "the terrain alone: {:.0} bytes a patch; the catalog of records: {:.0}; the engine and \
         its database: {:.0}",
        terrain_only as f64 / patches as f64,
        (with_catalog - terrain_only) as f64 / patches as f64,
        (held - with_catalog) as f64 / patches as f64
    );
}
