//! Patchwork: a terrain database after *Patchwork Terrains* (Rocca, Panozzo, Puppo).
//!
//! This package is the daemon's binary and its command line. Every layer under it is a crate
//! of its own, and data flows one way through them (docs/ARCHITECTURE.md):
//!
//! - [`patchwork_core`]: geometry, CRSs, the model, the index, resampling, meshes and the
//!   in-memory terrain, with no I/O; [`patchwork_read`]: DEM files;
//! - [`store`] (`patchwork-store`): surveys, patches and the index on disk (sled and the
//!   chunk pack), migrations, the lease, the journal, compaction and verification;
//! - [`engine`] (`patchwork-engine`): one store, one published state, one writer, and every
//!   request; with it the settings ([`config`]), ingest, the inbox watcher and the GPU;
//! - [`serve`] (`patchwork-server`): the gRPC services and the HTTP tiles.
//!
//! The names below let the command line, the integration tests and the examples reach each
//! layer through one crate.

pub use patchwork_engine as engine;
pub use patchwork_engine::config;
#[cfg(feature = "gpu")]
pub use patchwork_engine::gpu;
pub use patchwork_engine::tune_allocator;
pub use patchwork_engine::{ingest, paths, restore, watch};
pub use patchwork_server as serve;
pub use patchwork_store as store;
