//! 11 → 12: two overlapping surveys are also judged by the spectrum of their differences: a
//! line in it (stripes) that one side holds and the other, smooth there, lacks marks the
//! side that holds it as the altered one. Each `o/` value gains that line. The old figures
//! cannot say whether a copy was striped, so the step is the one from 10 to 11: it drops
//! them and, where there were any, marks the store for a rebuild, which measures every pair
//! again from the samples.

use super::Ctx;

pub(super) fn run(tree: &sled::Tree, ctx: &Ctx) -> Result<sled::Batch, String> {
    super::v10_to_v11::run(tree, ctx)
}
