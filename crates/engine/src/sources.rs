//! Provenance: which survey served a height. A height is blended from the patches whose
//! windows hold it; the one that weighs most there is what served it (the resampler's
//! `resample_serving`), and its survey, level and error are what a client is told: the file
//! it came from, what its sidecar says of it (title, licence, attribution, acquisition), its
//! cell at that level and the patch's error.

use patchwork_core::crs::metres_per_degree;
use patchwork_core::index::query::Extracted;
use patchwork_core::model::ids::SurveyId;
use patchwork_core::model::survey::SurveyMeta;
use patchwork_core::terrain::Terrain;
use patchwork_store::Catalog;
use std::collections::BTreeMap;

/// What served a height.
#[derive(Clone, Debug, PartialEq)]
pub struct Source {
    /// The survey.
    pub survey: SurveyId,
    /// The file it was read from.
    pub file: String,
    /// What its sidecar says of it.
    pub about: About,
    /// The mipmap level of the patch that served the height: 0 is the survey's own cells.
    pub level: u8,
    /// That level's cell, metres: the longer of its two sides, where the survey is.
    pub cell_m: f64,
    /// The patch's error, metres.
    pub error_m: f64,
}

/// What a survey's sidecar says of where it came from: title, licence, attribution, when.
pub use patchwork_store::form::About;

/// A survey's share of a tile: how many of the tile's samples it served.
#[derive(Clone, Debug, PartialEq)]
pub struct Share {
    /// What served them (at the finest level and least error it served any at).
    pub source: Source,
    /// Samples it served.
    pub samples: u64,
    /// Of the tile's samples with a height, the share it served, in (0, 1].
    pub share: f64,
}

/// The source of a height that patch `x` served, from the terrain and catalog of one commit.
pub fn source_of(t: &Terrain, catalog: &Catalog, x: &Extracted) -> Source {
    let record = catalog.record(x.survey);
    Source {
        survey: x.survey,
        file: record.map(|r| r.source.clone()).unwrap_or_default(),
        about: record.map(|r| r.about.clone()).unwrap_or_default(),
        level: x.level,
        cell_m: t.survey(x.survey).map_or(f64::NAN, |s| cell_m(s, x.level)),
        error_m: x.span.min_z,
    }
}

/// A level's cell in metres, the longer side, at the middle of the survey.
fn cell_m(s: &SurveyMeta, level: u8) -> f64 {
    let Some(shape) = s.shapes.get(level as usize) else {
        return f64::NAN;
    };
    let step = shape.georef.step;
    let m = match &s.crs {
        Some(c) if c.is_geographic() => {
            let mid = shape
                .georef
                .to_world(shape.cols as f64 / 2.0, shape.rows as f64 / 2.0);
            metres_per_degree(mid[1])
        }
        Some(c) => [c.unit_m().unwrap_or(1.0); 2],
        None => [1.0; 2],
    };
    (step[0].abs() * m[0]).max(step[1].abs() * m[1])
}

/// The surveys that served `served` (one patch or none a sample), each with its share, most
/// first.
pub fn shares(t: &Terrain, catalog: &Catalog, served: &[Option<Extracted>]) -> Vec<Share> {
    let with = served.iter().flatten().count() as u64;
    let mut by: BTreeMap<SurveyId, (Source, u64)> = BTreeMap::new();
    for x in served.iter().flatten() {
        let s = source_of(t, catalog, x);
        let e = by.entry(x.survey).or_insert((s.clone(), 0));
        e.1 += 1;
        // The finest it served at, and the least error.
        if s.level < e.0.level {
            e.0.level = s.level;
            e.0.cell_m = s.cell_m;
        }
        e.0.error_m = e.0.error_m.min(s.error_m);
    }
    let mut out: Vec<Share> = by
        .into_values()
        .map(|(source, samples)| Share {
            source,
            samples,
            share: samples as f64 / with.max(1) as f64,
        })
        .collect();
    out.sort_by(|a, b| {
        b.samples
            .cmp(&a.samples)
            .then(a.source.survey.cmp(&b.source.survey))
    });
    out
}
