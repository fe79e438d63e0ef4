//! Job-end notifications (issue 38): when a job ends (done, failed,
//! cancelled) the coordinator POSTs its JSON, exactly what `tessera
//! status JOB --json` prints ([`crate::status_json::job_json`]), to the
//! job's `--on-done` URLs and the coordinator's `--notify` URLs, signed
//! with HMAC-SHA256 under the `--notify-secret-file` secret
//! (`X-Tessera-Signature: sha256=<hex>`), retried with exponential
//! back-off. Each delivery is its own task, at most [`MAX_IN_FLIGHT`] at
//! once: the farm only hands the job's status over and never waits.
//!
//! Plain `http://` only: the signature proves who sent a body, not that
//! nobody else read it (a TLS-terminating proxy in front of an `https`
//! receiver covers that).

use std::sync::Arc;
use std::time::Duration;

use http_body_util::{BodyExt as _, Full};
use hyper::Uri;
use hyper::body::Bytes;
use hyper_util::rt::TokioIo;
use tessera_proto::pb;

/// Attempts of one delivery: the first and its retries.
pub const ATTEMPTS: u32 = 5;
/// Wait before the first retry; doubled before each next (0.5, 1, 2, 4 s).
pub const FIRST_BACKOFF: Duration = Duration::from_millis(500);
/// One attempt's limit, connecting to reading the response's status.
pub const ATTEMPT_TIMEOUT: Duration = Duration::from_secs(10);
/// Deliveries in flight at once; more wait their turn (on their task).
pub const MAX_IN_FLIGHT: usize = 16;
/// The signature header: `sha256=` and the hex HMAC-SHA256 of the body.
pub const SIGNATURE_HEADER: &str = "x-tessera-signature";
/// The shortest secret accepted (bytes).
pub const MIN_SECRET_BYTES: usize = 16;

/// Why a notification URL or secret was refused.
#[derive(Debug, thiserror::Error)]
pub enum NotifyError {
    #[error("{what} {url:?}: {why}")]
    Url {
        what: &'static str,
        url: String,
        why: String,
    },
    #[error(
        "the notification secret is {0} bytes; it must be at least {MIN_SECRET_BYTES} (e.g. `head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \\n'`)"
    )]
    ShortSecret(usize),
}

/// Checks a notification URL: `http://HOST[:PORT]/PATH`. `what` names
/// where it came from (`--notify`, `--on-done`) in the error.
pub fn check_url(what: &'static str, url: &str) -> Result<(), NotifyError> {
    let err = |why: String| NotifyError::Url {
        what,
        url: url.chars().take(200).collect(),
        why,
    };
    let uri: Uri = url.parse().map_err(|e| err(format!("not a URL: {e}")))?;
    match uri.scheme_str() {
        Some("http") => {}
        Some("https") => {
            return Err(err(
                "https is not supported; POSTs are plain http, signed (put a TLS-terminating proxy in front of an https receiver)".into(),
            ));
        }
        _ => return Err(err("must be an http:// URL".into())),
    }
    if uri.host().is_none_or(str::is_empty) {
        return Err(err("has no host".into()));
    }
    Ok(())
}

/// The HMAC-SHA256 of `body` under `secret`, as the header carries it.
pub fn signature(secret: &[u8], body: &[u8]) -> String {
    let key = ring::hmac::Key::new(ring::hmac::HMAC_SHA256, secret);
    let tag = ring::hmac::sign(&key, body);
    format!("sha256={}", tessera_proto::transport::hex(tag.as_ref()))
}

/// The coordinator's notification settings and the deliveries' limit.
pub struct Notifier {
    /// `--notify`: told of every job's end.
    pub global: Vec<String>,
    /// `--notify-secret-file`'s content; None: no notification can be
    /// signed, so none is configured (`--notify` and `--on-done` are refused).
    pub secret: Option<Arc<[u8]>>,
    slots: Arc<tokio::sync::Semaphore>,
}

impl Notifier {
    pub fn new(global: Vec<String>, secret: Option<Vec<u8>>) -> Result<Self, NotifyError> {
        for u in &global {
            check_url("--notify", u)?;
        }
        if let Some(s) = &secret
            && s.len() < MIN_SECRET_BYTES
        {
            return Err(NotifyError::ShortSecret(s.len()));
        }
        Ok(Notifier {
            global,
            secret: secret.map(Arc::from),
            slots: Arc::new(tokio::sync::Semaphore::new(MAX_IN_FLIGHT)),
        })
    }

    /// Whether a job with these `--on-done` URLs has anyone to tell.
    pub fn wanted(&self, on_done: &[String]) -> bool {
        !self.global.is_empty() || !on_done.is_empty()
    }

    /// Sends `status` (an ended job's) to `on_done` and the `--notify`
    /// URLs, on tasks of their own: returns at once. `settled` runs once
    /// every URL has answered or been given up.
    pub fn send(
        &self,
        status: pb::JobStatus,
        on_done: &[String],
        settled: impl FnOnce() + Send + 'static,
    ) {
        let Some(secret) = self.secret.clone() else {
            return;
        };
        let Ok(rt) = tokio::runtime::Handle::try_current() else {
            tracing::error!(job = %status.job_id, "no runtime to send the job's notifications on");
            return;
        };
        let urls: Vec<String> = on_done.iter().chain(&self.global).cloned().collect();
        let slots = self.slots.clone();
        rt.spawn(async move {
            // Off the farm's lock and its caller: the JSON as `status --json`.
            let body = Bytes::from(
                serde_json::to_vec(&crate::status_json::job_json(&status))
                    .expect("JSON serialises"),
            );
            let sig = signature(&secret, &body);
            let state = crate::status_json::state_name(status.state);
            let mut deliveries = Vec::new();
            for url in urls {
                let (body, sig, slots) = (body.clone(), sig.clone(), slots.clone());
                let (job, state) = (status.job_id.clone(), state);
                deliveries.push(tokio::spawn(async move {
                    let _slot = slots.acquire_owned().await;
                    deliver(&url, &job, state, body, &sig).await;
                }));
            }
            for d in deliveries {
                let _ = d.await;
            }
            settled();
        });
    }
}

/// POSTs `body` to `url` until a 2xx answers or [`ATTEMPTS`] are spent.
async fn deliver(url: &str, job: &str, state: &str, body: Bytes, sig: &str) {
    let mut wait = FIRST_BACKOFF;
    for attempt in 1..=ATTEMPTS {
        let r = tokio::time::timeout(ATTEMPT_TIMEOUT, post(url, job, state, body.clone(), sig))
            .await
            .unwrap_or_else(|_| Err(format!("no answer within {ATTEMPT_TIMEOUT:?}")));
        match r {
            Ok(()) => {
                tracing::info!(job, url, attempt, state, "job notification delivered");
                return;
            }
            Err(error) if attempt < ATTEMPTS => {
                tracing::warn!(job, url, attempt, %error, retry_in_s = wait.as_secs_f64(),
                    "job notification not delivered; retrying");
                tokio::time::sleep(wait).await;
                wait *= 2;
            }
            Err(error) => {
                tracing::error!(job, url, attempts = ATTEMPTS, %error,
                    "job notification not delivered; giving up");
            }
        }
    }
}

/// One POST over a new HTTP/1.1 connection: Ok on a 2xx status.
async fn post(url: &str, job: &str, state: &str, body: Bytes, sig: &str) -> Result<(), String> {
    let uri: Uri = url.parse().map_err(|e| format!("{e}"))?;
    let host = uri.host().ok_or("no host")?.to_string();
    let port = uri.port_u16().unwrap_or(80);
    // [::1] as the URL writes it, ::1 as a socket address takes it.
    let addr = host
        .trim_start_matches('[')
        .trim_end_matches(']')
        .to_string();
    let stream = tokio::net::TcpStream::connect((addr.as_str(), port))
        .await
        .map_err(|e| format!("connect to {host}:{port}: {e}"))?;
    let (mut sender, conn) = hyper::client::conn::http1::handshake(TokioIo::new(stream))
        .await
        .map_err(|e| format!("HTTP handshake: {e}"))?;
    let conn = tokio::spawn(conn);
    let authority = uri.authority().map_or(host.clone(), |a| a.to_string());
    let path = uri.path_and_query().map_or("/", |p| p.as_str()).to_string();
    let req = hyper::Request::post(path)
        .header(hyper::header::HOST, authority)
        .header(hyper::header::CONTENT_TYPE, "application/json")
        .header(
            hyper::header::USER_AGENT,
            concat!("tessera/", env!("CARGO_PKG_VERSION")),
        )
        .header(SIGNATURE_HEADER, sig)
        .header("x-tessera-job", job)
        .header("x-tessera-event", format!("job.{state}"))
        .body(Full::new(body))
        .map_err(|e| format!("request: {e}"))?;
    let resp = sender
        .send_request(req)
        .await
        .map_err(|e| format!("POST: {e}"))?;
    let status = resp.status();
    // Read (and drop) the answer so the connection ends cleanly.
    let _ = resp.into_body().collect().await;
    conn.abort();
    if status.is_success() {
        Ok(())
    } else {
        Err(format!("answered {status}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_signature_is_rfc_4231s_hmac_sha256() {
        // RFC 4231, test case 2.
        assert_eq!(
            signature(b"Jefe", b"what do ya want for nothing?"),
            "sha256=5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
    }

    #[test]
    fn urls_are_http_with_a_host() {
        assert!(check_url("--notify", "http://127.0.0.1:9000/hook?x=1").is_ok());
        let e = check_url("--on-done", "https://example.com/")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("--on-done \"https://example.com/\": https is not supported"),
            "{e}"
        );
        let e = check_url("--notify", "ftp://example.com/hook")
            .unwrap_err()
            .to_string();
        assert!(e.contains("must be an http:// URL"), "{e}");
        let e = check_url("--notify", "example.com/hook")
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a URL"), "{e}");
    }
}
