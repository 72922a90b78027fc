//! Writing the store: one change of the terrain in one batch ([`Store::commit`]), the
//! derived index, failures and pins, repair. Every write takes `&mut Store`: the one writer
//! the engine holds is the only one the compiler allows.

use super::*;

/// A sled batch that knows how many bytes it writes, so that the disk can be asked first.
#[derive(Default)]
pub(super) struct Writes {
    batch: sled::Batch,
    bytes: u64,
    /// The keys written or removed, for the commit's log (see [`super::journal`]).
    touched: Vec<sled::IVec>,
}

/// One change of the terrain, as [`Store::commit`] writes it in one batch.
#[derive(Default)]
pub struct Change<'a> {
    /// The survey going out, if any.
    pub retire: Option<Retirement<'a>>,
    /// The survey coming in, if any: with `retire`, it replaces that one.
    pub insert: Option<Insertion<'a>>,
    /// The edge patches the new terrain holds among the boxes the change moved.
    pub edges: &'a [Arc<EdgePatch>],
}

/// A survey going out of the terrain. Its samples stay until [`Store::compact`].
pub struct Retirement<'a> {
    /// The survey: its boxes' states go with it.
    pub id: SurveyId,
    /// What retiring it from the terrain changed.
    pub change: &'a ChangeStats,
    /// Whether its file, should it stay where it is, is kept from bringing it back (see
    /// [`Store::pins`]).
    pub pin: bool,
}

/// A survey coming into the terrain.
pub struct Insertion<'a> {
    /// The survey, as built and placed in the store's CRS.
    pub survey: &'a Survey,
    /// Its record.
    pub record: &'a SurveyRecord,
    /// What inserting it into the terrain changed (other surveys' tops among it).
    pub change: &'a ChangeStats,
    /// The evidence of its overlaps with the surveys already there.
    pub pairs: &'a [Arc<PairEvidence>],
    /// Its chunks, already in the pack.
    pub packed: Packed,
}

/// A survey's chunks and patch list, appended to the pack and synced but not yet committed:
/// the commit that follows points the database at them (see [`Store::pack_survey`]).
pub struct Packed {
    survey: SurveyId,
    entries: Vec<(Vec<u8>, pack::Loc)>,
}

impl Writes {
    pub(super) fn insert(&mut self, k: impl Into<sled::IVec>, v: impl Into<sled::IVec>) {
        let (k, v) = (k.into(), v.into());
        self.bytes += (k.len() + v.len()) as u64;
        self.touched.push(k.clone());
        self.batch.insert(k, v);
    }

    pub(super) fn remove(&mut self, k: impl Into<sled::IVec>) {
        let k = k.into();
        self.bytes += k.len() as u64;
        self.touched.push(k.clone());
        self.batch.remove(k);
    }
}

/// The writes a survey commit adds to a batch; kept so that the record can get its commit time.
pub(super) struct Staged {
    key: Vec<u8>,
    rec: SurveyRecord,
    crs: (Option<Crs>, Option<VerticalCrs>),
}

impl Store {
    /// Writes `meta/quarantined` as it stands once `healed` are no longer damaged; nothing
    /// when none of them was. Call [`Store::healed`] once the batch is applied.
    pub(super) fn stage_healed(
        &self,
        batch: &mut Writes,
        healed: &[SurveyId],
    ) -> Result<(), StoreError> {
        let damaged = read(&self.damaged);
        if !healed.iter().any(|id| damaged.contains_key(id)) {
            return Ok(());
        }
        let left: Vec<SurveyId> = damaged
            .keys()
            .copied()
            .filter(|id| !healed.contains(id))
            .collect();
        if left.is_empty() {
            batch.remove(keys::QUARANTINED);
        } else {
            batch.insert(keys::QUARANTINED, encode(&form::ids(&left))?);
        }
        Ok(())
    }

    pub(super) fn healed(&self, ids: &[SurveyId]) {
        let mut damaged = write(&self.damaged);
        for id in ids {
            damaged.remove(id);
        }
    }

    /// Drops every damaged survey for good, in one batch: its record, patches, accuracies,
    /// chunk locations and pairs (its bytes in the pack go at the next compaction). The index
    /// already leaves them out. Its file, if still in the inbox, is then ingested afresh.
    /// Returns what was dropped.
    pub fn repair(&mut self) -> Result<Vec<Damaged>, StoreError> {
        let damaged: Vec<Damaged> = self.damaged().into_values().collect();
        if damaged.is_empty() {
            return Ok(damaged);
        }
        let mut batch = Writes::default();
        for d in &damaged {
            batch.remove(keys::survey(d.id));
            batch.remove(keys::patches(d.id));
            batch.remove(keys::accuracy(d.id));
            for prefix in [keys::chunks_of(d.id), keys::overlaps_of(d.id)] {
                for kv in self.db.scan_prefix(prefix) {
                    let (k, _) = kv?;
                    if let Some((_, other)) = keys::parse_overlap(&k) {
                        batch.remove(keys::overlap(other, d.id));
                    }
                    batch.remove(k);
                }
            }
        }
        batch.remove(keys::QUARANTINED);
        self.apply(batch)?;
        let ids: Vec<SurveyId> = damaged.iter().map(|d| d.id).collect();
        self.healed(&ids);
        Ok(damaged)
    }

    /// Replaces every box state, edge patch and pair, in one batch: an index derived again
    /// from the surveys. Clears the mark that asked for it.
    pub fn write_derived(
        &mut self,
        units: &[(SurveyId, Vec<(PatchId, BoxState)>)],
        edges: &[Arc<EdgePatch>],
        pairs: &[Arc<PairEvidence>],
    ) -> Result<(), StoreError> {
        // Every edge record goes, so every edge patch must come whole.
        if let Some(e) = edges.iter().find(|e| e.grid.is_none()) {
            return Err(StoreError::Inconsistent {
                survey: e.owner,
                what: "an edge patch it owns holds no samples to write",
            });
        }
        let mut batch = Writes::default();
        for prefix in [keys::BOXES_PREFIX, keys::EDGE_PREFIX, keys::OVERLAP_PREFIX] {
            for kv in self.db.scan_prefix(prefix) {
                batch.remove(kv?.0);
            }
        }
        stage_pairs(&mut batch, pairs)?;
        for (unit, states) in units {
            batch.insert(keys::boxes(*unit), encode_states(states));
        }
        stage_edges(&mut batch, edges)?;
        batch.remove(keys::REBUILD);
        let left_out: Vec<SurveyId> = self.damaged().into_keys().collect();
        if left_out.is_empty() {
            batch.remove(keys::QUARANTINED);
        } else {
            batch.insert(keys::QUARANTINED, encode(&form::ids(&left_out))?);
        }
        self.apply(batch)
    }

    /// Adds a survey's writes to `batch`. The survey was placed in a store of some CRS (see
    /// [`SurveyMeta::placed_for`]): this store's, which the batch sets if the store had none,
    /// as it sets the vertical CRS the survey's heights are in. `replacing` is a survey the
    /// same batch retires, which may be this very one.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn stage_survey(
        &self,
        batch: &mut Writes,
        insertion: &Insertion<'_>,
        replacing: Option<SurveyId>,
    ) -> Result<Staged, StoreError> {
        let (s, rec, change, pairs, packed) = (
            insertion.survey,
            insertion.record,
            insertion.change,
            insertion.pairs,
            &insertion.packed,
        );
        if rec.id != s.id {
            return Err(StoreError::Inconsistent {
                survey: s.id,
                what: "the record given is another survey's",
            });
        }
        let headers: Vec<LevelHeader> = s.levels.iter().map(|g| LevelHeader::of(g)).collect();
        if rec.levels != headers
            || rec.accuracy.to_bits() != s.accuracy.to_bits()
            || rec.crs != s.crs
        {
            return Err(StoreError::Inconsistent {
                survey: s.id,
                what: "the record does not describe it (levels, accuracy or CRS differ)",
            });
        }
        if s.layout != self.layout {
            return Err(StoreError::Inconsistent {
                survey: s.id,
                what: "it is cut with another patch layout than the store's",
            });
        }
        if replacing != Some(s.id) {
            if let Some(old) = self.record(s.id)? {
                if old.status == Status::Active {
                    return Err(StoreError::Duplicate(s.id));
                }
            }
        }
        let (crs, vertical) = (self.crs(), self.vertical_crs());
        let crs = match (crs, s.placed_for()) {
            (Some(c), Some(placed)) if c != placed => {
                return Err(StoreError::CrsMismatch {
                    survey: s.id,
                    placed_in: placed.label(),
                    store_crs: c.label(),
                })
            }
            (None, Some(placed)) => {
                batch.insert(keys::CRS, placed.key().as_bytes());
                Some(placed)
            }
            (c, _) => c,
        };
        let vertical = match (vertical, &s.vertical) {
            (Some(v), Some(w)) if !v.same_reference(w) => {
                return Err(StoreError::VerticalMismatch {
                    survey: s.id,
                    survey_vertical: w.label(),
                    store_vertical: v.label(),
                })
            }
            (None, Some(w)) => {
                batch.insert(keys::VERTICAL_CRS, w.key().as_bytes());
                Some(w.clone())
            }
            (v, _) => v,
        };
        let crs = (crs, vertical);
        let mut rec = rec.clone();
        rec.status = Status::Active;
        let key = keys::survey(s.id);
        batch.insert(key.clone(), encode(&rec)?);
        if packed.survey != s.id {
            return Err(StoreError::Inconsistent {
                survey: s.id,
                what: "the chunks packed are another survey's",
            });
        }
        for (k, loc) in &packed.entries {
            batch.insert(k.clone(), &loc.to_bytes()[..]);
        }
        batch.insert(keys::PACK_LEN, &self.pack.len().to_le_bytes()[..]);
        if s.spec == AccuracySpec::Auto {
            batch.insert(
                keys::accuracy(s.id),
                encode(&form::Accuracies::from(&s.kernel_accuracy))?,
            );
        }
        stage_change(batch, change);
        stage_pairs(batch, pairs)?;
        batch.remove(keys::failure(&rec.source));
        batch.remove(keys::pin(&rec.source));
        Ok(Staged { key, rec, crs })
    }

    pub(super) fn stage_retire(
        &self,
        batch: &mut Writes,
        id: SurveyId,
        change: &ChangeStats,
    ) -> Result<SurveyRecord, StoreError> {
        let mut rec = match self.record(id)? {
            Some(r) if r.status == Status::Active => r,
            _ => return Err(StoreError::NotActive(id)),
        };
        rec.status = Status::Retired;
        batch.insert(keys::survey(id), encode(&rec)?);
        batch.remove(keys::boxes(id));
        stage_change(batch, change);
        for kv in self.db.scan_prefix(keys::overlaps_of(id)) {
            let (k, _) = kv?;
            if let Some((_, other)) = keys::parse_overlap(&k) {
                batch.remove(k);
                batch.remove(keys::overlap(other, id));
            }
        }
        Ok(rec)
    }

    /// Applies a batch and makes it durable before returning, once the disk has room for it.
    pub(super) fn apply(&self, batch: Writes) -> Result<(), StoreError> {
        self.apply_unpublished(batch)?;
        self.publish();
        Ok(())
    }

    /// Applies a batch, durably, and leaves its log for [`Store::publish`]: a commit adds its
    /// record's last write in between. On an object store the previous commit's log must be
    /// up first; while it cannot be, writes are refused as the object store being down.
    fn apply_unpublished(&self, mut batch: Writes) -> Result<(), StoreError> {
        self.guard.check(&self.dir, batch.bytes)?;
        let seq = match &self.replication {
            Replication::None => None,
            Replication::Writer(j) => {
                j.publish(&self.db)?;
                Some(j.stage(&mut batch.batch, &batch.touched)?)
            }
            Replication::Follower(f) => return Err(f.refusal()),
        };
        self.db.apply_batch(batch.batch)?;
        lock(&self.catalog).touched(&batch.touched);
        self.db.flush()?;
        if let (Some(seq), Replication::Writer(j)) = (seq, &self.replication) {
            j.applied(seq);
        }
        Ok(())
    }

    /// Publishes the newest commit's log for replicas if it is not up yet. The commit is
    /// durable whatever happens here: a failure is logged, the replicas wait, and the next
    /// write (or the daemon's next round) tries again.
    pub fn publish(&self) {
        if let Replication::Writer(j) = &self.replication {
            if let Err(e) = j.publish(&self.db) {
                tracing::warn!(error = %e, "a commit's log could not be published yet; replicas wait for it");
            }
        }
    }

    /// Records how long the commit took. The batch is already durable; should this small
    /// write be lost, the record keeps the caller's figure.
    pub(super) fn finish(&self, staged: Staged, t0: Instant) -> Result<(), StoreError> {
        *write(&self.crs) = staged.crs;
        let mut rec = staged.rec;
        rec.ingest.commit_ms = t0.elapsed().as_secs_f64() * 1e3;
        let key = sled::IVec::from(staged.key);
        self.db.insert(key.clone(), encode(&rec)?)?;
        lock(&self.catalog).touched([&key]);
        Ok(())
    }

    /// Encodes a survey's levels and its patch list and appends them to the pack, synced,
    /// once the disk has room: the part of a commit that needs no index work, so a caller can
    /// run it beside that work. Until a commit points at them the bytes are not the store's:
    /// an open cuts them, or a later commit leaves them as garbage for compaction.
    pub fn pack_survey(&self, s: &Survey) -> Result<Packed, StoreError> {
        let stored = StoredPatches::of(s);
        let mut entries_keys = vec![keys::patches(s.id)];
        let mut bytes = vec![chunks::seal(&encode(&stored)?)];
        for (level, g) in s.levels.iter().enumerate() {
            for (k, b) in chunks::encode_level(g) {
                entries_keys.push(keys::chunk(s.id, level, k));
                bytes.push(b);
            }
        }
        let total: usize = bytes.iter().map(Vec::len).sum();
        self.guard.check(&self.dir, total as u64)?;
        let locs = self.pack.append(&bytes)?;
        Ok(Packed {
            survey: s.id,
            entries: entries_keys.into_iter().zip(locs).collect(),
        })
    }

    /// Commits one change of the terrain in one batch, then flushes: a survey retired, one
    /// inserted (its chunks already packed: [`Store::pack_survey`]), or one replaced by the
    /// other, a file that changed. Every top the change moved is written, other surveys'
    /// among them; where a retirement and an insertion moved one box, the insertion's top wins,
    /// as it does in the terrain (a sled batch keeps the last write of a key). A failure
    /// leaves the store as it was, so the caller swaps in the terrain it computed the change
    /// with only on success.
    pub fn commit(&mut self, change: Change<'_>) -> Result<(), StoreError> {
        let t0 = Instant::now();
        let mut batch = Writes::default();
        let mut touched = Vec::with_capacity(2);
        if let Some(r) = &change.retire {
            let rec = self.stage_retire(&mut batch, r.id, r.change)?;
            if r.pin && !rec.content_id.is_empty() {
                batch.insert(keys::pin(&rec.source), rec.content_id.as_bytes());
            }
            touched.push(r.id);
        }
        let replacing = change.retire.as_ref().map(|r| r.id);
        let staged = match change.insert {
            Some(i) => {
                touched.push(i.survey.id);
                Some(self.stage_survey(&mut batch, &i, replacing)?)
            }
            None => None,
        };
        stage_edges(&mut batch, change.edges)?;
        self.stage_healed(&mut batch, &touched)?;
        self.apply_unpublished(batch)?;
        self.healed(&touched);
        let done = match staged {
            Some(staged) => self.finish(staged, t0),
            None => Ok(()),
        };
        self.publish();
        done
    }

    /// Records a file that could not be ingested, replacing any earlier record of the same
    /// path. When `keep` records are already there, the oldest go in the same batch: a client
    /// that sends thousands of bad paths cannot grow the store without bound.
    pub fn record_failure(&mut self, f: &FailedRecord, keep: usize) -> Result<(), StoreError> {
        let key = keys::failure(&f.source);
        let mut others: Vec<(u64, sled::IVec)> = Vec::new();
        for kv in self.db.scan_prefix(keys::FAILURE_PREFIX) {
            let (k, v) = kv?;
            if k.as_ref() != key.as_slice() {
                let old: FailedRecord = decode(&v, "failure")?;
                others.push((old.at_unix, k));
            }
        }
        let mut batch = Writes::default();
        if others.len() >= keep {
            others.sort();
            for (_, k) in others.drain(..=others.len() - keep.max(1)) {
                batch.remove(k);
            }
        }
        batch.insert(key, encode(f)?);
        self.apply(batch)
    }

    /// Removes the failure recorded for `source`; whether there was one.
    pub fn forget_failure(&mut self, source: &str) -> Result<bool, StoreError> {
        let key = keys::failure(source);
        if self.db.get(&key)?.is_none() {
            return Ok(false);
        }
        let mut batch = Writes::default();
        batch.remove(key);
        self.apply(batch)?;
        Ok(true)
    }

    /// Rewrites what an active survey's record says of where it came from, and the content
    /// id its file and sidecar now hash to: a sidecar whose title or licence changed leaves
    /// the samples, and so the survey, as they were.
    pub fn set_about(
        &mut self,
        id: SurveyId,
        about: &crate::form::About,
        content_id: &str,
    ) -> Result<(), StoreError> {
        let mut rec = match self.record(id)? {
            Some(r) if r.status == Status::Active => r,
            _ => return Err(StoreError::NotActive(id)),
        };
        if rec.about == *about && rec.content_id == content_id {
            return Ok(());
        }
        rec.about = about.clone();
        rec.content_id = content_id.to_string();
        let mut batch = Writes::default();
        batch.insert(keys::survey(id), encode(&rec)?);
        self.apply(batch)
    }

    /// Removes the failure recorded for `source`, if there is one.
    pub fn clear_failure(&mut self, source: &str) -> Result<(), StoreError> {
        if self.db.get(keys::failure(source))?.is_some() {
            self.forget_failure(source)?;
        }
        Ok(())
    }

    /// Drops the pin of `source`, whose file is gone.
    pub fn unpin(&mut self, source: &str) -> Result<(), StoreError> {
        let mut batch = Writes::default();
        batch.remove(keys::pin(source));
        self.apply(batch)
    }
}

/// The writes an index change calls for: the states of every unit a box of which it moved,
/// whole, the removal of the units it took out, and of the edge patches it removed.
pub(super) fn stage_change(batch: &mut Writes, change: &ChangeStats) {
    for id in &change.removed {
        batch.remove(keys::edge(*id));
    }
    for (unit, states) in &change.units {
        match states {
            Some(states) => batch.insert(keys::boxes(*unit), encode_states(states)),
            None => batch.remove(keys::boxes(*unit)),
        }
    }
}

/// Writes each pair's evidence under both its surveys' keys.
pub(super) fn stage_pairs(
    batch: &mut Writes,
    pairs: &[Arc<PairEvidence>],
) -> Result<(), StoreError> {
    for p in pairs {
        let v = encode(&form::Pair::from(p.as_ref()))?;
        batch.insert(keys::overlap(p.finer, p.coarser), v.clone());
        batch.insert(keys::overlap(p.coarser, p.finer), v);
    }
    Ok(())
}

/// The edge patches a commit leaves in place, written after every removal it stages: one
/// that a retirement removed and an insertion brought back is there, built again with its
/// samples. One whose samples the terrain let go of was read from the store, under its id,
/// which names what it holds: a change that moved its top leaves its record as it stands.
pub(super) fn stage_edges(batch: &mut Writes, edges: &[Arc<EdgePatch>]) -> Result<(), StoreError> {
    for e in edges {
        if let Ok(f) = form::Edge::try_from(e.as_ref()) {
            batch.insert(keys::edge(e.id), encode(&f)?);
        }
    }
    Ok(())
}
