//! The LIBR+ gRPC contract (`proto/librplus/v1/librplus.proto`): generated messages, the
//! `LibRPlus` client and server, and the encoded file descriptor set for server reflection.
#![forbid(unsafe_code)]
#![allow(clippy::all, missing_docs)]

/// Package `librplus.v1`.
pub mod v1 {
    tonic::include_proto!("librplus.v1");
}

/// Encoded `FileDescriptorSet` of `librplus.v1` (with its imports), for server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("librplus_descriptor");

/// The canonical gRPC name of a status code ("OK", "INVALID_ARGUMENT", "RESOURCE_EXHAUSTED", ...).
pub fn code_name(code: tonic::Code) -> &'static str {
    use tonic::Code::*;
    match code {
        Ok => "OK",
        Cancelled => "CANCELLED",
        Unknown => "UNKNOWN",
        InvalidArgument => "INVALID_ARGUMENT",
        DeadlineExceeded => "DEADLINE_EXCEEDED",
        NotFound => "NOT_FOUND",
        AlreadyExists => "ALREADY_EXISTS",
        PermissionDenied => "PERMISSION_DENIED",
        ResourceExhausted => "RESOURCE_EXHAUSTED",
        FailedPrecondition => "FAILED_PRECONDITION",
        Aborted => "ABORTED",
        OutOfRange => "OUT_OF_RANGE",
        Unimplemented => "UNIMPLEMENTED",
        Internal => "INTERNAL",
        Unavailable => "UNAVAILABLE",
        DataLoss => "DATA_LOSS",
        Unauthenticated => "UNAUTHENTICATED",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn code_names_match_grpc() {
        assert_eq!(code_name(tonic::Code::Ok), "OK");
        assert_eq!(code_name(tonic::Code::InvalidArgument), "INVALID_ARGUMENT");
        assert_eq!(
            code_name(tonic::Code::ResourceExhausted),
            "RESOURCE_EXHAUSTED"
        );
        assert_eq!(code_name(tonic::Code::Unauthenticated), "UNAUTHENTICATED");
        // Every code round-trips through its number: the names are distinct and all 17 exist.
        let names: std::collections::BTreeSet<_> = (0..17)
            .map(|i| code_name(tonic::Code::from_i32(i)))
            .collect();
        assert_eq!(names.len(), 17);
    }
}
