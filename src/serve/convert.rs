//! Engine results as API messages. The server and the CLI's direct mode share these, so both
//! print the same thing.

use super::proto as pb;
use crate::engine::{
    Backend, Conflict, Cut, Engine, EngineError, Event, Ingested, Stats, SurveyListing, TileHead,
};
use crate::index::geom::Aabb;
use crate::index::query::Extracted;
use crate::model::grid::{Georef, SampleRect};
use crate::model::patch::CellRect;
use crate::model::source::SampleError;
use crate::store::Status;
use crate::terrain::{PatchRef, Terrain, Tile};

pub fn rect(b: &Aabb) -> pb::Rect {
    pb::Rect {
        xmin: b.min[0],
        ymin: b.min[1],
        xmax: b.max[0],
        ymax: b.max[1],
    }
}

pub fn aabb(r: &Option<pb::Rect>) -> Result<Aabb, EngineError> {
    let r = r
        .as_ref()
        .ok_or_else(|| EngineError::Invalid("the request needs a region (roi)".into()))?;
    Ok(Aabb::new(r.xmin, r.ymin, r.xmax, r.ymax))
}

pub fn uniform_cut(c: &pb::UniformCut) -> Result<Cut, EngineError> {
    Ok(Cut::Uniform {
        roi: aabb(&c.roi)?,
        error: c.error,
    })
}

pub fn view_cut(engine: &Engine, v: &pb::ViewCut) -> Result<Cut, EngineError> {
    Ok(Cut::View(engine.view_query(
        [v.eye_x, v.eye_y, v.eye_z],
        [v.look_x, v.look_y, v.look_z],
        v.fov_deg,
        v.viewport_px,
        v.pixel_error,
    )?))
}

pub fn backend(b: i32) -> Result<Backend, EngineError> {
    match pb::Backend::try_from(b) {
        Ok(pb::Backend::Auto) => Ok(Backend::Auto),
        Ok(pb::Backend::Cpu) => Ok(Backend::Cpu),
        Ok(pb::Backend::Gpu) => Ok(Backend::Gpu),
        Err(_) => Err(EngineError::Invalid(format!(
            "unknown backend {b}: use auto, cpu or gpu"
        ))),
    }
}

/// A patch with its window's samples, ready to send; None when the terrain no longer has it.
pub fn patch(t: &Terrain, x: &Extracted) -> Result<Option<pb::Patch>, SampleError> {
    let (georef, w, kernel, samples, flags, kind): (
        Georef,
        CellRect,
        CellRect,
        Vec<f32>,
        Vec<u8>,
        _,
    ) = match t.patch(x.id) {
        None => return Ok(None),
        Some(PatchRef::Survey(s, p)) => {
            let w = p.window;
            let rect = SampleRect {
                c0: w.c0 as usize,
                r0: w.r0 as usize,
                c1: w.c1 as usize + 1,
                r1: w.r1 as usize + 1,
            };
            let level = t.window(s, p.level as usize, rect)?;
            let mut samples = Vec::with_capacity(rect.len());
            for r in rect.r0..rect.r1 {
                let start = (r - level.r0) * level.grid.cols + (rect.c0 - level.c0);
                samples.extend_from_slice(&level.grid.samples[start..start + rect.cols()]);
            }
            (
                level.level.georef,
                w,
                p.kernel,
                samples,
                Vec::new(),
                pb::PatchKind::Bilinear,
            )
        }
        Some(PatchRef::Edge(e)) => (
            e.grid.georef,
            e.window,
            e.kernel,
            e.grid.heights.clone(),
            e.grid.flags.clone(),
            pb::PatchKind::Edge,
        ),
    };
    let o = georef.to_world(w.c0 as f64, w.r0 as f64);
    Ok(Some(pb::Patch {
        id: x.id.0,
        survey: x.survey.0,
        level: x.level as u32,
        error: x.span.min_z,
        max_error: x.span.max_z,
        bounds: Some(rect(&x.kernel.aabb())),
        frame: Some(pb::Frame {
            origin_x: o[0],
            origin_y: o[1],
            theta: georef.theta,
            step_x: georef.step[0],
            step_y: georef.step[1],
        }),
        cols: w.cols() + 1,
        rows: w.rows() + 1,
        samples,
        kernel_c0: kernel.c0 - w.c0,
        kernel_r0: kernel.r0 - w.r0,
        kernel_c1: kernel.c1 - w.c0,
        kernel_r1: kernel.r1 - w.r0,
        kind: kind as i32,
        flags,
        fallback: x.fallback,
    }))
}

pub fn tile(t: &Tile, backend: &str, crs: Option<u32>) -> pb::Tile {
    pb::Tile {
        width: t.width as u32,
        height: t.height as u32,
        valid: t.heights.iter().map(|z| u8::from(!z.is_nan())).collect(),
        heights: t.heights.clone(),
        patches: t.patches.len() as u32,
        backend: backend.into(),
        crs: crs.unwrap_or(0),
        max_error: max_error(&t.patches),
    }
}

/// The largest error of the patches a tile blended.
fn max_error(patches: &[Extracted]) -> f64 {
    patches.iter().map(|p| p.span.min_z).fold(0.0, f64::max)
}

/// Most bytes of heights in one [`pb::TileBand`]: a quarter of gRPC's default receive limit.
pub const BAND_BYTES: usize = 1 << 20;

/// Rows of a `width`-sample tile in one band: as many as [`BAND_BYTES`] holds, one at least.
pub fn band_rows(width: usize) -> usize {
    (BAND_BYTES / (4 * width.max(1))).max(1)
}

/// Rows `row..` of a tile as bands of whole rows of f32 little-endian bytes; the tile's first
/// band carries what is said of the whole tile.
pub fn tile_bands(
    head: &TileHead,
    row: usize,
    heights: &[f32],
    crs: Option<u32>,
) -> Vec<pb::TileBand> {
    let width = head.width.max(1);
    let rows = band_rows(width);
    heights
        .chunks(rows * width)
        .enumerate()
        .map(|(k, band)| {
            let first = row == 0 && k == 0;
            pb::TileBand {
                width: head.width as u32,
                height: head.height as u32,
                row: (row + k * rows) as u32,
                rows: (band.len() / width) as u32,
                heights: le_bytes(band),
                patches: if first { head.patches.len() as u32 } else { 0 },
                backend: if first {
                    head.backend.into()
                } else {
                    String::new()
                },
                crs: if first { crs.unwrap_or(0) } else { 0 },
                max_error: if first { max_error(head.patches) } else { 0.0 },
            }
        })
        .collect()
}

/// f32s as little-endian bytes: a copy of memory where that is the machine's order.
fn le_bytes(v: &[f32]) -> Vec<u8> {
    if cfg!(target_endian = "little") {
        bytemuck::cast_slice(v).to_vec()
    } else {
        v.iter().flat_map(|z| z.to_le_bytes()).collect()
    }
}

pub fn conflicts(cs: &[Conflict]) -> Vec<pb::Conflict> {
    cs.iter()
        .map(|c| pb::Conflict {
            survey: c.survey.to_string(),
            max_m: c.max_m,
            rms_m: c.rms_m,
        })
        .collect()
}

pub fn ingested(i: &Ingested) -> pb::IngestResult {
    pb::IngestResult {
        source: i.source.clone(),
        outcome: i.outcome.as_str().into(),
        survey: i.survey.map(|s| s.0).unwrap_or(0),
        error: i.error.clone(),
        samples: i.samples,
        seconds: i.seconds,
        conflicts: conflicts(&i.conflicts),
    }
}

pub fn surveys(t: &Terrain, l: &SurveyListing) -> pb::SurveyList {
    let mut out: Vec<pb::SurveyInfo> = l
        .records
        .iter()
        .map(|r| pb::SurveyInfo {
            id: r.id.to_string(),
            source: r.source.clone(),
            status: match r.status {
                Status::Active => "active".into(),
                Status::Retired => "retired".into(),
            },
            error: String::new(),
            accuracy_m: r.accuracy,
            accuracy_source: r.accuracy_source.as_str().into(),
            samples: r.samples,
            crs: r.crs.unwrap_or(0),
            patches: t.index().survey_patches(r.id).map_or(0, |p| p.len() as u32),
            conflicts: l
                .conflicts
                .get(&r.id)
                .map(|c| conflicts(c))
                .unwrap_or_default(),
        })
        .collect();
    out.extend(l.failures.iter().map(|f| pb::SurveyInfo {
        id: String::new(),
        source: f.source.clone(),
        status: "failed".into(),
        error: f.error.clone(),
        ..Default::default()
    }));
    out.sort_by(|a, b| a.source.cmp(&b.source).then(a.id.cmp(&b.id)));
    pb::SurveyList { surveys: out }
}

pub fn stats(s: &Stats) -> pb::StatsReply {
    pb::StatsReply {
        surveys: s.surveys,
        retired: s.retired,
        failed: s.failed,
        patches: s.patches,
        active_boxes: s.active_boxes,
        samples: s.samples,
        disk_bytes: s.disk_bytes,
        crs: s.crs.unwrap_or(0),
        backend: s.backend.clone(),
        quadtree_nodes: s.quadtree_nodes,
        read_only: s.read_only.clone().unwrap_or_default(),
        cache_bytes: s.cache.bytes,
        cache_capacity_bytes: s.cache.capacity,
        cache_hits: s.cache.hits,
        cache_misses: s.cache.misses,
        ingesting_source: s
            .ingesting
            .as_ref()
            .map(|p| p.source.clone())
            .unwrap_or_default(),
        ingesting_bytes: s.ingesting.as_ref().map_or(0, |p| p.bytes),
        ingesting_phase: s
            .ingesting
            .as_ref()
            .map(|p| p.phase.as_str().to_string())
            .unwrap_or_default(),
        ingesting_seconds: s
            .ingesting
            .as_ref()
            .map_or(0.0, |p| p.started.elapsed().as_secs_f64()),
        // The requests are the server's to count, not the engine's; it fills them in.
        ..Default::default()
    }
}

pub fn event(e: &Event) -> pb::ChangeEvent {
    pb::ChangeEvent {
        kind: e.kind.as_str().into(),
        survey: e.survey.map(|s| s.0).unwrap_or(0),
        source: e.source.clone(),
        error: e.error.clone(),
        at_unix: e.at_unix,
        conflicts: conflicts(&e.conflicts),
    }
}
