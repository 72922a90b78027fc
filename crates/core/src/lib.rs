//! The core of Patchwork, a terrain database after *Patchwork Terrains* (Rocca, Panozzo,
//! Puppo): every layer from plane geometry up to the in-memory terrain, as pure computation.
//! Nothing here reads a file, opens a socket or touches a GPU; the daemon (`patchwork`) adds
//! the store, the readers and the servers on top.
//!
//! Each layer is a crate of its own, so that an import of a higher layer does not compile;
//! this crate re-exports them under one name, in their order from the bottom:
//!
//! - [`geom`]: bounds, oriented rectangles, affine maps, the one snap rule;
//! - [`crs`]: what coordinates mean, and carrying points between CRSs;
//! - [`model`]: grids, mipmaps, patches, surveys, accuracy and the evidence of overlaps;
//! - [`index`]: the order-independent LOD space and its cuts;
//! - [`resample`]: extracted patches blended into heights on the CPU (Formula 1);
//! - [`mesh`]: triangle meshes of resampled tiles, and their encodings;
//! - [`terrain`]: all of it together in memory, the state the daemon publishes.

pub use patchwork_crs as crs;
pub use patchwork_geom as geom;
pub use patchwork_index as index;
pub use patchwork_mesh as mesh;
pub use patchwork_model as model;
pub use patchwork_resample as resample;

pub mod sync;
pub mod terrain;
