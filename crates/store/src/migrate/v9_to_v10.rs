//! 9 → 10: an edge patch's grid keeps only the samples at the corners of its edge cells, the
//! only ones it evaluates, and the slope of its whole window, which its reprojection error
//! reads. On a mosaic that is a tenth of the samples. The step rewrites each `e/` record;
//! nothing the index derives changes (ids, errors and tops are those of the whole grid), so
//! it needs no rebuild.

use super::v9::EdgeV9;
use super::Ctx;
use crate::form::Edge;
use crate::{decode, encode, keys};

pub(super) fn run(tree: &sled::Tree, _: &Ctx) -> Result<sled::Batch, String> {
    let mut b = sled::Batch::default();
    for kv in tree.scan_prefix(keys::EDGE_PREFIX) {
        let (k, v) = kv.map_err(|e| e.to_string())?;
        let what = format!("edge record {}", String::from_utf8_lossy(&k));
        let old: EdgeV9 = match decode(&v, &what) {
            Ok(r) => r,
            // Already in the version-10 form (a store made for a test, say): left as it is.
            Err(e) => match decode::<Edge>(&v, &what) {
                Ok(_) => continue,
                Err(_) => return Err(e.to_string()),
            },
        };
        b.insert(k, encode(&old.now()?).map_err(|e| e.to_string())?);
    }
    Ok(b)
}
