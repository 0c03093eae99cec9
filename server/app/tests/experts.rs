//! Proof of solvability and of checker soundness for every task with a scripted privileged expert, through the
//! real binary and the real episode path (`libero-agent expert`: episodes prepared like any other, the expert acting
//! only through `osc_sequence`). The full proof of a release task, in one `expert --behaviour all --runs 2` process:
//! the expert succeeds in 2 of 2 identical runs from the task's init state, an idle agent (start, then finish)
//! fails, and every near-miss behaviour fails (`partial_n` completes exactly n stages, `undo` records a
//! regression); perception tasks (those with a `wrong_target` behaviour) also judge target identification: the
//! expert's record has `judgment_correct == true`, wrong_target's `false`.
//!
//! A task's behaviours run in one process, which compiles and uploads its scene once, but every episode still
//! simulates and renders (seconds each on a software renderer), so the whole proof of the 30 tasks (tens of
//! minutes) is too long for every test run on 2 cores: an ordinary run gives the full proof to
//! a sample of the tasks chosen by the day's seed (printed; `LIBERO_AGENT_EXPERT_SEED=N` repeats a day) and plays
//! the expert of a second sample once, so every release task is solved on some day of a week's runs. The whole proof: `LIBERO_AGENT_EXPERT_TASKS=all cargo test -p libero-agent
//! --test experts` (or a comma-separated list of tasks). The 3-run solvability sweep of the whole pool is
//! `libero-agent expert --all --runs 3 --no-video --json --jobs N` (writes
//! `tasks/results/expert_sweep.jsonl`, which the dashboard's task pages show); the release tasks' alone,
//! `libero-agent expert --tasks release --runs 3 --no-video --jobs N`.
use std::process::Command;

use libero_testkit::sample::{day_seed, seeded_pick};
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

/// Runs `behaviours` (`all`, or a comma-separated list) of `task` in one `expert` process, `runs` runs of `solve`
/// (of each listed behaviour); returns the printed result records by behaviour, in order (and whether the command
/// succeeded).
fn run(task: &str, behaviours: &str, runs: u32) -> (bool, Vec<Value>) {
    let data = tempfile::tempdir().expect("tempdir");
    let out = bin()
        .args(["expert", "--task", task, "--behaviour", behaviours, "--runs", &runs.to_string(), "--no-video", "--data"])
        .arg(data.path())
        .output()
        .expect("run libero-agent expert");
    let records: Vec<Value> =
        String::from_utf8_lossy(&out.stdout).lines().filter_map(|l| serde_json::from_str(l).ok()).collect();
    assert!(!records.is_empty(), "{task} {behaviours}: no record\nstderr:\n{}", String::from_utf8_lossy(&out.stderr));
    for r in &records {
        assert_eq!(r["task"], task);
        assert!(r["required_stage_count"].as_u64().is_some_and(|k| k >= 1), "{r}");
        // every record carries one diagnostic per stage, the required ones counting K
        let stages = r["stage_diagnostics"].as_array().expect("stage diagnostics");
        assert_eq!(stages.iter().filter(|s| s["required"] == true).count() as u64, r["required_stage_count"].as_u64().unwrap_or(0), "{r}");
    }
    (out.status.success(), records)
}

/// The records of `behaviour` among `records`, asserting there are `n`.
fn of<'a>(task: &str, records: &'a [Value], behaviour: &str, n: usize) -> Vec<&'a Value> {
    let mine: Vec<&Value> = records.iter().filter(|r| r["behaviour"] == behaviour).collect();
    assert_eq!(mine.len(), n, "{task}: expected {n} {behaviour} record(s): {records:?}");
    mine
}

/// How much of a task's proof a run covers.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Depth {
    /// The expert solves it twice identically, idle fails and every near-miss fails.
    Full,
    /// The expert solves it (once): the rotating sample covers the rest.
    SolveOnly,
}

fn check_task(task: &str, behaviours: &[String], depth: Depth) {
    let (ok, records) = match depth {
        Depth::Full => run(task, "all", 2),
        Depth::SolveOnly => run(task, "solve", 1),
    };
    let solved = of(task, &records, "solve", if depth == Depth::Full { 2 } else { 1 });
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
    assert!(ok, "{task}: the expert command must exit 0 when every solving run succeeds");
    let actions: Vec<_> = solved.iter().map(|r| r["actions"].clone()).collect();
    assert!(actions.windows(2).all(|w| w[0] == w[1]), "{task}: runs from the same init state must be identical: {actions:?}");

    // perception tasks: the expert's first commitment is the private target, the wrong-target run's is not
    let judged = behaviours.iter().any(|b| b == "wrong_target");
    if judged {
        for r in &solved {
            assert_eq!(r["judgment_correct"], true, "{task}: the expert commits to the target first: {r}");
        }
    }
    if depth == Depth::SolveOnly {
        return;
    }

    let idle = of(task, &records, "idle", 1);
    assert_eq!(idle[0]["success"], false, "{task}: the idle agent must fail: {}", idle[0]);
    assert_eq!(idle[0]["completed_stage_count"], 0, "{}", idle[0]);
    assert_eq!(idle[0]["actions"], 0);

    let near_misses: Vec<&String> = behaviours.iter().filter(|b| *b != "solve" && *b != "idle").collect();
    assert!(!near_misses.is_empty(), "{task}: every evaluator needs at least one near-miss");
    assert_eq!(records.len(), 3 + near_misses.len(), "{task}: `--behaviour all` plays each near-miss once: {records:?}");
    for b in near_misses {
        let r = of(task, &records, b, 1);
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

/// How many release tasks get the full proof on an ordinary test run, of those without and with staged
/// (`partial_n`) near-misses. Sized, with [`SOLVE_SAMPLE`], so the test stays near 2.5 minutes on 2 cores.
const FULL_SAMPLE: (usize, usize) = (2, 1);
/// How many of the other release tasks play their expert once on an ordinary run (the day's seed picks them; with
/// 27 others, each is picked every three days on average).
const SOLVE_SAMPLE: usize = 9;

/// What each release task is checked for. `LIBERO_AGENT_EXPERT_TASKS=all`: every task in full; a comma-separated
/// list: those tasks in full, no other; else [`FULL_SAMPLE`] tasks in full and [`SOLVE_SAMPLE`] others solving
/// once, chosen by the day's seed (printed; `LIBERO_AGENT_EXPERT_SEED` repeats another day's). Full checks come first (they are the long ones).
fn sample<'a>(release: &[&'a (String, Vec<String>)]) -> Vec<(&'a (String, Vec<String>), Depth)> {
    let only = std::env::var("LIBERO_AGENT_EXPERT_TASKS").ok().filter(|o| !o.trim().is_empty());
    let full: Vec<&String> = match only.as_deref() {
        Some("all") => release.iter().map(|(t, _)| t).collect(),
        Some(list) => {
            let wanted: Vec<&str> = list.split(',').map(str::trim).collect();
            let chosen: Vec<_> = release.iter().filter(|(t, _)| wanted.contains(&t.as_str())).map(|(t, _)| t).collect();
            assert_eq!(chosen.len(), wanted.len(), "LIBERO_AGENT_EXPERT_TASKS names tasks without an expert: {list}");
            return release.iter().filter(|(t, _)| chosen.contains(&t)).map(|e| (*e, Depth::Full)).collect();
        }
        None => {
            let seed = day_seed("LIBERO_AGENT_EXPERT_SEED");
            let staged = |b: &[String]| b.iter().any(|b| b.starts_with("partial_"));
            let short = release.iter().filter(|(_, b)| !staged(b)).map(|(t, _)| t).collect();
            let long = release.iter().filter(|(_, b)| staged(b)).map(|(t, _)| t).collect();
            let mut chosen = seeded_pick(short, FULL_SAMPLE.0, seed);
            chosen.extend(seeded_pick(long, FULL_SAMPLE.1, seed));
            let others = release.iter().map(|(t, _)| t).filter(|t| !chosen.contains(t)).collect();
            let once = seeded_pick(others, SOLVE_SAMPLE, seed.wrapping_add(1));
            eprintln!(
                "experts: the full proof for {chosen:?}, one solve for {once:?} (LIBERO_AGENT_EXPERT_SEED={seed}); \
                 LIBERO_AGENT_EXPERT_TASKS=all for the full proof of every task"
            );
            let depth = |t: &String| if chosen.contains(&t) { Some(Depth::Full) } else { once.contains(&t).then_some(Depth::SolveOnly) };
            let mut plan: Vec<_> = release.iter().filter_map(|e| depth(&e.0).map(|d| (*e, d))).collect();
            plan.sort_by_key(|(_, d)| *d == Depth::SolveOnly);
            return plan;
        }
    };
    let depth = |t: &String| if full.contains(&t) { Depth::Full } else { Depth::SolveOnly };
    let mut plan: Vec<_> = release.iter().map(|e| (*e, depth(&e.0))).collect();
    plan.sort_by_key(|(_, d)| *d == Depth::SolveOnly);
    plan
}

/// The day's sample of release tasks' experts solve them, some in full (or `LIBERO_AGENT_EXPERT_TASKS`'s tasks).
/// Tasks are checked on as many threads as the machine has cores (each `expert` process is single-threaded with
/// `--no-video`), each in one `expert` process; every failing task is named at the end, not only the first.
#[test]
fn the_days_sample_of_experts_solves_and_its_full_part_twice_identically_with_idle_and_near_misses_failing() {
    let experts: Vec<(String, Vec<String>)> = experts().into_iter().filter(|(_, b)| !b.is_empty()).collect();
    let release: Vec<&(String, Vec<String>)> = experts.iter().take_while(|(t, _)| !t.contains('/')).collect();
    assert_eq!(release.len(), 30, "`expert --list` names the 30 release tasks first: {experts:?}");
    let plan = sample(&release);
    let next = std::sync::atomic::AtomicUsize::new(0);
    let failed = std::sync::Mutex::new(Vec::new());
    let jobs = std::thread::available_parallelism().map_or(1, |n| n.get()).clamp(1, 4);
    std::thread::scope(|s| {
        for _ in 0..jobs {
            s.spawn(|| {
                while let Some(((task, behaviours), depth)) = plan.get(next.fetch_add(1, std::sync::atomic::Ordering::SeqCst)) {
                    let t0 = std::time::Instant::now();
                    let res = std::panic::catch_unwind(|| check_task(task, behaviours, *depth));
                    let verdict = if res.is_ok() { "ok" } else { "FAILED" };
                    eprintln!("{task} ({depth:?}): {verdict} in {:.0} s", t0.elapsed().as_secs_f64());
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
    let t = std::time::Instant::now();
    let out = bin().args(["expert", "--task", "T14", "--runs", "1", "--data"]).arg(data.path()).output().unwrap();
    let command_s = t.elapsed().as_secs_f64();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("waiting for the private video") && err.contains("video ready"), "{err}");
    let line: Value = serde_json::from_slice(&out.stdout).expect("one JSON record");
    let wall = line["episode_wall_time_s"].as_f64().unwrap_or_else(|| panic!("episode_wall_time_s: {line}"));
    let ready = line["video_ready_s"].as_f64().unwrap_or_else(|| panic!("video_ready_s: {line}"));
    // The episode (start to stop) and the wait for its video (after the stop) are two disjoint stretches of the
    // command's own run.
    assert!(wall > 0.0 && wall + ready <= command_s, "{wall} s + {ready} s within the command's {command_s} s: {line}");
    let run = data.path().join("runs").join(line["episode_id"].as_str().unwrap());
    assert!(run.join("continuous_video.mp4").is_file() && run.join("state_record.bin").is_file());
    // Without the video there is neither a record nor a wait.
    let out = bin().args(["expert", "--task", "T14", "--runs", "1", "--no-video", "--data"]).arg(data.path()).output().unwrap();
    let line: Value = serde_json::from_slice(&out.stdout).expect("one JSON record");
    assert!(line["episode_wall_time_s"].as_f64().is_some() && line["video_ready_s"].is_null(), "{line}");
    let run = data.path().join("runs").join(line["episode_id"].as_str().unwrap());
    assert!(!run.join("state_record.bin").exists() && !run.join("continuous_video.mp4").exists());
}

/// `expert --all --jobs 2 --out FILE`: one row per task in task order (whatever finishes first) with the runs, the
/// successes and the seconds; the metadata beside it (date, commit, command line, cores); progress on stderr with
/// done/total, failures so far and the time left; `--markdown` renders the file as the README's table per suite;
/// `--update` replaces just the re-run rows (and refuses a table run with other `--runs`, changing nothing).
#[test]
fn the_expert_sweep_writes_its_rows_and_metadata_and_reports_progress_with_an_eta() {
    let (data, out) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let sweep = out.path().join("sweep.jsonl");
    let run = bin()
        .args(["expert", "--tasks", "T10,T06", "--runs", "1", "--no-video", "--json", "--jobs", "2"])
        .arg("--out")
        .arg(&sweep)
        .arg("--data")
        .arg(data.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    let rows: Vec<Value> = std::fs::read_to_string(&sweep).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let tasks: Vec<&str> = rows.iter().filter_map(|r| r["task"].as_str()).collect();
    assert_eq!(tasks, ["T06", "T10"], "{rows:?}");
    for r in &rows {
        assert_eq!((r["suite"].as_str(), r["runs"].as_u64(), r["successes"].as_u64()), (Some("release"), Some(1), Some(1)), "{r}");
        assert!(r["seconds"].as_f64().is_some_and(|s| s > 0.0), "{r}");
    }
    let meta: Value = serde_json::from_str(&std::fs::read_to_string(out.path().join("sweep.meta.json")).unwrap()).unwrap();
    assert!(meta["date_utc"].as_str().is_some_and(|d| d.len() >= 10 && d.ends_with('Z')), "{meta}");
    assert!(meta["commit"].as_str().is_some_and(|c| !c.is_empty()), "{meta}");
    assert!(meta["command"].as_str().is_some_and(|c| c.contains("--jobs 2")), "{meta}");
    assert!(meta["cores"].as_u64().is_some_and(|n| n >= 1), "{meta}");
    for done in ["[1/2] ", "[2/2] "] {
        assert!(stderr.contains(done), "{stderr}");
    }
    assert!(stderr.contains("0 failed so far") && stderr.contains("left"), "{stderr}");
    // the JSON summary is the last line of stdout
    let last: Value = serde_json::from_str(String::from_utf8_lossy(&run.stdout).lines().last().unwrap()).unwrap();
    assert_eq!(last["summary"], "2 of 2 solved 1/1", "{last}");

    let md = bin().args(["expert", "--all", "--markdown", "--out"]).arg(&sweep).output().unwrap();
    let md = String::from_utf8_lossy(&md.stdout);
    assert!(md.contains("| suite | entries | with expert | solved 1/1 |") && md.contains("| release | 2 | 2 | 2 |"), "{md}");

    // `--update` re-runs a selection and replaces only its rows, stamped with their own date and commit
    let before = std::fs::read_to_string(&sweep).unwrap();
    let refused = bin().args(["expert", "--tasks", "T10", "--runs", "2", "--no-video", "--update", "--out"]).arg(&sweep).output().unwrap();
    let why = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && why.contains("--runs 1"), "{why}");
    assert_eq!(std::fs::read_to_string(&sweep).unwrap(), before, "a refused update changed the table");
    let update = bin()
        .args(["expert", "--tasks", "T10", "--runs", "1", "--no-video", "--json", "--update", "--out"])
        .arg(&sweep)
        .arg("--data")
        .arg(data.path())
        .output()
        .unwrap();
    assert!(update.status.success(), "{}", String::from_utf8_lossy(&update.stderr));
    let after: Vec<Value> = std::fs::read_to_string(&sweep).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(after.iter().filter_map(|r| r["task"].as_str()).collect::<Vec<_>>(), ["T06", "T10"], "{after:?}");
    assert_eq!(after[0], rows[0], "the row not re-run changed");
    assert!(after[1]["date_utc"].as_str().is_some_and(|d| d.ends_with('Z')) && after[1]["commit"].is_string(), "{}", after[1]);
    assert_eq!(after[1]["successes"], 1, "{}", after[1]);
    let meta: Value = serde_json::from_str(&std::fs::read_to_string(out.path().join("sweep.meta.json")).unwrap()).unwrap();
    assert_eq!(meta["summary"], "2 of 2 solved 1/1", "{meta}");
    let updates = meta["updates"].as_array().expect("the update is listed");
    assert!(updates.len() == 1 && updates[0]["tasks"] == 1 && updates[0]["command"].as_str().is_some_and(|c| c.contains("--update")), "{meta}");
}

/// A sweep journals each row as its task ends; a sweep stopped midway (killed here) and run again with `--resume`
/// keeps the journal's rows and runs only the rest (a journal of another sweep is refused), and the finished table
/// leaves no journal behind.
#[test]
fn a_stopped_sweep_resumes_from_its_journal_running_only_the_tasks_left() {
    let (data, out) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let sweep = out.path().join("sweep.jsonl");
    let journal = out.path().join("sweep.journal.jsonl");
    let args = ["expert", "--tasks", "T10,T06", "--runs", "1", "--no-video", "--json"];
    let mut first = bin()
        .args(args)
        .arg("--out")
        .arg(&sweep)
        .arg("--data")
        .arg(data.path())
        .stderr(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let lines = |p: &std::path::Path| std::fs::read_to_string(p).map_or(0, |t| t.lines().count());
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(600);
    while lines(&journal) < 2 {
        assert!(first.try_wait().unwrap().is_none(), "the sweep ended before its first task was journaled");
        assert!(std::time::Instant::now() < deadline, "no row journaled in 10 min");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    first.kill().unwrap();
    first.wait().unwrap();
    assert!(!sweep.exists(), "a stopped sweep wrote its table");
    let journaled: Value = serde_json::from_str(std::fs::read_to_string(&journal).unwrap().lines().nth(1).unwrap()).unwrap();
    assert!(journaled["date_utc"].is_string() && journaled["commit"].is_string(), "{journaled}");

    let other = bin().args(["expert", "--tasks", "T10,T06", "--runs", "2", "--no-video", "--resume", "--out"]).arg(&sweep).output().unwrap();
    let why = String::from_utf8_lossy(&other.stderr);
    assert!(!other.status.success() && why.contains("another sweep"), "{why}");

    let resumed = bin().args(args).arg("--resume").arg("--out").arg(&sweep).arg("--data").arg(data.path()).output().unwrap();
    let stderr = String::from_utf8_lossy(&resumed.stderr);
    assert!(resumed.status.success(), "{stderr}");
    assert!(stderr.contains("resuming: 1 of 2 tasks done") && stderr.contains("[2/2] ") && !stderr.contains("[1/2] "), "{stderr}");
    let rows: Vec<Value> = std::fs::read_to_string(&sweep).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(rows.iter().filter_map(|r| r["task"].as_str()).collect::<Vec<_>>(), ["T06", "T10"], "{rows:?}");
    assert!(rows.contains(&journaled), "the journaled row was not kept as it was: {rows:?}");
    assert!(!journal.exists(), "the finished sweep left its journal");
}

/// The README's pool table is the committed sweep's own (`expert --all --markdown` over
/// `tasks/results/expert_sweep.jsonl`): a re-run sweep or an update without the README refreshed fails here.
#[test]
fn the_readme_pool_table_is_the_committed_sweeps() {
    let out = bin().args(["expert", "--all", "--markdown"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let table = String::from_utf8(out.stdout).unwrap();
    let readme = std::fs::read_to_string(libero_testkit::repo_root().join("README.md")).unwrap();
    assert!(table.lines().count() > 3 && readme.contains(table.trim()), "README.md lacks the sweep's table (paste `libero-agent expert --all --markdown`):\n{table}");
}

/// `expert --list` names every entry with an expert (the release tasks first, then the stock LIBERO tasks and the
/// pool's own definitions), each with its suite and behaviours, `solve` and `idle` first.
#[test]
fn the_expert_list_names_release_stock_and_pool_entries_with_their_behaviours() {
    let out = bin().args(["expert", "--list"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let lines: Vec<Value> = String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let suite = |s: &str| lines.iter().filter(|l| l["suite"] == s).count();
    assert!(lines[..30].iter().all(|l| l["suite"] == "release"), "{lines:?}");
    assert_eq!(suite("release"), 30);
    assert_eq!(["libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90"].map(suite), [10, 10, 10, 10, 90]);
    assert!(lines.iter().any(|l| l["suite"] == "robomemarena" && l["entry"].as_str().is_some_and(|e| e.starts_with("robomemarena/"))));
    for l in &lines {
        let b: Vec<&str> = l["behaviours"].as_array().unwrap().iter().filter_map(Value::as_str).collect();
        assert!(b.len() >= 3 && b[..2] == ["solve", "idle"], "{l}");
    }
}
