//! 0 → 1: a directory with no schema version becomes an empty version-1 store.
//!
//! Version 0 means "no `meta/schema` key". That is only a fresh, empty tree: keys without a
//! version are something else's data, and adopting them would hide the mistake.

use super::Ctx;
use crate::keys;
use crate::{encode, form};

pub(super) fn run(tree: &sled::Tree, ctx: &Ctx) -> Result<sled::Batch, String> {
    if let Some(kv) = tree.iter().next() {
        let (k, _) = kv.map_err(|e| e.to_string())?;
        return Err(format!(
            "the directory holds data but no schema version (first key {:?}); it is not a Patchwork store",
            String::from_utf8_lossy(&k)
        ));
    }
    let mut b = sled::Batch::default();
    b.insert(
        keys::LAYOUT,
        encode(&form::Layout::from(ctx.layout)).map_err(|e| e.to_string())?,
    );
    b.insert(
        keys::INDEX,
        encode(&form::Index::from(ctx.index)).map_err(|e| e.to_string())?,
    );
    Ok(b)
}
