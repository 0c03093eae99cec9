//! Issue 17's proof with an adversary: a red-team agent (`tests/redteam/agent.py`) runs exactly where a real
//! agent runs — `libero-agent run --harness command`, inside the bubblewrap sandbox, against the runner's own
//! in-process server — and tries every operator route, page and WebSocket with no credential and with its own
//! episode token, foreign `Host` names, other episodes' endpoints, megabytes of rejected call arguments, and a
//! watcher that plants symlinks to a host secret and FIFOs into everything that appears under
//! `benchmark_inputs/` (inotify) while the reference agent plays the episode. Every attempt must be refused, no
//! byte of the secret may reach any record, nothing may hang, the private action log must stay small, and the
//! episode must end exactly as the same agent's episode without the attacks. The workspace goes with the rollout's
//! disk when it ends: the red team's and its watcher's reports are the lines they printed on stdout, which the
//! runner keeps (`command_stdout.log`).
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use libero_testkit::repo_root;
use serde_json::Value;

mod common;

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_libero-agent")
}

/// Runs a one-rollout T14 batch with `agent_cmd`; fails the test if it does not end within `limit`.
fn run_batch(batch: &Path, workspaces: &Path, agent_cmd: &str, limit: Duration) {
    let mut child = Command::new(bin())
        .args(["run", "--experiment", "main_table", "--harness", "command", "--model", "redteam", "--tasks", "T14", "--reps", "1"])
        .args(["--agent-cmd", agent_cmd, "--wall-time-s", "300", "--batch"])
        .arg(batch)
        .arg("--workspace-root")
        .arg(workspaces)
        .stdout(Stdio::null())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("run libero-agent run");
    common::wait_success(&mut child, limit, "the batch (a planted FIFO or link blocking the server?)");
}

fn records(batch: &Path) -> Vec<Value> {
    std::fs::read_to_string(batch.join("rollouts.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// The run directory of the batch's only episode (`<batch>/server/runs/<episode id>/`).
fn run_dir(batch: &Path) -> PathBuf {
    let runs: Vec<PathBuf> = std::fs::read_dir(batch.join("server/runs")).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(runs.len(), 1, "{runs:?}");
    runs[0].clone()
}

/// Every regular file under `dir`, never following a link.
fn regular_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let p = e.path();
        let Ok(meta) = std::fs::symlink_metadata(&p) else { continue };
        if meta.is_dir() {
            regular_files(&p, out);
        } else if meta.is_file() {
            out.push(p);
        }
    }
}

/// What the episode's end says about the robot and the task, without wall-clock fields.
fn verdict(batch: &Path) -> Value {
    let run = run_dir(batch);
    let result: Value = serde_json::from_slice(&std::fs::read(run.join("result.json")).unwrap()).unwrap();
    let telemetry = std::fs::read_to_string(run.join("telemetry.jsonl")).unwrap_or_default();
    let last_step: Value = telemetry.lines().last().map(|l| serde_json::from_str(l).unwrap()).unwrap_or(Value::Null);
    serde_json::json!({
        "success": result["success"],
        "accepted_agent_steps": result["accepted_agent_steps"],
        "status": result["status"],
        "stages": result["private_evaluation"]["completed_stage_count"],
        "last_step": strip_clock(&last_step),
    })
}

fn strip_clock(v: &Value) -> Value {
    match v {
        Value::Object(m) => Value::Object(
            m.iter().filter(|(k, _)| !k.contains("wall") && !k.ends_with("_at") && !k.contains("unix")).map(|(k, v)| (k.clone(), strip_clock(v))).collect(),
        ),
        other => other.clone(),
    }
}

#[test]
fn a_red_team_agent_in_the_sandbox_reaches_nothing_but_its_own_endpoint() {
    let dir = tempfile::tempdir().unwrap();
    let secret_dir = dir.path().join("host-secret");
    std::fs::create_dir(&secret_dir).unwrap();
    let marker = format!("HOST-SECRET-{}-{:?}", std::process::id(), Instant::now());
    let secret = secret_dir.join("secret.txt");
    std::fs::write(&secret, format!("{marker}\n").repeat(64)).unwrap();
    let script = std::fs::read_to_string(repo_root().join("tests/redteam/agent.py")).unwrap();
    let attack = format!(
        "python3 - {secret} 240 <<'PY'\n{script}\nPY\nexec {{libero_agent}} agent --workspace {{workspace}}",
        secret = secret.display()
    );
    let attacked = dir.path().join("attacked");
    run_batch(&attacked, &dir.path().join("ws-attacked"), &attack, Duration::from_secs(900));
    let clean = dir.path().join("clean");
    run_batch(&clean, &dir.path().join("ws-clean"), "exec {libero_agent} agent --workspace {workspace}", Duration::from_secs(900));

    let rec = &records(&attacked)[0];
    // What the red team printed, for any failure's message.
    let agent_log = std::fs::read(attacked.join("rollouts/w1_t14_level3/command_stderr.log")).unwrap_or_default();
    let agent_log = String::from_utf8_lossy(&agent_log[agent_log.len().saturating_sub(4000)..]).into_owned();
    assert_eq!(rec["agent_exit_code"], 0, "{rec}\n{agent_log}");
    let ws = PathBuf::from(rec["workspace"].as_str().unwrap());
    let stdout = attacked.join("rollouts/w1_t14_level3/command_stdout.log");
    let report = common::marked_line(&stdout, "LIBERO-REDTEAM-REPORT ")
        .unwrap_or_else(|| panic!("no report of the red team on its stdout; its stderr:\n{agent_log}"));
    let attempts = report["attempts"].as_array().unwrap();
    assert!(attempts.len() >= 100, "{} attempts", attempts.len());
    let let_through: Vec<&Value> = attempts.iter().filter(|a| a["refused"] != true).collect();
    assert!(let_through.is_empty(), "the boundary let these through: {let_through:#?}");
    let watcher = common::marked_line(&stdout, "LIBERO-WATCHER-REPORT ")
        .unwrap_or_else(|| panic!("the watcher ran and said so on stdout; the red team's stderr:\n{agent_log}"));
    assert!(watcher["inotify_events"].as_u64().unwrap() > 0, "the watcher saw publications: {watcher}");

    // Nothing of the secret in any record, observation archive, video or log; the secret is untouched.
    let mut files = Vec::new();
    regular_files(&attacked, &mut files);
    // Where the runner caps the rollout (root), the workspace went with its disk: nothing of it is left to leak.
    // SAFETY: geteuid(2) has no preconditions.
    if unsafe { libc::geteuid() } == 0 {
        assert!(!ws.exists(), "the workspace outlived its rollout: {}", ws.display());
    }
    regular_files(&ws, &mut files);
    assert!(files.len() > 20, "{files:?}");
    for f in &files {
        let bytes = std::fs::read(f).unwrap();
        assert!(!bytes.windows(marker.len()).any(|w| w == marker.as_bytes()), "the secret reached {}", f.display());
    }
    let secret_listing: Vec<_> = std::fs::read_dir(&secret_dir).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(secret_listing, vec![std::ffi::OsString::from("secret.txt")], "the server wrote into the secret's directory");

    // Megabytes of rejected arguments, a small private action log.
    let actions = std::fs::metadata(run_dir(&attacked).join("actions.jsonl")).unwrap().len();
    assert!(report["oversized_bytes_sent"].as_u64().unwrap() > 3_000_000);
    assert!(actions < 64 * 1024, "actions.jsonl is {actions} bytes");

    // A batch that ends normally waits for its episodes' private videos.
    for batch in [&attacked, &clean] {
        assert!(run_dir(batch).join("continuous_video.mp4").is_file(), "the video of {} is finalised", batch.display());
    }

    // The same verdict as the same agent without the attacks.
    assert_eq!(rec["outcome"], records(&clean)[0]["outcome"]);
    assert_eq!(verdict(&attacked), verdict(&clean));
}
