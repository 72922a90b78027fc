//! The engine's one error type, by what the caller should do about it, and the [`Reason`]
//! each error and each failed file is given on the wire. The server maps each kind to a
//! status code in one place (`serve::status`).

use crate::ingest::IngestError;
use crate::paths::quote_short;
use crate::request::BadRequest;
use patchwork_core::crs::CrsError;
use patchwork_core::model::survey::SurveyError;
use patchwork_read::ReadError;
use patchwork_store::StoreError;
use std::path::PathBuf;
use thiserror::Error;

/// Everything that can go wrong in a request, one variant a kind of failure with what it
/// needs to say, grouped by what the caller should do about it ([`EngineError::reason`]). The
/// server maps each [`Reason`] to a status code in one place.
#[non_exhaustive]
#[derive(Debug, Error)]
pub enum EngineError {
    /// The request is malformed: refused before any work (see [`crate::request`]).
    #[error(transparent)]
    Request(#[from] BadRequest),
    /// The request asks for more than a limit allows: ask for less.
    #[error(transparent)]
    TooLarge(#[from] TooLarge),
    /// The request's CRS has no map to the store's.
    #[error("crs: {0}")]
    Reprojection(CrsError),
    /// Part of a region of another CRS lies where the map to the store's does not reach.
    #[error("part of the region lies where {from} cannot be carried into the store's {to}")]
    Unreachable {
        /// The request's CRS.
        from: String,
        /// The store's.
        to: String,
    },
    /// The settings disagree with the store they open.
    #[error("the config says {key} = {config} but the store at {} is in {store}", dir.display())]
    ConfigMismatch {
        /// The setting: `crs` or `vertical.crs`.
        key: &'static str,
        /// What the setting says.
        config: String,
        /// What the store is in.
        store: String,
        /// Where the store is.
        dir: PathBuf,
    },
    /// The object store `[storage]` names cannot be reached as configured.
    #[error("storage: {what}: {source}")]
    Storage {
        /// Which part: `s3`, `folder`, …
        what: String,
        /// Why.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A geoid grid the config names cannot be read or used; found at start.
    #[error("{0}")]
    GeoidGrid(IngestError),
    /// No active survey has this id or source.
    #[error("no active survey has id or source {}; `patchwork surveys` lists them", quote_short(.0))]
    NoSurvey(String),
    /// No failure is recorded for this source.
    #[error("no failure is recorded for {}; `patchwork surveys` lists them", quote_short(.0))]
    NoFailure(String),
    /// The store has no CRS yet, so a request in another CRS cannot be placed in it.
    #[error(
        "the store has no CRS yet (no survey and none in the config): ask in its own \
         coordinates once it has one"
    )]
    NoCrs,
    /// The GPU backend was asked for and this daemon has none.
    #[error("backend gpu was asked for, but this daemon has no GPU device; use auto or cpu")]
    NoGpu,
    /// The GPU failed under the request.
    #[error("GPU resampling failed: {0}")]
    Gpu(String),
    /// The store could not be reopened after a compaction: nothing can be written.
    #[error(
        "the store is not open: it could not be reopened after compaction; restart the daemon"
    )]
    NotOpen,
    /// The store failed under a write and takes no more until the daemon restarts.
    #[error(
        "the store failed on a disk error and takes no writes until the daemon restarts \
         (reads go on): {0}"
    )]
    StoreFailed(String),
    /// The store failed under a read or a write; its error says how (see [`Reason`]).
    #[error(transparent)]
    Store(#[from] StoreError),
    /// An answer could not be encoded (a GeoTIFF tile, say): a bug, not the request's.
    #[error("the answer cannot be encoded: {0}")]
    Encode(String),
    /// The caller gave up (its deadline passed) and the work stopped.
    #[error("the request was cancelled: its deadline passed")]
    Cancelled,
    /// The heights cannot be given from the vertical CRS asked.
    #[error(transparent)]
    Heights(#[from] HeightsError),
    /// A replica of one region was asked beyond it (or for a view-dependent cut, which has
    /// no bounds): ask the replica of the region, or one of the whole store.
    #[error(
        "this replica holds the region {} of the store's plane, and the request reaches {}: \
         ask the replica of that region, or one of the whole store",
        bounds(.region),
        .asked.as_ref().map_or("beyond any bounds (a view-dependent cut)".into(), bounds)
    )]
    OutsideRegion {
        /// The request's bounds in the store's plane; `None` for a view-dependent cut.
        asked: Option<patchwork_core::geom::Aabb>,
        /// The replica's region.
        region: patchwork_core::geom::Aabb,
    },
}

// These variants' messages name the inner error already, so it is not also their source: a
// reporter that walks the chain would print it twice.
impl From<CrsError> for EngineError {
    fn from(e: CrsError) -> Self {
        EngineError::Reprojection(e)
    }
}

fn bounds(b: &patchwork_core::geom::Aabb) -> String {
    format!("{},{},{},{}", b.min[0], b.min[1], b.max[0], b.max[1])
}

/// Why the store's heights cannot be carried into the frame a request asked for.
#[non_exhaustive]
#[derive(Debug, Error)]
pub enum HeightsError {
    /// Nothing says what the store's heights are measured from.
    #[error(
        "the store's heights name no vertical CRS (no survey and no vertical.crs say what \
         they are measured from), so they cannot be given as {asked}: ask for heights=store, \
         or set vertical.crs"
    )]
    Unknown {
        /// The frame asked for.
        asked: String,
    },
    /// A geoid grid the conversion needs is neither configured nor installed.
    #[error(
        "heights as {asked} from a store whose heights are {store} need a geoid grid for \
         {missing}: name one in the config, [vertical.geoids] \"{key}\" = \"<grid>\"{}",
        if .files.is_empty() { String::new() } else {
            format!(", or install PROJ's {} (Debian's proj-data)", .files)
        }
    )]
    NoGrid {
        /// The frame asked for.
        asked: String,
        /// The store's vertical CRS.
        store: String,
        /// The vertical CRS whose grid is missing.
        missing: String,
        /// The `[vertical.geoids]` key that would name it.
        key: String,
        /// The files of PROJ's directories that would be taken for it, if any.
        files: String,
    },
    /// A grid the conversion needs cannot be read or used.
    #[error("{0}")]
    Grid(IngestError),
    /// A height lies where a grid has no undulation.
    #[error(transparent)]
    Convert(#[from] patchwork_core::model::geoid::GeoidError),
}

/// A request over a limit of `[limits]`, with the figures.
#[non_exhaustive]
#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum TooLarge {
    /// A cut with more patches than `limits.max_patches`.
    #[error(
        "the query needs {n} patches, more than the limit of {max}: ask for a smaller region or \
         a larger error"
    )]
    Patches {
        /// Patches the cut holds.
        n: u64,
        /// The limit.
        max: u64,
    },
    /// A tile with more samples than `limits.max_tile_samples`.
    #[error(
        "a {width}×{height} tile has {n} samples, more than the limit of {max}: ask for a \
         smaller tile"
    )]
    TileSamples {
        /// Samples a row.
        width: u32,
        /// Rows.
        height: u32,
        /// Samples in all.
        n: u64,
        /// The limit.
        max: u64,
    },
    /// More points than `limits.max_points`.
    #[error("{n} points, more than the limit of {max}: send them in smaller requests")]
    Points {
        /// Points asked for.
        n: u64,
        /// The limit.
        max: u64,
    },
    /// More paths in one ingest request than `limits.max_ingest_paths`.
    #[error(
        "{n} paths in one request, more than the limit of {max} (limits.max_ingest_paths): \
         send them in smaller requests"
    )]
    IngestPaths {
        /// Paths asked for.
        n: u64,
        /// The limit.
        max: u64,
    },
}

/// Why a request or a file failed, as clients branch on it: carried in a gRPC status's
/// `google.rpc.ErrorInfo` (domain `patchwork`), in `IngestResult.reason`, and in the `reason`
/// of an HTTP error's body, spelled as [`Reason::as_str`] gives it (the proto's
/// `ErrorReason` without its prefix). New kinds may come; a client treats one it does not
/// know by the status code.
#[non_exhaustive]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Reason {
    /// The request is malformed or out of range.
    InvalidRequest,
    /// The request asks for more than the limits allow.
    TooLarge,
    /// What the request names does not exist.
    NotFound,
    /// The request cannot be served in this state (no GPU, no CRS yet).
    Unavailable,
    /// The request ran past its deadline, or its caller gave up.
    Deadline,
    /// The call carries no token this service takes: none, or a wrong one.
    Unauthenticated,
    /// The token is valid but does not open this call: the read token on an Admin call.
    PermissionDenied,
    /// The store failed on a disk error and takes no writes until a restart.
    StoreFailed,
    /// The disk is too full for the write.
    DiskFull,
    /// Another process holds the store.
    StoreLocked,
    /// A replica takes no writes: the message names the writer.
    ReadOnlyReplica,
    /// The disk or the object store failed under a read or a write; a retry may succeed.
    StorageUnavailable,
    /// Stored samples are gone or damaged.
    DataLoss,
    /// The store is corrupt, newer than this binary, or failed to migrate.
    StoreCorrupt,
    /// The daemon failed in a way no request could cause: a bug, or the store refusing its own
    /// writer.
    Internal,
    /// A file outside the folders the daemon ingests from.
    OutsideIngestFolders,
    /// A file that cannot be read, or is not a regular file.
    Unreadable,
    /// A file that is not a DEM this daemon reads, or a damaged one.
    NotADem,
    /// A file too large for the configured limits.
    FileTooLarge,
    /// A sidecar that cannot be read or says something wrong.
    Sidecar,
    /// A file without a CRS, or with one that cannot be used or placed in the store's.
    Crs,
    /// The file and its sidecar name different CRSs, horizontal or vertical.
    CrsConflict,
    /// Converting the heights needs a geoid grid the daemon does not have, or cannot read.
    Geoid,
    /// An accuracy outside [0, the top of LOD space).
    BadAccuracy,
    /// Heights outside the plausible range: not metres, or an undeclared nodata value.
    Implausible,
    /// A georeference or grid a survey cannot be made of.
    BadGrid,
    /// A replica of one region was asked beyond it.
    OutsideRegion,
}

impl Reason {
    /// The kind as it travels: `DISK_FULL`, `CRS_CONFLICT`, …
    pub fn as_str(self) -> &'static str {
        match self {
            Reason::InvalidRequest => "INVALID_REQUEST",
            Reason::TooLarge => "TOO_LARGE",
            Reason::NotFound => "NOT_FOUND",
            Reason::Unavailable => "UNAVAILABLE",
            Reason::Deadline => "DEADLINE",
            Reason::Unauthenticated => "UNAUTHENTICATED",
            Reason::PermissionDenied => "PERMISSION_DENIED",
            Reason::StoreFailed => "STORE_FAILED",
            Reason::DiskFull => "DISK_FULL",
            Reason::StoreLocked => "STORE_LOCKED",
            Reason::ReadOnlyReplica => "READ_ONLY_REPLICA",
            Reason::StorageUnavailable => "STORAGE_UNAVAILABLE",
            Reason::DataLoss => "DATA_LOSS",
            Reason::StoreCorrupt => "STORE_CORRUPT",
            Reason::Internal => "INTERNAL",
            Reason::OutsideIngestFolders => "OUTSIDE_INGEST_FOLDERS",
            Reason::Unreadable => "UNREADABLE",
            Reason::NotADem => "NOT_A_DEM",
            Reason::FileTooLarge => "FILE_TOO_LARGE",
            Reason::Sidecar => "SIDECAR",
            Reason::Crs => "CRS",
            Reason::CrsConflict => "CRS_CONFLICT",
            Reason::Geoid => "GEOID",
            Reason::BadAccuracy => "BAD_ACCURACY",
            Reason::Implausible => "IMPLAUSIBLE",
            Reason::BadGrid => "BAD_GRID",
            Reason::OutsideRegion => "OUTSIDE_REGION",
        }
    }

    /// Every kind, for the wire's tables and their tests.
    pub const ALL: [Reason; 27] = [
        Reason::InvalidRequest,
        Reason::TooLarge,
        Reason::NotFound,
        Reason::Unavailable,
        Reason::Deadline,
        Reason::Unauthenticated,
        Reason::PermissionDenied,
        Reason::StoreFailed,
        Reason::DiskFull,
        Reason::StoreLocked,
        Reason::ReadOnlyReplica,
        Reason::StorageUnavailable,
        Reason::DataLoss,
        Reason::StoreCorrupt,
        Reason::Internal,
        Reason::OutsideIngestFolders,
        Reason::Unreadable,
        Reason::NotADem,
        Reason::FileTooLarge,
        Reason::Sidecar,
        Reason::Crs,
        Reason::CrsConflict,
        Reason::Geoid,
        Reason::BadAccuracy,
        Reason::Implausible,
        Reason::BadGrid,
        Reason::OutsideRegion,
    ];

    /// The kind [`Reason::as_str`] spells `s`.
    pub fn parse(s: &str) -> Option<Reason> {
        Reason::ALL.into_iter().find(|r| r.as_str() == s)
    }
}

impl From<patchwork_core::model::geoid::GeoidError> for EngineError {
    fn from(e: patchwork_core::model::geoid::GeoidError) -> Self {
        EngineError::Heights(HeightsError::Convert(e))
    }
}

impl EngineError {
    /// What kind of failure this is, for clients to branch on.
    pub fn reason(&self) -> Reason {
        match self {
            EngineError::Request(_)
            | EngineError::Reprojection(_)
            | EngineError::Unreachable { .. }
            | EngineError::ConfigMismatch { .. }
            | EngineError::Storage { .. } => Reason::InvalidRequest,
            EngineError::TooLarge(_) => Reason::TooLarge,
            EngineError::NoSurvey(_) | EngineError::NoFailure(_) => Reason::NotFound,
            EngineError::NoCrs
            | EngineError::NoGpu
            | EngineError::Gpu(_)
            | EngineError::NotOpen => Reason::Unavailable,
            EngineError::StoreFailed(_) => Reason::StoreFailed,
            EngineError::Encode(_) => Reason::Internal,
            EngineError::GeoidGrid(_) | EngineError::Heights(_) => Reason::Geoid,
            EngineError::Cancelled => Reason::Deadline,
            EngineError::Store(e) => store_reason(e),
            EngineError::OutsideRegion { .. } => Reason::OutsideRegion,
        }
    }
}

fn store_reason(e: &StoreError) -> Reason {
    match e {
        StoreError::Full { .. } => Reason::DiskFull,
        StoreError::Locked { .. } => Reason::StoreLocked,
        StoreError::Replica { .. } => Reason::ReadOnlyReplica,
        StoreError::Sled(sled::Error::Io(io)) if io.kind() == std::io::ErrorKind::StorageFull => {
            Reason::DiskFull
        }
        StoreError::Sled(sled::Error::Io(_)) | StoreError::Io(_) => Reason::StorageUnavailable,
        StoreError::Samples(e) if e.unavailable => Reason::StorageUnavailable,
        StoreError::Samples(_) => Reason::DataLoss,
        StoreError::Corrupt(_) | StoreError::Newer { .. } | StoreError::Migration { .. } => {
            Reason::StoreCorrupt
        }
        // The store refusing what its writer or its settings asked: the daemon's fault, not
        // the request's.
        _ => Reason::Internal,
    }
}

/// What kind of failure a file's is.
pub fn ingest_reason(e: &IngestError) -> Reason {
    match e {
        IngestError::Read(r) => match r {
            ReadError::Truncated | ReadError::Unsupported { .. } | ReadError::Invalid { .. } => {
                Reason::NotADem
            }
            ReadError::TooLarge { .. } => Reason::FileTooLarge,
            ReadError::Outside => Reason::OutsideIngestFolders,
            ReadError::Io(_) => Reason::Unreadable,
        },
        IngestError::Sidecar { .. } => Reason::Sidecar,
        IngestError::NoCrs { .. } | IngestError::UnknownCrs { .. } => Reason::Crs,
        IngestError::CrsConflict { .. } | IngestError::VerticalConflict { .. } => {
            Reason::CrsConflict
        }
        IngestError::NoGeoid { .. } | IngestError::Geoid { .. } | IngestError::Convert(_) => {
            Reason::Geoid
        }
        IngestError::BadAccuracy { .. } | IngestError::Survey(SurveyError::BadAccuracy(_)) => {
            Reason::BadAccuracy
        }
        IngestError::Survey(SurveyError::AllNodata) | IngestError::Implausible { .. } => {
            Reason::Implausible
        }
        IngestError::Survey(_) | IngestError::Grid(_) => Reason::BadGrid,
        IngestError::Refused => Reason::OutsideIngestFolders,
        IngestError::Directory { .. }
        | IngestError::NotAFile { .. }
        | IngestError::Unreadable { .. } => Reason::Unreadable,
    }
}
