//! The persistent store: surveys, their samples and the LOD index's box tops, in one sled tree.
//!
//! Everything but the chunk bytes lives in sled's default tree, so that one `sled::Batch` can
//! commit a survey and every index change it caused atomically; the chunk bytes go to an
//! append-only pack beside it first, and the batch points at them (see [`pack`]). Keys (ids are 16 lowercase hex digits):
//!
//! | key | value |
//! | --- | --- |
//! | `meta/schema` | `u32` LE: the schema version (see `migrations/`) |
//! | `meta/crs` | the store's horizontal CRS as its [`Crs::key`] (UTF-8): the config's, or the first survey's |
//! | `meta/vertical_crs` | the store's vertical CRS as its [`VerticalCrs::key`] (UTF-8): the config's, or the first survey's that names one |
//! | `meta/layout`, `meta/index` | the [`PatchLayout`] and [`IndexConfig`] (bincode) |
//! | `meta/mipmap` | the name of the mipmap [`Filter`] its surveys are built with, set when the store is made (absent: `smooth`, a store from before the choice) |
//! | `meta/patches` | the name of the [`PatchKind`] its surveys' patches are, set when the store is made (absent: `bilinear`, a store from before the choice) |
//! | `meta/contradicted` | `distrust` or `keep`: what the store does with a claim other surveys find false, set when the store is made |
//! | `s/<survey>` | [`SurveyRecord`] (bincode) |
//! | `p/<survey>` | where the survey's [`StoredPatches`] are in the pack: its patches and the edge tiles it reaches (bincode, sealed with [`chunks::seal`]) |
//! | `a/<survey>` | the [`KernelAccuracy`] of a survey whose ε was estimated (bincode) |
//! | `c/<survey>/<level:02>/<k:08>` | where chunk `k` of a level is in the pack ([`pack::Loc`]): [`chunks::CHUNK`]² samples, compressed and checksummed (see [`chunks`]) |
//! | `meta/pack_len` | `u64` LE: the committed length of the chunk pack |
//! | `e/<patch>` | an [`EdgePatch`] the active surveys call for (bincode) |
//! | `t/<patch>` | the patch's [`BoxState`] in the LOD index: `f64` LE top, then a byte that is 1 when the box is exposed; for active surveys' patches and the edge patches they call for |
//! | `o/<survey>/<other>` | [`PairEvidence`] (bincode): what two overlapping surveys say of each other's claims, under both orders |
//! | `f/<source path>` | [`FailedRecord`] (bincode); at most one a path, and a bounded number |
//! | `r/<source path>` | hex content id of a file whose survey was retired by hand while the file stayed in the inbox |
//! | `meta/rebuild` | present when the next open must derive the index again from the surveys |
//! | `meta/quarantined` | the ids of the damaged surveys the stored index was derived without (bincode `Vec<SurveyId>`); absent when none are |
//!
//! A survey whose record, patch list, accuracies or chunks do not read back as written (a
//! checksum that does not match, bytes past the end of a truncated pack) is *damaged*: every
//! open checks them, leaves a damaged survey out of the terrain and serves the rest. The
//! terrain without it is what the index would be had it never been inserted, so the index is
//! derived again from the other surveys, once; `meta/quarantined` records which surveys the
//! stored index leaves out, so that the next open restores it without deriving it again.
//! Ingesting the survey's file again heals it; [`Store::repair`] drops it for good.
//!
//! Storing the box states and the edge patches is what lets `open` rebuild the index without
//! running the cutter or reading a sample: the boxes follow from the patches and the level
//! georeferences. Samples stay on disk and are read through a bounded cache of decoded chunks
//! ([`ChunkReader`]) when a cut needs them.
//!
//! Every write is checked against the free disk space first (see [`space`]): sled cannot
//! recover from running out of it.
//!
//! Besides sled's own lock inside the directory, a store holds an exclusive lock on the file
//! `<dir>.lock` beside it for as long as it is open. Compaction swaps whole directories, so
//! the lock that keeps two processes apart must not live inside one of them.

pub mod chunks;
mod compact;
pub(crate) mod keys;
mod migrate;
pub mod pack;
pub mod space;
mod verify;

use crate::sync::{read, write};
pub use chunks::{CacheStats, ChunkReader};
pub use compact::CompactReport;
pub use migrate::CURRENT as SCHEMA_VERSION;
use pack::{ChunkStore, PackFile};
pub use space::{DiskSpace, SpaceGuard, SystemDisk};
pub use verify::{Checked, VerifyReport};

use fs2::FileExt;
use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::Crs;
use patchwork_core::index::lod::{BoxState, ChangeStats, IndexConfig};
use patchwork_core::model::accuracy::{AccuracySource, AccuracySpec, KernelAccuracy};
use patchwork_core::model::edge::EdgePatch;
use patchwork_core::model::evidence::{Contradicted, PairEvidence};
use patchwork_core::model::grid::{Georef, Grid, Shape};
use patchwork_core::model::ids::{PatchId, SurveyId};
use patchwork_core::model::mipmap::Filter;
use patchwork_core::model::patch::{Patch, PatchKind, PatchLayout, Tiling};
use patchwork_core::model::source::SampleSource;
use patchwork_core::model::survey::Recipe;
use patchwork_core::model::survey::{Survey, SurveyMeta};
use rayon::prelude::*;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};
use std::time::{Instant, SystemTime, UNIX_EPOCH};
use thiserror::Error;

/// The largest record read back from the pack: far above any survey's patch list (a
/// 3600² survey's is about 2.5 MB), so that a damaged length cannot allocate without bound.
const MAX_RECORD_BYTES: usize = 1 << 30;

/// The decoded-chunk cache of a store opened without saying: 512 MiB.
pub const DEFAULT_CACHE_BYTES: u64 = 512 << 20;

/// How a store is opened: its space rules and how much memory its caches may take.
#[derive(Clone, Debug)]
pub struct StoreOptions {
    pub guard: SpaceGuard,
    /// Bytes of decoded chunks kept in memory; sled's own page cache takes a quarter of it
    /// more (see [`StoreOptions::sled_cache_bytes`]).
    pub cache_bytes: u64,
    /// The mipmap filter and patch kind of a new store; an existing one keeps its own.
    pub recipe: Recipe,
    /// What a new store does with contradicted claims; an existing one keeps its own.
    pub contradicted: Contradicted,
}

impl StoreOptions {
    /// sled's page cache: a quarter of the chunk cache, at least 8 MiB. It holds the records,
    /// patches and tops that an open reads once and commits touch; the samples have their own
    /// cache, so a large sled cache would only hold the same chunks a second time, compressed.
    pub fn sled_cache_bytes(&self) -> u64 {
        (self.cache_bytes / 4).max(8 << 20)
    }
}

impl Default for StoreOptions {
    fn default() -> Self {
        StoreOptions {
            guard: SpaceGuard::default(),
            cache_bytes: DEFAULT_CACHE_BYTES,
            recipe: Recipe::default(),
            contradicted: Contradicted::default(),
        }
    }
}

impl From<SpaceGuard> for StoreOptions {
    fn from(guard: SpaceGuard) -> Self {
        StoreOptions {
            guard,
            ..Default::default()
        }
    }
}

/// A survey's patches and the edge tiles its samples reach, stored together under `p/`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredPatches {
    pub patches: Vec<Patch>,
    pub edge_tiles: Vec<[i64; 2]>,
}

#[derive(Debug, Error)]
pub enum StoreError {
    #[error(
        "the store's schema is version {found}, but this binary supports versions up to \
         {supported}: open it with a newer patchwork"
    )]
    Newer { found: u32, supported: u32 },
    #[error("the store at {} is in use by another process (is the daemon running?)", dir.display())]
    Locked { dir: PathBuf },
    #[error("the store is corrupt: {0}")]
    Corrupt(String),
    #[error("migration of the store from schema {from} to {to} failed: {msg}")]
    Migration { from: u32, to: u32, msg: String },
    #[error(
        "survey {survey} was placed in {placed_in}, but the store's CRS is {store_crs}; the \
         engine places a survey in the store's CRS before committing it"
    )]
    CrsMismatch {
        survey: SurveyId,
        placed_in: String,
        store_crs: String,
    },
    #[error(
        "survey {survey}'s heights are in {survey_vertical}, but the store's are in \
         {store_vertical}: the store took that vertical CRS while the file was read; it will \
         be ingested again"
    )]
    VerticalMismatch {
        survey: SurveyId,
        survey_vertical: String,
        store_vertical: String,
    },
    #[error("survey {0} is already stored and active")]
    Duplicate(SurveyId),
    #[error("survey {0} is not an active survey of the store")]
    NotActive(SurveyId),
    #[error("invalid request: {0}")]
    Invalid(String),
    #[error(
        "the disk holding the store has {available_mb} MiB free, and this write needs \
         {needed_mb} MiB with the space kept free (storage.min_free_mb): free some space or \
         compact the store; nothing was written"
    )]
    Full { available_mb: u64, needed_mb: u64 },
    #[error("storage engine: {0}")]
    Sled(sled::Error),
    #[error("store I/O: {0}")]
    Io(#[from] std::io::Error),
    #[error("could not encode {0}")]
    Encode(String),
    #[error("could not decode {0}")]
    Decode(String),
    /// Samples a read or an index change needed could not be read back.
    #[error(transparent)]
    Samples(#[from] patchwork_core::model::source::SampleError),
    #[error("{0}")]
    Place(#[from] patchwork_core::model::place::PlaceError),
}

impl From<sled::Error> for StoreError {
    fn from(e: sled::Error) -> Self {
        StoreError::Sled(e)
    }
}

/// Whether an error says that another handle holds the directory's lock. sled wraps the
/// `WouldBlock` from `flock` into an `Other` error with this message, so both are looked for.
pub fn is_lock_error(e: &std::io::Error) -> bool {
    e.kind() == std::io::ErrorKind::WouldBlock || e.to_string().contains("could not acquire lock")
}

/// Turns an error from opening the store at `dir` into a [`StoreError`], recognising a lock
/// held by another process.
pub fn open_error(e: sled::Error, dir: &Path) -> StoreError {
    match e {
        sled::Error::Io(io) if is_lock_error(&io) => StoreError::Locked {
            dir: dir.to_path_buf(),
        },
        e => StoreError::Sled(e),
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Status {
    Active,
    /// Out of the index; its samples stay until the next compaction.
    Retired,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LevelHeader {
    pub cols: u64,
    pub rows: u64,
    pub georef: Georef,
}

impl LevelHeader {
    fn of(g: &Grid) -> Self {
        LevelHeader {
            cols: g.cols as u64,
            rows: g.rows as u64,
            georef: g.georef,
        }
    }

    pub fn shape(&self) -> Shape {
        Shape {
            cols: self.cols as usize,
            rows: self.rows as usize,
            georef: self.georef,
        }
    }
}

/// Where the time of one ingestion went, in milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct IngestTimings {
    pub read_ms: f64,
    pub build_ms: f64,
    pub index_ms: f64,
    /// Filled in by the store: encoding, the atomic batch and its flush.
    pub commit_ms: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurveyRecord {
    pub id: SurveyId,
    /// The file it was read from.
    pub source: String,
    /// Hex blake3 of the file's bytes; empty when unknown.
    pub content_id: String,
    /// ε in metres: the largest of the survey's kernels'.
    pub accuracy: f64,
    pub accuracy_source: AccuracySource,
    /// Its horizontal CRS: the plane its grid is in, which may not be the store's.
    pub crs: Option<Crs>,
    /// The vertical CRS its file or sidecar named; None where nothing did.
    pub vertical_source: Option<VerticalCrs>,
    /// What its stored heights are measured from: the store's vertical CRS where they were
    /// converted to it; None where nothing was named.
    pub vertical: Option<VerticalCrs>,
    /// What converting its heights between vertical CRSs added to ε, in metres.
    pub vertical_error_m: f64,
    pub status: Status,
    pub cols: u64,
    pub rows: u64,
    pub georef: Georef,
    /// Valid level-0 samples.
    pub samples: u64,
    /// Level 0 first, as stored in the chunks.
    pub levels: Vec<LevelHeader>,
    /// Where level 0's kernel boundaries fall (see [`Tiling`]).
    pub tiling_offset: [i64; 2],
    pub ingest: IngestTimings,
    pub created_unix: u64,
}

impl SurveyRecord {
    /// The record of an active survey read from `source`.
    pub fn new(
        s: &Survey,
        source: impl Into<String>,
        content_id: impl Into<String>,
        accuracy_source: AccuracySource,
        ingest: IngestTimings,
    ) -> Self {
        let l0 = &s.levels[0];
        SurveyRecord {
            id: s.id,
            source: source.into(),
            content_id: content_id.into(),
            accuracy: s.accuracy,
            accuracy_source: if s.spec == AccuracySpec::Auto {
                AccuracySource::Estimated
            } else {
                accuracy_source
            },
            crs: s.crs.clone(),
            vertical_source: s.vertical.clone(),
            vertical: s.vertical.clone(),
            vertical_error_m: 0.0,
            status: Status::Active,
            cols: l0.cols as u64,
            rows: l0.rows as u64,
            georef: l0.georef,
            samples: l0.valid_count() as u64,
            levels: s.levels.iter().map(|g| LevelHeader::of(g)).collect(),
            tiling_offset: s.tiling.offset,
            ingest,
            created_unix: now_unix(),
        }
    }

    /// How the survey's ε was decided, as its id hashes it.
    pub fn spec(&self) -> AccuracySpec {
        match self.accuracy_source {
            AccuracySource::Estimated => AccuracySpec::Auto,
            _ => AccuracySpec::Fixed(self.accuracy),
        }
    }
}

/// A survey whose records or chunks cannot be read back as they were written: out of the
/// terrain until its file is ingested again or [`Store::repair`] drops it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Damaged {
    pub id: SurveyId,
    /// Its file; empty when its record itself is what is damaged.
    pub source: String,
    /// What was found wrong, first problem only.
    pub reason: String,
}

/// What an operator is told of it, at open and by `verify`.
impl std::fmt::Display for Damaged {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let source = if self.source.is_empty() {
            "its record is unreadable"
        } else {
            &self.source
        };
        write!(
            f,
            "survey {} ({source}) is damaged and out of the terrain: {}; ingest its file again \
             or run `patchwork repair` to drop it",
            self.id, self.reason
        )
    }
}

/// Everything the store holds besides samples and patches: what listings, stats and the inbox
/// read. The engine keeps it beside the terrain, so that they never wait on the disk.
#[derive(Clone, Debug, Default)]
pub struct Catalog {
    /// Every survey record, active and retired, in id order.
    pub records: Vec<SurveyRecord>,
    /// Every recorded failure, in source order.
    pub failures: Vec<FailedRecord>,
    /// Sources retired by hand, with the content that stays retired (see [`Store::pins`]).
    pub pins: HashMap<String, String>,
    /// Active surveys left out of the terrain because they are damaged, by id.
    pub damaged: BTreeMap<SurveyId, Damaged>,
    pub crs: Option<Crs>,
    pub vertical: Option<VerticalCrs>,
    pub layout: PatchLayout,
    pub recipe: Recipe,
}

impl Catalog {
    /// The record of the active survey read from `source`, if any.
    /// Not a damaged one: its file is to be ingested again.
    pub fn active_from(&self, source: &str) -> Option<&SurveyRecord> {
        self.active().find(|r| r.source == source)
    }

    /// The active surveys the terrain holds: damaged ones are not among them.
    pub fn active(&self) -> impl Iterator<Item = &SurveyRecord> {
        self.records
            .iter()
            .filter(|r| r.status == Status::Active && !self.damaged.contains_key(&r.id))
    }
}

/// A file that could not be ingested. The inbox leaves it alone until its content changes;
/// size and mtime are what it had, for listings.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FailedRecord {
    pub source: String,
    pub error: String,
    pub size: u64,
    pub mtime_unix: u64,
    pub at_unix: u64,
    /// Hex blake3 of the bytes that failed; empty when they could not be read (or the
    /// failure was recorded before the store kept it), which matches no file.
    pub content_id: String,
}

pub fn now_unix() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

pub(crate) fn encode<T: Serialize>(v: &T) -> Result<Vec<u8>, StoreError> {
    bincode::serde::encode_to_vec(v, bincode::config::standard())
        .map_err(|e| StoreError::Encode(e.to_string()))
}

/// A choice recorded in the store when it is made, under its own key, by name.
pub(crate) trait Setting: Copy + PartialEq {
    const KEY: &'static [u8];
    /// What the choice is, for messages.
    const WHAT: &'static str;
    /// What a store made before the choice existed holds.
    const LEGACY: Self;
    fn name(self) -> &'static str;
    fn from_name(name: &str) -> Option<Self>;
}

impl Setting for Filter {
    const KEY: &'static [u8] = keys::MIPMAP;
    const WHAT: &'static str = "mipmap filter";
    const LEGACY: Self = Filter::Smooth;
    fn name(self) -> &'static str {
        Filter::name(self)
    }
    fn from_name(name: &str) -> Option<Self> {
        Filter::from_name(name)
    }
}

impl Setting for Contradicted {
    const KEY: &'static [u8] = keys::CONTRADICTED;
    const WHAT: &'static str = "policy for contradicted claims";
    // Stores made before the choice come to this one through the migration that measures
    // their pairs, which derives their index again.
    const LEGACY: Self = Contradicted::Distrust;
    fn name(self) -> &'static str {
        Contradicted::name(self)
    }
    fn from_name(name: &str) -> Option<Self> {
        Contradicted::from_name(name)
    }
}

impl Setting for PatchKind {
    const KEY: &'static [u8] = keys::PATCHES;
    const WHAT: &'static str = "patch kind";
    const LEGACY: Self = PatchKind::Bilinear;
    fn name(self) -> &'static str {
        PatchKind::name(self)
    }
    fn from_name(name: &str) -> Option<Self> {
        PatchKind::from_name(name)
    }
}

/// What is wrong with a recorded setting `v` in a store opened with `open`, if anything.
pub(crate) fn setting_problem<T: Setting>(v: &[u8], open: T) -> Option<String> {
    match T::from_name(&String::from_utf8_lossy(v)) {
        Some(t) if t == open => None,
        Some(t) => Some(format!(
            "{} {} differs from the open store's",
            T::WHAT,
            t.name()
        )),
        None => Some(format!(
            "{} names no {}",
            String::from_utf8_lossy(T::KEY),
            T::WHAT
        )),
    }
}

/// A store's setting: the recorded one, or for a store that has none, the legacy one when it
/// already holds surveys (they were built before the choice) and `configured` when it is new,
/// recorded then. On a disk too full to record it, it is used unrecorded: no survey can be
/// written there either.
fn setting_of<T: Setting>(
    db: &sled::Db,
    dir: &Path,
    guard: &SpaceGuard,
    configured: T,
) -> Result<T, StoreError> {
    let key = String::from_utf8_lossy(T::KEY);
    if let Some(v) = db.get(T::KEY)? {
        let name = String::from_utf8_lossy(&v);
        return T::from_name(&name)
            .ok_or_else(|| StoreError::Corrupt(format!("{key} names no choice: {name:?}")));
    }
    let legacy = db.scan_prefix(keys::SURVEY_PREFIX).next().is_some();
    let v = if legacy { T::LEGACY } else { configured };
    if guard.check(dir, 64).is_ok() {
        db.insert(T::KEY, v.name())?;
    }
    Ok(v)
}

/// The store's recipe, each part by [`setting_of`].
fn recipe_of(
    db: &sled::Db,
    dir: &Path,
    guard: &SpaceGuard,
    configured: Recipe,
) -> Result<Recipe, StoreError> {
    Ok(Recipe {
        mipmap: setting_of(db, dir, guard, configured.mipmap)?,
        patches: setting_of(db, dir, guard, configured.patches)?,
    })
}

pub(crate) fn decode<T: DeserializeOwned>(b: &[u8], what: &str) -> Result<T, StoreError> {
    let (v, n) = bincode::serde::decode_from_slice(b, bincode::config::standard())
        .map_err(|e| StoreError::Decode(format!("{what}: {e}")))?;
    if n != b.len() {
        return Err(StoreError::Decode(format!(
            "{what}: {} bytes left over after the value",
            b.len() - n
        )));
    }
    Ok(v)
}

pub(crate) fn encode_state(s: &BoxState) -> [u8; 9] {
    let mut b = [0u8; 9];
    b[..8].copy_from_slice(&s.top.to_le_bytes());
    b[8] = u8::from(s.exposed);
    b
}

pub(crate) fn decode_state(b: &[u8], what: &str) -> Result<BoxState, StoreError> {
    let bad = || StoreError::Decode(format!("{what}: {} bytes, not a top and a flag", b.len()));
    let a: [u8; 9] = b.try_into().map_err(|_| bad())?;
    if a[8] > 1 {
        return Err(bad());
    }
    Ok(BoxState {
        top: f64::from_le_bytes(a[..8].try_into().expect("8 bytes")),
        exposed: a[8] == 1,
    })
}

/// A CRS recorded as its key.
fn decode_crs<T>(
    b: &[u8],
    what: &str,
    parse: impl Fn(&str) -> Result<T, patchwork_core::crs::CrsError>,
) -> Result<T, StoreError> {
    let text = std::str::from_utf8(b)
        .map_err(|_| StoreError::Decode(format!("{what}: not UTF-8 text")))?;
    parse(text).map_err(|e| StoreError::Decode(format!("{what}: {e}")))
}

fn decode_u32(b: &[u8], what: &str) -> Result<u32, StoreError> {
    let a: [u8; 4] = b
        .try_into()
        .map_err(|_| StoreError::Decode(format!("{what}: {} bytes, not 4", b.len())))?;
    Ok(u32::from_le_bytes(a))
}

/// Runs `f`, turning a panic into its message without printing it (the default hook would
/// print a backtrace over the message the caller gives instead).
fn quietly<T>(f: impl FnOnce() -> T + std::panic::UnwindSafe) -> Result<T, String> {
    thread_local!(static QUIET: std::cell::Cell<bool> = const { std::cell::Cell::new(false) });
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(|q| q.get()) {
                previous(info);
            }
        }));
    });
    QUIET.with(|q| q.set(true));
    let r = std::panic::catch_unwind(f);
    QUIET.with(|q| q.set(false));
    r.map_err(|p| {
        p.downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| p.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "a panic".into())
    })
}

/// What to do about sled's own files being damaged: a snapshot file can go (sled rebuilds it
/// from its log); otherwise the directory must come back from a backup.
fn damaged_database(dir: &Path, what: &str) -> StoreError {
    let snaps: Vec<String> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("snap."))
        .collect();
    let advice = if snaps.is_empty() {
        format!(
            "restore {} from a backup (the chunk pack beside it cannot be read without it)",
            dir.display()
        )
    } else {
        format!(
            "first move {} out of {} and open again (sled rebuilds its snapshot from its log); \
             if that does not help, restore the directory from a backup",
            snaps.join(", "),
            dir.display()
        )
    };
    StoreError::Corrupt(format!(
        "the database files in {} are damaged ({}): {advice}",
        dir.display(),
        what.lines().next().unwrap_or(what)
    ))
}

/// A store's path to a sibling of its directory: `<dir><suffix>`.
fn sibling(dir: &Path, suffix: &str) -> Result<PathBuf, StoreError> {
    let name = dir.file_name().ok_or_else(|| {
        StoreError::Invalid(format!("the store path {} has no name", dir.display()))
    })?;
    let mut n = name.to_os_string();
    n.push(suffix);
    Ok(dir.with_file_name(n))
}

/// Opens sled's database in `dir`, once this process holds `<dir>.lock`. Holding it means no
/// other handle is open, so a lock that sled still finds held belongs to a handle of this
/// process that was just dropped: sled releases its lock from a background thread, a moment
/// later. Waiting a little for that is safe; waiting on another process never happens here.
fn open_sled(dir: &Path, cache_bytes: u64) -> Result<sled::Db, StoreError> {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    loop {
        match sled::Config::new()
            .path(dir)
            .cache_capacity(cache_bytes)
            .open()
        {
            Ok(db) => return Ok(db),
            Err(sled::Error::Io(io))
                if is_lock_error(&io) && std::time::Instant::now() < deadline =>
            {
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
            Err(e) => return Err(open_error(e, dir)),
        }
    }
}

/// Takes the exclusive lock that keeps other processes (and other handles in this one) out.
fn lock_dir(dir: &Path) -> Result<File, StoreError> {
    let path = sibling(dir, ".lock")?;
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent)?;
    }
    let f = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)?;
    match f.try_lock_exclusive() {
        Ok(()) => Ok(f),
        Err(e) if is_lock_error(&e) => Err(StoreError::Locked {
            dir: dir.to_path_buf(),
        }),
        Err(e) => Err(e.into()),
    }
}

/// A sled batch that knows how many bytes it writes, so that the disk can be asked first.
#[derive(Default)]
struct Writes {
    batch: sled::Batch,
    bytes: u64,
}

/// One change of the terrain, as [`Store::commit`] writes it in one batch.
#[derive(Default)]
pub struct Change<'a> {
    /// The survey going out, if any.
    pub retire: Option<Retirement<'a>>,
    /// The survey coming in, if any: with `retire`, it replaces that one.
    pub insert: Option<Insertion<'a>>,
    /// The edge patches the new terrain holds among the boxes the change moved.
    pub edges: &'a [Arc<EdgePatch>],
}

/// A survey going out of the terrain. Its samples stay until [`Store::compact`].
pub struct Retirement<'a> {
    /// The survey.
    pub id: SurveyId,
    /// Its patches, whose tops go.
    pub patches: &'a [PatchId],
    /// What retiring it from the terrain changed.
    pub change: &'a ChangeStats,
    /// Whether its file, should it stay where it is, is kept from bringing it back (see
    /// [`Store::pins`]).
    pub pin: bool,
}

/// A survey coming into the terrain.
pub struct Insertion<'a> {
    /// The survey, as built and placed in the store's CRS.
    pub survey: &'a Survey,
    /// Its record.
    pub record: &'a SurveyRecord,
    /// What inserting it into the terrain changed (other surveys' tops among it).
    pub change: &'a ChangeStats,
    /// The evidence of its overlaps with the surveys already there.
    pub pairs: &'a [Arc<PairEvidence>],
    /// Its chunks, already in the pack.
    pub packed: Packed,
}

/// A survey's chunks and patch list, appended to the pack and synced but not yet committed:
/// the commit that follows points the database at them (see [`Store::pack_survey`]).
pub struct Packed {
    survey: SurveyId,
    entries: Vec<(Vec<u8>, pack::Loc)>,
}

impl Writes {
    fn insert(&mut self, k: impl Into<sled::IVec>, v: impl Into<sled::IVec>) {
        let (k, v) = (k.into(), v.into());
        self.bytes += (k.len() + v.len()) as u64;
        self.batch.insert(k, v);
    }

    fn remove(&mut self, k: impl Into<sled::IVec>) {
        let k = k.into();
        self.bytes += k.len() as u64;
        self.batch.remove(k);
    }
}

/// Closes the store's chunk reader when the store goes, however it goes.
struct CloseReader(Arc<ChunkReader>);

impl Drop for CloseReader {
    fn drop(&mut self) {
        self.0.close();
    }
}

pub struct Store {
    db: sled::Db,
    pack: Arc<PackFile>,
    reader: Arc<ChunkReader>,
    _close_reader: CloseReader,
    opts: StoreOptions,
    guard: SpaceGuard,
    dir: PathBuf,
    layout: PatchLayout,
    index: IndexConfig,
    recipe: Recipe,
    contradicted: Contradicted,
    /// The horizontal and vertical CRSs, once set.
    crs: RwLock<(Option<Crs>, Option<VerticalCrs>)>,
    migrated: Vec<(u32, u32)>,
    /// The damaged surveys the last open found, less those healed or dropped since.
    damaged: RwLock<BTreeMap<SurveyId, Damaged>>,
    _lock: File,
}

/// What the index is rebuilt from at open: the surveys without their samples, the edge
/// patches and the box states. Building the terrain from it is the caller's (see
/// `crate::restore`); the store reads and writes, and builds nothing.
pub struct Contents {
    pub surveys: Vec<Arc<SurveyMeta>>,
    /// What each overlapping pair says of the other's claims.
    pub pairs: Vec<Arc<PairEvidence>>,
    pub edges: Vec<Arc<EdgePatch>>,
    pub tops: HashMap<PatchId, BoxState>,
    /// The index must be derived again from the surveys (a migration asked for it, or a
    /// survey is damaged that the stored index holds).
    pub rebuild: bool,
    /// Active surveys left out because they are damaged; not among `surveys`.
    pub damaged: Vec<Damaged>,
}

/// A store just opened, with what it holds for the index.
pub struct Loaded {
    pub store: Store,
    pub contents: Contents,
    /// Problems met while opening that did not stop it.
    pub warnings: Vec<String>,
    /// Whether the disk was so full that the reserve file was given back to open the store.
    pub released_reserve: bool,
}

/// The writes a survey commit adds to a batch; kept so that the record can get its commit time.
struct Staged {
    key: Vec<u8>,
    rec: SurveyRecord,
    crs: (Option<Crs>, Option<VerticalCrs>),
}

impl Store {
    /// Opens or creates the store at `dir`, recovering from an interrupted compaction and
    /// running migrations, and reads what the index is restored from (see [`Contents`]; the
    /// terrain is built by `crate::restore`).
    ///
    /// `layout` and `index` only apply to a fresh store: an existing one keeps the settings its
    /// surveys were built and indexed with (see [`Store::layout`], [`Store::index_config`]).
    pub fn open(dir: &Path, layout: PatchLayout, index: IndexConfig) -> Result<Loaded, StoreError> {
        Self::open_with(dir, layout, index, StoreOptions::default())
    }

    /// [`Store::open`] under the given space rules. On a disk too full to write, the store
    /// opens all the same (releasing its reserve file if that is what it takes), and every
    /// write is refused with [`StoreError::Full`] until space returns.
    pub fn open_with(
        dir: &Path,
        layout: PatchLayout,
        index: IndexConfig,
        opts: impl Into<StoreOptions>,
    ) -> Result<Loaded, StoreError> {
        let dir = std::path::absolute(dir)?;
        let lock = lock_dir(&dir)?;
        let opts = opts.into();
        // sled panics on some damage to its own files (a database file cut short) where it
        // returns an error on other damage: both end here, as one message that says what to do.
        let opened = quietly(std::panic::AssertUnwindSafe(|| {
            Self::open_locked(dir.clone(), lock, layout, index, opts)
        }));
        let mut opened = match opened {
            Ok(Err(StoreError::Sled(sled::Error::Corruption { .. }))) => {
                return Err(damaged_database(
                    &dir,
                    "sled read data that fails its checksum",
                ))
            }
            Ok(Err(StoreError::Sled(sled::Error::ReportableBug(why)))) => {
                return Err(damaged_database(&dir, &why))
            }
            Ok(r) => r?,
            Err(panic) => return Err(damaged_database(&dir, &panic)),
        };
        if opened.released_reserve {
            opened.warnings.push(
                "the disk was full: the store's reserve file was released so that it could open"
                    .into(),
            );
        }
        Ok(opened)
    }

    fn open_locked(
        dir: PathBuf,
        lock: File,
        layout: PatchLayout,
        index: IndexConfig,
        opts: StoreOptions,
    ) -> Result<Loaded, StoreError> {
        compact::recover(&dir)?;
        let guard = opts.guard.clone();
        let released_reserve = guard.release_if_full(&dir)?;
        let db = open_sled(&dir, opts.sled_cache_bytes())?;
        if migrate::version(&db)? < migrate::CURRENT && db.get(keys::SCHEMA)?.is_some() {
            // A migration rewrites much of the store; refuse it on a full disk rather than
            // let sled run out of space halfway.
            guard.check(&dir, db.size_on_disk()?)?;
        }
        let committed = match db.get(keys::PACK_LEN)? {
            None => 0,
            Some(v) => u64::from_le_bytes(v.as_ref().try_into().map_err(|_| {
                StoreError::Corrupt(format!("meta/pack_len holds {} bytes, not 8", v.len()))
            })?),
        };
        let pack = Arc::new(PackFile::open(&dir, committed)?);
        let migrated = migrate::migrate(
            &db,
            &migrate::Ctx {
                layout,
                index,
                pack: pack.as_ref(),
            },
        )?;
        let get = |k: &[u8]| -> Result<sled::IVec, StoreError> {
            db.get(k)?.ok_or_else(|| {
                StoreError::Corrupt(format!("{} is missing", String::from_utf8_lossy(k)))
            })
        };
        let layout: PatchLayout = decode(&get(keys::LAYOUT)?, "meta/layout")?;
        let index: IndexConfig = decode(&get(keys::INDEX)?, "meta/index")?;
        let recipe = recipe_of(&db, &dir, &guard, opts.recipe)?;
        let contradicted = setting_of(&db, &dir, &guard, opts.contradicted)?;
        let crs = (
            db.get(keys::CRS)?
                .map(|v| decode_crs(&v, "meta/crs", Crs::parse))
                .transpose()?,
            db.get(keys::VERTICAL_CRS)?
                .map(|v| decode_crs(&v, "meta/vertical_crs", VerticalCrs::parse))
                .transpose()?,
        );
        let reader = Arc::new(ChunkReader::new(
            (*db).clone(),
            pack.clone(),
            opts.cache_bytes,
        ));
        let store = Store {
            db,
            pack,
            _close_reader: CloseReader(reader.clone()),
            reader,
            opts,
            guard,
            dir,
            layout,
            index,
            recipe,
            contradicted,
            crs: RwLock::new(crs),
            migrated,
            damaged: RwLock::new(BTreeMap::new()),
            _lock: lock,
        };
        let mut warnings = Vec::new();
        if store.pack.lost() > 0 {
            warnings.push(format!(
                "{} holds {} bytes fewer than were committed: the surveys whose bytes are gone \
                 are damaged",
                store.pack.path().display(),
                store.pack.lost()
            ));
        }
        let contents = store.load()?;
        warnings.extend(contents.damaged.iter().map(Damaged::to_string));
        if let Err(e) = store.guard.restore(&store.dir) {
            warnings.push(format!("could not make the reserve file: {e}"));
        }
        Ok(Loaded {
            store,
            contents,
            warnings,
            released_reserve,
        })
    }

    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// The layout every survey of this store is cut with.
    pub fn layout(&self) -> PatchLayout {
        self.layout
    }

    /// The mipmap filter and patch kind every survey of this store is built with.
    pub fn recipe(&self) -> Recipe {
        self.recipe
    }

    /// What the store does with claims other surveys contradict (see
    /// [`patchwork_core::model::evidence`]).
    pub fn contradicted(&self) -> Contradicted {
        self.contradicted
    }

    /// The index settings the stored tops were computed with.
    pub fn index_config(&self) -> IndexConfig {
        self.index
    }

    /// Migration steps this `open` ran, as (from, to).
    pub fn migrations_run(&self) -> &[(u32, u32)] {
        &self.migrated
    }

    /// The store's horizontal CRS, once it has one.
    pub fn crs(&self) -> Option<Crs> {
        read(&self.crs).0.clone()
    }

    /// The store's vertical CRS, once it has one.
    pub fn vertical_crs(&self) -> Option<VerticalCrs> {
        read(&self.crs).1.clone()
    }

    /// The reader the terrain gets its samples through.
    pub fn reader(&self) -> Arc<ChunkReader> {
        self.reader.clone()
    }

    /// What the index needs of the active surveys, the edge patches and the box states; no
    /// sample is decoded. Every active survey's records are decoded and its chunks checked
    /// against their checksums: a damaged one is left out (see [`Damaged`]), and the index is
    /// derived again without it unless the stored one already leaves out just these.
    fn load(&self) -> Result<Contents, StoreError> {
        let (active, unreadable) = self.records()?;
        let mut damaged: BTreeMap<SurveyId, Damaged> =
            unreadable.into_iter().map(|d| (d.id, d)).collect();
        let checked: Vec<(&SurveyRecord, Result<SurveyMeta, String>)> = active
            .par_iter()
            .filter(|r| r.status == Status::Active)
            .map(|r| Ok((r, self.load_checked(r)?)))
            .collect::<Result<_, StoreError>>()?;
        let mut surveys = Vec::with_capacity(checked.len());
        for (r, meta) in checked {
            match meta {
                Ok(m) => surveys.push(Arc::new(m)),
                Err(reason) => {
                    damaged.insert(
                        r.id,
                        Damaged {
                            id: r.id,
                            source: r.source.clone(),
                            reason,
                        },
                    );
                }
            }
        }
        let left_out = self.quarantined()?;
        let rebuild = self.db.get(keys::REBUILD)?.is_some()
            || !damaged.keys().copied().eq(left_out.iter().copied());
        let found: Vec<Damaged> = damaged.values().cloned().collect();
        *write(&self.damaged) = damaged;
        // A store to be rebuilt may hold tops of an older format, or tops of an index with a
        // survey now damaged: they are replaced, never read.
        if rebuild {
            return Ok(Contents {
                surveys,
                pairs: Vec::new(),
                edges: Vec::new(),
                tops: HashMap::new(),
                rebuild: true,
                damaged: found,
            });
        }
        Ok(Contents {
            surveys,
            pairs: self.all_pairs()?,
            edges: self.edges()?,
            tops: self.states()?,
            rebuild: false,
            damaged: found,
        })
    }

    /// A survey's meta, once its records decode and every chunk it should have is there and
    /// matches its checksum; otherwise what is wrong. Only an error of the database itself
    /// is an `Err`.
    fn load_checked(&self, r: &SurveyRecord) -> Result<Result<SurveyMeta, String>, StoreError> {
        let meta = match self.load_meta(r) {
            Ok(m) => m,
            Err(e @ (StoreError::Corrupt(_) | StoreError::Decode(_))) => {
                return Ok(Err(e.to_string()))
            }
            Err(e) => return Err(e),
        };
        let mut locs: HashMap<(usize, usize), sled::IVec> = HashMap::new();
        for kv in self.db.scan_prefix(keys::chunks_of(r.id)) {
            let (k, v) = kv?;
            if let Some((_, level, n)) = keys::parse_chunk(&k) {
                locs.insert((level, n), v);
            }
        }
        for (level, h) in r.levels.iter().enumerate() {
            let [nx, ny] = chunks::chunk_counts(&h.shape());
            for k in 0..nx * ny {
                let what = || format!("chunk {k} of level {level}");
                let Some(v) = locs.get(&(level, k)) else {
                    return Ok(Err(format!("{} is missing", what())));
                };
                let Some(loc) = pack::Loc::from_bytes(v) else {
                    return Ok(Err(format!(
                        "{}: its location is {} bytes",
                        what(),
                        v.len()
                    )));
                };
                let bytes = match self.pack.read(loc) {
                    Ok(b) => b,
                    Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => {
                        return Ok(Err(format!(
                            "{}: its bytes ({}..{}) are past the end of the pack",
                            what(),
                            loc.offset,
                            loc.end()
                        )))
                    }
                    Err(e) => return Err(e.into()),
                };
                if let Err(e) = chunks::intact(&bytes) {
                    return Ok(Err(format!("{}: {e}", what())));
                }
            }
        }
        Ok(Ok(meta))
    }

    /// The ids the stored index was derived without.
    fn quarantined(&self) -> Result<Vec<SurveyId>, StoreError> {
        match self.db.get(keys::QUARANTINED)? {
            None => Ok(Vec::new()),
            Some(v) => decode(&v, "meta/quarantined"),
        }
    }

    /// The damaged surveys, as the last open found them less those healed or dropped since.
    pub fn damaged(&self) -> BTreeMap<SurveyId, Damaged> {
        read(&self.damaged).clone()
    }

    fn is_damaged(&self, id: SurveyId) -> bool {
        read(&self.damaged).contains_key(&id)
    }

    /// Writes `meta/quarantined` as it stands once `healed` are no longer damaged; nothing
    /// when none of them was. Call [`Store::healed`] once the batch is applied.
    fn stage_healed(&self, batch: &mut Writes, healed: &[SurveyId]) -> Result<(), StoreError> {
        let damaged = read(&self.damaged);
        if !healed.iter().any(|id| damaged.contains_key(id)) {
            return Ok(());
        }
        let left: Vec<SurveyId> = damaged
            .keys()
            .copied()
            .filter(|id| !healed.contains(id))
            .collect();
        if left.is_empty() {
            batch.remove(keys::QUARANTINED);
        } else {
            batch.insert(keys::QUARANTINED, encode(&left)?);
        }
        Ok(())
    }

    fn healed(&self, ids: &[SurveyId]) {
        let mut damaged = write(&self.damaged);
        for id in ids {
            damaged.remove(id);
        }
    }

    /// Drops every damaged survey for good, in one batch: its record, patches, accuracies,
    /// chunk locations and pairs (its bytes in the pack go at the next compaction). The index
    /// already leaves them out. Its file, if still in the inbox, is then ingested afresh.
    /// Returns what was dropped.
    pub fn repair(&mut self) -> Result<Vec<Damaged>, StoreError> {
        let damaged: Vec<Damaged> = self.damaged().into_values().collect();
        if damaged.is_empty() {
            return Ok(damaged);
        }
        let mut batch = Writes::default();
        for d in &damaged {
            batch.remove(keys::survey(d.id));
            batch.remove(keys::patches(d.id));
            batch.remove(keys::accuracy(d.id));
            for prefix in [keys::chunks_of(d.id), keys::overlaps_of(d.id)] {
                for kv in self.db.scan_prefix(prefix) {
                    let (k, _) = kv?;
                    if let Some((_, other)) = keys::parse_overlap(&k) {
                        batch.remove(keys::overlap(other, d.id));
                    }
                    batch.remove(k);
                }
            }
        }
        batch.remove(keys::QUARANTINED);
        self.apply(batch)?;
        let ids: Vec<SurveyId> = damaged.iter().map(|d| d.id).collect();
        self.healed(&ids);
        Ok(damaged)
    }

    fn active_records(&self) -> Result<Vec<SurveyRecord>, StoreError> {
        let mut all = self.surveys()?;
        all.retain(|r| r.status == Status::Active && !self.is_damaged(r.id));
        Ok(all)
    }

    /// Every active survey whole, samples and all: what deriving the index again needs.
    pub fn whole_surveys(&self) -> Result<Vec<Arc<Survey>>, StoreError> {
        self.active_records()?
            .par_iter()
            .map(|r| self.load_survey(r).map(Arc::new))
            .collect()
    }

    /// Replaces every box state, edge patch and pair, in one batch: an index derived again
    /// from the surveys. Clears the mark that asked for it.
    pub fn write_derived(
        &mut self,
        tops: &[(PatchId, BoxState)],
        edges: &[Arc<EdgePatch>],
        pairs: &[Arc<PairEvidence>],
    ) -> Result<(), StoreError> {
        let mut batch = Writes::default();
        for prefix in [keys::TOP_PREFIX, keys::EDGE_PREFIX, keys::OVERLAP_PREFIX] {
            for kv in self.db.scan_prefix(prefix) {
                batch.remove(kv?.0);
            }
        }
        stage_pairs(&mut batch, pairs)?;
        for (id, st) in tops {
            batch.insert(keys::top(*id), &encode_state(st));
        }
        stage_edges(&mut batch, edges)?;
        batch.remove(keys::REBUILD);
        let left_out: Vec<SurveyId> = self.damaged().into_keys().collect();
        if left_out.is_empty() {
            batch.remove(keys::QUARANTINED);
        } else {
            batch.insert(keys::QUARANTINED, encode(&left_out)?);
        }
        self.apply(batch)
    }

    fn states(&self) -> Result<HashMap<PatchId, BoxState>, StoreError> {
        let mut out = HashMap::new();
        for kv in self.db.scan_prefix(keys::TOP_PREFIX) {
            let (k, v) = kv?;
            let id = keys::parse_top(&k).ok_or_else(|| {
                StoreError::Corrupt(format!("bad top key {:?}", String::from_utf8_lossy(&k)))
            })?;
            out.insert(id, decode_state(&v, &format!("top of patch {id}"))?);
        }
        Ok(out)
    }

    /// Every stored edge patch.
    fn edges(&self) -> Result<Vec<Arc<EdgePatch>>, StoreError> {
        let mut out = Vec::new();
        for kv in self.db.scan_prefix(keys::EDGE_PREFIX) {
            let (k, v) = kv?;
            let id = keys::parse_edge(&k).ok_or_else(|| {
                StoreError::Corrupt(format!("bad edge key {:?}", String::from_utf8_lossy(&k)))
            })?;
            let e: EdgePatch = decode(&v, &format!("edge patch {id}"))?;
            out.push(Arc::new(e));
        }
        Ok(out)
    }

    /// A survey's patches and edge tiles, from the pack.
    #[doc(hidden)]
    pub fn load_patches(&self, id: SurveyId) -> Result<StoredPatches, StoreError> {
        let what = format!("the patches of survey {id}");
        let sealed = chunks::read_packed(&self.db, self.pack.as_ref(), &keys::patches(id))
            .map_err(|e| StoreError::Corrupt(format!("{what}: {e}")))?;
        let v = chunks::unseal(&sealed, MAX_RECORD_BYTES)
            .map_err(|e| StoreError::Corrupt(format!("{what}: {e}")))?;
        decode(&v, &what)
    }

    /// One whole level's samples from its chunks.
    fn load_level(&self, id: SurveyId, level: usize, h: &LevelHeader) -> Result<Grid, StoreError> {
        let shape = h.shape();
        if shape.cols < 2 || shape.rows < 2 {
            return Err(StoreError::Corrupt(format!(
                "level {level} of survey {id} is {}×{} samples",
                shape.cols, shape.rows
            )));
        }
        self.reader
            .read(id, level, &shape, shape.all())
            .map_err(|e| StoreError::Corrupt(e.to_string()))
    }

    /// A survey without its samples, from its record, patches and accuracies.
    fn load_meta(&self, r: &SurveyRecord) -> Result<SurveyMeta, StoreError> {
        let stored = self.load_patches(r.id)?;
        if let Some(p) = stored
            .patches
            .iter()
            .find(|p| p.survey != r.id || p.level as usize >= r.levels.len())
        {
            return Err(StoreError::Corrupt(format!(
                "survey {} lists patch {} of survey {} at level {}, which it does not have",
                r.id, p.id, p.survey, p.level
            )));
        }
        let Some(l0) = r.levels.first() else {
            return Err(StoreError::Corrupt(format!(
                "survey {} has no levels",
                r.id
            )));
        };
        let shape0 = l0.shape();
        if shape0.cols < 2 || shape0.rows < 2 {
            return Err(StoreError::Corrupt(format!(
                "level 0 of survey {} is {}×{} samples",
                r.id, shape0.cols, shape0.rows
            )));
        }
        let tiling = Tiling::new(shape0.cells(), self.layout.kernel, r.tiling_offset);
        let kernel_accuracy = match r.spec() {
            AccuracySpec::Fixed(a) => KernelAccuracy::constant(&tiling, a),
            AccuracySpec::Auto => {
                let v = self.db.get(keys::accuracy(r.id))?.ok_or_else(|| {
                    StoreError::Corrupt(format!("the accuracies of survey {} are missing", r.id))
                })?;
                let k: KernelAccuracy = decode(&v, &format!("accuracies of survey {}", r.id))?;
                if k.dims != tiling.counts() {
                    return Err(StoreError::Corrupt(format!(
                        "survey {} has {:?} kernel accuracies for {:?} kernels",
                        r.id,
                        k.dims,
                        tiling.counts()
                    )));
                }
                k
            }
        };
        Ok(SurveyMeta {
            id: r.id,
            accuracy: kernel_accuracy.max(),
            spec: r.spec(),
            crs: r.crs.clone(),
            vertical: r.vertical.clone(),
            placement: None,
            // Every survey of a store was placed in it before it was committed.
            placed_in: self.crs().or_else(|| r.crs.clone()),
            layout: self.layout,
            kind: self.recipe.patches,
            tiling,
            kernel_accuracy,
            shapes: r.levels.iter().map(LevelHeader::shape).collect(),
            patches: stored.patches,
            edge_tiles: stored.edge_tiles,
        })
    }

    /// A whole survey, samples and all: what deriving the index again and `verify` need.
    fn load_survey(&self, r: &SurveyRecord) -> Result<Survey, StoreError> {
        let meta = self.load_meta(r)?;
        let levels: Vec<Arc<Grid>> = r
            .levels
            .iter()
            .enumerate()
            .map(|(k, h)| self.load_level(r.id, k, h).map(Arc::new))
            .collect::<Result<_, _>>()?;
        let meta = Arc::new(meta);
        Ok(Survey { meta, levels })
    }

    fn record(&self, id: SurveyId) -> Result<Option<SurveyRecord>, StoreError> {
        self.db
            .get(keys::survey(id))?
            .map(|v| decode(&v, &format!("record of survey {id}")))
            .transpose()
    }

    /// Adds a survey's writes to `batch`. The survey was placed in a store of some CRS (see
    /// [`SurveyMeta::placed_for`]): this store's, which the batch sets if the store had none,
    /// as it sets the vertical CRS the survey's heights are in. `replacing` is a survey the
    /// same batch retires, which may be this very one.
    #[allow(clippy::too_many_arguments)]
    fn stage_survey(
        &self,
        batch: &mut Writes,
        insertion: &Insertion<'_>,
        replacing: Option<SurveyId>,
    ) -> Result<Staged, StoreError> {
        let (s, rec, change, pairs, packed) = (
            insertion.survey,
            insertion.record,
            insertion.change,
            insertion.pairs,
            &insertion.packed,
        );
        if rec.id != s.id {
            return Err(StoreError::Invalid(format!(
                "the record is of survey {}, the survey is {}",
                rec.id, s.id
            )));
        }
        let headers: Vec<LevelHeader> = s.levels.iter().map(|g| LevelHeader::of(g)).collect();
        if rec.levels != headers
            || rec.accuracy.to_bits() != s.accuracy.to_bits()
            || rec.crs != s.crs
        {
            return Err(StoreError::Invalid(format!(
                "the record of survey {} does not describe it (levels, accuracy or CRS differ)",
                s.id
            )));
        }
        if s.layout != self.layout {
            return Err(StoreError::Invalid(format!(
                "survey {} is cut with {:?}, the store with {:?}",
                s.id, s.layout, self.layout
            )));
        }
        if replacing != Some(s.id) {
            if let Some(old) = self.record(s.id)? {
                if old.status == Status::Active {
                    return Err(StoreError::Duplicate(s.id));
                }
            }
        }
        let (crs, vertical) = (self.crs(), self.vertical_crs());
        let crs = match (crs, s.placed_for()) {
            (Some(c), Some(placed)) if c != placed => {
                return Err(StoreError::CrsMismatch {
                    survey: s.id,
                    placed_in: placed.label(),
                    store_crs: c.label(),
                })
            }
            (None, Some(placed)) => {
                batch.insert(keys::CRS, placed.key().as_bytes());
                Some(placed)
            }
            (c, _) => c,
        };
        let vertical = match (vertical, &s.vertical) {
            (Some(v), Some(w)) if !v.same_reference(w) => {
                return Err(StoreError::VerticalMismatch {
                    survey: s.id,
                    survey_vertical: w.label(),
                    store_vertical: v.label(),
                })
            }
            (None, Some(w)) => {
                batch.insert(keys::VERTICAL_CRS, w.key().as_bytes());
                Some(w.clone())
            }
            (v, _) => v,
        };
        let crs = (crs, vertical);
        let mut rec = rec.clone();
        rec.status = Status::Active;
        let key = keys::survey(s.id);
        batch.insert(key.clone(), encode(&rec)?);
        if packed.survey != s.id {
            return Err(StoreError::Invalid(format!(
                "the chunks packed are survey {}'s, the survey is {}",
                packed.survey, s.id
            )));
        }
        for (k, loc) in &packed.entries {
            batch.insert(k.clone(), &loc.to_bytes()[..]);
        }
        batch.insert(keys::PACK_LEN, &self.pack.len().to_le_bytes()[..]);
        if s.spec == AccuracySpec::Auto {
            batch.insert(keys::accuracy(s.id), encode(&s.kernel_accuracy)?);
        }
        stage_change(batch, change);
        stage_pairs(batch, pairs)?;
        batch.remove(keys::failure(&rec.source));
        batch.remove(keys::pin(&rec.source));
        Ok(Staged { key, rec, crs })
    }

    fn stage_retire(
        &self,
        batch: &mut Writes,
        id: SurveyId,
        patch_ids: &[PatchId],
        change: &ChangeStats,
    ) -> Result<SurveyRecord, StoreError> {
        let mut rec = match self.record(id)? {
            Some(r) if r.status == Status::Active => r,
            _ => return Err(StoreError::NotActive(id)),
        };
        rec.status = Status::Retired;
        batch.insert(keys::survey(id), encode(&rec)?);
        for p in patch_ids {
            batch.remove(keys::top(*p));
        }
        stage_change(batch, change);
        for kv in self.db.scan_prefix(keys::overlaps_of(id)) {
            let (k, _) = kv?;
            if let Some((_, other)) = keys::parse_overlap(&k) {
                batch.remove(k);
                batch.remove(keys::overlap(other, id));
            }
        }
        Ok(rec)
    }

    /// Applies a batch and makes it durable before returning, once the disk has room for it.
    fn apply(&self, batch: Writes) -> Result<(), StoreError> {
        self.guard.check(&self.dir, batch.bytes)?;
        self.db.apply_batch(batch.batch)?;
        self.db.flush()?;
        Ok(())
    }

    /// Records how long the commit took. The batch is already durable; should this small
    /// write be lost, the record keeps the caller's figure.
    fn finish(&self, staged: Staged, t0: Instant) -> Result<(), StoreError> {
        *write(&self.crs) = staged.crs;
        let mut rec = staged.rec;
        rec.ingest.commit_ms = t0.elapsed().as_secs_f64() * 1e3;
        self.db.insert(staged.key, encode(&rec)?)?;
        Ok(())
    }

    /// Encodes a survey's levels and its patch list and appends them to the pack, synced,
    /// once the disk has room: the part of a commit that needs no index work, so a caller can
    /// run it beside that work. Until a commit points at them the bytes are not the store's:
    /// an open cuts them, or a later commit leaves them as garbage for compaction.
    pub fn pack_survey(&self, s: &Survey) -> Result<Packed, StoreError> {
        let stored = StoredPatches {
            patches: s.patches.clone(),
            edge_tiles: s.edge_tiles.clone(),
        };
        let mut entries_keys = vec![keys::patches(s.id)];
        let mut bytes = vec![chunks::seal(&encode(&stored)?)];
        for (level, g) in s.levels.iter().enumerate() {
            for (k, b) in chunks::encode_level(g) {
                entries_keys.push(keys::chunk(s.id, level, k));
                bytes.push(b);
            }
        }
        let total: usize = bytes.iter().map(Vec::len).sum();
        self.guard.check(&self.dir, total as u64)?;
        let locs = self.pack.append(&bytes)?;
        Ok(Packed {
            survey: s.id,
            entries: entries_keys.into_iter().zip(locs).collect(),
        })
    }

    /// Commits one change of the terrain in one batch, then flushes: a survey retired, one
    /// inserted (its chunks already packed: [`Store::pack_survey`]), or one replaced by the
    /// other, a file that changed. Every top the change moved is written, other surveys'
    /// among them; where a retirement and an insertion moved one box, the insertion's top wins,
    /// as it does in the terrain (a sled batch keeps the last write of a key). A failure
    /// leaves the store as it was, so the caller swaps in the terrain it computed the change
    /// with only on success.
    pub fn commit(&mut self, change: Change<'_>) -> Result<(), StoreError> {
        let t0 = Instant::now();
        let mut batch = Writes::default();
        let mut touched = Vec::with_capacity(2);
        if let Some(r) = &change.retire {
            let rec = self.stage_retire(&mut batch, r.id, r.patches, r.change)?;
            if r.pin && !rec.content_id.is_empty() {
                batch.insert(keys::pin(&rec.source), rec.content_id.as_bytes());
            }
            touched.push(r.id);
        }
        let replacing = change.retire.as_ref().map(|r| r.id);
        let staged = match change.insert {
            Some(i) => {
                touched.push(i.survey.id);
                Some(self.stage_survey(&mut batch, &i, replacing)?)
            }
            None => None,
        };
        stage_edges(&mut batch, change.edges)?;
        self.stage_healed(&mut batch, &touched)?;
        self.apply(batch)?;
        self.healed(&touched);
        match staged {
            Some(staged) => self.finish(staged, t0),
            None => Ok(()),
        }
    }

    /// Records a file that could not be ingested, replacing any earlier record of the same
    /// path. When `keep` records are already there, the oldest go in the same batch: a client
    /// that sends thousands of bad paths cannot grow the store without bound.
    pub fn record_failure(&mut self, f: &FailedRecord, keep: usize) -> Result<(), StoreError> {
        let key = keys::failure(&f.source);
        let mut others: Vec<(u64, sled::IVec)> = Vec::new();
        for kv in self.db.scan_prefix(keys::FAILURE_PREFIX) {
            let (k, v) = kv?;
            if k.as_ref() != key.as_slice() {
                let old: FailedRecord = decode(&v, "failure")?;
                others.push((old.at_unix, k));
            }
        }
        let mut batch = Writes::default();
        if others.len() >= keep {
            others.sort();
            for (_, k) in others.drain(..=others.len() - keep.max(1)) {
                batch.remove(k);
            }
        }
        batch.insert(key, encode(f)?);
        self.apply(batch)
    }

    /// Removes the failure recorded for `source`; whether there was one.
    pub fn forget_failure(&mut self, source: &str) -> Result<bool, StoreError> {
        let key = keys::failure(source);
        if self.db.get(&key)?.is_none() {
            return Ok(false);
        }
        let mut batch = Writes::default();
        batch.remove(key);
        self.apply(batch)?;
        Ok(true)
    }

    pub fn clear_failure(&mut self, source: &str) -> Result<(), StoreError> {
        if self.db.get(keys::failure(source))?.is_some() {
            self.forget_failure(source)?;
        }
        Ok(())
    }

    /// The files whose surveys were retired by hand, with the content that stays retired.
    pub fn pins(&self) -> Result<HashMap<String, String>, StoreError> {
        self.db
            .scan_prefix(keys::PIN_PREFIX)
            .map(|kv| {
                let (k, v) = kv?;
                let source = String::from_utf8_lossy(&k[keys::PIN_PREFIX.len()..]).into_owned();
                let content = String::from_utf8(v.to_vec()).map_err(|_| {
                    StoreError::Corrupt(format!("the pin of {source:?} is not text"))
                })?;
                Ok((source, content))
            })
            .collect()
    }

    /// Drops the pin of `source`, whose file is gone.
    pub fn unpin(&mut self, source: &str) -> Result<(), StoreError> {
        let mut batch = Writes::default();
        batch.remove(keys::pin(source));
        self.apply(batch)
    }

    /// Every pair's evidence, once each (under its smaller id's key).
    pub fn all_pairs(&self) -> Result<Vec<Arc<PairEvidence>>, StoreError> {
        let mut out = Vec::new();
        for kv in self.db.scan_prefix(keys::OVERLAP_PREFIX) {
            let (k, v) = kv?;
            let (a, b) = keys::parse_overlap(&k).ok_or_else(|| {
                StoreError::Corrupt(format!("bad overlap key {:?}", String::from_utf8_lossy(&k)))
            })?;
            if a < b {
                let p = decode(&v, &format!("overlap {}", String::from_utf8_lossy(&k)))?;
                out.push(Arc::new(p));
            }
        }
        Ok(out)
    }

    /// The records, failures and pins as they stand.
    pub fn catalog(&self) -> Result<Catalog, StoreError> {
        Ok(Catalog {
            records: self.surveys()?,
            failures: self.failures()?,
            pins: self.pins()?,
            damaged: self.damaged(),
            crs: self.crs(),
            vertical: self.vertical_crs(),
            layout: self.layout,
            recipe: self.recipe,
        })
    }

    /// The space rules the store writes under.
    pub fn guard(&self) -> &SpaceGuard {
        &self.guard
    }

    /// Whether a small write would fit now; the reason when it would not.
    pub fn writable(&self) -> Result<(), StoreError> {
        self.guard.check(&self.dir, 0)
    }

    /// Every survey record, active and retired, in id order; a record that does not decode is
    /// left out (it is among [`Store::damaged`]).
    pub fn surveys(&self) -> Result<Vec<SurveyRecord>, StoreError> {
        Ok(self.records()?.0)
    }

    /// Every record that decodes under its own key, and, by the id in their key, the surveys
    /// whose records do not: one scan, each record decoded once.
    fn records(&self) -> Result<(Vec<SurveyRecord>, Vec<Damaged>), StoreError> {
        let (mut good, mut bad) = (Vec::new(), Vec::new());
        for kv in self.db.scan_prefix(keys::SURVEY_PREFIX) {
            let (k, v) = kv?;
            let what = format!("record {}", String::from_utf8_lossy(&k));
            let Some(id) = keys::parse_survey(&k) else {
                continue;
            };
            match decode::<SurveyRecord>(&v, &what) {
                Ok(r) if r.id == id => good.push(r),
                Ok(r) => bad.push(Damaged {
                    id,
                    reason: format!("{what} holds the record of {}", r.id),
                    source: r.source,
                }),
                Err(e) => bad.push(Damaged {
                    id,
                    source: String::new(),
                    reason: e.to_string(),
                }),
            }
        }
        Ok((good, bad))
    }

    /// The evidence of every pair `id` is in, by the other's id.
    pub fn pairs_of(&self, id: SurveyId) -> Result<Vec<PairEvidence>, StoreError> {
        self.db
            .scan_prefix(keys::overlaps_of(id))
            .map(|kv| {
                let (k, v) = kv?;
                decode(&v, &format!("overlap {}", String::from_utf8_lossy(&k)))
            })
            .collect()
    }

    /// Every recorded failure, in source order.
    pub fn failures(&self) -> Result<Vec<FailedRecord>, StoreError> {
        self.db
            .scan_prefix(keys::FAILURE_PREFIX)
            .map(|kv| {
                let (k, v) = kv?;
                decode(&v, &format!("failure {}", String::from_utf8_lossy(&k)))
            })
            .collect()
    }

    /// Bytes of the files under the store's directory.
    pub fn disk_bytes(&self) -> u64 {
        dir_bytes(&self.dir)
    }

    /// The raw tree, for tests and tools that need to look under the records.
    #[doc(hidden)]
    pub fn raw(&self) -> &sled::Tree {
        &self.db
    }

    /// The chunk pack, for tests and tools that need to look under the records.
    #[doc(hidden)]
    pub fn raw_pack(&self) -> &dyn ChunkStore {
        self.pack.as_ref()
    }
}

/// The writes an index change calls for: the tops of the boxes it moved, and the removal of
/// the boxes it removed (an edge patch's record among them).
fn stage_change(batch: &mut Writes, change: &ChangeStats) {
    for id in &change.removed {
        batch.remove(keys::top(*id));
        batch.remove(keys::edge(*id));
    }
    for (id, st) in &change.moved {
        batch.insert(keys::top(*id), &encode_state(st));
    }
}

/// Writes each pair's evidence under both its surveys' keys.
fn stage_pairs(batch: &mut Writes, pairs: &[Arc<PairEvidence>]) -> Result<(), StoreError> {
    for p in pairs {
        let v = encode(p.as_ref())?;
        batch.insert(keys::overlap(p.finer, p.coarser), v.clone());
        batch.insert(keys::overlap(p.coarser, p.finer), v);
    }
    Ok(())
}

/// The edge patches a commit leaves in place, written after every removal it stages: one
/// that a retirement removed and an insertion brought back is there.
fn stage_edges(batch: &mut Writes, edges: &[Arc<EdgePatch>]) -> Result<(), StoreError> {
    for e in edges {
        batch.insert(keys::edge(e.id), encode(e.as_ref())?);
    }
    Ok(())
}

/// Bytes of the files under `dir`: a store's size on disk.
pub fn dir_bytes(dir: &Path) -> u64 {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return 0;
    };
    rd.filter_map(Result::ok)
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => dir_bytes(&e.path()),
            Ok(t) if t.is_file() => e.metadata().map(|m| m.len()).unwrap_or(0),
            _ => 0,
        })
        .sum()
}
