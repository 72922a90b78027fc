//! A country of surveys (`patchwork-bench --many N`): N abutting grids of real heights, cut from
//! the first file (the Copernicus tile N34W119), dropped into a daemon's inbox at once.
//!
//! The daemon is this process's engine with its inbox watcher, as `patchwork serve` runs it.
//! The files are written beside the inbox and renamed into it one after another, as a copy
//! tool that finishes each file does, so the watcher takes each as complete. Reported:
//!
//! - files a second in each fifth of the files, and the last fifth's time over the first's
//!   (the cost of a commit as the store grows; the target is ≤ 1.3×);
//! - seconds a file by store size, over windows of a fiftieth of the files;
//! - the open of the store in a fresh process (this binary again, `--open-only`): its time,
//!   and the resident memory it adds to the process (Linux's VmRSS, less the process's before
//!   the open), beyond what the open of an empty store adds, a patch and a survey;
//! - with the chunks on an object store (the environment's overrides, as the daemon takes
//!   them: `PATCHWORK_STORAGE_BACKEND=folder PATCHWORK_STORAGE_FOLDER=DIR`, or S3's), the
//!   start of a read replica in a fresh process: from an empty folder, the newest snapshot and
//!   the logs after it, to a terrain it serves.

use crate::Fail;
use patchwork_core::model::grid::Grid;
use patchwork_engine::config::Config;
use patchwork_engine::Engine;
use std::io::Write;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// What one run measured.
#[derive(Clone, Debug, Default)]
pub struct Report {
    /// Files dropped.
    pub files: usize,
    /// Samples a side of each.
    pub side: usize,
    /// Seconds each fifth of the files took to be active.
    pub fifths: Vec<f64>,
    /// (surveys in the store, seconds a file) over windows of a fiftieth of the files.
    pub by_size: Vec<(usize, f64)>,
    /// The open in a fresh process: seconds, bytes it added, patches and surveys.
    pub open_s: f64,
    /// Resident bytes the open added.
    pub open_bytes: u64,
    /// Patches in the index.
    pub patches: u64,
    /// Active surveys.
    pub surveys: u32,
}

/// The process's resident memory, bytes (Linux; 0 elsewhere).
pub fn resident_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

/// The tiles: N squares of `side` samples, row-major over the grid, each written as a GeoTIFF
/// of its samples in the grid's CRS.
fn write_tiles(
    g: &Grid,
    crs: Option<&patchwork_core::crs::Crs>,
    n: usize,
    dir: &Path,
) -> Result<usize, Fail> {
    let across = (n as f64).sqrt().ceil() as usize;
    let side = (g.cols.min(g.rows) / across).clamp(4, 36);
    let per_row = g.cols / side;
    if per_row * (g.rows / side) < n {
        return Err(format!(
            "{} × {} samples hold {} tiles of {side}², not {n}",
            g.cols,
            g.rows,
            per_row * (g.rows / side)
        )
        .into());
    }
    std::fs::create_dir_all(dir)?;
    let step = g.georef.step;
    for k in 0..n {
        let (c0, r0) = ((k % per_row) * side, (k / per_row) * side);
        let tile = g.window(c0, r0, side, side);
        let corner = g.georef.to_world(c0 as f64 - 0.5, r0 as f64 - 0.5);
        let gt = [corner[0], step[0], 0.0, corner[1], 0.0, -step[1]];
        let level = patchwork_read::write_cog::Level {
            width: side,
            height: side,
            samples: tile.samples.clone(),
        };
        let bytes = patchwork_read::write_cog::cog_f32_bytes(&[level], gt, crs, -32768.0)?;
        std::fs::write(dir.join(format!("t{k:06}.tif")), bytes)?;
    }
    Ok(side)
}

/// Runs the bench: `first` is the file the grids are cut from.
pub fn run(first: &Path, n: usize, out: &Path, keep: Option<&Path>) -> Result<Report, Fail> {
    std::fs::create_dir_all(out)?;
    let r = patchwork_read::read_raster(first, &Default::default())?;
    let crs = r.crs.crs.clone();
    let g = r.into_grid()?;
    let tmp = tempfile::tempdir()?;
    let staging = tmp.path().join("staging");
    let inbox = tmp.path().join("inbox");
    std::fs::create_dir_all(&inbox)?;
    let t0 = Instant::now();
    let side = write_tiles(&g, crs.as_ref(), n, &staging)?;
    println!(
        "many: {n} tiles of {side}² written in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    let data = tmp.path().join("data");
    // The defaults, with the environment's overrides, as `--open-only` takes them: the chunks
    // may go to an object store.
    let mut cfg = Config::default();
    cfg.apply_env(|k| std::env::var(k).ok())?;
    cfg.data_dir = data.clone();
    cfg.inbox = vec![inbox.clone()];
    let place = cfg.storage.url();
    let engine = Arc::new(Engine::open(cfg)?);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let watcher = rt.spawn(patchwork_engine::watch::run(
        engine.clone(),
        stopped.clone(),
    ));
    // As `serve` runs them: on an object store, the writer's log that did not go up at once is
    // published again here.
    let rounds = rt.spawn(patchwork_engine::rounds(engine.clone(), stopped));
    // The watcher's first scan, before anything arrives.
    std::thread::sleep(Duration::from_millis(500));
    let start = Instant::now();
    let mut names: Vec<_> = std::fs::read_dir(&staging)?
        .map(|e| e.map(|e| e.file_name()))
        .collect::<Result<_, _>>()?;
    names.sort();
    for name in &names {
        std::fs::rename(staging.join(name), inbox.join(name))?;
    }
    println!(
        "many: {n} files renamed into the inbox in {:.2} s",
        start.elapsed().as_secs_f64()
    );
    // When each count of active surveys was first seen.
    let mut seen: Vec<f64> = Vec::with_capacity(n);
    let mut last_print = Instant::now();
    loop {
        // The catalog's count, which costs nothing: `stats` goes through the whole store
        // (its samples, boxes and quadtree), and asked this often it took a growing share of
        // the two cores from the ingest it measures.
        let c = engine.catalog();
        let active = c.active_count();
        let at = start.elapsed().as_secs_f64();
        while seen.len() < active.min(n) {
            seen.push(at);
        }
        if active >= n {
            break;
        }
        if !c.failures.is_empty() {
            return Err(format!("{} files failed to ingest", c.failures.len()).into());
        }
        if last_print.elapsed() > Duration::from_secs(10) {
            println!("many: {active} of {n} active after {at:.0} s");
            last_print = Instant::now();
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = stop.send(true);
    let _ = rt.block_on(watcher);
    let _ = rt.block_on(rounds);
    let stats = engine.stats();
    drop(engine);
    drop(rt);
    let fifth = n / 5;
    let fifths: Vec<f64> = (0..5)
        .map(|k| {
            let from = if k == 0 { 0.0 } else { seen[k * fifth - 1] };
            seen[((k + 1) * fifth).min(n) - 1] - from
        })
        .collect();
    let window = (n / 50).max(1);
    let by_size: Vec<(usize, f64)> = (window..=n)
        .step_by(window)
        .map(|k| {
            let from = if k == window {
                0.0
            } else {
                seen[k - window - 1]
            };
            (k, (seen[k - 1] - from) / window as f64)
        })
        .collect();
    for (k, f) in fifths.iter().enumerate() {
        println!(
            "many: fifth {}: {:.1} s, {:.0} files/s",
            k + 1,
            f,
            fifth as f64 / f.max(1e-9)
        );
    }
    println!(
        "many: the last fifth took {:.2}× the first",
        fifths[4] / fifths[0].max(1e-9)
    );
    // The open, in a process of its own, so that the memory it adds is the open's alone,
    // less what the open of an empty store adds (sled, the thread pools, the caches' tables).
    let [open_s, open_bytes, patches, surveys] = open_in_child(&data, &[])?;
    // Again: an open reads back only the chunks committed since the one before.
    let [again_s, _, _, _] = open_in_child(&data, &[])?;
    // The empty store on the local pack: an object store's place holds the store above.
    let local = [("PATCHWORK_STORAGE_BACKEND", "local")];
    let [_, empty_bytes, _, _] = open_in_child(&tmp.path().join("empty"), &local)?;
    let open_bytes = (open_bytes - empty_bytes).max(0.0);
    if let Some(url) = &place {
        let [s, bytes, p, n] = open_in_child(
            &tmp.path().join("replica"),
            &[("PATCHWORK_FOLLOW", url.as_str())],
        )?;
        if (p, n) != (patches, surveys) {
            return Err(format!(
                "the replica holds {n} surveys and {p} patches, the writer {surveys} and \
                 {patches}"
            )
            .into());
        }
        println!(
            "many: a replica of {url} started in {s:.2} s, {:.0} bytes a survey",
            (bytes - empty_bytes).max(0.0) / n.max(1.0)
        );
    }
    let report = Report {
        files: n,
        side,
        fifths,
        by_size,
        open_s,
        open_bytes: open_bytes as u64,
        patches: patches as u64,
        surveys: surveys as u32,
    };
    println!(
        "many: open {:.2} s, again {again_s:.2} s; {} surveys, {} patches; {:.0} bytes a \
         patch, {:.0} a survey",
        report.open_s,
        report.surveys,
        report.patches,
        report.open_bytes as f64 / report.patches.max(1) as f64,
        report.open_bytes as f64 / report.surveys.max(1) as f64
    );
    debug_assert_eq!(stats.surveys as usize, n);
    write_csv(out, &report)?;
    if let Some(keep) = keep {
        std::fs::rename(&data, keep)
            .map_err(|e| format!("keeping the store in {}: {e}", keep.display()))?;
    }
    Ok(report)
}

/// [`open_only`] in a process of its own, with `env` on top of this one's: seconds, bytes
/// added, patches, surveys.
fn open_in_child(data: &Path, env: &[(&str, &str)]) -> Result<[f64; 4], Fail> {
    let child = std::process::Command::new(std::env::current_exe()?)
        .arg("--open-only")
        .arg(data)
        .envs(env.iter().copied())
        .output()?;
    if !child.status.success() {
        return Err(format!(
            "the open failed: {}",
            String::from_utf8_lossy(&child.stderr)
        )
        .into());
    }
    let line = String::from_utf8_lossy(&child.stdout);
    let v: Vec<f64> = line
        .split_whitespace()
        .filter_map(|w| w.parse().ok())
        .collect();
    v[..]
        .try_into()
        .map_err(|_| format!("the open said {line:?}").into())
}

/// Opens the store at `data` as the daemon does and prints its time, the resident bytes it
/// added, and its patches and active surveys, on one line.
pub fn open_only(data: &Path) -> Result<(), Fail> {
    let before = resident_bytes();
    let t0 = Instant::now();
    // The defaults, with the environment's overrides (PATCHWORK_CACHE_MB, say).
    let mut cfg = Config::default();
    cfg.apply_env(|k| std::env::var(k).ok())?;
    cfg.data_dir = data.to_path_buf();
    cfg.inbox = vec![];
    let engine = Engine::open(cfg)?;
    let open_s = t0.elapsed().as_secs_f64();
    patchwork_engine::release_free_memory();
    let added = resident_bytes().saturating_sub(before);
    let s = engine.stats();
    println!("{open_s} {added} {} {}", s.patches, s.surveys);
    // Which of the resident pages are the heap's and which are files' (the binary, sled's
    // log), on standard error so that the parent's parse of the line above stays as it is.
    if let Ok(status) = std::fs::read_to_string("/proc/self/status") {
        let of = |k: &str| {
            status
                .lines()
                .find(|l| l.starts_with(k))
                .and_then(|l| l.split_whitespace().nth(1))
                .unwrap_or("?")
                .to_string()
        };
        eprintln!(
            "RssAnon {} kB, RssFile {} kB",
            of("RssAnon:"),
            of("RssFile:")
        );
    }
    Ok(())
}

fn write_csv(out: &Path, r: &Report) -> std::io::Result<()> {
    let mut f = std::fs::File::create(out.join(format!("many_{}.csv", r.files)))?;
    writeln!(f, "surveys,seconds_per_file")?;
    for (k, s) in &r.by_size {
        writeln!(f, "{k},{s:.5}")?;
    }
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(out.join("many.csv"))?;
    if f.metadata()?.len() == 0 {
        writeln!(
            f,
            "files,side,fifth1_s,fifth2_s,fifth3_s,fifth4_s,fifth5_s,last_over_first,open_s,open_bytes,patches,surveys,bytes_per_patch"
        )?;
    }
    let fifths: Vec<String> = r.fifths.iter().map(|s| format!("{s:.2}")).collect();
    writeln!(
        f,
        "{},{},{},{:.3},{:.3},{},{},{},{:.0}",
        r.files,
        r.side,
        fifths.join(","),
        r.fifths[4] / r.fifths[0].max(1e-9),
        r.open_s,
        r.open_bytes,
        r.patches,
        r.surveys,
        r.open_bytes as f64 / r.patches.max(1) as f64
    )
}
