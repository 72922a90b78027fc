//! 10 → 11: two overlapping surveys are placed against each other by an affine map and a
//! plane (a rotation, stretch or shear about the overlap's centre, and a vertical tilt)
//! where that explains their differences markedly better than a shift, and their tests of
//! degradation and detail read them so placed. Each `o/` value's coregistration gains the
//! overlap's centre and half extent, the linear part and the tilt. The old figures do not say
//! whether a copy was turned, so the step drops them and, where there were any, marks the
//! store for a rebuild, which measures every pair again from the samples.

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
