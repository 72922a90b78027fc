//! 6 → 7: box states a unit at a time. Version 6 kept each box's state (its top and whether it
//! is exposed) under a key of its own, `t/<patch>`; the database then held a node entry in
//! memory for every patch, about 250 bytes each, more than the patch's box itself. Version 7
//! keeps one record a unit (a survey, or an edge patch), `b/<unit>`, with the states of all
//! its boxes in id order (see `encode_states`). The step finds each patch's unit in its
//! survey's patch list and each edge patch's in its record, and moves the states over
//! unchanged. A state whose patch no record names leaves the store to a rebuild, as does a
//! rebuild already pending (which derives every state again anyway).

use super::Ctx;
use crate::{chunks, decode_state, encode_states, keys, MAX_RECORD_BYTES};
use patchwork_core::index::lod::BoxState;
use patchwork_core::model::ids::{PatchId, SurveyId};
use serde::Deserialize;
use std::collections::{BTreeMap, HashMap};

/// A cell rectangle as version 6 wrote it.
#[derive(Deserialize)]
#[allow(dead_code)]
struct CellsV6 {
    c0: u32,
    r0: u32,
    c1: u32,
    r1: u32,
}

/// A patch as version 6 wrote it in a survey's patch list: a frozen copy, so that the step
/// reads version 6 whatever the patch becomes.
#[derive(Deserialize)]
#[allow(dead_code)]
struct PatchV6 {
    id: PatchId,
    survey: SurveyId,
    level: u8,
    index: [u32; 2],
    kernel: CellsV6,
    window: CellsV6,
    centre: [f64; 2],
    half: [f64; 2],
    valid: Vec<CellsV6>,
    delta: f64,
    error: f64,
}

/// The front of a version-6 patch list: the patches (the edge tiles that follow are not
/// needed).
#[derive(Deserialize)]
struct PatchListV6 {
    patches: Vec<PatchV6>,
}

/// The front of a version-6 edge patch record: its unit and id.
#[derive(Deserialize)]
struct EdgeHeadV6 {
    owner: SurveyId,
    id: PatchId,
}

pub(super) fn run(tree: &sled::Tree, ctx: &Ctx) -> Result<sled::Batch, String> {
    let config = bincode::config::standard();
    let mut b = sled::Batch::default();
    let mut tops = Vec::new();
    for kv in tree.scan_prefix(keys::TOP_PREFIX) {
        let (k, v) = kv.map_err(|e| e.to_string())?;
        b.remove(k.clone());
        tops.push((k, v));
    }
    if tops.is_empty()
        || tree
            .get(keys::REBUILD)
            .map_err(|e| e.to_string())?
            .is_some()
    {
        return Ok(b);
    }
    let mut unit: HashMap<PatchId, SurveyId> = HashMap::new();
    for kv in tree.scan_prefix(keys::PATCHES_PREFIX) {
        let (k, _) = kv.map_err(|e| e.to_string())?;
        let Some(survey) = keys::parse_patches(&k) else {
            continue;
        };
        let what = format!("the patches of survey {survey}");
        let sealed = chunks::read_packed(tree, ctx.pack, &k).map_err(|e| format!("{what}: {e}"))?;
        let v = chunks::unseal(&sealed, MAX_RECORD_BYTES).map_err(|e| format!("{what}: {e}"))?;
        let (list, _): (PatchListV6, usize) =
            bincode::serde::decode_from_slice(&v, config).map_err(|e| format!("{what}: {e}"))?;
        unit.extend(list.patches.into_iter().map(|p| (p.id, survey)));
    }
    for kv in tree.scan_prefix(keys::EDGE_PREFIX) {
        let (k, v) = kv.map_err(|e| e.to_string())?;
        let (e, _): (EdgeHeadV6, usize) = bincode::serde::decode_from_slice(&v, config)
            .map_err(|e| format!("{}: {e}", String::from_utf8_lossy(&k)))?;
        unit.insert(e.id, e.owner);
    }
    let mut units: BTreeMap<SurveyId, Vec<(PatchId, BoxState)>> = BTreeMap::new();
    for (k, v) in &tops {
        let what = String::from_utf8_lossy(k).to_string();
        let id = keys::parse_top(k).ok_or_else(|| format!("bad top key {what}"))?;
        let state = decode_state(v, &what).map_err(|e| e.to_string())?;
        match unit.get(&id) {
            Some(u) => units.entry(*u).or_default().push((id, state)),
            // A state of nothing: the index is derived again rather than carried over.
            None => {
                b.insert(keys::REBUILD, &[1u8][..]);
                return Ok(b);
            }
        }
    }
    for (u, mut states) in units {
        states.sort_unstable_by_key(|(id, _)| *id);
        b.insert(keys::boxes(u), encode_states(&states));
    }
    Ok(b)
}
