//! What the engine reports of the store: its surveys with their conflicts, and its figures.

use super::Phase;
use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::{Crs, Transform};
use patchwork_core::geom::Aabb;
use patchwork_core::model::evidence::{Blame, Decided};
use patchwork_core::model::ids::SurveyId;
use patchwork_core::terrain::Terrain;
use patchwork_store::{CacheStats, Damaged, FailedRecord, SurveyRecord};
use std::collections::{BTreeMap, HashMap};
use std::time::Instant;

/// Two surveys that disagree by more than their accuracies allow where they overlap.
#[derive(Clone, Debug, PartialEq)]
pub struct Conflict {
    /// The other survey.
    pub survey: SurveyId,
    /// How far they differ where they overlap, measured at the finer one's samples.
    pub max_m: f64,
    /// Their root-mean-square difference there.
    pub rms_m: f64,
    /// Where the other lies against this one, metres east, north and up, and how far they
    /// differ once it is moved back; None where they could not be coregistered.
    pub shift_m: Option<[f64; 3]>,
    /// Their root-mean-square difference once the other is moved back by `shift_m`.
    pub rms_after_m: Option<f64>,
    /// How the other lies turned, scaled and tilted against this one beyond the shift; None
    /// where they could not be coregistered.
    pub placed: Option<Placed>,
    /// Whose claim the evidence finds false.
    pub distrusted: Distrusted,
    /// The test that decided it, with its statistic and confidence.
    pub decided: Decided,
    /// Whether the coregistration is determined; one that is not blames nobody.
    pub shift_determined: bool,
    /// Undetermined: whether this survey takes the tie.
    pub takes_tie: bool,
    /// Where the ground changed between the two.
    pub changes: Vec<ChangeRegion>,
}

/// How one survey's content lies against another's beyond a shift: what an affine placement
/// and a vertical plane found over their overlap (a turn of 0, a scale of 1 and no tilt where
/// a shift explained them as well).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placed {
    /// Degrees anticlockwise.
    pub turned_deg: f64,
    /// Its scale: over 1 where the other's content is stretched against this one's.
    pub scale: f64,
    /// The other's heights less this one's, their slope: metres per kilometre east and
    /// north.
    pub tilt_m_per_km: [f64; 2],
}

/// A region where the ground changed between two surveys, from one of the two's side.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChangeRegion {
    /// Which saw the ground last, by their epochs: that one serves there.
    pub later: Later,
    /// Its area, square metres.
    pub area_m2: f64,
    /// The volume the ground gained from the earlier survey to the later, cubic metres (from
    /// this survey to the other where undated).
    pub gained_m3: f64,
    /// The volume it lost, cubic metres (positive).
    pub lost_m3: f64,
    /// The largest height change, metres.
    pub most_m: f64,
    /// Its extent in the finer survey's plane.
    pub bounds: Aabb,
}

/// Which of two surveys saw changed ground last.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Later {
    /// This survey: it serves the change.
    This,
    /// The other.
    Other,
    /// Neither's epoch says: one is unknown, or the two overlap. The change is read as any
    /// contradiction of their claims is.
    Undated,
}

impl Later {
    /// As listings and the API name it.
    pub fn as_str(&self) -> &'static str {
        match self {
            Later::This => "this",
            Later::Other => "other",
            Later::Undated => "undated",
        }
    }
}

/// Which claim of a conflicting pair is false, from one of the two's side.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Distrusted {
    /// This survey's: a degraded copy of the other, or the one shifted from where a third
    /// survey lies.
    This,
    /// The other survey's, for the same reasons.
    Other,
    /// Either could be: nothing tells them apart.
    Both,
}

impl Distrusted {
    /// The verdict as listings and the API name it.
    pub fn as_str(&self) -> &'static str {
        match self {
            Distrusted::This => "this",
            Distrusted::Other => "other",
            Distrusted::Both => "both",
        }
    }
}

/// The conflicts of a survey of `t`: its pairs whose evidence finds a claim false (where their
/// claims contradict each other, or one is a degraded copy of the other), by the other's id.
pub fn conflicts_of(t: &Terrain, id: SurveyId) -> Vec<Conflict> {
    let mut out: Vec<Conflict> = t
        .pairs_of(id)
        .iter()
        .filter_map(|p| {
            let other = p.other(id);
            let finer = p.finer == id;
            let verdict = t.verdict(id, other)?;
            let distrusted = match verdict.blame? {
                Blame::Finer if finer => Distrusted::This,
                Blame::Coarser if !finer => Distrusted::This,
                Blame::Finer | Blame::Coarser => Distrusted::Other,
                Blame::Both => Distrusted::Both,
            };
            Some(Conflict {
                survey: other,
                max_m: p.deviation.max_m,
                rms_m: p.deviation.rms_m,
                // The pair measures the coarser against the finer.
                shift_m: p.shift_m().map(|s| if finer { s } else { s.map(|v| -v) }),
                rms_after_m: p.coreg.as_ref().map(|c| c.rms_after),
                placed: p.coreg.as_ref().map(|c| {
                    // The pair places the coarser on the finer; from the coarser's side, the
                    // other is turned, scaled and tilted the other way.
                    let (turned, scale) = c.placement().rotation_and_scale();
                    let per_km = |i: usize| 1000.0 * c.tilt[i] / p.metres_per_unit[i];
                    let tilt = [per_km(0), per_km(1)];
                    if finer {
                        Placed {
                            turned_deg: turned,
                            scale,
                            tilt_m_per_km: tilt,
                        }
                    } else {
                        Placed {
                            turned_deg: -turned,
                            scale: 1.0 / scale,
                            tilt_m_per_km: tilt.map(|v| -v),
                        }
                    }
                }),
                distrusted,
                decided: verdict.by,
                shift_determined: p.coreg.as_ref().is_some_and(|c| c.conditioned),
                takes_tie: p.tie_to_finer() == Some(finer),
                changes: {
                    let later = match t.later(p) {
                        Some(l) if l == id => Later::This,
                        Some(_) => Later::Other,
                        None => Later::Undated,
                    };
                    // The pair measures the coarser above the finer; a listing, the later
                    // above the earlier (the other above this one where undated).
                    let coarser_up = match later {
                        Later::This => p.coarser == id,
                        Later::Other | Later::Undated => p.coarser != id,
                    };
                    p.changes
                        .iter()
                        .map(|c| {
                            let (gained_m3, lost_m3) = if coarser_up {
                                (c.above_m3, c.below_m3)
                            } else {
                                (c.below_m3, c.above_m3)
                            };
                            ChangeRegion {
                                later,
                                area_m2: c.area_m2,
                                gained_m3,
                                lost_m3,
                                most_m: c.most_m,
                                bounds: c.bounds,
                            }
                        })
                        .collect()
                },
            })
        })
        .collect();
    out.sort_by_key(|c| c.survey);
    out
}

/// The store's surveys with their failures and conflicts.
#[derive(Clone, Debug, Default)]
pub struct SurveyListing {
    /// Every survey record, active, retired or damaged.
    pub records: Vec<SurveyRecord>,
    /// The files that failed, as remembered (at most `limits.max_failures`).
    pub failures: Vec<FailedRecord>,
    /// Active surveys out of the terrain because they are damaged.
    pub damaged: BTreeMap<SurveyId, Damaged>,
    /// Conflicts of each active survey, in the other survey's id order.
    pub conflicts: HashMap<SurveyId, Vec<Conflict>>,
    /// Inbox files the watcher holds back, by source.
    pub held: BTreeMap<String, Held>,
}

/// Why the inbox watcher holds a file back. Not stored: a deferral is what a full disk
/// could not record, and both are found again by the first pass after a restart.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Held {
    /// The store could not take it now: not read again until space is freed or it changes.
    Deferred(String),
    /// Not an elevation file the daemon reads.
    Skipped(String),
}

/// A store and the figures `stats` reports.
#[derive(Clone, Debug, Default)]
pub struct Stats {
    /// Active surveys.
    pub surveys: u32,
    /// Retired surveys the store still holds, until a compaction removes them.
    pub retired: u32,
    /// Failed files remembered.
    pub failed: u32,
    /// Active surveys out of the terrain because they are damaged.
    pub damaged: u32,
    /// Boxes in the index, active or not.
    pub patches: u64,
    /// Boxes in the index not cut to nothing: those whose span is non-empty.
    pub active_boxes: u64,
    /// Valid level-0 samples of the active surveys.
    pub samples: u64,
    /// Bytes of the files under the store's directory: its size on disk.
    pub disk_bytes: u64,
    /// The store's horizontal CRS: the config's, else the store's own.
    pub crs: Option<Crs>,
    /// The store's vertical CRS: the config's, else the store's own.
    pub vertical_crs: Option<VerticalCrs>,
    /// "cpu", or "gpu (adapter)".
    pub backend: String,
    /// How the store blends its patches.
    pub blend: patchwork_core::model::patch::Blend,
    /// Nodes of the index's quadtree.
    pub quadtree_nodes: u32,
    /// Why writes are refused now (a full disk, a failed store); None when they are not.
    pub read_only: Option<String>,
    /// How the chunk cache is doing: its size, hits and misses.
    pub cache: CacheStats,
    /// The ingest under way, if any.
    pub ingesting: Option<Progress>,
    /// The commit the store is at and, on a replica, how far behind its writer it is.
    pub replication: super::Replication,
    /// The verification under way, if any.
    pub verifying: Option<Verifying>,
    /// Passes the inbox watcher has finished since the daemon started.
    pub inbox_passes: u64,
}

/// Where a verification stands: what it checks now, how many of how many, since when.
#[derive(Clone, Debug)]
pub struct Verifying {
    /// What it checks now: `"surveys"`, then `"index"`.
    pub step: &'static str,
    /// How many of `total` it has checked.
    pub done: u64,
    /// How many there are to check in this step.
    pub total: u64,
    /// When the verification started.
    pub started: Instant,
}

/// The ingest under way: which file, how big, where it is and since when.
#[derive(Clone, Debug)]
pub struct Progress {
    /// The file's source: its absolute path (see [`crate::paths::source_name`]).
    pub source: String,
    /// The file's size when the ingest started.
    pub bytes: u64,
    /// The step it is at.
    pub phase: Phase,
    /// When the ingest started, its wait for a slot excluded.
    pub started: Instant,
}

/// Where a survey lies, in longitude and latitude: what web maps draw and tile pyramids are
/// made over.
#[derive(Clone, Debug, PartialEq)]
pub struct Footprint {
    /// The survey's id.
    pub id: SurveyId,
    /// ε, metres: the largest over its kernels.
    pub accuracy_m: f64,
    /// Its footprint's outline: the edges of its pixels in its own grid and CRS (a UTM
    /// survey's is the rotated quadrilateral it really covers), carried into longitude and
    /// latitude, 16 points a side, closed.
    pub ring: Vec<[f64; 2]>,
    /// The outline's bounds, degrees.
    pub bounds: Aabb,
    /// Its level 0's cell, in degrees of latitude: how fine a tile pyramid over it goes.
    pub cell_deg: f64,
    /// Where its arrival or departure can change heights, degrees: its footprint grown by
    /// the cells that edge patches and the fill of voids reach across.
    pub reach: Aabb,
    /// The file it was read from.
    pub file: String,
    /// What its sidecar says of where it came from.
    pub about: crate::sources::About,
}

impl super::Engine {
    /// Every survey's footprint in longitude and latitude, in id order; empty until the store
    /// has a CRS.
    pub fn footprints(&self) -> Vec<Footprint> {
        let (t, catalog) = self.published();
        let Some(to) = self.lonlat_transform() else {
            return Vec::new();
        };
        let mut out: Vec<Footprint> = t
            .surveys()
            .filter_map(|s| {
                // Out to the edges of its pixels, as far as its data is served, in its own
                // grid and CRS.
                let g = &s.shapes[0];
                let (c, r) = (g.cols as f64 - 0.5, g.rows as f64 - 0.5);
                let corners = [[-0.5, -0.5], [c, -0.5], [c, r], [-0.5, r]]
                    .map(|[i, j]| g.georef.to_world(i, j));
                let own = match &s.crs {
                    Some(c) => Some(Transform::new(c, &Crs::wgs84()).ok()?),
                    None => None,
                };
                let ring = outline_of(own.as_ref().unwrap_or(&to), corners)?;
                let bounds = Aabb::of_points(&ring);
                let reach = Aabb::of_points(&outline(&to, &super::write::changed_area(s))?);
                let rows = g.rows.max(2) - 1;
                let record = catalog.record(s.id);
                Some(Footprint {
                    file: record.map(|r| r.source.clone()).unwrap_or_default(),
                    about: record.map(|r| r.about.clone()).unwrap_or_default(),
                    id: s.id,
                    accuracy_m: s.accuracy,
                    ring,
                    cell_deg: bounds.height() / (rows + 1) as f64,
                    bounds,
                    reach,
                })
            })
            .collect();
        out.sort_by_key(|f| f.id);
        out
    }

    /// A rectangle of the store's plane in longitude and latitude: the bounds of its outline
    /// carried over. None where it cannot be (outside the projection's domain, or no CRS).
    pub fn to_lonlat(&self, area: &Aabb) -> Option<Aabb> {
        Some(Aabb::of_points(&outline(&self.lonlat_transform()?, area)?))
    }

    fn lonlat_transform(&self) -> Option<Transform> {
        Transform::new(&self.crs()?, &Crs::wgs84()).ok()
    }
}

/// A rectangle's outline carried by `to`, 16 points a side, closed.
fn outline(to: &Transform, r: &Aabb) -> Option<Vec<[f64; 2]>> {
    outline_of(
        to,
        [
            [r.min[0], r.min[1]],
            [r.max[0], r.min[1]],
            [r.max[0], r.max[1]],
            [r.min[0], r.max[1]],
        ],
    )
}

/// A quadrilateral's outline carried by `to`, 16 points a side, closed.
fn outline_of(to: &Transform, corners: [[f64; 2]; 4]) -> Option<Vec<[f64; 2]>> {
    let n = 16;
    let mut ring = Vec::with_capacity(4 * n + 1);
    for k in 0..4 {
        let (a, b) = (corners[k], corners[(k + 1) % 4]);
        for i in 0..n {
            let t = i as f64 / n as f64;
            ring.push(to.apply([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])])?);
        }
    }
    ring.push(ring[0]);
    Some(ring)
}
