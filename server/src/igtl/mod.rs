//! OpenIGTLink for the operating room's navigation software (3D Slicer's OpenIGTLinkIF, PLUS,
//! CustusX, IBIS, MITK): the wire codec ([`wire`]: header, CRC-64, TRANSFORM, POINT, STATUS,
//! POLYDATA), on which the bridge (`librplus-server igtl`, issue 30) is built.

#[cfg(feature = "igtl")]
pub mod bridge;
pub mod wire;
