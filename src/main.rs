//! `patchwork`: the daemon and its command line.

use clap::{Args, Parser, Subcommand, ValueEnum};
use patchwork::config::Config;
use patchwork::engine::Engine;
use patchwork::mesh::encode;
use patchwork::serve::proto::{
    self as pb, admin_client::AdminClient, terrain_client::TerrainClient,
};
use patchwork::serve::{api, convert, grpc};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

#[derive(Parser)]
#[command(
    name = "patchwork",
    version,
    about = "A terrain database of overlapping DEM surveys"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Args, Clone)]
struct Target {
    /// The daemon to talk to.
    #[arg(
        long,
        env = "PATCHWORK_SERVER",
        default_value = "http://127.0.0.1:50051"
    )]
    server: String,
    /// Open the store in DIR directly instead of talking to a daemon.
    #[arg(long, value_name = "DIR")]
    data_dir: Option<PathBuf>,
    /// Config for direct mode (layout, limits); defaults otherwise.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// A file holding the bearer token to send; otherwise PATCHWORK_TOKEN, then
    /// PATCHWORK_ADMIN_TOKEN, is sent when set.
    #[arg(long, env = "PATCHWORK_TOKEN_FILE", value_name = "FILE")]
    token_file: Option<PathBuf>,
    /// PEM certificate of the authority that signed the daemon's TLS certificate, for an
    /// https:// server (the system's roots are not used).
    #[arg(long, env = "PATCHWORK_CA", value_name = "FILE")]
    ca: Option<PathBuf>,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run the daemon: watch the inbox and serve the gRPC API.
    Serve {
        #[arg(long, env = "PATCHWORK_CONFIG", value_name = "FILE")]
        config: Option<PathBuf>,
    },
    /// Ingest files now.
    Ingest {
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// Accuracy ε in metres for files without a sidecar.
        #[arg(long, value_name = "M")]
        accuracy: Option<f64>,
        #[command(flatten)]
        target: Target,
    },
    /// List surveys, failed files included.
    Surveys {
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        target: Target,
    },
    /// Retire a survey by id or source path. A survey whose file stays in the inbox stays
    /// retired until that file's content changes.
    Retire {
        id_or_source: String,
        #[command(flatten)]
        target: Target,
    },
    /// Remove the failure recorded for a file.
    Forget {
        path: PathBuf,
        #[command(flatten)]
        target: Target,
    },
    /// Store statistics.
    Stats {
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        target: Target,
    },
    /// Re-check the store and the index.
    Verify {
        #[command(flatten)]
        target: Target,
    },
    /// Drop damaged surveys for good, so that their files can be ingested again.
    Repair {
        #[command(flatten)]
        target: Target,
    },
    /// Remove retired surveys for good and give disk space back.
    Compact {
        #[command(flatten)]
        target: Target,
    },
    /// Patches for a region and error, or for a view.
    Query {
        #[command(flatten)]
        cut: CutArgs,
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        target: Target,
    },
    /// List the GPU adapters with compute shaders, one a line. The daemon runs this in a child
    /// process, so that drivers it will not use are never loaded into it.
    #[command(hide = true)]
    ProbeGpu,
    /// Resample a north-up tile and write it as GeoTIFF (.tif) or numpy (.npy).
    Tile {
        #[arg(long, value_name = "XMIN,YMIN,XMAX,YMAX", allow_hyphen_values = true)]
        roi: String,
        #[arg(long, value_name = "WxH")]
        size: String,
        #[arg(long, value_name = "E", default_value_t = 0.0)]
        error: f64,
        #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
        backend: BackendArg,
        /// The tile's CRS (an EPSG code such as EPSG:3857, a WKT or a PROJ string): --roi is
        /// in it, and so are the tile's samples and its GeoTIFF. The store's by default.
        #[arg(long, value_name = "CRS")]
        crs: Option<String>,
        #[arg(long, value_name = "FILE")]
        out: PathBuf,
        #[command(flatten)]
        target: Target,
    },
    /// Heights at points, or along a line: what any tile holding them gives there.
    Sample {
        /// Points as X,Y pairs: X1,Y1,X2,Y2,...
        #[arg(long, value_name = "X,Y,...", allow_hyphen_values = true)]
        points: Option<String>,
        /// A line from X0,Y0 to X1,Y1, sampled at --count evenly spaced points.
        #[arg(long, value_name = "X0,Y0,X1,Y1", allow_hyphen_values = true)]
        line: Option<String>,
        #[arg(long, value_name = "N", default_value_t = 100)]
        count: usize,
        #[arg(long, value_name = "E", default_value_t = 0.0)]
        error: f64,
        /// The points' CRS; the store's by default.
        #[arg(long, value_name = "CRS")]
        crs: Option<String>,
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        target: Target,
    },
    /// Triangulate a uniform cut's surface and write it as OBJ (.obj), binary glTF (.glb) or
    /// Cesium quantized-mesh (.terrain; a geographic store only).
    Mesh {
        #[arg(long, value_name = "XMIN,YMIN,XMAX,YMAX", allow_hyphen_values = true)]
        roi: String,
        /// The cut's error, metres.
        #[arg(long, value_name = "E", default_value_t = 0.0)]
        error: f64,
        /// How far the triangles may depart from the resampled heights, metres.
        #[arg(long, value_name = "M", default_value_t = 1.0)]
        mesh_error: f64,
        /// Grid vertices a row; 2^n + 1 wastes nothing, any other size is padded inside.
        #[arg(long, value_name = "N", default_value_t = 257)]
        size: u32,
        /// Grid rows (default: as many as --size).
        #[arg(long, value_name = "N")]
        rows: Option<u32>,
        /// How far the surface may be drawn over a void from the nearest measured vertex,
        /// metres: holes narrower than twice this close, wider ones shrink by this much at
        /// most (0: holes kept exact).
        #[arg(long, value_name = "M", default_value_t = 0.0)]
        hole_reach: f64,
        /// Depth of the skirts under the tile's border, metres (0: none). Quantized-mesh
        /// leaves them out: Cesium makes its own from the edge vertices.
        #[arg(long, value_name = "M", default_value_t = 0.0)]
        skirt: f64,
        #[arg(long, value_enum, default_value_t = BorderArg::Shared)]
        border: BorderArg,
        #[arg(long, value_enum, default_value_t = MethodArg::Rtin)]
        method: MethodArg,
        /// Where the cut is resampled.
        #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
        backend: BackendArg,
        /// The CRS of --roi and of the vertices (an EPSG code, a WKT or a PROJ string); the
        /// store's by default.
        #[arg(long, value_name = "CRS")]
        crs: Option<String>,
        #[arg(long, value_name = "FILE")]
        out: PathBuf,
        #[command(flatten)]
        target: Target,
    },
}

/// Where a tile is resampled.
#[derive(Clone, Copy, ValueEnum)]
enum BackendArg {
    /// The GPU when there is one, else the CPU.
    Auto,
    Cpu,
    Gpu,
}

impl From<BackendArg> for pb::Backend {
    fn from(b: BackendArg) -> Self {
        match b {
            BackendArg::Auto => pb::Backend::Auto,
            BackendArg::Cpu => pb::Backend::Cpu,
            BackendArg::Gpu => pb::Backend::Gpu,
        }
    }
}

/// How a mesh is triangulated.
#[derive(Clone, Copy, ValueEnum)]
enum MethodArg {
    /// A triangle bintree: the fewest triangles.
    Rtin,
    /// A restricted quadtree of fans, midpoints omitted where a coarser node meets.
    Quadtree,
}

impl From<MethodArg> for pb::MeshMethod {
    fn from(m: MethodArg) -> Self {
        match m {
            MethodArg::Rtin => pb::MeshMethod::Rtin,
            MethodArg::Quadtree => pb::MeshMethod::Quadtree,
        }
    }
}

/// What a mesh keeps on the tile's border.
#[derive(Clone, Copy, ValueEnum)]
enum BorderArg {
    /// Every border vertex, so that tiles of one error fit without cracks.
    Shared,
    /// Simplified like the inside: fewer triangles, cracks hidden only by skirts.
    Adaptive,
}

impl From<BorderArg> for pb::MeshBorder {
    fn from(b: BorderArg) -> Self {
        match b {
            BorderArg::Shared => pb::MeshBorder::Shared,
            BorderArg::Adaptive => pb::MeshBorder::Adaptive,
        }
    }
}

#[derive(Args, Clone)]
struct CutArgs {
    #[arg(long, value_name = "XMIN,YMIN,XMAX,YMAX", allow_hyphen_values = true)]
    roi: Option<String>,
    #[arg(long, value_name = "E")]
    error: Option<f64>,
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true)]
    eye: Option<String>,
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true)]
    look: Option<String>,
    #[arg(long, value_name = "DEG", default_value_t = 60.0)]
    fov: f64,
    #[arg(long, value_name = "PX", default_value_t = 1024)]
    viewport: u32,
    #[arg(long, value_name = "P", default_value_t = 1.0)]
    pixel_error: f64,
    /// The CRS of --roi (an EPSG code, a WKT or a PROJ string); the store's by default.
    #[arg(long, value_name = "CRS")]
    crs: Option<String>,
}

type Fail = Box<dyn std::error::Error>;

fn numbers<const N: usize>(s: &str, what: &str) -> Result<[f64; N], Fail> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("{what}: expected {N} comma-separated numbers, got {s:?}"))?;
    v.try_into()
        .map_err(|_| format!("{what}: expected {N} comma-separated numbers, got {s:?}").into())
}

fn rect(s: &str) -> Result<pb::Rect, Fail> {
    let [xmin, ymin, xmax, ymax] = numbers::<4>(s, "--roi")?;
    Ok(pb::Rect {
        xmin,
        ymin,
        xmax,
        ymax,
    })
}

/// Adds the bearer token, when there is one, to every request.
#[derive(Clone)]
struct Bearer(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

type Authed = InterceptedService<Channel, Bearer>;

/// The token to send: from --token-file, else PATCHWORK_TOKEN, else PATCHWORK_ADMIN_TOKEN.
fn token(t: &Target) -> Result<Bearer, Fail> {
    let text = match &t.token_file {
        Some(f) => Some(
            std::fs::read_to_string(f)
                .map_err(|e| format!("cannot read the token file {}: {e}", f.display()))?,
        ),
        None => std::env::var("PATCHWORK_TOKEN")
            .or_else(|_| std::env::var("PATCHWORK_ADMIN_TOKEN"))
            .ok(),
    };
    let Some(text) = text.map(|t| t.trim().to_string()).filter(|t| !t.is_empty()) else {
        return Ok(Bearer(None));
    };
    let v = format!("Bearer {text}")
        .parse()
        .map_err(|_| "the token must be printable ASCII")?;
    Ok(Bearer(Some(v)))
}

/// The daemon, or the store opened in this process.
enum Client {
    Remote {
        terrain: Box<TerrainClient<Authed>>,
        admin: Box<AdminClient<Authed>>,
    },
    Local(Arc<Engine>),
}

impl Client {
    async fn connect(t: &Target) -> Result<Client, Fail> {
        if let Some(dir) = &t.data_dir {
            let mut cfg = Config::load(t.config.as_deref())?;
            cfg.data_dir = dir.clone();
            // Whoever opens the store directly has the files already: confinement is for
            // clients of a daemon.
            cfg.ingest_roots.push(PathBuf::from("/"));
            let engine = tokio::task::spawn_blocking(move || Engine::open(cfg)).await??;
            return Ok(Client::Local(Arc::new(engine)));
        }
        // Window sizes follow the connection's measured bandwidth-delay product, so that a
        // large tile is not held back by HTTP/2's default 64 KiB window.
        let mut endpoint = Channel::from_shared(t.server.clone())?
            .http2_adaptive_window(true)
            .tcp_nodelay(true);
        if let Some(ca) = &t.ca {
            let pem = std::fs::read(ca)
                .map_err(|e| format!("cannot read the CA certificate {}: {e}", ca.display()))?;
            endpoint = endpoint.tls_config(
                tonic::transport::ClientTlsConfig::new()
                    .ca_certificate(tonic::transport::Certificate::from_pem(pem)),
            )?;
        }
        let ch = endpoint.connect().await.map_err(|e| {
            let why = std::error::Error::source(&e).map(|s| format!(" ({s})")).unwrap_or_default();
            format!("cannot reach the daemon at {}: {e}{why}; start it with `patchwork serve`, or use --data-dir DIR", t.server)
        })?;
        let bearer = token(t)?;
        if bearer.0.is_some() && !is_loopback_url(&t.server) && t.server.starts_with("http://") {
            eprintln!(
                "patchwork: warning: sending the token in clear to {}; use https:// and --ca",
                t.server
            );
        }
        Ok(Client::Remote {
            terrain: Box::new(
                TerrainClient::with_interceptor(ch.clone(), bearer.clone())
                    .max_decoding_message_size(1 << 30),
            ),
            admin: Box::new(
                AdminClient::with_interceptor(ch, bearer).max_decoding_message_size(1 << 30),
            ),
        })
    }
}

/// Runs one request either way: over gRPC, or through the same dispatcher the daemon uses.
/// Shows the daemon's ingest under way on `bar` until aborted: its phase, and a position
/// within the file by phase (reading and modelling take most of an ingest, committing the
/// rest), on top of `done`, the bytes of files finished. Polls `stats` every 200 ms.
fn watch_ingest(
    c: &Client,
    bar: indicatif::ProgressBar,
    done: Arc<std::sync::atomic::AtomicU64>,
) -> tokio::task::JoinHandle<()> {
    let mut remote = match c {
        Client::Remote { admin, .. } => Some(admin.as_ref().clone()),
        Client::Local(_) => None,
    };
    let local = match c {
        Client::Local(e) => Some(e.clone()),
        Client::Remote { .. } => None,
    };
    tokio::spawn(async move {
        loop {
            tokio::time::sleep(std::time::Duration::from_millis(200)).await;
            let s = match (&mut remote, &local) {
                (Some(a), _) => match a.stats(pb::StatsRequest {}).await {
                    Ok(r) => r.into_inner(),
                    Err(_) => continue,
                },
                (None, Some(e)) => patchwork::serve::convert::stats(&e.stats()),
                (None, None) => return,
            };
            if s.ingesting_source.is_empty() {
                continue;
            }
            let share = match s.ingesting_phase.as_str() {
                "reading" => 0.0,
                "modelling" => 0.25,
                "indexing" => 0.6,
                _ => 0.8,
            };
            let base = done.load(std::sync::atomic::Ordering::Relaxed);
            bar.set_position(base + (share * s.ingesting_bytes as f64) as u64);
            let name = std::path::Path::new(&s.ingesting_source)
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            bar.set_message(format!(
                "{} {} ({:.1} s)",
                s.ingesting_phase,
                printable(&name),
                s.ingesting_seconds
            ));
        }
    })
}

macro_rules! call {
    ($client:expr, $svc:ident . $rpc:ident($req:expr), $local:expr) => {
        match $client {
            Client::Remote { $svc, .. } => $svc
                .$rpc($req)
                .await
                .map(|r| r.into_inner())
                .map_err(|s| -> Fail { s.message().to_string().into() }),
            Client::Local(engine) => {
                let engine = engine.clone();
                tokio::task::spawn_blocking(move || $local(&engine))
                    .await?
                    .map_err(|e| -> Fail { e.to_string().into() })
            }
        }
    };
}

fn view_of(c: &CutArgs) -> Result<Option<pb::ViewCut>, Fail> {
    match (&c.eye, &c.look) {
        (Some(e), Some(l)) => {
            let [ex, ey, ez] = numbers::<3>(e, "--eye")?;
            let [lx, ly, lz] = numbers::<3>(l, "--look")?;
            Ok(Some(pb::ViewCut {
                eye_x: ex,
                eye_y: ey,
                eye_z: ez,
                look_x: lx,
                look_y: ly,
                look_z: lz,
                fov_deg: c.fov,
                viewport_px: c.viewport,
                pixel_error: c.pixel_error,
            }))
        }
        (None, None) => Ok(None),
        _ => Err("a view needs both --eye and --look".into()),
    }
}

/// What a tile or mesh achieved against the error `e` asked: its largest patch error, or
/// where no data is as accurate as `e`, how much of it and what served there.
fn achieved(e: f64, max_error: f64, short: Option<&pb::Shortfall>, what: &str) -> String {
    match short {
        Some(s) => format!(
            "no data as accurate as {e} m over {:.0}% of the {what}: served the most accurate there, errors {:.1}–{:.1} m",
            100.0 * s.share,
            s.min_error_m,
            s.max_error_m
        ),
        None => format!("max error {max_error:.3} m"),
    }
}

/// A tile put back together from its bands, which must cover its rows in order.
fn assemble(bands: Vec<pb::TileBand>) -> Result<pb::Tile, Fail> {
    let Some(first) = bands.first() else {
        return Err("the daemon sent no tile".into());
    };
    let (width, height) = (first.width as usize, first.height as usize);
    let mut t = pb::Tile {
        width: first.width,
        height: first.height,
        patches: first.patches,
        backend: first.backend.clone(),
        crs: first.crs,
        crs_key: first.crs_key.clone(),
        max_error: first.max_error,
        shortfall: first.shortfall,
        heights: Vec::with_capacity(width * height),
        valid: Vec::new(),
    };
    for b in &bands {
        let row = t.heights.len() / width.max(1);
        if b.row as usize != row || b.heights.len() != 4 * width * b.rows as usize {
            return Err(format!(
                "band at row {} of {} rows does not follow row {row}",
                b.row, b.rows
            )
            .into());
        }
        t.heights.extend(
            b.heights
                .chunks_exact(4)
                .map(|q| f32::from_le_bytes([q[0], q[1], q[2], q[3]])),
        );
    }
    if t.heights.len() != width * height {
        return Err(format!(
            "the bands hold {} of the tile's {} heights",
            t.heights.len(),
            width * height
        )
        .into());
    }
    Ok(t)
}

/// The CRS a reply names by its key; None for an empty key.
fn tile_crs(key: &str) -> Result<Option<patchwork::crs::Crs>, Fail> {
    if key.is_empty() {
        return Ok(None);
    }
    Ok(Some(patchwork::crs::Crs::parse(key)?))
}

fn write_tile(out: &Path, t: &pb::Tile, roi: &pb::Rect) -> Result<(), Fail> {
    match out.extension().and_then(|e| e.to_str()) {
        Some("tif") | Some("tiff") => {
            let gt = [
                roi.xmin,
                (roi.xmax - roi.xmin) / t.width as f64,
                0.0,
                roi.ymax,
                0.0,
                -(roi.ymax - roi.ymin) / t.height as f64,
            ];
            patchwork::read::write_tiff::write_geotiff_f32(
                out,
                t.width as usize,
                t.height as usize,
                &t.heights,
                gt,
                tile_crs(&t.crs_key)?.as_ref(),
                Some(-9999.0),
            )?;
        }
        Some("npy") => {
            patchwork::read::write_npy(out, t.height as usize, t.width as usize, &t.heights)?
        }
        _ => return Err(format!("--out {}: use a .tif or .npy name", out.display()).into()),
    }
    Ok(())
}

/// How long requests in flight get to finish after SIGTERM or Ctrl-C. Stopping mid-ingest
/// is safe: a commit is one atomic batch, and the inbox picks the file up again.
const GRACE: std::time::Duration = std::time::Duration::from_secs(3);

async fn serve(config: Option<PathBuf>) -> Result<(), Fail> {
    let cfg = Config::load(config.as_deref())?;
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&cfg.log).unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    patchwork::serve::auth::check_exposure(&cfg)?;
    // Before the store opens and anything is said to be served.
    if let (Some(cert), Some(key)) = (&cfg.tls_cert, &cfg.tls_key) {
        patchwork::serve::tls::load(cert, key)?;
    }
    std::fs::create_dir_all(&cfg.data_dir)?;
    let listen = cfg.listen.clone();
    let engine = Arc::new(
        tokio::task::spawn_blocking(move || {
            let e = Engine::open(cfg)?;
            match real_gpu(e.config().allow_emulated_gpu) {
                Ok(()) => e.enable_gpu(),
                Err(why) => {
                    tracing::info!(reason = %why, "no GPU device: resampling on the CPU")
                }
            }
            Ok::<_, patchwork::engine::EngineError>(e)
        })
        .await??,
    );
    let listener = tokio::net::TcpListener::bind(&listen)
        .await
        .map_err(|e| format!("cannot listen on {listen}: {e}"))?;
    let c = engine.config();
    let tls = c.tls_cert.is_some();
    if !patchwork::serve::auth::is_loopback(&listen) && !tls {
        tracing::warn!("serving beyond this machine without TLS: tokens and data travel in clear; set tls_cert and tls_key");
    }
    tracing::info!(address = %listener.local_addr()?, tls, admin_token = c.admin_token.is_some(), read_token = c.read_token.is_some(), data = ?c.data_dir, inbox = ?c.inbox, "serving");
    if let Some(why) = engine.read_only() {
        tracing::warn!(reason = %why, "read-only: queries are served, writes are refused until this is resolved");
    }
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let watcher = tokio::spawn(patchwork::watch::run(engine.clone(), stop_rx.clone()));
    tokio::spawn(async move {
        let ctrl_c = tokio::signal::ctrl_c();
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
            .expect("signal handler");
        tokio::select! { _ = ctrl_c => {}, _ = term.recv() => {} }
        tracing::info!("shutting down");
        let _ = stop_tx.send(true);
    });
    let stopped = |mut rx: tokio::sync::watch::Receiver<bool>| async move {
        let _ = rx.wait_for(|s| *s).await;
    };
    let server = grpc::serve(engine, listener, stopped(stop_rx.clone()));
    tokio::select! {
        r = server => r.map_err(|e| -> Fail { e.to_string().into() })?,
        _ = async { stopped(stop_rx.clone()).await; tokio::time::sleep(GRACE).await } => {
            tracing::warn!("requests still running {} s after the signal; stopping without them", GRACE.as_secs());
        }
    }
    if tokio::time::timeout(std::time::Duration::from_secs(1), watcher)
        .await
        .is_err()
    {
        tracing::warn!("the inbox pass in progress was left unfinished; it runs again at start");
    }
    Ok(())
}

async fn run(cli: Cli) -> Result<(), Fail> {
    match cli.cmd {
        Cmd::Serve { config } => serve(config).await,
        Cmd::ProbeGpu => {
            for line in patchwork::resample::gpu::list_adapters() {
                println!("{line}");
            }
            Ok(())
        }
        Cmd::Ingest {
            files,
            accuracy,
            target,
        } => {
            let mut c = Client::connect(&target).await?;
            // The bar counts bytes of files: a large file moves it through its phases while
            // the daemon reads, models, indexes and commits it.
            let sizes: Vec<u64> = files
                .iter()
                .map(|f| std::fs::metadata(f).map_or(1, |m| m.len().max(1)))
                .collect();
            let bar = indicatif::ProgressBar::new(sizes.iter().sum());
            bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "{bar:30} {bytes}/{total_bytes} {elapsed} {msg}",
                )
                .expect("template"),
            );
            let done = Arc::new(std::sync::atomic::AtomicU64::new(0));
            let watcher = watch_ingest(&c, bar.clone(), done.clone());
            // A hidden bar (no terminal) swallows its own println: print plainly then.
            let say = |line: String| {
                if bar.is_hidden() {
                    println!("{line}");
                } else {
                    bar.println(line);
                }
            };
            let mut failed = 0;
            for (f, size) in files.into_iter().zip(sizes) {
                let path = patchwork::engine::source_name(&f);
                if f.to_str().is_none() {
                    // The wire carries text: the name cannot be sent as it is.
                    failed += 1;
                    say(format!(
                        "failed    {}: the file name is not valid UTF-8: rename the file to ingest it",
                        printable(&path)
                    ));
                    done.fetch_add(size, std::sync::atomic::Ordering::Relaxed);
                    continue;
                }
                let req = pb::IngestRequest {
                    paths: vec![path],
                    accuracy_m: accuracy,
                };
                let r = req.clone();
                let reply = call!(&mut c, admin.ingest(req), move |e: &Engine| api::ingest(
                    e, &r
                ))?;
                for r in reply.results {
                    if r.outcome == "failed" {
                        failed += 1;
                        say(format!(
                            "failed    {}: {}",
                            printable(&r.source),
                            printable(&r.error)
                        ));
                    } else {
                        say(format!(
                            "{:<9} {} {:016x} ({} samples, {:.2} s)",
                            r.outcome,
                            printable(&r.source),
                            r.survey,
                            r.samples,
                            r.seconds
                        ));
                        for c in &r.conflicts {
                            say(format!(
                                "          conflicts with {}: up to {:.2} m apart, {:.2} m RMS",
                                c.survey, c.max_m, c.rms_m
                            ));
                        }
                    }
                }
                done.fetch_add(size, std::sync::atomic::Ordering::Relaxed);
                bar.set_position(done.load(std::sync::atomic::Ordering::Relaxed));
            }
            watcher.abort();
            bar.finish_and_clear();
            if failed > 0 {
                return Err(format!("{failed} file(s) failed").into());
            }
            Ok(())
        }
        Cmd::Surveys { json, target } => {
            let mut c = Client::connect(&target).await?;
            let list = call!(
                &mut c,
                admin.list_surveys(pb::ListSurveysRequest {}),
                api::list_surveys
            )?;
            if json {
                let v: Vec<SurveyJson> = list.surveys.iter().map(SurveyJson::of).collect();
                println!("{}", serde_json::to_string_pretty(&v)?);
            } else {
                for s in &list.surveys {
                    match s.status.as_str() {
                        "failed" => println!(
                            "{:<16}  failed   {}  {}",
                            "-",
                            printable(&s.source),
                            printable(&s.error)
                        ),
                        // Out of the terrain: what is wrong matters, not its claims.
                        "damaged" => println!(
                            "{:<16}  damaged  {}  {}; ingest the file again or run `patchwork repair`",
                            s.id,
                            printable(&s.source),
                            printable(&s.error)
                        ),
                        st => {
                            // What most of it achieves beside what all of it does.
                            let claimed = if s.claimed_accuracy_m < s.accuracy_m {
                                format!(", claimed {:.3} m", s.claimed_accuracy_m)
                            } else {
                                String::new()
                            };
                            println!(
                                "{:<16}  {:<7}  {}  ε median {:.3} m, 90% {:.3} m, largest {:.3} m ({}{claimed})  {} samples  {} patches",
                                s.id,
                                st,
                                printable(&s.source),
                                s.accuracy_median_m,
                                s.accuracy_p90_m,
                                s.accuracy_m,
                                s.accuracy_source,
                                s.samples,
                                s.patches
                            );
                            for c in &s.conflicts {
                                println!("{:<16}  {}", "", conflict_line(c));
                            }
                        }
                    }
                }
            }
            Ok(())
        }
        Cmd::Retire {
            id_or_source,
            target,
        } => {
            let mut c = Client::connect(&target).await?;
            let source = if Path::new(&id_or_source).exists() {
                patchwork::engine::source_name(Path::new(&id_or_source))
            } else {
                id_or_source
            };
            let req = pb::RetireRequest {
                id_or_source: source,
            };
            let r = req.clone();
            let reply = call!(&mut c, admin.retire(req), move |e: &Engine| api::retire(
                e, &r
            ))?;
            println!("retired {} ({} patches)", reply.id, reply.patches);
            Ok(())
        }
        Cmd::Forget { path, target } => {
            let mut c = Client::connect(&target).await?;
            let source = patchwork::engine::source_name(&path);
            let req = pb::ForgetRequest {
                source: source.clone(),
            };
            let r = req.clone();
            call!(&mut c, admin.forget(req), move |e: &Engine| api::forget(
                e, &r
            ))?;
            println!("forgot the failure of {}", printable(&source));
            Ok(())
        }
        Cmd::Stats { json, target } => {
            let mut c = Client::connect(&target).await?;
            let s = call!(&mut c, admin.stats(pb::StatsRequest {}), api::stats)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&StatsJson::of(&s))?);
            } else {
                let crs = match tile_crs(&s.crs_key)? {
                    Some(c) => c.label(),
                    None => "none yet".into(),
                };
                let vertical = if s.vertical_crs.is_empty() {
                    "none yet".to_string()
                } else {
                    s.vertical_crs.clone()
                };
                if s.damaged > 0 {
                    println!(
                        "damaged {} surveys, out of the terrain: `patchwork surveys` says why, `patchwork repair` drops them",
                        s.damaged
                    );
                }
                println!("surveys {} active, {} retired, {} failed\npatches {} ({} active boxes, {} quadtree nodes)\nsamples {}\ndisk {} bytes\ncrs {crs}\nvertical crs {vertical}\nbackend {}",
                    s.surveys, s.retired, s.failed, s.patches, s.active_boxes, s.quadtree_nodes, s.samples, s.disk_bytes, s.backend);
                println!(
                    "cache {} of {} bytes, {} hits, {} misses",
                    s.cache_bytes, s.cache_capacity_bytes, s.cache_hits, s.cache_misses
                );
                if s.requests_limit > 0 {
                    println!(
                        "requests {} at work of at most {}, {} waiting, {} served",
                        s.requests_running, s.requests_limit, s.requests_waiting, s.requests_served
                    );
                }
                if !s.read_only.is_empty() {
                    println!("read-only: {}", s.read_only);
                }
            }
            Ok(())
        }
        Cmd::Verify { target } => {
            let mut c = Client::connect(&target).await?;
            let v = call!(&mut c, admin.verify(pb::VerifyRequest {}), api::verify)?;
            for p in &v.problems {
                println!("problem: {p}");
            }
            if v.ok {
                println!("ok: {} surveys, {} patches", v.surveys, v.patches);
                Ok(())
            } else {
                Err(format!("{} problem(s) found", v.problems.len()).into())
            }
        }
        Cmd::Repair { target } => {
            let mut c = Client::connect(&target).await?;
            let r = call!(&mut c, admin.repair(pb::RepairRequest {}), api::repair)?;
            for d in &r.dropped {
                let source = if d.source.is_empty() {
                    "unreadable record".to_string()
                } else {
                    printable(&d.source).to_string()
                };
                println!("dropped {} ({source}): {}", d.id, d.reason);
            }
            println!("{} damaged surveys dropped", r.dropped.len());
            Ok(())
        }
        Cmd::Compact { target } => {
            let mut c = Client::connect(&target).await?;
            let spinner = indicatif::ProgressBar::new_spinner();
            spinner.set_message("compacting");
            spinner.enable_steady_tick(std::time::Duration::from_millis(120));
            let r = call!(&mut c, admin.compact(pb::CompactRequest {}), api::compact)?;
            spinner.finish_and_clear();
            println!(
                "compacted: {} → {} bytes, {} retired surveys removed",
                r.bytes_before, r.bytes_after, r.surveys_removed
            );
            Ok(())
        }
        Cmd::Sample {
            points,
            line,
            count,
            error,
            crs,
            json,
            target,
        } => {
            let pts: Vec<[f64; 2]> = match (&points, &line) {
                (Some(p), None) => {
                    let v: Vec<f64> = p
                        .split(',')
                        .map(|t| t.trim().parse::<f64>())
                        .collect::<Result<_, _>>()
                        .map_err(|_| format!("--points: expected X,Y pairs, got {p:?}"))?;
                    if v.is_empty() || !v.len().is_multiple_of(2) {
                        return Err(format!("--points: expected X,Y pairs, got {p:?}").into());
                    }
                    v.chunks(2).map(|c| [c[0], c[1]]).collect()
                }
                (None, Some(l)) => {
                    let [x0, y0, x1, y1] = numbers::<4>(l, "--line")?;
                    let n = count.max(2);
                    (0..n)
                        .map(|k| {
                            let t = k as f64 / (n - 1) as f64;
                            [x0 + t * (x1 - x0), y0 + t * (y1 - y0)]
                        })
                        .collect()
                }
                _ => return Err("give either --points or --line".into()),
            };
            let mut c = Client::connect(&target).await?;
            let req = pb::SampleRequest {
                points: pts.iter().map(|p| pb::Point { x: p[0], y: p[1] }).collect(),
                error,
                crs: crs.unwrap_or_default(),
            };
            let local = req.clone();
            let r = call!(&mut c, terrain.sample_heights(req), move |e: &Engine| {
                api::sample_heights(e, &local, &Default::default())
            })?;
            let height = |k: usize| (r.valid.get(k) == Some(&1)).then(|| r.heights[k]);
            if json {
                let v: Vec<SampleJson> = pts
                    .iter()
                    .enumerate()
                    .map(|(k, p)| SampleJson {
                        x: p[0],
                        y: p[1],
                        height: height(k),
                    })
                    .collect();
                println!("{}", serde_json::to_string_pretty(&v)?);
            } else {
                for (k, p) in pts.iter().enumerate() {
                    match height(k) {
                        Some(z) => println!("{} {} {z}", p[0], p[1]),
                        None => println!("{} {} nodata", p[0], p[1]),
                    }
                }
            }
            Ok(())
        }
        Cmd::Query { cut, json, target } => {
            let mut c = Client::connect(&target).await?;
            let q = match (view_of(&cut)?, &cut.roi) {
                (Some(v), None) => pb::PatchQuery {
                    cut: Some(pb::patch_query::Cut::View(v)),
                    batch_size: 0,
                    crs: cut.crs.clone().unwrap_or_default(),
                },
                (None, Some(roi)) => pb::PatchQuery {
                    cut: Some(pb::patch_query::Cut::Uniform(pb::UniformCut {
                        roi: Some(rect(roi)?),
                        error: cut.error.ok_or("--roi needs --error")?,
                    })),
                    batch_size: 0,
                    crs: cut.crs.clone().unwrap_or_default(),
                },
                _ => return Err("give either --roi with --error, or --eye and --look".into()),
            };
            let patches: Vec<pb::Patch> = match &mut c {
                Client::Remote { terrain, .. } => {
                    let mut s = terrain
                        .query_patches(q)
                        .await
                        .map_err(|s| -> Fail { s.message().to_string().into() })?
                        .into_inner();
                    let mut all = Vec::new();
                    while let Some(b) = s
                        .message()
                        .await
                        .map_err(|s| -> Fail { s.message().to_string().into() })?
                    {
                        all.extend(b.patches);
                    }
                    all
                }
                Client::Local(e) => api::query_patches(e, &q)
                    .map_err(|e| -> Fail { e.to_string().into() })?
                    .into_iter()
                    .flat_map(|b| b.patches)
                    .collect(),
            };
            if json {
                let v = QueryJson {
                    patches: patches.iter().map(PatchJson::of).collect(),
                };
                println!("{}", serde_json::to_string_pretty(&v)?);
            } else {
                for p in &patches {
                    let b = p.bounds.unwrap_or_default();
                    println!(
                        "{:016x}  survey {:016x}  level {}  error {:.3}..{:.3} m  [{}, {}, {}, {}]",
                        p.id,
                        p.survey,
                        p.level,
                        p.error,
                        p.max_error,
                        b.xmin,
                        b.ymin,
                        b.xmax,
                        b.ymax
                    );
                }
                println!("{} patches", patches.len());
            }
            Ok(())
        }
        Cmd::Mesh {
            roi,
            error,
            mesh_error,
            size,
            rows,
            hole_reach,
            skirt,
            border,
            method,
            backend,
            crs,
            out,
            target,
        } => {
            let kind = out.extension().and_then(|e| e.to_str()).unwrap_or("");
            if !["obj", "glb", "terrain"].contains(&kind) {
                return Err(
                    format!("--out {}: write .obj, .glb or .terrain", out.display()).into(),
                );
            }
            let mut c = Client::connect(&target).await?;
            let req = pb::MeshRequest {
                cut: Some(pb::UniformCut {
                    roi: Some(rect(&roi)?),
                    error,
                }),
                size,
                rows: rows.unwrap_or(size),
                mesh_error,
                hole_reach_m: hole_reach,
                skirt_m: skirt,
                backend: pb::Backend::from(backend) as i32,
                border: pb::MeshBorder::from(border) as i32,
                method: pb::MeshMethod::from(method) as i32,
                crs: crs.unwrap_or_default(),
            };
            let local = req.clone();
            let m = call!(&mut c, terrain.mesh_tile(req), move |e: &Engine| {
                api::mesh_tile(e, &local, &Default::default())
            })?;
            let (mesh, tile) = convert::mesh_of(&m)?;
            let bytes = match kind {
                "obj" => encode::obj(&mesh, &tile).into_bytes(),
                "glb" => {
                    let lonlat = tile_crs(&m.crs_key)?.is_some_and(|c| c.is_geographic());
                    encode::glb(&mesh, &tile, lonlat)
                }
                _ => {
                    let crs = tile_crs(&m.crs_key)?;
                    if !crs.as_ref().is_some_and(|c| c.is_geographic()) {
                        return Err(format!(
                            "quantized-mesh tiles are in longitude and latitude; this mesh is in {} (ask with --crs EPSG:4326)",
                            crs.map_or("no CRS".into(), |c| c.label())
                        )
                        .into());
                    }
                    encode::quantized_mesh(&mesh, &tile)
                }
            };
            std::fs::write(&out, bytes)?;
            println!(
                "wrote {} ({} vertices, {} triangles of which {} skirt; max deviation {:.3} m from the resampled heights, surface up to {:.1} m over voids; {} patches, {}, {})",
                out.display(),
                mesh.grid.len(),
                mesh.triangles.len(),
                mesh.triangles.len() - mesh.skirt_triangles,
                mesh.max_deviation,
                mesh.max_reach,
                m.patches,
                achieved(error, m.max_error, m.shortfall.as_ref(), "mesh"),
                m.backend
            );
            Ok(())
        }
        Cmd::Tile {
            roi,
            size,
            error,
            backend,
            crs,
            out,
            target,
        } => {
            let mut c = Client::connect(&target).await?;
            let roi = rect(&roi)?;
            let (w, h) = size
                .split_once(['x', 'X'])
                .and_then(|(a, b)| Some((a.parse::<u32>().ok()?, b.parse::<u32>().ok()?)))
                .ok_or_else(|| format!("--size: expected WxH, e.g. 512x512, got {size:?}"))?;
            let backend = pb::Backend::from(backend);
            let req = pb::TileRequest {
                cut: Some(pb::tile_request::Cut::Uniform(pb::UniformCut {
                    roi: Some(roi),
                    error,
                })),
                width: w,
                height: h,
                backend: backend as i32,
                crs: crs.unwrap_or_default(),
            };
            let bands = match &mut c {
                Client::Remote { terrain, .. } => {
                    let mut s = terrain
                        .tile_bands(req)
                        .await
                        .map_err(|s| -> Fail { s.message().to_string().into() })?
                        .into_inner();
                    let mut bands = Vec::new();
                    while let Some(b) = s
                        .message()
                        .await
                        .map_err(|s| -> Fail { s.message().to_string().into() })?
                    {
                        bands.push(b);
                    }
                    bands
                }
                Client::Local(engine) => {
                    let engine = engine.clone();
                    tokio::task::spawn_blocking(move || {
                        let mut bands = Vec::new();
                        api::tile_bands(&engine, &req, &Default::default(), &mut |b| {
                            bands.push(b);
                            true
                        })
                        .map(|()| bands)
                    })
                    .await??
                }
            };
            let t = assemble(bands)?;
            write_tile(&out, &t, &roi)?;
            let valid = t.heights.iter().filter(|z| !z.is_nan()).count();
            println!(
                "wrote {} ({}×{}, {} valid samples, {} patches, {}, {})",
                out.display(),
                t.width,
                t.height,
                valid,
                t.patches,
                achieved(error, t.max_error, t.shortfall.as_ref(), "tile"),
                t.backend
            );
            Ok(())
        }
    }
}

/// `surveys --json`: one object per survey or failed file. The README documents each field.
#[derive(Serialize)]
struct SurveyJson<'a> {
    id: &'a str,
    source: &'a str,
    status: &'a str,
    error: Option<&'a str>,
    accuracy_m: f64,
    accuracy_median_m: f64,
    accuracy_p90_m: f64,
    claimed_accuracy_m: f64,
    accuracy_source: Option<&'a str>,
    /// The survey's own CRS ("EPSG:n" or a WKT 2 definition), and the vertical CRS its file
    /// named ("unknown" where none); null for failures.
    crs: Option<&'a str>,
    vertical_crs: Option<&'a str>,
    /// What converting its heights into the store's vertical CRS added to ε.
    vertical_error_m: f64,
    samples: u64,
    patches: u32,
    conflicts: Vec<ConflictJson<'a>>,
}

#[derive(Serialize)]
struct ConflictJson<'a> {
    survey: &'a str,
    max_m: f64,
    rms_m: f64,
    /// Where the other lies against this one, [east, north, up] metres, and the RMS once it
    /// is moved back; null where they could not be coregistered.
    shift_m: Option<[f64; 3]>,
    rms_after_m: Option<f64>,
    /// Whose claim the evidence finds false: "this", "other" or "both".
    distrusted: &'static str,
}

fn distrusted_name(d: i32) -> &'static str {
    match pb::Distrusted::try_from(d) {
        Ok(pb::Distrusted::This) => "this",
        Ok(pb::Distrusted::Other) => "other",
        _ => "both",
    }
}

/// A conflict as `patchwork surveys` says it.
fn conflict_line(c: &pb::Conflict) -> String {
    let whose = match distrusted_name(c.distrusted) {
        "this" => "this survey's claim is the false one",
        "other" => "the other's claim is the false one",
        _ => "either claim may be the false one",
    };
    let shift = match &c.shift {
        Some(s) => format!(
            "; it lies {:.1} m east, {:.1} m north and {:.2} m up of this one, {:.2} m RMS once moved back",
            s.east_m, s.north_m, s.up_m, s.rms_after_m
        ),
        None => String::new(),
    };
    format!(
        "conflicts with {}: up to {:.2} m apart, {:.2} m RMS{shift}; {whose}",
        c.survey, c.max_m, c.rms_m
    )
}

impl<'a> SurveyJson<'a> {
    fn of(s: &'a pb::SurveyInfo) -> Self {
        let failed = s.status == "failed" || s.status == "damaged";
        SurveyJson {
            id: &s.id,
            source: &s.source,
            status: &s.status,
            error: failed.then_some(s.error.as_str()),
            accuracy_m: s.accuracy_m,
            accuracy_median_m: s.accuracy_median_m,
            accuracy_p90_m: s.accuracy_p90_m,
            claimed_accuracy_m: s.claimed_accuracy_m,
            accuracy_source: (!failed).then_some(s.accuracy_source.as_str()),
            crs: (!failed).then_some(s.crs_key.as_str()),
            vertical_crs: (!failed).then_some(s.vertical_crs.as_str()),
            vertical_error_m: s.vertical_error_m,
            samples: s.samples,
            patches: s.patches,
            conflicts: s
                .conflicts
                .iter()
                .map(|c| ConflictJson {
                    survey: &c.survey,
                    max_m: c.max_m,
                    rms_m: c.rms_m,
                    shift_m: c.shift.as_ref().map(|s| [s.east_m, s.north_m, s.up_m]),
                    rms_after_m: c.shift.as_ref().map(|s| s.rms_after_m),
                    distrusted: distrusted_name(c.distrusted),
                })
                .collect(),
        }
    }
}

/// `sample --json`: a point and its height, null where there is no data.
#[derive(Serialize)]
struct SampleJson {
    x: f64,
    y: f64,
    height: Option<f32>,
}

/// `stats --json`.
#[derive(Serialize)]
struct StatsJson<'a> {
    surveys: u32,
    retired: u32,
    failed: u32,
    damaged: u32,
    patches: u64,
    active_boxes: u64,
    samples: u64,
    disk_bytes: u64,
    /// "EPSG:n", or a WKT 2 definition; null until the store has one.
    crs: Option<&'a str>,
    vertical_crs: Option<&'a str>,
    backend: &'a str,
    quadtree_nodes: u32,
    /// Why writes are refused now; null when they are not.
    read_only: Option<&'a str>,
    cache_bytes: u64,
    cache_capacity_bytes: u64,
    cache_hits: u64,
    cache_misses: u64,
    /// Requests at work, of at most `requests_limit`; waiting for a turn; finished.
    requests_running: u32,
    requests_waiting: u32,
    requests_served: u64,
    requests_limit: u32,
}

impl<'a> StatsJson<'a> {
    fn of(s: &'a pb::StatsReply) -> Self {
        StatsJson {
            surveys: s.surveys,
            retired: s.retired,
            failed: s.failed,
            damaged: s.damaged,
            patches: s.patches,
            active_boxes: s.active_boxes,
            samples: s.samples,
            disk_bytes: s.disk_bytes,
            crs: (!s.crs_key.is_empty()).then_some(s.crs_key.as_str()),
            vertical_crs: (!s.vertical_crs.is_empty()).then_some(s.vertical_crs.as_str()),
            backend: &s.backend,
            quadtree_nodes: s.quadtree_nodes,
            read_only: (!s.read_only.is_empty()).then_some(s.read_only.as_str()),
            cache_bytes: s.cache_bytes,
            cache_capacity_bytes: s.cache_capacity_bytes,
            cache_hits: s.cache_hits,
            cache_misses: s.cache_misses,
            requests_running: s.requests_running,
            requests_waiting: s.requests_waiting,
            requests_served: s.requests_served,
            requests_limit: s.requests_limit,
        }
    }
}

/// `query --json`.
#[derive(Serialize)]
struct QueryJson {
    patches: Vec<PatchJson>,
}

#[derive(Serialize)]
struct PatchJson {
    id: String,
    survey: String,
    level: u32,
    kind: &'static str,
    error: f64,
    max_error: f64,
    fallback: bool,
    bounds: [f64; 4],
}

impl PatchJson {
    fn of(p: &pb::Patch) -> Self {
        let b = p.bounds.unwrap_or_default();
        PatchJson {
            id: format!("{:016x}", p.id),
            survey: format!("{:016x}", p.survey),
            level: p.level,
            kind: match pb::PatchKind::try_from(p.kind) {
                Ok(pb::PatchKind::Edge) => "edge",
                _ => "bilinear",
            },
            error: p.error,
            max_error: p.max_error,
            fallback: p.fallback,
            bounds: [b.xmin, b.ymin, b.xmax, b.ymax],
        }
    }
}

/// Whether a server URL names this machine.
fn is_loopback_url(url: &str) -> bool {
    let rest = url.split_once("://").map_or(url, |(_, r)| r);
    let authority = rest.split('/').next().unwrap_or("");
    let host = match authority.strip_prefix('[') {
        Some(v6) => v6.split(']').next().unwrap_or(""),
        None => authority.split(':').next().unwrap_or(""),
    };
    host == "localhost"
        || host
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// A path for a line of output: control characters (a newline in a file name, say) escaped,
/// so that one name stays one line.
fn printable(s: &str) -> std::borrow::Cow<'_, str> {
    if s.chars().any(char::is_control) {
        s.escape_debug().to_string().into()
    } else {
        s.into()
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    quiet_vulkan_layers();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime");
    let result = rt.block_on(run(cli));
    // Work still running on blocking threads (an ingest, a query past its deadline) is not
    // waited for: every commit is atomic, so stopping now is as safe as a crash.
    rt.shutdown_timeout(std::time::Duration::from_millis(500));
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("patchwork: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Whether the daemon should open a GPU device: with software adapters refused, only when a
/// child process finds a real one. Asking in a child keeps a software driver the daemon will
/// not use out of its memory (Mesa's lavapipe maps 50 MB of libLLVM that never unloads), and
/// a driver that crashes while probing takes only the child with it.
fn real_gpu(allow_emulated: bool) -> Result<(), String> {
    if allow_emulated {
        return Ok(());
    }
    let exe = std::env::current_exe().map_err(|e| format!("cannot find this program: {e}"))?;
    let out = std::process::Command::new(exe)
        .arg("probe-gpu")
        .stdin(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .output()
        .map_err(|e| format!("the GPU probe did not run: {e}"))?;
    if !out.status.success() {
        return Err(format!("the GPU probe failed ({})", out.status));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let seen: Vec<&str> = text.lines().collect();
    if seen.iter().any(|l| l.starts_with("gpu\t")) {
        return Ok(());
    }
    let software: Vec<&str> = seen
        .iter()
        .filter_map(|l| l.strip_prefix("software\t"))
        .collect();
    Err(if software.is_empty() {
        "no GPU adapter with compute shaders".into()
    } else {
        patchwork::resample::gpu::software_refused(&software.join(", "))
    })
}

/// Turns off Mesa's device-select Vulkan layer, which the loader adds to every instance. To
/// pick a default device it connects to a Wayland display, and on a server without one that
/// prints an error to stderr at every start; the GPU probe ranks adapters itself. A value set
/// by the user stands.
fn quiet_vulkan_layers() {
    if std::env::var_os("NODEVICE_SELECT").is_none() {
        // SAFETY: called first thing in main, before the runtime or anything else starts a
        // thread that could read the environment at the same time.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loopback_urls_are_told_from_others() {
        for u in [
            "http://127.0.0.1:50051",
            "http://localhost:1",
            "http://[::1]:50051",
            "https://127.0.0.2",
        ] {
            assert!(is_loopback_url(u), "{u}");
        }
        for u in [
            "http://10.0.0.1:50051",
            "http://[2001:db8::1]:1",
            "http://example.org",
        ] {
            assert!(!is_loopback_url(u), "{u}");
        }
    }
}
