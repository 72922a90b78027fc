//! The daemon as its users meet it, in a child process: the command line, gRPC, tokens and TLS,
//! load and limits, view sessions, the Python client, and crashes and signals.

#[path = "../common/mod.rs"]
mod common;

mod daemon;
mod exports;
mod exposure;
mod hostile;
mod load;
mod objects;
mod python_client;
mod quickstart;
mod reliability;
mod replicas;
mod view_session;
mod web;
mod web_browser;
mod web_clients;
