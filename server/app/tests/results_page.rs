//! The dashboard's Results page over real batches: `libero-agent run` plays two T14 rollouts with the built-in
//! reference agent into `<data>/batches/main`, a hand-written observation-ablation batch is registered with
//! `serve --batches`, and `libero-agent serve` must show the same numbers as `libero-agent report --format
//! json`, per-task cells that link every rollout to its episode's review page (which opens, although the
//! episodes ran on the batch's own in-process server), the ablation table, progress, and batch selection.
mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::{Server, bin, http_get_json, http_get_text};
use serde_json::Value;

fn libero(args: &[&str]) -> std::process::Output {
    let out = Command::new(bin()).args(args).output().expect("run libero-agent");
    eprintln!("$ libero-agent {}\n{}", args.join(" "), String::from_utf8_lossy(&out.stderr));
    out
}

/// A manip_observation batch still running: T11 at level 1 (two successes) and level 2 (one failure so far).
fn write_ablation_batch(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    let batch = serde_json::json!({
        "schema_version": "libero_agent.batch.v1", "status": "running",
        "settings": {"experiment": "manip_observation", "harness": "command", "model": "fixture", "effort": "high",
            "reps": 2, "tasks": [11], "seed": 100, "wall_time_s": 300.0, "max_agent_steps": 100, "agent_cmd": "true",
            "sandbox": false},
        "rollout_count": 4, "counts": {"done": 3, "running": 1, "left": 0}, "running": ["w2_t11_level2"],
        "outcomes": {"SUCCESS": 2, "FAIL": 1},
    });
    std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
    let mut lines = String::new();
    for (level, rep, outcome, c) in [(1, 1, "SUCCESS", 1), (1, 2, "SUCCESS", 1), (2, 1, "FAIL", 0)] {
        let r = serde_json::json!({
            "schema_version": "libero_agent.rollout.v1", "rollout_id": format!("w{rep}_t11_level{level}"), "task": "T11",
            "task_number": 11, "split": "short_horizon_easy", "stage_count": 1, "repetition": rep, "level": level,
            "demo": "none", "outcome": outcome, "episode_id": format!("ep-fixture-{level}{rep}"), "completed_stages": c,
            "wall_time_s": 60.0, "started_at": "2025-01-01T00:00:00Z", "finished_at": "2025-01-01T00:01:00Z",
        });
        lines.push_str(&format!("{r}\n"));
    }
    std::fs::write(dir.join("rollouts.jsonl"), lines).unwrap();
}

/// A finished pool batch: libero_90/35 twice (one success), robomemarena/18 twice (1 and 2 of 2 stages).
fn write_pool_batch(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    let batch = serde_json::json!({
        "schema_version": "libero_agent.batch.v1", "status": "finished",
        "settings": {"experiment": "pool", "harness": "command", "model": "pool-fixture", "effort": "high",
            "reps": 2, "tasks": [], "pool_tasks": ["libero_90/35", "robomemarena/18"], "seed": 100, "wall_time_s": 300.0,
            "max_agent_steps": 100, "agent_cmd": "true", "sandbox": false},
        "rollout_count": 4, "counts": {"done": 4, "running": 0, "left": 0}, "running": [],
        "outcomes": {"SUCCESS": 2, "FAIL": 2},
    });
    std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
    let mut lines = String::new();
    for (suite, task, key, k, rep, outcome, c) in [
        ("libero_90", "libero_90/35", "libero_90_035", 1, 1, "SUCCESS", 1),
        ("libero_90", "libero_90/35", "libero_90_035", 1, 2, "FAIL", 0),
        ("robomemarena", "robomemarena/18", "robomemarena_018", 2, 1, "FAIL", 1),
        ("robomemarena", "robomemarena/18", "robomemarena_018", 2, 2, "SUCCESS", 2),
    ] {
        let r = serde_json::json!({
            "schema_version": "libero_agent.rollout.v1", "rollout_id": format!("w{rep}_{key}_level3"), "task": task,
            "task_number": if task == "libero_90/35" { 16 } else { 0 }, "split": null, "suite": suite, "stage_count": k,
            "repetition": rep, "level": 3, "demo": "none", "outcome": outcome, "episode_id": format!("ep-pool-{key}-{rep}"),
            "completed_stages": c, "wall_time_s": 90.0, "started_at": "2025-01-01T00:00:00Z", "finished_at": "2025-01-01T00:01:30Z",
        });
        lines.push_str(&format!("{r}\n"));
    }
    std::fs::write(dir.join("rollouts.jsonl"), lines).unwrap();
}

/// A reference-agent T14 batch (2 rollouts) in `<data>/batches/main`, the ablation fixture under `extra/`, and a
/// server that sees both.
fn setup() -> (tempfile::TempDir, Server, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let batch = data.join("batches/main");
    let workspaces = dir.path().join("workspaces");
    let out = libero(&[
        "run", "--experiment", "main_table", "--harness", "command", "--model", "reference", "--tasks", "T14", "--reps",
        "2", "--concurrency", "2", "--agent-cmd", "exec {libero_agent} agent --workspace {workspace}", "--wall-time-s",
        "300", "--no-sandbox", "--batch", batch.to_str().unwrap(), "--workspace-root", workspaces.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "run failed");
    let extra = dir.path().join("extra");
    write_ablation_batch(&extra.join("abl"));
    write_pool_batch(&extra.join("pool"));

    let server = Server::start_with(&data, &["--batches", extra.to_str().unwrap()]);
    (dir, server, batch)
}

#[test]
fn results_show_the_report_numbers_and_link_every_rollout_to_its_review() {
    let (_dir, server, batch) = setup();

    // The JSON: both batches, the main one with exactly the report's rows.
    let (status, all) = http_get_json(&format!("{}/api/results", server.url));
    assert_eq!(status, 200, "{all}");
    assert_eq!(all["available"], serde_json::json!(["abl", "main", "pool"]));
    let main = all["batches"].as_array().unwrap().iter().find(|b| b["name"] == "main").expect("main batch").clone();
    assert_eq!((main["reps"].as_u64(), main["status"].as_str()), (Some(2), Some("finished")));
    let out = libero(&["report", batch.to_str().unwrap(), "--format", "json", "--reps", "2"]);
    assert!(out.status.success());
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(main["report"]["rows"], report["rows"], "the dashboard and `report` disagree");
    assert_eq!(main["report"]["batches"][0]["outcomes"], report["batches"][0]["outcomes"]);
    let row = &main["report"]["rows"][0];
    assert!(row["summary"]["score"].is_null() && row["summary"]["score_lower_bound"].is_number(), "one task: a lower bound");
    let episodes = main["episodes"].as_array().unwrap();
    assert_eq!(episodes.len(), 2);
    assert_eq!(main["progress"]["counts"]["done"], 2);

    // The page: main table (Score marked as a lower bound), Wilson intervals, per-task cells with review links.
    let (status, html) = http_get_text(&format!("{}/results", server.url));
    assert_eq!(status, 200, "{html}");
    assert!(html.contains("id=\"main-table\"") && html.contains("command + reference") && html.contains("≥ "), "{html}");
    assert!(html.contains("id=\"ordinary\"") && html.contains(" = ") && html.contains("["), "Wilson intervals");
    assert!(html.contains("<td>T14</td>") && html.contains("<td>T11</td>"), "per-task rows");
    for e in episodes {
        let id = e["episode_id"].as_str().expect("episode id");
        let href = format!("href=\"/episodes/{id}/review\"");
        assert!(html.contains(&href), "no review link {href}");
        // The episode ran on the batch's in-process server; this server finds it through the batch.
        let (status, page) = http_get_text(&format!("{}/episodes/{id}/review", server.url));
        assert!(status == 200 && page.contains(id), "{page}");
        let (status, review) = http_get_json(&format!("{}/api/episodes/{id}/review", server.url));
        assert_eq!(status, 200);
        assert!(review["result"].is_object() && review["calls"].as_array().is_some_and(|c| !c.is_empty()), "{review}");
    }
    let successes = episodes.iter().filter(|e| e["outcome"] == "SUCCESS").count();
    assert!(html.contains(&format!("<b>{successes}/2</b>")), "T14 cell: successes out of the repetitions");
    assert!(html.contains("Observation ablation") && html.contains("<td>L1</td>") && html.contains("<td>L2</td>"), "ablation");
    assert!(html.contains("id=\"progress\"") && html.contains("http-equiv=\"refresh\""), "a running batch refreshes");

    // Selection: one batch, two side by side, an unknown one.
    let (_, one) = http_get_json(&format!("{}/api/results?batch=abl", server.url));
    assert_eq!(one["batches"].as_array().map(Vec::len), Some(1));
    assert_eq!(one["batches"][0]["progress"]["counts"]["running"], 1);
    let (_, two) = http_get_json(&format!("{}/api/results?batch=main&batch=abl&reps=3", server.url));
    let names: Vec<&str> = two["batches"].as_array().unwrap().iter().filter_map(|b| b["name"].as_str()).collect();
    assert_eq!(names, ["main", "abl"]);
    assert_eq!(two["batches"][0]["reps"], 3);
    let (_, html) = http_get_text(&format!("{}/results?batch=main", server.url));
    assert!(html.contains("<td>T14</td>") && !html.contains("<td>T11</td>") && !html.contains("http-equiv=\"refresh\""));
    let (status, _) = http_get_json(&format!("{}/api/results?batch=nope", server.url));
    assert_eq!(status, 404);
}

#[test]
fn pool_batches_are_shown_per_suite_beside_and_never_inside_the_paper_table() {
    let dir = tempfile::tempdir().unwrap();
    let pool_dir = dir.path().join("extra/pool");
    write_pool_batch(&pool_dir);
    let server = Server::start_with(&dir.path().join("data"), &["--batches", dir.path().join("extra").to_str().unwrap()]);
    let (status, one) = http_get_json(&format!("{}/api/results?batch=pool", server.url));
    assert_eq!(status, 200, "{one}");
    let b = &one["batches"][0];
    let out = libero(&["report", pool_dir.to_str().unwrap(), "--format", "json", "--reps", "2"]);
    assert!(out.status.success());
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(b["report"]["pool"], report["pool"], "the dashboard and `report` disagree on the pool");
    assert_eq!(report["rows"], serde_json::json!([]), "pool rollouts never enter the paper's table or Score");
    let suites = report["pool"][0]["summary"]["suites"].as_array().unwrap();
    let l90 = suites.iter().find(|s| s["suite"] == "libero_90").unwrap();
    assert_eq!((l90["tasks_scored"].as_u64(), l90["stable_success"].as_f64()), (Some(1), Some(0.0)));
    let rma = suites.iter().find(|s| s["suite"] == "robomemarena").unwrap();
    assert_eq!((rma["stable_stage_completion"].as_f64(), rma["mean_stage_completion"].as_f64()), (Some(0.5), Some(0.75)));

    let (status, html) = http_get_text(&format!("{}/results?batch=pool", server.url));
    assert_eq!(status, 200, "{html}");
    assert!(html.contains("id=\"pool-suites\"") && html.contains("<td>robomemarena</td>") && html.contains("<td>libero_90</td>"), "{html}");
    assert!(!html.contains("id=\"main-table\""), "a pool-only selection has no paper table");
    assert!(html.contains("id=\"pool-tasks\"") && html.contains("<td>robomemarena/18</td>") && html.contains("min c/K 0.50"), "{html}");
    for key in ["libero_90_035-1", "libero_90_035-2", "robomemarena_018-1", "robomemarena_018-2"] {
        assert!(html.contains(&format!("href=\"/episodes/ep-pool-{key}/review\"")), "a review link per pool rollout: {key}");
    }
    // Markdown and CSV carry the same per-suite lines.
    let md = libero(&["report", pool_dir.to_str().unwrap(), "--reps", "2"]);
    assert!(String::from_utf8_lossy(&md.stdout).contains("| command/pool-fixture | robomemarena | 1 (1) | 0.0 | 50.0 | 75.0 |"));
    let csv = libero(&["report", pool_dir.to_str().unwrap(), "--format", "csv", "--reps", "2"]);
    assert!(String::from_utf8_lossy(&csv.stdout).contains("command/pool-fixture,3,none,pool:libero_90,1,1,0.0000,1,2,"));
}

/// Chromium opens `/results` and clicks a T14 rollout through to its review page. Needs `python3
/// scripts/setup.py --test` (chromium, node, playwright-core); fails saying so otherwise.
#[test]
fn chromium_clicks_a_results_cell_through_to_the_review() {
    let chromium = std::env::var_os("LIBERO_AGENT_CHROMIUM").map(PathBuf::from).unwrap_or_else(|| "/usr/bin/chromium".into());
    let cache = std::env::var_os("LIBERO_AGENT_CACHE")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(std::env::var_os("HOME").expect("HOME")).join(".cache/libero-agent"));
    let node_modules = cache.join("node/node_modules");
    assert!(
        chromium.is_file() && node_modules.join("playwright-core/package.json").is_file(),
        "chromium or playwright-core missing: run `python3 scripts/setup.py --test`"
    );
    let (_dir, server, _batch) = setup();
    let artifacts = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/dashboard");
    std::fs::create_dir_all(&artifacts).unwrap();
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/dashboard/results_click.cjs");
    let out = Command::new("node")
        .arg(script)
        .args([server.url.as_str(), "T14"])
        .arg(&artifacts)
        .env("NODE_PATH", &node_modules)
        .env("LIBERO_AGENT_CHROMIUM", &chromium)
        .env("LIBERO_OPERATOR_TOKEN", &server.token)
        .output()
        .expect("run node (Debian: apt-get install nodejs)");
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}{}", String::from_utf8_lossy(&out.stderr));
    let last: Value = stdout.lines().last().and_then(|l| serde_json::from_str(l).ok()).expect("a JSON line from the script");
    assert_eq!(last["ok"], true, "{last}");
}
