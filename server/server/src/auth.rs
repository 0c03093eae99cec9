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
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use anyhow::Context;
use axum::extract::{Request, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Redirect, Response};
use libero_records::json::sha256_hex;

use crate::credential::{self, TOKEN_FILE};
use crate::episodes::{random_hex, tokens_equal};
use crate::{ApiError, ApiResult};

/// Name of the dashboard's session cookie.
pub const COOKIE: &str = "libero_session";
/// Where, beside the token, the open browser sessions and unused login links are kept (0600, hashes only), so a
/// restart logs nobody out and a used link stays used.
pub const SESSIONS_FILE: &str = "operator_sessions";
/// Browser sessions kept at once; the oldest is forgotten first.
const MAX_SESSIONS: usize = 256;
/// Unused one-time login links kept at once (one is printed per start); the oldest is forgotten first.
const MAX_LOGIN_CODES: usize = 16;
/// How long a printed login link stays usable: a link left in a terminal's scrollback must not open the console
/// forever.
const LOGIN_CODE_TTL_S: u64 = 24 * 3600;
/// Largest sessions file read at start (256 sessions and 16 links take about 20 kB).
const MAX_SESSIONS_FILE_BYTES: u64 = 1 << 20;

/// What the login form may say about this server; `failed` when the token just given was wrong.
#[derive(Debug, Clone, Default)]
pub struct LoginInfo {
    pub failed: bool,
    /// The address the server listens on (`127.0.0.1:8080`), if known.
    pub listen: Option<SocketAddr>,
    /// Whether that address is a loopback address (only this machine reaches the server).
    pub loopback_only: bool,
    /// The absolute path of `<data>/operator_token`, if this server keeps one.
    pub token_file: Option<PathBuf>,
}

/// What survives a restart: hashes of open sessions and unused login codes, tied to the token they belong to.
#[derive(Debug, Default, serde::Serialize, serde::Deserialize)]
struct Persisted {
    /// sha256 of the operator token these belong to: a rotated or replaced token drops them all.
    token_sha256: String,
    /// sha256 of each open session id, oldest first.
    sessions: VecDeque<String>,
    /// sha256 of each unused one-time login code and when it was made (Unix seconds), oldest first.
    login_codes: VecDeque<(String, u64)>,
}

/// The operator's secret, the browser sessions it opened and the one-time login links not used yet.
#[derive(Clone)]
pub struct Operator {
    token: Arc<str>,
    state: Arc<Mutex<Persisted>>,
    /// `<data>/operator_sessions`, where [`Persisted`] is kept; `None` keeps everything in memory.
    state_file: Option<Arc<Path>>,
    /// The login form (the console's, or [`plain_login_page`] on a server without one).
    login_page: fn(&LoginInfo) -> String,
    /// What the login form tells about this server (`failed` is set per answer).
    info: Arc<LoginInfo>,
}

/// The login form of a server without a console: the operator API's browser sessions still open through it.
pub fn plain_login_page(info: &LoginInfo) -> String {
    let notice = if info.failed { "<p role=\"alert\">That token is not this server's operator token.</p>" } else { "" };
    let file = info.token_file.as_ref().map(|f| format!("<p>The operator token is in <code>{}</code>.</p>", html_escape(&f.display().to_string()))).unwrap_or_default();
    format!(
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>libero-agent: sign in</title></head><body>\
         <h1>Operator sign-in</h1>{notice}{file}<form method=\"post\" action=\"/login\"><label>Operator token \
         <input type=\"password\" name=\"token\" autocomplete=\"current-password\"></label> \
         <button type=\"submit\">Sign in</button></form></body></html>"
    )
}

fn html_escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

fn now_s() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0)
}

impl Operator {
    /// The operator of the server on `data`: the token from `file`, a fresh random one when `rotate`, otherwise the
    /// one kept in `<data>/operator_token` (made at the first start), so a restart keeps everyone signed in.
    /// Either way it is kept (0600) in `<data>/operator_token`, where client commands of the same user find it.
    /// Sessions and unused login links of the same token come back from `<data>/operator_sessions`.
    pub fn for_server(data: &Path, file: Option<&Path>, rotate: bool) -> anyhow::Result<Self> {
        let kept = data.join(TOKEN_FILE);
        let token = match (file, rotate) {
            (Some(f), _) => credential::read_token_file(f)?,
            (None, true) => random_hex(32)?,
            (None, false) => match std::fs::symlink_metadata(&kept) {
                Ok(meta) => {
                    use std::os::unix::fs::PermissionsExt;
                    if meta.permissions().mode() & 0o077 != 0 {
                        eprintln!(
                            "warning: {} was readable by other users; it is 0600 again, but pass --rotate-token if they may have read it",
                            kept.display()
                        );
                    }
                    credential::read_token_file(&kept)
                        .with_context(|| format!("{} holds no usable operator token; pass --rotate-token to replace it", kept.display()))?
                }
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => random_hex(32)?,
                Err(e) => return Err(e).with_context(|| format!("cannot read {}", kept.display())),
            },
        };
        credential::write_private(&kept, &token)?;
        let state_file = data.join(SESSIONS_FILE);
        let state = load_state(&state_file, &token);
        let op = Self { state_file: Some(state_file.into()), state: Arc::new(Mutex::new(state)), ..Self::with_token(token) };
        op.persist().context("cannot keep the operator's sessions")?;
        Ok(op)
    }

    /// An operator whose sessions live in memory only (tests, and servers without a data directory).
    pub fn with_token(token: String) -> Self {
        let state = Persisted { token_sha256: sha256_hex(token.as_bytes()), ..Persisted::default() };
        Self {
            token: token.into(),
            state: Arc::new(Mutex::new(state)),
            state_file: None,
            login_page: plain_login_page,
            info: Arc::new(LoginInfo::default()),
        }
    }

    /// The same operator, answering browsers with `page` as its login form.
    pub fn with_login_page(self, page: fn(&LoginInfo) -> String) -> Self {
        Self { login_page: page, ..self }
    }

    /// The same operator, its login form saying where the server listens and where its token is.
    pub fn listening_on(self, addr: SocketAddr, token_file: Option<PathBuf>) -> Self {
        let token_file = token_file.map(|f| std::path::absolute(&f).unwrap_or(f));
        let info = LoginInfo { failed: false, listen: Some(addr), loopback_only: addr.ip().is_loopback(), token_file };
        Self { info: Arc::new(info), ..self }
    }

    pub fn token(&self) -> &str {
        &self.token
    }

    /// The login form's HTML.
    fn login_html(&self, failed: bool) -> String {
        (self.login_page)(&LoginInfo { failed, ..(*self.info).clone() })
    }

    /// Whether `headers` carry the operator token (bearer) or an open browser session (cookie).
    pub fn admits(&self, headers: &HeaderMap) -> bool {
        let bearer = crate::bearer(headers);
        if bearer.is_some_and(|t| tokens_equal(t, &self.token)) {
            return true;
        }
        let Some(session) = cookie(headers, COOKIE) else { return false };
        if session.len() > 128 {
            return false;
        }
        let hash = sha256_hex(session.as_bytes());
        let Ok(state) = self.state.lock() else { return false };
        state.sessions.iter().any(|s| tokens_equal(s, &hash))
    }

    /// Writes the sessions and login codes to `<data>/operator_sessions` (nothing without a data directory).
    fn persist_locked(&self, state: &Persisted) -> anyhow::Result<()> {
        let Some(file) = &self.state_file else { return Ok(()) };
        credential::write_private(file, &serde_json::to_string(state)?)
    }

    fn persist(&self) -> anyhow::Result<()> {
        let state = self.state.lock().map_err(|_| anyhow::anyhow!("operator state poisoned"))?;
        self.persist_locked(&state)
    }

    /// Opens a browser session, kept across restarts; returns its `Set-Cookie` value.
    fn open_session(&self) -> Option<String> {
        let id = random_hex(32).ok()?;
        let mut state = self.state.lock().ok()?;
        while state.sessions.len() >= MAX_SESSIONS {
            state.sessions.pop_front();
        }
        state.sessions.push_back(sha256_hex(id.as_bytes()));
        if let Err(e) = self.persist_locked(&state) {
            // The session still works until this server stops.
            eprintln!("warning: the new browser session will not survive a restart: {e:#}");
        }
        Some(format!("{COOKIE}={id}; HttpOnly; SameSite=Strict; Path=/"))
    }

    /// A new one-time login code (for the link `serve` prints): it opens one browser session, once, within
    /// [`LOGIN_CODE_TTL_S`], also after a restart; `--rotate-token` voids it.
    pub fn new_login_code(&self) -> anyhow::Result<String> {
        let code = random_hex(32)?;
        let mut state = self.state.lock().map_err(|_| anyhow::anyhow!("operator state poisoned"))?;
        let now = now_s();
        state.login_codes.retain(|(_, made)| now.saturating_sub(*made) < LOGIN_CODE_TTL_S);
        while state.login_codes.len() >= MAX_LOGIN_CODES {
            state.login_codes.pop_front();
        }
        state.login_codes.push_back((sha256_hex(code.as_bytes()), now));
        self.persist_locked(&state)?;
        Ok(code)
    }

    /// Uses up login code `candidate`: `Ok(true)` if it was an unused, unexpired code; the use is on disk before
    /// this returns, so the link cannot work again, not even after a restart.
    fn consume_login_code(&self, candidate: &str) -> anyhow::Result<bool> {
        if candidate.len() > 128 {
            return Ok(false);
        }
        let hash = sha256_hex(candidate.as_bytes());
        let mut state = self.state.lock().map_err(|_| anyhow::anyhow!("operator state poisoned"))?;
        let now = now_s();
        let Some(i) = state.login_codes.iter().position(|(h, made)| tokens_equal(h, &hash) && now.saturating_sub(*made) < LOGIN_CODE_TTL_S)
        else {
            return Ok(false);
        };
        state.login_codes.remove(i);
        self.persist_locked(&state)?;
        Ok(true)
    }

    fn token_matches(&self, candidate: &str) -> bool {
        tokens_equal(candidate.trim(), &self.token)
    }
}

/// The kept sessions and login codes of `token` from `file`; none when the file is missing, unreadable, too large,
/// or belongs to another token (a rotated or replaced one).
fn load_state(file: &Path, token: &str) -> Persisted {
    let fresh = Persisted { token_sha256: sha256_hex(token.as_bytes()), ..Persisted::default() };
    let text = match std::fs::metadata(file) {
        Ok(m) if m.len() > MAX_SESSIONS_FILE_BYTES => {
            eprintln!("warning: {} is larger than {MAX_SESSIONS_FILE_BYTES} bytes; browser sessions start afresh", file.display());
            return fresh;
        }
        Ok(_) => match std::fs::read_to_string(file) {
            Ok(t) => t,
            Err(e) => {
                eprintln!("warning: cannot read {}: {e}; browser sessions start afresh", file.display());
                return fresh;
            }
        },
        Err(_) => return fresh,
    };
    let mut state: Persisted = match serde_json::from_str(&text) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("warning: {} is not a sessions file ({e}); browser sessions start afresh", file.display());
            return fresh;
        }
    };
    if !tokens_equal(&state.token_sha256, &fresh.token_sha256) {
        return fresh;
    }
    let now = now_s();
    state.login_codes.retain(|(_, made)| now.saturating_sub(*made) < LOGIN_CODE_TTL_S);
    while state.sessions.len() > MAX_SESSIONS {
        state.sessions.pop_front();
    }
    while state.login_codes.len() > MAX_LOGIN_CODES {
        state.login_codes.pop_front();
    }
    state
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
    ApiError::new(
        StatusCode::MISDIRECTED_REQUEST,
        format!("this server does not answer to Host {:?}; use 127.0.0.1:{} or a name given with --public-host", host.unwrap_or(""), hosts.port),
    )
    .with_header(header::CONNECTION, "close")
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
pub async fn require_operator(State(op): State<Operator>, req: Request, next: Next) -> ApiResult {
    if cross_site(req.headers()) {
        return Err(ApiError::forbidden(CROSS_SITE));
    }
    let path = req.uri().path().to_owned();
    let is_page = req.method() == axum::http::Method::GET && !path.starts_with("/api/") && !path.starts_with("/ws/");
    if is_page && let Some((token, rest)) = split_token_query(req.uri().query()) {
        // The operator token itself (a bookmarkable credential, Jupyter's convention) or a one-time login code.
        let admitted = op.token_matches(&token)
            || match op.consume_login_code(&token) {
                Ok(used) => used,
                Err(e) => return Err(ApiError::internal(format!("cannot record the login link's use: {e:#}"))),
            };
        if !admitted {
            return Ok((StatusCode::UNAUTHORIZED, axum::response::Html(op.login_html(true))).into_response());
        }
        let cookie = op.open_session().ok_or_else(|| ApiError::internal(NO_SESSION))?;
        let location = if rest.is_empty() { path } else { format!("{path}?{rest}") };
        return Ok((StatusCode::SEE_OTHER, [(header::SET_COOKIE, cookie), (header::LOCATION, location)]).into_response());
    }
    if op.admits(req.headers()) {
        return Ok(next.run(req).await);
    }
    if is_page {
        return Ok(Redirect::to("/login").into_response());
    }
    Err(ApiError::unauthorized("operator token required").with_header(header::WWW_AUTHENTICATE, "Bearer"))
}

const CROSS_SITE: &str = "cross-site requests to the dashboard are refused";
const NO_SESSION: &str = "cannot open a session";

#[derive(serde::Deserialize)]
pub struct LoginForm {
    pub token: String,
}

/// `POST /login`: the right token opens a session (HttpOnly, SameSite=Strict cookie).
pub async fn login(State(op): State<Operator>, headers: HeaderMap, axum::Form(form): axum::Form<LoginForm>) -> ApiResult {
    if cross_site(&headers) {
        return Err(ApiError::forbidden(CROSS_SITE));
    }
    if !op.token_matches(&form.token) {
        return Ok((StatusCode::UNAUTHORIZED, axum::response::Html(op.login_html(true))).into_response());
    }
    let cookie = op.open_session().ok_or_else(|| ApiError::internal(NO_SESSION))?;
    Ok((StatusCode::SEE_OTHER, [(header::SET_COOKIE, cookie), (header::LOCATION, "/".to_owned())]).into_response())
}

pub async fn login_form(State(op): State<Operator>) -> Response {
    axum::response::Html(op.login_html(false)).into_response()
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
        assert_eq!(op.state.lock().unwrap().sessions.len(), MAX_SESSIONS);
    }

    fn session_headers(cookie: &str) -> HeaderMap {
        let mut headers = HeaderMap::new();
        headers.insert(header::COOKIE, cookie.split(';').next().unwrap().parse().unwrap());
        headers
    }

    #[test]
    fn the_token_sessions_and_login_codes_outlive_a_restart_until_the_token_is_rotated() {
        let data = tempfile::tempdir().unwrap();
        let first = Operator::for_server(data.path(), None, false).unwrap();
        let cookie = first.open_session().unwrap();
        let code = first.new_login_code().unwrap();
        let used = first.new_login_code().unwrap();
        assert!(first.consume_login_code(&used).unwrap());
        drop(first);

        let second = Operator::for_server(data.path(), None, false).unwrap();
        assert!(second.admits(&session_headers(&cookie)), "a session opened before the restart still works");
        assert!(!second.consume_login_code(&used).unwrap(), "a used login code stays used after a restart");
        assert!(second.consume_login_code(&code).unwrap(), "an unused code works once after a restart");
        assert!(!second.consume_login_code(&code).unwrap(), "and only once");
        let kept = std::fs::read_to_string(data.path().join(SESSIONS_FILE)).unwrap();
        assert!(!kept.contains(&code) && !kept.contains(cookie.split(';').next().unwrap().split('=').nth(1).unwrap()), "only hashes on disk");
        let token = second.token().to_owned();
        let pending = second.new_login_code().unwrap();
        drop(second);

        let rotated = Operator::for_server(data.path(), None, true).unwrap();
        assert_ne!(rotated.token(), token);
        assert!(!rotated.admits(&session_headers(&cookie)), "rotation ends every session");
        assert!(!rotated.consume_login_code(&pending).unwrap(), "rotation voids unused links");
        assert_eq!(credential::read_token_file(&data.path().join(TOKEN_FILE)).unwrap(), rotated.token());
    }

    #[test]
    fn a_corrupt_token_file_is_an_error_that_names_the_way_out() {
        let data = tempfile::tempdir().unwrap();
        std::fs::write(data.path().join(TOKEN_FILE), "short\n").unwrap();
        let err = Operator::for_server(data.path(), None, false).err().expect("refused");
        assert!(format!("{err:#}").contains("--rotate-token"), "{err:#}");
        assert!(Operator::for_server(data.path(), None, true).is_ok());
    }
}
