//! A server that runs for weeks: what an ended episode held (its thread, world, video recorder, MCP sessions,
//! live view) is released within seconds, so threads, open files and memory do not grow with the number of
//! episodes served; the ended episode's endpoint keeps answering clearly (for its token only), and a dashboard
//! viewer of it gets its final state.
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::{Value, json};

mod common;
use common::{Server, bin, http, python};

const TASK: &str = "T14";
/// Threads or open files an in-process server may keep above its level after the first episode (pool
/// connections opened under load).
const TOLERANCE: i64 = 2;
/// Resident memory the second half of the episodes may add: no growth per episode, with room for allocator noise.
const MEMORY_MARGIN_MB: f64 = 150.0;

#[test]
fn twelve_episodes_four_at_a_time_leave_threads_files_and_memory_where_the_first_left_them() {
    let out = Command::new(bin())
        .args(["bench", "soak", "--episodes", "12", "--concurrent", "4", "--task", TASK, "--json"])
        .output()
        .expect("run bench soak");
    assert!(out.status.success(), "bench soak failed: {}", String::from_utf8_lossy(&out.stderr));
    let report: Value = serde_json::from_slice(&out.stdout).expect("bench soak prints JSON");
    let kinds = &report["threads_by_kind"];
    let files = &report["open_files_by_kind"];
    let threads_over = report["threads_over_baseline"].as_i64().unwrap();
    assert!(threads_over <= TOLERANCE, "{threads_over} threads more than after the first episode: {kinds}");
    let files_over = report["open_files_over_baseline"].as_i64().unwrap();
    assert!(files_over <= TOLERANCE, "{files_over} open files more than after the first episode: {files}");
    let kinds_after = &kinds["after_last_episode"];
    assert!(kinds_after.get("episode").is_none() && kinds_after.get("video").is_none(), "{kinds_after}");
    // Every scene model went with its episode and its video (a video drawn after its episode was retired once
    // kept the scene's base model, hundreds of MB, until some later episode ended).
    assert_eq!(report["after_last_episode"]["models_alive"], 0, "scene models still alive: {report}");
    let growth = report["rss_growth_second_half_mb"].as_f64().unwrap();
    assert!(growth < MEMORY_MARGIN_MB, "episodes 7-12 added {growth:.0} MB resident: {report}");
}

/// The JSON-RPC message with `id` in a JSON or SSE body.
fn reply(body: &[u8], id: u64) -> Value {
    let text = String::from_utf8_lossy(body);
    let messages: Vec<Value> = match serde_json::from_str::<Value>(&text) {
        Ok(v) => vec![v],
        Err(_) => text.lines().filter_map(|l| l.strip_prefix("data:")).filter_map(|d| serde_json::from_str(d.trim()).ok()).collect(),
    };
    messages.into_iter().find(|m| m["id"] == id).unwrap_or_else(|| panic!("no reply with id {id} in {text:?}"))
}

struct Episode {
    id: String,
    url: String,
    token: String,
}

impl Episode {
    fn prepare(server: &Server, ws: &Path) -> Self {
        let req = json!({"task": TASK, "level": 1, "video": false, "workspace": ws});
        let op = format!("Bearer {}", server.token);
        let headers = [("Content-Type", "application/json"), ("Authorization", op.as_str())];
        let (status, _, body) = http("POST", &format!("{}/api/episodes", server.url), &headers, req.to_string().as_bytes());
        let p: Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(status, 201, "{p}");
        let token = p["mcp_headers"]["Authorization"].as_str().unwrap().trim_start_matches("Bearer ").to_owned();
        Self { id: p["episode_id"].as_str().unwrap().to_owned(), url: p["mcp_url"].as_str().unwrap().to_owned(), token }
    }

    fn post(&self, token: &str, session: Option<&str>, message: &Value) -> (u16, String, Vec<u8>) {
        let auth = format!("Bearer {token}");
        let mut headers =
            vec![("Authorization", auth.as_str()), ("Content-Type", "application/json"), ("Accept", "application/json, text/event-stream")];
        if let Some(s) = session {
            headers.extend([("Mcp-Session-Id", s), ("Mcp-Protocol-Version", "2025-06-18")]);
        }
        http("POST", &self.url, &headers, message.to_string().as_bytes())
    }

    /// `initialize`; status, session id, the reply.
    fn initialize(&self, id: u64) -> (u16, Option<String>, Value) {
        let init = json!({"jsonrpc": "2.0", "id": id, "method": "initialize",
            "params": {"protocolVersion": "2025-06-18", "capabilities": {}, "clientInfo": {"name": "soak-test", "version": "0"}}});
        let (status, head, body) = self.post(&self.token, None, &init);
        let session = head.lines().find_map(|l| l.split_once(':').filter(|(k, _)| k.eq_ignore_ascii_case("mcp-session-id"))).map(|(_, v)| v.trim().to_owned());
        (status, session, reply(&body, id))
    }

    fn call(&self, session: &str, id: u64, tool: &str, arguments: Value) -> (u16, Value) {
        let message = json!({"jsonrpc": "2.0", "id": id, "method": "tools/call", "params": {"name": tool, "arguments": arguments}});
        let (status, _, body) = self.post(&self.token, Some(session), &message);
        (status, reply(&body, id))
    }
}

/// The text messages a WebSocket sends until it closes (frames from a server are unmasked).
fn websocket_texts(url: &str, operator_token: &str) -> Vec<Value> {
    let rest = url.strip_prefix("http://").unwrap();
    let (host, path) = rest.split_at(rest.find('/').unwrap());
    let mut s = TcpStream::connect(host).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nAuthorization: Bearer {operator_token}\r\n\r\n"
    )
    .unwrap();
    let mut raw = Vec::new();
    let _ = s.read_to_end(&mut raw);
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n").expect("handshake");
    assert!(raw.starts_with(b"HTTP/1.1 101"), "{}", String::from_utf8_lossy(&raw[..split]));
    let mut frames = &raw[split + 4..];
    let mut texts = Vec::new();
    while frames.len() >= 2 {
        let (opcode, mut len, mut at) = (frames[0] & 0x0f, (frames[1] & 0x7f) as usize, 2);
        if len == 126 {
            len = u16::from_be_bytes([frames[2], frames[3]]) as usize;
            at = 4;
        }
        if opcode == 1 {
            texts.push(serde_json::from_slice(&frames[at..at + len]).unwrap());
        }
        frames = &frames[at + len..];
    }
    texts
}

/// What the official Python SDK raises when it connects to `url` with `token`: its error message.
fn python_sdk_error(url: &str, token: &str) -> String {
    let script = r#"
import asyncio, sys
from mcp import Client
from mcp.client.streamable_http import streamable_http_client
from mcp.shared._httpx_utils import create_mcp_http_client
async def main(url, token):
    try:
        http = create_mcp_http_client(headers={"Authorization": f"Bearer {token}"})
        async with Client(streamable_http_client(url, http_client=http)) as c:
            await c.list_tools()
        print("no error")
    except BaseException as e:
        while isinstance(e, BaseExceptionGroup):
            e = e.exceptions[0]
        print(f"{type(e).__name__}: {getattr(e, 'message', e)}")
asyncio.run(main(sys.argv[1], sys.argv[2]))
"#;
    let out = Command::new(python()).args(["-c", script, url, token]).output().expect("run python");
    String::from_utf8_lossy(&out.stdout).trim().to_owned()
}

#[test]
fn an_ended_episode_answers_clearly_for_its_token_only_and_caps_its_sessions() {
    let tmp = tempfile::tempdir().unwrap();
    let server = Server::start(&tmp.path().join("data"));
    let ep = Episode::prepare(&server, &tmp.path().join("ws"));
    // Eight sessions at once are fine; a ninth is refused with a JSON-RPC error saying why.
    let sessions: Vec<String> = (1..=8)
        .map(|i| {
            let (status, session, r) = ep.initialize(i);
            assert_eq!((status, r.get("error")), (200, None), "{r}");
            session.expect("session id")
        })
        .collect();
    let (status, _, refused) = ep.initialize(9);
    assert_eq!(status, 429, "{refused}");
    assert!(refused["error"]["message"].as_str().unwrap().contains("already has 8 open MCP sessions"), "{refused}");
    let s = &sessions[0];
    for (i, tool) in ["start_episode", "finish_episode"].into_iter().enumerate() {
        let (status, r) = ep.call(s, 20 + i as u64, tool, json!({}));
        assert_eq!((status, &r["result"]["structuredContent"]["ok"]), (200, &json!(true)), "{tool}: {r}");
    }
    // Within seconds the sessions are closed: a new client is told the episode has ended (HTTP 410, JSON-RPC error).
    let ended = format!("episode {} has ended (finished); its MCP endpoint accepts no further calls", ep.id);
    let deadline = Instant::now() + Duration::from_secs(20);
    let gone = loop {
        let (status, _, r) = ep.initialize(30);
        if status == 410 {
            break r;
        }
        assert!(Instant::now() < deadline, "the ended episode still opens sessions: HTTP {status} {r}");
        std::thread::sleep(Duration::from_millis(250));
    };
    assert_eq!(gone["error"]["message"], ended.as_str(), "{gone}");
    assert_eq!(gone["error"]["data"]["outcome"], "FAIL");
    // A client that still has its session gets the protocol's answer to a call after finish.
    let (status, late) = ep.call(s, 31, "osc_sequence", json!({"actions": [[0, 0, 0, 0, 0, 0, 1]]}));
    assert_eq!(status, 200);
    assert_eq!(late["result"]["isError"], true, "{late}");
    let text = "the episode is already finished; finish_episode was called and no further commands are accepted";
    let late = &late["result"]["structuredContent"];
    assert_eq!((&late["error_type"], &late["error"]), (&json!("RuntimeError"), &json!(text)), "{late}");
    // Only for the right token: a wrong one learns nothing.
    let (status, _, _) = ep.post(&"0".repeat(64), None, &json!({"jsonrpc": "2.0", "id": 1, "method": "ping"}));
    assert_eq!(status, 401);
    let auth = format!("Bearer {}", ep.token);
    assert_eq!(http("DELETE", &ep.url, &[("Authorization", &auth), ("Mcp-Session-Id", s)], b"").0, 204);
    assert_eq!(http("GET", &ep.url, &[("Authorization", &auth), ("Accept", "text/event-stream")], b"").0, 405);
    // The official Python SDK shows the server's message.
    assert_eq!(python_sdk_error(&ep.url, &ep.token), format!("MCPError: {ended}"));
    // The dashboard: a viewer of the ended episode gets its budgets and final state, then the socket closes.
    let texts = websocket_texts(&format!("{}/ws/episodes/{}", server.url, ep.id), &server.token);
    assert_eq!(texts.len(), 2, "{texts:?}");
    assert_eq!((&texts[0]["type"], &texts[0]["max_wall_time_s"]), (&json!("hello"), &json!(1800.0)), "{texts:?}");
    assert_eq!((&texts[1]["type"], &texts[1]["outcome"]), (&json!("finished"), &json!("FAIL")), "{texts:?}");
    let op = format!("Bearer {}", server.token);
    let (status, _, _) = http("GET", &format!("{}/episodes/{}/review", server.url, ep.id), &[("Authorization", op.as_str())], b"");
    assert_eq!(status, 200, "the review page reads the run directory and the store");
}
