//! Nothing an agent does can make its outcome INVALID (a free rerun): an agent that ends without
//! `finish_episode` — it exits, or kills its own CLI mid-episode, or exits after the runner's gateway refused it
//! (no model API configured) or after cutting its own model request short, or never starts its episode and is
//! ended by the watchdog — gets its own FAIL, on the record and on the server, through the real sandbox (as a uid
//! of the rollout's own when the runner is root). INVALID stays for what the agent did not cause: here, a model API
//! that fails it (the runner's gateway records the 502 of an unreachable provider, or the provider's own 503, with
//! the cause `upstream`, which the agent cannot write). The agents are `tests/clis/quitting_agent.py`, a plain
//! `exit 3`, `sleep`, and short inline Python.
use std::io::{Read, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use libero_records::batch_doc::harness_manifest::HarnessManifest;
use serde_json::Value;

mod common;
use common::bin;

/// One sandboxed T14 rollout of `agent_cmd`; its record, the run's exit status and stderr.
fn rollout(dir: &Path, name: &str, agent_cmd: &str, credentials: Option<&Path>) -> (Value, bool, String) {
    rollout_with(dir, name, agent_cmd, credentials, "300")
}

/// The same with a wall-time budget of `wall_time_s` seconds.
fn rollout_with(dir: &Path, name: &str, agent_cmd: &str, credentials: Option<&Path>, wall_time_s: &str) -> (Value, bool, String) {
    let batch = dir.join(name);
    let mut cmd = Command::new(bin());
    cmd.args(["run", "--experiment", "main_table", "--harness", "command", "--model", "quitter", "--tasks", "T14", "--reps", "1"])
        .args(["--agent-cmd", agent_cmd, "--wall-time-s", wall_time_s, "--batch"])
        .arg(&batch)
        .arg("--workspace-root")
        .arg(dir.join(format!("{name}-ws")));
    if let Some(c) = credentials {
        cmd.arg("--credentials-file").arg(c);
    }
    let out = cmd.output().expect("run libero-agent run");
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    let text = std::fs::read_to_string(batch.join("rollouts.jsonl")).unwrap_or_else(|e| panic!("{e}: {stderr}"));
    let record: Value = serde_json::from_str(text.lines().next().unwrap()).unwrap();
    (record, out.status.success(), stderr)
}

fn quitting_agent(mode: &str) -> String {
    common::inline_python_agent("quitting_agent.py", mode)
}

/// The episode's own result, as the server wrote it.
fn result_of(record: &Value) -> Value {
    let run_dir = PathBuf::from(record["run_dir"].as_str().unwrap());
    serde_json::from_str(&std::fs::read_to_string(run_dir.join("result.json")).unwrap()).unwrap()
}

#[test]
fn an_agent_that_exits_or_kills_its_own_cli_before_finishing_gets_its_own_fail_never_invalid() {
    let tmp = tempfile::tempdir().unwrap();

    // It never starts the episode: it exits at once.
    let (rec, ok, err) = rollout(tmp.path(), "exits", "exit 3", None);
    assert!(ok, "a FAIL is an ordinary outcome: {err}");
    assert_eq!(rec["outcome"], "FAIL", "{rec}\n{err}");
    assert!(rec["infrastructure_error"].is_null(), "{rec}");
    assert_eq!((rec["agent_exit_code"].as_i64(), rec["termination_reason"].as_str()), (Some(3), Some("agent_ended_without_finish_episode")), "{rec}");
    let result = result_of(&rec);
    assert_eq!((result["status"].as_str(), result["success"].as_bool()), (Some("finished"), Some(false)), "{result}");
    assert!(err.contains("w1_t14_level3: FAIL"), "the progress line: {err}");

    // It acts once, then kills its whole process group, its "CLI" included.
    let (rec, ok, err) = rollout(tmp.path(), "kills", &quitting_agent("kill"), None);
    assert!(ok, "{err}");
    assert_eq!(rec["outcome"], "FAIL", "{rec}\n{err}");
    assert!(rec["infrastructure_error"].is_null(), "{rec}");
    assert_eq!(rec["accepted_agent_steps"], 1, "{rec}");
    let result = result_of(&rec);
    assert_eq!((result["termination_reason"].as_str(), result["success"].as_bool()), (Some("agent_ended_without_finish_episode"), Some(false)), "{result}");
    assert!(result["private_evaluation"].is_object(), "the verdict's diagnostics are kept: {result}");
    let log = std::fs::read_to_string(PathBuf::from(rec["run_dir"].as_str().unwrap()).join("actions.jsonl")).unwrap();
    assert!(log.lines().last().is_some_and(|l| l.contains("agent_ended_without_finish_episode") && l.contains("exit code")), "the action log says why: {log}");
}

#[test]
fn an_agent_whose_model_api_fails_is_invalid_with_the_gateways_cause() {
    let tmp = tempfile::tempdir().unwrap();
    let closed = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let creds = tmp.path().join("credentials");
    std::fs::write(&creds, format!("APIKEY=sk-quitter-0123456789abcdef\nAPIURL=http://127.0.0.1:{closed}\n")).unwrap();
    let (rec, ok, err) = rollout(tmp.path(), "provider-down", &quitting_agent("model"), Some(&creds));
    assert!(!ok, "every rollout INVALID: run exits non-zero: {err}");
    assert_eq!(rec["outcome"], "INVALID", "{rec}\n{err}");
    let why = rec["infrastructure_error"].as_str().expect("the reason");
    assert!(why.contains("harness exited before finish_episode (exit code 1)") && why.contains("the model API answered 502"), "{why}");
}

/// The rollout's directory in the batch `name` (its logs, the gateway's records, the manifest).
fn rollout_dir(dir: &Path, name: &str) -> PathBuf {
    dir.join(name).join("rollouts/w1_t14_level3")
}

/// What the runner's gateway recorded of the agent's model traffic.
fn gateway_records(dir: &Path, name: &str) -> Vec<Value> {
    let text = std::fs::read_to_string(rollout_dir(dir, name).join("sandbox/model_api.jsonl")).unwrap_or_default();
    text.lines().filter(|l| !l.trim().is_empty()).map(|l| serde_json::from_str(l).unwrap()).collect()
}

/// The agent's stdout as the runner kept it.
fn agent_stdout(dir: &Path, name: &str) -> String {
    String::from_utf8_lossy(&std::fs::read(rollout_dir(dir, name).join("command_stdout.log")).unwrap_or_default()).into_owned()
}

/// A `--agent-cmd` running `script` with the sandbox's python3 (inlined in a heredoc).
fn inline_python(script: &str) -> String {
    format!("python3 - <<'PY'\n{script}\nPY")
}

/// The agent's own FAIL: a finished episode, no infrastructure error, the forfeit's termination reason.
fn assert_own_fail(rec: &Value, ok: bool, err: &str) {
    assert!(ok, "a FAIL is an ordinary outcome: {err}");
    assert_eq!(rec["outcome"], "FAIL", "{rec}\n{err}");
    assert!(rec["infrastructure_error"].is_null(), "{rec}");
    let result = result_of(rec);
    assert_eq!((result["status"].as_str(), result["success"].as_bool()), (Some("finished"), Some(false)), "{result}");
    assert_eq!(result["termination_reason"], libero_episode::actor::FORFEIT_REASON, "{result}");
}

/// A model API on the host's loopback: reads each request whole (its head, then the body its Content-Length
/// declares) and answers it `status` with a JSON body; a request whose body breaks off is closed unanswered, as a
/// real server does. Counts the requests it answered and the ones cut short.
fn model_api(status: &'static str) -> (u16, Arc<AtomicUsize>, Arc<AtomicUsize>) {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = l.local_addr().unwrap().port();
    let (answered, cut) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicUsize::new(0)));
    let (a, c) = (answered.clone(), cut.clone());
    std::thread::spawn(move || {
        for mut conn in l.incoming().flatten() {
            let _ = conn.set_read_timeout(Some(Duration::from_secs(10)));
            let mut raw = Vec::new();
            let mut buf = [0u8; 65536];
            let whole = loop {
                let head_end = raw.windows(4).position(|w| w == b"\r\n\r\n");
                if let Some(end) = head_end {
                    let head = String::from_utf8_lossy(&raw[..end]).to_ascii_lowercase();
                    let length: usize = head.lines().find_map(|l| l.strip_prefix("content-length:").and_then(|v| v.trim().parse().ok())).unwrap_or(0);
                    if raw.len() >= end + 4 + length {
                        break true;
                    }
                }
                match conn.read(&mut buf) {
                    Ok(0) | Err(_) => break false,
                    Ok(n) => raw.extend_from_slice(&buf[..n]),
                }
            };
            if !whole {
                c.fetch_add(1, Ordering::SeqCst);
                continue;
            }
            a.fetch_add(1, Ordering::SeqCst);
            let body = if status.starts_with("200") {
                r#"{"object":"list","data":[{"id":"scripted-model"}]}"#
            } else {
                r#"{"error":{"message":"the provider is overloaded","type":"overloaded"}}"#
            };
            let _ = write!(conn, "HTTP/1.1 {status}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}", body.len());
        }
    });
    (port, answered, cut)
}

/// Without a credentials file the agent has no model API: the runner's gateway answers its request itself (no
/// model API is configured for the sandbox). An agent that then exits forfeits: the gateway's refusal is not a
/// provider failing it.
#[test]
fn an_agent_that_exits_after_the_gateway_refused_it_for_want_of_a_model_api_gets_its_own_fail() {
    let tmp = tempfile::tempdir().unwrap();
    // No LIBERO_MODEL_API_BASE without credentials: the gateway is where the proxy variables point.
    let agent = inline_python(
        r#"import os, sys, urllib.error, urllib.request
base = os.environ.get("LIBERO_MODEL_API_BASE") or os.environ["HTTPS_PROXY"].rstrip("/") + "/v1"
opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
try:
    opener.open(base + "/models", timeout=30).read()
    print("MODELS answered", flush=True)
except urllib.error.HTTPError as e:
    print("MODELS HTTP %d" % e.code, flush=True)
except OSError as e:
    print("MODELS failed: %r" % e, flush=True)
sys.exit(3)"#,
    );
    let (rec, ok, err) = rollout(tmp.path(), "no-model-api", &agent, None);
    let stdout = agent_stdout(tmp.path(), "no-model-api");
    assert!(stdout.contains("MODELS HTTP 5"), "the gateway answered the agent itself: {stdout}\n{err}");
    assert_own_fail(&rec, ok, &err);
    assert_eq!(rec["agent_exit_code"], 3, "{rec}");
    let records = gateway_records(tmp.path(), "no-model-api");
    let refused = records.iter().find(|r| r["path"].as_str().is_some_and(|p| p.ends_with("/models"))).unwrap_or_else(|| panic!("{records:#?}"));
    assert!(refused["status"].as_u64().is_some_and(|s| s >= 500), "{refused}");
    assert_eq!(refused["cause"], "gateway", "the gateway's own answer, not a provider's: {refused}");
}

/// An agent that declares a 100000-byte request body to its (working) model API, sends 9 bytes and hangs up, then
/// exits: the request broke off on the agent's side, so the exit is its forfeit.
#[test]
fn an_agent_that_cuts_its_own_model_request_short_then_exits_gets_its_own_fail() {
    let tmp = tempfile::tempdir().unwrap();
    let (port, answered, _cut) = model_api("200 OK");
    let creds = tmp.path().join("credentials");
    std::fs::write(&creds, format!("APIKEY=sk-quitter-0123456789abcdef\nAPIURL=http://127.0.0.1:{port}/v1\n")).unwrap();
    let agent = inline_python(
        r#"import os, socket, sys, time
base = os.environ["LIBERO_MODEL_API_BASE"]
hostport, _, prefix = base[len("http://"):].partition("/")
path = ("/" + prefix.strip("/") + "/chat/completions").replace("//", "/")
host, port = hostport.rsplit(":", 1)
s = socket.create_connection((host, int(port)), timeout=10)
head = ("POST %s HTTP/1.1\r\nHost: %s\r\nContent-Type: application/json\r\n"
        "Authorization: Bearer %s\r\nContent-Length: 100000\r\n\r\n") % (path, hostport, os.environ.get("LIBERO_MODEL_API_KEY", ""))
body = b'{"model":'
assert len(body) == 9
s.sendall(head.encode() + body)
time.sleep(0.5)
s.close()
print("CUT after %d of 100000 body bytes" % len(body), flush=True)
time.sleep(1)
sys.exit(3)"#,
    );
    let (rec, ok, err) = rollout(tmp.path(), "cut-short", &agent, Some(&creds));
    let stdout = agent_stdout(tmp.path(), "cut-short");
    assert!(stdout.contains("CUT after 9 of 100000"), "{stdout}\n{err}");
    assert_own_fail(&rec, ok, &err);
    assert_eq!(rec["agent_exit_code"], 3, "{rec}");
    assert_eq!(answered.load(Ordering::SeqCst), 0, "the model API never got the whole request");
    let records = gateway_records(tmp.path(), "cut-short");
    let cut = records
        .iter()
        .find(|r| r["path"].as_str().is_some_and(|p| p.ends_with("/chat/completions")))
        .unwrap_or_else(|| panic!("the gateway recorded the request: {records:#?}"));
    assert_eq!(cut["cause"], "client", "the request body broke off on the agent's side: {cut}");
}

/// An agent that never calls `start_episode` and never exits: the runner's watchdog ends it at the budget (5 s)
/// plus its grace (45 s), and the episode it never started is its forfeit, not a free rerun.
#[test]
fn an_agent_that_never_starts_its_episode_is_ended_by_the_watchdog_as_its_own_fail() {
    let tmp = tempfile::tempdir().unwrap();
    let t0 = Instant::now();
    let (rec, ok, err) = rollout_with(tmp.path(), "sleeps", "exec sleep infinity", None, "5");
    let took = t0.elapsed();
    assert!(took >= Duration::from_secs(50), "the watchdog waits for the budget and its grace: {took:?}\n{err}");
    assert_own_fail(&rec, ok, &err);
    assert_eq!(rec["accepted_agent_steps"], 0, "{rec}");
    let log = std::fs::read_to_string(PathBuf::from(rec["run_dir"].as_str().unwrap()).join("actions.jsonl")).unwrap();
    assert!(log.lines().last().is_some_and(|l| l.contains(libero_episode::actor::FORFEIT_REASON)), "the action log says why: {log}");
}

/// The control of the tests above: the provider itself answers 503 to the agent's request, then the agent exits
/// (as a CLI does when its provider fails). That is not the agent's doing: INVALID, with the gateway's cause.
#[test]
fn an_agent_whose_model_api_answers_503_before_it_exits_is_invalid() {
    let tmp = tempfile::tempdir().unwrap();
    let (port, answered, _cut) = model_api("503 Service Unavailable");
    let creds = tmp.path().join("credentials");
    std::fs::write(&creds, format!("APIKEY=sk-quitter-0123456789abcdef\nAPIURL=http://127.0.0.1:{port}/v1\n")).unwrap();
    let (rec, ok, err) = rollout(tmp.path(), "provider-503", &quitting_agent("model"), Some(&creds));
    assert!(answered.load(Ordering::SeqCst) >= 1, "the request reached the model API: {err}");
    assert!(!ok, "every rollout INVALID: run exits non-zero: {err}");
    assert_eq!(rec["outcome"], "INVALID", "{rec}\n{err}");
    let why = rec["infrastructure_error"].as_str().expect("the reason");
    assert!(why.contains("harness exited before finish_episode (exit code 1)") && why.contains("the model API answered 503"), "{why}");
    let records = gateway_records(tmp.path(), "provider-503");
    assert!(records.iter().any(|r| r["status"] == 503 && r["cause"] == "upstream"), "{records:#?}");
}

/// A 30 s flood of model-API requests the gateway refuses (the agent's own, from inside the sandbox) leaves the
/// gateway's records under 32 MiB (full records for the first 10,000, counters after) and the episode's transcript
/// still showing what the agent printed after the flood, beside a count of what was not shown; the episode is
/// then played to a valid outcome, and the flood made nothing INVALID.
#[test]
fn a_request_flood_leaves_bounded_records_and_a_transcript_that_still_shows_the_agent_s_later_lines() {
    let tmp = tempfile::tempdir().unwrap();
    let flood = r#"import os, socket, time
host, port = os.environ["HTTPS_PROXY"][len("http://"):].rsplit(":", 1)
end, n = time.time() + 30, 0
while time.time() < end:
    try:
        s = socket.create_connection((host, int(port)), timeout=5)
        s.sendall(b"GET /v1/files HTTP/1.1\r\nHost: api\r\n\r\n")
        s.recv(256)
        s.close()
        n += 1
    except OSError:
        pass
print("LIBERO-FLOOD %d" % n, flush=True)
print("agent line after the flood", flush=True)
"#;
    let agent = format!("python3 - <<'PY'\n{flood}PY\nexec {{libero_agent}} agent --workspace {{workspace}}");
    let (rec, ok, err) = rollout(tmp.path(), "flood", &agent, None);
    assert!(ok, "{err}");
    assert!(rec["outcome"] == "SUCCESS" || rec["outcome"] == "FAIL", "{rec}\n{err}");
    assert_eq!(rec["result_status"], "finished", "{rec}");
    let rollout_dir = tmp.path().join("flood/rollouts/w1_t14_level3");
    let stdout = std::fs::read_to_string(rollout_dir.join("command_stdout.log")).unwrap();
    let sent: u64 = stdout.lines().find_map(|l| l.strip_prefix("LIBERO-FLOOD ")).and_then(|n| n.trim().parse().ok()).expect("the flood's count");
    assert!(sent > 10_000, "the flood must pass the record cap to prove anything: {sent} requests");
    let records = rollout_dir.join("sandbox/model_api.jsonl");
    let size = std::fs::metadata(&records).unwrap().len();
    assert!(size < 32 << 20, "the gateway's records are {size} bytes after {sent} requests");
    let text = std::fs::read_to_string(&records).unwrap();
    let overflow: Value = text.lines().filter_map(|l| serde_json::from_str::<Value>(l).ok()).find(|v| v["kind"] == "overflow").expect("the counters line");
    let counted = text.lines().count() as u64 - 1 + overflow["overflowed"].as_u64().unwrap_or(0);
    assert!(counted >= sent, "every request counted: {counted} of {sent}; {overflow}");
    let manifest = HarnessManifest::read(&rollout_dir).unwrap().expect("the rollout's harness manifest");
    assert!(manifest.model_api().and_then(|m| m.requests).is_some_and(|r| r >= sent), "{manifest}");
    let transcript = PathBuf::from(rec["run_dir"].as_str().unwrap()).join("agent_events.jsonl");
    let events = std::fs::read_to_string(&transcript).unwrap();
    assert!(events.len() <= 16 << 20, "{} bytes", events.len());
    eprintln!("flood: {sent} requests in 30 s; records {size} bytes; transcript {} bytes", events.len());
    assert!(events.contains("agent line after the flood"), "the agent's later line is in the transcript");
    assert!(events.contains("not shown") || events.contains("overflow") || events.contains("quota"), "the hidden requests are counted");
}
