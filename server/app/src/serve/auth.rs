//! The operator's guard on the dashboard and the operator API. On loopback no token is needed unless one is
//! given; beyond loopback a token is required: from `--operator-token-file`, or generated and printed once to
//! stderr. Browsers present it as the `libero_operator` cookie (set by `POST /login`), scripts as a bearer
//! header. Episode (agent) tokens are a different secret and never pass here.
use std::net::SocketAddr;
use std::path::Path;

use anyhow::{Context, bail};
use axum::extract::{Request, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Redirect, Response};

use super::episodes::tokens_equal;

/// Name of the dashboard's session cookie.
pub const COOKIE: &str = "libero_operator";

/// `None`: the dashboard is open (loopback without a token file).
#[derive(Clone)]
pub struct OperatorToken(pub Option<String>);

impl OperatorToken {
    /// The token for a server bound to `addr`, read from `file` or generated (and then announced on stderr).
    pub fn for_server(addr: SocketAddr, file: Option<&Path>) -> anyhow::Result<Self> {
        if let Some(file) = file {
            let text = std::fs::read_to_string(file).with_context(|| format!("cannot read {}", file.display()))?;
            let token = text.trim().to_owned();
            if token.len() < 16 || token.chars().any(|c| c.is_whitespace() || c == ';' || c == ',') {
                bail!("{}: the operator token must be at least 16 characters without spaces, ';' or ','", file.display());
            }
            return Ok(Self(Some(token)));
        }
        if addr.ip().is_loopback() {
            return Ok(Self(None));
        }
        let token = super::episodes::random_hex(24)?;
        eprintln!(
            "libero-agent serve: listening beyond loopback; the dashboard and operator API need this operator token \
             (shown only now; use --operator-token-file to choose one):\n  {token}"
        );
        Ok(Self(Some(token)))
    }

    /// Whether `headers` carry the operator token (always true without one).
    pub fn admits(&self, headers: &HeaderMap) -> bool {
        let Some(expected) = &self.0 else { return true };
        let bearer = headers
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(str::trim);
        bearer.into_iter().chain(cookie(headers, COOKIE)).any(|t| tokens_equal(t, expected))
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

/// Whether a browser sent this request from another site: its `Origin` names a different host than `Host`.
/// WebSockets and form posts carry no CORS protection, so without this check any web page the operator
/// visits could read an open (loopback) dashboard's streams or prepare episodes.
fn cross_site(headers: &HeaderMap) -> bool {
    let Some(origin) = headers.get(header::ORIGIN) else { return false };
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
    let origin_host = origin.to_str().ok().and_then(|o| o.split_once("://")).map(|(_, rest)| rest.trim_end_matches('/'));
    !matches!((origin_host, host), (Some(o), Some(h)) if o.eq_ignore_ascii_case(h))
}

/// Middleware: cross-site requests answer 403; without the token, pages redirect to the login form and
/// everything else answers 401.
pub async fn require_operator(State(token): State<OperatorToken>, req: Request, next: Next) -> Response {
    if cross_site(req.headers()) {
        return (
            StatusCode::FORBIDDEN,
            axum::Json(serde_json::json!({"ok": false, "error": "cross-site requests to the dashboard are refused"})),
        )
            .into_response();
    }
    if token.admits(req.headers()) {
        return next.run(req).await;
    }
    let path = req.uri().path();
    let is_page = req.method() == axum::http::Method::GET && !path.starts_with("/api/") && !path.starts_with("/ws/");
    if is_page {
        return Redirect::to("/login").into_response();
    }
    (
        StatusCode::UNAUTHORIZED,
        [(header::WWW_AUTHENTICATE, "Bearer")],
        axum::Json(serde_json::json!({"ok": false, "error": "operator token required"})),
    )
        .into_response()
}

#[derive(serde::Deserialize)]
pub struct LoginForm {
    pub token: String,
}

/// `POST /login`: a right token becomes an HttpOnly, SameSite=Strict cookie.
pub async fn login(State(token): State<OperatorToken>, axum::Form(form): axum::Form<LoginForm>) -> Response {
    match &token.0 {
        Some(expected) if tokens_equal(form.token.trim(), expected) => (
            StatusCode::SEE_OTHER,
            [
                (header::SET_COOKIE, format!("{COOKIE}={expected}; HttpOnly; SameSite=Strict; Path=/")),
                (header::LOCATION, "/".to_owned()),
            ],
        )
            .into_response(),
        Some(_) => (StatusCode::UNAUTHORIZED, axum::response::Html(super::dashboard::login_page(true))).into_response(),
        None => Redirect::to("/").into_response(),
    }
}

pub async fn login_form() -> Response {
    axum::response::Html(super::dashboard::login_page(false)).into_response()
}
