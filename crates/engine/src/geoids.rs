//! The geoid grids heights are carried between vertical CRSs with: those the config's
//! `[vertical.geoids]` names, else, for EGM96 and EGM2008, the grids PROJ's packages install
//! (Debian's `proj-data` puts `egm96_15.gtx` in `/usr/share/proj`), so that a fresh machine
//! with that package gives Cesium ellipsoidal heights without a line of config.

use crate::ingest::IngestError;
use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::Crs;
use patchwork_core::model::geoid::{Geoid, Shift};
use patchwork_core::sync::lock;
use patchwork_read::ReadLimits;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// The grids PROJ distributes for the global geoid models, by vertical CRS, most accurate
/// first: PROJ's own GeoTIFF name, then the GTX that Debian's `proj-data` ships.
const KNOWN: [(&str, &[&str]); 2] = [
    ("EPSG:5773", &["us_nga_egm96_15.tif", "egm96_15.gtx"]),
    ("EPSG:3855", &["us_nga_egm08_25.tif", "egm08_25.gtx"]),
];

/// Where PROJ's packages and `PROJ_DATA` put grids.
fn proj_dirs() -> Vec<PathBuf> {
    let mut dirs = Vec::new();
    for var in ["PROJ_DATA", "PROJ_LIB"] {
        if let Some(v) = std::env::var_os(var) {
            dirs.extend(std::env::split_paths(&v));
        }
    }
    dirs.extend(["/usr/share/proj", "/usr/local/share/proj"].map(PathBuf::from));
    dirs
}

/// The grid files a vertical CRS's conversions can be found under in PROJ's directories,
/// as a message names them; empty for a CRS PROJ ships no global grid for.
pub fn known_files(v: &VerticalCrs) -> Vec<&'static str> {
    KNOWN
        .iter()
        .find(|(k, _)| *k == v.key())
        .map(|(_, f)| f.to_vec())
        .unwrap_or_default()
}

/// The geoid grids in use, read on first use and kept.
#[derive(Debug, Default)]
pub struct Geoids {
    /// Grid files by the key of the vertical CRS they relate to the ellipsoid: the config's.
    paths: BTreeMap<String, PathBuf>,
    /// Those found in PROJ's directories for a CRS the config names none for.
    found: BTreeMap<String, PathBuf>,
    loaded: Mutex<HashMap<String, Arc<Geoid>>>,
    limits: ReadLimits,
}

impl Geoids {
    /// The grids of the config's `[vertical.geoids]` (keys that do not parse are left out:
    /// the config's validation refuses them), and with `proj_data`, those of PROJ's
    /// directories for EGM96 and EGM2008 where the config names none.
    pub fn new(paths: &BTreeMap<String, PathBuf>, proj_data: bool) -> Geoids {
        let paths: BTreeMap<String, PathBuf> = paths
            .iter()
            .filter_map(|(k, p)| Some((VerticalCrs::parse(k).ok()?.key().to_string(), p.clone())))
            .collect();
        let mut found = BTreeMap::new();
        if proj_data {
            let dirs = proj_dirs();
            for (key, files) in KNOWN {
                if paths.contains_key(key) {
                    continue;
                }
                let hit = files
                    .iter()
                    .flat_map(|f| dirs.iter().map(move |d| d.join(f)))
                    .find(|p| p.is_file());
                if let Some(p) = hit {
                    found.insert(key.to_string(), p);
                }
            }
        }
        Geoids {
            paths,
            found,
            loaded: Mutex::new(HashMap::new()),
            limits: ReadLimits::mb(4096),
        }
    }

    /// Reads every grid the config names, so that one that cannot be used is found when the
    /// daemon starts rather than at the first survey that needs it. Grids found in PROJ's
    /// directories are read when first needed.
    pub fn load_all(&self) -> Result<(), IngestError> {
        for key in self.paths.keys() {
            if let Ok(v) = VerticalCrs::parse(key) {
                self.for_conversion(&v, &v, &v)?;
            }
        }
        Ok(())
    }

    /// The grid file heights of `v` are related to the ellipsoid by, if any.
    pub fn path(&self, v: &VerticalCrs) -> Option<&Path> {
        let key = v.key();
        self.paths
            .get(key)
            .or_else(|| self.found.get(key))
            .map(|p| p.as_path())
    }

    /// Whether heights of `v` can be related to the ellipsoid: it is the ellipsoid, or a grid
    /// is known for it.
    pub fn has(&self, v: &VerticalCrs) -> bool {
        v.is_ellipsoidal() || self.path(v).is_some()
    }

    /// How heights are carried from `from` to `to`, the grids they need read.
    pub fn shift(&self, from: &VerticalCrs, to: &VerticalCrs) -> Result<Shift, IngestError> {
        let (geoid_from, geoid_to) = if from.same_reference(to) {
            (None, None)
        } else {
            (
                self.for_conversion(from, from, to)?,
                self.for_conversion(to, from, to)?,
            )
        };
        Ok(Shift {
            from: from.clone(),
            to: to.clone(),
            geoid_from,
            geoid_to,
        })
    }

    /// The geoid of `v` for a conversion from `from` to `to`: None for ellipsoidal heights, an
    /// error naming the config key when no grid is configured.
    pub(crate) fn for_conversion(
        &self,
        v: &VerticalCrs,
        from: &VerticalCrs,
        to: &VerticalCrs,
    ) -> Result<Option<Arc<Geoid>>, IngestError> {
        if v.is_ellipsoidal() {
            return Ok(None);
        }
        let key = v.key().to_string();
        if let Some(g) = lock(&self.loaded).get(&key) {
            return Ok(Some(g.clone()));
        }
        let Some(path) = self.path(v) else {
            return Err(IngestError::NoGeoid {
                from: from.label(),
                to: to.label(),
                missing: v.label(),
                key,
            });
        };
        let bad = |message: String| IngestError::Geoid {
            path: path.to_path_buf(),
            vertical: v.label(),
            message,
        };
        let raster = patchwork_read::gtx::read_geoid_grid(path, &self.limits)
            .map_err(|e| bad(e.to_string()))?;
        let crs = raster.crs.crs.clone().unwrap_or_else(Crs::wgs84);
        let grid = raster.into_grid().map_err(|e| bad(e.to_string()))?;
        let g = Arc::new(
            Geoid::new(v.clone(), grid, crs, path.display().to_string())
                .map_err(|e| bad(e.to_string()))?,
        );
        lock(&self.loaded).insert(key, g.clone());
        Ok(Some(g))
    }
}
