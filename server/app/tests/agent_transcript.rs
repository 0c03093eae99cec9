//! The agent's transcript beside the robot (issue 32, item 2): a `--harness command` agent
//! (`tests/clis/transcript_agent.py`) runs in the real sandbox through `libero-agent run --server`, prints lines
//! around its MCP calls, asks the scripted model API once through the runner's gateway and prints what a hostile
//! agent would. Its printed lines reach the episode's live socket while it runs, `GET /api/episodes/{id}/agent`
//! returns them and the robot's calls in the order they happened, bounded and scrubbed, to the operator only, and
//! the review page in chromium shows what the agent printed before the call a line led to; its
//! tokens are the gateway's, never the usage line it printed. A runner whose server is on another machine posts
//! the transcript to the operator API instead (`POST /api/episodes/{id}/agent/events`), which only the operator
//! may do.
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use libero_records::agent_events::{AgentEvent, Kind, Source};
use libero_records::batch_doc::harness_manifest::HarnessManifest;
use libero_runner::harness::Harness;
use libero_runner::transcript::{Follower, Normalizer, Streams, Target};
use serde_json::{Value, json};

mod common;
use common::scripted_model::{API_KEY, ScriptedModel};
use common::{Server, bin, http, http_get_json, timeline, wait_success};

/// The agent's numbered lines and the robot's calls, in the timeline's order.
fn story(items: &[Value]) -> Vec<String> {
    items
        .iter()
        .filter_map(|it| match it["kind"].as_str() {
            Some("robot_call") => Some(format!("call {}", it["tool"].as_str().unwrap_or("?"))),
            Some("message") => it["text"].as_str().and_then(|t| t.strip_prefix("agent line ")).map(|t| format!("line {}", &t[..1])),
            _ => None,
        })
        .collect()
}

/// The episode token the workspace's MCP configuration holds.
fn episode_token(workspace: &Path) -> String {
    let cfg: Value = serde_json::from_str(&std::fs::read_to_string(workspace.join(".libero/mcp.json")).unwrap()).unwrap();
    cfg["mcpServers"]["libero"]["headers"]["Authorization"].as_str().unwrap().trim_start_matches("Bearer ").to_owned()
}

#[test]
fn a_sandboxed_agents_printed_lines_stream_live_and_come_back_in_order_with_the_robot_calls() {
    let tmp = tempfile::tempdir().unwrap();
    let model = ScriptedModel::start(tmp.path());
    let creds = model.credentials(tmp.path());
    let server = Server::start(&tmp.path().join("data"));
    let agent_cmd = common::inline_python_agent("transcript_agent.py", "1.0");
    let batch = tmp.path().join("batch");
    let log = tmp.path().join("run.log");
    let mut run = Command::new(bin())
        .args(["run", "--experiment", "main_table", "--tasks", "T14", "--reps", "1", "--harness", "command", "--model", "scripted"])
        .args(["--wall-time-s", "300", "--server", &server.url, "--agent-cmd", &agent_cmd, "--credentials-file"])
        .arg(&creds)
        .arg("--batch")
        .arg(&batch)
        .arg("--workspace-root")
        .arg(tmp.path().join("ws"))
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();

    // The live page's socket, opened as soon as the episode is listed (prepared: its live view exists).
    let t = Instant::now();
    let id = loop {
        let (_, list) = http_get_json(&format!("{}/api/episodes", server.url));
        if let Some(id) = list["episodes"].as_array().and_then(|e| e.first()).and_then(|e| e["id"].as_str()) {
            break id.to_owned();
        }
        assert!(t.elapsed() < Duration::from_secs(300), "no episode was prepared: {}", std::fs::read_to_string(&log).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(100));
    };
    let socket = common::read_socket(&format!("{}/ws/episodes/{id}", server.url), &server.token);
    // The episode's token, from the workspace while the agent runs (the workspace goes with the rollout's disk).
    let episode_token = common::episode_token_while_running(&tmp.path().join("ws"), Duration::from_secs(120), || matches!(run.try_wait(), Ok(Some(_))));
    wait_success(&mut run, Duration::from_secs(600), "libero-agent run --harness command");
    let live = socket.join().unwrap().unwrap_or_else(|e| panic!("the live socket: {e}"));
    let run_log = std::fs::read_to_string(&log).unwrap_or_default();

    let record: Value = serde_json::from_str(std::fs::read_to_string(batch.join("rollouts.jsonl")).unwrap().lines().next().unwrap()).unwrap();
    assert_eq!((record["outcome"].is_string(), record["accepted_agent_steps"].as_u64()), (true, Some(1)), "{record}\n{run_log}");
    assert_eq!(record["episode_id"], json!(id));

    // Live: the agent's lines reached the socket while the episode ran (before `finished`), in order.
    let live_lines: Vec<String> = live
        .iter()
        .filter(|m| m["type"] == "agent")
        .flat_map(|m| m["events"].as_array().unwrap().iter().filter_map(|e| e["text"].as_str().map(str::to_owned)))
        .filter_map(|t| t.strip_prefix("agent line ").map(|r| r[..1].to_owned()))
        .collect();
    assert!(live.last().is_some_and(|m| m["type"] == "finished"), "the stream ran to the verdict");
    assert_eq!(live_lines, ["1", "2", "3", "4", "5", "6", "7"], "every line printed before finish_episode, live: {live:?}");

    // The API: the printed lines and the robot's calls in the order they happened.
    let (items, _) = timeline(&server, &id);
    assert_eq!(
        story(&items),
        ["line 1", "line 2", "call start_episode", "line 3", "line 4", "call osc_sequence", "line 5", "line 6", "line 7", "call finish_episode", "line 8"],
        "{items:#?}"
    );
    let texts: Vec<&str> = items.iter().filter_map(|i| i["text"].as_str()).collect();
    assert!(texts.iter().any(|t| t.starts_with("agent line 4: head depth (256, 256) median")), "numpy read the published depth: {texts:?}");
    assert!(texts.contains(&"agent line 6: the model said 'ok'"), "the model API through the gateway: {texts:?}");
    // Hostile output: a line of 3 MiB counted, not kept; invalid UTF-8 shown replaced; the key scrubbed.
    assert!(texts.iter().any(|t| t.contains("line of 3145729 bytes") || t.contains("line of 3145728 bytes")), "{texts:?}");
    assert!(texts.iter().any(|t| t.starts_with("not utf-8: \u{fffd}\u{fffd}")), "{texts:?}");
    assert!(texts.contains(&"my key is <redacted>"), "{texts:?}");
    assert!(items.iter().all(|i| i["kind"] != "usage" || i["source"] == "model_api_gateway"), "no usage event from what the agent printed");
    let gateway: Vec<&Value> = items.iter().filter(|i| i["kind"] == "usage").collect();
    assert_eq!(gateway.len(), 1, "the one model request, from the gateway's record: {gateway:?}");
    let run_dir = PathBuf::from(record["run_dir"].as_str().unwrap());
    let transcript = std::fs::read_to_string(run_dir.join("agent_events.jsonl")).unwrap();
    assert!(!transcript.contains(API_KEY) && transcript.len() < 1 << 20, "scrubbed and bounded ({} bytes)", transcript.len());

    // Tokens: the gateway's figures (one request: 1200 in, of them 400 cached, 30 out), not the printed line's.
    let u = &record["usage"];
    assert_eq!((u["source"].as_str(), u["input_tokens"].as_u64(), u["output_tokens"].as_u64()), (Some("model_api_gateway"), Some(1200), Some(30)), "{u}");
    assert_eq!(model.answered().len(), 1);
    let manifest = HarnessManifest::read(&batch.join("rollouts").join(record["rollout_id"].as_str().unwrap())).unwrap().expect("the rollout's harness manifest");
    assert_eq!(manifest.agent_events.as_ref().and_then(|e| e.events), Some(transcript.lines().count() as u64), "{manifest}");

    // The review page: the transcript beside the calls, and what came before the call a line led to.
    let artifacts = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/dashboard");
    std::fs::create_dir_all(&artifacts).unwrap();
    let checked = common::browser_script("agent_review_check.cjs", &[&server.url, &id, &artifacts.to_string_lossy()], &server.token);
    assert_eq!(checked["ok"], true, "{checked}");

    // Operator only: no credential, or the episode's own token, gets nothing.
    let url = format!("{}/api/episodes/{id}/agent", server.url);
    assert_eq!(http("GET", &url, &[], b"").0, 401);
    let token = format!("Bearer {}", episode_token.expect("the workspace's MCP configuration, read while the agent ran"));
    assert_eq!(http("GET", &url, &[("Authorization", &token)], b"").0, 401);
}

/// A Claude Code `stream-json` line calling its Read tool on `path`.
fn claude_read(id: &str, path: &Path) -> String {
    json!({"type": "assistant", "message": {"content": [{"type": "tool_use", "id": id, "name": "Read", "input": {"file_path": path}}]}}).to_string()
}

#[test]
fn a_runner_whose_server_is_elsewhere_posts_the_transcript_and_only_the_operator_may() {
    let tmp = tempfile::tempdir().unwrap();
    let server = Server::start(&tmp.path().join("data"));
    let ws = tmp.path().join("ws");
    let prepared = common::prepare_t14(&server.url, &ws);
    let id = prepared["episode_id"].as_str().unwrap().to_owned();
    let mut mcp = libero_server::client::McpClient::connect_with_token(prepared["mcp_url"].as_str().unwrap(), &episode_token(&ws), "transcript-test").unwrap();
    let start = mcp.call_tool("start_episode", json!({})).unwrap();
    assert_eq!(start["observation_id"], "obs_000000");

    // What a Claude Code agent printed, as a runner on another machine follows it: posted, with a copy of its own.
    // It viewed the published head image, an image it made itself, and a file outside its workspace.
    let (stdout, stderr, local) = (tmp.path().join("claude_code_stdout.jsonl"), tmp.path().join("claude_code_stderr.log"), tmp.path().join("agent_events.jsonl"));
    let lines = [
        json!({"type": "assistant", "message": {"content": [{"type": "text", "text": "first line"}]}}).to_string(),
        claude_read("t1", &ws.join("benchmark_inputs/current_observation/head/rgb.png")),
        claude_read("t2", &ws.join("scratch/planted.png")),
        claude_read("t3", Path::new("/etc/passwd")),
    ];
    std::fs::write(&stdout, lines.join("\n") + "\n").unwrap();
    std::fs::write(&stderr, "a warning\n").unwrap();
    let follower = Follower::start(
        Normalizer::new(Harness::ClaudeCode, &ws, &[]),
        Streams { stdout, stderr, gateway: None },
        Target::Remote { server_url: server.url.clone(), episode_id: id.clone(), local: local.clone() },
    );
    let summary = follower.finish();
    assert!(summary.errors.is_empty(), "{:?}", summary.errors);
    assert_eq!((summary.posted, summary.written.events), (Some(5), 5));
    let kept: Vec<AgentEvent> = std::fs::read_to_string(&local).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let kinds: Vec<(Kind, Option<Source>)> = kept.iter().map(|e| (e.kind, e.source)).collect();
    let (from_stdout, from_stderr) = (Some(Source::Stdout), Some(Source::Stderr));
    assert_eq!(kinds, [(Kind::Message, from_stdout), (Kind::ImageView, from_stdout), (Kind::ImageView, from_stdout), (Kind::FileRead, from_stdout), (Kind::Stderr, from_stderr)]);

    // The server's timeline: the robot's call, then the agent's events; the published image opens from the
    // episode's private copy of the observation current then, the others are paths only.
    let (items, _) = timeline(&server, &id);
    let kinds: Vec<&str> = items.iter().map(|i| i["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds, ["robot_call", "message", "image_view", "image_view", "file_read", "stderr"], "{items:#?}");
    let url = items[2]["observation_url"].as_str().expect("the published image is served");
    assert_eq!(url, format!("/episodes/{id}/observations/obs_000000/head/rgb.png"));
    let (status, _, png) = http("GET", &format!("{}{url}", server.url), &[("Authorization", &format!("Bearer {}", server.token))], b"");
    assert!(status == 200 && png.starts_with(b"\x89PNG"), "{status}");
    assert!(items[3]["observation_url"].is_null() && items[3]["workspace_path"] == "scratch/planted.png", "{}", items[3]);
    assert!(items[4]["observation_url"].is_null() && items[4]["workspace_path"].is_null(), "{}", items[4]);

    // The operator API only: no credential, the episode's token, a body that is not events, too many events.
    let url = format!("{}/api/episodes/{id}/agent/events", server.url);
    let forged = json!({"t": "9999", "seq": 9, "kind": "image_view", "text": "forged", "observation_file": "../../../../etc/passwd"});
    let body = json!({"events": [forged]}).to_string();
    let json_header = ("Content-Type", "application/json");
    assert_eq!(http("POST", &url, &[json_header], body.as_bytes()).0, 401);
    let token = format!("Bearer {}", episode_token(&ws));
    assert_eq!(http("POST", &url, &[json_header, ("Authorization", &token)], body.as_bytes()).0, 401);
    let operator = format!("Bearer {}", server.token);
    let with = |b: &str| http("POST", &url, &[json_header, ("Authorization", &operator)], b.as_bytes()).0;
    assert_eq!(with(r#"{"events": [{"kind": "not a kind"}]}"#), 400);
    let many = json!({"events": vec![json!({"t": "x", "seq": 0, "kind": "other"}); 1001]}).to_string();
    assert_eq!(with(&many), 413);
    assert_eq!(with(&body), 200);
    let (items, _) = timeline(&server, &id);
    let last = items.last().unwrap();
    assert_eq!(last["text"], "forged", "the operator's post was kept");
    assert!(last["observation_url"].is_null(), "a path out of the observation is never served: {last}");
    assert_eq!(http("POST", &format!("{}/api/episodes/ep-none/agent/events", server.url), &[json_header, ("Authorization", &operator)], body.as_bytes()).0, 404);
}
