//! Scale-out end to end with real components and no model API: a throwaway PostgreSQL cluster (the store and the
//! queue), an S3-compatible server speaking the S3 protocol over HTTP (`s3s-fs` from crates.io, the artifact
//! store), three `libero-agent worker` processes and the reference agent. `run --store postgres://… --detach`
//! enqueues a 12-rollout batch; one worker is killed with SIGKILL while it runs a rollout. Every rollout ends
//! exactly once: the killed worker's in-flight rollout INVALID (`worker_lost`), all others finished, none lost,
//! none twice; `run --resume` queues the INVALID one again and follows the batch to its end; every finished
//! rollout's run directory is in the bucket, and its review and video open from a dashboard that never ran it
//! (the workers' own directories deleted first). While the batch runs, a dashboard on the same store shows an
//! episode worker 3 runs with a link to that worker's own live view, which opens with the worker's token.
mod common;

use std::collections::{BTreeMap, BTreeSet};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::postgres::TestPostgres;
use common::{Server, bin, http_get_json};
use serde_json::Value;

const BUCKET: &str = "artifacts";
const ROLLOUTS: usize = 12;

fn s3_server_exe() -> PathBuf {
    let exe = libero_testkit::cache_dir().join("s3s-fs-0.14.1/bin/s3s-fs");
    assert!(exe.is_file(), "{} is missing: run `python3 scripts/setup.py --test`", exe.display());
    exe
}

/// The S3-compatible server on a free loopback port over `root`, with one bucket; killed on drop.
struct S3Server {
    child: Child,
    endpoint: String,
}

impl S3Server {
    fn start(root: &Path) -> Self {
        std::fs::create_dir_all(root.join(BUCKET)).unwrap();
        let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let child = Command::new(s3_server_exe())
            .args(["--host", "127.0.0.1", "--port", &port.to_string(), "--access-key", "test-access", "--secret-key", "test-secret-key"])
            .arg(root)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start s3s-fs");
        let t = Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(t.elapsed() < Duration::from_secs(30), "the S3 server did not listen");
            std::thread::sleep(Duration::from_millis(100));
        }
        Self { child, endpoint: format!("http://127.0.0.1:{port}") }
    }
}

impl Drop for S3Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn libero(args: &[&str]) -> Output {
    Command::new(bin()).args(args).output().expect("run libero-agent")
}

fn run_args<'a>(pg: &'a str, resume: bool) -> Vec<&'a str> {
    let mut a = vec![
        "run", "--experiment", "main_table", "--harness", "command", "--model", "reference", "--tasks", "T14", "--reps", "12",
        "--agent-cmd", "exec {libero_agent} agent --workspace {workspace}", "--wall-time-s", "300", "--store", pg, "--batch", "q12",
    ];
    a.push(if resume { "--resume" } else { "--detach" });
    a
}

/// A worker process; its stderr goes to a file the test reads for the worker's id.
struct Worker {
    child: Child,
    log: PathBuf,
    data: PathBuf,
}

impl Worker {
    fn start(dir: &Path, n: usize, pg: &str, extra: &[&str]) -> Self {
        let (data, log) = (dir.join(format!("worker{n}")), dir.join(format!("worker{n}.log")));
        let child = Command::new(bin())
            .args(["worker", "--store", pg, "--artifacts", &format!("s3://{BUCKET}/bench"), "--slots", "1", "--lease-s", "10", "--data"])
            .arg(&data)
            .arg("--workspace-root")
            .arg(dir.join(format!("workspaces{n}")))
            .args(extra)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("start a worker");
        Self { child, log, data }
    }

    /// The id the worker registered under (the first line of its log).
    fn id(&self) -> String {
        let t = Instant::now();
        loop {
            let text = std::fs::read_to_string(&self.log).unwrap_or_default();
            if let Some(id) = text.lines().find_map(|l| l.strip_prefix("worker ")).and_then(|l| l.split(':').next()) {
                return id.to_owned();
            }
            assert!(t.elapsed() < Duration::from_secs(120), "the worker did not start: {text}");
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn store(runtime: &tokio::runtime::Runtime, url: &str) -> libero_store::Store {
    runtime.block_on(libero_store::Store::connect(url)).unwrap()
}

#[test]
fn workers_on_a_shared_queue_end_every_rollout_once_and_a_dashboard_elsewhere_reviews_them() {
    let dir = tempfile::tempdir().unwrap();
    let pg = TestPostgres::start();
    let s3 = S3Server::start(&dir.path().join("s3"));
    // Every process of this test (and this one, which reads the bucket below) reaches the bucket through the
    // standard AWS environment; set before any thread starts.
    for (k, v) in [
        ("AWS_ACCESS_KEY_ID", "test-access"),
        ("AWS_SECRET_ACCESS_KEY", "test-secret-key"),
        ("AWS_REGION", "us-east-1"),
        ("AWS_ENDPOINT_URL", s3.endpoint.as_str()),
        ("AWS_ALLOW_HTTP", "true"),
    ] {
        // SAFETY: the test's only thread so far; nothing reads the environment concurrently.
        unsafe { std::env::set_var(k, v) };
    }
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let store = store(&runtime, &pg.url);

    // Enqueue and return.
    let out = libero(&run_args(&pg.url, false));
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let queued: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(queued["batch"], "q12");
    let again = libero(&run_args(&pg.url, false));
    assert!(!again.status.success() && String::from_utf8_lossy(&again.stderr).contains("already has a batch"));
    let progress = runtime.block_on(store.queue_progress("q12")).unwrap();
    assert_eq!((progress.total, progress.queued), (ROLLOUTS as u64, ROLLOUTS as u64));

    // Three workers; the second is killed with SIGKILL while it runs a rollout. The third serves its live views
    // where other machines reach it (a fixed port, a known operator token, a public URL).
    let w3_port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let (w3_addr, w3_url) = (format!("127.0.0.1:{w3_port}"), format!("http://127.0.0.1:{w3_port}"));
    let w3_token_file = dir.path().join("worker3_token");
    std::fs::write(&w3_token_file, "worker-three-operator-token").unwrap();
    let w3_token_arg = w3_token_file.to_string_lossy().into_owned();
    let w3_extra = ["--addr", w3_addr.as_str(), "--public-url", w3_url.as_str(), "--operator-token-file", w3_token_arg.as_str()];
    let mut workers: Vec<Worker> =
        (1..=3).map(|n| Worker::start(dir.path(), n, &pg.url, if n == 3 { &w3_extra[..] } else { &[] })).collect();
    let watcher = Server::start_with(&dir.path().join("watcher"), &["--store", &pg.url]);
    let victim = workers[1].id();
    let t = Instant::now();
    let held: Vec<String> = loop {
        let p = runtime.block_on(store.queue_progress("q12")).unwrap();
        let mine: Vec<String> = p.running_on.iter().filter(|(_, w)| *w == victim).map(|(r, _)| r.clone()).collect();
        if !mine.is_empty() {
            // Mid-rollout: its agent is at work.
            std::thread::sleep(Duration::from_secs(3));
            break mine;
        }
        assert!(t.elapsed() < Duration::from_secs(600), "worker 2 never ran a rollout");
        std::thread::sleep(Duration::from_millis(200));
    };
    workers[1].child.kill().unwrap();
    workers[1].child.wait().unwrap();

    // An episode worker 3 runs: the watcher's live page links to the worker's own live view, which opens there.
    let t = Instant::now();
    'linked: loop {
        let (_, listed) = http_get_json(&format!("{}/api/episodes", watcher.url));
        let open_on_w3: Vec<String> = listed["episodes"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|e| e["outcome"].is_null() && e["server_url"] == w3_url.as_str())
            .map(|e| e["id"].as_str().unwrap().to_owned())
            .collect();
        for id in open_on_w3 {
            let (status, page) = common::http_get_text(&format!("{}/episodes/{id}", watcher.url));
            if status != 200 {
                continue; // ended meanwhile: the watcher sends the viewer to the review
            }
            assert!(page.contains(&format!("href=\"{w3_url}/episodes/{id}\"")), "the watcher links to worker 3's live view: {page}");
            let auth = "Bearer worker-three-operator-token";
            let (status, _, live) = common::http("GET", &format!("{w3_url}/episodes/{id}"), &[("Authorization", auth)], b"");
            if status == 200 {
                let live = String::from_utf8_lossy(&live);
                assert!(live.contains(&format!("data-episode=\"{id}\"")), "worker 3 serves the episode's live page: {live}");
                break 'linked;
            }
        }
        assert!(t.elapsed() < Duration::from_secs(900), "no episode of worker 3 was seen open from the watcher");
        std::thread::sleep(Duration::from_millis(300));
    }
    drop(watcher);

    // The other two finish the batch; the lost lease is closed as worker_lost.
    let t = Instant::now();
    while !runtime.block_on(store.queue_progress("q12")).unwrap().finished() {
        assert!(t.elapsed() < Duration::from_secs(1500), "the batch did not finish: {:?}", runtime.block_on(store.queue_progress("q12")));
        std::thread::sleep(Duration::from_millis(500));
    }
    let b = runtime.block_on(store.batch("q12")).unwrap().unwrap();
    let ids: Vec<&str> = b.records.iter().map(|r| r["rollout_id"].as_str().unwrap()).collect();
    assert_eq!(ids.len(), ROLLOUTS, "every rollout ended exactly once: {ids:?}");
    assert_eq!(ids.iter().collect::<BTreeSet<_>>().len(), ROLLOUTS, "none twice: {ids:?}");
    let by_id: BTreeMap<&str, &Value> = b.records.iter().map(|r| (r["rollout_id"].as_str().unwrap(), r)).collect();
    for (id, r) in &by_id {
        if held.iter().any(|h| h == id) {
            assert_eq!((r["outcome"].as_str(), r["termination_reason"].as_str()), (Some("INVALID"), Some("worker_lost")), "{id}: {r}");
        } else {
            // The reference agent plays its four calls: a finished episode, judged (it need not succeed).
            assert!(r["outcome"] == "SUCCESS" || r["outcome"] == "FAIL", "{id}: {r}");
        }
    }
    assert_eq!(b.doc["status"], "finished");
    assert_eq!(b.doc["outcomes"]["INVALID"].as_u64(), Some(held.len() as u64));

    // `--resume` queues exactly the INVALID ones again and follows the batch to its end.
    let resumed = libero(&run_args(&pg.url, true));
    let stderr = String::from_utf8_lossy(&resumed.stderr);
    assert!(resumed.status.success(), "{stderr}");
    assert!(stderr.contains(&format!("{} INVALID rollout(s) queued again", held.len())), "{stderr}");
    assert!(stderr.contains("ended ·"), "the follower draws its progress bar: {stderr}");
    let changed = libero(&[&run_args(&pg.url, true)[..], &["--seed", "7"]].concat());
    assert!(!changed.status.success() && String::from_utf8_lossy(&changed.stderr).contains("refuses changed settings"));
    let b = runtime.block_on(store.batch("q12")).unwrap().unwrap();
    assert_eq!(b.records.len(), ROLLOUTS, "the re-run replaced the INVALID record");
    let outcomes: BTreeSet<&str> = b.records.iter().map(|r| r["outcome"].as_str().unwrap()).collect();
    assert!(outcomes.len() == 1 && !outcomes.contains("INVALID"), "same task, seed and actions: one outcome, never INVALID: {outcomes:?}");
    let outcome = *outcomes.first().unwrap();
    let ran_on: BTreeSet<&str> = b.records.iter().map(|r| r["worker"].as_str().unwrap()).collect();
    assert!(ran_on.len() >= 2, "the rollouts were spread over the workers: {ran_on:?}");

    // `report --store` reads the queued batch in today's JSON shape.
    let report = libero(&["report", "--store", &pg.url, "q12", "--format", "json"]);
    assert!(report.status.success(), "{}", String::from_utf8_lossy(&report.stderr));
    let report: Value = serde_json::from_slice(&report.stdout).unwrap();
    assert_eq!(report["batches"][0]["outcomes"][outcome].as_u64(), Some(ROLLOUTS as u64), "{report}");

    // Every finished rollout's files are in the bucket, over the S3 protocol.
    let artifacts = libero_artifacts::Artifacts::open(&format!("s3://{BUCKET}/bench")).unwrap();
    for r in &b.records {
        let episode = r["episode_id"].as_str().unwrap();
        let keys: Vec<String> = runtime.block_on(artifacts.list(&format!("runs/{episode}"))).unwrap().into_iter().map(|(k, _)| k).collect();
        for needed in ["result.json", "actions.jsonl", "continuous_video.mp4", "state_record.bin", libero_artifacts::COMPLETE_MARKER] {
            assert!(keys.iter().any(|k| k.ends_with(needed)), "{episode}: {needed} missing from {keys:?}");
        }
        let rollout = r["rollout_id"].as_str().unwrap();
        let files = runtime.block_on(artifacts.list(&format!("batches/q12/rollouts/{rollout}"))).unwrap();
        assert!(files.iter().any(|(k, _)| k == "harness_manifest.json"), "{rollout}: {files:?}");
        assert!(files.iter().all(|(k, _)| !k.starts_with("home")), "the agent's session home is never copied: {files:?}");
    }

    // A dashboard on "another machine": the workers and their directories are gone.
    for w in &mut workers {
        let _ = w.child.kill();
        let _ = w.child.wait();
        std::fs::remove_dir_all(&w.data).unwrap();
    }
    let elsewhere = dir.path().join("dashboard");
    let artifacts_url = format!("s3://{BUCKET}/bench");
    let server = Server::start_with(&elsewhere, &["--store", &pg.url, "--artifacts", &artifacts_url]);
    for r in b.records.iter().take(3) {
        let episode = r["episode_id"].as_str().unwrap();
        let (status, review) = http_get_json(&format!("{}/api/episodes/{episode}/review", server.url));
        assert_eq!(status, 200, "{review}");
        assert_eq!(review["result"]["success"], outcome == "SUCCESS", "{review}");
        assert_eq!(review["video"], true, "{review}");
        let auth = format!("Bearer {}", server.token);
        let (status, _, video) = common::http("GET", &format!("{}/episodes/{episode}/video.mp4", server.url), &[("Authorization", &auth)], b"");
        assert_eq!(status, 200);
        assert!(video.len() > 1000 && &video[4..8] == b"ftyp", "an MP4 from the bucket");
    }
}
