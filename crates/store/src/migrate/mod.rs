//! Schema versions and the steps between them, one file a step (`v<N>_to_v<N+1>.rs`), so
//! that a schema change is visible as a file of its own in review. The rules are in the
//! top-level `migrations/README.md`.

use super::keys;
use super::{Corruption, StoreError};
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::patch::PatchLayout;

mod v0_to_v1;
mod v10_to_v11;
mod v11_to_v12;
mod v12_to_v13;
mod v1_to_v2;
mod v2_to_v3;
mod v3;
mod v3_to_v4;
mod v4_to_v5;
mod v5_to_v6;
mod v6_to_v7;
mod v7_to_v8;
mod v8;
mod v8_to_v9;
mod v9;
mod v9_to_v10;

/// Every step, as (from version, to version, step). `migrate` follows them from the version a
/// store records up to `migrate::CURRENT`.
const STEPS: &[(u32, u32, Step)] = &[
    (0, 1, v0_to_v1::run),
    (1, 2, v1_to_v2::run),
    (2, 3, v2_to_v3::run),
    (3, 4, v3_to_v4::run),
    (4, 5, v4_to_v5::run),
    (5, 6, v5_to_v6::run),
    (6, 7, v6_to_v7::run),
    (7, 8, v7_to_v8::run),
    (8, 9, v8_to_v9::run),
    (9, 10, v9_to_v10::run),
    (10, 11, v10_to_v11::run),
    (11, 12, v11_to_v12::run),
    (12, 13, v12_to_v13::run),
];

/// The schema this binary writes.
pub const CURRENT: u32 = 13;

/// What a step may need beyond the tree: the settings `open` was called with, which a fresh
/// store adopts, and the pack that chunk bytes go to.
pub struct Ctx<'a> {
    /// The patch layout `open` was called with.
    pub layout: PatchLayout,
    /// The index settings `open` was called with.
    pub index: IndexConfig,
    /// The pack that chunk bytes go to.
    pub pack: &'a dyn super::pack::ChunkStore,
}

/// A step reads the tree as it is and returns the writes that take it one version further.
/// The runner adds the version bump to that same batch, so a step is applied whole, bump
/// included, or not at all, and no step can forget the bump.
pub type Step = fn(&sled::Tree, &Ctx) -> Result<sled::Batch, String>;

pub(super) fn steps() -> &'static [(u32, u32, Step)] {
    STEPS
}

/// The schema version recorded in the tree; 0 when none is (a fresh or foreign directory).
pub fn version(tree: &sled::Tree) -> Result<u32, StoreError> {
    match tree.get(keys::SCHEMA)? {
        None => Ok(0),
        Some(v) => {
            let b: [u8; 4] = v.as_ref().try_into().map_err(|_| {
                StoreError::from(Corruption::Length {
                    key: "meta/schema",
                    len: v.len(),
                    expected: 4,
                })
            })?;
            Ok(u32::from_le_bytes(b))
        }
    }
}

/// Brings the tree to [`CURRENT`], one flushed step at a time, and returns the steps run.
pub fn migrate(tree: &sled::Tree, ctx: &Ctx) -> Result<Vec<(u32, u32)>, StoreError> {
    let mut v = version(tree)?;
    if v > CURRENT {
        return Err(StoreError::Newer {
            found: v,
            supported: CURRENT,
        });
    }
    let mut ran = Vec::new();
    while v < CURRENT {
        let &(from, to, step) = steps()
            .iter()
            .find(|(from, to, _)| *from == v && *to > v && *to <= CURRENT)
            .ok_or_else(|| StoreError::from(Corruption::NoMigration(v)))?;
        let mut batch = step(tree, ctx).map_err(|msg| StoreError::Migration { from, to, msg })?;
        batch.insert(keys::SCHEMA, &to.to_le_bytes());
        tree.apply_batch(batch)?;
        tree.flush()?;
        ran.push((from, to));
        v = to;
    }
    Ok(ran)
}
