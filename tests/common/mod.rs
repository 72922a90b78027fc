//! Helpers shared by the daemon's integration tests: the shared surveys and oracles, a daemon
//! in a child process, and the Python environment.
#![allow(dead_code, unused_imports)]

pub mod daemon;
pub mod http;
pub mod python;
pub mod s3;

pub use patchwork_testkit::fixtures::*;
