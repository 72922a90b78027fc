//! 7 → 8: overlaps are judged on the whole overlap and at every scale both surveys resolve.
//! Each `o/` value gains the detail the two hold and share band by band, the finer survey's
//! cell, and whether the coregistration is determined; the degradation test reads windows
//! spread over the overlap instead of its middle. None of that follows from the old figures,
//! so the step drops them and marks the store for a rebuild, which measures every pair again
//! from the samples and derives the index from the verdicts.

use super::Ctx;
use crate::keys;

pub(super) fn run(tree: &sled::Tree, _: &Ctx) -> Result<sled::Batch, String> {
    let mut b = sled::Batch::default();
    let mut any = false;
    for kv in tree.scan_prefix(keys::OVERLAP_PREFIX) {
        let (k, _) = kv.map_err(|e| e.to_string())?;
        b.remove(k);
        any = true;
    }
    // Without pairs no claim was raised, and the stored index stands as it is.
    if any {
        b.insert(keys::REBUILD, &[1u8][..]);
    }
    Ok(b)
}
