//! Configuration: compiled-in defaults, then an optional TOML file, then environment overrides
//! for the top-level keys (`PATCHWORK_<KEY>`). `config/patchwork.toml` documents every key.

use crate::index::lod::IndexConfig;
use crate::model::patch::PatchLayout;
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
    /// Largest raster accepted, in samples; larger headers are refused before reading.
    pub max_file_samples: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_tile_samples: 4096 * 4096,
            max_patches: 250_000,
            max_points: 1_000_000,
            deadline_ms: 30_000,
            max_file_samples: 1 << 31,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub data_dir: PathBuf,
    pub inbox: Vec<PathBuf>,
    pub listen: String,
    /// ε for files with no sidecar and no `--accuracy`, in metres.
    pub accuracy_m: f64,
    /// The store's CRS as "EPSG:n"; unset adopts the first survey's.
    pub crs: Option<String>,
    /// How long a file's size and mtime must stay unchanged before it is ingested.
    pub settle_ms: u64,
    pub on_delete: OnDelete,
    /// Log filter, e.g. "info" or "patchwork=debug".
    pub log: String,
    pub limits: Limits,
    pub index: IndexConfig,
    pub patches: PatchLayout,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            data_dir: PathBuf::from("./data"),
            inbox: vec![PathBuf::from("./inbox")],
            listen: "127.0.0.1:50051".into(),
            accuracy_m: 0.0,
            crs: None,
            settle_ms: 1500,
            on_delete: OnDelete::Retire,
            log: "info".into(),
            limits: Limits::default(),
            index: IndexConfig::default(),
            patches: PatchLayout::default(),
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
        if let Some(v) = get("PATCHWORK_LISTEN") {
            self.listen = v;
        }
        if let Some(v) = get("PATCHWORK_ACCURACY_M") {
            self.accuracy_m = num("PATCHWORK_ACCURACY_M", &v)?;
        }
        if let Some(v) = get("PATCHWORK_CRS") {
            self.crs = Some(v);
        }
        if let Some(v) = get("PATCHWORK_SETTLE_MS") {
            self.settle_ms = num("PATCHWORK_SETTLE_MS", &v)?;
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
        Ok(())
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(self.accuracy_m.is_finite() && self.accuracy_m >= 0.0) {
            return Err(ConfigError::Invalid(format!(
                "accuracy_m must be ≥ 0, got {}",
                self.accuracy_m
            )));
        }
        if let Some(c) = &self.crs {
            if parse_epsg(c).is_none() {
                return Err(ConfigError::Invalid(format!(
                    "crs must look like \"EPSG:4326\", got {c:?}"
                )));
            }
        }
        if self.patches.kernel < 2 || self.patches.margin < 1 {
            return Err(ConfigError::Invalid(
                "patches.kernel must be ≥ 2 cells and patches.margin ≥ 1".into(),
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

    pub fn crs_epsg(&self) -> Option<u32> {
        self.crs.as_deref().and_then(parse_epsg)
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
    fn environment_overrides_top_level_keys() {
        let mut c = Config::default();
        let env = |k: &str| match k {
            "PATCHWORK_INBOX" => Some("/a:/b".to_string()),
            "PATCHWORK_LISTEN" => Some("127.0.0.1:1".to_string()),
            "PATCHWORK_ON_DELETE" => Some("keep".to_string()),
            _ => None,
        };
        c.apply_env(env).unwrap();
        assert_eq!(c.inbox, vec![PathBuf::from("/a"), PathBuf::from("/b")]);
        assert_eq!(c.listen, "127.0.0.1:1");
        assert_eq!(c.on_delete, OnDelete::Keep);
        let bad = |k: &str| (k == "PATCHWORK_SETTLE_MS").then(|| "soon".to_string());
        assert!(c
            .apply_env(bad)
            .unwrap_err()
            .to_string()
            .contains("PATCHWORK_SETTLE_MS"));
    }
}
