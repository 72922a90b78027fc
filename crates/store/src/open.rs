//! Opening a store: its lock, sled, migrations, and what the index is restored from, with
//! every survey checked and a damaged one left out; and reading surveys back.

use super::*;

/// Runs `f`, turning a panic into its message without printing it (the default hook would
/// print a backtrace over the message the caller gives instead).
pub(super) fn quietly<T>(f: impl FnOnce() -> T + std::panic::UnwindSafe) -> Result<T, String> {
    thread_local!(static QUIET: std::cell::Cell<bool> = const { std::cell::Cell::new(false) });
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(|q| q.get()) {
                previous(info);
            }
        }));
    });
    QUIET.with(|q| q.set(true));
    let r = std::panic::catch_unwind(f);
    QUIET.with(|q| q.set(false));
    r.map_err(|p| {
        p.downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| p.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "a panic".into())
    })
}

/// What to do about sled's own files being damaged: a snapshot file can go (sled rebuilds it
/// from its log); otherwise the directory must come back from a backup.
pub(super) fn damaged_database(dir: &Path, what: &str) -> StoreError {
    let snaps: Vec<String> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("snap."))
        .collect();
    let advice = if snaps.is_empty() {
        format!(
            "restore {} from a backup (the chunk pack beside it cannot be read without it)",
            dir.display()
        )
    } else {
        format!(
            "first move {} out of {} and open again (sled rebuilds its snapshot from its log); \
             if that does not help, restore the directory from a backup",
            snaps.join(", "),
            dir.display()
        )
    };
    Corruption::Files {
        dir: dir.to_path_buf(),
        what: what.lines().next().unwrap_or(what).to_string(),
        advice,
    }
    .into()
}

/// Opens sled's database in `dir`, once this process holds `<dir>.lock`. Holding it means no
/// other handle is open, so a lock that sled still finds held belongs to a handle of this
/// process that was just dropped: sled releases its lock from a background thread, a moment
/// later. Waiting a little for that is safe; waiting on another process never happens here.
pub(super) fn open_sled(dir: &Path, cache_bytes: u64) -> Result<sled::Db, StoreError> {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    loop {
        match sled::Config::new()
            .path(dir)
            .cache_capacity(cache_bytes)
            .open()
        {
            Ok(db) => return Ok(db),
            Err(sled::Error::Io(io))
                if is_lock_error(&io) && std::time::Instant::now() < deadline =>
            {
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
            Err(e) => return Err(open_error(e, dir)),
        }
    }
}

/// How long taking `<dir>.lock` waits on a holder before saying the store is locked.
///
/// A flock belongs to the open file, and a child process shares its parent's open files from
/// its fork until its exec closes them: a handle that this process has just closed can stay
/// locked for as long as a child that another thread spawns takes to reach its exec (rarely
/// more than milliseconds, seen to last long enough on a loaded machine for a compaction that
/// failed to lose its reopen). A second daemon on the store still hears "locked", this much
/// later.
const LOCK_WAIT: std::time::Duration = std::time::Duration::from_secs(2);

/// Takes the exclusive lock that keeps other processes (and other handles in this one) out.
pub(super) fn lock_dir(dir: &Path) -> Result<File, StoreError> {
    lock_dir_within(dir, LOCK_WAIT)
}

fn lock_dir_within(dir: &Path, wait: std::time::Duration) -> Result<File, StoreError> {
    let path = sibling(dir, ".lock")?;
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent)?;
    }
    let f = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)?;
    let deadline = std::time::Instant::now() + wait;
    loop {
        match f.try_lock_exclusive() {
            Ok(()) => return Ok(f),
            Err(e) if is_lock_error(&e) && std::time::Instant::now() < deadline => {
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
            Err(e) if is_lock_error(&e) => {
                return Err(StoreError::Locked {
                    dir: dir.to_path_buf(),
                })
            }
            Err(e) => return Err(e.into()),
        }
    }
}

impl Store {
    /// Opens or creates the store at `dir`, recovering from an interrupted compaction and
    /// running migrations, and reads what the index is restored from (see [`Contents`]; the
    /// terrain is built by the engine's `restore`).
    ///
    /// `layout` and `index` only apply to a fresh store: an existing one keeps the settings its
    /// surveys were built and indexed with (see [`Store::layout`], [`Store::index_config`]).
    pub fn open(dir: &Path, layout: PatchLayout, index: IndexConfig) -> Result<Loaded, StoreError> {
        Self::open_with(dir, layout, index, StoreOptions::default())
    }

    /// [`Store::open`] under the given space rules. On a disk too full to write, the store
    /// opens all the same (releasing its reserve file if that is what it takes), and every
    /// write is refused with [`StoreError::Full`] until space returns.
    pub fn open_with(
        dir: &Path,
        layout: PatchLayout,
        index: IndexConfig,
        opts: impl Into<StoreOptions>,
    ) -> Result<Loaded, StoreError> {
        let dir = std::path::absolute(dir)?;
        let lock = lock_dir(&dir)?;
        let opts = opts.into();
        // sled panics on some damage to its own files (a database file cut short) where it
        // returns an error on other damage: both end here, as one message that says what to do.
        let opened = quietly(std::panic::AssertUnwindSafe(|| {
            Self::open_locked(dir.clone(), lock, layout, index, opts)
        }));
        let mut opened = match opened {
            Ok(Err(StoreError::Sled(sled::Error::Corruption { .. }))) => {
                return Err(damaged_database(
                    &dir,
                    "sled read data that fails its checksum",
                ))
            }
            Ok(Err(StoreError::Sled(sled::Error::ReportableBug(why)))) => {
                return Err(damaged_database(&dir, &why))
            }
            Ok(r) => r?,
            Err(panic) => return Err(damaged_database(&dir, &panic)),
        };
        if opened.released_reserve {
            opened.warnings.push(
                "the disk was full: the store's reserve file was released so that it could open"
                    .into(),
            );
        }
        Ok(opened)
    }

    pub(super) fn open_locked(
        dir: PathBuf,
        lock: File,
        layout: PatchLayout,
        index: IndexConfig,
        opts: StoreOptions,
    ) -> Result<Loaded, StoreError> {
        compact::recover(&dir)?;
        let guard = opts.guard.clone();
        let released_reserve = guard.release_if_full(&dir)?;
        let db = open_sled(&dir, opts.sled_cache_bytes())?;
        // A replica's database is the writer's as published: filled from the newest snapshot
        // and the logs after it before anything below reads it.
        let follower = match &opts.backend {
            ChunkBackend::Follow(o) => {
                let pack = Arc::new(objects::ObjectPack::follow(o.clone())?);
                let f = journal::Follower::start(pack, &db, &dir)?;
                let v = migrate::version(&db)?;
                if v != migrate::CURRENT {
                    return Err(StoreError::ReplicaSchema {
                        url: o.url.clone(),
                        found: v,
                        supported: migrate::CURRENT,
                    });
                }
                Some(f)
            }
            _ => None,
        };
        if migrate::version(&db)? < migrate::CURRENT && db.get(keys::SCHEMA)?.is_some() {
            // A migration rewrites much of the store; refuse it on a full disk rather than
            // let sled run out of space halfway.
            guard.check(&dir, db.size_on_disk()?)?;
        }
        let committed = match db.get(keys::PACK_LEN)? {
            None => 0,
            Some(v) => u64::from_le_bytes(v.as_ref().try_into().map_err(|_| {
                StoreError::from(Corruption::Length {
                    key: "meta/pack_len",
                    len: v.len(),
                    expected: 8,
                })
            })?),
        };
        let (pack, objects): (Arc<dyn ChunkStore>, _) = match &follower {
            Some(f) => (f.pack(), None),
            None => open_pack(&db, &dir, committed, &opts.backend)?,
        };
        let migrated = match follower {
            Some(_) => Vec::new(),
            None => migrate::migrate(
                &db,
                &migrate::Ctx {
                    layout,
                    index,
                    pack: pack.as_ref(),
                },
            )?,
        };
        if let ChunkBackend::Objects(o) = &opts.backend {
            // After the migration, which makes a fresh store from an empty tree: from now on
            // the store names the place, and no other store may take it.
            if db.get(keys::PACK_AT)?.is_none() {
                db.insert(keys::PACK_AT, o.url.as_bytes())?;
                db.flush()?;
            }
        }
        let get = |k: &[u8]| -> Result<sled::IVec, StoreError> {
            db.get(k)?.ok_or_else(|| {
                StoreError::from(Corruption::Missing(String::from_utf8_lossy(k).into_owned()))
            })
        };
        let layout: PatchLayout =
            decode::<form::Layout>(&get(keys::LAYOUT)?, "meta/layout")?.into();
        let index: IndexConfig = decode::<form::Index>(&get(keys::INDEX)?, "meta/index")?.into();
        let recipe = recipe_of(&db, &dir, &guard, opts.recipe)?;
        let contradicted = setting_of(&db, &dir, &guard, opts.contradicted)?;
        let blend = setting_of(&db, &dir, &guard, opts.blend)?;
        let crs = (
            db.get(keys::CRS)?
                .map(|v| decode_crs(&v, "meta/crs", Crs::parse))
                .transpose()?,
            db.get(keys::VERTICAL_CRS)?
                .map(|v| decode_crs(&v, "meta/vertical_crs", VerticalCrs::parse))
                .transpose()?,
        );
        let replication = match (follower, objects) {
            (Some(f), _) => Replication::Follower(f),
            // Last, once the database is whole: its first snapshot is what replicas start from.
            (None, Some(pack)) => {
                Replication::Writer(journal::Journal::open(pack, &db, opts.snapshot_every)?)
            }
            (None, None) => Replication::None,
        };
        let assemble = |db: sled::Db, replication: Replication, lock: File| {
            let reader = Arc::new(ChunkReader::new(
                (*db).clone(),
                pack.clone(),
                opts.cache_bytes,
            ));
            Store {
                db,
                pack: pack.clone(),
                _close_reader: CloseReader(reader.clone()),
                reader,
                opts: opts.clone(),
                guard: guard.clone(),
                dir: dir.clone(),
                layout,
                index,
                recipe,
                contradicted,
                blend,
                catalog: Default::default(),
                crs: RwLock::new(crs.clone()),
                migrated: migrated.clone(),
                damaged: RwLock::new(BTreeMap::new()),
                replication,
                _lock: lock,
            }
        };
        // The load reads every record of the store once. sled evicts from its cache only once
        // 64 reads have queued on one of its 256 shards, so those pages would stay in memory
        // whatever the cache's size: 2.3 kB a survey at 10,000, more than the index's own
        // share. The load runs on a first start of the database, and the store serves from a
        // second one, whose cache holds nothing yet.
        let first = assemble(db, Replication::None, lock.try_clone()?);
        let contents = first.load()?;
        // Once every chunk was read back, the pack marks it beside itself: a write to the
        // database here kept 3.5 MB that sled let go of but never returned (docs/SCALE.md).
        first.pack.note_checked();
        let damaged = read(&first.damaged).clone();
        // The catalog too, which the engine asks for next: it reads every record again.
        first.catalog()?;
        let catalog = std::mem::take(&mut *super::lock(&first.catalog));
        first.db.flush()?;
        drop(first);
        let store = assemble(open_sled(&dir, opts.sled_cache_bytes())?, replication, lock);
        *write(&store.damaged) = damaged;
        *super::lock(&store.catalog) = catalog;
        let mut warnings = Vec::new();
        if store.pack.lost() > 0 {
            warnings.push(format!(
                "{} holds {} bytes fewer than were committed: the surveys whose bytes are gone \
                 are damaged",
                store.pack.describe(),
                store.pack.lost()
            ));
        }
        warnings.extend(contents.damaged.iter().map(Damaged::to_string));
        if let Err(e) = store.guard.restore(&store.dir) {
            warnings.push(format!("could not make the reserve file: {e}"));
        }
        Ok(Loaded {
            store,
            contents,
            warnings,
            released_reserve,
        })
    }

    /// What the index needs of the active surveys, the edge patches and the box states; no
    /// sample is decoded. Every active survey's records are decoded and its chunks checked
    /// against their checksums: a damaged one is left out (see [`Damaged`]), and the index is
    /// derived again without it unless the stored one already leaves out just these.
    pub(super) fn load(&self) -> Result<Contents, StoreError> {
        let (active, unreadable) = self.records()?;
        let mut damaged: BTreeMap<SurveyId, Damaged> =
            unreadable.into_iter().map(|d| (d.id, d)).collect();
        let left_out = self.quarantined()?;
        let checked_to = self.checked_to()?;
        // The reads and the chunk check run in parallel (on an object store each read is a
        // request); the metadata the index keeps is decoded here, on this thread. Decoded on
        // the workers, between their reads, it left each worker's malloc arena with holes it
        // could not give back: 5.5 kB a survey resident at 10,000 surveys, 4.9 kB decoded here.
        let checked: Vec<(&SurveyRecord, Result<Vec<u8>, String>)> = active
            .par_iter()
            .filter(|r| r.status == Status::Active)
            .map(|r| {
                // A survey found damaged is read whole again: its damage is in what was
                // checked, and it must be found again to stay left out.
                let skip = if left_out.contains(&r.id) {
                    0
                } else {
                    checked_to
                };
                Ok((r, self.load_checked(r, skip)?))
            })
            .collect::<Result<_, StoreError>>()?;
        let mut surveys = Vec::with_capacity(checked.len());
        for (r, patches) in checked {
            let meta = match patches {
                Err(reason) => Err(reason),
                Ok(p) => match self.meta_of(r, &p) {
                    Ok((m, _)) => Ok(m),
                    Err(e @ (StoreError::Corrupt(_) | StoreError::Decode { .. })) => {
                        Err(e.to_string())
                    }
                    Err(e) => return Err(e),
                },
            };
            match meta {
                Ok(m) => surveys.push(Arc::new(m)),
                Err(reason) => {
                    damaged.insert(
                        r.id,
                        Damaged {
                            id: r.id,
                            source: r.source.clone(),
                            reason,
                        },
                    );
                }
            }
        }
        let rebuild = self.db.get(keys::REBUILD)?.is_some()
            || !damaged.keys().copied().eq(left_out.iter().copied());
        let found: Vec<Damaged> = damaged.values().cloned().collect();
        *write(&self.damaged) = damaged;
        // A store to be rebuilt may hold tops of an older format, or tops of an index with a
        // survey now damaged: they are replaced, never read.
        if rebuild {
            return Ok(Contents {
                surveys,
                pairs: Vec::new(),
                edges: Vec::new(),
                tops: HashMap::new(),
                rebuild: true,
                damaged: found,
            });
        }
        Ok(Contents {
            surveys,
            pairs: self.all_pairs()?,
            edges: self.edges()?,
            tops: self.states()?,
            rebuild: false,
            damaged: found,
        })
    }

    /// How far into the local pack earlier opens read every chunk back: the pack's mark
    /// ([`pack::CHECKED_FILE`]), or where a store from before it has none, the database's
    /// [`keys::CHECKED_TO`], which is read and never written now. 0 where an open must read
    /// them all: on an object store (which reads none), or where the pack lost bytes.
    fn checked_to(&self) -> Result<u64, StoreError> {
        if !self.pack.local() || self.pack.lost() > 0 {
            return Ok(0);
        }
        if let Some(at) = self.pack.checked_to() {
            return Ok(at);
        }
        Ok(self
            .db
            .get(keys::CHECKED_TO)?
            .and_then(|v| <[u8; 8]>::try_from(v.as_ref()).ok())
            .map_or(0, u64::from_le_bytes)
            .min(self.pack.len()))
    }

    /// A survey's meta, once its records decode and every chunk it should have is there and
    /// matches its checksum (a local chunk that ends at or before `skip` was checked by an
    /// earlier open, and is not read again); otherwise what is wrong. Only an error of the
    /// database itself is an `Err`.
    pub(super) fn load_checked(
        &self,
        r: &SurveyRecord,
        skip: u64,
    ) -> Result<Result<Vec<u8>, String>, StoreError> {
        let patches = match self.read_patches(r.id) {
            Ok(p) => p,
            Err(e @ (StoreError::Corrupt(_) | StoreError::Decode { .. })) => {
                return Ok(Err(e.to_string()))
            }
            Err(e) => return Err(e),
        };
        let mut locs: HashMap<(usize, usize), sled::IVec> = HashMap::new();
        for kv in self.db.scan_prefix(keys::chunks_of(r.id)) {
            let (k, v) = kv?;
            if let Some((_, level, n)) = keys::parse_chunk(&k) {
                locs.insert((level, n), v);
            }
        }
        for (level, h) in r.levels.iter().enumerate() {
            let [nx, ny] = chunks::chunk_counts(&h.shape());
            for k in 0..nx * ny {
                let what = || format!("chunk {k} of level {level}");
                let Some(v) = locs.get(&(level, k)) else {
                    return Ok(Err(format!("{} is missing", what())));
                };
                let Some(loc) = pack::Loc::from_bytes(v) else {
                    return Ok(Err(format!(
                        "{}: its location is {} bytes",
                        what(),
                        v.len()
                    )));
                };
                if !self.pack.local() {
                    // Over a network, reading every chunk back would fetch the whole store:
                    // each read and `verify` check the checksums instead.
                    if !self.pack.holds(loc) {
                        return Ok(Err(format!(
                            "{}: its bytes ({}..{}) are in no segment of {}",
                            what(),
                            loc.offset,
                            loc.end(),
                            self.pack.describe()
                        )));
                    }
                    continue;
                }
                if loc.end() <= skip {
                    continue;
                }
                let bytes = match self.pack.read(loc) {
                    Ok(b) => b,
                    Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => {
                        return Ok(Err(format!(
                            "{}: its bytes ({}..{}) are past the end of the pack",
                            what(),
                            loc.offset,
                            loc.end()
                        )))
                    }
                    Err(e) => return Err(e.into()),
                };
                if let Err(e) = chunks::intact(&bytes) {
                    return Ok(Err(format!("{}: {e}", what())));
                }
            }
        }
        Ok(Ok(patches))
    }

    /// The ids the stored index was derived without.
    pub(super) fn quarantined(&self) -> Result<Vec<SurveyId>, StoreError> {
        match self.db.get(keys::QUARANTINED)? {
            None => Ok(Vec::new()),
            Some(v) => Ok(decode::<Vec<u64>>(&v, "meta/quarantined")?
                .into_iter()
                .map(SurveyId)
                .collect()),
        }
    }

    /// The damaged surveys, as the last open found them less those healed or dropped since.
    pub fn damaged(&self) -> BTreeMap<SurveyId, Damaged> {
        read(&self.damaged).clone()
    }

    pub(super) fn is_damaged(&self, id: SurveyId) -> bool {
        read(&self.damaged).contains_key(&id)
    }

    /// Every active survey whole, samples and all: what deriving the index again needs.
    pub fn whole_surveys(&self) -> Result<Vec<Arc<Survey>>, StoreError> {
        self.active_records()?
            .par_iter()
            .map(|r| self.load_survey(r).map(Arc::new))
            .collect()
    }

    pub(super) fn states(&self) -> Result<HashMap<PatchId, BoxState>, StoreError> {
        let mut out = HashMap::new();
        for kv in self.db.scan_prefix(keys::BOXES_PREFIX) {
            let (k, v) = kv?;
            let unit = keys::parse_boxes(&k).ok_or_else(|| {
                StoreError::from(Corruption::Key {
                    kind: "boxes",
                    key: String::from_utf8_lossy(&k).into_owned(),
                })
            })?;
            out.extend(decode_states(&v, &format!("the boxes of unit {unit}"))?);
        }
        Ok(out)
    }

    /// Every stored edge patch.
    pub(super) fn edges(&self) -> Result<Vec<Arc<EdgePatch>>, StoreError> {
        let mut out = Vec::new();
        for kv in self.db.scan_prefix(keys::EDGE_PREFIX) {
            let (k, v) = kv?;
            let id = keys::parse_edge(&k).ok_or_else(|| {
                StoreError::from(Corruption::Key {
                    kind: "edge",
                    key: String::from_utf8_lossy(&k).into_owned(),
                })
            })?;
            let e = decode_edge(&v, &format!("edge patch {id}"))?;
            out.push(Arc::new(e));
        }
        Ok(out)
    }

    /// A survey's patches and edge tiles, from the pack.
    #[doc(hidden)]
    pub fn load_patches(&self, id: SurveyId) -> Result<StoredPatches, StoreError> {
        decode_patches(id, &self.read_patches(id)?)
    }

    /// The encoded form of a survey's patches and edge tiles, read from the pack and unsealed.
    fn read_patches(&self, id: SurveyId) -> Result<Vec<u8>, StoreError> {
        let unreadable = |why: String| Corruption::Unreadable {
            what: format!("the patches of survey {id}"),
            why,
        };
        let sealed = chunks::read_packed(&self.db, self.pack.as_ref(), &keys::patches(id))
            .map_err(|e| unreadable(e.to_string()))?;
        Ok(chunks::unseal(&sealed, MAX_RECORD_BYTES).map_err(unreadable)?)
    }

    /// One whole level's samples from its chunks.
    pub(super) fn load_level(
        &self,
        id: SurveyId,
        level: usize,
        h: &LevelHeader,
    ) -> Result<Grid, StoreError> {
        let shape = h.shape();
        if shape.cols < 2 || shape.rows < 2 {
            return Err(Corruption::LevelShape {
                survey: id,
                level,
                cols: shape.cols,
                rows: shape.rows,
            }
            .into());
        }
        self.reader
            .read(id, level, &shape, shape.all())
            .map_err(|e| {
                Corruption::Unreadable {
                    what: format!("level {level} of survey {id}"),
                    why: e.to_string(),
                }
                .into()
            })
    }

    /// A survey without its samples, from its record, the encoded form of its patches, and
    /// its accuracies; and its patches' δ, which the survey in memory does not keep.
    fn meta_of(
        &self,
        r: &SurveyRecord,
        patches: &[u8],
    ) -> Result<(SurveyMeta, Vec<f64>), StoreError> {
        let stored = decode_patches(r.id, patches)?;
        if let Some(p) = stored
            .patches
            .iter()
            .find(|p| p.survey != r.id.0 || p.level as usize >= r.levels.len())
        {
            return Err(Corruption::ForeignPatch {
                survey: r.id,
                patch: PatchId(p.id),
                of: SurveyId(p.survey),
                level: p.level as usize,
            }
            .into());
        }
        let Some(l0) = r.levels.first() else {
            return Err(Corruption::NoLevels(r.id).into());
        };
        let shape0 = l0.shape();
        if shape0.cols < 2 || shape0.rows < 2 {
            return Err(Corruption::LevelShape {
                survey: r.id,
                level: 0,
                cols: shape0.cols,
                rows: shape0.rows,
            }
            .into());
        }
        let tiling = Tiling::new(shape0.cells(), self.layout.kernel, r.tiling_offset);
        let kernel_accuracy = match r.spec() {
            AccuracySpec::Fixed(a) => KernelAccuracy::constant(&tiling, a),
            AccuracySpec::Auto => {
                let v = self.db.get(keys::accuracy(r.id))?.ok_or_else(|| {
                    StoreError::from(Corruption::Missing(format!(
                        "the accuracies of survey {}",
                        r.id
                    )))
                })?;
                let k: KernelAccuracy =
                    decode::<form::Accuracies>(&v, &format!("accuracies of survey {}", r.id))?
                        .into();
                if k.dims != tiling.counts() {
                    return Err(Corruption::Accuracies {
                        survey: r.id,
                        have: k.dims,
                        want: tiling.counts(),
                    }
                    .into());
                }
                k
            }
        };
        use patchwork_core::model::patch::CellRect;
        type Placed = ([u32; 2], CellRect, CellRect, [f64; 2], [f64; 2]);
        let windows: Vec<Placed> = stored
            .patches
            .iter()
            .map(|p| (p.index, p.kernel.into(), p.window.into(), p.centre, p.half))
            .collect();
        let deltas: Vec<f64> = stored.patches.iter().map(|p| p.delta).collect();
        let mut meta = SurveyMeta {
            id: r.id,
            accuracy: kernel_accuracy.max(),
            spec: r.spec(),
            crs: r.crs.clone(),
            vertical: r.vertical.clone(),
            placement: None,
            // Every survey of a store was placed in it before it was committed.
            placed_in: self.crs().or_else(|| r.crs.clone()),
            layout: self.layout,
            kind: self.recipe.patches,
            tiling,
            kernel_accuracy,
            shapes: r.levels.iter().map(LevelHeader::shape).collect(),
            patches: Arc::from([]),
            raised: None,
            edge_tiles: stored.edge_tiles,
            // From what its sidecar (or its file) said, as recorded; a text that is no date
            // was refused at ingest, and one from an older store gives no epoch.
            epoch: r
                .about
                .acquired
                .as_deref()
                .and_then(|a| Epoch::parse(a).ok()),
        };
        // A patch in memory keeps its place in its level's tiling, row-major, for which the
        // tiling's row is needed.
        let rows: Vec<u32> = (0..r.levels.len())
            .map(|l| meta.level_tiling(l).counts()[0] as u32)
            .collect();
        meta.patches = stored
            .patches
            .into_iter()
            .map(|p| {
                let (id, nx) = (PatchId(p.id), rows[p.level as usize]);
                p.into_patch(nx).ok_or_else(|| {
                    StoreError::from(Corruption::PatchWindow {
                        survey: r.id,
                        patch: id,
                    })
                })
            })
            .collect::<Result<_, _>>()?;
        // The patches in memory leave their kernels' cells, their windows and the windows'
        // centres and half sides to the survey: those stored must be the ones it gives.
        let half = meta.half();
        if let Some(p) = (meta.patches.iter().zip(&windows))
            .find(|(p, &(index, kernel, window, centre, h))| {
                meta.kernel_index(p) != index
                    || meta.kernel(p) != kernel
                    || meta.window(p) != window
                    || meta.centre(p) != centre
                    || h != half
            })
            .map(|(p, _)| p)
        {
            return Err(Corruption::PatchWindow {
                survey: r.id,
                patch: p.id,
            }
            .into());
        }
        Ok((meta, deltas))
    }

    /// A whole survey, samples and all: what deriving the index again and `verify` need.
    pub(super) fn load_survey(&self, r: &SurveyRecord) -> Result<Survey, StoreError> {
        let (meta, deltas) = self.meta_of(r, &self.read_patches(r.id)?)?;
        let levels: Vec<Arc<Grid>> = r
            .levels
            .iter()
            .enumerate()
            .map(|(k, h)| self.load_level(r.id, k, h).map(Arc::new))
            .collect::<Result<_, _>>()?;
        let meta = Arc::new(meta);
        Ok(Survey {
            meta,
            levels,
            deltas: deltas.into(),
        })
    }
}

/// The chunk pack of the backend the store was made with: refused when the options name
/// another. On an object store, the segments compaction let go of go once their grace period
/// has passed.
/// The pack a writer opens, and the same as an object store's, which also carries the
/// journal.
type Opened = (Arc<dyn ChunkStore>, Option<Arc<objects::ObjectPack>>);

fn open_pack(
    db: &sled::Db,
    dir: &Path,
    committed: u64,
    backend: &ChunkBackend,
) -> Result<Opened, StoreError> {
    let at = db
        .get(keys::PACK_AT)?
        .map(|v| String::from_utf8_lossy(&v).into_owned());
    let o = match (backend, at.as_deref()) {
        (ChunkBackend::Local, None) => {
            return Ok((Arc::new(pack::PackFile::open(dir, committed)?), None))
        }
        (ChunkBackend::Follow(_), _) => unreachable!("a replica's pack is its follower's"),
        (ChunkBackend::Local, Some(url)) => {
            return Err(StoreError::Backend {
                stored: url.to_string(),
                configured: "the local pack (backend \"local\")".into(),
            })
        }
        (ChunkBackend::Objects(o), Some(url)) if url != o.url => {
            return Err(StoreError::Backend {
                stored: url.to_string(),
                configured: o.url.clone(),
            })
        }
        (ChunkBackend::Objects(o), None) if committed > 0 => {
            return Err(StoreError::Backend {
                stored: dir.join(pack::PACK_FILE).display().to_string(),
                configured: o.url.clone(),
            })
        }
        (ChunkBackend::Objects(o), _) => o,
    };
    let pack = objects::ObjectPack::open(o.clone(), committed, at.is_some())?;
    if let Some(v) = db.get(keys::PACK_BASE)? {
        let (base, since) = decode_base(&v)?;
        if now_unix() >= since.saturating_add(o.grace.as_secs()) {
            pack.collect_below(base)?;
        }
    }
    let pack = Arc::new(pack);
    Ok((pack.clone(), Some(pack)))
}

/// `meta/pack_base` for an address space that ends at `base`, left behind now.
/// A survey's patches and edge tiles from their encoded form.
fn decode_patches(id: SurveyId, v: &[u8]) -> Result<StoredPatches, StoreError> {
    decode(v, &format!("the patches of survey {id}"))
}

pub(super) fn encode_base(base: u64) -> Vec<u8> {
    let mut v = base.to_le_bytes().to_vec();
    v.extend_from_slice(&now_unix().to_le_bytes());
    v
}

/// `meta/pack_base`: where the address space compaction left behind ends, and when.
pub(super) fn decode_base(v: &[u8]) -> Result<(u64, u64), StoreError> {
    let b: [u8; 16] = v.try_into().map_err(|_| {
        StoreError::from(Corruption::Length {
            key: "meta/pack_base",
            len: v.len(),
            expected: 16,
        })
    })?;
    Ok((
        u64::from_le_bytes(b[..8].try_into().expect("8 bytes")),
        u64::from_le_bytes(b[8..].try_into().expect("8 bytes")),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A copy of the lock's open file, as a child process holds one between its fork and its
    /// exec, keeps the lock held after this process closed its own handle: the next open waits
    /// for it rather than calling the store locked.
    #[test]
    fn a_lock_held_a_moment_by_a_copy_of_the_handle_is_waited_for() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("store");
        let first = lock_dir(&dir).unwrap();
        let child = first.try_clone().unwrap();
        drop(first);
        let exec = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(150));
            drop(child);
        });
        let started = std::time::Instant::now();
        let again = lock_dir(&dir).expect("taken once the copy closes");
        assert!(started.elapsed() >= std::time::Duration::from_millis(100));
        exec.join().unwrap();

        // A holder that stays is still refused, once the wait is over.
        let err = lock_dir_within(&dir, std::time::Duration::from_millis(60)).unwrap_err();
        assert!(matches!(err, StoreError::Locked { .. }), "{err}");
        drop(again);
    }
}
