//! Issue 49, item 5: a batch's rollouts link to their review and their logs. A real reference-agent T28 batch (the
//! agent's command also writes a marker to stderr) is served; Chromium (`tests/dashboard/batch_logs_check.cjs`)
//! follows Results → the rollout's logs (stdout, stderr, manifest, transcript checked by content) → plain text →
//! review → batch; the log routes refuse a file the test replaced with a symlink to the operator token (never
//! reading it), serve a 9 MiB log from its end with a note, and answer 404 for names outside the runner's files.
//! Needs `python3 scripts/setup.py --test` (chromium, node, playwright-core); fails saying so otherwise.
use std::path::PathBuf;
use std::process::Command;

mod common;
use common::{Server, http_get_json, http_get_text};

const MARKER: &str = "stderr-marker-4f9c";

#[test]
fn a_batch_links_each_rollout_to_its_review_and_logs_and_the_log_routes_open_only_the_runners_files() {
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
    // What an agent without the cage could do in its rollout directory: a link where the runner keeps a file.
    std::fs::remove_file(rollout_dir.join("harness_usage.json")).unwrap();
    std::os::unix::fs::symlink(data.join("operator_token"), rollout_dir.join("harness_usage.json")).unwrap();

    let server = Server::start(&data);
    let base = format!("{}/results/logs/logs-b/{rollout}", server.url);
    let (_, api) = http_get_json(&format!("{}/api/results?batch=logs-b", server.url));
    assert_eq!(api["batches"][0]["episodes"][0]["logs"], format!("/results/logs/logs-b/{rollout}"), "{api}");

    let artifacts = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/batch_logs");
    std::fs::create_dir_all(&artifacts).unwrap();
    let last = common::browser_script(
        "batch_logs_check.cjs",
        &[&server.url, "logs-b", &rollout, &episode, MARKER, "harness_usage", &artifacts.to_string_lossy()],
        &server.token,
    );
    assert_eq!(last["ok"], true, "{last}");

    // The symlink is refused, its target never read.
    let (status, body) = http_get_text(&format!("{base}/harness_usage"));
    assert_eq!(status, 403, "{body}");
    assert!(!body.contains(&server.token), "the operator token leaked through a symlink");
    let (status, page) = http_get_text(&base);
    assert_eq!(status, 200);
    assert!(page.contains("refused") && !page.contains(&server.token), "the page refuses the link");

    // A long log: the last 8 MiB, from a line, with a note; the page shows its last 256 KiB.
    let stdout_path = rollout_dir.join("command_stdout.log");
    let mut long = std::fs::read_to_string(&stdout_path).unwrap();
    long.extend((0..150_000).map(|i| format!("filler line {i:06} {}\n", "x".repeat(50))));
    long.push_str("the last line\n");
    std::fs::write(&stdout_path, &long).unwrap();
    let (status, raw) = http_get_text(&format!("{base}/stdout"));
    assert_eq!(status, 200);
    let (note, rest) = raw.split_once('\n').unwrap();
    assert!(note.starts_with("[libero-agent: the first ") && note.contains("bytes are left out"), "{note}");
    assert!(rest.len() <= 8 << 20 && rest.len() > (8 << 20) - 200, "{} bytes served", rest.len());
    assert!(rest.starts_with("filler line ") && rest.ends_with("the last line\n"), "{}", &rest[..40]);
    let (_, page) = http_get_text(&base);
    assert!(page.len() < 600 << 10 && page.contains("are left out") && page.contains("the last line"), "{} bytes of page", page.len());

    // Only the runner's files of finished rollouts of known batches.
    for path in [
        format!("{base}/home"),
        format!("{base}/..%2F..%2Foperator_token"),
        format!("{}/results/logs/logs-b/w9_t28_level3", server.url),
        format!("{}/results/logs/logs-b/..", server.url),
        format!("{}/results/logs/nope/{rollout}/stdout", server.url),
    ] {
        let (status, body) = http_get_text(&path);
        assert_eq!(status, 404, "{path}: {body}");
    }
}
