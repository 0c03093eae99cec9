//! Issue 30: an agent that sabotages its own workspace gets FAIL (or SUCCESS), never INVALID. Real T14 episodes
//! run on the project's in-process server; a test agent plays each over MCP (the project's own client, over
//! HTTP) while a saboteur thread, driven by a seeded RNG, attacks the workspace at random moments with every
//! kind of sabotage: `benchmark_inputs` deleted (also in tight-loop bursts), renamed away, replaced by a file, a
//! symlink to a host directory, a FIFO, a socket or a deep tree, filled with junk, `chmod 000`; the same for
//! `current_observation`, the demonstration's place (`benchmark_inputs/expert_demo`), the task reference and
//! the workspace root. Some of it is done before `start_episode` too.
//!
//! Every tool call must either succeed or fail with the agent-visible publication error (never the server's
//! generic EnvironmentCommandError); once the saboteur stops, the next call publishes normally; every episode
//! ends `finished` with outcome SUCCESS or FAIL and a `result.json`; nothing outside the workspaces is written
//! (the host directory the links point to is untouched, no staging is left beside the workspaces).
//!
//! The server runs as this user; when that is root, `chmod 000` does not bind it, and the publisher's unit tests
//! (`publish::tests`, which drop the DAC capabilities on their thread) prove the mode repairs.
use std::os::unix::fs::{PermissionsExt, symlink};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use libero_records::records::{Outcome, RunDir, classify, read_result};
use libero_server::client::{InProcessServer, McpClient, get_json, prepare_episode};
use libero_server::episodes::PrepareRequest;
use serde_json::{Value, json};

/// The seed of the first episode's saboteur (the next episodes use the following ones).
const SEED: u64 = 30;
const EPISODES: u64 = 2;
/// `osc_sequence` calls made while the saboteur runs, and micro-actions per call.
const SABOTAGED_CALLS: usize = 10;
const ACTIONS_PER_CALL: usize = 5;
/// How the agent-visible publication error begins (`libero_episode::actor::PUBLICATION_FAILED`).
const PUBLICATION_FAILED: &str = libero_episode::actor::PUBLICATION_FAILED;

/// splitmix64: a small reproducible generator.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

fn set_mode(path: &Path, mode: u32) {
    let _ = std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode));
}

fn is_real_dir(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok_and(|m| m.is_dir())
}

/// `ws/rel` if every directory on the way to it is a real one. The saboteur checks before it writes, so that
/// it never writes or chmods through a link it planted itself: what lands outside the workspace can only be the
/// server's doing (only the saboteur makes links, so the check does not race).
fn under(ws: &Path, rel: &str) -> Option<PathBuf> {
    let mut p = ws.to_path_buf();
    let parts: Vec<&str> = rel.split('/').collect();
    for dir in &parts[..parts.len() - 1] {
        p.push(dir);
        if !is_real_dir(&p) {
            return None;
        }
    }
    p.push(parts[parts.len() - 1]);
    Some(p)
}

/// `ws/rel` if it and every directory on the way are real directories.
fn real_dir_at(ws: &Path, rel: &str) -> Option<PathBuf> {
    under(ws, rel).filter(|p| is_real_dir(p))
}

/// `chmod` of the directory `ws/rel`, never through a link.
fn chmod_dir(ws: &Path, rel: &str, mode: u32) {
    if let Some(p) = real_dir_at(ws, rel) {
        set_mode(&p, mode);
    }
}

/// What an agent does to remove whatever is at `ws/rel` (giving itself access to its own directories first).
fn remove_any(ws: &Path, rel: &str) {
    fn open_up(path: &Path) {
        if is_real_dir(path) {
            set_mode(path, 0o700);
            for e in std::fs::read_dir(path).into_iter().flatten().flatten() {
                open_up(&e.path());
            }
        }
    }
    let Some(path) = under(ws, rel) else { return };
    if is_real_dir(&path) {
        open_up(&path);
        let _ = std::fs::remove_dir_all(&path);
    } else {
        let _ = std::fs::remove_file(&path);
    }
}

fn fifo(path: &Path) {
    use std::os::unix::ffi::OsStrExt;
    let Ok(c) = std::ffi::CString::new(path.as_os_str().as_bytes()) else { return };
    // SAFETY: `c` is a NUL-terminated path that outlives the call.
    unsafe { libc::mkfifo(c.as_ptr(), 0o600) };
}

fn deep_tree(root: &Path, levels: usize) {
    let mut p = root.to_path_buf();
    for i in 0..levels {
        p.push(format!("l{i}"));
    }
    let _ = std::fs::create_dir_all(&p);
    let _ = std::fs::write(p.join("junk"), b"junk");
}

/// Every kind of sabotage: (name, what it does to the workspace `ws`, with `host` a directory outside it and
/// `n` a fresh number).
type Sabotage = fn(&Path, &Path, u64);

const BI: &str = "benchmark_inputs";
const CUR: &str = "benchmark_inputs/current_observation";

const SABOTAGES: [(&str, Sabotage); 17] = [
    ("delete benchmark_inputs", |ws, _, _| remove_any(ws, BI)),
    ("delete benchmark_inputs in a tight loop", |ws, _, _| {
        let t = Instant::now();
        while t.elapsed() < Duration::from_millis(1500) {
            remove_any(ws, BI);
        }
    }),
    ("rename benchmark_inputs away", |ws, _, n| {
        let _ = std::fs::rename(ws.join(BI), ws.join(format!("scratch-moved-{n}")));
    }),
    ("replace benchmark_inputs by a file", |ws, _, _| {
        remove_any(ws, BI);
        let _ = std::fs::write(ws.join(BI), b"not a directory");
    }),
    ("replace benchmark_inputs by a symlink to a host directory", |ws, host, _| {
        remove_any(ws, BI);
        let _ = symlink(host, ws.join(BI));
    }),
    ("replace benchmark_inputs by a FIFO", |ws, _, _| {
        remove_any(ws, BI);
        fifo(&ws.join(BI));
    }),
    ("replace benchmark_inputs by a socket", |ws, _, _| {
        remove_any(ws, BI);
        let _ = std::os::unix::net::UnixListener::bind(ws.join(BI));
    }),
    ("replace benchmark_inputs by a deep tree", |ws, _, _| {
        remove_any(ws, BI);
        deep_tree(&ws.join(BI), 60);
    }),
    ("fill benchmark_inputs with junk", |ws, host, n| {
        let Some(bi) = real_dir_at(ws, BI) else { return };
        for i in 0..200 {
            let _ = std::fs::write(bi.join(format!("junk-{n}-{i}")), b"junk");
        }
        let _ = symlink(host, bi.join(format!(".current_observation.next-{n}")));
    }),
    ("chmod 000 benchmark_inputs", |ws, _, _| chmod_dir(ws, BI, 0o000)),
    ("chmod 000 the workspace root", |ws, _, _| set_mode(ws, 0o000)),
    ("chmod 000 current_observation", |ws, _, _| {
        chmod_dir(ws, &format!("{CUR}/head"), 0o000);
        chmod_dir(ws, CUR, 0o000);
    }),
    ("replace current_observation by a symlink to a host directory", |ws, host, _| {
        remove_any(ws, CUR);
        if let Some(cur) = under(ws, CUR) {
            let _ = symlink(host, cur);
        }
    }),
    ("replace current_observation by a FIFO", |ws, _, _| {
        remove_any(ws, CUR);
        if let Some(cur) = under(ws, CUR) {
            fifo(&cur);
        }
    }),
    ("plant a deep tree and links in current_observation", |ws, host, _| {
        let Some(cur) = real_dir_at(ws, CUR) else { return };
        deep_tree(&cur.join("deep"), 80);
        if is_real_dir(&cur.join("head")) {
            let _ = symlink(host, cur.join("head/link_out"));
        }
        let _ = std::fs::remove_file(cur.join("observation.json"));
        let _ = symlink(host.join("secret.txt"), cur.join("observation.json"));
    }),
    ("wreck the task reference", |ws, host, _| {
        let Some(cur) = real_dir_at(ws, CUR) else { return };
        let reference = cur.join("task_reference");
        let _ = std::fs::create_dir(&reference);
        if is_real_dir(&reference) {
            let _ = symlink(host.join("secret.txt"), reference.join("rgb.png"));
            set_mode(&reference, 0o000);
        }
    }),
    ("wreck the demonstration bundle", |ws, host, _| {
        remove_any(ws, &format!("{BI}/expert_demo"));
        let Some(demo) = under(ws, &format!("{BI}/expert_demo")) else { return };
        if std::fs::create_dir(&demo).is_err() {
            return; // something else is there (or benchmark_inputs is not a directory any more)
        }
        let _ = std::fs::create_dir(demo.join("video"));
        let _ = symlink(host, demo.join("video/head_rgb.mp4"));
        fifo(&demo.join("manifest.json"));
        set_mode(&demo.join("video"), 0o000);
        set_mode(&demo, 0o000);
    }),
];

/// Attacks `ws` until told to stop: every kind in a seeded random order (each round a new permutation, so every
/// kind is used once per round), at seeded random moments. Returns how often each kind ran.
fn saboteur(ws: PathBuf, host: PathBuf, seed: u64, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<Vec<u64>> {
    std::thread::spawn(move || {
        let mut rng = Rng(seed);
        let mut counts = vec![0u64; SABOTAGES.len()];
        let mut n = 0u64;
        while !stop.load(Ordering::Relaxed) {
            let mut order: Vec<usize> = (0..SABOTAGES.len()).collect();
            for i in (1..order.len()).rev() {
                order.swap(i, rng.below(i as u64 + 1) as usize);
            }
            for k in order {
                if stop.load(Ordering::Relaxed) {
                    break;
                }
                std::thread::sleep(Duration::from_millis(rng.below(40)));
                SABOTAGES[k].1(&ws, &host, n);
                counts[k] += 1;
                n += 1;
            }
        }
        counts
    })
}

/// A tool call's payload: success, or the agent-visible publication error (never the server's own failure).
fn checked(client: &mut McpClient, tool: &str, arguments: Value, errors: &Mutex<Vec<String>>) -> Value {
    let payload = client.call_tool_payload(tool, arguments).unwrap_or_else(|e| panic!("{tool}: the MCP call itself failed: {e:#}"));
    if payload["ok"] != true {
        let text = payload["error"].as_str().unwrap_or_default();
        assert_eq!(payload["error_type"], "RuntimeError", "{tool}: {payload}");
        assert!(text.starts_with(PUBLICATION_FAILED), "{tool}: {payload}");
        if tool == "osc_sequence" {
            assert_eq!(payload["execution"]["command_completed"], true, "the step ran: {payload}");
        }
        errors.lock().unwrap().push(format!("{tool}: {text}"));
    }
    payload
}

/// The observation the workspace holds now, if the agent can read one.
fn observation_id(ws: &Path) -> Option<Value> {
    let text = std::fs::read(ws.join("benchmark_inputs/current_observation/observation.json")).ok()?;
    serde_json::from_slice::<Value>(&text).ok().map(|v| v["observation_id"].clone())
}

fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

#[test]
fn an_agent_sabotaging_its_workspace_gets_fail_or_success_never_invalid() {
    let t0 = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    let host = dir.path().join("host");
    std::fs::create_dir(&host).unwrap();
    std::fs::write(host.join("secret.txt"), b"host secret").unwrap();
    set_mode(&host, 0o750);
    let workspaces = dir.path().join("workspaces");
    std::fs::create_dir(&workspaces).unwrap();
    let server = InProcessServer::start(dir.path().join("data"), "test_finished_before_finish").unwrap();
    let errors = Mutex::new(Vec::new());
    let mut all_counts = vec![0u64; SABOTAGES.len()];
    let mut expected_workspaces = Vec::new();
    for episode in 0..EPISODES {
        let seed = SEED + episode;
        let name = format!("ws{episode}");
        let ws = workspaces.join(&name);
        expected_workspaces.push(name);
        let req = PrepareRequest {
            level: 3,
            seed,
            workspace: Some(ws.clone()),
            wall_time_s: 300.0,
            video: false,
            ..PrepareRequest::new("T14")
        };
        let prepared = prepare_episode(&server.url, &req).unwrap();
        let headers: Vec<(String, String)> = prepared.mcp_headers.clone().into_iter().collect();
        let mut client = McpClient::connect(&prepared.mcp_url, &headers, "saboteur-test").unwrap();

        // Before start: the workspace is wrecked three ways at once (seeded), and the saboteur starts.
        let mut rng = Rng(seed ^ 0xA5A5);
        for _ in 0..3 {
            let k = rng.below(SABOTAGES.len() as u64) as usize;
            SABOTAGES[k].1(&ws, &host, 1_000_000 + k as u64);
            all_counts[k] += 1;
        }
        let stop = Arc::new(AtomicBool::new(false));
        let attacker = saboteur(ws.clone(), host.clone(), seed, stop.clone());

        // start_episode until the agent's own sabotage lets it through (the error says to call it again).
        let mut started = None;
        for _ in 0..30 {
            let p = checked(&mut client, "start_episode", json!({}), &errors);
            if p["ok"] == true {
                started = Some(p);
                break;
            }
        }
        let started = started.expect("start_episode got through within 30 calls");
        assert_eq!(started["observation_id"], "obs_000000");
        let mut accepted = 0u64;
        for call in 0..SABOTAGED_CALLS {
            let x = if call % 2 == 0 { 0.4 } else { -0.4 };
            let actions = vec![json!([x, 0.0, -0.2, 0.0, 0.0, 0.0, -1.0]); ACTIONS_PER_CALL];
            let p = checked(&mut client, "osc_sequence", json!({"actions": actions}), &errors);
            accepted += 1;
            if p["ok"] == true {
                let _ = observation_id(&ws); // what an agent would read; the saboteur may have removed it
            }
        }
        stop.store(true, Ordering::Relaxed);
        let counts = attacker.join().expect("the saboteur thread");
        for (total, c) in all_counts.iter_mut().zip(&counts) {
            *total += c;
        }

        // The saboteur stopped: the next call publishes, into a real benchmark_inputs, what the agent reads.
        let clean = checked(&mut client, "osc_sequence", json!({"actions": [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]]}), &errors);
        accepted += 1;
        assert_eq!(clean["ok"], true, "after the sabotage: {clean}");
        let bi = std::fs::symlink_metadata(ws.join("benchmark_inputs")).unwrap();
        assert!(bi.is_dir() && !bi.file_type().is_symlink());
        assert_eq!(observation_id(&ws), Some(clean["observation_id"].clone()), "the published observation is readable");

        let finished = checked(&mut client, "finish_episode", json!({}), &errors);
        assert_eq!(finished["status"], "finished", "{finished}");
        assert_eq!(finished["accepted_agent_steps"], accepted, "every executed call counted: {finished}");

        // The records: finished, a verdict, no infrastructure error.
        let run = RunDir::new(&prepared.run_dir);
        let result = read_result(&run).expect("result.json");
        assert_eq!(result.status.as_deref(), Some("finished"), "{result}");
        assert!(!result.has_infrastructure_error(), "{result}");
        let outcome = classify(Some(&result));
        assert!(matches!(outcome, Outcome::Success | Outcome::Fail), "episode {episode}: {outcome:?}");
        let deadline = Instant::now() + Duration::from_secs(30);
        let row = loop {
            let (status, row) = get_json(&server.url, &format!("/api/episodes/{}", prepared.episode_id)).unwrap();
            assert_eq!(status, 200, "{row}");
            if row["outcome"].is_string() || Instant::now() > deadline {
                break row;
            }
            std::thread::sleep(Duration::from_millis(200));
        };
        assert!(row["outcome"] == "SUCCESS" || row["outcome"] == "FAIL", "the store's row: {row}");
        eprintln!("episode {episode}: {outcome:?} after {accepted} steps; sabotage counts {counts:?}");
    }
    server.stop().unwrap();

    // Every kind of sabotage ran; nothing outside the workspaces was written.
    for ((what, _), n) in SABOTAGES.iter().zip(&all_counts) {
        assert!(*n > 0, "the saboteur never did: {what}");
    }
    assert_eq!(listing(&host), ["secret.txt"], "nothing written into the host directory");
    assert_eq!(std::fs::read(host.join("secret.txt")).unwrap(), b"host secret");
    assert_eq!(std::fs::metadata(&host).unwrap().permissions().mode() & 0o777, 0o750, "the host directory's mode");
    assert_eq!(listing(&workspaces), expected_workspaces, "no staging or other entry beside the workspaces");
    assert_eq!(listing(dir.path()), ["data", "host", "workspaces"]);
    let errors = errors.into_inner().unwrap();
    let starts = errors.iter().filter(|e| e.starts_with("start_episode")).count();
    eprintln!(
        "{} calls got the publication error ({starts} start_episode, {} osc_sequence), e.g. {:?}; {:.0} s",
        errors.len(),
        errors.len() - starts,
        errors.iter().find(|e| e.starts_with("osc_sequence")).or(errors.first()),
        t0.elapsed().as_secs_f64()
    );
}
