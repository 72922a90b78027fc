//! The writer: ingest, retire, repair, forget, verify and compact. One writer holds the store
//! at a time; it computes the next terrain on a copy, commits the change in one batch, and
//! publishes the copy with the catalog the store now holds.

use super::error::{ingest_reason, Reason};
use super::listing::{conflicts_of, Conflict};
use super::{release_free_memory, store_options, Engine, EngineError, Phase, Progress};
use crate::ingest::{open_file, prepare_with, IngestError, IngestSettings};
use crate::paths::{size_mtime, source_name};
use crate::restore;
use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::ChangeStats;
use patchwork_core::model::ids::SurveyId;
use patchwork_core::model::place::Planes;
use patchwork_core::model::survey::{Survey, SurveyMeta};
use patchwork_core::sync::{lock, write};
use patchwork_core::terrain::Terrain;
use patchwork_read::{content_id, file_content_id, ReadError, ReadLimits, REFUSED_PATH};
use patchwork_store::{
    now_unix, Catalog, Change, CompactFailed, Damaged, FailedRecord, IngestTimings, Insertion,
    Retirement, Store, StoreError, SurveyRecord,
};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// What happened to a file or a survey.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// A new survey was inserted.
    Inserted,
    /// The same path held another survey, which this one replaced in one commit.
    Replaced,
    /// The content is already served, or was retired by hand; nothing changed.
    Unchanged,
    /// A survey was retired: by hand, or because its file was deleted from the inbox.
    Retired,
    /// The file could not be ingested; its `error` says why.
    Failed,
}

impl Outcome {
    /// The outcome as events, logs and the API name it.
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

/// A change to the store, for subscribers.
#[derive(Clone, Debug, PartialEq)]
pub struct Event {
    /// What happened.
    pub kind: Outcome,
    /// The survey inserted, replacing another or retired; `None` for a failure.
    pub survey: Option<SurveyId>,
    /// The survey's source: the absolute path of its file.
    pub source: String,
    /// Why the file failed; empty unless it did.
    pub error: String,
    /// When, in seconds since the Unix epoch.
    pub at_unix: u64,
    /// For an inserted or replacing survey, the surveys it conflicts with.
    pub conflicts: Vec<Conflict>,
    /// Where in the store's plane the terrain may have changed: the footprints of the
    /// surveys that came and went, grown by the cells that edge patches reach across. None
    /// for a failure, which changes nothing served.
    pub area: Option<Aabb>,
}

/// Where a survey's arrival or departure can change heights: its footprint (its samples'
/// bounds) grown by two of its cells, the half pixel every survey reaches out to and the cell
/// an edge patch interpolates across to a neighbour.
pub(super) fn changed_area(s: &SurveyMeta) -> Aabb {
    let f = s.footprint();
    let g = &s.shapes[0];
    let cell =
        (f.width() / (g.cols.max(2) - 1) as f64).max(f.height() / (g.rows.max(2) - 1) as f64);
    let m = 2.0 * cell;
    f.grown(m)
}

/// The outcome of ingesting one file.
#[derive(Clone, Debug)]
pub struct Ingested {
    /// The absolute path the survey is known by (see [`crate::paths::source_name`]).
    pub source: String,
    /// What became of the file.
    pub outcome: Outcome,
    /// The survey that serves the file's content; `None` for a failure.
    pub survey: Option<SurveyId>,
    /// Why the file failed, in words; empty unless it did.
    pub error: String,
    /// Why the file failed; None unless it did.
    pub reason: Option<Reason>,
    /// The survey's valid samples at level 0; 0 for a failure.
    pub samples: u64,
    /// How long the ingest took, its wait for a slot included.
    pub seconds: f64,
    /// For an inserted or replacing survey, the surveys it conflicts with.
    pub conflicts: Vec<Conflict>,
}

/// One of the engine's ingest slots, given back when dropped.
struct IngestSlot<'a>(&'a Engine);

impl Drop for IngestSlot<'_> {
    fn drop(&mut self) {
        let (count, freed) = &self.0.ingest_slots;
        *lock(count) -= 1;
        freed.notify_one();
    }
}

/// What one file's ingest committed (or found already served).
struct Committed {
    outcome: Outcome,
    /// The survey the file's content is served as.
    survey: SurveyId,
    /// Its valid samples at level 0.
    samples: u64,
    /// The surveys it conflicts with, for a survey inserted or replacing another.
    conflicts: Vec<Conflict>,
}

impl Engine {
    /// Runs `f` as the writer. `f` returns the terrain it committed, if it changed it; that
    /// terrain is published with the catalog as the store now holds it.
    fn write<T>(
        &self,
        f: impl FnOnce(&mut Store, &Arc<Terrain>) -> Result<(T, Option<Terrain>), StoreError>,
    ) -> Result<T, EngineError> {
        self.write_and(f, |_| {})
    }

    /// [`Engine::write`], then `after` with the result once it is published, still as the
    /// writer: what `after` sends (change events) goes out in commit order.
    fn write_and<T>(
        &self,
        f: impl FnOnce(&mut Store, &Arc<Terrain>) -> Result<(T, Option<Terrain>), StoreError>,
        after: impl FnOnce(&T),
    ) -> Result<T, EngineError> {
        if let Some(why) = self.broken.get() {
            return Err(EngineError::StoreFailed(why.clone()));
        }
        self.refuse_on_replica()?;
        let mut guard = lock(&self.writer);
        let store = guard.as_mut().ok_or_else(|| EngineError::NotOpen)?;
        let current = self.snapshot();
        let done = f(store, &current);
        write(&self.replication).commit = store.commit_seq();
        let (v, next) = done.map_err(|e| self.failed(e))?;
        // The change is committed: its terrain is published whatever happens next, or later
        // writes would build on a terrain the store no longer holds.
        let catalog = store.catalog();
        let mut p = write(&self.published);
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

    /// Waits for one of the `limits.ingest_parallel` ingest slots; the slot is given back
    /// when the guard goes.
    fn ingest_slot(&self) -> IngestSlot<'_> {
        let (count, freed) = &self.ingest_slots;
        let mut n = lock(count);
        while *n >= self.cfg.limits.ingest_parallel {
            n = freed.wait(n).unwrap_or_else(|e| e.into_inner());
        }
        *n += 1;
        IngestSlot(self)
    }

    /// Notes a store error; one from sled's I/O leaves its handle unusable.
    pub(super) fn failed(&self, e: StoreError) -> EngineError {
        if let StoreError::Sled(sled::Error::Io(io)) = &e {
            let why = io.to_string();
            if self.broken.set(why.clone()).is_ok() {
                tracing::error!(error = %why, "the store failed under a write: no more writes until restart; reads go on");
            }
            return EngineError::StoreFailed(why);
        }
        EngineError::Store(e)
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
        let failed = |reason: Reason, error: String| Ingested {
            source: source.clone(),
            outcome: Outcome::Failed,
            survey: None,
            error,
            reason: Some(reason),
            samples: 0,
            seconds: t0.elapsed().as_secs_f64(),
            conflicts: Vec::new(),
        };
        // Before the file is read: a replica would only model it to refuse the commit.
        self.refuse_on_replica()?;
        let slot = self.ingest_slot();
        lock(&self.progress).push(Progress {
            source: source.clone(),
            bytes: std::fs::metadata(path).map_or(0, |m| m.len()),
            phase: Phase::Reading,
            started: Instant::now(),
        });
        let mut content = None;
        let result = self.ingest_inner(path, &source, accuracy, origin, &mut content);
        let idle = {
            let mut progress = lock(&self.progress);
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
                Ok(failed(Reason::OutsideIngestFolders, REFUSED_PATH.into()))
            }
            Ok(c) => {
                let seconds = t0.elapsed().as_secs_f64();
                if c.outcome != Outcome::Unchanged {
                    tracing::info!(source = ?source, survey = %c.survey, outcome = c.outcome.as_str(), seconds, conflicts = c.conflicts.len(), "ingested");
                }
                Ok(Ingested {
                    source,
                    outcome: c.outcome,
                    survey: Some(c.survey),
                    error: String::new(),
                    reason: None,
                    samples: c.samples,
                    seconds,
                    conflicts: c.conflicts,
                })
            }
            Err(Refusal::Store(e)) => {
                tracing::warn!(source = ?source, error = ?e.to_string(), "ingest deferred: the store cannot take it now");
                Err(e)
            }
            Err(Refusal::File(reason, error)) => {
                tracing::warn!(source = ?source, error = ?error, reason = reason.as_str(), "ingest failed");
                self.record_failure(path, &source, &error, content.as_deref());
                Ok(failed(reason, error))
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
            self.emit(Outcome::Failed, None, source, error, Vec::new(), None);
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
            |_| self.emit(Outcome::Failed, None, source, error, Vec::new(), None),
        );
        if let Err(e) = recorded {
            tracing::warn!(source = ?source, error = ?e.to_string(), "could not record the failure");
            self.emit(Outcome::Failed, None, source, error, Vec::new(), None);
        }
    }

    fn ingest_inner(
        &self,
        path: &Path,
        source: &str,
        accuracy: Option<f64>,
        origin: Origin,
        content_out: &mut Option<String>,
    ) -> Result<Committed, Refusal> {
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
            e => Refusal::File(ingest_reason(&e), e.to_string()),
        };
        // This look decides only whether the file needs reading at all (its content may be
        // served already). What a new survey records is the content id of the very bytes its
        // parse read (`Prepared::content_id`): the file may change between the two.
        let handle = open_file(path, Some(&roots)).map_err(file)?;
        let content = content_id(&handle).map_err(|e| {
            Refusal::File(
                Reason::Unreadable,
                format!("cannot read {}: {e}", path.display()),
            )
        })?;
        drop(handle);
        let content = crate::ingest::with_sidecar(path, content, Some(&roots));
        *content_out = Some(content.clone());
        if path.to_str().is_none() {
            // Sources are text everywhere (listings, events, the wire): a name that is not
            // cannot be one. Recorded under its escaped name, so that it is seen and can be
            // forgotten.
            return Err(Refusal::File(
                Reason::InvalidRequest,
                format!("the file name {source} is not valid UTF-8: rename the file to ingest it"),
            ));
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
                                .values()
                                .rev()
                                .find(|r| r.content_id == content)
                                .map(|r| &**r)
                        })
                        .flatten()
                });
            if let Some(r) = kept {
                return Ok(Committed {
                    outcome: Outcome::Unchanged,
                    survey: r.id,
                    samples: r.samples,
                    conflicts: Vec::new(),
                });
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
                    .map_err(|e| Refusal::File(Reason::Crs, e.to_string()))?
            }
            None => prepared.survey.clone(),
        };
        let survey = Arc::new(survey);
        // Which survey serves where the ground changed follows from the epochs, through every
        // pair the survey is in: a new epoch for the same samples is a new survey, not a new
        // label. (The writer's turn below sees the same surveys: only this path writes them.)
        if let Some(served) = self.snapshot().survey(survey.id) {
            if served.epoch != survey.epoch {
                return Err(Refusal::File(
                    Reason::InvalidRequest,
                    format!(
                        "the sidecar's acquired changed ({} to {}) for samples already \
                         served; retire the survey and add the file again",
                        epoch_text(served.epoch),
                        epoch_text(survey.epoch)
                    ),
                ));
            }
        }
        let samples = survey.levels[0].valid_count() as u64;
        let t1 = Instant::now();
        let mut conflicts = Vec::new();
        let area = std::cell::Cell::new(None);
        let outcome = self
            .write_and(
                |store, current| {
                    self.set_phase(source, Phase::Indexing);
                    let previous = store_active_from(&self.catalog(), source);
                    let before = previous
                        .as_ref()
                        .and_then(|o| current.survey(o.id))
                        .map(|o| changed_area(o));
                    let now = changed_area(&survey.meta);
                    area.set(Some(before.map_or(now, |b| b.union(&now))));
                    if current.survey(survey.id).is_some() {
                        // The content is already served (from this path or a copy elsewhere);
                        // what this path held before, if anything else, is gone.
                        let same = previous.as_ref().is_some_and(|o| o.id == survey.id);
                        let next = match previous.filter(|o| o.id != survey.id) {
                            Some(old) => Some(retire_in(store, current, &old, false)?),
                            None => None,
                        };
                        store.clear_failure(source)?;
                        if same {
                            // This file's samples are the same; what its sidecar says of them
                            // may not be.
                            store.set_about(survey.id, &prepared.about, &prepared.content_id)?;
                        }
                        return Ok(((Outcome::Unchanged, Vec::new()), next));
                    }
                    let mut next = (**current).clone();
                    // The record, once the index work is done, so that it can say how long
                    // that took.
                    let rec = || {
                        record(&survey, source, &prepared, t1)
                    };
                    // The index work and the encoding of the samples need nothing of each
                    // other: the chunks go to the pack while the index takes the survey in.
                    let shared: &Store = store;
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
                        || shared.pack_survey(&survey),
                    );
                    let ((retire, insert, pairs), packed) = (indexed?, packed?);
                    self.set_phase(source, Phase::Committing);
                    let record = rec();
                    let insertion = Insertion {
                        survey: &survey,
                        record: &record,
                        change: &insert,
                        pairs: &pairs,
                        packed,
                    };
                    let outcome = match &previous {
                        Some(old) => {
                            store.commit(Change {
                                retire: Some(Retirement {
                                    id: old.id,
                                    change: &retire,
                                    pin: false,
                                }),
                                insert: Some(insertion),
                                edges: &next.edges_of(&[&retire, &insert]),
                            })?;
                            Outcome::Replaced
                        }
                        None => {
                            store.commit(Change {
                                insert: Some(insertion),
                                edges: &next.edges_of(&[&insert]),
                                ..Change::default()
                            })?;
                            Outcome::Inserted
                        }
                    };
                    let outcome = (outcome, conflicts_of(&next, survey.id));
                    // The samples are on disk now; the terrain reads them from there, and
                    // makes its new edge patches' again from them.
                    next.page_out(survey.id);
                    next.page_out_edges(&[&retire, &insert]);
                    Ok((outcome, Some(next)))
                },
                |(outcome, found)| {
                    if *outcome == Outcome::Unchanged {
                        return;
                    }
                    let catalog = self.catalog();
                    if let Some(r) = catalog.record(survey.id) {
                        let t = &r.ingest;
                        tracing::debug!(source = ?source, read_ms = t.read_ms, build_ms = t.build_ms, index_ms = t.index_ms, commit_ms = t.commit_ms, "ingest timings");
                    }
                    conflicts = found.clone();
                    self.emit(*outcome, Some(survey.id), source, "", conflicts.clone(), area.get());
                },
            )
            .map_err(Refusal::Store)?
            .0;
        Ok(Committed {
            outcome,
            survey: survey.id,
            samples,
            conflicts,
        })
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
            .ok_or_else(|| EngineError::NoSurvey(id_or_source.to_string()))?;
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
                .map(|c| crate::ingest::with_sidecar(Path::new(&rec.source), c, Some(&inbox)))
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
        let area = std::cell::Cell::new(None);
        let n = self.write_and(
            |store, current| {
                area.set(current.survey(rec.id).map(|s| changed_area(s)));
                // Another writer may have retired it since the catalog was read.
                if store_active_from(&self.catalog(), &rec.source).is_none_or(|r| r.id != rec.id) {
                    return Err(StoreError::NotActive(rec.id));
                }
                let n = current.index().unit_len(rec.id).unwrap_or(0);
                let next = retire_in(store, current, rec, pin)?;
                Ok((n, Some(next)))
            },
            |_| {
                self.emit(
                    Outcome::Retired,
                    Some(rec.id),
                    &rec.source,
                    "",
                    Vec::new(),
                    area.get(),
                )
            },
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

    /// Re-checks the whole store against what inserting its surveys again derives (see
    /// [`restore::verify`]), holding the writer meanwhile; `stats` shows how far it has got.
    pub fn verify(&self) -> Result<patchwork_store::VerifyReport, EngineError> {
        let guard = lock(&self.writer);
        let store = guard.as_ref().ok_or(EngineError::NotOpen)?;
        let started = std::time::Instant::now();
        let report = restore::verify_with(store, &|step, done, total| {
            *lock(&self.verifying) = Some(super::listing::Verifying {
                step,
                done,
                total,
                started,
            });
        });
        *lock(&self.verifying) = None;
        Ok(report?)
    }

    /// Physically removes retired surveys and rewrites the store's files.
    pub fn compact(&self) -> Result<patchwork_store::CompactReport, EngineError> {
        if let Some(why) = self.broken.get() {
            return Err(EngineError::StoreFailed(why.clone()));
        }
        self.refuse_on_replica()?;
        let mut guard = lock(&self.writer);
        let store = guard.take().ok_or(EngineError::NotOpen)?;
        let live = self.snapshot().index().state().into_keys().collect();
        let result = restore::compact(store, &live);
        let (opened, report) = match result {
            Ok((opened, report)) => (opened, Ok(report)),
            // A failure before the swap (a full disk, say) gives the store back as it was:
            // the terrain published from it stands.
            Err(CompactFailed {
                store: Some(store),
                error,
            }) => {
                *guard = Some(*store);
                return Err(error.into());
            }
            // Compaction leaves the old files in place on failure: reopen them.
            Err(CompactFailed {
                store: None,
                error: e,
            }) => {
                let opened = restore::open_within(
                    &self.dir,
                    self.cfg.patches.layout(),
                    self.cfg.index,
                    store_options(&self.cfg, &self.guard)?,
                    self.region.as_ref(),
                )?;
                (opened, Err(e.into()))
            }
        };
        let catalog = opened.store.catalog()?;
        *write(&self.reader) = opened.store.reader();
        write(&self.replication).commit = opened.store.commit_seq();
        self.publish(opened.terrain, catalog);
        *guard = Some(opened.store);
        drop(guard);
        // The old terrain, its chunk cache and the old database's pages are free now (unless a
        // request still holds that terrain): given back to the system, not kept by the
        // allocator, which otherwise held ~60 MB more after every compaction (RSS 250 → 490 MB
        // over five rounds of load and compaction on a four-survey store).
        release_free_memory();
        report
    }
}

/// Why an ingest did not happen: the path leads outside, the file's fault, or the store's.
enum Refusal {
    Outside,
    /// The file is at fault: why, in kind and in words.
    File(Reason, String),
    Store(EngineError),
}

/// The active survey `source` holds, as the store has it: a damaged one included, which a new
/// ingest of the file replaces. Read from the catalog, which the writer publishes after every
/// commit and so is the store's own while the writer is held, rather than by decoding every
/// record again.
fn store_active_from(catalog: &Catalog, source: &str) -> Option<SurveyRecord> {
    catalog.stored_active_from(source).cloned()
}

/// Commits the retirement of `rec` from `current` and returns the terrain without it.
fn retire_in(
    store: &mut Store,
    current: &Terrain,
    rec: &SurveyRecord,
    pin: bool,
) -> Result<Terrain, StoreError> {
    let mut next = current.clone();
    let change = next.try_retire(rec.id)?.unwrap_or_default();
    store.commit(Change {
        retire: Some(Retirement {
            id: rec.id,
            change: &change,
            pin,
        }),
        edges: &next.edges_of(&[&change]),
        ..Change::default()
    })?;
    next.page_out_edges(&[&change]);
    Ok(next)
}

fn record(
    s: &Survey,
    source: &str,
    prepared: &crate::ingest::Prepared,
    index_start: Instant,
) -> SurveyRecord {
    let t = prepared.timings;
    let mut rec = SurveyRecord::new(
        s,
        source,
        &prepared.content_id,
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
    rec.about = prepared.about.clone();
    rec
}

fn epoch_text(e: Option<patchwork_core::model::epoch::Epoch>) -> String {
    e.map_or_else(|| "unknown".to_string(), |e| e.to_string())
}
