//! The operator's guard. Every page, API, WebSocket, video, observation file, teleop and demo route needs the
//! operator credential on every address, loopback included; only `/api/health` and `/mcp/{id}` (behind its own
//! episode token) are outside it. Scripts send the token as `Authorization: Bearer …`; a browser opens the
//! one-time login URL `serve` prints (`/?token=…`, Jupyter's convention) or posts the login form, and gets a
//! random session id as an HttpOnly cookie, never the token itself. Episode (agent) tokens never pass here.
//!
//! In front of everything, the Host allow-list: a request whose `Host` is not a loopback name of the bound
//! port (or a `--public-host` name) answers 421 before any handler runs, so a DNS-rebinding page cannot talk
//! to the server through a name it controls.
use std::collections::VecDeque;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::{Arc, Mutex};

use axum::extract::{Request, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Redirect, Response};

use crate::credential::{self, TOKEN_FILE};
use crate::episodes::{random_hex, tokens_equal};

/// Name of the dashboard's session cookie.
pub const COOKIE: &str = "libero_session";
/// Browser sessions kept at once; the oldest is forgotten first.
const MAX_SESSIONS: usize = 256;

/// The operator's secret and the browser sessions it opened.
#[derive(Clone)]
pub struct Operator {
    token: Arc<str>,
    sessions: Arc<Mutex<VecDeque<String>>>,
    /// The login form (the console's, or [`plain_login_page`] on a server without one).
    login_page: fn(bool) -> String,
}

/// The login form of a server without a console: the operator API's browser sessions still open through it.
pub fn plain_login_page(failed: bool) -> String {
    let notice = if failed { "<p role=\"alert\">That token is not this server's operator token.</p>" } else { "" };
    format!(
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>libero-agent: sign in</title></head><body>\
         <h1>Operator sign-in</h1>{notice}<form method=\"post\" action=\"/login\"><label>Operator token \
         <input type=\"password\" name=\"token\" autocomplete=\"current-password\"></label> \
         <button type=\"submit\">Sign in</button></form></body></html>"
    )
}

impl Operator {
    /// The token from `file`, or a fresh random one; either way kept (0600) in `<data>/operator_token`, where
    /// client commands of the same user find it.
    pub fn for_server(data: &Path, file: Option<&Path>) -> anyhow::Result<Self> {
        let token = match file {
            Some(f) => credential::read_token_file(f)?,
            None => random_hex(32)?,
        };
        credential::write_private(&data.join(TOKEN_FILE), &token)?;
        Ok(Self::with_token(token))
    }

    pub fn with_token(token: String) -> Self {
        Self { token: token.into(), sessions: Arc::default(), login_page: plain_login_page }
    }

    /// The same operator, answering browsers with `page` as its login form.
    pub fn with_login_page(self, page: fn(bool) -> String) -> Self {
        Self { login_page: page, ..self }
    }

    pub fn token(&self) -> &str {
        &self.token
    }

    /// Whether `headers` carry the operator token (bearer) or an open browser session (cookie).
    pub fn admits(&self, headers: &HeaderMap) -> bool {
        let bearer = crate::bearer(headers);
        if bearer.is_some_and(|t| tokens_equal(t, &self.token)) {
            return true;
        }
        let Some(session) = cookie(headers, COOKIE) else { return false };
        let Ok(sessions) = self.sessions.lock() else { return false };
        sessions.iter().any(|s| tokens_equal(s, session))
    }

    /// Opens a browser session; returns its `Set-Cookie` value.
    fn open_session(&self) -> Option<String> {
        let id = random_hex(32).ok()?;
        let mut sessions = self.sessions.lock().ok()?;
        if sessions.len() >= MAX_SESSIONS {
            sessions.pop_front();
        }
        sessions.push_back(id.clone());
        Some(format!("{COOKIE}={id}; HttpOnly; SameSite=Strict; Path=/"))
    }

    fn token_matches(&self, candidate: &str) -> bool {
        tokens_equal(candidate.trim(), &self.token)
    }
}

/// The value of cookie `name`, if sent.
fn cookie<'a>(headers: &'a HeaderMap, name: &str) -> Option<&'a str> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .filter_map(|kv| kv.trim().split_once('='))
        .find(|(k, _)| *k == name)
        .map(|(_, v)| v)
}

/// The `Host` names this server answers to: the loopback names and the bound address with the bound port,
/// and every `--public-host` (`name` for any port a proxy in front uses, or exactly `name:port`).
#[derive(Clone, Debug)]
pub struct AllowedHosts {
    port: u16,
    /// (name, port if the entry names one, whether it came from `--public-host`)
    entries: Arc<Vec<(String, Option<u16>, bool)>>,
}

/// `name[:port]` with IPv6 names in brackets; `Err` for a port that is no number.
fn split_host(host: &str) -> Result<(&str, Option<u16>), ()> {
    match host.rfind(':') {
        Some(i) if !host[i..].contains(']') => host[i + 1..].parse().map(|p| (&host[..i], Some(p))).map_err(|_| ()),
        _ => Ok((host, None)),
    }
}

impl AllowedHosts {
    pub fn new(bound: SocketAddr, public_hosts: &[String]) -> Self {
        let mut entries: Vec<(String, Option<u16>, bool)> =
            ["127.0.0.1", "localhost", "[::1]"].iter().map(|n| ((*n).to_owned(), None, false)).collect();
        if !bound.ip().is_unspecified() {
            let name = match bound {
                SocketAddr::V4(a) => a.ip().to_string(),
                SocketAddr::V6(a) => format!("[{}]", a.ip()),
            };
            entries.push((name, None, false));
        }
        for h in public_hosts {
            let h = h.trim().to_ascii_lowercase();
            if let Ok((name, port)) = split_host(&h) {
                entries.push((name.to_owned(), port, true));
            }
        }
        Self { port: bound.port(), entries: Arc::new(entries) }
    }

    /// Whether `host` (a `Host` header value or URI authority) names this server.
    pub fn allows(&self, host: &str) -> bool {
        let host = host.trim().to_ascii_lowercase();
        let Ok((name, port)) = split_host(&host) else { return false };
        self.entries.iter().any(|(n, entry_port, public)| {
            n == name
                && match (port, entry_port) {
                    (Some(p), Some(e)) => p == *e,
                    (Some(p), None) => p == self.port,
                    // No port: the scheme's default, which a proxy in front of a public name may use.
                    (None, Some(_)) => false,
                    (None, None) => *public || self.port == 80,
                }
        })
    }
}

/// Middleware, outermost: 421 Misdirected Request for a `Host` this server does not answer to.
pub async fn check_host(State(hosts): State<AllowedHosts>, req: Request, next: Next) -> Response {
    let host = req.headers().get(header::HOST).and_then(|h| h.to_str().ok()).or_else(|| req.uri().authority().map(|a| a.as_str()));
    if host.is_some_and(|h| hosts.allows(h)) {
        return next.run(req).await;
    }
    (
        StatusCode::MISDIRECTED_REQUEST,
        [(header::CONNECTION, "close")],
        axum::Json(serde_json::json!({
            "ok": false,
            "error": format!("this server does not answer to Host {:?}; use 127.0.0.1:{} or a name given with --public-host", host.unwrap_or(""), hosts.port),
        })),
    )
        .into_response()
}

/// Whether a browser sent this request from another site: its `Origin` names a different host than `Host`.
/// WebSockets and form posts carry no CORS protection, so without this check any web page the operator
/// visits could read the dashboard's streams or prepare episodes with the operator's cookie.
fn cross_site(headers: &HeaderMap) -> bool {
    let Some(origin) = headers.get(header::ORIGIN) else { return false };
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
    let origin_host = origin.to_str().ok().and_then(|o| o.split_once("://")).map(|(_, rest)| rest.trim_end_matches('/'));
    !matches!((origin_host, host), (Some(o), Some(h)) if o.eq_ignore_ascii_case(h))
}

/// The `token` query parameter and the rest of the query, if the URL carries one.
fn split_token_query(query: Option<&str>) -> Option<(String, String)> {
    let query = query?;
    let mut token = None;
    let mut rest = Vec::new();
    for pair in query.split('&') {
        match pair.strip_prefix("token=") {
            Some(t) => token = Some(t.to_owned()),
            None if !pair.is_empty() => rest.push(pair),
            None => {}
        }
    }
    Some((token?, rest.join("&")))
}

/// Middleware: cross-site requests answer 403; a page URL with the right `?token=` opens a session and
/// redirects to itself without the token; without the credential, pages redirect to the login form and
/// everything else answers 401.
pub async fn require_operator(State(op): State<Operator>, req: Request, next: Next) -> Response {
    if cross_site(req.headers()) {
        return crate::json_error(StatusCode::FORBIDDEN, "cross-site requests to the dashboard are refused");
    }
    let path = req.uri().path().to_owned();
    let is_page = req.method() == axum::http::Method::GET && !path.starts_with("/api/") && !path.starts_with("/ws/");
    if is_page && let Some((token, rest)) = split_token_query(req.uri().query()) {
        if !op.token_matches(&token) {
            return (StatusCode::UNAUTHORIZED, axum::response::Html((op.login_page)(true))).into_response();
        }
        let Some(cookie) = op.open_session() else {
            return crate::json_error(StatusCode::INTERNAL_SERVER_ERROR, "cannot open a session");
        };
        let location = if rest.is_empty() { path } else { format!("{path}?{rest}") };
        return (StatusCode::SEE_OTHER, [(header::SET_COOKIE, cookie), (header::LOCATION, location)]).into_response();
    }
    if op.admits(req.headers()) {
        return next.run(req).await;
    }
    if is_page {
        return Redirect::to("/login").into_response();
    }
    let mut resp = crate::json_error(StatusCode::UNAUTHORIZED, "operator token required");
    resp.headers_mut().insert(header::WWW_AUTHENTICATE, header::HeaderValue::from_static("Bearer"));
    resp
}

#[derive(serde::Deserialize)]
pub struct LoginForm {
    pub token: String,
}

/// `POST /login`: the right token opens a session (HttpOnly, SameSite=Strict cookie).
pub async fn login(State(op): State<Operator>, headers: HeaderMap, axum::Form(form): axum::Form<LoginForm>) -> Response {
    if cross_site(&headers) {
        return crate::json_error(StatusCode::FORBIDDEN, "cross-site requests to the dashboard are refused");
    }
    if !op.token_matches(&form.token) {
        return (StatusCode::UNAUTHORIZED, axum::response::Html((op.login_page)(true))).into_response();
    }
    match op.open_session() {
        Some(cookie) => (StatusCode::SEE_OTHER, [(header::SET_COOKIE, cookie), (header::LOCATION, "/".to_owned())]).into_response(),
        None => crate::json_error(StatusCode::INTERNAL_SERVER_ERROR, "cannot open a session"),
    }
}

pub async fn login_form(State(op): State<Operator>) -> Response {
    axum::response::Html((op.login_page)(false)).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hosts(bound: &str, public: &[&str]) -> AllowedHosts {
        AllowedHosts::new(bound.parse().unwrap(), &public.iter().map(|s| s.to_string()).collect::<Vec<_>>())
    }

    #[test]
    fn only_loopback_names_of_the_bound_port_and_public_hosts_are_allowed() {
        let h = hosts("127.0.0.1:8080", &[]);
        for ok in ["127.0.0.1:8080", "localhost:8080", "LOCALHOST:8080", "[::1]:8080"] {
            assert!(h.allows(ok), "{ok}");
        }
        for bad in ["127.0.0.1:8081", "evil.example:8080", "evil.example", "localhost", "127.0.0.1", "10.0.0.1:8080", "", "localhost:80x80", "127.0.0.1.nip.io:8080"] {
            assert!(!h.allows(bad), "{bad}");
        }
        let h = hosts("0.0.0.0:8080", &["bench.lab", "proxy.lab:443"]);
        assert!(h.allows("bench.lab:8080") && h.allows("bench.lab") && h.allows("proxy.lab:443"));
        assert!(!h.allows("proxy.lab:8080") && !h.allows("0.0.0.0:8080") && !h.allows("other.lab:8080"));
        let h = hosts("192.168.1.5:9000", &[]);
        assert!(h.allows("192.168.1.5:9000") && !h.allows("192.168.1.6:9000"));
    }

    #[test]
    fn the_token_query_is_split_from_the_rest() {
        assert_eq!(split_token_query(Some("token=abc")), Some(("abc".into(), String::new())));
        assert_eq!(split_token_query(Some("task=T14&token=abc&x=1")), Some(("abc".into(), "task=T14&x=1".into())));
        assert_eq!(split_token_query(Some("task=T14")), None);
        assert_eq!(split_token_query(None), None);
    }

    #[test]
    fn sessions_are_random_ids_not_the_token_and_bounded() {
        let op = Operator::with_token("0123456789abcdef0123456789abcdef".into());
        let cookie = op.open_session().unwrap();
        assert!(!cookie.contains(op.token()));
        let id = cookie.split(';').next().unwrap().trim_start_matches("libero_session=").to_owned();
        let mut headers = HeaderMap::new();
        headers.insert(header::COOKIE, format!("{COOKIE}={id}").parse().unwrap());
        assert!(op.admits(&headers));
        headers.insert(header::COOKIE, format!("{COOKIE}={}", op.token()).parse().unwrap());
        assert!(!op.admits(&headers), "the token is no session id");
        for _ in 0..MAX_SESSIONS {
            op.open_session();
        }
        headers.insert(header::COOKIE, format!("{COOKIE}={id}").parse().unwrap());
        assert!(!op.admits(&headers), "the oldest session is forgotten past the limit");
        assert_eq!(op.sessions.lock().unwrap().len(), MAX_SESSIONS);
    }
}
