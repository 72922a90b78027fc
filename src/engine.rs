//! The engine behind the server and the CLI: one store, one terrain snapshot, one writer.
//!
//! Queries take the current snapshot (an `Arc<Terrain>`) and never wait for a writer. A writer
//! computes the next terrain on a copy, commits the change to the store in one batch, and only
//! then publishes the copy, so readers see the old state or the new one, never half of a
//! change, and a failed commit leaves both as they were.

use crate::config::Config;
use crate::index::geom::Aabb;
use crate::index::lod::ChangeStats;
use crate::index::query::{Extracted, Metric, ViewQuery};
use crate::ingest::{prepare, IngestError, IngestSettings};
use crate::model::accuracy::{AccuracySource, Deviation};
use crate::model::ids::SurveyId;
use crate::model::survey::Survey;
use crate::resample::gpu::{GpuError, GpuResampler};
pub use crate::resample::Backend;
use crate::resample::SampleGrid;
use crate::store::{
    file_content_id, now_unix, FailedRecord, IngestTimings, Status, Store, StoreError, SurveyRecord,
};
use crate::terrain::{Terrain, Tile};
use rayon::prelude::*;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, RwLock};
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
    #[error("{0}")]
    Store(#[from] StoreError),
}

/// What happened to a file or a survey.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    Inserted,
    /// The same path held another survey, which this one replaced in one commit.
    Replaced,
    /// The content is already served; nothing changed.
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

/// Two surveys that disagree by more than their accuracies allow where they overlap.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Conflict {
    /// The other survey.
    pub survey: SurveyId,
    pub max_m: f64,
    pub rms_m: f64,
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
    /// Conflicts of each active survey, in the other survey's id order.
    pub conflicts: HashMap<SurveyId, Vec<Conflict>>,
}

/// A query's cut through LOD space.
#[derive(Clone, Debug)]
pub enum Cut {
    Uniform { roi: Aabb, error: f64 },
    View(ViewQuery),
}

/// A store and the figures `stats` reports.
#[derive(Clone, Debug, Default)]
pub struct Stats {
    pub surveys: u32,
    pub retired: u32,
    pub failed: u32,
    pub patches: u64,
    pub active_boxes: u64,
    pub samples: u64,
    pub disk_bytes: u64,
    pub crs: Option<u32>,
    /// "cpu", or "gpu (adapter)".
    pub backend: String,
    pub quadtree_nodes: u32,
}

pub struct Engine {
    cfg: Config,
    store: Mutex<Option<Store>>,
    terrain: RwLock<Arc<Terrain>>,
    /// Serialises writers; readers never take it.
    writer: Mutex<()>,
    events: broadcast::Sender<Event>,
    /// The GPU resampler, when the daemon opened one; dropped if the device is lost.
    gpu: Mutex<Option<GpuResampler>>,
}

/// Whether an EPSG code names a geographic (longitude/latitude) CRS.
pub fn is_geographic(epsg: u32) -> bool {
    (4000..5000).contains(&epsg)
}

impl Engine {
    pub fn open(cfg: Config) -> Result<Engine, EngineError> {
        let opened = Store::open(&cfg.data_dir, cfg.patches, cfg.index)?;
        for w in &opened.warnings {
            tracing::warn!(warning = %w, "store opened with a problem; `patchwork verify` tells more");
        }
        if let (Some(want), Some(have)) = (cfg.crs_epsg(), opened.store.crs()) {
            if want != have {
                return Err(EngineError::Invalid(format!(
                    "the config says EPSG:{want} but the store at {} is in EPSG:{have}",
                    cfg.data_dir.display()
                )));
            }
        }
        let (events, _) = broadcast::channel(1024);
        Ok(Engine {
            cfg,
            store: Mutex::new(Some(opened.store)),
            terrain: RwLock::new(Arc::new(opened.terrain)),
            writer: Mutex::new(()),
            events,
            gpu: Mutex::new(None),
        })
    }

    /// Opens the GPU device the daemon resamples on, once, at start-up. Without an adapter
    /// the daemon says so and resamples on the CPU.
    pub fn enable_gpu(&self) {
        match GpuResampler::new() {
            Ok(g) => {
                tracing::info!(adapter = %g.adapter(), "resampling on the GPU");
                *self.gpu.lock().expect("gpu lock") = Some(g);
            }
            Err(e) => tracing::info!(reason = %e, "no GPU device: resampling on the CPU"),
        }
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

    /// The current state; cheap, and stable for as long as the caller holds it.
    pub fn snapshot(&self) -> Arc<Terrain> {
        self.terrain.read().expect("terrain lock").clone()
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Event> {
        self.events.subscribe()
    }

    fn with_store<T>(
        &self,
        f: impl FnOnce(&Store) -> Result<T, StoreError>,
    ) -> Result<T, EngineError> {
        let guard = self.store.lock().expect("store lock");
        let store = guard
            .as_ref()
            .ok_or_else(|| EngineError::Unavailable("the store is being compacted".into()))?;
        Ok(f(store)?)
    }

    fn publish(&self, t: Terrain) {
        *self.terrain.write().expect("terrain lock") = Arc::new(t);
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

    pub fn crs(&self) -> Option<u32> {
        self.cfg
            .crs_epsg()
            .or_else(|| self.with_store(|s| Ok(s.crs())).ok().flatten())
    }

    /// The record of the active survey read from `source`, if any.
    fn active_from(&self, source: &str) -> Result<Option<SurveyRecord>, EngineError> {
        Ok(self
            .with_store(|s| s.surveys())?
            .into_iter()
            .find(|r| r.status == Status::Active && r.source == source))
    }

    /// Ingests one file: a new survey, a replacement for the survey the same path held, or
    /// nothing when the content is already present. A bad file is recorded as a failure and
    /// leaves everything stored as it was.
    pub fn ingest(&self, path: &Path, accuracy: Option<f64>) -> Ingested {
        let t0 = Instant::now();
        let source = source_name(path);
        let result = self.ingest_inner(path, &source, accuracy);
        let seconds = t0.elapsed().as_secs_f64();
        match result {
            Ok((outcome, survey, samples, conflicts)) => {
                if outcome != Outcome::Unchanged {
                    tracing::info!(%source, survey = %survey, outcome = outcome.as_str(), seconds, conflicts = conflicts.len(), "ingested");
                    self.emit(outcome, Some(survey), &source, "", conflicts.clone());
                }
                Ingested {
                    source,
                    outcome,
                    survey: Some(survey),
                    error: String::new(),
                    samples,
                    seconds,
                    conflicts,
                }
            }
            Err(e) => {
                let error = e.to_string();
                tracing::warn!(%source, %error, "ingest failed");
                let (size, mtime_unix) = size_mtime(path).unwrap_or((0, 0));
                let rec = FailedRecord {
                    source: source.clone(),
                    error: error.clone(),
                    size,
                    mtime_unix,
                    at_unix: now_unix(),
                };
                if let Err(e) = self.with_store(|s| s.record_failure(&rec)) {
                    tracing::error!(%source, error = %e, "could not record the failure");
                }
                self.emit(Outcome::Failed, None, &source, &error, Vec::new());
                Ingested {
                    source,
                    outcome: Outcome::Failed,
                    survey: None,
                    error,
                    samples: 0,
                    seconds,
                    conflicts: Vec::new(),
                }
            }
        }
    }

    fn ingest_inner(
        &self,
        path: &Path,
        source: &str,
        accuracy: Option<f64>,
    ) -> Result<(Outcome, SurveyId, u64, Vec<Conflict>), EngineError> {
        let settings = IngestSettings {
            accuracy,
            default_accuracy: self.cfg.accuracy_m,
            max_accuracy: self.cfg.index.max_error,
            store_crs: self.crs(),
            // An existing store keeps the layout its tops were computed with.
            layout: self.with_store(|s| Ok(s.layout()))?,
            read_limits: crate::read::ReadLimits::mb(self.cfg.limits.max_ingest_mb),
            heights: (self.cfg.limits.min_height_m, self.cfg.limits.max_height_m),
        };
        let prepared = prepare(path, &settings).map_err(ingest_error)?;
        let survey = prepared.survey;
        let samples = survey.levels[0].valid_count() as u64;
        let content = file_content_id(path).map_err(|e| EngineError::Invalid(e.to_string()))?;
        let _w = self.writer.lock().expect("writer lock");
        let current = self.snapshot();
        let previous = self.active_from(source)?;
        if current.survey(survey.id).is_some() {
            // The content is already served (from this path or a copy elsewhere); what this
            // path held before, if anything else, is gone.
            if let Some(old) = previous.filter(|o| o.id != survey.id) {
                self.retire_locked(&current, &old)?;
            }
            self.with_store(|s| s.clear_failure(source))?;
            return Ok((Outcome::Unchanged, survey.id, samples, Vec::new()));
        }
        let survey = Arc::new(survey);
        let mut next = (*current).clone();
        let t1 = Instant::now();
        let rec =
            |s: &Arc<Survey>| record(s, source, &content, prepared.source, prepared.timings, t1);
        let outcome = match &previous {
            Some(old) => {
                let old_patches: Vec<_> = current
                    .index()
                    .survey_patches(old.id)
                    .map(|p| p.to_vec())
                    .unwrap_or_default();
                let retire: ChangeStats = next.retire(old.id).unwrap_or_default();
                let insert = next.insert(survey.clone());
                let overlaps = overlaps_with(&next, &survey);
                let rec = rec(&survey);
                self.with_store(|s| {
                    s.commit_replace(
                        old.id,
                        &old_patches,
                        &retire,
                        &survey,
                        &rec,
                        &insert,
                        &overlaps,
                    )
                })?;
                (Outcome::Replaced, overlaps)
            }
            None => {
                let insert = next.insert(survey.clone());
                let overlaps = overlaps_with(&next, &survey);
                let rec = rec(&survey);
                self.with_store(|s| s.commit_survey(&survey, &rec, &insert, &overlaps))?;
                (Outcome::Inserted, overlaps)
            }
        };
        // The commit cleared any failure recorded for this source in the same batch.
        self.publish(next);
        let (outcome, overlaps) = outcome;
        let records = self.with_store(|s| s.surveys())?;
        let accuracy = |id: SurveyId| records.iter().find(|r| r.id == id).map(|r| r.accuracy);
        let conflicts = overlaps
            .iter()
            .filter_map(|(o, d)| conflict(survey.accuracy, accuracy(*o)?, *o, d))
            .collect();
        Ok((outcome, survey.id, samples, conflicts))
    }

    /// Retires a survey named by id or by the source path it came from.
    pub fn retire(&self, id_or_source: &str) -> Result<(SurveyId, usize), EngineError> {
        let _w = self.writer.lock().expect("writer lock");
        let records = self.with_store(|s| s.surveys())?;
        let wanted = id_or_source.parse::<SurveyId>().ok();
        let absolute = source_name(Path::new(id_or_source));
        let rec = records
            .iter()
            .find(|r| {
                r.status == Status::Active
                    && (Some(r.id) == wanted || r.source == id_or_source || r.source == absolute)
            })
            .ok_or_else(|| {
                EngineError::NotFound(format!(
                    "no active survey has id or source {id_or_source:?}; `patchwork surveys` lists them"
                ))
            })?;
        let n = self.retire_locked(&self.snapshot(), rec)?;
        Ok((rec.id, n))
    }

    /// Retires `rec` from `current`; the caller holds the writer lock.
    fn retire_locked(&self, current: &Terrain, rec: &SurveyRecord) -> Result<usize, EngineError> {
        let patches: Vec<_> = current
            .index()
            .survey_patches(rec.id)
            .map(|p| p.to_vec())
            .unwrap_or_default();
        let mut next = current.clone();
        let change = next.retire(rec.id).unwrap_or_default();
        self.with_store(|s| s.commit_retire(rec.id, &patches, &change))?;
        self.publish(next);
        tracing::info!(survey = %rec.id, source = %rec.source, "retired");
        self.emit(Outcome::Retired, Some(rec.id), &rec.source, "", Vec::new());
        Ok(patches.len())
    }

    /// Every survey record and the failed files.
    pub fn records(&self) -> Result<(Vec<SurveyRecord>, Vec<FailedRecord>), EngineError> {
        self.with_store(|s| Ok((s.surveys()?, s.failures()?)))
    }

    /// Every survey record, the failed files, and each active survey's conflicts.
    pub fn surveys(&self) -> Result<SurveyListing, EngineError> {
        self.with_store(|s| {
            let records = s.surveys()?;
            let accuracy: HashMap<SurveyId, f64> = records
                .iter()
                .filter(|r| r.status == Status::Active)
                .map(|r| (r.id, r.accuracy))
                .collect();
            let mut conflicts = HashMap::new();
            for (id, a) in &accuracy {
                let mine: Vec<Conflict> = s
                    .overlaps(*id)?
                    .iter()
                    .filter_map(|(o, d)| conflict(*a, *accuracy.get(o)?, *o, d))
                    .collect();
                if !mine.is_empty() {
                    conflicts.insert(*id, mine);
                }
            }
            Ok(SurveyListing {
                records,
                failures: s.failures()?,
                conflicts,
            })
        })
    }

    pub fn stats(&self) -> Result<Stats, EngineError> {
        let (records, failures) = self.records()?;
        let t = self.snapshot();
        let active: Vec<_> = records
            .iter()
            .filter(|r| r.status == Status::Active)
            .collect();
        Ok(Stats {
            surveys: active.len() as u32,
            retired: (records.len() - active.len()) as u32,
            failed: failures.len() as u32,
            patches: t.index().len() as u64,
            active_boxes: t.index().active_count() as u64,
            samples: active.iter().map(|r| r.samples).sum(),
            disk_bytes: self.with_store(|s| Ok(s.disk_bytes()))?,
            crs: self.crs(),
            backend: self.backend_name(),
            quadtree_nodes: t.index().tree_stats().nodes as u32,
        })
    }

    pub fn verify(&self) -> Result<crate::store::VerifyReport, EngineError> {
        self.with_store(|s| s.verify())
    }

    /// Physically removes retired surveys and rewrites the store's files.
    pub fn compact(&self) -> Result<crate::store::CompactReport, EngineError> {
        let _w = self.writer.lock().expect("writer lock");
        let store = self
            .store
            .lock()
            .expect("store lock")
            .take()
            .ok_or_else(|| EngineError::Unavailable("the store is being compacted".into()))?;
        let dir = store.path().to_path_buf();
        let live = self.snapshot().index().state().into_keys().collect();
        match store.compact(&live) {
            Ok((opened, report)) => {
                *self.store.lock().expect("store lock") = Some(opened.store);
                self.publish(opened.terrain);
                Ok(report)
            }
            Err(e) => {
                // Compaction leaves the old files in place on failure: reopen them.
                let opened = Store::open(&dir, self.cfg.patches, self.cfg.index)?;
                *self.store.lock().expect("store lock") = Some(opened.store);
                self.publish(opened.terrain);
                Err(e.into())
            }
        }
    }

    fn metric_at(&self, lat: f64) -> Metric {
        match self.crs() {
            Some(c) if is_geographic(c) => Metric::geographic(lat),
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

    /// The patches of a cut, with the snapshot they came from.
    pub fn query(&self, cut: &Cut) -> Result<(Arc<Terrain>, Vec<Extracted>), EngineError> {
        let t = self.snapshot();
        let ps = match cut {
            Cut::Uniform { roi, error } => {
                check_roi(roi)?;
                check_error(*error)?;
                t.uniform(roi, *error)
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
            Cut::View(v) => SampleGrid::view(v, width as usize, height as usize, v.look[2]),
        };
        if backend != Backend::Cpu {
            let mut gpu = self.gpu.lock().expect("gpu lock");
            match gpu.as_mut() {
                Some(g) => match g.resample(&t.resolve(&ps), &grid) {
                    Ok(heights) => {
                        let tile = Tile {
                            width: grid.width,
                            height: grid.height,
                            heights,
                            patches: ps,
                        };
                        return Ok((tile, "gpu"));
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
                },
                None if backend == Backend::Gpu => return Err(EngineError::Unavailable(
                    "backend gpu was asked for, but this daemon has no GPU device; use auto or cpu"
                        .into(),
                )),
                None => {}
            }
        }
        Ok((t.resample(ps, &grid), "cpu"))
    }

    /// Heights at points, at error `e`: what any tile holding the same points gives there.
    pub fn sample(&self, points: &[[f64; 2]], e: f64) -> Result<Vec<f32>, EngineError> {
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
        Ok(self.snapshot().sample(points, e))
    }
}

/// How a new survey disagrees with every survey of the terrain it overlaps.
fn overlaps_with(t: &crate::terrain::Terrain, s: &Survey) -> Vec<(SurveyId, Deviation)> {
    let others: Vec<&Arc<Survey>> = t.surveys().filter(|o| o.id != s.id).collect();
    let mut out: Vec<(SurveyId, Deviation)> = others
        .par_iter()
        .filter_map(|o| s.overlap(o).map(|d| (o.id, d)))
        .collect();
    out.sort_by_key(|(id, _)| *id);
    out
}

/// A conflict, when two surveys of accuracies `a` and `b` disagree by more than a + b.
fn conflict(a: f64, b: f64, other: SurveyId, d: &Deviation) -> Option<Conflict> {
    (d.max_m > a + b).then_some(Conflict {
        survey: other,
        max_m: d.max_m,
        rms_m: d.rms_m,
    })
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

fn ingest_error(e: IngestError) -> EngineError {
    EngineError::Invalid(e.to_string())
}

fn record(
    s: &Survey,
    source: &str,
    content: &str,
    accuracy_source: AccuracySource,
    t: crate::ingest::Timings,
    index_start: Instant,
) -> SurveyRecord {
    SurveyRecord::new(
        s,
        source,
        content,
        accuracy_source,
        IngestTimings {
            read_ms: t.read_ms as f64,
            build_ms: t.build_ms as f64,
            index_ms: index_start.elapsed().as_secs_f64() * 1e3,
            commit_ms: 0.0,
        },
    )
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
    abs.to_string_lossy().into_owned()
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
