//! Patchwork: a terrain database after *Patchwork Terrains* (Rocca, Panozzo, Puppo).
//!
//! Data flows read → model → index → store → serve, and so do the modules: [`read`] decodes
//! DEM files, [`model`] turns grids into mipmaps and patches, [`index`] keeps the
//! order-independent LOD space and answers cuts through it, [`resample`] blends extracted
//! patches into heights, [`mesh`] triangulates them for renderers, [`terrain`] ties them
//! together in memory, [`store`] keeps them on disk, and [`engine`], [`watch`] and [`serve`]
//! make the daemon.

pub mod bench;
pub mod config;
pub mod crs;
pub mod engine;
pub mod index;
pub mod ingest;
pub mod mesh;
pub mod model;
pub mod read;
pub mod resample;
pub mod restore;
pub mod serve;
pub mod store;
pub mod terrain;
pub mod watch;

/// Reproducible pseudo-random numbers, for the bench's scenes and the unit tests.
pub(crate) mod rng {
    /// Uniform numbers in [0, 1) from a 64-bit LCG: reproducible, and enough for spreading
    /// test points.
    pub fn uniform(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed;
        move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        }
    }
}
