//! The engine behind the server and the CLI: one store, one published state, one writer.
//!
//! Readers take the published state, the terrain and the catalog of records beside it, and
//! never touch the store or wait for a writer. The writer owns the store: it computes the next
//! terrain on a copy, commits the change in one batch, and only then publishes the copy with
//! the catalog read back from the store, so readers see the old state or the new one, never
//! half of a change, and a failed commit leaves both as they were.
//!
//! A write that would not fit on the disk is refused before sled sees it (see
//! [`patchwork_store::space`]). Should sled fail all the same (an I/O error, or a disk another
//! process filled in the meantime), its handle is unusable from then on, so the engine stops
//! writing, says why, and keeps serving reads from what it has published.

pub mod config;
pub mod geoids;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod ingest;
pub mod paths;
pub mod request;
pub mod restore;
pub mod watch;

mod error;
mod follow;
mod listing;
mod read;
mod route;
pub mod sources;
mod write;

pub use crate::ingest::Phase;
pub use error::{EngineError, HeightsError, Reason, TooLarge};
pub use follow::{rounds, Replication};
pub use listing::{
    conflicts_of, ChangeRegion, Conflict, Distrusted, Footprint, Held, Later, Placed, Progress,
    Stats, SurveyListing,
};
pub use patchwork_core::resample::Backend;
pub use patchwork_read::REFUSED_PATH;
pub use read::{Bands, Cut, Frame, MeshSpec, MeshTile, Sampled, TileHead, MAX_MESH_SIZE};
pub use request::{
    BadRequest, Camera, Ctx, Heights, Made, Metres, Points, Region, SampleRequest, TileRequest,
    TileSize,
};
pub use route::Used;
pub use write::{Event, Ingested, Origin, Outcome};

use crate::config::{BackendKind, Config, Storage};
use crate::geoids::Geoids;
use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::{Crs, Reprojection};
use patchwork_core::geom::Aabb;
use patchwork_core::model::ids::SurveyId;
use patchwork_core::sync::{lock, read, write};
use patchwork_core::terrain::Terrain;
use patchwork_store::objects::Objects;
use patchwork_store::ChunkBackend;
use patchwork_store::{
    now_unix, Catalog, ChunkReader, DiskSpace, FailedRecord, SpaceGuard, Store, StoreOptions,
    SurveyRecord, SystemDisk,
};
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock, RwLock};
use tokio::sync::broadcast;

/// Lets the allocator reuse freed buffers of up to 512 MiB instead of handing each back to the
/// system at once. An ingest allocates a few raster-sized buffers (52 MB for a 3600² tile) and
/// frees them within a second; by default glibc maps each afresh, and the kernel's faulting
/// and zeroing of those pages cost about a tenth of the CPU time of a batch of ingests (the
/// scale bench, docs/BENCHMARKS.md). Freed pages still go back after each batch (the engine
/// trims the heap once no ingest is left running); one ingest peaks some 12% higher.
///
/// On jemalloc, it also starts rayon's pool, whose workers alone keep a cache of the blocks
/// they free (see [`malloc_conf`]).
///
/// Process-wide, so it is the program's to set: `main` calls it first thing, before any
/// thread starts.
pub fn tune_allocator() {
    #[cfg(feature = "jemalloc")]
    {
        // Fails only where the pool was started already, whose workers then go without the
        // cache: a few per cent slower at most, no less right.
        let _ = workers().build_global();
    }
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets a parameter of the allocator, which serialises it with
    // allocations; called from main before any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 512 << 20);
        // Nor is the free space at the top of a thread's heap handed back after every
        // request: a 256² web tile frees a few MB, and giving them back (then faulting them in
        // again, with a TLB shootdown across the cores each time) took 7 of its 12 ms. The
        // engine still trims after its large work (`malloc_trim`).
        libc::mallopt(libc::M_TRIM_THRESHOLD, 256 << 20);
    }
}

/// The allocator the daemon and the bench run on: jemalloc, chosen by measurement
/// (docs/SCALE.md, "The allocator"). glibc's arenas kept, after an open, the pages the open's
/// parallel reads left partly in use: the Copernicus and NASADEM pair's open held twice the
/// memory its structures need. A library cannot set the global allocator (the tests and
/// examples that count allocations set their own), so each program names it:
/// `#[global_allocator] static A: Jemalloc = Jemalloc;`.
#[cfg(feature = "jemalloc")]
pub use tikv_jemallocator::Jemalloc;

/// jemalloc's settings, which it reads at its first allocation, by this symbol's name: a
/// background thread gives back pages a second after they were last freed (not ten), and
/// straight to the system rather than marked free first (pages the resident set still counts
/// until the kernel wants them). A second keeps the buffers of one request or one ingest for the
/// next, whose faults would cost more than the pages (see [`tune_allocator`]). Nothing
/// reads it where jemalloc is not the program's allocator.
///
/// No thread keeps a cache of the small blocks it freed (`tcache:false`) but rayon's workers,
/// which do the heavy work and which the engine flushes after an open or an ingest (see
/// [`release_free_memory`]). A cache is flushed only by its own thread, and a thread that
/// goes idle never does: sled's seven I/O threads, the object store's runtime and the
/// server's threads each held theirs, whose blocks kept the slabs around them in use. A
/// replica's first start of 10,000 surveys held 5.9–6.2 kB a survey with every thread
/// caching, 4.0–4.2 kB without (docs/SCALE.md, "The allocator").
#[cfg(feature = "jemalloc")]
#[allow(non_upper_case_globals)]
#[export_name = "_rjem_malloc_conf"]
pub static malloc_conf: &u8 =
    &b"background_thread:true,dirty_decay_ms:1000,muzzy_decay_ms:0,tcache:false\0"[0];

/// Rayon's pool as the programs start it: its workers keep a thread cache.
#[cfg(feature = "jemalloc")]
fn workers() -> rayon::ThreadPoolBuilder {
    rayon::ThreadPoolBuilder::new().start_handler(|_| keep_thread_cache())
}

/// Gives the calling thread a cache of the small blocks it frees (see [`malloc_conf`]).
#[cfg(feature = "jemalloc")]
fn keep_thread_cache() {
    let mut on = true;
    // SAFETY: "thread.tcache.enabled" takes a bool, given by pointer with its size, and
    // writes nothing back through the null old-value pointers.
    unsafe {
        tikv_jemalloc_sys::mallctl(
            c"thread.tcache.enabled".as_ptr(),
            std::ptr::null_mut(),
            std::ptr::null_mut(),
            (&raw mut on).cast(),
            std::mem::size_of::<bool>(),
        );
    }
}

/// What readers see: a terrain and the catalog of the same commit.
struct Published {
    terrain: Arc<Terrain>,
    catalog: Arc<Catalog>,
}

/// One store, the terrain and catalog published from it, and its one writer.
pub struct Engine {
    cfg: Config,
    published: RwLock<Published>,
    /// The writer owns the store: every write, and verification, holds it. `None` only when
    /// a compaction could not reopen the store.
    writer: Mutex<Option<Store>>,
    /// Set once the store failed under a write: sled cannot recover its handle.
    broken: OnceLock<String>,
    /// Ingests under way, at most `limits.ingest_parallel`: an ingest takes about five times
    /// its raster in memory, and `limits.max_ingest_mb` bounds one raster, not many at once.
    ingest_slots: (Mutex<u64>, std::sync::Condvar),
    /// The ingests under way, oldest first, for progress displays.
    progress: Mutex<Vec<Progress>>,
    /// The store's directory and space rules, for `stats` without the writer.
    dir: PathBuf,
    guard: SpaceGuard,
    events: broadcast::Sender<Event>,
    /// The GPU resampler, when the daemon opened one; dropped if the device is lost.
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    gpu: route::Device,
    /// The store's chunk reader, for cache figures without the writer.
    reader: RwLock<Arc<ChunkReader>>,
    /// The geoid grids the config names, read once each when a conversion needs them.
    geoids: Arc<Geoids>,
    /// The maps from the CRSs requests have named to the store's.
    request_crs: Mutex<HashMap<Crs, Arc<Reprojection>>>,
    /// Where the store stands in replication (see [`follow`]).
    replication: RwLock<Replication>,
    /// Inbox files the watcher holds back, and why, by source.
    held: Mutex<std::collections::BTreeMap<String, Held>>,
    /// The verification under way, for `stats`.
    verifying: Mutex<Option<listing::Verifying>>,
    /// Passes the inbox watcher has finished over its folders: a client that changed a
    /// folder knows the daemon has seen the change once two more have finished.
    inbox_passes: std::sync::atomic::AtomicU64,
    /// A replica of one region: the part of the store's plane it holds and answers.
    region: Option<Aabb>,
}

impl Engine {
    /// Opens the store of `cfg.data_dir` (making it if there is none) and publishes its terrain;
    /// refuses a store whose CRSs differ from the ones the config sets.
    pub fn open(cfg: Config) -> Result<Engine, EngineError> {
        Self::open_on(cfg, Arc::new(SystemDisk))
    }

    /// [`Engine::open`] with free space measured by `disk`.
    pub fn open_on(cfg: Config, disk: Arc<dyn DiskSpace>) -> Result<Engine, EngineError> {
        let guard = SpaceGuard {
            disk,
            min_free: cfg.storage.min_free_mb << 20,
            reserve: cfg.storage.reserve_mb << 20,
        };
        let region = cfg.storage.region_box().map_err(|e| EngineError::Storage {
            what: "region".into(),
            source: Box::new(e),
        })?;
        let opened = restore::open_within(
            &cfg.data_dir,
            cfg.patches.layout(),
            cfg.index,
            store_options(&cfg, &guard)?,
            region.as_ref(),
        )?;
        for w in &opened.warnings {
            tracing::warn!(warning = %w, "store opened with a problem; `patchwork verify` tells more");
        }
        if let (Some(want), Some(have)) = (cfg.crs_def(), opened.store.crs()) {
            if want != have {
                return Err(EngineError::ConfigMismatch {
                    key: "crs",
                    config: want.label(),
                    store: have.label(),
                    dir: cfg.data_dir.clone(),
                });
            }
        }
        if let (Some(want), Some(have)) = (cfg.vertical_crs(), opened.store.vertical_crs()) {
            if !want.same_reference(&have) {
                return Err(EngineError::ConfigMismatch {
                    key: "vertical.crs",
                    config: want.label(),
                    store: have.label(),
                    dir: cfg.data_dir.clone(),
                });
            }
        }
        let mut opened = opened;
        if opened.terrain.crs().is_none() {
            // An empty store takes the config's CRS, else EPSG:4326: never its first survey's,
            // which would make the store's plane (and the web pyramid's root tiles) depend on
            // which file finished first. A store of surveys that name no CRS keeps none.
            if let Some(c) = cfg.crs_def() {
                opened.terrain.set_crs(c);
            } else if opened.terrain.surveys().next().is_none() {
                opened.terrain.set_crs(Crs::wgs84());
            }
        }
        if let Err(e) = opened.store.writable() {
            tracing::warn!(reason = %e, "serving read-only: writes resume once the disk has room");
        }
        let catalog = opened.store.catalog()?;
        let replication = Replication {
            commit: opened.store.commit_seq(),
            following: opened.store.following(),
        };
        let geoids = Arc::new(Geoids::new(&cfg.vertical.geoids, cfg.vertical.proj_data));
        geoids.load_all().map_err(EngineError::GeoidGrid)?;
        // Cesium and GPS take heights above the ellipsoid: a store that cannot give them says
        // so now, rather than at the first tile.
        let vertical = cfg.vertical_crs().or_else(|| catalog.vertical.clone());
        match &vertical {
            Some(v) if !geoids.has(v) => {
                let files = geoids::known_files(v);
                tracing::warn!(
                    vertical = %v.label(),
                    missing = if files.is_empty() { "a grid" } else { files[0] },
                    "no geoid grid for the store's heights: quantized-mesh tiles carry them \
                     as they are, not above the ellipsoid, with a Warning header; name one \
                     in [vertical.geoids] \"{}\"{}",
                    v.key(),
                    if files.is_empty() { "" } else { " or install proj-data" }
                );
            }
            Some(v) => {
                if let Some(p) = geoids.path(v) {
                    tracing::info!(vertical = %v.label(), grid = %p.display(), "geoid grid");
                }
            }
            None => {}
        }
        release_all_free_memory();
        let (events, _) = broadcast::channel(1024);
        Ok(Engine {
            progress: Mutex::new(Vec::new()),
            reader: RwLock::new(opened.store.reader()),
            dir: opened.store.path().to_path_buf(),
            guard,
            published: RwLock::new(Published {
                terrain: Arc::new(opened.terrain),
                catalog: Arc::new(catalog),
            }),
            writer: Mutex::new(Some(opened.store)),
            broken: OnceLock::new(),
            ingest_slots: (Mutex::new(0), std::sync::Condvar::new()),
            geoids,
            request_crs: Mutex::new(HashMap::new()),
            replication: RwLock::new(replication),
            held: Mutex::new(Default::default()),
            verifying: Mutex::new(None),
            inbox_passes: Default::default(),
            region,
            cfg,
            events,
            gpu: route::Device::default(),
        })
    }

    /// The configuration the engine was opened with.
    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// The current terrain; cheap, and stable for as long as the caller holds it.
    pub fn snapshot(&self) -> Arc<Terrain> {
        read(&self.published).terrain.clone()
    }

    /// The records, failures, overlaps and pins of the current terrain.
    pub fn catalog(&self) -> Arc<Catalog> {
        read(&self.published).catalog.clone()
    }

    /// The terrain and its catalog, of one and the same commit.
    pub fn published(&self) -> (Arc<Terrain>, Arc<Catalog>) {
        let p = read(&self.published);
        (p.terrain.clone(), p.catalog.clone())
    }

    /// A receiver of every event from now on: ingests, failures, retirements. A receiver that falls
    /// more than 1024 behind loses the oldest.
    pub fn subscribe(&self) -> broadcast::Receiver<Event> {
        self.events.subscribe()
    }

    fn set_phase(&self, source: &str, phase: Phase) {
        let mut all = lock(&self.progress);
        if let Some(p) = all.iter_mut().find(|p| p.source == source) {
            p.phase = phase;
        }
    }

    /// The oldest ingest under way, if any.
    pub fn progress(&self) -> Option<Progress> {
        lock(&self.progress).first().cloned()
    }

    /// How many files may be ingested at once.
    pub fn ingest_parallel(&self) -> usize {
        self.cfg.limits.ingest_parallel as usize
    }

    fn publish(&self, terrain: Terrain, catalog: Catalog) {
        *write(&self.published) = Published {
            terrain: Arc::new(terrain),
            catalog: Arc::new(catalog),
        };
    }

    fn emit(
        &self,
        kind: Outcome,
        survey: Option<SurveyId>,
        source: &str,
        error: &str,
        conflicts: Vec<Conflict>,
        area: Option<patchwork_core::geom::Aabb>,
    ) {
        // Nobody listening is fine.
        let _ = self.events.send(Event {
            kind,
            survey,
            source: source.into(),
            error: error.into(),
            at_unix: now_unix(),
            conflicts,
            area,
        });
    }

    /// The store's horizontal CRS: the config's, else EPSG:4326 (or, for a store made before
    /// that default, the one it took from its first survey).
    pub fn crs(&self) -> Option<Crs> {
        self.cfg.crs_def().or_else(|| self.catalog().crs.clone())
    }

    /// The store's vertical CRS, once it has one.
    pub fn vertical_crs(&self) -> Option<VerticalCrs> {
        self.cfg
            .vertical_crs()
            .or_else(|| self.catalog().vertical.clone())
    }

    /// The folders files may be ingested from, as they resolve now: a folder that appears
    /// later (a share mounted late) counts from then on.
    fn roots(&self) -> Vec<PathBuf> {
        self.cfg
            .inbox
            .iter()
            .chain(&self.cfg.ingest_roots)
            .filter_map(|d| d.canonicalize().ok())
            .collect()
    }

    /// Every survey record and the failed files.
    pub fn records(&self) -> (Vec<SurveyRecord>, Vec<FailedRecord>) {
        let c = self.catalog();
        (
            c.records.values().map(|r| (**r).clone()).collect(),
            c.failures.clone(),
        )
    }

    /// The terrain, and every survey record, the failed files, and each active survey's
    /// conflicts, all of one commit.
    pub fn surveys(&self) -> (Arc<Terrain>, SurveyListing) {
        let (t, c) = self.published();
        let mut conflicts = HashMap::new();
        for r in c.active() {
            let mine = conflicts_of(&t, r.id);
            if !mine.is_empty() {
                conflicts.insert(r.id, mine);
            }
        }
        let listing = SurveyListing {
            records: c.records.values().map(|r| (**r).clone()).collect(),
            failures: c.failures.clone(),
            damaged: c.damaged.clone(),
            conflicts,
            held: lock(&self.held).clone(),
        };
        (t, listing)
    }

    /// Records that the inbox watcher holds `source` back (None: no longer), for `surveys`.
    pub fn hold(&self, source: &str, why: Option<Held>) {
        let mut held = lock(&self.held);
        match why {
            Some(h) => {
                held.insert(source.to_string(), h);
            }
            None => {
                held.remove(source);
            }
        }
    }

    /// Bytes writes may still use on the store's disk, past what they must leave free.
    pub fn free_bytes(&self) -> u64 {
        self.guard
            .disk
            .available(&self.dir)
            .unwrap_or(0)
            .saturating_sub(self.guard.min_free)
    }

    /// Why writes are refused now, if they are.
    pub fn read_only(&self) -> Option<String> {
        if let Some(why) = self.broken.get() {
            return Some(EngineError::StoreFailed(why.clone()).to_string());
        }
        self.guard.check(&self.dir, 0).err().map(|e| e.to_string())
    }

    /// Counts a pass of the inbox watcher over its folders, finished.
    pub fn note_inbox_pass(&self) {
        self.inbox_passes
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    }

    /// Figures for `patchwork stats`, all from the published state and the caches, without the
    /// writer.
    pub fn stats(&self) -> Stats {
        let (t, c) = self.published();
        let active: Vec<_> = c.active().collect();
        Stats {
            surveys: c.active_count() as u32,
            retired: c
                .records
                .values()
                .filter(|r| r.status == patchwork_store::Status::Retired)
                .count() as u32,
            failed: c.failures.len() as u32,
            damaged: c.damaged.len() as u32,
            patches: t.index().len() as u64,
            active_boxes: t.index().active_count() as u64,
            samples: active.iter().map(|r| r.samples).sum(),
            disk_bytes: patchwork_store::dir_bytes(&self.dir),
            crs: self.cfg.crs_def().or_else(|| c.crs.clone()),
            vertical_crs: self.cfg.vertical_crs().or_else(|| c.vertical.clone()),
            backend: self.backend_name(),
            blend: t.blend(),
            quadtree_nodes: t.index().tree_stats().nodes as u32,
            read_only: self.read_only(),
            cache: read(&self.reader).stats(),
            ingesting: self.progress(),
            verifying: lock(&self.verifying).clone(),
            inbox_passes: self.inbox_passes.load(std::sync::atomic::Ordering::Relaxed),
            replication: self.replication(),
        }
    }
}

/// Gives the allocator's free memory back to the system. Opening a store and ingesting a file
/// allocate far more, briefly, than serving keeps (tops read once, a raster's mipmap and
/// chunks); glibc keeps such freed pages in its arenas, so without this a daemon's resident
/// memory would stay at its largest ingest rather than what it serves from.
pub fn release_free_memory() {
    release(false);
}

/// [`release_free_memory`], after every worker thread has handed back what its cache holds.
/// Only where nothing else runs, as an open: a worker busy with another request's work would
/// keep the caller waiting until it is done.
fn release_all_free_memory() {
    release(true);
}

fn release(wait: bool) {
    #[cfg(not(feature = "jemalloc"))]
    let _ = wait;
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free pages of the allocator's own arenas to the
    // system; it touches no memory in use.
    unsafe {
        libc::malloc_trim(0);
    }
    // jemalloc's background thread would give them back within a second; an open or an ingest
    // just done gives them back now. First each worker thread's cache of the small blocks it
    // freed, which keeps their slabs in use (15 bytes a patch of the Copernicus and NASADEM
    // pair's open), then the arenas' free pages: arena 4096 is MALLCTL_ARENAS_ALL, every
    // arena. Without waiting, the workers' caches are flushed as each comes to it, and the
    // background thread returns the pages that frees.
    #[cfg(feature = "jemalloc")]
    {
        fn ctl(name: &std::ffi::CStr) {
            // SAFETY: "thread.tcache.flush" and "arena.<i>.purge" read and write nothing
            // through the pointers, which are null; they only hand freed blocks back to
            // their arenas and the arenas' unused pages back to the system.
            unsafe {
                let (none, len) = (std::ptr::null_mut(), std::ptr::null_mut());
                tikv_jemalloc_sys::mallctl(name.as_ptr(), none, len, none, 0);
            }
        }
        if wait {
            rayon::broadcast(|_| ctl(c"thread.tcache.flush"));
        } else {
            rayon::spawn_broadcast(|_| ctl(c"thread.tcache.flush"));
        }
        ctl(c"thread.tcache.flush");
        ctl(c"arena.4096.purge");
    }
}

/// How the engine's store is opened.
fn store_options(cfg: &Config, guard: &SpaceGuard) -> Result<StoreOptions, EngineError> {
    Ok(StoreOptions {
        guard: guard.clone(),
        cache_bytes: cfg.cache_mb << 20,
        recipe: cfg.recipe(),
        contradicted: cfg.accuracy.contradicted,
        blend: cfg.patches.blend,
        backend: backend(&cfg.storage)?,
        snapshot_every: cfg.storage.snapshot_every,
    })
}

/// The object store `[storage]` names, as a client: nothing is sent until the store opens.
fn backend(st: &Storage) -> Result<ChunkBackend, EngineError> {
    use object_store::{ClientOptions, RetryConfig};
    let timeout = std::time::Duration::from_millis(st.timeout_ms);
    // Each try gets the whole deadline; the retries, with backoff, share it.
    let retry = RetryConfig {
        max_retries: st.retries as usize,
        retry_timeout: timeout,
        ..RetryConfig::default()
    };
    let bad = |what: &str, e: object_store::Error| EngineError::Storage {
        what: what.to_string(),
        source: Box::new(e),
    };
    let (store, prefix, url): (Arc<dyn object_store::ObjectStore>, _, _) = match st.backend {
        BackendKind::Local => return Ok(ChunkBackend::Local),
        BackendKind::S3 => {
            let s3 = &st.s3;
            let mut b = object_store::aws::AmazonS3Builder::from_env()
                .with_bucket_name(&s3.bucket)
                .with_region(&s3.region)
                .with_retry(retry)
                .with_client_options(
                    ClientOptions::new()
                        .with_timeout(timeout)
                        .with_connect_timeout(timeout.min(std::time::Duration::from_secs(5)))
                        .with_allow_http(s3.allow_http),
                );
            if !s3.endpoint.is_empty() {
                b = b.with_endpoint(&s3.endpoint);
            }
            let store = b.build().map_err(|e| bad("s3", e))?;
            let prefix = s3.prefix.trim_matches('/').to_string();
            (Arc::new(store), prefix, st.url().expect("a bucket"))
        }
        BackendKind::Folder => {
            let dir = st.folder.as_ref().expect("validated: folder is set");
            std::fs::create_dir_all(dir).map_err(|e| EngineError::Storage {
                what: format!("folder {}", dir.display()),
                source: Box::new(e),
            })?;
            // LocalFileSystem with the conditional PUT the writer's lease is renewed with.
            let store = patchwork_store::folder::Folder::new(dir).map_err(|e| bad("folder", e))?;
            (Arc::new(store), String::new(), st.url().expect("a folder"))
        }
    };
    let objects = Objects {
        store,
        prefix: object_store::path::Path::from(prefix),
        url,
        grace: std::time::Duration::from_secs(st.gc_grace_s),
        lease: std::time::Duration::from_secs(st.lease_s),
    };
    Ok(if st.follow.is_empty() {
        ChunkBackend::Objects(objects)
    } else {
        ChunkBackend::Follow(objects)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paths::source_name;
    use patchwork_store::StoreError;
    use std::path::Path;

    /// Whether the calling thread keeps a jemalloc thread cache.
    #[cfg(feature = "jemalloc")]
    fn cached() -> bool {
        let (mut on, mut len) = (false, std::mem::size_of::<bool>());
        // SAFETY: "thread.tcache.enabled" writes a bool through the pointer given, whose size
        // is given with it.
        let rc = unsafe {
            tikv_jemalloc_sys::mallctl(
                c"thread.tcache.enabled".as_ptr(),
                (&raw mut on).cast(),
                &raw mut len,
                std::ptr::null_mut(),
                0,
            )
        };
        assert_eq!(rc, 0, "jemalloc answers");
        on
    }

    #[cfg(feature = "jemalloc")]
    #[test]
    fn only_the_pools_workers_keep_a_thread_cache() {
        assert!(
            !std::thread::spawn(cached).join().unwrap(),
            "a thread starts without one"
        );
        let pool = super::workers().num_threads(3).build().unwrap();
        assert_eq!(pool.broadcast(|_| cached()), vec![true; 3]);
    }

    #[test]
    fn after_an_io_error_under_a_write_the_engine_stops_writing_and_keeps_reading() {
        let tmp = tempfile::tempdir().unwrap();
        let inbox = tmp.path().join("inbox");
        std::fs::create_dir_all(&inbox).unwrap();
        let cfg = Config {
            data_dir: tmp.path().join("data"),
            inbox: vec![inbox.clone()],
            ..Config::default()
        };
        let e = Engine::open(cfg).unwrap();
        let file = inbox.join("a.tif");
        std::fs::copy(
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../tests/data/copernicus_n34w119_crop.tif"),
            &file,
        )
        .unwrap();
        // sled cannot go on after an I/O error; the engine must not try.
        let eio = std::io::Error::other("Input/output error");
        let err = e.failed(StoreError::Sled(sled::Error::Io(eio)));
        assert!(matches!(err, EngineError::StoreFailed(_)), "{err}");
        let err = e.ingest(&file, None, Origin::Request).unwrap_err();
        assert!(
            err.to_string().contains("until the daemon restarts"),
            "{err}"
        );
        assert!(matches!(e.compact(), Err(EngineError::StoreFailed(_))));
        assert!(e.read_only().unwrap().contains("Input/output error"));
        assert_eq!(e.stats().surveys, 0);
        let at = SampleRequest::new(vec![[0.0, 0.0]], None, 0.0).unwrap();
        assert!(e.sample(&at, Ctx::default()).is_ok());
    }

    /// Engine over a fresh store whose inbox is `inbox`.
    fn engine_in(tmp: &Path, inbox: &Path) -> Engine {
        std::fs::create_dir_all(inbox).unwrap();
        Engine::open(Config {
            data_dir: tmp.join("data"),
            inbox: vec![inbox.to_path_buf()],
            ..Config::default()
        })
        .unwrap()
    }

    fn crop(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/data")
            .join(name)
    }

    /// The content id a survey records is that of the very bytes its samples came from, even
    /// while its file is replaced again and again as it is ingested: the file is opened and
    /// read once, hashed as it is parsed.
    #[test]
    fn the_content_id_recorded_is_of_the_bytes_ingested() {
        let tmp = tempfile::tempdir().unwrap();
        let inbox = tmp.path().join("inbox");
        // What each content is served as, from a store that takes the two files as they lie.
        let truth = engine_in(&tmp.path().join("truth"), &inbox);
        let mut pairs = Vec::new();
        for name in ["copernicus_n34w119_crop.tif", "nasadem_n34w119_crop.tif"] {
            let f = inbox.join(name);
            std::fs::copy(crop(name), &f).unwrap();
            truth.ingest(&f, None, Origin::Request).unwrap();
            let r = truth
                .catalog()
                .active_from(&source_name(&f))
                .cloned()
                .unwrap();
            pairs.push((r.content_id, r.id));
        }
        drop(truth);

        let e = engine_in(tmp.path(), &inbox);
        let file = inbox.join("swapped.tif");
        std::fs::copy(crop("copernicus_n34w119_crop.tif"), &file).unwrap();
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let swapper = {
            let (stop, file) = (stop.clone(), file.clone());
            let dir = inbox.clone();
            std::thread::spawn(move || {
                let names = ["copernicus_n34w119_crop.tif", "nasadem_n34w119_crop.tif"];
                let mut k = 0;
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    // Each replacement is whole (a rename), as a careful writer makes it.
                    let part = dir.join(".swap.part");
                    std::fs::copy(dir.join(names[k % 2]), &part).unwrap();
                    std::fs::rename(&part, &file).unwrap();
                    k += 1;
                }
                k
            })
        };
        let mut seen = std::collections::HashSet::new();
        for _ in 0..30 {
            e.ingest(&file, None, Origin::Request).unwrap();
            let r = e
                .catalog()
                .active_from(&source_name(&file))
                .cloned()
                .unwrap();
            assert!(
                pairs.contains(&(r.content_id.clone(), r.id)),
                "survey {} was recorded with the content id {} of other bytes",
                r.id,
                r.content_id
            );
            seen.insert(r.id);
        }
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        let swaps = swapper.join().unwrap();
        assert!(swaps > 30, "the file was replaced only {swaps} times");
    }

    /// A tile reads its patches' samples before it asks for the GPU device, so that tiles on
    /// the GPU never wait for each other's disk reads: while the device is held, another
    /// tile's reads still go on.
    #[cfg(feature = "gpu")]
    #[test]
    fn a_tile_reads_its_samples_before_it_waits_for_the_gpu() {
        let tmp = tempfile::tempdir().unwrap();
        let inbox = tmp.path().join("inbox");
        let file = inbox.join("a.tif");
        {
            let e = engine_in(tmp.path(), &inbox);
            std::fs::copy(crop("copernicus_n34w119_crop.tif"), &file).unwrap();
            e.ingest(&file, None, Origin::Request).unwrap();
        }
        // Opened afresh: no chunk is cached, so the tile must read its samples from the pack.
        let e = Arc::new(engine_in(tmp.path(), &inbox));
        let bounds = patchwork_read::read_raster(&file, &Default::default())
            .unwrap()
            .into_grid()
            .unwrap()
            .world_bounds();
        let misses = |e: &Engine| read(&e.reader).stats().misses;
        let before = misses(&e);
        let device = e.hold_gpu();
        let tile = {
            let e = e.clone();
            std::thread::spawn(move || {
                let cut = Cut::new(None, bounds, 0.0).unwrap();
                let req = TileRequest::new(cut, 64, 64, Backend::Auto).unwrap();
                e.tile(&req, Ctx::default())
                    .map(|(t, _, _)| t.heights.len())
            })
        };
        let t0 = std::time::Instant::now();
        while misses(&e) == before && t0.elapsed() < std::time::Duration::from_secs(20) {
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        let read_while_held = misses(&e) > before;
        drop(device);
        assert_eq!(tile.join().unwrap().unwrap(), 64 * 64);
        assert!(
            read_while_held,
            "the tile waited for the GPU device before reading its samples"
        );
    }
}
