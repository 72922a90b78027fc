//! Code generated from `proto/patchwork/v1`.
// Generated code carries no docs of its own: the messages are documented in the .proto files.
#![allow(clippy::all, missing_docs)]

tonic::include_proto!("patchwork.v1");

/// The encoded descriptors, for the reflection service.
pub const DESCRIPTOR: &[u8] = tonic::include_file_descriptor_set!("patchwork_descriptor");
