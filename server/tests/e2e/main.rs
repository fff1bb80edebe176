//! The server's end-to-end tests over loopback gRPC, one module per concern (as tonic's own
//! integration tests are laid out), built as one test binary so that `cargo test` links the
//! server and the library once.

mod common;

mod adversary;
mod auth;
mod bad_input;
mod cases;
mod coarse;
mod demo_load;
mod discovery;
mod igtl;
mod interop;
mod limits;
mod probe;
mod probe_errors;
mod refine;
mod replicas;
mod resume;
mod safety;
mod shutdown;
mod stream;
mod tls;
mod unary;
mod upload;
