//! The commit journal on an object store, which read replicas follow.
//!
//! A writer whose chunks are on an object store publishes each database batch it applies as
//! a numbered log object, `<prefix>/log/<seq:020>.log`, written only if absent
//! (`If-None-Match: *`), and now and then a snapshot of the whole database,
//! `<prefix>/snapshots/<seq:020>.snap`: the state after commit `seq`. A snapshot is due once
//! `every` commits have passed since the last one *and* their logs add up to a
//! [`SNAPSHOT_SHARE`]th of its size: a snapshot costs the whole database, so one every fixed
//! number of commits made each commit's cost grow with the store (the last fifth of 10,000
//! surveys took 1.45× the first on a folder, 8.5 MB written every 64 commits of 7 kB logs);
//! tied to the logs' bytes, the snapshots cost each commit at most that many times its own
//! log, and a replica starting from the newest replays at most that share of it in logs. A replica starts from
//! the newest snapshot and applies the logs after it in order; the same commits give it the
//! same database, and order independence makes its terrain answer as the writer's does.
//!
//! The order of a commit on the writer is: its segment (see [`super::objects`]), then the
//! database batch, then the log. A log names only segments that exist, and a replica never
//! sees a commit the writer's database does not hold. The batch itself records the commit's
//! number and the keys it wrote (`meta/log_seq`, `meta/log_pending`); the log is made from
//! those keys' values as the database holds them once the commit is done. A writer that
//! crashed before its log went up publishes it at the next open, from the same keys; one that
//! could not reach the object store publishes it before its next commit, which waits for it.
//! Compaction rewrites the database without a batch to replay: it records a pending
//! *snapshot* instead, and its log tells replicas to start again from that snapshot.
//!
//! Snapshots older than the two newest are deleted, with the logs up to the older of the
//! two: a replica that fell further behind than that starts again from the newest snapshot.

use super::chunks::{seal, unseal};
use super::objects::ObjectPack;
use super::*;
use patchwork_core::sync::lock;
use std::sync::Mutex;
use std::time::Duration;

/// The folder of the logs and of the snapshots under the prefix.
const LOGS: &str = "log";
const SNAPSHOTS: &str = "snapshots";

/// A snapshot is due once the logs since the last add up to this fraction (1 / this) of its
/// size (and `every` commits have passed).
pub const SNAPSHOT_SHARE: u64 = 4;

/// The bytes of keys and values a replica writes to its database in one batch as it takes a
/// snapshot (less in the unit tests, whose snapshots are small, so that they take several).
const RESET_BATCH_BYTES: usize = if cfg!(test) { 64 << 10 } else { 4 << 20 };

/// Logs a replica reads ahead of the one it applies.
const READ_AHEAD: usize = 64;

/// The largest log or snapshot a replica decodes: a database, without its samples, of a
/// store far larger than one replica serves.
const LIMIT: usize = 8 << 30;

/// What a commit's log is made from, as the batch records it.
#[derive(Serialize, Deserialize)]
enum Pending {
    /// The keys the batch wrote or removed.
    Batch(Vec<Vec<u8>>),
    /// The database was rewritten whole (a compaction): replicas start again from the
    /// snapshot of this commit.
    Snapshot,
}

/// One published commit.
#[derive(Serialize, Deserialize)]
enum Entry {
    /// Each key with its value after the commit, `None` where the commit removed it.
    Batch(Vec<(Vec<u8>, Option<Vec<u8>>)>),
    Snapshot,
}

/// A snapshot: every key of the database after commit `seq` but the journal's own.
#[derive(Serialize, Deserialize)]
struct Snapshot {
    seq: u64,
    keys: Vec<(Vec<u8>, Vec<u8>)>,
}

fn log_name(seq: u64) -> String {
    format!("{LOGS}/{seq:020}.log")
}

fn snapshot_name(seq: u64) -> String {
    format!("{SNAPSHOTS}/{seq:020}.snap")
}

/// The numbers of the objects in `names` (`<seq:020>.<ext>`), in order.
fn numbers(names: &[(String, u64)], ext: &str) -> Vec<(u64, u64)> {
    let mut out: Vec<(u64, u64)> = names
        .iter()
        .filter_map(|(n, at)| Some((n.strip_suffix(ext)?.parse().ok()?, *at)))
        .collect();
    out.sort_unstable();
    out
}

fn seq_of(db: &sled::Db) -> Result<u64, StoreError> {
    match db.get(keys::LOG_SEQ)? {
        None => Ok(0),
        Some(v) => Ok(u64::from_le_bytes(v.as_ref().try_into().map_err(|_| {
            StoreError::from(Corruption::Length {
                key: "meta/log_seq",
                len: v.len(),
                expected: 8,
            })
        })?)),
    }
}

/// Whether a key is the journal's own bookkeeping, which each side keeps for itself.
fn own(k: &[u8]) -> bool {
    k == keys::LOG_SEQ || k == keys::LOG_PENDING || k == keys::FOLLOWS
}

fn io(e: std::io::Error) -> StoreError {
    StoreError::Io(e)
}

/// The writer's side.
pub(super) struct Journal {
    pack: Arc<ObjectPack>,
    /// At least this many commits between snapshots.
    every: u64,
    /// The newest commit, and whether its log is up.
    state: Mutex<(u64, bool)>,
    /// What the logs published since the last snapshot add up to.
    since: Mutex<Since>,
}

/// Commits and their logs' bytes since the last snapshot this writer wrote, and its size: 0
/// until it writes one (after an open, the first comes `every` commits on).
#[derive(Default)]
struct Since {
    commits: u64,
    log_bytes: u64,
    snapshot_bytes: u64,
}

impl Journal {
    /// The journal of the writer whose database is `db`: the newest commit's log published
    /// if a crash kept it back, and a first snapshot written if there is none.
    pub(super) fn open(
        pack: Arc<ObjectPack>,
        db: &sled::Db,
        every: u64,
    ) -> Result<Journal, StoreError> {
        let seq = seq_of(db)?;
        let up =
            db.get(keys::LOG_PENDING)?.is_none() || pack.get(&log_name(seq)).map_err(io)?.is_some();
        let j = Journal {
            pack,
            every: every.max(1),
            state: Mutex::new((seq, up)),
            since: Mutex::default(),
        };
        j.publish(db)?;
        let snapshots = j.pack.list_names(SNAPSHOTS).map_err(io)?;
        if numbers(&snapshots, ".snap").is_empty() {
            j.snapshot(db, seq)?;
        }
        Ok(j)
    }

    /// The newest commit.
    pub(super) fn seq(&self) -> u64 {
        lock(&self.state).0
    }

    /// Adds the journal's keys to a batch about to be applied: the commit's number and what
    /// its log is made from. The previous commit's log must be up first (see
    /// [`Journal::publish`]), or its keys would be lost.
    pub(super) fn stage(
        &self,
        batch: &mut sled::Batch,
        touched: &[sled::IVec],
    ) -> Result<u64, StoreError> {
        self.pack.check_lease().map_err(io)?;
        let (seq, up) = *lock(&self.state);
        if !up {
            return Err(StoreError::Unpublished {
                seq,
                url: self.pack.url().to_string(),
            });
        }
        let keys: Vec<Vec<u8>> = touched.iter().map(|k| k.to_vec()).collect();
        batch.insert(keys::LOG_SEQ, &(seq + 1).to_le_bytes()[..]);
        batch.insert(keys::LOG_PENDING, encode(&Pending::Batch(keys))?);
        Ok(seq + 1)
    }

    /// Notes that the batch of commit `seq` was applied: its log is due.
    pub(super) fn applied(&self, seq: u64) {
        *lock(&self.state) = (seq, false);
    }

    /// Publishes the newest commit's log if it is not up yet, and the snapshot it is due.
    /// Fails (UNAVAILABLE to a caller) while the object store cannot be reached; the commit
    /// stays in the database, and is published by the next call.
    pub(super) fn publish(&self, db: &sled::Db) -> Result<(), StoreError> {
        let (seq, up) = *lock(&self.state);
        if up {
            return Ok(());
        }
        let pending: Pending = match db.get(keys::LOG_PENDING)? {
            Some(v) => decode(&v, "meta/log_pending")?,
            None => return Err(Corruption::Missing("meta/log_pending".into()).into()),
        };
        let whole = matches!(pending, Pending::Snapshot);
        let entry = match pending {
            Pending::Batch(touched) => {
                let mut out = Vec::with_capacity(touched.len());
                for k in touched {
                    let v = db.get(&k)?.map(|v| v.to_vec());
                    out.push((k, v));
                }
                Entry::Batch(out)
            }
            Pending::Snapshot => {
                self.snapshot(db, seq)?;
                Entry::Snapshot
            }
        };
        // Written at most once: a writer that crashed after its PUT went through finds it
        // there, made from the same keys.
        let log = seal(&encode(&(seq, entry))?);
        let log_bytes = log.len() as u64;
        self.pack.put_new(&log_name(seq), log).map_err(io)?;
        lock(&self.state).1 = true;
        let due = {
            let mut since = lock(&self.since);
            since.commits += 1;
            since.log_bytes += log_bytes;
            since.commits >= self.every
                && since.log_bytes.saturating_mul(SNAPSHOT_SHARE) >= since.snapshot_bytes
        };
        if due && !whole {
            if let Err(e) = self.snapshot(db, seq) {
                // Replicas apply more logs until the next one; nothing is lost.
                tracing::warn!(error = %e, "could not write a snapshot for replicas");
            }
        }
        Ok(())
    }

    /// Writes the snapshot of commit `seq` (the database as it is now), and deletes what the
    /// two newest snapshots make unneeded.
    fn snapshot(&self, db: &sled::Db, seq: u64) -> Result<(), StoreError> {
        let mut keys = Vec::new();
        for kv in db.iter() {
            let (k, v) = kv?;
            if !own(&k) {
                keys.push((k.to_vec(), v.to_vec()));
            }
        }
        let bytes = seal(&encode(&Snapshot { seq, keys })?);
        let snapshot_bytes = bytes.len() as u64;
        self.pack
            .put_whole(&snapshot_name(seq), bytes)
            .map_err(io)?;
        *lock(&self.since) = Since {
            snapshot_bytes,
            ..Since::default()
        };
        let snapshots = numbers(&self.pack.list_names(SNAPSHOTS).map_err(io)?, ".snap");
        if snapshots.len() > 2 {
            let keep_from = snapshots[snapshots.len() - 2].0;
            for &(s, _) in snapshots.iter().filter(|(s, _)| *s < keep_from) {
                self.pack.delete_named(&snapshot_name(s)).map_err(io)?;
            }
            let logs = numbers(&self.pack.list_names(LOGS).map_err(io)?, ".log");
            for &(s, _) in logs.iter().filter(|(s, _)| *s <= keep_from) {
                self.pack.delete_named(&log_name(s)).map_err(io)?;
            }
        }
        Ok(())
    }
}

/// What is wrong with a recorded `meta/log_pending`, if anything.
pub(super) fn pending_problem(v: &[u8]) -> Option<String> {
    decode::<Pending>(v, "meta/log_pending")
        .err()
        .map(|e| e.to_string())
}

/// Marks, in a batch that rewrites the database whole, that the next commit is a snapshot.
pub(super) fn stage_rewrite(batch: &mut sled::Batch, seq: u64) -> Result<(), StoreError> {
    batch.insert(keys::LOG_SEQ, &(seq + 1).to_le_bytes()[..]);
    batch.insert(keys::LOG_PENDING, encode(&Pending::Snapshot)?);
    Ok(())
}

/// Where a replica stands.
#[derive(Clone, Debug, Default)]
pub struct Following {
    /// The place it follows.
    pub url: String,
    /// The newest commit it applied.
    pub applied: u64,
    /// The newest commit it has seen published.
    pub published: u64,
    /// How long ago the oldest commit it has not applied yet was published; zero when it has
    /// applied all it saw.
    pub lag: Duration,
    /// When it last asked the object store, as Unix milliseconds.
    pub polled_ms: u64,
}

/// The replica's side: the database it keeps is the writer's, as of the newest commit it
/// applied.
pub(super) struct Follower {
    pack: Arc<ObjectPack>,
    state: Mutex<Following>,
}

impl Follower {
    /// Starts a replica's database `db` from the newest snapshot at `pack` and applies the
    /// logs after it. `db` must be empty or a replica's of the same place: a replica never
    /// writes over a database that is a store's own.
    pub(super) fn start(
        pack: Arc<ObjectPack>,
        db: &sled::Db,
        dir: &Path,
    ) -> Result<Follower, StoreError> {
        match db.get(keys::FOLLOWS)? {
            Some(url) if url.as_ref() == pack.url().as_bytes() => {}
            Some(url) => {
                return Err(StoreError::NotAReplica {
                    dir: dir.to_path_buf(),
                    holds: format!("is a replica of {}", String::from_utf8_lossy(&url)),
                    url: pack.url().to_string(),
                })
            }
            None if db.iter().next().is_some() => {
                return Err(StoreError::NotAReplica {
                    dir: dir.to_path_buf(),
                    holds: "holds a store of its own".into(),
                    url: pack.url().to_string(),
                })
            }
            None => {}
        }
        let f = Follower {
            state: Mutex::new(Following {
                url: pack.url().to_string(),
                ..Following::default()
            }),
            pack,
        };
        let Some(newest) = f.newest_snapshot()? else {
            return Err(StoreError::Io(std::io::Error::new(
                std::io::ErrorKind::NotFound,
                format!(
                    "{} has no snapshot yet: its writer writes one when it first opens",
                    f.pack.url()
                ),
            )));
        };
        let at = seq_of(db)?;
        if db.get(keys::FOLLOWS)?.is_none() || at < newest {
            f.reset(db, newest)?;
        }
        lock(&f.state).applied = seq_of(db)?;
        f.catch_up(db)?;
        Ok(f)
    }

    pub(super) fn following(&self) -> Following {
        lock(&self.state).clone()
    }

    fn newest_snapshot(&self) -> Result<Option<u64>, StoreError> {
        let names = self.pack.list_names(SNAPSHOTS).map_err(io)?;
        Ok(numbers(&names, ".snap").last().map(|(s, _)| *s))
    }

    /// Makes `db` the snapshot of commit `seq`.
    ///
    /// In batches of about [`RESET_BATCH_BYTES`]: one batch of the whole snapshot took sled
    /// 270 MB at 10,000 surveys (an 8.5 MB snapshot), ten times the keys it wrote, and the
    /// replica's start peaked at 354 MB. The pieces need no atomicity of their own: the first
    /// names the place followed, so a start that finds a piece applied knows the database for
    /// a replica's; the commit the database stands at goes in the last, with the removal of
    /// the keys the snapshot no longer has, so that one interrupted is a database behind the
    /// newest snapshot, which the next start resets again.
    fn reset(&self, db: &sled::Db, seq: u64) -> Result<(), StoreError> {
        let name = snapshot_name(seq);
        let bytes = self.pack.get(&name).map_err(io)?.ok_or_else(|| {
            StoreError::Io(std::io::Error::new(
                std::io::ErrorKind::NotFound,
                format!("{}/{name} went while it was being read", self.pack.url()),
            ))
        })?;
        let what = format!("{}/{name}", self.pack.url());
        let raw = unseal(&bytes, LIMIT).map_err(|why| Corruption::Unreadable {
            what: what.clone(),
            why,
        })?;
        drop(bytes);
        let snap: Snapshot = decode(&raw, &what)?;
        drop(raw);
        let fresh: std::collections::HashSet<&[u8]> =
            snap.keys.iter().map(|(k, _)| k.as_slice()).collect();
        let mut stale = Vec::new();
        for kv in db.iter() {
            let (k, _) = kv?;
            if !fresh.contains(k.as_ref()) && !own(&k) {
                stale.push(k);
            }
        }
        drop(fresh);
        let mut batch = sled::Batch::default();
        batch.insert(keys::FOLLOWS, self.pack.url().as_bytes());
        let mut held = 0;
        for (k, v) in &snap.keys {
            batch.insert(k.as_slice(), v.as_slice());
            held += k.len() + v.len();
            if held >= RESET_BATCH_BYTES {
                db.apply_batch(std::mem::take(&mut batch))?;
                held = 0;
            }
        }
        for k in stale {
            batch.remove(k);
        }
        batch.insert(keys::LOG_SEQ, &snap.seq.to_le_bytes()[..]);
        batch.remove(keys::LOG_PENDING);
        db.apply_batch(batch)?;
        db.flush()?;
        lock(&self.state).applied = snap.seq;
        Ok(())
    }

    /// Applies, in order, the commits published since the last call. Returns how many.
    /// Stops at a commit not yet published: the logs are numbered without gaps, so one that
    /// is missing while later ones are there was deleted behind a newer snapshot, which the
    /// replica then starts again from.
    pub(super) fn catch_up(&self, db: &sled::Db) -> Result<u64, StoreError> {
        let polled_ms = now_ms();
        let logs = numbers(&self.pack.list_names(LOGS).map_err(io)?, ".log");
        let start = lock(&self.state).applied;
        let mut applied = start;
        let published = logs.last().map_or(applied, |(s, _)| (*s).max(applied));
        // The segments the new commits name were written before their logs.
        if published > applied {
            self.pack.refresh().map_err(io)?;
        }
        let due: Vec<u64> = logs
            .iter()
            .map(|(s, _)| *s)
            .filter(|s| *s > start)
            .collect();
        // Read ahead, many at once; applied in order.
        let mut fetched: HashMap<u64, std::io::Result<Option<Vec<u8>>>> = HashMap::new();
        for (i, &seq) in due.iter().enumerate() {
            if seq != applied + 1 {
                match self.newest_snapshot()? {
                    Some(s) if s > applied => {
                        self.reset(db, s)?;
                        applied = s;
                        if seq <= applied {
                            continue;
                        }
                        if seq != applied + 1 {
                            break;
                        }
                    }
                    _ => break,
                }
            }
            let name = log_name(seq);
            let what = format!("{}/{name}", self.pack.url());
            if !fetched.contains_key(&seq) {
                let ahead: Vec<u64> = due[i..].iter().take(READ_AHEAD).copied().collect();
                let names: Vec<String> = ahead.iter().map(|&s| log_name(s)).collect();
                fetched = ahead.into_iter().zip(self.pack.get_many(&names)).collect();
            }
            let Some(bytes) = fetched.remove(&seq).expect("read ahead").map_err(io)? else {
                break;
            };
            let raw = unseal(&bytes, LIMIT).map_err(|why| Corruption::Unreadable {
                what: what.clone(),
                why,
            })?;
            let (n, entry): (u64, Entry) = decode(&raw, &what)?;
            if n != seq {
                return Err(Corruption::Commit { what, found: n }.into());
            }
            match entry {
                Entry::Batch(writes) => {
                    let mut batch = sled::Batch::default();
                    for (k, v) in writes {
                        match v {
                            Some(v) => batch.insert(k, v),
                            None => batch.remove(k),
                        }
                    }
                    batch.insert(keys::LOG_SEQ, &seq.to_le_bytes()[..]);
                    // Made durable once, after the last (each batch is atomic, and carries
                    // the commit it brings the database to: a crash before the flush only
                    // leaves logs to apply again).
                    db.apply_batch(batch)?;
                }
                Entry::Snapshot => self.reset(db, seq)?,
            }
            applied = seq;
            lock(&self.state).applied = seq;
        }
        if applied > start {
            db.flush()?;
        }
        let lag = logs
            .iter()
            .find(|(s, _)| *s > applied)
            .map_or(Duration::ZERO, |(_, at)| {
                Duration::from_millis(polled_ms.saturating_sub(*at))
            });
        let mut st = lock(&self.state);
        st.published = published;
        st.lag = lag;
        st.polled_ms = polled_ms;
        Ok(applied - start)
    }

    /// The error that refuses a write, naming the writer that holds the lease now.
    pub(super) fn refusal(&self) -> StoreError {
        StoreError::Replica {
            url: self.pack.url().to_string(),
            writer: self.pack.writer().map(|h| h.holder),
        }
    }

    pub(super) fn pack(&self) -> Arc<ObjectPack> {
        self.pack.clone()
    }
}

fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

impl Store {
    /// Where this replica stands; `None` unless the store is one.
    pub fn following(&self) -> Option<Following> {
        match &self.replication {
            Replication::Follower(f) => Some(f.following()),
            _ => None,
        }
    }

    /// The newest commit of the journal replicas follow; `None` on the local pack.
    pub fn commit_seq(&self) -> Option<u64> {
        match &self.replication {
            Replication::Writer(j) => Some(j.seq()),
            Replication::Follower(f) => Some(f.following().applied),
            Replication::None => None,
        }
    }

    /// On a replica, applies the commits published since the last call and, if there were
    /// any, reads back what the index is restored from. `None` when nothing changed.
    pub fn catch_up(&mut self) -> Result<Option<Contents>, StoreError> {
        let Replication::Follower(f) = &self.replication else {
            return Ok(None);
        };
        if f.catch_up(&self.db)? == 0 {
            return Ok(None);
        }
        // The writer's keys came as its log said, not through this store's writes.
        lock(&self.catalog).forget();
        *write(&self.crs) = (
            self.db
                .get(keys::CRS)?
                .map(|v| decode_crs(&v, "meta/crs", Crs::parse))
                .transpose()?,
            self.db
                .get(keys::VERTICAL_CRS)?
                .map(|v| decode_crs(&v, "meta/vertical_crs", VerticalCrs::parse))
                .transpose()?,
        );
        self.load().map(Some)
    }

    /// Whether this store is a replica, which writes nothing.
    pub fn is_replica(&self) -> bool {
        matches!(self.replication, Replication::Follower(_))
    }

    /// The error a replica refuses writes with; `None` on a writer.
    pub fn refusal(&self) -> Option<StoreError> {
        match &self.replication {
            Replication::Follower(f) => Some(f.refusal()),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::objects::tests::objects as under;
    use object_store::memory::InMemory;

    /// Snapshots come as the logs since the last one add up to a quarter of its size, not
    /// every `every` commits: on a database of 400 kB, 200 commits of 1 kB each write three,
    /// where a snapshot every 8 commits wrote 25 (10 MB for 200 kB of logs). A replica that
    /// starts from the newest then finds the database as the writer has it.
    #[test]
    fn snapshots_come_in_proportion_to_the_logs_not_to_the_commits() {
        let tmp = tempfile::tempdir().unwrap();
        let db = sled::Config::new()
            .path(tmp.path().join("db"))
            .open()
            .unwrap();
        // Bytes that do not compress, as a commit's mostly do not.
        let noise = |seed: u32| -> Vec<u8> {
            (0..1000u32)
                .map(|i| (i ^ seed.wrapping_mul(40_503)).wrapping_mul(2_654_435_761) >> 24)
                .map(|b| b as u8)
                .collect()
        };
        for k in 0..400u32 {
            db.insert(format!("s/{k:08}"), noise(k + 1000)).unwrap();
        }
        let mem: Arc<dyn object_store::ObjectStore> = Arc::new(InMemory::new());
        let objects = || under(mem.clone());
        let pack = Arc::new(ObjectPack::open(objects(), 0, false).unwrap());
        let j = Journal::open(pack.clone(), &db, 8).unwrap();
        let mut written = 0;
        let mut last = None;
        for c in 0..200u32 {
            let mut batch = sled::Batch::default();
            let k = sled::IVec::from(format!("s/{:08}", c % 400).as_bytes());
            batch.insert(k.clone(), noise(c));
            let seq = j.stage(&mut batch, &[k]).unwrap();
            db.apply_batch(batch).unwrap();
            j.applied(seq);
            j.publish(&db).unwrap();
            if lock(&j.since).commits == 0 {
                written += 1;
                assert!(
                    c + 1 >= last.map_or(8, |l| l + 8),
                    "commit {c}: a snapshot {last:?} too soon"
                );
                last = Some(c + 1);
            }
        }
        assert!((1..=3).contains(&written), "{written} snapshots");
        println!("{written} snapshots after 200 commits");
        // A replica from the newest snapshot and the logs after it.
        let r = tempfile::tempdir().unwrap();
        let rdb = sled::Config::new()
            .path(r.path().join("db"))
            .open()
            .unwrap();
        let follower = ObjectPack::follow(objects()).unwrap();
        Follower::start(Arc::new(follower), &rdb, r.path()).unwrap();
        let same = |rdb: &sled::Db| {
            for kv in db.iter() {
                let (k, v) = kv.unwrap();
                if !own(&k) {
                    assert_eq!(rdb.get(&k).unwrap().as_ref(), Some(&v), "{k:?}");
                }
            }
            // The writer's keys, the commit and the place followed.
            let theirs = db
                .iter()
                .keys()
                .filter(|k| !own(k.as_ref().unwrap()))
                .count();
            assert_eq!(rdb.len(), theirs + 2, "the replica holds other keys");
            assert_eq!(seq_of(rdb).unwrap(), 200);
        };
        same(&rdb);
        // A replica stopped while it took the snapshot in pieces: the place it follows named,
        // some of the snapshot's keys written and one it no longer has, the commit it stood
        // at before. Its next start takes the snapshot again.
        let r = tempfile::tempdir().unwrap();
        let rdb = sled::Config::new()
            .path(r.path().join("db"))
            .open()
            .unwrap();
        rdb.insert(keys::FOLLOWS, "memory://store1").unwrap();
        rdb.insert(keys::LOG_SEQ, &3u64.to_le_bytes()[..]).unwrap();
        for kv in db
            .iter()
            .filter(|kv| !own(&kv.as_ref().unwrap().0))
            .take(50)
        {
            let (k, v) = kv.unwrap();
            rdb.insert(k, v).unwrap();
        }
        rdb.insert("s/gone", "a survey retired since").unwrap();
        let follower = ObjectPack::follow(objects()).unwrap();
        Follower::start(Arc::new(follower), &rdb, r.path()).unwrap();
        assert_eq!(rdb.get("s/gone").unwrap(), None);
        same(&rdb);
    }
}
