//! The monitor's gate: the coordinator's client token, as the gRPC job
//! service takes it (`Authorization: Bearer TOKEN`). The page keeps the
//! token in the tab's sessionStorage and sends it with every request,
//! the event stream included (read with fetch, not EventSource, which
//! cannot send headers), so a token never appears in a URL or a log.

use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::{ApiError, Monitor};
use crate::server::same;

pub async fn require_token(
    State(monitor): State<Arc<Monitor>>,
    req: Request,
    next: Next,
) -> Response {
    check(&[&monitor.token], req, next).await
}

/// `/metrics`: the client token or the scrape-only metrics token; open
/// only when neither is set.
pub async fn require_metrics_token(
    State(monitor): State<Arc<Monitor>>,
    req: Request,
    next: Next,
) -> Response {
    check(&[&monitor.token, &monitor.metrics_token], req, next).await
}

/// Lets `req` through when it carries one of `tokens` (or none is set).
async fn check(tokens: &[&Option<Arc<str>>], req: Request, next: Next) -> Response {
    let expected: Vec<&str> = tokens.iter().filter_map(|t| t.as_deref()).collect();
    if expected.is_empty() {
        return next.run(req).await;
    }
    let given = req
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .map(|v| v.strip_prefix("Bearer ").unwrap_or(v).trim());
    let refusal = match given {
        // Every token compared, in constant time each.
        Some(t)
            if expected
                .iter()
                .fold(false, |ok, e| same(t.as_bytes(), e.as_bytes()) | ok) =>
        {
            return next.run(req).await;
        }
        None => "this coordinator needs its client token: send `Authorization: Bearer TOKEN`",
        Some(_) if tokens.len() > 1 => {
            "the token sent is neither this coordinator's client token nor its metrics token"
        }
        Some(_) => "the token sent is not this coordinator's client token",
    };
    let mut resp = ApiError::new(StatusCode::UNAUTHORIZED, refusal).into_response();
    resp.headers_mut().insert(
        header::WWW_AUTHENTICATE,
        HeaderValue::from_static("Bearer realm=\"tessera\""),
    );
    resp
}
