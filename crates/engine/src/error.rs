//! The engine's one error type, by what the caller should do about it, and the [`Reason`]
//! each error and each failed file is given on the wire. The server maps each kind to a
//! status code in one place (`serve::status`).

use crate::ingest::IngestError;
use crate::request::BadRequest;
use patchwork_core::model::survey::SurveyError;
use patchwork_read::ReadError;
use patchwork_store::StoreError;
use thiserror::Error;

/// Everything that can go wrong in a request, by what the caller should do about it. The
/// server maps these to status codes in one place.
#[derive(Debug, Error)]
pub enum EngineError {
    /// The request itself is wrong: fix the request.
    #[error("{0}")]
    Invalid(String),
    /// The request is too big: ask for less.
    #[error("{0}")]
    TooLarge(String),
    #[error("{0}")]
    NotFound(String),
    /// The request is fine but cannot be served in this state (no GPU, say).
    #[error("{0}")]
    Unavailable(String),
    /// The store failed under a write and takes no more until the daemon restarts.
    #[error(
        "the store failed on a disk error and takes no writes until the daemon restarts \
         (reads go on): {0}"
    )]
    StoreFailed(String),
    #[error("{0}")]
    Store(#[from] StoreError),
    /// The request is malformed: refused before any work (see [`crate::request`]).
    #[error(transparent)]
    Request(#[from] BadRequest),
    /// The caller gave up (its deadline passed) and the work stopped.
    #[error("the request was cancelled: its deadline passed")]
    Cancelled,
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
    NotFound,
    /// The request cannot be served in this state (no GPU, no CRS yet).
    Unavailable,
    /// The request ran past its deadline, or its caller gave up.
    Deadline,
    Unauthenticated,
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
        }
    }

    /// Every kind, for the wire's tables and their tests.
    pub const ALL: [Reason; 26] = [
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
    ];

    /// The kind [`Reason::as_str`] spells `s`.
    pub fn parse(s: &str) -> Option<Reason> {
        Reason::ALL.into_iter().find(|r| r.as_str() == s)
    }
}

impl EngineError {
    /// What kind of failure this is, for clients to branch on.
    pub fn reason(&self) -> Reason {
        match self {
            EngineError::Invalid(_) | EngineError::Request(_) => Reason::InvalidRequest,
            EngineError::TooLarge(_) => Reason::TooLarge,
            EngineError::NotFound(_) => Reason::NotFound,
            EngineError::Unavailable(_) => Reason::Unavailable,
            EngineError::StoreFailed(_) => Reason::StoreFailed,
            EngineError::Cancelled => Reason::Deadline,
            EngineError::Store(e) => store_reason(e),
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
