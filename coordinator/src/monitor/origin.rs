//! The monitor's defence against web pages in its viewers' browsers, with
//! or without a token (docs/monitor.md, "What the monitor defends against"):
//!
//! - **DNS rebinding**: a page on `evil.example` whose name then resolves
//!   to 127.0.0.1 reaches the monitor as the same origin, but its requests
//!   say `Host: evil.example`. Only the listen address, `localhost`,
//!   `127.0.0.1`, `[::1]` and the `--http-allow-host` names are answered;
//!   on an unspecified listen address (0.0.0.0, ::) any IP literal too (a
//!   literal cannot be rebound).
//! - **Cross-site requests** (CSRF): a page elsewhere can make the browser
//!   send a POST (a form, `fetch` with `text/plain`) without asking. A
//!   request whose `Origin` is another origin is refused, and one that
//!   changes something needs `Content-Type: application/json` (which a
//!   page elsewhere cannot send without a CORS preflight, which is never
//!   granted) and either a same-origin `Origin` or `Sec-Fetch-Site:
//!   same-origin` (what a browser sends for the monitor's own page) or an
//!   `Authorization` token (which no page elsewhere can make a browser
//!   add). A program without a token sends `Origin` itself.

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{HeaderMap, Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::{ApiError, Monitor};

/// Which `Host` headers the monitor answers.
#[derive(Clone, Debug)]
pub struct Hosts {
    listen: SocketAddr,
    /// `--http-allow-host` names, lowercase: `NAME` (any port) or `NAME:PORT`.
    names: Vec<String>,
}

impl Hosts {
    pub fn new(listen: SocketAddr, names: &[String]) -> Self {
        Hosts {
            listen,
            names: names
                .iter()
                .map(|n| n.trim().to_ascii_lowercase())
                .collect(),
        }
    }

    fn allows(&self, host: &str) -> bool {
        let host = host.to_ascii_lowercase();
        let name = hostname(&host);
        if matches!(name, "localhost" | "127.0.0.1" | "[::1]") {
            return true;
        }
        if self.names.iter().any(|n| *n == host || n == name) {
            return true;
        }
        let literal = name
            .strip_prefix('[')
            .and_then(|n| n.strip_suffix(']'))
            .unwrap_or(name)
            .parse::<IpAddr>()
            .ok();
        match literal {
            Some(_) if self.listen.ip().is_unspecified() => true,
            Some(ip) => ip == self.listen.ip(),
            None => false,
        }
    }

    /// Why a request is refused, or Ok.
    pub fn check(&self, method: &Method, headers: &HeaderMap) -> Result<(), String> {
        let text = |h| {
            headers
                .get(h)
                .and_then(|v: &header::HeaderValue| v.to_str().ok())
        };
        let Some(host) = text(header::HOST) else {
            return Err("the request has no Host header".into());
        };
        if !self.allows(host) {
            return Err(format!(
                "Host {host:?} is not this monitor's: it answers its listen address ({}), localhost, \
                 127.0.0.1, [::1] and names given with --http-allow-host",
                self.listen
            ));
        }
        let origin = text(header::ORIGIN);
        if let Some(o) = origin
            && !same_origin(o, host)
        {
            return Err(format!(
                "a request from the page at {o:?} (another origin) is refused"
            ));
        }
        if matches!(*method, Method::GET | Method::HEAD | Method::OPTIONS) {
            return Ok(());
        }
        if let Some(site) = text(header::HeaderName::from_static("sec-fetch-site"))
            && site != "same-origin"
        {
            return Err(format!(
                "a {method} from a page elsewhere (Sec-Fetch-Site: {site}) is refused"
            ));
        }
        let json = text(header::CONTENT_TYPE).is_some_and(|t| {
            t.split(';')
                .next()
                .is_some_and(|m| m.trim().eq_ignore_ascii_case("application/json"))
        });
        if !json {
            return Err(format!(
                "a {method} needs Content-Type: application/json (so that a page elsewhere cannot send it)"
            ));
        }
        // Belt and braces behind the content type: the request says it is
        // the page's own (a browser always sends Origin on a POST), or it
        // carries a token, which no page elsewhere can make a browser add.
        let says_where = origin.is_some()
            || headers.contains_key(header::HeaderName::from_static("sec-fetch-site"));
        if !says_where && !headers.contains_key(header::AUTHORIZATION) {
            return Err(format!(
                "a {method} needs Origin: http://{host} (or Sec-Fetch-Site: same-origin), as the monitor's page sends, \
                 or a token in Authorization; a program without a token adds the header: curl -H 'Origin: http://{host}'"
            ));
        }
        Ok(())
    }
}

/// `name` of `name:port`, `[v6]` of `[v6]:port`.
fn hostname(host: &str) -> &str {
    if host.starts_with('[') {
        return host.find(']').map_or(host, |i| &host[..=i]);
    }
    host.rsplit_once(':').map_or(host, |(n, _)| n)
}

/// Whether `origin` (`scheme://host[:port]`) is the page of `host`.
fn same_origin(origin: &str, host: &str) -> bool {
    ["http://", "https://"]
        .iter()
        .filter_map(|s| origin.strip_prefix(s))
        .any(|authority| authority.eq_ignore_ascii_case(host))
}

/// The middleware: 403 with the reason, before the token is looked at.
pub async fn guard(State(monitor): State<Arc<Monitor>>, req: Request, next: Next) -> Response {
    match monitor.hosts.check(req.method(), req.headers()) {
        Ok(()) => next.run(req).await,
        Err(why) => ApiError::new(StatusCode::FORBIDDEN, why).into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn req(method: &str, h: &[(&str, &str)]) -> (Method, HeaderMap) {
        let mut m = HeaderMap::new();
        for (k, v) in h {
            m.insert(
                header::HeaderName::from_bytes(k.as_bytes()).unwrap(),
                v.parse().unwrap(),
            );
        }
        (method.parse().unwrap(), m)
    }

    #[test]
    fn hosts_origins_and_content_types() {
        let hosts = Hosts::new("127.0.0.1:7880".parse().unwrap(), &["Farm.Example".into()]);
        let ok = |m, h: &[(&str, &str)]| {
            let (m, h) = req(m, h);
            hosts.check(&m, &h)
        };
        for host in [
            "127.0.0.1:7880",
            "localhost:7880",
            "[::1]:7880",
            "farm.example",
            "FARM.example:443",
        ] {
            assert_eq!(ok("GET", &[("host", host)]), Ok(()), "{host}");
        }
        for host in [
            "evil.example",
            "10.0.0.1:7880",
            "localhost.evil.example:7880",
            "[::2]",
        ] {
            let e = ok("GET", &[("host", host)]).unwrap_err();
            assert!(e.contains("is not this monitor's"), "{host}: {e}");
        }
        assert!(ok("GET", &[]).unwrap_err().contains("no Host header"));
        let h = ("host", "127.0.0.1:7880");
        let json = ("content-type", "application/json");
        assert_eq!(
            ok("POST", &[h, json, ("origin", "http://127.0.0.1:7880")]),
            Ok(())
        );
        assert_eq!(
            ok(
                "POST",
                &[
                    h,
                    ("content-type", "application/json; charset=utf-8"),
                    ("origin", "http://127.0.0.1:7880")
                ]
            ),
            Ok(())
        );
        assert_eq!(
            ok("POST", &[h, json, ("authorization", "Bearer t")]),
            Ok(())
        );
        let e = ok("POST", &[h, json]).unwrap_err();
        assert!(
            e.contains("needs Origin: http://127.0.0.1:7880") && e.contains("curl -H"),
            "{e}"
        );
        assert_eq!(
            ok("POST", &[h, json, ("sec-fetch-site", "same-origin")]),
            Ok(())
        );
        let e = ok("POST", &[h, json, ("origin", "http://evil.example")]).unwrap_err();
        assert!(e.contains("another origin"), "{e}");
        let e = ok("GET", &[h, ("origin", "null")]).unwrap_err();
        assert!(e.contains("another origin"), "{e}");
        let e = ok("POST", &[h, json, ("sec-fetch-site", "cross-site")]).unwrap_err();
        assert!(e.contains("Sec-Fetch-Site: cross-site"), "{e}");
        let e = ok(
            "POST",
            &[
                h,
                ("content-type", "text/plain"),
                ("origin", "http://127.0.0.1:7880"),
            ],
        )
        .unwrap_err();
        assert!(e.contains("needs Content-Type: application/json"), "{e}");

        let any = Hosts::new("0.0.0.0:7880".parse().unwrap(), &[]);
        let (m, hd) = req("GET", &[("host", "192.168.1.5:7880")]);
        assert_eq!(any.check(&m, &hd), Ok(()));
        let (m, hd) = req("GET", &[("host", "box.lan:7880")]);
        assert!(any.check(&m, &hd).is_err());
    }
}
