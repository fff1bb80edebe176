//! The LIBR+ gRPC contract (`proto/librplus/v1/librplus.proto`): generated messages, the
//! `LibRPlus` client and server, and the encoded file descriptor set for server reflection.
#![forbid(unsafe_code)]
#![allow(clippy::all, missing_docs)]

/// Package `librplus.v1`.
pub mod v1 {
    tonic::include_proto!("librplus.v1");
}

/// The codec of every `librplus.v1` call: prost's, except that a request that does not decode
/// as its message is INVALID_ARGUMENT (the client sent it), not INTERNAL as tonic's default says.
pub mod codec {
    use std::marker::PhantomData;
    use tonic::Status;
    use tonic::codec::{BufferSettings, Codec, DecodeBuf, Decoder};
    use tonic_prost::{ProstCodec, ProstDecoder, ProstEncoder};

    /// prost's codec with decode failures as INVALID_ARGUMENT.
    #[derive(Debug, Clone)]
    pub struct Checked<T, U> {
        _pd: PhantomData<(T, U)>,
    }

    impl<T, U> Default for Checked<T, U> {
        fn default() -> Self {
            Self::new()
        }
    }

    impl<T, U> Checked<T, U> {
        /// A codec.
        pub fn new() -> Self {
            Self { _pd: PhantomData }
        }
    }

    /// The decoder: prost's, its error's code changed.
    #[derive(Debug, Clone)]
    pub struct CheckedDecoder<U>(ProstDecoder<U>);

    impl<U: prost::Message + Default> Decoder for CheckedDecoder<U> {
        type Item = U;
        type Error = Status;

        fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
            self.0.decode(buf).map_err(|s| {
                Status::invalid_argument(format!(
                    "the message does not decode as {}: {}",
                    std::any::type_name::<U>()
                        .rsplit("::")
                        .next()
                        .unwrap_or("?"),
                    s.message()
                ))
            })
        }

        fn buffer_settings(&self) -> BufferSettings {
            self.0.buffer_settings()
        }
    }

    impl<T, U> Codec for Checked<T, U>
    where
        T: prost::Message + Send + 'static,
        U: prost::Message + Default + Send + 'static,
    {
        type Encode = T;
        type Decode = U;
        type Encoder = ProstEncoder<T>;
        type Decoder = CheckedDecoder<U>;

        fn encoder(&mut self) -> Self::Encoder {
            ProstEncoder::new(BufferSettings::default())
        }

        fn decoder(&mut self) -> Self::Decoder {
            CheckedDecoder(ProstCodec::<T, U>::raw_decoder(BufferSettings::default()))
        }
    }
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
