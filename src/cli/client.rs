//! Reaching the daemon: the target and its token, the gRPC clients, or the store opened in
//! this process with `--data-dir`; and the one way every command makes a request of either.

use super::Fail;
use clap::Args;
use patchwork::config::Config;
use patchwork::engine::Engine;
use patchwork::serve::proto::{
    self as pb, admin_client::AdminClient, terrain_client::TerrainClient,
};
use std::path::PathBuf;
use std::sync::Arc;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

#[derive(Args, Clone)]
pub struct Target {
    /// The daemon to talk to.
    #[arg(
        long,
        env = "PATCHWORK_SERVER",
        default_value = "http://127.0.0.1:50051"
    )]
    pub server: String,
    /// Open the store in DIR directly instead of talking to a daemon.
    #[arg(long, value_name = "DIR")]
    pub data_dir: Option<PathBuf>,
    /// Config for direct mode (layout, limits); defaults otherwise.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// A file holding the bearer token to send; otherwise PATCHWORK_TOKEN, then
    /// PATCHWORK_ADMIN_TOKEN, is sent when set.
    #[arg(long, env = "PATCHWORK_TOKEN_FILE", value_name = "FILE")]
    pub token_file: Option<PathBuf>,
    /// PEM certificate of the authority that signed the daemon's TLS certificate, for an
    /// https:// server (the system's roots are not used).
    #[arg(long, env = "PATCHWORK_CA", value_name = "FILE")]
    pub ca: Option<PathBuf>,
}

/// Adds the bearer token, when there is one, to every request.
#[derive(Clone)]
pub struct Bearer(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

pub type Authed = InterceptedService<Channel, Bearer>;

/// The token to send: from --token-file, else PATCHWORK_TOKEN, else PATCHWORK_ADMIN_TOKEN.
pub fn token(t: &Target) -> Result<Bearer, Fail> {
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
pub enum Client {
    Remote {
        terrain: Box<TerrainClient<Authed>>,
        admin: Box<AdminClient<Authed>>,
    },
    Local(Arc<Engine>),
}

impl Client {
    pub async fn connect(t: &Target) -> Result<Client, Fail> {
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

impl Client {
    /// Opens the GPU of a store opened in this process, for a request whose `backend` may use
    /// it, as the daemon opens its own at start; a daemon's client has nothing to open.
    pub async fn open_gpu_for(&self, backend: pb::Backend) -> Result<(), Fail> {
        if let (Client::Local(e), false) = (self, backend == pb::Backend::Cpu) {
            let e = e.clone();
            tokio::task::spawn_blocking(move || super::serve::open_gpu(&e)).await?;
        }
        Ok(())
    }
}

/// Whether a server URL names this machine.
pub fn is_loopback_url(url: &str) -> bool {
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

/// Runs one request either way: over gRPC, or through the same dispatcher the daemon uses.
macro_rules! call {
    ($client:expr, $svc:ident . $rpc:ident($req:expr), $local:expr) => {
        match $client {
            $crate::cli::client::Client::Remote { $svc, .. } => $svc
                .$rpc($req)
                .await
                .map(|r| r.into_inner())
                .map_err(|s| -> $crate::cli::Fail { s.message().to_string().into() }),
            $crate::cli::client::Client::Local(engine) => {
                let engine = engine.clone();
                tokio::task::spawn_blocking(move || $local(&engine))
                    .await?
                    .map_err(|e| -> $crate::cli::Fail { e.to_string().into() })
            }
        }
    };
}

pub(crate) use call;

/// Every message of a server stream, in order, or the first error.
pub async fn collect<T>(
    reply: Result<tonic::Response<tonic::Streaming<T>>, tonic::Status>,
) -> Result<Vec<T>, Fail> {
    let mut s = reply.map_err(status)?.into_inner();
    let mut all = Vec::new();
    while let Some(m) = s.message().await.map_err(status)? {
        all.push(m);
    }
    Ok(all)
}

/// A status from the daemon as the CLI says it: its message alone.
pub fn status(s: tonic::Status) -> Fail {
    s.message().to_string().into()
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
