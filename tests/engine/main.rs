//! The engine and the layers under it, in this process: the store and its faults, CRSs and
//! vertical datums, the evidence of overlaps, readers fed hostile files, meshes, and the GPU
//! against the CPU.

#[path = "../common/mod.rs"]
mod common;

mod change;
mod crs;
mod docs;
mod evidence;
mod format;
mod fuzz;
#[cfg(feature = "gpu")]
mod gpu;
mod mesh;
mod objects;
mod sources;
mod store;
mod vertical;
