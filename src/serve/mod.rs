//! The gRPC API: generated messages, conversions, the dispatcher, the error mapping and the
//! tonic services.

pub mod api;
pub mod convert;
pub mod grpc;
pub mod proto;
pub mod status;
