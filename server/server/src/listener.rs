//! Every listener of the server, and what keeps a flood of connections from taking the process down.
//!
//! An agent shares the server's loopback: without limits it could open connections until the process has no
//! file descriptor left, and the next episode step (a render, a record, the store) would fail. So:
//!
//! - **File descriptors**: [`raise_nofile_limit`] lifts the soft `RLIMIT_NOFILE` to the hard limit at start, and
//!   the connection cap keeps a reserve below it (at least 1024 descriptors, or a quarter) for the episodes' own
//!   work. An `accept` that fails with `EMFILE`/`ENFILE` backs off briefly instead of spinning.
//! - **Caps**: at most `--max-connections` open connections in total and `--max-connections-per-ip` per peer
//!   address. A connection over a cap takes the place of the oldest connection that has no request in progress
//!   (one that never completed a request head first: fresh, half-sent, or a request body trickling in for
//!   longer than the header timeout; then idle keep-alive ones), so a flood cannot lock real clients out: their
//!   requests arrive at once and are never cut. When every connection is busy, the new one is refused.
//! - **Timeouts**: a fresh connection must complete a request head within `--header-read-timeout-s`, and so must
//!   any request head once its first byte arrived (slowloris); a keep-alive connection with no request in
//!   progress is closed after `--idle-timeout-s`; a request body must arrive whole within
//!   `--body-read-timeout-s`. A request in progress has no time limit (an `osc_sequence` call may take minutes,
//!   an MCP SSE stream lives as long as its session), nor has an upgraded connection (WebSockets).
//! - **Loopback on both families**: a server on `127.0.0.1:PORT` (or `0.0.0.0:PORT`) also listens on
//!   `[::1]:PORT`, and one on `[::1]:PORT` on `127.0.0.1:PORT`, so no other local process can take the same
//!   port on the other loopback address and answer clients that resolve `localhost` there ([`bind`]).
//!
//! HTTP/1.1 only (with upgrades): no client of this server speaks cleartext HTTP/2, and one connection
//! multiplexing many streams would escape the per-connection accounting above.
use std::collections::{BTreeMap, HashMap};
use std::convert::Infallible;
use std::future::Future;
use std::io;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use anyhow::{Context as _, bail};
use axum::Router;
use axum::body::{Body, Bytes};
use axum::extract::ConnectInfo;
use axum::http::{Request, Response, StatusCode};
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, watch};
use tokio::time::{Instant, Sleep, sleep_until};
use tower::ServiceExt;

pub const DEFAULT_MAX_CONNECTIONS: usize = 4096;
pub const DEFAULT_MAX_CONNECTIONS_PER_IP: usize = 256;
pub const DEFAULT_HEADER_READ_TIMEOUT_S: f64 = 10.0;
pub const DEFAULT_IDLE_TIMEOUT_S: f64 = 30.0;
pub const DEFAULT_BODY_READ_TIMEOUT_S: f64 = 30.0;
/// File descriptors kept for the episodes' own work (renders, records, the store, video encoders) at least.
pub const MIN_FD_RESERVE: u64 = 1024;
/// How long the accept loop sleeps when the process (or the system) is out of file descriptors.
const ACCEPT_BACKOFF: Duration = Duration::from_millis(100);
/// Displaced connections whose tasks have not closed them yet, at most (plus one per listener): their descriptors
/// stay open until their tasks run, so on a busy machine a flood could hold any number over the cap. At this
/// many the accept loops wait for those tasks before they accept more (new connections wait in the kernel's
/// backlog, holding no descriptor of the server's; none is refused for it).
const MAX_PENDING_EVICTIONS: usize = 32;
/// At most one warning about refused or displaced connections per this period.
const WARN_PERIOD: Duration = Duration::from_secs(10);

/// Connection limits of `serve` (and of every in-process server: [`ConnLimits::default`]).
#[derive(clap::Args, Debug, Clone, Copy, PartialEq)]
pub struct ConnLimits {
    /// Most open connections in total, on all listeners together; lowered to what the file-descriptor limit
    /// allows after a reserve for the episodes (the larger of 1024 descriptors and a quarter of the limit).
    #[arg(long, value_name = "N", default_value_t = DEFAULT_MAX_CONNECTIONS)]
    pub max_connections: usize,
    /// Most open connections from one peer address (all local agents share 127.0.0.1 and ::1).
    #[arg(long, value_name = "N", default_value_t = DEFAULT_MAX_CONNECTIONS_PER_IP)]
    pub max_connections_per_ip: usize,
    /// Seconds a client has to send a whole request head, counted from the connection's start or from the
    /// head's first byte.
    #[arg(long, value_name = "SECONDS", default_value_t = DEFAULT_HEADER_READ_TIMEOUT_S)]
    pub header_read_timeout_s: f64,
    /// Seconds a keep-alive connection may wait for its next request (a request in progress never times out).
    #[arg(long, value_name = "SECONDS", default_value_t = DEFAULT_IDLE_TIMEOUT_S)]
    pub idle_timeout_s: f64,
    /// Seconds a request body may take to arrive whole.
    #[arg(long, value_name = "SECONDS", default_value_t = DEFAULT_BODY_READ_TIMEOUT_S)]
    pub body_read_timeout_s: f64,
}

impl Default for ConnLimits {
    fn default() -> Self {
        Self {
            max_connections: DEFAULT_MAX_CONNECTIONS,
            max_connections_per_ip: DEFAULT_MAX_CONNECTIONS_PER_IP,
            header_read_timeout_s: DEFAULT_HEADER_READ_TIMEOUT_S,
            idle_timeout_s: DEFAULT_IDLE_TIMEOUT_S,
            body_read_timeout_s: DEFAULT_BODY_READ_TIMEOUT_S,
        }
    }
}

/// The limits in force: [`ConnLimits`] checked, with the total cap fitted to the file-descriptor limit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    pub max_total: usize,
    pub max_per_ip: usize,
    pub header_read: Duration,
    pub idle: Duration,
    pub body_read: Duration,
}

fn seconds(name: &str, s: f64) -> anyhow::Result<Duration> {
    if !(0.1..=86_400.0).contains(&s) {
        bail!("--{name} must be 0.1 to 86400 seconds (got {s})");
    }
    Ok(Duration::from_secs_f64(s))
}

/// The connections a process with `nofile` descriptors may hold: all but a reserve of the larger of
/// [`MIN_FD_RESERVE`] and a quarter of the limit (half the limit when that reserve would leave less).
pub fn connection_room(nofile: u64) -> usize {
    let reserve = (nofile / 4).max(MIN_FD_RESERVE);
    let room = if nofile > reserve.saturating_mul(2) { nofile - reserve } else { nofile / 2 };
    usize::try_from(room).unwrap_or(usize::MAX).max(1)
}

impl ConnLimits {
    /// The limits for a process whose file-descriptor limit is `nofile`.
    pub fn resolve(&self, nofile: u64) -> anyhow::Result<Limits> {
        if self.max_connections == 0 || self.max_connections_per_ip == 0 {
            bail!("--max-connections and --max-connections-per-ip must be at least 1");
        }
        Ok(Limits {
            max_total: self.max_connections.min(connection_room(nofile)),
            max_per_ip: self.max_connections_per_ip,
            header_read: seconds("header-read-timeout-s", self.header_read_timeout_s)?,
            idle: seconds("idle-timeout-s", self.idle_timeout_s)?,
            body_read: seconds("body-read-timeout-s", self.body_read_timeout_s)?,
        })
    }
}

/// Raises this process's soft `RLIMIT_NOFILE` to its hard limit; returns the soft limit now in force.
pub fn raise_nofile_limit() -> u64 {
    let mut lim = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
    // SAFETY: getrlimit/setrlimit with a valid pointer to a local struct.
    unsafe {
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) != 0 {
            return 1024;
        }
        if lim.rlim_cur < lim.rlim_max {
            let raised = libc::rlimit { rlim_cur: lim.rlim_max, rlim_max: lim.rlim_max };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &raised) == 0 {
                lim.rlim_cur = lim.rlim_max;
            }
        }
    }
    lim.rlim_cur
}

/// The other loopback address a server on `ip` must hold as well, if any.
fn loopback_twin(ip: IpAddr) -> Option<IpAddr> {
    match ip {
        IpAddr::V4(v4) if v4 == Ipv4Addr::LOCALHOST || v4.is_unspecified() => Some(IpAddr::V6(Ipv6Addr::LOCALHOST)),
        IpAddr::V6(v6) if v6 == Ipv6Addr::LOCALHOST => Some(IpAddr::V4(Ipv4Addr::LOCALHOST)),
        _ => None,
    }
}

/// Whether binding failed because the machine has no such address family or address (IPv6 disabled).
fn family_unavailable(e: &io::Error) -> bool {
    matches!(e.raw_os_error(), Some(libc::EAFNOSUPPORT | libc::EADDRNOTAVAIL | libc::EPROTONOSUPPORT))
}

/// Binds `addr` and, for a loopback address (or `0.0.0.0`), the same port on the other loopback address
/// ([`loopback_twin`]); the first listener is `addr`'s. With port 0 a port free on both is chosen. Where the
/// machine has no IPv6 (or IPv4) loopback, says so and goes on with the one listener; where another process
/// holds the twin address on a fixed port, fails: clients reaching the server by `localhost` could reach it.
pub async fn bind(addr: SocketAddr) -> anyhow::Result<Vec<TcpListener>> {
    const PORT_TRIES: usize = 16;
    for _ in 0..PORT_TRIES {
        let first = TcpListener::bind(addr).await.with_context(|| format!("cannot bind {addr}"))?;
        let Some(twin_ip) = loopback_twin(addr.ip()) else { return Ok(vec![first]) };
        let twin = SocketAddr::new(twin_ip, first.local_addr()?.port());
        match TcpListener::bind(twin).await {
            Ok(second) => return Ok(vec![first, second]),
            Err(e) if family_unavailable(&e) => {
                eprintln!("libero-agent serve: no {twin_ip} on this machine ({e}); listening on {addr} only");
                return Ok(vec![first]);
            }
            Err(e) if e.kind() == io::ErrorKind::AddrInUse && addr.port() == 0 => continue,
            Err(e) => bail!(
                "cannot bind {twin} beside {addr}: {e}; another process holds this port on the other loopback \
                 address and would answer clients that reach the server as localhost; pick another port"
            ),
        }
    }
    bail!("no port is free on both loopback addresses after {PORT_TRIES} tries")
}

// ---------------------------------------------------------------------------------------------------------
// Per-connection state

/// Where a connection stands, for its timeouts and for choosing which one a new connection displaces.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    /// Waiting for a request head, nothing of it read yet (fresh, or idle after a response).
    Waiting,
    /// Part of a request head arrived.
    Head,
    /// A request is in progress (from its complete head until its response body is dropped).
    Busy { body_done: bool },
    /// Handed to a WebSocket (or another upgrade): none of the HTTP timeouts apply.
    Upgraded,
}

#[derive(Debug)]
struct Track {
    phase: Phase,
    since: Instant,
    /// Request heads completed on this connection.
    served: u64,
}

struct ConnState {
    track: Mutex<Track>,
    /// Notified when the connection is displaced by a newer one over a cap.
    evict: Notify,
}

impl ConnState {
    fn new() -> Self {
        Self { track: Mutex::new(Track { phase: Phase::Waiting, since: Instant::now(), served: 0 }), evict: Notify::new() }
    }

    fn with<R>(&self, f: impl FnOnce(&mut Track) -> R) -> Option<R> {
        self.track.lock().ok().map(|mut t| f(&mut t))
    }

    fn bytes_arrived(&self) {
        self.with(|t| {
            if t.phase == Phase::Waiting {
                *t = Track { phase: Phase::Head, since: Instant::now(), served: t.served };
            }
        });
    }

    fn request_started(&self, body_done: bool) {
        self.with(|t| *t = Track { phase: Phase::Busy { body_done }, since: Instant::now(), served: t.served + 1 });
    }

    fn body_finished(&self) {
        self.with(|t| {
            if let Phase::Busy { body_done } = &mut t.phase {
                *body_done = true;
            }
        });
    }

    fn request_ended(&self) {
        self.with(|t| {
            if matches!(t.phase, Phase::Busy { .. }) {
                *t = Track { phase: Phase::Waiting, since: Instant::now(), served: t.served };
            }
        });
    }

    fn upgraded(&self) {
        self.with(|t| t.phase = Phase::Upgraded);
    }

    /// When a read that is waiting must give up, if ever.
    fn read_deadline(&self, limits: &Limits) -> Option<Instant> {
        self.with(|t| match t.phase {
            Phase::Waiting if t.served == 0 => Some(t.since + limits.header_read),
            Phase::Waiting => Some(t.since + limits.idle),
            Phase::Head => Some(t.since + limits.header_read),
            Phase::Busy { .. } | Phase::Upgraded => None,
        })
        .flatten()
    }

    /// How readily this connection gives way to a new one: 0 first (it never completed a request head, or its
    /// request body has trickled for longer than the header timeout), then 1 (idle keep-alive); `None` while a
    /// request is in progress or the connection is upgraded.
    fn displace_rank(&self, limits: &Limits) -> Option<u8> {
        self.with(|t| match t.phase {
            Phase::Waiting if t.served == 0 => Some(0),
            Phase::Head => Some(0),
            Phase::Busy { body_done: false } if t.since.elapsed() > limits.header_read => Some(0),
            Phase::Waiting => Some(1),
            Phase::Busy { .. } | Phase::Upgraded => None,
        })
        .flatten()
    }
}

// ---------------------------------------------------------------------------------------------------------
// The table of open connections

#[derive(Default)]
struct Table {
    next: u64,
    all: BTreeMap<u64, (IpAddr, Arc<ConnState>)>,
    per_ip: HashMap<IpAddr, BTreeMap<u64, Arc<ConnState>>>,
    /// Connections displaced (out of `all`) whose slots have not been dropped yet: their descriptors are open.
    evicting: usize,
}

impl Table {
    /// The connection a new one displaces: lowest rank, oldest first; among `ip`'s when given.
    fn victim(&self, ip: Option<IpAddr>, limits: &Limits) -> Option<u64> {
        let mut best: Option<(u8, u64)> = None;
        let mut consider = |seq: u64, state: &ConnState| -> bool {
            if let Some(rank) = state.displace_rank(limits)
                && best.is_none_or(|(r, _)| rank < r)
            {
                best = Some((rank, seq));
            }
            best.is_some_and(|(r, _)| r == 0)
        };
        match ip {
            Some(ip) => {
                for (seq, state) in self.per_ip.get(&ip).into_iter().flatten() {
                    if consider(*seq, state) {
                        break;
                    }
                }
            }
            None => {
                for (seq, (_, state)) in &self.all {
                    if consider(*seq, state) {
                        break;
                    }
                }
            }
        }
        best.map(|(_, seq)| seq)
    }

    fn remove(&mut self, seq: u64) -> Option<Arc<ConnState>> {
        let (ip, state) = self.all.remove(&seq)?;
        if let Some(m) = self.per_ip.get_mut(&ip) {
            m.remove(&seq);
            if m.is_empty() {
                self.per_ip.remove(&ip);
            }
        }
        Some(state)
    }
}

/// Counters of a serving run (what the warnings report).
#[derive(Default)]
struct Stats {
    accepted: AtomicU64,
    refused: AtomicU64,
    displaced: AtomicU64,
    timed_out: AtomicU64,
}

struct Registry {
    limits: Limits,
    table: Mutex<Table>,
    /// Told whenever a displaced connection's slot is dropped.
    evicted: Notify,
    stats: Stats,
    /// When the last warning was printed, and the counters it reported.
    warned: Mutex<Option<(Instant, u64, u64)>>,
}

/// Why a connection was not admitted.
#[derive(Debug)]
enum Refusal {
    PerIp,
    Total,
}

/// A connection's place in the table; dropping it frees the place (unless it was displaced already).
struct Slot {
    registry: Arc<Registry>,
    seq: u64,
}

impl Drop for Slot {
    fn drop(&mut self) {
        if let Ok(mut t) = self.registry.table.lock()
            && t.remove(self.seq).is_none()
        {
            // displaced earlier: its descriptor closes now
            t.evicting = t.evicting.saturating_sub(1);
            self.registry.evicted.notify_waiters();
        }
    }
}

impl Registry {
    fn new(limits: Limits) -> Self {
        Self { limits, table: Mutex::new(Table::default()), evicted: Notify::new(), stats: Stats::default(), warned: Mutex::new(None) }
    }

    fn pending_evictions(&self) -> usize {
        self.table.lock().map_or(0, |t| t.evicting)
    }

    /// Returns once fewer than [`MAX_PENDING_EVICTIONS`] displaced connections are still open.
    async fn until_evictions_caught_up(&self) {
        loop {
            // created before the check: a slot dropped in between still wakes it
            let dropped = self.evicted.notified();
            if self.pending_evictions() < MAX_PENDING_EVICTIONS {
                return;
            }
            dropped.await;
        }
    }

    /// A place for a new connection from `ip`, displacing an older one over a cap if one may give way.
    fn admit(self: &Arc<Self>, ip: IpAddr) -> Result<(Slot, Arc<ConnState>), Refusal> {
        let Ok(mut t) = self.table.lock() else { return Err(Refusal::Total) };
        let limits = &self.limits;
        let mut displaced = Vec::new();
        if t.per_ip.get(&ip).map_or(0, BTreeMap::len) >= limits.max_per_ip {
            let seq = t.victim(Some(ip), limits).ok_or(Refusal::PerIp)?;
            displaced.extend(t.remove(seq));
            t.evicting += 1;
        }
        if t.all.len() >= limits.max_total {
            let seq = t.victim(None, limits).ok_or(Refusal::Total)?;
            displaced.extend(t.remove(seq));
            t.evicting += 1;
        }
        let seq = t.next;
        t.next += 1;
        let state = Arc::new(ConnState::new());
        t.all.insert(seq, (ip, state.clone()));
        t.per_ip.entry(ip).or_default().insert(seq, state.clone());
        drop(t);
        for d in displaced {
            self.stats.displaced.fetch_add(1, Ordering::Relaxed);
            d.evict.notify_one();
        }
        self.stats.accepted.fetch_add(1, Ordering::Relaxed);
        Ok((Slot { registry: self.clone(), seq }, state))
    }

    /// Tells the operator, at most once per [`WARN_PERIOD`], that connections were refused or displaced.
    fn warn_if_limited(&self) {
        let refused = self.stats.refused.load(Ordering::Relaxed);
        let displaced = self.stats.displaced.load(Ordering::Relaxed);
        let Ok(mut warned) = self.warned.lock() else { return };
        let (last_refused, last_displaced) = warned.map_or((0, 0), |(_, r, d)| (r, d));
        if (refused, displaced) == (last_refused, last_displaced) || warned.is_some_and(|(at, _, _)| at.elapsed() < WARN_PERIOD) {
            return;
        }
        *warned = Some((Instant::now(), refused, displaced));
        let open = self.table.lock().map(|t| t.all.len()).unwrap_or(0);
        eprintln!(
            "warning: connection limits reached ({} in total, {} per address; {open} open): {} connection(s) refused \
             and {} idle or incomplete one(s) closed for newer ones so far",
            self.limits.max_total, self.limits.max_per_ip, refused, displaced
        );
    }
}

// ---------------------------------------------------------------------------------------------------------
// The connection's byte stream, with its read deadlines

/// A TCP stream that holds its connection's place in the table (so an upgraded connection, handed to a
/// WebSocket, still counts) and fails a read that waits past the connection's deadline.
struct Guarded {
    io: TcpStream,
    state: Arc<ConnState>,
    limits: Limits,
    registry: Arc<Registry>,
    sleep: Option<Pin<Box<Sleep>>>,
    _slot: Slot,
}

impl AsyncRead for Guarded {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        match Pin::new(&mut this.io).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                if buf.filled().len() > before {
                    this.state.bytes_arrived();
                }
                Poll::Ready(Ok(()))
            }
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
            Poll::Pending => {
                let Some(deadline) = this.state.read_deadline(&this.limits) else { return Poll::Pending };
                let sleep = this.sleep.get_or_insert_with(|| Box::pin(sleep_until(deadline)));
                if sleep.deadline() != deadline {
                    sleep.as_mut().reset(deadline);
                }
                match sleep.as_mut().poll(cx) {
                    Poll::Ready(()) => {
                        this.registry.stats.timed_out.fetch_add(1, Ordering::Relaxed);
                        Poll::Ready(Err(io::Error::new(io::ErrorKind::TimedOut, "no complete request in time")))
                    }
                    Poll::Pending => Poll::Pending,
                }
            }
        }
    }
}

impl AsyncWrite for Guarded {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write(cx, buf)
    }

    fn poll_write_vectored(self: Pin<&mut Self>, cx: &mut Context<'_>, bufs: &[io::IoSlice<'_>]) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

// ---------------------------------------------------------------------------------------------------------
// Bodies

/// A request body that must arrive whole by `deadline`; reports its end to the connection.
struct RequestBody {
    inner: Incoming,
    deadline: Instant,
    sleep: Option<Pin<Box<Sleep>>>,
    state: Arc<ConnState>,
}

impl http_body::Body for RequestBody {
    type Data = Bytes;
    type Error = axum::BoxError;

    fn poll_frame(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
        let this = self.get_mut();
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(None) => {
                this.state.body_finished();
                Poll::Ready(None)
            }
            Poll::Ready(Some(frame)) => {
                if this.inner.is_end_stream() {
                    this.state.body_finished();
                }
                Poll::Ready(Some(frame.map_err(Into::into)))
            }
            Poll::Pending => {
                let deadline = this.deadline;
                let sleep = this.sleep.get_or_insert_with(|| Box::pin(sleep_until(deadline)));
                match sleep.as_mut().poll(cx) {
                    Poll::Ready(()) => Poll::Ready(Some(Err("the request body did not arrive in time".into()))),
                    Poll::Pending => Poll::Pending,
                }
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// Ends its connection's request when dropped (the response body is done or abandoned).
struct InFlight(Arc<ConnState>);

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.request_ended();
    }
}

/// A response body that keeps its request in progress until hyper is done with it (an SSE stream for as
/// long as it runs).
struct ResponseBody {
    inner: Body,
    _in_flight: InFlight,
}

impl http_body::Body for ResponseBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
        Pin::new(&mut self.get_mut().inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// The router as one connection's hyper service.
#[derive(Clone)]
struct ConnService {
    router: Router,
    state: Arc<ConnState>,
    peer: SocketAddr,
    body_read: Duration,
}

impl hyper::service::Service<Request<Incoming>> for ConnService {
    type Response = Response<ResponseBody>;
    type Error = Infallible;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, Infallible>> + Send>>;

    fn call(&self, req: Request<Incoming>) -> Self::Future {
        let state = self.state.clone();
        state.request_started(http_body::Body::is_end_stream(req.body()));
        let in_flight = InFlight(state.clone());
        let deadline = Instant::now() + self.body_read;
        let mut req = req.map(|inner| Body::new(RequestBody { inner, deadline, sleep: None, state: state.clone() }));
        req.extensions_mut().insert(ConnectInfo(self.peer));
        let router = self.router.clone();
        Box::pin(async move {
            let resp = match router.oneshot(req).await {
                Ok(r) => r,
                Err(never) => match never {},
            };
            if resp.status() == StatusCode::SWITCHING_PROTOCOLS {
                state.upgraded();
            }
            Ok(resp.map(|inner| ResponseBody { inner, _in_flight: in_flight }))
        })
    }
}

// ---------------------------------------------------------------------------------------------------------
// Serving

/// Whether an `accept` error means the process or the system has no file descriptor left.
fn out_of_descriptors(e: &io::Error) -> bool {
    matches!(e.raw_os_error(), Some(libc::EMFILE | libc::ENFILE | libc::ENOBUFS | libc::ENOMEM))
}

/// Whether an `accept` error concerns only the connection being accepted.
fn connection_error(e: &io::Error) -> bool {
    matches!(e.kind(), io::ErrorKind::ConnectionRefused | io::ErrorKind::ConnectionAborted | io::ErrorKind::ConnectionReset)
        || matches!(e.raw_os_error(), Some(libc::EPROTO | libc::EPERM | libc::ENETDOWN | libc::EHOSTUNREACH))
}

/// The answer a refused connection gets (best effort, never waited for).
const REFUSED: &[u8] = b"HTTP/1.1 503 Service Unavailable\r\nConnection: close\r\nContent-Length: 0\r\nRetry-After: 1\r\n\r\n";

/// Serves `router` on `listeners` under `limits` until `shutdown` resolves, then stops accepting, lets
/// requests in progress finish (as `axum::serve`'s graceful shutdown does) and returns when every connection
/// task has ended. Connections handed to WebSockets are not waited for.
pub async fn serve(listeners: Vec<TcpListener>, router: Router, limits: Limits, shutdown: impl Future<Output = ()> + Send) {
    let registry = Arc::new(Registry::new(limits));
    let (stop_tx, stop_rx) = watch::channel(false);
    // Every connection task holds a sender; `recv` yields `None` once all of them ended.
    let (alive_tx, mut alive_rx) = tokio::sync::mpsc::channel::<()>(1);
    let mut accept_loops = Vec::new();
    for listener in listeners {
        let (registry, router, stop, alive) = (registry.clone(), router.clone(), stop_rx.clone(), alive_tx.clone());
        accept_loops.push(tokio::spawn(accept_loop(listener, registry, router, stop, alive)));
    }
    drop(alive_tx);
    shutdown.await;
    let _ = stop_tx.send(true);
    for l in accept_loops {
        let _ = l.await;
    }
    let _ = alive_rx.recv().await;
    let st = &registry.stats;
    let (refused, displaced) = (st.refused.load(Ordering::Relaxed), st.displaced.load(Ordering::Relaxed));
    if refused + displaced > 0 {
        eprintln!(
            "libero-agent serve: {} connection(s) served, {refused} refused and {displaced} closed for newer ones at the \
             connection limits, {} timed out waiting for a request",
            st.accepted.load(Ordering::Relaxed),
            st.timed_out.load(Ordering::Relaxed)
        );
    }
}

async fn accept_loop(
    listener: TcpListener,
    registry: Arc<Registry>,
    router: Router,
    mut stop: watch::Receiver<bool>,
    alive: tokio::sync::mpsc::Sender<()>,
) {
    let mut said_exhausted: Option<Instant> = None;
    loop {
        let accepted = tokio::select! {
            biased;
            _ = stop.wait_for(|s| *s) => return,
            a = async {
                registry.until_evictions_caught_up().await;
                listener.accept().await
            } => a,
        };
        let (stream, peer) = match accepted {
            Ok(a) => a,
            Err(e) if connection_error(&e) => continue,
            Err(e) => {
                // Out of descriptors (or another transient failure): the pending connections wait in the
                // kernel's backlog until closed ones free descriptors; never spin, never stop serving.
                if said_exhausted.is_none_or(|at| at.elapsed() > WARN_PERIOD) {
                    let what = if out_of_descriptors(&e) { "out of file descriptors" } else { "accept failed" };
                    eprintln!("warning: {what} ({e}); accepting again in {ACCEPT_BACKOFF:?}");
                    said_exhausted = Some(Instant::now());
                }
                tokio::time::sleep(ACCEPT_BACKOFF).await;
                continue;
            }
        };
        let ip = peer.ip().to_canonical();
        let (slot, state) = match registry.admit(ip) {
            Ok(a) => a,
            Err(_why) => {
                registry.stats.refused.fetch_add(1, Ordering::Relaxed);
                let _ = stream.try_write(REFUSED);
                drop(stream);
                registry.warn_if_limited();
                continue;
            }
        };
        registry.warn_if_limited();
        let _ = stream.set_nodelay(true);
        let limits = registry.limits;
        let io = Guarded { io: stream, state: state.clone(), limits, registry: registry.clone(), sleep: None, _slot: slot };
        let service = ConnService { router: router.clone(), state: state.clone(), peer, body_read: limits.body_read };
        let (stop, alive) = (stop.clone(), alive.clone());
        tokio::spawn(serve_connection(io, service, state, limits, stop, alive));
    }
}

async fn serve_connection(
    io: Guarded,
    service: ConnService,
    state: Arc<ConnState>,
    limits: Limits,
    mut stop: watch::Receiver<bool>,
    _alive: tokio::sync::mpsc::Sender<()>,
) {
    let mut builder = hyper::server::conn::http1::Builder::new();
    // hyper's own head timeout backs up the connection's deadlines (which are always shorter).
    builder.timer(TokioTimer::new()).header_read_timeout(limits.idle + limits.header_read).keep_alive(true);
    let conn = builder.serve_connection(TokioIo::new(io), service).with_upgrades();
    let mut conn = std::pin::pin!(conn);
    let mut stopping = false;
    loop {
        tokio::select! {
            _ = conn.as_mut() => return,
            () = state.evict.notified() => return,
            _ = stop.wait_for(|s| *s), if !stopping => {
                stopping = true;
                conn.as_mut().graceful_shutdown();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(total: usize, per_ip: usize) -> Limits {
        Limits {
            max_total: total,
            max_per_ip: per_ip,
            header_read: Duration::from_secs(10),
            idle: Duration::from_secs(30),
            body_read: Duration::from_secs(30),
        }
    }

    #[test]
    fn the_cap_leaves_a_reserve_of_descriptors_for_the_episodes() {
        assert_eq!(connection_room(1024), 512);
        assert_eq!(connection_room(4096), 3072);
        assert_eq!(connection_room(20_000), 15_000);
        assert_eq!(ConnLimits::default().resolve(1_048_576).unwrap().max_total, DEFAULT_MAX_CONNECTIONS);
        assert_eq!(ConnLimits::default().resolve(1024).unwrap().max_total, 512);
        assert!(ConnLimits { max_connections_per_ip: 0, ..ConnLimits::default() }.resolve(4096).is_err());
        assert!(ConnLimits { idle_timeout_s: 0.0, ..ConnLimits::default() }.resolve(4096).is_err());
    }

    #[test]
    fn raising_the_descriptor_limit_reaches_the_hard_limit() {
        let soft = raise_nofile_limit();
        let mut lim = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
        // SAFETY: valid pointer to a local struct.
        assert_eq!(unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) }, 0);
        assert_eq!(soft, lim.rlim_cur);
        assert_eq!(lim.rlim_cur, lim.rlim_max);
    }

    #[tokio::test]
    async fn a_new_connection_displaces_the_oldest_that_never_sent_a_request_and_never_a_busy_one() {
        let registry = Arc::new(Registry::new(limits(100, 3)));
        let ip: IpAddr = Ipv4Addr::LOCALHOST.into();
        let (_a, a) = registry.admit(ip).unwrap();
        let (_b, b) = registry.admit(ip).unwrap();
        let (_c, c) = registry.admit(ip).unwrap();
        // `a` is busy (a long call), `b` idle after one request, `c` fresh: `c` gives way first, then `b`.
        a.request_started(true);
        b.request_started(true);
        b.request_ended();
        let (_d, d) = registry.admit(ip).unwrap();
        assert!(tokio::time::timeout(Duration::from_millis(10), c.evict.notified()).await.is_ok());
        d.request_started(false);
        let (_e, _) = registry.admit(ip).unwrap();
        assert!(tokio::time::timeout(Duration::from_millis(10), b.evict.notified()).await.is_ok());
        // Now `a` and `d` are busy and `e` is fresh: `e` gives way; once all are busy, the next is refused.
        let (_f, f) = registry.admit(ip).unwrap();
        f.request_started(true);
        assert!(matches!(registry.admit(ip), Err(Refusal::PerIp)));
        // Another address has its own quota; the total cap counts all of them.
        let other: IpAddr = Ipv6Addr::LOCALHOST.into();
        assert!(registry.admit(other).is_ok());
        assert_eq!(registry.table.lock().unwrap().all.len(), 3);
    }

    #[tokio::test]
    async fn the_total_cap_displaces_across_addresses_and_a_dropped_slot_frees_its_place() {
        let registry = Arc::new(Registry::new(limits(2, 10)));
        let (slot_a, _) = registry.admit("127.0.0.1".parse().unwrap()).unwrap();
        let (_b, b) = registry.admit("127.0.0.2".parse().unwrap()).unwrap();
        b.request_started(true);
        let (slot_c, c) = registry.admit("127.0.0.3".parse().unwrap()).unwrap();
        c.request_started(true);
        assert_eq!(registry.table.lock().unwrap().all.len(), 2);
        assert!(matches!(registry.admit("127.0.0.4".parse().unwrap()), Err(Refusal::Total)));
        drop(slot_a); // displaced already: nothing changes
        c.request_ended();
        drop(slot_c);
        assert!(registry.admit("127.0.0.4".parse().unwrap()).is_ok());
    }

    #[tokio::test]
    async fn displaced_connections_not_closed_yet_hold_the_accept_loops_back_until_one_closes() {
        let registry = Arc::new(Registry::new(limits(4, 1000)));
        let ip = |n: usize| format!("10.0.{}.{}", n / 250, n % 250).parse::<IpAddr>().unwrap();
        // Each new connection displaces one that never sent a request; the displaced slots are kept (their
        // connection tasks have not run yet), so their descriptors are still open.
        let mut slots: Vec<Slot> = (0..4 + MAX_PENDING_EVICTIONS).map(|n| registry.admit(ip(n)).unwrap().0).collect();
        assert_eq!(registry.pending_evictions(), MAX_PENDING_EVICTIONS);
        let caught_up = tokio::time::timeout(Duration::from_millis(200), registry.until_evictions_caught_up());
        assert!(caught_up.await.is_err(), "the accept loops wait while that many are pending");
        let waiting = tokio::spawn({
            let registry = registry.clone();
            async move { registry.until_evictions_caught_up().await }
        });
        tokio::time::sleep(Duration::from_millis(50)).await;
        drop(slots.remove(0)); // a displaced connection's task closes it
        tokio::time::timeout(Duration::from_secs(5), waiting).await.expect("woken by the closed one").unwrap();
        assert_eq!(registry.pending_evictions(), MAX_PENDING_EVICTIONS - 1);
        drop(slots.remove(0));
        registry.until_evictions_caught_up().await;
        // the live connections' slots leave no pending eviction behind
        drop(slots);
        assert_eq!(registry.pending_evictions(), 0);
    }

    #[tokio::test]
    async fn deadlines_follow_the_phase_of_the_connection() {
        let l = Limits { header_read: Duration::from_millis(50), ..limits(10, 10) };
        let s = ConnState::new();
        let t0 = s.track.lock().unwrap().since;
        assert_eq!(s.read_deadline(&l), Some(t0 + l.header_read));
        assert_eq!(s.displace_rank(&l), Some(0));
        s.bytes_arrived();
        let t1 = s.track.lock().unwrap().since;
        assert_eq!((s.read_deadline(&l), s.displace_rank(&l)), (Some(t1 + l.header_read), Some(0)));
        s.request_started(false);
        assert_eq!((s.read_deadline(&l), s.displace_rank(&l)), (None, None));
        tokio::time::sleep(l.header_read + Duration::from_millis(20)).await;
        // A body trickling for longer than a head may take gives way first.
        assert_eq!(s.displace_rank(&l), Some(0));
        s.body_finished();
        assert_eq!(s.displace_rank(&l), None);
        s.request_ended();
        let t2 = s.track.lock().unwrap().since;
        assert_eq!((s.read_deadline(&l), s.displace_rank(&l)), (Some(t2 + l.idle), Some(1)));
        s.request_started(true);
        s.upgraded();
        s.request_ended();
        assert_eq!((s.read_deadline(&l), s.displace_rank(&l)), (None, None));
    }

    /// Serving over real sockets, with short timeouts.
    mod served {
        use super::super::*;
        use axum::extract::ws::{WebSocket, WebSocketUpgrade};
        use axum::routing::{get, post};
        use tokio::io::{AsyncReadExt, AsyncWriteExt};

        const HEADER: Duration = Duration::from_millis(500);
        const IDLE: Duration = Duration::from_millis(1500);
        const BODY: Duration = Duration::from_millis(1000);
        /// Longer than every timeout above.
        const LONG: Duration = Duration::from_millis(2500);

        /// Three chunks, [`LONG`] / 3 apart.
        struct Trickle {
            left: u8,
            sleep: Pin<Box<Sleep>>,
        }

        impl http_body::Body for Trickle {
            type Data = Bytes;
            type Error = Infallible;
            fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<http_body::Frame<Bytes>, Infallible>>> {
                if self.left == 0 {
                    return Poll::Ready(None);
                }
                std::task::ready!(self.sleep.as_mut().poll(cx));
                self.left -= 1;
                let next = Instant::now() + LONG / 3;
                self.sleep.as_mut().reset(next);
                Poll::Ready(Some(Ok(http_body::Frame::data(Bytes::from_static(b"chunk\n")))))
            }
        }

        async fn echo(mut socket: WebSocket) {
            while let Some(Ok(msg)) = socket.recv().await {
                if socket.send(msg).await.is_err() {
                    break;
                }
            }
        }

        async fn start(per_ip: usize) -> SocketAddr {
            let router = Router::new()
                .route("/ok", get(|| async { "ok" }))
                .route(
                    "/slow",
                    get(|| async {
                        tokio::time::sleep(LONG).await;
                        "slow"
                    }),
                )
                .route("/stream", get(|| async { Body::new(Trickle { left: 3, sleep: Box::pin(sleep_until(Instant::now())) }) }))
                .route("/echo", post(|body: Bytes| async move { body }))
                .route("/ws", get(|ws: WebSocketUpgrade| async move { ws.on_upgrade(echo) }));
            let limits = Limits { max_total: 100, max_per_ip: per_ip, header_read: HEADER, idle: IDLE, body_read: BODY };
            let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
            let addr = listener.local_addr().unwrap();
            tokio::spawn(serve(vec![listener], router, limits, std::future::pending()));
            addr
        }

        /// Reads until the server closes the connection (or `within` passes); all bytes read, and whether it closed.
        async fn read_until_closed(s: &mut TcpStream, within: Duration) -> (Vec<u8>, bool) {
            let mut all = Vec::new();
            let mut buf = [0u8; 4096];
            let deadline = Instant::now() + within;
            loop {
                match tokio::time::timeout_at(deadline, s.read(&mut buf)).await {
                    Err(_) => return (all, false),
                    Ok(Ok(0)) | Ok(Err(_)) => return (all, true),
                    Ok(Ok(n)) => all.extend_from_slice(&buf[..n]),
                }
            }
        }

        /// Reads one response (headers and a `Content-Length` body) from a kept-alive connection.
        async fn read_response(s: &mut TcpStream) -> String {
            let mut all = Vec::new();
            let mut buf = [0u8; 4096];
            loop {
                let text = String::from_utf8_lossy(&all).into_owned();
                if let Some(end) = text.find("\r\n\r\n") {
                    let len = text[..end]
                        .lines()
                        .find_map(|l| l.to_ascii_lowercase().strip_prefix("content-length:").map(|v| v.trim().parse::<usize>().unwrap()))
                        .unwrap_or(0);
                    if all.len() >= end + 4 + len {
                        return text;
                    }
                }
                let n = tokio::time::timeout(LONG * 2, s.read(&mut buf)).await.unwrap().unwrap();
                assert!(n > 0, "closed mid-response: {}", String::from_utf8_lossy(&all));
                all.extend_from_slice(&buf[..n]);
            }
        }

        fn get_request(path: &str) -> String {
            format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        }

        #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
        async fn silent_and_trickling_heads_are_closed_after_the_header_timeout() {
            let addr = start(16).await;
            let t = Instant::now();
            let mut silent = TcpStream::connect(addr).await.unwrap();
            let (_, closed) = read_until_closed(&mut silent, LONG).await;
            assert!(closed && t.elapsed() >= HEADER - Duration::from_millis(50), "{:?}", t.elapsed());
            // A byte every 100 ms keeps the connection busy reading, but the head never completes.
            let mut slow = TcpStream::connect(addr).await.unwrap();
            let t = Instant::now();
            let head = get_request("/ok");
            let mut closed_after = None;
            for b in head.as_bytes()[..head.len() - 2].iter() {
                if slow.write_all(&[*b]).await.is_err() {
                    closed_after = Some(t.elapsed());
                    break;
                }
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            if closed_after.is_none() {
                let (_, closed) = read_until_closed(&mut slow, LONG).await;
                assert!(closed);
                closed_after = Some(t.elapsed());
            }
            assert!(closed_after.is_some_and(|d| d < HEADER + Duration::from_millis(1500)), "{closed_after:?}");
        }

        #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
        async fn requests_in_progress_and_upgraded_connections_outlive_every_timeout() {
            let addr = start(16).await;
            // A slow handler, then a slowly streamed body.
            for (path, expect, times) in [("/slow", "slow", 1), ("/stream", "chunk\n", 3)] {
                let mut s = TcpStream::connect(addr).await.unwrap();
                s.write_all(format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n").as_bytes()).await.unwrap();
                let (raw, closed) = read_until_closed(&mut s, LONG * 3).await;
                let text = String::from_utf8_lossy(&raw);
                assert!(closed && text.starts_with("HTTP/1.1 200"), "{text}");
                let body = text.split_once("\r\n\r\n").unwrap().1;
                assert_eq!(body.matches(expect).count(), times, "{text}");
            }
            // A WebSocket silent for longer than every timeout still echoes.
            let mut ws = TcpStream::connect(addr).await.unwrap();
            ws.write_all(
                b"GET /ws HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
                  Sec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n",
            )
            .await
            .unwrap();
            let mut buf = [0u8; 1024];
            let n = ws.read(&mut buf).await.unwrap();
            assert!(buf[..n].starts_with(b"HTTP/1.1 101"), "{}", String::from_utf8_lossy(&buf[..n]));
            tokio::time::sleep(LONG).await;
            let mask = [1u8, 2, 3, 4];
            let mut frame = vec![0x81, 0x80 | 2];
            frame.extend_from_slice(&mask);
            frame.extend(b"hi".iter().zip(mask.iter().cycle()).map(|(b, m)| b ^ m));
            ws.write_all(&frame).await.unwrap();
            let n = tokio::time::timeout(LONG, ws.read(&mut buf)).await.unwrap().unwrap();
            assert_eq!(&buf[..n], &[0x81, 2, b'h', b'i']);
        }

        #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
        async fn keep_alive_waits_the_idle_timeout_and_bodies_must_arrive_in_time() {
            let addr = start(16).await;
            let mut s = TcpStream::connect(addr).await.unwrap();
            s.write_all(get_request("/ok").as_bytes()).await.unwrap();
            assert!(read_response(&mut s).await.starts_with("HTTP/1.1 200"));
            // Longer than the header timeout, shorter than the idle one: still open.
            tokio::time::sleep(HEADER + Duration::from_millis(200)).await;
            s.write_all(get_request("/ok").as_bytes()).await.unwrap();
            assert!(read_response(&mut s).await.starts_with("HTTP/1.1 200"));
            let t = Instant::now();
            let (_, closed) = read_until_closed(&mut s, LONG * 2).await;
            assert!(closed && t.elapsed() >= IDLE - Duration::from_millis(100), "{:?}", t.elapsed());
            // A body that trickles in is cut at the body timeout.
            let mut s = TcpStream::connect(addr).await.unwrap();
            s.write_all(b"POST /echo HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 100\r\n\r\n").await.unwrap();
            let t = Instant::now();
            let mut answer = Vec::new();
            while t.elapsed() < LONG * 2 {
                if s.write_all(b"x").await.is_err() {
                    break;
                }
                let mut buf = [0u8; 1024];
                match tokio::time::timeout(Duration::from_millis(200), s.read(&mut buf)).await {
                    Ok(Ok(0)) | Ok(Err(_)) => break,
                    Ok(Ok(n)) => {
                        answer.extend_from_slice(&buf[..n]);
                        break;
                    }
                    Err(_) => {}
                }
            }
            let answer = String::from_utf8_lossy(&answer);
            assert!(t.elapsed() < BODY + Duration::from_millis(1000), "{:?}", t.elapsed());
            assert!(answer.is_empty() || answer.starts_with("HTTP/1.1 4"), "{answer}");
        }

        #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
        async fn over_the_cap_an_idle_connection_gives_way_and_busy_ones_never_do() {
            let addr = start(2).await;
            let mut idle = TcpStream::connect(addr).await.unwrap();
            let mut busy = TcpStream::connect(addr).await.unwrap();
            busy.write_all(get_request("/slow").as_bytes()).await.unwrap();
            tokio::time::sleep(Duration::from_millis(200)).await;
            // A third connection takes the idle one's place and is served.
            let mut third = TcpStream::connect(addr).await.unwrap();
            third.write_all(get_request("/slow").as_bytes()).await.unwrap();
            let (_, closed) = read_until_closed(&mut idle, Duration::from_millis(400)).await;
            assert!(closed, "the idle connection was kept");
            tokio::time::sleep(Duration::from_millis(200)).await;
            // Both places are busy now: a fourth is refused at once.
            let mut fourth = TcpStream::connect(addr).await.unwrap();
            let (raw, closed) = read_until_closed(&mut fourth, Duration::from_millis(400)).await;
            assert!(closed && raw.starts_with(b"HTTP/1.1 503"), "{}", String::from_utf8_lossy(&raw));
            for s in [&mut busy, &mut third] {
                assert!(read_response(s).await.starts_with("HTTP/1.1 200"));
            }
        }
    }

    #[test]
    fn loopback_twins() {
        assert_eq!(loopback_twin("127.0.0.1".parse().unwrap()), Some("::1".parse().unwrap()));
        assert_eq!(loopback_twin("0.0.0.0".parse().unwrap()), Some("::1".parse().unwrap()));
        assert_eq!(loopback_twin("::1".parse().unwrap()), Some("127.0.0.1".parse().unwrap()));
        assert_eq!(loopback_twin("10.1.2.3".parse().unwrap()), None);
        assert_eq!(loopback_twin("::".parse().unwrap()), None);
    }
}
