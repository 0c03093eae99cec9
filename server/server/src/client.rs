//! The client side of our own server, shared by `bench mcp`, the batch runner and the reference agent: an MCP
//! session over streamable HTTP (what the Python SDK does in legacy mode), preparing episodes over the HTTP
//! API, and an in-process server on a free loopback port.
use std::path::PathBuf;
use std::sync::mpsc;
use std::time::Duration;

use anyhow::{Context, bail};
use serde_json::{Value, json};

use crate::episodes::{PrepareRequest, Prepared};
use libero_records::episode_view::{EpisodeList, EpisodeResultReply, EpisodeVideo, EpisodeView};
use libero_records::records::RunResult;
use crate::http_client::{HttpUrl, request};
use crate::{ApiError, ServeArgs, credential, start};
use crate::http_client::messages_of;

/// Per-request timeout (a debug build under load can take seconds per call; a call never outlives an episode).
pub const CALL_TIMEOUT: Duration = Duration::from_secs(600);

/// One MCP client session over streamable HTTP.
pub struct McpClient {
    url: HttpUrl,
    headers: Vec<(String, String)>,
    next_id: u64,
}

impl McpClient {
    /// `initialize` + `notifications/initialized` with `extra_headers` (e.g. the bearer token) on every request.
    pub fn connect(mcp_url: &str, extra_headers: &[(String, String)], client_name: &str) -> anyhow::Result<Self> {
        let mut headers = extra_headers.to_vec();
        headers.push(("Content-Type".to_owned(), "application/json".to_owned()));
        headers.push(("Accept".to_owned(), "application/json, text/event-stream".to_owned()));
        let mut c = Self { url: HttpUrl::parse(mcp_url)?, headers, next_id: 1 };
        let init = json!({"protocolVersion": "2025-06-18", "capabilities": {},
            "clientInfo": {"name": client_name, "version": env!("CARGO_PKG_VERSION")}});
        let (reply, session) = c.post("initialize", init)?;
        if reply.get("result").is_none() {
            bail!("initialize failed: {reply}");
        }
        if let Some(s) = session {
            c.headers.push(("Mcp-Session-Id".to_owned(), s));
        }
        if let Some(v) = reply.pointer("/result/protocolVersion").and_then(Value::as_str) {
            c.headers.push(("Mcp-Protocol-Version".to_owned(), v.to_owned()));
        }
        let note = json!({"jsonrpc": "2.0", "method": "notifications/initialized"});
        let resp = request("POST", &c.url, &c.headers, note.to_string().as_bytes(), CALL_TIMEOUT)?;
        if resp.status >= 400 {
            bail!("notifications/initialized: HTTP {}", resp.status);
        }
        Ok(c)
    }

    /// With `Authorization: Bearer <token>`.
    pub fn connect_with_token(mcp_url: &str, token: &str, client_name: &str) -> anyhow::Result<Self> {
        Self::connect(mcp_url, &[("Authorization".to_owned(), format!("Bearer {token}"))], client_name)
    }

    /// One JSON-RPC request; the reply with its id and the session id header, if any.
    pub fn post(&mut self, method: &str, params: Value) -> anyhow::Result<(Value, Option<String>)> {
        let id = self.next_id;
        self.next_id += 1;
        let body = json!({"jsonrpc": "2.0", "id": id, "method": method, "params": params});
        let resp = request("POST", &self.url, &self.headers, body.to_string().as_bytes(), CALL_TIMEOUT)?;
        if resp.status >= 400 {
            bail!("{method}: HTTP {}: {}", resp.status, String::from_utf8_lossy(&resp.body));
        }
        let session = resp.header("mcp-session-id").map(str::to_owned);
        let reply = messages_of(&resp)
            .into_iter()
            .find(|m| m.get("id") == Some(&json!(id)))
            .with_context(|| format!("{method}: no JSON-RPC reply with id {id}"))?;
        Ok((reply, session))
    }

    /// `tools/list`: the tool names.
    pub fn tool_names(&mut self) -> anyhow::Result<Vec<String>> {
        let (reply, _) = self.post("tools/list", json!({}))?;
        let tools = reply.pointer("/result/tools").and_then(Value::as_array).with_context(|| format!("tools/list: {reply}"))?;
        Ok(tools.iter().filter_map(|t| t["name"].as_str().map(str::to_owned)).collect())
    }

    /// `tools/call`; the tool's payload (`structuredContent`), whatever its `ok`.
    pub fn call_tool_payload(&mut self, name: &str, arguments: Value) -> anyhow::Result<Value> {
        let (reply, _) = self.post("tools/call", json!({"name": name, "arguments": arguments}))?;
        reply.pointer("/result/structuredContent").cloned().with_context(|| format!("{name}: {reply}"))
    }

    /// `tools/call`; the tool's payload, which must say `ok: true`.
    pub fn call_tool(&mut self, name: &str, arguments: Value) -> anyhow::Result<Value> {
        let payload = self.call_tool_payload(name, arguments)?;
        if libero_records::action_event::ToolReply::of(&payload).ok != Some(true) {
            bail!("{name} failed: {payload}");
        }
        Ok(payload)
    }
}

/// `request` to the operator API at `base` with the operator credential this user can find; a 401 says how
/// to pass one.
pub fn operator_request(method: &str, base: &str, path: &str, body: &[u8], timeout: Duration) -> anyhow::Result<crate::http_client::HttpResponse> {
    let base = base.trim_end_matches('/');
    let url = HttpUrl::parse(&format!("{base}{path}"))?;
    let mut headers = credential::operator_headers(base)?;
    if !body.is_empty() {
        headers.push(("Content-Type".to_owned(), "application/json".to_owned()));
    }
    let resp = request(method, &url, &headers, body, timeout).with_context(|| format!("is `libero-agent serve` running at {base}?"))?;
    if resp.status == 401 {
        bail!("{}", credential::missing_token_hint(base));
    }
    Ok(resp)
}

/// Prepares one episode on the server at `base` (`POST /api/episodes`).
pub fn prepare_episode(base: &str, req: &PrepareRequest) -> anyhow::Result<Prepared> {
    let resp = operator_request("POST", base, "/api/episodes", &serde_json::to_vec(req)?, CALL_TIMEOUT)?;
    let v: Value = serde_json::from_slice(&resp.body).context("prepare reply is not JSON")?;
    if resp.status != 201 {
        let msg = ApiError::message_in(&resp.body).unwrap_or_else(|| v.to_string());
        bail!("the server refused to prepare the episode (HTTP {}): {msg}", resp.status);
    }
    serde_json::from_value(v).context("prepare reply does not describe an episode")
}

/// `GET <base><path>` of the operator API as JSON (status, body).
pub fn get_json(base: &str, path: &str) -> anyhow::Result<(u16, Value)> {
    let resp = operator_request("GET", base, path, b"", Duration::from_secs(30))?;
    Ok((resp.status, serde_json::from_slice(&resp.body).unwrap_or(Value::Null)))
}

/// `POST <base><path>` of the operator API with a JSON body (status, body).
pub fn post_json(base: &str, path: &str, body: &Value) -> anyhow::Result<(u16, Value)> {
    post_json_within(base, path, body, CALL_TIMEOUT)
}

/// [`post_json`] that gives up after `timeout` (calls that must not hold their caller for minutes).
pub fn post_json_within(base: &str, path: &str, body: &Value, timeout: Duration) -> anyhow::Result<(u16, Value)> {
    let resp = operator_request("POST", base, path, body.to_string().as_bytes(), timeout)?;
    Ok((resp.status, serde_json::from_slice(&resp.body).unwrap_or(Value::Null)))
}

/// `GET <base><path>` of the operator API, its reply typed: a non-2xx status is an error with the server's
/// message.
fn get_typed<T: serde::de::DeserializeOwned>(base: &str, path: &str) -> anyhow::Result<T> {
    let resp = operator_request("GET", base, path, b"", Duration::from_secs(30))?;
    if !(200..300).contains(&resp.status) {
        let msg = ApiError::message_in(&resp.body).unwrap_or_else(|| String::from_utf8_lossy(&resp.body).into_owned());
        bail!("GET {path}: HTTP {}: {msg}", resp.status);
    }
    serde_json::from_slice(&resp.body).with_context(|| format!("GET {path}: the reply is not what the API sends"))
}

/// `GET /api/episodes/{id}`: the episode as the server at `base` shows it.
pub fn episode(base: &str, episode_id: &str) -> anyhow::Result<EpisodeView> {
    get_typed(base, &format!("/api/episodes/{episode_id}"))
}

/// `GET /api/episodes?limit=…`: the stored episodes, newest first.
pub fn episodes(base: &str, limit: u32) -> anyhow::Result<Vec<EpisodeView>> {
    Ok(get_typed::<EpisodeList>(base, &format!("/api/episodes?limit={limit}"))?.episodes)
}

/// `GET /api/episodes/{id}/result`: the episode's `result.json` as its server holds it (None while it is open).
pub fn episode_result(base: &str, episode_id: &str) -> anyhow::Result<Option<RunResult>> {
    Ok(get_typed::<EpisodeResultReply>(base, &format!("/api/episodes/{episode_id}/result"))?.result)
}

/// `GET /api/episodes/{id}/video`: whether the episode's private video is written, and its rendering.
pub fn episode_video(base: &str, episode_id: &str) -> anyhow::Result<EpisodeVideo> {
    get_typed(base, &format!("/api/episodes/{episode_id}/video"))
}

/// Waits until the operator API says the private video of `episode_id` is written (an episode's video is rendered
/// after it ends), at most `timeout`.
pub fn wait_for_video(base: &str, episode_id: &str, timeout: Duration) -> anyhow::Result<()> {
    let t = std::time::Instant::now();
    loop {
        let v = episode_video(base, episode_id)?;
        if v.video {
            return Ok(());
        }
        if v.will_not_come() || t.elapsed() > timeout {
            bail!("episode {episode_id}: the video did not complete: {}", serde_json::to_string(&v).unwrap_or_default());
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// A server running in this process on a free loopback port; stops (recording open episodes as aborted with
/// `stop_reason`) when [`InProcessServer::stop`] is called (waiting for every episode's records and video) or
/// [`InProcessServer::stop_now`] / drop (waiting only seconds: an interrupted batch must exit promptly).
pub struct InProcessServer {
    pub url: String,
    stop: Option<mpsc::Sender<Duration>>,
    thread: Option<std::thread::JoinHandle<anyhow::Result<()>>>,
}

impl InProcessServer {
    /// Starts the server on a free loopback port with a fresh operator token of its own, known to this
    /// process's client calls and to no agent (it is in no environment and on no command line).
    /// No browser console: MCP and the operator API only.
    pub fn start(data: PathBuf, stop_reason: &str) -> anyhow::Result<Self> {
        Self::start_with(data, None, None, stop_reason)
    }

    /// As [`InProcessServer::start`], recording episodes in the store `store` names (a worker's server writes to
    /// the shared store, so every dashboard lists its episodes) instead of `<data>/episodes.sqlite`, and serving
    /// `console`'s pages when given one.
    pub fn start_with(data: PathBuf, store: Option<String>, console: Option<crate::Console>, stop_reason: &str) -> anyhow::Result<Self> {
        let args = ServeArgs {
            server: crate::ServerFlags {
                addr: std::net::SocketAddr::from(([127, 0, 0, 1], 0)),
                data: Some(data),
                operator_token_file: None,
                public_hosts: vec![],
                public_url: None,
            },
            rotate_token: false,
            batches: vec![],
            stores: crate::StoreFlags { store, artifacts: None },
            limits: crate::listener::ConnLimits::default(),
            console,
            thumbnails: crate::ThumbnailArgs::off(),
            teleop_abandon_s: crate::args::DEFAULT_TELEOP_ABANDON_S,
        };
        Self::start_args(args, stop_reason)
    }

    /// A server with these settings in a thread of this process (a worker's, listening where it is told).
    pub fn start_args(args: ServeArgs, stop_reason: &str) -> anyhow::Result<Self> {
        let (url_tx, url_rx) = mpsc::channel::<anyhow::Result<String>>();
        let (stop_tx, stop_rx) = mpsc::channel::<Duration>();
        let stop_reason = stop_reason.to_owned();
        let thread = std::thread::spawn(move || -> anyhow::Result<()> {
            let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
            let result = runtime.block_on(async move {
                let bound = match start(&args).await {
                    Ok(b) => b,
                    Err(e) => {
                        let _ = url_tx.send(Err(anyhow::anyhow!("{e:#}")));
                        return Err(e);
                    }
                };
                credential::remember_in_process(bound.url(), bound.operator_token());
                let stop = async move {
                    let grace = tokio::task::spawn_blocking(move || stop_rx.recv()).await.ok().and_then(Result::ok);
                    (stop_reason, grace.unwrap_or(crate::SIGNAL_GRACE))
                };
                let listening = move |l: crate::serve::Listening| {
                    let _ = url_tx.send(Ok(l.url));
                };
                bound.serve(listening, stop).await
            });
            runtime.shutdown_timeout(Duration::from_secs(1));
            result
        });
        match url_rx.recv() {
            Ok(Ok(url)) if !url.is_empty() => Ok(Self { url, stop: Some(stop_tx), thread: Some(thread) }),
            Ok(Err(e)) => Err(e.context("the server did not start")),
            _ => match thread.join() {
                Ok(Err(e)) => Err(e.context("the server did not start")),
                _ => bail!("the server did not start"),
            },
        }
    }

    /// Stops the server once every episode has written its records and video (bounded by [`crate::DRAIN_GRACE`]).
    pub fn stop(mut self) -> anyhow::Result<()> {
        self.shutdown(crate::DRAIN_GRACE)
    }

    /// Stops the server within seconds (an interrupted batch): a video still draining may stay partial.
    pub fn stop_now(mut self) -> anyhow::Result<()> {
        self.shutdown(crate::SIGNAL_GRACE)
    }

    fn shutdown(&mut self, grace: Duration) -> anyhow::Result<()> {
        credential::forget_in_process(&self.url);
        if let Some(s) = self.stop.take() {
            let _ = s.send(grace);
        }
        match self.thread.take() {
            Some(t) => t.join().map_err(|_| anyhow::anyhow!("the server thread panicked"))?,
            None => Ok(()),
        }
    }
}

impl Drop for InProcessServer {
    fn drop(&mut self) {
        let _ = self.shutdown(crate::SIGNAL_GRACE);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use libero_records::episode_view::EpisodeState;

    fn get(base: &str, path: &str, with_operator_token: bool) -> (u16, String) {
        let headers = if with_operator_token { credential::operator_headers(base).unwrap() } else { vec![] };
        let resp = request("GET", &HttpUrl::parse(&format!("{base}{path}")).unwrap(), &headers, b"", Duration::from_secs(30)).unwrap();
        (resp.status, String::from_utf8_lossy(&resp.body).into_owned())
    }

    #[test]
    fn a_server_without_a_console_serves_mcp_and_the_operator_api_but_no_pages() {
        let dir = tempfile::tempdir().unwrap();
        let server = InProcessServer::start(dir.path().join("data"), "test_finished").unwrap();
        assert_eq!(get(&server.url, "/api/health", false).0, 200);
        let (status, list) = get(&server.url, "/api/episodes", true);
        assert_eq!(status, 200, "{list}");
        assert_eq!(get(&server.url, "/api/episodes", false).0, 401, "the operator API stays guarded");
        for page in ["/", "/tasks", "/results", "/static/style.css", "/ws/episodes"] {
            assert_eq!(get(&server.url, page, true).0, 404, "{page} belongs to the console");
        }
        let (status, login) = get(&server.url, "/login", false);
        assert_eq!(status, 200);
        assert!(login.contains("Operator sign-in") && login.contains("name=\"token\""), "{login}");
        assert_eq!(get(&server.url, "/api/episodes/ep-none/video", true).0, 404);
        server.stop_now().unwrap();
    }

    #[test]
    fn an_episode_s_steps_and_end_reach_the_store_and_the_typed_api_for_machines_elsewhere() {
        let _alone = crate::PROCESS_WIDE_TEST_LOCK.lock().unwrap_or_else(|p| p.into_inner());
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("data");
        let server = InProcessServer::start(data.clone(), "test_finished").unwrap();
        let req = PrepareRequest { level: 3, workspace: Some(dir.path().join("ws")), wall_time_s: 300.0, max_agent_steps: 10, ..PrepareRequest::new("T14") };
        let prepared = prepare_episode(&server.url, &req).unwrap();
        let headers: Vec<(String, String)> = prepared.mcp_headers.clone().into_iter().collect();
        let mut client = McpClient::connect(&prepared.mcp_url, &headers, "progress-test").unwrap();
        client.call_tool("start_episode", json!({})).unwrap();
        for _ in 0..2 {
            client.call_tool("osc_sequence", json!({"actions": [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]]})).unwrap();
        }
        // What a dashboard on another machine reads: the store's row, not this server's live state.
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        let store = runtime.block_on(libero_store::Store::open(&data.join(libero_store::STORE_FILE))).unwrap();
        let t = std::time::Instant::now();
        let row = loop {
            let row = runtime.block_on(store.get(&prepared.episode_id)).unwrap().unwrap();
            if row.accepted_agent_steps == Some(2) || t.elapsed() > Duration::from_secs(20) {
                break row;
            }
            std::thread::sleep(Duration::from_millis(100));
        };
        assert_eq!((row.outcome.as_deref(), row.accepted_agent_steps), (None, Some(2)), "{row:?}");
        assert_eq!(row.episode.server_url, None, "a server without a console has no live view for other dashboards to link to");
        assert!(row.required_stage_count.is_some_and(|r| r > 0), "the evaluator's stage count is stored while open: {row:?}");
        // What a runner on another machine reads: the typed view and, once ended, the result over the API.
        let open = episode(&server.url, &prepared.episode_id).unwrap();
        assert_eq!((open.state, open.accepted_agent_steps, open.outcome), (Some(EpisodeState::Active), Some(2), None), "{open:?}");
        assert!(!open.has_ended());
        assert_eq!(episode_result(&server.url, &prepared.episode_id).unwrap(), None, "no result while open");
        client.call_tool("finish_episode", json!({})).unwrap();
        let ended = episode(&server.url, &prepared.episode_id).unwrap();
        assert!(ended.has_ended() && ended.state == Some(EpisodeState::Finished), "{ended:?}");
        let result = episode_result(&server.url, &prepared.episode_id).unwrap().expect("the result once ended");
        assert!(result.is_finished(), "{result:?}");
        assert_eq!(ended.outcome, Some(libero_records::records::classify(Some(&result))), "the row's outcome is the result's");
        assert!(episodes(&server.url, 10).unwrap().iter().any(|e| e.id == prepared.episode_id));
        assert!(episode(&server.url, "ep-none").is_err_and(|e| e.to_string().contains("HTTP 404")));
        server.stop_now().unwrap();
    }

    /// Different routes, middleware and handlers alike, fail in the one shape of `ApiError`.
    #[test]
    fn failing_routes_answer_the_same_error_shape() {
        let dir = tempfile::tempdir().unwrap();
        let server = InProcessServer::start(dir.path().join("data"), "test_finished").unwrap();
        let operator = credential::operator_headers(&server.url).unwrap();
        let call = |method: &str, path: &str, headers: &[(String, String)], body: &[u8]| {
            let url = HttpUrl::parse(&format!("{}{path}", server.url)).unwrap();
            let resp = request(method, &url, headers, body, Duration::from_secs(30)).unwrap();
            let value: Value = serde_json::from_slice(&resp.body).unwrap_or_else(|e| panic!("{path}: {e}"));
            (resp.status, value)
        };
        let failures = [
            (call("GET", "/api/episodes/ep-none", &operator, b""), 404, "no episode ep-none"),
            (call("POST", "/api/batches", &operator, b"{}"), 400, "body must be"),
            (call("POST", "/api/episodes/ep-none/abort", &operator, b"{\"reason\": \"x\"}"), 404, "no open episode ep-none"),
            (call("GET", "/api/episodes", &[], b""), 401, "operator token required"),
            (call("POST", "/mcp/ep-none", &[], b"{}"), 401, "missing or invalid episode token"),
        ];
        for ((status, body), want_status, want_start) in failures {
            assert_eq!(status, want_status, "{body}");
            let mut keys: Vec<&str> = body.as_object().map(|o| o.keys().map(String::as_str).collect()).unwrap_or_default();
            keys.sort_unstable();
            assert_eq!(keys, ["error", "ok"], "{body}");
            assert_eq!(body["ok"], false, "{body}");
            assert!(body["error"].as_str().is_some_and(|e| e.starts_with(want_start)), "{body}");
        }
        server.stop_now().unwrap();
    }

    #[test]
    fn a_public_url_must_be_a_plain_http_url() {
        for good in ["http://worker-3.lab:8090", "https://bench.example/libero"] {
            assert!(crate::check_public_url(good).is_ok(), "{good}");
        }
        let long = format!("http://{}", "a".repeat(600));
        for bad in ["worker-3:8090", "ftp://x", "http://a b", "http://x\"><script>", "javascript:alert(1)", long.as_str()] {
            assert!(crate::check_public_url(bad).is_err(), "{bad}");
        }
    }
}
