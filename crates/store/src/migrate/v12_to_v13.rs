//! 12 → 13: two overlapping surveys are also judged by their transfer function, ring by ring
//! of their spectra: a side that lost power coherently, or whose spectrum falls off an edge
//! where the other's is smooth, is a filter of the other. Each `o/` value gains it. The old
//! figures cannot say, so the step is the one from 10 to 11: it drops them and, where there
//! were any, marks the store for a rebuild, which measures every pair again from the samples.

use super::Ctx;

pub(super) fn run(tree: &sled::Tree, ctx: &Ctx) -> Result<sled::Batch, String> {
    super::v10_to_v11::run(tree, ctx)
}
