//! Issue 49, item 5: a batch's rollouts link to their review and their logs. A real reference-agent T28 batch (the
//! agent's command also writes a marker to stderr) is served; Chromium (`tests/dashboard/batch_logs_check.cjs`)
//! follows Results → the rollout's logs (stdout, stderr, manifest, transcript checked by content) → plain text →
//! review → batch, and sees the usage record the test replaced with a symlink refused. Asked of the full router in process over a finished fixture batch: the log routes refuse a file
//! replaced with a symlink to the operator token (never reading it), serve a 9 MiB log from its end with a note, and
//! answer 404 for names outside the runner's files. Needs `python3 scripts/setup.py --test` (chromium, node,
//! playwright-core); fails saying so otherwise.
use std::path::{Path, PathBuf};
use std::process::Command;

mod common;
use common::Server;
use libero_testkit::server::TestServer;
use serde_json::json;

const MARKER: &str = "stderr-marker-4f9c";

#[test]
fn chromium_follows_a_batchs_rollout_to_its_logs_review_and_back_to_the_batch() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let batch = data.join("batches/logs-b");
    let agent = format!("echo {MARKER} >&2; exec {{libero_agent}} agent --workspace {{workspace}}");
    let out = Command::new(common::bin())
        .args(["run", "--experiment", "main_table", "--harness", "command", "--model", "reference", "--tasks", "T28", "--reps", "1"])
        .args(["--concurrency", "1", "--agent-cmd", &agent, "--wall-time-s", "300", "--no-sandbox", "--batch"])
        .arg(&batch)
        .arg("--workspace-root")
        .arg(dir.path().join("ws"))
        .output()
        .unwrap();
    assert!(out.status.success(), "run: {}", String::from_utf8_lossy(&out.stderr));
    let record: serde_json::Value =
        serde_json::from_str(std::fs::read_to_string(batch.join("rollouts.jsonl")).unwrap().lines().next().unwrap()).unwrap();
    let (rollout, episode) = (record["rollout_id"].as_str().unwrap().to_owned(), record["episode_id"].as_str().unwrap().to_owned());
    let rollout_dir = batch.join("rollouts").join(&rollout);
    // What an agent without the cage could do in its rollout directory: a link where the runner keeps a file (the
    // browser sees it refused).
    std::fs::remove_file(rollout_dir.join("harness_usage.json")).unwrap();
    std::os::unix::fs::symlink(data.join("operator_token"), rollout_dir.join("harness_usage.json")).unwrap();

    let server = Server::start(&data);

    let artifacts = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/batch_logs");
    std::fs::create_dir_all(&artifacts).unwrap();
    let last = common::browser_script(
        "batch_logs_check.cjs",
        &[&server.url, "logs-b", &rollout, &episode, MARKER, "harness_usage", &artifacts.to_string_lossy()],
        &server.token,
    );
    assert_eq!(last["ok"], true, "{last}");
}

/// A finished one-rollout T28 batch of the `command` harness named `logs-b` under `root`, whose stdout log is
/// `stdout`; the rollout's directory.
fn write_batch(root: &Path, stdout: &str) -> PathBuf {
    let dir = root.join("logs-b");
    let rollout = dir.join("rollouts/w1_t28_level3");
    std::fs::create_dir_all(&rollout).unwrap();
    let batch = json!({
        "schema_version": "libero_agent.batch.v1", "status": "finished", "created_at": "2025-01-01T00:00:00Z",
        "settings": {"experiment": "main_table", "harness": "command", "model": "reference", "reps": 1, "tasks": [28], "seed": 100,
            "wall_time_s": 300.0, "max_agent_steps": 100, "agent_cmd": "true", "sandbox": false},
        "rollout_count": 1, "counts": {"done": 1, "running": 0, "left": 0}, "outcomes": {"SUCCESS": 1},
    });
    std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
    let record = json!({
        "schema_version": "libero_agent.rollout.v1", "rollout_id": "w1_t28_level3", "task": "T28", "task_number": 28,
        "split": "long_horizon_hard", "stage_count": 2, "repetition": 1, "level": 3, "demo": "none", "outcome": "SUCCESS",
        "episode_id": "ep-20250101T000000Z-logs", "completed_stages": 2, "wall_time_s": 60.0,
        "started_at": "2025-01-01T00:00:00Z", "finished_at": "2025-01-01T00:01:00Z",
    });
    std::fs::write(dir.join("rollouts.jsonl"), format!("{record}\n")).unwrap();
    std::fs::write(rollout.join("command_stdout.log"), stdout).unwrap();
    std::fs::write(rollout.join("command_stderr.log"), format!("{MARKER}\n")).unwrap();
    rollout
}

/// The log routes, asked of the full router in process: the rollout's logs are linked from `/api/results`; a file
/// replaced with a symlink to the operator token is refused on the page and the raw route, its target never read; a
/// 9 MiB log is served from its last 8 MiB (from a line, with a note) and shown from its last 256 KiB; only the
/// runner's files of finished rollouts of known batches are served.
#[tokio::test(flavor = "multi_thread")]
async fn the_log_routes_open_only_the_runners_regular_files_and_serve_long_logs_from_their_end() {
    let extra = tempfile::tempdir().unwrap();
    let mut long = String::from("the agent's first line\n");
    long.extend((0..150_000).map(|i| format!("filler line {i:06} {}\n", "x".repeat(50))));
    long.push_str("the last line\n");
    let rollout = write_batch(extra.path(), &long);
    let server = TestServer::start_with(&["--batches", extra.path().to_str().unwrap()]).await;
    // What an agent without the cage could do in its rollout directory: a link where the runner keeps a file, here to
    // the operator token.
    std::os::unix::fs::symlink(server.data().join("operator_token"), rollout.join("harness_usage.json")).unwrap();
    assert!(server.data().join("operator_token").is_file(), "the link's target exists");
    let token = server.token().to_owned();
    let base = "/results/logs/logs-b/w1_t28_level3";
    let api = server.get_as_operator("/api/results?batch=logs-b").await.json();
    assert_eq!(api["batches"][0]["episodes"][0]["logs"], base, "{api}");

    // The symlink is refused, its target never read.
    let usage = server.get_as_operator(&format!("{base}/harness_usage")).await;
    assert_eq!(usage.status, 403, "{}", usage.text());
    assert!(!usage.text().contains(&token), "the operator token leaked through a symlink");
    let page = server.get_as_operator(base).await;
    assert_eq!(page.status, 200, "{}", page.text());
    assert!(page.text().contains("refused") && !page.text().contains(&token), "the page refuses the link");
    let stderr = server.get_as_operator(&format!("{base}/stderr")).await;
    assert_eq!((stderr.status, stderr.text()), (200, format!("{MARKER}\n")), "a regular file is served");

    // A long log: the last 8 MiB, from a line, with a note; the page shows its last 256 KiB.
    let raw = server.get_as_operator(&format!("{base}/stdout")).await;
    assert_eq!(raw.status, 200);
    let raw = raw.text();
    let (note, rest) = raw.split_once('\n').unwrap();
    assert!(note.starts_with("[libero-agent: the first ") && note.contains("bytes are left out"), "{note}");
    assert!(rest.len() <= 8 << 20 && rest.len() > (8 << 20) - 200, "{} bytes served", rest.len());
    assert!(rest.starts_with("filler line ") && rest.ends_with("the last line\n"), "{}", &rest[..40]);
    let page = server.get_as_operator(base).await.text();
    assert!(page.len() < 600 << 10 && page.contains("are left out") && page.contains("the last line"), "{} bytes of page", page.len());

    // Only the runner's files of finished rollouts of known batches.
    for path in [
        format!("{base}/home"),
        format!("{base}/..%2F..%2Foperator_token"),
        "/results/logs/logs-b/w9_t28_level3".to_owned(),
        "/results/logs/logs-b/..".to_owned(),
        "/results/logs/nope/w1_t28_level3/stdout".to_owned(),
    ] {
        let a = server.get_as_operator(&path).await;
        assert_eq!(a.status, 404, "{path}: {}", a.text());
        assert!(!a.text().contains(&token), "{path}");
    }
}
