//! The inbox watcher, in three parts: a trigger (file-system events and a timer) that only
//! wakes the reconciler; discovery, which lists what the inbox folders hold; and a sink (the
//! engine) that takes the files and retirements the reconciler decides on. A burst of events,
//! a full channel or changes made while the daemon was down all end in the same place: a
//! store that matches the inbox.
//!
//! A file is ingested once its stamp (size, mtime, ctime, inode) has stayed the same for
//! `settle_ms`, or at once when it is known complete: it arrived by rename (the usual way to
//! publish a finished file), or its writer closed it. The stamp only says when to look: a file
//! is unchanged only if its content is, which the engine decides by the hash of its bytes. A
//! file rewritten in place with its size and mtime kept (`cp -p`, `rsync -a`, tar) still has
//! a new ctime, and one renamed into place a new inode. A file that fails is recorded once
//! and not retried until its stamp changes, and across restarts until its content does; one
//! the store could not take (a full disk) is tried again on a later pass.
//!
//! Only a file seen missing from a folder that is there retires its survey. A folder that is
//! gone, or empty while surveys came from it (a share not mounted yet), retires nothing: the
//! watcher warns, keeps the surveys, and watches the folder again once it is back.

use crate::config::OnDelete;
use crate::ingest::is_temporary;
use crate::paths::{escaped, source_name};
use crate::{Engine, EngineError, Held, Ingested, Origin};
use notify::event::{AccessKind, AccessMode, EventKind, ModifyKind, RenameMode};
use notify_debouncer_full::{new_debouncer, DebounceEventResult};
use patchwork_core::sync::lock;
use patchwork_read::file_content_id;
use patchwork_store::Catalog;
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// Where the reconciler's decisions go: the engine, or a fake in tests.
pub trait Sink: Send + Sync + 'static {
    /// The records, failures and pins as the store holds them now: what the inbox is matched
    /// against.
    fn catalog(&self) -> Arc<Catalog>;
    /// Ingests a file found in the inbox. An error is the store's: try again later.
    fn ingest(&self, path: &Path) -> Result<Ingested, EngineError>;
    /// Retires the survey of a file seen deleted.
    fn retire_deleted(&self, source: &str) -> Result<(), EngineError>;
    /// How many files the sink takes at once.
    fn parallel(&self) -> usize {
        1
    }
    /// Says that `source` is held back, and why (None: no longer).
    fn hold(&self, _source: &str, _why: Option<Held>) {}
    /// Bytes the store may still write: a file deferred for lack of space is read again
    /// once this grows.
    fn free_bytes(&self) -> u64 {
        u64::MAX
    }
}

impl Sink for Engine {
    fn catalog(&self) -> Arc<Catalog> {
        Engine::catalog(self)
    }

    fn ingest(&self, path: &Path) -> Result<Ingested, EngineError> {
        Engine::ingest(self, path, None, Origin::Inbox)
    }

    fn retire_deleted(&self, source: &str) -> Result<(), EngineError> {
        Engine::retire_deleted(self, source)
    }

    fn parallel(&self) -> usize {
        self.ingest_parallel()
    }

    fn hold(&self, source: &str, why: Option<Held>) {
        Engine::hold(self, source, why)
    }

    fn free_bytes(&self) -> u64 {
        Engine::free_bytes(self)
    }
}

/// Names beside elevation files that are theirs, not files of their own: world files, GDAL's
/// auxiliary files and overviews, masks, checksums. (Sidecar `.toml` and `.prj` files are
/// passed over with temporary names.)
const COMPANION_EXTENSIONS: [&str; 9] = [
    "xml", "tfw", "tifw", "ovr", "msk", "aux", "hdr", "md5", "sha256",
];

/// Why a file in the inbox that is not a DEM is skipped, or None for a DEM's companion.
fn skipped_reason(p: &Path) -> Option<String> {
    let ext = p
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    if COMPANION_EXTENSIONS.contains(&ext.as_str()) {
        return None;
    }
    Some(format!(
        "not an elevation file{}: the inbox takes GeoTIFF and COG (.tif, .tiff), SRTM (.hgt) \
         and ESRI ASCII grids (.asc)",
        if ext.is_empty() {
            String::new()
        } else {
            format!(" (.{ext})")
        }
    ))
}

/// A file the store could not take (a full disk): when, and what the disk had then.
struct Deferred {
    stamp: Stamp,
    /// [`Sink::free_bytes`] when it was deferred: it is read again once there is more.
    free: u64,
    /// Read again after this all the same, in case space came back unseen (a quota lifted).
    retry_at: Instant,
    wait: Duration,
}

/// Longest a deferred file waits before it is read again with nothing changed.
const MOST_DEFERRED: Duration = Duration::from_secs(600);

/// Extensions of files the readers take. A directory with one of these names is a candidate
/// too, so that it is reported rather than silently skipped.
const DEM_EXTENSIONS: [&str; 4] = ["tif", "tiff", "hgt", "asc"];

fn is_dem_name(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| DEM_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

/// What a file's metadata says of it, by which the watcher tells when to look at it again:
/// none of it can be set back by a writer but the mtime, and the ctime and inode change with
/// any rewrite or rename. None when it cannot be read.
type Stamp = Option<FileStamp>;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct FileStamp {
    /// The file's length in bytes.
    pub size: u64,
    mtime: (i64, i64),
    ctime: (i64, i64),
    dev: u64,
    ino: u64,
    /// The sidecar's own (size, mtime, ctime, inode), where there is one: adding, editing or
    /// removing it changes the file's stamp, and the file is looked at again.
    sidecar: Option<SidecarStamp>,
}

/// A sidecar's size, mtime, ctime and inode.
type SidecarStamp = (u64, (i64, i64), (i64, i64), u64);

/// The stamp of the file at `p`, following symlinks.
fn stamp(p: &Path) -> Stamp {
    use std::os::unix::fs::MetadataExt;
    let m = std::fs::metadata(p).ok()?;
    let sidecar = std::fs::metadata(crate::ingest::sidecar_path(p))
        .ok()
        .map(|s| {
            (
                s.len(),
                (s.mtime(), s.mtime_nsec()),
                (s.ctime(), s.ctime_nsec()),
                s.ino(),
            )
        });
    Some(FileStamp {
        size: m.len(),
        mtime: (m.mtime(), m.mtime_nsec()),
        ctime: (m.ctime(), m.ctime_nsec()),
        dev: m.dev(),
        ino: m.ino(),
        sidecar,
    })
}

/// Every candidate under `dir`, with its stamp (None when unreadable), into `out`; folders
/// that could not be listed whole go into `incomplete`, since what they hold is unknown, not
/// gone.
fn scan(
    dir: &Path,
    out: &mut HashMap<PathBuf, Stamp>,
    incomplete: &mut Vec<PathBuf>,
    skipped: &mut Vec<(PathBuf, String)>,
) {
    let mut stack = vec![dir.to_path_buf()];
    while let Some(dir) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            incomplete.push(dir);
            continue;
        };
        for e in entries {
            let Ok(e) = e else {
                incomplete.push(dir.clone());
                continue;
            };
            let p = e.path();
            if is_temporary(&p) {
                continue;
            }
            let is_dir = match e.file_type() {
                Ok(t) => t.is_dir(),
                Err(_) => {
                    incomplete.push(p);
                    continue;
                }
            };
            if is_dem_name(&p) {
                out.insert(
                    p.clone(),
                    if is_dir {
                        Some(FileStamp::default())
                    } else {
                        stamp(&p)
                    },
                );
            } else if is_dir {
                stack.push(p);
            } else if let Some(why) = skipped_reason(&p) {
                skipped.push((p, why));
            }
        }
    }
}

/// One inbox folder as configured, and where it resolves while it is there.
struct Root {
    configured: PathBuf,
    /// The resolved folder, while it is there to be trusted.
    real: Option<PathBuf>,
    /// The folder's device and inode when it was last seen holding files.
    identity: Option<(u64, u64)>,
}

/// What discovery found: the candidates under the folders that are there, the folders, and
/// the folders under them that could not be listed.
struct Discovered {
    files: HashMap<PathBuf, Stamp>,
    /// The files' sources, as [`escaped`] writes their paths.
    sources: HashSet<String>,
    /// Resolved folders that are there.
    present: Vec<PathBuf>,
    incomplete: Vec<PathBuf>,
    /// Files that are not elevation files, and why they are skipped.
    skipped: Vec<(PathBuf, String)>,
}

impl Discovered {
    /// Whether `source` is known to be gone: under a folder that is there and was listed
    /// whole, and not found.
    fn gone(&self, source: &str) -> bool {
        let p = Path::new(source);
        self.present.iter().any(|r| p.starts_with(r))
            && !self.incomplete.iter().any(|d| p.starts_with(d))
            && !self.sources.contains(source)
    }
}

/// Resolves `root`, and says whether it can be trusted to list what the inbox holds, with its
/// identity (device and inode). It must exist; and an empty folder that surveys came from
/// counts only if it is the very folder last seen holding files (its files were deleted), not
/// another one: a share unmounted from it or not mounted yet, or a folder made anew.
fn resolve(root: &Root, catalog: &Catalog) -> Option<(PathBuf, (u64, u64))> {
    use std::os::unix::fs::MetadataExt;
    let real = root.configured.canonicalize().ok()?;
    let meta = std::fs::metadata(&real).ok()?;
    let identity = (meta.dev(), meta.ino());
    let mut entries = std::fs::read_dir(&real).ok()?;
    let empty = entries.next().is_none();
    let had_surveys = || {
        catalog
            .active()
            .any(|r| Path::new(&r.source).starts_with(&real))
    };
    if empty && root.identity != Some(identity) && had_surveys() {
        return None;
    }
    Some((real, identity))
}

struct Pending {
    stamp: Stamp,
    since: Instant,
    renamed: bool,
}

/// Decides, from what the inbox folders hold and what the store has, which files to ingest and
/// which surveys to retire; the trigger only says when to look.
pub struct Reconciler<S: Sink> {
    sink: Arc<S>,
    roots: Vec<Root>,
    settle: Duration,
    on_delete: OnDelete,
    /// What each source looked like when it was last ingested or failed.
    done: HashMap<String, Stamp>,
    pending: HashMap<PathBuf, Pending>,
    renamed: HashSet<PathBuf>,
    /// Files the store could not take, by path: not read again until space is freed, they
    /// change, or their wait runs out. A full disk once had two files read and modelled
    /// every 3 s, at 85% of a core.
    deferred: HashMap<PathBuf, Deferred>,
    /// Sources listed as skipped (not elevation files).
    skipped: HashSet<String>,
}

impl<S: Sink> Reconciler<S> {
    /// A reconciler of the folders `inbox` into `sink`, ingesting a file once its stamp has been
    /// stable for `settle`, and doing `on_delete` with surveys whose files are gone. Nothing is
    /// listed until [`Reconciler::startup`].
    pub fn new(sink: Arc<S>, inbox: &[PathBuf], settle: Duration, on_delete: OnDelete) -> Self {
        Reconciler {
            sink,
            roots: inbox
                .iter()
                .map(|d| Root {
                    configured: d.clone(),
                    real: None,
                    identity: None,
                })
                .collect(),
            settle,
            on_delete,
            done: HashMap::new(),
            pending: HashMap::new(),
            renamed: HashSet::new(),
            deferred: HashMap::new(),
            skipped: HashSet::new(),
        }
    }

    /// Lists the folders that are there and what they hold. Returns the folders that came
    /// back (or appeared) since the last look, which the trigger must watch again.
    fn discover(&mut self, catalog: &Catalog) -> (Discovered, Vec<PathBuf>) {
        let mut found = Discovered {
            files: HashMap::new(),
            sources: HashSet::new(),
            present: Vec::new(),
            incomplete: Vec::new(),
            skipped: Vec::new(),
        };
        let mut back = Vec::new();
        for root in &mut self.roots {
            let now = resolve(root, catalog);
            match (&root.real, &now) {
                (None, Some((real, _))) => {
                    tracing::info!(dir = ?root.configured, "inbox folder is there: watching it");
                    back.push(real.clone());
                }
                (Some(_), None) => tracing::warn!(
                    dir = ?root.configured,
                    "inbox folder is gone or empty: its surveys stay, and watching resumes once it is back"
                ),
                _ => {}
            }
            root.real = now.as_ref().map(|(real, _)| real.clone());
            if let Some((real, identity)) = now {
                let before = found.files.len();
                scan(
                    &real,
                    &mut found.files,
                    &mut found.incomplete,
                    &mut found.skipped,
                );
                if found.files.len() > before {
                    root.identity = Some(identity);
                }
                found.present.push(real);
            }
        }
        // The roots are resolved, so the paths under them are already as sources name them.
        found.sources = found.files.keys().map(|p| escaped(p)).collect();
        (found, back)
    }

    /// Whether every inbox folder is there.
    pub fn all_present(&self) -> bool {
        self.roots.iter().all(|r| r.real.is_some())
    }

    /// At start-up: a stored survey whose file still has the same content, a file retired by
    /// hand whose content has not changed, and a failure whose file still holds the bytes
    /// that failed need nothing; everything else (a damaged survey's file among them) is
    /// reconciled by the first pass. Returns the folders there.
    pub fn startup(&mut self) -> Vec<PathBuf> {
        let catalog = self.sink.catalog();
        let (found, _) = self.discover(&catalog);
        for (p, stamp) in &found.files {
            let source = source_name(p);
            let served = catalog.active_from(&source).map(|r| r.content_id.clone());
            let pinned = catalog.pins.get(&source).cloned();
            let failed = catalog
                .failures
                .iter()
                .find(|f| f.source == source)
                .map(|f| f.content_id.clone());
            let known = [served, pinned, failed]
                .into_iter()
                .flatten()
                .filter(|c| !c.is_empty())
                .collect::<Vec<_>>();
            let content = file_content_id(p, None).map(|c| crate::ingest::with_sidecar(p, c, None));
            if !known.is_empty() && content.is_ok_and(|c| known.contains(&c)) {
                self.done.insert(source, *stamp);
            }
        }
        for root in self.roots.iter().filter(|r| r.real.is_none()) {
            tracing::warn!(dir = ?root.configured, "inbox folder is missing or empty: its surveys stay until it is back");
        }
        found.present
    }

    /// One pass: ingest what is ready, retire what is gone. Returns whether anything is still
    /// waiting to settle, and the folders to watch again.
    pub fn pass(&mut self) -> (bool, Vec<PathBuf>) {
        let now = Instant::now();
        let mut ready = Vec::new();
        let catalog = self.sink.catalog();
        let (found, back) = self.discover(&catalog);
        self.note_skipped(&found);
        // Free space is asked only while something waits for it.
        let free = (!self.deferred.is_empty()).then(|| self.sink.free_bytes());
        for (p, stamp) in &found.files {
            let source = source_name(p);
            if self.done.get(&source) == Some(stamp) {
                self.pending.remove(p);
                continue;
            }
            if let (Some(d), Some(free)) = (self.deferred.get(p), free) {
                let room = free > d.free.saturating_add(1 << 20);
                if d.stamp == *stamp && !room && now < d.retry_at {
                    continue;
                }
            }
            let renamed = self.renamed.remove(p);
            let entry = self.pending.entry(p.clone()).or_insert(Pending {
                stamp: *stamp,
                since: now,
                renamed,
            });
            if entry.stamp != *stamp {
                *entry = Pending {
                    stamp: *stamp,
                    since: now,
                    renamed,
                };
            }
            entry.renamed |= renamed;
            if entry.renamed || now.duration_since(entry.since) >= self.settle {
                self.pending.remove(p);
                ready.push((p.clone(), source, *stamp));
            }
        }
        // The files that are ready, several at once: the store's answer does not depend on
        // the order they are taken in, and the sink bounds how many it reads at a time. They
        // go in by path, not in the listing's hash order: a national programme names its
        // tiles by where they lie, so neighbours come one after another, and a commit's edge
        // tiles reach surveys already in (10,000 abutting files dropped at once: each tile's
        // edge patch read 4 members in the first fifth and 15 in the last in hash order).
        ready.sort_by(|a, b| a.0.cmp(&b.0));
        for ((p, source, stamp), result) in ready.iter().zip(self.ingest_all(&ready)) {
            match result {
                Ok(r) => {
                    tracing::debug!(source = ?r.source, outcome = r.outcome.as_str(), "reconciled");
                    self.done.insert(source.clone(), *stamp);
                    if self.deferred.remove(p).is_some() {
                        self.sink.hold(source, None);
                    }
                }
                // Not the file's fault: it is read again once there is room, it changes, or
                // its wait (doubling from 10 s to 10 min) runs out.
                Err(e) => {
                    let wait = match self.deferred.get(p) {
                        Some(d) => (d.wait * 2).min(MOST_DEFERRED),
                        None => {
                            tracing::warn!(source = ?source, error = %e, "ingest deferred until the store has room or the file changes");
                            Duration::from_secs(10)
                        }
                    };
                    self.deferred.insert(
                        p.clone(),
                        Deferred {
                            stamp: *stamp,
                            free: self.sink.free_bytes(),
                            retry_at: Instant::now() + wait,
                            wait,
                        },
                    );
                    self.sink.hold(source, Some(Held::Deferred(e.to_string())));
                }
            }
        }
        self.pending.retain(|p, _| found.files.contains_key(p));
        let sink = &self.sink;
        self.deferred.retain(|p, _| {
            let there = found.files.contains_key(p);
            if !there {
                sink.hold(&source_name(p), None);
            }
            there
        });
        if self.on_delete == OnDelete::Retire {
            self.retire_missing(&found);
        }
        // Files under a folder that is away, or that could not be listed, keep their
        // entries: they are not gone.
        self.done.retain(|s, _| !found.gone(s));
        (!self.pending.is_empty(), back)
    }

    /// Lists the files that are not elevation files as skipped, each once, and forgets those
    /// no longer there.
    fn note_skipped(&mut self, found: &Discovered) {
        for (p, why) in &found.skipped {
            let source = source_name(p);
            if self.skipped.insert(source.clone()) {
                tracing::info!(source = ?source, reason = %why, "skipped");
                self.sink.hold(&source, Some(Held::Skipped(why.clone())));
            }
        }
        // Those in a folder that is away are not gone, only unseen.
        let now: HashSet<String> = found.skipped.iter().map(|(p, _)| source_name(p)).collect();
        let sink = &self.sink;
        self.skipped.retain(|s| {
            let gone =
                !now.contains(s) && found.present.iter().any(|r| Path::new(s).starts_with(r));
            if gone {
                sink.hold(s, None);
            }
            !gone
        });
    }

    /// Ingests files on up to [`Sink::parallel`] threads; the results in the files' order.
    #[allow(clippy::type_complexity)]
    fn ingest_all(&self, ready: &[(PathBuf, String, Stamp)]) -> Vec<Result<Ingested, EngineError>> {
        let workers = self.sink.parallel().clamp(1, ready.len().max(1));
        let next = std::sync::atomic::AtomicUsize::new(0);
        let results: Vec<std::sync::Mutex<Option<Result<Ingested, EngineError>>>> =
            ready.iter().map(|_| std::sync::Mutex::new(None)).collect();
        std::thread::scope(|scope| {
            for _ in 0..workers {
                scope.spawn(|| loop {
                    let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    let Some((p, _, _)) = ready.get(i) else {
                        return;
                    };
                    let r = self.sink.ingest(p);
                    *lock(&results[i]) = Some(r);
                });
            }
        });
        results
            .into_iter()
            .map(|m| {
                m.into_inner()
                    .unwrap_or_else(|e| e.into_inner())
                    .expect("every file was taken")
            })
            .collect()
    }

    fn retire_missing(&mut self, found: &Discovered) {
        let catalog = self.sink.catalog();
        let sources: Vec<String> = catalog
            .active()
            .map(|r| r.source.clone())
            .chain(catalog.pins.keys().cloned())
            .filter(|s| found.gone(s))
            .collect();
        for source in sources {
            if let Err(e) = self.sink.retire_deleted(&source) {
                tracing::warn!(source = ?source, error = ?e.to_string(), "could not retire a deleted file's survey");
                continue;
            }
            // A copy of the same content elsewhere in the inbox was "unchanged" when it
            // arrived; it must now bring the survey back, so look at it again.
            let size = self.done.get(&source).copied().flatten().map(|s| s.size);
            self.done.retain(|_, st| st.map(|s| s.size) != size);
            self.done.remove(&source);
        }
    }
}

/// How often the inbox is listed without an event: a slow pass catches what the watcher
/// misses (network shares, overflow); a folder that is away is looked for more often.
const IDLE_PASS: Duration = Duration::from_secs(30);
const ABSENT_PASS: Duration = Duration::from_secs(2);

/// Watches the inbox folders until `shutdown` resolves.
pub async fn run(engine: Arc<Engine>, mut shutdown: tokio::sync::watch::Receiver<bool>) {
    let cfg = engine.config();
    let catalog = engine.catalog();
    for d in cfg.inbox.iter().filter(|d| !d.exists()) {
        // A missing folder is made on first run; one that surveys came from is away (an
        // unmounted share, say) and is waited for, or files would land beside the mount.
        let abs = std::path::absolute(d).unwrap_or_else(|_| d.clone());
        if catalog
            .active()
            .any(|r| Path::new(&r.source).starts_with(&abs))
        {
            continue;
        }
        if let Err(e) = std::fs::create_dir_all(d) {
            tracing::error!(dir = ?d, error = %e, "cannot create the inbox folder");
        }
    }
    let (tx, mut rx) = mpsc::channel::<Wake>(64);
    // Long enough to see a burst (a copy, then its rename) as one; short beside an ingest.
    let mut debouncer = match new_debouncer(
        Duration::from_millis(100),
        None,
        move |res: DebounceEventResult| {
            let Ok(events) = res else { return };
            // Opening and reading are no change, and the reconciler's own listing of a folder
            // is one: waking on them would have the watcher wake itself for ever.
            let events: Vec<_> = events
                .into_iter()
                .filter(|e| match e.kind {
                    EventKind::Access(AccessKind::Close(AccessMode::Write)) => true,
                    EventKind::Access(_) => false,
                    _ => true,
                })
                .collect();
            if events.is_empty() {
                return;
            }
            // Complete files: renamed into place, or closed by their writer. A copy renamed
            // into place within the debounce window comes out as a creation and a close.
            let renamed: Vec<PathBuf> = events
                .iter()
                .filter(|e| {
                    matches!(
                        e.kind,
                        EventKind::Modify(ModifyKind::Name(RenameMode::To | RenameMode::Both))
                            | EventKind::Access(AccessKind::Close(AccessMode::Write))
                    )
                })
                .flat_map(|e| {
                    e.paths
                        .last()
                        .map(|p| p.canonicalize().unwrap_or_else(|_| p.clone()))
                })
                .collect();
            // A full channel already holds a wake-up; the pass it triggers sees this change too.
            let _ = tx.try_send(if renamed.is_empty() {
                Wake::Changed
            } else {
                Wake::Renamed(renamed)
            });
        },
    ) {
        Ok(d) => Some(d),
        Err(e) => {
            tracing::error!(error = %e, "cannot watch the inbox; only periodic scans will run");
            None
        }
    };
    let mut watch = |dirs: Vec<PathBuf>| {
        if let Some(d) = debouncer.as_mut() {
            for dir in dirs {
                if let Err(e) = d.watch(&dir, notify::RecursiveMode::Recursive) {
                    tracing::error!(dir = ?dir, error = %e, "cannot watch the inbox folder");
                }
            }
        }
    };
    let mut rec = Reconciler::new(
        engine.clone(),
        &cfg.inbox,
        Duration::from_millis(cfg.settle_ms),
        cfg.on_delete,
    );
    let (r, present) = tokio::task::spawn_blocking(move || {
        let present = rec.startup();
        (rec, present)
    })
    .await
    .expect("start-up scan");
    rec = r;
    watch(present);
    let tick = Duration::from_millis((cfg.settle_ms / 2).clamp(100, 2000));
    let mut last_pass = Instant::now();
    let mut waiting = true;
    loop {
        if waiting || !rx.is_empty() {
            let (r, (more, back)) = tokio::task::spawn_blocking(move || {
                let out = rec.pass();
                (rec, out)
            })
            .await
            .expect("reconcile pass");
            rec = r;
            engine.note_inbox_pass();
            watch(back);
            waiting = more;
            last_pass = Instant::now();
        }
        let idle = if rec.all_present() {
            IDLE_PASS
        } else {
            ABSENT_PASS
        };
        let next_idle = idle.saturating_sub(last_pass.elapsed());
        tokio::select! {
            _ = shutdown.changed() => break,
            w = rx.recv() => match w {
                Some(Wake::Renamed(ps)) => { rec.renamed.extend(ps); waiting = true; }
                Some(Wake::Changed) => waiting = true,
                None => break,
            },
            _ = tokio::time::sleep(tick), if waiting => {},
            _ = tokio::time::sleep(next_idle) => waiting = true,
        }
    }
}

enum Wake {
    Changed,
    Renamed(Vec<PathBuf>),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_is_gone_only_from_a_folder_that_is_there_and_was_listed_whole() {
        let found = Discovered {
            files: [(PathBuf::from("/in/a.tif"), Some(FileStamp::default()))].into(),
            sources: ["/in/a.tif".to_string()].into(),
            present: vec![PathBuf::from("/in")],
            incomplete: vec![PathBuf::from("/in/stale")],
            skipped: Vec::new(),
        };
        assert!(!found.gone("/in/a.tif"), "it is there");
        assert!(found.gone("/in/b.tif"), "listed whole and not found");
        assert!(
            !found.gone("/in/stale/c.tif"),
            "its folder could not be listed"
        );
        assert!(!found.gone("/away/d.tif"), "its folder is not there");
    }
}
