//! `patchwork export`: the web pyramid as one file to host without a server (PMTiles,
//! MBTiles), made in this process from the store, as the daemon's HTTP server makes its tiles.

use super::Fail;
use clap::{Args, ValueEnum};
use patchwork::config::Config;
use patchwork::engine::{Engine, Heights};
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
    /// The kind of file; by default, from OUT's extension (.pmtiles, .mbtiles).
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
    /// West,south,east,north in degrees: only the tiles touching it.
    #[arg(
        long,
        value_name = "W,S,E,N",
        allow_hyphen_values = true,
        conflicts_with = "geojson"
    )]
    pub roi: Option<String>,
    /// A GeoJSON file of polygons (a Polygon, a MultiPolygon, features of them): only the
    /// tiles touching them. By default, the surveys' footprints.
    #[arg(long, value_name = "FILE")]
    pub geojson: Option<PathBuf>,
    /// The cut's error, metres; by default each zoom's own, as the HTTP server's.
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
    let container = match args.format {
        Some(FormatArg::Pmtiles) => Container::Pmtiles,
        Some(FormatArg::Mbtiles) => Container::Mbtiles,
        None => match args.out.extension().and_then(|e| e.to_str()) {
            Some("pmtiles") => Container::Pmtiles,
            Some("mbtiles") => Container::Mbtiles,
            _ => {
                return Err(format!(
                    "{}: say --format pmtiles or mbtiles, or name the file .pmtiles or .mbtiles",
                    args.out.display()
                )
                .into())
            }
        },
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
    let mut cfg = Config::load(args.config.as_deref())?;
    if let Some(d) = args.data_dir {
        cfg.data_dir = d;
    }
    let dir = cfg.data_dir.clone();
    let engine = tokio::task::spawn_blocking(move || Engine::open(cfg))
        .await?
        .map_err(|e| format!("cannot open the store in {}: {e}", dir.display()))?;
    let engine = Arc::new(engine);
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
    let cancel = Cancel::default();
    {
        // Ctrl-C stops between batches, keeping every tile made for the next run.
        let cancel = cancel.clone();
        tokio::spawn(async move {
            if tokio::signal::ctrl_c().await.is_ok() {
                cancel.cancel();
            }
        });
    }
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
