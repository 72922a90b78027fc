//! Configuration: compiled-in defaults, then an optional TOML file, then environment overrides
//! for the top-level keys (`PATCHWORK_<KEY>`). `config/patchwork.toml` documents every key.

use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::Crs;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::evidence::Contradicted;
use patchwork_core::model::mipmap::Filter;
use patchwork_core::model::patch::{PatchKind, PatchLayout};
use patchwork_core::model::survey::Recipe;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OnDelete {
    /// A file deleted from the inbox retires its survey.
    Retire,
    /// The survey stays; only `patchwork retire` removes it.
    Keep,
}

/// The ε given to files with no sidecar and no `--accuracy`: a number of metres, or `"auto"`
/// to estimate it from each survey's own samples.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DefaultAccuracy {
    Auto,
    Metres(f64),
}

impl std::str::FromStr for DefaultAccuracy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let t = s.trim();
        if t.eq_ignore_ascii_case("auto") {
            return Ok(DefaultAccuracy::Auto);
        }
        t.parse()
            .map(DefaultAccuracy::Metres)
            .map_err(|_| format!("{s:?} is neither \"auto\" nor a number of metres"))
    }
}

impl Serialize for DefaultAccuracy {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            DefaultAccuracy::Auto => s.serialize_str("auto"),
            DefaultAccuracy::Metres(m) => s.serialize_f64(*m),
        }
    }
}

impl<'de> Deserialize<'de> for DefaultAccuracy {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Number(f64),
            Text(String),
        }
        match Raw::deserialize(d)? {
            Raw::Number(m) => Ok(DefaultAccuracy::Metres(m)),
            Raw::Text(t) => t.parse().map_err(serde::de::Error::custom),
        }
    }
}

/// A token, kept out of debug output and logs.
#[derive(Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Secret(pub String);

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Secret(…)")
    }
}

impl Secret {
    pub fn expose(&self) -> &str {
        &self.0
    }
}

/// How the store uses its disk, and where its chunk bytes go.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Storage {
    /// Free space every write leaves on the store's disk, in MiB.
    pub min_free_mb: u64,
    /// Size of the reserve file beside the store, in MiB; 0 keeps none.
    pub reserve_mb: u64,
    /// Where the chunk bytes go; the database stays in `data_dir` with every backend.
    pub backend: BackendKind,
    /// The S3 (or S3-compatible) bucket of `backend = "s3"`.
    pub s3: S3,
    /// The folder of `backend = "folder"`: an object store's layout on a local or mounted
    /// disk.
    pub folder: Option<PathBuf>,
    /// Object-store backends: the longest one request may take, retries included, in ms.
    pub timeout_ms: u64,
    /// Object-store backends: how many times a failed request (a 503, a dropped connection)
    /// is tried again, with exponential backoff, within `timeout_ms`.
    pub retries: u64,
    /// Object-store backends: how long the segments a compaction let go of are kept, in
    /// seconds, for readers still holding the database from before it.
    pub gc_grace_s: u64,
    /// Object-store backends: how long the writer's lease lasts unless renewed, in seconds;
    /// it is renewed every third of that.
    pub lease_s: u64,
    /// Object-store backends: the writer publishes a snapshot of its database for replicas
    /// every this many commits (each commit's log goes up anyway).
    pub snapshot_every: u64,
    /// Serve as a read replica of the store at this URL (`s3://bucket/prefix`, or
    /// `file:///folder`) instead of as its writer; empty: the writer. Set by `serve --follow`.
    pub follow: String,
    /// A replica: how often it asks for the writer's new commits, in ms. The writer, too,
    /// tries this often to publish a commit's log that could not go up at once.
    pub poll_ms: u64,
}

impl Storage {
    /// Makes this the config of a replica of the store at `url`: `s3://bucket/prefix` (the
    /// endpoint, region and credentials stay as configured) or `file:///folder`.
    pub fn set_follow(&mut self, url: &str) -> Result<(), ConfigError> {
        let bad = |why: &str| ConfigError::Invalid(format!("--follow {url}: {why}"));
        if let Some(rest) = url.strip_prefix("s3://") {
            let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
            if bucket.is_empty() {
                return Err(bad("names no bucket"));
            }
            self.backend = BackendKind::S3;
            self.s3.bucket = bucket.to_string();
            self.s3.prefix = prefix.trim_matches('/').to_string();
        } else if let Some(path) = url.strip_prefix("file://") {
            if !path.starts_with('/') {
                return Err(bad("a folder is named by an absolute path, file:///…"));
            }
            self.backend = BackendKind::Folder;
            self.folder = Some(path.into());
        } else {
            return Err(bad("expected s3://bucket/prefix or file:///folder"));
        }
        self.follow = url.to_string();
        Ok(())
    }
}

impl Default for Storage {
    fn default() -> Self {
        Storage {
            min_free_mb: 64,
            reserve_mb: 64,
            backend: BackendKind::Local,
            s3: S3::default(),
            folder: None,
            timeout_ms: 10_000,
            retries: 4,
            gc_grace_s: 3600,
            lease_s: 15,
            snapshot_every: 64,
            follow: String::new(),
            poll_ms: 1000,
        }
    }
}

/// Where a store's chunk bytes go.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendKind {
    /// The pack file beside the database.
    #[default]
    Local,
    /// An S3 bucket, or any server that speaks S3's protocol.
    S3,
    /// A folder, laid out as an object store is.
    Folder,
}

impl std::str::FromStr for BackendKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim() {
            "local" => Ok(BackendKind::Local),
            "s3" => Ok(BackendKind::S3),
            "folder" => Ok(BackendKind::Folder),
            other => Err(format!(
                "{other:?} is not a storage backend: \"local\", \"s3\" or \"folder\""
            )),
        }
    }
}

/// The `[storage.s3]` section. Credentials are read from the environment as AWS's tools read
/// them (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`, …), never from
/// this file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct S3 {
    /// The server's URL; empty for AWS itself.
    pub endpoint: String,
    pub bucket: String,
    /// The folder inside the bucket that this store's objects go under.
    pub prefix: String,
    pub region: String,
    /// Whether a plain `http://` endpoint is allowed.
    pub allow_http: bool,
}

impl Default for S3 {
    fn default() -> Self {
        S3 {
            endpoint: String::new(),
            bucket: String::new(),
            prefix: String::new(),
            region: "us-east-1".into(),
            allow_http: false,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    /// Most samples in one resampled tile (width × height).
    pub max_tile_samples: u64,
    /// Most patches one query may return.
    pub max_patches: u64,
    /// Most points in one SampleHeights request.
    pub max_points: u64,
    /// Longest a request may run, in milliseconds.
    pub deadline_ms: u64,
    /// Requests that run at once (queries, tiles, listings); more wait their turn within
    /// their deadline. Together with the tile and point limits, this bounds the memory
    /// clients can make the daemon hold.
    pub max_running_requests: u64,
    /// Most memory one file's decoded raster may take, in MiB; larger headers are refused
    /// before anything is read.
    pub max_ingest_mb: u64,
    /// Files read and modelled at once. Each takes about five times its raster in memory;
    /// two keep both cores busy, one reading and modelling while the other's survey is
    /// indexed and committed (commits are one at a time whatever this says).
    pub ingest_parallel: u64,
    /// Heights outside [min_height_m, max_height_m] are not terrain in metres: a file holding
    /// any is refused.
    pub min_height_m: f64,
    pub max_height_m: f64,
    /// Most paths in one Ingest request.
    pub max_ingest_paths: u64,
    /// Most failed files remembered; the oldest records go first.
    pub max_failures: u64,
    /// Most streams that stay open (view sessions and subscriptions) at once, and on one
    /// connection; more are refused with RESOURCE_EXHAUSTED.
    pub max_streams: u64,
    pub max_streams_per_connection: u64,
    /// Most connections held open on both ports together; the daemon takes fewer where its
    /// file limit leaves less after what the store and the inbox need. A connection past it
    /// closes the one idle longest, or is closed itself when none is idle.
    pub max_connections: u64,
    /// Longest a new connection may take to send its first request's headers (and an
    /// HTTP/1 request its headers), in milliseconds: a client that connects and says nothing,
    /// or trickles its headers, is closed then.
    pub header_timeout_ms: u64,
    /// Longest a connection may sit with no request running and nothing sent either way, in
    /// milliseconds. gRPC's keepalive pings (every 30 s) keep a live gRPC client's
    /// connection from ever being idle that long.
    pub idle_timeout_ms: u64,
    /// Most patches the cut of one web map tile (XYZ raster) may blend: a tile whose cut at
    /// the error asked holds more (a low zoom at a tiny error) is made from the finest coarser
    /// cut within it, and its `X-Patchwork-Error` header says the error served.
    pub max_web_tile_patches: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_tile_samples: 4096 * 4096,
            max_patches: 250_000,
            max_points: 1_000_000,
            deadline_ms: 30_000,
            max_running_requests: 8,
            max_ingest_mb: 4096,
            ingest_parallel: 2,
            min_height_m: -12_000.0,
            max_height_m: 9_000.0,
            max_ingest_paths: 256,
            max_failures: 1000,
            max_streams: 256,
            max_streams_per_connection: 32,
            max_connections: 4096,
            header_timeout_ms: 10_000,
            idle_timeout_ms: 75_000,
            max_web_tile_patches: 4096,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub data_dir: PathBuf,
    pub inbox: Vec<PathBuf>,
    /// Folders besides the inbox that Ingest requests may name files in.
    pub ingest_roots: Vec<PathBuf>,
    pub listen: String,
    /// Where the HTTP server for web map clients listens; empty serves no HTTP.
    pub http_listen: String,
    /// Bearer token for the Admin service (and for reads too).
    pub admin_token: Option<Secret>,
    /// Bearer token for the Terrain service; unset leaves reads open.
    pub read_token: Option<Secret>,
    /// PEM certificate chain and private key: both set serves TLS.
    pub tls_cert: Option<PathBuf>,
    pub tls_key: Option<PathBuf>,
    /// ε for files with no sidecar and no `--accuracy`.
    pub accuracy_m: DefaultAccuracy,
    /// The store's horizontal CRS: an EPSG code, a WKT or a PROJ string; unset, a new store
    /// is in EPSG:4326 whatever survey arrives first.
    pub crs: Option<String>,
    /// How long a file's size and mtime must stay unchanged before it is ingested.
    pub settle_ms: u64,
    /// Memory for decoded samples, in MiB; the store's page cache takes a quarter more.
    pub cache_mb: u64,
    pub on_delete: OnDelete,
    /// Log filter, e.g. "info" or "patchwork=debug".
    pub log: String,
    /// Whether a software GPU adapter (llvmpipe, lavapipe, WARP) may resample when no real
    /// one is present; it is slower than the CPU path.
    pub allow_emulated_gpu: bool,
    pub limits: Limits,
    pub storage: Storage,
    pub index: IndexConfig,
    pub patches: Patches,
    /// How a new store makes its surveys' coarser levels; an existing store keeps its own.
    pub mipmap: Filter,
    pub vertical: Vertical,
    pub accuracy: Accuracy,
    pub http: Http,
}

/// The `[http]` section: the web map clients' server (tiles, terrain, the viewer page).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Http {
    /// Whether the read token may come as `?token=` on the URL, for browsers' tile
    /// requests, which cannot set a header. URLs end up in logs and histories: turn it off
    /// where that matters and put a proxy that adds the header in front.
    pub query_token: bool,
    /// The `Cache-Control` of tiles and their documents. Tiles carry an ETag that changes
    /// exactly when the data under them does, so a short max-age costs only revalidations.
    pub cache_control: String,
    /// Memory for encoded tiles (PNG, GeoTIFF, quantized-mesh), MiB; 0 keeps none.
    pub tile_cache_mb: u64,
    /// A `node_modules` folder holding `maplibre-gl` and `cesium`, served under `/lib/` for
    /// the viewer page (`npm install maplibre-gl cesium` makes one); unset, the page loads
    /// them from a CDN.
    pub assets_dir: Option<PathBuf>,
    /// The URL clients reach this server at (`https://terrain.example.org`, a proxy's), for
    /// the absolute tile URLs of TileJSON. Unset, they name the Host the request came to,
    /// and never carry a token: a header is the client's to write.
    pub public_url: Option<String>,
}

impl Default for Http {
    fn default() -> Self {
        Http {
            query_token: true,
            cache_control: "public, max-age=60".into(),
            tile_cache_mb: 64,
            assets_dir: None,
            public_url: None,
        }
    }
}

/// The `[accuracy]` section: what a new store does with accuracy claims that other surveys'
/// evidence finds false (docs/MODEL.md, "Overlaps"); an existing store keeps its own.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Accuracy {
    pub contradicted: Contradicted,
}

/// The `[vertical]` section: the store's vertical CRS and the geoid grids that carry heights
/// into it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Vertical {
    /// "EPSG:n" or "ellipsoidal"; unset adopts the first survey's that names one.
    pub crs: Option<String>,
    /// Geoid undulation grids, by the vertical CRS ("EPSG:n") they relate to the ellipsoid.
    pub geoids: std::collections::BTreeMap<String, PathBuf>,
}

/// The `[patches]` section: the layout every store keeps, and the kind of a new store.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Patches {
    /// Kernel side in cells.
    pub kernel: usize,
    /// Extension zone around the kernel, in cells.
    pub margin: usize,
    /// What a new store's patches evaluate; an existing store keeps its own.
    pub kind: PatchKind,
}

impl Default for Patches {
    fn default() -> Self {
        let l = PatchLayout::default();
        Patches {
            kernel: l.kernel,
            margin: l.margin,
            kind: PatchKind::default(),
        }
    }
}

impl Patches {
    pub fn layout(&self) -> PatchLayout {
        PatchLayout {
            kernel: self.kernel,
            margin: self.margin,
        }
    }
}

impl Config {
    /// How a new store builds its surveys.
    pub fn recipe(&self) -> Recipe {
        Recipe {
            mipmap: self.mipmap,
            patches: self.patches.kind,
        }
    }
}

impl Default for Config {
    fn default() -> Self {
        Config {
            data_dir: PathBuf::from("./data"),
            inbox: vec![PathBuf::from("./inbox")],
            ingest_roots: Vec::new(),
            listen: "127.0.0.1:50051".into(),
            http_listen: "127.0.0.1:50052".into(),
            admin_token: None,
            read_token: None,
            tls_cert: None,
            tls_key: None,
            accuracy_m: DefaultAccuracy::Auto,
            crs: None,
            settle_ms: 1500,
            cache_mb: 512,
            on_delete: OnDelete::Retire,
            log: "info".into(),
            allow_emulated_gpu: false,
            limits: Limits::default(),
            storage: Storage::default(),
            index: IndexConfig::default(),
            patches: Patches::default(),
            mipmap: Filter::default(),
            vertical: Vertical::default(),
            accuracy: Accuracy::default(),
            http: Http::default(),
        }
    }
}

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("cannot read config {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("config {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("environment variable {var}: {message}")]
    Env { var: String, message: String },
    #[error("{0}")]
    Invalid(String),
}

/// Whether a token can travel in an HTTP header and is long enough not to be guessed.
pub fn valid_token(t: &str) -> bool {
    (16..=1024).contains(&t.len()) && t.bytes().all(|b| b.is_ascii_graphic())
}

/// Parses "EPSG:4326" (or a bare number).
pub fn parse_epsg(s: &str) -> Option<u32> {
    let t = s.trim();
    let n = t
        .strip_prefix("EPSG:")
        .or_else(|| t.strip_prefix("epsg:"))
        .unwrap_or(t);
    n.parse().ok()
}

impl Config {
    /// Defaults, then `file` if given, then the environment.
    pub fn load(file: Option<&Path>) -> Result<Config, ConfigError> {
        let mut cfg = match file {
            Some(path) => {
                let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
                    path: path.into(),
                    source,
                })?;
                toml::from_str(&text).map_err(|e| ConfigError::Parse {
                    path: path.into(),
                    message: e.to_string(),
                })?
            }
            None => Config::default(),
        };
        if !cfg.storage.follow.is_empty() {
            let url = cfg.storage.follow.clone();
            cfg.storage.set_follow(&url)?;
        }
        cfg.apply_env(|k| std::env::var(k).ok())?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Applies `PATCHWORK_<KEY>` overrides for the top-level keys.
    pub fn apply_env(&mut self, get: impl Fn(&str) -> Option<String>) -> Result<(), ConfigError> {
        fn num<T: std::str::FromStr>(var: &str, v: &str) -> Result<T, ConfigError> {
            v.trim().parse().map_err(|_| ConfigError::Env {
                var: var.into(),
                message: format!("{v:?} is not a number"),
            })
        }
        if let Some(v) = get("PATCHWORK_STORAGE_BACKEND") {
            self.storage.backend = v.parse().map_err(|message| ConfigError::Env {
                var: "PATCHWORK_STORAGE_BACKEND".into(),
                message,
            })?;
        }
        for (var, field) in [
            ("PATCHWORK_S3_ENDPOINT", &mut self.storage.s3.endpoint),
            ("PATCHWORK_S3_BUCKET", &mut self.storage.s3.bucket),
            ("PATCHWORK_S3_PREFIX", &mut self.storage.s3.prefix),
        ] {
            if let Some(v) = get(var) {
                *field = v;
            }
        }
        if let Some(v) = get("PATCHWORK_FOLLOW").filter(|v| !v.is_empty()) {
            self.storage.set_follow(&v)?;
        }
        if let Some(v) = get("PATCHWORK_STORAGE_POLL_MS") {
            self.storage.poll_ms = num("PATCHWORK_STORAGE_POLL_MS", &v)?;
        }
        if let Some(v) = get("PATCHWORK_STORAGE_SNAPSHOT_EVERY") {
            self.storage.snapshot_every = num("PATCHWORK_STORAGE_SNAPSHOT_EVERY", &v)?;
        }
        if let Some(v) = get("PATCHWORK_STORAGE_FOLDER") {
            self.storage.folder = Some(v.into());
        }
        if let Some(v) = get("PATCHWORK_S3_ALLOW_HTTP") {
            self.storage.s3.allow_http = matches!(v.trim(), "1" | "true" | "yes");
        }
        if let Some(v) = get("PATCHWORK_DATA_DIR") {
            self.data_dir = v.into();
        }
        if let Some(v) = get("PATCHWORK_INBOX") {
            self.inbox = v
                .split(':')
                .filter(|s| !s.is_empty())
                .map(PathBuf::from)
                .collect();
        }
        if let Some(v) = get("PATCHWORK_INGEST_ROOTS") {
            self.ingest_roots = v
                .split(':')
                .filter(|s| !s.is_empty())
                .map(PathBuf::from)
                .collect();
        }
        if let Some(v) = get("PATCHWORK_LISTEN") {
            self.listen = v;
        }
        if let Some(v) = get("PATCHWORK_HTTP_LISTEN") {
            self.http_listen = v;
        }
        if let Some(v) = get("PATCHWORK_PUBLIC_URL") {
            self.http.public_url = (!v.is_empty()).then_some(v);
        }
        if let Some(v) = get("PATCHWORK_HTTP_ASSETS") {
            self.http.assets_dir = (!v.is_empty()).then(|| v.into());
        }
        // An empty value unsets a token, so that a config file's can be switched off.
        if let Some(v) = get("PATCHWORK_ADMIN_TOKEN") {
            self.admin_token = (!v.is_empty()).then_some(Secret(v));
        }
        if let Some(v) = get("PATCHWORK_READ_TOKEN") {
            self.read_token = (!v.is_empty()).then_some(Secret(v));
        }
        if let Some(v) = get("PATCHWORK_TLS_CERT") {
            self.tls_cert = Some(v.into());
        }
        if let Some(v) = get("PATCHWORK_TLS_KEY") {
            self.tls_key = Some(v.into());
        }
        if let Some(v) = get("PATCHWORK_ACCURACY_M") {
            self.accuracy_m = v.parse().map_err(|message| ConfigError::Env {
                var: "PATCHWORK_ACCURACY_M".into(),
                message,
            })?;
        }
        if let Some(v) = get("PATCHWORK_CRS") {
            self.crs = Some(v);
        }
        if let Some(v) = get("PATCHWORK_VERTICAL_CRS") {
            self.vertical.crs = Some(v);
        }
        if let Some(v) = get("PATCHWORK_SETTLE_MS") {
            self.settle_ms = num("PATCHWORK_SETTLE_MS", &v)?;
        }
        if let Some(v) = get("PATCHWORK_CACHE_MB") {
            self.cache_mb = num("PATCHWORK_CACHE_MB", &v)?;
        }
        if let Some(v) = get("PATCHWORK_ON_DELETE") {
            self.on_delete = match v.trim() {
                "retire" => OnDelete::Retire,
                "keep" => OnDelete::Keep,
                other => {
                    return Err(ConfigError::Env {
                        var: "PATCHWORK_ON_DELETE".into(),
                        message: format!("{other:?} is neither \"retire\" nor \"keep\""),
                    })
                }
            };
        }
        if let Some(v) = get("PATCHWORK_LOG") {
            self.log = v;
        }
        if let Some(v) = get("PATCHWORK_CONTRADICTED") {
            self.accuracy.contradicted =
                Contradicted::from_name(&v).ok_or_else(|| ConfigError::Env {
                    var: "PATCHWORK_CONTRADICTED".into(),
                    message: format!("{v:?} is not a policy: use distrust or keep"),
                })?;
        }
        if let Some(v) = get("PATCHWORK_MIPMAP") {
            self.mipmap = Filter::from_name(&v).ok_or_else(|| ConfigError::Env {
                var: "PATCHWORK_MIPMAP".into(),
                message: format!("{v:?} is not a filter: use minimax, smooth or decimate"),
            })?;
        }
        if let Some(v) = get("PATCHWORK_PATCHES") {
            self.patches.kind = PatchKind::from_name(&v).ok_or_else(|| ConfigError::Env {
                var: "PATCHWORK_PATCHES".into(),
                message: format!("{v:?} is not a patch kind: use bilinear or bicubic"),
            })?;
        }
        if let Some(v) = get("PATCHWORK_ALLOW_EMULATED_GPU") {
            self.allow_emulated_gpu = match v.as_str() {
                "1" | "true" => true,
                "0" | "false" => false,
                other => {
                    return Err(ConfigError::Env {
                        var: "PATCHWORK_ALLOW_EMULATED_GPU".into(),
                        message: format!("{other:?} is neither true nor false (or 1 and 0)"),
                    })
                }
            };
        }
        Ok(())
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        if let DefaultAccuracy::Metres(m) = self.accuracy_m {
            if !(m.is_finite() && m >= 0.0 && m < self.index.max_error) {
                return Err(ConfigError::Invalid(format!(
                    "accuracy_m must be \"auto\" or a number of metres in [0, index.max_error = {}), got {m}",
                    self.index.max_error
                )));
            }
        }
        if let Some(c) = &self.crs {
            Crs::parse(c).map_err(|e| ConfigError::Invalid(format!("crs: {e}")))?;
        }
        if let Some(v) = &self.vertical.crs {
            VerticalCrs::parse(v)
                .map_err(|e| ConfigError::Invalid(format!("vertical.crs: {e}")))?;
        }
        for k in self.vertical.geoids.keys() {
            let v = VerticalCrs::parse(k)
                .map_err(|e| ConfigError::Invalid(format!("vertical.geoids: {e}")))?;
            if v.is_ellipsoidal() {
                return Err(ConfigError::Invalid(
                    "vertical.geoids: ellipsoidal heights need no geoid grid".into(),
                ));
            }
        }
        if self.patches.kernel < 2 || self.patches.margin < 1 {
            return Err(ConfigError::Invalid(
                "patches.kernel must be ≥ 2 cells and patches.margin ≥ 1".into(),
            ));
        }
        let l = &self.limits;
        let ordered = l.min_height_m < l.max_height_m;
        let counts = [
            l.max_ingest_mb,
            l.max_failures,
            l.max_ingest_paths,
            l.max_running_requests,
            l.ingest_parallel,
            l.max_streams,
            l.max_streams_per_connection,
            l.max_connections,
            l.header_timeout_ms,
            l.idle_timeout_ms,
            l.max_web_tile_patches,
        ];
        if !ordered || counts.contains(&0) {
            return Err(ConfigError::Invalid(
                "limits.min_height_m must be below limits.max_height_m, and \
                 limits.max_ingest_mb, max_failures, max_ingest_paths, max_running_requests, \
                 ingest_parallel, max_streams, max_streams_per_connection, max_connections, \
                 header_timeout_ms, idle_timeout_ms and max_web_tile_patches at least 1"
                    .into(),
            ));
        }
        if let Some(u) = &self.http.public_url {
            let ok = (u.starts_with("http://") || u.starts_with("https://"))
                && !u.contains(['?', '#', ' ']);
            if !ok {
                return Err(ConfigError::Invalid(format!(
                    "http.public_url must be an http:// or https:// URL without a query, got \
                     {u:?}"
                )));
            }
        }
        if self.read_token.is_some() && self.admin_token.is_none() {
            return Err(ConfigError::Invalid(
                "read_token needs admin_token too: with reads closed and no admin token, \
                 Admin calls would be open to all"
                    .into(),
            ));
        }
        for (name, t) in [
            ("admin_token", &self.admin_token),
            ("read_token", &self.read_token),
        ] {
            if t.as_ref().is_some_and(|t| !valid_token(t.expose())) {
                return Err(ConfigError::Invalid(format!(
                    "{name} must be 16 to 1024 printable ASCII characters without spaces"
                )));
            }
        }
        match self.storage.backend {
            BackendKind::S3 if self.storage.s3.bucket.is_empty() => {
                return Err(ConfigError::Invalid(
                    "storage.backend = \"s3\" needs storage.s3.bucket".into(),
                ))
            }
            BackendKind::Folder if self.storage.folder.is_none() => {
                return Err(ConfigError::Invalid(
                    "storage.backend = \"folder\" needs storage.folder".into(),
                ))
            }
            _ => {}
        }
        if self.storage.timeout_ms == 0
            || self.storage.lease_s == 0
            || self.storage.poll_ms == 0
            || self.storage.snapshot_every == 0
        {
            return Err(ConfigError::Invalid(
                "storage.timeout_ms, lease_s, poll_ms and snapshot_every must be at least 1".into(),
            ));
        }
        if self.tls_cert.is_some() != self.tls_key.is_some() {
            return Err(ConfigError::Invalid(
                "TLS needs both tls_cert and tls_key (PEM files)".into(),
            ));
        }
        if self.index.max_error.is_nan()
            || self.index.max_error <= 0.0
            || self.index.node_capacity == 0
        {
            return Err(ConfigError::Invalid(
                "index.max_error must be > 0 and index.node_capacity ≥ 1".into(),
            ));
        }
        Ok(())
    }

    /// The store's horizontal CRS, as the config sets it.
    pub fn crs_def(&self) -> Option<Crs> {
        self.crs.as_deref().and_then(|c| Crs::parse(c).ok())
    }

    /// The store's vertical CRS, as the config sets it.
    pub fn vertical_crs(&self) -> Option<VerticalCrs> {
        self.vertical
            .crs
            .as_deref()
            .and_then(|c| VerticalCrs::parse(c).ok())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_commented_config_file_equals_the_compiled_defaults() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/patchwork.toml");
        let text = std::fs::read_to_string(path).unwrap();
        let parsed: Config = toml::from_str(&text).unwrap();
        assert_eq!(parsed, Config::default());
    }

    #[test]
    fn a_read_token_alone_is_refused() {
        let mut c = Config {
            read_token: Some(Secret("read-0123456789abcdef".into())),
            ..Config::default()
        };
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("admin_token"), "{e}");
        c.admin_token = Some(Secret("short".into()));
        assert!(c.validate().is_err(), "a short token is refused");
        c.admin_token = Some(Secret("admin-0123456789abcdef".into()));
        assert!(c.validate().is_ok());
    }

    #[test]
    fn environment_overrides_top_level_keys() {
        let mut c = Config::default();
        let env = |k: &str| match k {
            "PATCHWORK_INBOX" => Some("/a:/b".to_string()),
            "PATCHWORK_LISTEN" => Some("127.0.0.1:1".to_string()),
            "PATCHWORK_ON_DELETE" => Some("keep".to_string()),
            "PATCHWORK_ALLOW_EMULATED_GPU" => Some("1".to_string()),
            _ => None,
        };
        assert!(
            !c.allow_emulated_gpu,
            "a software GPU is refused by default"
        );
        c.apply_env(env).unwrap();
        assert!(c.allow_emulated_gpu);
        let emulated = |k: &str| (k == "PATCHWORK_ALLOW_EMULATED_GPU").then(|| "maybe".to_string());
        assert!(c.apply_env(emulated).is_err());
        assert_eq!(c.inbox, vec![PathBuf::from("/a"), PathBuf::from("/b")]);
        let acc =
            |v: &'static str| move |k: &str| (k == "PATCHWORK_ACCURACY_M").then(|| v.to_string());
        c.apply_env(acc("2.5")).unwrap();
        assert_eq!(c.accuracy_m, DefaultAccuracy::Metres(2.5));
        c.apply_env(acc("AUTO")).unwrap();
        assert_eq!(c.accuracy_m, DefaultAccuracy::Auto);
        assert!(c.apply_env(acc("fine")).is_err());
        assert_eq!(c.listen, "127.0.0.1:1");
        assert_eq!(c.on_delete, OnDelete::Keep);
        let bad = |k: &str| (k == "PATCHWORK_SETTLE_MS").then(|| "soon".to_string());
        assert!(c
            .apply_env(bad)
            .unwrap_err()
            .to_string()
            .contains("PATCHWORK_SETTLE_MS"));
    }

    #[test]
    fn the_storage_backend_comes_from_the_environment_and_needs_its_place() {
        let mut c = Config::default();
        let s3 = |k: &str| match k {
            "PATCHWORK_STORAGE_BACKEND" => Some("s3".to_string()),
            "PATCHWORK_S3_ENDPOINT" => Some("http://127.0.0.1:9000".to_string()),
            "PATCHWORK_S3_PREFIX" => Some("store1".to_string()),
            "PATCHWORK_S3_ALLOW_HTTP" => Some("true".to_string()),
            _ => None,
        };
        c.apply_env(s3).unwrap();
        assert_eq!(c.storage.backend, BackendKind::S3);
        assert!(c.storage.s3.allow_http);
        // No bucket: refused, saying what is missing.
        assert!(c.validate().unwrap_err().to_string().contains("s3.bucket"));
        c.apply_env(|k| (k == "PATCHWORK_S3_BUCKET").then(|| "terrain".to_string()))
            .unwrap();
        assert!(c.validate().is_ok());
        let odd = |k: &str| (k == "PATCHWORK_STORAGE_BACKEND").then(|| "tape".to_string());
        assert!(c.apply_env(odd).unwrap_err().to_string().contains("tape"));
    }
}
