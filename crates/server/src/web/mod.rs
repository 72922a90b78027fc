//! HTTP for web map clients: MapLibre's raster-DEM tiles and TileJSON, Cesium's
//! quantized-mesh terrain and layer.json, float GeoTIFF tiles, heights at points, the
//! survey footprints and a viewer page.
//!
//! It runs on a port of its own (`http_listen`) rather than beside tonic on the gRPC one:
//! browsers speak HTTP/1.1 and gRPC needs HTTP/2, proxies and CDNs put in front of tile
//! servers want a plain HTTP origin, and the two can be exposed, cached and firewalled apart.
//! Handlers are thin: they read the request, run the work through the gRPC service's runner
//! (so the limits on running requests and their deadline hold for both, counted together), and
//! map its status to an HTTP code in one place ([`status_response`]).

pub mod proxy;
pub mod pyramid;
pub(crate) mod raster;
mod terrain;

use super::auth::Gate;
use super::grpc::Service;
use axum::body::Bytes;
use axum::extract::{Path, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use patchwork_core::geom::tiles::{geographic, mercator};
use patchwork_core::geom::Aabb;
use patchwork_core::index::query::Extracted;
use patchwork_core::sync::lock;
use patchwork_core::terrain::Terrain;
use patchwork_engine::request::parse_crs;
use patchwork_engine::{Ctx, Engine, EngineError, Heights, Metres, Reason, SampleRequest};
use pyramid::Pyramid;
use serde::Deserialize;
use std::sync::{Arc, Mutex, Weak};
use tonic::{Code, Status};

/// The viewer page: MapLibre hillshade and 3D terrain, and a Cesium globe, over the store.
const VIEWER: &str = include_str!("viewer.html");

/// Longest request URI taken: a tile's is under a hundred bytes, and a `/heights` request of
/// a few hundred points fits.
const MAX_URI: usize = 16 * 1024;

/// What the handlers share.
pub struct Web {
    svc: Service,
    gate: Gate,
    /// EPSG:3857 and EPSG:4326, the CRSs of the two pyramids.
    mercator: patchwork_core::crs::Crs,
    geographic: patchwork_core::crs::Crs,
    query_token: bool,
    /// `[http] public_url`, for TileJSON's absolute URLs.
    public_url: Option<String>,
    cache_control: HeaderValue,
    /// Encoded tiles by ETag: the ETag is made from the cut each time, so a tile found here is
    /// the one the data gives now.
    tiles: Option<quick_cache::sync::Cache<[u8; 16], Bytes, TileBytes>>,
    /// The pyramids over the last terrain published, made again when another is.
    pyramid: Mutex<(Weak<Terrain>, Arc<Pyramid>)>,
    /// What besides the data and the request changes a tile's bytes: this program's version
    /// and the top of LOD space (where the fill of voids stops). Part of every ETag, so that
    /// a client's copy made by another build or config is not taken for current.
    fingerprint: String,
}

/// Weighs a cached tile by its bytes.
#[derive(Clone)]
struct TileBytes;

impl quick_cache::Weighter<[u8; 16], Bytes> for TileBytes {
    fn weight(&self, _: &[u8; 16], v: &Bytes) -> u64 {
        v.len() as u64 + 64
    }
}

/// A tile as it goes out: its ETag, and its bytes unless the client has them.
pub struct Produced {
    pub(crate) etag: [u8; 16],
    /// Shared with the cache: a response takes no copy.
    pub(crate) body: Option<Bytes>,
    content_type: &'static str,
    /// The error the tile was made at where it is not the one asked (see
    /// `limits.max_web_tile_patches`): sent as `X-Patchwork-Error`.
    pub(crate) error: Option<f64>,
    /// Why the tile's heights are not in the frame the client expects: sent as a
    /// `Warning` header (code 299, a persistent warning).
    pub(crate) warning: Option<String>,
}

impl Web {
    /// The handlers' state over `svc`: the Terrain service's gate, the `[http]` config, and a
    /// tile cache of `http.tile_cache_mb` (none at 0).
    pub fn new(svc: Service) -> Web {
        let cfg = svc.engine().config();
        let mb = cfg.http.tile_cache_mb;
        let tiles = (mb > 0).then(|| {
            // About 20 kB a tile.
            let items = ((mb << 20) / 20_000).max(16) as usize;
            quick_cache::sync::Cache::with_weighter(items, mb << 20, TileBytes)
        });
        let gate = Gate::terrain(cfg);
        Web {
            mercator: patchwork_core::crs::Crs::epsg(3857)
                .expect("EPSG:3857 is in every CRS database"),
            geographic: patchwork_core::crs::Crs::wgs84(),
            query_token: cfg.http.query_token,
            public_url: cfg.http.public_url.clone(),
            cache_control: cache_control(&cfg.http.cache_control, gate.is_open()),
            gate,
            fingerprint: format!("{}/{}", env!("CARGO_PKG_VERSION"), cfg.index.max_error),
            tiles,
            pyramid: Mutex::new((Weak::new(), Arc::new(Pyramid::empty()))),
            svc,
        }
    }

    pub(crate) fn engine(&self) -> &Arc<Engine> {
        self.svc.engine()
    }

    /// `crs`, or None where it is the store's own: the CRS a cut names.
    fn unless_store(
        &self,
        engine: &Engine,
        crs: &patchwork_core::crs::Crs,
    ) -> Option<patchwork_core::crs::Crs> {
        (engine.crs().as_ref() != Some(crs)).then(|| crs.clone())
    }

    /// The pyramids over the terrain published now.
    pub fn pyramid(&self, engine: &Engine) -> Arc<Pyramid> {
        let now = engine.snapshot();
        {
            let p = lock(&self.pyramid);
            if p.0.upgrade().is_some_and(|t| Arc::ptr_eq(&t, &now)) {
                return p.1.clone();
            }
        }
        // Made without the lock: requests that find it stale meanwhile make their own, and
        // the last one kept is as good as any.
        let made = Arc::new(Pyramid::of(engine));
        *lock(&self.pyramid) = (Arc::downgrade(&now), made.clone());
        made
    }

    /// A tile's ETag: what was asked (`what`, which names the kind of tile, where it is and
    /// every parameter that changes its bytes), the patches its cut blends, and the surveys
    /// that can reach into it (`near`), whose coarser levels fill its voids. Patch ids are
    /// derived from their content, so the ETag changes exactly when the data under the tile
    /// does.
    fn etag(&self, what: &str, patches: &[Extracted], near: &[u64]) -> [u8; 16] {
        let mut h = blake3::Hasher::new();
        h.update(self.fingerprint.as_bytes());
        h.update(what.as_bytes());
        for p in patches {
            h.update(&p.id.0.to_le_bytes());
            h.update(&p.survey.0.to_le_bytes());
            h.update(&[p.fallback as u8]);
        }
        h.update(b"near");
        for s in near {
            h.update(&s.to_le_bytes());
        }
        let mut out = [0u8; 16];
        out.copy_from_slice(&h.finalize().as_bytes()[..16]);
        out
    }

    /// The tile of `etag`: None when the client has it (`if_none_match`), the cached bytes,
    /// or those `make` encodes, then kept.
    fn produce(
        &self,
        etag: [u8; 16],
        if_none_match: Option<&str>,
        content_type: &'static str,
        make: impl FnOnce() -> Result<Vec<u8>, EngineError>,
    ) -> Result<Produced, EngineError> {
        if if_none_match.is_some_and(|v| matches_etag(v, &etag)) {
            return Ok(Produced {
                etag,
                body: None,
                content_type,
                error: None,
                warning: None,
            });
        }
        let body = match self.tiles.as_ref().and_then(|c| c.get(&etag)) {
            Some(b) => b,
            None => {
                let b = Bytes::from(make()?);
                if let Some(c) = &self.tiles {
                    c.insert(etag, b.clone());
                }
                b
            }
        };
        Ok(Produced {
            etag,
            body: Some(body),
            content_type,
            error: None,
            warning: None,
        })
    }

    /// A tile's response: 200 with its bytes, or 304.
    fn reply(&self, p: Produced) -> Response {
        let etag = HeaderValue::from_str(&quote_etag(&p.etag)).expect("hex is a header value");
        let mut r = match p.body {
            Some(b) => (
                [(
                    header::CONTENT_TYPE,
                    HeaderValue::from_static(p.content_type),
                )],
                b,
            )
                .into_response(),
            None => StatusCode::NOT_MODIFIED.into_response(),
        };
        let h = r.headers_mut();
        h.insert(header::ETAG, etag);
        h.insert(header::CACHE_CONTROL, self.cache_control.clone());
        if let Some(e) = p.error {
            h.insert(
                "x-patchwork-error",
                HeaderValue::from_str(&e.to_string()).expect("a number is a header value"),
            );
        }
        if let Some(w) = p.warning {
            // A quoted string of visible ASCII: anything else in the text is left out.
            let text: String = w
                .chars()
                .map(|c| match c {
                    '"' | '\\' => '\'',
                    c if c.is_ascii_graphic() || c == ' ' => c,
                    _ => '?',
                })
                .collect();
            if let Ok(v) = HeaderValue::from_str(&format!("299 patchwork \"{text}\"")) {
                h.insert(header::WARNING, v);
            }
        }
        r
    }

    /// Runs `f` through the service: within the limits on running requests and the deadline,
    /// cancelled when the client hangs up.
    async fn run<T, F>(&self, f: F) -> Result<T, Response>
    where
        T: Send + 'static,
        F: FnOnce(&Engine, &patchwork_core::resample::Cancel) -> Result<T, EngineError>
            + Send
            + 'static,
    {
        self.svc.run(f).await.map_err(status_response)
    }
}

/// The configured `Cache-Control`, made `private` where reads need a token: a shared cache
/// may not keep what one client's token opened for the next (RFC 9111 §3.5).
fn cache_control(configured: &str, open: bool) -> HeaderValue {
    let v = if open {
        configured.to_string()
    } else {
        configured.replace("public", "private")
    };
    HeaderValue::from_str(&v).unwrap_or(HeaderValue::from_static("no-cache"))
}

/// An ETag as sent: weak, since the same tile goes out gzipped or not (RFC 9110 §8.8.3 keeps
/// strong validators for one representation's bytes).
pub(crate) fn quote_etag(e: &[u8; 16]) -> String {
    let mut s = String::with_capacity(36);
    s.push_str("W/\"");
    for b in e {
        s.push_str(&format!("{b:02x}"));
    }
    s.push('"');
    s
}

/// Whether an `If-None-Match` header names `etag` (or is `*`), weak or strong alike, as
/// RFC 9110 §13.1.2 compares them.
fn matches_etag(header: &str, etag: &[u8; 16]) -> bool {
    let sent = quote_etag(etag);
    let want = sent.trim_start_matches("W/");
    header
        .split(',')
        .map(str::trim)
        .any(|t| t == "*" || t.trim_start_matches("W/") == want)
}

/// The one place where a request's outcome becomes an HTTP code (gRPC's codes come from
/// [`super::status`], which maps the engine's errors).
pub fn status_response(s: Status) -> Response {
    let code = match s.code() {
        // A request a proxy sent to the replica of another region: 421, "misdirected".
        Code::OutOfRange if super::status::reason_of(&s) == Some(Reason::OutsideRegion) => {
            StatusCode::MISDIRECTED_REQUEST
        }
        Code::InvalidArgument | Code::OutOfRange => StatusCode::BAD_REQUEST,
        Code::Unauthenticated => StatusCode::UNAUTHORIZED,
        Code::PermissionDenied => StatusCode::FORBIDDEN,
        Code::NotFound => StatusCode::NOT_FOUND,
        // On the read path only a request that asks too much is refused so.
        Code::ResourceExhausted => StatusCode::PAYLOAD_TOO_LARGE,
        Code::FailedPrecondition => StatusCode::CONFLICT,
        // Too busy to answer within the deadline, stopping, or a store that cannot be read
        // now: trying again later can help.
        Code::Unavailable | Code::DeadlineExceeded | Code::Cancelled => {
            StatusCode::SERVICE_UNAVAILABLE
        }
        _ => StatusCode::INTERNAL_SERVER_ERROR,
    };
    let reason = super::status::reason_of(&s).unwrap_or(match s.code() {
        Code::InvalidArgument | Code::OutOfRange => Reason::InvalidRequest,
        Code::Unauthenticated => Reason::Unauthenticated,
        Code::PermissionDenied => Reason::PermissionDenied,
        Code::NotFound => Reason::NotFound,
        Code::ResourceExhausted => Reason::TooLarge,
        Code::FailedPrecondition | Code::Unavailable => Reason::Unavailable,
        Code::DeadlineExceeded | Code::Cancelled => Reason::Deadline,
        _ => Reason::Internal,
    });
    let mut r = error_body(code, s.message(), reason);
    if code == StatusCode::UNAUTHORIZED {
        r.headers_mut()
            .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
    }
    r
}

fn bad_request(m: impl Into<String>) -> Response {
    error_body(StatusCode::BAD_REQUEST, &m.into(), Reason::InvalidRequest)
}

/// An error's body: `{"error": what went wrong, "reason": its kind}`, the kind spelled as on
/// gRPC (`Reason::as_str`), for clients to branch on.
fn error_body(code: StatusCode, m: &str, reason: Reason) -> Response {
    (
        code,
        axum::Json(serde_json::json!({"error": m, "reason": reason.as_str()})),
    )
        .into_response()
}

/// The token a request carries: its `Authorization` header, else, where the config allows
/// it, a `token` in its query.
async fn admit(State(web): State<Arc<Web>>, req: Request, next: Next) -> Response {
    let path = req.uri().path();
    // The page and the libraries it loads hold no data.
    let open = path == "/" || path.starts_with("/lib/") || req.method() == Method::OPTIONS;
    if !open && !web.gate.is_open() {
        let header = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string);
        let from_query = || {
            req.uri()
                .query()
                .and_then(query_token)
                .map(|t| format!("Bearer {t}"))
        };
        let token = header.or_else(|| web.query_token.then(from_query).flatten());
        if let Err(s) = web.gate.check(token.as_deref()) {
            return status_response(s);
        }
    }
    next.run(req).await
}

/// Refuses a URI past [`MAX_URI`] before anything reads it.
async fn bounded(req: Request, next: Next) -> Response {
    if req.uri().to_string().len() > MAX_URI {
        return error_body(
            StatusCode::URI_TOO_LONG,
            &format!(
                "the request's URI is longer than {MAX_URI} bytes: ask for fewer points at once"
            ),
            Reason::TooLarge,
        );
    }
    next.run(req).await
}

/// Every error the router answers with outside the handlers (a path or a query that does not
/// parse, a route that does not exist) in the same JSON body as the handlers' own
/// ([`error_body`]), its kind from its code.
async fn json_errors(r: Response) -> Response {
    let status = r.status();
    let json = r
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/json"));
    if !(status.is_client_error() || status.is_server_error()) || json {
        return r;
    }
    let reason = match status {
        StatusCode::BAD_REQUEST => Reason::InvalidRequest,
        StatusCode::UNAUTHORIZED => Reason::Unauthenticated,
        StatusCode::FORBIDDEN => Reason::PermissionDenied,
        StatusCode::NOT_FOUND | StatusCode::METHOD_NOT_ALLOWED => Reason::NotFound,
        StatusCode::PAYLOAD_TOO_LARGE | StatusCode::URI_TOO_LONG => Reason::TooLarge,
        StatusCode::CONFLICT | StatusCode::SERVICE_UNAVAILABLE => Reason::Unavailable,
        _ => Reason::Internal,
    };
    let (parts, body) = r.into_parts();
    let text = axum::body::to_bytes(body, 64 << 10)
        .await
        .unwrap_or_default();
    let text = String::from_utf8_lossy(&text);
    let m = if text.is_empty() {
        status.canonical_reason().unwrap_or("error")
    } else {
        &text
    };
    let mut out = error_body(status, m, reason);
    for (k, v) in &parts.headers {
        if k != header::CONTENT_TYPE && k != header::CONTENT_LENGTH {
            out.headers_mut().insert(k.clone(), v.clone());
        }
    }
    out
}

/// The router of the web server over `svc`.
pub fn router(svc: Service) -> Router {
    let assets = svc.engine().config().http.assets_dir.clone();
    let web = Arc::new(Web::new(svc));
    let mut app = Router::new()
        .route("/", get(viewer))
        .route("/tiles.json", get(tilejson))
        .route("/tiles/{z}/{x}/{file}", get(raster_tile))
        .route("/tiles/{z}/{x}/{y}/{file}", get(tile_sources))
        .route("/terrain/layer.json", get(layer_json))
        .route("/terrain/{z}/{x}/{file}", get(terrain_tile))
        .route("/surveys.geojson", get(geojson))
        .route("/heights", get(heights));
    if let Some(dir) = assets {
        app = app.nest_service("/lib", tower_http::services::ServeDir::new(dir));
    }
    let cors = tower_http::cors::CorsLayer::new()
        .allow_origin(tower_http::cors::Any)
        .allow_methods([Method::GET, Method::HEAD, Method::OPTIONS])
        .allow_headers([header::AUTHORIZATION, header::IF_NONE_MATCH, header::ACCEPT])
        .expose_headers([
            header::ETAG,
            header::HeaderName::from_static("x-patchwork-error"),
            header::WARNING,
        ]);
    app.layer(middleware::from_fn_with_state(web.clone(), admit))
        .layer(middleware::map_response(json_errors))
        // Quantized-mesh tiles and the documents are gzipped once, here, for clients that
        // accept it; PNG and GeoTIFF tiles are compressed already and go as they are.
        .layer(tower_http::compression::CompressionLayer::new().gzip(true))
        .layer(cors)
        .layer(middleware::from_fn(bounded))
        .with_state(web)
}

/// Serves the web clients on `listener` until `shutdown`: over TLS with the daemon's
/// certificate when it has one (`tls_cert`, `tls_key`), as gRPC is, since tokens travel in
/// the requests. Each connection is one of the service's [`super::conns`], within their limit
/// and timeouts; its TLS handshake runs in a task of its own within [`HANDSHAKE`], so that a
/// client that connects and says nothing holds up no other. Requests run knowing their
/// connection, for the fair turns, and counted as running on it, so that it is not idle.
pub async fn serve(
    svc: Service,
    listener: tokio::net::TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), String> {
    use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
    let cfg = svc.engine().config().clone();
    let conns = svc.conns().clone();
    conns.start();
    let app = router(svc);
    let tls = match (&cfg.tls_cert, &cfg.tls_key) {
        (Some(cert), Some(key)) => Some(tokio_rustls::TlsAcceptor::from(
            super::tls::server_config(cert, key)?,
        )),
        _ => None,
    };
    let mut builder = hyper_util::server::conn::auto::Builder::new(TokioExecutor::new());
    builder
        .http1()
        .timer(TokioTimer::new())
        .header_read_timeout(std::time::Duration::from_millis(
            cfg.limits.header_timeout_ms,
        ));
    let builder = Arc::new(builder);
    let graceful = hyper_util::server::graceful::GracefulShutdown::new();
    tokio::pin!(shutdown);
    loop {
        let tcp = tokio::select! {
            t = conns.accept(&listener) => t,
            _ = &mut shutdown => break,
        };
        let conn = tcp.conn().clone();
        let app = app.clone();
        let service =
            hyper::service::service_fn(move |req: hyper::Request<hyper::body::Incoming>| {
                let running = conn.begin();
                let call = tower::ServiceExt::oneshot(app.clone(), req);
                super::conns::CLIENT.scope(conn.clone(), async move {
                    let r = call.await;
                    drop(running);
                    r
                })
            });
        let (builder, watcher) = (builder.clone(), graceful.watcher());
        let tls = tls.clone();
        tokio::spawn(async move {
            match tls {
                None => {
                    let c = builder.serve_connection_with_upgrades(TokioIo::new(tcp), service);
                    let _ = watcher.watch(c.into_owned()).await;
                }
                Some(acceptor) => {
                    let Ok(Ok(s)) = tokio::time::timeout(HANDSHAKE, acceptor.accept(tcp)).await
                    else {
                        return;
                    };
                    let c = builder.serve_connection_with_upgrades(TokioIo::new(s), service);
                    let _ = watcher.watch(c.into_owned()).await;
                }
            }
        });
    }
    // Requests in flight get the daemon's grace to finish; idle connections close now.
    drop(listener);
    graceful.shutdown().await;
    Ok(())
}

/// Longest a TLS handshake may take.
const HANDSHAKE: std::time::Duration = std::time::Duration::from_secs(10);

async fn viewer() -> Response {
    ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], VIEWER).into_response()
}

/// The raster-DEM encodings MapLibre decodes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Encoding {
    /// height = R·256 + G + B/256 − 32768: steps of 1/256 m.
    Terrarium,
    /// height = −10000 + (R·65536 + G·256 + B)·0.1: steps of 0.1 m.
    Mapbox,
}

impl Encoding {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Encoding::Terrarium => "terrarium",
            Encoding::Mapbox => "mapbox",
        }
    }
}

/// The image a raster-DEM tile comes as: the same pixels either way, WebP losslessly.
#[derive(Clone, Copy, Debug, Deserialize)]
#[serde(rename_all = "lowercase")]
enum Image {
    Png,
    Webp,
}

#[derive(Debug, Deserialize)]
struct TileParams {
    encoding: Option<Encoding>,
    /// TileJSON's tile image: `png` (the default) or `webp`.
    image: Option<Image>,
    size: Option<u32>,
    error: Option<f64>,
    /// What the heights are measured from: `store` (the default), `ellipsoid`, `EPSG:n`.
    heights: Option<String>,
    /// TileJSON's: the area, `west,south,east,north` in degrees, whose surveys its
    /// attribution names (every survey's by default).
    bounds: Option<String>,
}

impl TileParams {
    /// Tile (z, x, y) in `format`, at the size, error and heights these ask for: checked.
    fn request(
        &self,
        z: u32,
        x: u32,
        y: u32,
        format: raster::Format,
    ) -> Result<raster::Request, String> {
        if !mercator::valid(z, x, y) {
            return Err(format!(
                "tile {z}/{x}/{y} does not exist: z is 0 to 24, x and y 0 to 2^z − 1"
            ));
        }
        let size = self.size()?;
        let error = self.error()?;
        Ok(raster::Request {
            z,
            x,
            y,
            size,
            format,
            error: error.map_or_else(|| mercator::error(z, size), Metres::get),
            heights: self.heights()?,
        })
    }

    fn heights(&self) -> Result<Heights, String> {
        Heights::parse(self.heights.as_deref().unwrap_or("")).map_err(|e| e.to_string())
    }

    fn bounds(&self) -> Result<Option<Aabb>, String> {
        let Some(b) = &self.bounds else {
            return Ok(None);
        };
        let v: Vec<f64> = b
            .split(',')
            .map(|v| v.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| format!("bounds must be west,south,east,north in degrees, got {b:?}"))?;
        match v[..] {
            [w, s, e, n] if w <= e && s <= n && v.iter().all(|x| x.is_finite()) => {
                Ok(Some(Aabb::new(w, s, e, n)))
            }
            _ => Err(format!(
                "bounds must be west,south,east,north in degrees, got {b:?}"
            )),
        }
    }

    fn size(&self) -> Result<u32, String> {
        match self.size.unwrap_or(256) {
            s @ (256 | 512) => Ok(s),
            s => Err(format!("size must be 256 or 512, got {s}")),
        }
    }

    fn error(&self) -> Result<Option<Metres>, String> {
        self.error
            .map(Metres::error)
            .transpose()
            .map_err(|e| e.to_string())
    }
}

/// The URL of this server as the client reached it, for the documents' absolute URLs.
fn base_url(headers: &HeaderMap) -> String {
    let host = headers
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .unwrap_or("127.0.0.1");
    let scheme = headers
        .get("x-forwarded-proto")
        .and_then(|h| h.to_str().ok())
        .filter(|p| *p == "https")
        .unwrap_or("http");
    format!("{scheme}://{host}")
}

/// The `token` of a query, percent-decoded as a browser's `URLSearchParams` encodes it.
fn query_token(query: &str) -> Option<String> {
    form_urlencoded::parse(query.as_bytes())
        .find(|(k, _)| k == "token")
        .map(|(_, v)| v.into_owned())
}

/// The `token=…` of a query as it came, to pass on in the URLs a document hands out: only
/// where tokens may travel in URLs at all.
fn token_param<'a>(web: &Web, query: Option<&'a str>) -> Option<&'a str> {
    if !web.query_token {
        return None;
    }
    query?.split('&').find(|kv| kv.starts_with("token="))
}

async fn tilejson(
    State(web): State<Arc<Web>>,
    Query(p): Query<TileParams>,
    headers: HeaderMap,
    uri: axum::http::Uri,
) -> Response {
    let checked = p.size().and_then(|s| {
        p.error()?;
        Ok((s, p.heights()?, p.bounds()?))
    });
    let (size, frame, within) = match checked {
        Ok(c) => c,
        Err(m) => return bad_request(m),
    };
    let encoding = p.encoding.unwrap_or(Encoding::Terrarium);
    let mut query = format!("encoding={}&size={size}", encoding.name());
    if let Some(e) = p.error {
        query.push_str(&format!("&error={e}"));
    }
    if frame != Heights::Store {
        query.push_str(&format!("&heights={}", frame.key()));
    }
    // TileJSON's tile URLs must be absolute. They name the configured public URL, with the
    // request's token where tokens travel in URLs; else the Host the request came to, never
    // with a token: any client may write that header, and a document naming another host
    // with the token in it would hand the token to that host (or to whoever a shared cache
    // serves the document to). The viewer page adds its token to each tile URL itself.
    let base = match &web.public_url {
        Some(u) => {
            if let Some(t) = token_param(&web, uri.query()) {
                query.push('&');
                query.push_str(t);
            }
            u.trim_end_matches('/').to_string()
        }
        None => base_url(&headers),
    };
    let ext = match p.image.unwrap_or(Image::Png) {
        Image::Png => "png",
        Image::Webp => "webp",
    };
    let url = format!("{base}/tiles/{{z}}/{{x}}/{{y}}.{ext}?{query}");
    let engine = web.engine().clone();
    let doc = web
        .pyramid(&engine)
        .tilejson(url, size, encoding.name(), within.as_ref(), &frame);
    document(&web, doc)
}

fn document(web: &Web, doc: serde_json::Value) -> Response {
    let mut r = axum::Json(doc).into_response();
    r.headers_mut()
        .insert(header::CACHE_CONTROL, web.cache_control.clone());
    r
}

/// Splits `{y}.{ext}`.
fn tile_file(file: &str) -> Option<(u32, &str)> {
    let (y, ext) = file.split_once('.')?;
    Some((y.parse().ok()?, ext))
}

async fn raster_tile(
    State(web): State<Arc<Web>>,
    Path((z, x, file)): Path<(u32, u32, String)>,
    Query(p): Query<TileParams>,
    headers: HeaderMap,
) -> Response {
    let Some((y, ext)) = tile_file(&file) else {
        return bad_request(format!(
            "{file:?} is not a tile: ask for {{y}}.png, {{y}}.webp or {{y}}.tif"
        ));
    };
    let mut req = match p.request(z, x, y, raster::Format::Tiff) {
        Ok(r) => r,
        Err(m) => return bad_request(m),
    };
    req.format = match ext {
        "png" => raster::Format::Png(p.encoding.unwrap_or(Encoding::Terrarium)),
        "webp" => raster::Format::Webp(p.encoding.unwrap_or(Encoding::Terrarium)),
        "tif" | "tiff" => raster::Format::Tiff,
        other => {
            return (
                StatusCode::NOT_FOUND,
                format!("tiles come as .png, .webp or .tif, not .{other}"),
            )
                .into_response()
        }
    };
    let inm = if_none_match(&headers);
    let w = web.clone();
    match web
        .run(move |e, cancel| raster::tile(e, &w, &req, inm.as_deref(), cancel))
        .await
    {
        Ok(p) => web.reply(p),
        Err(r) => r,
    }
}

fn if_none_match(h: &HeaderMap) -> Option<String> {
    h.get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .map(str::to_string)
}

async fn layer_json(State(web): State<Arc<Web>>, uri: axum::http::Uri) -> Response {
    let engine = web.engine().clone();
    let p = web.pyramid(&engine);
    let doc = p.layer_json(&p.version(), token_param(&web, uri.query()).unwrap_or(""));
    document(&web, doc)
}

/// The surveys that served a raster tile, with their shares: what its `.png` holds, at the
/// same size and error.
async fn tile_sources(
    State(web): State<Arc<Web>>,
    Path((z, x, y, file)): Path<(u32, u32, u32, String)>,
    Query(p): Query<TileParams>,
) -> Response {
    if file != "sources.json" {
        return (StatusCode::NOT_FOUND, "ask for sources.json").into_response();
    }
    // The tile whose cut it tells of: its format and heights' frame change nothing of that.
    let req = match p.request(z, x, y, raster::Format::Tiff) {
        Ok(r) => r,
        Err(m) => return bad_request(m),
    };
    let w = web.clone();
    match web
        .run(move |e, cancel| raster::sources(e, &w, &req, cancel))
        .await
    {
        Ok(doc) => document(&web, doc),
        Err(r) => r,
    }
}

#[derive(Debug, Deserialize)]
struct TerrainParams {
    /// What the heights are measured from: `ellipsoid` (the default, Cesium's), `store`,
    /// `EPSG:n`.
    heights: Option<String>,
}

async fn terrain_tile(
    State(web): State<Arc<Web>>,
    Path((z, x, file)): Path<(u32, u32, String)>,
    Query(p): Query<TerrainParams>,
    headers: HeaderMap,
) -> Response {
    let Some((y, "terrain")) = tile_file(&file) else {
        return bad_request(format!(
            "{file:?} is not a terrain tile: ask for {{y}}.terrain"
        ));
    };
    if !geographic::valid(z, x, y) {
        return bad_request(format!(
            "terrain tile {z}/{x}/{y} does not exist: z is 0 to 24, x 0 to 2^(z+1) − 1 and y 0 \
             to 2^z − 1"
        ));
    }
    let asked = terrain::Asked::from_accept(
        headers
            .get(header::ACCEPT)
            .and_then(|v| v.to_str().ok())
            .unwrap_or(""),
    );
    let heights = match p.heights.as_deref() {
        None => None,
        Some(h) => match Heights::parse(h) {
            Ok(h) => Some(h),
            Err(e) => return bad_request(e.to_string()),
        },
    };
    let inm = if_none_match(&headers);
    let w = web.clone();
    let tile = terrain::Tile {
        z,
        x,
        y,
        asked,
        heights,
    };
    match web
        .run(move |e, cancel| terrain::tile(e, &w, &tile, inm.as_deref(), cancel))
        .await
    {
        Ok(p) => {
            // The extensions in the bytes are those the Accept header asked for.
            let mut r = web.reply(p);
            r.headers_mut()
                .append(header::VARY, HeaderValue::from_static("accept"));
            r
        }
        Err(r) => r,
    }
}

async fn geojson(State(web): State<Arc<Web>>) -> Response {
    let engine = web.engine().clone();
    let mut r = document(&web, web.pyramid(&engine).geojson());
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/geo+json"),
    );
    r
}

#[derive(Debug, Deserialize)]
struct HeightParams {
    points: String,
    error: Option<f64>,
    crs: Option<String>,
    /// What the heights are measured from: `store` (the default), `ellipsoid`, `EPSG:n`.
    heights: Option<String>,
    /// Whether to say what served each height.
    sources: Option<bool>,
}

/// What served a height, as `/heights` and `sources.json` say it: the survey's id, its file
/// (the name, without the daemon's folders), what its sidecar says of it, and the patch's
/// level, cell and error.
fn source_json(s: &patchwork_engine::sources::Source) -> serde_json::Value {
    let a = &s.about;
    serde_json::json!({
        "id": s.survey.to_string(),
        "file": pyramid::file_name(&s.file),
        "title": a.title,
        "license": a.license,
        "attribution": a.attribution,
        "acquired": a.acquired,
        "level": s.level,
        "cell_m": s.cell_m,
        "error_m": s.error_m,
    })
}

/// Heights at points: what SampleHeights answers, as JSON, null where there is no data.
async fn heights(State(web): State<Arc<Web>>, Query(p): Query<HeightParams>) -> Response {
    let coords: Result<Vec<f64>, _> = p.points.split(',').map(|v| v.trim().parse()).collect();
    let coords = match coords {
        Ok(c) if !c.is_empty() && c.len() % 2 == 0 => c,
        _ => {
            return bad_request(
                "points must be x,y pairs of numbers separated by commas: points=x0,y0,x1,y1",
            )
        }
    };
    let points: Vec<[f64; 2]> = coords.chunks(2).map(|c| [c[0], c[1]]).collect();
    let error = p.error.unwrap_or(0.0);
    let asked_sources = p.sources.unwrap_or(false);
    let crs = p.crs.clone().unwrap_or_else(|| "EPSG:4326".into());
    let req = parse_crs(&crs).and_then(|crs| {
        let heights = Heights::parse(p.heights.as_deref().unwrap_or(""))?;
        Ok(SampleRequest::new(points, crs, error)?
            .with_heights(heights)
            .with_sources(p.sources.unwrap_or(false)))
    });
    let req = match req {
        Ok(r) => r,
        Err(e) => return bad_request(e.to_string()),
    };
    let r = web
        .run(move |e, cancel| e.sample(&req, Ctx::until(cancel)))
        .await;
    match r {
        Ok(s) => {
            let hs: Vec<Option<f32>> = s
                .heights
                .iter()
                .map(|v| (!v.is_nan()).then_some(*v))
                .collect();
            let vertical = s.frame.vertical.as_ref().map(|v| v.key().to_string());
            let mut doc = serde_json::json!({
                "heights": hs,
                "error": error,
                "vertical_crs": vertical,
                "frame_error": s.frame.error_m,
            });
            if asked_sources {
                let sources: Vec<serde_json::Value> = s
                    .sources
                    .iter()
                    .map(|x| x.as_ref().map_or(serde_json::Value::Null, source_json))
                    .collect();
                doc["sources"] = sources.into();
            }
            axum::Json(doc).into_response()
        }
        Err(r) => r,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn if_none_match_takes_lists_weak_tags_and_stars() {
        let e = [0xab; 16];
        let q = quote_etag(&e);
        assert!(q.starts_with("W/\""));
        assert!(matches_etag(&q, &e));
        assert!(matches_etag(q.trim_start_matches("W/"), &e));
        assert!(matches_etag(&format!("\"x\", {q}"), &e));
        assert!(matches_etag("*", &e));
        assert!(!matches_etag("\"abab\"", &e));
    }

    #[test]
    fn query_tokens_are_percent_decoded_and_public_becomes_private_behind_tokens() {
        assert_eq!(
            query_token("a=1&token=ab%2Bc%3D%3D&b=2").as_deref(),
            Some("ab+c==")
        );
        assert_eq!(query_token("tokens=x"), None);
        assert_eq!(
            cache_control("public, max-age=60", true),
            "public, max-age=60"
        );
        assert_eq!(
            cache_control("public, max-age=60", false),
            "private, max-age=60"
        );
    }

    #[test]
    fn tile_files_name_a_row_and_a_format() {
        assert_eq!(tile_file("817.png"), Some((817, "png")));
        assert_eq!(tile_file("3.terrain"), Some((3, "terrain")));
        assert_eq!(tile_file("x.png"), None);
        assert_eq!(tile_file("817"), None);
    }
}
