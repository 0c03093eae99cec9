//! A blocking MCP client over streamable HTTP (JSON or SSE replies), for the CLI's own agents: `bench mcp`, the
//! scripted experts with `--server`.
use std::time::Duration;

use anyhow::{Context, bail};
use serde_json::{Value, json};

use super::episodes::PrepareRequest;
use super::http_client::{HttpUrl, request};
use crate::cmd_mcp_stdio::messages_of;

/// Longest wait for one call (an `osc_sequence` of 50 actions under heavy load stays well under this).
pub const CALL_TIMEOUT: Duration = Duration::from_secs(600);

/// One MCP client session over streamable HTTP (what the Python SDK does in legacy mode).
pub struct McpClient {
    url: HttpUrl,
    headers: Vec<(String, String)>,
    next_id: u64,
}

impl McpClient {
    pub fn connect(mcp_url: &str, token: &str) -> anyhow::Result<Self> {
        let headers = vec![
            ("Authorization".to_owned(), format!("Bearer {token}")),
            ("Content-Type".to_owned(), "application/json".to_owned()),
            ("Accept".to_owned(), "application/json, text/event-stream".to_owned()),
        ];
        let mut c = Self { url: HttpUrl::parse(mcp_url)?, headers, next_id: 1 };
        let init = json!({"protocolVersion": "2025-06-18", "capabilities": {},
            "clientInfo": {"name": "libero-agent", "version": env!("CARGO_PKG_VERSION")}});
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

    /// `tools/call`; the tool's payload (`structuredContent`), whatever its `ok`.
    pub fn call_tool_payload(&mut self, name: &str, arguments: Value) -> anyhow::Result<Value> {
        let (reply, _) = self.post("tools/call", json!({"name": name, "arguments": arguments}))?;
        reply.pointer("/result/structuredContent").cloned().with_context(|| format!("{name}: {reply}"))
    }

    /// `tools/call`; the tool's payload, which must say `ok: true`.
    pub fn call_tool(&mut self, name: &str, arguments: Value) -> anyhow::Result<Value> {
        let payload = self.call_tool_payload(name, arguments)?;
        if payload["ok"] != true {
            bail!("{name} failed: {payload}");
        }
        Ok(payload)
    }
}


/// Prepares an episode on a running server (`POST /api/episodes`): `(episode_id, mcp_url, bearer token)`.
pub fn prepare_on_server(server: &str, req: &PrepareRequest) -> anyhow::Result<(String, String, String)> {
    let base = server.trim_end_matches('/');
    let url = HttpUrl::parse(&format!("{base}/api/episodes"))?;
    let headers = [("Content-Type".to_owned(), "application/json".to_owned())];
    let resp = request("POST", &url, &headers, &serde_json::to_vec(req)?, CALL_TIMEOUT)
        .with_context(|| format!("is `libero-agent serve` running at {base}?"))?;
    let v: Value = serde_json::from_slice(&resp.body).context("the server's reply is not JSON")?;
    if resp.status != 201 {
        bail!("the server refused to prepare the episode (HTTP {}): {}", resp.status, v["error"]);
    }
    let token = v.pointer("/mcp_headers/Authorization").and_then(Value::as_str).context("no token in the reply")?;
    let field = |k: &str| v[k].as_str().map(str::to_owned).with_context(|| format!("no {k} in the reply"));
    Ok((field("episode_id")?, field("mcp_url")?, token.trim_start_matches("Bearer ").to_owned()))
}
