//! The real agent CLIs and a third-party MCP client, end to end, with no model and no network.
//!
//! `libero-agent run --harness claude_code|codex|qwen_code|kimi_code` launches the real CLI (pinned, installed by
//! `scripts/setup.py --test` under the cache's `node/node_modules/.bin`) in the real bubblewrap sandbox against
//! the real episode endpoint; its model is `tests/clis/scripted_model.py`, a local endpoint speaking the CLI's
//! wire API (Anthropic Messages for Claude Code, OpenAI Responses for Codex, OpenAI chat completions for Qwen
//! Code and Kimi Code, all streamed) that answers with a fixed script: start_episode, two osc_sequence calls,
//! finish_episode, a final text. The checks: the rollout's
//! record (a valid outcome, the two accepted steps, a clean exit), the harness's own stdout (its tool calls),
//! the token usage (exactly the figures the endpoint reported), and the scrubbing (the API key nowhere in the
//! batch or the workspace, the episode token in no log or record). The MCP Inspector's CLI plays one whole
//! episode from the workspace's own `.libero/mcp.json`, a second independent client beside the Python SDK.
//! A missing CLI fails the test with the command that installs it.
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use libero_records::batch_doc::harness_manifest::HarnessManifest;
use serde_json::{Value, json};

mod common;
use common::scripted_model::{API_KEY, ScriptedModel};
use common::{Server, bin, timeline};

const SETUP_HINT: &str = "run `python3 scripts/setup.py --test`, which installs the pinned agent CLIs and the MCP \
                          Inspector with npm into ~/.cache/libero-agent/node";

fn cli_dir() -> PathBuf {
    libero_testkit::cache_dir().join("node/node_modules/.bin")
}

fn require_cli(name: &str) -> PathBuf {
    let p = cli_dir().join(name);
    assert!(p.is_file(), "{} is missing: {SETUP_HINT}", p.display());
    p
}

/// PATH with the cache's CLIs (and their Node 22) first.
fn cli_path() -> String {
    format!("{}:{}", cli_dir().display(), std::env::var("PATH").unwrap_or_default())
}

fn jsonl(path: &Path) -> Vec<Value> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    text.lines().filter(|l| !l.trim().is_empty()).map(|l| serde_json::from_str(l).unwrap()).collect()
}

/// Sum of one usage figure over the endpoint's answers (`pointer` into each reported usage).
fn reported(answers: &[Value], pointer: &str) -> u64 {
    answers.iter().filter_map(|a| a["usage"].pointer(pointer).and_then(Value::as_u64)).sum()
}

/// Every file below `dir` (no links followed).
fn files_below(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir(dir) else { return out };
    for e in entries.flatten() {
        let p = e.path();
        match e.file_type() {
            Ok(t) if t.is_dir() => out.extend(files_below(&p)),
            Ok(t) if t.is_file() => out.push(p),
            _ => {}
        }
    }
    out
}

fn contains(path: &Path, needle: &str) -> bool {
    std::fs::read(path).is_ok_and(|b| b.windows(needle.len()).any(|w| w == needle.as_bytes()))
}

/// One `run` of T14 by `harness` against the scripted model; the rollout's record, directory and workspace (gone
/// with the rollout's disk where the runner caps it), and the episode's token, read from the workspace while the CLI
/// ran.
/// The rollout's `harness_manifest.json`.
fn manifest_of(r: &Rollout) -> HarnessManifest {
    HarnessManifest::read(&r.dir).unwrap().expect("the rollout's harness manifest")
}

struct Rollout {
    record: Value,
    dir: PathBuf,
    workspace: PathBuf,
    token: Option<String>,
    batch: PathBuf,
    answers: Vec<Value>,
    _tmp: tempfile::TempDir,
}

fn run_t14(harness: &str, cli: &str) -> Rollout {
    run_t14_with(harness, cli, &[])
}

/// [`run_t14`] with more arguments to `run` (`--harness-version V`).
fn run_t14_with(harness: &str, cli: &str, extra: &[&str]) -> Rollout {
    require_cli(cli);
    let tmp = tempfile::tempdir().unwrap();
    let model = ScriptedModel::start(tmp.path());
    let creds = model.credentials(tmp.path());
    let (batch, workspaces) = (tmp.path().join("batch"), tmp.path().join("workspaces"));
    let t0 = std::time::Instant::now();
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let watch = {
        let (workspaces, done) = (workspaces.clone(), done.clone());
        std::thread::spawn(move || {
            common::episode_token_while_running(&workspaces, std::time::Duration::from_secs(900), || done.load(std::sync::atomic::Ordering::SeqCst))
        })
    };
    let out = Command::new(bin())
        .args(["run", "--experiment", "main_table", "--tasks", "T14", "--reps", "1", "--harness", harness, "--model", "scripted"])
        .args(["--wall-time-s", "300", "--credentials-file"])
        .arg(&creds)
        .arg("--batch")
        .arg(&batch)
        .arg("--workspace-root")
        .arg(&workspaces)
        .args(extra)
        .env("PATH", cli_path())
        .output()
        .expect("run libero-agent run");
    done.store(true, std::sync::atomic::Ordering::SeqCst);
    let token = watch.join().unwrap();
    eprintln!("run --harness {harness}: {:.1} s\n{}", t0.elapsed().as_secs_f64(), String::from_utf8_lossy(&out.stderr));
    let records = jsonl(&batch.join("rollouts.jsonl"));
    assert_eq!(records.len(), 1, "{records:?}");
    let record = records[0].clone();
    let dir = batch.join("rollouts").join(record["rollout_id"].as_str().unwrap());
    let logs = files_below(&dir).into_iter().filter(|f| f.parent() == Some(dir.as_path()) && f.extension().is_some_and(|e| e == "log" || e == "jsonl"));
    for f in logs {
        eprintln!("--- {}\n{}", f.display(), std::fs::read_to_string(&f).unwrap_or_default().chars().take(6000).collect::<String>());
    }
    assert!(out.status.success(), "run failed");
    let workspace = PathBuf::from(record["workspace"].as_str().unwrap());
    let answers = model.answered();
    Rollout { record, dir, workspace, token, batch, answers, _tmp: tmp }
}

/// What every CLI's run must show: a valid outcome with the scripted steps, the whole script answered with
/// the tool names the CLI offered, the API key nowhere, the episode token in no log or record.
fn check_rollout(r: &Rollout) {
    let rec = &r.record;
    assert!(rec["outcome"] == "SUCCESS" || rec["outcome"] == "FAIL", "a valid outcome: {rec}");
    assert_eq!(rec["result_status"], "finished", "{rec}");
    assert_eq!(rec["accepted_agent_steps"], 2, "the two scripted osc_sequence calls: {rec}");
    assert_eq!(rec["agent_exit_code"], 0, "{rec}");
    assert!(rec["infrastructure_error"].is_null(), "{rec}");
    let b: Value = serde_json::from_str(&std::fs::read_to_string(r.batch.join("batch.json")).unwrap()).unwrap();
    assert_eq!((b["status"].as_str(), b["sandbox"]["kind"].as_str()), (Some("finished"), Some("bubblewrap")), "{b}");

    assert!(r.answers.iter().all(|a| a["auth_ok"] == true), "the CLI sent the API key: {:?}", r.answers);
    // The script's steps (side requests and a tool search are not steps), by the names the CLI offered: every
    // CLI here prefixes the MCP server's name (Codex as a `mcp__libero` namespace of plain tool names).
    let answered: Vec<&str> = r.answers.iter().filter(|a| a["step"].is_u64()).filter_map(|a| a["answer"].as_str()).collect();
    let script = ["start_episode", "osc_sequence", "osc_sequence", "finish_episode"].map(|t| format!("mcp__libero__{t}"));
    let script: Vec<&str> = script.iter().map(String::as_str).chain(["text"]).collect();
    assert_eq!(answered, script, "the whole script, by the names the CLI offered: {:?}", r.answers);

    // The workspace, where it outlives the rollout (a runner that caps no rollout): the key in none of its files.
    // SAFETY: geteuid(2) has no preconditions.
    if unsafe { libc::geteuid() } == 0 {
        assert!(!r.workspace.exists(), "the workspace outlived the rollout's disk: {}", r.workspace.display());
    }
    let api_key_at: Vec<_> = files_below(&r.batch).into_iter().chain(files_below(&r.workspace)).filter(|f| contains(f, API_KEY)).collect();
    assert!(api_key_at.is_empty(), "the API key leaked into {api_key_at:?}");
    let token = r.token.clone().expect("the episode's token, read from the workspace while the CLI ran");
    let logs = files_below(&r.dir).into_iter().filter(|f| f.parent() == Some(r.dir.as_path()));
    let token_at: Vec<_> = logs.chain([r.batch.join("rollouts.jsonl")]).filter(|f| contains(f, &token)).collect();
    assert!(token_at.is_empty(), "the episode token is in {token_at:?}");

    // The scripted model lives on the host's loopback, outside the agent's network namespace: every answer went
    // through the runner's gateway, which recorded it.
    let manifest = manifest_of(r);
    let via_gateway = manifest.model_requests_passed();
    assert!(via_gateway >= r.answers.len() as u64, "{} answers, {via_gateway} requests through the gateway: {manifest}", r.answers.len());
    assert_eq!(manifest.sandbox_report().and_then(|s| s.network_interfaces.clone()), Some(vec!["lo".to_owned()]), "{manifest}");

    // The transcript the runner followed while the CLI ran (docs/agent_transcript.md): the robot calls in order,
    // each after the observation it acted on, the gateway's usage per answered request, no key.
    let transcript = Path::new(r.record["run_dir"].as_str().unwrap()).join("agent_events.jsonl");
    let text = std::fs::read_to_string(&transcript).unwrap_or_else(|e| panic!("{}: {e}", transcript.display()));
    assert!(!text.contains(API_KEY));
    let events: Vec<Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let calls: Vec<(&str, Option<&str>)> = events
        .iter()
        .filter(|e| e["kind"] == "tool_call" && e["robot_tool"].is_string())
        .map(|e| (e["robot_tool"].as_str().unwrap(), e["observation_id"].as_str()))
        .collect();
    assert_eq!(
        calls,
        [("start_episode", None), ("osc_sequence", Some("obs_000000")), ("osc_sequence", Some("obs_000001")), ("finish_episode", Some("obs_000002"))],
        "{text}"
    );
    let gateway_usage = events.iter().filter(|e| e["kind"] == "usage" && e["source"] == "model_api_gateway").count();
    assert_eq!(gateway_usage, r.answers.len(), "one usage event per answered request: {text}");
    assert_eq!(manifest.agent_events.as_ref().and_then(|e| e.events), Some(events.len() as u64), "{manifest}");
}

/// The record's usage is the sum of what the endpoint reported, read under the provider's own names:
/// `[input, cached input, output]` pointers into each reply's usage.
fn check_usage(r: &Rollout, [input, cached, output]: [&str; 3]) {
    let u = &r.record["usage"];
    assert_eq!(u["available"], true, "usage from the harness's stdout or the runner's gateway: {u}");
    for (field, pointer) in [("input_tokens", input), ("cache_read_input_tokens", cached), ("output_tokens", output)] {
        assert_eq!(u[field], reported(&r.answers, pointer), "{field}: {u}");
    }
    assert!(u["input_tokens"].as_u64() > Some(0), "{u}");
}

/// The harness's stdout (`<harness>_stdout.jsonl` in the rollout directory).
fn stdout_of(r: &Rollout, harness: &str) -> String {
    std::fs::read_to_string(r.dir.join(format!("{harness}_stdout.jsonl"))).unwrap()
}

/// A stream-json `result` line of a successful session (Claude Code, Qwen Code).
fn ends_in_success(stdout: &str) -> bool {
    stdout.lines().any(|l| l.contains(r#""type":"result""#) && l.contains(r#""subtype":"success""#))
}

/// Claude Code in `--print --output-format stream-json` mode plays T14 through the sandbox and the MCP endpoint;
/// the usage of its final `result` line is the sum of what the endpoint reported (Anthropic counts input
/// without the cached part).
#[test]
fn claude_code_plays_a_t14_episode_against_a_scripted_model() {
    let r = run_t14("claude_code", "claude");
    check_rollout(&r);
    let stdout = stdout_of(&r, "claude_code");
    assert!(stdout.contains(r#""name":"mcp__libero__osc_sequence""#), "its tool calls are in its stdout");
    assert!(ends_in_success(&stdout), "{stdout}");
    check_usage(&r, ["/input_tokens", "/cache_read_input_tokens", "/output_tokens"]);
    assert_eq!(r.record["harness_version"]["observed"], "2.1.330", "the rollout's own probe: {}", r.record);
}

/// The CLI of the version asked for, installed apart by `scripts/setup.py --harnesses` (part of `--test`) and picked
/// with `run --harness-version`, launched by its path; the record and the manifest say the version it ran.
fn check_version_ran(r: &Rollout, harness: &str, version: &str) {
    assert_eq!(r.record["harness_version"]["observed"], version, "{}", r.record);
    let manifest = manifest_of(r);
    let apart = cli_dir().parent().unwrap().parent().unwrap().parent().unwrap().join(format!("harnesses/{harness}-{version}"));
    assert!(manifest.command.as_ref().and_then(|c| c.first()).is_some_and(|c| Path::new(c).starts_with(&apart)), "{manifest}");
    assert_eq!(manifest.harness_version.as_ref().and_then(|v| v.observed.as_deref()), Some(version), "{manifest}");
    let b: Value = serde_json::from_str(&std::fs::read_to_string(r.batch.join("batch.json")).unwrap()).unwrap();
    assert_eq!((b["settings"]["harness_version"].as_str(), b["harness"]["version"]["observed"].as_str()), (Some(version), Some(version)), "{b}");
}

/// The paper's Claude Code (2.1.139, App. A) plays T14 as the tests' version does.
#[test]
fn the_papers_claude_code_plays_a_t14_episode_when_asked_for() {
    let r = run_t14_with("claude_code", "claude", &["--harness-version", "2.1.139"]);
    check_rollout(&r);
    assert!(ends_in_success(&stdout_of(&r, "claude_code")));
    check_usage(&r, ["/input_tokens", "/cache_read_input_tokens", "/output_tokens"]);
    check_version_ran(&r, "claude_code", "2.1.139");
}

/// The paper's Codex (0.154.0, App. A) plays T14 as the tests' version does.
#[test]
fn the_papers_codex_plays_a_t14_episode_when_asked_for() {
    let r = run_t14_with("codex", "codex", &["--harness-version", "0.154.0"]);
    check_rollout(&r);
    check_usage(&r, ["/input_tokens", "/input_tokens_details/cached_tokens", "/output_tokens"]);
    check_version_ran(&r, "codex", "0.154.0");
}

/// Codex (`exec --json`, pointed at the endpoint by `openai_base_url`) plays T14 through the sandbox and the
/// MCP endpoint; the usage of its `turn.completed` events is the sum of what the endpoint reported (OpenAI
/// counts cached input inside the input).
#[test]
fn codex_plays_a_t14_episode_against_a_scripted_model() {
    let r = run_t14("codex", "codex");
    check_rollout(&r);
    let stdout = stdout_of(&r, "codex");
    let calls: Vec<Value> = stdout
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|e| e["type"] == "item.completed" && e["item"]["type"] == "mcp_tool_call")
        .map(|e| json!([e["item"]["server"], e["item"]["tool"], e["item"]["status"]]))
        .collect();
    assert_eq!(calls.len(), 4, "its MCP tool calls are in its stdout: {calls:?}");
    assert!(calls.iter().all(|c| c[0] == "libero" && c[2] == "completed"), "{calls:?}");
    check_usage(&r, ["/input_tokens", "/input_tokens_details/cached_tokens", "/output_tokens"]);
    assert_eq!(r.record["usage"]["total_tokens"], reported(&r.answers, "/total_tokens"));
    assert_eq!(r.record["harness_version"]["observed"], "0.169.0", "the rollout's own probe: {}", r.record);
}

/// Qwen Code, the pinned version installed (so `run` starts it directly rather than through `npx`), plays T14
/// over OpenAI chat completions. It offers MCP tools only after its `tool_search`, which the script calls first,
/// as a model would. The usage of its `result` line is the sum of what the endpoint reported.
#[test]
fn qwen_code_plays_a_t14_episode_against_a_scripted_model() {
    let r = run_t14("qwen_code", "qwen");
    check_rollout(&r);
    assert_eq!(r.answers[0]["answer"], "tool_search", "the episode's tools are found by search first");
    let manifest = manifest_of(&r);
    assert_eq!(manifest.command.as_ref().and_then(|c| c.first()).map(String::as_str), Some("qwen"), "{manifest}");
    assert_eq!(manifest.harness_version.as_ref().and_then(|v| v.observed.as_deref()), Some("0.24.0"), "{manifest}");
    let stdout = stdout_of(&r, "qwen_code");
    assert!(ends_in_success(&stdout), "{stdout}");
    check_usage(&r, ["/prompt_tokens", "/prompt_tokens_details/cached_tokens", "/completion_tokens"]);
}

/// Kimi Code, the pinned version installed, plays T14 over OpenAI chat completions with the launch's
/// `config.toml` and `mcp.json` in KIMI_CODE_HOME. Its `stream-json` stdout carries messages and tool calls but
/// no token counts; its model traffic went through the runner's gateway (its sandbox has no other way out), whose
/// records give the usage — exactly the endpoint's sums — never the agent-writable session files.
#[test]
fn kimi_code_plays_a_t14_episode_against_a_scripted_model() {
    let r = run_t14("kimi_code", "kimi");
    check_rollout(&r);
    let stdout = stdout_of(&r, "kimi_code");
    assert!(stdout.contains(r#""name":"mcp__libero__finish_episode""#), "its tool calls are in its stdout: {stdout}");
    check_usage(&r, ["/prompt_tokens", "/prompt_tokens_details/cached_tokens", "/completion_tokens"]);
    let manifest = manifest_of(&r);
    assert_eq!(manifest.usage_source.clone().flatten().as_deref(), Some("model_api_gateway"), "{manifest}");
    assert_eq!(manifest.model_api().and_then(|m| m.responses_with_usage), Some(r.answers.len() as u64), "{manifest}");
}

/// `mcp-inspector --cli` with the workspace's `.libero/mcp.json`; stdout parsed as JSON.
fn inspector(config: &Path, args: &[&str]) -> (Output, Value) {
    let out = Command::new(require_cli("mcp-inspector"))
        .args(["--cli", "--config"])
        .arg(config)
        .args(["--server", "libero"])
        .args(args)
        .env("PATH", cli_path())
        .env("MCP_INSPECTOR_SECRET_STORE", "memory")
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let v = serde_json::from_slice(&out.stdout).unwrap_or(Value::Null);
    (out, v)
}

/// A `tools/call`: the tool's structured payload, and whether it was a tool error (the Inspector then exits 1).
fn call(config: &Path, tool: &str, args: &[&str]) -> (Value, bool) {
    let mut a = vec!["--method", "tools/call", "--tool-name", tool];
    if !args.is_empty() {
        a.push("--tool-arg");
        a.extend(args);
    }
    let (out, v) = inspector(config, &a);
    let is_error = v["isError"] == true;
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(v["structuredContent"].is_object() && out.status.success() != is_error, "inspector {tool}: {said}");
    (v["structuredContent"].clone(), is_error)
}

/// A call that must succeed.
fn ok_call(config: &Path, tool: &str, args: &[&str]) -> Value {
    let (payload, is_error) = call(config, tool, args);
    assert!(!is_error && payload["ok"] == true, "{tool}: {payload}");
    payload
}

/// The official MCP Inspector, as a command-line client, plays a whole episode from the workspace's published
/// MCP configuration: it lists the three tools, starts, acts twice, sees an out-of-range action refused with
/// the protocol's message (not counted), finishes with the verdict; a wrong token gets nothing.
#[test]
fn mcp_inspector_cli_plays_a_whole_episode() {
    require_cli("mcp-inspector");
    let tmp = tempfile::tempdir().unwrap();
    let server = Server::start(&tmp.path().join("data"));
    let ws = tmp.path().join("ws");
    let prepared = common::prepare_t14(&server.url, &ws);
    let config = ws.join(".libero/mcp.json");

    let (out, listed) = inspector(&config, &["--method", "tools/list"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let names: Vec<&str> = listed["tools"].as_array().unwrap().iter().filter_map(|t| t["name"].as_str()).collect();
    assert_eq!(names, ["start_episode", "osc_sequence", "finish_episode"]);

    let start = ok_call(&config, "start_episode", &[]);
    assert!(ws.join(start["observation_file"].as_str().unwrap()).is_file(), "{start}");
    let down = ok_call(&config, "osc_sequence", &["actions=[[0,0,-0.5,0,0,0,-1],[0,0,-0.5,0,0,0,-1]]"]);
    assert_eq!(down["execution"]["micro_step_count"], 2, "{down}");
    let (refused, is_error) = call(&config, "osc_sequence", &["actions=[[0,0,3,0,0,0,1]]"]);
    assert!(is_error && refused["ok"] == false, "{refused}");
    assert_eq!(refused["error"], "native OSC action components must be within [-1, 1]", "{refused}");
    let up = ok_call(&config, "osc_sequence", &["actions=[[0,0,0.5,0,0,0,1]]"]);
    assert_ne!(up["observation_id"], down["observation_id"]);
    let finish = ok_call(&config, "finish_episode", &[]);
    assert_eq!((finish["status"].as_str(), finish["accepted_agent_steps"].as_u64()), (Some("finished"), Some(2)), "{finish}");
    assert!(finish["success"].is_boolean(), "{finish}");
    let result: Value =
        serde_json::from_str(&std::fs::read_to_string(Path::new(prepared["run_dir"].as_str().unwrap()).join("result.json")).unwrap()).unwrap();
    assert_eq!((result["status"].as_str(), result["accepted_agent_steps"].as_u64()), (Some("finished"), Some(2)), "{result}");
    assert_eq!(result["success"], finish["success"]);

    let mut wrong: Value = serde_json::from_str(&std::fs::read_to_string(&config).unwrap()).unwrap();
    wrong["mcpServers"]["libero"]["headers"]["Authorization"] = json!("Bearer wrong-token");
    let wrong_config = tmp.path().join("wrong.json");
    std::fs::write(&wrong_config, wrong.to_string()).unwrap();
    let (out, v) = inspector(&wrong_config, &["--method", "tools/list"]);
    assert!(!out.status.success() && v["tools"].is_null(), "a wrong token lists nothing: {v}");
}

/// The action `LIBERO_PERCEPTION action=…` line of a command's output.
fn perceived_action(output: &str) -> Option<Vec<f64>> {
    let line = output.lines().rev().find_map(|l| l.trim().strip_prefix("LIBERO_PERCEPTION action="))?;
    line.split(',').map(|x| x.trim().parse::<f64>().ok()).collect()
}

/// What the paper's agents did (Appendix F), by a real CLI in the real sandbox, played on a real server: the
/// scripted model (`--script perception`) starts the episode, has the CLI's own shell tool run
/// `tests/clis/perception_program.py` (numpy, scipy, Pillow and OpenCV back-projecting the published head depth
/// through the published calibration), reads the action that program printed from the command's output in the
/// conversation, acts with it through `osc_sequence` and finishes. Checked: the program ran with the toolbox
/// inside the sandbox (its interpreter and numpy under `/opt/libero-toolbox`), exited 0, its output reached the
/// model (the executed action is the printed one), and the review API returns the command, its output and the
/// robot's calls in the order they happened.
fn check_perception(harness: &str, cli: &str, shell_tool: &str) {
    require_cli(cli);
    let tmp = tempfile::tempdir().unwrap();
    let model = ScriptedModel::start_script(tmp.path(), "perception");
    let creds = model.credentials(tmp.path());
    let server = Server::start(&tmp.path().join("data"));
    let batch = tmp.path().join("batch");
    let out = Command::new(bin())
        .args(["run", "--experiment", "main_table", "--tasks", "T14", "--reps", "1", "--harness", harness, "--model", "scripted"])
        .args(["--wall-time-s", "300", "--server", &server.url, "--credentials-file"])
        .arg(&creds)
        .arg("--batch")
        .arg(&batch)
        .arg("--workspace-root")
        .arg(tmp.path().join("ws"))
        .env("PATH", cli_path())
        .output()
        .expect("run libero-agent run");
    let stderr = String::from_utf8_lossy(&out.stderr);
    let records = jsonl(&batch.join("rollouts.jsonl"));
    let record = &records[0];
    let answers = model.answered();
    let steps: Vec<&str> = answers.iter().filter(|a| a["step"].is_u64()).filter_map(|a| a["answer"].as_str()).collect();
    assert!(out.status.success(), "run failed: {stderr}\n{record}\nthe model answered {steps:?}: {answers:?}");
    assert_eq!(
        steps,
        ["mcp__libero__start_episode", shell_tool, "mcp__libero__osc_sequence", "mcp__libero__finish_episode", "text"],
        "the whole perception script: {answers:?}"
    );
    assert_eq!((record["result_status"].as_str(), record["accepted_agent_steps"].as_u64()), (Some("finished"), Some(1)), "{record}");
    assert!(record["outcome"] == "SUCCESS" || record["outcome"] == "FAIL", "{record}");

    // The review API: the shell command with its output, between the start and the call it led to.
    let id = record["episode_id"].as_str().unwrap();
    let (items, _) = timeline(&server, id);
    let at = |pred: &dyn Fn(&Value) -> bool| items.iter().position(|i| pred(i)).unwrap_or_else(|| panic!("not in the timeline: {items:#?}"));
    let shell = at(&|i| i["kind"] == "shell" && i["output"].as_str().is_some_and(|o| o.contains("LIBERO_PERCEPTION")));
    let item = &items[shell];
    let (command, output) = (item["command"].as_str().unwrap(), item["output"].as_str().unwrap());
    assert!(command.contains("from scipy.spatial.transform import Rotation") && command.contains("np.load("), "the program as the model sent it: {item}");
    // Codex reports the exit code; Claude Code's Bash result says only whether it failed.
    assert!(item["exit_code"] == 0 || (item["exit_code"].is_null() && item["is_error"] == false), "it ran without error: {item}");
    assert!(output.contains("python=/opt/libero-toolbox/bin/python3") && output.contains("numpy=/opt/libero-toolbox/"), "the toolbox's python3 and numpy ran it: {output}");
    assert!(output.contains("valid depth pixels back-projected"), "{output}");
    let printed = perceived_action(output).expect("the printed action");
    let start = at(&|i| i["kind"] == "robot_call" && i["tool"] == "start_episode");
    let act = at(&|i| i["kind"] == "robot_call" && i["tool"] == "osc_sequence");
    let finish = at(&|i| i["kind"] == "robot_call" && i["tool"] == "finish_episode");
    let asked = at(&|i| i["kind"] == "tool_call" && i["robot_tool"] == "osc_sequence");
    assert!(start < shell && shell < asked && asked <= act + 1 && act < finish, "start {start}, shell {shell}, osc call {asked}/{act}, finish {finish}: {items:#?}");

    // The output reached the model: the action the server executed is the one the program printed.
    let run_dir = PathBuf::from(record["run_dir"].as_str().unwrap());
    let calls = jsonl(&run_dir.join("actions.jsonl"));
    let osc = calls.iter().find(|c| c["request"]["tool"] == "osc_sequence").expect("the osc_sequence call");
    let executed: Vec<f64> = osc["request"]["arguments"]["actions"][0].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
    assert_eq!(executed.len(), 7);
    assert!(executed.iter().zip(&printed).all(|(a, b)| (a - b).abs() < 1e-9), "executed {executed:?}, printed {printed:?}");
    assert!(printed[..3].iter().any(|x| x.abs() > 1e-3), "a move computed from the depth, not zeros: {printed:?}");
}

#[test]
fn codex_runs_the_papers_depth_back_projection_with_the_toolbox_and_acts_on_it() {
    check_perception("codex", "codex", "exec_command");
}

#[test]
fn claude_code_runs_the_papers_depth_back_projection_with_the_toolbox_and_acts_on_it() {
    check_perception("claude_code", "claude", "Bash");
}
