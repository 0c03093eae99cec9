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
