//! Disk space: every write is checked against the free space before sled sees it.
//!
//! sled 0.34 does not survive running out of space: after one `ENOSPC` every later read and
//! write of that handle fails or blocks, freeing space does not help, and its lock outlives the
//! handle, so the store cannot even be reopened in the same process. So a write that might not
//! fit is refused here, with nothing written, and the store keeps `min_free` bytes free for
//! everyone else.
//!
//! A reserve file beside the store (`<dir>.reserve`) holds some space back for the one moment
//! it is needed: opening a store on a disk that something else filled. Opening releases it, so
//! that sled can start, and the daemon serves read-only until space returns; the reserve is
//! taken back once there is room for it again.

use super::StoreError;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Where free space is asked for; the system's, or a stand-in in tests.
pub trait DiskSpace: Send + Sync {
    /// Bytes a writer may still use on the filesystem holding `dir`.
    fn available(&self, dir: &Path) -> std::io::Result<u64>;
}

/// The filesystem's own figure (`statvfs`).
pub struct SystemDisk;

impl DiskSpace for SystemDisk {
    fn available(&self, dir: &Path) -> std::io::Result<u64> {
        // The store's directory may not exist yet; its parent tells the same.
        let mut p = dir;
        loop {
            match fs2::available_space(p) {
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => match p.parent() {
                    Some(parent) if !parent.as_os_str().is_empty() => p = parent,
                    _ => return Err(e),
                },
                r => return r,
            }
        }
    }
}

/// sled writes a log and cleans it later, so a batch can take several times its own size on
/// disk before its segments are reclaimed.
const AMPLIFICATION: u64 = 3;
/// What a write costs beyond its bytes: a new log segment, the metadata.
const OVERHEAD: u64 = 4 << 20;

/// The space rules of one store.
#[derive(Clone)]
pub struct SpaceGuard {
    /// Where the free space is asked for.
    pub disk: Arc<dyn DiskSpace>,
    /// Bytes every write leaves free.
    pub min_free: u64,
    /// Size of the reserve file; 0 keeps none.
    pub reserve: u64,
}

impl Default for SpaceGuard {
    fn default() -> Self {
        SpaceGuard {
            disk: Arc::new(SystemDisk),
            min_free: 64 << 20,
            reserve: 64 << 20,
        }
    }
}

impl std::fmt::Debug for SpaceGuard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SpaceGuard")
            .field("min_free", &self.min_free)
            .field("reserve", &self.reserve)
            .finish_non_exhaustive()
    }
}

/// The disk space a batch of `bytes` is allowed for.
pub fn needed_for(bytes: u64) -> u64 {
    bytes.saturating_mul(AMPLIFICATION).saturating_add(OVERHEAD)
}

impl SpaceGuard {
    /// Refuses a write of `bytes` to the store in `dir` that would leave less than `min_free`.
    pub fn check(&self, dir: &Path, bytes: u64) -> Result<(), StoreError> {
        let available = self.disk.available(dir)?;
        let needed = needed_for(bytes).saturating_add(self.min_free);
        if available < needed {
            return Err(StoreError::Full {
                available_mb: available >> 20,
                needed_mb: needed.div_ceil(1 << 20),
            });
        }
        Ok(())
    }

    fn reserve_path(dir: &Path) -> Result<PathBuf, StoreError> {
        super::sibling(dir, ".reserve")
    }

    /// Before opening: gives the reserve back to the disk when the disk is too full to open
    /// the store on. Returns whether it did.
    pub fn release_if_full(&self, dir: &Path) -> Result<bool, StoreError> {
        let path = Self::reserve_path(dir)?;
        if !path.exists() || self.disk.available(dir)? >= self.min_free {
            return Ok(false);
        }
        std::fs::remove_file(&path)?;
        Ok(true)
    }

    /// Takes the reserve back when there is room for it and for `min_free` besides. A reserve
    /// that cannot be made now is tried again after the next commit.
    pub fn restore(&self, dir: &Path) -> Result<(), StoreError> {
        let path = Self::reserve_path(dir)?;
        if self.reserve == 0 || path.exists() {
            return Ok(());
        }
        if self.disk.available(dir)? < self.reserve + self.min_free + OVERHEAD {
            return Ok(());
        }
        let f = std::fs::File::create(&path)?;
        // Allocated, not sparse: the blocks must really be held.
        if let Err(e) = fs2::FileExt::allocate(&f, self.reserve) {
            drop(f);
            let _ = std::fs::remove_file(&path);
            return Err(e.into());
        }
        f.sync_all()?;
        Ok(())
    }
}
