//! `libero-agent agent --workspace DIR`: the built-in reference agent — a real MCP client with no model behind
//! it. It reads the workspace's `.libero/mcp.json` (URL and token), calls `start_episode`, reads the published
//! observation after every call (public files only), plays a fixed scripted motion (open the gripper, move
//! down and forward, close, lift) and calls `finish_episode`. It is the agent of the runner's end-to-end test,
//! so scheduling, sandbox, MCP, evaluation, metrics and report run without any model API.
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use libero_episode::tools::MCP_SERVER_KEY;
use libero_episode::workspace::OBSERVATION_FILE;
use libero_records::records::RunResult;
use serde::Deserialize;
use serde_json::{Map, Value, json};

use libero_server::client::McpClient;

#[derive(clap::Args, Debug)]
pub struct AgentArgs {
    /// The prepared workspace (holds `.libero/mcp.json` and `TASK_PROMPT.txt`).
    #[arg(long)]
    pub workspace: PathBuf,
    /// Micro-actions per `osc_sequence` call (1–50).
    #[arg(long, default_value_t = 10)]
    pub actions_per_call: usize,
}

/// The scripted policy: (description, micro-action repeated `actions_per_call` times).
const SCRIPT: [(&str, [f64; 7]); 4] = [
    ("open and descend", [0.0, 0.0, -0.5, 0.0, 0.0, 0.0, -1.0]),
    ("move forward", [0.5, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]),
    ("close the gripper", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]),
    ("lift", [0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0]),
];

/// `.libero/mcp.json` as [`libero_episode::workspace::mcp_config`] writes it: servers by name.
#[derive(Deserialize, Default)]
struct McpConfig {
    #[serde(rename = "mcpServers", default)]
    servers: Map<String, Value>,
}

/// One server entry of [`McpConfig`] (values kept as JSON: one of another type reads as absent, as before).
#[derive(Deserialize, Default)]
struct McpServerEntry {
    #[serde(default)]
    url: Value,
    #[serde(default)]
    headers: Value,
}

/// What a `start_episode` or `osc_sequence` reply says of the observation it published; `observation.json`
/// (written by `libero_episode::observation`) names itself with the same `observation_id`.
#[derive(Deserialize, Default)]
struct Published {
    #[serde(default)]
    observation_file: Value,
    #[serde(default)]
    observation_id: Value,
}

/// URL and headers of the `libero` server in a Claude-style MCP config.
pub fn endpoint_of(mcp_json: &Value) -> anyhow::Result<(String, Vec<(String, String)>)> {
    let config = McpConfig::deserialize(mcp_json).unwrap_or_default();
    let entry = config.servers.get(MCP_SERVER_KEY).and_then(|e| McpServerEntry::deserialize(e).ok()).unwrap_or_default();
    let url = entry.url.as_str().context("mcp.json has no mcpServers.libero.url")?.to_owned();
    let headers = entry
        .headers
        .as_object()
        .map(|h| h.iter().filter_map(|(k, v)| v.as_str().map(|v| (k.clone(), v.to_owned()))).collect())
        .unwrap_or_default();
    Ok((url, headers))
}

/// Reads the published observation, checks it is the one the tool reply names and returns its id.
fn read_observation(workspace: &Path, payload: &Value) -> anyhow::Result<Value> {
    let reply = Published::deserialize(payload).unwrap_or_default();
    let file = reply.observation_file.as_str().unwrap_or(OBSERVATION_FILE);
    let path = workspace.join(file);
    let obs: Value = serde_json::from_str(&std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))?)
        .with_context(|| format!("{} is not JSON", path.display()))?;
    let published = Published::deserialize(&obs).unwrap_or_default();
    if published.observation_id != reply.observation_id {
        bail!("published observation {} does not match the reply's {}", published.observation_id, reply.observation_id);
    }
    Ok(published.observation_id)
}

pub fn run(args: AgentArgs) -> anyhow::Result<()> {
    if !(1..=50).contains(&args.actions_per_call) {
        bail!("--actions-per-call must be 1..=50");
    }
    let ws = &args.workspace;
    let cfg_path = ws.join(".libero/mcp.json");
    let cfg: Value = serde_json::from_str(&std::fs::read_to_string(&cfg_path).with_context(|| format!("cannot read {}", cfg_path.display()))?)?;
    let (url, headers) = endpoint_of(&cfg)?;
    let mut client = McpClient::connect(&url, &headers, "libero-agent-reference")?;
    let tools = client.tool_names()?;
    let start = client.call_tool("start_episode", json!({}))?;
    let mut trace = vec![json!({"call": "start_episode", "observation_id": read_observation(ws, &start)?})];
    for (what, action) in SCRIPT {
        let payload = client.call_tool("osc_sequence", json!({"actions": vec![action; args.actions_per_call]}))?;
        trace.push(json!({"call": "osc_sequence", "what": what, "observation_id": read_observation(ws, &payload)?}));
    }
    let finish = client.call_tool("finish_episode", json!({}))?;
    // The finish payload is the episode's result (`result.json` holds it too).
    let result = RunResult::deserialize(&finish).unwrap_or_default();
    let summary = json!({"agent": "libero-agent-reference", "tools": tools, "trace": trace,
        "success": result.success, "accepted_agent_steps": result.accepted_agent_steps});
    println!("{summary}");
    Ok(())
}
