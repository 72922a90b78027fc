//! The store at scale, end to end through the daemon: N copies of the full Copernicus N34W119
//! tile laid side by side as a mosaic (the file itself, its tiepoint moved by whole degrees),
//! dropped into the inbox at once.
//!
//! Reports the ingest rate from drop to committed, store bytes against input bytes, the time a
//! restart takes to serve, and over 200 random 512² tiles at e = 0, 5 and 50 m with a small
//! chunk cache, cold and warm latency and the daemon's peak resident memory. The same run goes
//! on the local pack and on an S3 server on loopback (s3s-fs, in this process), where it also
//! reports the bytes fetched per tile and, with a read replica following the writer, the lag
//! from a commit to the replica serving it.
//!
//! cargo bench -p patchwork-bench --bench scale   (N = 8: 104 M samples, both backends)
//! PATCHWORK_SCALE_BACKENDS=s3 cargo bench -p patchwork-bench --bench scale
//! PATCHWORK_SCALE_N=12 PATCHWORK_SCALE_CACHE_MB=64 cargo bench -p patchwork-bench --bench scale
//! PATCHWORK_SCALE_LOG=debug cargo bench -p patchwork-bench --bench scale   (the daemon's log, with each ingest's timings)

mod common;

use common::{quantile, shared};
use patchwork_server::proto::{
    self as pb, admin_client::AdminClient, terrain_client::TerrainClient,
};
use patchwork_testkit::s3::S3Server;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

fn env_or(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn mib(b: u64) -> f64 {
    b as f64 / (1 << 20) as f64
}

/// CPU seconds a process has used, user and system (/proc/<pid>/stat, in clock ticks of
/// 1/100 s on Linux).
fn cpu_seconds(pid: u32) -> f64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    // Fields after the command name, which is in parentheses and may hold spaces.
    let rest = s.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<u64> = rest
        .split_whitespace()
        .map(|v| v.parse().unwrap_or(0))
        .collect();
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the name.
    f.get(11)
        .zip(f.get(12))
        .map_or(0.0, |(u, s)| (u + s) as f64 / 100.0)
}

/// A /proc/<pid>/status figure in bytes (VmRSS, VmHWM).
fn proc_bytes(pid: u32, field: &str) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    s.lines()
        .find(|l| l.starts_with(field))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse::<u64>().ok())
        .map_or(0, |kb| kb << 10)
}

/// The Copernicus file with its ModelTiepoint moved by (dx, dy) degrees: the same bytes but
/// for two doubles, so the copy reads exactly like a neighbouring tile of the product.
fn shifted_copy(src: &[u8], dx: f64, dy: f64) -> Vec<u8> {
    let le = &src[..2] == b"II";
    assert!(le, "the source TIFF is little-endian");
    let u16_at = |o: usize| u16::from_le_bytes(src[o..o + 2].try_into().unwrap());
    let u32_at = |o: usize| u32::from_le_bytes(src[o..o + 4].try_into().unwrap());
    assert_eq!(u16_at(2), 42, "a classic TIFF");
    let ifd = u32_at(4) as usize;
    let n = u16_at(ifd) as usize;
    let mut out = src.to_vec();
    for i in 0..n {
        let e = ifd + 2 + 12 * i;
        if u16_at(e) == 33922 {
            // (I, J, K, X, Y, Z): X and Y are the fourth and fifth doubles.
            let at = u32_at(e + 8) as usize;
            for (k, d) in [(3, dx), (4, dy)] {
                let o = at + 8 * k;
                let v = f64::from_le_bytes(out[o..o + 8].try_into().unwrap()) + d;
                out[o..o + 8].copy_from_slice(&v.to_le_bytes());
            }
            return out;
        }
    }
    panic!("no ModelTiepoint tag");
}

struct Daemon {
    child: Child,
    url: String,
}

impl Daemon {
    fn start(
        data: &Path,
        inbox: &Path,
        cache_mb: u64,
        env: &[(String, String)],
    ) -> std::io::Result<Daemon> {
        let port = std::net::TcpListener::bind("127.0.0.1:0")?
            .local_addr()?
            .port();
        let child = Command::new(common::daemon_exe())
            .arg("serve")
            .envs(env.iter().map(|(k, v)| (k, v)))
            .env("PATCHWORK_DATA_DIR", data)
            .env("PATCHWORK_INBOX", inbox)
            .env("PATCHWORK_LISTEN", format!("127.0.0.1:{port}"))
            .env("PATCHWORK_HTTP_LISTEN", "")
            .env("PATCHWORK_CACHE_MB", cache_mb.to_string())
            .env(
                "PATCHWORK_LOG",
                std::env::var("PATCHWORK_SCALE_LOG").unwrap_or_else(|_| "warn".into()),
            )
            .stdout(Stdio::null())
            .spawn()?;
        Ok(Daemon {
            child,
            url: format!("http://127.0.0.1:{port}"),
        })
    }

    async fn channel(&self) -> tonic::transport::Channel {
        loop {
            let c = tonic::transport::Channel::from_shared(self.url.clone())
                .expect("url")
                .connect()
                .await;
            match c {
                Ok(c) => return c,
                Err(_) => tokio::time::sleep(Duration::from_millis(10)).await,
            }
        }
    }

    fn stop(mut self) {
        let _ = Command::new("kill")
            .arg(self.child.id().to_string())
            .status();
        let _ = self.child.wait();
    }
}

/// The figures of one backend, for the table that sets them side by side.
#[derive(Default)]
struct Figures {
    ingest_msps: f64,
    store_mib: f64,
    restart_s: f64,
    index_bytes_per_patch: f64,
    /// Per error: cold p50, warm p50 (ms), bytes fetched per cold and per warm tile.
    tiles: Vec<(f64, f64, f64, f64, f64)>,
    /// Commit to served on a replica, ms.
    lag_ms: Vec<f64>,
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let which = std::env::var("PATCHWORK_SCALE_BACKENDS").unwrap_or_else(|_| "local,s3".into());
    let rt = tokio::runtime::Runtime::new()?;
    let mut all = Vec::new();
    for b in which.split(',').map(str::trim).filter(|b| !b.is_empty()) {
        println!("== {b}");
        let tmp = tempfile::tempdir()?;
        // The S3 server runs on a runtime of its own, which may be neither made nor dropped
        // inside another.
        let s3 = (b == "s3").then(|| S3Server::start(&tmp.path().join("s3")));
        all.push((b.to_string(), rt.block_on(run(tmp.path(), s3.as_ref()))?));
    }
    println!(
        "\n| figure | {} |",
        all.iter()
            .map(|(b, _)| b.as_str())
            .collect::<Vec<_>>()
            .join(" | ")
    );
    println!("|---|{}", "---|".repeat(all.len()));
    let row = |name: &str, f: &dyn Fn(&Figures) -> String| {
        println!(
            "| {name} | {} |",
            all.iter()
                .map(|(_, x)| f(x))
                .collect::<Vec<_>>()
                .join(" | ")
        );
    };
    row("ingest, M samples/s", &|f| format!("{:.1}", f.ingest_msps));
    row("store, MiB (segments on S3)", &|f| {
        format!("{:.0}", f.store_mib)
    });
    row("restart to first answer, s", &|f| {
        format!("{:.2}", f.restart_s)
    });
    row("index, bytes a patch", &|f| {
        format!("{:.0}", f.index_bytes_per_patch)
    });
    for (i, e) in [0, 5, 50].iter().enumerate() {
        row(&format!("512² tile e = {e} m, cold / warm p50 ms"), &|f| {
            format!("{:.1} / {:.1}", f.tiles[i].1, f.tiles[i].2)
        });
        row(&format!("e = {e} m, kB fetched a cold / warm tile"), &|f| {
            format!("{:.0} / {:.0}", f.tiles[i].3 / 1e3, f.tiles[i].4 / 1e3)
        });
    }
    row("replica lag after a commit, ms (each)", &|f| {
        if f.lag_ms.is_empty() {
            "–".into()
        } else {
            f.lag_ms
                .iter()
                .map(|l| format!("{l:.0}"))
                .collect::<Vec<_>>()
                .join(", ")
        }
    });
    Ok(())
}

async fn run(root: &Path, s3: Option<&S3Server>) -> Result<Figures, Box<dyn std::error::Error>> {
    let mut fig = Figures::default();
    let n = env_or("PATCHWORK_SCALE_N", 8) as usize;
    let cache_mb = env_or("PATCHWORK_SCALE_CACHE_MB", 64);
    let requests = env_or("PATCHWORK_SCALE_REQUESTS", 200) as usize;
    let (data, inbox, staging) = (root.join("data"), root.join("inbox"), root.join("staging"));
    std::fs::create_dir_all(&inbox)?;
    std::fs::create_dir_all(&staging)?;
    let env = s3.map(|s| s.env("scale")).unwrap_or_default();
    let fetched = || s3.map_or(0, |s| s.faults.fetched.load(Ordering::Relaxed));

    // The mosaic: `cols` tiles a row, rows going south.
    let src = std::fs::read(shared("Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif"))?;
    let cols = (n as f64).sqrt().ceil() as usize;
    let mut names = Vec::new();
    for k in 0..n {
        let (dx, dy) = ((k % cols) as f64, -((k / cols) as f64));
        let name = format!("tile{k:02}.tif");
        std::fs::write(staging.join(&name), shifted_copy(&src, dx, dy))?;
        names.push(name);
    }
    let input_bytes = (src.len() * n) as u64;
    let rows = n.div_ceil(cols);
    let mosaic = [-119.0, 35.0 - rows as f64, -119.0 + cols as f64, 35.0];

    // An empty daemon: the memory that is not the store's.
    let d = Daemon::start(&data, &inbox, cache_mb, &env)?;
    let mut admin = AdminClient::new(d.channel().await);
    admin.stats(pb::StatsRequest {}).await?;
    let empty_rss = proc_bytes(d.child.id(), "VmRSS");

    let cpu0 = cpu_seconds(d.child.id());
    let t0 = Instant::now();
    for name in &names {
        std::fs::rename(staging.join(name), inbox.join(name))?;
    }
    let samples = loop {
        let list = admin
            .list_surveys(pb::ListSurveysRequest {})
            .await?
            .into_inner();
        if let Some(f) = list
            .surveys
            .iter()
            .find(|s| s.status() == pb::SurveyStatus::Failed)
        {
            return Err(format!("ingest failed: {}", f.error).into());
        }
        let active: Vec<_> = list
            .surveys
            .iter()
            .filter(|s| s.status() == pb::SurveyStatus::Active)
            .collect();
        if active.len() == n {
            break active.iter().map(|s| s.samples).sum::<u64>();
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let ingest_s = t0.elapsed().as_secs_f64();
    fig.ingest_msps = samples as f64 / ingest_s / 1e6;
    let ingest_cpu = cpu_seconds(d.child.id()) - cpu0;
    let ingest_peak = proc_bytes(d.child.id(), "VmHWM");
    let stats = admin.stats(pb::StatsRequest {}).await?.into_inner();
    println!(
        "ingest: {n} tiles, {:.1} M samples in {ingest_s:.1} s from drop to committed: {:.1} M samples/s (peak RSS {:.0} MiB; {ingest_cpu:.1} CPU-s, {:.0}% of the cores)",
        samples as f64 / 1e6,
        samples as f64 / ingest_s / 1e6,
        mib(ingest_peak),
        100.0 * ingest_cpu / ingest_s / std::thread::available_parallelism().map_or(1, |n| n.get()) as f64
    );
    let segments: u64 = s3.map_or(0, |s| {
        s.segments("scale")
            .iter()
            .map(|p| std::fs::metadata(p).map_or(0, |m| m.len()))
            .sum()
    });
    let stored = stats.disk_bytes + segments;
    fig.store_mib = mib(stored);
    println!(
        "store: {:.1} MiB ({:.1} MiB of it segments on S3) for {:.1} MiB of input files: {:.2}×",
        mib(stored),
        mib(segments),
        mib(input_bytes),
        stored as f64 / input_bytes as f64
    );
    d.stop();

    // A restart: from the process started to the first answer of a store with every survey.
    let t0 = Instant::now();
    let d = Daemon::start(&data, &inbox, cache_mb, &env)?;
    let mut admin = AdminClient::new(d.channel().await);
    let stats = admin.stats(pb::StatsRequest {}).await?.into_inner();
    let restart_s = t0.elapsed().as_secs_f64();
    fig.restart_s = restart_s;
    let open_rss = proc_bytes(d.child.id(), "VmRSS");
    let index = open_rss.saturating_sub(empty_rss);
    fig.index_bytes_per_patch = index as f64 / stats.patches.max(1) as f64;
    println!(
        "restart: serving {} patches {restart_s:.2} s after the process started; RSS {:.0} MiB, of which the index {:.0} MiB ({:.0} bytes a patch)",
        stats.patches,
        mib(open_rss),
        mib(index),
        index as f64 / stats.patches.max(1) as f64
    );

    let mut terrain = TerrainClient::new(d.channel().await).max_decoding_message_size(256 << 20);
    // Deterministic random ROIs of 0.05°, anywhere on the mosaic.
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    let side = 0.05;
    println!("{requests} random 512² tiles of {side}° per error, cache {cache_mb} MiB:");
    for e in [0.0, 5.0, 50.0] {
        let (mut cold, mut warm) = (Vec::new(), Vec::new());
        let mut patches = 0u64;
        let (mut cold_bytes, mut warm_bytes) = (0u64, 0u64);
        for _ in 0..requests {
            let x0 = mosaic[0] + next() * (mosaic[2] - mosaic[0] - side);
            let y0 = mosaic[1] + next() * (mosaic[3] - mosaic[1] - side);
            let req = pb::TileRequest {
                crs: String::new(),
                cut: Some(pb::tile_request::Cut::Uniform(pb::UniformCut {
                    roi: Some(pb::Rect {
                        xmin: x0,
                        ymin: y0,
                        xmax: x0 + side,
                        ymax: y0 + side,
                    }),
                    error: e,
                })),
                width: 512,
                height: 512,
                backend: pb::Backend::Cpu as i32,
                ..Default::default()
            };
            let (t, b) = (Instant::now(), fetched());
            let tile = terrain.resample_tile(req.clone()).await?.into_inner();
            cold.push(t.elapsed().as_secs_f64() * 1e3);
            cold_bytes += fetched() - b;
            patches += tile.patches as u64;
            let (t, b) = (Instant::now(), fetched());
            terrain.resample_tile(req).await?;
            warm.push(t.elapsed().as_secs_f64() * 1e3);
            warm_bytes += fetched() - b;
        }
        cold.sort_by(f64::total_cmp);
        warm.sort_by(f64::total_cmp);
        println!(
            "  e = {e:>4} m: cold p50 {:.1} ms, p99 {:.1} ms; warm p50 {:.1} ms, p99 {:.1} ms; {:.0} patches a tile",
            quantile(&cold, 0.5),
            quantile(&cold, 0.99),
            quantile(&warm, 0.5),
            quantile(&warm, 0.99),
            patches as f64 / requests as f64
        );
        let per = |b: u64| b as f64 / requests as f64;
        if s3.is_some() {
            println!(
                "           {:.0} kB fetched a cold tile, {:.0} kB a warm one",
                per(cold_bytes) / 1e3,
                per(warm_bytes) / 1e3
            );
        }
        fig.tiles.push((
            e,
            quantile(&cold, 0.5),
            quantile(&warm, 0.5),
            per(cold_bytes),
            per(warm_bytes),
        ));
    }
    let peak = proc_bytes(d.child.id(), "VmHWM");
    let budget = (cache_mb << 20) * 5 / 4 + index + (100 << 20);
    println!(
        "serving peak RSS {:.0} MiB; cache {cache_mb} MiB + sled's quarter + index {:.0} MiB + 100 MiB = {:.0} MiB: {}",
        mib(peak),
        mib(index),
        mib(budget),
        if peak <= budget { "within" } else { "OVER" }
    );
    if s3.is_some() {
        fig.lag_ms = replica_lag(&d, &mut admin, &root.join("replica"), &env, &names).await?;
        println!(
            "replica: a commit served {:?} ms after the writer made it",
            fig.lag_ms
        );
    }
    d.stop();
    Ok(fig)
}

/// Starts a replica of the writer `d`, then retires three tiles one by one and measures, for
/// each, the time from the writer's answer to the replica standing at the same commit.
async fn replica_lag(
    d: &Daemon,
    admin: &mut AdminClient<tonic::transport::Channel>,
    root: &Path,
    env: &[(String, String)],
    names: &[String],
) -> Result<Vec<f64>, Box<dyn std::error::Error>> {
    let mut env = env.to_vec();
    env.push(("PATCHWORK_FOLLOW".into(), "s3://terrain/scale".into()));
    std::fs::create_dir_all(root.join("inbox"))?;
    let r = Daemon::start(&root.join("data"), &root.join("inbox"), 64, &env)?;
    let mut radmin = AdminClient::new(r.channel().await);
    let commit = |s: &pb::StatsReply| s.commit;
    let mut lags = Vec::new();
    let list = admin
        .list_surveys(pb::ListSurveysRequest {})
        .await?
        .into_inner();
    for name in names.iter().take(3) {
        let source = list
            .surveys
            .iter()
            .find(|s| s.source.ends_with(name.as_str()))
            .ok_or("a tile's survey")?
            .source
            .clone();
        admin
            .retire(pb::RetireRequest {
                id_or_source: source,
            })
            .await?;
        let t0 = Instant::now();
        let want = commit(&admin.stats(pb::StatsRequest {}).await?.into_inner());
        loop {
            // The replica may still be starting: its Stats answers once it serves.
            if let Ok(s) = radmin.stats(pb::StatsRequest {}).await {
                if commit(&s.into_inner()) >= want {
                    break;
                }
            }
            if t0.elapsed() > Duration::from_secs(120) {
                return Err("the replica did not catch up in 120 s".into());
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        lags.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    r.stop();
    let _ = d;
    Ok(lags)
}
