//! From a file to a survey: read, apply the sidecar, check the CRS, build the model.

use crate::config::{parse_epsg, DefaultAccuracy};
use crate::model::accuracy::{AccuracySource, AccuracySpec};
use crate::model::patch::PatchLayout;
use crate::model::survey::{Recipe, Survey, SurveyError};
use crate::read::{open_untrusted, read_raster, OpenError, ReadError, ReadLimits, REFUSED_PATH};
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::time::Instant;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum IngestError {
    #[error("{0}")]
    Read(#[from] ReadError),
    #[error("sidecar {path}: {message}")]
    Sidecar { path: PathBuf, message: String },
    #[error("the file has no CRS: add a sidecar {sidecar} with crs = \"EPSG:…\"")]
    NoCrs { sidecar: PathBuf },
    #[error(
        "the file's CRS is {found}, which matches no EPSG code Patchwork knows: add a sidecar \
         {sidecar} with crs = \"EPSG:…\" naming it"
    )]
    UnknownCrs { found: String, sidecar: PathBuf },
    #[error(
        "sidecar {sidecar} says crs = EPSG:{sidecar_crs}, but the file itself is in \
         EPSG:{file_crs}; remove the sidecar's crs or fix the file"
    )]
    CrsConflict {
        sidecar: PathBuf,
        sidecar_crs: u32,
        file_crs: u32,
    },
    #[error(
        "accuracy {value} m ({given_by}) is refused: it must be a number of metres in \
         [0, {max}), the top of LOD space (index.max_error); a survey that inaccurate would \
         never serve any answer"
    )]
    BadAccuracy {
        value: f64,
        given_by: &'static str,
        max: f64,
    },
    #[error("the file is in EPSG:{file} but the store is in EPSG:{store}; reproject it first")]
    CrsMismatch { file: u32, store: u32 },
    #[error("georeference: {0}")]
    Grid(#[from] crate::model::grid::GridError),
    #[error("{0}")]
    Survey(#[from] SurveyError),
    #[error(
        "{outside} of the valid samples lie outside the plausible heights [{lo}, {hi}] m (they \
         range from {min} to {max} m): the file is not elevation in metres, or its nodata \
         value is not declared; limits.min_height_m and limits.max_height_m set the range"
    )]
    Implausible {
        outside: u64,
        lo: f64,
        hi: f64,
        min: f32,
        max: f32,
    },
    #[error("{}", REFUSED_PATH)]
    Refused,
    #[error("{path} is a directory, not a DEM file")]
    Directory { path: PathBuf },
    #[error("{path} is not a regular file")]
    NotAFile { path: PathBuf },
    #[error("cannot read {path}: {source}")]
    Unreadable {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// What `<file>.toml` beside a DEM may say.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sidecar {
    pub accuracy_m: Option<f64>,
    pub crs: Option<String>,
}

/// A sidecar is a line or two; anything far larger is not one.
const SIDECAR_MOST: usize = 64 << 10;

/// Parses a sidecar's bytes. The error says where and what is wrong without quoting the text.
pub fn parse_sidecar(bytes: &[u8]) -> Result<Sidecar, String> {
    if bytes.len() > SIDECAR_MOST {
        return Err(format!(
            "larger than {} KiB, so not a sidecar",
            SIDECAR_MOST >> 10
        ));
    }
    let text = std::str::from_utf8(bytes).map_err(|_| "not UTF-8 text".to_string())?;
    toml::from_str(text).map_err(|e| toml_error(text, &e))
}

/// Where an ingest is: what a progress display shows. The first two are [`prepare`]'s; the
/// engine reports the others.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    Reading,
    Modelling,
    Indexing,
    Committing,
}

impl Phase {
    pub fn as_str(&self) -> &'static str {
        match self {
            Phase::Reading => "reading",
            Phase::Modelling => "modelling",
            Phase::Indexing => "indexing",
            Phase::Committing => "committing",
        }
    }
}

/// How a survey was made, for its record.
#[derive(Clone, Copy, Debug, Default)]
pub struct Timings {
    pub read_ms: u64,
    pub build_ms: u64,
}

pub fn sidecar_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(".toml");
    PathBuf::from(s)
}

fn read_sidecar(path: &Path, roots: Option<&[PathBuf]>) -> Result<Sidecar, IngestError> {
    let side = sidecar_path(path);
    // No entry at all is no sidecar; anything else is opened like the DEM itself.
    if side.symlink_metadata().is_err() {
        return Ok(Sidecar::default());
    }
    let bad = |message: String| IngestError::Sidecar {
        path: side.clone(),
        message,
    };
    let file = open_untrusted(&side, roots).map_err(|e| match e {
        OpenError::Outside => IngestError::Refused,
        e => bad(e.to_string()),
    })?;
    let mut bytes = Vec::new();
    std::io::Read::read_to_end(
        &mut std::io::Read::take(file, SIDECAR_MOST as u64 + 1),
        &mut bytes,
    )
    .map_err(|e| bad(e.to_string()))?;
    parse_sidecar(&bytes).map_err(bad)
}

/// Where and why a sidecar failed to parse, without quoting it: the TOML error's own text
/// repeats the offending line, and the sidecar could be any file.
fn toml_error(text: &str, e: &toml::de::Error) -> String {
    let line = e
        .span()
        .map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
    let at = line.map(|l| format!(" at line {l}")).unwrap_or_default();
    let msg = e.message();
    let what = if msg.starts_with("unknown field") {
        "a key other than accuracy_m and crs"
    } else if msg.starts_with("invalid type") {
        "a value of the wrong type (accuracy_m is a number, crs a string like \"EPSG:4326\")"
    } else {
        "something that is not TOML"
    };
    format!(
        "the sidecar has {what}{at}; it may set accuracy_m = <metres> and crs = \"EPSG:<code>\""
    )
}

/// The settings an ingest needs from the store and the config.
#[derive(Clone, Debug)]
pub struct IngestSettings {
    /// `--accuracy` from the caller, which a sidecar overrides.
    pub accuracy: Option<f64>,
    pub default_accuracy: DefaultAccuracy,
    /// Accuracies must stay below this: the top of LOD space.
    pub max_accuracy: f64,
    /// The store's CRS, once it has one.
    pub store_crs: Option<u32>,
    pub layout: PatchLayout,
    pub recipe: Recipe,
    pub read_limits: ReadLimits,
    /// Plausible heights, in metres: a file with a valid sample outside is refused.
    pub heights: (f64, f64),
}

/// A file read and modelled.
#[derive(Clone, Debug)]
pub struct Prepared {
    pub survey: Survey,
    pub source: AccuracySource,
    pub timings: Timings,
}

/// ε as the sidecar, the caller and the config decide it, in that order.
fn accuracy(
    side: &Sidecar,
    s: &IngestSettings,
) -> Result<(AccuracySpec, AccuracySource), IngestError> {
    let (spec, source) = match (side.accuracy_m, s.accuracy, s.default_accuracy) {
        (Some(a), _, _) => (AccuracySpec::Fixed(a), AccuracySource::Sidecar),
        (None, Some(a), _) => (AccuracySpec::Fixed(a), AccuracySource::Flag),
        (None, None, DefaultAccuracy::Metres(a)) => {
            (AccuracySpec::Fixed(a), AccuracySource::Config)
        }
        (None, None, DefaultAccuracy::Auto) => (AccuracySpec::Auto, AccuracySource::Estimated),
    };
    if let AccuracySpec::Fixed(a) = spec {
        if !(a.is_finite() && a >= 0.0 && a < s.max_accuracy) {
            return Err(IngestError::BadAccuracy {
                value: a,
                given_by: source.as_str(),
                max: s.max_accuracy,
            });
        }
    }
    Ok((spec, source))
}

/// Refuses what is not a regular file that can be opened, with a message that says which.
/// Opens what is to be ingested, refusing what is not a regular file, or not where `roots`
/// allow, with a message that says which.
pub fn open_file(path: &Path, roots: Option<&[PathBuf]>) -> Result<std::fs::File, IngestError> {
    open_untrusted(path, roots).map_err(|e| match e {
        OpenError::Outside => IngestError::Refused,
        OpenError::Directory(path) => IngestError::Directory { path },
        OpenError::NotAFile(path) => IngestError::NotAFile { path },
        OpenError::Io { path, source } => IngestError::Unreadable { path, source },
    })
}

/// Reads and models one file. Pure of the store: nothing is written.
pub fn prepare(path: &Path, s: &IngestSettings) -> Result<Prepared, IngestError> {
    prepare_with(path, s, &|_| {})
}

/// [`prepare`], telling `phase` when it starts reading and when it starts modelling.
pub fn prepare_with(
    path: &Path,
    s: &IngestSettings,
    phase: &dyn Fn(Phase),
) -> Result<Prepared, IngestError> {
    phase(Phase::Reading);
    let roots = s.read_limits.roots.as_deref();
    open_file(path, roots)?;
    let side = read_sidecar(path, roots)?;
    let (spec, source) = accuracy(&side, s)?;
    let t0 = Instant::now();
    let raster = read_raster(path, &s.read_limits)?;
    let read_ms = t0.elapsed().as_millis() as u64;
    check_heights(&raster.samples, s.heights)?;
    let side_crs = side
        .crs
        .as_deref()
        .map(|c| {
            parse_epsg(c).ok_or_else(|| IngestError::Sidecar {
                path: sidecar_path(path),
                message: "crs must look like \"EPSG:4326\"".into(),
            })
        })
        .transpose()?;
    let crs = match (side_crs, raster.epsg, raster.crs_name.as_ref()) {
        (Some(sc), Some(fc), _) if sc != fc => {
            return Err(IngestError::CrsConflict {
                sidecar: sidecar_path(path),
                sidecar_crs: sc,
                file_crs: fc,
            })
        }
        (Some(c), _, _) | (None, Some(c), _) => c,
        (None, None, Some(name)) => {
            return Err(IngestError::UnknownCrs {
                found: crate::read::crs::crs_label(name),
                sidecar: sidecar_path(path),
            })
        }
        (None, None, None) => {
            return Err(IngestError::NoCrs {
                sidecar: sidecar_path(path),
            })
        }
    };
    if let Some(store) = s.store_crs {
        if store != crs {
            return Err(IngestError::CrsMismatch { file: crs, store });
        }
    }
    let t1 = Instant::now();
    phase(Phase::Modelling);
    let grid = raster.into_grid()?;
    let survey = Survey::build_with(grid, spec, Some(crs), s.layout, s.recipe)?;
    if survey.accuracy >= s.max_accuracy {
        return Err(IngestError::BadAccuracy {
            value: survey.accuracy,
            given_by: source.as_str(),
            max: s.max_accuracy,
        });
    }
    Ok(Prepared {
        survey,
        source,
        timings: Timings {
            read_ms,
            build_ms: t1.elapsed().as_millis() as u64,
        },
    })
}

/// Refuses samples that cannot be heights on Earth in metres: random bytes, feet, or an
/// undeclared nodata value such as -32767, which would otherwise be served as a pit.
fn check_heights(samples: &[f32], (lo, hi): (f64, f64)) -> Result<(), IngestError> {
    let (lo32, hi32) = (lo as f32, hi as f32);
    let (mut outside, mut min, mut max) = (0u64, f32::INFINITY, f32::NEG_INFINITY);
    for &z in samples.iter().filter(|z| !z.is_nan()) {
        if z < lo32 || z > hi32 {
            outside += 1;
        }
        min = min.min(z);
        max = max.max(z);
    }
    if outside > 0 {
        return Err(IngestError::Implausible {
            outside,
            lo,
            hi,
            min,
            max,
        });
    }
    Ok(())
}

/// Names the watcher leaves alone: files still being written or editor droppings.
pub fn is_temporary(path: &Path) -> bool {
    let Some(name) = path.file_name().and_then(|n| n.to_str()) else {
        return true;
    };
    name.starts_with(".~")
        || name.starts_with('.')
        || name.ends_with(".part")
        || name.ends_with(".tmp")
        || name.ends_with(".toml")
        || name.ends_with(".prj")
        || name.ends_with('~')
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings() -> IngestSettings {
        IngestSettings {
            accuracy: None,
            default_accuracy: DefaultAccuracy::Auto,
            max_accuracy: 10_000.0,
            store_crs: None,
            layout: PatchLayout::default(),
            recipe: Recipe::default(),
            read_limits: ReadLimits::mb(64),
            heights: (-12_000.0, 9_000.0),
        }
    }

    /// A 4×4 ESRI ASCII grid, with a `.prj` holding `wkt` if given.
    fn grid(dir: &Path, name: &str, wkt: Option<&str>) -> PathBuf {
        let p = dir.join(name);
        let mut text =
            "ncols 4\nnrows 4\nxllcorner 500000\nyllcorner 4000000\ncellsize 30\n".to_string();
        for r in 0..4 {
            text += &format!("{} {} {} {}\n", r, r + 1, 2 * r, 3);
        }
        std::fs::write(&p, text).unwrap();
        if let Some(w) = wkt {
            std::fs::write(p.with_extension("prj"), w).unwrap();
        }
        p
    }

    #[test]
    fn accuracy_comes_from_sidecar_flag_or_config_and_must_stay_below_the_top() {
        let dir = tempfile::tempdir().unwrap();
        let utm = r#"PROJCS["WGS_1984_UTM_Zone_31N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]]],PROJECTION["Transverse_Mercator"],PARAMETER["False_Easting",500000.0],PARAMETER["False_Northing",0.0],PARAMETER["Central_Meridian",3.0],PARAMETER["Scale_Factor",0.9996],PARAMETER["Latitude_Of_Origin",0.0],UNIT["Meter",1.0]]"#;
        let p = grid(dir.path(), "a.asc", Some(utm));
        let mut s = settings();
        let got = prepare(&p, &s).unwrap();
        assert_eq!(got.source, AccuracySource::Estimated);
        assert_eq!(got.survey.crs, Some(32631), "the ESRI UTM zone resolves");
        s.default_accuracy = DefaultAccuracy::Metres(3.0);
        assert_eq!(prepare(&p, &s).unwrap().source, AccuracySource::Config);
        s.accuracy = Some(2.0);
        let got = prepare(&p, &s).unwrap();
        assert_eq!(
            (got.source, got.survey.accuracy),
            (AccuracySource::Flag, 2.0)
        );
        std::fs::write(sidecar_path(&p), "accuracy_m = 0.5\n").unwrap();
        let got = prepare(&p, &s).unwrap();
        assert_eq!(
            (got.source, got.survey.accuracy),
            (AccuracySource::Sidecar, 0.5)
        );
        for bad in ["1e308", "10000.0", "-1.0", "nan"] {
            std::fs::write(sidecar_path(&p), format!("accuracy_m = {bad}\n")).unwrap();
            let e = prepare(&p, &s).unwrap_err().to_string();
            assert!(e.contains("refused") && e.contains("sidecar"), "{bad}: {e}");
        }
    }

    #[test]
    fn implausible_heights_and_bad_sidecars_are_refused_without_quoting_them() {
        let dir = tempfile::tempdir().unwrap();
        // Random bytes of the size of an SRTM3 tile.
        let hgt = dir.path().join("N44E005.hgt");
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        let bytes: Vec<u8> = (0..2_884_802)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state as u8
            })
            .collect();
        std::fs::write(&hgt, bytes).unwrap();
        let e = prepare(&hgt, &settings()).unwrap_err().to_string();
        assert!(e.contains("plausible heights [-12000, 9000] m"), "{e}");
        let mut wide = settings();
        wide.heights = (-40_000.0, 40_000.0);
        if let Err(e) = prepare(&hgt, &wide) {
            assert!(
                !e.to_string().contains("plausible"),
                "a wider range lets them in: {e}"
            );
        }

        let p = grid(
            dir.path(),
            "a.asc",
            Some(r#"GEOGCS["WGS 84",AUTHORITY["EPSG","4326"]]"#),
        );
        for text in [
            "secret = 1\n",
            "accuracy_m = \"secret\"\n",
            "secret\n",
            "crs = \"secret\"\n",
        ] {
            std::fs::write(sidecar_path(&p), text).unwrap();
            let e = prepare(&p, &settings()).unwrap_err().to_string();
            assert!(
                e.contains("sidecar") && !e.contains("secret"),
                "{text:?}: {e}"
            );
        }
        std::fs::write(sidecar_path(&p), vec![b'#'; 100_000]).unwrap();
        let e = prepare(&p, &settings()).unwrap_err().to_string();
        assert!(e.contains("not a sidecar"), "{e}");
    }

    #[test]
    fn a_crs_is_resolved_named_or_refused_when_the_sidecar_contradicts_it() {
        let dir = tempfile::tempdir().unwrap();
        let lambert = r#"PROJCS["RGF93_Lambert_93",GEOGCS["GCS_RGF_1993",DATUM["D_RGF_1993",SPHEROID["GRS_1980",6378137.0,298.257222101]]],PROJECTION["Lambert_Conformal_Conic"]]"#;
        let p = grid(dir.path(), "l.asc", Some(lambert));
        let e = prepare(&p, &settings()).unwrap_err().to_string();
        assert!(e.contains("RGF93_Lambert_93") && e.contains("crs"), "{e}");
        // A sidecar may name the code for a CRS the file only describes...
        std::fs::write(sidecar_path(&p), "crs = \"EPSG:2154\"\n").unwrap();
        assert_eq!(prepare(&p, &settings()).unwrap().survey.crs, Some(2154));
        // ...but not contradict one the file states.
        let q = grid(
            dir.path(),
            "g.asc",
            Some(r#"GEOGCS["WGS 84",AUTHORITY["EPSG","4326"]]"#),
        );
        std::fs::write(sidecar_path(&q), "crs = \"EPSG:32630\"\n").unwrap();
        let e = prepare(&q, &settings()).unwrap_err().to_string();
        assert!(e.contains("EPSG:32630") && e.contains("EPSG:4326"), "{e}");
        let none = grid(dir.path(), "n.asc", None);
        let e = prepare(&none, &settings()).unwrap_err().to_string();
        assert!(e.contains("has no CRS"), "{e}");
    }
}
