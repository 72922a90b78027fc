//! The loopback S3 server of the tests, shared with the bench.

pub use patchwork_testkit::s3::*;
