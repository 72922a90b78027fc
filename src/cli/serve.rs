//! `patchwork serve`: the daemon, from its config to a clean stop on SIGTERM; and the GPU probe
//! it runs in a child process.

use super::Fail;
use patchwork::config::Config;
use patchwork::engine::Engine;
use patchwork::serve::grpc;
use std::path::PathBuf;
use std::sync::Arc;

/// How long requests in flight get to finish after SIGTERM or Ctrl-C. Stopping mid-ingest
/// is safe: a commit is one atomic batch, and the inbox picks the file up again.
const GRACE: std::time::Duration = std::time::Duration::from_secs(3);

pub async fn serve(
    config: Option<PathBuf>,
    follow: Option<String>,
    region: Option<String>,
) -> Result<(), Fail> {
    let mut cfg = Config::load(config.as_deref())?;
    if let Some(url) = follow {
        cfg.storage.set_follow(&url)?;
    }
    if let Some(r) = region {
        cfg.storage.set_region(&r)?;
    }
    cfg.validate()?;
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
            open_gpu(&e);
            Ok::<_, patchwork::engine::EngineError>(e)
        })
        .await??,
    );
    let listener = tokio::net::TcpListener::bind(&listen)
        .await
        .map_err(|e| format!("cannot listen on {listen}: {e}"))?;
    let http_listen = engine.config().http_listen.clone();
    let http = if http_listen.trim().is_empty() {
        None
    } else {
        Some(
            tokio::net::TcpListener::bind(&http_listen)
                .await
                .map_err(|e| format!("cannot listen on {http_listen} (http_listen): {e}"))?,
        )
    };
    let c = engine.config();
    let tls = c.tls_cert.is_some();
    if !patchwork::serve::auth::is_loopback(&listen) && !tls {
        tracing::warn!("serving beyond this machine without TLS: tokens and data travel in clear; set tls_cert and tls_key");
    }
    tracing::info!(address = %listener.local_addr()?, tls, admin_token = c.admin_token.is_some(), read_token = c.read_token.is_some(), data = ?c.data_dir, inbox = ?c.inbox, "serving");
    if let Some(h) = &http {
        let address = h.local_addr()?;
        let scheme = if tls { "https" } else { "http" };
        tracing::info!(%address, tls, "serving web map clients: the viewer at {scheme}://{address}/");
        if !patchwork::serve::auth::is_loopback(&http_listen) && !tls {
            tracing::warn!("serving HTTP beyond this machine without TLS: tokens and data travel in clear; set tls_cert and tls_key");
        }
    }
    if let Some(why) = engine.read_only() {
        tracing::warn!(reason = %why, "read-only: queries are served, writes are refused until this is resolved");
    }
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    // A replica watches no inbox: its terrain is the writer's, as published.
    let watcher = match engine.follows() {
        Some(url) => {
            tracing::info!(%url, "a read replica: following the writer's commits");
            tokio::spawn(async {})
        }
        None => tokio::spawn(patchwork::watch::run(engine.clone(), stop_rx.clone())),
    };
    tokio::spawn(patchwork::engine::rounds(engine.clone(), stop_rx.clone()));
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
    // Before the service sizes its connection limit from it.
    let files = patchwork::serve::conns::raise_file_limit();
    // One service for both servers: the limits on running requests and connections hold for
    // them together.
    let svc = grpc::Service::new(engine, stop_rx.clone());
    tracing::info!(
        connections = svc.conns().most(),
        file_limit = files,
        "connections held at most on both ports together"
    );
    if let Some(h) = http {
        let web = patchwork::serve::web::serve(svc.clone(), h, stopped(stop_rx.clone()));
        tokio::spawn(async move {
            if let Err(e) = web.await {
                tracing::error!(error = %e, "the HTTP server stopped");
            }
        });
    }
    let server = grpc::serve_service(svc, listener, stopped(stop_rx.clone()));
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

/// Opens the GPU device `e` resamples on, where a real one (or an allowed software one) is
/// there; otherwise says why not, and `e` resamples on the CPU. The daemon does this at start,
/// and a command on a store opened in its own process (`--data-dir`) before a tile or mesh
/// that may use the GPU.
pub(super) fn open_gpu(e: &Engine) {
    match real_gpu(e.config().allow_emulated_gpu) {
        Ok(()) => e.enable_gpu(),
        Err(why) => tracing::info!(reason = %why, "no GPU device: resampling on the CPU"),
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
        software_refused(&software.join(", "))
    })
}

/// Lists the GPU adapters with compute shaders, one a line (`patchwork probe-gpu`).
pub fn probe_gpu() -> Result<(), Fail> {
    #[cfg(feature = "gpu")]
    for line in patchwork::gpu::list_adapters() {
        println!("{line}");
    }
    Ok(())
}

#[cfg(feature = "gpu")]
use patchwork::gpu::software_refused;

/// Without the `gpu` feature no adapter is ever taken, software or not.
#[cfg(not(feature = "gpu"))]
fn software_refused(adapters: &str) -> String {
    format!("this build has no GPU support (the gpu feature); adapters seen: {adapters}")
}

/// `patchwork config`: every key that is set, with its value and where it came from.
pub fn print_config(file: Option<&std::path::Path>) -> Result<(), Fail> {
    let settings = patchwork::config::explain(file, |k| std::env::var(k).ok())?;
    let lines: Vec<String> = settings
        .iter()
        .map(|s| format!("{} = {}", s.key, s.value))
        .collect();
    let width = lines
        .iter()
        .map(|l| l.chars().count())
        .max()
        .unwrap_or(0)
        .min(60);
    match file {
        Some(f) => println!(
            "# serve's configuration: {} and the environment",
            f.display()
        ),
        None => println!("# serve's configuration: the compiled-in defaults and the environment"),
    }
    for (line, s) in lines.iter().zip(&settings) {
        let pad = width.saturating_sub(line.chars().count());
        println!("{line}{}  # {}", " ".repeat(pad), s.origin.word());
    }
    Ok(())
}
