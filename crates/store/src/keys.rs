//! Key names. Every key starts with an ASCII prefix, and ids are 16 lowercase hex digits, so a
//! prefix scan finds one kind of record and keys of one survey sort together, level by level
//! and band by band.

use patchwork_core::model::ids::{PatchId, SurveyId};

/// `u32` LE: the schema version the store is written in (see `migrate`).
pub const SCHEMA: &[u8] = b"meta/schema";
/// The store's horizontal CRS as its `Crs::key` (UTF-8).
pub const CRS: &[u8] = b"meta/crs";
/// The store's vertical CRS as its `VerticalCrs::key` (UTF-8), once it has one.
pub const VERTICAL_CRS: &[u8] = b"meta/vertical_crs";
/// The `PatchLayout` every survey of the store is cut with (bincode).
pub const LAYOUT: &[u8] = b"meta/layout";
/// The `IndexConfig` the stored box tops were computed with (bincode).
pub const INDEX: &[u8] = b"meta/index";
/// The name of the mipmap filter every survey of the store is built with; absent in stores
/// made before there was a choice, whose surveys are all `smooth`.
pub const MIPMAP: &[u8] = b"meta/mipmap";
/// The name of the patch kind every survey of the store is made of; absent in stores made
/// before there was a choice, whose patches are all `bilinear`.
pub const PATCHES: &[u8] = b"meta/patches";
/// `distrust` or `keep`: what the store does with a claim other surveys find false.
pub const CONTRADICTED: &[u8] = b"meta/contradicted";
/// The name of the blend the store's patches are resampled with; absent in stores made
/// before there was a choice, which blend with `formula1`.
pub const BLEND: &[u8] = b"meta/blend";
/// `u64` LE: how many bytes of the chunk pack are committed (see [`super::pack`]).
pub const PACK_LEN: &[u8] = b"meta/pack_len";
/// The URL of the object store that holds the chunks (UTF-8); absent for the local pack.
pub const PACK_AT: &[u8] = b"meta/pack_at";
/// On an object store, after a compaction: where the address space it left behind ends, and
/// when (`u64` LE each: offset, Unix seconds). See [`super::objects`].
pub const PACK_BASE: &[u8] = b"meta/pack_base";
/// `u64` LE: on an object store, the newest commit of the journal replicas follow (see
/// [`super::journal`]): on the writer, the newest applied; on a replica, the newest it applied.
pub const LOG_SEQ: &[u8] = b"meta/log_seq";
/// On the writer: what the newest commit's log is made from (bincode).
pub const LOG_PENDING: &[u8] = b"meta/log_pending";
/// On a replica: the URL of the place it follows (UTF-8).
pub const FOLLOWS: &[u8] = b"meta/follows";
/// Present when the index must be derived again from the surveys on the next open (a
/// migration that changed what the index keeps writes it).
pub const REBUILD: &[u8] = b"meta/rebuild";
/// The surveys the stored index was derived without, because their records or chunks are
/// damaged (bincode `Vec<SurveyId>`, in id order); absent when there are none.
pub const QUARANTINED: &[u8] = b"meta/quarantined";

/// `u64` LE, the local pack only, in stores written before the mark moved beside the pack
/// ([`super::pack::CHECKED_FILE`]): how far into the pack an open had read every chunk back
/// and checked it. Read where the pack has no mark of its own, never written now; a
/// compaction, which moves every chunk, leaves it behind.
pub const CHECKED_TO: &[u8] = b"meta/checked_to";

/// Every store-wide setting and counter.
pub const META_PREFIX: &[u8] = b"meta/";
/// Survey records, by survey id.
pub const SURVEY_PREFIX: &[u8] = b"s/";
/// Where each survey's patch list is in the pack, by survey id.
pub const PATCHES_PREFIX: &[u8] = b"p/";
/// Where each chunk of samples is in the pack, by survey, level and chunk.
pub const CHUNK_PREFIX: &[u8] = b"c/";
/// One key a patch, holding its box's state: schema 6 and before, read only by the step to 7.
pub const TOP_PREFIX: &[u8] = b"t/";
/// One key a unit (a survey, with the edge patches it owns), holding the states of all its
/// boxes: a key a patch kept a node entry of the database in memory for every patch.
pub const BOXES_PREFIX: &[u8] = b"b/";
/// Files that failed to ingest, by source path.
pub const FAILURE_PREFIX: &[u8] = b"f/";
/// What overlapping surveys say of each other's claims, by pair.
pub const OVERLAP_PREFIX: &[u8] = b"o/";
/// The estimated accuracy of a survey whose ε was estimated, by survey id.
pub const ACCURACY_PREFIX: &[u8] = b"a/";
/// Content ids of files whose surveys were retired by hand, by source path.
pub const PIN_PREFIX: &[u8] = b"r/";
/// Edge patches the active surveys call for, by patch id.
pub const EDGE_PREFIX: &[u8] = b"e/";

/// A survey's record.
pub fn survey(id: SurveyId) -> Vec<u8> {
    format!("s/{id}").into_bytes()
}

/// Where a survey's patches and edge tiles are in the pack.
pub fn patches(id: SurveyId) -> Vec<u8> {
    format!("p/{id}").into_bytes()
}

/// A survey's estimated accuracy.
pub fn accuracy(id: SurveyId) -> Vec<u8> {
    format!("a/{id}").into_bytes()
}

/// Every chunk of a survey, all levels.
pub fn chunks_of(id: SurveyId) -> Vec<u8> {
    format!("c/{id}/").into_bytes()
}

/// Chunk `k` of a level, numbered row-major over the level's chunks.
pub fn chunk(id: SurveyId, level: usize, k: usize) -> Vec<u8> {
    format!("c/{id}/{level:02}/{k:08}").into_bytes()
}

/// Whether the key's value is a location in the chunk pack rather than the record itself.
pub fn in_pack(k: &[u8]) -> bool {
    k.starts_with(CHUNK_PREFIX) || k.starts_with(PATCHES_PREFIX)
}

/// An edge patch, by its patch id.
pub fn edge(id: PatchId) -> Vec<u8> {
    format!("e/{id}").into_bytes()
}

/// `e/<patch>` → the patch id.
pub fn parse_edge(k: &[u8]) -> Option<PatchId> {
    hex_id(k.strip_prefix(EDGE_PREFIX)?).map(PatchId)
}

/// The states of a unit's boxes.
pub fn boxes(unit: SurveyId) -> Vec<u8> {
    format!("b/{unit}").into_bytes()
}

/// `b/<unit>` → the unit.
pub fn parse_boxes(k: &[u8]) -> Option<SurveyId> {
    hex_id(k.strip_prefix(BOXES_PREFIX)?).map(SurveyId)
}

/// How survey `b` disagrees with survey `a`; stored under both orders.
pub fn overlap(a: SurveyId, b: SurveyId) -> Vec<u8> {
    format!("o/{a}/{b}").into_bytes()
}

/// Every overlap of a survey.
pub fn overlaps_of(a: SurveyId) -> Vec<u8> {
    format!("o/{a}/").into_bytes()
}

/// The failure recorded for a source path.
pub fn failure(source: &str) -> Vec<u8> {
    let mut k = FAILURE_PREFIX.to_vec();
    k.extend_from_slice(source.as_bytes());
    k
}

/// A survey retired by hand from a file still in the inbox: the file's content id, which the
/// watcher leaves retired until the content changes.
pub fn pin(source: &str) -> Vec<u8> {
    let mut k = PIN_PREFIX.to_vec();
    k.extend_from_slice(source.as_bytes());
    k
}

fn hex_id(s: &[u8]) -> Option<u64> {
    if s.len() != 16
        || !s
            .iter()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(b))
    {
        return None;
    }
    u64::from_str_radix(std::str::from_utf8(s).ok()?, 16).ok()
}

/// `s/<survey>` → the survey id.
pub fn parse_survey(k: &[u8]) -> Option<SurveyId> {
    hex_id(k.strip_prefix(SURVEY_PREFIX)?).map(SurveyId)
}

/// `a/<survey>` → the survey id.
pub fn parse_accuracy(k: &[u8]) -> Option<SurveyId> {
    hex_id(k.strip_prefix(ACCURACY_PREFIX)?).map(SurveyId)
}

/// `p/<survey>` → the survey id.
pub fn parse_patches(k: &[u8]) -> Option<SurveyId> {
    hex_id(k.strip_prefix(PATCHES_PREFIX)?).map(SurveyId)
}

/// `o/<a>/<b>` → (a, b).
pub fn parse_overlap(k: &[u8]) -> Option<(SurveyId, SurveyId)> {
    let rest = k.strip_prefix(OVERLAP_PREFIX)?;
    if rest.len() != 33 || rest[16] != b'/' {
        return None;
    }
    Some((
        SurveyId(hex_id(&rest[..16])?),
        SurveyId(hex_id(&rest[17..])?),
    ))
}

/// `t/<patch>` (schema 6 and before) → the patch id.
pub fn parse_top(k: &[u8]) -> Option<PatchId> {
    hex_id(k.strip_prefix(TOP_PREFIX)?).map(PatchId)
}

/// `c/<survey>/<level:02>/<k:08>` → (survey, level, k).
pub fn parse_chunk(k: &[u8]) -> Option<(SurveyId, usize, usize)> {
    let rest = k.strip_prefix(CHUNK_PREFIX)?;
    if rest.len() != 16 + 1 + 2 + 1 + 8 || rest[16] != b'/' || rest[19] != b'/' {
        return None;
    }
    let id = hex_id(&rest[..16])?;
    let num = |s: &[u8]| -> Option<usize> {
        s.iter()
            .all(u8::is_ascii_digit)
            .then(|| std::str::from_utf8(s).ok()?.parse().ok())?
    };
    Some((SurveyId(id), num(&rest[17..19])?, num(&rest[20..])?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_round_trip() {
        let s = SurveyId(0x00ab_cdef_0123_4567);
        let p = PatchId(u64::MAX);
        assert_eq!(survey(s), b"s/00abcdef01234567");
        assert_eq!(parse_survey(&survey(s)), Some(s));
        assert_eq!(parse_patches(&patches(s)), Some(s));
        assert_eq!(parse_accuracy(&accuracy(s)), Some(s));
        assert_eq!(parse_top(b"t/ffffffffffffffff"), Some(p));
        assert_eq!(boxes(s), b"b/00abcdef01234567");
        assert_eq!(parse_boxes(&boxes(s)), Some(s));
        assert_eq!(parse_edge(&edge(p)), Some(p));
        assert_eq!(chunk(s, 3, 17), b"c/00abcdef01234567/03/00000017");
        assert_eq!(parse_chunk(&chunk(s, 3, 17)), Some((s, 3, 17)));
        assert!(chunk(s, 3, 17).starts_with(&chunks_of(s)));
        assert_eq!(parse_top(b"t/FFFFFFFFFFFFFFFF"), None);
        let q = SurveyId(7);
        assert_eq!(parse_overlap(&overlap(s, q)), Some((s, q)));
        assert!(overlap(s, q).starts_with(&overlaps_of(s)));
        assert_eq!(parse_chunk(b"c/00abcdef01234567/03/0000001x"), None);
    }
}
