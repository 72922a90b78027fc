//! Patchwork: a terrain database after *Patchwork Terrains* (Rocca, Panozzo, Puppo).
//!
//! This crate is the daemon and its command line; the pure layers under it are
//! [`patchwork_core`] (geometry, CRSs, the model, the index, resampling, meshes, the
//! in-memory terrain) and [`patchwork_read`] (DEM files). Data flows one way, and so do the
//! modules here, each importing only those listed before it (docs/ARCHITECTURE.md):
//!
//! - [`config`]: settings, compiled-in defaults, file and environment;
//! - [`store`]: surveys, patches and the index on disk (sled and the chunk pack);
//! - [`restore`]: a terrain built from what the store holds, verification and compaction;
//! - [`gpu`]: resampling on the GPU (the `gpu` feature);
//! - [`ingest`]: a file read and modelled into a survey, nothing written;
//! - [`engine`]: one store, one published state, one writer, and every request;
//! - [`watch`]: the inbox folders;
//! - [`serve`]: the gRPC services and their wire types.

pub mod config;
pub mod engine;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod ingest;
pub mod paths;
pub mod restore;
pub mod serve;
pub mod store;
pub mod sync;
pub mod watch;

/// Lets the allocator reuse freed buffers of up to 512 MiB instead of handing each back to the
/// system at once. An ingest allocates a few raster-sized buffers (52 MB for a 3600² tile) and
/// frees them within a second; by default glibc maps each afresh, and the kernel's faulting
/// and zeroing of those pages cost about a tenth of the CPU time of a batch of ingests (the
/// scale bench, docs/BENCHMARKS.md). Freed pages still go back after each batch (the engine
/// trims the heap once no ingest is left running); one ingest peaks some 12% higher.
///
/// Process-wide, so it is the program's to set: `main` calls it first thing, before any
/// thread starts.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets a parameter of the allocator, which serialises it with
    // allocations; called from main before any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 512 << 20);
        // Nor is the free space at the top of a thread's heap handed back after every
        // request: a 256² web tile frees a few MB, and giving them back (then faulting them in
        // again, with a TLB shootdown across the cores each time) took 7 of its 12 ms. The
        // engine still trims after its large work (`malloc_trim`).
        libc::mallopt(libc::M_TRIM_THRESHOLD, 256 << 20);
    }
}
