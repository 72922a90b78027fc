//! The JSON the commands print with `--json`: stable, and documented field by field in
//! docs/API.md.

use patchwork::serve::proto as pb;
use serde::{Serialize, Serializer};

/// The lower-case word for a value of a wire enum, as the CLI prints it and its JSON carries
/// it: the proto name without the enum's prefix (`SURVEY_STATUS_ACTIVE` is "active").
pub trait Word {
    /// The word.
    fn word(&self) -> String;
}

macro_rules! words {
    ($($t:ty => $prefix:literal),* $(,)?) => {
        $(impl Word for $t {
            fn word(&self) -> String {
                self.as_str_name().trim_start_matches($prefix).to_ascii_lowercase()
            }
        })*
    };
}

words!(
    pb::Outcome => "OUTCOME_",
    pb::SurveyStatus => "SURVEY_STATUS_",
    pb::AccuracySource => "ACCURACY_SOURCE_",
    pb::IngestPhase => "INGEST_PHASE_",
    pb::Distrusted => "DISTRUSTED_",
    pb::PatchKind => "PATCH_KIND_",
);

fn word<S: Serializer, E: Word>(e: &E, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&e.word())
}

fn maybe_word<S: Serializer, E: Word>(e: &Option<E>, s: S) -> Result<S::Ok, S::Error> {
    match e {
        Some(e) => s.serialize_str(&e.word()),
        None => s.serialize_none(),
    }
}

/// `surveys --json`: one object per survey or failed file. docs/API.md documents each field.
#[derive(Serialize)]
pub struct SurveyJson<'a> {
    id: &'a str,
    source: &'a str,
    #[serde(serialize_with = "word")]
    status: pb::SurveyStatus,
    error: Option<&'a str>,
    accuracy_m: f64,
    accuracy_median_m: f64,
    accuracy_p90_m: f64,
    claimed_accuracy_m: f64,
    #[serde(serialize_with = "maybe_word")]
    accuracy_source: Option<pb::AccuracySource>,
    /// The survey's own CRS ("EPSG:n" or a WKT 2 definition), and the vertical CRS its file
    /// named ("unknown" where none); null for failures.
    crs: Option<&'a str>,
    vertical_crs: Option<&'a str>,
    /// What converting its heights into the store's vertical CRS added to ε.
    vertical_error_m: f64,
    samples: u64,
    patches: u32,
    conflicts: Vec<ConflictJson<'a>>,
    /// What its sidecar says of where it came from; null for each field it does not give.
    title: Option<&'a str>,
    license: Option<&'a str>,
    attribution: Option<&'a str>,
    acquired: Option<&'a str>,
}

/// A field of an `About`, null where it is empty.
fn given(v: &str) -> Option<&str> {
    (!v.is_empty()).then_some(v)
}

#[derive(Serialize)]
pub struct ConflictJson<'a> {
    survey: &'a str,
    max_m: f64,
    rms_m: f64,
    /// Where the other lies against this one, [east, north, up] metres, and the RMS once it
    /// is moved back; null where they could not be coregistered.
    shift_m: Option<[f64; 3]>,
    rms_after_m: Option<f64>,
    /// Beyond the shift: the other turned (degrees anticlockwise), scaled, and tilted (its
    /// heights less this one's, metres per kilometre east and north); null where they could
    /// not be coregistered.
    turned_deg: Option<f64>,
    scale: Option<f64>,
    tilt_m_per_km: Option<[f64; 2]>,
    /// Whose claim the evidence finds false: "this", "other" or "both".
    #[serde(serialize_with = "word")]
    distrusted: pb::Distrusted,
    /// The test that decided it ("prediction", "detail", "transfer", "noise", "line", "consensus" or
    /// "undetermined"), its statistic and confidence.
    decided_by: &'a str,
    statistic: f64,
    confidence: f64,
    /// Whether the shift is determined; one that is not blames nobody.
    shift_determined: bool,
    /// Undetermined: whether this survey takes the tie.
    takes_tie: bool,
    /// Where the ground changed between the two.
    changes: Vec<ChangeJson<'a>>,
}

/// A region where the ground changed, as `surveys --json` gives it.
#[derive(Serialize)]
pub struct ChangeJson<'a> {
    /// Which saw the ground last and serves there: "this", "other" or "undated".
    later: &'a str,
    area_m2: f64,
    /// From the earlier survey to the later (this one to the other where undated).
    gained_m3: f64,
    lost_m3: f64,
    most_m: f64,
    /// In the finer survey's CRS: least x, least y, greatest x, greatest y.
    bounds: &'a [f64],
}

/// Whose claim a conflict distrusts; either, for a value this client does not know.
pub fn distrusted(c: &pb::Conflict) -> pb::Distrusted {
    match c.distrusted() {
        pb::Distrusted::Unspecified => pb::Distrusted::Both,
        d => d,
    }
}

impl<'a> SurveyJson<'a> {
    pub fn of(s: &'a pb::SurveyInfo) -> Self {
        let failed = matches!(
            s.status(),
            pb::SurveyStatus::Failed
                | pb::SurveyStatus::Damaged
                | pb::SurveyStatus::Deferred
                | pb::SurveyStatus::Skipped
        );
        SurveyJson {
            id: &s.id,
            source: &s.source,
            status: s.status(),
            error: failed.then_some(s.error.as_str()),
            accuracy_m: s.accuracy_m,
            accuracy_median_m: s.accuracy_median_m,
            accuracy_p90_m: s.accuracy_p90_m,
            claimed_accuracy_m: s.claimed_accuracy_m,
            accuracy_source: (!failed).then_some(s.accuracy_source()),
            crs: (!failed).then_some(s.crs_key.as_str()),
            vertical_crs: (!failed).then_some(s.vertical_crs.as_str()),
            vertical_error_m: s.vertical_error_m,
            samples: s.samples,
            patches: s.patches,
            title: s.about.as_ref().and_then(|a| given(&a.title)),
            license: s.about.as_ref().and_then(|a| given(&a.license)),
            attribution: s.about.as_ref().and_then(|a| given(&a.attribution)),
            acquired: s.about.as_ref().and_then(|a| given(&a.acquired)),
            conflicts: s
                .conflicts
                .iter()
                .map(|c| ConflictJson {
                    survey: &c.survey,
                    max_m: c.max_m,
                    rms_m: c.rms_m,
                    shift_m: c.shift.as_ref().map(|s| [s.east_m, s.north_m, s.up_m]),
                    rms_after_m: c.shift.as_ref().map(|s| s.rms_after_m),
                    turned_deg: c.shift.as_ref().map(|s| s.turned_deg),
                    scale: c.shift.as_ref().map(|s| s.scale),
                    tilt_m_per_km: c
                        .shift
                        .as_ref()
                        .map(|s| [s.tilt_east_m_per_km, s.tilt_north_m_per_km]),
                    distrusted: distrusted(c),
                    decided_by: &c.decided_by,
                    statistic: c.statistic,
                    confidence: c.confidence,
                    shift_determined: c.shift_determined,
                    takes_tie: c.takes_tie,
                    changes: c
                        .changes
                        .iter()
                        .map(|r| ChangeJson {
                            later: &r.later,
                            area_m2: r.area_m2,
                            gained_m3: r.gained_m3,
                            lost_m3: r.lost_m3,
                            most_m: r.most_m,
                            bounds: &r.bounds,
                        })
                        .collect(),
                })
                .collect(),
        }
    }
}

/// `sample --json`: a point and its height, null where there is no data.
#[derive(Serialize)]
pub struct SampleJson<'a> {
    pub x: f64,
    pub y: f64,
    pub height: Option<f32>,
    /// With `--sources`: what served the height (null where there is none).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub source: Option<Option<SourceJson<'a>>>,
}

/// What served a height.
#[derive(Serialize)]
pub struct SourceJson<'a> {
    survey: &'a str,
    file: &'a str,
    title: Option<&'a str>,
    license: Option<&'a str>,
    attribution: Option<&'a str>,
    acquired: Option<&'a str>,
    level: u32,
    cell_m: f64,
    error_m: f64,
}

impl<'a> SourceJson<'a> {
    /// None where the point has no height.
    pub fn of(s: &'a pb::Source) -> Option<Self> {
        if s.survey.is_empty() {
            return None;
        }
        let a = s.about.as_ref();
        Some(SourceJson {
            survey: &s.survey,
            file: &s.file,
            title: a.and_then(|a| given(&a.title)),
            license: a.and_then(|a| given(&a.license)),
            attribution: a.and_then(|a| given(&a.attribution)),
            acquired: a.and_then(|a| given(&a.acquired)),
            level: s.level,
            cell_m: s.cell_m,
            error_m: s.error_m,
        })
    }
}

/// `stats --json`.
#[derive(Serialize)]
pub struct StatsJson<'a> {
    surveys: u32,
    retired: u32,
    failed: u32,
    damaged: u32,
    patches: u64,
    active_boxes: u64,
    samples: u64,
    disk_bytes: u64,
    /// "EPSG:n", or a WKT 2 definition; null until the store has one.
    crs: Option<&'a str>,
    vertical_crs: Option<&'a str>,
    backend: &'a str,
    quadtree_nodes: u32,
    /// Why writes are refused now; null when they are not.
    read_only: Option<&'a str>,
    cache_bytes: u64,
    cache_capacity_bytes: u64,
    cache_hits: u64,
    cache_misses: u64,
    /// Requests at work, of at most `requests_limit`; waiting for a turn; finished.
    requests_running: u32,
    requests_waiting: u32,
    requests_served: u64,
    requests_limit: u32,
    /// On an object store, the commit the store is at; 0 on the local pack.
    commit: u64,
    /// On a read replica: the store it follows, its writer's newest commit, and how far behind
    /// it is; null on a writer.
    follows: Option<&'a str>,
    published_commit: u64,
    lag_seconds: f64,
    /// A verification under way: what it checks now ("surveys", then "index"), how many of
    /// how many, for how long; null step when none runs.
    verify_step: Option<&'a str>,
    verify_done: u64,
    verify_total: u64,
    verify_seconds: f64,
    /// Passes the inbox watcher has finished since the daemon started.
    inbox_passes: u64,
    /// The ingest under way: its file and phase ("reading", "modelling", "indexing",
    /// "committing"); null when none runs.
    ingesting_source: Option<&'a str>,
    #[serde(serialize_with = "maybe_word")]
    ingesting_phase: Option<pb::IngestPhase>,
}

impl<'a> StatsJson<'a> {
    pub fn of(s: &'a pb::StatsReply) -> Self {
        StatsJson {
            surveys: s.surveys,
            retired: s.retired,
            failed: s.failed,
            damaged: s.damaged,
            patches: s.patches,
            active_boxes: s.active_boxes,
            samples: s.samples,
            disk_bytes: s.disk_bytes,
            crs: (!s.crs_key.is_empty()).then_some(s.crs_key.as_str()),
            vertical_crs: (!s.vertical_crs.is_empty()).then_some(s.vertical_crs.as_str()),
            backend: &s.backend,
            quadtree_nodes: s.quadtree_nodes,
            read_only: (!s.read_only.is_empty()).then_some(s.read_only.as_str()),
            cache_bytes: s.cache_bytes,
            cache_capacity_bytes: s.cache_capacity_bytes,
            cache_hits: s.cache_hits,
            cache_misses: s.cache_misses,
            requests_running: s.requests_running,
            requests_waiting: s.requests_waiting,
            requests_served: s.requests_served,
            requests_limit: s.requests_limit,
            commit: s.commit,
            follows: (!s.follows.is_empty()).then_some(s.follows.as_str()),
            published_commit: s.published_commit,
            lag_seconds: s.lag_seconds,
            verify_step: (!s.verify_step.is_empty()).then_some(s.verify_step.as_str()),
            verify_done: s.verify_done,
            verify_total: s.verify_total,
            verify_seconds: s.verify_seconds,
            inbox_passes: s.inbox_passes,
            ingesting_source: (!s.ingesting_source.is_empty())
                .then_some(s.ingesting_source.as_str()),
            ingesting_phase: (!s.ingesting_source.is_empty()).then(|| s.ingesting_phase()),
        }
    }
}

/// `query --json`.
#[derive(Serialize)]
pub struct QueryJson {
    pub patches: Vec<PatchJson>,
}

#[derive(Serialize)]
pub struct PatchJson {
    id: String,
    survey: String,
    level: u32,
    #[serde(serialize_with = "word")]
    kind: pb::PatchKind,
    error: f64,
    max_error: f64,
    fallback: bool,
    bounds: [f64; 4],
}

impl PatchJson {
    pub fn of(p: &pb::Patch) -> Self {
        let b = p.bounds.unwrap_or_default();
        PatchJson {
            id: format!("{:016x}", p.id),
            survey: format!("{:016x}", p.survey),
            level: p.level,
            kind: p.kind(),
            error: p.error,
            max_error: p.max_error,
            fallback: p.fallback,
            bounds: [b.xmin, b.ymin, b.xmax, b.ymax],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each kind of patch is named as the proto names it: a bicubic patch is not "bilinear".
    #[test]
    fn query_json_names_every_kind_of_patch() {
        for (kind, word) in [
            (pb::PatchKind::Bilinear, "bilinear"),
            (pb::PatchKind::Edge, "edge"),
            (pb::PatchKind::Bicubic, "bicubic"),
        ] {
            let p = pb::Patch {
                kind: kind as i32,
                ..Default::default()
            };
            let json = serde_json::to_value(PatchJson::of(&p)).unwrap();
            assert_eq!(json["kind"], word);
        }
    }

    /// The words of the JSON are docs/API.md's, spelled from the wire enums.
    #[test]
    fn survey_json_keeps_its_words() {
        let s = pb::SurveyInfo {
            status: pb::SurveyStatus::Active as i32,
            accuracy_source: pb::AccuracySource::Estimated as i32,
            conflicts: vec![pb::Conflict {
                distrusted: pb::Distrusted::Other as i32,
                ..Default::default()
            }],
            ..Default::default()
        };
        let json = serde_json::to_value(SurveyJson::of(&s)).unwrap();
        assert_eq!(json["status"], "active");
        assert_eq!(json["accuracy_source"], "estimated");
        assert_eq!(json["conflicts"][0]["distrusted"], "other");
        let failed = pb::SurveyInfo {
            status: pb::SurveyStatus::Failed as i32,
            ..Default::default()
        };
        let json = serde_json::to_value(SurveyJson::of(&failed)).unwrap();
        assert_eq!(json["status"], "failed");
        assert!(json["accuracy_source"].is_null());
        assert_eq!(pb::IngestPhase::Committing.word(), "committing");
        assert_eq!(pb::Outcome::Unchanged.word(), "unchanged");
    }
}
