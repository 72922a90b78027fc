//! Where chunk bytes live: an append-only pack file beside the database, behind a small trait
//! so that another backend, an object store ([`super::objects`]), can take its place.
//!
//! sled keeps, for every chunk, where its bytes are ([`Loc`]), and how far the pack is
//! committed (`meta/pack_len`). A commit appends its chunks and syncs them before the sled
//! batch that points at them is applied, so a crash between the two leaves only bytes past the
//! committed length, which the next open cuts off. Chunks of retired surveys stay in the pack
//! until compaction writes a new one with the live chunks alone.
//!
//! Why not in sled: sled 0.34 keeps values of this size at two to three times their bytes on
//! disk, and compacting it grows it further (docs/BENCHMARKS.md, "Store size"); a pack holds
//! each chunk once.

use patchwork_core::sync::lock;
use std::fs::{File, OpenOptions};
use std::io;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// The pack's file name inside the store's directory.
pub const PACK_FILE: &str = "chunks.pack";

/// Beside the pack: how far into it an open read every chunk back and checked it (see
/// [`ChunkStore::checked_to`]). Kept out of the database so that an open writes nothing there:
/// the write of a sled key in an open's first start of the database left 3.5 MB of memory that
/// sled let go of but never returned (80 bytes a patch on a 45,000-patch store, docs/SCALE.md).
pub const CHECKED_FILE: &str = "chunks.checked";

/// Where a chunk's bytes are in the pack.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Loc {
    /// Where the chunk's first byte is in the pack's address space.
    pub offset: u64,
    /// The chunk's length in bytes.
    pub len: u32,
}

impl Loc {
    /// Bytes of a location as a record stores it: the offset, then the length.
    pub const BYTES: usize = 12;

    /// The location as a record stores it: the offset (`u64` LE), then the length (`u32` LE).
    pub fn to_bytes(self) -> [u8; Self::BYTES] {
        let mut b = [0u8; Self::BYTES];
        b[..8].copy_from_slice(&self.offset.to_le_bytes());
        b[8..].copy_from_slice(&self.len.to_le_bytes());
        b
    }

    /// [`Loc::to_bytes`] read back; `None` when `b` is not [`Loc::BYTES`] long.
    pub fn from_bytes(b: &[u8]) -> Option<Loc> {
        (b.len() == Self::BYTES).then(|| Loc {
            offset: u64::from_le_bytes(b[..8].try_into().expect("8 bytes")),
            len: u32::from_le_bytes(b[8..].try_into().expect("4 bytes")),
        })
    }

    /// The offset just past the chunk's last byte.
    pub fn end(&self) -> u64 {
        self.offset + self.len as u64
    }
}

/// A place to keep chunk bytes: appended in commits, read by location.
pub trait ChunkStore: Send + Sync + std::fmt::Debug {
    /// The bytes at `loc`.
    fn read(&self, loc: Loc) -> io::Result<Vec<u8>>;
    /// Appends chunks and makes them durable; returns where each went.
    fn append(&self, chunks: &[Vec<u8>]) -> io::Result<Vec<Loc>>;
    /// Bytes written so far, committed or not.
    fn len(&self) -> u64;
    /// Whether nothing was written yet.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// The bytes at each of `locs`, in order. An object store fetches the neighbouring ones
    /// of a segment together.
    fn read_many(&self, locs: &[Loc]) -> Vec<io::Result<Vec<u8>>> {
        locs.iter().map(|&l| self.read(l)).collect()
    }
    /// Where the bytes are, for messages: a file's path, or an object store's URL.
    fn describe(&self) -> String;
    /// Committed bytes the backend found missing when it opened.
    fn lost(&self) -> u64 {
        0
    }
    /// Whether reading every chunk back is cheap, as from a local disk: an open then checks
    /// every chunk's checksum. Over a network it checks that each location is held
    /// ([`ChunkStore::holds`]), and leaves the checksums to each read and to `verify`.
    fn local(&self) -> bool {
        true
    }
    /// Whether the bytes at `loc` are there to read, as far as the backend knows without
    /// reading them.
    fn holds(&self, loc: Loc) -> bool {
        loc.end() <= self.len()
    }
    /// How far from its start an earlier open read every chunk back and checked it, where the
    /// backend keeps that mark (a local pack that lost no bytes): the pack is append-only, so
    /// an open checks only what comes after. `None` where no mark is kept or none was found.
    fn checked_to(&self) -> Option<u64> {
        None
    }
    /// Marks that every chunk up to the end of what is committed was read back and checked.
    /// Best effort: a mark that cannot be written only makes the next open read more.
    fn note_checked(&self) {}
}

/// Bytes of chunks an append writes at a time.
const RUN_BYTES: usize = 1 << 20;

/// The pack file.
#[derive(Debug)]
pub struct PackFile {
    file: File,
    path: PathBuf,
    /// The end of the file: where the next append goes. Appends take it in turn.
    end: Mutex<u64>,
    /// Committed bytes missing from the end of the file when it was opened.
    lost: u64,
}

impl PackFile {
    /// Opens the pack in `dir`, made if missing, cut back to `committed` bytes: anything past
    /// that was appended by a commit that never reached the database.
    ///
    /// A pack shorter than `committed` has lost bytes that records point at (a truncated copy,
    /// a damaged disk): it opens all the same, so that the surveys whose bytes are still there
    /// are served, and appends go on at `committed`, past a hole, so that the lost locations
    /// never hold another survey's bytes. [`PackFile::lost`] says how much is gone.
    pub fn open(dir: &Path, committed: u64) -> io::Result<PackFile> {
        let path = dir.join(PACK_FILE);
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)?;
        let len = file.metadata()?.len();
        if len > committed {
            file.set_len(committed)?;
            file.sync_all()?;
        }
        Ok(PackFile {
            file,
            path,
            end: Mutex::new(committed),
            lost: committed.saturating_sub(len),
        })
    }

    /// The pack file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn checked_path(&self) -> PathBuf {
        self.path.with_file_name(CHECKED_FILE)
    }
}

/// The mark's 16 bytes: the offset, then its complement, so that a damaged file reads as no
/// mark (and the open reads more) rather than as a mark past what was checked.
fn encode_mark(at: u64) -> [u8; 16] {
    let mut b = [0u8; 16];
    b[..8].copy_from_slice(&at.to_le_bytes());
    b[8..].copy_from_slice(&(!at).to_le_bytes());
    b
}

fn decode_mark(b: &[u8]) -> Option<u64> {
    let b: &[u8; 16] = b.try_into().ok()?;
    let at = u64::from_le_bytes(b[..8].try_into().expect("8 bytes"));
    let not = u64::from_le_bytes(b[8..].try_into().expect("8 bytes"));
    (at == !not).then_some(at)
}

impl ChunkStore for PackFile {
    fn read(&self, loc: Loc) -> io::Result<Vec<u8>> {
        let mut buf = vec![0u8; loc.len as usize];
        self.file.read_exact_at(&mut buf, loc.offset)?;
        Ok(buf)
    }

    fn append(&self, chunks: &[Vec<u8>]) -> io::Result<Vec<Loc>> {
        let mut end = lock(&self.end);
        let mut at = *end;
        let mut locs = Vec::with_capacity(chunks.len());
        // Chunks go out in runs of about a megabyte through one buffer: a survey's whole pack
        // (44 MB for a 3600² tile) gathered into one buffer first cost its allocation, its
        // pages faulted in and a copy, for one write call.
        let mut buf = Vec::with_capacity(RUN_BYTES);
        let mut written = Ok(());
        let mut run = at;
        for c in chunks {
            locs.push(Loc {
                offset: at,
                len: c.len() as u32,
            });
            at += c.len() as u64;
            if !buf.is_empty() && buf.len() + c.len() > RUN_BYTES {
                written = written.and_then(|()| self.file.write_all_at(&buf, run));
                run += buf.len() as u64;
                buf.clear();
            }
            buf.extend_from_slice(c);
        }
        let written = written
            .and_then(|()| self.file.write_all_at(&buf, run))
            .and_then(|()| self.file.sync_data());
        if let Err(e) = written {
            // Whatever part landed is past the committed length, and is cut at the next open.
            let _ = self.file.set_len(*end);
            return Err(e);
        }
        *end = at;
        Ok(locs)
    }

    fn len(&self) -> u64 {
        *lock(&self.end)
    }

    fn describe(&self) -> String {
        self.path.display().to_string()
    }

    /// Bytes the database says were committed that the file no longer holds.
    fn lost(&self) -> u64 {
        self.lost
    }

    /// The mark in [`CHECKED_FILE`], never past the committed end. None on a pack that lost
    /// bytes: what a mark says of it may be of bytes that are gone, and it is read whole.
    fn checked_to(&self) -> Option<u64> {
        if self.lost > 0 {
            return None;
        }
        let b = std::fs::read(self.checked_path()).ok()?;
        Some(decode_mark(&b)?.min(self.len()))
    }

    /// Written to a file beside it, then renamed over the mark: a crash leaves the old mark or
    /// the new one. A compaction, which writes a new pack in a new directory, leaves the mark
    /// behind with the old pack.
    fn note_checked(&self) {
        if self.lost > 0 {
            return;
        }
        let to = self.checked_path();
        let end = self.len();
        if std::fs::read(&to).ok().as_deref().and_then(decode_mark) == Some(end) {
            return;
        }
        let tmp = to.with_extension("checked.new");
        let written = (|| {
            let mut f = File::create(&tmp)?;
            io::Write::write_all(&mut f, &encode_mark(end))?;
            f.sync_all()?;
            std::fs::rename(&tmp, &to)
        })();
        if let Err(e) = written {
            let _ = std::fs::remove_file(&tmp);
            tracing::warn!(error = %e, "could not note how far the open checked the pack");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_append_larger_than_a_run_reads_back_chunk_by_chunk() {
        let tmp = tempfile::tempdir().unwrap();
        let p = PackFile::open(tmp.path(), 0).unwrap();
        // Chunks of many sizes, one larger than a run by itself, spanning several runs.
        let chunks: Vec<Vec<u8>> = (0..40u32)
            .map(|k| {
                let n = if k == 7 {
                    RUN_BYTES + 3
                } else {
                    (k as usize * 7919) % 200_000
                };
                (0..n).map(|i| (i as u32 ^ k) as u8).collect()
            })
            .collect();
        let locs = p.append(&chunks).unwrap();
        let total: usize = chunks.iter().map(Vec::len).sum();
        assert!(total > 3 * RUN_BYTES);
        assert_eq!(p.len(), total as u64);
        for (c, l) in chunks.iter().zip(&locs) {
            assert_eq!(&p.read(*l).unwrap(), c);
        }
    }

    #[test]
    fn appends_read_back_and_an_uncommitted_tail_is_cut() {
        let tmp = tempfile::tempdir().unwrap();
        let p = PackFile::open(tmp.path(), 0).unwrap();
        let locs = p.append(&[b"abc".to_vec(), b"defgh".to_vec()]).unwrap();
        assert_eq!(locs[1], Loc { offset: 3, len: 5 });
        assert_eq!(p.read(locs[1]).unwrap(), b"defgh");
        assert_eq!(Loc::from_bytes(&locs[1].to_bytes()), Some(locs[1]));
        drop(p);
        // Only the first chunk was committed.
        let p = PackFile::open(tmp.path(), 3).unwrap();
        assert_eq!(p.len(), 3);
        assert_eq!(std::fs::metadata(p.path()).unwrap().len(), 3);
        let locs = p.append(&[b"xy".to_vec()]).unwrap();
        assert_eq!(locs[0].offset, 3);
        // A pack shorter than what was committed opens, says how much is gone, and appends
        // past the hole, so that no lost location is ever reused.
        drop(p);
        let p = PackFile::open(tmp.path(), 100).unwrap();
        assert_eq!(p.lost(), 95);
        assert!(p.read(Loc { offset: 90, len: 4 }).is_err());
        let locs = p.append(&[b"z".to_vec()]).unwrap();
        assert_eq!(locs[0].offset, 100);
        assert_eq!(p.read(locs[0]).unwrap(), b"z");
        assert_eq!(p.read(Loc { offset: 3, len: 2 }).unwrap(), b"xy");
    }
}
