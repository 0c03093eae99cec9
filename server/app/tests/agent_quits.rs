//! Nothing an agent does can make its outcome INVALID (a free rerun): an agent that ends without
//! `finish_episode` — it exits, or kills its own CLI mid-episode — gets its own FAIL, on the record and on the
//! server, through the real sandbox (as `nobody` when the runner is root). INVALID stays for what the agent did
//! not cause: here, a model API that fails it (the runner's gateway records the 502 of an unreachable provider,
//! which the agent cannot write). The agents are `tests/clis/quitting_agent.py` and a plain `exit 3`.
use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

mod common;
use common::bin;

/// One sandboxed T14 rollout of `agent_cmd`; its record, the run's exit status and stderr.
fn rollout(dir: &Path, name: &str, agent_cmd: &str, credentials: Option<&Path>) -> (Value, bool, String) {
    let batch = dir.join(name);
    let mut cmd = Command::new(bin());
    cmd.args(["run", "--experiment", "main_table", "--harness", "command", "--model", "quitter", "--tasks", "T14", "--reps", "1"])
        .args(["--agent-cmd", agent_cmd, "--wall-time-s", "300", "--batch"])
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
