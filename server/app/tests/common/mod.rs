//! Shared by the integration tests that run the real binary and server.
#![allow(dead_code)]
use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use serde_json::Value;

pub mod postgres;
pub mod scripted_model;

/// The test venv's interpreter (`scripts/setup.py --test`): the independent Python peers of some tests.
pub fn python() -> PathBuf {
    libero_testkit::venv_python()
}

pub fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_libero-agent")
}

/// The first line a child prints on its piped stdout, as JSON (what `serve` and the scripted model announce).
pub fn first_json_line(child: &mut Child) -> Value {
    let mut line = String::new();
    BufReader::new(child.stdout.take().expect("stdout")).read_line(&mut line).expect("a first line");
    serde_json::from_str(&line).unwrap_or_else(|e| panic!("bad first line {line:?}: {e}"))
}

/// A running `libero-agent serve` on a free loopback port; killed on drop.
pub struct Server {
    pub child: Child,
    pub url: String,
    /// The operator token `serve` keeps in `<data>/operator_token`.
    pub token: String,
}

/// Operator tokens of the servers this test process started, by URL: `http_get_*` send them.
static TOKENS: std::sync::Mutex<Vec<(String, String)>> = std::sync::Mutex::new(Vec::new());

fn token_for(url: &str) -> Option<String> {
    TOKENS.lock().ok()?.iter().find(|(base, _)| url.starts_with(base.as_str())).map(|(_, t)| t.clone())
}

impl Server {
    pub fn start(data: &Path) -> Self {
        Self::start_with(data, &[])
    }

    /// With more `serve` arguments (e.g. `--batches DIR`). Thumbnails are not rendered ahead (every test server
    /// would otherwise render every task's in the background) unless `extra` asks with `--thumbnails-ahead`.
    pub fn start_with(data: &Path, extra: &[&str]) -> Self {
        Self::start_with_env(data, extra, &[])
    }

    /// With more `serve` arguments and environment variables (e.g. `LIBERO_AGENT_TASKS_DIR`).
    pub fn start_with_env(data: &Path, extra: &[&str], env: &[(&str, &std::ffi::OsStr)]) -> Self {
        let mut child = Command::new(bin())
            .args(["serve", "--addr", "127.0.0.1:0", "--data"])
            .arg(data)
            .args(extra)
            .env("LIBERO_AGENT_THUMBNAILS_AHEAD", "off")
            .envs(env.iter().copied())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start libero-agent serve");
        let v = first_json_line(&mut child);
        let url = v["url"].as_str().expect("url").to_owned();
        let token = std::fs::read_to_string(data.join("operator_token")).expect("serve keeps its operator token").trim().to_owned();
        TOKENS.lock().unwrap().push((url.clone(), token.clone()));
        Self { child, url, token }
    }

    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.kill();
    }
}

/// `GET` of a loopback URL (status, body as text), with the operator token of the test's server.
pub fn http_get_text(url: &str) -> (u16, String) {
    let rest = url.strip_prefix("http://").expect("http url");
    let (host, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
    let mut stream = std::net::TcpStream::connect(host).expect("connect");
    let auth = token_for(url).map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
    write!(stream, "GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n{auth}\r\n").unwrap();
    let mut text = String::new();
    stream.read_to_string(&mut text).unwrap();
    let status = text.split_whitespace().nth(1).and_then(|s| s.parse().ok()).expect("status");
    let body = text[text.find("\r\n\r\n").expect("headers end") + 4..].to_owned();
    (status, body)
}

/// `GET` of a loopback JSON endpoint (status, body).
pub fn http_get_json(url: &str) -> (u16, Value) {
    let (status, body) = http_get_text(url);
    (status, serde_json::from_str(&body).unwrap_or_else(|e| panic!("body {body:?} is not JSON: {e}")))
}

/// One HTTP/1.1 request on loopback; (status, headers text, body bytes).
pub fn http(method: &str, url: &str, headers: &[(&str, &str)], body: &[u8]) -> (u16, String, Vec<u8>) {
    let rest = url.strip_prefix("http://").expect("http url");
    let (host, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
    let mut stream = std::net::TcpStream::connect(host).expect("connect");
    stream.set_read_timeout(Some(Duration::from_secs(300))).unwrap();
    let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {host}\r\nContent-Length: {}\r\n", body.len());
    if !headers.iter().any(|(k, _)| k.eq_ignore_ascii_case("connection")) {
        head.push_str("Connection: close\r\n");
    }
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes()).unwrap();
    stream.write_all(body).unwrap();
    let mut raw = Vec::new();
    let mut buf = [0u8; 4096];
    // Up to the end of the headers first: a 101 (WebSocket) answer keeps the connection open.
    let split = loop {
        let n = stream.read(&mut buf).unwrap();
        assert!(n > 0, "connection closed before the headers ended");
        raw.extend_from_slice(&buf[..n]);
        if let Some(p) = raw.windows(4).position(|w| w == b"\r\n\r\n") {
            break p;
        }
    };
    let head = String::from_utf8_lossy(&raw[..split]).into_owned();
    let status = head.split_whitespace().nth(1).and_then(|s| s.parse().ok()).expect("status");
    if status == 101 {
        return (status, head, Vec::new());
    }
    let length = head
        .lines()
        .find_map(|l| l.to_ascii_lowercase().strip_prefix("content-length:").map(|v| v.trim().parse::<usize>().unwrap()));
    match length {
        // A kept-alive connection (the caller chose its own `Connection`) ends after the body, not at EOF.
        Some(n) => {
            while raw.len() < split + 4 + n {
                let k = stream.read(&mut buf).unwrap();
                assert!(k > 0, "connection closed inside the body");
                raw.extend_from_slice(&buf[..k]);
            }
        }
        None => {
            stream.read_to_end(&mut raw).unwrap();
        }
    }
    let mut body = raw[split + 4..].to_vec();
    if head.to_ascii_lowercase().contains("transfer-encoding: chunked") {
        body = dechunk(&body);
    }
    (status, head, body)
}

pub fn dechunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let line_end = b.windows(2).position(|w| w == b"\r\n").expect("chunk size line");
        let size = usize::from_str_radix(std::str::from_utf8(&b[..line_end]).unwrap().trim(), 16).unwrap();
        if size == 0 {
            return out;
        }
        out.extend_from_slice(&b[line_end + 2..line_end + 2 + size]);
        b = &b[line_end + 4 + size..];
    }
}

/// Waits for `child` (a batch run) to exit successfully within `limit`; kills it and fails the test otherwise.
pub fn wait_success(child: &mut Child, limit: std::time::Duration, what: &str) {
    let start = std::time::Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(status.success(), "{what} failed: {status}");
            return;
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            panic!("{what} hung for more than {limit:?}");
        }
        std::thread::sleep(std::time::Duration::from_millis(200));
    }
}

/// A minimal WebSocket client of the episode socket: every text message until `finished` or the close.
pub fn read_socket(url: &str, operator_token: &str) -> std::thread::JoinHandle<Result<Vec<Value>, String>> {
    let rest = url.strip_prefix("http://").expect("http url").to_owned();
    let (host, path) = rest.split_at(rest.find('/').expect("path"));
    let (host, path) = (host.to_owned(), path.to_owned());
    let mut stream = std::net::TcpStream::connect(&host).expect("connect");
    stream.set_read_timeout(Some(Duration::from_secs(300))).expect("timeout");
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nAuthorization: Bearer {operator_token}\r\n\r\n"
    )
    .expect("handshake");
    let mut r = BufReader::new(stream);
    // The answer's head, byte by byte up to the blank line (the frames follow at once).
    let mut head = Vec::new();
    while !head.ends_with(b"\r\n\r\n") {
        let mut b = [0u8; 1];
        r.read_exact(&mut b).expect("handshake answer");
        head.push(b[0]);
    }
    assert!(head.starts_with(b"HTTP/1.1 101"), "{}", String::from_utf8_lossy(&head));
    std::thread::spawn(move || {
        let mut texts = Vec::new();
        loop {
            let mut h = [0u8; 2];
            if r.read_exact(&mut h).is_err() {
                return Ok(texts);
            }
            let mut len = u64::from(h[1] & 0x7f);
            if len == 126 {
                let mut l = [0u8; 2];
                r.read_exact(&mut l).map_err(|e| e.to_string())?;
                len = u64::from(u16::from_be_bytes(l));
            } else if len == 127 {
                let mut l = [0u8; 8];
                r.read_exact(&mut l).map_err(|e| e.to_string())?;
                len = u64::from_be_bytes(l);
            }
            let mut payload = vec![0u8; usize::try_from(len).map_err(|e| e.to_string())?];
            r.read_exact(&mut payload).map_err(|e| e.to_string())?;
            match h[0] & 0x0f {
                1 => {
                    let v: Value = serde_json::from_slice(&payload).map_err(|e| e.to_string())?;
                    if v["type"] == "reset" {
                        return Err("the socket fell behind the events and was sent the history again".into());
                    }
                    let end = v["type"] == "finished";
                    texts.push(v);
                    if end {
                        return Ok(texts);
                    }
                }
                8 => return Ok(texts),
                _ => {} // frames (binary), pings
            }
        }
    })
}

/// Runs a browser script of `tests/dashboard/` (node, playwright-core, Debian's chromium; `scripts/setup.py --test`
/// installs them) with `args` and the operator token, and returns its last JSON line; fails saying what is missing.
pub fn browser_script(script: &str, args: &[&str], operator_token: &str) -> Value {
    let chromium = std::env::var_os("LIBERO_AGENT_CHROMIUM").map(PathBuf::from).unwrap_or_else(|| "/usr/bin/chromium".into());
    let cache = libero_testkit::cache_dir();
    let node_modules = cache.join("node/node_modules");
    assert!(
        chromium.is_file() && node_modules.join("playwright-core/package.json").is_file(),
        "chromium or playwright-core missing: run `python3 scripts/setup.py --test`"
    );
    let out = Command::new("node")
        .arg(libero_testkit::tests_dir().join("dashboard").join(script))
        .args(args)
        .env("NODE_PATH", &node_modules)
        .env("LIBERO_AGENT_CHROMIUM", &chromium)
        .env("LIBERO_OPERATOR_TOKEN", operator_token)
        .output()
        .expect("run node (Debian: apt-get install nodejs)");
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}{}", String::from_utf8_lossy(&out.stderr));
    stdout.lines().last().and_then(|l| serde_json::from_str(l).ok()).expect("a JSON line from the script")
}

/// `task`'s scripted expert run once on the server at `server_url` with `--no-video`: its last JSON result line.
pub fn expert_on_server(server_url: &str, task: &str) -> Value {
    let out = Command::new(bin()).args(["expert", "--task", task, "--no-video", "--server", server_url]).output().expect("run libero-agent expert");
    assert!(out.status.success(), "expert: {}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().filter(|l| l.trim_start().starts_with('{')).last().expect("a result line");
    serde_json::from_str(line).unwrap_or_else(|e| panic!("{line}: {e}"))
}

/// `episode prepare --server URL --task T14` into `workspace`: the prepared episode as `prepare` prints it.
pub fn prepare_t14(server_url: &str, workspace: &Path) -> Value {
    let out = Command::new(bin())
        .args(["episode", "prepare", "--server", server_url, "--task", "T14", "--wall-time-s", "300", "--workspace"])
        .arg(workspace)
        .output()
        .unwrap();
    assert!(out.status.success(), "prepare: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

/// Every item of the agent timeline, following `timeline_next` to its end.
pub fn timeline(server: &Server, id: &str) -> (Vec<Value>, usize) {
    let mut items = Vec::new();
    let mut query = String::new();
    let mut pages = 0;
    loop {
        let (status, page) = http_get_json(&format!("{}/api/episodes/{id}/agent{query}", server.url));
        assert_eq!(status, 200, "{page}");
        assert_eq!(page["available"], true, "{page}");
        items.extend(page["timeline"].as_array().unwrap().iter().cloned());
        pages += 1;
        let Some(next) = page["timeline_next"].as_object() else { return (items, pages) };
        let pairs: Vec<String> = next.iter().filter(|(_, v)| !v.is_null()).map(|(k, v)| format!("{k}={}", v.as_str().map_or(v.to_string(), str::to_owned))).collect();
        query = format!("?{}", pairs.join("&"));
    }
}

/// An `--agent-cmd` running `tests/clis/<script>` with `args`, inlined after the test agents' MCP client
/// (`tests/clis/mcp_http.py`) in a heredoc: the sandbox shows the workspace, not the repository.
pub fn inline_python_agent(script: &str, args: &str) -> String {
    let dir = libero_testkit::tests_dir().join("clis");
    let client = std::fs::read_to_string(dir.join("mcp_http.py")).unwrap();
    let agent = std::fs::read_to_string(dir.join(script)).unwrap();
    format!("python3 - {args} <<'PY'\n{client}\n{agent}\nPY")
}

/// The JSON of the last line of `log` that starts with `marker` and parses (an agent's report, printed on its
/// stdout: a rollout's workspace goes with its disk when it ends, the runner keeps the scrubbed stdout as
/// `<batch>/rollouts/<rollout id>/command_stdout.log`). A line cut short by a process killed mid-write does not
/// parse and is passed over.
pub fn marked_line(log: &Path, marker: &str) -> Option<Value> {
    let text = std::fs::read(log).ok()?;
    String::from_utf8_lossy(&text)
        .lines()
        .rev()
        .filter_map(|l| l.strip_prefix(marker))
        .find_map(|rest| serde_json::from_str(rest.trim()).ok())
}

/// Every line of `log` that starts with `marker`, without it.
pub fn marked_lines(log: &Path, marker: &str) -> Vec<String> {
    let text = std::fs::read(log).unwrap_or_default();
    String::from_utf8_lossy(&text).lines().filter_map(|l| l.strip_prefix(marker)).map(str::to_owned).collect()
}

/// The episode token of the one rollout running under `workspace_root`, read from its workspace's
/// `.libero/mcp.json` while the agent runs (the workspace goes with the rollout's disk when it ends): waits up to
/// `limit` for it to appear (`<root>/<rollout id>/workspace/`, or `<root>/<rollout id>/` where the runner caps no
/// rollout), or until `done()` says the run is over.
pub fn episode_token_while_running(workspace_root: &Path, limit: Duration, mut done: impl FnMut() -> bool) -> Option<String> {
    let t = std::time::Instant::now();
    while t.elapsed() < limit {
        let over = done();
        for rollout in std::fs::read_dir(workspace_root).into_iter().flatten().flatten() {
            for ws in [rollout.path().join("workspace"), rollout.path()] {
                let Ok(text) = std::fs::read_to_string(ws.join(".libero/mcp.json")) else { continue };
                let Ok(cfg) = serde_json::from_str::<Value>(&text) else { continue };
                if let Some(auth) = cfg["mcpServers"]["libero"]["headers"]["Authorization"].as_str() {
                    return Some(auth.trim_start_matches("Bearer ").to_owned());
                }
            }
        }
        if over {
            return None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    None
}

/// `POST` of a JSON body to `server` with the operator token (or without it: `token` None); (status, JSON answer).
pub fn post_json(server: &Server, path: &str, body: &Value, token: Option<&str>) -> (u16, Value) {
    let auth = token.map(|t| format!("Bearer {t}"));
    let mut headers = vec![("Content-Type", "application/json")];
    if let Some(a) = &auth {
        headers.push(("Authorization", a.as_str()));
    }
    let (status, _, body) = http("POST", &format!("{}{path}", server.url), &headers, body.to_string().as_bytes());
    (status, serde_json::from_slice(&body).unwrap_or_else(|_| serde_json::json!({"raw": String::from_utf8_lossy(&body)})))
}

/// An MCP session on a prepared episode (`POST /api/episodes`'s answer), as client `name`.
#[cfg(feature = "episode-serve")]
pub fn mcp_session(prepared: &Value, name: &str) -> libero_server::client::McpClient {
    let token = prepared["mcp_headers"]["Authorization"].as_str().expect("token").trim_start_matches("Bearer ");
    libero_server::client::McpClient::connect_with_token(prepared["mcp_url"].as_str().expect("mcp url"), token, name).expect("MCP session")
}

/// A tool call's payload, checked to be ok.
#[cfg(feature = "episode-serve")]
pub fn call_ok(client: &mut libero_server::client::McpClient, tool: &str, args: Value) -> Value {
    let payload = client.call_tool_payload(tool, args).expect("the MCP call");
    assert_eq!(payload["ok"], true, "{tool}: {payload}");
    payload
}
