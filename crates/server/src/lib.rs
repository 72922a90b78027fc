//! The gRPC API: generated messages, conversions, the dispatcher, the error mapping, the
//! tokens and the tonic services.

pub mod api;
pub mod auth;
pub mod conns;
pub mod convert;
pub mod door;
pub mod export;
pub mod grpc;
pub mod proto;
pub mod status;
pub mod tls;
pub mod turns;
pub mod web;
