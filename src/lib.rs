//! Patchwork: a terrain database after *Patchwork Terrains* (Rocca, Panozzo, Puppo).
//!
//! Data flows read → model → index → store → serve. This crate's modules follow that flow:
//! [`model`] turns grids into mipmaps and patches, [`index`] keeps the order-independent LOD
//! space and answers cuts through it, [`resample`] blends the extracted patches into heights,
//! [`terrain`] ties them together in memory, and [`store`] keeps them on disk.

pub mod index;
pub mod model;
pub mod read;
pub mod resample;
pub mod store;
pub mod terrain;
