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

/// What the client of a view session holds: the patches it was sent, each with what of it
/// can change while its id stays. At most one cut's worth, so `limits.max_patches` bounds it.
#[derive(Debug, Default)]
pub struct ViewSession {
    held: std::collections::HashMap<patchwork_core::model::ids::PatchId, Held>,
    frame: u64,
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

impl ViewSession {
    /// The messages that take the client from what it holds to the cut for `v`. What the
    /// session holds changes only once the step is made whole, so a step that fails leaves it
    /// as the client has it.
    pub fn step(
        &mut self,
        engine: &Engine,
        v: &pb::ViewCut,
    ) -> Result<Vec<pb::ViewDelta>, EngineError> {
        let camera = Camera::try_from(v)?;
        let (t, ps) = engine.query(&Cut::View(camera))?;
        let next: std::collections::HashMap<_, _> =
            ps.iter().map(|x| (x.id, Held::of(x))).collect();
        let mut removed: Vec<u64> = self
            .held
            .iter()
            .filter(|(id, f)| next.get(id) != Some(f))
            .map(|(id, _)| id.0)
            .collect();
        removed.sort_unstable();
        let added: Vec<Extracted> = ps
            .into_iter()
            .filter(|x| self.held.get(&x.id) != next.get(&x.id))
            .collect();
        let mut deltas = Vec::with_capacity(added.len().div_ceil(BATCH).max(1));
        for chunk in added.chunks(BATCH) {
            deltas.push(pb::ViewDelta {
                frame: self.frame,
                added: patch_batch(&t, chunk)?.patches,
                ..Default::default()
            });
        }
        if deltas.is_empty() {
            deltas.push(pb::ViewDelta {
                frame: self.frame,
                ..Default::default()
            });
        }
        deltas[0].removed = removed;
        let last = deltas.last_mut().expect("one message at least");
        last.last = true;
        last.patches = next.len() as u32;
        self.held = next;
        self.frame += 1;
        Ok(deltas)
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
