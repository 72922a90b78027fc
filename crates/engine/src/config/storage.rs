//! The `[storage]` section: the disk, and where the chunk bytes go.

use super::ConfigError;
use patchwork_core::geom::Aabb;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

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
    /// Object-store backends: the writer publishes a snapshot of its database for replicas at
    /// most every this many commits, once the commits' logs since the last add up to a
    /// quarter of its size (each commit's log goes up anyway).
    pub snapshot_every: u64,
    /// Serve as a read replica of the store at this URL (`s3://bucket/prefix`, or
    /// `file:///folder`) instead of as its writer; empty: the writer. Set by `serve --follow`.
    pub follow: String,
    /// A replica: how often it asks for the writer's new commits, in ms. The writer, too,
    /// tries this often to publish a commit's log that could not go up at once.
    pub poll_ms: u64,
    /// A replica of one region, `[xmin, ymin, xmax, ymax]` in the store's CRS: it keeps only
    /// the surveys that answer there and refuses requests beyond it. Absent: the whole
    /// store. Set by `serve --region`.
    pub region: Option<[f64; 4]>,
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

    /// Makes this replica one of the region `XMIN,YMIN,XMAX,YMAX` (the store's CRS).
    pub fn set_region(&mut self, text: &str) -> Result<(), ConfigError> {
        let v: Vec<f64> = text
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| {
                ConfigError::Invalid(format!("--region {text}: expected XMIN,YMIN,XMAX,YMAX"))
            })?;
        let b: [f64; 4] = v
            .try_into()
            .map_err(|_| ConfigError::Invalid(format!("--region {text}: expected four numbers")))?;
        self.region = Some(b);
        Ok(())
    }

    /// The region of a replica of one, checked: finite, with area, and on a replica.
    pub fn region_box(&self) -> Result<Option<Aabb>, ConfigError> {
        let Some([x0, y0, x1, y1]) = self.region else {
            return Ok(None);
        };
        if ![x0, y0, x1, y1].iter().all(|v| v.is_finite()) || x0 >= x1 || y0 >= y1 {
            return Err(ConfigError::Invalid(format!(
                "storage.region {x0},{y0},{x1},{y1}: expected finite XMIN < XMAX and YMIN < YMAX"
            )));
        }
        if self.follow.is_empty() {
            return Err(ConfigError::Invalid(
                "storage.region is for a read replica (serve --follow URL --region ...): the \
                 writer holds the whole store"
                    .into(),
            ));
        }
        Ok(Some(Aabb::new(x0, y0, x1, y1)))
    }

    /// The URL of the object store the chunks go to, as the store records it and replicas
    /// follow it (`s3://bucket/prefix`, `file:///folder` with the folder's canonical path once
    /// it exists); `None` for the local pack.
    pub fn url(&self) -> Option<String> {
        let url = match self.backend {
            BackendKind::Local => return None,
            BackendKind::S3 => format!(
                "s3://{}/{}",
                self.s3.bucket,
                self.s3.prefix.trim_matches('/')
            ),
            BackendKind::Folder => {
                let dir = self.folder.as_ref()?;
                let dir = std::fs::canonicalize(dir)
                    .or_else(|_| std::path::absolute(dir))
                    .unwrap_or_else(|_| dir.clone());
                format!("file://{}", dir.display())
            }
        };
        Some(url.trim_end_matches('/').to_string())
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
            region: None,
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
    /// The bucket the segments go in.
    pub bucket: String,
    /// The folder inside the bucket that this store's objects go under.
    pub prefix: String,
    /// The bucket's region, as the S3 API names it.
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
