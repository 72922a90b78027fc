//! What the store records of its surveys and files: a survey's record and its levels, the
//! failures and pins, the catalog readers take, and reading them back.

use super::*;
use std::collections::BTreeSet;
use std::sync::Arc;

/// A survey's patches and the edge tiles its samples reach, stored together under `p/`, as
/// they are stored: each patch with what the patches in memory leave to their survey (its id,
/// its window's centre and half side), which the open checks against the survey.
pub type StoredPatches = form::Patches;

/// Whether a survey is part of the terrain.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Status {
    /// In the index and served.
    Active,
    /// Out of the index; its samples stay until the next compaction.
    Retired,
}

/// A level's size and georeference, as a survey's record keeps it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LevelHeader {
    /// Samples in a row.
    pub cols: u64,
    /// Rows of samples.
    pub rows: u64,
    /// Where the level's samples are in the survey's plane.
    pub georef: Georef,
}

impl LevelHeader {
    pub(super) fn of(g: &Grid) -> Self {
        LevelHeader {
            cols: g.cols as u64,
            rows: g.rows as u64,
            georef: g.georef,
        }
    }

    /// The level's size and georeference as a [`Shape`].
    pub fn shape(&self) -> Shape {
        Shape {
            cols: self.cols as usize,
            rows: self.rows as usize,
            georef: self.georef,
        }
    }
}

/// Where the time of one ingestion went, in milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct IngestTimings {
    /// Reading and decoding the file.
    pub read_ms: f64,
    /// Building the survey from the raster.
    pub build_ms: f64,
    /// Working out what the survey changes in the index.
    pub index_ms: f64,
    /// Filled in by the store: encoding, the atomic batch and its flush.
    pub commit_ms: f64,
}

/// What the store keeps of a survey besides its samples and patches, under `s/` in its
/// [`form::Survey`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "form::Survey", into = "form::Survey")]
pub struct SurveyRecord {
    /// The survey's id.
    pub id: SurveyId,
    /// The file it was read from.
    pub source: String,
    /// Hex blake3 of the file's bytes; empty when unknown.
    pub content_id: String,
    /// ε in metres: the largest of the survey's kernels'.
    pub accuracy: f64,
    /// Where ε came from.
    pub accuracy_source: AccuracySource,
    /// Its horizontal CRS: the plane its grid is in, which may not be the store's.
    pub crs: Option<Crs>,
    /// The vertical CRS its file or sidecar named; None where nothing did.
    pub vertical_source: Option<VerticalCrs>,
    /// What its stored heights are measured from: the store's vertical CRS where they were
    /// converted to it; None where nothing was named.
    pub vertical: Option<VerticalCrs>,
    /// What converting its heights between vertical CRSs added to ε, in metres.
    pub vertical_error_m: f64,
    /// Whether it is in the terrain or retired.
    pub status: Status,
    /// Level 0's samples in a row.
    pub cols: u64,
    /// Level 0's rows of samples.
    pub rows: u64,
    /// Level 0's georeference.
    pub georef: Georef,
    /// Valid level-0 samples.
    pub samples: u64,
    /// Level 0 first, as stored in the chunks.
    pub levels: Vec<LevelHeader>,
    /// Where level 0's kernel boundaries fall (see [`Tiling`]).
    pub tiling_offset: [i64; 2],
    /// Where the time of its ingestion went.
    pub ingest: IngestTimings,
    /// When the record was made, in Unix seconds.
    pub created_unix: u64,
    /// What its sidecar says of where it came from: title, licence, attribution, when.
    pub about: form::About,
}

impl SurveyRecord {
    /// The record of an active survey read from `source`.
    pub fn new(
        s: &Survey,
        source: impl Into<String>,
        content_id: impl Into<String>,
        accuracy_source: AccuracySource,
        ingest: IngestTimings,
    ) -> Self {
        let l0 = &s.levels[0];
        SurveyRecord {
            id: s.id,
            source: source.into(),
            content_id: content_id.into(),
            accuracy: s.accuracy,
            accuracy_source: if s.spec == AccuracySpec::Auto {
                AccuracySource::Estimated
            } else {
                accuracy_source
            },
            crs: s.crs.clone(),
            vertical_source: s.vertical.clone(),
            vertical: s.vertical.clone(),
            vertical_error_m: 0.0,
            status: Status::Active,
            cols: l0.cols as u64,
            rows: l0.rows as u64,
            georef: l0.georef,
            samples: l0.valid_count() as u64,
            levels: s.levels.iter().map(|g| LevelHeader::of(g)).collect(),
            tiling_offset: s.tiling.offset,
            ingest,
            created_unix: now_unix(),
            about: form::About::default(),
        }
    }

    /// How the survey's ε was decided, as its id hashes it.
    pub fn spec(&self) -> AccuracySpec {
        match self.accuracy_source {
            AccuracySource::Estimated => AccuracySpec::Auto,
            _ => AccuracySpec::Fixed(self.accuracy),
        }
    }
}

/// A survey whose records or chunks cannot be read back as they were written: out of the
/// terrain until its file is ingested again or [`Store::repair`] drops it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Damaged {
    /// The survey's id.
    pub id: SurveyId,
    /// Its file; empty when its record itself is what is damaged.
    pub source: String,
    /// What was found wrong, first problem only.
    pub reason: String,
}

/// What an operator is told of it, at open and by `verify`.
impl std::fmt::Display for Damaged {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let source = if self.source.is_empty() {
            "its record is unreadable"
        } else {
            &self.source
        };
        write!(
            f,
            "survey {} ({source}) is damaged and out of the terrain: {}; ingest its file again \
             or run `patchwork repair` to drop it",
            self.id, self.reason
        )
    }
}

/// Everything the store holds besides samples and patches: what listings, stats and the inbox
/// read. The engine keeps it beside the terrain, so that they never wait on the disk.
///
/// The records are a persistent map: the catalog after a commit is the one before with the
/// commit's records put in (see [`Store::catalog`]), sharing the rest, so that a commit costs
/// what it changes and not the store's size.
#[derive(Clone, Debug, Default)]
pub struct Catalog {
    /// Every survey record, active and retired, by id. Behind an `Arc`, so that the map's
    /// nodes hold a pointer a record rather than the record (about 450 bytes) and the slack
    /// of their unfilled slots costs pointers.
    pub records: imbl::OrdMap<SurveyId, Arc<SurveyRecord>>,
    /// The active records, as (source, id): the first of a source is the record
    /// [`Catalog::stored_active_from`] gives, should two share one, and a retirement takes
    /// its own pair out without looking for the next.
    by_source: imbl::OrdSet<(String, SurveyId)>,
    /// How many records are active, damaged ones included: kept as records come and go, so
    /// that counting them costs nothing however large the store.
    active_records: usize,
    /// Every recorded failure, in source order.
    pub failures: Vec<FailedRecord>,
    /// Sources retired by hand, with the content that stays retired (see [`Store::pins`]).
    pub pins: HashMap<String, String>,
    /// Active surveys left out of the terrain because they are damaged, by id.
    pub damaged: BTreeMap<SurveyId, Damaged>,
    /// The store's horizontal CRS, once it has one.
    pub crs: Option<Crs>,
    /// The store's vertical CRS, once it has one.
    pub vertical: Option<VerticalCrs>,
    /// The layout every survey of the store is cut with.
    pub layout: PatchLayout,
    /// The mipmap filter and patch kind every survey of the store is built with.
    pub recipe: Recipe,
}

impl Catalog {
    /// The record of survey `id`, active or retired.
    pub fn record(&self, id: SurveyId) -> Option<&SurveyRecord> {
        self.records.get(&id).map(|r| &**r)
    }

    /// The record of the active survey read from `source`, if any.
    /// Not a damaged one: its file is to be ingested again.
    pub fn active_from(&self, source: &str) -> Option<&SurveyRecord> {
        self.stored_active_from(source)
            .filter(|r| !self.damaged.contains_key(&r.id))
    }

    /// The record of the active survey read from `source` as the store has it, a damaged one
    /// included.
    pub fn stored_active_from(&self, source: &str) -> Option<&SurveyRecord> {
        let from = (source.to_string(), SurveyId(0));
        let (s, id) = self.by_source.range(from..).next()?;
        (s == source).then(|| self.records.get(id).map(|r| &**r))?
    }

    /// How many surveys [`Catalog::active`] yields, without going through them.
    pub fn active_count(&self) -> usize {
        let damaged = self
            .damaged
            .keys()
            .filter(|id| {
                self.records
                    .get(id)
                    .is_some_and(|r| r.status == Status::Active)
            })
            .count();
        self.active_records - damaged
    }

    /// The active surveys the terrain holds, in id order: damaged ones are not among them.
    pub fn active(&self) -> impl Iterator<Item = &SurveyRecord> {
        self.records
            .values()
            .map(|r| &**r)
            .filter(|r| r.status == Status::Active && !self.damaged.contains_key(&r.id))
    }

    /// Puts a record in, in place of any of its id.
    fn put(&mut self, r: SurveyRecord) {
        self.take(r.id);
        if r.status == Status::Active {
            self.active_records += 1;
            self.by_source.insert((r.source.clone(), r.id));
        }
        self.records.insert(r.id, Arc::new(r));
    }

    /// Takes the record of `id` out, if there is one.
    fn take(&mut self, id: SurveyId) {
        let Some(old) = self.records.remove(&id) else {
            return;
        };
        if old.status == Status::Active {
            self.active_records -= 1;
            self.by_source.remove(&(old.source.clone(), id));
        }
    }
}

/// What [`Store::catalog`] keeps between calls: the catalog it last made, and the keys written
/// since (None: every key may have changed, and the next call reads them all).
#[derive(Default)]
pub(crate) struct CatalogCache {
    made: Option<Catalog>,
    touched: Option<BTreeSet<sled::IVec>>,
}

impl CatalogCache {
    /// Notes keys a write changed.
    pub(crate) fn touched<'a>(&mut self, keys: impl IntoIterator<Item = &'a sled::IVec>) {
        if let Some(t) = self.touched.as_mut() {
            t.extend(keys.into_iter().cloned());
        }
    }

    /// Forgets the catalog: a write whose keys are not known (a compaction, a replica's
    /// catch-up).
    pub(crate) fn forget(&mut self) {
        *self = CatalogCache::default();
    }
}

/// A file that could not be ingested. The inbox leaves it alone until its content changes;
/// size and mtime are what it had, for listings.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FailedRecord {
    /// The file's path, as the inbox names it.
    pub source: String,
    /// Why it could not be ingested.
    pub error: String,
    /// The file's size in bytes; 0 when unknown.
    pub size: u64,
    /// The file's modification time, in Unix seconds; 0 when unknown.
    pub mtime_unix: u64,
    /// When the failure was recorded, in Unix seconds.
    pub at_unix: u64,
    /// Hex blake3 of the bytes that failed; empty when they could not be read (or the
    /// failure was recorded before the store kept it), which matches no file.
    pub content_id: String,
}

impl Store {
    /// The files whose surveys were retired by hand, with the content that stays retired.
    pub fn pins(&self) -> Result<HashMap<String, String>, StoreError> {
        self.db
            .scan_prefix(keys::PIN_PREFIX)
            .map(|kv| {
                let (k, v) = kv?;
                let source = String::from_utf8_lossy(&k[keys::PIN_PREFIX.len()..]).into_owned();
                let content = String::from_utf8(v.to_vec()).map_err(|_| {
                    StoreError::from(Corruption::Unreadable {
                        what: format!("the pin of {source:?}"),
                        why: "not text".into(),
                    })
                })?;
                Ok((source, content))
            })
            .collect()
    }

    /// Every pair's evidence, once each (under its smaller id's key).
    pub fn all_pairs(&self) -> Result<Vec<Arc<PairEvidence>>, StoreError> {
        let mut out = Vec::new();
        for kv in self.db.scan_prefix(keys::OVERLAP_PREFIX) {
            let (k, v) = kv?;
            let (a, b) = keys::parse_overlap(&k).ok_or_else(|| {
                StoreError::from(Corruption::Key {
                    kind: "overlap",
                    key: String::from_utf8_lossy(&k).into_owned(),
                })
            })?;
            if a < b {
                let p: form::Pair =
                    decode(&v, &format!("overlap {}", String::from_utf8_lossy(&k)))?;
                out.push(Arc::new(p.into()));
            }
        }
        Ok(out)
    }

    /// The records, failures and pins as they stand. After the first call, only what was
    /// written since is read again: the records under the keys the writes touched, and the
    /// failures or pins if any of theirs was.
    pub fn catalog(&self) -> Result<Catalog, StoreError> {
        let mut cache = lock(&self.catalog);
        let (Some(made), Some(touched)) = (cache.made.take(), cache.touched.take()) else {
            let mut c = Catalog::default();
            for r in self.surveys()? {
                c.put(r);
            }
            c.failures = self.failures()?;
            c.pins = self.pins()?;
            let c = self.with_meta(c);
            *cache = CatalogCache {
                made: Some(c.clone()),
                touched: Some(BTreeSet::new()),
            };
            return Ok(c);
        };
        let mut c = made;
        let (mut failures, mut pins) = (false, false);
        for k in &touched {
            if let Some(id) = keys::parse_survey(k) {
                let what = format!("record {}", String::from_utf8_lossy(k));
                // As the full read takes them: a record that does not decode under its own
                // key is left out (it is among the damaged).
                match self.db.get(k)?.map(|v| decode::<SurveyRecord>(&v, &what)) {
                    Some(Ok(r)) if r.id == id => c.put(r),
                    _ => c.take(id),
                }
            } else if k.starts_with(keys::FAILURE_PREFIX) {
                failures = true;
            } else if k.starts_with(keys::PIN_PREFIX) {
                pins = true;
            }
        }
        if failures {
            c.failures = self.failures()?;
        }
        if pins {
            c.pins = self.pins()?;
        }
        let c = self.with_meta(c);
        #[cfg(debug_assertions)]
        {
            // What the full read gives, in builds with their checks on (the tests').
            let full: Vec<SurveyRecord> = self.surveys()?;
            assert!(
                full.len() == c.records.len()
                    && full.iter().zip(c.records.values()).all(|(a, b)| a == &**b),
                "the catalog kept between writes differs from the store's records"
            );
            assert_eq!(c.failures, self.failures()?, "failures kept between writes");
            assert_eq!(c.pins, self.pins()?, "pins kept between writes");
            assert_eq!(
                c.active_count(),
                c.active().count(),
                "active records counted"
            );
        }
        *cache = CatalogCache {
            made: Some(c.clone()),
            touched: Some(BTreeSet::new()),
        };
        Ok(c)
    }

    /// `c` with what the store keeps beside its records.
    fn with_meta(&self, c: Catalog) -> Catalog {
        Catalog {
            damaged: self.damaged(),
            crs: self.crs(),
            vertical: self.vertical_crs(),
            layout: self.layout,
            recipe: self.recipe,
            ..c
        }
    }

    /// Every survey record, active and retired, in id order; a record that does not decode is
    /// left out (it is among [`Store::damaged`]).
    pub fn surveys(&self) -> Result<Vec<SurveyRecord>, StoreError> {
        Ok(self.records()?.0)
    }

    /// Every record that decodes under its own key, and, by the id in their key, the surveys
    /// whose records do not: one scan, each record decoded once.
    pub(super) fn records(&self) -> Result<(Vec<SurveyRecord>, Vec<Damaged>), StoreError> {
        let (mut good, mut bad) = (Vec::new(), Vec::new());
        for kv in self.db.scan_prefix(keys::SURVEY_PREFIX) {
            let (k, v) = kv?;
            let what = format!("record {}", String::from_utf8_lossy(&k));
            let Some(id) = keys::parse_survey(&k) else {
                continue;
            };
            match decode::<SurveyRecord>(&v, &what) {
                Ok(r) if r.id == id => good.push(r),
                Ok(r) => bad.push(Damaged {
                    id,
                    reason: format!("{what} holds the record of {}", r.id),
                    source: r.source,
                }),
                Err(e) => bad.push(Damaged {
                    id,
                    source: String::new(),
                    reason: e.to_string(),
                }),
            }
        }
        Ok((good, bad))
    }

    /// The evidence of every pair `id` is in, by the other's id.
    pub fn pairs_of(&self, id: SurveyId) -> Result<Vec<PairEvidence>, StoreError> {
        self.db
            .scan_prefix(keys::overlaps_of(id))
            .map(|kv| {
                let (k, v) = kv?;
                decode::<form::Pair>(&v, &format!("overlap {}", String::from_utf8_lossy(&k)))
                    .map(PairEvidence::from)
            })
            .collect()
    }

    /// Every recorded failure, in source order.
    pub fn failures(&self) -> Result<Vec<FailedRecord>, StoreError> {
        self.db
            .scan_prefix(keys::FAILURE_PREFIX)
            .map(|kv| {
                let (k, v) = kv?;
                decode(&v, &format!("failure {}", String::from_utf8_lossy(&k)))
            })
            .collect()
    }

    pub(super) fn active_records(&self) -> Result<Vec<SurveyRecord>, StoreError> {
        let mut all = self.surveys()?;
        all.retain(|r| r.status == Status::Active && !self.is_damaged(r.id));
        Ok(all)
    }

    pub(super) fn record(&self, id: SurveyId) -> Result<Option<SurveyRecord>, StoreError> {
        self.db
            .get(keys::survey(id))?
            .map(|v| decode(&v, &format!("record of survey {id}")))
            .transpose()
    }
}
