//! `libero-agent mcp-stdio --url URL [--header K:V]`: a stdio MCP server for stdio-only harnesses that relays
//! every JSON-RPC line to an episode's streamable-HTTP endpoint and writes the replies back, one line each.
use std::io::{BufRead, Write};
use std::time::Duration;

use anyhow::Context;
use serde_json::{Value, json};

use libero_server::http_client::{HttpUrl, messages_of, request};

#[derive(clap::Args, Debug)]
pub struct McpStdioArgs {
    /// The episode's MCP endpoint (`mcp_url` from `episode prepare`).
    #[arg(long)]
    pub url: String,
    /// Extra header, e.g. `X-Trace: 1`; repeatable. Secrets belong in `--bearer-env`, not on a command line
    /// that every process of the machine can read.
    #[arg(long = "header", value_name = "K:V")]
    pub headers: Vec<String>,
    /// Environment variable holding the episode token, sent as `Authorization: Bearer <token>`.
    #[arg(long = "bearer-env", value_name = "VAR")]
    pub bearer_env: Option<String>,
}

pub fn run_mcp_stdio(args: McpStdioArgs) -> anyhow::Result<()> {
    let url = HttpUrl::parse(&args.url)?;
    let mut headers = Vec::new();
    for h in &args.headers {
        let (k, v) = h.split_once(':').with_context(|| format!("--header must be K:V, got {h:?}"))?;
        headers.push((k.trim().to_owned(), v.trim().to_owned()));
    }
    if let Some(var) = &args.bearer_env {
        let token = std::env::var(var).with_context(|| format!("--bearer-env {var}: the variable is not set"))?;
        headers.push(("Authorization".into(), format!("Bearer {}", token.trim())));
    }
    let mut session: Option<String> = None;
    let mut protocol: Option<String> = None;
    let stdin = std::io::stdin();
    let mut stdout = std::io::stdout().lock();
    for line in stdin.lock().lines() {
        let line = line?;
        if line.trim().is_empty() {
            continue;
        }
        let id = serde_json::from_str::<Value>(&line).ok().and_then(|v| v.get("id").cloned());
        let mut h = headers.clone();
        h.push(("Content-Type".into(), "application/json".into()));
        h.push(("Accept".into(), "application/json, text/event-stream".into()));
        if let Some(s) = &session {
            h.push(("Mcp-Session-Id".into(), s.clone()));
        }
        if let Some(p) = &protocol {
            h.push(("Mcp-Protocol-Version".into(), p.clone()));
        }
        let replies = match request("POST", &url, &h, line.as_bytes(), Duration::from_secs(3600)) {
            Ok(resp) => {
                if let Some(s) = resp.header("mcp-session-id") {
                    session = Some(s.to_owned());
                }
                if resp.status == 401 {
                    vec![error_reply(id.clone(), "the episode endpoint refused the token (HTTP 401)")]
                } else if resp.status >= 400 {
                    let text = String::from_utf8_lossy(&resp.body).into_owned();
                    let mut m = messages_of(&resp);
                    if m.is_empty() {
                        m.push(error_reply(id.clone(), &format!("HTTP {}: {}", resp.status, text.trim())));
                    }
                    m
                } else {
                    messages_of(&resp)
                }
            }
            Err(e) => vec![error_reply(id.clone(), &format!("cannot reach the episode endpoint: {e:#}"))],
        };
        for r in replies {
            if let Some(v) = r.pointer("/result/protocolVersion").and_then(Value::as_str) {
                protocol = Some(v.to_owned());
            }
            // Notifications have no id and get no reply; only answer what was asked.
            if id.is_none() && r.get("id").is_some_and(Value::is_null) && r.get("error").is_some() {
                continue;
            }
            writeln!(stdout, "{}", serde_json::to_string(&r)?)?;
            stdout.flush()?;
        }
    }
    if let Some(s) = session {
        let mut h = headers.clone();
        h.push(("Mcp-Session-Id".into(), s));
        let _ = request("DELETE", &url, &h, b"", Duration::from_secs(5));
    }
    Ok(())
}

fn error_reply(id: Option<Value>, message: &str) -> Value {
    json!({"jsonrpc": "2.0", "id": id.unwrap_or(Value::Null), "error": {"code": -32603, "message": message}})
}
