//! OpenIGTLink for the operating room's navigation software (3D Slicer's OpenIGTLinkIF, PLUS,
//! CustusX, IBIS, MITK): the wire codec ([`wire`], the `librplus-igtl` crate: header, CRC-64,
//! TRANSFORM, POINT, STATUS, POLYDATA), on which the bridge (`librplus-server igtl`) is built.

#[cfg(feature = "igtl")]
pub mod bridge;
pub use librplus_igtl as wire;
