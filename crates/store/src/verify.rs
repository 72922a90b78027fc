//! The store's half of `verify`: every key decodes, every chunk matches its checksum, every
//! active survey is whole and its samples still hash to its id. The other half, that the
//! stored box states and edge patches are the ones inserting the surveys again derives, needs
//! a terrain and is the engine's `restore::verify`.

use super::chunks::{chunk_counts, chunk_rect, decode as decode_chunk, read_chunk};
use super::pack::Loc;
use super::{
    decode, decode_crs, decode_states, decode_u32, keys, migrate, setting_problem, FailedRecord,
    Status, Store, StoreError, StoredPatches, SurveyRecord,
};
use patchwork_core::index::lod::{BoxState, IndexConfig};
use patchwork_core::model::edge::{self, EdgePatch};
use patchwork_core::model::evidence::PairEvidence;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::ids::{PatchId, SurveyId};
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::survey::Survey;
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

/// What `verify` found: counts of what the store holds, and every problem.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VerifyReport {
    /// Active surveys.
    pub active: usize,
    /// Retired surveys whose records are still kept.
    pub retired: usize,
    /// Patches of the active surveys.
    pub patches: usize,
    /// Stored box states.
    pub tops: usize,
    /// Chunk locations, of active and retired surveys.
    pub chunks: usize,
    /// Recorded failures.
    pub failures: usize,
    /// Active surveys left out of the terrain because they are damaged.
    pub damaged: usize,
    /// Keys in the database.
    pub keys: u64,
    /// Everything found wrong, one line each; empty for a sound store.
    pub problems: Vec<String>,
}

impl VerifyReport {
    /// Whether nothing was found wrong.
    pub fn is_ok(&self) -> bool {
        self.problems.is_empty()
    }
}

/// Stop listing problems of one kind past this many; the count still tells how bad it is.
const MAX_LISTED: usize = 20;

/// Problems found, counted by kind, the first few of each kind listed.
pub struct Problems {
    list: Vec<String>,
    counts: BTreeMap<&'static str, usize>,
}

impl Problems {
    /// Counts a problem of `kind`, and lists it if fewer than a few of its kind are.
    pub fn add(&mut self, kind: &'static str, msg: String) {
        let n = self.counts.entry(kind).or_default();
        *n += 1;
        if *n <= MAX_LISTED {
            self.list.push(msg);
        }
    }

    /// The listed problems, and a line for each kind that had more than were listed.
    pub fn finish(mut self) -> Vec<String> {
        for (kind, n) in &self.counts {
            if *n > MAX_LISTED {
                self.list.push(format!(
                    "… and {} more problems of kind {kind}",
                    n - MAX_LISTED
                ));
            }
        }
        self.list
    }
}

fn key_str(k: &[u8]) -> String {
    String::from_utf8_lossy(k).into_owned()
}

/// What the store's own checks found, and what the index check needs: the whole surveys (when
/// every active one could be loaded and no rebuild is pending), and the stored tops and edge
/// patches to compare with the ones they derive.
pub struct Checked {
    /// What the store's own checks found.
    pub report: VerifyReport,
    /// The problems found so far, which the index check adds to.
    pub problems: Problems,
    /// Every active survey whole, or `None` when one could not be loaded or a rebuild is
    /// pending (the index cannot then be derived to compare).
    pub whole: Option<Vec<Arc<Survey>>>,
    /// The stored state of every box.
    pub tops: HashMap<PatchId, BoxState>,
    /// The stored edge patches.
    pub edges: HashMap<PatchId, EdgePatch>,
}

impl Store {
    /// Re-checks everything the store holds but the index. Problems go in the report; `Err` is
    /// only for failing to read.
    pub fn check(&self) -> Result<Checked, StoreError> {
        self.check_with(&|_, _| {})
    }

    /// [`Store::check`], telling `progress` how many of the surveys it has checked.
    pub fn check_with(&self, progress: &dyn Fn(u64, u64)) -> Result<Checked, StoreError> {
        let mut pr = Problems {
            list: Vec::new(),
            counts: BTreeMap::new(),
        };
        let mut rep = VerifyReport::default();
        let mut records: BTreeMap<SurveyId, SurveyRecord> = BTreeMap::new();
        let mut patches: HashMap<SurveyId, StoredPatches> = HashMap::new();
        // (survey, level, k) → where the chunk is in the pack
        let mut chunks: BTreeMap<(SurveyId, usize, usize), sled::IVec> = BTreeMap::new();
        let mut edges: HashMap<PatchId, EdgePatch> = HashMap::new();
        let mut tops: HashMap<PatchId, BoxState> = HashMap::new();
        let mut overlaps: Vec<(SurveyId, SurveyId)> = Vec::new();
        let mut accuracies: Vec<SurveyId> = Vec::new();

        for kv in self.db.iter() {
            let (k, v) = kv?;
            rep.keys += 1;
            if k.starts_with(keys::META_PREFIX) {
                self.check_meta(&k, &v, &mut pr);
            } else if let Some(id) = keys::parse_survey(&k) {
                match decode::<SurveyRecord>(&v, &key_str(&k)) {
                    Ok(r) if r.id != id => pr.add(
                        "record",
                        format!("{} holds the record of {}", key_str(&k), r.id),
                    ),
                    Ok(r) => {
                        records.insert(id, r);
                    }
                    Err(e) => pr.add("record", e.to_string()),
                }
            } else if let Some(id) = keys::parse_patches(&k) {
                match self.load_patches(id) {
                    Ok(ps) => {
                        patches.insert(id, ps);
                    }
                    Err(e) => pr.add("patches", e.to_string()),
                }
            } else if let Some((id, level, k)) = keys::parse_chunk(&k) {
                chunks.insert((id, level, k), v);
            } else if let Some(id) = keys::parse_edge(&k) {
                match crate::decode_edge(&v, &key_str(&k)) {
                    Ok(e) if e.id != id => {
                        pr.add("edge", format!("{} holds edge patch {}", key_str(&k), e.id))
                    }
                    Ok(e) => {
                        edges.insert(id, e);
                    }
                    Err(e) => pr.add("edge", e.to_string()),
                }
            } else if keys::parse_boxes(&k).is_some() {
                match decode_states(&v, &key_str(&k)) {
                    Ok(states) => tops.extend(states),
                    Err(e) => pr.add("top", e.to_string()),
                }
            } else if let Some(id) = keys::parse_accuracy(&k) {
                accuracies.push(id);
            } else if let Some((a, b)) = keys::parse_overlap(&k) {
                match decode::<crate::form::Pair>(&v, &key_str(&k)).map(PairEvidence::from) {
                    Ok(p)
                        if !(p.finer == a && p.coarser == b || p.finer == b && p.coarser == a) =>
                    {
                        pr.add(
                            "overlap",
                            format!(
                                "{} holds the pair of {} and {}",
                                key_str(&k),
                                p.finer,
                                p.coarser
                            ),
                        )
                    }
                    Ok(_) => overlaps.push((a, b)),
                    Err(e) => pr.add("overlap", e.to_string()),
                }
            } else if k.starts_with(keys::PIN_PREFIX) {
                if v.len() != 64 || !v.iter().all(u8::is_ascii_hexdigit) {
                    pr.add("pin", format!("{} does not hold a content id", key_str(&k)));
                }
            } else if k.starts_with(keys::FAILURE_PREFIX) {
                rep.failures += 1;
                if let Err(e) = decode::<FailedRecord>(&v, &key_str(&k)) {
                    pr.add("failure", e.to_string());
                }
            } else {
                pr.add("unknown key", format!("unknown key {:?}", key_str(&k)));
            }
        }
        rep.chunks = chunks.len();
        rep.tops = tops.len();

        let store_vertical = self.vertical_crs();
        let mut whole: Vec<Arc<Survey>> = Vec::new();
        let total = records.len() as u64;
        for (n, (id, r)) in records.iter().enumerate() {
            progress(n as u64, total);
            if r.status == Status::Retired {
                rep.retired += 1;
                // Retired samples stay until compaction, and must stay sound until then.
                self.check_chunks(*id, r, &chunks, &mut pr)?;
                continue;
            }
            rep.active += 1;
            // Surveys of any horizontal CRS share a store; their heights are all in its
            // vertical CRS.
            if let (Some(v), Some(s)) = (&r.vertical, &store_vertical) {
                if !v.same_reference(s) {
                    pr.add(
                        "vertical_crs",
                        format!(
                            "survey {id}'s heights are in {}, the store's in {}",
                            v.label(),
                            s.label()
                        ),
                    );
                }
            }
            if r.levels.is_empty() {
                pr.add("record", format!("survey {id} has no levels"));
                continue;
            }
            let chunks_ok = self.check_chunks(*id, r, &chunks, &mut pr)?;
            let Some(ps) = patches.get(id) else {
                pr.add("patches", format!("survey {id} has no patch list"));
                continue;
            };
            rep.patches += ps.patches.len();
            if let Some(p) = ps
                .patches
                .iter()
                .find(|p| p.survey != id.0 || p.level as usize >= r.levels.len())
            {
                pr.add(
                    "patches",
                    format!(
                        "survey {id} lists patch {} that is not its own",
                        PatchId(p.id)
                    ),
                );
                continue;
            }
            if chunks_ok {
                match self.load_survey(r) {
                    Ok(s) => {
                        let g = &s.levels[0];
                        let index = s.lattice_index();
                        if edge::edge_tiles(g, index, &self.layout) != ps.edge_tiles {
                            pr.add(
                                "patches",
                                format!("the edge tiles stored for survey {id} are not its own"),
                            );
                        }
                        whole.push(Arc::new(s));
                    }
                    Err(StoreError::Corrupt(m)) => pr.add("level", m.to_string()),
                    Err(e) => return Err(e),
                }
            }
        }
        for (a, b) in &overlaps {
            let active =
                |id: &SurveyId| records.get(id).is_some_and(|r| r.status == Status::Active);
            if !(active(a) && active(b)) {
                pr.add(
                    "orphan overlap",
                    format!("the overlap of {a} and {b} names a survey that is not active"),
                );
            }
        }
        for (id, _, _) in chunks.keys() {
            if !records.contains_key(id) {
                pr.add(
                    "orphan chunk",
                    format!("chunks of survey {id}, which has no record"),
                );
            }
        }
        for id in &accuracies {
            if !records.contains_key(id) {
                pr.add(
                    "orphan accuracies",
                    format!("kernel accuracies of survey {id}, which has no record"),
                );
            }
        }
        for id in patches.keys() {
            if !records.contains_key(id) {
                pr.add(
                    "orphan patches",
                    format!("patches of survey {id}, which has no record"),
                );
            }
        }
        // Without every active survey the index cannot be derived as the store holds it (its
        // neighbours' tops and the edge patches depend on the missing one): what is wrong with
        // the surveys is reported above, and the index is checked once they are whole. After a
        // migration the index is derived on the next open; there are no states to check yet.
        // A damaged survey is out of the terrain, and the stored index was derived without it:
        // the index is checked against the other surveys alone.
        let damaged = self.damaged();
        rep.damaged = damaged.len();
        for d in damaged.values() {
            pr.add("damaged", d.to_string());
        }
        let left_out = self.quarantined()?;
        let unreadable = damaged
            .keys()
            .filter(|id| !records.contains_key(id))
            .count();
        let whole = (whole.len() + damaged.len() == rep.active + unreadable
            && whole.iter().all(|s| !damaged.contains_key(&s.id))
            && damaged.keys().copied().eq(left_out.iter().copied())
            && self.db.get(keys::REBUILD)?.is_none())
        .then_some(whole);
        Ok(Checked {
            report: rep,
            problems: pr,
            whole,
            tops,
            edges,
        })
    }

    /// What is wrong with a `u64` LE offset into the pack that must not pass its end.
    fn within_pack(&self, what: &str, v: &[u8]) -> Option<String> {
        match <[u8; 8]>::try_from(v).map(u64::from_le_bytes) {
            Ok(n) if n <= self.pack.len() => None,
            Ok(n) => Some(format!(
                "{what} says {n} bytes, the pack holds {}",
                self.pack.len()
            )),
            Err(_) => Some(format!("{what} holds {} bytes, not 8", v.len())),
        }
    }

    fn check_meta(&self, k: &[u8], v: &[u8], pr: &mut Problems) {
        let what = key_str(k);
        let res = match k {
            keys::SCHEMA => decode_u32(v, &what).map(|n| {
                (n != migrate::CURRENT).then(|| {
                    format!(
                        "schema version {n}, this binary writes {}",
                        migrate::CURRENT
                    )
                })
            }),
            keys::CRS => decode_crs(v, &what, patchwork_core::crs::Crs::parse).map(|_| None),
            keys::VERTICAL_CRS => {
                decode_crs(v, &what, patchwork_core::crs::vertical::VerticalCrs::parse)
                    .map(|_| None)
            }
            keys::LAYOUT => decode::<PatchLayout>(v, &what).map(|l| {
                (l != self.layout).then(|| format!("layout {l:?} differs from the open store's"))
            }),
            keys::REBUILD => Ok(None),
            keys::QUARANTINED => decode::<Vec<SurveyId>>(v, &what).map(|_| None),
            keys::MIPMAP => Ok(setting_problem(v, self.recipe.mipmap)),
            keys::PATCHES => Ok(setting_problem(v, self.recipe.patches)),
            keys::CONTRADICTED => Ok(setting_problem(v, self.contradicted)),
            keys::BLEND => Ok(setting_problem(v, self.blend)),
            // Bytes past the committed length are a commit that did not happen (or has not
            // yet): an open cuts them. Fewer bytes than committed would be lost chunks.
            keys::PACK_LEN => Ok(self.within_pack(&what, v)),
            // How far opens read the pack back: never past its end.
            keys::CHECKED_TO => Ok(self.within_pack(&what, v)),
            keys::PACK_AT => Ok(
                (String::from_utf8_lossy(v) != self.pack.describe()).then(|| {
                    format!(
                        "meta/pack_at names {}, but the chunks are read from {}",
                        String::from_utf8_lossy(v),
                        self.pack.describe()
                    )
                }),
            ),
            keys::PACK_BASE => super::open::decode_base(v).map(|_| None),
            keys::LOG_SEQ => {
                Ok((v.len() != 8).then(|| format!("meta/log_seq holds {} bytes, not 8", v.len())))
            }
            keys::LOG_PENDING => Ok(super::journal::pending_problem(v)),
            keys::FOLLOWS => Ok(
                (String::from_utf8_lossy(v) != self.pack.describe()).then(|| {
                    format!(
                        "meta/follows names {}, but the chunks are read from {}",
                        String::from_utf8_lossy(v),
                        self.pack.describe()
                    )
                }),
            ),
            keys::INDEX => decode::<IndexConfig>(v, &what).map(|c| {
                (c != self.index)
                    .then(|| format!("index config {c:?} differs from the open store's"))
            }),
            _ => Ok(Some(format!("unknown key {what:?}"))),
        };
        match res {
            Ok(None) => {}
            Ok(Some(msg)) => pr.add("meta", msg),
            Err(e) => pr.add("meta", e.to_string()),
        }
    }

    /// Every chunk of every level is there and matches its checksum, nothing else is, and
    /// level 0 still hashes to the survey's id. Returns whether the samples can be loaded.
    fn check_chunks(
        &self,
        id: SurveyId,
        r: &SurveyRecord,
        chunks: &BTreeMap<(SurveyId, usize, usize), sled::IVec>,
        pr: &mut Problems,
    ) -> Result<bool, StoreError> {
        let mut whole = true;
        // Level 0 as the chunks hold it now, not as a cache may remember it.
        let mut level0: Option<Grid> = None;
        for (level, h) in r.levels.iter().enumerate() {
            let shape = h.shape();
            let [nx, ny] = chunk_counts(&shape);
            let n = nx * ny;
            if level == 0 && shape.cols >= 2 && shape.rows >= 2 {
                level0 = Some(Grid {
                    cols: shape.cols,
                    rows: shape.rows,
                    samples: vec![f32::NAN; shape.cols * shape.rows],
                    georef: shape.georef,
                });
            }
            // From an object store the level's chunks are fetched together first; a chunk
            // that is not among them is read (and explained) one by one as from a local pack.
            let mut fetched: HashMap<usize, std::io::Result<Vec<u8>>> = HashMap::new();
            if !self.pack.local() {
                let at: Vec<(usize, Loc)> = (0..n)
                    .filter_map(|k| Some((k, Loc::from_bytes(chunks.get(&(id, level, k))?)?)))
                    .filter(|(_, l)| l.end() <= self.pack.len())
                    .collect();
                let locs: Vec<Loc> = at.iter().map(|(_, l)| *l).collect();
                fetched = at
                    .iter()
                    .map(|(k, _)| *k)
                    .zip(self.pack.read_many(&locs))
                    .collect();
            }
            for k in 0..n {
                if !chunks.contains_key(&(id, level, k)) {
                    whole = false;
                    pr.add(
                        "missing chunk",
                        format!("chunk {k} of level {level} of survey {id} is missing"),
                    );
                    continue;
                }
                let rect = chunk_rect(&shape, k);
                let read = match fetched.remove(&k) {
                    Some(got) => got.map_err(|e| format!("reading the pack: {e}")),
                    None => read_chunk(&self.db, self.pack.as_ref(), id, level, k),
                };
                match read.and_then(|b| decode_chunk(&b, rect.len(), rect.cols())) {
                    Err(e) => {
                        whole = false;
                        pr.add(
                            "chunk",
                            format!("chunk {k} of level {level} of survey {id}: {e}"),
                        );
                    }
                    Ok(v) => {
                        if let (0, Some(g)) = (level, level0.as_mut()) {
                            for (i, row) in v.chunks(rect.cols()).enumerate() {
                                let at = (rect.r0 + i) * g.cols + rect.c0;
                                g.samples[at..at + row.len()].copy_from_slice(row);
                            }
                        }
                    }
                }
            }
            let extra = chunks
                .range((id, level, n)..=(id, level, usize::MAX))
                .count();
            if extra > 0 {
                pr.add(
                    "extra chunk",
                    format!("{extra} chunks past the end of level {level} of survey {id}"),
                );
            }
        }
        let levels = r.levels.len();
        let beyond = chunks
            .range((id, levels, 0)..=(id, usize::MAX, usize::MAX))
            .count();
        if beyond > 0 {
            pr.add(
                "extra chunk",
                format!("{beyond} chunks of levels survey {id} does not have"),
            );
        }
        if r.status == Status::Retired {
            return Ok(whole);
        }
        if let (true, Some(g)) = (whole, level0) {
            if g.valid_count() as u64 != r.samples {
                pr.add(
                    "samples",
                    format!(
                        "survey {id} has {} valid samples, its record says {}",
                        g.valid_count(),
                        r.samples
                    ),
                );
            }
            let hashed = Survey::id_of(&g, r.spec(), r.crs.as_ref());
            if hashed != id {
                pr.add(
                    "content",
                    format!("the samples of survey {id} hash to {hashed}: they have changed"),
                );
            }
        }
        Ok(whole)
    }
}
