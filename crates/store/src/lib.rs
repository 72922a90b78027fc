//! The persistent store: surveys, their samples and the LOD index's box tops, in one sled tree.
//!
//! Everything but the chunk bytes lives in sled's default tree, so that one `sled::Batch` can
//! commit a survey and every index change it caused atomically; the chunk bytes go to an
//! append-only pack beside it first, and the batch points at them (see [`pack`]). Keys (ids are 16 lowercase hex digits):
//!
//! | key | value |
//! | --- | --- |
//! | `meta/schema` | `u32` LE: the schema version (see `migrations/`) |
//! | `meta/crs` | the store's horizontal CRS as its [`Crs::key`] (UTF-8): the config's, else EPSG:4326 (a store made before that default: its first survey's) |
//! | `meta/vertical_crs` | the store's vertical CRS as its [`VerticalCrs::key`] (UTF-8): the config's, or the first survey's that names one |
//! | `meta/layout`, `meta/index` | the [`PatchLayout`] and [`IndexConfig`] (bincode) |
//! | `meta/mipmap` | the name of the mipmap [`Filter`] its surveys are built with, set when the store is made (absent: `smooth`, a store from before the choice) |
//! | `meta/patches` | the name of the [`PatchKind`] its surveys' patches are, set when the store is made (absent: `bilinear`, a store from before the choice) |
//! | `meta/contradicted` | `distrust` or `keep`: what the store does with a claim other surveys find false, set when the store is made |
//! | `meta/blend` | the name of the [`Blend`] its patches are resampled with, set when the store is made (absent: `formula1`, a store from before the choice) |
//! | `s/<survey>` | [`SurveyRecord`] (bincode) |
//! | `p/<survey>` | where the survey's [`StoredPatches`] are in the pack: its patches and the edge tiles it reaches (bincode, sealed with [`chunks::seal`]) |
//! | `a/<survey>` | the [`KernelAccuracy`] of a survey whose ε was estimated (bincode) |
//! | `c/<survey>/<level:02>/<k:08>` | where chunk `k` of a level is in the pack ([`pack::Loc`]): [`chunks::CHUNK`]² samples, compressed and checksummed (see [`chunks`]) |
//! | `meta/pack_len` | `u64` LE: the committed length of the chunk pack |
//! | `meta/pack_at` | the URL of the object store the chunks are in (UTF-8); absent for the local pack |
//! | `meta/pack_base` | on an object store, after a compaction: `u64` LE where the address space it left behind ends, then `u64` LE the Unix time it did; the segments below it are deleted once the grace period has passed |
//! | `meta/log_seq` | on an object store: `u64` LE, the newest commit of the journal replicas follow (see [`journal`]) |
//! | `meta/log_pending` | on the writer: what the newest commit's log is made from (bincode) |
//! | `meta/follows` | on a replica: the URL of the place it follows (UTF-8) |
//! | `e/<patch>` | an [`EdgePatch`] the active surveys call for (bincode) |
//! | `b/<unit>` | the [`BoxState`] of every box of a unit (a survey, or an edge patch) in the LOD index, in patch id order: each the patch id `u64` LE, the top `f64` LE, then a byte that is 1 when the box is exposed. One record a unit, not a key a box: the database keeps a node entry in memory for every key |
//! | `o/<survey>/<other>` | [`PairEvidence`] (bincode): what two overlapping surveys say of each other's claims, under both orders |
//! | `f/<source path>` | [`FailedRecord`] (bincode); at most one a path, and a bounded number |
//! | `r/<source path>` | hex content id of a file whose survey was retired by hand while the file stayed in the inbox |
//! | `meta/rebuild` | present when the next open must derive the index again from the surveys |
//! | `meta/quarantined` | the ids of the damaged surveys the stored index was derived without (bincode `Vec<SurveyId>`); absent when none are |
//! | `meta/checked_to` | in stores from before [`pack::CHECKED_FILE`]: how far opens had read the local pack back (`u64` LE); read where the pack has no such file, never written now |
//!
//! Beside the database, in the same directory: the local pack ([`pack::PACK_FILE`]) and the
//! note of how far opens read it back ([`pack::CHECKED_FILE`]), kept out of the database so
//! that an open writes nothing to it.
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
mod commit;
mod compact;
pub mod folder;
pub mod form;
mod journal;
pub mod keys;
mod lease;
mod migrate;
pub mod objects;
mod open;
pub mod pack;
mod records;
mod settings;
pub mod space;
mod verify;

pub use chunks::{CacheStats, ChunkReader};
pub use compact::{CompactFailed, CompactReport};
pub use journal::Following;
pub use migrate::CURRENT as SCHEMA_VERSION;
use pack::ChunkStore;
use patchwork_core::sync::{lock, read, write};
pub use space::{DiskSpace, SpaceGuard, SystemDisk};
pub use verify::{Checked, VerifyReport};

pub use commit::{Change, Insertion, Packed, Retirement};
use open::*;
pub use records::{
    Catalog, Damaged, FailedRecord, IngestTimings, LevelHeader, Status, StoredPatches, SurveyRecord,
};
use settings::*;

use fs2::FileExt;
use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::Crs;
use patchwork_core::index::lod::{BoxState, ChangeStats, IndexConfig};
use patchwork_core::model::accuracy::{AccuracySource, AccuracySpec, KernelAccuracy};
use patchwork_core::model::edge::EdgePatch;
use patchwork_core::model::epoch::Epoch;
use patchwork_core::model::evidence::{Contradicted, PairEvidence};
use patchwork_core::model::grid::{Georef, Grid, Shape};
use patchwork_core::model::ids::{PatchId, SurveyId};
use patchwork_core::model::mipmap::Filter;
use patchwork_core::model::patch::Blend;
use patchwork_core::model::patch::{PatchKind, PatchLayout, Tiling};
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
    /// The free-space rules every write is checked against.
    pub guard: SpaceGuard,
    /// Bytes of decoded chunks kept in memory; sled's own page cache takes a quarter of it
    /// more (see [`StoreOptions::sled_cache_bytes`]).
    pub cache_bytes: u64,
    /// The mipmap filter and patch kind of a new store; an existing one keeps its own.
    pub recipe: Recipe,
    /// What a new store does with contradicted claims; an existing one keeps its own.
    pub contradicted: Contradicted,
    /// How a new store blends its patches; an existing one keeps its own.
    pub blend: Blend,
    /// Where the chunk bytes go. A store keeps the backend it was made with.
    pub backend: ChunkBackend,
    /// On an object store, at least this many commits between snapshots of the database for
    /// replicas (one is due once the logs since the last add up to a quarter of its size).
    pub snapshot_every: u64,
}

/// Where a store's chunk bytes live; the database stays in the store's directory either way.
#[derive(Clone, Debug, Default)]
pub enum ChunkBackend {
    /// The pack file beside the database.
    #[default]
    Local,
    /// Segments of an object store (see [`objects`]).
    Objects(objects::Objects),
    /// Another writer's segments, followed read-only: the store is a read replica whose
    /// database is the writer's as published (see [`journal`]).
    Follow(objects::Objects),
}

impl StoreOptions {
    /// sled's page cache: a quarter of the chunk cache, at least 8 MiB. It holds the records,
    /// patches and tops that an open reads once and commits touch; the samples have their own
    /// cache, so a large sled cache would only hold the same chunks a second time, compressed.
    pub fn sled_cache_bytes(&self) -> u64 {
        (self.cache_bytes / 4).max(8 << 20)
    }

    /// The terrain's cache of edge patches' samples, made again from the chunks when a read
    /// needs them: an eighth of the chunk cache, at least 4 MiB. An edge patch's samples are
    /// about 10 kB, so 64 MiB (the default's) holds some 6,000 of them; a store of 10,000
    /// abutting tiles of 36² has 1,156.
    pub fn edge_cache_bytes(&self) -> u64 {
        (self.cache_bytes / 8).max(4 << 20)
    }
}

impl Default for StoreOptions {
    fn default() -> Self {
        StoreOptions {
            guard: SpaceGuard::default(),
            cache_bytes: DEFAULT_CACHE_BYTES,
            recipe: Recipe::default(),
            contradicted: Contradicted::default(),
            blend: Blend::default(),
            backend: ChunkBackend::Local,
            snapshot_every: 64,
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

/// Why a store could not be opened, read or written.
#[non_exhaustive]
#[derive(Debug, Error)]
pub enum StoreError {
    /// The store was written by a newer patchwork, in a schema this one cannot read.
    #[error(
        "the store's schema is version {found}, but this binary supports versions up to \
         {supported}: open it with a newer patchwork"
    )]
    Newer {
        /// The store's schema version.
        found: u32,
        /// The newest schema version this binary reads.
        supported: u32,
    },
    /// Another process holds the store's lock.
    #[error("the store at {} is in use by another process (is the daemon running?)", dir.display())]
    Locked {
        /// The store's directory.
        dir: PathBuf,
    },
    /// The store's files are not as the store leaves them.
    #[error("the store is corrupt: {0}")]
    Corrupt(Corruption),
    /// The store is kept elsewhere than `[storage]` says: a store keeps the backend it was
    /// made with.
    #[error(
        "the store's chunks are in {stored}, but [storage] names {configured}: a store keeps \
         the backend it was made with"
    )]
    Backend {
        /// Where its chunks are.
        stored: String,
        /// Where the settings say they are.
        configured: String,
    },
    /// A replica's writer is at another schema than this binary.
    #[error(
        "the store {url} follows is at schema {found}, this build's is {supported}: a replica \
         runs the writer's version"
    )]
    ReplicaSchema {
        /// The place the replica follows.
        url: String,
        /// The writer's schema.
        found: u32,
        /// This binary's.
        supported: u32,
    },
    /// A replica's directory follows another place, or holds a store of its own.
    #[error("{} {}: a replica needs a directory of its own, which it fills from {url}", dir.display(), holds)]
    NotAReplica {
        /// The directory.
        dir: PathBuf,
        /// What it holds instead: `holds a store of its own`, `is a replica of …`.
        holds: String,
        /// The place asked to follow.
        url: String,
    },
    /// A commit a replica was asked to read is not published yet.
    #[error("commit {seq} is not yet published to {url}")]
    Unpublished {
        /// The commit.
        seq: u64,
        /// Where it would be.
        url: String,
    },
    /// The writer asked the store to commit something that does not hold together (a bug of
    /// the caller's, refused before anything is written).
    #[error("survey {survey}: {what}; nothing was written")]
    Inconsistent {
        /// The survey committed.
        survey: SurveyId,
        /// What does not match.
        what: &'static str,
    },
    /// A migration step failed; the store is left at the schema it had before the step.
    #[error("migration of the store from schema {from} to {to} failed: {msg}")]
    Migration {
        /// The schema version the step starts from.
        from: u32,
        /// The schema version the step goes to.
        to: u32,
        /// What went wrong.
        msg: String,
    },
    /// A survey placed in another horizontal CRS than the store's was committed.
    #[error(
        "survey {survey} was placed in {placed_in}, but the store's CRS is {store_crs}; the \
         engine places a survey in the store's CRS before committing it"
    )]
    CrsMismatch {
        /// The survey committed.
        survey: SurveyId,
        /// The CRS it was placed in, as its label.
        placed_in: String,
        /// The store's CRS, as its label.
        store_crs: String,
    },
    /// A survey's heights are in another vertical CRS than the store's.
    #[error(
        "survey {survey}'s heights are in {survey_vertical}, but the store's are in \
         {store_vertical}: the store took that vertical CRS while the file was read; it will \
         be ingested again"
    )]
    VerticalMismatch {
        /// The survey committed.
        survey: SurveyId,
        /// The survey's vertical CRS, as its label.
        survey_vertical: String,
        /// The store's vertical CRS, as its label.
        store_vertical: String,
    },
    /// The survey inserted is already an active survey of the store.
    #[error("survey {0} is already stored and active")]
    Duplicate(SurveyId),
    /// The survey retired or replaced is not an active survey of the store.
    #[error("survey {0} is not an active survey of the store")]
    NotActive(SurveyId),
    /// A compaction asked of a store with a damaged survey, which it would lose.
    #[error(
        "survey {survey} is damaged ({reason}): ingest its file again or run `patchwork repair` \
         before compacting"
    )]
    Damaged {
        /// The damaged survey.
        survey: SurveyId,
        /// What is wrong with it.
        reason: String,
    },
    /// A store directory whose path has no last component (`/`, `..`).
    #[error("the store path {} has no name", .0.display())]
    Unnamed(PathBuf),
    /// The write would leave less free disk space than the store keeps; nothing was written.
    #[error(
        "the disk holding the store has {available_mb} MiB free, and this write needs \
         {needed_mb} MiB with the space kept free (storage.min_free_mb): free some space or \
         compact the store; nothing was written"
    )]
    Full {
        /// MiB free on the disk.
        available_mb: u64,
        /// MiB the write needs, the space kept free included.
        needed_mb: u64,
    },
    /// The database (sled) failed.
    #[error("storage engine: {0}")]
    Sled(sled::Error),
    /// A file or the object store the store uses could not be read or written.
    #[error("store I/O: {0}")]
    Io(std::io::Error),
    /// A record could not be encoded.
    #[error("could not encode a record: {0}")]
    Encode(String),
    /// A record does not decode as what the store wrote under its key.
    #[error("could not decode {what}: {why}")]
    Decode {
        /// The record.
        what: String,
        /// Why not.
        why: String,
    },
    /// Samples a read or an index change needed could not be read back.
    #[error(transparent)]
    Samples(#[from] patchwork_core::model::source::SampleError),
    /// A survey could not be placed in the store's CRS.
    #[error(transparent)]
    Place(#[from] patchwork_core::model::place::PlaceError),
    /// A read replica refuses writes: they go to the writer it follows.
    #[error("this is a read replica of {url}: writes go to its writer{}", writer.as_ref().map(|w| format!(", {w}")).unwrap_or_default())]
    Replica {
        /// The URL of the place the replica follows.
        url: String,
        /// Who holds the writer's lease there now, if anyone does and it could be read.
        writer: Option<String>,
    },
}

// These variants' messages name the inner error already, so it is not also their source: a
// reporter that walks the chain would print it twice.
impl From<Corruption> for StoreError {
    fn from(e: Corruption) -> Self {
        StoreError::Corrupt(e)
    }
}

impl From<std::io::Error> for StoreError {
    fn from(e: std::io::Error) -> Self {
        StoreError::Io(e)
    }
}

/// What is wrong with a store's files: the part that does not read back as written.
#[non_exhaustive]
#[derive(Debug, Error)]
pub enum Corruption {
    /// sled's own files are damaged; `advice` says how to recover.
    #[error("the database files in {} are damaged ({what}): {advice}", dir.display())]
    Files {
        /// The store's directory.
        dir: PathBuf,
        /// sled's first line about it.
        what: String,
        /// What to do: move a snapshot aside, or restore from a backup.
        advice: String,
    },
    /// A fixed-size value of another size.
    #[error("{key} holds {len} bytes, not {expected}")]
    Length {
        /// The key.
        key: &'static str,
        /// Its length.
        len: usize,
        /// The length it must have.
        expected: usize,
    },
    /// A record the store must have is not there.
    #[error("{0} is missing")]
    Missing(String),
    /// A key of a prefix that does not parse.
    #[error("bad {kind} key {key:?}")]
    Key {
        /// The prefix's records: `boxes`, `edge`, `overlap`.
        kind: &'static str,
        /// The key, lossily as text.
        key: String,
    },
    /// A record that does not read back: a bad checksum, bytes past the end, not text.
    #[error("{what}: {why}")]
    Unreadable {
        /// The record.
        what: String,
        /// Why not.
        why: String,
    },
    /// A level with too few samples to be one.
    #[error("level {level} of survey {survey} is {cols}×{rows} samples")]
    LevelShape {
        /// The survey.
        survey: SurveyId,
        /// The level.
        level: usize,
        /// Its columns.
        cols: usize,
        /// Its rows.
        rows: usize,
    },
    /// A survey without levels.
    #[error("survey {0} has no levels")]
    NoLevels(SurveyId),
    /// A survey's patch list names a patch of another survey, or a level it does not have.
    #[error("survey {survey} lists patch {patch} of survey {of} at level {level}, which it does not have")]
    ForeignPatch {
        /// The survey.
        survey: SurveyId,
        /// The patch.
        patch: PatchId,
        /// The survey the patch says it is of.
        of: SurveyId,
        /// The level the patch says it is at.
        level: usize,
    },
    /// A patch's stored place in its level's tiling lies outside it, or its kernel or
    /// window is not the one its survey's tiling gives there.
    #[error("patch {patch} of survey {survey} has a window its survey's tiling does not give")]
    PatchWindow {
        /// The survey.
        survey: SurveyId,
        /// The patch.
        patch: PatchId,
    },
    /// A survey's kernel accuracies do not match its kernels.
    #[error("survey {survey} has {have:?} kernel accuracies for {want:?} kernels")]
    Accuracies {
        /// The survey.
        survey: SurveyId,
        /// The accuracies stored.
        have: [usize; 2],
        /// The kernels it has.
        want: [usize; 2],
    },
    /// A replica's log holds another commit than its name says.
    #[error("{what} holds commit {found}")]
    Commit {
        /// The log.
        what: String,
        /// The commit it holds.
        found: u64,
    },
    /// A compaction's copy is there and the store is not: moved by hand, since compaction
    /// never leaves that state.
    #[error("{} is missing but {} exists; if that is the store, rename it back", dir.display(), copy.display())]
    Swapped {
        /// The store's directory.
        dir: PathBuf,
        /// The copy found beside it.
        copy: PathBuf,
    },
    /// A schema version no migration starts from.
    #[error("no migration leads from schema version {0}")]
    NoMigration(u32),
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

/// Seconds since the Unix epoch now; 0 on a clock set before it.
pub fn now_unix() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

/// A record as the store writes it: bincode's standard configuration. Part of the format
/// (the format tests decode every committed record and encode it back).
pub fn encode<T: Serialize>(v: &T) -> Result<Vec<u8>, StoreError> {
    bincode::serde::encode_to_vec(v, bincode::config::standard())
        .map_err(|e| StoreError::Encode(e.to_string()))
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

/// The error of a record `what` that does not decode, and why.
pub fn decode_error(what: &str, why: impl std::fmt::Display) -> StoreError {
    StoreError::Decode {
        what: what.to_string(),
        why: why.to_string(),
    }
}

/// A record as the store reads it: the whole of `b`, or an error naming `what`.
pub fn decode<T: DeserializeOwned>(b: &[u8], what: &str) -> Result<T, StoreError> {
    let (v, n) = bincode::serde::decode_from_slice(b, bincode::config::standard())
        .map_err(|e| decode_error(what, e))?;
    if n != b.len() {
        let left = b.len() - n;
        return Err(decode_error(
            what,
            format!("{left} bytes left over after the value"),
        ));
    }
    Ok(v)
}

/// An edge patch's record (`e/`) read back, its grid's parts checked to agree.
pub fn decode_edge(b: &[u8], what: &str) -> Result<EdgePatch, StoreError> {
    EdgePatch::try_from(decode::<form::Edge>(b, what)?).map_err(|e| decode_error(what, e))
}

/// A box's state in a unit's record: the top (f64 LE), then 1 where it is exposed.
pub fn encode_state(s: &BoxState) -> [u8; 9] {
    let mut b = [0u8; 9];
    b[..8].copy_from_slice(&s.top.to_le_bytes());
    b[8] = u8::from(s.exposed);
    b
}

/// [`encode_state`] read back.
pub fn decode_state(b: &[u8], what: &str) -> Result<BoxState, StoreError> {
    let bad = || decode_error(what, format!("{} bytes, not a top and a flag", b.len()));
    let a: [u8; 9] = b.try_into().map_err(|_| bad())?;
    if a[8] > 1 {
        return Err(bad());
    }
    Ok(BoxState {
        top: f64::from_le_bytes(a[..8].try_into().expect("8 bytes")),
        exposed: a[8] == 1,
    })
}

/// Bytes a box takes in a unit's record: its patch id, then its state.
const BOX_BYTES: usize = 8 + 9;

/// A unit's box states as one record: each box's id (`u64` LE) and state, in id order.
pub(crate) fn encode_states(states: &[(PatchId, BoxState)]) -> Vec<u8> {
    let mut b = Vec::with_capacity(states.len() * BOX_BYTES);
    for (id, st) in states {
        b.extend_from_slice(&id.0.to_le_bytes());
        b.extend_from_slice(&encode_state(st));
    }
    b
}

pub(crate) fn decode_states(b: &[u8], what: &str) -> Result<Vec<(PatchId, BoxState)>, StoreError> {
    if !b.len().is_multiple_of(BOX_BYTES) {
        return Err(decode_error(
            what,
            format!("{} bytes, not a whole number of box states", b.len()),
        ));
    }
    let mut out: Vec<(PatchId, BoxState)> = Vec::with_capacity(b.len() / BOX_BYTES);
    for e in b.chunks_exact(BOX_BYTES) {
        let id = PatchId(u64::from_le_bytes(e[..8].try_into().expect("8 bytes")));
        if out.last().is_some_and(|(last, _)| *last >= id) {
            return Err(decode_error(what, format!("patch {id} out of order")));
        }
        out.push((id, decode_state(&e[8..], what)?));
    }
    Ok(out)
}

/// A store's path to a sibling of its directory: `<dir><suffix>`.
fn sibling(dir: &Path, suffix: &str) -> Result<PathBuf, StoreError> {
    let name = dir
        .file_name()
        .ok_or_else(|| StoreError::Unnamed(dir.to_path_buf()))?;
    let mut n = name.to_os_string();
    n.push(suffix);
    Ok(dir.with_file_name(n))
}

/// Closes the store's chunk reader when the store goes, however it goes.
struct CloseReader(Arc<ChunkReader>);

impl Drop for CloseReader {
    fn drop(&mut self) {
        self.0.close();
    }
}

// The engine's writer and every reader's thread share one store: it stays Send and Sync, which
// the crate's compilation checks (a type, not a behaviour, so not a test).
const _: () = {
    const fn shared<T: Send + Sync>() {}
    shared::<Store>()
};

/// An open store: its database, its chunk pack and its settings, under its lock.
pub struct Store {
    db: sled::Db,
    pack: Arc<dyn ChunkStore>,
    reader: Arc<ChunkReader>,
    _close_reader: CloseReader,
    opts: StoreOptions,
    guard: SpaceGuard,
    dir: PathBuf,
    layout: PatchLayout,
    index: IndexConfig,
    recipe: Recipe,
    contradicted: Contradicted,
    blend: Blend,
    /// The catalog last made, and the keys written since (see [`Store::catalog`]).
    catalog: std::sync::Mutex<records::CatalogCache>,
    /// The horizontal and vertical CRSs, once set.
    crs: RwLock<(Option<Crs>, Option<VerticalCrs>)>,
    migrated: Vec<(u32, u32)>,
    /// The damaged surveys the last open found, less those healed or dropped since.
    damaged: RwLock<BTreeMap<SurveyId, Damaged>>,
    /// The journal replicas follow, on a writer whose chunks are on an object store; or the
    /// writer's journal this replica follows.
    replication: Replication,
    _lock: File,
}

/// A store's part in replication (see [`journal`]).
enum Replication {
    /// The local pack: no replicas.
    None,
    Writer(journal::Journal),
    Follower(journal::Follower),
}

/// What the index is rebuilt from at open: the surveys without their samples, the edge
/// patches and the box states. Building the terrain from it is the caller's (see
/// the engine's `restore`); the store reads and writes, and builds nothing.
pub struct Contents {
    /// The active surveys, damaged ones aside, without their samples.
    pub surveys: Vec<Arc<SurveyMeta>>,
    /// What each overlapping pair says of the other's claims.
    pub pairs: Vec<Arc<PairEvidence>>,
    /// The edge patches the surveys call for.
    pub edges: Vec<Arc<EdgePatch>>,
    /// The stored state of every box of the index, by patch id.
    pub tops: HashMap<PatchId, BoxState>,
    /// The index must be derived again from the surveys (a migration asked for it, or a
    /// survey is damaged that the stored index holds).
    pub rebuild: bool,
    /// Active surveys left out because they are damaged; not among `surveys`.
    pub damaged: Vec<Damaged>,
}

/// A store just opened, with what it holds for the index.
pub struct Loaded {
    /// The store, open.
    pub store: Store,
    /// What the index is rebuilt from.
    pub contents: Contents,
    /// Problems met while opening that did not stop it.
    pub warnings: Vec<String>,
    /// Whether the disk was so full that the reserve file was given back to open the store.
    pub released_reserve: bool,
}

impl Store {
    /// The store's directory.
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

    /// How this store's patches are blended into heights.
    pub fn blend(&self) -> Blend {
        self.blend
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

    /// How many bytes of edge patches' samples the terrain keeps (see
    /// [`StoreOptions::edge_cache_bytes`]).
    pub fn edge_cache_bytes(&self) -> u64 {
        self.opts.edge_cache_bytes()
    }

    /// The reader the terrain gets its samples through.
    pub fn reader(&self) -> Arc<ChunkReader> {
        self.reader.clone()
    }

    /// The space rules the store writes under.
    pub fn guard(&self) -> &SpaceGuard {
        &self.guard
    }

    /// Whether a small write would fit now; the reason when it would not.
    pub fn writable(&self) -> Result<(), StoreError> {
        self.guard.check(&self.dir, 0)
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
