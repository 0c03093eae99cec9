//! Workers and batches as operators run them, with the real binary and the built-in reference agent (no sandbox:
//! what is checked here is the scheduling, not the isolation):
//!
//! - two `libero-agent worker`s started on one machine with no `--data` and no `--workspace-root` (a SQLite
//!   queue) both register, claim and run rollouts, each in a directory of its own under the user's data
//!   directory; the agents' workspaces and session homes are removed once uploaded, their logs kept;
//! - the same batch name queued again on a fresh database, run by a worker whose `--data` and `--workspace-root`
//!   still hold the first batch's files, runs (it used to end every rollout INVALID on the leftovers, silently);
//! - a worker prints why a rollout ended INVALID;
//! - `run --server` at an address where nothing listens stops at once, non-zero, before anything is written;
//! - `run` of a batch whose every rollout ends INVALID exits non-zero naming the reasons, which `report` and the
//!   Results page show next to the rollout.
mod common;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::{Server, bin, http_get_text};
use libero_records::batch_doc::harness_manifest::HarnessManifest;
use libero_runner::batch::BatchSettings;
use libero_runner::schedule::{Experiment, plan};
use serde_json::Value;

fn libero(args: &[&str]) -> Output {
    let out = Command::new(bin()).args(args).output().expect("run libero-agent");
    eprintln!("$ libero-agent {}\n{}", args.join(" "), String::from_utf8_lossy(&out.stderr));
    out
}

fn settings(reps: u32, agent_cmd: &str) -> BatchSettings {
    BatchSettings {
        experiment: "main_table".into(),
        harness: "command".into(),
        harness_version: None,
        model: "reference".into(),
        effort: "high".into(),
        reps,
        tasks: vec![14],
        pool_tasks: vec![],
        seed: 100,
        wall_time_s: 300.0,
        max_agent_steps: libero_episode::tools::MAX_AGENT_STEPS_CAP,
        agent_cmd: Some(agent_cmd.into()),
        sandbox: false,
    }
}

const REFERENCE: &str = "exec {libero_agent} agent --workspace {workspace}";

/// Queues `reps` T14 rollouts as batch `name` in the store at `url`.
fn enqueue(runtime: &tokio::runtime::Runtime, url: &str, name: &str, reps: u32, agent_cmd: &str) {
    let catalog = libero_tasks::catalog::Catalog::discover().unwrap();
    let (schedule, _) = plan(Experiment::MainTable, catalog.tasks(), Some(&[14]), reps).unwrap();
    let store = runtime.block_on(libero_store::Store::connect(url)).unwrap();
    runtime.block_on(libero_runner::queue::enqueue(&store, url, name, &settings(reps, agent_cmd), &schedule, &[])).unwrap();
    runtime.block_on(store.close());
}

/// A `worker --exit-when-idle` with the environment of a machine whose home and temporary directory are `env`'s.
fn worker(store: &str, env: &Path, artifacts: &Path, log: &Path, extra: &[&str]) -> std::process::Child {
    Command::new(bin())
        .args(["worker", "--store", store, "--artifacts"])
        .arg(artifacts)
        .args(["--exit-when-idle", "--lease-s", "30"])
        .args(extra)
        .env("LIBERO_AGENT_DATA", env.join("data"))
        .env("TMPDIR", env.join("tmp"))
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .expect("start a worker")
}

fn wait(mut child: std::process::Child, log: &Path, limit: Duration) -> String {
    let t = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t.elapsed() > limit {
            let _ = child.kill();
            panic!("the worker did not finish: {}", std::fs::read_to_string(log).unwrap_or_default());
        }
        std::thread::sleep(Duration::from_millis(250));
    };
    let text = std::fs::read_to_string(log).unwrap_or_default();
    assert!(status.success(), "the worker failed: {text}");
    text
}

fn records(runtime: &tokio::runtime::Runtime, url: &str, name: &str) -> Vec<Value> {
    let store = runtime.block_on(libero_store::Store::connect(url)).unwrap();
    let b = runtime.block_on(store.batch(name)).unwrap().expect("the batch");
    runtime.block_on(store.close());
    b.records
}

/// Every directory below `root` named like a rollout, and every `home` directory.
fn find_dirs(root: &Path, pred: &dyn Fn(&Path) -> bool, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(root).into_iter().flatten().flatten() {
        let p = e.path();
        if e.file_type().map(|t| t.is_dir()).unwrap_or(false) {
            if pred(&p) {
                out.push(p.clone());
            }
            find_dirs(&p, pred, out);
        }
    }
}

#[test]
fn workers_on_one_machine_need_no_flags_and_a_reused_batch_name_runs() {
    let dir = tempfile::tempdir().unwrap();
    let env = dir.path().join("machine");
    std::fs::create_dir_all(env.join("tmp")).unwrap();
    let artifacts = dir.path().join("artifacts");
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();

    // Two workers, default flags, one queue.
    let db1 = libero_store::sqlite_url(&dir.path().join("queue1.sqlite"));
    enqueue(&runtime, &db1, "twice", 4, REFERENCE);
    let logs = [dir.path().join("w1.log"), dir.path().join("w2.log")];
    let children: Vec<_> = logs.iter().map(|l| worker(&db1, &env, &artifacts, l, &[])).collect();
    let texts: Vec<String> = children.into_iter().zip(&logs).map(|(c, l)| wait(c, l, Duration::from_secs(900))).collect();
    let mut data_dirs = BTreeSet::new();
    for text in &texts {
        assert!(!text.contains("another libero-agent server"), "{text}");
        let first = text.lines().find(|l| l.starts_with("worker ")).unwrap_or_else(|| panic!("no start line: {text}"));
        let data = first.split(", data ").nth(1).and_then(|r| r.split(", workspaces").next()).expect("the data directory is printed");
        assert!(Path::new(data).starts_with(env.join("data/workers")), "{first}");
        data_dirs.insert(data.to_owned());
    }
    assert_eq!(data_dirs.len(), 2, "a directory each: {data_dirs:?}");
    let recs = records(&runtime, &db1, "twice");
    assert_eq!(recs.len(), 4, "{texts:?}");
    for r in &recs {
        assert!(r["outcome"] == "SUCCESS" || r["outcome"] == "FAIL", "the reference agent's rollout ran: {r}\n{texts:?}");
    }
    let ran_on: BTreeSet<&str> = recs.iter().map(|r| r["worker"].as_str().unwrap()).collect();
    assert_eq!(ran_on.len(), 2, "both workers claimed and ran rollouts: {ran_on:?}");
    // The agents' workspaces and session homes are gone; the runner's files (logs, manifest) stay.
    let mut left = Vec::new();
    find_dirs(&env.join("tmp"), &|p| p.file_name().is_some_and(|n| n.to_string_lossy().starts_with("w")) && p.join(".libero").exists(), &mut left);
    find_dirs(&env.join("data"), &|p| p.file_name().is_some_and(|n| n == "home"), &mut left);
    assert!(left.is_empty(), "left behind: {left:?}");
    let mut manifests = Vec::new();
    find_dirs(&env.join("data"), &|p| p.join("harness_manifest.json").is_file(), &mut manifests);
    assert_eq!(manifests.len(), 4, "{manifests:?}");
    let manifest = HarnessManifest::read(&manifests[0]).unwrap().expect("the rollout's harness manifest");
    let stdout_log = manifest.logs.as_ref().and_then(|l| l.get("command_stdout.log"));
    assert!(stdout_log.and_then(|l| l.size_bytes).is_some(), "the logs' record: {manifest}");

    // The same name on a fresh database, run by a worker whose --data and --workspace-root hold the first batch's
    // files: it runs (attempt numbers start at 1 again; every path of this attempt is new).
    let db2 = libero_store::sqlite_url(&dir.path().join("queue2.sqlite"));
    enqueue(&runtime, &db2, "twice", 2, REFERENCE);
    let reused = data_dirs.first().unwrap().clone();
    let workspaces = env.join("tmp/libero-agent-workspaces");
    let log = dir.path().join("w3.log");
    let extra = ["--data", reused.as_str(), "--workspace-root", workspaces.to_str().unwrap()];
    let text = wait(worker(&db2, &env, &artifacts, &log, &extra), &log, Duration::from_secs(600));
    let recs = records(&runtime, &db2, "twice");
    assert_eq!(recs.len(), 2, "{text}");
    for r in &recs {
        assert!(r["outcome"] == "SUCCESS" || r["outcome"] == "FAIL", "a reused batch name runs: {r}\n{text}");
    }

    // A rollout that ends INVALID: the worker says why.
    enqueue(&runtime, &db2, "broken", 1, "exit 3");
    let log = dir.path().join("w4.log");
    let text = wait(worker(&db2, &env, &artifacts, &log, &[]), &log, Duration::from_secs(300));
    let recs = records(&runtime, &db2, "broken");
    assert_eq!(recs[0]["outcome"], "INVALID");
    let why = recs[0]["infrastructure_error"].as_str().expect("the record names the reason");
    assert!(why.contains("harness exited before finish_episode (exit code 3)"), "{why}");
    assert!(text.lines().any(|l| l.contains("broken/w1_t14_level3: INVALID (harness exited before finish_episode")), "{text}");
}

#[test]
fn run_refuses_an_unreachable_server_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let batch = dir.path().join("b");
    let t = Instant::now();
    let out = libero(&[
        "run", "--experiment", "main_table", "--harness", "command", "--model", "reference", "--tasks", "T14", "--reps", "1",
        "--agent-cmd", REFERENCE, "--no-sandbox", "--server", &format!("http://127.0.0.1:{port}"), "--batch", batch.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(t.elapsed() < Duration::from_secs(20), "it took {:?}", t.elapsed());
    assert!(err.contains(&format!("127.0.0.1:{port}")) && err.contains("nothing answers"), "{err}");
    assert!(!batch.exists(), "nothing written");
}

#[test]
fn a_batch_whose_rollouts_all_end_invalid_fails_and_says_why_everywhere() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let batch = data.join("batches/doomed");
    let out = libero(&[
        "run", "--experiment", "main_table", "--harness", "command", "--model", "reference", "--tasks", "T14", "--reps", "2",
        "--concurrency", "2", "--agent-cmd", "exit 3", "--no-sandbox", "--wall-time-s", "120", "--batch", batch.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(err.contains("every rollout of batch doomed ended INVALID (2 of them)"), "{err}");
    assert!(err.contains("w1_t14_level3: harness exited before finish_episode (exit code 3)"), "{err}");
    assert!(err.contains("w1_t14_level3: INVALID (harness exited before finish_episode"), "the progress line says why: {err}");

    let report = libero(&["report", batch.to_str().unwrap()]);
    let md = String::from_utf8_lossy(&report.stdout);
    assert!(report.status.success());
    assert!(md.contains("## Excluded rollouts") && md.contains("| doomed | w2_t14_level3 | T14 | INVALID |"), "{md}");
    assert!(md.contains("harness exited before finish_episode (exit code 3)"), "{md}");
    let json = libero(&["report", batch.to_str().unwrap(), "--format", "json"]);
    let v: Value = serde_json::from_slice(&json.stdout).unwrap();
    assert_eq!(v["excluded"].as_array().map(Vec::len), Some(2), "{v}");

    let server = Server::start(&data);
    let (status, page) = http_get_text(&format!("{}/results", server.url));
    assert_eq!(status, 200);
    assert!(page.contains("id=\"excluded\""), "{page}");
    assert!(page.contains("INVALID: harness exited before finish_episode (exit code 3)"), "the reason beside the rollout: {page}");
    let (_, api) = common::http_get_json(&format!("{}/api/results", server.url));
    let reason = api["batches"][0]["episodes"][0]["reason"].as_str().unwrap_or_default();
    assert!(reason.contains("exit code 3"), "{api}");
}
