//! The gateway's HTTP side: the reverse proxy to the model API (origin-form requests, only the routes), forwards
//! and `CONNECT` tunnels to allowed hosts, the bounds on heads and bodies, and the record of each request as it ends.
use super::*;

/// The upstream of reverse-proxied requests.
#[derive(Debug)]
pub(super) struct Upstream {
    pub(super) tls: bool,
    /// Without IPv6 brackets, as connected to and as the TLS server name.
    pub(super) host: String,
    pub(super) port: u16,
    /// The `Host` header.
    pub(super) authority: String,
}

pub(super) fn parse_upstream(url: &url::Url) -> Result<Upstream, GatewayError> {
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

pub(super) fn normal_host(h: &str) -> String {
    h.trim().trim_start_matches('[').trim_end_matches(']').to_ascii_lowercase()
}

pub(super) fn tls_connector() -> Result<tokio_rustls::TlsConnector, GatewayError> {
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

pub(super) struct Shared {
    pub(super) upstream: Option<Upstream>,
    pub(super) routes: Vec<Route>,
    pub(super) allowed: Vec<(String, u16)>,
    pub(super) tls: Option<tokio_rustls::TlsConnector>,
    pub(super) log: Mutex<Log>,
    /// Set before the gateway stops: what is cut from then on, the gateway cut.
    pub(super) stopping: AtomicBool,
}

impl Shared {
    pub(super) fn allows(&self, host: &str, port: u16) -> bool {
        let host = normal_host(host);
        self.allowed.iter().any(|(h, p)| *h == host && *p == port)
    }

    /// The model API's own host:port, which only the reverse proxy reaches (through the routes, metered).
    pub(super) fn is_upstream(&self, host: &str, port: u16) -> bool {
        self.upstream.as_ref().is_some_and(|u| u.host == normal_host(host) && u.port == port)
    }

    pub(super) fn routes_allow(&self, method: &Method, path: &str) -> bool {
        self.routes.iter().any(|r| r.method == *method && r.path == path)
    }

    pub(super) fn record(&self, r: Record) {
        if let Ok(mut log) = self.log.lock() {
            log.add(r);
        }
    }

    pub(super) fn flush_sidecar(&self) {
        if let Ok(mut log) = self.log.lock() {
            log.flush_sidecar();
        }
    }

    pub(super) fn close_log(&self) {
        if let Ok(mut log) = self.log.lock() {
            log.close();
        }
    }
}

/// Which side of a tunnel failed first.
pub(super) const FAULT_CLIENT: u8 = 1;
pub(super) const FAULT_REMOTE: u8 = 2;

/// Bytes each way of one request or tunnel, and what broke it.
#[derive(Default)]
pub(super) struct Counters {
    pub(super) from_client: AtomicU64,
    pub(super) to_client: AtomicU64,
    /// The client's request body was passed on to its end.
    pub(super) body_complete: AtomicBool,
    /// The client's request body could not be passed on whole.
    pub(super) body_fault: Mutex<Option<BodyFault>>,
    /// A tunnel's first failing side ([`FAULT_CLIENT`], [`FAULT_REMOTE`]), 0 while none failed.
    pub(super) tunnel_fault: AtomicU8,
}

impl Counters {
    pub(super) fn body_fault(&self) -> Option<BodyFault> {
        self.body_fault.lock().ok().and_then(|f| f.clone())
    }

    pub(super) fn set_body_fault(&self, f: BodyFault) {
        if let Ok(mut slot) = self.body_fault.lock() {
            slot.get_or_insert(f);
        }
    }
}

/// Why a request body was not passed on whole.
#[derive(Debug, Clone)]
pub(super) enum BodyFault {
    /// Over [`MAX_REQUEST_BODY_BYTES`].
    TooLarge,
    /// The client's stream broke off (shorter than it declared, connection gone).
    Client(String),
}

pub(super) fn clipped(s: &str, max: usize) -> String {
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
pub(super) struct Pending {
    pub(super) shared: Arc<Shared>,
    pub(super) at: SystemTime,
    pub(super) started: Instant,
    pub(super) mode: Mode,
    pub(super) method: String,
    pub(super) host: String,
    pub(super) path: String,
    pub(super) status: u16,
    pub(super) cause: Cause,
    pub(super) bytes: Arc<Counters>,
    pub(super) content_type: Option<String>,
    pub(super) capture: Option<Capture>,
    pub(super) error: Option<String>,
    /// The request went to the upstream (its body may still have been cut).
    pub(super) sent: bool,
    pub(super) done: bool,
}

impl Pending {
    pub(super) fn new(shared: Arc<Shared>, method: &str, path: &str) -> Self {
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

    pub(super) fn set_host(&mut self, host: &str, port: u16) {
        let host = normal_host(host);
        self.host = clipped(&if host.contains(':') { format!("[{host}]:{port}") } else { format!("{host}:{port}") }, 300);
    }

    /// Whether the tokens this request cost are unknown: it reached the upstream whole (a cut request costs no
    /// model call), and its response was
    /// encoded, ended early, or (a successful `POST`, `count_tokens` aside) reported no usage.
    pub(super) fn unmetered(&self, has_usage: bool) -> bool {
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

    pub(super) fn finish(&mut self) {
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
    pub(super) fn answer(mut self, status: StatusCode, cause: Cause, message: &str) -> Response<GateBody> {
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
    pub(super) fn refuse(mut self, status: StatusCode, message: &str) -> Response<GateBody> {
        self.mode = Mode::Refused;
        self.answer(status, Cause::Gateway, message)
    }

    /// The upstream could not be reached or did not answer.
    pub(super) fn unreachable(self, status: StatusCode, message: &str) -> Response<GateBody> {
        self.answer(status, Cause::Upstream, message)
    }

    /// The request body could not be passed on whole: the client's doing, or over the gateway's bound.
    pub(super) fn body_cut(self, fault: BodyFault) -> Response<GateBody> {
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

pub(super) fn text_response(status: StatusCode, text: String) -> Response<GateBody> {
    let mut r = Response::new(GateBody::Full(Some(Bytes::from(text))));
    *r.status_mut() = status;
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("text/plain; charset=utf-8"));
    // The gateway's own answers are refusals and failures: the connection ends with them.
    r.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    r
}

/// Every place is held by a request or a tunnel in progress: 503 at once (one write to a fresh socket's empty
/// buffer, never waited on), recorded.
pub(super) fn too_many_connections(shared: &Arc<Shared>, stream: UnixStream) {
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

pub(super) async fn serve_gateway_connection(shared: Arc<Shared>, stream: UnixStream, slot: Arc<Slot>) {
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
pub(super) fn suspicious_path(path: &str) -> Option<&'static str> {
    let lower = path.to_ascii_lowercase();
    if lower.contains("..") || lower.contains("//") || lower.contains('\\') || lower.contains('#') {
        return Some("dot segments, empty segments, backslashes and fragments are not passed on");
    }
    if ["%2e", "%2f", "%5c", "%00"].iter().any(|e| lower.contains(e)) {
        return Some("encoded dots, slashes and backslashes are not passed on");
    }
    None
}

pub(super) async fn handle(shared: Arc<Shared>, req: Request<Incoming>, slot: &Arc<Slot>) -> Response<GateBody> {
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

pub(super) async fn connect(shared: Arc<Shared>, mut req: Request<Incoming>, mut p: Pending, slot: Arc<Slot>) -> Response<GateBody> {
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
pub(super) struct Target {
    pub(super) tls: bool,
    pub(super) host: String,
    pub(super) port: u16,
    pub(super) authority: String,
}

pub(super) trait Io: AsyncRead + AsyncWrite + Send + Unpin {}
impl<T: AsyncRead + AsyncWrite + Send + Unpin> Io for T {}

pub(super) async fn open(shared: &Shared, t: &Target) -> Result<Box<dyn Io>, String> {
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
pub(super) fn strip_hop_by_hop(h: &mut HeaderMap) {
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

pub(super) async fn proxy(shared: &Shared, req: Request<Incoming>, target: Target, mut p: Pending) -> Response<GateBody> {
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
pub(super) struct RequestBody {
    pub(super) inner: Incoming,
    pub(super) bytes: Arc<Counters>,
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
pub(super) struct Served {
    pub(super) body: GateBody,
    pub(super) _busy: Busy,
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
pub(super) enum GateBody {
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
pub(super) struct TeeBody {
    pub(super) inner: Incoming,
    pub(super) pending: Pending,
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
pub(super) struct Counted<T> {
    pub(super) inner: T,
    pub(super) bytes: Arc<Counters>,
    /// [`FAULT_CLIENT`] or [`FAULT_REMOTE`].
    pub(super) side: u8,
}

impl<T> Counted<T> {
    pub(super) fn note<R>(&self, r: &Poll<std::io::Result<R>>) {
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
