//! The effective configuration, key by key, with where each value came from: what
//! `patchwork config` prints, so that a setting that does not take is found at a glance.

use super::{parse_file, read_file, Config, ConfigError};
use std::path::Path;

/// Where a key's value came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Origin {
    /// The compiled-in default.
    Default,
    /// The config file.
    File,
    /// An environment variable, which overrides the file.
    Environment,
}

impl Origin {
    /// The word `patchwork config` prints.
    pub fn word(self) -> &'static str {
        match self {
            Origin::Default => "default",
            Origin::File => "file",
            Origin::Environment => "environment",
        }
    }
}

/// One key of the effective configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct Setting {
    /// Its dotted path: `listen`, `limits.max_streams`, `storage.s3.bucket`.
    pub key: String,
    /// Its value as TOML writes it; a token is shown only as set.
    pub value: String,
    /// Where it came from.
    pub origin: Origin,
}

/// Keys whose values are never printed.
const SECRET: [&str; 2] = ["admin_token", "read_token"];

/// The configuration `serve` would run with, from `file` and the environment that `get`
/// reads, key by key, each section's keys sorted by name (keys left unset are not listed).
/// Fails as `serve` would, naming what is wrong.
pub fn explain(
    file: Option<&Path>,
    get: impl Fn(&str) -> Option<String>,
) -> Result<Vec<Setting>, ConfigError> {
    let (from_file, written) = match file {
        Some(path) => {
            let text = read_file(path)?;
            (parse_file(path, &text)?, parse_file(path, &text)?)
        }
        None => (Config::default(), toml::Table::new()),
    };
    let mut effective = from_file.clone();
    effective.finish_load(get)?;
    let before = flatten(&from_file);
    let written = flat_table(&written);
    Ok(flatten(&effective)
        .into_iter()
        .map(|(key, value)| {
            let origin = if before.iter().find(|(k, _)| *k == key).map(|(_, v)| v) != Some(&value) {
                Origin::Environment
            } else if written.iter().any(|(k, _)| *k == key) {
                Origin::File
            } else {
                Origin::Default
            };
            let value = if SECRET.contains(&key.as_str()) {
                "(set)".to_string()
            } else {
                value.to_string()
            };
            Setting { key, value, origin }
        })
        .collect())
}

/// A config's keys and values, dotted: a section's keys sorted by name, as TOML's tables
/// keep them.
fn flatten(c: &Config) -> Vec<(String, toml::Value)> {
    let table = toml::Table::try_from(c).expect("a config serialises as TOML");
    flat_table(&table)
}

fn flat_table(t: &toml::Table) -> Vec<(String, toml::Value)> {
    let mut out = Vec::new();
    walk("", t, &mut out);
    out
}

fn walk(prefix: &str, t: &toml::Table, out: &mut Vec<(String, toml::Value)>) {
    for (k, v) in t {
        let key = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match v {
            // A table of the user's own keys (geoid grids by CRS) is one setting.
            toml::Value::Table(inner) if key != "vertical.geoids" => walk(&key, inner, out),
            v => out.push((key, v.clone())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_value_says_where_it_came_from_and_tokens_stay_hidden() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("p.toml");
        std::fs::write(
            &file,
            "settle_ms = 1500\ncache_mb = 64\n[limits]\nmax_streams = 10\n",
        )
        .unwrap();
        let env = |k: &str| match k {
            "PATCHWORK_LISTEN" => Some("127.0.0.1:1".to_string()),
            "PATCHWORK_CACHE_MB" => Some("32".to_string()),
            "PATCHWORK_ADMIN_TOKEN" => Some("admin-0123456789abcdef".to_string()),
            _ => None,
        };
        let s = explain(Some(&file), env).unwrap();
        let of = |k: &str| s.iter().find(|x| x.key == k).unwrap().clone();
        assert_eq!(of("listen").origin, Origin::Environment);
        assert_eq!(of("listen").value, "\"127.0.0.1:1\"");
        assert_eq!(
            of("cache_mb").origin,
            Origin::Environment,
            "the environment wins"
        );
        assert_eq!(of("cache_mb").value, "32");
        // Written in the file, even at its default.
        assert_eq!(of("settle_ms").origin, Origin::File);
        assert_eq!(of("limits.max_streams").origin, Origin::File);
        assert_eq!(of("limits.max_patches").origin, Origin::Default);
        assert_eq!(of("admin_token").value, "(set)");
        assert!(!format!("{s:?}").contains("0123456789abcdef"));
        // A bad value fails as serve would.
        let bad = explain(None, |k| {
            (k == "PATCHWORK_SETTLE_MS").then(|| "soon".to_string())
        });
        assert!(bad.unwrap_err().to_string().contains("PATCHWORK_SETTLE_MS"));
    }
}
