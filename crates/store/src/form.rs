//! The stored form of every record: the store's own types, whose fields, their order and
//! their types are the schema's, encoded with bincode's standard configuration.
//!
//! The model's types are what the rest of the daemon works with, and they change as it needs;
//! what the store writes must not change with them unless a migration says so (see
//! `migrations/README.md`). So no model type is encoded as it is: each record goes through its
//! form here, field by field, and a change to a model type that the form does not follow is a
//! compile error in a `From` below rather than a silent change of the bytes on disk. The
//! committed stores of `tests/data/stores` pin the bytes themselves: the format tests decode
//! every record of the current schema into these forms and encode it back to the same bytes.
//!
//! Ids are stored as their `u64`, CRSs as their keys (`"EPSG:n"` or a WKT 2 definition), enums
//! as their variant's index, in the order the forms list them.

use crate::records::{IngestTimings, LevelHeader, Status, SurveyRecord};
use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::Crs;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::accuracy::{self, KernelAccuracy};
use patchwork_core::model::change;
use patchwork_core::model::coreg;
use patchwork_core::model::detail;
use patchwork_core::model::edge::{self, EdgePatch};
use patchwork_core::model::evidence::{Departures, PairEvidence};
use patchwork_core::model::grid;
use patchwork_core::model::ids::{PatchId, SurveyId};
use patchwork_core::model::lines;
use patchwork_core::model::patch::{self, PatchLayout};
use patchwork_core::model::survey::{Survey as Cut, SurveyMeta};
use patchwork_core::model::transfer;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Survey ids as stored (`meta/quarantined`): their numbers.
pub fn ids(ids: &[SurveyId]) -> Vec<u64> {
    ids.iter().map(|s| s.0).collect()
}

/// A grid's georeference: origin, column axis angle and steps, and the row axis's own angle
/// where the grid is skewed.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Georef {
    /// The first sample's position.
    pub origin: [f64; 2],
    /// The column axis's angle, radians.
    pub theta: f64,
    /// The steps along the columns and the rows.
    pub step: [f64; 2],
    /// The row axis's angle where it is not square to the columns.
    pub row_theta: Option<f64>,
}

impl From<&grid::Georef> for Georef {
    fn from(g: &grid::Georef) -> Self {
        Georef {
            origin: g.origin,
            theta: g.theta,
            step: g.step,
            row_theta: g.row_theta,
        }
    }
}

impl From<Georef> for grid::Georef {
    fn from(g: Georef) -> Self {
        grid::Georef {
            origin: g.origin,
            theta: g.theta,
            step: g.step,
            row_theta: g.row_theta,
        }
    }
}

/// A rectangle of cells, ends included.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CellRect {
    /// First column.
    pub c0: u32,
    /// First row.
    pub r0: u32,
    /// Last column.
    pub c1: u32,
    /// Last row.
    pub r1: u32,
}

impl From<&patch::CellRect> for CellRect {
    fn from(r: &patch::CellRect) -> Self {
        CellRect {
            c0: r.c0,
            r0: r.r0,
            c1: r.c1,
            r1: r.r1,
        }
    }
}

impl From<CellRect> for patch::CellRect {
    fn from(r: CellRect) -> Self {
        patch::CellRect {
            c0: r.c0,
            r0: r.r0,
            c1: r.c1,
            r1: r.r1,
        }
    }
}

/// A patch of a survey's level.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Patch {
    /// Its id.
    pub id: u64,
    /// Its survey's id.
    pub survey: u64,
    /// Its level.
    pub level: u8,
    /// Its kernel's column and row in the level's tiling.
    pub index: [u32; 2],
    /// Its kernel's cells.
    pub kernel: CellRect,
    /// Its window's cells: the kernel and the extension zone.
    pub window: CellRect,
    /// The kernel's centre in the plane.
    pub centre: [f64; 2],
    /// The kernel's half-extent along its axes.
    pub half: [f64; 2],
    /// The valid cells' rectangles.
    pub valid: Vec<CellRect>,
    /// Its exact error δ against level 0, metres.
    pub delta: f64,
    /// Its ε, metres.
    pub error: f64,
}

impl Patch {
    /// The stored form of `p`, one of the survey `s`'s patches, whose δ is `delta`.
    pub fn of(p: &patch::Patch, s: &SurveyMeta, delta: f64) -> Self {
        let (kernel, window) = s.kernel_and_window(p);
        Patch {
            id: p.id.0,
            survey: s.id.0,
            level: p.level,
            index: s.kernel_index(p),
            kernel: (&kernel).into(),
            window: (&window).into(),
            centre: s.centre(p),
            half: s.half(),
            valid: s.valid(p).iter().map(CellRect::from).collect(),
            delta,
            error: p.error,
        }
    }

    /// The patch as memory holds it, in a level whose tiling has `nx` kernels along a row:
    /// its place in that tiling, row-major, for its kernel's cells and its window with that
    /// window's centre and half side, which its survey gives (the open checks that they are
    /// the ones stored); without its survey's id, and without its δ, which only the store
    /// keeps. None where the stored place is outside a row (a damaged record).
    pub fn into_patch(self, nx: u32) -> Option<patch::Patch> {
        let [i, j] = self.index;
        if i >= nx {
            return None;
        }
        let kernel = self.kernel.into();
        Some(patch::Patch {
            id: PatchId(self.id),
            level: self.level,
            index: j.checked_mul(nx)?.checked_add(i)?,
            valid: patch::ValidCells::of(&kernel, self.valid.into_iter().map(Into::into).collect()),
            error: self.error,
        })
    }
}

/// A survey's patches and the edge tiles its samples reach (`p/`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Patches {
    /// The patches, of every level.
    pub patches: Vec<Patch>,
    /// The lattice tiles whose edge patches the survey's samples can reach.
    pub edge_tiles: Vec<[i64; 2]>,
}

impl Patches {
    /// The stored form of a survey's patches, with their δ, and its edge tiles.
    pub fn of(s: &Cut) -> Self {
        Patches {
            patches: (s.patches.iter().zip(s.deltas.iter()))
                .map(|(p, &delta)| Patch::of(p, s, delta))
                .collect(),
            edge_tiles: s.edge_tiles.clone(),
        }
    }
}

/// Where a survey's ε came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum AccuracySource {
    /// Its sidecar.
    Sidecar,
    /// The request's or the command line's accuracy.
    Flag,
    /// The config's default.
    Config,
    /// Estimated from its own samples.
    Estimated,
    /// Not known (a store from before the choice was kept).
    Unknown,
}

impl From<accuracy::AccuracySource> for AccuracySource {
    fn from(a: accuracy::AccuracySource) -> Self {
        match a {
            accuracy::AccuracySource::Sidecar => AccuracySource::Sidecar,
            accuracy::AccuracySource::Flag => AccuracySource::Flag,
            accuracy::AccuracySource::Config => AccuracySource::Config,
            accuracy::AccuracySource::Estimated => AccuracySource::Estimated,
            accuracy::AccuracySource::Unknown => AccuracySource::Unknown,
        }
    }
}

impl From<AccuracySource> for accuracy::AccuracySource {
    fn from(a: AccuracySource) -> Self {
        match a {
            AccuracySource::Sidecar => accuracy::AccuracySource::Sidecar,
            AccuracySource::Flag => accuracy::AccuracySource::Flag,
            AccuracySource::Config => accuracy::AccuracySource::Config,
            AccuracySource::Estimated => accuracy::AccuracySource::Estimated,
            AccuracySource::Unknown => accuracy::AccuracySource::Unknown,
        }
    }
}

/// A level's size and georeference in a survey's record.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Level {
    /// Samples in a row.
    pub cols: u64,
    /// Rows of samples.
    pub rows: u64,
    /// Where its samples are in the survey's plane.
    pub georef: Georef,
}

/// A survey's record (`s/`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Survey {
    /// Its id.
    pub id: u64,
    /// The file it was read from.
    pub source: String,
    /// Hex blake3 of the file's bytes; empty when unknown.
    pub content_id: String,
    /// ε, metres.
    pub accuracy: f64,
    /// Where ε came from.
    pub accuracy_source: AccuracySource,
    /// Its horizontal CRS's key.
    pub crs: Option<String>,
    /// The key of the vertical CRS its file or sidecar named.
    pub vertical_source: Option<String>,
    /// The key of the vertical CRS its stored heights are in.
    pub vertical: Option<String>,
    /// What converting its heights added to ε, metres.
    pub vertical_error_m: f64,
    /// Active or retired.
    pub status: Status,
    /// Level 0's samples in a row.
    pub cols: u64,
    /// Level 0's rows.
    pub rows: u64,
    /// Level 0's georeference.
    pub georef: Georef,
    /// Valid level-0 samples.
    pub samples: u64,
    /// Its levels, level 0 first.
    pub levels: Vec<Level>,
    /// Where level 0's kernel boundaries fall.
    pub tiling_offset: [i64; 2],
    /// Where the time of its ingestion went.
    pub ingest: IngestTimings,
    /// When the record was made, Unix seconds.
    pub created_unix: u64,
    /// What its sidecar says of where it came from (from version 9).
    pub about: About,
}

/// What a survey's sidecar says of where it came from, for attribution: each field as the
/// sidecar gives it, None where it says nothing.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct About {
    /// Its title.
    pub title: Option<String>,
    /// Its licence.
    pub license: Option<String>,
    /// The attribution its licence asks for.
    pub attribution: Option<String>,
    /// When it was acquired, as its producer gives it (a date, or a range of them).
    pub acquired: Option<String>,
}

impl From<SurveyRecord> for Survey {
    fn from(r: SurveyRecord) -> Self {
        Survey {
            id: r.id.0,
            source: r.source,
            content_id: r.content_id,
            accuracy: r.accuracy,
            accuracy_source: r.accuracy_source.into(),
            crs: r.crs.map(|c| c.key().to_string()),
            vertical_source: r.vertical_source.map(|c| c.key().to_string()),
            vertical: r.vertical.map(|c| c.key().to_string()),
            vertical_error_m: r.vertical_error_m,
            status: r.status,
            cols: r.cols,
            rows: r.rows,
            georef: (&r.georef).into(),
            samples: r.samples,
            levels: r
                .levels
                .iter()
                .map(|l| Level {
                    cols: l.cols,
                    rows: l.rows,
                    georef: (&l.georef).into(),
                })
                .collect(),
            tiling_offset: r.tiling_offset,
            ingest: r.ingest,
            created_unix: r.created_unix,
            about: r.about,
        }
    }
}

impl TryFrom<Survey> for SurveyRecord {
    type Error = String;
    fn try_from(r: Survey) -> Result<Self, String> {
        let crs = |k: Option<String>| k.map(|k| Crs::parse(&k)).transpose();
        let vertical = |k: Option<String>| k.map(|k| VerticalCrs::parse(&k)).transpose();
        Ok(SurveyRecord {
            id: SurveyId(r.id),
            source: r.source,
            content_id: r.content_id,
            accuracy: r.accuracy,
            accuracy_source: r.accuracy_source.into(),
            crs: crs(r.crs).map_err(|e| e.to_string())?,
            vertical_source: vertical(r.vertical_source).map_err(|e| e.to_string())?,
            vertical: vertical(r.vertical).map_err(|e| e.to_string())?,
            vertical_error_m: r.vertical_error_m,
            status: r.status,
            cols: r.cols,
            rows: r.rows,
            georef: r.georef.into(),
            samples: r.samples,
            levels: r
                .levels
                .into_iter()
                .map(|l| LevelHeader {
                    cols: l.cols,
                    rows: l.rows,
                    georef: l.georef.into(),
                })
                .collect(),
            tiling_offset: r.tiling_offset,
            ingest: r.ingest,
            created_unix: r.created_unix,
            about: r.about,
        })
    }
}

/// A survey's ε kernel by kernel (`a/`), where it was estimated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Accuracies {
    /// Kernels a row and rows of kernels.
    pub dims: [usize; 2],
    /// ε of each kernel, row by row, metres.
    pub values: Vec<f64>,
}

impl From<&KernelAccuracy> for Accuracies {
    fn from(k: &KernelAccuracy) -> Self {
        Accuracies {
            dims: k.dims,
            values: k.values.clone(),
        }
    }
}

impl From<Accuracies> for KernelAccuracy {
    fn from(k: Accuracies) -> Self {
        KernelAccuracy {
            dims: k.dims,
            values: k.values,
        }
    }
}

/// The samples of an edge patch: the heights where surveys meet, on a lattice tile, kept
/// at the corners of its edge cells only (since version 10).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EdgeGrid {
    /// Samples a row of the window.
    pub cols: usize,
    /// Rows of the window.
    pub rows: usize,
    /// A bit a sample of the window, row by row, 64 to a word: whether it is kept.
    pub kept: Vec<u64>,
    /// The kept samples' heights, row by row.
    pub heights: Vec<f32>,
    /// A flag byte a kept sample.
    pub flags: Vec<u8>,
    /// The largest height change between neighbours of the whole window, metres.
    pub slope: f64,
    /// Where the grid is.
    pub georef: Georef,
}

/// An edge patch (`e/`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Edge {
    /// The survey that owns it.
    pub owner: u64,
    /// Its id.
    pub id: u64,
    /// Its lattice tile.
    pub tile: [i64; 2],
    /// The surveys that meet in it.
    pub members: Vec<u64>,
    /// Its kernel's cells.
    pub kernel: CellRect,
    /// Its window's cells.
    pub window: CellRect,
    /// Cells of its kernel.
    pub kernel_cells: u32,
    /// Its flat error part, metres.
    pub flat: f64,
    /// The kernel's centre.
    pub centre: [f64; 2],
    /// The kernel's half-extent.
    pub half: [f64; 2],
    /// The valid rectangles, in grid coordinates.
    pub valid: Vec<[f64; 4]>,
    /// Its ε, metres.
    pub error: f64,
    /// Its samples.
    pub grid: EdgeGrid,
}

/// An edge patch whose samples a terrain let go of: a store writes an edge patch whole, from
/// the terrain that built it, and never such a one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("edge patch {0} holds no samples to write")]
pub struct NoSamples(pub PatchId);

impl TryFrom<&EdgePatch> for Edge {
    type Error = NoSamples;

    fn try_from(e: &EdgePatch) -> Result<Self, Self::Error> {
        let grid = e.grid.as_ref().ok_or(NoSamples(e.id))?;
        Ok(Edge {
            owner: e.owner.0,
            id: e.id.0,
            tile: e.tile,
            members: e.members.iter().map(|m| m.0).collect(),
            kernel: (&e.kernel).into(),
            window: (&e.window).into(),
            kernel_cells: e.kernel_cells,
            flat: e.flat,
            centre: e.centre,
            half: e.half,
            valid: e.valid.clone(),
            error: e.error,
            grid: EdgeGrid {
                cols: grid.cols,
                rows: grid.rows,
                kept: grid.kept().to_vec(),
                heights: grid.kept_heights().to_vec(),
                flags: grid.kept_flags().to_vec(),
                slope: grid.slope,
                georef: (&grid.georef).into(),
            },
        })
    }
}

impl TryFrom<Edge> for EdgePatch {
    type Error = edge::BadEdgeGrid;

    fn try_from(e: Edge) -> Result<Self, Self::Error> {
        let grid = edge::EdgeGrid::from_parts(
            e.grid.cols,
            e.grid.rows,
            e.grid.kept,
            e.grid.heights,
            e.grid.flags,
            e.grid.slope,
            e.grid.georef.into(),
        )?;
        Ok(EdgePatch {
            owner: SurveyId(e.owner),
            id: PatchId(e.id),
            tile: e.tile,
            members: e.members.into_iter().map(SurveyId).collect(),
            kernel: e.kernel.into(),
            window: e.window.into(),
            kernel_cells: e.kernel_cells,
            flat: e.flat,
            centre: e.centre,
            half: e.half,
            valid: e.valid,
            error: e.error,
            georef: grid.georef,
            grid: Some(Arc::new(grid)),
        })
    }
}

/// How far two surveys' heights are apart where both have data.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Deviation {
    /// Largest, metres.
    pub max_m: f64,
    /// RMS, metres.
    pub rms_m: f64,
    /// Samples compared.
    pub samples: u64,
}

/// The placement that registers one survey on another.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Coregistration {
    /// Horizontal shift at the overlap's centre, plane units.
    pub shift: [f64; 2],
    /// Vertical offset at the overlap's centre, metres.
    pub dz: f64,
    /// The overlap's centre, plane units (from version 11).
    pub centre: [f64; 2],
    /// Half the overlap's width and height, plane units (from version 11).
    pub half_extent: [f64; 2],
    /// The placement's linear part beyond the identity, row-major (from version 11).
    pub linear: [[f64; 2]; 2],
    /// The vertical difference's slope, metres a plane unit (from version 11).
    pub tilt: [f64; 2],
    /// RMS before, metres.
    pub rms_before: f64,
    /// RMS after, metres.
    pub rms_after: f64,
    /// NMAD after, metres.
    pub nmad_after: f64,
    /// Samples used.
    pub samples: u64,
    /// Whether the shift is determined by the terrain.
    pub conditioned: bool,
}

/// How well one survey predicts the other.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Prediction {
    /// RMS of the prediction's residual, metres.
    pub rms: f64,
    /// The smoothing it took, cells.
    pub sigma: f64,
}

/// Which of two surveys is a degraded copy of the other, as predictions tell.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Degradation {
    /// The other predicted from the reference.
    pub other_from_reference: Prediction,
    /// The reference predicted from the other.
    pub reference_from_other: Prediction,
}

/// The detail two surveys hold in one scale band.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Band {
    /// The band's scale, cells.
    pub sigma: f64,
    /// The reference's energy in it.
    pub energy_reference: f64,
    /// The other's energy in it.
    pub energy_other: f64,
    /// The energy they share.
    pub shared: f64,
    /// Samples compared.
    pub samples: u64,
}

/// The detail two surveys hold, band by band.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Detail {
    /// The bands, finest first.
    pub bands: Vec<Band>,
}

/// The strongest line of a pair's differences' spectrum.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Line {
    /// Its wavelength, reference plane units.
    pub period: f64,
    /// Its direction, degrees.
    pub angle: f64,
    /// Its share of the differences' power.
    pub share: f64,
    /// How far it stands above its ring in the differences.
    pub strength: f64,
    /// How far each side's spectrum stands there, the reference's first.
    pub prominence: [f64; 2],
    /// Each side's power there over the differences'.
    pub held: [f64; 2],
}

impl From<lines::Line> for Line {
    fn from(l: lines::Line) -> Self {
        Line {
            period: l.period,
            angle: l.angle,
            share: l.share,
            strength: l.strength,
            prominence: l.prominence,
            held: l.held,
        }
    }
}

impl From<Line> for lines::Line {
    fn from(l: Line) -> Self {
        lines::Line {
            period: l.period,
            angle: l.angle,
            share: l.share,
            strength: l.strength,
            prominence: l.prominence,
            held: l.held,
        }
    }
}

/// Whether either side of a pair is a filter of the other, ring by ring of their spectra.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Transfer {
    /// Rings of coherent loss, the reference's first.
    pub lossy: [u32; 2],
    /// The largest fall of each side's spectrum over two rings, the reference's first.
    pub edge: [f64; 2],
    /// Tiles the spectra are over.
    pub tiles: u32,
}

impl From<transfer::Transfer> for Transfer {
    fn from(t: transfer::Transfer) -> Self {
        Transfer {
            lossy: t.lossy,
            edge: t.edge,
            tiles: t.tiles,
        }
    }
}

impl From<Transfer> for transfer::Transfer {
    fn from(t: Transfer) -> Self {
        transfer::Transfer {
            lossy: t.lossy,
            edge: t.edge,
            tiles: t.tiles,
        }
    }
}

/// What two overlapping surveys say of each other's claims (`o/`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pair {
    /// The finer survey.
    pub finer: u64,
    /// The coarser survey.
    pub coarser: u64,
    /// Their deviation.
    pub deviation: Deviation,
    /// Their coregistration, where measured.
    pub coreg: Option<Coregistration>,
    /// Which is degraded, where the predictions tell.
    pub degradation: Option<Degradation>,
    /// Their detail band by band, where measured.
    pub detail: Option<Detail>,
    /// The strongest line of their differences' spectrum, where measured (from version 12).
    pub line: Option<Line>,
    /// Whether either is a filter of the other, where measured (from version 13).
    pub transfer: Option<Transfer>,
    /// The finer survey's cell, plane units.
    pub finer_cell: f64,
    /// Their claimed ε.
    pub claims: (f64, f64),
    /// The cell the comparison was made at.
    pub cell: f64,
    /// Metres a plane unit, each way.
    pub metres_per_unit: [f64; 2],
    /// Kernels of the finer survey and what the coarser says of them.
    pub against_finer: Vec<(u32, f32)>,
    /// Kernels of the coarser survey and what the finer says of them.
    pub against_coarser: Vec<(u32, f32)>,
    /// Kernels of the finer survey whose claim the coarser contradicts.
    pub departs_finer: Vec<(u32, u32, f32)>,
    /// Kernels of the coarser survey whose claim the finer contradicts.
    pub departs_coarser: Vec<(u32, u32, f32)>,
    /// Where the ground changed between them (from version 11).
    pub changes: Vec<Change>,
}

/// A region where the ground changed between two surveys.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Change {
    /// Its extent in the finer survey's plane: least x and y, then greatest.
    pub bounds: [f64; 4],
    /// The finer survey's samples in it.
    pub samples: u64,
    /// Its area, m².
    pub area_m2: f64,
    /// Volume where the coarser lies above the finer, m³.
    pub above_m3: f64,
    /// Volume where it lies below, m³.
    pub below_m3: f64,
    /// Largest |difference|, m.
    pub most_m: f64,
    /// The finer survey's kernels in it, each with its largest |difference|.
    pub finer_kernels: Vec<(u32, f32)>,
    /// The coarser survey's.
    pub coarser_kernels: Vec<(u32, f32)>,
}

impl From<&change::Change> for Change {
    fn from(c: &change::Change) -> Self {
        Change {
            bounds: [
                c.bounds.min[0],
                c.bounds.min[1],
                c.bounds.max[0],
                c.bounds.max[1],
            ],
            samples: c.samples,
            area_m2: c.area_m2,
            above_m3: c.above_m3,
            below_m3: c.below_m3,
            most_m: c.most_m,
            finer_kernels: c.finer_kernels.clone(),
            coarser_kernels: c.coarser_kernels.clone(),
        }
    }
}

impl From<Change> for change::Change {
    fn from(c: Change) -> Self {
        let b = c.bounds;
        change::Change {
            bounds: patchwork_core::geom::Aabb::new(b[0], b[1], b[2], b[3]),
            samples: c.samples,
            area_m2: c.area_m2,
            above_m3: c.above_m3,
            below_m3: c.below_m3,
            most_m: c.most_m,
            finer_kernels: c.finer_kernels,
            coarser_kernels: c.coarser_kernels,
        }
    }
}

impl From<&PairEvidence> for Pair {
    fn from(p: &PairEvidence) -> Self {
        let d = &p.deviation;
        Pair {
            finer: p.finer.0,
            coarser: p.coarser.0,
            deviation: Deviation {
                max_m: d.max_m,
                rms_m: d.rms_m,
                samples: d.samples,
            },
            coreg: p.coreg.map(|c| Coregistration {
                shift: c.shift,
                dz: c.dz,
                centre: c.centre,
                half_extent: c.half_extent,
                linear: c.linear,
                tilt: c.tilt,
                rms_before: c.rms_before,
                rms_after: c.rms_after,
                nmad_after: c.nmad_after,
                samples: c.samples,
                conditioned: c.conditioned,
            }),
            degradation: p.degradation.map(|g| {
                let pr = |x: coreg::Prediction| Prediction {
                    rms: x.rms,
                    sigma: x.sigma,
                };
                Degradation {
                    other_from_reference: pr(g.other_from_reference),
                    reference_from_other: pr(g.reference_from_other),
                }
            }),
            detail: p.detail.as_ref().map(|d| Detail {
                bands: d
                    .bands
                    .iter()
                    .map(|b| Band {
                        sigma: b.sigma,
                        energy_reference: b.energy_reference,
                        energy_other: b.energy_other,
                        shared: b.shared,
                        samples: b.samples,
                    })
                    .collect(),
            }),
            line: p.line.map(Line::from),
            transfer: p.transfer.map(Transfer::from),
            finer_cell: p.finer_cell,
            claims: p.claims,
            cell: p.cell,
            metres_per_unit: p.metres_per_unit,
            against_finer: p.against_finer.clone(),
            against_coarser: p.against_coarser.clone(),
            departs_finer: p.departs_finer.to_vec(),
            departs_coarser: p.departs_coarser.to_vec(),
            changes: p.changes.iter().map(Change::from).collect(),
        }
    }
}

impl From<Pair> for PairEvidence {
    fn from(p: Pair) -> Self {
        let d = p.deviation;
        PairEvidence {
            finer: SurveyId(p.finer),
            coarser: SurveyId(p.coarser),
            deviation: accuracy::Deviation {
                max_m: d.max_m,
                rms_m: d.rms_m,
                samples: d.samples,
            },
            coreg: p.coreg.map(|c| coreg::Coregistration {
                shift: c.shift,
                dz: c.dz,
                centre: c.centre,
                half_extent: c.half_extent,
                linear: c.linear,
                tilt: c.tilt,
                rms_before: c.rms_before,
                rms_after: c.rms_after,
                nmad_after: c.nmad_after,
                samples: c.samples,
                conditioned: c.conditioned,
            }),
            degradation: p.degradation.map(|g| {
                let pr = |x: Prediction| coreg::Prediction {
                    rms: x.rms,
                    sigma: x.sigma,
                };
                coreg::Degradation {
                    other_from_reference: pr(g.other_from_reference),
                    reference_from_other: pr(g.reference_from_other),
                }
            }),
            detail: p.detail.map(|d| detail::Detail {
                bands: d
                    .bands
                    .into_iter()
                    .map(|b| detail::Band {
                        sigma: b.sigma,
                        energy_reference: b.energy_reference,
                        energy_other: b.energy_other,
                        shared: b.shared,
                        samples: b.samples,
                    })
                    .collect(),
            }),
            line: p.line.map(lines::Line::from),
            transfer: p.transfer.map(transfer::Transfer::from),
            finer_cell: p.finer_cell,
            claims: p.claims,
            cell: p.cell,
            metres_per_unit: p.metres_per_unit,
            against_finer: p.against_finer,
            against_coarser: p.against_coarser,
            departs_finer: Departures::new(&p.departs_finer),
            departs_coarser: Departures::new(&p.departs_coarser),
            changes: p.changes.into_iter().map(change::Change::from).collect(),
        }
    }
}

/// The patch layout every survey of the store is cut with (`meta/layout`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Layout {
    /// Kernel side, cells.
    pub kernel: usize,
    /// Extension zone, cells.
    pub margin: usize,
}

impl From<PatchLayout> for Layout {
    fn from(l: PatchLayout) -> Self {
        Layout {
            kernel: l.kernel,
            margin: l.margin,
        }
    }
}

impl From<Layout> for PatchLayout {
    fn from(l: Layout) -> Self {
        PatchLayout {
            kernel: l.kernel,
            margin: l.margin,
        }
    }
}

/// The LOD index's settings (`meta/index`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Index {
    /// The top of LOD space, metres.
    pub max_error: f64,
    /// Entries a quadtree node holds before it splits.
    pub node_capacity: usize,
}

impl From<IndexConfig> for Index {
    fn from(c: IndexConfig) -> Self {
        Index {
            max_error: c.max_error,
            node_capacity: c.node_capacity,
        }
    }
}

impl From<Index> for IndexConfig {
    fn from(c: Index) -> Self {
        IndexConfig {
            max_error: c.max_error,
            node_capacity: c.node_capacity,
        }
    }
}
