//! OpenIGTLink for the operating room's navigation software (3D Slicer's OpenIGTLinkIF, PLUS,
//! CustusX, IBIS, MITK): the wire codec ([`wire`], the `librplus-igtl` crate: header, CRC-64,
//! TRANSFORM, POINT, STATUS, POLYDATA), on which the bridge (`librplus-server igtl`) is built:
//! `bridge` (its connections and sessions), `answers` (what it sends the peer: STATUS, and each
//! registration's messages), `geometry` (frames, targets, the case's surface) and `requests`
//! (what a peer sends, as a session's requests).

#[cfg(feature = "igtl")]
mod answers;
#[cfg(feature = "igtl")]
pub mod bridge;
#[cfg(feature = "igtl")]
mod geometry;
#[cfg(feature = "igtl")]
mod requests;
pub use librplus_igtl as wire;
