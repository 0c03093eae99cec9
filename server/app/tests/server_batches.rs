//! Batches belong to the server they ran on: `libero-agent run --server URL` with its batch directory outside the
//! server's data directory registers the batch there as it runs, so `GET /api/results` and the Results page list it
//! without `--batches` right after `run` ends; `run` names that Results URL and the `report` command; its episode
//! carries harness, model and batch (and the home page's harness/batch filters find it), an expert's episode carries
//! harness `expert`; `report` and the Results page use the batch's own repetitions (1) by default and agree; every
//! row shows tokens with their source, and the Results page shows the agent toolbox each batch ran with (asked in
//! process over a fixture batch). (That the registration route is operator-only, refusing no token and an episode
//! token, is `routes_in_process`'s.)
mod common;

use std::path::Path;
use std::process::Command;

use common::{Server, bin, http_get_json, http_get_text};
use libero_testkit::server::TestServer;
use serde_json::{Value, json};

fn libero(args: &[&str]) -> std::process::Output {
    let out = Command::new(bin()).args(args).output().expect("run libero-agent");
    eprintln!("$ libero-agent {}\n{}", args.join(" "), String::from_utf8_lossy(&out.stderr));
    out
}

const REFERENCE: &str = "exec {libero_agent} agent --workspace {workspace}";

fn run_t14(server: &str, batch: &Path, workspaces: &Path) -> std::process::Output {
    libero(&[
        "run", "--experiment", "main_table", "--harness", "command", "--model", "reference", "--tasks", "T14", "--reps", "1",
        "--agent-cmd", REFERENCE, "--wall-time-s", "300", "--no-sandbox", "--server", server, "--batch",
        batch.to_str().unwrap(), "--workspace-root", workspaces.to_str().unwrap(),
    ])
}

/// A finished fixture batch that ran with the project's toolbox, whose two T14 rollouts took their tokens from the
/// gateway (where the harness printed other figures on stdout) and from the harness's stdout.
fn write_toolbox_batch(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    let batch = json!({
        "schema_version": "libero_agent.batch.v1", "status": "finished", "created_at": "2025-01-01T00:00:00Z",
        "settings": {"experiment": "main_table", "harness": "codex", "model": "fixture-model", "effort": "high", "reps": 2,
            "tasks": [14], "seed": 100, "wall_time_s": 300.0, "max_agent_steps": 100, "agent_cmd": null, "sandbox": true},
        "toolbox": {"name": "libero-toolbox", "source": "the project's lock (assets/third_party.lock.json)", "python": "3.11",
            "packages": [{"name": "numpy", "version": "1.26.4"}, {"name": "scipy", "version": "1.14.1"}]},
        "rollout_count": 2, "counts": {"done": 2, "running": 0, "left": 0}, "outcomes": {"SUCCESS": 1, "FAIL": 1},
    });
    std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
    let usage = [
        json!({"available": true, "requests_with_usage": 3, "lines_scanned": 3, "input_tokens": 8000, "output_tokens": 610,
            "total_tokens": 8610, "source": "model_api_gateway",
            "harness_stdout": {"input_tokens": 9000, "output_tokens": 610, "total_tokens": 9610, "agrees": false}}),
        json!({"available": true, "requests_with_usage": 1, "lines_scanned": 4, "input_tokens": 900, "output_tokens": 100,
            "total_tokens": 1000, "source": "harness_stdout"}),
    ];
    let mut lines = String::new();
    for (rep, (outcome, u)) in [("SUCCESS", &usage[0]), ("FAIL", &usage[1])].into_iter().enumerate() {
        let r = json!({
            "schema_version": "libero_agent.rollout.v1", "rollout_id": format!("w{}_t14_level3", rep + 1), "task": "T14",
            "task_number": 14, "split": "short_horizon_easy", "stage_count": 1, "repetition": rep + 1, "level": 3,
            "demo": "none", "outcome": outcome, "episode_id": format!("ep-toolbox-{rep}"), "completed_stages": u32::from(outcome == "SUCCESS"),
            "wall_time_s": 60.0, "usage": u, "started_at": "2025-01-01T00:00:00Z", "finished_at": "2025-01-01T00:01:00Z",
        });
        lines.push_str(&format!("{r}\n"));
    }
    std::fs::write(dir.join("rollouts.jsonl"), lines).unwrap();
}

#[test]
fn a_batch_run_against_a_server_is_on_its_results_page_without_flags_and_its_episodes_carry_their_agent() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let server = Server::start(&data);

    // The batch directory is nowhere the server looks: not under <data>/batches, not under --batches.
    let batch = dir.path().join("elsewhere/srv_batch");
    let out = run_t14(&server.url, &batch, &dir.path().join("ws"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains(&format!("results: {}/results?batch=srv_batch", server.url)), "run names the Results URL: {err}");
    assert!(err.contains(&format!("report: libero-agent report '{}'", batch.display())), "run names the report command: {err}");

    // At once on /api/results and the page, with the same numbers `report` prints by default (the batch's 1 rep).
    let (status, all) = http_get_json(&format!("{}/api/results", server.url));
    assert_eq!(status, 200, "{all}");
    assert!(all["available"].as_array().unwrap().contains(&json!("srv_batch")), "{}", all["available"]);
    let (_, one) = http_get_json(&format!("{}/api/results?batch=srv_batch", server.url));
    let b = &one["batches"][0];
    assert_eq!((b["name"].as_str(), b["status"].as_str(), b["reps"].as_u64()), (Some("srv_batch"), Some("finished"), Some(1)));
    let episodes = b["episodes"].as_array().unwrap();
    assert_eq!(episodes.len(), 1, "{b}");
    let episode_id = episodes[0]["episode_id"].as_str().expect("the rollout's episode").to_owned();
    assert_eq!(episodes[0]["tokens"]["source"], "unavailable", "the reference agent uses no model: {}", episodes[0]);
    let report = libero(&["report", batch.to_str().unwrap(), "--format", "json"]);
    assert!(report.status.success());
    let report: Value = serde_json::from_slice(&report.stdout).unwrap();
    assert_eq!(report["reps"], 1, "report defaults to the batch's own repetitions");
    assert_eq!(b["report"]["rows"], report["rows"], "the Results page and `report` disagree on a 1-rep batch");
    let summary = &report["rows"][0]["summary"];
    assert!(summary["tasks"][0]["stable_success"].is_boolean(), "one rollout settles T14 under a 1-rep rule: {summary}");
    assert_eq!(report["rows"][0]["tokens"]["sources"]["unavailable"], 1);
    let (_, html) = http_get_text(&format!("{}/results?batch=srv_batch", server.url));
    assert!(html.contains("command + reference") && html.contains(&format!("/episodes/{episode_id}/review")), "{html}");
    assert!(html.contains("– (no usage: 1 rollout)"), "no usage is said, never 0: {html}");
    assert!(html.contains("none (run without the sandbox: the host&#x27;s python3)") || html.contains("none (run without the sandbox"), "{html}");

    // The episode carries harness, model and batch; the home page's filters find it.
    let (_, list) = http_get_json(&format!("{}/api/episodes", server.url));
    let ep = list["episodes"].as_array().unwrap().iter().find(|e| e["id"] == episode_id.as_str()).expect("the episode").clone();
    assert_eq!((ep["harness"].as_str(), ep["model"].as_str(), ep["batch"].as_str()), (Some("command"), Some("reference"), Some("srv_batch")), "{ep}");
    let (_, home) = http_get_text(&format!("{}/?harness=command&batch=srv_batch", server.url));
    assert!(home.contains(&episode_id), "the harness + batch filter finds it");
    let (_, home) = http_get_text(&format!("{}/?harness=expert", server.url));
    assert!(!home.contains(&episode_id), "another harness does not");

    // Another batch of the same name elsewhere is refused before anything runs, saying why.
    let other = dir.path().join("other/srv_batch");
    let out = run_t14(&server.url, &other, &dir.path().join("ws2"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("already has a batch named \"srv_batch\""), "{err}");
}

#[test]
fn an_expert_episode_carries_harness_expert() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(&dir.path().join("data"));
    let out = libero(&["expert", "--task", "T14", "--runs", "1", "--no-video", "--server", &server.url]);
    assert!(out.status.success());
    let (_, list) = http_get_json(&format!("{}/api/episodes", server.url));
    let ep = &list["episodes"][0];
    assert_eq!((ep["harness"].as_str(), ep["model"].as_str()), (Some("expert"), Some("solve")), "{ep}");
    let batch = ep["batch"].as_str().expect("an expert run's batch");
    assert!(batch.starts_with("expert_"), "{batch}");
    let id = ep["id"].as_str().unwrap();
    let (_, home) = http_get_text(&format!("{}/?harness=expert&batch={batch}", server.url));
    assert!(home.contains(id), "the home page's harness + batch filter finds the expert's episode");
}

/// The Results page shows the agent toolbox each batch ran with, and tokens with their source on every row (gateway,
/// stdout, and where the harness's stdout disagrees with the gateway): a fixture batch, asked of the full router in
/// process.
#[tokio::test(flavor = "multi_thread")]
async fn the_results_show_each_batchs_toolbox_and_every_rows_tokens_with_their_source() {
    let extra = tempfile::tempdir().unwrap();
    write_toolbox_batch(&extra.path().join("toolboxed"));
    let server = TestServer::start_with(&["--batches", extra.path().to_str().unwrap()]).await;
    let page = server.get_as_operator("/results").await;
    let html = page.text();
    assert_eq!(page.status, 200, "{html}");
    assert!(html.contains("id=\"toolboxes\"") && html.contains("libero-toolbox") && html.contains("numpy 1.26.4, scipy 1.14.1"), "{html}");
    assert!(html.contains("4,805 (gateway 1, stdout 1; stdout disagrees: 1)"), "main row tokens with sources: {html}");
    assert!(html.contains("8,610 G · 1,000 S"), "per-task tokens with source marks: {html}");
    let tb = server.get_as_operator("/api/results?batch=toolboxed").await.json();
    assert_eq!(tb["batches"][0]["toolbox"]["packages"][0]["name"], "numpy");
    let tokens = &tb["batches"][0]["report"]["rows"][0]["tokens"];
    assert_eq!(tokens["sources"], json!({"model_api_gateway": 1, "harness_stdout": 1, "unavailable": 0, "not_recorded": 0}));
    assert_eq!(tokens["stdout_disagrees"][0]["rollout_id"], "w1_t14_level3");
    assert_eq!(tokens["stdout_disagrees"][0]["harness_stdout"]["total"], 9610);
}
