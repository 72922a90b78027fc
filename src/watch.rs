//! The inbox watcher. File-system events only wake the reconciler, through a bounded channel;
//! the reconciler then diffs the inbox against what it has seen and what the store holds, so
//! a burst of events, a full channel or changes made while the daemon was down all end in the
//! same place: a store that matches the inbox.
//!
//! A file is ingested once its size and mtime have stayed the same for `settle_ms`, or at once
//! when it arrived by rename (the usual way to publish a finished file). A file that fails is
//! recorded once and not retried until its size or mtime changes.

use crate::config::OnDelete;
use crate::engine::{size_mtime, source_name, Engine};
use crate::ingest::is_temporary;
use crate::store::Status;
use notify::event::{EventKind, ModifyKind, RenameMode};
use notify_debouncer_full::{new_debouncer, DebounceEventResult};
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// Extensions of files the readers take. A directory with one of these names is a candidate
/// too, so that it is reported rather than silently skipped.
const DEM_EXTENSIONS: [&str; 4] = ["tif", "tiff", "hgt", "asc"];

fn is_dem_name(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| DEM_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

enum Wake {
    Changed,
    Renamed(Vec<PathBuf>),
}

/// Every candidate under the inbox folders, with its size and mtime (None when unreadable).
fn scan(dirs: &[PathBuf]) -> HashMap<PathBuf, Option<(u64, u64)>> {
    let mut out = HashMap::new();
    let mut stack: Vec<PathBuf> = dirs.to_vec();
    while let Some(dir) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if is_temporary(&p) {
                continue;
            }
            let is_dir = e.file_type().map(|t| t.is_dir()).unwrap_or(false);
            if is_dem_name(&p) {
                out.insert(
                    p.clone(),
                    if is_dir { Some((0, 0)) } else { size_mtime(&p) },
                );
            } else if is_dir {
                stack.push(p);
            }
        }
    }
    out
}

struct Pending {
    stamp: Option<(u64, u64)>,
    since: Instant,
    renamed: bool,
}

pub struct Reconciler {
    engine: Arc<Engine>,
    dirs: Vec<PathBuf>,
    settle: Duration,
    /// What each source looked like when it was last ingested or failed.
    done: HashMap<String, Option<(u64, u64)>>,
    pending: HashMap<PathBuf, Pending>,
    renamed: HashSet<PathBuf>,
}

impl Reconciler {
    pub fn new(engine: Arc<Engine>) -> Self {
        let cfg = engine.config();
        let dirs = cfg
            .inbox
            .iter()
            .map(|d| d.canonicalize().unwrap_or_else(|_| d.clone()))
            .collect();
        Reconciler {
            settle: Duration::from_millis(cfg.settle_ms),
            engine,
            dirs,
            done: HashMap::new(),
            pending: HashMap::new(),
            renamed: HashSet::new(),
        }
    }

    /// At start-up: a stored survey whose file still has the same content, and a failure whose
    /// file has not changed, need nothing; everything else is reconciled by the first pass.
    pub fn startup(&mut self) {
        let Ok((records, failures)) = self.engine.records() else {
            return;
        };
        let on_disk = scan(&self.dirs);
        for r in records.iter().filter(|r| r.status == Status::Active) {
            let p = PathBuf::from(&r.source);
            if let Some(stamp) = on_disk.get(&p) {
                let same = crate::store::file_content_id(&p).is_ok_and(|c| c == r.content_id);
                if same {
                    self.done.insert(r.source.clone(), *stamp);
                }
            }
        }
        for f in failures {
            if on_disk.get(Path::new(&f.source)) == Some(&Some((f.size, f.mtime_unix))) {
                self.done
                    .insert(f.source.clone(), Some((f.size, f.mtime_unix)));
            }
        }
    }

    /// One pass: ingest what is ready, retire what is gone. Returns whether anything is still
    /// waiting to settle.
    pub fn pass(&mut self) -> bool {
        let now = Instant::now();
        let on_disk = scan(&self.dirs);
        for (p, stamp) in &on_disk {
            let source = source_name(p);
            if self.done.get(&source) == Some(stamp) {
                self.pending.remove(p);
                continue;
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
                let r = self.engine.ingest(p, None);
                tracing::debug!(source = %r.source, outcome = r.outcome.as_str(), "reconciled");
                self.done.insert(source, *stamp);
                self.pending.remove(p);
            }
        }
        self.pending.retain(|p, _| on_disk.contains_key(p));
        if self.engine.config().on_delete == OnDelete::Retire {
            self.retire_missing(&on_disk);
        }
        self.done.retain(|s, _| on_disk.contains_key(Path::new(s)));
        !self.pending.is_empty()
    }

    fn retire_missing(&mut self, on_disk: &HashMap<PathBuf, Option<(u64, u64)>>) {
        let Ok((records, _)) = self.engine.records() else {
            return;
        };
        for r in records.iter().filter(|r| r.status == Status::Active) {
            let p = Path::new(&r.source);
            let in_inbox = self.dirs.iter().any(|d| p.starts_with(d));
            if in_inbox && !on_disk.contains_key(p) {
                if let Err(e) = self.engine.retire(&r.source) {
                    tracing::warn!(source = %r.source, error = %e, "could not retire a deleted file's survey");
                }
                // A copy of the same content elsewhere in the inbox was "unchanged" when it
                // arrived; it must now bring the survey back, so look at it again.
                let size = self.done.get(&r.source).copied().flatten().map(|s| s.0);
                self.done.retain(|_, st| st.map(|s| s.0) != size);
            }
        }
    }
}

/// Watches the inbox folders until `shutdown` resolves.
pub async fn run(engine: Arc<Engine>, mut shutdown: tokio::sync::watch::Receiver<bool>) {
    for d in &engine.config().inbox {
        if let Err(e) = std::fs::create_dir_all(d) {
            tracing::error!(dir = %d.display(), error = %e, "cannot create the inbox folder");
        }
    }
    let (tx, mut rx) = mpsc::channel::<Wake>(64);
    let mut debouncer = match new_debouncer(
        Duration::from_millis(200),
        None,
        move |res: DebounceEventResult| {
            let Ok(events) = res else { return };
            let renamed: Vec<PathBuf> = events
                .iter()
                .filter(|e| {
                    matches!(
                        e.kind,
                        EventKind::Modify(ModifyKind::Name(RenameMode::To | RenameMode::Both))
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
        Ok(d) => d,
        Err(e) => {
            tracing::error!(error = %e, "cannot watch the inbox; only start-up and periodic scans will run");
            return;
        }
    };
    let mut rec = Reconciler::new(engine.clone());
    for d in &rec.dirs {
        if let Err(e) = debouncer.watch(d, notify::RecursiveMode::Recursive) {
            tracing::error!(dir = %d.display(), error = %e, "cannot watch the inbox folder");
        }
    }
    let mut rec = tokio::task::spawn_blocking(move || {
        rec.startup();
        rec
    })
    .await
    .expect("start-up scan");
    let tick = Duration::from_millis((engine.config().settle_ms / 2).clamp(100, 2000));
    // A slow periodic pass catches anything the watcher misses (network shares, overflow).
    let mut idle = tokio::time::interval(Duration::from_secs(30));
    let mut waiting = true;
    loop {
        if waiting || !rx.is_empty() {
            let (r, more) = tokio::task::spawn_blocking(move || {
                let more = rec.pass();
                (rec, more)
            })
            .await
            .expect("reconcile pass");
            rec = r;
            waiting = more;
        }
        tokio::select! {
            _ = shutdown.changed() => break,
            w = rx.recv() => match w {
                Some(Wake::Renamed(ps)) => { rec.renamed.extend(ps); waiting = true; }
                Some(Wake::Changed) => waiting = true,
                None => break,
            },
            _ = tokio::time::sleep(tick), if waiting => {},
            _ = idle.tick() => waiting = true,
        }
    }
}
