//! The dashboard's Results page over real batches: `libero-agent run` plays two T14 rollouts with the built-in
//! reference agent, a hand-written observation-ablation batch and a pool batch are registered with `serve
//! --batches`, and the served Results must show the same numbers as `libero-agent report --format json`, per-task
//! cells that link every rollout to its episode's review page (which opens, although the episodes ran on the batch's
//! own in-process server), the ablation table, progress, and batch selection. The pages and APIs are asked of the
//! full router in process (`libero_testkit::server::TestServer`); only Chromium's click through a cell needs a real
//! `serve`. A batch's rollout logs (its page and raw files, what they refuse) are this file's too: Chromium follows
//! a real batch's rollout to them, and their routes are asked in process over a fixture batch.
mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::{Server, bin};
use libero_testkit::server::TestServer;
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

/// `reps` T14 rollouts of the built-in reference agent, played by `libero-agent run` into `batch`.
fn run_reference_batch(batch: &Path, workspaces: &Path, reps: &str) {
    let out = libero(&[
        "run", "--experiment", "main_table", "--harness", "command", "--model", "reference", "--tasks", "T14", "--reps",
        reps, "--concurrency", "2", "--agent-cmd", "exec {libero_agent} agent --workspace {workspace}", "--wall-time-s",
        "300", "--no-sandbox", "--batch", batch.to_str().unwrap(), "--workspace-root", workspaces.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "run failed");
}

/// A reference-agent T14 batch of one rollout (all a click through to a review needs) in `<data>/batches/main`, the
/// ablation and pool fixtures under `extra/`, and a real `serve` that sees them (for Chromium).
fn setup() -> (tempfile::TempDir, Server) {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    run_reference_batch(&data.join("batches/main"), &dir.path().join("workspaces"), "1");
    let extra = dir.path().join("extra");
    write_ablation_batch(&extra.join("abl"));
    write_pool_batch(&extra.join("pool"));

    let server = Server::start_with(&data, &["--batches", extra.to_str().unwrap()]);
    (dir, server)
}

/// A page or file of the in-process server, asked with the operator token: (status, text).
async fn text(server: &TestServer, path: &str) -> (u16, String) {
    let a = server.get_as_operator(path).await;
    (a.status, a.text())
}

/// A JSON answer of the in-process server, asked with the operator token: (status, JSON).
async fn json(server: &TestServer, path: &str) -> (u16, Value) {
    let a = server.get_as_operator(path).await;
    (a.status, a.json())
}

/// The reference batch (as `main`), the ablation (`abl`) and pool (`pool`) fixtures in one `--batches` folder, read by
/// the full router in process: the JSON carries exactly `report`'s rows, the page links every rollout to a review
/// that opens, downloads are exactly what `report --format csv|markdown|latex` prints, selections pick batches, and
/// a bad `reps`, download format, batch or home-page outcome filter is an error that says what is wrong.
#[tokio::test(flavor = "multi_thread")]
async fn results_show_the_report_numbers_link_every_rollout_to_its_review_and_download_as_the_report_prints() {
    let dir = tempfile::tempdir().unwrap();
    let extra = dir.path().join("extra");
    let batch = extra.join("main");
    run_reference_batch(&batch, &dir.path().join("workspaces"), "2");
    write_ablation_batch(&extra.join("abl"));
    write_pool_batch(&extra.join("pool"));
    let server = TestServer::start_with(&["--batches", extra.to_str().unwrap()]).await;

    // The JSON: both batches, the main one with exactly the report's rows.
    let (status, all) = json(&server, "/api/results").await;
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
    let (status, html) = text(&server, "/results").await;
    assert_eq!(status, 200, "{html}");
    assert!(html.contains("id=\"main-table\"") && html.contains("command + reference") && html.contains("≥ "), "{html}");
    assert!(html.contains("id=\"ordinary\"") && html.contains(" = ") && html.contains("["), "Wilson intervals");
    // each per-task row names its task as a link to the task's page
    let task_cell = |t: &str| format!("<td><a class=\"task-page-link\" href=\"/tasks/{t}\">{t}</a></td>");
    assert!(html.contains(&task_cell("T14")) && html.contains(&task_cell("T11")), "per-task rows");
    for e in episodes {
        let id = e["episode_id"].as_str().expect("episode id");
        let href = format!("href=\"/episodes/{id}/review\"");
        assert!(html.contains(&href), "no review link {href}");
        // The episode ran on the batch's in-process server; this server finds it through the batch.
        let (status, page) = text(&server, &format!("/episodes/{id}/review")).await;
        assert!(status == 200 && page.contains(id), "{page}");
        let (status, review) = json(&server, &format!("/api/episodes/{id}/review")).await;
        assert_eq!(status, 200);
        assert!(review["result"].is_object() && review["calls"].as_array().is_some_and(|c| !c.is_empty()), "{review}");
    }
    let successes = episodes.iter().filter(|e| e["outcome"] == "SUCCESS").count();
    assert!(html.contains(&format!("<b>{successes}/2</b>")), "T14 cell: successes out of the repetitions");
    assert!(html.contains("Observation ablation") && html.contains("<td>L1</td>") && html.contains("<td>L2</td>"), "ablation");
    assert!(html.contains("id=\"progress\"") && html.contains("http-equiv=\"refresh\""), "a running batch refreshes");

    // Selection: one batch, two side by side, an unknown one.
    let (_, one) = json(&server, "/api/results?batch=abl").await;
    assert_eq!(one["batches"].as_array().map(Vec::len), Some(1));
    assert_eq!(one["batches"][0]["progress"]["counts"]["running"], 1);
    let (_, two) = json(&server, "/api/results?batch=main&batch=abl&reps=3").await;
    let names: Vec<&str> = two["batches"].as_array().unwrap().iter().filter_map(|b| b["name"].as_str()).collect();
    assert_eq!(names, ["main", "abl"]);
    assert_eq!(two["batches"][0]["reps"], 3);
    let (_, html) = text(&server, "/results?batch=main").await;
    assert!(html.contains(&task_cell("T14")) && !html.contains(&task_cell("T11")) && !html.contains("http-equiv=\"refresh\""));
    let (status, _) = json(&server, "/api/results?batch=nope").await;
    assert_eq!(status, 404);

    // Issue 49 (links and downloads, bad input): the downloads are what `report` prints for the selection, the batch
    // name links to the batch's own Results, the review names its batch.
    for (format, cli) in [("csv", "csv"), ("markdown", "markdown"), ("latex", "latex")] {
        let (status, body) = text(&server, &format!("/results/report/{format}?batch=main&reps=2")).await;
        assert_eq!(status, 200, "{format}: {body}");
        let out = libero(&["report", batch.to_str().unwrap(), "--format", cli, "--reps", "2"]);
        assert!(out.status.success());
        assert_eq!(body, String::from_utf8_lossy(&out.stdout), "{format}: the download is the report");
    }
    let (_, page) = text(&server, "/results?batch=main&reps=2").await;
    for link in [
        r#"id="download-csv" href="/results/report/csv?batch=main&#38;reps=2""#,
        r#"id="download-latex" href="/results/report/latex?batch=main&#38;reps=2""#,
        r#"class="batch-link" href="/results?batch=main">main</a>"#,
    ] {
        assert!(page.contains(link), "{link} in the Results page");
    }
    let (_, all) = json(&server, "/api/results?batch=main").await;
    let episode = all["batches"][0]["episodes"][0]["episode_id"].as_str().expect("an episode").to_owned();
    let (status, review) = text(&server, &format!("/episodes/{episode}/review")).await;
    assert_eq!(status, 200);
    assert!(review.contains(r#"<a id="batch-link" href="/results?batch=main">main</a>"#), "the review names its batch");
    // A bad value is an error page (or JSON error) that says what is wrong, never a silent default.
    for (query, says) in [
        ("/results?reps=abc", "reps must be a whole number from 1 to 100"),
        ("/results?reps=0", "reps must be a whole number from 1 to 100"),
        ("/api/results?reps=1000", "reps must be a whole number from 1 to 100"),
        ("/results/report/pdf", "csv, markdown or latex, not"),
        ("/results/report/csv?batch=nope", "no batch"),
        ("/?outcome=bogus", "outcome must be one of RUNNING, SUCCESS, FAIL, SIM_TIMEOUT, WATCHDOG_TIMEOUT, INVALID, INTERRUPTED"),
    ] {
        let (status, body) = text(&server, query).await;
        assert!((400..500).contains(&status), "{query}: {status}");
        assert!(body.contains(says), "{query}: {body}");
    }
    let (status, home) = text(&server, "/?outcome=fail").await;
    assert_eq!(status, 200, "an outcome in any case filters");
    assert!(home.contains(r#"<option value="FAIL" selected>"#), "the filter shows what it filters on");
    assert!(home.contains(r#"<option value="WATCHDOG_TIMEOUT">"#), "every outcome is a choice");
    // A filter that matches nothing says so (not "no episodes yet"), and an unknown task group is named.
    let (status, home) = text(&server, "/?batch=no-such-batch").await;
    assert_eq!(status, 200);
    assert!(home.contains("No episode matches batch “no-such-batch”") && !home.contains("No episodes yet"), "{home}");
    let (_, tasks) = text(&server, "/tasks?group=nope").await;
    assert!(tasks.contains("group must be one of perception, short_horizon, long_horizon, not &#34;nope&#34;"), "{tasks}");
}

#[tokio::test(flavor = "multi_thread")]
async fn pool_batches_are_shown_per_suite_beside_and_never_inside_the_paper_table() {
    let dir = tempfile::tempdir().unwrap();
    let pool_dir = dir.path().join("extra/pool");
    write_pool_batch(&pool_dir);
    let server = TestServer::start_with(&["--batches", dir.path().join("extra").to_str().unwrap()]).await;
    let (status, one) = json(&server, "/api/results?batch=pool").await;
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

    let (status, html) = text(&server, "/results?batch=pool").await;
    assert_eq!(status, 200, "{html}");
    assert!(html.contains("id=\"pool-suites\"") && html.contains("<td>robomemarena</td>") && html.contains("<td>libero_90</td>"), "{html}");
    assert!(!html.contains("id=\"main-table\""), "a pool-only selection has no paper table");
    assert!(html.contains("id=\"pool-tasks\"") && html.contains("<td><a class=\"task-page-link\" href=\"/tasks/robomemarena/18\">robomemarena/18</a></td>") && html.contains("min c/K 0.50"), "{html}");
    for key in ["libero_90_035-1", "libero_90_035-2", "robomemarena_018-1", "robomemarena_018-2"] {
        assert!(html.contains(&format!("href=\"/episodes/ep-pool-{key}/review\"")), "a review link per pool rollout: {key}");
    }
    // Markdown and CSV carry the same per-suite lines.
    let md = libero(&["report", pool_dir.to_str().unwrap(), "--reps", "2"]);
    assert!(String::from_utf8_lossy(&md.stdout).contains("| command/pool-fixture | robomemarena | 1 (1) | 0.0 | 50.0 | 75.0 |"));
    let csv = libero(&["report", pool_dir.to_str().unwrap(), "--format", "csv", "--reps", "2"]);
    assert!(String::from_utf8_lossy(&csv.stdout).contains("command/pool-fixture,3,none,pool:libero_90,1,1,0.0000,1,2,"));
}

/// A batch of agent `command/fixture` (`reps` 2) whose rollouts are `(task, level, demo, repetition, outcome, c/K,
/// private evaluation)`; a rollout with a private evaluation gets a run directory with its `result.json`.
fn write_fixture_batch(dir: &Path, experiment: &str, rollouts: &[(u32, u8, &str, u32, &str, (u32, u32), Option<Value>)]) {
    std::fs::create_dir_all(dir).unwrap();
    let batch = serde_json::json!({
        "schema_version": "libero_agent.batch.v1", "status": "finished",
        "settings": {"experiment": experiment, "harness": "command", "model": "fixture", "effort": "high", "reps": 2,
            "tasks": [], "seed": 100, "wall_time_s": 300.0, "max_agent_steps": 100, "agent_cmd": "true", "sandbox": false},
        "rollout_count": rollouts.len(), "counts": {"done": rollouts.len(), "running": 0, "left": 0}, "outcomes": {},
    });
    std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
    let mut lines = String::new();
    for (task, level, demo, rep, outcome, (c, k), private) in rollouts {
        let id = format!("w{rep}_t{task}_level{level}_{demo}");
        let run_dir = private.as_ref().map(|pe| {
            let d = dir.join("runs").join(&id);
            std::fs::create_dir_all(&d).unwrap();
            std::fs::write(d.join("result.json"), serde_json::json!({"private_evaluation": pe}).to_string()).unwrap();
            d
        });
        let split = libero_metrics::Split::of_task(*task).unwrap().as_str();
        let r = serde_json::json!({
            "schema_version": "libero_agent.rollout.v1", "rollout_id": id, "task": format!("T{task}"), "task_number": task,
            "split": split, "stage_count": k, "repetition": rep, "level": level, "demo": demo, "outcome": outcome,
            "episode_id": format!("ep-{id}"), "run_dir": run_dir, "completed_stages": c, "wall_time_s": 60.0,
            "started_at": "2025-01-01T00:00:00Z", "finished_at": "2025-01-01T00:01:00Z",
        });
        lines.push_str(&format!("{r}\n"));
    }
    std::fs::write(dir.join("rollouts.jsonl"), lines).unwrap();
}

/// Tables 2–4, Figure 3 and Appendix E on the page come from all the selected batches of one agent: the
/// observation batch's L1/L2 rows beside the main table's L3 row, the context batch's Video row beside the main
/// table's None row, the stage diagnosis and the opening operations read from the rollouts' records, and Figure 3 as
/// inline SVG drawn by the server; `/api/results` carries the same numbers as `report` over the same batches.
#[tokio::test(flavor = "multi_thread")]
async fn the_paper_tables_and_figure_3_are_computed_across_the_batches_of_one_agent() {
    let dir = tempfile::tempdir().unwrap();
    let extra = dir.path().join("extra");
    write_ablation_batch(&extra.join("abl"));
    let t16 = |scr: f64, opened: bool| {
        serde_json::json!({"stage_diagnostics": [{"stage_name": "01_BDDL_Goal_At_Finish", "required": true, "reached": true, "succeeded": opened}],
            "details": {"opening_operations": [{"stage_name": "01_BDDL_Goal_At_Finish", "operation": "open", "exec_steps": 60,
                "sustained_contact_ratio_percent": scr, "completed": opened}]}})
    };
    // The first rollout unlatched holding the lever (24 of 60 steps in one handle run: SCR 40 %) and pushed the door's
    // panel without its handle (SCR 0 %); the second never touched the door: its unlatching was never entered.
    let t28 = |unlatched: bool| {
        let op = |stage: &str, contact: &[u64], handle: &[u64], completed: bool| {
            serde_json::json!({"stage_name": stage, "operation": "open", "exec_steps": 60, "contact_runs": contact,
                "handle_contact_runs": handle, "completed": completed})
        };
        let ops = if unlatched {
            vec![op("01_Unlatch_Door", &[30], &[24], true), op("02_Open_Door", &[20], &[], false)]
        } else {
            vec![op("01_Unlatch_Door", &[], &[], false)]
        };
        serde_json::json!({"stage_diagnostics": [
            {"stage_name": "01_Unlatch_Door", "type": "mechanism_interaction", "required": true, "reached": true, "succeeded": unlatched},
            {"stage_name": "02_Open_Door", "type": "mechanism_interaction", "required": true, "reached": unlatched, "succeeded": false}],
            "details": {"opening_operations": ops}})
    };
    write_fixture_batch(
        &extra.join("main"),
        "main_table",
        &[
            (11, 3, "none", 1, "SUCCESS", (1, 1), None),
            (11, 3, "none", 2, "SUCCESS", (1, 1), None),
            (16, 3, "none", 1, "SUCCESS", (1, 1), Some(t16(40.0, true))),
            (16, 3, "none", 2, "FAIL", (0, 1), Some(t16(0.0, false))),
            (28, 3, "none", 1, "FAIL", (1, 2), Some(t28(true))),
            (28, 3, "none", 2, "FAIL", (0, 2), Some(t28(false))),
        ],
    );
    write_fixture_batch(
        &extra.join("ctx"),
        "context",
        &[(28, 3, "video", 1, "SUCCESS", (2, 2), None), (28, 3, "video", 2, "SUCCESS", (2, 2), None)],
    );
    let server = TestServer::start_with(&["--batches", extra.to_str().unwrap()]).await;
    let (status, html) = text(&server, "/results?batch=abl&batch=main&batch=ctx").await;
    assert_eq!(status, 200, "{html}");
    let table = |id: &str| {
        let start = html.find(&format!("id=\"{id}\"")).unwrap_or_else(|| panic!("no table {id}: {html}"));
        html[start..start + html[start..].find("</table>").unwrap()].to_owned()
    };
    // Table 2: L1/L2 from the observation batch, L3 (T11 stable: easy 100 over 1 of 5) from the main table.
    let t2 = table("table-2");
    assert!(t2.contains("<td>L1</td><td>100.0 (1/5)</td><td>— (0/5)</td><td>—</td><td>abl</td>"), "{t2}");
    assert!(t2.contains("<td>L3</td><td>100.0 (1/5)</td><td>0.0 (1/5)</td><td>50.0</td><td>main</td>"), "{t2}");
    // Table 3: None from the main table (T28 min c/K 0), Video from the context batch (T28 stable 1.0).
    let t3 = table("table-3");
    assert!(t3.contains("<td>None</td><td>— (0/5)</td><td>0.0 (1/5)</td><td>—</td><td>main</td>"), "{t3}");
    assert!(t3.contains("<td>Video</td><td>— (0/5)</td><td>100.0 (1/5)</td><td>—</td><td>ctx</td>"), "{t3}");
    // Table 4 from the T28 records: 4 opportunities; reached 2 (the first rollout's latch, and its door once the latch
    // was open; the second rollout shows no evidence of touching either), 1 success, both mechanism stages; the door's
    // failure is local execution.
    let t4 = table("table-4");
    assert!(t4.contains("<td>2/4 = 50.0%</td><td>1/4 = 25.0%</td><td>—</td><td>1/2 = 50.0%</td><td>1/1 = 100.0%</td><td>0/1 = 0.0%</td>"), "{t4}");
    let t4x = table("table-4-extension");
    assert!(t4x.contains("<td>2</td><td>4</td><td>2/4 = 50.0%</td><td>1/4 = 25.0%</td><td>—</td><td>1/2 = 50.0 [9.5, 90.5]</td>"), "{t4x}");
    // Figure 3 from the main table's T28 records (not T16's: short horizon): the lever held (SCR 40, opened) and the
    // panel pushed (SCR 0, not opened) count, the untouched latch does not; and its two-panel figure, drawn inline.
    let f3 = table("figure-3");
    assert!(f3.contains("<td>command/fixture</td><td>2</td><td>20.0%</td><td>1/2 = 50.0%</td>"), "{f3}");
    let bins = table("figure-3-bins");
    assert!(bins.contains("<td>SCR 0</td><td>1</td><td>0</td><td>0/1 = 0.0 [0.0, 79.3]</td>"), "{bins}");
    assert!(bins.contains("<td>all</td><td>2</td><td>1</td><td>1/2 = 50.0 [9.5, 90.5]</td><td>1.000</td>"), "{bins}");
    let plots = &html[html.find("id=\"figure-3-plots\"").expect("the plots")..];
    assert_eq!(plots.matches("<svg xmlns=\"http://www.w3.org/2000/svg\"").count(), 1);
    assert!(plots.contains("(b) local opening success by SCR bin, pooled: n = 2"));
    assert!(html.contains("id=\"appendix-e-short-horizon\"") && html.contains("id=\"appendix-e-long-horizon\""));

    // The API: the same numbers as `report` over the same three batches.
    let (_, api) = json(&server, "/api/results?batch=abl&batch=main&batch=ctx").await;
    let dirs: Vec<String> = ["abl", "main", "ctx"].iter().map(|n| extra.join(n).to_string_lossy().into_owned()).collect();
    let mut args: Vec<&str> = vec!["report", "--format", "json", "--reps", "2"];
    args.extend(dirs.iter().map(String::as_str));
    let report: Value = serde_json::from_slice(&libero(&args).stdout).unwrap();
    for key in ["observation_ablation", "demonstration_ablation", "stage_diagnosis", "stage_diagnosis_extension", "sustained_contact", "appendix_e"] {
        assert_eq!(api["across_batches"][key], report[key], "{key}: the page and `report` disagree");
    }
}

/// Chromium opens `/results` and clicks a T14 rollout through to its review page. Needs `python3
/// scripts/setup.py --test` (chromium, node, playwright-core); fails saying so otherwise.
#[test]
fn chromium_clicks_a_results_cell_through_to_the_review() {
    let (_dir, server) = setup();
    let artifacts = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/dashboard");
    std::fs::create_dir_all(&artifacts).unwrap();
    let last = common::browser_script("results_click.cjs", &[server.url.as_str(), "T14", &artifacts.to_string_lossy()], &server.token);
    assert_eq!(last["ok"], true, "{last}");
}

// Issue 49, item 5: a batch's rollouts link to their review and their logs. A real reference-agent T28 batch (the
// agent's command also writes a marker to stderr) is served; Chromium (`tests/dashboard/batch_logs_check.cjs`)
// follows Results → the rollout's logs (stdout, stderr, manifest, transcript checked by content) → plain text →
// review → batch, and sees the usage record the test replaced with a symlink refused. Asked of the full router in
// process over a finished fixture batch: the log routes refuse a file replaced with a symlink to the operator token
// (never reading it), serve a 9 MiB log from its end with a note, and answer 404 for names outside the runner's files.

/// What the logs batch's agent command writes to stderr.
const MARKER: &str = "stderr-marker-4f9c";

#[test]
fn chromium_follows_a_batchs_rollout_to_its_logs_review_and_back_to_the_batch() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let batch = data.join("batches/logs-b");
    let agent = format!("echo {MARKER} >&2; exec {{libero_agent}} agent --workspace {{workspace}}");
    let out = Command::new(bin())
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
fn write_logs_batch(root: &Path, stdout: &str) -> PathBuf {
    let dir = root.join("logs-b");
    let rollout = dir.join("rollouts/w1_t28_level3");
    std::fs::create_dir_all(&rollout).unwrap();
    let batch = serde_json::json!({
        "schema_version": "libero_agent.batch.v1", "status": "finished", "created_at": "2025-01-01T00:00:00Z",
        "settings": {"experiment": "main_table", "harness": "command", "model": "reference", "reps": 1, "tasks": [28], "seed": 100,
            "wall_time_s": 300.0, "max_agent_steps": 100, "agent_cmd": "true", "sandbox": false},
        "rollout_count": 1, "counts": {"done": 1, "running": 0, "left": 0}, "outcomes": {"SUCCESS": 1},
    });
    std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
    let record = serde_json::json!({
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
    let rollout = write_logs_batch(extra.path(), &long);
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
