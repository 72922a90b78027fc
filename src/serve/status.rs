//! The one place where engine errors become gRPC status codes.

use crate::engine::EngineError;
use crate::store::StoreError;
use tonic::Status;

pub fn to_status(e: EngineError) -> Status {
    match e {
        EngineError::Invalid(m) => Status::invalid_argument(m),
        EngineError::TooLarge(m) => Status::resource_exhausted(m),
        EngineError::NotFound(m) => Status::not_found(m),
        EngineError::Unavailable(m) => Status::failed_precondition(m),
        EngineError::Store(StoreError::Locked { dir }) => Status::unavailable(format!(
            "the store at {} is in use by another process",
            dir.display()
        )),
        EngineError::Store(e) => Status::internal(e.to_string()),
    }
}

/// What a request that ran past its deadline gets.
pub fn deadline(ms: u64) -> Status {
    Status::deadline_exceeded(format!(
        "the request took longer than the {ms} ms limit: ask for a smaller region, a larger error or a smaller tile"
    ))
}
