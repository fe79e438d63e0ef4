//! Tessera's gRPC API (protobuf package `tessera.v1`, sources in
//! `proto/tessera/v1/`), the Rust shape of a job request both its ends
//! share ([`JobSpec`]), and the conversions between its messages and those
//! types. Prost types stop here: the coordinator, the worker and the
//! client commands convert at their edges, and tracer-core never sees them.

pub mod convert;
pub mod film_codec;
pub mod job;
pub use job::JobSpec;
pub mod lease;
pub use lease::{LeasedJob, LeasedUnit, MalformedUnit};
pub mod placement;
pub mod transport;

/// Generated messages, clients and servers.
pub mod pb {
    tonic::include_proto!("tessera.v1");
}

/// Encoded `FileDescriptorSet` of the API, for gRPC server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("tessera_descriptor");

/// Version of the protocol spoken by this build. Bumped on any change that
/// an older peer would misread.
pub const PROTOCOL_VERSION: u32 = 1;

/// gRPC metadata key carrying [`PROTOCOL_VERSION`] on every request.
pub const PROTOCOL_VERSION_KEY: &str = "tessera-protocol-version";

/// Checks a request's protocol version metadata. Absent is accepted (generic
/// gRPC tools); a different or unreadable value is refused with a message that
/// names both versions.
pub fn check_protocol_version(meta: &tonic::metadata::MetadataMap) -> Result<(), tonic::Status> {
    let Some(v) = meta.get(PROTOCOL_VERSION_KEY) else {
        return Ok(());
    };
    match v.to_str().ok().and_then(|s| s.trim().parse::<u32>().ok()) {
        Some(PROTOCOL_VERSION) => Ok(()),
        other => Err(tonic::Status::failed_precondition(format!(
            "protocol version mismatch: the client speaks tessera protocol {}, this coordinator speaks {PROTOCOL_VERSION}; \
             use a client and coordinator from the same Tessera release",
            other.map_or_else(|| format!("{v:?}"), |n| n.to_string())
        ))),
    }
}

/// A client interceptor that stamps every request with this build's
/// protocol version and, when the farm uses tokens, the caller's token
/// (`authorization: Bearer TOKEN`).
#[derive(Clone, Debug, Default)]
pub struct VersionStamp {
    authorization: Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>,
}

impl VersionStamp {
    /// Stamps `token` too (None: no token, for farms without tokens).
    pub fn with_token(token: Option<&str>) -> Result<Self, transport::TransportError> {
        let authorization = token
            .map(|t| {
                format!("Bearer {t}")
                    .parse()
                    .map_err(|_| transport::TransportError::BadToken)
            })
            .transpose()?;
        Ok(VersionStamp { authorization })
    }
}

impl tonic::service::Interceptor for VersionStamp {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        req.metadata_mut().insert(
            PROTOCOL_VERSION_KEY,
            tonic::metadata::MetadataValue::from(PROTOCOL_VERSION),
        );
        if let Some(a) = &self.authorization {
            req.metadata_mut()
                .insert(transport::AUTHORIZATION, a.clone());
        }
        Ok(req)
    }
}
