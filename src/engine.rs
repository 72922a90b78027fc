//! The engine behind the server and the CLI: one store, one published state, one writer.
//!
//! Readers take the published state, the terrain and the catalog of records beside it, and
//! never touch the store or wait for a writer. The writer owns the store: it computes the next
//! terrain on a copy, commits the change in one batch, and only then publishes the copy with
//! the catalog read back from the store, so readers see the old state or the new one, never
//! half of a change, and a failed commit leaves both as they were.
//!
//! A write that would not fit on the disk is refused before sled sees it (see
//! [`crate::store::space`]). Should sled fail all the same (an I/O error, or a disk another
//! process filled in the meantime), its handle is unusable from then on, so the engine stops
//! writing, says why, and keeps serving reads from what it has published.

use crate::config::Config;
use crate::crs::vertical::VerticalCrs;
use crate::crs::{Crs, Reprojection};
use crate::index::geom::Aabb;
use crate::index::lod::ChangeStats;
use crate::index::query::{Extracted, Metric, Shortfall, ViewQuery};
pub use crate::ingest::Phase;
use crate::ingest::{open_file, prepare_with, Geoids, IngestError, IngestSettings};
use crate::model::evidence::Blame;
use crate::model::ids::SurveyId;
use crate::model::place::Planes;
use crate::model::survey::Survey;
pub use crate::read::REFUSED_PATH;
use crate::read::{content_id, file_content_id, ReadError, ReadLimits};
use crate::resample::gpu::{Emulated, GpuError, GpuResampler};
pub use crate::resample::Backend;
use crate::resample::{cpu, Cancel, SampleGrid};
use crate::restore;
use crate::store::{
    now_unix, CacheStats, Catalog, ChunkReader, Damaged, DiskSpace, FailedRecord, IngestTimings,
    SpaceGuard, Store, StoreError, StoreOptions, SurveyRecord, SystemDisk,
};
use crate::terrain::{Terrain, Tile};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock, RwLock};
use std::time::Instant;
use thiserror::Error;
use tokio::sync::broadcast;

/// Everything that can go wrong in a request, by what the caller should do about it. The
/// server maps these to status codes in one place.
#[derive(Debug, Error)]
pub enum EngineError {
    /// The request itself is wrong: fix the request.
    #[error("{0}")]
    Invalid(String),
    /// The request is too big: ask for less.
    #[error("{0}")]
    TooLarge(String),
    #[error("{0}")]
    NotFound(String),
    /// The request is fine but cannot be served in this state (no GPU, say).
    #[error("{0}")]
    Unavailable(String),
    /// The store failed under a write and takes no more until the daemon restarts.
    #[error(
        "the store failed on a disk error and takes no writes until the daemon restarts \
         (reads go on): {0}"
    )]
    StoreFailed(String),
    #[error("{0}")]
    Store(#[from] StoreError),
    /// The caller gave up (its deadline passed) and the work stopped.
    #[error("the request was cancelled: its deadline passed")]
    Cancelled,
}

/// What happened to a file or a survey.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    Inserted,
    /// The same path held another survey, which this one replaced in one commit.
    Replaced,
    /// The content is already served, or was retired by hand; nothing changed.
    Unchanged,
    Retired,
    Failed,
}

impl Outcome {
    pub fn as_str(&self) -> &'static str {
        match self {
            Outcome::Inserted => "inserted",
            Outcome::Replaced => "replaced",
            Outcome::Unchanged => "unchanged",
            Outcome::Retired => "retired",
            Outcome::Failed => "failed",
        }
    }
}

/// Who asked for a file to be ingested.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Origin {
    /// The inbox watcher: a file retired by hand stays retired until its content changes.
    Inbox,
    /// A client naming the file: it comes back even if it was retired by hand.
    Request,
}

/// Two surveys that disagree by more than their accuracies allow where they overlap.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Conflict {
    /// The other survey.
    pub survey: SurveyId,
    /// How far they differ where they overlap, measured at the finer one's samples.
    pub max_m: f64,
    pub rms_m: f64,
    /// Where the other lies against this one, metres east, north and up, and how far they
    /// differ once it is moved back; None where they could not be coregistered.
    pub shift_m: Option<[f64; 3]>,
    pub rms_after_m: Option<f64>,
    /// Whose claim the evidence finds false.
    pub distrusted: Distrusted,
}

/// Which claim of a conflicting pair is false, from one of the two's side.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Distrusted {
    /// This survey's: a degraded copy of the other, or the one shifted from where a third
    /// survey lies.
    This,
    Other,
    /// Either could be: nothing tells them apart.
    Both,
}

impl Distrusted {
    pub fn as_str(&self) -> &'static str {
        match self {
            Distrusted::This => "this",
            Distrusted::Other => "other",
            Distrusted::Both => "both",
        }
    }
}

/// The conflicts of a survey of `t`: its pairs whose evidence finds a claim false (where their
/// claims contradict each other, or one is a degraded copy of the other), by the other's id.
pub fn conflicts_of(t: &Terrain, id: SurveyId) -> Vec<Conflict> {
    let mut out: Vec<Conflict> = t
        .pairs_of(id)
        .iter()
        .filter_map(|p| {
            let other = p.other(id);
            let finer = p.finer == id;
            let distrusted = match t.blame(id, other)? {
                Blame::Finer if finer => Distrusted::This,
                Blame::Coarser if !finer => Distrusted::This,
                Blame::Finer | Blame::Coarser => Distrusted::Other,
                Blame::Both => Distrusted::Both,
            };
            Some(Conflict {
                survey: other,
                max_m: p.deviation.max_m,
                rms_m: p.deviation.rms_m,
                // The pair measures the coarser against the finer.
                shift_m: p.shift_m().map(|s| if finer { s } else { s.map(|v| -v) }),
                rms_after_m: p.coreg.as_ref().map(|c| c.rms_after),
                distrusted,
            })
        })
        .collect();
    out.sort_by_key(|c| c.survey);
    out
}

/// A change to the store, for subscribers.
#[derive(Clone, Debug, PartialEq)]
pub struct Event {
    pub kind: Outcome,
    pub survey: Option<SurveyId>,
    pub source: String,
    pub error: String,
    pub at_unix: u64,
    /// For an inserted or replacing survey, the surveys it conflicts with.
    pub conflicts: Vec<Conflict>,
}

/// The outcome of ingesting one file.
#[derive(Clone, Debug)]
pub struct Ingested {
    pub source: String,
    pub outcome: Outcome,
    pub survey: Option<SurveyId>,
    pub error: String,
    pub samples: u64,
    pub seconds: f64,
    pub conflicts: Vec<Conflict>,
}

/// The store's surveys with their failures and conflicts.
#[derive(Clone, Debug, Default)]
pub struct SurveyListing {
    pub records: Vec<SurveyRecord>,
    pub failures: Vec<FailedRecord>,
    /// Active surveys out of the terrain because they are damaged.
    pub damaged: BTreeMap<SurveyId, Damaged>,
    /// Conflicts of each active survey, in the other survey's id order.
    pub conflicts: HashMap<SurveyId, Vec<Conflict>>,
}

/// A query's cut through LOD space.
#[derive(Clone, Debug)]
pub enum Cut {
    /// Over a rectangle of the store's CRS.
    Uniform {
        roi: Aabb,
        error: f64,
    },
    /// Over a rectangle of another CRS: a tile of it is resampled at its own sample
    /// positions, carried into the store's.
    UniformIn {
        crs: Crs,
        roi: Aabb,
        error: f64,
    },
    View(ViewQuery),
}

impl Cut {
    /// The CRS the cut's region and a tile's positions are in; None for the store's.
    pub fn crs(&self) -> Option<&Crs> {
        match self {
            Cut::UniformIn { crs, .. } => Some(crs),
            _ => None,
        }
    }
}

/// Most vertices a row or column of a mesh: a 2049² grid resamples 4.2 M heights.
pub const MAX_MESH_SIZE: usize = 2049;

/// A mesh asked of a uniform cut.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshSpec {
    /// The tile the grid spans, and the cut's error in metres.
    pub roi: Aabb,
    pub error: f64,
    /// Grid vertices a row, and rows: 2 to [`MAX_MESH_SIZE`] each.
    pub cols: usize,
    pub rows: usize,
    /// How far the triangles may depart from the resampled heights at the grid's vertices.
    pub mesh_error: f64,
    /// Depth of the skirts under the border; 0 leaves them out.
    pub skirt_m: f64,
    pub border: crate::mesh::Border,
    pub method: crate::mesh::Method,
    /// How far the surface may be drawn over a void from the nearest measured vertex,
    /// metres (seed 004's horizontal error); 0 keeps holes exact.
    pub hole_reach_m: f64,
    /// The CRS of the ROI and of the vertices; None for the store's.
    pub crs: Option<Crs>,
}

/// A mesh of a uniform cut and what it was made from.
#[derive(Clone, Debug)]
pub struct MeshTile {
    pub mesh: crate::mesh::Mesh,
    /// The tile its grid spans.
    pub roi: Aabb,
    /// The patches blended, in id order.
    pub patches: Vec<Extracted>,
    pub backend: &'static str,
    /// Where no data is as accurate as the cut asked.
    pub shortfall: Option<Shortfall>,
}

/// What a tile is, told with each of its bands.
#[derive(Clone, Copy, Debug)]
pub struct TileHead<'a> {
    pub width: usize,
    pub height: usize,
    /// The patches the heights are blended from, in id order.
    pub patches: &'a [Extracted],
    /// The backend that resampled: "cpu" or "gpu".
    pub backend: &'static str,
    /// Where no data is as accurate as the cut asked.
    pub shortfall: Option<Shortfall>,
}

/// A store and the figures `stats` reports.
#[derive(Clone, Debug, Default)]
pub struct Stats {
    pub surveys: u32,
    pub retired: u32,
    pub failed: u32,
    /// Active surveys out of the terrain because they are damaged.
    pub damaged: u32,
    pub patches: u64,
    pub active_boxes: u64,
    pub samples: u64,
    pub disk_bytes: u64,
    pub crs: Option<Crs>,
    pub vertical_crs: Option<VerticalCrs>,
    /// "cpu", or "gpu (adapter)".
    pub backend: String,
    pub quadtree_nodes: u32,
    /// Why writes are refused now (a full disk, a failed store); None when they are not.
    pub read_only: Option<String>,
    pub cache: CacheStats,
    /// The ingest under way, if any.
    pub ingesting: Option<Progress>,
}

/// The ingest under way: which file, how big, where it is and since when.
#[derive(Clone, Debug)]
pub struct Progress {
    pub source: String,
    pub bytes: u64,
    pub phase: Phase,
    pub started: Instant,
}

/// One of the engine's ingest slots, given back when dropped.
struct IngestSlot<'a>(&'a Engine);

impl Drop for IngestSlot<'_> {
    fn drop(&mut self) {
        let (count, freed) = &self.0.ingest_slots;
        *count.lock().unwrap_or_else(|e| e.into_inner()) -= 1;
        freed.notify_one();
    }
}

/// What readers see: a terrain and the catalog of the same commit.
struct Published {
    terrain: Arc<Terrain>,
    catalog: Arc<Catalog>,
}

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
    gpu: Mutex<Option<GpuResampler>>,
    /// The store's chunk reader, for cache figures without the writer.
    reader: RwLock<Arc<ChunkReader>>,
    /// The geoid grids the config names, read once each when a conversion needs them.
    geoids: Arc<Geoids>,
    /// The maps from the CRSs requests have named to the store's.
    request_crs: Mutex<HashMap<Crs, Arc<Reprojection>>>,
}

impl Engine {
    pub fn open(cfg: Config) -> Result<Engine, EngineError> {
        Self::open_on(cfg, Arc::new(SystemDisk))
    }

    /// [`Engine::open`] with free space measured by `disk`.
    pub fn open_on(cfg: Config, disk: Arc<dyn DiskSpace>) -> Result<Engine, EngineError> {
        keep_large_buffers();
        let guard = SpaceGuard {
            disk,
            min_free: cfg.storage.min_free_mb << 20,
            reserve: cfg.storage.reserve_mb << 20,
        };
        let opened = restore::open(
            &cfg.data_dir,
            cfg.patches.layout(),
            cfg.index,
            store_options(&cfg, &guard),
        )?;
        for w in &opened.warnings {
            tracing::warn!(warning = %w, "store opened with a problem; `patchwork verify` tells more");
        }
        if let (Some(want), Some(have)) = (cfg.crs_def(), opened.store.crs()) {
            if want != have {
                return Err(EngineError::Invalid(format!(
                    "the config says crs = {} but the store at {} is in {}",
                    want.label(),
                    cfg.data_dir.display(),
                    have.label()
                )));
            }
        }
        if let (Some(want), Some(have)) = (cfg.vertical_crs(), opened.store.vertical_crs()) {
            if !want.same_reference(&have) {
                return Err(EngineError::Invalid(format!(
                    "the config says vertical.crs = {} but the heights of the store at {} are \
                     in {}",
                    want.label(),
                    cfg.data_dir.display(),
                    have.label()
                )));
            }
        }
        let mut opened = opened;
        if let (None, Some(c)) = (opened.terrain.crs(), cfg.crs_def()) {
            // An empty store takes the config's CRS, not its first survey's.
            opened.terrain.set_crs(c);
        }
        if let Err(e) = opened.store.writable() {
            tracing::warn!(reason = %e, "serving read-only: writes resume once the disk has room");
        }
        let catalog = opened.store.catalog()?;
        release_free_memory();
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
            geoids: Arc::new(Geoids::new(&cfg.vertical.geoids)),
            request_crs: Mutex::new(HashMap::new()),
            cfg,
            events,
            gpu: Mutex::new(None),
        })
    }

    /// Opens the GPU device the daemon resamples on, once, at start-up. Without an adapter
    /// the daemon says so and resamples on the CPU.
    pub fn enable_gpu(&self) {
        let emulated = if self.cfg.allow_emulated_gpu {
            Emulated::Allow
        } else {
            Emulated::Refuse
        };
        match GpuResampler::new(emulated) {
            Ok(g) => {
                tracing::info!(adapter = %g.adapter(), "resampling on the GPU");
                *self.gpu.lock().expect("gpu lock") = Some(g);
            }
            Err(e) => tracing::info!(reason = %e, "no GPU device: resampling on the CPU"),
        }
        // A refused software driver leaves its libraries' heap behind.
        release_free_memory();
    }

    fn backend_name(&self) -> String {
        match self.gpu.lock().expect("gpu lock").as_ref() {
            Some(g) => format!("gpu ({})", g.adapter()),
            None => "cpu".into(),
        }
    }

    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// The current terrain; cheap, and stable for as long as the caller holds it.
    pub fn snapshot(&self) -> Arc<Terrain> {
        self.published.read().expect("state lock").terrain.clone()
    }

    /// The records, failures, overlaps and pins of the current terrain.
    pub fn catalog(&self) -> Arc<Catalog> {
        self.published.read().expect("state lock").catalog.clone()
    }

    /// The terrain and its catalog, of one and the same commit.
    pub fn published(&self) -> (Arc<Terrain>, Arc<Catalog>) {
        let p = self.published.read().expect("state lock");
        (p.terrain.clone(), p.catalog.clone())
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Event> {
        self.events.subscribe()
    }

    /// Runs `f` as the writer. `f` returns the terrain it committed, if it changed it; that
    /// terrain is published with the catalog as the store now holds it.
    fn write<T>(
        &self,
        f: impl FnOnce(&Store, &Arc<Terrain>) -> Result<(T, Option<Terrain>), StoreError>,
    ) -> Result<T, EngineError> {
        self.write_and(f, |_| {})
    }

    /// [`Engine::write`], then `after` with the result once it is published, still as the
    /// writer: what `after` sends (change events) goes out in commit order.
    fn write_and<T>(
        &self,
        f: impl FnOnce(&Store, &Arc<Terrain>) -> Result<(T, Option<Terrain>), StoreError>,
        after: impl FnOnce(&T),
    ) -> Result<T, EngineError> {
        if let Some(why) = self.broken.get() {
            return Err(EngineError::StoreFailed(why.clone()));
        }
        let guard = self.writer.lock().unwrap_or_else(|e| e.into_inner());
        let store = guard.as_ref().ok_or_else(|| {
            EngineError::Unavailable(
                "the store could not be reopened after compaction; restart the daemon".into(),
            )
        })?;
        let current = self.snapshot();
        let (v, next) = f(store, &current).map_err(|e| self.failed(e))?;
        // The change is committed: its terrain is published whatever happens next, or later
        // writes would build on a terrain the store no longer holds.
        let catalog = store.catalog();
        let mut p = self.published.write().expect("state lock");
        if let Some(t) = next {
            p.terrain = Arc::new(t);
        }
        match catalog {
            Ok(c) => p.catalog = Arc::new(c),
            Err(e) => {
                // Listings would go stale, and the store cannot be read back: stop writing.
                drop(p);
                let why = format!("the store could not be read back after a commit: {e}");
                if self.broken.set(why.clone()).is_ok() {
                    tracing::error!(error = %why, "no more writes until restart; reads go on");
                }
                after(&v);
                return Ok(v);
            }
        }
        drop(p);
        after(&v);
        if let Err(e) = store.guard().restore(store.path()) {
            tracing::warn!(error = %e, "could not make the store's reserve file");
        }
        Ok(v)
    }

    fn set_phase(&self, source: &str, phase: Phase) {
        let mut all = self.progress.lock().expect("progress lock");
        if let Some(p) = all.iter_mut().find(|p| p.source == source) {
            p.phase = phase;
        }
    }

    /// The oldest ingest under way, if any.
    pub fn progress(&self) -> Option<Progress> {
        self.progress
            .lock()
            .expect("progress lock")
            .first()
            .cloned()
    }

    /// Waits for one of the `limits.ingest_parallel` ingest slots; the slot is given back
    /// when the guard goes.
    fn ingest_slot(&self) -> IngestSlot<'_> {
        let (count, freed) = &self.ingest_slots;
        let mut n = count.lock().unwrap_or_else(|e| e.into_inner());
        while *n >= self.cfg.limits.ingest_parallel {
            n = freed.wait(n).unwrap_or_else(|e| e.into_inner());
        }
        *n += 1;
        IngestSlot(self)
    }

    /// How many files may be ingested at once.
    pub fn ingest_parallel(&self) -> usize {
        self.cfg.limits.ingest_parallel as usize
    }

    /// Notes a store error; one from sled's I/O leaves its handle unusable.
    fn failed(&self, e: StoreError) -> EngineError {
        if let StoreError::Sled(sled::Error::Io(io)) = &e {
            let why = io.to_string();
            if self.broken.set(why.clone()).is_ok() {
                tracing::error!(error = %why, "the store failed under a write: no more writes until restart; reads go on");
            }
            return EngineError::StoreFailed(why);
        }
        EngineError::Store(e)
    }

    fn publish(&self, terrain: Terrain, catalog: Catalog) {
        *self.published.write().expect("state lock") = Published {
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
    ) {
        // Nobody listening is fine.
        let _ = self.events.send(Event {
            kind,
            survey,
            source: source.into(),
            error: error.into(),
            at_unix: now_unix(),
            conflicts,
        });
    }

    /// The store's horizontal CRS: the config's, else the one it took from its first survey.
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

    /// Ingests one file: a new survey, a replacement for the survey the same path held, or
    /// nothing when the content is already present. A bad file is a failed outcome, recorded
    /// when it lies where files may be ingested from, and leaves everything stored as it was.
    /// An error is the store's: the file was not at fault, and may be tried again later.
    pub fn ingest(
        &self,
        path: &Path,
        accuracy: Option<f64>,
        origin: Origin,
    ) -> Result<Ingested, EngineError> {
        let t0 = Instant::now();
        let source = source_name(path);
        let failed = |error: String| Ingested {
            source: source.clone(),
            outcome: Outcome::Failed,
            survey: None,
            error,
            samples: 0,
            seconds: t0.elapsed().as_secs_f64(),
            conflicts: Vec::new(),
        };
        let slot = self.ingest_slot();
        self.progress.lock().expect("progress lock").push(Progress {
            source: source.clone(),
            bytes: std::fs::metadata(path).map_or(0, |m| m.len()),
            phase: Phase::Reading,
            started: Instant::now(),
        });
        let mut content = None;
        let result = self.ingest_inner(path, &source, accuracy, origin, &mut content);
        let idle = {
            let mut progress = self.progress.lock().expect("progress lock");
            progress.retain(|p| p.source != source);
            progress.is_empty()
        };
        // Another ingest in flight would only fault the pages back in, at a cost that showed
        // in the ingest rate of a batch of files; the last one out returns them.
        if idle {
            release_free_memory();
        }
        drop(slot);
        match result {
            Err(Refusal::Outside) => {
                tracing::warn!(source = ?source, "refused a path outside the ingest folders");
                // A name in the inbox that leads outside (or nowhere) is a bad file like any
                // other; a client's path is not remembered, or clients could fill the store.
                if origin == Origin::Inbox {
                    self.record_failure(path, &source, REFUSED_PATH, content.as_deref());
                }
                Ok(failed(REFUSED_PATH.into()))
            }
            Ok((outcome, survey, samples, conflicts)) => {
                let seconds = t0.elapsed().as_secs_f64();
                if outcome != Outcome::Unchanged {
                    tracing::info!(source = ?source, survey = %survey, outcome = outcome.as_str(), seconds, conflicts = conflicts.len(), "ingested");
                }
                Ok(Ingested {
                    source,
                    outcome,
                    survey: Some(survey),
                    error: String::new(),
                    samples,
                    seconds,
                    conflicts,
                })
            }
            Err(Refusal::Store(e)) => {
                tracing::warn!(source = ?source, error = ?e.to_string(), "ingest deferred: the store cannot take it now");
                Err(e)
            }
            Err(Refusal::File(error)) => {
                tracing::warn!(source = ?source, error = ?error, "ingest failed");
                self.record_failure(path, &source, &error, content.as_deref());
                Ok(failed(error))
            }
        }
    }

    /// Remembers a file that failed, so that the inbox does not try it again until it
    /// changes. Only names that are there are remembered: one with nothing behind it would
    /// only fill the store.
    /// Records a failed file, and says so to subscribers in commit order.
    fn record_failure(&self, path: &Path, source: &str, error: &str, content: Option<&str>) {
        if path.symlink_metadata().is_err() {
            // Only names that exist are kept; the failure is still news.
            self.emit(Outcome::Failed, None, source, error, Vec::new());
            return;
        }
        let (size, mtime_unix) = size_mtime(path).unwrap_or((0, 0));
        let rec = FailedRecord {
            source: source.into(),
            error: error.into(),
            size,
            mtime_unix,
            at_unix: now_unix(),
            content_id: content.unwrap_or_default().into(),
        };
        let keep = self.cfg.limits.max_failures as usize;
        let recorded = self.write_and(
            |s, _| Ok((s.record_failure(&rec, keep)?, None)),
            |_| self.emit(Outcome::Failed, None, source, error, Vec::new()),
        );
        if let Err(e) = recorded {
            tracing::warn!(source = ?source, error = ?e.to_string(), "could not record the failure");
            self.emit(Outcome::Failed, None, source, error, Vec::new());
        }
    }

    fn ingest_inner(
        &self,
        path: &Path,
        source: &str,
        accuracy: Option<f64>,
        origin: Origin,
        content_out: &mut Option<String>,
    ) -> Result<(Outcome, SurveyId, u64, Vec<Conflict>), Refusal> {
        // Reading and modelling a file only to be refused at the commit would be wasted.
        if let Some(why) = self.broken.get() {
            return Err(Refusal::Store(EngineError::StoreFailed(why.clone())));
        }
        self.guard
            .check(&self.dir, 0)
            .map_err(|e| Refusal::Store(e.into()))?;
        // Every file is opened where it resolves, inside these, and checked there: a path
        // swapped for a symlink after any earlier look still cannot lead outside.
        let roots: Arc<[PathBuf]> = self.roots().into();
        let file = |e: IngestError| match e {
            IngestError::Refused | IngestError::Read(ReadError::Outside) => Refusal::Outside,
            e => Refusal::File(e.to_string()),
        };
        let handle = open_file(path, Some(&roots)).map_err(file)?;
        let content = content_id(&handle)
            .map_err(|e| Refusal::File(format!("cannot read {}: {e}", path.display())))?;
        drop(handle);
        *content_out = Some(content.clone());
        if path.to_str().is_none() {
            // Sources are text everywhere (listings, events, the wire): a name that is not
            // cannot be one. Recorded under its escaped name, so that it is seen and can be
            // forgotten.
            return Err(Refusal::File(format!(
                "the file name {source} is not valid UTF-8: rename the file to ingest it"
            )));
        }
        let catalog = self.catalog();
        if origin == Origin::Inbox {
            // The inbox leaves alone a file whose survey is served as it is, or whose content
            // was retired by hand (under this name or a copy's), until its content changes.
            let pinned = catalog.pins.values().any(|c| *c == content);
            let kept = catalog
                .active_from(source)
                .filter(|r| r.content_id == content)
                .or_else(|| {
                    pinned
                        .then(|| {
                            catalog
                                .records
                                .iter()
                                .rev()
                                .find(|r| r.content_id == content)
                        })
                        .flatten()
                });
            if let Some(r) = kept {
                return Ok((Outcome::Unchanged, r.id, r.samples, Vec::new()));
            }
        }
        let settings = IngestSettings {
            accuracy,
            default_accuracy: self.cfg.accuracy_m,
            max_accuracy: self.cfg.index.max_error,
            store_vertical: self.vertical_crs(),
            geoids: self.geoids.clone(),
            // An existing store keeps the layout its tops were computed with, and the recipe
            // its surveys were built with.
            layout: catalog.layout,
            recipe: catalog.recipe,
            read_limits: ReadLimits {
                roots: Some(roots),
                ..ReadLimits::mb(self.cfg.limits.max_ingest_mb)
            },
            heights: (self.cfg.limits.min_height_m, self.cfg.limits.max_height_m),
        };
        let prepared =
            prepare_with(path, &settings, &|p| self.set_phase(source, p)).map_err(file)?;
        // Placed in the store's CRS, on the terrain's planes (whose lattices cache what they
        // have worked out): a survey in another CRS gets its frames, and its patches' errors
        // what the reprojection can cost them. The writer checks that the store's CRS is
        // still the one it was placed in.
        let store_crs = self
            .crs()
            .or_else(|| self.snapshot().crs().cloned())
            .or_else(|| prepared.survey.crs.clone());
        let survey = match store_crs {
            Some(c) => {
                let planes = match self.snapshot().planes() {
                    Some(p) if *p.store_crs() == c => p.clone(),
                    _ => Arc::new(Planes::new(c)),
                };
                prepared
                    .survey
                    .placed(&planes)
                    .map_err(|e| Refusal::File(e.to_string()))?
            }
            None => prepared.survey.clone(),
        };
        let survey = Arc::new(survey);
        let samples = survey.levels[0].valid_count() as u64;
        let t1 = Instant::now();
        let mut conflicts = Vec::new();
        let outcome = self
            .write_and(
                |store, current| {
                    self.set_phase(source, Phase::Indexing);
                    let previous = store_active_from(&self.catalog(), source);
                    if current.survey(survey.id).is_some() {
                        // The content is already served (from this path or a copy elsewhere);
                        // what this path held before, if anything else, is gone.
                        let next = match previous.filter(|o| o.id != survey.id) {
                            Some(old) => Some(retire_in(store, current, &old, false)?),
                            None => None,
                        };
                        store.clear_failure(source)?;
                        return Ok(((Outcome::Unchanged, Vec::new()), next));
                    }
                    let mut next = (**current).clone();
                    // The record, once the index work is done, so that it can say how long
                    // that took.
                    let rec = || {
                        record(&survey, source, &content, &prepared, t1)
                    };
                    let old_patches: Vec<_> = previous
                        .as_ref()
                        .and_then(|old| current.index().survey_patches(old.id))
                        .map(|p| p.to_vec())
                        .unwrap_or_default();
                    // The index work and the encoding of the samples need nothing of each
                    // other: the chunks go to the pack while the index takes the survey in.
                    let (indexed, packed) = rayon::join(
                        || -> Result<_, StoreError> {
                            let retire = match &previous {
                                Some(old) => next.try_retire(old.id)?.unwrap_or_default(),
                                None => ChangeStats::default(),
                            };
                            let insert = next
                                .try_insert(&survey)
                                .map_err(restore::terrain_error)?;
                            Ok((retire, insert, next.pairs_of(survey.id)))
                        },
                        || store.pack_survey(&survey),
                    );
                    let ((retire, insert, pairs), packed) = (indexed?, packed?);
                    self.set_phase(source, Phase::Committing);
                    let outcome = match &previous {
                        Some(old) => {
                            store.commit_replace(
                                old.id,
                                &old_patches,
                                &retire,
                                &survey,
                                &rec(),
                                &insert,
                                &next.edges_of(&[&retire, &insert]),
                                &pairs,
                                packed,
                            )?;
                            (Outcome::Replaced, conflicts_of(&next, survey.id))
                        }
                        None => {
                            store.commit_packed(
                                &survey,
                                &rec(),
                                &insert,
                                &next.edges_of(&[&insert]),
                                &pairs,
                                packed,
                            )?;
                            (Outcome::Inserted, conflicts_of(&next, survey.id))
                        }
                    };
                    // The samples are on disk now; the terrain reads them from there.
                    next.page_out(survey.id);
                    Ok((outcome, Some(next)))
                },
                |(outcome, found)| {
                    if *outcome == Outcome::Unchanged {
                        return;
                    }
                    let catalog = self.catalog();
                    if let Some(r) = catalog.records.iter().find(|r| r.id == survey.id) {
                        let t = &r.ingest;
                        tracing::debug!(source = ?source, read_ms = t.read_ms, build_ms = t.build_ms, index_ms = t.index_ms, commit_ms = t.commit_ms, "ingest timings");
                    }
                    conflicts = found.clone();
                    self.emit(*outcome, Some(survey.id), source, "", conflicts.clone());
                },
            )
            .map_err(Refusal::Store)?
            .0;
        Ok((outcome, survey.id, samples, conflicts))
    }

    /// Retires a survey named by id or by the source path it came from, at a client's
    /// request. Should its file still be in place with the same content, the inbox leaves
    /// it retired until the content changes.
    pub fn retire(&self, id_or_source: &str) -> Result<(SurveyId, usize), EngineError> {
        let wanted = id_or_source.parse::<SurveyId>().ok();
        let absolute = source_name(Path::new(id_or_source));
        let catalog = self.catalog();
        let rec = catalog
            .active()
            .find(|r| Some(r.id) == wanted || r.source == id_or_source || r.source == absolute)
            .cloned()
            .ok_or_else(|| {
                EngineError::NotFound(format!(
                    "no active survey has id or source {}; `patchwork surveys` lists them",
                    quote_short(id_or_source)
                ))
            })?;
        // Only the inbox brings a file back by itself: a file there with the same content is
        // pinned, so that it stays retired.
        let inbox: Vec<PathBuf> = self
            .cfg
            .inbox
            .iter()
            .filter_map(|d| d.canonicalize().ok())
            .collect();
        let still_there = Path::new(&rec.source)
            .parent()
            .is_some_and(|d| inbox.iter().any(|r| d.starts_with(r)))
            && file_content_id(Path::new(&rec.source), Some(&inbox))
                .is_ok_and(|c| c == rec.content_id);
        let n = self.retire_record(&rec, still_there)?;
        Ok((rec.id, n))
    }

    /// Retires the survey of a file seen deleted from the inbox.
    pub fn retire_deleted(&self, source: &str) -> Result<(), EngineError> {
        if let Some(rec) = self.catalog().active_from(source).cloned() {
            self.retire_record(&rec, false)?;
        } else if self.catalog().pins.contains_key(source) {
            // The file of a survey retired by hand is gone: the pin has nothing to hold.
            self.write(|s, _| Ok((s.unpin(source)?, None)))?;
        }
        Ok(())
    }

    fn retire_record(&self, rec: &SurveyRecord, pin: bool) -> Result<usize, EngineError> {
        let n = self.write_and(
            |store, current| {
                // Another writer may have retired it since the catalog was read.
                if store_active_from(&self.catalog(), &rec.source).is_none_or(|r| r.id != rec.id) {
                    return Err(StoreError::NotActive(rec.id));
                }
                let n = current
                    .index()
                    .survey_patches(rec.id)
                    .map_or(0, |p| p.len());
                let next = retire_in(store, current, rec, pin)?;
                Ok((n, Some(next)))
            },
            |_| self.emit(Outcome::Retired, Some(rec.id), &rec.source, "", Vec::new()),
        )?;
        tracing::info!(survey = %rec.id, source = ?rec.source, pinned = pin, "retired");
        Ok(n)
    }

    /// Drops every damaged survey for good (see [`Store::repair`]); what was dropped. The
    /// terrain leaves them out already, so only the catalog changes: the inbox then ingests
    /// their files afresh.
    pub fn repair(&self) -> Result<Vec<Damaged>, EngineError> {
        let dropped = self.write(|s, _| Ok((s.repair()?, None)))?;
        for d in &dropped {
            tracing::info!(survey = %d.id, source = ?d.source, reason = ?d.reason, "dropped a damaged survey");
        }
        Ok(dropped)
    }

    /// Removes the failure recorded for `source`; whether there was one.
    pub fn forget(&self, source: &str) -> Result<bool, EngineError> {
        let absolute = source_name(Path::new(source));
        self.write(|s, _| {
            let forgot = s.forget_failure(source)? || s.forget_failure(&absolute)?;
            Ok((forgot, None))
        })
    }

    /// Every survey record and the failed files.
    pub fn records(&self) -> (Vec<SurveyRecord>, Vec<FailedRecord>) {
        let c = self.catalog();
        (c.records.clone(), c.failures.clone())
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
            records: c.records.clone(),
            failures: c.failures.clone(),
            damaged: c.damaged.clone(),
            conflicts,
        };
        (t, listing)
    }

    /// Why writes are refused now, if they are.
    pub fn read_only(&self) -> Option<String> {
        if let Some(why) = self.broken.get() {
            return Some(EngineError::StoreFailed(why.clone()).to_string());
        }
        self.guard.check(&self.dir, 0).err().map(|e| e.to_string())
    }

    pub fn stats(&self) -> Stats {
        let (t, c) = self.published();
        let active: Vec<_> = c.active().collect();
        Stats {
            surveys: active.len() as u32,
            retired: c
                .records
                .iter()
                .filter(|r| r.status == crate::store::Status::Retired)
                .count() as u32,
            failed: c.failures.len() as u32,
            damaged: c.damaged.len() as u32,
            patches: t.index().len() as u64,
            active_boxes: t.index().active_count() as u64,
            samples: active.iter().map(|r| r.samples).sum(),
            disk_bytes: crate::store::dir_bytes(&self.dir),
            crs: self.cfg.crs_def().or_else(|| c.crs.clone()),
            vertical_crs: self.cfg.vertical_crs().or_else(|| c.vertical.clone()),
            backend: self.backend_name(),
            quadtree_nodes: t.index().tree_stats().nodes as u32,
            read_only: self.read_only(),
            cache: self.reader.read().expect("reader lock").stats(),
            ingesting: self.progress(),
        }
    }

    pub fn verify(&self) -> Result<crate::store::VerifyReport, EngineError> {
        let guard = self.writer.lock().unwrap_or_else(|e| e.into_inner());
        let store = guard
            .as_ref()
            .ok_or_else(|| EngineError::Unavailable("the store is not open".into()))?;
        Ok(restore::verify(store)?)
    }

    /// Physically removes retired surveys and rewrites the store's files.
    pub fn compact(&self) -> Result<crate::store::CompactReport, EngineError> {
        if let Some(why) = self.broken.get() {
            return Err(EngineError::StoreFailed(why.clone()));
        }
        let mut guard = self.writer.lock().unwrap_or_else(|e| e.into_inner());
        let store = guard
            .take()
            .ok_or_else(|| EngineError::Unavailable("the store is not open".into()))?;
        let live = self.snapshot().index().state().into_keys().collect();
        let result = restore::compact(store, &live);
        let (opened, report) = match result {
            Ok((opened, report)) => (opened, Ok(report)),
            // Compaction leaves the old files in place on failure: reopen them.
            Err(e) => {
                let opened = restore::open(
                    &self.dir,
                    self.cfg.patches.layout(),
                    self.cfg.index,
                    store_options(&self.cfg, &self.guard),
                )?;
                (opened, Err(e.into()))
            }
        };
        let catalog = opened.store.catalog()?;
        *self.reader.write().expect("reader lock") = opened.store.reader();
        self.publish(opened.terrain, catalog);
        *guard = Some(opened.store);
        report
    }

    fn metric_at(&self, lat: f64) -> Metric {
        match self.crs() {
            Some(c) if c.is_geographic() => Metric::geographic(lat),
            _ => Metric::PROJECTED,
        }
    }

    /// A view query as a client describes it, with the store's metric.
    pub fn view_query(
        &self,
        eye: [f64; 3],
        look: [f64; 3],
        fov_deg: f64,
        viewport_px: u32,
        pixel_error: f64,
    ) -> Result<ViewQuery, EngineError> {
        let v = ViewQuery {
            eye,
            look,
            fov_deg,
            viewport_px,
            pixel_error,
            metric: self.metric_at(eye[1]),
        };
        v.validate().map_err(EngineError::Invalid)?;
        Ok(v)
    }

    /// The map from a CRS to the store's, None for the store's own: one per CRS, kept, so
    /// that its lattice's nodes are worked out once for every request in it.
    pub fn to_store(&self, crs: &Crs) -> Result<Option<Arc<Reprojection>>, EngineError> {
        let Some(store) = self.crs() else {
            return Err(EngineError::Unavailable(
                "the store has no CRS yet (no survey and none in the config): ask in its own \
                 coordinates once it has one"
                    .into(),
            ));
        };
        if *crs == store {
            return Ok(None);
        }
        let mut cache = self.request_crs.lock().expect("request CRS cache");
        if let Some(r) = cache.get(crs).filter(|r| *r.to() == store) {
            return Ok(Some(r.clone()));
        }
        let r = Arc::new(
            Reprojection::new(crs, &store).map_err(|e| EngineError::Invalid(e.to_string()))?,
        );
        // Clients name few CRSs; a bound keeps a client naming many from holding memory.
        if cache.len() >= 64 {
            cache.clear();
        }
        cache.insert(crs.clone(), r.clone());
        Ok(Some(r))
    }

    /// A CRS a request names: None for the store's own (or no CRS named).
    pub fn request_crs(&self, text: &str) -> Result<Option<Crs>, EngineError> {
        if text.trim().is_empty() {
            return Ok(None);
        }
        let c = Crs::parse(text).map_err(|e| EngineError::Invalid(format!("crs: {e}")))?;
        Ok((Some(&c) != self.crs().as_ref()).then_some(c))
    }

    /// The store-plane bounds of a rectangle of another CRS: its border carried over.
    fn store_roi(&self, crs: &Crs, roi: &Aabb) -> Result<Aabb, EngineError> {
        let Some(r) = self.to_store(crs)? else {
            return Ok(*roi);
        };
        let n = 32;
        let mut pts = Vec::with_capacity(4 * n + 1);
        for k in 0..=n {
            let t = k as f64 / n as f64;
            let x = roi.min[0] + t * roi.width();
            let y = roi.min[1] + t * roi.height();
            pts.extend([
                [x, roi.min[1]],
                [x, roi.max[1]],
                [roi.min[0], y],
                [roi.max[0], y],
            ]);
        }
        let mapped: Option<Vec<[f64; 2]>> = pts.iter().map(|&p| r.at(p)).collect();
        let mapped = mapped.ok_or_else(|| {
            EngineError::Invalid(format!(
                "part of the region lies where {} cannot be carried into the store's {}",
                crs.label(),
                r.to().label()
            ))
        })?;
        // A side bows between the points by far less than a thousandth of the extent.
        let b = Aabb::of_points(&mapped);
        let m = 1e-3 * b.width().max(b.height());
        Ok(Aabb::new(
            b.min[0] - m,
            b.min[1] - m,
            b.max[0] + m,
            b.max[1] + m,
        ))
    }

    /// The patches of a cut, with the snapshot they came from.
    pub fn query(&self, cut: &Cut) -> Result<(Arc<Terrain>, Vec<Extracted>), EngineError> {
        let t = self.snapshot();
        let ps = match cut {
            Cut::Uniform { roi, error } => {
                check_roi(roi)?;
                check_error(*error)?;
                t.uniform(roi, *error)
            }
            Cut::UniformIn { crs, roi, error } => {
                check_roi(roi)?;
                check_error(*error)?;
                t.uniform(&self.store_roi(crs, roi)?, *error)
            }
            Cut::View(v) => {
                v.validate().map_err(EngineError::Invalid)?;
                t.view(v)
            }
        };
        let max = self.cfg.limits.max_patches;
        if ps.len() as u64 > max {
            return Err(EngineError::TooLarge(format!(
                "the query needs {} patches, more than the limit of {max}: ask for a smaller region or a larger error",
                ps.len()
            )));
        }
        Ok((t, ps))
    }

    /// A resampled tile.
    pub fn tile(
        &self,
        cut: &Cut,
        width: u32,
        height: u32,
        backend: Backend,
    ) -> Result<(Tile, &'static str), EngineError> {
        self.tile_until(cut, width, height, backend, &Cancel::default())
    }

    /// A mesh of a uniform cut: the resampled heights at the corners of a `cols × rows` grid
    /// of vertices over the ROI (a tile over the ROI grown by half a cell, whose pixel
    /// centres fall on them), triangulated as `spec` says.
    pub fn mesh_until(
        &self,
        spec: &MeshSpec,
        backend: Backend,
        cancel: &Cancel,
    ) -> Result<MeshTile, EngineError> {
        let (roi, cols, rows) = (spec.roi, spec.cols, spec.rows);
        for (name, n) in [("columns", cols), ("rows", rows)] {
            if !(2..=MAX_MESH_SIZE).contains(&n) {
                return Err(EngineError::Invalid(format!(
                    "a mesh has 2 to {MAX_MESH_SIZE} {name}: got {n}"
                )));
            }
        }
        for (name, v) in [
            ("mesh_error", spec.mesh_error),
            ("skirt_m", spec.skirt_m),
            ("hole_reach_m", spec.hole_reach_m),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(EngineError::Invalid(format!(
                    "{name} must be a finite number of metres ≥ 0, got {v}"
                )));
            }
        }
        let pixels = crate::mesh::pixel_roi(&roi, cols, rows);
        let cut = match &spec.crs {
            Some(crs) => Cut::UniformIn {
                crs: crs.clone(),
                roi: pixels,
                error: spec.error,
            },
            None => Cut::Uniform {
                roi: pixels,
                error: spec.error,
            },
        };
        let (tile, used) = self.tile_until(&cut, cols as u32, rows as u32, backend, cancel)?;
        let holes = if spec.hole_reach_m > 0.0 {
            let mid = (roi.min[1] + roi.max[1]) / 2.0;
            let scale = match &spec.crs {
                Some(c) => match c.unit_m() {
                    Some(m) => [m, m],
                    None => Metric::geographic(mid).scale,
                },
                None => self.metric_at(mid).scale,
            };
            crate::mesh::Holes::Reach {
                reach: spec.hole_reach_m,
                cell: [
                    roi.width() / (cols - 1) as f64 * scale[0],
                    roi.height() / (rows - 1) as f64 * scale[1],
                ],
            }
        } else {
            crate::mesh::Holes::Exact
        };
        let options = crate::mesh::Options {
            max_error: spec.mesh_error,
            border: spec.border,
            method: spec.method,
            holes,
        };
        let mut mesh = crate::mesh::triangulate_until(&tile.heights, cols, rows, &options, &|| {
            cancel.is_cancelled()
        })
        .ok_or(EngineError::Cancelled)?;
        if spec.skirt_m > 0.0 {
            crate::mesh::add_skirts(&mut mesh, spec.skirt_m as f32);
        }
        Ok(MeshTile {
            mesh,
            roi,
            patches: tile.patches,
            backend: used,
            shortfall: tile.shortfall,
        })
    }

    /// A resampled tile, given up once `cancel` is set.
    pub fn tile_until(
        &self,
        cut: &Cut,
        width: u32,
        height: u32,
        backend: Backend,
        cancel: &Cancel,
    ) -> Result<(Tile, &'static str), EngineError> {
        let (mut heights, mut shortfall) = (Vec::new(), None);
        let (patches, used) = self.tile_bands_until(
            cut,
            width,
            height,
            backend,
            height as usize,
            cancel,
            &mut |head, _, band| {
                heights = band;
                shortfall = head.shortfall;
                true
            },
        )?;
        let tile = Tile {
            width: width as usize,
            height: height as usize,
            heights,
            patches,
            shortfall,
        };
        Ok((tile, used))
    }

    /// A resampled tile in bands of about `rows` rows, top first: `sink` gets what the tile
    /// is, each band's first row and its heights, and says whether to go on. On the CPU a band
    /// goes to `sink` as soon as it is done, so that it can be sent while the next is worked
    /// out. Returns the patches blended and the backend that ran.
    #[allow(clippy::too_many_arguments)]
    pub fn tile_bands_until(
        &self,
        cut: &Cut,
        width: u32,
        height: u32,
        backend: Backend,
        rows: usize,
        cancel: &Cancel,
        sink: &mut dyn FnMut(&TileHead, usize, Vec<f32>) -> bool,
    ) -> Result<(Vec<Extracted>, &'static str), EngineError> {
        let n = width as u64 * height as u64;
        if width == 0 || height == 0 {
            return Err(EngineError::Invalid(
                "tile width and height must be at least 1".into(),
            ));
        }
        let max = self.cfg.limits.max_tile_samples;
        if n > max {
            return Err(EngineError::TooLarge(format!(
                "a {width}×{height} tile has {n} samples, more than the limit of {max}: ask for a smaller tile"
            )));
        }
        let (t, ps) = self.query(cut)?;
        let grid = match cut {
            Cut::Uniform { roi, .. } => SampleGrid::uniform(roi, width as usize, height as usize),
            Cut::UniformIn { crs, roi, .. } => {
                // The tile's own positions, carried into the store's plane.
                let own = SampleGrid::uniform(roi, width as usize, height as usize);
                match self.to_store(crs)? {
                    Some(r) => {
                        let pts: Vec<[f64; 2]> = own.points().collect();
                        SampleGrid::of_points(own.width, own.height, r.map(&pts))
                    }
                    None => own,
                }
            }
            Cut::View(v) => SampleGrid::view(v, width as usize, height as usize, v.look[2]),
        };
        let shortfall = crate::terrain::tile_shortfall(&ps, &grid);
        let head = |backend| TileHead {
            width: grid.width,
            height: grid.height,
            patches: &ps,
            backend,
            shortfall,
        };
        if backend != Backend::Cpu {
            let mut gpu = self.gpu.lock().expect("gpu lock");
            match gpu.as_mut() {
                Some(g) => {
                    match g.resample(&t.try_resolve(&ps).map_err(StoreError::from)?, &grid) {
                        Ok(heights) => {
                            drop(gpu);
                            let head = head("gpu");
                            let rows = rows.max(1);
                            if rows >= grid.height {
                                if !sink(&head, 0, heights) {
                                    return Err(EngineError::Cancelled);
                                }
                            } else {
                                for (k, band) in heights.chunks(rows * grid.width).enumerate() {
                                    if !sink(&head, k * rows, band.to_vec()) {
                                        return Err(EngineError::Cancelled);
                                    }
                                }
                            }
                            return Ok((ps, "gpu"));
                        }
                        Err(e) => {
                            tracing::warn!(error = %e, "GPU resampling failed; this request and later ones use the CPU");
                            if matches!(e, GpuError::Lost(_) | GpuError::Device(_)) {
                                *gpu = None;
                            }
                            if backend == Backend::Gpu {
                                return Err(EngineError::Unavailable(format!(
                                    "GPU resampling failed: {e}"
                                )));
                            }
                        }
                    }
                }
                None if backend == Backend::Gpu => return Err(EngineError::Unavailable(
                    "backend gpu was asked for, but this daemon has no GPU device; use auto or cpu"
                        .into(),
                )),
                None => {}
            }
        }
        let set = t.try_resolve(&ps).map_err(StoreError::from)?;
        let head = head("cpu");
        cpu::resample_bands(&set, &grid, rows, cancel, &mut |j0, band| {
            sink(&head, j0, band)
        })
        .ok_or(EngineError::Cancelled)?;
        Ok((ps, "cpu"))
    }

    /// Heights at points, at error `e`: what any tile holding the same points gives there.
    pub fn sample(&self, points: &[[f64; 2]], e: f64) -> Result<Vec<f32>, EngineError> {
        self.sample_until(points, e, &Cancel::default())
    }

    /// Heights at points, given up once `cancel` is set.
    pub fn sample_until(
        &self,
        points: &[[f64; 2]],
        e: f64,
        cancel: &Cancel,
    ) -> Result<Vec<f32>, EngineError> {
        self.sample_in(points, None, e, cancel)
    }

    /// Heights at points of `crs` (None for the store's), given up once `cancel` is set: the
    /// points are carried into the store's plane as a tile's positions are, so a point has
    /// the height any tile of that CRS holding it gives.
    pub fn sample_in(
        &self,
        points: &[[f64; 2]],
        crs: Option<&Crs>,
        e: f64,
        cancel: &Cancel,
    ) -> Result<Vec<f32>, EngineError> {
        if points.len() as u64 > self.cfg.limits.max_points {
            return Err(EngineError::TooLarge(format!(
                "{} points, more than the limit of {}: send them in smaller requests",
                points.len(),
                self.cfg.limits.max_points
            )));
        }
        if points
            .iter()
            .any(|p| !(p[0].is_finite() && p[1].is_finite()))
        {
            return Err(EngineError::Invalid("points must be finite".into()));
        }
        check_error(e)?;
        let carried;
        let points = match crs.map(|c| self.to_store(c)).transpose()?.flatten() {
            Some(r) => {
                carried = r.map(points);
                &carried
            }
            None => points,
        };
        self.snapshot()
            .try_sample_until(points, e, cancel)
            .map_err(StoreError::from)?
            .ok_or(EngineError::Cancelled)
    }
}

/// Gives the allocator's free memory back to the system. Opening a store and ingesting a file
/// allocate far more, briefly, than serving keeps (tops read once, a raster's mipmap and
/// chunks); glibc keeps such freed pages in its arenas, so without this a daemon's resident
/// memory would stay at its largest ingest rather than what it serves from.
fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free pages of the allocator's own arenas to the
    // system; it touches no memory in use.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Lets the allocator reuse freed buffers of up to 512 MiB instead of handing each back to the
/// system at once. An ingest allocates a few raster-sized buffers (52 MB for a 3600² tile) and
/// frees them within a second; by default glibc maps each afresh, and the kernel's faulting
/// and zeroing of those pages cost about a tenth of the CPU time of a batch of ingests (the
/// scale bench, docs/BENCHMARKS.md). Freed pages still go back after each batch, by
/// [`release_free_memory`]; one ingest peaks some 12% higher.
fn keep_large_buffers() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets an allocator parameter; called before the engine's threads
    // allocate, and the allocator serialises it with allocations anyway.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 512 << 20);
    }
}

/// How the engine's store is opened.
fn store_options(cfg: &Config, guard: &SpaceGuard) -> StoreOptions {
    StoreOptions {
        guard: guard.clone(),
        cache_bytes: cfg.cache_mb << 20,
        recipe: cfg.recipe(),
        contradicted: cfg.accuracy.contradicted,
    }
}

fn check_error(e: f64) -> Result<(), EngineError> {
    if !(e.is_finite() && e >= 0.0) {
        return Err(EngineError::Invalid(format!(
            "error must be a number of metres ≥ 0, got {e}"
        )));
    }
    Ok(())
}

fn check_roi(roi: &Aabb) -> Result<(), EngineError> {
    if !roi.is_valid() || roi.width() <= 0.0 || roi.height() <= 0.0 {
        return Err(EngineError::Invalid(format!(
            "the region must have xmin < xmax and ymin < ymax, got [{}, {}, {}, {}]",
            roi.min[0], roi.min[1], roi.max[0], roi.max[1]
        )));
    }
    Ok(())
}

/// Why an ingest did not happen: the path leads outside, the file's fault, or the store's.
enum Refusal {
    Outside,
    File(String),
    Store(EngineError),
}

/// The active survey `source` holds, as the store has it: a damaged one included, which a new
/// ingest of the file replaces. Read from the catalog, which the writer publishes after every
/// commit and so is the store's own while the writer is held, rather than by decoding every
/// record again.
fn store_active_from(catalog: &Catalog, source: &str) -> Option<SurveyRecord> {
    catalog
        .records
        .iter()
        .find(|r| r.status == crate::store::Status::Active && r.source == source)
        .cloned()
}

/// Commits the retirement of `rec` from `current` and returns the terrain without it.
fn retire_in(
    store: &Store,
    current: &Terrain,
    rec: &SurveyRecord,
    pin: bool,
) -> Result<Terrain, StoreError> {
    let patches: Vec<_> = current
        .index()
        .survey_patches(rec.id)
        .map(|p| p.to_vec())
        .unwrap_or_default();
    let mut next = current.clone();
    let change = next.try_retire(rec.id)?.unwrap_or_default();
    store.commit_retire(rec.id, &patches, &change, &next.edges_of(&[&change]), pin)?;
    Ok(next)
}

/// A client's string for an error message: quoted, control characters escaped, and cut short,
/// so that a megabyte of input does not come back in the reply.
pub fn quote_short(s: &str) -> String {
    const MOST: usize = 120;
    match s.char_indices().nth(MOST) {
        Some((cut, _)) => format!("{:?}… ({} bytes)", &s[..cut], s.len()),
        None => format!("{s:?}"),
    }
}

fn record(
    s: &Survey,
    source: &str,
    content: &str,
    prepared: &crate::ingest::Prepared,
    index_start: Instant,
) -> SurveyRecord {
    let t = prepared.timings;
    let mut rec = SurveyRecord::new(
        s,
        source,
        content,
        prepared.source,
        IngestTimings {
            read_ms: t.read_ms as f64,
            build_ms: t.build_ms as f64,
            index_ms: index_start.elapsed().as_secs_f64() * 1e3,
            commit_ms: 0.0,
        },
    );
    rec.vertical_source = prepared.vertical_source.clone();
    rec.vertical_error_m = prepared.vertical_error_m;
    rec
}

/// The absolute path a survey is known by.
pub fn source_name(path: &Path) -> String {
    let abs: PathBuf = match (path.parent(), path.file_name()) {
        (Some(dir), Some(name)) if !dir.as_os_str().is_empty() => dir
            .canonicalize()
            .map(|d| d.join(name))
            .unwrap_or_else(|_| path.to_path_buf()),
        _ => std::env::current_dir()
            .map(|d| d.join(path))
            .unwrap_or_else(|_| path.to_path_buf()),
    };
    escaped(&abs)
}

/// A path as text: itself when it is UTF-8, else with each byte that is not written `\xNN`
/// (U+FFFD would make different names one).
pub fn escaped(path: &Path) -> String {
    use std::os::unix::ffi::OsStrExt;
    let bytes = path.as_os_str().as_bytes();
    let mut out = String::with_capacity(bytes.len());
    for chunk in bytes.utf8_chunks() {
        out.push_str(chunk.valid());
        for b in chunk.invalid() {
            out.push_str(&format!("\\x{b:02x}"));
        }
    }
    out
}

pub fn size_mtime(path: &Path) -> Option<(u64, u64)> {
    let m = std::fs::metadata(path).ok()?;
    let mtime = m
        .modified()
        .ok()?
        .duration_since(std::time::UNIX_EPOCH)
        .ok()?
        .as_secs();
    Some((m.len(), mtime))
}

#[cfg(test)]
mod tests {
    use super::*;

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
            Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/copernicus_n34w119_crop.tif"),
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
        assert!(e.sample(&[[0.0, 0.0]], 0.0).is_ok());
    }
}
