//! LIBR+ gRPC clients: `replay` streams recorded dataset scenarios to a server in lockstep and
//! scores the registrations against the ground truth (TRE); `load` runs many concurrent sessions
//! for a fixed time and reports throughput, latency percentiles and errors by code. The message
//! builders ([`stream_messages`], [`measurements_message`], [`measurements_from_stream`]) are
//! shared with the server's tests, which compare server results with the library called directly.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod cases;
pub mod data;
pub mod load;
pub mod messages;
pub mod replay;
pub mod session;
pub mod stats;

/// The generated wire types of `librplus.v1`.
pub use librplus_proto::v1 as pb;

pub use cases::{UploadOptions, UploadSummary, delete, upload};
pub use data::{Loaded, Replayable, ScenarioRef, Selection, load_selection, select};
pub use load::{LoadOptions, LoadSummary, load, load_table};
pub use messages::{
    MessageError, measurements_from_stream, measurements_message, rigid_from_message,
    rigid_message, stream_messages,
};
pub use replay::{
    DiscoveryRecord, ReplayOptions, ReplaySummary, degradations, discovery_wait, method_name,
    parse_method, parse_methods, replay, replay_table, result_sha256, series_name, sha256_hex,
};
pub use session::{
    Client, Resume, SessionConfig, SessionEnd, SessionOutcome, Tls, connect, connect_replicas,
    connect_with, run_session,
};
pub use stats::{Latencies, LatencyMs, code_name};

#[cfg(test)]
mod tests {
    /// `replay` and `load` can run on a spawned task (their futures are `Send`).
    #[test]
    fn futures_are_send() {
        fn send<T: Send>(_: &T) {}
        let (r, l) = (
            super::ReplayOptions::default(),
            super::LoadOptions::default(),
        );
        let (a, b) = (super::replay(&r), super::load(&l));
        send(&a);
        send(&b);
    }
}
