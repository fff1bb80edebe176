//! The LIBR+ gRPC contract (`proto/librplus/v1/librplus.proto`): generated messages, the
//! `LibRPlus` client and server, and the encoded file descriptor set for server reflection.

#![allow(clippy::all, missing_docs)]

/// Package `librplus.v1`.
pub mod v1 {
    tonic::include_proto!("librplus.v1");
}

/// Encoded `FileDescriptorSet` of `librplus.v1` (with its imports), for server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("librplus_descriptor");
