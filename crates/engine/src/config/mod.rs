//! Configuration: compiled-in defaults, then an optional TOML file, then environment overrides
//! for the top-level keys (`PATCHWORK_<KEY>`). `config/patchwork.toml` documents every key.

use patchwork_core::crs::vertical::VerticalCrs;
use patchwork_core::crs::Crs;
use patchwork_core::index::lod::IndexConfig;
use patchwork_core::model::evidence::Contradicted;
use patchwork_core::model::mipmap::Filter;
use patchwork_core::model::patch::{Blend, PatchKind};
use patchwork_core::model::survey::Recipe;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

mod explain;
mod http;
mod limits;
mod storage;
mod surveys;

pub use explain::{explain, Origin, Setting};
pub use http::{valid_token, Http, Secret};
pub use limits::Limits;
pub use storage::{BackendKind, Storage, S3};
pub use surveys::{Accuracy, DefaultAccuracy, OnDelete, Patches, Vertical};

/// The daemon's whole configuration, one field a key of `config/patchwork.toml`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// Where the store lives.
    pub data_dir: PathBuf,
    /// Folders watched for DEM files (GeoTIFF/COG, SRTM `.hgt`, ESRI ASCII `.asc`).
    pub inbox: Vec<PathBuf>,
    /// Folders besides the inbox that Ingest requests may name files in.
    pub ingest_roots: Vec<PathBuf>,
    /// The gRPC address; an address other than loopback needs `admin_token`.
    pub listen: String,
    /// Where the HTTP server for web map clients listens; empty serves no HTTP.
    pub http_listen: String,
    /// Bearer token for the Admin service (and for reads too).
    pub admin_token: Option<Secret>,
    /// Bearer token for the Terrain service; unset leaves reads open.
    pub read_token: Option<Secret>,
    /// PEM certificate chain and private key: both set serves TLS.
    pub tls_cert: Option<PathBuf>,
    /// See `tls_cert`.
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
    /// What a file deleted from the inbox does to its survey: retire it, or keep it.
    pub on_delete: OnDelete,
    /// Log filter, e.g. "info" or "patchwork=debug".
    pub log: String,
    /// Whether a software GPU adapter (llvmpipe, lavapipe, WARP) may resample when no real
    /// one is present; it is slower than the CPU path.
    pub allow_emulated_gpu: bool,
    /// The `[limits]` section.
    pub limits: Limits,
    /// The `[storage]` section.
    pub storage: Storage,
    /// The `[index]` section: the top of LOD space and the boxes per quadtree node.
    pub index: IndexConfig,
    /// The `[patches]` section.
    pub patches: Patches,
    /// How a new store makes its surveys' coarser levels; an existing store keeps its own.
    pub mipmap: Filter,
    /// The `[vertical]` section.
    pub vertical: Vertical,
    /// The `[accuracy]` section.
    pub accuracy: Accuracy,
    /// The `[http]` section.
    pub http: Http,
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

/// Why a config could not be loaded.
#[non_exhaustive]
#[derive(Debug, Error)]
pub enum ConfigError {
    /// The config file could not be read.
    #[error("cannot read config {path}: {source}")]
    Read {
        /// The file named.
        path: PathBuf,
        /// Why it could not be read.
        source: std::io::Error,
    },
    /// The config file is not valid TOML, or holds a key or value the config does not know.
    #[error("config {path}: {message}")]
    Parse {
        /// The file named.
        path: PathBuf,
        /// The parser's message, naming the key or line at fault.
        message: String,
    },
    /// An environment override holds a value its key cannot take.
    #[error("environment variable {var}: {message}")]
    Env {
        /// The variable, `PATCHWORK_<KEY>`.
        var: String,
        /// What is wrong with its value.
        message: String,
    },
    /// The config parsed but breaks a rule, such as a limit of 0 or a token too short.
    #[error("{0}")]
    Invalid(String),
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

/// A config file's text.
fn read_file(path: &Path) -> Result<String, ConfigError> {
    std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
        path: path.into(),
        source,
    })
}

/// A config file's text read as `T`: the config, or its bare table of keys.
fn parse_file<T: serde::de::DeserializeOwned>(path: &Path, text: &str) -> Result<T, ConfigError> {
    toml::from_str(text).map_err(|e| ConfigError::Parse {
        path: path.into(),
        message: e.to_string(),
    })
}

/// A boolean from the environment: `true`/`false`, `1`/`0`, `yes`/`no` or `on`/`off`, in any
/// case; anything else is refused, naming the variable, rather than read as false.
fn boolean(var: &str, v: &str) -> Result<bool, ConfigError> {
    match v.trim().to_ascii_lowercase().as_str() {
        "true" | "1" | "yes" | "on" => Ok(true),
        "false" | "0" | "no" | "off" => Ok(false),
        _ => Err(ConfigError::Env {
            var: var.into(),
            message: format!("{v:?} is not a boolean: use true or false (1 or 0)"),
        }),
    }
}

impl Config {
    /// Defaults, then `file` if given, then the environment.
    pub fn load(file: Option<&Path>) -> Result<Config, ConfigError> {
        let mut cfg = match file {
            Some(path) => parse_file(path, &read_file(path)?)?,
            None => Config::default(),
        };
        cfg.finish_load(|k| std::env::var(k).ok())?;
        Ok(cfg)
    }

    /// What a load does after the file: the follower's URL taken apart, the environment's
    /// overrides, and the rules checked.
    fn finish_load(&mut self, get: impl Fn(&str) -> Option<String>) -> Result<(), ConfigError> {
        if !self.storage.follow.is_empty() {
            let url = self.storage.follow.clone();
            self.storage.set_follow(&url)?;
        }
        self.apply_env(get)?;
        self.validate()
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
        if let Some(v) = get("PATCHWORK_REGION").filter(|v| !v.is_empty()) {
            self.storage.set_region(&v)?;
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
            self.storage.s3.allow_http = boolean("PATCHWORK_S3_ALLOW_HTTP", &v)?;
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
        if let Some(v) = get("PATCHWORK_BLEND") {
            self.patches.blend = Blend::from_name(&v).ok_or_else(|| ConfigError::Env {
                var: "PATCHWORK_BLEND".into(),
                message: format!("{v:?} is not a blend: use formula1 or accurate"),
            })?;
        }
        if let Some(v) = get("PATCHWORK_ALLOW_EMULATED_GPU") {
            self.allow_emulated_gpu = boolean("PATCHWORK_ALLOW_EMULATED_GPU", &v)?;
        }
        Ok(())
    }

    /// Checks the rules no single key can: ranges, limits of at least 1, what needs what else (a
    /// read token an admin token, an S3 backend a bucket), and that the CRSs parse.
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
        self.storage.region_box()?;
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
        // Each by its name, so that the message says which one is wrong.
        let counts = [
            ("max_ingest_mb", l.max_ingest_mb),
            ("max_failures", l.max_failures),
            ("max_ingest_paths", l.max_ingest_paths),
            ("max_running_requests", l.max_running_requests),
            ("ingest_parallel", l.ingest_parallel),
            ("max_streams", l.max_streams),
            ("max_streams_per_connection", l.max_streams_per_connection),
            ("max_connections", l.max_connections),
            ("header_timeout_ms", l.header_timeout_ms),
            ("idle_timeout_ms", l.idle_timeout_ms),
            ("max_web_tile_patches", l.max_web_tile_patches),
        ];
        if !ordered {
            return Err(ConfigError::Invalid(format!(
                "limits.min_height_m ({}) must be below limits.max_height_m ({})",
                l.min_height_m, l.max_height_m
            )));
        }
        if let Some((name, _)) = counts.iter().find(|(_, v)| *v == 0) {
            return Err(ConfigError::Invalid(format!(
                "limits.{name} must be at least 1, got 0"
            )));
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
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/patchwork.toml");
        let text = std::fs::read_to_string(path).unwrap();
        let parsed: Config = toml::from_str(&text).unwrap();
        assert_eq!(parsed, Config::default());
    }

    #[test]
    fn a_boolean_from_the_environment_is_one_or_refused() {
        for (v, want) in [
            ("1", true),
            ("TRUE", true),
            ("yes", true),
            ("off", false),
            ("0", false),
        ] {
            let mut c = Config::default();
            c.apply_env(|k| (k == "PATCHWORK_S3_ALLOW_HTTP").then(|| v.to_string()))
                .unwrap();
            assert_eq!(c.storage.s3.allow_http, want, "{v}");
        }
        for var in ["PATCHWORK_S3_ALLOW_HTTP", "PATCHWORK_ALLOW_EMULATED_GPU"] {
            let e = Config::default()
                .apply_env(|k| (k == var).then(|| "maybe".to_string()))
                .unwrap_err()
                .to_string();
            assert!(e.contains(var) && e.contains("\"maybe\""), "{e}");
        }
    }

    #[test]
    fn a_limit_of_0_is_named_alone() {
        let mut c = Config::default();
        c.limits.max_streams = 0;
        let e = c.validate().unwrap_err().to_string();
        assert_eq!(e, "limits.max_streams must be at least 1, got 0");
        let mut c = Config::default();
        c.limits.min_height_m = 10.0;
        c.limits.max_height_m = 5.0;
        let e = c.validate().unwrap_err().to_string();
        assert!(
            e.contains("min_height_m (10)") && !e.contains("max_streams"),
            "{e}"
        );
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
