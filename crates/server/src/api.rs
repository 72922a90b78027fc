//! Requests to replies: the dispatcher between the API and the engine. The gRPC handlers run
//! these on a blocking thread; the CLI's `--data-dir` mode calls them directly.

use super::convert;
use super::door::{self, MeshAsk};
use super::proto as pb;
use patchwork_core::index::query::Extracted;
use patchwork_core::resample::{Cancel, BLOCK};
use patchwork_core::terrain::Terrain;
use patchwork_engine::{
    BadRequest, Camera, Ctx, Cut, Engine, EngineError, Origin, SampleRequest, TileRequest, TooLarge,
};
use patchwork_store::StoreError;
use prost::Message;
use std::path::Path;

/// How many patches go in a batch: as the client asks, else [`BATCH`].
pub fn batch_size(asked: u32) -> usize {
    if asked == 0 {
        BATCH
    } else {
        asked as usize
    }
}

/// Patches in a batch when the client does not say.
pub const BATCH: usize = 256;

/// What the client of a view session holds: the patches of its cut, each with what of it can
/// change while its id stays and its size on the wire; the patches it keeps beyond the cut
/// (`ViewCut.cache_bytes`), evicted by the rule both sides follow; and the last cameras, from
/// which the next are predicted. The cut is at most one cut's worth, so `limits.max_patches`
/// bounds it; the cache is bounded by the client's own bytes.
#[derive(Debug, Default)]
pub struct ViewSession {
    held: std::collections::HashMap<patchwork_core::model::ids::PatchId, (Held, u64)>,
    cache: Kept,
    frame: u64,
    /// The last two cameras, eye and look, the latest last.
    cameras: Vec<([f64; 3], [f64; 3])>,
}

/// The parts of a sent patch that are the cut's rather than the patch's: whether it is a
/// fallback, and its box in LOD space, whose top comes down when a more accurate survey
/// arrives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Held {
    fallback: bool,
    span: [u64; 2],
}

impl Held {
    fn of(x: &Extracted) -> Self {
        Held {
            fallback: x.fallback,
            span: [x.span.min_z.to_bits(), x.span.max_z.to_bits()],
        }
    }
}

/// The client's cache as the server follows it: patches in the order they were put in, the
/// least recent evicted first until the rest fit (the rule `ViewDelta` states for clients).
#[derive(Clone, Debug, Default)]
struct Kept {
    by_id: std::collections::HashMap<patchwork_core::model::ids::PatchId, (u64, Held, u64)>,
    order: std::collections::BTreeMap<u64, patchwork_core::model::ids::PatchId>,
    bytes: u64,
    next: u64,
}

impl Kept {
    fn put(&mut self, id: patchwork_core::model::ids::PatchId, held: Held, bytes: u64) {
        self.take(id);
        self.by_id.insert(id, (self.next, held, bytes));
        self.order.insert(self.next, id);
        self.next += 1;
        self.bytes += bytes;
    }

    fn take(&mut self, id: patchwork_core::model::ids::PatchId) -> Option<(Held, u64)> {
        let (seq, held, bytes) = self.by_id.remove(&id)?;
        self.order.remove(&seq);
        self.bytes -= bytes;
        Some((held, bytes))
    }

    fn holds(&self, id: patchwork_core::model::ids::PatchId, held: Held) -> bool {
        self.by_id.get(&id).is_some_and(|k| k.1 == held)
    }

    fn fit(&mut self, most: u64) {
        while self.bytes > most {
            let Some((_, id)) = self.order.pop_first() else {
                break;
            };
            let (_, _, bytes) = self.by_id.remove(&id).expect("kept in both");
            self.bytes -= bytes;
        }
    }
}

/// About the most bytes of patches in one message of a view session (past it, the message
/// ends with the patch that crossed it). Small, since an unread session holds a few messages
/// (the one made ahead, the one in its channel, the one the connection is encoding): about a
/// megabyte, where a step of 256-patch messages held three or four and a whole step of a
/// large store is tens.
const MESSAGE_BYTES: u64 = 256 << 10;

/// Frames ahead the cameras are predicted.
const AHEAD: usize = 3;

impl ViewSession {
    /// The messages that take the client from what it holds to the cut for `v`, all at once:
    /// [`ViewSession::begin`], every message of the step, then [`ViewSession::finish`]. What
    /// the session holds changes only once the step is made whole, so a step that fails
    /// leaves it as the client has it.
    pub fn step(
        &mut self,
        engine: &Engine,
        v: &pb::ViewCut,
    ) -> Result<Vec<pb::ViewDelta>, EngineError> {
        let mut step = self.begin(engine, v)?;
        let mut deltas = Vec::new();
        while let Some(d) = step.next(engine)? {
            deltas.push(d);
        }
        self.finish(step);
        Ok(deltas)
    }

    /// A step to the cut for `v`: the cut, and what of it the client holds already or can take
    /// back from its cache. No patch is read yet: [`Step::next`] makes the messages one at a
    /// time, so that a client that stops reading costs the messages it has not taken, not the
    /// whole cut's samples.
    pub fn begin(&self, engine: &Engine, v: &pb::ViewCut) -> Result<Step, EngineError> {
        let camera = Camera::try_from(v)?;
        let (t, ps) = engine.query(&Cut::View(camera))?;
        let next: std::collections::HashMap<_, _> =
            ps.iter().map(|x| (x.id, Held::of(x))).collect();
        let mut removed: Vec<_> = self
            .held
            .iter()
            .filter(|(id, f)| next.get(id) != Some(&f.0))
            .map(|(id, f)| (*id, *f))
            .collect();
        removed.sort_unstable_by_key(|r| r.0 .0);
        // The client's cache after the removed patches join it, as the client keeps it: a
        // copy, kept only once the step is whole.
        let mut cache = self.cache.clone();
        if v.cache_bytes > 0 {
            for (id, (held, bytes)) in &removed {
                cache.put(*id, *held, *bytes);
            }
        }
        let mut held = std::collections::HashMap::with_capacity(next.len());
        let mut restored = Vec::new();
        let mut added: Vec<Extracted> = Vec::new();
        for x in ps {
            let h = next[&x.id];
            if let Some(&(had, bytes)) = self.held.get(&x.id) {
                if had == h {
                    held.insert(x.id, (h, bytes));
                    continue;
                }
            }
            if cache.holds(x.id, h) {
                let (_, bytes) = cache.take(x.id).expect("held");
                restored.push(x.id.0);
                held.insert(x.id, (h, bytes));
            } else {
                added.push(x);
            }
        }
        let cameras = {
            let mut c = self.cameras.clone();
            c.push(([v.eye_x, v.eye_y, v.eye_z], [v.look_x, v.look_y, v.look_z]));
            let n = c.len();
            c.split_off(n.saturating_sub(2))
        };
        Ok(Step {
            v: *v,
            frame: self.frame,
            t,
            first: Some((removed.iter().map(|r| r.0 .0).collect(), restored)),
            added: added.into_iter(),
            prefetch: None,
            held,
            cache,
            cameras,
            pending: None,
            done: false,
        })
    }

    /// Takes on what `step` left the client holding, once its last message is made: the
    /// cut, the cache as the client evicts it, and the camera.
    pub fn finish(&mut self, mut step: Step) {
        debug_assert!(
            step.done,
            "a step is finished once its last message is made"
        );
        step.cache.fit(step.v.cache_bytes);
        self.held = step.held;
        self.cache = step.cache;
        self.cameras = step.cameras;
        self.frame += 1;
    }
}

/// One step of a view session under way, whose messages are made as they are taken: the
/// patches still to send are ids and boxes until their message is made, so that what an unread
/// step holds is its plan and at most one message ahead of the client.
pub struct Step {
    v: pb::ViewCut,
    frame: u64,
    t: std::sync::Arc<Terrain>,
    /// `removed` and `restored`, for the step's first message.
    first: Option<(Vec<u64>, Vec<u64>)>,
    /// The cut's patches the client lacks, in id order.
    added: std::vec::IntoIter<Extracted>,
    /// The predicted cameras' patches: begun once the added ones are all sent, since what the
    /// client will hold then decides them.
    prefetch: Option<Prefetch>,
    held: std::collections::HashMap<patchwork_core::model::ids::PatchId, (Held, u64)>,
    cache: Kept,
    cameras: Vec<([f64; 3], [f64; 3])>,
    /// The message made ahead of the one given out, which tells whether that one is the last.
    pending: Option<pb::ViewDelta>,
    done: bool,
}

impl Step {
    /// The step's next message, None once its last (the one with `last` set) is out.
    pub fn next(&mut self, engine: &Engine) -> Result<Option<pb::ViewDelta>, EngineError> {
        if self.done {
            return Ok(None);
        }
        let current = match self.pending.take() {
            Some(m) => m,
            None => self.make(engine)?.expect("a step has one message at least"),
        };
        match self.make(engine)? {
            Some(following) => {
                self.pending = Some(following);
                Ok(Some(current))
            }
            None => {
                self.done = true;
                Ok(Some(pb::ViewDelta {
                    last: true,
                    patches: self.held.len() as u32,
                    ..current
                }))
            }
        }
    }

    /// Whether the step's last message is made.
    pub fn done(&self) -> bool {
        self.done
    }

    /// Makes the message after those made: up to [`BATCH`] added patches or
    /// [`MESSAGE_BYTES`] of them, else as many prefetched ones; the first message is made even
    /// when it carries nothing but the frame.
    fn make(&mut self, engine: &Engine) -> Result<Option<pb::ViewDelta>, EngineError> {
        let first = self.first.take();
        let mut d = pb::ViewDelta {
            frame: self.frame,
            ..Default::default()
        };
        let opening = first.is_some();
        let mut bytes = 0u64;
        if let Some((removed, restored)) = first {
            d.removed = removed;
            d.restored = restored;
        }
        for x in self.added.by_ref() {
            // One the snapshot no longer has (never, the cut being of that snapshot) is not
            // held, and so asked for again.
            if let Some(p) = convert::patch(&self.t, &x).map_err(StoreError::from)? {
                // An older copy in the client's cache leaves it, as the client drops it.
                self.cache.take(x.id);
                let n = p.encoded_len() as u64;
                self.held.insert(x.id, (Held::of(&x), n));
                bytes += n;
                d.added.push(p);
            }
            if d.added.len() == BATCH || bytes >= MESSAGE_BYTES {
                break;
            }
        }
        if d.added.is_empty() && self.v.cache_bytes > 0 && self.v.prefetch_bytes > 0 {
            let todo = self
                .prefetch
                .get_or_insert_with(|| Prefetch::new(&self.v, &self.cameras));
            while d.prefetched.len() < BATCH && bytes < MESSAGE_BYTES {
                let Some((t, x)) = todo.next(engine, &self.held, &self.cache)? else {
                    break;
                };
                let Some(p) = convert::patch(&t, &x).map_err(StoreError::from)? else {
                    continue;
                };
                let n = p.encoded_len() as u64;
                if todo.bytes + n > self.v.prefetch_bytes {
                    // The budget is spent: nothing more is prefetched this step.
                    todo.spent = true;
                    break;
                }
                todo.bytes += n;
                bytes += n;
                self.cache.put(x.id, Held::of(&x), n);
                d.prefetched.push(p);
            }
        }
        let empty = d.added.is_empty() && d.prefetched.is_empty();
        Ok((opening || !empty).then_some(d))
    }
}

/// A step's prefetch under way: the predicted cameras not cut yet, and of the one cut last
/// the patches the client has neither in its cut nor in its cache, nearest frame first. A
/// camera is cut only once the patches of the one before are used up, so that a budget the
/// first fills costs one cut, not [`AHEAD`].
struct Prefetch {
    cameras: std::vec::IntoIter<Camera>,
    t: Option<std::sync::Arc<Terrain>>,
    todo: std::vec::IntoIter<Extracted>,
    seen: std::collections::HashSet<patchwork_core::model::ids::PatchId>,
    /// Bytes of patches prefetched, within `ViewCut.prefetch_bytes`.
    bytes: u64,
    /// Whether the next patch found no room: nothing more is prefetched.
    spent: bool,
}

impl Prefetch {
    /// The cameras predicted after `cameras` (the last two, the latest last): the motion from
    /// one to the next goes on, the eye at the same velocity, the view turning about the
    /// vertical at the same rate. With fewer than two cameras, none.
    fn new(v: &pb::ViewCut, cameras: &[([f64; 3], [f64; 3])]) -> Prefetch {
        let mut ahead = Vec::new();
        if let [(e1, l1), (e2, l2)] = *cameras {
            let vel = [e2[0] - e1[0], e2[1] - e1[1], e2[2] - e1[2]];
            let (d1, d2) = (
                [l1[0] - e1[0], l1[1] - e1[1], l1[2] - e1[2]],
                [l2[0] - e2[0], l2[1] - e2[1], l2[2] - e2[2]],
            );
            let turn = {
                let w = d2[1].atan2(d2[0]) - d1[1].atan2(d1[0]);
                (w + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI)
                    - std::f64::consts::PI
            };
            for k in 1..=AHEAD {
                let kf = k as f64;
                let (s, c) = (kf * turn).sin_cos();
                let eye = [
                    e2[0] + kf * vel[0],
                    e2[1] + kf * vel[1],
                    e2[2] + kf * vel[2],
                ];
                let d = [d2[0] * c - d2[1] * s, d2[0] * s + d2[1] * c, d2[2]];
                let look = [eye[0] + d[0], eye[1] + d[1], eye[2] + d[2]];
                ahead.extend(Camera::new(eye, look, v.fov_deg, v.viewport_px, v.pixel_error).ok());
            }
        }
        Prefetch {
            cameras: ahead.into_iter(),
            t: None,
            todo: Vec::new().into_iter(),
            seen: Default::default(),
            bytes: 0,
            spent: false,
        }
    }

    /// The next patch to weigh, with the snapshot it was cut from; None once the cameras are
    /// used up or the budget spent. The client holds what `held` and `cache` say, and every
    /// patch given out before (which `seen` keeps out).
    fn next(
        &mut self,
        engine: &Engine,
        held: &std::collections::HashMap<patchwork_core::model::ids::PatchId, (Held, u64)>,
        cache: &Kept,
    ) -> Result<Option<(std::sync::Arc<Terrain>, Extracted)>, EngineError> {
        while !self.spent {
            if let Some(x) = self.todo.next() {
                return Ok(Some((self.t.clone().expect("cut with its patches"), x)));
            }
            let Some(camera) = self.cameras.next() else {
                break;
            };
            let (t, ps) = engine.query(&Cut::View(camera))?;
            let seen = &mut self.seen;
            let todo: Vec<Extracted> = ps
                .into_iter()
                .filter(|x| {
                    let h = Held::of(x);
                    held.get(&x.id).is_none_or(|k| k.0 != h)
                        && !cache.holds(x.id, h)
                        && seen.insert(x.id)
                })
                .collect();
            self.todo = todo.into_iter();
            self.t = Some(t);
        }
        Ok(None)
    }
}

/// The client's side of a view session: its cut and its cache, kept by the rule `ViewDelta`
/// states, from the messages alone. What a Rust client runs, and what the tests and the bench
/// hold the server's bookkeeping to.
#[derive(Debug, Default)]
pub struct ViewClient {
    /// The patches of the cut, by id.
    pub cut: std::collections::HashMap<u64, pb::Patch>,
    cache: std::collections::HashMap<u64, (u64, pb::Patch)>,
    order: std::collections::BTreeMap<u64, u64>,
    bytes: u64,
    next: u64,
    /// The cache's size, bytes: `ViewCut.cache_bytes` as sent.
    pub cache_bytes: u64,
}

impl ViewClient {
    /// A client keeping `cache_bytes` of patches beyond its cut.
    pub fn new(cache_bytes: u64) -> ViewClient {
        ViewClient {
            cache_bytes,
            ..ViewClient::default()
        }
    }

    fn put(&mut self, p: pb::Patch) {
        self.take(p.id);
        self.bytes += p.encoded_len() as u64;
        self.order.insert(self.next, p.id);
        self.cache.insert(p.id, (self.next, p));
        self.next += 1;
    }

    fn take(&mut self, id: u64) -> Option<pb::Patch> {
        let (seq, p) = self.cache.remove(&id)?;
        self.order.remove(&seq);
        self.bytes -= p.encoded_len() as u64;
        Some(p)
    }

    /// Whether the patch is here, in the cut or the cache.
    pub fn has(&self, id: u64) -> bool {
        self.cut.contains_key(&id) || self.cache.contains_key(&id)
    }

    /// Bytes of patches in the cache.
    pub fn cached_bytes(&self) -> u64 {
        self.bytes
    }

    /// Applies one message of a step (`first` for the step's first).
    pub fn apply(&mut self, d: &pb::ViewDelta, first: bool) -> Result<(), String> {
        if first {
            for id in &d.removed {
                let p = self
                    .cut
                    .remove(id)
                    .ok_or_else(|| format!("patch {id:016x} removed but never held"))?;
                if self.cache_bytes > 0 {
                    self.put(p);
                }
            }
            for id in &d.restored {
                let p = self
                    .take(*id)
                    .ok_or_else(|| format!("patch {id:016x} restored but not in the cache"))?;
                self.cut.insert(*id, p);
            }
        }
        for p in &d.added {
            self.take(p.id);
            self.cut.insert(p.id, p.clone());
        }
        for p in &d.prefetched {
            self.put(p.clone());
        }
        if d.last {
            while self.bytes > self.cache_bytes {
                let Some((_, id)) = self.order.pop_first() else {
                    break;
                };
                let (_, p) = self.cache.remove(&id).expect("kept in both");
                self.bytes -= p.encoded_len() as u64;
            }
        }
        Ok(())
    }
}

/// One batch of a patch query, samples read.
pub fn patch_batch(t: &Terrain, ps: &[Extracted]) -> Result<pb::PatchBatch, EngineError> {
    let patches = ps
        .iter()
        .filter_map(|x| convert::patch(t, x).transpose())
        .collect::<Result<_, _>>()
        .map_err(StoreError::from)?;
    Ok(pb::PatchBatch { patches })
}

/// Every batch of a patch query at once: for callers in the same process.
pub fn query_patches(
    engine: &Engine,
    r: &pb::PatchQuery,
) -> Result<Vec<pb::PatchBatch>, EngineError> {
    let (t, ps) = engine.query(&door::patch_cut(r)?)?;
    ps.chunks(batch_size(r.batch_size))
        .map(|c| patch_batch(&t, c))
        .collect()
}

/// A resampled tile.
pub fn resample_tile(
    engine: &Engine,
    r: &TileRequest,
    cancel: &Cancel,
) -> Result<pb::Tile, EngineError> {
    let (tile, used, frame) = engine.tile(r, Ctx::until(cancel))?;
    Ok(convert::tile(
        &tile,
        used,
        &frame,
        tile_crs(engine, &r.cut).as_ref(),
    ))
}

/// The tile of [`resample_tile`] as bands of f32 bytes, each handed to `send` as soon as it
/// is resampled; `send` says whether to go on.
pub fn tile_bands(
    engine: &Engine,
    r: &TileRequest,
    cancel: &Cancel,
    send: &mut dyn FnMut(pb::TileBand) -> bool,
) -> Result<(), EngineError> {
    let crs = tile_crs(engine, &r.cut);
    // Whole blocks of the resampler in a band where a band holds that many rows.
    let rows = convert::band_rows(r.size.width() as usize);
    let rows = if rows >= BLOCK {
        rows / BLOCK * BLOCK
    } else {
        rows
    };
    let frame = engine.frame_of(&r.heights);
    engine.tile_bands(r, Ctx::until(cancel), rows, &mut |head, row, heights| {
        convert::tile_bands(head, row, &heights, crs.as_ref(), &frame)
            .into_iter()
            .all(&mut *send)
    })?;
    Ok(())
}

/// The CRS a cut's tile is in: the request's, else the store's.
fn tile_crs(engine: &Engine, cut: &Cut) -> Option<patchwork_core::crs::Crs> {
    cut.crs().cloned().or_else(|| engine.crs())
}

/// A mesh of a uniform cut.
pub fn mesh_tile(engine: &Engine, r: &MeshAsk, cancel: &Cancel) -> Result<pb::Mesh, EngineError> {
    let m = engine.mesh(&r.spec, r.backend, Ctx::until(cancel))?;
    let crs = r.spec.crs.clone().or_else(|| engine.crs());
    Ok(convert::mesh(&m, crs.as_ref()))
}

/// Heights at points.
pub fn sample_heights(
    engine: &Engine,
    r: &SampleRequest,
    cancel: &Cancel,
) -> Result<pb::Samples, EngineError> {
    let s = engine.sample(r, Ctx::until(cancel))?;
    Ok(pb::Samples {
        valid: s.heights.iter().map(|z| u8::from(!z.is_nan())).collect(),
        vertical_crs: convert::vertical_key(&s.frame),
        frame_error_m: s.frame.error_m,
        sources: s
            .sources
            .iter()
            .map(|x| x.as_ref().map(convert::source).unwrap_or_default())
            .collect(),
        heights: s.heights,
    })
}

/// The surveys a tile's cut used, with their shares.
pub fn tile_sources(
    engine: &Engine,
    r: &TileRequest,
    cancel: &Cancel,
) -> Result<pb::TileSourceList, EngineError> {
    let shares = engine.tile_sources(r, Ctx::until(cancel))?;
    Ok(pb::TileSourceList {
        samples: shares.iter().map(|s| s.samples).sum(),
        sources: shares
            .iter()
            .map(|s| pb::SourceShare {
                source: Some(convert::source(&s.source)),
                samples: s.samples,
                share: s.share,
            })
            .collect(),
    })
}

/// Longest path or id a request may carry: PATH_MAX on Linux.
const MAX_PATH_BYTES: usize = 4096;

fn check_path(what: &'static str, p: &str) -> Result<(), BadRequest> {
    if p.is_empty() || p.len() > MAX_PATH_BYTES || p.contains('\0') {
        return Err(BadRequest::Path {
            what,
            most: MAX_PATH_BYTES,
        });
    }
    Ok(())
}

/// Ingests the files in order. A file's own problem is its result; a storage failure (a full
/// disk) fails the call, and the files before it stay ingested.
pub fn ingest(engine: &Engine, r: &pb::IngestRequest) -> Result<pb::IngestReply, EngineError> {
    if let Some(a) = r.accuracy_m {
        patchwork_engine::Metres::new("accuracy", a)?;
    }
    let most = engine.config().limits.max_ingest_paths;
    if r.paths.len() as u64 > most {
        return Err(TooLarge::IngestPaths {
            n: r.paths.len() as u64,
            max: most,
        }
        .into());
    }
    for p in &r.paths {
        check_path("a path", p)?;
    }
    let results = r
        .paths
        .iter()
        .map(|p| {
            engine
                .ingest(Path::new(p), r.accuracy_m, Origin::Request)
                .map(|i| convert::ingested(&i))
        })
        .collect::<Result<_, _>>()?;
    Ok(pb::IngestReply { results })
}

/// Every survey, failed file and held file, all of one commit.
pub fn list_surveys(engine: &Engine) -> Result<pb::SurveyList, EngineError> {
    let (terrain, listing) = engine.surveys();
    Ok(convert::surveys(&terrain, &listing))
}

/// Removes the failure recorded for a source, so that the inbox tries its file again;
/// NOT_FOUND when none is recorded.
pub fn forget(engine: &Engine, r: &pb::ForgetRequest) -> Result<pb::ForgetReply, EngineError> {
    check_path("the source", &r.source)?;
    if !engine.forget(&r.source)? {
        return Err(EngineError::NoFailure(r.source.clone()));
    }
    Ok(pb::ForgetReply {})
}

/// Retires a survey named by id or source; its id and how many patches went with it.
pub fn retire(engine: &Engine, r: &pb::RetireRequest) -> Result<pb::RetireReply, EngineError> {
    check_path("the id or source", &r.id_or_source)?;
    let (id, patches) = engine.retire(&r.id_or_source)?;
    Ok(pb::RetireReply {
        id: id.to_string(),
        patches: patches as u32,
    })
}

/// The store's and the engine's counts; the server adds its own of the requests.
pub fn stats(engine: &Engine) -> Result<pb::StatsReply, EngineError> {
    Ok(convert::stats(&engine.stats()))
}

/// Re-checks the whole store; the problems found go in the reply, not in an error.
pub fn verify(engine: &Engine) -> Result<pb::VerifyReply, EngineError> {
    let v = engine.verify()?;
    Ok(pb::VerifyReply {
        ok: v.problems.is_empty(),
        problems: v.problems.clone(),
        surveys: v.active as u32,
        patches: v.patches as u64,
    })
}

/// Drops every damaged survey for good, so that the inbox ingests their files afresh; the
/// surveys dropped.
pub fn repair(engine: &Engine) -> Result<pb::RepairReply, EngineError> {
    let dropped = engine.repair()?;
    Ok(pb::RepairReply {
        dropped: dropped
            .into_iter()
            .map(|d| pb::DroppedSurvey {
                id: d.id.to_string(),
                source: d.source,
                reason: d.reason,
            })
            .collect(),
    })
}

/// Removes retired surveys for good and rewrites the store's files; the sizes before and
/// after.
pub fn compact(engine: &Engine) -> Result<pb::CompactReply, EngineError> {
    let c = engine.compact()?;
    Ok(pb::CompactReply {
        bytes_before: c.bytes_before,
        bytes_after: c.bytes_after,
        surveys_removed: c.surveys_purged as u32,
    })
}
