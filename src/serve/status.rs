//! The one place where engine errors become gRPC status codes.

use crate::engine::{EngineError, Reason};
use crate::store::StoreError;
use std::collections::HashMap;
use tonic::Status;
use tonic_types::{ErrorDetails, StatusExt};

/// Longest message a status carries: it travels in an HTTP/2 header, and a client's megabyte
/// of input must not come back in it.
const MAX_MESSAGE: usize = 1024;

fn short(mut m: String) -> String {
    if m.len() > MAX_MESSAGE {
        let mut cut = MAX_MESSAGE;
        while !m.is_char_boundary(cut) {
            cut -= 1;
        }
        m.truncate(cut);
        m.push('…');
    }
    m
}

/// The status of an engine error: its code, its message, and its kind as the `reason` of a
/// `google.rpc.ErrorInfo` in the details (domain [`DOMAIN`]).
pub fn to_status(e: EngineError) -> Status {
    let r = e.reason();
    let s = code_of(e);
    with_reason(s.code(), s.message().to_string(), r)
}

/// The `domain` of the `ErrorInfo` the daemon's statuses carry.
pub const DOMAIN: &str = "patchwork";

/// A status of `code` and message `m` whose details name its kind.
pub fn with_reason(code: tonic::Code, m: String, r: Reason) -> Status {
    Status::with_error_details(
        code,
        m,
        ErrorDetails::with_error_info(r.as_str(), DOMAIN, HashMap::<String, String>::new()),
    )
}

/// The kind a status's details name, where they name one.
pub fn reason_of(s: &Status) -> Option<Reason> {
    let info = s.get_error_details().error_info()?.clone();
    (info.domain == DOMAIN)
        .then(|| Reason::parse(&info.reason))
        .flatten()
}

fn code_of(e: EngineError) -> Status {
    let m = short(e.to_string());
    match e {
        EngineError::Invalid(_) => Status::invalid_argument(m),
        EngineError::TooLarge(_) => Status::resource_exhausted(m),
        EngineError::NotFound(_) => Status::not_found(m),
        EngineError::Unavailable(_) => Status::failed_precondition(m),
        // Retrying later can help: the disk may get room, the daemon a restart.
        EngineError::StoreFailed(_) => Status::unavailable(m),
        EngineError::Store(StoreError::Full { .. }) => Status::resource_exhausted(m),
        EngineError::Store(StoreError::Locked { .. }) => Status::unavailable(m),
        // Not this server's to do: the message names the writer.
        EngineError::Store(StoreError::Replica { .. }) => Status::failed_precondition(m),
        EngineError::Store(StoreError::Sled(sled::Error::Io(io)))
            if io.kind() == std::io::ErrorKind::StorageFull =>
        {
            Status::resource_exhausted(m)
        }
        EngineError::Store(StoreError::Sled(sled::Error::Io(_)) | StoreError::Io(_)) => {
            Status::unavailable(m)
        }
        // An object store down or slow: the bytes are there, and a retry may find them.
        EngineError::Store(StoreError::Samples(e)) if e.unavailable => Status::unavailable(m),
        EngineError::Store(StoreError::Samples(_)) => Status::data_loss(m),
        EngineError::Store(_) => Status::internal(m),
        EngineError::Cancelled => Status::deadline_exceeded(m),
    }
}

/// What a request that ran past its deadline gets.
pub fn deadline(ms: u64) -> Status {
    with_reason(
        tonic::Code::DeadlineExceeded,
        format!(
            "the request took longer than the {ms} ms limit: ask for a smaller region, a larger error or a smaller tile"
        ),
        Reason::Deadline,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_error_gets_its_code_and_a_bounded_message() {
        use tonic::Code;
        let full = StoreError::Full {
            available_mb: 1,
            needed_mb: 70,
        };
        let s = to_status(full.into());
        assert_eq!(s.code(), Code::ResourceExhausted);
        assert_eq!(reason_of(&s), Some(Reason::DiskFull));
        let enospc = std::io::Error::from(std::io::ErrorKind::StorageFull);
        let s = to_status(StoreError::Sled(sled::Error::Io(enospc)).into());
        assert_eq!(s.code(), Code::ResourceExhausted);
        let eio = std::io::Error::other("Input/output error");
        let s = to_status(StoreError::Sled(sled::Error::Io(eio)).into());
        assert_eq!(s.code(), Code::Unavailable);
        assert_eq!(reason_of(&s), Some(Reason::StorageUnavailable));
        assert_eq!(reason_of(&deadline(5)), Some(Reason::Deadline));
        let s = to_status(EngineError::StoreFailed("Input/output error".into()));
        assert_eq!(s.code(), Code::Unavailable);
        let s = to_status(EngineError::NotFound("x".repeat(1 << 20)));
        assert_eq!(s.code(), Code::NotFound);
        assert!(s.message().len() <= MAX_MESSAGE + 3);
        let s = to_status(EngineError::Invalid("é".repeat(1000)));
        assert!(s.message().ends_with('…'));
    }
}
