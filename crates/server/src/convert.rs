//! Engine results as API messages. The server and the CLI's direct mode share these, so both
//! print the same thing.

use super::proto as pb;
use super::web::pyramid::Changed;
use patchwork_core::crs::Crs;
use patchwork_core::geom::tiles::TileRange;
use patchwork_core::geom::Aabb;
use patchwork_core::index::query::{Extracted, Shortfall};
use patchwork_core::mesh::Mesh;
use patchwork_core::model::accuracy::AccuracySource;
use patchwork_core::model::grid::{Georef, SampleRect};
use patchwork_core::model::patch::{CellRect, PatchKind};
use patchwork_core::model::source::SampleError;
use patchwork_core::resample::closed_sides;
use patchwork_core::terrain::{PatchRef, Terrain, Tile};
use patchwork_engine::sources::{About, Source};
use patchwork_engine::{
    Conflict, Distrusted, Event, Frame, Held, Ingested, MeshTile, Outcome, Phase, Reason, Stats,
    SurveyListing, TileHead, Used,
};
use patchwork_store::Status;

/// A box on the wire, in the coordinates it was given in.
pub fn rect(b: &Aabb) -> pb::Rect {
    pb::Rect {
        xmin: b.min[0],
        ymin: b.min[1],
        xmax: b.max[0],
        ymax: b.max[1],
    }
}

/// A CRS's EPSG code for the wire (0 for none) and its key (empty for none).
pub fn crs_fields(crs: Option<&Crs>) -> (u32, String) {
    match crs {
        Some(c) => (c.epsg_code().unwrap_or(0), c.key().to_string()),
        None => (0, String::new()),
    }
}

/// A patch with its window's samples and everything Formula 1 needs of it, ready to send;
/// None when the terrain no longer has it.
pub fn patch(t: &Terrain, x: &Extracted) -> Result<Option<pb::Patch>, SampleError> {
    struct Parts {
        georef: Georef,
        window: CellRect,
        kernel: CellRect,
        centre: [f64; 2],
        half: [f64; 2],
        flat: f64,
        /// In level (or edge grid) coordinates.
        valid: Vec<[f64; 4]>,
        samples: Vec<f32>,
        flags: Vec<u8>,
        kind: pb::PatchKind,
        /// The accurate blend's closed sides of the kernel.
        closed: u8,
    }
    let p = match t.patch(x) {
        None => return Ok(None),
        Some(PatchRef::Survey(s, p)) => {
            let (kernel, w) = s.kernel_and_window(p);
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
            Parts {
                georef: level.level.georef,
                window: w,
                kernel,
                centre: s.centre(p),
                half: s.half(),
                flat: 0.0,
                valid: s
                    .valid(p)
                    .iter()
                    .map(|v| [v.c0, v.r0, v.c1, v.r1].map(f64::from))
                    .collect(),
                samples,
                flags: Vec::new(),
                kind: match s.kind {
                    PatchKind::Bilinear => pb::PatchKind::Bilinear,
                    PatchKind::Bicubic => pb::PatchKind::Bicubic,
                },
                closed: closed_sides(s, p),
            }
        }
        Some(PatchRef::Edge(e)) => {
            let (samples, flags) = t.edge_grid(e)?.dense();
            Parts {
                georef: e.georef,
                window: e.window,
                kernel: e.kernel,
                centre: e.centre,
                half: e.half,
                flat: e.flat,
                valid: e.valid.clone(),
                samples,
                flags,
                kind: pb::PatchKind::Edge,
                closed: 0,
            }
        }
    };
    let (w, k) = (p.window, p.kernel);
    let (c0, r0) = (w.c0 as f64, w.r0 as f64);
    let o = p.georef.to_world(c0, r0);
    let packed = Packed::of(&p.samples);
    let crs = t.plane_crs(x.plane).map(|c| c.key().to_string());
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
            theta: p.georef.theta,
            step_x: p.georef.step[0],
            step_y: p.georef.step[1],
            row_theta: p.georef.row_theta,
        }),
        cols: w.cols() + 1,
        rows: w.rows() + 1,
        kernel_c0: k.c0 - w.c0,
        kernel_r0: k.r0 - w.r0,
        kernel_c1: k.c1 - w.c0,
        kernel_r1: k.r1 - w.r0,
        kind: p.kind as i32,
        flags: p.flags,
        fallback: x.fallback,
        data: packed.data,
        encoding: packed.encoding as i32,
        scale: packed.scale,
        offset: packed.offset,
        centre_x: p.centre[0] - c0,
        centre_y: p.centre[1] - r0,
        half_x: p.half[0],
        half_y: p.half[1],
        flat: p.flat,
        valid: p
            .valid
            .iter()
            .map(|v| pb::GridRect {
                c0: v[0] - c0,
                r0: v[1] - r0,
                c1: v[2] - c0,
                r1: v[3] - r0,
            })
            .collect(),
        crs: crs.unwrap_or_default(),
        closed: p.closed.into(),
    }))
}

/// A patch's samples as bytes: 16-bit integers with a scale and offset where that loses
/// nothing, else f32.
#[derive(Debug, PartialEq)]
pub struct Packed {
    /// How `data` holds the samples: i16 or f32.
    pub encoding: pb::SampleEncoding,
    /// The height of one i16 step, a power of two; 0 with f32.
    pub scale: f64,
    /// The height the i16 value 0 stands for; 0 with f32.
    pub offset: f64,
    /// The samples in order, little-endian; [`I16_VOID`] or NaN marks a void.
    pub data: Vec<u8>,
}

/// The i16 value that marks a void sample.
pub const I16_VOID: i16 = i16::MIN;

impl Packed {
    /// Finest binary fraction tried: minimax levels hold multiples of 1/16 m
    /// (`mipmap::FIT_STEP`), and a 16-bit survey's smooth level k multiples of 4^-k, so this
    /// serves their first six.
    const MAX_SHIFT: i32 = 12;

    /// `samples` as i16 where that is exact, else as f32.
    pub fn of(samples: &[f32]) -> Self {
        Self::as_i16(samples).unwrap_or_else(|| Packed {
            encoding: pb::SampleEncoding::F32,
            scale: 0.0,
            offset: 0.0,
            data: samples.iter().flat_map(|z| z.to_le_bytes()).collect(),
        })
    }

    /// Heights = offset + scale · i for i16 values i, exactly, with scale a power of two.
    fn as_i16(samples: &[f32]) -> Option<Self> {
        let (lo, hi) = samples
            .iter()
            .filter(|z| !z.is_nan())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &z| {
                (a.min(z as f64), b.max(z as f64))
            });
        if !lo.is_finite() {
            // All void: any encoding is exact.
            return Some(Packed {
                encoding: pb::SampleEncoding::I16,
                scale: 1.0,
                offset: 0.0,
                data: samples
                    .iter()
                    .flat_map(|_| I16_VOID.to_le_bytes())
                    .collect(),
            });
        }
        // The coarsest fraction all heights are whole multiples of.
        let shift = (0..=Self::MAX_SHIFT).find(|&k| {
            let m = (k as f64).exp2();
            samples
                .iter()
                .all(|&z| z.is_nan() || (z as f64 * m).fract() == 0.0)
        })?;
        let m = (shift as f64).exp2();
        let base = ((lo + hi) / 2.0 * m).round();
        // Values from −32767 to 32767: −32768 marks a void.
        if (hi * m - base).abs() > 32767.0 || (lo * m - base).abs() > 32767.0 {
            return None;
        }
        let data = samples
            .iter()
            .flat_map(|&z| {
                let i = if z.is_nan() {
                    I16_VOID
                } else {
                    (z as f64 * m - base) as i16
                };
                i.to_le_bytes()
            })
            .collect();
        Some(Packed {
            encoding: pb::SampleEncoding::I16,
            scale: 1.0 / m,
            offset: base / m,
            data,
        })
    }
}

/// A resampled tile on the wire, with the backend that made it and its CRS; `valid` marks
/// the samples that are not void.
pub fn tile(t: &Tile, backend: Used, frame: &Frame, crs: Option<&Crs>) -> pb::Tile {
    let (code, key) = crs_fields(crs);
    pb::Tile {
        width: t.width as u32,
        height: t.height as u32,
        valid: t.heights.iter().map(|z| u8::from(!z.is_nan())).collect(),
        heights: t.heights.clone(),
        patches: t.patches.len() as u32,
        backend: backend.as_str().into(),
        crs: code,
        crs_key: key,
        max_error: max_error(&t.patches),
        shortfall: t.shortfall.map(shortfall),
        vertical_crs: vertical_key(frame),
        frame_error_m: frame.error_m,
    }
}

/// What served a height, on the wire.
pub fn source(s: &Source) -> pb::Source {
    pb::Source {
        survey: s.survey.to_string(),
        file: s.file.clone(),
        about: Some(about(&s.about)),
        level: s.level as u32,
        cell_m: s.cell_m,
        error_m: s.error_m,
    }
}

/// What a sidecar says of a survey, on the wire: empty where it says nothing.
pub fn about(a: &About) -> pb::About {
    let f = |v: &Option<String>| v.clone().unwrap_or_default();
    pb::About {
        title: f(&a.title),
        license: f(&a.license),
        attribution: f(&a.attribution),
        acquired: f(&a.acquired),
    }
}

/// The key of the vertical CRS heights are measured from, empty where none is known.
pub fn vertical_key(frame: &Frame) -> String {
    frame
        .vertical
        .as_ref()
        .map(|v| v.key().to_string())
        .unwrap_or_default()
}

fn shortfall(s: Shortfall) -> pb::Shortfall {
    pb::Shortfall {
        share: s.share,
        min_error_m: s.min_error,
        max_error_m: s.max_error,
    }
}

/// A meshed tile on the wire, with its CRS: what [`mesh_of`] reads back.
pub fn mesh(m: &MeshTile, crs: Option<&Crs>) -> pb::Mesh {
    let mesh = &m.mesh;
    let (code, key) = crs_fields(crs);
    pb::Mesh {
        roi: Some(rect(&m.roi)),
        size: mesh.cols as u32,
        grid_rows: mesh.rows as u32,
        columns: mesh.grid.iter().map(|g| g[0]).collect(),
        rows: mesh.grid.iter().map(|g| g[1]).collect(),
        heights: mesh.heights.clone(),
        indices: mesh.triangles.iter().flatten().copied().collect(),
        skirt_vertices: mesh.skirt_vertices as u32,
        skirt_triangles: mesh.skirt_triangles as u32,
        max_deviation: mesh.max_deviation,
        max_hole_reach_m: mesh.max_reach,
        patches: m.patches.len() as u32,
        max_error: max_error(&m.patches),
        backend: m.backend.as_str().into(),
        crs: code,
        crs_key: key,
        shortfall: m.shortfall.map(shortfall),
        vertical_crs: vertical_key(&m.frame),
        frame_error_m: m.frame.error_m,
    }
}

/// A mesh message back as a mesh and the tile it spans, checked: what a client of
/// `MeshTile` encodes.
pub fn mesh_of(m: &pb::Mesh) -> Result<(Mesh, Aabb), String> {
    let n = m.columns.len();
    if m.rows.len() != n || m.heights.len() != n || !m.indices.len().is_multiple_of(3) {
        return Err(format!(
            "a mesh of {n} columns, {} rows, {} heights and {} indices",
            m.rows.len(),
            m.heights.len(),
            m.indices.len()
        ));
    }
    if m.size < 2
        || m.grid_rows < 2
        || m.columns.iter().any(|&c| c >= m.size)
        || m.rows.iter().any(|&r| r >= m.grid_rows)
        || m.indices.iter().any(|&i| i as usize >= n)
        || m.skirt_vertices as usize > n
        || m.skirt_triangles as usize > m.indices.len() / 3
    {
        return Err("the mesh's grid positions or indices are out of range".into());
    }
    let r = m.roi.as_ref().ok_or("the mesh has no region")?;
    let roi = Aabb::new(r.xmin, r.ymin, r.xmax, r.ymax);
    let mesh = Mesh {
        cols: m.size as usize,
        rows: m.grid_rows as usize,
        grid: m
            .columns
            .iter()
            .zip(&m.rows)
            .map(|(&c, &r)| [c, r])
            .collect(),
        heights: m.heights.clone(),
        triangles: m
            .indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect(),
        skirt_vertices: m.skirt_vertices as usize,
        skirt_triangles: m.skirt_triangles as usize,
        max_deviation: m.max_deviation,
        max_reach: m.max_hole_reach_m,
    };
    Ok((mesh, roi))
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
    crs: Option<&Crs>,
    frame: &Frame,
) -> Vec<pb::TileBand> {
    let width = head.width.max(1);
    let (code, key) = crs_fields(crs);
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
                    head.backend.as_str().into()
                } else {
                    String::new()
                },
                crs: if first { code } else { 0 },
                crs_key: if first { key.clone() } else { String::new() },
                max_error: if first { max_error(head.patches) } else { 0.0 },
                shortfall: head.shortfall.filter(|_| first).map(shortfall),
                vertical_crs: if first {
                    vertical_key(frame)
                } else {
                    String::new()
                },
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

/// Conflicts with other surveys on the wire: by how much they disagree, the shift that would
/// reconcile them, which survey is distrusted and the test that decided it.
pub fn conflicts(cs: &[Conflict]) -> Vec<pb::Conflict> {
    cs.iter()
        .map(|c| pb::Conflict {
            survey: c.survey.to_string(),
            max_m: c.max_m,
            rms_m: c.rms_m,
            shift: c.shift_m.map(|[e, n, u]| pb::Shift {
                east_m: e,
                north_m: n,
                up_m: u,
                rms_after_m: c.rms_after_m.unwrap_or(f64::NAN),
                turned_deg: c.placed.map_or(0.0, |p| p.turned_deg),
                scale: c.placed.map_or(1.0, |p| p.scale),
                tilt_east_m_per_km: c.placed.map_or(0.0, |p| p.tilt_m_per_km[0]),
                tilt_north_m_per_km: c.placed.map_or(0.0, |p| p.tilt_m_per_km[1]),
            }),
            distrusted: match c.distrusted {
                Distrusted::This => pb::Distrusted::This,
                Distrusted::Other => pb::Distrusted::Other,
                Distrusted::Both => pb::Distrusted::Both,
            } as i32,
            decided_by: c.decided.test.name().to_string(),
            statistic: c.decided.statistic,
            confidence: c.decided.confidence,
            shift_determined: c.shift_determined,
            takes_tie: c.takes_tie,
            changes: c
                .changes
                .iter()
                .map(|r| pb::ChangeRegion {
                    later: r.later.as_str().to_string(),
                    area_m2: r.area_m2,
                    gained_m3: r.gained_m3,
                    lost_m3: r.lost_m3,
                    most_m: r.most_m,
                    bounds: vec![
                        r.bounds.min[0],
                        r.bounds.min[1],
                        r.bounds.max[0],
                        r.bounds.max[1],
                    ],
                })
                .collect(),
        })
        .collect()
}

/// One file's ingest result on the wire.
pub fn ingested(i: &Ingested) -> pb::IngestResult {
    pb::IngestResult {
        source: i.source.clone(),
        outcome: outcome(i.outcome) as i32,
        survey: i.survey.map(|s| s.0).unwrap_or(0),
        error: i.error.clone(),
        samples: i.samples,
        seconds: i.seconds,
        conflicts: conflicts(&i.conflicts),
        reason: i.reason.map_or(pb::ErrorReason::Unspecified, reason) as i32,
    }
}

/// A failure's kind on the wire: the proto's value of the same name.
pub fn reason(r: Reason) -> pb::ErrorReason {
    pb::ErrorReason::from_str_name(&format!("ERROR_REASON_{}", r.as_str()))
        .unwrap_or(pb::ErrorReason::Unspecified)
}

/// The survey listing on the wire, by source: the surveys with their accuracy as the
/// terrain takes it, then the unreadable records, the failed files and the files held back.
pub fn surveys(t: &Terrain, l: &SurveyListing) -> pb::SurveyList {
    let mut out: Vec<pb::SurveyInfo> = l
        .records
        .iter()
        .map(|r| {
            // As the store takes it: its kernels' claims, raised where evidence finds them
            // false; a retired survey's as it claimed.
            let (accuracy, median, p90) = match t.survey(r.id) {
                Some(s) => (
                    s.accuracy,
                    s.kernel_accuracy.quantile(0.5),
                    s.kernel_accuracy.quantile(0.9),
                ),
                None => (r.accuracy, r.accuracy, r.accuracy),
            };
            pb::SurveyInfo {
                id: r.id.to_string(),
                source: r.source.clone(),
                status: match (r.status, l.damaged.get(&r.id)) {
                    (Status::Active, Some(_)) => pb::SurveyStatus::Damaged,
                    (Status::Active, None) => pb::SurveyStatus::Active,
                    (Status::Retired, _) => pb::SurveyStatus::Retired,
                } as i32,
                error: l
                    .damaged
                    .get(&r.id)
                    .map_or(String::new(), |d| d.reason.clone()),
                accuracy_m: accuracy,
                accuracy_median_m: median,
                accuracy_p90_m: p90,
                claimed_accuracy_m: r.accuracy,
                accuracy_source: accuracy_source(r.accuracy_source) as i32,
                samples: r.samples,
                crs: crs_fields(r.crs.as_ref()).0,
                crs_key: crs_fields(r.crs.as_ref()).1,
                vertical_crs: r
                    .vertical_source
                    .as_ref()
                    .map_or("unknown".into(), |v| v.key().to_string()),
                vertical_error_m: r.vertical_error_m,
                about: Some(about(&r.about)),
                patches: t.index().unit_len(r.id).map_or(0, |n| n as u32),
                conflicts: l
                    .conflicts
                    .get(&r.id)
                    .map(|c| conflicts(c))
                    .unwrap_or_default(),
            }
        })
        .collect();
    // A survey whose record itself is unreadable has nothing to list but its id.
    out.extend(
        l.damaged
            .values()
            .filter(|d| !l.records.iter().any(|r| r.id == d.id))
            .map(|d| pb::SurveyInfo {
                id: d.id.to_string(),
                source: d.source.clone(),
                status: pb::SurveyStatus::Damaged as i32,
                error: d.reason.clone(),
                ..Default::default()
            }),
    );
    out.extend(l.failures.iter().map(|f| pb::SurveyInfo {
        id: String::new(),
        source: f.source.clone(),
        status: pb::SurveyStatus::Failed as i32,
        error: f.error.clone(),
        ..Default::default()
    }));
    out.extend(l.held.iter().map(|(source, h)| {
        let (status, why) = match h {
            Held::Deferred(why) => (pb::SurveyStatus::Deferred, why),
            Held::Skipped(why) => (pb::SurveyStatus::Skipped, why),
        };
        pb::SurveyInfo {
            source: source.clone(),
            status: status as i32,
            error: why.clone(),
            ..Default::default()
        }
    }));
    out.sort_by(|a, b| a.source.cmp(&b.source).then(a.id.cmp(&b.id)));
    pb::SurveyList { surveys: out }
}

/// The engine's stats on the wire; the request counts are the server's to fill in.
pub fn stats(s: &Stats) -> pb::StatsReply {
    let f = s.replication.following.as_ref();
    pb::StatsReply {
        surveys: s.surveys,
        retired: s.retired,
        failed: s.failed,
        damaged: s.damaged,
        patches: s.patches,
        active_boxes: s.active_boxes,
        samples: s.samples,
        disk_bytes: s.disk_bytes,
        crs: crs_fields(s.crs.as_ref()).0,
        crs_key: crs_fields(s.crs.as_ref()).1,
        vertical_crs: s
            .vertical_crs
            .as_ref()
            .map(|v| v.key().to_string())
            .unwrap_or_default(),
        backend: s.backend.clone(),
        blend: s.blend.name().to_string(),
        quadtree_nodes: s.quadtree_nodes,
        read_only: s.read_only.clone().unwrap_or_default(),
        cache_bytes: s.cache.bytes,
        cache_capacity_bytes: s.cache.capacity,
        cache_hits: s.cache.hits,
        cache_misses: s.cache.misses,
        inbox_passes: s.inbox_passes,
        commit: s.replication.commit.unwrap_or(0),
        follows: f.map(|f| f.url.clone()).unwrap_or_default(),
        published_commit: f.map_or(0, |f| f.published),
        lag_seconds: f.map_or(0.0, |f| f.lag.as_secs_f64()),
        ingesting_source: s
            .ingesting
            .as_ref()
            .map(|p| p.source.clone())
            .unwrap_or_default(),
        ingesting_bytes: s.ingesting.as_ref().map_or(0, |p| p.bytes),
        ingesting_phase: s
            .ingesting
            .as_ref()
            .map_or(pb::IngestPhase::Unspecified, |p| phase(p.phase))
            as i32,
        ingesting_seconds: s
            .ingesting
            .as_ref()
            .map_or(0.0, |p| p.started.elapsed().as_secs_f64()),
        verify_step: s
            .verifying
            .as_ref()
            .map_or(String::new(), |v| v.step.to_string()),
        verify_done: s.verifying.as_ref().map_or(0, |v| v.done),
        verify_total: s.verifying.as_ref().map_or(0, |v| v.total),
        verify_seconds: s
            .verifying
            .as_ref()
            .map_or(0.0, |v| v.started.elapsed().as_secs_f64()),
        // The requests are the server's to count, not the engine's; it fills them in.
        ..Default::default()
    }
}

/// A change on the wire, with where it changed the terrain and the web tiles it invalidated.
pub fn event(e: &Event, changed: Option<&Changed>) -> pb::ChangeEvent {
    let ranges = |rs: &[TileRange]| -> Vec<pb::TileRange> {
        rs.iter()
            .map(|r| pb::TileRange {
                z: r.z,
                x0: r.x0,
                y0: r.y0,
                x1: r.x1,
                y1: r.y1,
            })
            .collect()
    };
    pb::ChangeEvent {
        outcome: outcome(e.kind) as i32,
        survey: e.survey.map(|s| s.0).unwrap_or(0),
        source: e.source.clone(),
        error: e.error.clone(),
        at_unix: e.at_unix,
        conflicts: conflicts(&e.conflicts),
        changed: changed.map(|c| pb::LonLatBounds {
            west: c.lonlat.min[0],
            south: c.lonlat.min[1],
            east: c.lonlat.max[0],
            north: c.lonlat.max[1],
        }),
        web_tiles: changed.map_or_else(Vec::new, |c| ranges(&c.web)),
        terrain_tiles: changed.map_or_else(Vec::new, |c| ranges(&c.terrain)),
    }
}

/// An outcome on the wire.
pub fn outcome(o: Outcome) -> pb::Outcome {
    match o {
        Outcome::Inserted => pb::Outcome::Inserted,
        Outcome::Replaced => pb::Outcome::Replaced,
        Outcome::Unchanged => pb::Outcome::Unchanged,
        Outcome::Retired => pb::Outcome::Retired,
        Outcome::Failed => pb::Outcome::Failed,
    }
}

/// Where an accuracy claim came from, on the wire.
pub fn accuracy_source(a: AccuracySource) -> pb::AccuracySource {
    match a {
        AccuracySource::Sidecar => pb::AccuracySource::Sidecar,
        AccuracySource::Flag => pb::AccuracySource::Flag,
        AccuracySource::Config => pb::AccuracySource::Config,
        AccuracySource::Estimated => pb::AccuracySource::Estimated,
        AccuracySource::Unknown => pb::AccuracySource::Unknown,
    }
}

/// An ingest's phase on the wire.
pub fn phase(p: Phase) -> pb::IngestPhase {
    match p {
        Phase::Reading => pb::IngestPhase::Reading,
        Phase::Modelling => pb::IngestPhase::Modelling,
        Phase::Indexing => pb::IngestPhase::Indexing,
        Phase::Committing => pb::IngestPhase::Committing,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The heights back, NaN where void: what a client decodes.
    fn unpack(p: &Packed) -> Vec<f32> {
        match p.encoding {
            pb::SampleEncoding::F32 => p
                .data
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
            pb::SampleEncoding::I16 => p
                .data
                .chunks_exact(2)
                .map(|b| match i16::from_le_bytes([b[0], b[1]]) {
                    I16_VOID => f32::NAN,
                    i => (p.offset + p.scale * i as f64) as f32,
                })
                .collect(),
        }
    }

    fn round_trips(samples: &[f32]) -> pb::SampleEncoding {
        let p = Packed::of(samples);
        let back = unpack(&p);
        assert_eq!(back.len(), samples.len());
        for (a, b) in samples.iter().zip(&back) {
            assert!(a == b || (a.is_nan() && b.is_nan()), "{a} came back as {b}");
        }
        p.encoding
    }

    #[test]
    fn whole_metres_and_their_filtered_levels_pack_in_16_bits() {
        let srtm = [812.0, 813.0, f32::NAN, -12.0, 4807.0];
        assert_eq!(round_trips(&srtm), pb::SampleEncoding::I16);
        // A level-2 mipmap of integers: multiples of 1/16 and 1/256.
        let level2 = [812.0625, 813.0 + 1.0 / 256.0, f32::NAN, 790.5];
        assert_eq!(round_trips(&level2), pb::SampleEncoding::I16);
        // 8,000 m at 1/16 m steps needs more than 16 bits.
        assert_eq!(round_trips(&[-10.5625, 8000.0]), pb::SampleEncoding::F32);
        assert_eq!(round_trips(&[f32::NAN; 3]), pb::SampleEncoding::I16);
    }

    #[test]
    fn float_surveys_stay_f32_bit_for_bit() {
        let cop = [812.3456f32, 813.1, f32::NAN, 1e-7];
        assert_eq!(round_trips(&cop), pb::SampleEncoding::F32);
        assert_eq!(Packed::of(&cop).data.len(), 16);
    }
}

#[cfg(test)]
mod reason_tests {
    use super::*;

    #[test]
    fn every_reason_has_its_value_on_the_wire() {
        for r in Reason::ALL {
            let v = reason(r);
            assert_ne!(v, pb::ErrorReason::Unspecified, "{r:?}");
            assert_eq!(v.as_str_name(), format!("ERROR_REASON_{}", r.as_str()));
            assert_eq!(Reason::parse(r.as_str()), Some(r));
        }
    }
}
