//! The tile pyramids over the store as the web clients see them: where the surveys lie in
//! longitude and latitude, how deep each pyramid goes, which tiles hold data; and the
//! documents that tell the clients so (TileJSON, Cesium's layer.json).

use patchwork_core::geom::tiles::{self, geographic, mercator, TileRange};
use patchwork_core::geom::Aabb;
use patchwork_engine::{Engine, Event, Footprint};
use serde_json::{json, Value};

/// Samples a side of a quantized-mesh tile's grid: 2^8 + 1, as RTIN needs, and fine enough that
/// a level's grid reaches a one-arc-second survey's cells at level 12.
pub const TERRAIN_GRID: usize = 257;

/// The store's extent and depth, from the footprints of its surveys.
#[derive(Clone, Debug)]
pub struct Pyramid {
    /// Where each survey lies, in longitude and latitude.
    pub footprints: Vec<Footprint>,
    /// The union of the footprints, degrees; None for an empty store.
    pub bounds: Option<Aabb>,
    /// The deepest level worth asking for: past it a client only magnifies what it has.
    pub web_max: u32,
    /// The same for the quantized-mesh pyramid (257-sample tiles, geographic TMS).
    pub terrain_max: u32,
    /// What the tiles' heights are measured from: the store's vertical CRS, as its key and
    /// its name; None where no survey or setting has named one.
    pub vertical: Option<(String, String)>,
    /// Whether the store's heights can be carried above the ellipsoid, as quantized-mesh
    /// tiles carry them then.
    pub ellipsoid: bool,
}

impl Pyramid {
    /// The pyramids of a store with no survey.
    pub fn empty() -> Pyramid {
        Pyramid {
            footprints: Vec::new(),
            bounds: None,
            web_max: 0,
            terrain_max: 0,
            vertical: None,
            ellipsoid: false,
        }
    }

    /// The frame the raster tiles' heights are in, as TileJSON says it: the store's,
    /// measured from its vertical CRS (named beside it), unless a tile URL asks otherwise.
    fn heights(&self) -> (Value, Value) {
        let vertical = match &self.vertical {
            Some((key, name)) => json!({"key": key, "name": name}),
            None => Value::Null,
        };
        (json!("store"), vertical)
    }

    /// The part of `lonlat` where any survey's data can reach (the union of the footprints'
    /// reaches), degrees; None where it holds none, or no area.
    pub fn reach_within(&self, lonlat: &Aabb) -> Option<Aabb> {
        self.footprints
            .iter()
            .map(|f| f.reach)
            .reduce(|a, b| a.union(&b))?
            .intersection(lonlat)
            .filter(|b| b.width() > 0.0 && b.height() > 0.0)
    }

    /// The ids of the surveys whose samples, edge patches or coarser levels can reach into
    /// `lonlat`.
    pub fn near(&self, lonlat: &Aabb) -> Vec<u64> {
        self.footprints
            .iter()
            .filter(|f| f.reach.intersects(lonlat))
            .map(|f| f.id.0)
            .collect()
    }

    /// What names the set of surveys: it changes whenever a survey comes or goes.
    pub fn version(&self) -> String {
        let mut h = blake3::Hasher::new();
        for f in &self.footprints {
            h.update(&f.id.0.to_le_bytes());
        }
        h.finalize().to_hex()[..16].to_string()
    }

    /// The pyramids over the surveys in `engine`'s store now, each as deep as its finest
    /// survey's cells call for.
    pub fn of(engine: &Engine) -> Pyramid {
        let footprints = engine.footprints();
        let bounds = footprints
            .iter()
            .map(|f| f.bounds)
            .reduce(|a, b| a.union(&b));
        let finest = footprints
            .iter()
            .map(|f| f.cell_deg)
            .filter(|c| *c > 0.0)
            .fold(f64::INFINITY, f64::min);
        let (web_max, terrain_max) = if finest.is_finite() {
            (
                tiles::finest_level(360.0, 256, finest),
                tiles::finest_level(180.0, (TERRAIN_GRID - 1) as u32, finest),
            )
        } else {
            (0, 0)
        };
        Pyramid {
            footprints,
            bounds,
            web_max,
            terrain_max,
            vertical: engine
                .vertical_crs()
                .map(|v| (v.key().to_string(), v.label())),
            ellipsoid: engine
                .can_give(&patchwork_engine::Heights::ellipsoid())
                .is_ok(),
        }
    }

    /// The quantized-mesh tiles that hold data, level by level to `terrain_max`: a range per
    /// survey (ranges may overlap, as layer.json allows). Level 0 lists both root tiles,
    /// which Cesium needs whatever the data.
    pub fn terrain_available(&self) -> Vec<Vec<TileRange>> {
        (0..=self.terrain_max)
            .map(|z| {
                if z == 0 {
                    return vec![TileRange {
                        z,
                        x0: 0,
                        y0: 0,
                        x1: 1,
                        y1: 0,
                    }];
                }
                let mut ranges: Vec<TileRange> = self
                    .footprints
                    .iter()
                    .map(|f| geographic::over(z, &f.bounds))
                    .collect();
                ranges.sort_by_key(|r| (r.x0, r.y0, r.x1, r.y1));
                ranges.dedup();
                ranges
            })
            .collect()
    }

    /// The TileJSON of the raster-DEM tiles, whose template is `tiles`.
    pub fn tilejson(
        &self,
        tiles: String,
        size: u32,
        encoding: &str,
        within: Option<&Aabb>,
        frame: &patchwork_engine::Heights,
    ) -> Value {
        let b = self.bounds.unwrap_or(Aabb::new(-180.0, -85.0, 180.0, 85.0));
        let c = [(b.min[0] + b.max[0]) / 2.0, (b.min[1] + b.max[1]) / 2.0];
        let (mut heights, vertical) = self.heights();
        if *frame != patchwork_engine::Heights::Store {
            // The tile URLs ask for another frame.
            heights = json!(frame.key());
        }
        // 512-pixel tiles hold a level's detail one level up.
        let max = if size == 512 {
            self.web_max.saturating_sub(1)
        } else {
            self.web_max
        };
        json!({
            "tilejson": "3.0.0",
            "name": "patchwork",
            "description": "heights of the store's surveys, resampled in EPSG:3857",
            "tiles": [tiles],
            "scheme": "xyz",
            "minzoom": 0,
            "maxzoom": max,
            "bounds": [b.min[0], b.min[1].max(-tiles::MERCATOR_MAX_LAT), b.max[0], b.max[1].min(tiles::MERCATOR_MAX_LAT)],
            "center": [c[0], c[1], max.min(10)],
            "tileSize": size,
            "encoding": encoding,
            "heights": heights,
            "vertical_crs": vertical,
            "attribution": self.attribution(within),
        })
    }

    /// Cesium's layer.json. `version` changes with the data, so that a client's cache of
    /// tile URLs (`{version}` is in them) goes with it.
    pub fn layer_json(&self, version: &str, query: &str) -> Value {
        let b = self.bounds.unwrap_or(Aabb::new(-180.0, -90.0, 180.0, 90.0));
        let available: Vec<Vec<Value>> = self
            .terrain_available()
            .iter()
            .map(|level| {
                level
                    .iter()
                    .map(|r| json!({"startX": r.x0, "startY": r.y0, "endX": r.x1, "endY": r.y1}))
                    .collect()
            })
            .collect();
        let sep = if query.is_empty() { "" } else { "&" };
        // Cesium's frame where the store's heights can be carried there; the tiles say so
        // in a Warning header where they cannot.
        let (heights, vertical) = match self.ellipsoid {
            true => (json!("ellipsoid"), self.heights().1),
            false => self.heights(),
        };
        json!({
            "tilejson": "2.1.0",
            "name": "patchwork",
            "description": "quantized-mesh tiles of the store's surveys",
            "version": version,
            "format": "quantized-mesh-1.0",
            "scheme": "tms",
            "projection": "EPSG:4326",
            "tiles": [format!("{{z}}/{{x}}/{{y}}.terrain?v={{version}}{sep}{query}")],
            "minzoom": 0,
            "maxzoom": self.terrain_max,
            "bounds": [b.min[0], b.min[1], b.max[0], b.max[1]],
            "available": available,
            "extensions": ["octvertexnormals", "watermask", "metadata"],
            // Tiles of levels 0, 10, 20 … tell in their metadata which tiles of the next ten
            // levels exist (`available` above says the same for every level); Cesium asks for
            // the metadata extension only where this is set.
            "metadataAvailability": super::terrain::METADATA_LEVELS,
            "attribution": self.attribution(None),
            "heights": heights,
            "vertical_crs": vertical,
        })
    }

    /// What a map credits for the surveys whose footprints meet `within` (every survey where
    /// None): each one's attribution, else its title, once each, in id order, joined by
    /// "; ". Empty where no sidecar says anything.
    pub fn attribution(&self, within: Option<&Aabb>) -> String {
        let mut credits: Vec<&str> = Vec::new();
        for f in &self.footprints {
            if within.is_some_and(|w| !w.intersects(&f.bounds)) {
                continue;
            }
            let credit = f.about.attribution.as_deref().or(f.about.title.as_deref());
            if let Some(c) = credit {
                if !credits.contains(&c) {
                    credits.push(c);
                }
            }
        }
        credits.join("; ")
    }

    /// The footprints as GeoJSON, each with its survey's file and what its sidecar says.
    pub fn geojson(&self) -> Value {
        let features: Vec<Value> = self
            .footprints
            .iter()
            .map(|f| {
                let a = &f.about;
                json!({
                    "type": "Feature",
                    "properties": {
                        "id": f.id.to_string(),
                        "accuracy_m": f.accuracy_m,
                        "file": file_name(&f.file),
                        "title": a.title,
                        "license": a.license,
                        "attribution": a.attribution,
                        "acquired": a.acquired,
                    },
                    "geometry": {"type": "Polygon", "coordinates": [f.ring]},
                })
            })
            .collect();
        json!({"type": "FeatureCollection", "features": features})
    }
}

/// A source's file name without its folders: where the daemon's inbox is is not a web
/// client's business.
pub fn file_name(source: &str) -> &str {
    std::path::Path::new(source)
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or(source)
}

/// Where a change to the store changed the terrain, and the tiles it invalidated.
#[derive(Clone, Debug, PartialEq)]
pub struct Changed {
    /// Degrees.
    pub lonlat: Aabb,
    /// Web Mercator XYZ ranges, one a level from 0 to [`tiles::MAX_LEVEL`], and the
    /// geographic TMS ranges of the quantized-mesh tiles likewise.
    pub web: Vec<TileRange>,
    /// The geographic TMS ranges of the quantized-mesh tiles, one a level likewise.
    pub terrain: Vec<TileRange>,
}

impl Changed {
    /// What `e` changed, read against the store as it is now; None for a change of nothing
    /// served (a failure).
    pub fn of(engine: &Engine, e: &Event) -> Option<Changed> {
        let lonlat = engine.to_lonlat(&e.area?)?;
        // Every level a client may have asked for, not only those the surveys now in the
        // store reach: a survey retired was perhaps the finest.
        Some(Changed {
            web: (0..=tiles::MAX_LEVEL)
                .map(|z| mercator::over(z, &lonlat))
                .collect(),
            terrain: (0..=tiles::MAX_LEVEL)
                .map(|z| geographic::over(z, &lonlat))
                .collect(),
            lonlat,
        })
    }
}
