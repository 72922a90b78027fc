//! From a file to a survey: read, apply the sidecar, check the CRS, build the model.

use crate::config::DefaultAccuracy;
use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::Crs;
use patchwork_core::model::accuracy::{AccuracySource, AccuracySpec};
use patchwork_core::model::epoch::Epoch;
use patchwork_core::model::geoid;
use patchwork_core::model::grid::Grid;
use patchwork_core::model::patch::PatchLayout;
use patchwork_core::model::survey::{Recipe, Survey, SurveyError};
use patchwork_read::{
    open_untrusted, read_raster_hashed, OpenError, ReadError, ReadLimits, REFUSED_PATH,
};
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;
use thiserror::Error;

/// Why a file could not be ingested; each message says what to do about it.
#[non_exhaustive]
#[derive(Debug, Error)]
pub enum IngestError {
    /// The file could not be read as a DEM.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// The sidecar could not be read, or says something that cannot be used.
    #[error("sidecar {path}: {message}")]
    Sidecar {
        /// The sidecar, `<file>.toml`.
        path: PathBuf,
        /// What is wrong, without quoting the file.
        message: String,
    },
    /// Neither the file nor a sidecar names a CRS.
    #[error("the file has no CRS: add a sidecar {sidecar} with crs = \"EPSG:…\"")]
    NoCrs {
        /// Where the sidecar that would name it goes.
        sidecar: PathBuf,
    },
    /// The file names a CRS this build cannot read, and no sidecar names one instead.
    #[error(
        "the file's CRS cannot be used ({found}): add a sidecar {sidecar} with crs = \
         \"EPSG:…\" (or a WKT or PROJ string) naming it"
    )]
    UnknownCrs {
        /// What the file names, as it names it.
        found: String,
        /// Where the sidecar that would name it goes.
        sidecar: PathBuf,
    },
    /// The sidecar's `crs` and the file's own differ.
    #[error(
        "sidecar {sidecar} says crs = {sidecar_crs}, but the file itself is in {file_crs}; \
         remove the sidecar's crs or fix the file"
    )]
    CrsConflict {
        /// The sidecar.
        sidecar: PathBuf,
        /// The CRS the sidecar names.
        sidecar_crs: String,
        /// The CRS the file names.
        file_crs: String,
    },
    /// The sidecar's `vertical_crs` and the file's own differ in reference or unit.
    #[error(
        "sidecar {sidecar} says vertical_crs = {sidecar_crs}, but the file itself names \
         {file_crs}; remove the sidecar's vertical_crs or fix the file"
    )]
    VerticalConflict {
        /// The sidecar.
        sidecar: PathBuf,
        /// The vertical CRS the sidecar names.
        sidecar_crs: String,
        /// The vertical CRS the file names.
        file_crs: String,
    },
    /// Converting the heights into the store's vertical CRS needs a geoid grid the config
    /// does not name.
    #[error(
        "the heights are in {from} but the store's are in {to}, and converting them needs a \
         geoid grid for {missing}: name one in the config, [vertical.geoids] \"{key}\" = \
         \"<grid>.tif\" (PROJ's grids, from https://cdn.proj.org, are such GeoTIFFs)"
    )]
    NoGeoid {
        /// The survey's vertical CRS.
        from: String,
        /// The store's vertical CRS.
        to: String,
        /// The vertical CRS whose grid is missing: `from` or `to`.
        missing: String,
        /// The `[vertical.geoids]` key that would name its grid.
        key: String,
    },
    /// A geoid grid the config names could not be read or used.
    #[error("the geoid grid {path} for {vertical}: {message}")]
    Geoid {
        /// The grid file.
        path: PathBuf,
        /// The vertical CRS it is named for.
        vertical: String,
        /// What went wrong.
        message: String,
    },
    /// The heights could not be converted between vertical CRSs.
    #[error("converting the heights between vertical CRSs: {0}")]
    Convert(patchwork_core::model::geoid::GeoidError),
    /// ε, given or estimated, is not below the top of LOD space.
    #[error(
        "accuracy {value} m ({given_by}) is refused: it must be a number of metres in \
         [0, {max}), the top of LOD space (index.max_error); a survey that inaccurate would \
         never serve any answer"
    )]
    BadAccuracy {
        /// ε, in metres.
        value: f64,
        /// Where ε came from: the sidecar, the caller, the config or the estimate.
        given_by: &'static str,
        /// `index.max_error`, which ε must stay below.
        max: f64,
    },
    /// The file's georeference cannot make a grid.
    #[error("georeference: {0}")]
    Grid(patchwork_core::model::grid::GridError),
    /// The survey could not be modelled.
    #[error(transparent)]
    Survey(#[from] SurveyError),
    /// Valid samples lie outside the plausible heights of `[limits]`.
    #[error(
        "{outside} of the valid samples lie outside the plausible heights [{lo}, {hi}] m (they \
         range from {min} to {max} m): the file is not elevation in metres, or its nodata \
         value is not declared; limits.min_height_m and limits.max_height_m set the range"
    )]
    Implausible {
        /// How many samples lie outside.
        outside: u64,
        /// `limits.min_height_m`.
        lo: f64,
        /// `limits.max_height_m`.
        hi: f64,
        /// The lowest valid sample.
        min: f32,
        /// The highest valid sample.
        max: f32,
    },
    /// The path is not where the daemon may read: outside the inbox and the ingest roots, or
    /// led out of them by a symlink. The message says nothing about what is there.
    #[error("{}", REFUSED_PATH)]
    Refused,
    /// The path is a directory.
    #[error("{path} is a directory, not a DEM file")]
    Directory {
        /// The path named.
        path: PathBuf,
    },
    /// The path names something other than a regular file (a device, a socket, a pipe).
    #[error("{path} is not a regular file")]
    NotAFile {
        /// The path named.
        path: PathBuf,
    },
    /// The file could not be opened.
    #[error("cannot read {path}: {source}")]
    Unreadable {
        /// The path named.
        path: PathBuf,
        /// Why it could not be opened.
        source: std::io::Error,
    },
}

// These variants' messages name the inner error already, so it is not also their source: a
// reporter that walks the chain would print it twice.
impl From<patchwork_core::model::geoid::GeoidError> for IngestError {
    fn from(e: patchwork_core::model::geoid::GeoidError) -> Self {
        IngestError::Convert(e)
    }
}

impl From<patchwork_core::model::grid::GridError> for IngestError {
    fn from(e: patchwork_core::model::grid::GridError) -> Self {
        IngestError::Grid(e)
    }
}

/// What `<file>.toml` beside a DEM may say.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sidecar {
    /// ε of the survey, in metres; overrides `--accuracy` and the config.
    pub accuracy_m: Option<f64>,
    /// The file's horizontal CRS: an EPSG code, a WKT or a PROJ string. Must agree with the file's
    /// own where it names one.
    pub crs: Option<String>,
    /// The vertical CRS of the file's heights, "EPSG:n" or "ellipsoidal".
    pub vertical_crs: Option<String>,
    /// A correction of where the survey lies: moved east, north and up by these metres (the
    /// negation of a conflict's `shift_m` puts it where the other survey lies).
    pub offset_m: Option<[f64; 3]>,
    /// What the correction leaves uncertain, metres of height, added to ε (default 0; a
    /// conflict's `rms_after_m` is a safe figure).
    pub offset_error_m: Option<f64>,
    /// The survey's title, for the provenance of its heights.
    pub title: Option<String>,
    /// Its licence ("CC-BY-4.0", a URL, ...).
    pub license: Option<String>,
    /// The attribution its licence asks for, as a map shows it.
    pub attribution: Option<String>,
    /// When it was acquired, in ISO 8601: a year, a month, a day, a date-time, or an interval
    /// of them ("2011-02", "2000-02-11/2000-02-22"). Where surveys disagree because the ground
    /// changed, the one acquired wholly after the other serves; where this says nothing, the
    /// file's own metadata is read, else the epoch is unknown.
    pub acquired: Option<String>,
}

/// The longest text a sidecar's provenance field may hold.
const ABOUT_MOST: usize = 1000;

impl Sidecar {
    /// What it says of where the survey came from, checked: each field a line of at most
    /// [`ABOUT_MOST`] characters.
    pub fn about(&self) -> Result<patchwork_store::form::About, String> {
        let field = |name: &str, v: &Option<String>| -> Result<Option<String>, String> {
            let Some(v) = v else { return Ok(None) };
            let v = v.trim();
            if v.chars().count() > ABOUT_MOST {
                return Err(format!("{name} is longer than {ABOUT_MOST} characters"));
            }
            if v.chars().any(char::is_control) {
                return Err(format!("{name} holds a control character (a line break?)"));
            }
            Ok((!v.is_empty()).then(|| v.to_string()))
        };
        Ok(patchwork_store::form::About {
            title: field("title", &self.title)?,
            license: field("license", &self.license)?,
            attribution: field("attribution", &self.attribution)?,
            acquired: field("acquired", &self.acquired)?,
        })
    }
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
    /// Reading the file and its sidecar.
    Reading,
    /// Building the survey's mipmap and patches.
    Modelling,
    /// Placing the survey's patches in the index.
    Indexing,
    /// Writing the survey to the store.
    Committing,
}

impl Phase {
    /// The phase as progress displays and the API name it.
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
    /// Reading and decoding the file, in ms.
    pub read_ms: u64,
    /// Building the survey from the raster, in ms.
    pub build_ms: u64,
}

/// The sidecar of a DEM: its path with `.toml` added, so that `a.tif` has `a.tif.toml`.
pub fn sidecar_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(".toml");
    PathBuf::from(s)
}

/// The content id of an elevation file as the store records it: the hash of its bytes, and
/// where a sidecar sits beside it, the hash of the sidecar's bytes after a `+`. A file whose
/// sidecar is added, edited or removed is then a new content, and ingested again; a file with
/// no sidecar keeps the id it always had.
pub fn with_sidecar(path: &Path, content: String, roots: Option<&[PathBuf]>) -> String {
    let side = sidecar_path(path);
    if side.symlink_metadata().is_err() {
        return content;
    }
    let bytes = open_untrusted(&side, roots).ok().and_then(|f| {
        let mut bytes = Vec::new();
        std::io::Read::read_to_end(
            &mut std::io::Read::take(f, SIDECAR_MOST as u64 + 1),
            &mut bytes,
        )
        .ok()
        .map(|_| bytes)
    });
    match bytes {
        Some(b) => format!("{content}+{}", &blake3::hash(&b).to_hex()[..16]),
        // One that cannot be read fails the ingest with its own message.
        None => format!("{content}+unreadable"),
    }
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
        "a key other than accuracy_m, crs, vertical_crs, offset_m and offset_error_m"
    } else if msg.starts_with("invalid type") || msg.starts_with("invalid length") {
        "a value of the wrong type (accuracy_m and offset_error_m are numbers, offset_m three \
         numbers, crs and vertical_crs strings like \"EPSG:4326\")"
    } else {
        "something that is not TOML"
    };
    format!(
        "the sidecar has {what}{at}; it may set accuracy_m = <metres>, crs = \"EPSG:<code>\" \
         (or a WKT or PROJ string), vertical_crs = \"EPSG:<code>\", offset_m = [east, north, \
         up] and offset_error_m = <metres>"
    )
}

/// The settings an ingest needs from the store and the config.
#[derive(Clone, Debug)]
pub struct IngestSettings {
    /// `--accuracy` from the caller, which a sidecar overrides.
    pub accuracy: Option<f64>,
    /// The config's `accuracy_m`, for files with neither a sidecar's ε nor the caller's.
    pub default_accuracy: DefaultAccuracy,
    /// Accuracies must stay below this: the top of LOD space.
    pub max_accuracy: f64,
    /// The store's vertical CRS, once it has one: heights in another are converted to it.
    pub store_vertical: Option<VerticalCrs>,
    /// The geoid grids the config names.
    pub geoids: Arc<crate::geoids::Geoids>,
    /// Kernel and margin of the store's patches.
    pub layout: PatchLayout,
    /// How the store builds a survey's mipmap and patches.
    pub recipe: Recipe,
    /// The largest raster one file may decode to, and the folders it may be read from.
    pub read_limits: ReadLimits,
    /// Plausible heights, in metres: a file with a valid sample outside is refused.
    pub heights: (f64, f64),
}

/// A file read and modelled.
#[derive(Clone, Debug)]
pub struct Prepared {
    /// The survey built from the file.
    pub survey: Survey,
    /// Hex BLAKE3 of the file's bytes as they were read to build the survey.
    pub content_id: String,
    /// Where ε came from: the sidecar, the caller, the config or the estimate.
    pub source: AccuracySource,
    /// How long reading and building took.
    pub timings: Timings,
    /// The vertical CRS the file or its sidecar named.
    pub vertical_source: Option<VerticalCrs>,
    /// What converting the heights into the store's vertical CRS added to ε, metres.
    pub vertical_error_m: f64,
    /// What the sidecar says of where the survey came from.
    pub about: patchwork_store::form::About,
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
    // Opened and read once: the content id recorded is that of the bytes parsed.
    let (raster, content_id) = read_raster_hashed(path, &s.read_limits)?;
    let content_id = with_sidecar(path, content_id, roots);
    let read_ms = t0.elapsed().as_millis() as u64;
    check_heights(&raster.samples, s.heights)?;
    // Not the CRS's own error: it quotes the text, and a sidecar could be any file.
    let side_bad = |what: &str, _: patchwork_core::crs::CrsError| IngestError::Sidecar {
        path: sidecar_path(path),
        message: format!(
            "{what} is not a CRS this build can read: give an EPSG code (\"EPSG:4326\"), a WKT \
             or a PROJ string"
        ),
    };
    let side_crs = side
        .crs
        .as_deref()
        .map(|c| Crs::parse(c).map_err(|e| side_bad("crs", e)))
        .transpose()?;
    let file = raster.crs.clone();
    let crs = match (side_crs, file.crs, file.unreadable) {
        (Some(sc), Some(fc), _) if sc != fc => {
            return Err(IngestError::CrsConflict {
                sidecar: sidecar_path(path),
                sidecar_crs: sc.label(),
                file_crs: fc.label(),
            })
        }
        (Some(c), _, _) | (None, Some(c), _) => c,
        (None, None, Some(found)) => {
            return Err(IngestError::UnknownCrs {
                found,
                sidecar: sidecar_path(path),
            })
        }
        (None, None, None) => {
            return Err(IngestError::NoCrs {
                sidecar: sidecar_path(path),
            })
        }
    };
    let side_vertical = side
        .vertical_crs
        .as_deref()
        .map(|c| VerticalCrs::parse(c).map_err(|e| side_bad("vertical_crs", e)))
        .transpose()?;
    let named = match (side_vertical, file.vertical) {
        (Some(sv), Some(fv)) if !sv.same_reference(&fv) || sv.unit_m() != fv.unit_m() => {
            return Err(IngestError::VerticalConflict {
                sidecar: sidecar_path(path),
                sidecar_crs: sv.label(),
                file_crs: fv.label(),
            })
        }
        (Some(v), _) | (None, Some(v)) => Some(v),
        (None, None) => None,
    };
    let t1 = Instant::now();
    phase(Phase::Modelling);
    let file_acquired = raster.acquired.clone();
    let mut grid = raster.into_grid()?;
    // Heights in another vertical CRS than the store's are converted to it; a survey that
    // names none is taken to be in the store's.
    let (vertical, vertical_error_m) = match (&named, &s.store_vertical) {
        (Some(from), Some(to)) => {
            let geoid = |v: &VerticalCrs| s.geoids.for_conversion(v, from, to);
            let (gf, gt) = if from.same_reference(to) {
                (None, None)
            } else {
                (geoid(from)?, geoid(to)?)
            };
            let done = geoid::convert(&mut grid, &crs, from, to, gf.as_ref(), gt.as_ref())?;
            (Some(to.clone()), done.error_m)
        }
        (Some(from), None) => {
            // The store will take this survey's vertical CRS, in metres.
            geoid::convert(&mut grid, &crs, from, from, None, None)?;
            (Some(from.clone()), 0.0)
        }
        (None, to) => (to.clone(), 0.0),
    };
    let mut about = side.about().map_err(|message| IngestError::Sidecar {
        path: sidecar_path(path),
        message,
    })?;
    // The epoch: the sidecar's, else the file's own; never the time the file arrived, which
    // would make the store depend on the order of its files.
    let epoch = match &about.acquired {
        Some(a) => Some(Epoch::parse(a).map_err(|e| IngestError::Sidecar {
            path: sidecar_path(path),
            message: format!("acquired: {e}"),
        })?),
        None => {
            about.acquired = file_acquired;
            about.acquired.as_deref().and_then(|a| Epoch::parse(a).ok())
        }
    };
    let offset_error_m =
        correct(&mut grid, &crs, &side).map_err(|message| IngestError::Sidecar {
            path: sidecar_path(path),
            message,
        })?;
    let added = vertical_error_m + offset_error_m;
    let spec = match spec {
        AccuracySpec::Fixed(a) => AccuracySpec::Fixed(a + added),
        auto => auto,
    };
    let extra = match spec {
        AccuracySpec::Auto => added,
        AccuracySpec::Fixed(_) => 0.0,
    };
    let mut survey = Survey::build_adding(grid, spec, Some(crs), s.layout, s.recipe, extra)?;
    let meta =
        std::sync::Arc::get_mut(&mut survey.meta).expect("a survey just built is not shared");
    meta.vertical = vertical;
    meta.epoch = epoch;
    if survey.accuracy >= s.max_accuracy {
        return Err(IngestError::BadAccuracy {
            value: survey.accuracy,
            given_by: source.as_str(),
            max: s.max_accuracy,
        });
    }
    Ok(Prepared {
        survey,
        content_id,
        source,
        timings: Timings {
            read_ms,
            build_ms: t1.elapsed().as_millis() as u64,
        },
        vertical_source: named,
        vertical_error_m,
        about,
    })
}

/// Applies a sidecar's `offset_m` to a grid: its georeference moved east and north (metres
/// turned into the CRS's units at the grid's middle), its heights raised. Returns what the
/// correction adds to ε.
fn correct(grid: &mut Grid, crs: &Crs, side: &Sidecar) -> Result<f64, String> {
    let error = side.offset_error_m.unwrap_or(0.0);
    if !(error.is_finite() && error >= 0.0) {
        return Err(format!(
            "offset_error_m = {error} is not a height of 0 m or more"
        ));
    }
    let Some([dx, dy, dz]) = side.offset_m else {
        return Ok(error);
    };
    if ![dx, dy, dz].iter().all(|v| v.is_finite() && v.abs() < 1e6) {
        return Err("offset_m must be three finite numbers of metres, under 1,000 km".into());
    }
    let per = if crs.is_geographic() {
        let mid = grid
            .georef
            .to_world(grid.cols as f64 / 2.0, grid.rows as f64 / 2.0);
        patchwork_core::crs::metres_per_degree(mid[1])
    } else {
        [crs.unit_m().unwrap_or(1.0); 2]
    };
    grid.georef.origin[0] += dx / per[0];
    grid.georef.origin[1] += dy / per[1];
    for z in grid.samples.iter_mut() {
        *z += dz as f32;
    }
    Ok(error)
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
    // A name that is not UTF-8 is judged by what it can be read as: such a file is no less
    // a DEM, and is reported rather than passed over.
    let Some(name) = path.file_name().map(|n| n.to_string_lossy()) else {
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
    use crate::error::ingest_reason;
    use crate::Reason;

    fn settings() -> IngestSettings {
        IngestSettings {
            accuracy: None,
            default_accuracy: DefaultAccuracy::Auto,
            max_accuracy: 10_000.0,
            store_vertical: None,
            geoids: Default::default(),
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
    fn a_sidecar_offset_moves_the_survey_and_counts_what_it_leaves_in_its_accuracy() {
        let dir = tempfile::tempdir().unwrap();
        let utm = r#"PROJCS["WGS_1984_UTM_Zone_31N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]]],PROJECTION["Transverse_Mercator"],PARAMETER["False_Easting",500000.0],PARAMETER["False_Northing",0.0],PARAMETER["Central_Meridian",3.0],PARAMETER["Scale_Factor",0.9996],PARAMETER["Latitude_Of_Origin",0.0],UNIT["Meter",1.0]]"#;
        let p = grid(dir.path(), "a.asc", Some(utm));
        let mut s = settings();
        s.default_accuracy = DefaultAccuracy::Metres(2.0);
        let plain = prepare(&p, &s).unwrap().survey;
        std::fs::write(
            sidecar_path(&p),
            "offset_m = [-30.0, 12.5, 4.0]\noffset_error_m = 1.5\n",
        )
        .unwrap();
        let moved = prepare(&p, &s).unwrap().survey;
        let (a, b) = (&plain.levels[0], &moved.levels[0]);
        assert_eq!(
            [
                b.georef.origin[0] - a.georef.origin[0],
                b.georef.origin[1] - a.georef.origin[1]
            ],
            [-30.0, 12.5]
        );
        assert!(a.samples.iter().zip(&b.samples).all(|(x, y)| y - x == 4.0));
        assert_eq!(moved.accuracy, plain.accuracy + 1.5);
        for bad in [
            "offset_m = [1.0, 2.0]",
            "offset_m = [1e9, 0.0, 0.0]",
            "offset_error_m = -1.0",
        ] {
            std::fs::write(sidecar_path(&p), format!("{bad}\n")).unwrap();
            let err = prepare(&p, &s).unwrap_err();
            assert_eq!(ingest_reason(&err), Reason::Sidecar, "{bad}: {err}");
            let e = err.to_string();
            assert!(e.contains("offset"), "{bad}: {e}");
        }
    }

    #[test]
    fn accuracy_comes_from_sidecar_flag_or_config_and_must_stay_below_the_top() {
        let dir = tempfile::tempdir().unwrap();
        let utm = r#"PROJCS["WGS_1984_UTM_Zone_31N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]]],PROJECTION["Transverse_Mercator"],PARAMETER["False_Easting",500000.0],PARAMETER["False_Northing",0.0],PARAMETER["Central_Meridian",3.0],PARAMETER["Scale_Factor",0.9996],PARAMETER["Latitude_Of_Origin",0.0],UNIT["Meter",1.0]]"#;
        let p = grid(dir.path(), "a.asc", Some(utm));
        let mut s = settings();
        let got = prepare(&p, &s).unwrap();
        assert_eq!(got.source, AccuracySource::Estimated);
        assert_eq!(
            got.survey.crs.as_ref().and_then(|c| c.epsg_code()),
            Some(32631),
            "the ESRI UTM zone resolves"
        );
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
            let err = prepare(&p, &s).unwrap_err();
            assert_eq!(ingest_reason(&err), Reason::BadAccuracy, "{bad}: {err}");
            let e = err.to_string();
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
        let err = prepare(&hgt, &settings()).unwrap_err();
        assert_eq!(ingest_reason(&err), Reason::Implausible, "{err}");
        let e = err.to_string();
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
            let err = prepare(&p, &settings()).unwrap_err();
            assert_eq!(ingest_reason(&err), Reason::Sidecar, "{text:?}: {err}");
            let e = err.to_string();
            assert!(
                e.contains("sidecar") && !e.contains("secret"),
                "{text:?}: {e}"
            );
        }
        std::fs::write(sidecar_path(&p), vec![b'#'; 100_000]).unwrap();
        let err = prepare(&p, &settings()).unwrap_err();
        assert_eq!(ingest_reason(&err), Reason::Sidecar, "{err}");
        assert!(err.to_string().contains("not a sidecar"), "{err}");
    }

    #[test]
    fn a_crs_is_resolved_named_or_refused_when_the_sidecar_contradicts_it() {
        let dir = tempfile::tempdir().unwrap();
        // A projection this build does not have.
        let bonne = r#"PROJCS["Bonne_Custom",GEOGCS["GCS_RGF_1993",DATUM["D_RGF_1993",SPHEROID["GRS_1980",6378137.0,298.257222101]]],PROJECTION["Bonne"],PARAMETER["Standard_Parallel_1",45.0]]"#;
        let p = grid(dir.path(), "l.asc", Some(bonne));
        let err = prepare(&p, &settings()).unwrap_err();
        assert_eq!(ingest_reason(&err), Reason::Crs, "{err}");
        let e = err.to_string();
        assert!(e.contains("Bonne_Custom") && e.contains("crs"), "{e}");
        // A sidecar may name the code for a CRS the file only describes...
        std::fs::write(sidecar_path(&p), "crs = \"EPSG:2154\"\n").unwrap();
        assert_eq!(
            prepare(&p, &settings())
                .unwrap()
                .survey
                .crs
                .as_ref()
                .and_then(|c| c.epsg_code()),
            Some(2154)
        );
        // ...but not contradict one the file states.
        let q = grid(
            dir.path(),
            "g.asc",
            Some(r#"GEOGCS["WGS 84",AUTHORITY["EPSG","4326"]]"#),
        );
        std::fs::write(sidecar_path(&q), "crs = \"EPSG:32630\"\n").unwrap();
        let err = prepare(&q, &settings()).unwrap_err();
        assert_eq!(ingest_reason(&err), Reason::CrsConflict, "{err}");
        let e = err.to_string();
        assert!(e.contains("EPSG:32630") && e.contains("EPSG:4326"), "{e}");
        let none = grid(dir.path(), "n.asc", None);
        let err = prepare(&none, &settings()).unwrap_err();
        assert_eq!(ingest_reason(&err), Reason::Crs, "{err}");
        assert!(err.to_string().contains("has no CRS"), "{err}");
    }
}
