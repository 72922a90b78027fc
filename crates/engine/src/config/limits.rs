//! The `[limits]` section: what one request, one file and one connection may take.

use serde::{Deserialize, Serialize};

/// The `[limits]` section: bounds on what one request, one file and one connection may take.
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
    /// Top of the plausible heights, in metres; see `min_height_m`.
    pub max_height_m: f64,
    /// Most paths in one Ingest request.
    pub max_ingest_paths: u64,
    /// Most failed files remembered; the oldest records go first.
    pub max_failures: u64,
    /// Most streams that stay open (view sessions and subscriptions) at once, and on one
    /// connection; more are refused with RESOURCE_EXHAUSTED.
    pub max_streams: u64,
    /// Most of those streams open on one connection.
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
