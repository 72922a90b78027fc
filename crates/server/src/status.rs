//! The one place where engine errors become gRPC status codes.

use patchwork_engine::{EngineError, Reason};
use std::collections::HashMap;
use tonic::{Code, Status};
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

/// The status of an engine error: the code of its kind ([`code`]), its message, and its kind
/// as the `reason` of a `google.rpc.ErrorInfo` in the details (domain [`DOMAIN`]).
pub fn to_status(e: EngineError) -> Status {
    let r = e.reason();
    with_reason(code(r), short(e.to_string()), r)
}

/// The `domain` of the `ErrorInfo` the daemon's statuses carry.
pub const DOMAIN: &str = "patchwork";

/// A status of `code` and message `m` whose details name its kind.
pub fn with_reason(code: Code, m: String, r: Reason) -> Status {
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

/// The gRPC code of a kind of failure: the one table of them.
pub fn code(r: Reason) -> Code {
    match r {
        Reason::InvalidRequest => Code::InvalidArgument,
        Reason::TooLarge | Reason::DiskFull => Code::ResourceExhausted,
        Reason::NotFound => Code::NotFound,
        // Not this server's to do: the message says what (no GPU; the writer's name).
        Reason::Unavailable | Reason::ReadOnlyReplica => Code::FailedPrecondition,
        Reason::Deadline => Code::DeadlineExceeded,
        // The request is valid, for another replica: out of this one's range.
        Reason::OutsideRegion => Code::OutOfRange,
        Reason::Unauthenticated => Code::Unauthenticated,
        Reason::PermissionDenied => Code::PermissionDenied,
        // Retrying later can help: the disk may get room, the daemon a restart, an object
        // store down or slow come back.
        Reason::StoreFailed | Reason::StoreLocked | Reason::StorageUnavailable => Code::Unavailable,
        Reason::DataLoss => Code::DataLoss,
        Reason::StoreCorrupt | Reason::Internal => Code::Internal,
        // A file's kinds, which reach a client in an ingest result rather than a status.
        Reason::OutsideIngestFolders
        | Reason::Unreadable
        | Reason::NotADem
        | Reason::FileTooLarge
        | Reason::Sidecar
        | Reason::Crs
        | Reason::CrsConflict
        | Reason::Geoid
        | Reason::BadAccuracy
        | Reason::Implausible
        | Reason::BadGrid => Code::InvalidArgument,
        // `Reason` is non-exhaustive across crates; a kind the engine adds without a row here
        // fails `every_kind_has_a_code_of_its_own` rather than compiling to UNKNOWN unseen.
        _ => Code::Unknown,
    }
}

/// What a request that ran past its deadline gets.
pub fn deadline(ms: u64) -> Status {
    with_reason(
        Code::DeadlineExceeded,
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
    fn every_kind_has_a_code_of_its_own() {
        for r in Reason::ALL {
            assert_ne!(
                code(r),
                Code::Unknown,
                "{} has no row in `code`",
                r.as_str()
            );
        }
    }
    use patchwork_store::StoreError;

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
        let s = to_status(EngineError::NoSurvey("x".repeat(1 << 20)));
        assert_eq!(s.code(), Code::NotFound);
        assert!(s.message().len() <= MAX_MESSAGE + 3);
        let s = to_status(EngineError::StoreFailed("é".repeat(1000)));
        assert!(s.message().ends_with('…'));
    }
}
