//! The `[http]` section, and the tokens both servers check.

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

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
    /// The token itself, for comparing with what a client sent; never for logs.
    pub fn expose(&self) -> &str {
        &self.0
    }
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

/// Whether a token can travel in an HTTP header and is long enough not to be guessed.
pub fn valid_token(t: &str) -> bool {
    (16..=1024).contains(&t.len()) && t.bytes().all(|b| b.is_ascii_graphic())
}
