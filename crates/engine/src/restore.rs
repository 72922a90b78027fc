//! From a store to a terrain: what opening, compacting and verifying a store need of the
//! in-memory engine. The store reads and writes records, chunks and tops and builds nothing;
//! this is where its contents become a terrain again, and where the index is derived anew when
//! the stored one cannot be trusted.

use patchwork_core::geom::Aabb;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::edge::EdgePatch;
use patchwork_core::model::ids::PatchId;
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::source::SampleSource;
use patchwork_core::terrain::{Terrain, TerrainError};
use patchwork_store::{
    encode, CompactFailed, CompactReport, Contents, Loaded, Store, StoreError, StoreOptions,
    VerifyReport,
};
use std::collections::HashSet;
use std::path::Path;
use std::sync::Arc;

/// A terrain's failure as the store's caller sees it: samples it could not read, or a survey
/// it could not place.
pub fn terrain_error(e: TerrainError) -> StoreError {
    match e {
        TerrainError::Samples(e) => StoreError::Samples(e),
        TerrainError::Place(e) => StoreError::Place(e),
    }
}

/// An edge patch as the store writes it: what `verify` compares.
fn as_stored(e: &EdgePatch) -> Result<Vec<u8>, StoreError> {
    let f = patchwork_store::form::Edge::try_from(e).map_err(|_| StoreError::Inconsistent {
        survey: e.owner,
        what: "an edge patch it owns holds no samples to compare",
    })?;
    encode(&f)
}

// An open store and its terrain are handed from the thread that opened them to the engine's:
// they stay Send and Sync, which the crate's compilation checks.
const _: () = {
    const fn shared<T: Send + Sync>() {}
    shared::<Opened>()
};

/// A store opened, and the terrain it holds.
pub struct Opened {
    /// The store, open for writing (or following, on a replica).
    pub store: Store,
    /// The terrain its surveys make, indexed.
    pub terrain: Terrain,
    /// Problems met while opening that did not stop it (missing or orphaned tops, a disk too
    /// full for the reserve file): `verify` tells more.
    pub warnings: Vec<String>,
    /// Whether the disk was so full that the reserve file was given back to open the store.
    pub released_reserve: bool,
}

/// Opens or creates the store at `dir` (see [`Store::open_with`]) and restores its terrain.
pub fn open(
    dir: &Path,
    layout: PatchLayout,
    index: IndexConfig,
    opts: impl Into<StoreOptions>,
) -> Result<Opened, StoreError> {
    open_within(dir, layout, index, opts, None)
}

/// [`open`], restoring on a replica of a region only the part of the terrain that answers
/// there (see [`terrain_of`]).
pub fn open_within(
    dir: &Path,
    layout: PatchLayout,
    index: IndexConfig,
    opts: impl Into<StoreOptions>,
    region: Option<&Aabb>,
) -> Result<Opened, StoreError> {
    restore_within(Store::open_with(dir, layout, index, opts)?, region)
}

/// The terrain of a store just opened: restored from the stored tops and edge patches without
/// reading a sample, or derived again from the surveys when the store asks for it or a patch
/// has no stored top.
pub fn restore(loaded: Loaded) -> Result<Opened, StoreError> {
    restore_within(loaded, None)
}

/// [`restore`], of only the part of the terrain that answers inside `region`, if given.
pub fn restore_within(loaded: Loaded, region: Option<&Aabb>) -> Result<Opened, StoreError> {
    let Loaded {
        mut store,
        contents,
        mut warnings,
        released_reserve,
    } = loaded;
    let terrain = terrain_of(&mut store, contents, &mut warnings, region)?;
    Ok(Opened {
        store,
        terrain,
        warnings,
        released_reserve,
    })
}

/// The terrain of a replica that applied its writer's new commits, restored as an open
/// restores it (see [`Store::catch_up`]); `None` when there were none.
pub fn follow_up(
    store: &mut Store,
    region: Option<&Aabb>,
) -> Result<Option<(Terrain, Vec<String>)>, StoreError> {
    let Some(contents) = store.catch_up()? else {
        return Ok(None);
    };
    let mut warnings = Vec::new();
    let terrain = terrain_of(store, contents, &mut warnings, region)?;
    Ok(Some((terrain, warnings)))
}

/// The terrain of a store's contents. With a `region` (a replica's, in the store's plane),
/// only the surveys that reach it grown by the largest window are kept (see
/// [`patchwork_core::terrain::reaching`]), which answer every point inside it as the whole
/// terrain does. An index derived again (tops missing) is derived whole.
fn terrain_of(
    store: &mut Store,
    contents: Contents,
    warnings: &mut Vec<String>,
    region: Option<&Aabb>,
) -> Result<Terrain, StoreError> {
    let Contents {
        surveys,
        pairs,
        edges,
        mut tops,
        rebuild,
        damaged: _,
    } = contents;
    let mut terrain = if rebuild {
        derive(store, warnings)?
    } else {
        let source: Arc<dyn SampleSource> = store.reader();
        let (terrain, missing) = Terrain::restore(
            store.index_config(),
            store.crs().as_ref(),
            store.contradicted(),
            surveys,
            pairs,
            edges,
            &tops,
            source,
            region,
        );
        if let Some(p) = missing.first() {
            // A patch without a state would be a hole; deriving the index again costs an
            // insertion per survey and writes every state.
            warnings.push(format!(
                "{} patches had no stored top (first: {p}); the index was derived again from \
                 the surveys",
                missing.len()
            ));
            derive(store, warnings)?
        } else {
            for id in terrain.index().state().keys() {
                tops.remove(id);
            }
            // A region's terrain holds only some patches; the others' tops are the writer's.
            if let Some(p) = tops.keys().min().filter(|_| region.is_none()) {
                warnings.push(format!(
                    "{} stored tops belong to no patch of the terrain (first: {p}); ignored",
                    tops.len()
                ));
            }
            terrain
        }
    };
    terrain.set_blend(store.blend());
    terrain.set_edge_cache(store.edge_cache_bytes());
    Ok(terrain)
}

/// Every active survey inserted again, in id order (each measured against those before it),
/// and every box state, edge patch and pair written in one batch. The result does not depend on the order, which only fixes
/// the work done. On a disk too full to take the writes, the terrain is still served and the
/// next open tries again.
fn derive(store: &mut Store, warnings: &mut Vec<String>) -> Result<Terrain, StoreError> {
    let mut surveys = store.whole_surveys()?;
    surveys.sort_by_key(|s| s.id);
    let mut t = Terrain::with_crs(store.index_config(), store.crs().as_ref(), None);
    t.set_contradicted(store.contradicted());
    for s in &surveys {
        t.try_insert(s).map_err(terrain_error)?;
    }
    let units = t.index().all_unit_states();
    let edges: Vec<_> = t.edges().cloned().collect();
    // A replica writes nothing: the writer stores what it derives, and the replica receives
    // it with the writer's commits.
    if !store.is_replica() {
        match store.write_derived(&units, &edges, &t.pairs()) {
            Ok(()) => {}
            Err(e @ StoreError::Full { .. }) => warnings.push(format!(
                "the index was derived again but could not be stored: {e}"
            )),
            Err(e) => return Err(e),
        }
    }
    t.set_source(store.reader());
    for s in &surveys {
        t.page_out(s.id);
    }
    Ok(t)
}

/// Physically removes retired surveys (see [`Store::compact`]) and restores the terrain of the
/// compacted store. A failure that left the store open gives it back.
pub fn compact(
    store: Store,
    live: &HashSet<PatchId>,
) -> Result<(Opened, CompactReport), CompactFailed> {
    let (loaded, report) = store.compact(live)?;
    // Only the writer compacts, and it holds the whole store.
    let opened = restore(loaded).map_err(|error| CompactFailed { store: None, error })?;
    Ok((opened, report))
}

/// Re-checks the whole store: its own checks (see [`Store::check`]), then that its box states
/// and edge patches are the ones inserting its surveys again derives. Problems go in the
/// report; `Err` is only for failing to read.
pub fn verify(store: &Store) -> Result<VerifyReport, StoreError> {
    verify_with(store, &|_, _, _| {})
}

/// [`verify`], telling `progress` what it checks (`"surveys"`, then `"index"`) and how many
/// of how many it has done.
pub fn verify_with(
    store: &Store,
    progress: &dyn Fn(&'static str, u64, u64),
) -> Result<VerifyReport, StoreError> {
    let checked = store.check_with(&|done, total| progress("surveys", done, total))?;
    let patchwork_store::Checked {
        mut report,
        mut problems,
        whole,
        mut tops,
        mut edges,
    } = checked;
    if let Some(mut whole) = whole {
        whole.sort_by_key(|s| s.id);
        let mut terrain = Terrain::with_crs(store.index_config(), store.crs().as_ref(), None);
        terrain.set_contradicted(store.contradicted());
        let total = whole.len() as u64;
        for (n, s) in whole.iter().enumerate() {
            progress("index", n as u64, total);
            terrain.try_insert(s).map_err(terrain_error)?;
        }
        for (id, (span, exposed)) in terrain.index().state() {
            match tops.remove(&id) {
                None => problems.add("missing top", format!("patch {id} has no top")),
                Some(t) if t.top != span.max_z || t.exposed != exposed => problems.add(
                    "top",
                    format!(
                        "wrong top of patch {id}: stored {} (exposed {}), derived {} (exposed {exposed})",
                        t.top, t.exposed, span.max_z
                    ),
                ),
                Some(_) => {}
            }
        }
        for p in tops.keys() {
            problems.add(
                "orphan top",
                format!("top of patch {p} belongs to no patch of the terrain"),
            );
        }
        for e in terrain.edges() {
            match edges.remove(&e.id) {
                None => problems.add("missing edge", format!("edge patch {} is missing", e.id)),
                // Compared as stored: heights hold NaN where nothing is near. Both hold their
                // samples: the stored one as read, the derived one as built, by a terrain
                // that has no store to read them again from.
                Some(stored)
                    if as_stored(&stored)?
                        != as_stored(
                            &e.with_grid(terrain.edge_grid(e).map_err(StoreError::Samples)?),
                        )? =>
                {
                    problems.add(
                        "edge",
                        format!("edge patch {} differs from the one derived", e.id),
                    )
                }
                Some(_) => {}
            }
        }
        for id in edges.keys() {
            problems.add(
                "orphan edge",
                format!("edge patch {id} belongs to no tile of the terrain"),
            );
        }
        if let Err(e) = terrain.index().check() {
            problems.add("index", format!("the derived index fails its check: {e}"));
        }
    }
    report.problems = problems.finish();
    Ok(report)
}
