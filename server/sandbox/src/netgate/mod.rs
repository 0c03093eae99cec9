//! The runner's end of a sandboxed agent's network: the agent's namespace holds only `lo`, where the sandbox's
//! forwarder ([`crate::sandbox_net`]) relays each TCP connection to a Unix socket the runner listens on. Behind one
//! such socket [`start`] runs the model-API gateway; behind another [`relay_unix_to_tcp`] relays bytes to the
//! episode's MCP endpoint.
//!
//! The gateway tells three kinds of HTTP/1.1 request apart, request by request:
//! - origin-form (`POST /v1/chat/completions`): reverse-proxied to [`GatewayConfig::upstream`], the credentials'
//!   base URL (the request's path and query on the upstream's origin, `Host` rewritten, TLS when https), but only
//!   to the harness's own endpoints, [`GatewayConfig::routes`] (method and exact path): anything else (`GET
//!   /v1/files`, `DELETE /v1/files/x`) would let an agent keep things at the provider from one rollout to the
//!   next, and is refused with 403, as is a path with `..`, `//`, `%2e`, `%2f`, `%5c` or `\`; a request for a
//!   protocol upgrade (WebSocket) gets 426, so that a client falls back to plain HTTP at once. Without an upstream,
//!   503. The agent's API base is the gateway's loopback address with the upstream's path.
//! - absolute-form (`GET http://host:port/path`): forwarded to that host when [`GatewayConfig::allowed`] names it.
//! - `CONNECT host:port` (HTTPS through a proxy): a raw tunnel when allowed; only its byte counts are visible.
//!
//! The upstream's own host:port is never reached by a tunnel or a forward, even when `allowed` names it: its
//! traffic would bypass the routes and the token metering. Anything else allowed lists do not name is refused with
//! 403. Proxied requests go upstream with `Connection: close` and `Accept-Encoding: identity`, and their responses
//! stream back as they arrive (SSE included) while a bounded head and tail of each response is kept to read the
//! model's token usage from.
//!
//! Every request becomes one JSON line in [`GatewayConfig::records`] ([`Record`]): times, mode, method, host:port,
//! path without query, status, who caused the answer ([`Cause`]), body bytes, duration and token usage. Never
//! headers or bodies: no prompts, no keys. Past [`GatewayConfig::max_records`] requests the gateway only counts
//! ([`Overflow`]: requests, statuses, bytes, token sums, the last request passed on), rewrites those counters to
//! the sidecar file [`overflow_sidecar`] at most once a second (so that a crash loses a second at most), and
//! appends them as the file's last line when it stops; a flood of refused requests thus cannot grow the file
//! without bound, and the token sums stay exact. [`summarize`] adds a records file up and
//! [`last_model_api_failure`] says whether the model API failed the agent, both in one streamed pass over lines
//! of at most [`MAX_RECORD_LINE_BYTES`].
//!
//! Bounds: a request head of at most 64 KiB (431 beyond), 10 s to send it (an idle keep-alive connection is closed
//! after as long), request bodies of at most 32 MiB (413), 256 connections at once per socket: a connection over
//! that takes the place of the connection idle the longest (the gateway's: one waiting for a request head; the
//! relay's: the one whose bytes moved last the longest ago), and when none of the gateway's is idle (every one in
//! a request or a tunnel) the new one is answered 503 at once; nothing waits in the listen backlog. 30 s to
//! connect upstream. A response may take as long as the model needs: no total timeout.
//!
//! Each gateway or relay runs on a current-thread tokio runtime of its own thread, so the synchronous runner can
//! start it and stop it ([`Gateway::stop`], or drop it); what is in flight is then cut and recorded as such.
use std::collections::BTreeMap;
use std::convert::Infallible;
use std::future::Future;
use std::io::{BufRead, BufReader, Read as _, Write as _};
use std::net::{IpAddr, SocketAddr};
use std::os::unix::net::UnixListener as StdUnixListener;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::task::{Context, Poll};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use bytes::Bytes;
use http::header::{self, HeaderName, HeaderValue};
use http::{HeaderMap, Method, Request, Response, StatusCode, Uri};
use hyper::body::{Body, Frame, Incoming, SizeHint};
use hyper_util::rt::{TokioIo, TokioTimer};
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpStream, UnixListener, UnixStream};
use tokio::sync::oneshot;

use libero_records::agent_events::Tokens;
use libero_records::json::iso_from_system_time;

/// Largest request head (request line and headers) the gateway reads; beyond it, 431.
pub const MAX_HEAD_BYTES: usize = 64 << 10;
/// Largest request body the gateway forwards; beyond it, 413.
pub const MAX_REQUEST_BODY_BYTES: u64 = 32 << 20;
/// Connections served at once per socket (gateway or relay); one more takes the place of an idle one (see the
/// module's docs), so that the agent's own slow or idle connections never stall its next one.
pub const MAX_CONNECTIONS: usize = 256;
/// Time a client has to send a request head; also how long an idle keep-alive connection stays open. Short: a
/// connection that sends nothing holds a place among [`MAX_CONNECTIONS`].
pub const HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);
/// Time to connect (and shake hands with TLS) upstream.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(30);
/// Requests recorded one line each ([`GatewayConfig::max_records`]'s default); past them, only counted.
pub const MAX_RECORDS: usize = 10_000;
/// Longest line [`summarize`] and [`last_model_api_failure`] read (a record is at most a few KiB); longer lines
/// are skipped and counted as unreadable.
pub const MAX_RECORD_LINE_BYTES: usize = 64 << 10;
/// How often, at most, the overflow counters are rewritten to their sidecar file.
const SIDECAR_EVERY: Duration = Duration::from_secs(1);
/// Of each response, the first bytes kept for reading token usage (Anthropic's `message_start`).
const HEAD_KEEP: usize = 64 << 10;
/// Of each response, the last bytes kept for reading token usage (the final SSE events, a JSON body's `usage`);
/// the buffer holds up to twice this between trims, so at most 256 KiB of a response are held.
const TAIL_KEEP: usize = 96 << 10;
/// How long stopping waits for the runtime's blocking work (name lookups) before leaving it behind.
const STOP_GRACE: Duration = Duration::from_secs(2);

/// What a gateway serves.
#[derive(Debug, Clone)]
pub struct GatewayConfig {
    /// Where origin-form requests (the agent's model API calls) go: the credentials' base URL, `http` or `https`,
    /// e.g. `https://api.example.com/v1`. Only its origin is used: the request's own path and query are sent
    /// there, so the agent's base URL must carry the same path. None: such requests get 503.
    pub upstream: Option<url::Url>,
    /// The origin-form requests passed on to the upstream: method and exact path (the full path the client sends,
    /// the API base's path included, without query). Everything else is refused with 403; empty: every one.
    pub routes: Vec<Route>,
    /// `(host, port)` pairs that `CONNECT` tunnels and absolute-form `http://` requests may reach (host names
    /// compared without case, IPv6 without brackets); everything else is refused with 403 and recorded. The
    /// upstream's own host:port is refused even when listed here.
    pub allowed: Vec<(String, u16)>,
    /// The JSON-lines file each request is appended to as a [`Record`] (created if missing).
    pub records: PathBuf,
    /// Requests written as records; past them only counted ([`Overflow`]), so that the file stays bounded.
    pub max_records: usize,
}

impl Default for GatewayConfig {
    fn default() -> Self {
        Self { upstream: None, routes: Vec::new(), allowed: Vec::new(), records: PathBuf::new(), max_records: MAX_RECORDS }
    }
}

/// One endpoint of the model API that origin-form requests may reach.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Route {
    pub method: Method,
    /// The request's whole path, e.g. `/v1/chat/completions`, compared exactly.
    pub path: String,
}

impl Route {
    pub fn new(method: Method, path: impl Into<String>) -> Self {
        Self { method, path: path.into() }
    }
}

impl std::fmt::Display for Route {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} {}", self.method, self.path)
    }
}

#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    #[error("the model API URL {0:?} is not http(s)://host[:port][/path] without user info")]
    Upstream(String),
    #[error("cannot open the gateway's records file {path}: {source}")]
    Records { path: PathBuf, source: std::io::Error },
    #[error("TLS to the model API: {0}")]
    Tls(String),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// How the gateway handled a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// Origin-form, to the configured upstream.
    Reverse,
    /// Absolute-form `http://…`, to an allowed host.
    Forward,
    /// A `CONNECT` tunnel to an allowed host.
    Connect,
    /// Not passed on: not allowed (403), not a request the gateway could read (malformed or oversized head or
    /// body), or no model API configured.
    Refused,
}

/// Who caused the answer a request got, or its end: only [`Cause::Upstream`] can make the model API's failure of
/// an agent ([`last_model_api_failure`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Cause {
    /// The host the request was passed on to: its response (whatever its status) and how its body ended, or no
    /// TCP connection, TLS handshake or HTTP exchange with it.
    Upstream,
    /// The gateway itself: a refusal, a bound (413, 431, 400), no model API configured, too many connections, the
    /// gateway stopping.
    Gateway,
    /// The client: its request body broke off, it went away before its answer was complete, it did not take its
    /// tunnel.
    Client,
    /// Records written before causes were recorded; never written now, never counted as the model API's failure.
    #[default]
    Unknown,
}

/// Token usage a model API reported in a response, normalised. `api` says whose convention the counts follow:
/// `openai_chat` and `openai_responses` count cached tokens inside `input_tokens` and reasoning tokens inside
/// `output_tokens`; `anthropic_messages` counts cache reads (`cached_input_tokens`) and cache writes
/// (`cache_creation_input_tokens`) beside `input_tokens`, and its `total_tokens` is input + output (as in
/// the runner's `usage`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TokenUsage {
    pub api: String,
    /// Input, output, cached input, reasoning and total tokens, the transcript's counts (same JSON fields).
    #[serde(flatten)]
    pub counts: Tokens,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cache_creation_input_tokens: Option<u64>,
}

/// One line of the records file: one request (or one tunnel), written when it ended.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Record {
    /// When the request arrived, ISO-8601 UTC.
    pub time: String,
    /// The same, in milliseconds since the Unix epoch.
    pub unix_ms: u64,
    pub mode: Mode,
    pub method: String,
    /// `host:port` the request went (or would have gone) to; empty when the head could not be read.
    pub host: String,
    /// The request's path without query; empty for `CONNECT`.
    pub path: String,
    /// The status sent to the client (200 for an established tunnel).
    pub status: u16,
    /// Who caused the answer (or the end): [`Cause`].
    #[serde(default)]
    pub cause: Cause,
    /// Body bytes from the client (tunnels: every byte from the client).
    pub request_bytes: u64,
    /// Body bytes to the client (tunnels: every byte to the client).
    pub response_bytes: u64,
    pub duration_ms: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub content_type: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub usage: Option<TokenUsage>,
    /// The request reached the upstream whole, but the tokens it cost could not be read: its response was
    /// encoded, ended early (cut by either side, or never came), or was a successful `POST` that reported no
    /// usage (`count_tokens` aside).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub unmetered: bool,
    /// Why the request failed or ended early (upstream unreachable, client gone, gateway stopped, …).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// A records file added up.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct UsageSummary {
    pub requests: u64,
    /// Requests in mode `refused`.
    pub refused: u64,
    /// Requests that recorded an error.
    pub failed: u64,
    /// Requests whose token cost could not be read ([`Record::unmetered`]).
    #[serde(default)]
    pub unmetered: u64,
    pub request_bytes: u64,
    pub response_bytes: u64,
    /// Of the bytes above, those through `CONNECT` tunnels and forwarded `http://` requests, both ways: traffic
    /// whose token usage the gateway cannot read.
    #[serde(default)]
    pub tunnel_bytes: u64,
    /// Responses that carried token usage; the token sums below are over these.
    pub responses_with_usage: u64,
    pub input_tokens: u64,
    pub output_tokens: u64,
    pub cached_input_tokens: u64,
    pub cache_creation_input_tokens: u64,
    pub reasoning_tokens: u64,
    pub total_tokens: u64,
    /// Lines that were not records (a line cut short when the runner died, a line over
    /// [`MAX_RECORD_LINE_BYTES`]).
    pub unreadable_lines: u64,
    /// Of the requests, those past the gateway's record cap: counted without a line of their own.
    #[serde(default)]
    pub overflowed: u64,
    /// The token sums are every token the agent's traffic cost: no bytes went through a tunnel or a forward
    /// (`tunnel_bytes` 0), no request was unmetered, every line was read, and the counters past the record cap
    /// are the gateway's final ones (not a crashed gateway's sidecar). False: the sums are a lower bound.
    /// Summaries written before this was recorded read false.
    #[serde(default)]
    pub complete: bool,
}

impl Default for UsageSummary {
    fn default() -> Self {
        Self {
            requests: 0,
            refused: 0,
            failed: 0,
            unmetered: 0,
            request_bytes: 0,
            response_bytes: 0,
            tunnel_bytes: 0,
            responses_with_usage: 0,
            input_tokens: 0,
            output_tokens: 0,
            cached_input_tokens: 0,
            cache_creation_input_tokens: 0,
            reasoning_tokens: 0,
            total_tokens: 0,
            unreadable_lines: 0,
            overflowed: 0,
            complete: true,
        }
    }
}

impl UsageSummary {
    fn add(&mut self, r: &Record) {
        self.requests += 1;
        self.refused += u64::from(r.mode == Mode::Refused);
        self.failed += u64::from(r.error.is_some());
        self.unmetered += u64::from(r.unmetered);
        self.request_bytes += r.request_bytes;
        self.response_bytes += r.response_bytes;
        if matches!(r.mode, Mode::Connect | Mode::Forward) {
            self.tunnel_bytes += r.request_bytes + r.response_bytes;
        }
        if let Some(u) = &r.usage {
            self.responses_with_usage += 1;
            self.input_tokens += u.counts.input_tokens.unwrap_or(0);
            self.output_tokens += u.counts.output_tokens.unwrap_or(0);
            self.cached_input_tokens += u.counts.cached_input_tokens.unwrap_or(0);
            self.cache_creation_input_tokens += u.cache_creation_input_tokens.unwrap_or(0);
            self.reasoning_tokens += u.counts.reasoning_tokens.unwrap_or(0);
            self.total_tokens += u.counts.total_tokens.unwrap_or(0);
        }
    }

    fn merge(&mut self, o: &UsageSummary) {
        self.requests += o.requests;
        self.refused += o.refused;
        self.failed += o.failed;
        self.unmetered += o.unmetered;
        self.request_bytes += o.request_bytes;
        self.response_bytes += o.response_bytes;
        self.tunnel_bytes += o.tunnel_bytes;
        self.responses_with_usage += o.responses_with_usage;
        self.input_tokens += o.input_tokens;
        self.output_tokens += o.output_tokens;
        self.cached_input_tokens += o.cached_input_tokens;
        self.cache_creation_input_tokens += o.cache_creation_input_tokens;
        self.reasoning_tokens += o.reasoning_tokens;
        self.total_tokens += o.total_tokens;
        self.unreadable_lines += o.unreadable_lines;
        self.overflowed += o.overflowed;
    }
}

/// The tag of an [`Overflow`] line: `"kind": "overflow"`, which no [`Record`] has.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OverflowKind {
    #[default]
    Overflow,
}

/// What the gateway counted of the requests past its record cap: the records file's last line once it stopped
/// (`{"kind":"overflow","requests":…,"by_status":{"403":…},…}`), and meanwhile its sidecar file
/// ([`overflow_sidecar`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Overflow {
    pub kind: OverflowKind,
    /// The requests' sums, as [`summarize`] makes them (`overflowed` = `requests`).
    #[serde(flatten)]
    pub summary: UsageSummary,
    /// Requests per status sent.
    pub by_status: BTreeMap<u16, u64>,
    /// Of the requests passed on (modes `reverse` and `forward`), the one that arrived last, whole.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_passed_on: Option<Record>,
}

impl Overflow {
    fn add(&mut self, r: Record) {
        self.summary.add(&r);
        self.summary.overflowed += 1;
        self.summary.complete = self.summary.tunnel_bytes == 0 && self.summary.unmetered == 0;
        *self.by_status.entry(r.status).or_default() += 1;
        keep_if_last_passed_on(&mut self.last_passed_on, &r);
    }
}

/// `r` becomes `last` when it was passed on (modes `reverse` and `forward`) and arrived no earlier.
fn keep_if_last_passed_on(last: &mut Option<Record>, r: &Record) {
    if matches!(r.mode, Mode::Reverse | Mode::Forward) && last.as_ref().is_none_or(|l| r.unix_ms >= l.unix_ms) {
        *last = Some(r.clone());
    }
}

/// Where a gateway keeps its overflow counters while it runs: beside `records`, `model_api.jsonl` →
/// `model_api.overflow.json`.
pub fn overflow_sidecar(records: &Path) -> PathBuf {
    records.with_extension("overflow.json")
}

/// A records file read once: its sums, and the last request passed on.
#[derive(Default)]
struct Scan {
    summary: UsageSummary,
    last_passed_on: Option<Record>,
}

impl Scan {
    fn passed_on(&mut self, r: &Record) {
        keep_if_last_passed_on(&mut self.last_passed_on, r);
    }

    fn overflow(&mut self, o: &Overflow) {
        self.summary.merge(&o.summary);
        if let Some(r) = &o.last_passed_on {
            self.passed_on(r);
        }
    }
}

/// Reads a records file in one streamed pass (never whole: it is bounded by the gateway, but not by what a
/// crashed gateway left), with the overflow line or, without one, the sidecar a crashed gateway left.
fn scan(records: &Path) -> std::io::Result<Scan> {
    let mut reader = BufReader::new(std::fs::File::open(records)?);
    let mut s = Scan::default();
    let (mut line, mut final_counters) = (Vec::new(), false);
    while let Some(whole) = next_line(&mut reader, &mut line, MAX_RECORD_LINE_BYTES)? {
        if !whole {
            s.summary.unreadable_lines += 1;
            continue;
        }
        if line.iter().all(u8::is_ascii_whitespace) {
            continue;
        }
        if let Ok(r) = serde_json::from_slice::<Record>(&line) {
            s.summary.add(&r);
            s.passed_on(&r);
        } else if let Ok(o) = serde_json::from_slice::<Overflow>(&line) {
            s.overflow(&o);
            final_counters = true;
        } else {
            s.summary.unreadable_lines += 1;
        }
    }
    let mut stale = false;
    if !final_counters {
        let mut text = String::new();
        let read = std::fs::File::open(overflow_sidecar(records)).and_then(|f| f.take(1 << 20).read_to_string(&mut text));
        if read.is_ok() {
            match serde_json::from_str::<Overflow>(&text) {
                Ok(o) => s.overflow(&o),
                Err(_) => s.summary.unreadable_lines += 1,
            }
            stale = true;
        }
    }
    let t = &s.summary;
    s.summary.complete = t.tunnel_bytes == 0 && t.unmetered == 0 && t.unreadable_lines == 0 && !stale;
    Ok(s)
}

/// The next line of `r` into `line`, without its newline: `Some(true)`, or `Some(false)` for a line over `max`
/// bytes (skipped, `line` left empty); `None` at the end.
fn next_line(r: &mut impl BufRead, line: &mut Vec<u8>, max: usize) -> std::io::Result<Option<bool>> {
    line.clear();
    let n = r.by_ref().take(max as u64 + 1).read_until(b'\n', line)?;
    if n == 0 {
        return Ok(None);
    }
    if line.last() == Some(&b'\n') {
        line.pop();
        return Ok(Some(true));
    }
    if line.len() <= max {
        return Ok(Some(true));
    }
    line.clear();
    loop {
        let buf = r.fill_buf()?;
        if buf.is_empty() {
            break;
        }
        if let Some(i) = buf.iter().position(|b| *b == b'\n') {
            r.consume(i + 1);
            break;
        }
        let n = buf.len();
        r.consume(n);
    }
    Ok(Some(false))
}

/// Adds up a gateway's records file (its overflow counters included).
pub fn summarize(records: &Path) -> std::io::Result<UsageSummary> {
    Ok(scan(records)?.summary)
}

/// Why the model API failed the agent, if it did: the last request the gateway passed on (to the upstream or an
/// allowed host; past the record cap too) was answered 429 or 5xx by that host, or its response broke off there,
/// or no connection or handshake with it succeeded ([`Cause::Upstream`]). What the agent's side or the gateway
/// does (a refused host or path, a client that went away, a request body cut short, an unreadable head, a 4xx,
/// no model API configured) is not a failure of the model API: only this may make an agent that quit without
/// `finish_episode` INVALID.
pub fn last_model_api_failure(records: &Path) -> Option<String> {
    let last = scan(records).ok()?.last_passed_on?;
    let failed = last.status == 429 || last.status >= 500 || last.error.is_some();
    (last.cause == Cause::Upstream && failed).then(|| {
        let why = last.error.as_deref().map(|e| format!(": {e}")).unwrap_or_default();
        format!("the model API answered {} to {} {}{why}", last.status, last.method, last.path)
    })
}

/// A running gateway; stopped by [`Gateway::stop`] or when dropped.
pub struct Gateway {
    running: Running,
    shared: Arc<Shared>,
}

impl Gateway {
    /// Stops accepting, cuts what is in flight (recorded with an error), waits for the gateway's thread and
    /// appends the overflow counters, if any, as the records file's last line.
    pub fn stop(mut self) {
        self.shut();
    }

    fn shut(&mut self) {
        self.shared.stopping.store(true, Ordering::SeqCst);
        self.running.stop();
        self.shared.close_log();
    }
}

impl Drop for Gateway {
    fn drop(&mut self) {
        self.shut();
    }
}

/// A running Unix-to-TCP relay; stopped by [`Relay::stop`] or when dropped.
pub struct Relay {
    running: Running,
}

impl Relay {
    /// Stops accepting, cuts the relayed connections and waits for the relay's thread.
    pub fn stop(mut self) {
        self.running.stop();
    }
}

/// Serves the gateway on `listener` (a bound Unix socket; the caller removes its file) until stopped.
pub fn start(listener: StdUnixListener, cfg: GatewayConfig) -> Result<Gateway, GatewayError> {
    start_capped(listener, cfg, MAX_CONNECTIONS)
}

fn start_capped(listener: StdUnixListener, cfg: GatewayConfig, max_connections: usize) -> Result<Gateway, GatewayError> {
    let upstream = cfg.upstream.as_ref().map(parse_upstream).transpose()?;
    let tls = match &upstream {
        Some(u) if u.tls => Some(tls_connector()?),
        _ => None,
    };
    let file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&cfg.records)
        .map_err(|source| GatewayError::Records { path: cfg.records.clone(), source })?;
    let sidecar = overflow_sidecar(&cfg.records);
    // A sidecar left by an earlier gateway on this file would be read as this one's.
    let _ = std::fs::remove_file(&sidecar);
    let log = Log { file, sidecar, max_records: cfg.max_records as u64, written: 0, overflow: None, dirty: false, sidecar_at: None, closed: false };
    let allowed = cfg.allowed.iter().map(|(h, p)| (normal_host(h), *p)).collect();
    let shared = Arc::new(Shared { upstream, routes: cfg.routes, allowed, tls, log: Mutex::new(log), stopping: AtomicBool::new(false) });
    let serving = shared.clone();
    let running = Running::spawn("netgate", listener, move |listener| async move {
        let (on_full, flushing) = (serving.clone(), serving.clone());
        let accept = accept_loop(
            listener,
            max_connections,
            move |stream, slot| serve_gateway_connection(serving.clone(), stream, slot),
            move |stream| too_many_connections(&on_full, stream),
        );
        // Counters of a flood that went quiet reach the sidecar too.
        let flush = async move {
            let mut tick = tokio::time::interval(SIDECAR_EVERY);
            loop {
                tick.tick().await;
                flushing.flush_sidecar();
            }
        };
        tokio::select! {
            _ = accept => {}
            _ = flush => {}
        }
    })?;
    Ok(Gateway { running, shared })
}

/// Relays each connection accepted on `listener` to a new TCP connection to `target`, bytes both ways (a side's
/// end of stream is passed on as a half-close), until stopped. For the episode's MCP endpoint.
pub fn relay_unix_to_tcp(listener: StdUnixListener, target: SocketAddr) -> Result<Relay, GatewayError> {
    relay_unix_to_tcp_from(listener, target, None)
}

/// [`relay_unix_to_tcp`] with the outgoing connections bound to `source` (an address of this machine). Every
/// address of 127.0.0.0/8 is loopback on Linux without any set-up, so each agent's relay can come from an
/// address of its own and the server's per-address connection caps hold per agent, not for all agents at once.
/// Each connection is served by a task of its own; past [`MAX_CONNECTIONS`], a new one takes the place of the one
/// whose bytes moved last the longest ago.
pub fn relay_unix_to_tcp_from(listener: StdUnixListener, target: SocketAddr, source: Option<IpAddr>) -> Result<Relay, GatewayError> {
    relay_capped(listener, target, source, MAX_CONNECTIONS)
}

fn relay_capped(listener: StdUnixListener, target: SocketAddr, source: Option<IpAddr>, max_connections: usize) -> Result<Relay, GatewayError> {
    let running = Running::spawn("netgate-relay", listener, move |listener| {
        let relay = move |stream: UnixStream, slot: Arc<Slot>| async move {
            if let Ok(Ok(tcp)) = tokio::time::timeout(CONNECT_TIMEOUT, connect_from(source, target)).await {
                let _ = tcp.set_nodelay(true);
                let mut client = Touch { inner: stream, slot: slot.clone() };
                let mut server = Touch { inner: tcp, slot };
                let _ = tokio::io::copy_bidirectional(&mut client, &mut server).await;
            }
        };
        // Every relayed connection can give its place up: there is always one to take.
        accept_loop(listener, max_connections, relay, drop)
    })?;
    Ok(Relay { running })
}

async fn connect_from(source: Option<IpAddr>, target: SocketAddr) -> std::io::Result<TcpStream> {
    let Some(source) = source.filter(|s| s.is_ipv4() == target.is_ipv4()) else { return TcpStream::connect(target).await };
    let socket = if target.is_ipv4() { tokio::net::TcpSocket::new_v4()? } else { tokio::net::TcpSocket::new_v6()? };
    socket.bind(SocketAddr::new(source, 0))?;
    socket.connect(target).await
}

/// A thread running a current-thread runtime that serves one listener until told to stop.
struct Running {
    stop: Option<oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Running {
    fn spawn<F, Fut>(name: &str, listener: StdUnixListener, serve: F) -> Result<Self, GatewayError>
    where
        F: FnOnce(UnixListener) -> Fut + Send + 'static,
        Fut: Future<Output = ()> + 'static,
    {
        listener.set_nonblocking(true)?;
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        let listener = {
            let _in_runtime = rt.enter();
            UnixListener::from_std(listener)?
        };
        let (stop, stopped) = oneshot::channel::<()>();
        let thread = std::thread::Builder::new().name(name.to_owned()).spawn(move || {
            rt.block_on(async move {
                tokio::select! {
                    _ = stopped => {}
                    () = serve(listener) => {}
                }
            });
            // Drops every task (their records are written as they drop), then waits a little for name lookups.
            rt.shutdown_timeout(STOP_GRACE);
        })?;
        Ok(Self { stop: Some(stop), thread: Some(thread) })
    }

    fn stop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The connections a socket serves, by age, so that one over the cap can take an idle one's place instead of
/// waiting in the backlog behind the agent's own slow connections.
struct Conns {
    cap: usize,
    epoch: Instant,
    next_id: AtomicU64,
    open: Mutex<BTreeMap<u64, Arc<Conn>>>,
}

/// One served connection.
struct Conn {
    /// Requests and tunnels in progress; 0: the connection waits for a request head and may be closed to make
    /// room (the relay's connections never count any).
    busy: AtomicU64,
    /// When a request began or ended, or bytes moved, in ms since [`Conns::epoch`].
    active_ms: AtomicU64,
    abort: OnceLock<tokio::task::AbortHandle>,
}

/// A connection's place among [`Conns`], given up when the last holder (its task, its tunnel) drops it.
struct Slot {
    conns: Arc<Conns>,
    id: u64,
    conn: Arc<Conn>,
}

impl Slot {
    fn touch(&self) {
        self.conn.active_ms.store(self.conns.epoch.elapsed().as_millis() as u64, Ordering::Relaxed);
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        if let Ok(mut open) = self.conns.open.lock() {
            open.remove(&self.id);
        }
    }
}

impl Conns {
    /// A place for a new connection: free, or taken from the open connection idle the longest (closed now);
    /// None when every one is busy.
    fn admit(self: &Arc<Self>) -> Option<Arc<Slot>> {
        let mut open = self.open.lock().ok()?;
        if open.len() >= self.cap {
            let victim = open
                .iter()
                .filter(|(_, c)| c.busy.load(Ordering::Relaxed) == 0 && c.abort.get().is_some())
                .min_by_key(|(id, c)| (c.active_ms.load(Ordering::Relaxed), **id))
                .map(|(id, _)| *id)?;
            if let Some(c) = open.remove(&victim)
                && let Some(a) = c.abort.get()
            {
                a.abort();
            }
        }
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let conn = Arc::new(Conn {
            busy: AtomicU64::new(0),
            active_ms: AtomicU64::new(self.epoch.elapsed().as_millis() as u64),
            abort: OnceLock::new(),
        });
        open.insert(id, conn.clone());
        Some(Arc::new(Slot { conns: self.clone(), id, conn }))
    }
}

/// Accepts without pause, each connection served by a task of its own: `handle` with a place among `cap`, or
/// `full` when every place is busy.
async fn accept_loop<H, HF, F>(listener: UnixListener, cap: usize, handle: H, full: F)
where
    H: Fn(UnixStream, Arc<Slot>) -> HF,
    HF: Future<Output = ()> + Send + 'static,
    F: Fn(UnixStream),
{
    let conns = Arc::new(Conns { cap: cap.max(1), epoch: Instant::now(), next_id: AtomicU64::new(0), open: Mutex::new(BTreeMap::new()) });
    loop {
        match listener.accept().await {
            Ok((stream, _)) => match conns.admit() {
                Some(slot) => {
                    let conn = slot.conn.clone();
                    let task = tokio::spawn(handle(stream, slot));
                    let _ = conn.abort.set(task.abort_handle());
                }
                None => full(stream),
            },
            // Out of descriptors or the like: wait rather than spin.
            Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    }
}

/// A request or tunnel in progress on a connection: it is not idle while this lives.
struct Busy(Arc<Slot>);

impl Busy {
    fn new(slot: Arc<Slot>) -> Self {
        slot.conn.busy.fetch_add(1, Ordering::Relaxed);
        slot.touch();
        Self(slot)
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        self.0.touch();
        self.0.conn.busy.fetch_sub(1, Ordering::Relaxed);
    }
}

/// A relayed side, marking its connection active whenever bytes come from it.
struct Touch<T> {
    inner: T,
    slot: Arc<Slot>,
}

impl<T: AsyncRead + Unpin> AsyncRead for Touch<T> {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<std::io::Result<()>> {
        let r = Pin::new(&mut self.inner).poll_read(cx, buf);
        if r.is_ready() {
            self.slot.touch();
        }
        r
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Touch<T> {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// The upstream of reverse-proxied requests.
#[derive(Debug)]
struct Upstream {
    tls: bool,
    /// Without IPv6 brackets, as connected to and as the TLS server name.
    host: String,
    port: u16,
    /// The `Host` header.
    authority: String,
}

fn parse_upstream(url: &url::Url) -> Result<Upstream, GatewayError> {
    let bad = || GatewayError::Upstream(format!("{}://{}{}", url.scheme(), url.host_str().unwrap_or_default(), url.path()));
    let tls = match url.scheme() {
        "https" => true,
        "http" => false,
        _ => return Err(bad()),
    };
    let host = url.host_str().filter(|h| !h.is_empty()).ok_or_else(bad)?;
    if !url.username().is_empty() || url.password().is_some() {
        return Err(bad());
    }
    let port = url.port_or_known_default().ok_or_else(bad)?;
    // The `Host` header: the URL's host, with its port where that is not the scheme's default.
    let authority = match url.port() {
        Some(p) => format!("{host}:{p}"),
        None => host.to_owned(),
    };
    Ok(Upstream { tls, host: normal_host(host), port, authority })
}

fn normal_host(h: &str) -> String {
    h.trim().trim_start_matches('[').trim_end_matches(']').to_ascii_lowercase()
}

fn tls_connector() -> Result<tokio_rustls::TlsConnector, GatewayError> {
    let found = rustls_native_certs::load_native_certs();
    let mut roots = rustls::RootCertStore::empty();
    let (added, _) = roots.add_parsable_certificates(found.certs);
    if added == 0 {
        let why = found.errors.first().map(|e| format!(": {e}")).unwrap_or_default();
        return Err(GatewayError::Tls(format!("no trusted root certificates found on this machine{why}")));
    }
    let provider = Arc::new(rustls::crypto::aws_lc_rs::default_provider());
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| GatewayError::Tls(e.to_string()))?
        .with_root_certificates(roots)
        .with_no_client_auth();
    Ok(tokio_rustls::TlsConnector::from(Arc::new(config)))
}

struct Shared {
    upstream: Option<Upstream>,
    routes: Vec<Route>,
    allowed: Vec<(String, u16)>,
    tls: Option<tokio_rustls::TlsConnector>,
    log: Mutex<Log>,
    /// Set before the gateway stops: what is cut from then on, the gateway cut.
    stopping: AtomicBool,
}

impl Shared {
    fn allows(&self, host: &str, port: u16) -> bool {
        let host = normal_host(host);
        self.allowed.iter().any(|(h, p)| *h == host && *p == port)
    }

    /// The model API's own host:port, which only the reverse proxy reaches (through the routes, metered).
    fn is_upstream(&self, host: &str, port: u16) -> bool {
        self.upstream.as_ref().is_some_and(|u| u.host == normal_host(host) && u.port == port)
    }

    fn routes_allow(&self, method: &Method, path: &str) -> bool {
        self.routes.iter().any(|r| r.method == *method && r.path == path)
    }

    fn record(&self, r: Record) {
        if let Ok(mut log) = self.log.lock() {
            log.add(r);
        }
    }

    fn flush_sidecar(&self) {
        if let Ok(mut log) = self.log.lock() {
            log.flush_sidecar();
        }
    }

    fn close_log(&self) {
        if let Ok(mut log) = self.log.lock() {
            log.close();
        }
    }
}

/// The records file: whole records up to the cap, counters past it.
struct Log {
    file: std::fs::File,
    sidecar: PathBuf,
    max_records: u64,
    written: u64,
    overflow: Option<Overflow>,
    /// The counters changed since the sidecar was last written.
    dirty: bool,
    sidecar_at: Option<Instant>,
    closed: bool,
}

impl Log {
    /// Appends one record, or counts it past the cap (a write error loses that line; the proxying goes on).
    fn add(&mut self, r: Record) {
        if self.written < self.max_records && self.overflow.is_none() {
            self.written += 1;
            if let Ok(mut line) = serde_json::to_vec(&r) {
                line.push(b'\n');
                let _ = self.file.write_all(&line);
            }
            return;
        }
        self.overflow.get_or_insert_with(Overflow::default).add(r);
        self.dirty = true;
        // The first time at once; then every [`SIDECAR_EVERY`], by the gateway's ticker.
        if self.sidecar_at.is_none() {
            self.flush_sidecar();
        }
    }

    /// Rewrites the sidecar (temporary file, then rename: never half a file) when the counters changed.
    fn flush_sidecar(&mut self) {
        let Some(o) = &self.overflow else { return };
        if self.closed || !self.dirty {
            return;
        }
        let Ok(text) = serde_json::to_vec(o) else { return };
        let tmp = self.sidecar.with_extension("json.tmp");
        if std::fs::write(&tmp, text).and_then(|()| std::fs::rename(&tmp, &self.sidecar)).is_ok() {
            self.dirty = false;
        }
        self.sidecar_at = Some(Instant::now());
    }

    /// The counters as the file's last line, once; the sidecar then goes.
    fn close(&mut self) {
        if self.closed {
            return;
        }
        if let Some(o) = &self.overflow
            && let Ok(mut line) = serde_json::to_vec(o)
        {
            line.push(b'\n');
            if self.file.write_all(&line).and_then(|()| self.file.sync_data()).is_ok() {
                let _ = std::fs::remove_file(&self.sidecar);
            } else {
                self.flush_sidecar();
            }
        }
        self.closed = true;
    }
}

/// Which side of a tunnel failed first.
const FAULT_CLIENT: u8 = 1;
const FAULT_REMOTE: u8 = 2;

/// Bytes each way of one request or tunnel, and what broke it.
#[derive(Default)]
struct Counters {
    from_client: AtomicU64,
    to_client: AtomicU64,
    /// The client's request body was passed on to its end.
    body_complete: AtomicBool,
    /// The client's request body could not be passed on whole.
    body_fault: Mutex<Option<BodyFault>>,
    /// A tunnel's first failing side ([`FAULT_CLIENT`], [`FAULT_REMOTE`]), 0 while none failed.
    tunnel_fault: AtomicU8,
}

impl Counters {
    fn body_fault(&self) -> Option<BodyFault> {
        self.body_fault.lock().ok().and_then(|f| f.clone())
    }

    fn set_body_fault(&self, f: BodyFault) {
        if let Ok(mut slot) = self.body_fault.lock() {
            slot.get_or_insert(f);
        }
    }
}

/// Why a request body was not passed on whole.
#[derive(Debug, Clone)]
enum BodyFault {
    /// Over [`MAX_REQUEST_BODY_BYTES`].
    TooLarge,
    /// The client's stream broke off (shorter than it declared, connection gone).
    Client(String),
}

fn clipped(s: &str, max: usize) -> String {
    if s.len() <= max {
        return s.to_owned();
    }
    let mut end = max;
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    s[..end].to_owned()
}

/// A request being served; its record is written once, when it ends (or when it is dropped unfinished).
struct Pending {
    shared: Arc<Shared>,
    at: SystemTime,
    started: Instant,
    mode: Mode,
    method: String,
    host: String,
    path: String,
    status: u16,
    cause: Cause,
    bytes: Arc<Counters>,
    content_type: Option<String>,
    capture: Option<Capture>,
    error: Option<String>,
    /// The request went to the upstream (its body may still have been cut).
    sent: bool,
    done: bool,
}

impl Pending {
    fn new(shared: Arc<Shared>, method: &str, path: &str) -> Self {
        Self {
            shared,
            at: SystemTime::now(),
            started: Instant::now(),
            mode: Mode::Refused,
            method: clipped(method, 32),
            host: String::new(),
            path: clipped(path, 512),
            status: 0,
            cause: Cause::Gateway,
            bytes: Arc::new(Counters::default()),
            content_type: None,
            capture: None,
            error: None,
            sent: false,
            done: false,
        }
    }

    fn set_host(&mut self, host: &str, port: u16) {
        let host = normal_host(host);
        self.host = clipped(&if host.contains(':') { format!("[{host}]:{port}") } else { format!("{host}:{port}") }, 300);
    }

    /// Whether the tokens this request cost are unknown: it reached the upstream whole (a cut request costs no
    /// model call), and its response was
    /// encoded, ended early, or (a successful `POST`, `count_tokens` aside) reported no usage.
    fn unmetered(&self, has_usage: bool) -> bool {
        if !self.sent || !self.bytes.body_complete.load(Ordering::Relaxed) || self.bytes.body_fault().is_some() {
            return false;
        }
        if self.error.is_some() {
            return true;
        }
        self.capture.as_ref().is_none_or(|c| {
            let silent_success = self.method == "POST" && (200..300).contains(&self.status) && !self.path.ends_with("/count_tokens");
            c.encoded || (silent_success && !has_usage)
        })
    }

    fn finish(&mut self) {
        if self.done {
            return;
        }
        self.done = true;
        let usage = self.capture.as_ref().and_then(Capture::usage);
        let unmetered = self.unmetered(usage.is_some());
        let r = Record {
            time: iso_from_system_time(self.at),
            unix_ms: self.at.duration_since(UNIX_EPOCH).map(|d| d.as_millis() as u64).unwrap_or(0),
            mode: self.mode,
            method: self.method.clone(),
            host: self.host.clone(),
            path: self.path.clone(),
            status: self.status,
            cause: self.cause,
            request_bytes: self.bytes.from_client.load(Ordering::Relaxed),
            response_bytes: self.bytes.to_client.load(Ordering::Relaxed),
            duration_ms: self.started.elapsed().as_millis() as u64,
            content_type: self.content_type.clone(),
            usage,
            unmetered,
            error: self.error.as_ref().map(|e| clipped(e, 500)),
        };
        self.shared.record(r);
    }

    /// A response the gateway makes itself (for `cause`), recorded now.
    fn answer(mut self, status: StatusCode, cause: Cause, message: &str) -> Response<GateBody> {
        self.status = status.as_u16();
        self.cause = cause;
        if status.is_client_error() || status.is_server_error() {
            self.error.get_or_insert_with(|| message.to_owned());
        }
        let text = format!("libero-agent gateway: {message}\n");
        self.bytes.to_client.store(text.len() as u64, Ordering::Relaxed);
        self.finish();
        text_response(status, text)
    }

    /// Not passed on: the gateway's answer.
    fn refuse(mut self, status: StatusCode, message: &str) -> Response<GateBody> {
        self.mode = Mode::Refused;
        self.answer(status, Cause::Gateway, message)
    }

    /// The upstream could not be reached or did not answer.
    fn unreachable(self, status: StatusCode, message: &str) -> Response<GateBody> {
        self.answer(status, Cause::Upstream, message)
    }

    /// The request body could not be passed on whole: the client's doing, or over the gateway's bound.
    fn body_cut(self, fault: BodyFault) -> Response<GateBody> {
        match fault {
            BodyFault::TooLarge => {
                self.answer(StatusCode::PAYLOAD_TOO_LARGE, Cause::Gateway, &format!("request body over {} MiB", MAX_REQUEST_BODY_BYTES >> 20))
            }
            BodyFault::Client(why) => self.answer(StatusCode::BAD_REQUEST, Cause::Client, &format!("client: the request body broke off: {why}")),
        }
    }
}

impl Drop for Pending {
    fn drop(&mut self) {
        if !self.done {
            if self.error.is_none() {
                let (cause, why) = if self.shared.stopping.load(Ordering::SeqCst) {
                    (Cause::Gateway, "ended early: the gateway stopped")
                } else {
                    (Cause::Client, "ended early: the client went away")
                };
                self.cause = cause;
                self.error = Some(why.to_owned());
            }
            self.finish();
        }
    }
}

fn text_response(status: StatusCode, text: String) -> Response<GateBody> {
    let mut r = Response::new(GateBody::Full(Some(Bytes::from(text))));
    *r.status_mut() = status;
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("text/plain; charset=utf-8"));
    // The gateway's own answers are refusals and failures: the connection ends with them.
    r.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    r
}

/// Every place is held by a request or a tunnel in progress: 503 at once (one write to a fresh socket's empty
/// buffer, never waited on), recorded.
fn too_many_connections(shared: &Arc<Shared>, stream: UnixStream) {
    let why = "too many connections at once, none of them idle".to_owned();
    let body = format!("libero-agent gateway: {why}\n");
    let head = format!(
        "HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    // Out of the runtime (tokio's readiness of a fresh socket is not known yet): a plain non-blocking write.
    if let Ok(mut s) = stream.into_std() {
        let _ = s.write_all(format!("{head}{body}").as_bytes());
        let _ = s.shutdown(std::net::Shutdown::Write);
    }
    let mut p = Pending::new(shared.clone(), "", "");
    p.status = 503;
    p.error = Some(why);
    p.bytes.to_client.store(body.len() as u64, Ordering::Relaxed);
    p.finish();
}

async fn serve_gateway_connection(shared: Arc<Shared>, stream: UnixStream, slot: Arc<Slot>) {
    let (svc_shared, svc_slot) = (shared.clone(), slot.clone());
    let svc = hyper::service::service_fn(move |req| {
        let (shared, slot) = (svc_shared.clone(), svc_slot.clone());
        async move {
            // Busy from the head until the response's body is done (or dropped).
            let busy = Busy::new(slot.clone());
            let resp = handle(shared, req, &slot).await;
            Ok::<_, Infallible>(resp.map(|body| Served { body, _busy: busy }))
        }
    });
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder.timer(TokioTimer::new()).header_read_timeout(HEADER_READ_TIMEOUT).max_header_size(MAX_HEAD_BYTES);
    if let Err(e) = builder.serve_connection(TokioIo::new(stream), svc).with_upgrades().await
        && e.is_parse()
    {
        // hyper has answered 431 (or 400) itself; a timed-out or vanished client is not a request.
        let mut p = Pending::new(shared, "", "");
        let (status, why) = if e.is_parse_too_large() {
            (431, format!("request head over {} KiB", MAX_HEAD_BYTES >> 10))
        } else {
            (400, format!("unreadable request head: {e}"))
        };
        p.status = status;
        p.error = Some(why);
        p.finish();
    }
    drop(slot);
}

/// Why an origin-form path is refused before routes are looked at: what an upstream or a server behind it could
/// read as another path (dot segments, empty segments, encoded dots or slashes, backslashes).
fn suspicious_path(path: &str) -> Option<&'static str> {
    let lower = path.to_ascii_lowercase();
    if lower.contains("..") || lower.contains("//") || lower.contains('\\') || lower.contains('#') {
        return Some("dot segments, empty segments, backslashes and fragments are not passed on");
    }
    if ["%2e", "%2f", "%5c", "%00"].iter().any(|e| lower.contains(e)) {
        return Some("encoded dots, slashes and backslashes are not passed on");
    }
    None
}

async fn handle(shared: Arc<Shared>, req: Request<Incoming>, slot: &Arc<Slot>) -> Response<GateBody> {
    let mut p = Pending::new(shared.clone(), req.method().as_str(), req.uri().path());
    if req.method() == Method::CONNECT {
        p.path.clear();
        return connect(shared, req, p, slot.clone()).await;
    }
    if let Some(scheme) = req.uri().scheme_str() {
        let Some(authority) = req.uri().authority().cloned() else {
            return p.refuse(StatusCode::BAD_REQUEST, "an absolute-form request needs a host");
        };
        let port = authority.port_u16().unwrap_or(80);
        p.set_host(authority.host(), port);
        if !scheme.eq_ignore_ascii_case("http") {
            return p.refuse(StatusCode::BAD_REQUEST, "only http:// is forwarded; https goes through CONNECT");
        }
        if shared.is_upstream(authority.host(), port) {
            return p.refuse(StatusCode::FORBIDDEN, "the model API is reached through the gateway's base URL, not through the proxy");
        }
        if !shared.allows(authority.host(), port) {
            let message = format!("{} is not reachable from the sandbox", p.host);
            return p.refuse(StatusCode::FORBIDDEN, &message);
        }
        p.mode = Mode::Forward;
        let target = Target { tls: false, host: normal_host(authority.host()), port, authority: authority.as_str().to_owned() };
        return proxy(&shared, req, target, p).await;
    }
    let path = req.uri().path();
    if !path.starts_with('/') {
        return p.refuse(StatusCode::BAD_REQUEST, "the request target must be a path");
    }
    let Some(u) = &shared.upstream else {
        return p.refuse(StatusCode::SERVICE_UNAVAILABLE, "no model API is configured for this sandbox");
    };
    p.set_host(&u.host, u.port);
    if let Some(why) = suspicious_path(path) {
        let message = format!("{} {}: {why}", p.method, p.path);
        return p.refuse(StatusCode::FORBIDDEN, &message);
    }
    if req.headers().contains_key(header::UPGRADE) {
        return p.refuse(StatusCode::UPGRADE_REQUIRED, "the gateway carries no WebSockets or other upgrades: use plain HTTP");
    }
    if !shared.routes_allow(req.method(), path) {
        let message = format!("{} {} is not an endpoint of this harness's model API", p.method, p.path);
        return p.refuse(StatusCode::FORBIDDEN, &message);
    }
    p.mode = Mode::Reverse;
    let target = Target { tls: u.tls, host: u.host.clone(), port: u.port, authority: u.authority.clone() };
    proxy(&shared, req, target, p).await
}

async fn connect(shared: Arc<Shared>, mut req: Request<Incoming>, mut p: Pending, slot: Arc<Slot>) -> Response<GateBody> {
    let Some((host, port)) = req.uri().authority().and_then(|a| Some((normal_host(a.host()), a.port_u16()?))) else {
        return p.refuse(StatusCode::BAD_REQUEST, "CONNECT needs host:port");
    };
    p.set_host(&host, port);
    if shared.is_upstream(&host, port) {
        return p.refuse(StatusCode::FORBIDDEN, "the model API is reached through the gateway's base URL, not a tunnel");
    }
    if !shared.allows(&host, port) {
        let message = format!("{} is not reachable from the sandbox", p.host);
        return p.refuse(StatusCode::FORBIDDEN, &message);
    }
    p.mode = Mode::Connect;
    let tcp = match tokio::time::timeout(CONNECT_TIMEOUT, TcpStream::connect((host.as_str(), port))).await {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => {
            let message = format!("cannot connect to {}: {e}", p.host);
            return p.unreachable(StatusCode::BAD_GATEWAY, &message);
        }
        Err(_) => {
            let message = format!("no connection to {} within 30 s", p.host);
            return p.unreachable(StatusCode::GATEWAY_TIMEOUT, &message);
        }
    };
    let _ = tcp.set_nodelay(true);
    let on_upgrade = hyper::upgrade::on(&mut req);
    p.status = 200;
    p.cause = Cause::Upstream;
    // The tunnel outlives the connection's HTTP handling, and keeps its place busy.
    let busy = Busy::new(slot);
    tokio::spawn(async move {
        let _busy = busy;
        match on_upgrade.await {
            Ok(upgraded) => {
                let mut client = Counted { inner: TokioIo::new(upgraded), bytes: p.bytes.clone(), side: FAULT_CLIENT };
                let mut server = Counted { inner: tcp, bytes: p.bytes.clone(), side: FAULT_REMOTE };
                if let Err(e) = tokio::io::copy_bidirectional(&mut client, &mut server).await {
                    p.error = Some(format!("tunnel: {e}"));
                    if p.bytes.tunnel_fault.load(Ordering::Relaxed) == FAULT_CLIENT {
                        p.cause = Cause::Client;
                    }
                }
            }
            Err(e) => {
                p.error = Some(format!("the client did not take the tunnel: {e}"));
                p.cause = Cause::Client;
            }
        }
        p.finish();
    });
    Response::new(GateBody::Full(None))
}

/// Where a proxied request goes.
struct Target {
    tls: bool,
    host: String,
    port: u16,
    authority: String,
}

trait Io: AsyncRead + AsyncWrite + Send + Unpin {}
impl<T: AsyncRead + AsyncWrite + Send + Unpin> Io for T {}

async fn open(shared: &Shared, t: &Target) -> Result<Box<dyn Io>, String> {
    let name = format!("{}:{}", t.host, t.port);
    let tcp = match tokio::time::timeout(CONNECT_TIMEOUT, TcpStream::connect((t.host.as_str(), t.port))).await {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => return Err(format!("cannot connect to {name}: {e}")),
        Err(_) => return Err(format!("no connection to {name} within 30 s")),
    };
    let _ = tcp.set_nodelay(true);
    if !t.tls {
        return Ok(Box::new(tcp));
    }
    let tls = shared.tls.as_ref().ok_or_else(|| "no TLS configuration".to_owned())?;
    let server_name = rustls::pki_types::ServerName::try_from(t.host.clone()).map_err(|e| format!("{name}: {e}"))?;
    match tokio::time::timeout(CONNECT_TIMEOUT, tls.connect(server_name, tcp)).await {
        Ok(Ok(s)) => Ok(Box::new(s)),
        Ok(Err(e)) => Err(format!("TLS with {name}: {e}")),
        Err(_) => Err(format!("no TLS handshake with {name} within 30 s")),
    }
}

/// Headers that describe one connection, not the message (RFC 9110 §7.6.1), and those named by `Connection`.
fn strip_hop_by_hop(h: &mut HeaderMap) {
    let listed: Vec<HeaderName> = h
        .get_all(header::CONNECTION)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .filter_map(|n| HeaderName::from_bytes(n.trim().as_bytes()).ok())
        .collect();
    for n in listed {
        h.remove(n);
    }
    for n in ["connection", "keep-alive", "proxy-connection", "proxy-authenticate", "proxy-authorization", "te", "trailer", "transfer-encoding", "upgrade"] {
        h.remove(n);
    }
}

async fn proxy(shared: &Shared, req: Request<Incoming>, target: Target, mut p: Pending) -> Response<GateBody> {
    let declared = req.headers().get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.trim().parse::<u64>().ok());
    if declared.is_some_and(|n| n > MAX_REQUEST_BODY_BYTES) {
        return p.refuse(StatusCode::PAYLOAD_TOO_LARGE, &format!("request body over {} MiB", MAX_REQUEST_BODY_BYTES >> 20));
    }
    let (parts, body) = req.into_parts();
    let Ok(uri) = parts.uri.path_and_query().map_or("/", |pq| pq.as_str()).parse::<Uri>() else {
        return p.refuse(StatusCode::BAD_REQUEST, "unreadable request target");
    };
    let Ok(host) = HeaderValue::from_str(&target.authority) else {
        return p.refuse(StatusCode::BAD_REQUEST, "unusable host");
    };
    let mut headers = parts.headers;
    strip_hop_by_hop(&mut headers);
    // hyper answers `Expect: 100-continue` itself as it reads the body.
    headers.remove(header::EXPECT);
    headers.insert(header::HOST, host);
    headers.insert(header::CONNECTION, HeaderValue::from_static("close"));
    headers.insert(header::ACCEPT_ENCODING, HeaderValue::from_static("identity"));
    // A body that has ended already (none, or empty) is never polled.
    p.bytes.body_complete.store(body.is_end_stream(), Ordering::Relaxed);
    let mut up = Request::new(RequestBody { inner: body, bytes: p.bytes.clone() });
    *up.method_mut() = parts.method;
    *up.uri_mut() = uri;
    *up.headers_mut() = headers;
    let io = match open(shared, &target).await {
        Ok(io) => io,
        Err(e) => return p.unreachable(StatusCode::BAD_GATEWAY, &e),
    };
    let (mut sender, conn) = match hyper::client::conn::http1::handshake(TokioIo::new(io)).await {
        Ok(x) => x,
        Err(e) => return p.unreachable(StatusCode::BAD_GATEWAY, &format!("upstream: {e}")),
    };
    tokio::spawn(async move {
        let _ = conn.await;
    });
    p.sent = true;
    let resp = match sender.send_request(up).await {
        Ok(r) => r,
        // The body's own error comes first: the client's (or the bound's), never the upstream's.
        Err(e) => match p.bytes.body_fault() {
            Some(fault) => return p.body_cut(fault),
            None => return p.unreachable(StatusCode::BAD_GATEWAY, &format!("upstream: {e}")),
        },
    };
    let (mut parts, body) = resp.into_parts();
    p.status = parts.status.as_u16();
    p.cause = Cause::Upstream;
    let content_type = parts.headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).map(|v| clipped(v, 100));
    let encoded = parts
        .headers
        .get(header::CONTENT_ENCODING)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| !v.trim().is_empty() && !v.trim().eq_ignore_ascii_case("identity"));
    let sse = content_type.as_deref().is_some_and(|c| c.to_ascii_lowercase().starts_with("text/event-stream"));
    p.content_type = content_type;
    p.capture = Some(Capture { sse, encoded, ..Capture::default() });
    strip_hop_by_hop(&mut parts.headers);
    let mut out = Response::new(GateBody::Tee(Box::new(TeeBody { inner: body, pending: p })));
    *out.status_mut() = parts.status;
    *out.headers_mut() = parts.headers;
    out
}

/// The client's request body on its way upstream: counted, and cut past [`MAX_REQUEST_BODY_BYTES`]; why it was
/// cut is noted, so that the upstream is never blamed for it.
struct RequestBody {
    inner: Incoming,
    bytes: Arc<Counters>,
}

impl Body for RequestBody {
    type Data = Bytes;
    type Error = Box<dyn std::error::Error + Send + Sync>;

    fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
        match Pin::new(&mut self.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(d) = frame.data_ref() {
                    let n = self.bytes.from_client.fetch_add(d.len() as u64, Ordering::Relaxed) + d.len() as u64;
                    if n > MAX_REQUEST_BODY_BYTES {
                        self.bytes.set_body_fault(BodyFault::TooLarge);
                        return Poll::Ready(Some(Err("request body over the gateway's limit".into())));
                    }
                }
                if self.inner.is_end_stream() {
                    self.bytes.body_complete.store(true, Ordering::Relaxed);
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Ready(Some(Err(e))) => {
                self.bytes.set_body_fault(BodyFault::Client(e.to_string()));
                Poll::Ready(Some(Err(e.into())))
            }
            Poll::Ready(None) => {
                self.bytes.body_complete.store(true, Ordering::Relaxed);
                Poll::Ready(None)
            }
            Poll::Pending => Poll::Pending,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// A response on its way to the client, keeping its connection busy until it is done.
struct Served {
    body: GateBody,
    _busy: Busy,
}

impl Body for Served {
    type Data = Bytes;
    type Error = hyper::Error;

    fn poll_frame(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, hyper::Error>>> {
        Pin::new(&mut self.get_mut().body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

/// What the gateway sends its client: its own short answers, or an upstream's response as it streams.
enum GateBody {
    Full(Option<Bytes>),
    Tee(Box<TeeBody>),
}

impl Body for GateBody {
    type Data = Bytes;
    type Error = hyper::Error;

    fn poll_frame(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, hyper::Error>>> {
        match self.get_mut() {
            GateBody::Full(b) => Poll::Ready(b.take().map(|b| Ok(Frame::data(b)))),
            GateBody::Tee(t) => Pin::new(&mut **t).poll_frame(cx),
        }
    }

    fn is_end_stream(&self) -> bool {
        match self {
            GateBody::Full(b) => b.is_none(),
            GateBody::Tee(t) => t.inner.is_end_stream(),
        }
    }

    fn size_hint(&self) -> SizeHint {
        match self {
            GateBody::Full(b) => SizeHint::with_exact(b.as_ref().map_or(0, |b| b.len() as u64)),
            GateBody::Tee(t) => t.inner.size_hint(),
        }
    }
}

/// An upstream response passed on frame by frame, counted and sampled for token usage; recorded at its end.
struct TeeBody {
    inner: Incoming,
    pending: Pending,
}

impl Body for TeeBody {
    type Data = Bytes;
    type Error = hyper::Error;

    fn poll_frame(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, hyper::Error>>> {
        let this = self.get_mut();
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(d) = frame.data_ref() {
                    this.pending.bytes.to_client.fetch_add(d.len() as u64, Ordering::Relaxed);
                    if let Some(c) = &mut this.pending.capture {
                        c.push(d);
                    }
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Ready(Some(Err(e))) => {
                // An exchange the client's body broke (the upstream answered before it had all of it) is the client's.
                match this.pending.bytes.body_fault() {
                    Some(BodyFault::Client(why)) => {
                        this.pending.cause = Cause::Client;
                        this.pending.error = Some(format!("client: the request body broke off: {why}"));
                    }
                    Some(BodyFault::TooLarge) => {
                        this.pending.cause = Cause::Gateway;
                        this.pending.error = Some(format!("request body over {} MiB", MAX_REQUEST_BODY_BYTES >> 20));
                    }
                    None => {
                        this.pending.cause = Cause::Upstream;
                        this.pending.error = Some(format!("upstream response: {e}"));
                    }
                }
                this.pending.finish();
                Poll::Ready(Some(Err(e)))
            }
            Poll::Ready(None) => {
                this.pending.finish();
                Poll::Ready(None)
            }
            Poll::Pending => Poll::Pending,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

impl Drop for TeeBody {
    fn drop(&mut self) {
        // An empty body (204, HEAD) is never polled: it ended well.
        if self.inner.is_end_stream() {
            self.pending.finish();
        }
    }
}

/// A tunnel's side, counting the bytes read from it and noting whether it failed first.
struct Counted<T> {
    inner: T,
    bytes: Arc<Counters>,
    /// [`FAULT_CLIENT`] or [`FAULT_REMOTE`].
    side: u8,
}

impl<T> Counted<T> {
    fn note<R>(&self, r: &Poll<std::io::Result<R>>) {
        if let Poll::Ready(Err(_)) = r {
            let _ = self.bytes.tunnel_fault.compare_exchange(0, self.side, Ordering::Relaxed, Ordering::Relaxed);
        }
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for Counted<T> {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let r = Pin::new(&mut self.inner).poll_read(cx, buf);
        if let Poll::Ready(Ok(())) = r {
            let n = (buf.filled().len() - before) as u64;
            let counter = if self.side == FAULT_CLIENT { &self.bytes.from_client } else { &self.bytes.to_client };
            counter.fetch_add(n, Ordering::Relaxed);
        }
        self.note(&r);
        r
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Counted<T> {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<std::io::Result<usize>> {
        let r = Pin::new(&mut self.inner).poll_write(cx, buf);
        self.note(&r);
        r
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        let r = Pin::new(&mut self.inner).poll_flush(cx);
        self.note(&r);
        r
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        let r = Pin::new(&mut self.inner).poll_shutdown(cx);
        self.note(&r);
        r
    }
}

/// The part of a response kept for reading token usage: its first [`HEAD_KEEP`] and last [`TAIL_KEEP`] bytes.
#[derive(Default)]
struct Capture {
    head: Vec<u8>,
    tail: Vec<u8>,
    total: u64,
    sse: bool,
    /// Compressed despite `Accept-Encoding: identity`: not read.
    encoded: bool,
}

impl Capture {
    fn push(&mut self, d: &[u8]) {
        self.total += d.len() as u64;
        let room = HEAD_KEEP.saturating_sub(self.head.len()).min(d.len());
        self.head.extend_from_slice(&d[..room]);
        let rest = &d[room..];
        if !rest.is_empty() {
            self.tail.extend_from_slice(rest);
            if self.tail.len() > 2 * TAIL_KEEP {
                let cut = self.tail.len() - TAIL_KEEP;
                self.tail.drain(..cut);
            }
        }
    }

    fn usage(&self) -> Option<TokenUsage> {
        if self.encoded || self.total == 0 {
            return None;
        }
        let whole = self.total == (self.head.len() + self.tail.len()) as u64;
        let sse = self.sse || self.head.starts_with(b"data:") || self.head.starts_with(b"event:");
        let mut acc = UsageAcc::default();
        match (sse, whole) {
            (true, true) => sse_events(&[&self.head[..], &self.tail[..]].concat(), &mut acc),
            (true, false) => {
                sse_events(&self.head, &mut acc);
                // The tail starts inside some line: from the next one.
                let from = self.tail.iter().position(|b| *b == b'\n').map_or(self.tail.len(), |i| i + 1);
                sse_events(&self.tail[from..], &mut acc);
            }
            (false, true) => {
                if let Ok(v) = serde_json::from_slice::<Value>(&[&self.head[..], &self.tail[..]].concat()) {
                    acc.feed(&v);
                }
            }
            (false, false) => {
                if let Some(u) = last_usage_object(&self.tail) {
                    acc.feed(&Value::Object(Map::from_iter([("usage".to_owned(), u)])));
                }
            }
        }
        acc.result()
    }
}

/// Feeds the JSON `data` of each server-sent event in `text` to `acc`.
fn sse_events(text: &[u8], acc: &mut UsageAcc) {
    let text = String::from_utf8_lossy(text);
    let mut data = String::new();
    let mut dispatch = |data: &mut String| {
        if !data.is_empty() {
            if let Ok(v) = serde_json::from_str::<Value>(data) {
                acc.feed(&v);
            }
            data.clear();
        }
    };
    for line in text.split('\n').map(|l| l.strip_suffix('\r').unwrap_or(l)) {
        if line.is_empty() {
            dispatch(&mut data);
        } else if let Some(d) = line.strip_prefix("data:") {
            if !data.is_empty() {
                data.push('\n');
            }
            data.push_str(d.strip_prefix(' ').unwrap_or(d));
        }
    }
    dispatch(&mut data);
}

/// The value of the last `"usage"` key in a piece of JSON (the end of a body too large to keep whole).
fn last_usage_object(text: &[u8]) -> Option<Value> {
    let key = b"\"usage\"";
    let mut end = text.len();
    while let Some(i) = text[..end].windows(key.len()).rposition(|w| w == key) {
        end = i;
        if i > 0 && text[i - 1] == b'\\' {
            continue; // inside a string
        }
        let rest = &text[i + key.len()..];
        let colon = rest.iter().position(|b| !b.is_ascii_whitespace())?;
        if rest[colon] != b':' {
            continue;
        }
        let mut values = serde_json::Deserializer::from_slice(&rest[colon + 1..]).into_iter::<Value>();
        if let Some(Ok(v @ Value::Object(_))) = values.next() {
            return Some(v);
        }
    }
    None
}

fn count(m: &Map<String, Value>, path: &[&str]) -> Option<u64> {
    let (last, parents) = path.split_last()?;
    let mut at = m;
    for p in parents {
        at = at.get(*p)?.as_object()?;
    }
    at.get(*last)?.as_u64()
}

/// Usage as the responses of one request report it: the last complete report wins; Anthropic's stream reports in
/// parts (`message_start`, then cumulative `message_delta`s), merged.
#[derive(Default)]
struct UsageAcc {
    last: Option<TokenUsage>,
    anthropic: Option<TokenUsage>,
}

impl UsageAcc {
    fn feed(&mut self, v: &Value) {
        let kind = v.get("type").and_then(Value::as_str).unwrap_or_default();
        match kind {
            "message_start" => {
                if let Some(u) = v.pointer("/message/usage").and_then(Value::as_object) {
                    self.merge_anthropic(u);
                }
            }
            "message_delta" => {
                if let Some(u) = v.get("usage").and_then(Value::as_object) {
                    self.merge_anthropic(u);
                }
            }
            k if k.starts_with("response.") => {
                if let Some(u) = v.pointer("/response/usage").and_then(Value::as_object) {
                    self.last = Some(responses_usage(u));
                }
            }
            _ => {
                let Some(u) = v.get("usage").and_then(Value::as_object) else { return };
                if u.contains_key("prompt_tokens") || u.contains_key("completion_tokens") {
                    self.last = Some(chat_usage(u));
                } else if kind == "message" || u.contains_key("cache_read_input_tokens") || u.contains_key("cache_creation_input_tokens") {
                    self.merge_anthropic(u);
                } else if u.contains_key("input_tokens") || u.contains_key("output_tokens") {
                    self.last = Some(responses_usage(u));
                }
            }
        }
    }

    fn merge_anthropic(&mut self, u: &Map<String, Value>) {
        let a = self.anthropic.get_or_insert_with(|| TokenUsage { api: "anthropic_messages".into(), ..TokenUsage::default() });
        for (key, field) in [
            ("input_tokens", &mut a.counts.input_tokens),
            ("output_tokens", &mut a.counts.output_tokens),
            ("cache_read_input_tokens", &mut a.counts.cached_input_tokens),
            ("cache_creation_input_tokens", &mut a.cache_creation_input_tokens),
        ] {
            if let Some(n) = count(u, &[key]) {
                *field = Some(n);
            }
        }
    }

    fn result(self) -> Option<TokenUsage> {
        let mut u = self.anthropic.or(self.last)?;
        let c = &mut u.counts;
        if c.total_tokens.is_none() && (c.input_tokens.is_some() || c.output_tokens.is_some()) {
            c.total_tokens = Some(c.input_tokens.unwrap_or(0) + c.output_tokens.unwrap_or(0));
        }
        Some(u)
    }
}

/// OpenAI chat completions (and the OpenAI-compatible APIs: DeepSeek's `prompt_cache_hit_tokens`, Moonshot's
/// top-level `cached_tokens`).
fn chat_usage(u: &Map<String, Value>) -> TokenUsage {
    TokenUsage {
        api: "openai_chat".into(),
        counts: Tokens {
            input_tokens: count(u, &["prompt_tokens"]),
            output_tokens: count(u, &["completion_tokens"]),
            cached_input_tokens: count(u, &["prompt_tokens_details", "cached_tokens"])
                .or_else(|| count(u, &["prompt_cache_hit_tokens"]))
                .or_else(|| count(u, &["cached_tokens"])),
            reasoning_tokens: count(u, &["completion_tokens_details", "reasoning_tokens"]).or_else(|| count(u, &["reasoning_tokens"])),
            total_tokens: count(u, &["total_tokens"]),
        },
        cache_creation_input_tokens: None,
    }
}

/// OpenAI Responses API.
fn responses_usage(u: &Map<String, Value>) -> TokenUsage {
    TokenUsage {
        api: "openai_responses".into(),
        counts: Tokens {
            input_tokens: count(u, &["input_tokens"]),
            output_tokens: count(u, &["output_tokens"]),
            cached_input_tokens: count(u, &["input_tokens_details", "cached_tokens"]),
            reasoning_tokens: count(u, &["output_tokens_details", "reasoning_tokens"]),
            total_tokens: count(u, &["total_tokens"]),
        },
        cache_creation_input_tokens: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(unix_ms: u64, mode: Mode, status: u16, cause: Cause, error: Option<&str>) -> Record {
        Record {
            time: String::new(), unix_ms, mode, method: "POST".into(), host: "api:443".into(), path: "/v1/responses".into(),
            status, cause, request_bytes: 1, response_bytes: 1, duration_ms: 1, content_type: None, usage: None, unmetered: false,
            error: error.map(str::to_owned),
        }
    }

    fn record(unix_ms: u64, mode: Mode, status: u16, cause: Cause, error: Option<&str>) -> String {
        serde_json::to_string(&rec(unix_ms, mode, status, cause, error)).unwrap()
    }

    /// Only what the agent cannot cause makes an early exit INVALID: the provider's 429/5xx (502: unreachable)
    /// or a response broken off upstream, on the last request passed on; never refusals, 4xx, a client gone, the
    /// gateway's own answers, or records that do not say who caused them.
    #[test]
    fn a_model_api_failure_is_only_the_last_passed_on_request_failing_upstream() {
        use Cause::{Client, Gateway, Unknown, Upstream};
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("model_api.jsonl");
        let case = |lines: &[String]| {
            std::fs::write(&p, lines.join("\n")).unwrap();
            last_model_api_failure(&p)
        };
        assert!(case(&[record(1, Mode::Reverse, 502, Upstream, Some("upstream: connection refused"))]).is_some_and(|w| w.contains("answered 502")));
        assert!(case(&[record(1, Mode::Reverse, 200, Upstream, None), record(2, Mode::Forward, 429, Upstream, None)]).is_some());
        assert!(case(&[record(1, Mode::Reverse, 200, Upstream, Some("upstream response: reset"))]).is_some());
        // An early failure the CLI got past, then an answered request: not a failure.
        assert!(case(&[record(1, Mode::Reverse, 503, Upstream, None), record(2, Mode::Reverse, 200, Upstream, None)]).is_none());
        // The agent's own doing: refused hosts, a 4xx, a client gone, a cut body, a tunnel.
        assert!(case(&[record(1, Mode::Reverse, 200, Upstream, None), record(2, Mode::Refused, 403, Gateway, None)]).is_none());
        assert!(case(&[record(1, Mode::Reverse, 401, Upstream, None)]).is_none());
        assert!(case(&[record(1, Mode::Reverse, 200, Client, Some("ended early: the client went away"))]).is_none());
        assert!(case(&[record(1, Mode::Reverse, 400, Client, Some("client: the request body broke off: x"))]).is_none());
        assert!(case(&[record(1, Mode::Reverse, 502, Client, Some("client: the request body broke off: x"))]).is_none());
        assert!(case(&[record(1, Mode::Connect, 502, Upstream, None)]).is_none());
        // The gateway's own answers: no model API configured, a bound, the gateway stopping.
        assert!(case(&[record(1, Mode::Reverse, 502, Gateway, Some("no model API is configured for this sandbox"))]).is_none());
        assert!(case(&[record(1, Mode::Reverse, 413, Gateway, Some("request body over 32 MiB"))]).is_none());
        assert!(case(&[record(1, Mode::Reverse, 200, Gateway, Some("ended early: the gateway stopped"))]).is_none());
        // Records without a cause (written before causes were) are never the model API's failure.
        let old = r#"{"time":"","unix_ms":1,"mode":"reverse","method":"POST","host":"h:1","path":"/v1/responses","status":502,"request_bytes":1,"response_bytes":1,"duration_ms":1,"error":"upstream: x"}"#;
        assert_eq!(serde_json::from_str::<Record>(old).unwrap().cause, Unknown);
        assert!(case(&[old.to_owned()]).is_none());
        assert!(case(&[]).is_none());
    }

    use http_body_util::{BodyExt, Either, Full};
    use std::io::{Read, Write};
    use std::os::unix::net::UnixStream as StdUnixStream;
    use tokio::net::TcpListener;

    const KEY: &str = "sk-test-SECRET-0123456789";

    type UpBody = Either<Full<Bytes>, ChanBody>;

    /// A response body sent piece by piece.
    struct ChanBody(tokio::sync::mpsc::Receiver<Bytes>);

    impl Body for ChanBody {
        type Data = Bytes;
        type Error = Infallible;

        fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
            self.0.poll_recv(cx).map(|b| b.map(|b| Ok(Frame::data(b))))
        }
    }

    /// What the local upstream saw, and the gate of its streamed chat completion.
    #[derive(Default)]
    struct Seen {
        requests: Mutex<Vec<(String, HeaderMap)>>,
        gate: Mutex<Option<oneshot::Receiver<()>>>,
        /// The stream's last chunk went out before the client had its first one.
        gate_timed_out: AtomicBool,
    }

    impl Seen {
        fn paths(&self) -> Vec<String> {
            self.requests.lock().unwrap().iter().map(|(p, _)| p.clone()).collect()
        }
    }

    fn sse_response(events: Vec<String>, gate: Option<(oneshot::Receiver<()>, Arc<Seen>)>) -> Response<UpBody> {
        let (tx, rx) = tokio::sync::mpsc::channel::<Bytes>(4);
        tokio::spawn(async move {
            let mut gate = gate;
            for (i, e) in events.into_iter().enumerate() {
                if i == 1
                    && let Some((rx, seen)) = gate.take()
                    && tokio::time::timeout(Duration::from_secs(10), rx).await.is_err()
                {
                    seen.gate_timed_out.store(true, Ordering::SeqCst);
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
                if tx.send(Bytes::from(e)).await.is_err() {
                    return;
                }
            }
        });
        let mut r = Response::new(Either::Right(ChanBody(rx)));
        r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("text/event-stream"));
        r
    }

    fn json_response(v: &str) -> Response<UpBody> {
        let mut r = Response::new(Either::Left(Full::new(Bytes::from(v.to_owned()))));
        r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("application/json"));
        r
    }

    fn data(v: &str) -> String {
        format!("data: {v}\n\n")
    }

    const CHAT: &str = r#"{"id":"c1","object":"chat.completion","choices":[{"index":0,"message":{"role":"assistant","content":"hi"}}],"usage":{"prompt_tokens":11,"completion_tokens":7,"total_tokens":18,"prompt_tokens_details":{"cached_tokens":3}}}"#;

    async fn upstream(seen: Arc<Seen>, req: Request<Incoming>) -> Result<Response<UpBody>, Infallible> {
        let (parts, body) = req.into_parts();
        let body = body.collect().await.map(|b| b.to_bytes()).unwrap_or_default();
        let body = String::from_utf8_lossy(&body).into_owned();
        seen.requests.lock().unwrap().push((parts.uri.path().to_owned(), parts.headers));
        // The provider failing (overloaded), or answering compressed against the gateway's asking.
        if body.contains(r#""fail":true"#) {
            let mut r = json_response(r#"{"error":{"message":"overloaded"}}"#);
            *r.status_mut() = StatusCode::SERVICE_UNAVAILABLE;
            return Ok(r);
        }
        if body.contains(r#""gzip":true"#) {
            let mut r = json_response(CHAT);
            r.headers_mut().insert(header::CONTENT_ENCODING, HeaderValue::from_static("gzip"));
            return Ok(r);
        }
        Ok(match parts.uri.path() {
            "/v1/chat/completions" if body.contains("\"stream\":true") => {
                let gate = seen.gate.lock().unwrap().take().map(|rx| (rx, seen.clone()));
                sse_response(
                    vec![
                        data(r#"{"choices":[{"delta":{"content":"Hel"}}],"usage":null}"#),
                        data(r#"{"choices":[{"delta":{"content":"lo!"}}],"usage":null}"#),
                        data(r#"{"choices":[],"usage":{"prompt_tokens":20,"completion_tokens":5,"total_tokens":25,"prompt_tokens_details":{"cached_tokens":4},"completion_tokens_details":{"reasoning_tokens":2}}}"#),
                        data("[DONE]"),
                    ],
                    gate,
                )
            }
            "/v1/chat/completions" => json_response(CHAT),
            "/v1/messages" => sse_response(
                vec![
                    format!("event: message_start\n{}", data(r#"{"type":"message_start","message":{"id":"m1","type":"message","role":"assistant","usage":{"input_tokens":30,"cache_read_input_tokens":100,"cache_creation_input_tokens":10,"output_tokens":1}}}"#)),
                    format!("event: content_block_delta\n{}", data(r#"{"type":"content_block_delta","index":0,"delta":{"type":"text_delta","text":"ok"}}"#)),
                    format!("event: message_delta\n{}", data(r#"{"type":"message_delta","delta":{"stop_reason":"end_turn"},"usage":{"output_tokens":15}}"#)),
                    format!("event: message_stop\n{}", data(r#"{"type":"message_stop"}"#)),
                ],
                None,
            ),
            "/v1/responses" => sse_response(
                vec![
                    data(r#"{"type":"response.created","response":{"id":"r1","usage":null}}"#),
                    data(r#"{"type":"response.output_text.delta","delta":"ok"}"#),
                    data(r#"{"type":"response.completed","response":{"id":"r1","usage":{"input_tokens":40,"input_tokens_details":{"cached_tokens":8},"output_tokens":9,"output_tokens_details":{"reasoning_tokens":6},"total_tokens":49}}}"#),
                ],
                None,
            ),
            _ => json_response(r#"{"object":"list","data":[]}"#),
        })
    }

    /// A local upstream, another HTTP host and a TCP echo server (all on real sockets), and a gateway in front of
    /// them that reverse-proxies to the upstream and lets the other two be reached by the proxy.
    struct Fixture {
        rt: tokio::runtime::Runtime,
        seen: Arc<Seen>,
        up: SocketAddr,
        other: SocketAddr,
        echo: SocketAddr,
        dir: tempfile::TempDir,
        sock: PathBuf,
        records: PathBuf,
        gateway: Option<Gateway>,
    }

    /// The endpoints of the fixture's "harness".
    fn routes() -> Vec<Route> {
        vec![
            Route::new(Method::POST, "/v1/chat/completions"),
            Route::new(Method::POST, "/v1/messages"),
            Route::new(Method::POST, "/v1/responses"),
            Route::new(Method::GET, "/v1/models"),
        ]
    }

    fn fixture(with_upstream: bool) -> Fixture {
        fixture_with(with_upstream, MAX_CONNECTIONS, |_, _| {})
    }

    /// [`fixture`] with at most `cap` connections, its configuration changed by `edit` (given the upstream's address).
    fn fixture_with(with_upstream: bool, cap: usize, edit: impl FnOnce(&mut GatewayConfig, SocketAddr)) -> Fixture {
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
        let seen = Arc::new(Seen::default());
        let (up, other, echo) = rt.block_on(async {
            let mut http = Vec::new();
            for _ in 0..2 {
                let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
                http.push(listener.local_addr().unwrap());
                let seen = seen.clone();
                tokio::spawn(async move {
                    while let Ok((s, _)) = listener.accept().await {
                        let seen = seen.clone();
                        tokio::spawn(async move {
                            let svc = hyper::service::service_fn(move |req| upstream(seen.clone(), req));
                            let _ = hyper::server::conn::http1::Builder::new().serve_connection(TokioIo::new(s), svc).await;
                        });
                    }
                });
            }
            let echo_listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
            let echo = echo_listener.local_addr().unwrap();
            tokio::spawn(async move {
                while let Ok((s, _)) = echo_listener.accept().await {
                    tokio::spawn(async move {
                        let (mut r, mut w) = s.into_split();
                        let _ = tokio::io::copy(&mut r, &mut w).await;
                        let _ = tokio::io::AsyncWriteExt::shutdown(&mut w).await;
                    });
                }
            });
            (http[0], http[1], echo)
        });
        let dir = tempfile::tempdir().unwrap();
        let sock = dir.path().join("model.sock");
        let records = dir.path().join("model_api.jsonl");
        let mut cfg = GatewayConfig {
            upstream: with_upstream.then(|| url::Url::parse(&format!("http://{up}/v1")).unwrap()),
            routes: routes(),
            allowed: vec![("127.0.0.1".into(), other.port()), ("127.0.0.1".into(), echo.port())],
            records: records.clone(),
            ..GatewayConfig::default()
        };
        edit(&mut cfg, up);
        let gateway = Some(start_capped(StdUnixListener::bind(&sock).unwrap(), cfg, cap).unwrap());
        Fixture { rt, seen, up, other, echo, dir, sock, records, gateway }
    }

    impl Fixture {
        fn connect(&self) -> StdUnixStream {
            let s = StdUnixStream::connect(&self.sock).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
            s
        }

        /// Sends `raw`, reads until the gateway closes.
        fn exchange(&self, raw: &[u8]) -> String {
            let mut s = self.connect();
            let _ = s.write_all(raw);
            let mut out = Vec::new();
            let _ = s.read_to_end(&mut out);
            String::from_utf8_lossy(&out).into_owned()
        }

        /// The records file once it holds at least `n` records.
        fn records(&self, n: usize) -> Vec<Record> {
            let deadline = Instant::now() + Duration::from_secs(10);
            loop {
                let text = std::fs::read_to_string(&self.records).unwrap_or_default();
                let rs: Vec<Record> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
                if rs.len() >= n || Instant::now() > deadline {
                    return rs;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        }

        /// Opens a tunnel to the echo server; returns the connection once it is established.
        fn tunnel(&self) -> StdUnixStream {
            let mut s = self.connect();
            s.write_all(format!("CONNECT {0} HTTP/1.1\r\nHost: {0}\r\n\r\n", self.echo).as_bytes()).unwrap();
            let mut buf = Vec::new();
            read_until(&mut s, &mut buf, "\r\n\r\n");
            assert!(buf.starts_with(b"HTTP/1.1 200"), "{}", String::from_utf8_lossy(&buf));
            s
        }
    }

    fn post(path: &str, body: &str) -> Vec<u8> {
        format!(
            "POST {path} HTTP/1.1\r\nHost: 127.0.0.1:18790\r\nAuthorization: Bearer {KEY}\r\nx-api-key: {KEY}\r\n\
             Content-Type: application/json\r\nAccept-Encoding: gzip, br\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
            body.len()
        )
        .into_bytes()
    }

    fn get(path: &str) -> Vec<u8> {
        format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1:18790\r\nConnection: close\r\n\r\n").into_bytes()
    }

    fn read_until(s: &mut StdUnixStream, buf: &mut Vec<u8>, needle: &str) {
        let mut chunk = [0u8; 4096];
        while !String::from_utf8_lossy(buf).contains(needle) {
            let n = s.read(&mut chunk).unwrap();
            assert!(n > 0, "closed before {needle:?}: {}", String::from_utf8_lossy(buf));
            buf.extend_from_slice(&chunk[..n]);
        }
    }

    #[test]
    fn reverse_proxy_streams_and_records_usage_without_secrets() {
        let f = fixture(true);
        // (a) A JSON chat completion.
        let out = f.exchange(&post("/v1/chat/completions", r#"{"model":"m","messages":[]}"#));
        assert!(out.starts_with("HTTP/1.1 200"), "{out}");
        assert!(out.contains(r#""content":"hi""#), "{out}");
        // (b) A streamed one: the upstream holds its later chunks until the client has the first.
        let (gate, gate_rx) = oneshot::channel();
        *f.seen.gate.lock().unwrap() = Some(gate_rx);
        let mut s = f.connect();
        s.write_all(&post("/v1/chat/completions", r#"{"model":"m","stream":true}"#)).unwrap();
        let mut buf = Vec::new();
        read_until(&mut s, &mut buf, r#""content":"Hel""#);
        assert!(!String::from_utf8_lossy(&buf).contains("[DONE]"));
        gate.send(()).unwrap();
        s.read_to_end(&mut buf).unwrap();
        let out = String::from_utf8_lossy(&buf);
        assert!(out.contains(r#""content":"lo!""#) && out.contains("data: [DONE]"), "{out}");
        assert!(out.to_ascii_lowercase().contains("content-type: text/event-stream"), "{out}");
        assert!(!f.seen.gate_timed_out.load(Ordering::SeqCst), "the first chunk reached the client only after the last was sent");
        // (c) Anthropic messages and the Responses API, streamed.
        let out = f.exchange(&post("/v1/messages", r#"{"model":"claude","stream":true}"#));
        assert!(out.contains("message_stop"), "{out}");
        let out = f.exchange(&post("/v1/responses?api-version=2", r#"{"model":"m","stream":true}"#));
        assert!(out.contains("response.completed"), "{out}");

        // Upstream saw the key (the agent's own call) with its own Host, identity encoding and one request per connection.
        for (path, h) in f.seen.requests.lock().unwrap().iter() {
            assert_eq!(h[header::HOST], f.up.to_string().as_str(), "{path}");
            assert_eq!(h[header::AUTHORIZATION], format!("Bearer {KEY}").as_str());
            assert_eq!(h[header::ACCEPT_ENCODING], "identity");
            assert_eq!(h[header::CONNECTION], "close");
        }
        let rs = f.records(4);
        assert_eq!(rs.len(), 4, "{rs:?}");
        assert!(rs.iter().all(|r| r.mode == Mode::Reverse && r.status == 200 && r.error.is_none() && r.host == f.up.to_string()), "{rs:?}");
        assert!(rs.iter().all(|r| r.cause == Cause::Upstream && !r.unmetered), "{rs:?}");
        assert!(rs.iter().all(|r| r.request_bytes > 0 && r.response_bytes > 0), "{rs:?}");
        assert_eq!(rs[3].path, "/v1/responses", "no query");
        let usage = |i: usize| rs[i].usage.clone().unwrap();
        assert_eq!(usage(0), TokenUsage { api: "openai_chat".into(), counts: Tokens { input_tokens: Some(11), output_tokens: Some(7), cached_input_tokens: Some(3), total_tokens: Some(18), ..Tokens::default() }, ..TokenUsage::default() });
        assert_eq!(usage(1), TokenUsage { api: "openai_chat".into(), counts: Tokens { input_tokens: Some(20), output_tokens: Some(5), cached_input_tokens: Some(4), reasoning_tokens: Some(2), total_tokens: Some(25) }, ..TokenUsage::default() });
        assert_eq!(usage(2), TokenUsage { api: "anthropic_messages".into(), counts: Tokens { input_tokens: Some(30), output_tokens: Some(15), cached_input_tokens: Some(100), total_tokens: Some(45), ..Tokens::default() }, cache_creation_input_tokens: Some(10) });
        assert_eq!(usage(3), TokenUsage { api: "openai_responses".into(), counts: Tokens { input_tokens: Some(40), output_tokens: Some(9), cached_input_tokens: Some(8), reasoning_tokens: Some(6), total_tokens: Some(49) }, ..TokenUsage::default() });
        let text = std::fs::read_to_string(&f.records).unwrap();
        assert!(!text.contains("SECRET") && !text.contains("Bearer"), "{text}");

        let s = summarize(&f.records).unwrap();
        assert_eq!((s.requests, s.refused, s.failed, s.responses_with_usage), (4, 0, 0, 4));
        assert_eq!((s.input_tokens, s.output_tokens, s.cached_input_tokens), (101, 36, 115));
        assert_eq!((s.cache_creation_input_tokens, s.reasoning_tokens, s.total_tokens), (10, 8, 137));
        assert_eq!(s.request_bytes, rs.iter().map(|r| r.request_bytes).sum::<u64>());
        assert_eq!(s.response_bytes, rs.iter().map(|r| r.response_bytes).sum::<u64>());
        assert_eq!((s.tunnel_bytes, s.unmetered, s.overflowed, s.complete), (0, 0, 0, true), "every token metered");
        drop(f.dir);
    }

    #[test]
    fn forward_and_connect_reach_only_allowed_hosts() {
        let f = fixture(true);
        let out = f.exchange(format!("GET http://{0}/v1/models HTTP/1.1\r\nHost: {0}\r\nConnection: close\r\n\r\n", f.other).as_bytes());
        assert!(out.starts_with("HTTP/1.1 200") && out.contains(r#""object":"list""#), "{out}");
        let out = f.exchange(b"GET http://127.0.0.1:1/secret?x=1 HTTP/1.1\r\nHost: 127.0.0.1:1\r\nConnection: close\r\n\r\n");
        assert!(out.starts_with("HTTP/1.1 403"), "{out}");
        let out = f.exchange(b"GET https://127.0.0.1:1/ HTTP/1.1\r\nHost: 127.0.0.1:1\r\nConnection: close\r\n\r\n");
        assert!(out.starts_with("HTTP/1.1 400"), "{out}");

        // A tunnel to the echo server: bytes both ways, then the half-close travels through.
        let mut s = f.tunnel();
        s.write_all(b"ping-pong").unwrap();
        let mut back = [0u8; 9];
        s.read_exact(&mut back).unwrap();
        assert_eq!(&back, b"ping-pong");
        s.shutdown(std::net::Shutdown::Write).unwrap();
        let mut rest = Vec::new();
        s.read_to_end(&mut rest).unwrap();
        assert!(rest.is_empty());
        let out = f.exchange(b"CONNECT 127.0.0.1:1 HTTP/1.1\r\nHost: 127.0.0.1:1\r\n\r\n");
        assert!(out.starts_with("HTTP/1.1 403"), "{out}");

        let rs = f.records(5);
        let by_mode = |m: Mode| rs.iter().filter(|r| r.mode == m).cloned().collect::<Vec<_>>();
        let fwd = by_mode(Mode::Forward);
        assert_eq!((fwd.len(), fwd[0].status, fwd[0].path.as_str(), fwd[0].usage.is_none()), (1, 200, "/v1/models", true));
        let tunnel = by_mode(Mode::Connect);
        assert_eq!(tunnel.len(), 1, "{rs:?}");
        assert_eq!((tunnel[0].status, tunnel[0].request_bytes, tunnel[0].response_bytes, tunnel[0].cause), (200, 9, 9, Cause::Upstream));
        assert_eq!(tunnel[0].host, f.echo.to_string());
        let refused = by_mode(Mode::Refused);
        assert_eq!(refused.iter().map(|r| (r.status, r.method.as_str(), r.host.as_str(), r.cause)).collect::<Vec<_>>(),
            [(403, "GET", "127.0.0.1:1", Cause::Gateway), (400, "GET", "127.0.0.1:1", Cause::Gateway), (403, "CONNECT", "127.0.0.1:1", Cause::Gateway)]);
        assert_eq!(refused[0].path, "/secret");
        // What went through the tunnel and the forward is traffic the gateway cannot meter.
        let s = summarize(&f.records).unwrap();
        assert_eq!(s.refused, 3);
        assert_eq!(s.tunnel_bytes, 18 + fwd[0].request_bytes + fwd[0].response_bytes);
        assert!(!s.complete, "{s:?}");
    }

    /// Problem 3: the model API's own host:port is reached through the routes only, never by a tunnel or a
    /// forward, even when the allow-list names it.
    #[test]
    fn the_upstream_is_reached_through_the_base_url_only() {
        let f = fixture_with(true, MAX_CONNECTIONS, |cfg, up| cfg.allowed.push(("127.0.0.1".into(), up.port())));
        let out = f.exchange(format!("CONNECT {0} HTTP/1.1\r\nHost: {0}\r\n\r\n", f.up).as_bytes());
        assert!(out.starts_with("HTTP/1.1 403") && out.contains("not a tunnel"), "{out}");
        let out = f.exchange(format!("GET http://{0}/v1/files HTTP/1.1\r\nHost: {0}\r\nConnection: close\r\n\r\n", f.up).as_bytes());
        assert!(out.starts_with("HTTP/1.1 403") && out.contains("base URL"), "{out}");
        let rs = f.records(2);
        assert!(rs.iter().all(|r| (r.mode, r.status, r.cause) == (Mode::Refused, 403, Cause::Gateway)), "{rs:?}");
        assert!(f.seen.paths().is_empty(), "{:?}", f.seen.paths());
    }

    /// Problem 2: only the harness's endpoints reach the upstream: a provider's stored files, or any other
    /// path, would be memory that outlives the rollout.
    #[test]
    fn only_the_harness_s_endpoints_are_passed_on() {
        let f = fixture(true);
        let refused = [
            get("/v1/files"),
            b"DELETE /v1/files/file-1 HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n".to_vec(),
            post("/v1/files", "{}"),
            post("/v1/chat/completions/../../v1/files", "{}"),
            post("/v1//chat/completions", "{}"),
            post("/v1/chat%2Fcompletions", "{}"),
            post("/v1/%2E%2E/v1/chat/completions", "{}"),
            post("/v1\\chat\\completions", "{}"),
            get("/v1/chat/completions"),
            get("/v1/models/gpt-5"),
        ];
        for raw in &refused {
            let out = f.exchange(raw);
            assert!(out.starts_with("HTTP/1.1 403"), "{}: {out}", String::from_utf8_lossy(raw));
        }
        let out = f.exchange(&post("/v1/files", "{}"));
        assert!(out.contains("POST /v1/files is not an endpoint of this harness's model API"), "{out}");
        // A WebSocket (Codex's first try of the Responses API): 426, so that the client streams over HTTP at once.
        let out = f.exchange(b"GET /v1/responses HTTP/1.1\r\nHost: x\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n\r\n");
        assert!(out.starts_with("HTTP/1.1 426"), "{out}");
        let out = f.exchange(&get("/v1/models?limit=5"));
        assert!(out.starts_with("HTTP/1.1 200"), "{out}");
        assert_eq!(f.seen.paths(), ["/v1/models"], "nothing else reached the upstream");
        let rs = f.records(refused.len() + 3);
        let (passed, refused_rs): (Vec<_>, Vec<_>) = rs.iter().partition(|r| r.mode == Mode::Reverse);
        assert_eq!(passed.len(), 1);
        assert!(refused_rs.iter().all(|r| r.mode == Mode::Refused && r.cause == Cause::Gateway && r.host == f.up.to_string()), "{refused_rs:?}");
        assert!(last_model_api_failure(&f.records).is_none());
    }

    /// Problem 1: only the upstream's own failures make the model API's failure: never the gateway's answer
    /// without an upstream, nor a client that cut its request body short.
    #[test]
    fn only_the_upstream_fails_the_model_api() {
        // No upstream: the gateway's own answer, not passed on.
        let f = fixture(false);
        let out = f.exchange(&post("/v1/chat/completions", "{}"));
        assert!(out.starts_with("HTTP/1.1 503") && out.contains("no model API is configured for this sandbox"), "{out}");
        let rs = f.records(1);
        assert_eq!((rs[0].mode, rs[0].status, rs[0].cause), (Mode::Refused, 503, Cause::Gateway));
        assert!(last_model_api_failure(&f.records).is_none());

        // A body that declares 100000 bytes, sends 9 and goes: the client's doing.
        let f = fixture(true);
        let mut s = f.connect();
        s.write_all(format!("POST /v1/chat/completions HTTP/1.1\r\nHost: x\r\nContent-Length: 100000\r\n\r\n{}", r#"{"model":"#).as_bytes()).unwrap();
        std::thread::sleep(Duration::from_millis(100));
        s.shutdown(std::net::Shutdown::Both).unwrap();
        drop(s);
        let rs = f.records(1);
        assert_eq!(rs.len(), 1, "{rs:?}");
        assert_eq!((rs[0].mode, rs[0].cause), (Mode::Reverse, Cause::Client), "{rs:?}");
        let error = rs[0].error.clone().unwrap_or_default();
        assert!(error.starts_with("client: the request body broke off") || error.contains("client went away"), "{error}");
        assert!(!error.contains("upstream"), "{error}");
        assert!(!rs[0].unmetered, "the upstream never had the whole request");
        assert!(last_model_api_failure(&f.records).is_none());

        // The upstream's 503, on the last request passed on: the model API's failure.
        let out = f.exchange(&post("/v1/chat/completions", r#"{"fail":true}"#));
        assert!(out.starts_with("HTTP/1.1 503"), "{out}");
        let rs = f.records(2);
        assert_eq!((rs[1].mode, rs[1].status, rs[1].cause), (Mode::Reverse, 503, Cause::Upstream));
        assert!(last_model_api_failure(&f.records).is_some_and(|w| w.contains("answered 503 to POST /v1/chat/completions")));
        // A refusal after it changes nothing (not passed on); an answered request does.
        f.exchange(&get("/v1/files"));
        assert!(f.records(3).len() == 3 && last_model_api_failure(&f.records).is_some());
        f.exchange(&get("/v1/models"));
        assert!(f.records(4).len() == 4 && last_model_api_failure(&f.records).is_none());
    }

    /// A response compressed against the gateway's asking cannot be read for usage: the summary says its sums
    /// are incomplete.
    #[test]
    fn unreadable_usage_makes_the_summary_incomplete() {
        let f = fixture(true);
        let out = f.exchange(&post("/v1/chat/completions", r#"{"gzip":true}"#));
        assert!(out.starts_with("HTTP/1.1 200"), "{out}");
        let rs = f.records(1);
        assert!(rs[0].unmetered && rs[0].usage.is_none() && rs[0].cause == Cause::Upstream, "{rs:?}");
        let s = summarize(&f.records).unwrap();
        assert_eq!((s.unmetered, s.complete), (1, false));
    }

    #[test]
    fn bounds_and_a_missing_upstream() {
        let f = fixture(false);
        let big = format!("GET /v1/models HTTP/1.1\r\nHost: x\r\nX-Big: {}\r\n\r\n", "a".repeat(MAX_HEAD_BYTES + 1024));
        let out = f.exchange(big.as_bytes());
        assert!(out.starts_with("HTTP/1.1 431"), "{out}");
        let too_long = format!("POST http://{0}/v1/chat/completions HTTP/1.1\r\nHost: {0}\r\nContent-Length: {1}\r\n\r\n", f.other, 40u64 << 20);
        let out = f.exchange(too_long.as_bytes());
        assert!(out.starts_with("HTTP/1.1 413"), "{out}");
        let out = f.exchange(&post("/v1/chat/completions", "{}"));
        assert!(out.starts_with("HTTP/1.1 503") && out.contains("no model API"), "{out}");
        let rs = f.records(3);
        let statuses: Vec<(Mode, u16, Cause)> = rs.iter().map(|r| (r.mode, r.status, r.cause)).collect();
        assert_eq!(statuses, [(Mode::Refused, 431, Cause::Gateway), (Mode::Refused, 413, Cause::Gateway), (Mode::Refused, 503, Cause::Gateway)]);
        assert!(rs.iter().all(|r| r.error.is_some()));
        assert!(!std::fs::read_to_string(&f.records).unwrap().contains("SECRET"));
    }

    #[test]
    fn stopping_cuts_a_stream_and_records_it() {
        let mut f = fixture(true);
        let (_gate, gate_rx) = oneshot::channel::<()>();
        *f.seen.gate.lock().unwrap() = Some(gate_rx);
        let mut s = f.connect();
        s.write_all(&post("/v1/chat/completions", r#"{"stream":true}"#)).unwrap();
        read_until(&mut s, &mut Vec::new(), "Hel");
        f.gateway.take().unwrap().stop();
        let mut rest = Vec::new();
        let _ = s.read_to_end(&mut rest);
        let rs = f.records(1);
        assert_eq!(rs.len(), 1);
        assert!(rs[0].error.as_deref().is_some_and(|e| e.contains("ended early: the gateway stopped")), "{rs:?}");
        assert_eq!(rs[0].cause, Cause::Gateway, "the gateway cut it, not the model API");
        assert!(rs[0].response_bytes > 0 && rs[0].usage.is_none() && rs[0].unmetered);
        assert!(last_model_api_failure(&f.records).is_none());
        f.rt.shutdown_background();
    }

    /// Problem 4: past the record cap, requests are counted, not written: the file stays bounded, the token sums
    /// stay exact, and the last request passed on is still known, from the final line or, after a crash, from the
    /// sidecar.
    #[test]
    fn past_the_record_cap_requests_are_counted_exactly() {
        let mut f = fixture_with(true, MAX_CONNECTIONS, |cfg, _| cfg.max_records = 3);
        for _ in 0..2 {
            assert!(f.exchange(&post("/v1/chat/completions", "{}")).starts_with("HTTP/1.1 200"));
        }
        for _ in 0..5 {
            assert!(f.exchange(&get("/v1/files")).starts_with("HTTP/1.1 403"));
        }
        for _ in 0..2 {
            assert!(f.exchange(&post("/v1/chat/completions", "{}")).starts_with("HTTP/1.1 200"));
        }
        assert!(f.exchange(&post("/v1/chat/completions", r#"{"fail":true}"#)).starts_with("HTTP/1.1 503"));
        let sidecar = overflow_sidecar(&f.records);
        assert_eq!(sidecar, f.dir.path().join("model_api.overflow.json"));
        // The sidecar catches up within a second or so; a crashed gateway leaves it and no final line.
        std::thread::sleep(SIDECAR_EVERY + Duration::from_millis(500));
        let crashed = f.dir.path().join("crashed");
        std::fs::create_dir(&crashed).unwrap();
        std::fs::copy(&f.records, crashed.join("model_api.jsonl")).unwrap();
        std::fs::copy(&sidecar, crashed.join("model_api.overflow.json")).unwrap();
        let s = summarize(&crashed.join("model_api.jsonl")).unwrap();
        assert_eq!((s.requests, s.overflowed, s.responses_with_usage, s.input_tokens), (10, 7, 4, 44), "{s:?}");
        assert!(!s.complete, "a crashed gateway's counters may lag");
        assert!(last_model_api_failure(&crashed.join("model_api.jsonl")).is_some_and(|w| w.contains("503")));

        f.gateway.take().unwrap().stop();
        assert!(!sidecar.exists(), "the final line replaces the sidecar");
        let text = std::fs::read_to_string(&f.records).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 4, "{text}");
        assert!(lines[..3].iter().all(|l| serde_json::from_str::<Record>(l).is_ok()));
        let o: Overflow = serde_json::from_str(lines[3]).unwrap();
        assert!(lines[3].starts_with(r#"{"kind":"overflow","requests":7,"#), "{}", lines[3]);
        assert_eq!(o.by_status, BTreeMap::from([(200, 2), (403, 4), (503, 1)]));
        assert_eq!((o.summary.requests, o.summary.refused, o.summary.responses_with_usage, o.summary.input_tokens), (7, 4, 2, 22));
        assert_eq!(o.last_passed_on.as_ref().map(|r| (r.status, r.cause)), Some((503, Cause::Upstream)));
        assert!(serde_json::from_str::<Record>(lines[3]).is_err(), "never read as a record");
        let s = summarize(&f.records).unwrap();
        assert_eq!((s.requests, s.refused, s.overflowed), (10, 5, 7));
        assert_eq!((s.responses_with_usage, s.input_tokens, s.output_tokens, s.total_tokens), (4, 44, 28, 72));
        assert_eq!((s.unreadable_lines, s.complete), (0, true));
        assert!(last_model_api_failure(&f.records).is_some_and(|w| w.contains("answered 503")));
        f.rt.shutdown_background();
    }

    /// Summaries read the file line by line and skip what is too long to be a record.
    #[test]
    fn summaries_skip_overlong_lines() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("model_api.jsonl");
        let long = "x".repeat(MAX_RECORD_LINE_BYTES + 10);
        let mut o = Overflow::default();
        o.add(rec(5, Mode::Reverse, 502, Cause::Upstream, Some("upstream: reset")));
        let lines = [
            record(1, Mode::Reverse, 200, Cause::Upstream, None),
            long,
            record(2, Mode::Reverse, 200, Cause::Upstream, None),
            serde_json::to_string(&o).unwrap(),
            "{\"time\": cut sho".to_owned(),
        ];
        std::fs::write(&p, lines.join("\n")).unwrap();
        let s = summarize(&p).unwrap();
        assert_eq!((s.requests, s.overflowed, s.unreadable_lines, s.complete), (3, 1, 2, false));
        assert!(last_model_api_failure(&p).is_some_and(|w| w.contains("502")), "the last passed-on request is past the cap");
        // A line of exactly the limit is read.
        let mut exact = record(9, Mode::Reverse, 200, Cause::Upstream, None);
        exact.insert_str(1, &format!("\"pad\":\"{}\",", "p".repeat(MAX_RECORD_LINE_BYTES - exact.len() - 9)));
        assert_eq!(exact.len(), MAX_RECORD_LINE_BYTES);
        std::fs::write(&p, format!("{exact}\n{exact}")).unwrap();
        assert_eq!(summarize(&p).unwrap().requests, 2);
    }

    /// Problem 5: the agent's own slow connections never stall its next one: past the cap, the connection idle
    /// the longest (here, one that sent half a head) gives its place up.
    #[test]
    fn half_sent_heads_never_stall_a_new_request() {
        let f = fixture(true);
        let mut slow = Vec::new();
        for _ in 0..MAX_CONNECTIONS + 8 {
            let mut s = f.connect();
            s.write_all(b"POST /v1/chat/completions HTTP/1.1\r\nHost: x\r\n").unwrap();
            slow.push(s);
        }
        let t0 = Instant::now();
        let mut s = f.connect();
        s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
        s.write_all(&post("/v1/chat/completions", "{}")).unwrap();
        let mut out = Vec::new();
        let _ = s.read_to_end(&mut out);
        let out = String::from_utf8_lossy(&out);
        assert!(out.starts_with("HTTP/1.1 200") && out.contains(r#""content":"hi""#), "{out}");
        assert!(t0.elapsed() < Duration::from_secs(2), "{:?}", t0.elapsed());
        // The oldest slow connection was closed to make room.
        slow[0].set_read_timeout(Some(Duration::from_secs(2))).unwrap();
        assert_eq!(slow[0].read(&mut [0u8; 16]).unwrap_or(0), 0);
    }

    /// When every place holds a request or a tunnel in progress, a new connection is answered 503 at once.
    #[test]
    fn a_full_gateway_answers_503_at_once() {
        let f = fixture_with(true, 2, |_, _| {});
        let _tunnels = [f.tunnel(), f.tunnel()];
        let t0 = Instant::now();
        let out = f.exchange(&get("/v1/models"));
        assert!(out.starts_with("HTTP/1.1 503") && out.contains("too many connections"), "{out}");
        assert!(t0.elapsed() < Duration::from_secs(2));
        let rs = f.records(1);
        assert_eq!((rs[0].mode, rs[0].status, rs[0].cause), (Mode::Refused, 503, Cause::Gateway));
    }

    #[test]
    fn relay_passes_bytes_and_half_closes() {
        let f = fixture(true);
        let sock = f.dir.path().join("mcp.sock");
        let relay = relay_unix_to_tcp(StdUnixListener::bind(&sock).unwrap(), f.echo).unwrap();
        for _ in 0..3 {
            let mut s = StdUnixStream::connect(&sock).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
            s.write_all(b"hello mcp").unwrap();
            s.shutdown(std::net::Shutdown::Write).unwrap();
            let mut out = Vec::new();
            s.read_to_end(&mut out).unwrap();
            assert_eq!(out, b"hello mcp");
        }
        relay.stop();
        assert!(StdUnixStream::connect(&sock).is_err_and(|e| e.kind() == std::io::ErrorKind::ConnectionRefused));
    }

    /// The relay serves its connections at once, each on its own; past the cap the one quiet the longest goes.
    #[test]
    fn the_relay_serves_connections_at_once_and_makes_room() {
        let f = fixture(true);
        let sock = f.dir.path().join("mcp.sock");
        let relay = relay_capped(StdUnixListener::bind(&sock).unwrap(), f.echo, None, 3).unwrap();
        let open = || {
            let s = StdUnixStream::connect(&sock).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
            s
        };
        let echo = |s: &mut StdUnixStream| {
            s.write_all(b"ping").unwrap();
            let mut b = [0u8; 4];
            s.read_exact(&mut b).unwrap();
            assert_eq!(&b, b"ping");
        };
        let mut quiet = open();
        echo(&mut quiet);
        std::thread::sleep(Duration::from_millis(20));
        let (mut a, mut b) = (open(), open());
        echo(&mut a);
        echo(&mut b);
        let mut d = open();
        echo(&mut d);
        assert_eq!(quiet.read(&mut [0u8; 4]).unwrap_or(0), 0, "the quietest connection gave its place up");
        echo(&mut a);
        relay.stop();
    }

    /// The relay's connections come from the agent's own loopback address, which the server sees as the peer.
    #[test]
    fn relayed_connections_come_from_the_given_loopback_address() {
        let dir = tempfile::tempdir().unwrap();
        let server = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let target = server.local_addr().unwrap();
        let sock = dir.path().join("mcp.sock");
        let source: IpAddr = "127.31.7.9".parse().unwrap();
        let relay = relay_unix_to_tcp_from(StdUnixListener::bind(&sock).unwrap(), target, Some(source)).unwrap();
        let _client = StdUnixStream::connect(&sock).unwrap();
        let (_conn, peer) = server.accept().unwrap();
        assert_eq!(peer.ip(), source);
        relay.stop();
    }

    #[test]
    fn usage_survives_bodies_larger_than_what_is_kept() {
        // An Anthropic stream of ~1 MiB: its input counts lead, its output count trails.
        let mut c = Capture { sse: true, ..Capture::default() };
        c.push(b"event: message_start\ndata: {\"type\":\"message_start\",\"message\":{\"usage\":{\"input_tokens\":7,\"cache_read_input_tokens\":70,\"output_tokens\":1}}}\n\n");
        let delta = "event: content_block_delta\ndata: {\"type\":\"content_block_delta\",\"delta\":{\"text\":\"xxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx\"}}\n\n";
        for _ in 0..10_000 {
            c.push(delta.as_bytes());
        }
        c.push(b"event: message_delta\ndata: {\"type\":\"message_delta\",\"usage\":{\"output_tokens\":900}}\n\n");
        assert!(c.head.len() + c.tail.len() <= HEAD_KEEP + 2 * TAIL_KEEP && c.total > 1 << 20);
        let u = c.usage().unwrap();
        assert_eq!((u.counts.input_tokens, u.counts.cached_input_tokens, u.counts.output_tokens, u.counts.total_tokens), (Some(7), Some(70), Some(900), Some(907)));
        // A JSON completion of ~1 MiB: `usage` comes last.
        let mut c = Capture::default();
        c.push(br#"{"choices":[{"message":{"content":""#);
        for _ in 0..20_000 {
            c.push(b"yyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyy \\\"usage\\\": {\\\"prompt_tokens\\\": 1}");
        }
        c.push(br#""}}],"usage":{"prompt_tokens":123,"completion_tokens":45,"total_tokens":168}}"#);
        let u = c.usage().unwrap();
        assert_eq!((u.api.as_str(), u.counts.input_tokens, u.counts.output_tokens, u.counts.total_tokens), ("openai_chat", Some(123), Some(45), Some(168)));
        // Compressed against our asking: not read. No usage at all: none.
        let mut c = Capture { encoded: true, ..Capture::default() };
        c.push(br#"{"usage":{"prompt_tokens":1}}"#);
        assert_eq!(c.usage(), None);
        let mut c = Capture::default();
        c.push(br#"{"object":"list","data":[]}"#);
        assert_eq!(c.usage(), None);
        // DeepSeek's cache hits, Moonshot's top-level cached_tokens.
        let mut acc = UsageAcc::default();
        acc.feed(&serde_json::json!({"usage": {"prompt_tokens": 10, "completion_tokens": 2, "prompt_cache_hit_tokens": 6}}));
        assert_eq!(acc.result().unwrap().counts.cached_input_tokens, Some(6));
    }

    /// An https upstream goes through rustls with this machine's roots: here a server that only echoes, so the
    /// handshake fails and the agent gets a 502 that says so: the upstream's failure.
    #[test]
    fn an_https_upstream_is_reached_over_tls() {
        let f = fixture(true);
        let sock = f.dir.path().join("tls.sock");
        let records = f.dir.path().join("tls.jsonl");
        let cfg = GatewayConfig {
            upstream: Some(url::Url::parse(&format!("https://{}/v1", f.echo)).unwrap()),
            routes: routes(),
            records: records.clone(),
            ..GatewayConfig::default()
        };
        let gateway = start(StdUnixListener::bind(&sock).unwrap(), cfg).unwrap();
        let mut s = StdUnixStream::connect(&sock).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
        s.write_all(&post("/v1/chat/completions", "{}")).unwrap();
        let mut out = String::new();
        let _ = s.read_to_string(&mut out);
        assert!(out.starts_with("HTTP/1.1 502") && out.contains("TLS"), "{out}");
        gateway.stop();
        let r: Record = serde_json::from_str(std::fs::read_to_string(&records).unwrap().trim()).unwrap();
        assert_eq!((r.mode, r.status, r.host.as_str(), r.cause), (Mode::Reverse, 502, f.echo.to_string().as_str(), Cause::Upstream));
        assert!(r.error.is_some_and(|e| e.contains("TLS")));
        assert!(last_model_api_failure(&records).is_some_and(|w| w.contains("answered 502")));
    }

    #[test]
    fn upstream_urls_are_checked() {
        let u = parse_upstream(&url::Url::parse("https://API.Example.com/v1/").unwrap()).unwrap();
        assert_eq!((u.tls, u.host.as_str(), u.port, u.authority.as_str()), (true, "api.example.com", 443, "api.example.com"));
        let u = parse_upstream(&url::Url::parse("http://[::1]:8080/x").unwrap()).unwrap();
        assert_eq!((u.tls, u.host.as_str(), u.port, u.authority.as_str()), (false, "::1", 8080, "[::1]:8080"));
        assert!(parse_upstream(&url::Url::parse("https://user:pw@api.example.com/v1").unwrap()).is_err());
        assert!(parse_upstream(&url::Url::parse("ftp://api.example.com/").unwrap()).is_err());
        let err = parse_upstream(&url::Url::parse("https://user:pw@api.example.com/v1?key=SECRET").unwrap()).unwrap_err().to_string();
        assert!(!err.contains("SECRET") && !err.contains("pw"), "{err}");
    }
}
