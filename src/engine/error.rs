//! The engine's one error type, by what the caller should do about it. The server maps each
//! kind to a status code in one place (`serve::status`).

use crate::store::StoreError;
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
    /// The caller gave up (its deadline passed) and the work stopped.
    #[error("the request was cancelled: its deadline passed")]
    Cancelled,
}
