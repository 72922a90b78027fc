//! `patchwork-bench`: speed beside measured accuracy on real surveys, with GDAL, martini and
//! delatin on the same data (docs/BENCHMARKS.md). A crate of its own, outside the workspace's
//! default members, so that the daemon carries none of the bench, its charts or their font.

use clap::Parser;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

// The daemon's allocator, so that what the bench measures (the resident set above all) is
// what the daemon would.
#[global_allocator]
static ALLOCATOR: patchwork_engine::Jemalloc = patchwork_engine::Jemalloc;

/// Measure speed against accuracy on real surveys, with GDAL on the same tiles.
#[derive(Parser)]
#[command(name = "patchwork-bench", version)]
struct Cli {
    /// Surveys to ingest; by default the Copernicus + NASADEM N34W119 pair and N44E005.hgt
    /// from the shared data folder (the committed crops with --smoke).
    files: Vec<PathBuf>,
    /// Where the CSV, charts and tiles go.
    #[arg(long, default_value = "docs/bench")]
    out: PathBuf,
    /// A run of a few seconds that proves the bench still works.
    #[arg(long)]
    smoke: bool,
    /// Skip the comparisons in Python: GDAL on the same tiles, martini and delatin on the
    /// same surveys (python3 -m pip install -r bench/requirements.txt).
    #[arg(long)]
    no_gdal: bool,
    /// Only the mesh triangulations, and their comparison with martini and delatin: a few
    /// minutes where the whole bench takes half an hour.
    #[arg(long)]
    meshes_only: bool,
    /// Only the surveys of two CRSs in one store, and their tiles beside GDAL's warps.
    #[arg(long, conflicts_with = "meshes_only")]
    crs_only: bool,
    /// Only the copies of the surveys (blurred, shifted, offset, coarser) beside their
    /// originals: what the store makes of each, before and after it distrusts them.
    #[arg(long, conflicts_with_all = ["meshes_only", "crs_only"])]
    copies_only: bool,
    /// Only this many draws of degraded copies of the committed crops, each beside its
    /// original: which degradations still displace the original, and by how much.
    #[arg(long, conflicts_with_all = ["meshes_only", "crs_only", "copies_only"])]
    draws: Option<usize>,
    /// The seed of the draws; by default the clock's, printed.
    #[arg(long, requires = "draws")]
    seed: Option<u64>,
    /// Only seed 001's Haar-wavelet estimate of each patch's δ beside the exact δ, on the
    /// surveys (the crops with --smoke): how often and by how much it falls short, its M/N_T,
    /// and its time.
    #[arg(long, conflicts_with_all = ["meshes_only", "crs_only", "copies_only", "draws"])]
    wavelet: bool,
    /// Only the view sessions' flights: bytes a frame, and with a client cache and the
    /// server's prefetch, the frames whole before they are asked for.
    #[arg(long, conflicts_with_all = ["meshes_only", "crs_only", "copies_only", "draws", "wavelet"])]
    sessions: bool,
    /// Only Formula 1 beside the accurate blend on the mixed scenes and the pair: error
    /// against the most accurate survey, slope jumps, patches per sample and time per tile.
    #[arg(long, conflicts_with_all = ["meshes_only", "crs_only", "copies_only", "draws", "wavelet", "sessions"])]
    blend: bool,
    /// Only N abutting grids cut from the first file, dropped into a daemon's inbox at once:
    /// files a second by fifths, seconds a file by store size, and the store's open.
    #[arg(long, value_name = "N", conflicts_with_all = ["meshes_only", "crs_only", "copies_only", "draws", "wavelet", "sessions", "blend"])]
    many: Option<usize>,
    /// Opens the store in this folder and prints its time and memory (what `--many` runs in
    /// a process of its own).
    #[arg(long, hide = true, value_name = "DIR")]
    open_only: Option<PathBuf>,
    /// With --many: keeps the store the files went into in this folder (it must not exist),
    /// for `--open-only` to open again.
    #[arg(long, hide = true, value_name = "DIR", requires = "many")]
    keep_store: Option<PathBuf>,
}

fn main() -> ExitCode {
    // As the daemon does: the ingest figures are the daemon's.
    patchwork_engine::tune_allocator();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("patchwork-bench: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<(), Box<dyn std::error::Error>> {
    let Cli {
        files,
        out,
        smoke,
        no_gdal,
        meshes_only,
        crs_only,
        copies_only,
        draws,
        seed,
        wavelet,
        sessions,
        blend,
        many,
        open_only,
        keep_store,
    } = cli;
    if let Some(dir) = open_only {
        return patchwork_bench::many::open_only(&dir);
    }
    if let Some(n) = draws {
        let seed = seed.unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(1, |d| d.as_nanos() as u64)
        });
        patchwork_bench::draws::run(&out, n, seed)?;
        println!("wrote {}", out.display());
        return Ok(());
    }
    let files = if !files.is_empty() {
        files
    } else if smoke {
        [
            "copernicus_n34w119_crop.tif",
            "nasadem_n34w119_crop.tif",
            "srtm_n44e005_voids_crop.tif",
        ]
        .iter()
        .map(|f| Path::new("tests/data").join(f))
        .collect()
    } else {
        let shared = std::env::var_os("PATCHWORK_SHARED_DATA")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("../shared/data"));
        [
            "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif",
            "NASADEM_HGT_n34w119.tif",
            "N44E005.hgt",
        ]
        .iter()
        .map(|f| shared.join(f))
        .collect()
    };
    if let Some(n) = many {
        patchwork_bench::many::run(&files[0], n, &out, keep_store.as_deref())?;
        println!("wrote {}", out.join("many.csv").display());
        return Ok(());
    }
    if blend {
        patchwork_bench::blend::run(&files, &out, smoke)?;
        println!("wrote {}", out.join("blend.csv").display());
        return Ok(());
    }
    if wavelet {
        patchwork_bench::wavelet::run(&files, &out)?;
        println!("wrote {}", out.join("wavelet.csv").display());
        return Ok(());
    }
    let opts = patchwork_bench::Options {
        files,
        out: out.clone(),
        smoke,
    };
    if sessions {
        patchwork_bench::run_sessions(&opts)?;
        println!("wrote {}", out.display());
        return Ok(());
    }
    if copies_only {
        patchwork_bench::run_copies(&opts)?;
        println!("wrote {}", out.display());
        return Ok(());
    }
    if meshes_only {
        patchwork_bench::run_meshes(&opts)?;
    } else if crs_only {
        patchwork_bench::run_crs(&opts)?;
    } else {
        patchwork_bench::run(&opts)?;
    }
    if !no_gdal && !meshes_only {
        // The main tiles, then those of surveys in two CRSs.
        let runs: &[(&str, &str)] = if crs_only {
            &[("crs_manifest.json", "crs_gdal.csv")]
        } else {
            &[
                ("manifest.json", "gdal.csv"),
                ("crs_manifest.json", "crs_gdal.csv"),
            ]
        };
        for (manifest, csv) in runs {
            let status = std::process::Command::new("python3")
                .arg("bench/gdal_compare.py")
                .arg(out.join("tiles").join(manifest))
                .arg(out.join(csv))
                .status()
                .map_err(|e| {
                    format!(
                        "cannot run python3 for the GDAL comparison: {e}; use --no-gdal to skip it"
                    )
                })?;
            if !status.success() {
                return Err("the GDAL comparison failed (python3 -m pip install -r bench/requirements.txt); use --no-gdal to skip it".into());
            }
        }
    }
    if !no_gdal && !crs_only {
        let status = std::process::Command::new("python3")
            .arg("bench/mesh_compare.py")
            .arg(&out)
            .args(meshes_only.then_some("--meshes-only"))
            .args(if meshes_only { &opts.files[..] } else { &[] })
            .status()
            .map_err(|e| format!("cannot run python3 for the mesh comparison: {e}"))?;
        if !status.success() {
            return Err("the mesh comparison failed (python3 -m pip install -r bench/requirements.txt); use --no-gdal to skip it".into());
        }
    }
    println!("wrote {}", out.display());
    Ok(())
}
