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
//!
//! The parts: `proxy` (the gateway's HTTP side: reverse proxy, forwards, `CONNECT` tunnels), `relay` (the MCP
//! relay), `records` (the records file and reading it back), `usage` (token accounting from responses) and
//! `conns` (the runtime thread and the connection cap both serve under).
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

mod conns;
mod proxy;
mod records;
mod relay;
mod usage;

pub use records::{Cause, Mode, Overflow, OverflowKind, Record, UsageSummary, last_model_api_failure, overflow_sidecar, summarize};
pub use relay::{Relay, relay_unix_to_tcp, relay_unix_to_tcp_from};
pub use usage::TokenUsage;
// Each part sees the others' items (and they this module's), as when they were one file.
use conns::*;
use proxy::*;
use records::*;
#[cfg(test)]
use relay::relay_capped;
use usage::*;

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

#[cfg(test)]
mod tests;
