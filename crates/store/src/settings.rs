//! The settings a store is made with and keeps (mipmap filter, patch kind, the policy for
//! contradicted claims, the blend, its CRSs), as their names under `meta/`.

use super::*;

/// A choice recorded in the store when it is made, under its own key, by name.
pub(crate) trait Setting: Copy + PartialEq {
    const KEY: &'static [u8];
    /// What the choice is, for messages.
    const WHAT: &'static str;
    /// What a store made before the choice existed holds.
    const LEGACY: Self;
    fn name(self) -> &'static str;
    fn from_name(name: &str) -> Option<Self>;
}

impl Setting for Filter {
    const KEY: &'static [u8] = keys::MIPMAP;
    const WHAT: &'static str = "mipmap filter";
    const LEGACY: Self = Filter::Smooth;
    fn name(self) -> &'static str {
        Filter::name(self)
    }
    fn from_name(name: &str) -> Option<Self> {
        Filter::from_name(name)
    }
}

impl Setting for Contradicted {
    const KEY: &'static [u8] = keys::CONTRADICTED;
    const WHAT: &'static str = "policy for contradicted claims";
    // Stores made before the choice come to this one through the migration that measures
    // their pairs, which derives their index again.
    const LEGACY: Self = Contradicted::Distrust;
    fn name(self) -> &'static str {
        Contradicted::name(self)
    }
    fn from_name(name: &str) -> Option<Self> {
        Contradicted::from_name(name)
    }
}

impl Setting for Blend {
    const KEY: &'static [u8] = keys::BLEND;
    const WHAT: &'static str = "blend";
    // Blending reads the stored patches and writes nothing, so a store from before the choice
    // could take either; it keeps the heights it served.
    const LEGACY: Self = Blend::Formula1;
    fn name(self) -> &'static str {
        Blend::name(self)
    }
    fn from_name(name: &str) -> Option<Self> {
        Blend::from_name(name)
    }
}

impl Setting for PatchKind {
    const KEY: &'static [u8] = keys::PATCHES;
    const WHAT: &'static str = "patch kind";
    const LEGACY: Self = PatchKind::Bilinear;
    fn name(self) -> &'static str {
        PatchKind::name(self)
    }
    fn from_name(name: &str) -> Option<Self> {
        PatchKind::from_name(name)
    }
}

/// A store's setting: the recorded one, or for a store that has none, the legacy one when it
/// already holds surveys (they were built before the choice) and `configured` when it is new,
/// recorded then. On a disk too full to record it, it is used unrecorded: no survey can be
/// written there either.
pub(super) fn setting_of<T: Setting>(
    db: &sled::Db,
    dir: &Path,
    guard: &SpaceGuard,
    configured: T,
) -> Result<T, StoreError> {
    let key = String::from_utf8_lossy(T::KEY);
    if let Some(v) = db.get(T::KEY)? {
        let name = String::from_utf8_lossy(&v);
        return T::from_name(&name).ok_or_else(|| {
            StoreError::from(Corruption::Unreadable {
                what: key.into_owned(),
                why: format!("names no choice: {name:?}"),
            })
        });
    }
    let legacy = db.scan_prefix(keys::SURVEY_PREFIX).next().is_some();
    let v = if legacy { T::LEGACY } else { configured };
    if guard.check(dir, 64).is_ok() {
        db.insert(T::KEY, v.name())?;
    }
    Ok(v)
}

/// The store's recipe, each part by [`setting_of`].
pub(super) fn recipe_of(
    db: &sled::Db,
    dir: &Path,
    guard: &SpaceGuard,
    configured: Recipe,
) -> Result<Recipe, StoreError> {
    Ok(Recipe {
        mipmap: setting_of(db, dir, guard, configured.mipmap)?,
        patches: setting_of(db, dir, guard, configured.patches)?,
    })
}

/// A CRS recorded as its key.
pub(super) fn decode_crs<T>(
    b: &[u8],
    what: &str,
    parse: impl Fn(&str) -> Result<T, patchwork_core::crs::CrsError>,
) -> Result<T, StoreError> {
    let text = std::str::from_utf8(b).map_err(|_| crate::decode_error(what, "not UTF-8 text"))?;
    parse(text).map_err(|e| crate::decode_error(what, e))
}

pub(super) fn decode_u32(b: &[u8], what: &str) -> Result<u32, StoreError> {
    let a: [u8; 4] = b
        .try_into()
        .map_err(|_| crate::decode_error(what, format!("{} bytes, not 4", b.len())))?;
    Ok(u32::from_le_bytes(a))
}
