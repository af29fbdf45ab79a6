//! The gRPC service as a client sees it: a real server on port 0, a tonic client, every RPC,
//! streaming, a restart that keeps templates, deadlines, a full queue, bad input, and the real
//! `grpcurl` binary. One test binary, one module per concern:
//!
//! - `registry`: the registry RPCs' contract, restarts, stray files, SIGKILL, a read-only
//!   template directory;
//! - `matching`: Match and MatchStream, the official checkpoint and the classical matcher over
//!   gRPC;
//! - `limits`: oversize messages, bad requests, a full queue, deadlines, the compute budget,
//!   image bombs;
//! - `health`: the standard health service while the model loads;
//! - `security`: TLS, bearer tokens, SIGHUP;
//! - `reflection`: `grpcurl` through reflection;
//! - `http`: the same API as JSON on the HTTP port, its statuses, tokens, TLS and OpenAPI
//!   document.
//!
//! Most tests run an *untrained* (randomly initialised) network: they check the service's
//! contract, not accuracy. The accuracy test over gRPC uses the official checkpoint and skips
//! when `../shared/reference` is absent (see `common::unavailable`). Servers in child processes
//! are ready once their health service answers SERVING.

// `mod common;` here would look for tests/service/common.rs: the helpers are shared with the
// other test binaries.
#[path = "../common/mod.rs"]
mod common;

mod health;
mod http;
mod limits;
mod matching;
mod reflection;
mod registry;
mod security;
