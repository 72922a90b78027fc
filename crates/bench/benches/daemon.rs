//! Figures of the daemon end to end, over loopback gRPC:
//! - ingest throughput of Copernicus N34W119, in samples/s from the file dropped to committed;
//! - store size against input size;
//! - p50 and p99 latency of a 512² tile at 5 m;
//! - under load: clients (32 unless `--clients N`) asking for tiles of 0.05° at 5 m anywhere
//!   on the cell for 60 s, the tiles served a second, p50 and p99 latency, and how many
//!   requests queued; for each backend of `--backend` (cpu unless given, e.g.
//!   `--backend auto,cpu,gpu`) and each size of `--size` (512 unless given, e.g.
//!   `--size 512,2048`), one after the other on the same daemon and store.
//!
//! cargo bench -p patchwork-bench --bench daemon [-- --backend auto,cpu --size 512 --clients 16]
//! (PATCHWORK_BENCH_REQUESTS sets the tile count, PATCHWORK_LOAD_SECONDS the load's length;
//! PATCHWORK_ALLOW_EMULATED_GPU=1 lets the daemon take a software GPU such as lavapipe.)

mod common;

use common::{quantile, shared};
use patchwork_server::proto::{
    self as pb, admin_client::AdminClient, terrain_client::TerrainClient,
};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

struct KillOnDrop(std::process::Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    // `cargo bench` passes criterion-style flags (`--bench`); only these are read.
    let args: Vec<String> = std::env::args().collect();
    let arg = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1).cloned())
    };
    let backends: Vec<pb::Backend> = arg("--backend")
        .unwrap_or_else(|| "cpu".into())
        .split(',')
        .map(|b| match b {
            "auto" => Ok(pb::Backend::Auto),
            "cpu" => Ok(pb::Backend::Cpu),
            "gpu" => Ok(pb::Backend::Gpu),
            other => Err(format!("--backend: {other:?} is not auto, cpu or gpu")),
        })
        .collect::<Result<_, _>>()?;
    let sizes: Vec<u32> = arg("--size")
        .unwrap_or_else(|| "512".into())
        .split(',')
        .map(|s| {
            s.parse()
                .map_err(|_| format!("--size: {s:?} is not a number"))
        })
        .collect::<Result<_, _>>()?;
    let clients: usize = arg("--clients").map_or(Ok(32), |c| c.parse())?;
    let tmp = tempfile::tempdir()?;
    let inbox = tmp.path().join("inbox");
    std::fs::create_dir_all(&inbox)?;
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let child = Command::new(common::daemon_exe())
        .arg("serve")
        .env("PATCHWORK_DATA_DIR", tmp.path().join("data"))
        .env("PATCHWORK_INBOX", &inbox)
        .env("PATCHWORK_LISTEN", format!("127.0.0.1:{port}"))
        .env("PATCHWORK_HTTP_LISTEN", "")
        .env("PATCHWORK_LOG", "warn")
        .stdout(Stdio::null())
        .spawn()?;
    // Stopped however this program ends, an error included.
    let _daemon = KillOnDrop(child);
    let url = format!("http://127.0.0.1:{port}");
    let channel = loop {
        match tonic::transport::Channel::from_shared(url.clone())?
            .connect()
            .await
        {
            Ok(c) => break c,
            Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    };
    let mut admin = AdminClient::new(channel.clone());
    let mut terrain = TerrainClient::new(channel).max_decoding_message_size(1 << 30);

    let src = shared("Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif");
    let input_bytes = std::fs::metadata(&src)?.len();
    let staged = inbox.join("copernicus.tif.part");
    std::fs::copy(&src, &staged)?;
    let t0 = Instant::now();
    std::fs::rename(&staged, inbox.join("copernicus.tif"))?;
    let samples = loop {
        let list = admin
            .list_surveys(pb::ListSurveysRequest {})
            .await?
            .into_inner();
        if let Some(s) = list
            .surveys
            .iter()
            .find(|s| s.status() == pb::SurveyStatus::Active)
        {
            break s.samples;
        }
        if let Some(f) = list
            .surveys
            .iter()
            .find(|s| s.status() == pb::SurveyStatus::Failed)
        {
            return Err(format!("ingest failed: {}", f.error).into());
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let ingest = t0.elapsed().as_secs_f64();
    let stats = admin.stats(pb::StatsRequest {}).await?.into_inner();
    println!(
        "ingest: {samples} samples in {ingest:.2} s from drop to committed: {:.1} M samples/s",
        samples as f64 / ingest / 1e6
    );
    println!(
        "store: {} bytes on disk for a {} byte input ({:.2}×) and {} bytes of raw f32 samples ({:.2}×)",
        stats.disk_bytes,
        input_bytes,
        stats.disk_bytes as f64 / input_bytes as f64,
        samples * 4,
        stats.disk_bytes as f64 / (samples * 4) as f64
    );

    let n: usize = std::env::var("PATCHWORK_BENCH_REQUESTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(200);
    let roi = pb::Rect {
        xmin: -118.7,
        ymin: 34.3,
        xmax: -118.6,
        ymax: 34.4,
    };
    let req = pb::TileRequest {
        crs: String::new(),
        cut: Some(pb::tile_request::Cut::Uniform(pb::UniformCut {
            roi: Some(roi),
            error: 5.0,
        })),
        width: 512,
        height: 512,
        backend: pb::Backend::Cpu as i32,
        ..Default::default()
    };
    let mut ms = Vec::with_capacity(n);
    let mut last = None;
    for _ in 0..n {
        let t = Instant::now();
        let tile = terrain.resample_tile(req.clone()).await?.into_inner();
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        last = Some(tile);
    }
    ms.sort_by(f64::total_cmp);
    let tile = last.expect("at least one request");
    println!(
        "tile 512² at 5 m over loopback gRPC: p50 {:.2} ms, p99 {:.2} ms over {n} requests ({} patches, max patch error {:.2} m, {} valid samples)",
        quantile(&ms, 0.5),
        quantile(&ms, 0.99),
        tile.patches,
        tile.max_error,
        tile.valid.iter().filter(|&&v| v == 1).count()
    );
    let secs: u64 = std::env::var("PATCHWORK_LOAD_SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(60);
    let backend = admin.stats(pb::StatsRequest {}).await?.into_inner().backend;
    println!("the daemon resamples on {backend}");
    let mut rows = Vec::new();
    for &size in &sizes {
        for &b in &backends {
            if let Some(r) = load(
                &terrain,
                &mut admin,
                clients,
                size,
                b,
                Duration::from_secs(secs),
            )
            .await?
            {
                rows.push((size, b, r));
            }
        }
    }
    println!("\n| tiles | clients | backend | tiles/s | p50 | p99 |\n|---|---|---|---|---|---|");
    for (size, b, (rate, p50, p99)) in &rows {
        println!(
            "| {size}² | {clients} | {} | {rate:.1} | {p50:.1} ms | {p99:.1} ms |",
            b.as_str_name()
                .trim_start_matches("BACKEND_")
                .to_lowercase()
        );
    }
    Ok(())
}

/// `clients` clients, each asking for one tile after another for `length`: `size`² tiles of
/// 0.05° at 5 m on `backend`, placed by a seeded hash anywhere on the cell so that the chunk
/// cache does not answer them all. The tiles a second, p50 and p99 in milliseconds; None
/// where the daemon refuses the backend.
async fn load(
    terrain: &TerrainClient<tonic::transport::Channel>,
    admin: &mut AdminClient<tonic::transport::Channel>,
    clients: usize,
    size: u32,
    backend: pb::Backend,
    length: Duration,
) -> Result<Option<(f64, f64, f64)>, Box<dyn std::error::Error>> {
    let probe = pb::TileRequest {
        crs: String::new(),
        cut: Some(pb::tile_request::Cut::Uniform(pb::UniformCut {
            roi: Some(pb::Rect {
                xmin: -118.7,
                ymin: 34.3,
                xmax: -118.65,
                ymax: 34.35,
            }),
            error: 5.0,
        })),
        width: 16,
        height: 16,
        backend: backend as i32,
        ..Default::default()
    };
    if let Err(e) = terrain.clone().resample_tile(probe).await {
        println!("load on {backend:?}: refused ({})", e.message());
        return Ok(None);
    }
    let end = Instant::now() + length;
    let tasks: Vec<_> = (0..clients as u64)
        .map(|c| {
            let mut t = terrain.clone();
            tokio::spawn(async move {
                let mut ms = Vec::new();
                let mut failed = 0usize;
                let mut k = 0u64;
                while Instant::now() < end {
                    let h = (c * 1_000_003 + k).wrapping_mul(0x9E37_79B9_7F4A_7C15);
                    let (fx, fy) = (
                        (h >> 40) as f64 / (1u64 << 24) as f64,
                        (h & 0xFF_FFFF) as f64 / (1u64 << 24) as f64,
                    );
                    let (x, y) = (-119.0 + 0.95 * fx, 34.0 + 0.95 * fy);
                    let req = pb::TileRequest {
                        crs: String::new(),
                        cut: Some(pb::tile_request::Cut::Uniform(pb::UniformCut {
                            roi: Some(pb::Rect {
                                xmin: x,
                                ymin: y,
                                xmax: x + 0.05,
                                ymax: y + 0.05,
                            }),
                            error: 5.0,
                        })),
                        width: size,
                        height: size,
                        backend: backend as i32,
                        ..Default::default()
                    };
                    let t0 = Instant::now();
                    // A request the daemon gives up (past its deadline) is counted, not fatal.
                    let done = async {
                        let mut s = t.tile_bands(req.clone()).await?.into_inner();
                        while s.message().await?.is_some() {}
                        Ok::<_, tonic::Status>(())
                    };
                    match done.await {
                        Ok(()) => ms.push(t0.elapsed().as_secs_f64() * 1e3),
                        Err(_) => failed += 1,
                    }
                    k += 1;
                }
                Ok::<_, tonic::Status>((ms, failed))
            })
        })
        .collect();
    // How many requests wait their turn, sampled as the load runs.
    let mut waiting = Vec::new();
    while Instant::now() < end {
        // Stats queue with the tiles: under a slow backend they may miss their deadline.
        if let Ok(s) = admin.stats(pb::StatsRequest {}).await {
            let s = s.into_inner();
            waiting.push((s.requests_waiting, s.requests_running, s.requests_limit));
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    let (mut ms, mut failed) = (Vec::new(), 0);
    for t in tasks {
        let (m, f) = t.await??;
        ms.extend(m);
        failed += f;
    }
    ms.sort_by(f64::total_cmp);
    let most = waiting.iter().map(|w| w.0).max().unwrap_or(0);
    let mean = waiting.iter().map(|w| w.0 as f64).sum::<f64>() / waiting.len().max(1) as f64;
    let limit = waiting.first().map_or(0, |w| w.2);
    let rate = ms.len() as f64 / length.as_secs_f64();
    println!(
        "load on {backend:?}: {clients} clients for {:.0} s: {} tiles of {size}² (TileBands), {rate:.1} tiles/s, p50 {:.1} ms, p99 {:.1} ms, {failed} given up; {limit} at work at most, {mean:.1} waiting on average, {most} at most",
        length.as_secs_f64(),
        ms.len(),
        quantile(&ms, 0.5),
        quantile(&ms, 0.99),
    );
    Ok(Some((rate, quantile(&ms, 0.5), quantile(&ms, 0.99))))
}
