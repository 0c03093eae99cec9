//! End to end without any model API: `libero-agent run` schedules a 2-rollout batch on T14 with concurrency 2,
//! the built-in reference agent (`libero-agent agent`) plays each episode over MCP from inside its bubblewrap
//! sandbox, the server evaluates, and `libero-agent report` computes the tables. Before playing, the agent's
//! command probes what the sandbox must hide — the repository's `tasks/`, the server's data directory and
//! store, the asset cache, the other episode's workspace — and every probe must fail while the episode itself
//! still succeeds in running (a valid outcome). Also: `--resume` skips finished rollouts and refuses changed
//! settings; `--dry-run --json` prints one object per rollout.
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use libero_records::batch_doc::harness_manifest::{CREDENTIAL_MATERIAL_NEVER_RECORDED, HarnessManifest};
use libero_testkit::{cache_dir, repo_root};
use serde_json::Value;

mod common;
use common::postgres::TestPostgres;
use common::{Server, http_get_json};

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_libero-agent")
}

fn as_refs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

fn libero(args: &[&str]) -> Output {
    let out = Command::new(bin()).args(args).output().expect("run libero-agent");
    eprintln!("$ libero-agent {}\n{}", args.join(" "), String::from_utf8_lossy(&out.stderr));
    out
}

/// The agent command: probes (each line `LIBERO-PROBE denied …` or `LIBERO-PROBE READABLE …`, on stdout: the
/// workspace goes with the rollout's disk when it ends, the runner keeps stdout as `command_stdout.log`), then the
/// reference agent.
fn agent_cmd(batch: &Path) -> String {
    let tasks = repo_root().join("tasks/manifest.json");
    let probes = [
        format!("cat {}", tasks.display()),
        format!("ls {}", repo_root().join("tasks").display()),
        format!("ls {}", batch.join("server").display()),
        format!("cat {}", batch.join("server/episodes.sqlite").display()),
        format!("cat {}", batch.join("batch.json").display()),
        format!("cat {}", batch.join("rollouts.jsonl").display()),
        // The asset cache: BDDL files and init states of every task (only libmujoco itself is bound).
        format!("ls {}", cache_dir().join("hf-libero-0.1.4/bddl_files").display()),
        format!("ls {}", cache_dir().join("libero-assets-0.1.0/assets").display()),
    ];
    let mut script =
        String::from("probe() { if \"$@\" >/dev/null 2>&1; then echo \"LIBERO-PROBE READABLE $*\"; else echo \"LIBERO-PROBE denied $*\"; fi; }; ");
    for p in probes {
        script.push_str(&format!("probe {p}; "));
    }
    // The sibling rollouts' workspaces: only this rollout's own directory below the workspace root may be visible.
    // The workspace is `<root>/<rollout id>/workspace` on the rollout's own disk (`<root>/<rollout id>` where the
    // runner caps no rollout).
    script.push_str("ws={workspace}; if [ \"$(basename \"$ws\")\" = workspace ]; then root=$(dirname \"$(dirname \"$ws\")\"); sub=/workspace; \
                     else root=$(dirname \"$ws\"); sub=; fi; ");
    script.push_str("for w in w1_t14_level3 w2_t14_level3; do probe ls \"$root/$w$sub/.libero\"; done; ");
    script.push_str("echo \"LIBERO-PROBE siblings: $(ls \"$root\" | tr '\\n' ' ')\"; ");
    script.push_str("exec {libero_agent} agent --workspace {workspace}");
    script
}

#[test]
fn a_sandboxed_reference_agent_batch_runs_and_reports() {
    let dir = tempfile::tempdir().unwrap();
    let batch = dir.path().join("batch");
    let workspaces = dir.path().join("workspaces");
    let cmd = agent_cmd(&batch);
    // The batch is also written to a real PostgreSQL (`run --store`), and reported from there below.
    let pg = TestPostgres::start();
    let run_args = |model: &str, resume: bool| {
        let mut a = vec![
            "run", "--experiment", "main_table", "--harness", "command", "--model", model, "--tasks", "T14", "--reps", "2",
            "--concurrency", "2", "--agent-cmd", &cmd, "--wall-time-s", "300",
        ]
        .into_iter()
        .map(str::to_owned)
        .collect::<Vec<_>>();
        a.extend(["--batch".into(), batch.display().to_string(), "--workspace-root".into(), workspaces.display().to_string()]);
        // `--local`: run here and mirror to the store (without it a PostgreSQL store queues the batch for workers).
        a.extend(["--local".into(), "--store".into(), pg.url.clone()]);
        if resume {
            a.push("--resume".into());
        }
        a
    };

    // The schedule alone.
    let mut dry = run_args("reference", false);
    dry.extend(["--dry-run".into(), "--json".into()]);
    let out = libero(&as_refs(&dry));
    assert!(out.status.success());
    let planned: Vec<Value> = String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(planned.len(), 2);
    assert_eq!((planned[1]["task"].as_str(), planned[1]["repetition"].as_u64()), (Some("T14"), Some(2)));
    assert_eq!((planned[0]["level"].as_u64(), planned[0]["demo"].as_str()), (Some(3), Some("none")));
    assert!(!batch.exists(), "a dry run launches and writes nothing");

    // A store that cannot be opened stops the run before anything is written.
    let mut bad = run_args("reference", false);
    *bad.last_mut().unwrap() = "mysql://u:hunter2@127.0.0.1/db".into();
    let out = libero(&as_refs(&bad));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("expected sqlite://PATH or postgres://") && !err.contains("hunter2"), "{err}");
    assert!(!batch.exists(), "nothing written for a bad store");

    // The batch.
    let out = libero(&as_refs(&run_args("reference", false)));
    assert!(out.status.success(), "run failed");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("[2 done, 0 running, 0 left]"), "progress on stderr: {stderr}");
    let b: Value = serde_json::from_str(&std::fs::read_to_string(batch.join("batch.json")).unwrap()).unwrap();
    assert_eq!(b["status"], "finished");
    assert_eq!(b["settings"]["model"], "reference");
    assert!(b["sandbox"]["kind"] == "bubblewrap", "{b}");
    let records: Vec<Value> = std::fs::read_to_string(batch.join("rollouts.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(records.len(), 2);
    for r in &records {
        let outcome = r["outcome"].as_str().unwrap();
        assert!(outcome == "FAIL" || outcome == "SUCCESS", "the sandboxed agent did its episode: {r}");
        assert_eq!(r["accepted_agent_steps"], 4, "{r}");
        assert!(r["wall_time_s"].as_f64().unwrap() > 0.0);
        assert_eq!(r["agent_exit_code"], 0);
        let own = r["rollout_id"].as_str().unwrap();
        let ws = PathBuf::from(r["workspace"].as_str().unwrap());
        let probe = common::marked_lines(&batch.join("rollouts").join(own).join("command_stdout.log"), "LIBERO-PROBE ").join("\n");
        let own_libero = format!("{}/.libero", ws.display());
        assert!(probe.lines().filter(|l| l.starts_with("READABLE")).all(|l| l.ends_with(&own_libero)), "the sandbox leaked:\n{probe}");
        assert!(probe.contains("denied cat") && probe.contains("episodes.sqlite"), "{probe}");
        assert!(probe.lines().any(|l| l == format!("READABLE ls {own_libero}")), "own workspace visible:\n{probe}");
        assert!(probe.lines().any(|l| l.trim_end() == format!("siblings: {own}")), "only its own workspace:\n{probe}");
        // The token and records stay out of the public log; the manifest never holds credentials.
        let manifest = HarnessManifest::read(&batch.join("rollouts").join(own)).unwrap().expect("the rollout's harness manifest");
        assert_eq!(manifest.credential_material.as_deref(), Some(CREDENTIAL_MATERIAL_NEVER_RECORDED), "{manifest}");
    }
    assert!(!String::from_utf8_lossy(&std::fs::read(batch.join("rollouts.jsonl")).unwrap()).contains("Bearer"));

    // The report.
    let out = libero(&["report", batch.to_str().unwrap(), "--format", "json", "--reps", "2"]);
    assert!(out.status.success());
    let rep: Value = serde_json::from_slice(&out.stdout).unwrap();
    let row = &rep["rows"][0];
    assert_eq!(row["agent"], "command/reference");
    let easy = row["summary"]["splits"].as_array().unwrap().iter().find(|s| s["split"] == "short_horizon_easy").unwrap();
    assert_eq!(easy["tasks_scored"], 1);
    assert_eq!(easy["ordinary"]["trials"], 2);
    assert!(easy["ordinary"]["wilson_high"].as_f64().unwrap() > 0.5);
    for format in ["markdown", "csv", "latex"] {
        let out = libero(&["report", batch.to_str().unwrap(), "--format", format]);
        assert!(out.status.success() && String::from_utf8_lossy(&out.stdout).to_lowercase().contains("short"), "{format}");
    }
    // The same report from the store, without the batch directory: byte for byte, in every format.
    for format in ["json", "markdown", "csv"] {
        let from_dir = libero(&["report", batch.to_str().unwrap(), "--format", format, "--reps", "2"]);
        let from_store = libero(&["report", "--store", &pg.url, "batch", "--format", format, "--reps", "2"]);
        assert!(from_store.status.success(), "{}", String::from_utf8_lossy(&from_store.stderr));
        assert_eq!(String::from_utf8_lossy(&from_store.stdout), String::from_utf8_lossy(&from_dir.stdout), "{format}");
    }
    // A dashboard that never saw the batch directory shows the batch from the shared store, with the report's rows.
    let elsewhere = dir.path().join("elsewhere");
    let server = Server::start_with(&elsewhere, &["--store", &pg.url]);
    let (status, all) = http_get_json(&format!("{}/api/results?batch=batch&reps=2", server.url));
    assert_eq!(status, 200, "{all}");
    assert!(all["available"].as_array().unwrap().iter().any(|n| n == "batch"), "{all}");
    let report: Value = serde_json::from_slice(&libero(&["report", batch.to_str().unwrap(), "--format", "json", "--reps", "2"]).stdout).unwrap();
    assert_eq!(all["batches"][0]["report"]["rows"], report["rows"], "the store's batch on the dashboard and `report` disagree");
    drop(server);
    let out = libero(&["report", "--store", &pg.url, "no-such-batch", "--format", "json"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("no batch \"no-such-batch\"") && err.contains("batch"), "{err}");

    // Resume: nothing left to run; changed settings refused; a second run without --resume refused.
    let out = libero(&as_refs(&run_args("reference", true)));
    assert!(out.status.success());
    assert_eq!(std::fs::read_to_string(batch.join("rollouts.jsonl")).unwrap().lines().count(), 2, "no rollout re-run");
    let out = libero(&as_refs(&run_args("another-model", true)));
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("refuses changed settings"));
    let out = libero(&as_refs(&run_args("reference", false)));
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("--resume"));
}

/// `run --experiment pool` plays pool addresses next to a release id (a stock LIBERO task, RoboMemArena task 18
/// on its own definition, T14) with the sandboxed reference agent, records each rollout with its suite, and
/// `report` shows them per suite and never in the paper's table. Selectors that cannot run are refused before
/// anything is launched, with their reason.
#[test]
fn a_pool_batch_runs_pool_addresses_and_reports_them_per_suite() {
    let dir = tempfile::tempdir().unwrap();
    let batch = dir.path().join("pool");
    let workspaces = dir.path().join("workspaces");
    let args = |tasks: &str, experiment: &str| -> Vec<String> {
        [
            "run", "--experiment", experiment, "--harness", "command", "--model", "reference", "--tasks", tasks, "--reps", "1",
            "--concurrency", "2", "--agent-cmd", "exec {libero_agent} agent --workspace {workspace}", "--wall-time-s", "300",
            "--batch", batch.to_str().unwrap(), "--workspace-root", workspaces.to_str().unwrap(),
        ]
        .map(str::to_owned)
        .to_vec()
    };

    // Refused before launching: a pool address outside the pool experiment, an excluded and an unknown entry.
    for (tasks, experiment, why) in [
        ("libero_90/35", "main_table", "--experiment pool"),
        ("libero_90/999", "pool", "libero_90 has task ids"),
        ("suite:nope", "pool", "no pool suite"),
    ] {
        let out = libero(&as_refs(&args(tasks, experiment)));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(why), "{tasks}: {err}");
    }
    assert!(!batch.exists(), "nothing written");

    // The schedule of a whole suite: every vlabench_perception entry that runs, the others (the excluded bloomed
    // flower) named on stderr.
    let mut dry = args("suite:vlabench_perception", "pool");
    dry.extend(["--dry-run".into(), "--json".into()]);
    let out = libero(&as_refs(&dry));
    assert!(out.status.success());
    let planned: Vec<Value> = String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert!(planned.iter().any(|p| p["task"] == "vlabench_perception/0" && p["suite"] == "vlabench_perception"), "{planned:?}");
    assert!(!planned.iter().any(|p| p["task"] == "vlabench_perception/1"), "{planned:?}");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("left out") && err.contains("vlabench_perception/1"), "the entries that do not run are named: {err}");

    // The batch.
    let out = libero(&as_refs(&args("libero_object/0,robomemarena/18,T14", "pool")));
    assert!(out.status.success(), "run failed");
    let b: Value = serde_json::from_str(&std::fs::read_to_string(batch.join("batch.json")).unwrap()).unwrap();
    assert_eq!((b["status"].as_str(), b["settings"]["experiment"].as_str()), (Some("finished"), Some("pool")));
    assert_eq!(b["settings"]["pool_tasks"], serde_json::json!(["libero_object/0", "robomemarena/18", "T14"]));
    let records: Vec<Value> = std::fs::read_to_string(batch.join("rollouts.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let mut seen: Vec<(String, String)> = records
        .iter()
        .map(|r| {
            let outcome = r["outcome"].as_str().unwrap();
            assert!(outcome == "FAIL" || outcome == "SUCCESS", "the sandboxed agent played its episode: {r}");
            assert_eq!(r["accepted_agent_steps"], 4, "{r}");
            (r["suite"].as_str().unwrap().to_owned(), r["rollout_id"].as_str().unwrap().to_owned())
        })
        .collect();
    seen.sort();
    assert_eq!(
        seen,
        [
            ("libero_object".into(), "w1_libero_object_000_level3".into()),
            ("release".into(), "w1_t14_level3".into()),
            ("robomemarena".into(), "w1_robomemarena_018_level3".into()),
        ]
    );
    let rma = records.iter().find(|r| r["suite"] == "robomemarena").unwrap();
    assert_eq!(rma["stage_count"], 2);

    // The report: per suite, nothing in the paper's rows.
    let out = libero(&["report", batch.to_str().unwrap(), "--format", "json", "--reps", "1"]);
    assert!(out.status.success());
    let rep: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(rep["rows"], serde_json::json!([]));
    let suites = rep["pool"][0]["summary"]["suites"].as_array().unwrap();
    let names: Vec<&str> = suites.iter().filter_map(|s| s["suite"].as_str()).collect();
    assert_eq!(names, ["libero_object", "release", "robomemarena"]);
    assert!(suites.iter().all(|s| s["tasks"] == 1 && s["tasks_scored"] == 1 && s["ordinary"]["trials"] == 1), "{suites:?}");
    let md = libero(&["report", batch.to_str().unwrap(), "--reps", "1"]);
    assert!(String::from_utf8_lossy(&md.stdout).contains("## Task pool, per suite"));
}

/// `bench queue` on a real PostgreSQL: claim latency per claimer count, and a real batch drained by `worker`
/// processes that exit on their own once the queue is empty (no timing asserted).
#[test]
fn bench_queue_prints_claim_latency_and_rollouts_per_hour_for_each_worker_count() {
    let pg = TestPostgres::start();
    let out = libero(&["bench", "queue", "--json", "--store", &pg.url, "--workers", "1,2", "--rollouts", "2", "--claims", "40"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["backend"], "postgres");
    let claims = v["claim_latency"].as_array().unwrap();
    assert_eq!(claims.iter().map(|c| c["claimers"].as_u64().unwrap()).collect::<Vec<_>>(), [1, 2]);
    assert!(claims.iter().all(|c| c["claims"] == 40 && c["claim_p50_ms"].as_f64().unwrap() > 0.0 && c["claim_p95_ms"].as_f64() >= c["claim_p50_ms"].as_f64()));
    let rates = v["rollouts"].as_array().unwrap();
    assert_eq!(rates.len(), 2);
    for r in rates {
        assert!(r["rollouts_per_hour"].as_f64().unwrap() > 0.0, "{r}");
        let ended: u64 = r["outcomes"].as_object().unwrap().values().map(|n| n.as_u64().unwrap()).sum();
        assert_eq!(ended, 2, "every queued rollout ended: {r}");
        assert!(r["outcomes"].get("INVALID").is_none(), "{r}");
    }
    assert_eq!(rates[0]["speedup"], 1.0);
}
