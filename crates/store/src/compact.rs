//! Compaction: drop what retirements left behind and rewrite the sled files to give the space
//! back.
//!
//! sled reclaims space lazily and never shrinks its files much, so the live keys are copied
//! into a fresh database beside the store and the directories are swapped:
//!
//! 1. copy the live keys into `<dir>.compact` and flush it;
//! 2. close the store, rename `<dir>` → `<dir>.old`;
//! 3. rename `<dir>.compact` → `<dir>`;
//! 4. delete `<dir>.old`.
//!
//! [`recover`] runs on every open and finishes or undoes whatever a crash interrupted.

use super::chunks::read_packed;
use super::pack::{ChunkStore, PackFile};
use super::{
    decode_states, dir_bytes, keys, open_sled, sibling, ChunkBackend, Corruption, Loaded,
    Replication, Status, Store, StoreError,
};
use patchwork_core::model::ids::{PatchId, SurveyId};
use patchwork_core::sync::lock;
use std::collections::HashSet;
use std::path::Path;
use std::sync::Arc;

/// What a compaction ([`Store::compact`]) did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CompactReport {
    /// Bytes of the store's directory before the compaction.
    pub bytes_before: u64,
    /// Bytes of the store's directory after it.
    pub bytes_after: u64,
    /// Retired surveys whose samples and patches were removed (their records stay).
    pub surveys_purged: usize,
    /// Keys dropped because they belong to no active survey or live patch.
    pub keys_removed: u64,
    /// Whether the compacted copy replaced the store: not when nothing was removed and the
    /// copy was no smaller.
    pub swapped: bool,
    /// Keys the store keeps.
    pub keys_kept: u64,
}

/// A compaction that failed ([`Store::compact`]): why, and the store, open as it was, where the
/// failure came before the copy replaced it. Without it (the swap or the open of the copy
/// failed), the next open finds the directories as [`recover`] expects them.
pub struct CompactFailed {
    /// The store, open, where the failure left it as it was.
    pub store: Option<Box<Store>>,
    /// Why it failed.
    pub error: StoreError,
}

impl std::fmt::Debug for CompactFailed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CompactFailed")
            .field("store_open", &self.store.is_some())
            .field("error", &self.error)
            .finish()
    }
}

impl From<CompactFailed> for StoreError {
    fn from(f: CompactFailed) -> StoreError {
        f.error
    }
}

/// What [`Store::copy_live`] did, for the report, and whether the copy is to replace the store.
struct Copied {
    bytes_before: u64,
    surveys_purged: usize,
    kept: u64,
    removed: u64,
    swap: bool,
}

/// Batches of about this many bytes fill the new database, so that a large store is not held
/// in memory twice.
const COPY_BATCH_BYTES: usize = 64 << 20;

fn sync_dir(dir: &Path) {
    // Makes the renames durable. Best effort: not every filesystem lets a directory be synced.
    if let Some(parent) = dir.parent() {
        if let Ok(f) = std::fs::File::open(parent) {
            let _ = f.sync_all();
        }
    }
}

/// Puts the directories back in order after a crash during compaction. Called with the
/// store's lock held, so no compaction is running.
pub(super) fn recover(dir: &Path) -> Result<(), StoreError> {
    let old = sibling(dir, ".old")?;
    let tmp = sibling(dir, ".compact")?;
    match (dir.exists(), old.exists()) {
        // Between the two renames: `.old` is the whole store as it was before compaction.
        // Rolling back to it loses nothing; the compaction can simply be run again.
        (false, true) => {
            if tmp.exists() {
                std::fs::remove_dir_all(&tmp)?;
            }
            std::fs::rename(&old, dir)?;
            sync_dir(dir);
        }
        // After both renames: `<dir>` is the compacted store and `.old` is garbage.
        (true, true) => std::fs::remove_dir_all(&old)?,
        (false, false) if tmp.exists() => {
            // Compaction never leaves this state, so someone moved things by hand: the copy
            // may be all there is, and deleting it is not ours to decide.
            return Err(Corruption::Swapped {
                dir: dir.to_path_buf(),
                copy: tmp.clone(),
            }
            .into());
        }
        _ => {}
    }
    // A copy that was never swapped in.
    if dir.exists() && tmp.exists() {
        std::fs::remove_dir_all(&tmp)?;
    }
    Ok(())
}

impl Store {
    /// Removes retired surveys for good (records, samples, patches) and every key that belongs
    /// to no active survey, then rewrites the files. `live` holds the patches of the terrain
    /// the store holds (its surveys' and the edge patches they call for): only their box
    /// states and edge patches are kept. A pin stays: it names a file's content, not a survey.
    ///
    /// A failure before the copy replaces the store gives the store back as it was, open (see
    /// [`CompactFailed`]): a full disk, the commonest cause, is no reason to close and open a
    /// store again.
    pub fn compact(
        self,
        live: &HashSet<PatchId>,
    ) -> Result<(Loaded, CompactReport), CompactFailed> {
        let back = |store: Store, error| CompactFailed {
            store: Some(Box::new(store)),
            error,
        };
        let copied = match self.copy_live(live) {
            Ok(c) => c,
            Err(e) => return Err(back(self, e)),
        };
        let Copied {
            bytes_before,
            surveys_purged,
            kept,
            removed,
            swap,
        } = copied;
        if swap {
            return self
                .swap(bytes_before, surveys_purged, removed, kept)
                .map_err(|error| CompactFailed { store: None, error });
        }
        let contents = match self.load() {
            Ok(c) => c,
            Err(e) => return Err(back(self, e)),
        };
        let bytes_after = self.disk_bytes();
        Ok((
            Loaded {
                store: self,
                contents,
                warnings: Vec::new(),
                released_reserve: false,
            },
            CompactReport {
                bytes_before,
                bytes_after,
                surveys_purged,
                keys_removed: removed,
                keys_kept: kept,
                swapped: false,
            },
        ))
    }

    /// Compaction's work up to the swap, which leaves the store as it is: the live keys copied
    /// to `<dir>.compact` where that pays, or what retirements left removed in place.
    fn copy_live(&self, live: &HashSet<PatchId>) -> Result<Copied, StoreError> {
        let bytes_before = self.disk_bytes();
        let dir = self.dir.clone();
        let tmp = sibling(&dir, ".compact")?;
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp)?;
        }
        match &self.replication {
            Replication::Follower(f) => return Err(f.refusal()),
            // Its log must be up before the copy, whose own log replaces the batches with a
            // snapshot.
            Replication::Writer(j) => j.publish(&self.db)?,
            Replication::None => {}
        }
        if let Some(d) = self.damaged().into_values().next() {
            return Err(StoreError::Damaged {
                survey: d.id,
                reason: d.reason,
            });
        }
        let records = self.surveys()?;
        let active: HashSet<SurveyId> = records
            .iter()
            .filter(|r| r.status == Status::Active)
            .map(|r| r.id)
            .collect();

        let surveys_purged = records
            .iter()
            .filter(|r| r.status == Status::Retired)
            .filter(|r| {
                self.db.scan_prefix(keys::chunks_of(r.id)).next().is_some()
                    || matches!(self.db.get(keys::patches(r.id)), Ok(Some(_)))
                    || matches!(self.db.get(keys::accuracy(r.id)), Ok(Some(_)))
            })
            .count();
        // A unit's box states go with the last of its boxes: units are surveys and edge
        // patches, and an edge patch's unit is no survey.
        let mut live_units = HashSet::new();
        for kv in self.db.scan_prefix(keys::BOXES_PREFIX) {
            let (k, v) = kv?;
            if let Some(unit) = keys::parse_boxes(&k) {
                let states = decode_states(&v, &String::from_utf8_lossy(&k))?;
                if states.iter().any(|(id, _)| live.contains(id)) {
                    live_units.insert(unit);
                }
            }
        }
        let live = |k: &[u8]| -> bool {
            if k.starts_with(keys::META_PREFIX)
                || k.starts_with(keys::FAILURE_PREFIX)
                || k.starts_with(keys::PIN_PREFIX)
            {
                return true;
            }
            if let Some(id) = keys::parse_survey(k) {
                return active.contains(&id);
            }
            if let Some(id) = keys::parse_patches(k).or_else(|| keys::parse_accuracy(k)) {
                return active.contains(&id);
            }
            if let Some((id, _, _)) = keys::parse_chunk(k) {
                return active.contains(&id);
            }
            if let Some(id) = keys::parse_edge(k) {
                return live.contains(&id);
            }
            if let Some(unit) = keys::parse_boxes(k) {
                return live_units.contains(&unit);
            }
            if let Some((a, b)) = keys::parse_overlap(k) {
                return active.contains(&a) && active.contains(&b);
            }
            false
        };
        // On an object store the copy uploads every live chunk again, which pays only where
        // something goes: with nothing to drop the store stays as it is, as after a copy that
        // gains nothing, and the bucket gains no segment to collect. (A key that cannot be
        // read counts as something to do: the copy reports it.)
        let remote = !matches!(self.opts.backend, ChunkBackend::Local);
        if remote {
            let mut keys_kept = 0u64;
            let nothing_goes = self.db.iter().keys().all(|k| {
                keys_kept += 1;
                k.is_ok_and(|k| live(&k))
            });
            if nothing_goes {
                return Ok(Copied {
                    bytes_before,
                    surveys_purged,
                    kept: keys_kept,
                    removed: 0,
                    swap: false,
                });
            }
        }
        let (mut kept, mut removed) = (0u64, 0u64);
        // The copy is checked against the free space batch by batch, like any write: a full
        // disk stops it with the store untouched, and the partial copy is deleted.
        let copied = (|| -> Result<(), StoreError> {
            let fresh = sled::Config::new().path(&tmp).open()?;
            // Live chunks alone go to the new pack, each synced before the batch naming it. On
            // an object store they go to new segments past the end instead, and the database
            // records where the old ones end, to be deleted once no reader can want them.
            let (pack, base): (Arc<dyn ChunkStore>, _) = match &self.opts.backend {
                ChunkBackend::Local => (Arc::new(PackFile::open(&tmp, 0)?), None),
                ChunkBackend::Objects(_) | ChunkBackend::Follow(_) => {
                    (self.pack.clone(), Some(self.pack.len()))
                }
            };
            let mut batch = sled::Batch::default();
            let mut chunks: Vec<(sled::IVec, Vec<u8>)> = Vec::new();
            let mut bytes = 0usize;
            let flush = |batch: &mut sled::Batch,
                         chunks: &mut Vec<(sled::IVec, Vec<u8>)>,
                         bytes: &mut usize|
             -> Result<(), StoreError> {
                self.guard.check(&dir, *bytes as u64)?;
                let (ks, vs): (Vec<_>, Vec<_>) = chunks.drain(..).unzip();
                let locs = pack.append(&vs)?;
                for (k, loc) in ks.into_iter().zip(locs) {
                    batch.insert(k, &loc.to_bytes()[..]);
                }
                batch.insert(keys::PACK_LEN, &pack.len().to_le_bytes()[..]);
                fresh.apply_batch(std::mem::take(batch))?;
                *bytes = 0;
                Ok(())
            };
            for kv in self.db.iter() {
                let (k, v) = kv?;
                if !live(&k) {
                    removed += 1;
                    continue;
                }
                // Every chunk moves to the new pack: the next open reads them all back.
                if k == keys::CHECKED_TO {
                    continue;
                }
                kept += 1;
                if keys::in_pack(&k) {
                    let b = read_packed(&self.db, self.pack.as_ref(), &k).map_err(|e| {
                        StoreError::from(Corruption::Unreadable {
                            what: String::from_utf8_lossy(&k).into_owned(),
                            why: e.to_string(),
                        })
                    })?;
                    bytes += k.len() + b.len();
                    chunks.push((k, b));
                } else if k.as_ref() != keys::PACK_LEN && k.as_ref() != keys::PACK_BASE {
                    bytes += k.len() + v.len();
                    batch.insert(k, v);
                }
                if bytes >= COPY_BATCH_BYTES {
                    flush(&mut batch, &mut chunks, &mut bytes)?;
                }
            }
            if let Some(base) = base {
                batch.insert(keys::PACK_BASE, super::open::encode_base(base));
            }
            // The copy has no batch a replica could replay: its log says to start again from
            // its snapshot, which the reopened store publishes.
            if let Replication::Writer(j) = &self.replication {
                super::journal::stage_rewrite(&mut batch, j.seq())?;
            }
            flush(&mut batch, &mut chunks, &mut bytes)?;
            fresh.flush()?;
            Ok(())
        })();
        if let Err(e) = copied {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
        // sled's files can come out of a copy larger than they went in (its log allocates
        // whole segments, and every open of them adds a little: 0.2–0.6 kB a time measured on
        // a 0.7 MB store), and a copy that removed a small retired survey was seen 4.8% larger
        // than the store. Compaction never grows a store: the copy, measured as the store
        // would be after opening it, replaces the store only when it is smaller, and with
        // nothing removed only when it saves clearly more than an open adds (1%, 64 KiB at
        // least), so that compacting again leaves the store's bytes as they are.
        drop(open_sled(&tmp, self.opts.sled_cache_bytes())?);
        let margin = if removed > 0 {
            1
        } else {
            (bytes_before / 100).max(64 << 10)
        };
        // On an object store the bytes that go are the old segments in the bucket, which the
        // database's size does not show: a copy that removed something always replaces it.
        let smaller = dir_bytes(&tmp) + margin <= bytes_before;
        if !(smaller || remote && removed > 0) {
            std::fs::remove_dir_all(&tmp)?;
            let as_is = Copied {
                bytes_before,
                surveys_purged,
                kept,
                removed: 0,
                swap: false,
            };
            if removed == 0 {
                return Ok(as_is);
            }
            // What retirements left goes all the same, from the store itself: its keys are
            // removed in one batch, and the chunks they named stay in the pack as dead bytes
            // for a later compaction to leave behind.
            let mut batch = sled::Batch::default();
            let mut gone = 0u64;
            for k in self.db.iter().keys() {
                let k = k?;
                if !live(&k) {
                    batch.remove(k);
                    gone += 1;
                }
            }
            self.guard.check(&dir, 0)?;
            self.db.apply_batch(batch)?;
            lock(&self.catalog).forget();
            self.db.flush()?;
            return Ok(Copied {
                removed: gone,
                ..as_is
            });
        }
        self.db.flush()?;
        Ok(Copied {
            bytes_before,
            surveys_purged,
            kept,
            removed,
            swap: true,
        })
    }

    /// Replaces the store with its copy in `<dir>.compact` and opens that.
    fn swap(
        self,
        bytes_before: u64,
        surveys_purged: usize,
        removed: u64,
        kept: u64,
    ) -> Result<(Loaded, CompactReport), StoreError> {
        let dir = self.dir.clone();
        let tmp = sibling(&dir, ".compact")?;
        let old = sibling(&dir, ".old")?;
        let Store {
            db,
            pack,
            reader,
            layout,
            index,
            opts,
            replication,
            _lock: lock,
            _close_reader,
            ..
        } = self;
        // Terrains published from this store must not keep its database open.
        drop(_close_reader);
        // Nor its pack: on an object store, the pack holds the writer's lease, which the
        // store reopened below must take.
        drop((reader, pack, replication));
        // Closing sled ends its use of the directory; the lock beside it stays held, so no
        // other process can open the store while the directories move.
        drop(db);
        std::fs::rename(&dir, &old)?;
        sync_dir(&dir);
        std::fs::rename(&tmp, &dir)?;
        sync_dir(&dir);
        std::fs::remove_dir_all(&old)?;
        let opened = Store::open_locked(dir.clone(), lock, layout, index, opts)?;
        let bytes_after = dir_bytes(&dir);
        Ok((
            opened,
            CompactReport {
                bytes_before,
                bytes_after,
                surveys_purged,
                keys_removed: removed,
                keys_kept: kept,
                swapped: true,
            },
        ))
    }
}
