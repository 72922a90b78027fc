//! The chunk pack on an object store (S3 and the servers that speak its protocol, or a folder
//! through the same interface), in place of the local pack file.
//!
//! The pack keeps its one address space: a [`Loc`] is still an offset and a length, and
//! `meta/pack_len` still the committed end. Each commit's chunks become one immutable
//! *segment* object named by the offset it starts at (`<prefix>/segments/<start:020>.seg`),
//! so a location names its segment: the one whose range holds it. Keeping the addresses is
//! what leaves the commit protocol, the records and `verify` as they are, and lets a store
//! move between backends without rewriting a location.
//!
//! - **Commit.** A commit PUTs its segment (multipart above [`MULTIPART_BYTES`]) and only then
//!   applies the database batch that names it. A crash between the two leaves a segment at or
//!   past the committed end, which no location names: the next open deletes it.
//! - **Reads** are ranged GETs of one chunk each, through the store's decoded-chunk cache.
//!   Checksums are checked as for the local pack, at each read and by `verify`; an open does
//!   not read every chunk back as it does from a local disk (that would fetch the whole store),
//!   it checks that every location lies in a segment that exists.
//! - **Compaction** writes the live chunks into new segments past the end, and the database
//!   that names them records where the old address space ended (`meta/pack_base`). The
//!   segments below it are deleted by an open once the grace period has passed, so that a
//!   reader still holding the old database finds its bytes until then.
//!
//! The object store's client is async; the store is called from blocking threads (and from
//! tests' async ones), so each call is run on a small runtime of the pack's own and waited for
//! on a channel, which works from any thread.

use super::lease::{self, Lease, LeaseError};
use super::pack::{ChunkStore, Loc};
use futures::TryStreamExt;
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt, PutMode, PutPayload, WriteMultipart};
use patchwork_core::sync::{lock, read, write};
use std::collections::BTreeMap;
use std::future::Future;
use std::io;
use std::sync::{Arc, Mutex, RwLock};
use std::time::Duration;

/// Requests [`ObjectPack::get_many`] keeps in flight: a GET to S3 takes tens of
/// milliseconds, and a replica may start with hundreds of logs to read.
pub const GETS_AT_ONCE: usize = 16;

/// Segments larger than this go up in parts; S3 takes at most 5 GiB in one PUT, and a part
/// that fails is sent again alone.
pub const MULTIPART_BYTES: usize = 64 << 20;

/// The size of each part of a multipart upload.
const PART_BYTES: usize = 16 << 20;

/// How long a commit waits for a lease that ran out to be renewed before it is refused.
const RENEW_WAIT: Duration = Duration::from_secs(3);

/// The folder of the prefix that holds the segments.
const SEGMENTS: &str = "segments";

/// An object store and where in it one Patchwork store keeps its segments.
#[derive(Clone)]
pub struct Objects {
    /// The object store's client.
    pub store: Arc<dyn ObjectStore>,
    /// The path in it under which this store's objects lie.
    pub prefix: ObjectPath,
    /// The place as a URL (`s3://bucket/prefix`), for messages and for the database's record
    /// of where its chunks are.
    pub url: String,
    /// How long a segment that compaction let go of is kept before it is deleted.
    pub grace: Duration,
    /// How long the writer's lease lasts unless renewed (see [`super::lease`]).
    pub lease: Duration,
}

impl std::fmt::Debug for Objects {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Objects").field("url", &self.url).finish()
    }
}

/// An object store that could not be reached or answered with an error other than "not
/// found": the request may succeed later, and the bytes are not known to be lost.
#[derive(Debug)]
pub struct Unreachable(pub String);

impl std::fmt::Display for Unreachable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Unreachable {}

/// Whether an I/O error is an object store that could not be reached (see [`Unreachable`]).
pub fn is_unreachable(e: &io::Error) -> bool {
    e.get_ref().is_some_and(|r| r.is::<Unreachable>())
}

fn io_error(what: &str, e: object_store::Error) -> io::Error {
    match e {
        object_store::Error::NotFound { .. } => {
            io::Error::new(io::ErrorKind::NotFound, format!("{what}: {e}"))
        }
        e => io::Error::other(Unreachable(format!("{what}: {e}"))),
    }
}

/// The chunk pack as segments of an object store.
pub struct ObjectPack {
    objects: Objects,
    /// The writer's lease: taken before anything is written or deleted, and checked before
    /// every append.
    lease: Option<Lease>,
    runtime: Option<tokio::runtime::Runtime>,
    /// The committed segments: start → length.
    segments: RwLock<BTreeMap<u64, u64>>,
    /// Where the next segment starts. Appends take it in turn.
    end: Mutex<u64>,
    /// A replica's view of another writer's pack: it reads, lists again as the writer's
    /// commits arrive, and never writes or deletes.
    follower: bool,
}

impl std::fmt::Debug for ObjectPack {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ObjectPack")
            .field("url", &self.objects.url)
            .field("segments", &read(&self.segments).len())
            .finish()
    }
}

impl Drop for ObjectPack {
    fn drop(&mut self) {
        // The lease is given back, so that the next writer need not wait it out.
        // Only while it is surely ours: one that ran out may have been taken over since.
        if let Some(lease) = self.lease.take().filter(|l| l.check().is_ok()) {
            let store = self.objects.store.clone();
            let path = self.lease_path();
            drop(lease);
            let _ = self.run(async move {
                tokio::time::timeout(Duration::from_secs(2), store.delete(&path)).await
            });
        }
        // Not `drop`, which waits for the runtime's threads and may not be called from an
        // async context: nothing of it is in flight once the pack goes.
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}

impl ObjectPack {
    /// Opens the pack at `objects`, committed up to `committed`. A segment at or past that was
    /// written by a commit that never reached the database, and is deleted.
    ///
    /// `claimed` says whether the database already names this place. A store that does not
    /// yet must find it empty: segments there are another store's, whose commits this one's
    /// open would otherwise take for its own crashed ones and delete.
    pub fn open(objects: Objects, committed: u64, claimed: bool) -> io::Result<ObjectPack> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("patchwork-objects")
            .enable_all()
            .build()?;
        let mut pack = ObjectPack {
            objects,
            lease: None,
            runtime: Some(runtime),
            segments: RwLock::new(BTreeMap::new()),
            end: Mutex::new(committed),
            follower: false,
        };
        // Before the lease, so that a place that is another store's is named as such, rather
        // than as held by its writer.
        if !claimed {
            if let Some((start, _)) = pack.list()?.first() {
                return Err(io::Error::new(
                    io::ErrorKind::AlreadyExists,
                    format!(
                        "{} already holds segments ({}, …) that this store's database does not \
                         name: they are another store's; give each store its own prefix",
                        pack.objects.url,
                        pack.name(*start)
                    ),
                ));
            }
        }
        let (store, path, ttl) = (
            pack.objects.store.clone(),
            pack.lease_path(),
            pack.objects.lease,
        );
        let taken = pack.run(lease::take(store, path, lease::holder(), ttl));
        pack.lease = Some(taken.map_err(|e| match e {
            LeaseError::Held(_) => io::Error::new(
                io::ErrorKind::WouldBlock,
                format!("{}: {e}", pack.objects.url),
            ),
            e => io::Error::other(Unreachable(format!("{}: {e}", pack.objects.url))),
        })?);
        // Listed under the lease: what is deleted below must be what no writer can be adding
        // to.
        let listed = pack.list()?;
        let mut segments = BTreeMap::new();
        let mut end = committed;
        for (start, len) in listed {
            if start >= committed {
                pack.delete(start)?;
            } else {
                segments.insert(start, len);
                // A segment across the committed end is no commit's, but appends must still
                // not write over it.
                end = end.max(start + len);
            }
        }
        *write(&pack.segments) = segments;
        *lock(&pack.end) = end;
        Ok(pack)
    }

    /// The pack at `objects` as a replica sees it: every segment listed, no lease taken,
    /// nothing written or deleted. A segment past what the replica's database names yet is
    /// the writer's commit on its way (see [`ObjectPack::refresh`]).
    pub fn follow(objects: Objects) -> io::Result<ObjectPack> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("patchwork-objects")
            .enable_all()
            .build()?;
        let pack = ObjectPack {
            objects,
            lease: None,
            runtime: Some(runtime),
            segments: RwLock::new(BTreeMap::new()),
            end: Mutex::new(0),
            follower: true,
        };
        pack.refresh()?;
        Ok(pack)
    }

    /// Lists the segments again: a replica does before it applies the writer's commits, whose
    /// segments were written before the commits were published.
    pub fn refresh(&self) -> io::Result<()> {
        let listed = self.list()?;
        let end = listed.last().map_or(0, |(s, l)| s + l);
        *write(&self.segments) = listed.into_iter().collect();
        *lock(&self.end) = end;
        Ok(())
    }

    /// The place, as a URL.
    pub fn url(&self) -> &str {
        &self.objects.url
    }

    /// The object `name` under the prefix (`log/…`, `snapshots/…`).
    fn object(&self, name: &str) -> ObjectPath {
        name.split('/')
            .fold(self.objects.prefix.clone(), |p, part| p.join(part))
    }

    /// Writes `name` only if it is absent (`If-None-Match: *`). Returns whether this call
    /// made it; `false` means it was there already.
    pub fn put_new(&self, name: &str, bytes: Vec<u8>) -> io::Result<bool> {
        let store = self.objects.store.clone();
        let path = self.object(name);
        let put = self.run(async move {
            store
                .put_opts(&path, PutPayload::from(bytes), PutMode::Create.into())
                .await
        });
        match put {
            Ok(_) => Ok(true),
            Err(object_store::Error::AlreadyExists { .. }) => Ok(false),
            Err(e) => Err(io_error(&format!("writing {}/{name}", self.objects.url), e)),
        }
    }

    /// Writes `name` whole, in parts when large; what was there is replaced.
    pub fn put_whole(&self, name: &str, bytes: Vec<u8>) -> io::Result<()> {
        let path = self.object(name);
        self.put_at(path, bytes)
            .map_err(|e| io_error(&format!("writing {}/{name}", self.objects.url), e))
    }

    /// The object `name`, or `None` if it is absent.
    pub fn get(&self, name: &str) -> io::Result<Option<Vec<u8>>> {
        let store = self.objects.store.clone();
        let path = self.object(name);
        let got = self.run(async move {
            match store.get(&path).await {
                Ok(r) => r.bytes().await.map(Some),
                Err(object_store::Error::NotFound { .. }) => Ok(None),
                Err(e) => Err(e),
            }
        });
        got.map(|b| b.map(|b| b.to_vec()))
            .map_err(|e| io_error(&format!("reading {}/{name}", self.objects.url), e))
    }

    /// [`ObjectPack::get`] of each of `names`, up to [`GETS_AT_ONCE`] requests in flight:
    /// a replica starting from a snapshot reads the logs after it, each one object.
    pub fn get_many(&self, names: &[String]) -> Vec<io::Result<Option<Vec<u8>>>> {
        use futures::StreamExt;
        let store = self.objects.store.clone();
        let paths: Vec<ObjectPath> = names.iter().map(|n| self.object(n)).collect();
        let got: Vec<object_store::Result<Option<bytes::Bytes>>> = self.run(async move {
            futures::stream::iter(paths)
                .map(|path| {
                    let store = store.clone();
                    async move {
                        match store.get(&path).await {
                            Ok(r) => r.bytes().await.map(Some),
                            Err(object_store::Error::NotFound { .. }) => Ok(None),
                            Err(e) => Err(e),
                        }
                    }
                })
                .buffered(GETS_AT_ONCE)
                .collect()
                .await
        });
        got.into_iter()
            .zip(names)
            .map(|(g, name)| {
                g.map(|b| b.map(|b| b.to_vec()))
                    .map_err(|e| io_error(&format!("reading {}/{name}", self.objects.url), e))
            })
            .collect()
    }

    /// The objects of the folder `dir` under the prefix: (file name, when last written, as
    /// Unix milliseconds), in name order.
    pub fn list_names(&self, dir: &str) -> io::Result<Vec<(String, u64)>> {
        let store = self.objects.store.clone();
        let path = self.object(dir);
        let listed = self
            .run(async move { store.list(Some(&path)).try_collect::<Vec<_>>().await })
            .map_err(|e| io_error(&format!("listing {}/{dir}", self.objects.url), e))?;
        let mut out: Vec<(String, u64)> = listed
            .iter()
            .filter_map(|m| {
                let name = m.location.filename()?.to_string();
                Some((name, m.last_modified.timestamp_millis().max(0) as u64))
            })
            .collect();
        out.sort();
        Ok(out)
    }

    /// Deletes the object `name`; one already gone is no error.
    pub fn delete_named(&self, name: &str) -> io::Result<()> {
        let store = self.objects.store.clone();
        let path = self.object(name);
        match self.run(async move { store.delete(&path).await }) {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(io_error(
                &format!("deleting {}/{name}", self.objects.url),
                e,
            )),
        }
    }

    /// Whether this writer may commit: its lease is still its own and has not run out. A
    /// commit that writes no segment (a retirement) is held to it as much as one that does.
    /// One that ran out while the object store was away is renewed first, waiting a little
    /// for it: writes resume as soon as the store is back.
    pub fn check_lease(&self) -> io::Result<()> {
        let Some(lease) = &self.lease else {
            return Ok(());
        };
        if lease.check().is_err() && !lease.lost() {
            lease.nudge();
            let t0 = std::time::Instant::now();
            while lease.check().is_err() && !lease.lost() && t0.elapsed() < RENEW_WAIT {
                std::thread::sleep(Duration::from_millis(20));
            }
        }
        lease
            .check()
            .map_err(|why| io::Error::other(Unreachable(format!("{}: {why}", self.objects.url))))
    }

    /// Who holds the writer's lease now, if anyone: for a replica's messages.
    pub fn writer(&self) -> Option<lease::Held> {
        let (store, path) = (self.objects.store.clone(), self.lease_path());
        self.run(lease::holder_of(store, path))
    }

    /// The segments' objects, as (start, length), in order.
    fn list(&self) -> io::Result<Vec<(u64, u64)>> {
        let store = self.objects.store.clone();
        let dir = self.objects.prefix.clone().join(SEGMENTS);
        let listed = self
            .run(async move { store.list(Some(&dir)).try_collect::<Vec<_>>().await })
            .map_err(|e| io_error(&format!("listing {}", self.objects.url), e))?;
        let mut out: Vec<(u64, u64)> = listed
            .iter()
            .filter_map(|m| {
                let start = m.location.filename()?.strip_suffix(".seg")?.parse().ok()?;
                Some((start, m.size))
            })
            .collect();
        out.sort_unstable();
        Ok(out)
    }

    fn lease_path(&self) -> ObjectPath {
        self.objects.prefix.clone().join("lease")
    }

    /// The object of the segment that starts at `start`.
    fn path(&self, start: u64) -> ObjectPath {
        self.objects
            .prefix
            .clone()
            .join(SEGMENTS)
            .join(format!("{start:020}.seg"))
    }

    /// The segment's name, for messages.
    pub fn name(&self, start: u64) -> String {
        format!("{}/{SEGMENTS}/{start:020}.seg", self.objects.url)
    }

    fn delete(&self, start: u64) -> io::Result<()> {
        self.delete_named(&format!("{SEGMENTS}/{start:020}.seg"))
    }

    /// Deletes the segments that end at or before `base`: those compaction let go of. Returns
    /// how many went.
    pub fn collect_below(&self, base: u64) -> io::Result<usize> {
        let gone: Vec<u64> = read(&self.segments)
            .iter()
            .filter(|(s, l)| *s + *l <= base)
            .map(|(s, _)| *s)
            .collect();
        for &s in &gone {
            self.delete(s)?;
            write(&self.segments).remove(&s);
        }
        Ok(gone.len())
    }

    /// The segment that holds `loc` whole, as (start, length).
    fn segment_of(&self, loc: Loc) -> Option<(u64, u64)> {
        let segments = read(&self.segments);
        let (&start, &len) = segments.range(..=loc.offset).next_back()?;
        (loc.end() <= start + len).then_some((start, len))
    }

    /// Runs `f` on the pack's runtime and waits for it.
    fn run<T: Send + 'static>(&self, f: impl Future<Output = T> + Send + 'static) -> T {
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        self.runtime
            .as_ref()
            .expect("the runtime lives as long as the pack")
            .spawn(async move {
                let _ = tx.send(f.await);
            });
        rx.recv()
            .expect("the pack's runtime runs every call it is given")
    }

    /// Writes one segment.
    fn put(&self, start: u64, bytes: Vec<u8>) -> Result<(), object_store::Error> {
        self.put_at(self.path(start), bytes)
    }

    /// Writes one object whole: in one PUT, or in parts above [`MULTIPART_BYTES`].
    fn put_at(&self, path: ObjectPath, bytes: Vec<u8>) -> Result<(), object_store::Error> {
        let store = self.objects.store.clone();
        self.run(async move {
            if bytes.len() <= MULTIPART_BYTES {
                store.put(&path, PutPayload::from(bytes)).await.map(|_| ())
            } else {
                let upload = store.put_multipart(&path).await?;
                let mut parts = WriteMultipart::new_with_chunk_size(upload, PART_BYTES);
                parts.write(&bytes);
                parts.finish().await.map(|_| ())
            }
        })
    }
}

impl ChunkStore for ObjectPack {
    fn read(&self, loc: Loc) -> io::Result<Vec<u8>> {
        let Some((start, _)) = self.segment_of(loc) else {
            return Err(io::Error::new(
                io::ErrorKind::NotFound,
                format!(
                    "no segment of {} holds bytes {}..{}",
                    self.objects.url,
                    loc.offset,
                    loc.end()
                ),
            ));
        };
        let store = self.objects.store.clone();
        let path = self.path(start);
        let range = (loc.offset - start)..(loc.end() - start);
        let bytes = self
            .run(async move { store.get_range(&path, range).await })
            .map_err(|e| io_error(&format!("reading {}", self.name(start)), e))?;
        if bytes.len() != loc.len as usize {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                format!(
                    "{} gave {} bytes at {}, not {}",
                    self.name(start),
                    bytes.len(),
                    loc.offset - start,
                    loc.len
                ),
            ));
        }
        Ok(bytes.to_vec())
    }

    fn read_many(&self, locs: &[Loc]) -> Vec<io::Result<Vec<u8>>> {
        // By segment, each segment's ranges in one call: the client merges ranges that lie
        // close together into one GET, where a GET a chunk cost ~1 ms each on loopback.
        let mut by_segment: BTreeMap<u64, Vec<usize>> = BTreeMap::new();
        let mut out: Vec<Option<io::Result<Vec<u8>>>> = locs.iter().map(|_| None).collect();
        for (i, &loc) in locs.iter().enumerate() {
            match self.segment_of(loc) {
                Some((start, _)) => by_segment.entry(start).or_default().push(i),
                None => out[i] = Some(self.read(loc)),
            }
        }
        for (start, at) in by_segment {
            let store = self.objects.store.clone();
            let path = self.path(start);
            let ranges: Vec<std::ops::Range<u64>> = at
                .iter()
                .map(|&i| (locs[i].offset - start)..(locs[i].end() - start))
                .collect();
            match self.run(async move { store.get_ranges(&path, &ranges).await }) {
                Ok(got) => {
                    for (&i, b) in at.iter().zip(got) {
                        out[i] = Some(Ok(b.to_vec()));
                    }
                }
                Err(e) => {
                    let e = io_error(&format!("reading {}", self.name(start)), e);
                    for &i in &at {
                        let again = if is_unreachable(&e) {
                            io::Error::other(Unreachable(e.to_string()))
                        } else {
                            io::Error::new(e.kind(), e.to_string())
                        };
                        out[i] = Some(Err(again));
                    }
                }
            }
        }
        out.into_iter()
            .map(|r| r.expect("every location answered"))
            .collect()
    }

    fn append(&self, chunks: &[Vec<u8>]) -> io::Result<Vec<Loc>> {
        if self.follower {
            return Err(io::Error::new(
                io::ErrorKind::PermissionDenied,
                format!("{}: a replica does not write", self.objects.url),
            ));
        }
        self.check_lease()?;
        let mut end = lock(&self.end);
        let start = *end;
        let mut at = start;
        let mut locs = Vec::with_capacity(chunks.len());
        let mut bytes = Vec::with_capacity(chunks.iter().map(Vec::len).sum());
        for c in chunks {
            locs.push(Loc {
                offset: at,
                len: c.len() as u32,
            });
            at += c.len() as u64;
            bytes.extend_from_slice(c);
        }
        if bytes.is_empty() {
            return Ok(locs);
        }
        let len = bytes.len() as u64;
        // A failed PUT may still have left the object: it lies past the committed end, where
        // the next append writes over it and the next open deletes it.
        self.put(start, bytes)
            .map_err(|e| io_error(&format!("writing {}", self.name(start)), e))?;
        write(&self.segments).insert(start, len);
        *end = at;
        Ok(locs)
    }

    fn len(&self) -> u64 {
        *lock(&self.end)
    }

    fn describe(&self) -> String {
        self.objects.url.clone()
    }

    fn local(&self) -> bool {
        false
    }

    fn holds(&self, loc: Loc) -> bool {
        self.segment_of(loc).is_some()
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use object_store::memory::InMemory;

    /// A store's objects under `store1` of `store`, for the crate's tests.
    pub(crate) fn objects(store: Arc<dyn ObjectStore>) -> Objects {
        Objects {
            store,
            prefix: ObjectPath::from("store1"),
            url: "memory://store1".into(),
            grace: Duration::ZERO,
            lease: Duration::from_secs(30),
        }
    }

    #[test]
    fn segments_read_back_and_an_uncommitted_one_is_deleted_at_open() {
        let mem: Arc<dyn ObjectStore> = Arc::new(InMemory::new());
        let p = ObjectPack::open(objects(mem.clone()), 0, false).unwrap();
        let a = p.append(&[b"abc".to_vec(), b"defgh".to_vec()]).unwrap();
        assert_eq!(a[1], Loc { offset: 3, len: 5 });
        let b = p.append(&[b"xy".to_vec()]).unwrap();
        assert_eq!(b[0], Loc { offset: 8, len: 2 });
        assert_eq!(p.read(a[1]).unwrap(), b"defgh");
        assert_eq!(p.read(b[0]).unwrap(), b"xy");
        let many = p.read_many(&[b[0], a[1], a[0], Loc { offset: 90, len: 1 }]);
        assert_eq!(many[0].as_ref().unwrap(), b"xy");
        assert_eq!(many[1].as_ref().unwrap(), b"defgh");
        assert_eq!(many[2].as_ref().unwrap(), b"abc");
        assert!(many[3].is_err());
        // Across two segments is no chunk's location.
        assert!(p.read(Loc { offset: 7, len: 2 }).is_err());
        drop(p);
        // Only the first segment was committed: the second is a crashed commit's.
        let p = ObjectPack::open(objects(mem.clone()), 8, true).unwrap();
        assert_eq!(p.len(), 8);
        assert_eq!(read(&p.segments).len(), 1);
        let e = p.read(b[0]).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::NotFound);
        assert!(!is_unreachable(&e));
        // A store that does not yet name the place refuses one with segments in it.
        drop(p);
        let e = ObjectPack::open(objects(mem), 0, false).unwrap_err();
        assert!(e.to_string().contains("another store's"), "{e}");
    }

    #[test]
    fn a_second_writer_is_refused_while_the_lease_lives_and_takes_it_once_expired() {
        let mem: Arc<dyn ObjectStore> = Arc::new(InMemory::new());
        let short = Objects {
            lease: Duration::from_millis(600),
            ..objects(mem.clone())
        };
        let first = ObjectPack::open(short.clone(), 0, false).unwrap();
        let e = ObjectPack::open(short.clone(), 0, true).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::WouldBlock);
        assert!(e.to_string().contains("holds the store's lease"), "{e}");
        // Renewed while its holder lives, past several lifetimes of the lease.
        std::thread::sleep(Duration::from_millis(1500));
        assert!(ObjectPack::open(short.clone(), 0, true).is_err());
        first.append(&[b"still the writer".to_vec()]).unwrap();
        // A holder that stopped renewing without giving it back (its runtime gone, as in a
        // crash): the lease runs out, and the next writer takes it.
        let mut crashed = first;
        std::mem::forget(crashed.lease.take());
        crashed.runtime.take().unwrap().shutdown_background();
        std::thread::sleep(Duration::from_millis(800));
        let second = ObjectPack::open(short.clone(), 16, true).unwrap();
        second.append(&[b"the new writer".to_vec()]).unwrap();
        drop(second);
        // Given back when the pack closes: the next one opens at once.
        ObjectPack::open(short, 30, true).unwrap();
    }

    #[test]
    fn a_segment_past_the_multipart_size_goes_up_in_parts() {
        let mem: Arc<dyn ObjectStore> = Arc::new(InMemory::new());
        let p = ObjectPack::open(objects(mem), 0, false).unwrap();
        let big: Vec<u8> = (0..MULTIPART_BYTES + 12345)
            .map(|i| (i % 251) as u8)
            .collect();
        let locs = p.append(&[b"head".to_vec(), big.clone()]).unwrap();
        assert_eq!(p.read(locs[1]).unwrap(), big);
        assert_eq!(p.read(locs[0]).unwrap(), b"head");
        assert_eq!(p.collect_below(0).unwrap(), 0);
        assert_eq!(p.collect_below(p.len()).unwrap(), 1);
        assert!(p.read(locs[0]).is_err());
    }
}
