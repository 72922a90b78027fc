//! `patchwork export`: the web pyramid as one file to host without a server (PMTiles,
//! MBTiles), made in this process from the store as the daemon's HTTP server makes its tiles;
//! or a region at a resolution as a cloud-optimized GeoTIFF.

use super::Fail;
use clap::{Args, ValueEnum};
use patchwork::config::Config;
use patchwork::engine::{Engine, Heights};
use patchwork::serve::export::cog::CogPlan;
use patchwork::serve::export::{self, Area, Container, Image, Plan, Progress};
use patchwork::serve::grpc::Service;
use patchwork::serve::web::{Encoding, Web};
use patchwork_core::geom::Aabb;
use patchwork_core::resample::Cancel;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Args)]
pub struct ExportArgs {
    /// The file to write. A partial export of the same options beside it (OUT.part) is
    /// carried on from where it stopped.
    pub out: PathBuf,
    /// The kind of file; by default, from OUT's extension (.pmtiles, .mbtiles, .tif).
    #[arg(long, value_enum)]
    pub format: Option<FormatArg>,
    /// How heights are coded in the tiles' colours.
    #[arg(long, value_enum, default_value_t = EncodingArg::Terrarium)]
    pub encoding: EncodingArg,
    /// The tiles' image: lossless WebP (about 0.6× the bytes) or PNG.
    #[arg(long, value_enum, default_value_t = ImageArg::Webp)]
    pub image: ImageArg,
    /// Pixels on a tile's side: 256 or 512.
    #[arg(long, default_value_t = 512)]
    pub size: u32,
    /// The zooms, as A-B (or one zoom); by default 0 to the deepest worth having.
    #[arg(long, value_name = "A-B")]
    pub zooms: Option<String>,
    /// West,south,east,north in degrees: only the tiles touching it. For a COG, the
    /// region XMIN,YMIN,XMAX,YMAX in --crs (required).
    #[arg(
        long,
        value_name = "W,S,E,N",
        allow_hyphen_values = true,
        conflicts_with = "geojson"
    )]
    pub roi: Option<String>,
    /// A COG's pixel size, in --crs's units (required for a COG).
    #[arg(long, value_name = "R")]
    pub resolution: Option<f64>,
    /// A COG's CRS (an EPSG code, a WKT or a PROJ string): --roi is in it, and so is the
    /// raster. The store's by default.
    #[arg(long, value_name = "CRS")]
    pub crs: Option<String>,
    /// A GeoJSON file of polygons (a Polygon, a MultiPolygon, features of them): only the
    /// tiles touching them. By default, the surveys' footprints.
    #[arg(long, value_name = "FILE")]
    pub geojson: Option<PathBuf>,
    /// The cut's error, metres; by default each zoom's own, as the HTTP server's (0 for a
    /// COG: the most accurate the store holds).
    #[arg(long, value_name = "M")]
    pub error: Option<f64>,
    /// What the heights are measured from: store (the store's vertical CRS), ellipsoid, or
    /// a vertical CRS as EPSG:n.
    #[arg(long, default_value = "store")]
    pub heights: String,
    /// The store; the config's data_dir by default. A daemon's store is exported from a
    /// replica of it, or with the daemon stopped: one process opens a store at a time.
    #[arg(long, value_name = "DIR")]
    pub data_dir: Option<PathBuf>,
    #[arg(long, env = "PATCHWORK_CONFIG", value_name = "FILE")]
    pub config: Option<PathBuf>,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum FormatArg {
    Pmtiles,
    Mbtiles,
    Cog,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum EncodingArg {
    Terrarium,
    Mapbox,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum ImageArg {
    Webp,
    Png,
}

/// `A-B` or `A`.
fn zooms(s: &str) -> Result<(u32, u32), Fail> {
    let bad = || format!("--zooms: expected A-B, as 0-12, got {s:?}");
    let (a, b) = s.split_once('-').unwrap_or((s, s));
    let a: u32 = a.trim().parse().map_err(|_| bad())?;
    let b: u32 = b.trim().parse().map_err(|_| bad())?;
    Ok((a, b))
}

pub async fn export(args: ExportArgs) -> Result<(), Fail> {
    let format = match args.format {
        Some(f) => f,
        None => match args.out.extension().and_then(|e| e.to_str()) {
            Some("pmtiles") => FormatArg::Pmtiles,
            Some("mbtiles") => FormatArg::Mbtiles,
            Some("tif" | "tiff") => FormatArg::Cog,
            _ => {
                return Err(format!(
                    "{}: say --format pmtiles, mbtiles or cog, or name the file .pmtiles, \
                     .mbtiles or .tif",
                    args.out.display()
                )
                .into())
            }
        },
    };
    let container = match format {
        FormatArg::Pmtiles => Container::Pmtiles,
        FormatArg::Mbtiles => Container::Mbtiles,
        FormatArg::Cog => return cog(args).await,
    };
    let area = match (&args.roi, &args.geojson) {
        (Some(r), _) => {
            let [w, s, e, n] = super::numbers::<4>(r, "--roi")?;
            let lon = -180.0..=180.0;
            let lat = -90.0..=90.0;
            let valid = w < e
                && s < n
                && lon.contains(&w)
                && lon.contains(&e)
                && lat.contains(&s)
                && lat.contains(&n);
            if !valid {
                return Err(
                    format!("--roi: expected west,south,east,north in degrees, got {r:?}").into(),
                );
            }
            Some(Area::Bounds(Aabb::new(w, s, e, n)))
        }
        (None, Some(f)) => {
            let text = std::fs::read_to_string(f)
                .map_err(|e| format!("cannot read {}: {e}", f.display()))?;
            Some(Area::from_geojson(&text).map_err(|e| format!("{}: {e}", f.display()))?)
        }
        (None, None) => None,
    };
    let heights = Heights::parse(&args.heights).map_err(|e| format!("--heights: {e}"))?;
    let engine = open(&args).await?;
    let (_stopping, watch) = tokio::sync::watch::channel(false);
    let web = Web::new(Service::new(engine.clone(), watch));
    let zooms = match &args.zooms {
        Some(z) => zooms(z)?,
        None => {
            // As deep as the finest survey's cells call for, as TileJSON says.
            let max = web.pyramid(&engine).web_max;
            (
                0,
                if args.size == 512 {
                    max.saturating_sub(1)
                } else {
                    max
                },
            )
        }
    };
    let plan = Plan {
        container,
        encoding: match args.encoding {
            EncodingArg::Terrarium => Encoding::Terrarium,
            EncodingArg::Mapbox => Encoding::Mapbox,
        },
        image: match args.image {
            ImageArg::Webp => Image::Webp,
            ImageArg::Png => Image::Png,
        },
        size: args.size,
        zooms,
        area,
        error: args.error,
        heights,
    };
    // Ctrl-C stops between batches, keeping every tile made for the next run.
    let cancel = stop_on_ctrl_c();
    let out = args.out.clone();
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{bar:30} {pos}/{len} tiles {per_sec} {elapsed}<{eta} {msg}",
        )
        .expect("template"),
    );
    let shown = bar.clone();
    let started = std::time::Instant::now();
    let summary = tokio::task::spawn_blocking(move || {
        export::export(&web, &plan, &out, &cancel, &mut |p: Progress| {
            shown.set_length(p.total);
            shown.set_position(p.done);
            shown.set_message(format!(
                "{} MB{}",
                p.bytes >> 20,
                if p.kept > 0 {
                    format!(", {} kept from before", p.kept)
                } else {
                    String::new()
                }
            ));
        })
    })
    .await?;
    bar.finish_and_clear();
    let s = summary?;
    let secs = started.elapsed().as_secs_f64();
    println!(
        "wrote {}: {} tiles ({} distinct, {} kept from before) of zooms {}-{}, {} bytes, in {:.1} s ({:.0} tiles/s)",
        args.out.display(),
        s.progress.total,
        s.distinct,
        s.progress.kept,
        zooms.0,
        zooms.1,
        s.file_bytes,
        secs,
        s.progress.total as f64 / secs.max(1e-9),
    );
    if let Some(e) = s.coarsened {
        println!("some tiles were made at an error of up to {e} m: more patches than limits.max_web_tile_patches at the one asked");
    }
    if let Some(w) = s.warning {
        println!("warning: {w}");
    }
    Ok(())
}

/// The store, opened in this process.
async fn open(args: &ExportArgs) -> Result<Arc<Engine>, Fail> {
    let mut cfg = Config::load(args.config.as_deref())?;
    if let Some(d) = &args.data_dir {
        cfg.data_dir = d.clone();
    }
    let dir = cfg.data_dir.clone();
    let engine = tokio::task::spawn_blocking(move || Engine::open(cfg))
        .await?
        .map_err(|e| format!("cannot open the store in {}: {e}", dir.display()))?;
    Ok(Arc::new(engine))
}

/// A cancel that Ctrl-C sets.
fn stop_on_ctrl_c() -> Cancel {
    let cancel = Cancel::default();
    let c = cancel.clone();
    tokio::spawn(async move {
        if tokio::signal::ctrl_c().await.is_ok() {
            c.cancel();
        }
    });
    cancel
}

/// `--format cog`.
async fn cog(args: ExportArgs) -> Result<(), Fail> {
    let roi = args
        .roi
        .as_deref()
        .ok_or("a COG needs its region: --roi XMIN,YMIN,XMAX,YMAX in --crs")?;
    let [xmin, ymin, xmax, ymax] = super::numbers::<4>(roi, "--roi")?;
    let resolution = args
        .resolution
        .ok_or("a COG needs its pixel size: --resolution R in --crs's units")?;
    let crs = match &args.crs {
        Some(c) => Some(patchwork_core::crs::Crs::parse(c).map_err(|e| format!("--crs: {e}"))?),
        None => None,
    };
    let plan = CogPlan {
        roi: Aabb::new(xmin, ymin, xmax, ymax),
        crs,
        resolution,
        error: args.error.unwrap_or(0.0),
        heights: Heights::parse(&args.heights).map_err(|e| format!("--heights: {e}"))?,
    };
    let engine = open(&args).await?;
    let cancel = stop_on_ctrl_c();
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} blocks {elapsed}<{eta}")
            .expect("template"),
    );
    let shown = bar.clone();
    let out = args.out.clone();
    let started = std::time::Instant::now();
    let s = tokio::task::spawn_blocking(move || {
        export::cog::write(&engine, &plan, &out, &cancel, &mut |p: Progress| {
            shown.set_length(p.total);
            shown.set_position(p.done);
        })
    })
    .await?;
    bar.finish_and_clear();
    let s = s?;
    println!(
        "wrote {}: {} x {} samples and {} overviews, {} voids, {} bytes, in {:.1} s{}",
        args.out.display(),
        s.size.0,
        s.size.1,
        s.levels - 1,
        s.voids,
        s.file_bytes,
        started.elapsed().as_secs_f64(),
        if s.frame_error_m > 0.0 {
            format!(", heights' frame within {:.3} m", s.frame_error_m)
        } else {
            String::new()
        }
    );
    Ok(())
}
