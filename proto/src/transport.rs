//! How Tessera's processes reach each other: the channel to a coordinator
//! (plain HTTP/2 or TLS through rustls), bearer tokens, and the size of
//! asset chunks. The one place clients and workers share this.

use std::time::Duration;

use tonic::transport::{Certificate, ClientTlsConfig, Endpoint};

/// Environment variables that hold the client's and the worker's token.
pub const CLIENT_TOKEN_ENV: &str = "TESSERA_TOKEN";
pub const WORKER_TOKEN_ENV: &str = "TESSERA_WORKER_TOKEN";

/// Metadata key of the bearer token.
pub const AUTHORIZATION: &str = "authorization";
/// Largest `AssetChunk.data` (both directions).
pub const ASSET_CHUNK_BYTES: usize = 1 << 20;

#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    #[error("invalid coordinator URL {url:?}: {message}")]
    Url { url: String, message: String },
    #[error(
        "a CA certificate (--ca) was given but the coordinator URL {url:?} is plain http; use https://"
    )]
    CaWithoutTls { url: String },
    #[error("TLS set-up for {url}: {message}")]
    Tls { url: String, message: String },
    #[error(
        "the token contains characters that cannot travel in gRPC metadata (printable ASCII only)"
    )]
    BadToken,
}

/// Lowercase hex, the form in which files are named by their SHA-256 on
/// the wire, in the coordinator's store and in a worker's cache.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

pub fn sha256_hex(data: &[u8]) -> String {
    use sha2::Digest as _;
    hex(&sha2::Sha256::digest(data))
}

/// The name under which a worker is shown (ListWorkers, the monitor,
/// logs): a hash of its session (`RegisterResponse.worker_id`), so that
/// what anyone may see never lets them speak as the worker.
pub fn public_worker_id(session: &str) -> String {
    format!("w{}", &sha256_hex(session.as_bytes())[..16])
}

/// Whether `s` is a SHA-256 as files are named: 64 lowercase hex digits.
pub fn is_sha256_hex(s: &str) -> bool {
    s.len() == 64
        && s.bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

/// An error with its chain of sources on one line, each said once
/// (transport errors repeat their source in their own text).
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut detail = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let text = s.to_string();
        if !detail.contains(&text) {
            detail = format!("{detail}: {text}");
        }
        source = s.source();
    }
    detail
}

/// The endpoint for a coordinator URL. `https://` URLs use TLS, trusting
/// `ca_pem` when given (a farm's own CA, as `tessera cert` makes) or else
/// the public web roots; `http://` is plain and refuses a CA.
pub fn endpoint(url: &str, ca_pem: Option<&[u8]>) -> Result<Endpoint, TransportError> {
    let bad = |message: String| TransportError::Url {
        url: url.to_string(),
        message,
    };
    // tonic's error says only "invalid URI"; its source says what is wrong.
    let mut endpoint = Endpoint::from_shared(url.to_string()).map_err(|e| bad(error_chain(&e)))?;
    let tls = match endpoint.uri().scheme_str() {
        Some("https") => true,
        Some("http") => false,
        None => {
            return Err(bad(format!(
                "no scheme; write http://{url} (https:// for a coordinator serving TLS)"
            )));
        }
        Some(other) => {
            return Err(bad(format!(
                "the scheme must be http or https, not {other:?}"
            )));
        }
    };
    if tls {
        let host = endpoint.uri().host().unwrap_or_default().to_string();
        let mut config = ClientTlsConfig::new().domain_name(host.trim_matches(['[', ']']));
        config = match ca_pem {
            Some(pem) => config.ca_certificate(Certificate::from_pem(pem)),
            None => config.with_webpki_roots(),
        };
        endpoint = endpoint
            .tls_config(config)
            .map_err(|e| TransportError::Tls {
                url: url.to_string(),
                message: e.to_string(),
            })?;
    } else if ca_pem.is_some() {
        return Err(TransportError::CaWithoutTls {
            url: url.to_string(),
        });
    }
    Ok(endpoint
        .connect_timeout(Duration::from_secs(5))
        .tcp_nodelay(true)
        // HTTP/2's default 64 KiB windows allow 64 KiB per round trip;
        // results, frames and asset chunks are megabytes.
        .initial_stream_window_size(8 << 20)
        .initial_connection_window_size(32 << 20))
}
