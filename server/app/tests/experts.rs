//! Proof of solvability and of checker soundness for every task with a scripted privileged expert, through the
//! real binary and the real episode path (`libero-agent expert`: episodes prepared like any other, the expert acting
//! only through `osc_sequence`): the expert succeeds in 2 of 2 identical runs from the task's init state (the 3-run sweep
//! is `libero-agent expert --all --runs 3 --no-video`, tasks/README.md), an idle agent (start,
//! then finish) fails, and every near-miss behaviour fails. Perception tasks (those with a `wrong_target` behaviour)
//! also judge target identification: the expert's record has `judgment_correct == true`, wrong_target's `false`.
use std::process::Command;

use serde_json::Value;

mod common;

fn bin() -> Command {
    let mut c = Command::new(common::bin());
    c.env("XDG_RUNTIME_DIR", std::env::temp_dir());
    c
}

/// `(task, behaviours)` from `expert --list`.
fn experts() -> Vec<(String, Vec<String>)> {
    let out = bin().args(["expert", "--list"]).output().expect("run libero-agent");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| {
            let v: Value = serde_json::from_str(l).expect("JSON line");
            let task = v["task"].as_str().expect("task").to_owned();
            let behaviours = v["behaviours"].as_array().expect("behaviours").iter().filter_map(|b| b.as_str().map(str::to_owned)).collect();
            (task, behaviours)
        })
        .collect()
}

/// Runs `behaviour` of `task` `runs` times; returns the printed result records (and whether the command succeeded).
fn run(task: &str, behaviour: &str, runs: u32) -> (bool, Vec<Value>) {
    let data = tempfile::tempdir().expect("tempdir");
    let out = bin()
        .args(["expert", "--task", task, "--behaviour", behaviour, "--runs", &runs.to_string(), "--no-video", "--data"])
        .arg(data.path())
        .output()
        .expect("run libero-agent expert");
    let records: Vec<Value> =
        String::from_utf8_lossy(&out.stdout).lines().filter_map(|l| serde_json::from_str(l).ok()).collect();
    assert_eq!(
        records.len(),
        runs as usize,
        "{task} {behaviour}: expected {runs} records\nstderr:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for r in &records {
        assert_eq!(r["task"], task);
        assert!(r["required_stage_count"].as_u64().is_some_and(|k| k >= 1), "{r}");
        // every record carries one diagnostic per stage, the required ones counting K
        let stages = r["stage_diagnostics"].as_array().expect("stage diagnostics");
        assert_eq!(stages.iter().filter(|s| s["required"] == true).count() as u64, r["required_stage_count"].as_u64().unwrap_or(0), "{r}");
    }
    (out.status.success(), records)
}

fn check_task(task: &str, behaviours: &[String]) {
    let (ok, solved) = run(task, "solve", 2);
    for r in &solved {
        assert_eq!(r["success"], true, "{task} expert run failed: {r}");
        assert_eq!(r["completed_stage_count"], r["required_stage_count"], "{r}");
        let stages = r["stage_diagnostics"].as_array().expect("stage diagnostics");
        assert!(stages.iter().all(|s| s["reached"] == true && s["succeeded"] == true || s["required"] == false), "{r}");
        // opening operations carry the sustained-contact ratio; a solved opening holds the handle for a while
        for s in stages.iter().filter(|s| s["contact_exec_steps"].is_u64()) {
            assert!(s["sustained_contact_ratio_percent"].as_f64().is_some_and(|p| p > 0.0), "{task}: {s}");
        }
    }
    assert!(ok, "{task}: the expert command must exit 0 when every run succeeds");
    let actions: Vec<_> = solved.iter().map(|r| r["actions"].clone()).collect();
    assert!(actions.windows(2).all(|w| w[0] == w[1]), "{task}: runs from the same init state must be identical: {actions:?}");

    // perception tasks: the expert's first commitment is the private target, the wrong-target run's is not
    let judged = behaviours.iter().any(|b| b == "wrong_target");
    if judged {
        for r in &solved {
            assert_eq!(r["judgment_correct"], true, "{task}: the expert commits to the target first: {r}");
        }
    }

    let (_, idle) = run(task, "idle", 1);
    assert_eq!(idle[0]["success"], false, "{task}: the idle agent must fail: {}", idle[0]);
    assert_eq!(idle[0]["completed_stage_count"], 0, "{}", idle[0]);
    assert_eq!(idle[0]["actions"], 0);

    let near_misses: Vec<&String> = behaviours.iter().filter(|b| *b != "solve" && *b != "idle").collect();
    assert!(!near_misses.is_empty(), "{task}: every evaluator needs at least one near-miss");
    for b in near_misses {
        let (_, r) = run(task, b, 1);
        assert_eq!(r[0]["success"], false, "{task}: near-miss {b} must fail: {}", r[0]);
        assert!(r[0]["actions"].as_u64().is_some_and(|n| n > 0), "{task} {b} must act: {}", r[0]);
        // long-horizon behaviours: `partial_<n>` completes exactly n stages; `undo` completes a stage and undoes it
        if let Some(n) = b.strip_prefix("partial_").and_then(|n| n.parse::<u64>().ok()) {
            assert_eq!(r[0]["completed_stage_count"].as_u64(), Some(n), "{task} {b}: exactly {n} stages: {}", r[0]);
            // the diagnostics agree: n stages succeeded and (ordered stages) the next one was reached but failed
            let stages = r[0]["stage_diagnostics"].as_array().expect("stage diagnostics");
            let succeeded = stages.iter().filter(|s| s["required"] == true && s["succeeded"] == true).count() as u64;
            assert_eq!(succeeded, n, "{task} {b}: {}", r[0]);
        }
        if b == "undo" {
            let regressions = r[0]["stage_regressions"].as_array().map_or(0, Vec::len);
            assert!(regressions > 0, "{task} undo: the evaluator must record the regression: {}", r[0]);
            let stages = r[0]["stage_diagnostics"].as_array().expect("stage diagnostics");
            assert!(stages.iter().any(|s| s["regressions"].as_u64().is_some_and(|n| n > 0)), "{task} undo: {}", r[0]);
        }
        if b == "wrong_target" {
            assert_eq!(r[0]["judgment_correct"], false, "{task}: wrong_target commits to a distractor: {}", r[0]);
            assert!(r[0]["first_commitment"].is_object(), "{task}: wrong_target commits to something: {}", r[0]);
        }
    }
}

/// Tasks are checked on as many threads as the machine has cores (each `expert` process is single-threaded with
/// `--no-video`); every failing task is named at the end, not only the first.
#[test]
fn every_expert_solves_its_task_twice_identically_and_idle_and_near_miss_runs_fail() {
    let experts = experts();
    assert!(experts.iter().any(|(t, _)| t == "T14"), "{experts:?}");
    let only = std::env::var("LIBERO_AGENT_EXPERT_TASKS").ok();
    let todo: Vec<&(String, Vec<String>)> =
        experts.iter().filter(|(task, _)| only.as_deref().is_none_or(|o| o.split(',').any(|t| t == task))).collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let failed = std::sync::Mutex::new(Vec::new());
    let jobs = std::thread::available_parallelism().map_or(1, |n| n.get()).clamp(1, 4);
    std::thread::scope(|s| {
        for _ in 0..jobs {
            s.spawn(|| {
                while let Some((task, behaviours)) = todo.get(next.fetch_add(1, std::sync::atomic::Ordering::SeqCst)) {
                    let t0 = std::time::Instant::now();
                    let res = std::panic::catch_unwind(|| check_task(task, behaviours));
                    eprintln!("{task}: {} in {:.0} s", if res.is_ok() { "ok" } else { "FAILED" }, t0.elapsed().as_secs_f64());
                    if res.is_err() {
                        failed.lock().unwrap_or_else(|e| e.into_inner()).push(task.clone());
                    }
                }
            });
        }
    });
    let failed = failed.into_inner().unwrap_or_else(|e| e.into_inner());
    assert!(failed.is_empty(), "these tasks failed (their panics are above): {failed:?}");
}

#[test]
fn unknown_tasks_and_behaviours_are_refused_clearly() {
    let out = bin().args(["expert", "--task", "T99"]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no scripted expert"), "{}", String::from_utf8_lossy(&out.stderr));
    let data = tempfile::tempdir().unwrap();
    let out = bin().args(["expert", "--task", "T14", "--behaviour", "dance", "--no-video", "--data"]).arg(data.path()).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no expert behaviour \"dance\"") && err.contains("push_half"), "{err}");
}

/// With `--server`, expert runs are ordinary episodes of that server: prepared over its API, driven over MCP, and in
/// its store with their outcome (so the dashboard shows them).
#[test]
fn expert_runs_on_a_running_server_are_recorded_there() {
    let data = tempfile::tempdir().unwrap();
    let server = common::Server::start(data.path());
    let out = bin().args(["expert", "--task", "T14", "--server", &server.url]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let line: Value = serde_json::from_slice(&out.stdout).expect("one JSON record");
    assert_eq!(line["success"], true, "{line}");
    let id = line["episode_id"].as_str().expect("episode id");
    let (status, row) = common::http_get_json(&format!("{}/api/episodes/{id}", server.url));
    assert_eq!(status, 200, "{row}");
    assert_eq!(row["outcome"], "SUCCESS", "{row}");
    assert_eq!(row["state"], "finished", "{row}");
}

/// With the private video on, `expert` waits for the background worker to render each run's video from its state
/// record, says so, and reports the episode's own wall time and how long after its end the video was complete.
#[test]
fn an_expert_run_with_the_video_waits_for_it_and_reports_both_times() {
    let data = tempfile::tempdir().unwrap();
    let out = bin().args(["expert", "--task", "T14", "--runs", "1", "--data"]).arg(data.path()).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("waiting for the private video") && err.contains("video ready"), "{err}");
    let line: Value = serde_json::from_slice(&out.stdout).expect("one JSON record");
    let wall = line["episode_wall_time_s"].as_f64().unwrap_or_else(|| panic!("episode_wall_time_s: {line}"));
    let ready = line["video_ready_s"].as_f64().unwrap_or_else(|| panic!("video_ready_s: {line}"));
    assert!(wall > 0.0 && ready >= 0.0, "{line}");
    let run = data.path().join("runs").join(line["episode_id"].as_str().unwrap());
    assert!(run.join("continuous_video.mp4").is_file() && run.join("state_record.bin").is_file());
    // Without the video there is neither a record nor a wait.
    let out = bin().args(["expert", "--task", "T14", "--runs", "1", "--no-video", "--data"]).arg(data.path()).output().unwrap();
    let line: Value = serde_json::from_slice(&out.stdout).expect("one JSON record");
    assert!(line["episode_wall_time_s"].as_f64().is_some() && line["video_ready_s"].is_null(), "{line}");
    let run = data.path().join("runs").join(line["episode_id"].as_str().unwrap());
    assert!(!run.join("state_record.bin").exists() && !run.join("continuous_video.mp4").exists());
}
