//! `libero-worker`, the queue's worker without the browser console: its binary links the runner, the episode
//! server and the store but not `libero-dashboard`, and it runs a queued batch end to end on a real PostgreSQL
//! (Debian's package, a throwaway cluster): the sandboxed reference agent (through the `libero-agent` beside it),
//! the outcomes recorded once each, the run directories in the artifact store, and no live view recorded for
//! dashboards to link to. Needs `python3 scripts/setup.py --test` and the workspace's `libero-agent` built beside
//! it (`cargo test --workspace` builds both).
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use libero_store::testing::TestPostgres;

fn worker_bin() -> &'static str {
    env!("CARGO_BIN_EXE_libero-worker")
}

/// The `libero-agent` of the same build, which `libero-worker` runs agents through.
fn agent_bin() -> PathBuf {
    let p = Path::new(worker_bin()).with_file_name("libero-agent");
    assert!(p.is_file(), "{} missing: build the workspace (cargo test --workspace builds it)", p.display());
    p
}

#[test]
fn the_worker_binary_links_the_runner_but_not_the_console() {
    let contains = |bin: &Path, needle: &str| {
        let bytes = std::fs::read(bin).unwrap();
        bytes.windows(needle.len()).any(|w| w == needle.as_bytes())
    };
    let worker = Path::new(worker_bin());
    assert!(contains(worker, "libero_runner") && contains(worker, "libero_server"), "the symbols this check reads are there");
    assert!(!contains(worker, "libero_dashboard"), "libero-worker links the console");
    assert!(contains(&agent_bin(), "libero_dashboard"), "the check finds the console where it is linked");
}

#[test]
fn the_worker_without_a_console_runs_a_queued_batch_to_its_end() {
    let pg = TestPostgres::start();
    let dir = tempfile::tempdir().unwrap();
    let queued = Command::new(agent_bin())
        .args(["run", "--experiment", "main_table", "--harness", "command", "--model", "reference", "--tasks", "T14", "--reps", "2"])
        .args(["--agent-cmd", "exec {libero_agent} agent --workspace {workspace}", "--wall-time-s", "300"])
        .args(["--store", &pg.url, "--batch", "slim", "--detach"])
        .output()
        .unwrap();
    assert!(queued.status.success(), "{}", String::from_utf8_lossy(&queued.stderr));

    let artifacts = dir.path().join("artifacts");
    let log = dir.path().join("worker.log");
    let mut worker = Command::new(worker_bin())
        .args(["--store", &pg.url, "--artifacts"])
        .arg(&artifacts)
        .arg("--data")
        .arg(dir.path().join("worker"))
        .arg("--workspace-root")
        .arg(dir.path().join("workspaces"))
        .args(["--exit-when-idle", "--lease-s", "30"])
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let t = Instant::now();
    let status = loop {
        if let Some(status) = worker.try_wait().unwrap() {
            break status;
        }
        if t.elapsed() > Duration::from_secs(600) {
            let _ = worker.kill();
            panic!("the worker did not finish the batch: {}", std::fs::read_to_string(&log).unwrap_or_default());
        }
        std::thread::sleep(Duration::from_millis(250));
    };
    let log_text = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(status.success(), "{log_text}");

    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let store = runtime.block_on(libero_store::Store::connect(&pg.url)).unwrap();
    let batch = runtime.block_on(store.batch("slim")).unwrap().expect("the batch is in the store");
    assert_eq!(batch.records.len(), 2, "{log_text}");
    for r in &batch.records {
        assert!(r["outcome"].is_string() && r["outcome"] != "INVALID", "the reference agent's rollout ran: {r}\n{log_text}");
        assert!(r["worker"].is_string(), "{r}");
        let episode = r["episode_id"].as_str().unwrap();
        assert!(artifacts.join("runs").join(episode).join(libero_artifacts::COMPLETE_MARKER).is_file(), "{episode} uploaded: {log_text}");
        assert!(artifacts.join("runs").join(episode).join("result.json").is_file());
        let row = runtime.block_on(store.get(episode)).unwrap().expect("the episode's row");
        assert!(row.outcome.is_some(), "{row:?}");
        assert_eq!(row.episode.server_url, None, "a server without a console records no live view to link to");
    }
    runtime.block_on(store.close());
}
