//! End-to-end proof with real clients: the `libero-agent` binary serves prepared episodes and the official
//! MCP Python SDK (PyPI `mcp`, in the test venv of `scripts/setup.py --test`) drives them over streamable HTTP
//! and through the `mcp-stdio` relay; malformed traffic is thrown at the endpoint; a killed server's open
//! episode is recorded as INVALID on restart, in its run directory and in the episode store, while the
//! store keeps the finished episode's row; `bench mcp` prints its JSON.
use std::path::{Path, PathBuf};
use std::process::Command;

use libero_testkit::repo_root;
use serde_json::Value;

const TASK: &str = "libero_object/pick_up_the_ketchup_and_place_it_in_the_basket";

mod common;
use common::{Server, bin, http_get_json, python};

fn prepare(server: &Server, workspace: &Path, level: u8) -> Value {
    let out = Command::new(bin())
        .args(["episode", "prepare", "--server", &server.url, "--task", TASK, "--level", &level.to_string()])
        .arg("--workspace")
        .arg(workspace)
        .output()
        .expect("run episode prepare");
    assert!(out.status.success(), "prepare failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("prepare prints JSON")
}

fn token(prepared: &Value) -> String {
    prepared["mcp_headers"]["Authorization"].as_str().expect("auth header").trim_start_matches("Bearer ").to_owned()
}

fn run_client(prepared: &Value, level: u8, extra: &[&str]) -> Value {
    let script = repo_root().join("tests/mcp/episode_client.py");
    let fixture = repo_root().join("server/episode/tests/fixtures/tools_list.json");
    let out = Command::new(python())
        .arg(script)
        .args(["--url", prepared["mcp_url"].as_str().unwrap(), "--token", &token(prepared)])
        .args(["--workspace", prepared["workspace"].as_str().unwrap(), "--level", &level.to_string()])
        .arg("--tools-fixture")
        .arg(fixture)
        .args(extra)
        .output()
        .expect("run the python client");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "python client failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_str(stdout.lines().last().unwrap_or("")).expect("report JSON")
}

fn workspace_files(ws: &Path) -> Vec<String> {
    fn walk(dir: &Path, root: &Path, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            out.push(p.strip_prefix(root).unwrap().to_string_lossy().into_owned());
            if p.is_dir() {
                walk(&p, root, out);
            }
        }
    }
    let mut v = Vec::new();
    walk(ws, ws, &mut v);
    v.sort();
    v
}

#[test]
fn python_sdk_drives_a_level3_episode_over_http_and_the_workspace_stays_public() {
    let tmp = tempfile::tempdir().unwrap();
    let server = Server::start(&tmp.path().join("data"));
    let ws = tmp.path().join("ws");
    let prepared = prepare(&server, &ws, 3);
    for key in ["episode_id", "mcp_url", "workspace", "prompt_file"] {
        assert!(prepared[key].is_string(), "prepare output lacks {key}: {prepared}");
    }
    let mcp: Value = serde_json::from_str(&std::fs::read_to_string(ws.join(".libero/mcp.json")).unwrap()).unwrap();
    assert_eq!(mcp["mcpServers"]["libero"]["url"], prepared["mcp_url"]);
    let report = run_client(&prepared, 3, &[]);
    assert_eq!(report["ok"], true, "{report}");
    // The private run directory holds the records; the workspace holds none of them.
    let run = PathBuf::from(prepared["run_dir"].as_str().unwrap());
    let log = std::fs::read_to_string(run.join("actions.jsonl")).unwrap();
    assert!(log.lines().count() >= 15, "every request is logged, errors included");
    assert!(run.join("private_observations/obs_000001/observation.json").is_file());
    // The episode has ended (finish): its thread, no longer serving calls, finalises the private video within
    // seconds, under its final name.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while !run.join("continuous_video.mp4").is_file() && std::time::Instant::now() < deadline {
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    let video = std::fs::read(run.join("continuous_video.mp4")).expect("continuous_video.mp4");
    assert_eq!(&video[4..8], b"ftyp");
    assert!(!run.join("continuous_video.mp4.partial").exists());
    let files = workspace_files(&ws);
    let allowed_prefixes = ["TASK_PROMPT.txt", ".libero", "benchmark_inputs", "scratch"];
    for f in &files {
        assert!(allowed_prefixes.iter().any(|p| f.starts_with(p)), "unexpected workspace file {f}");
        assert!(!f.contains(".current_observation."), "staging directory left behind: {f}");
    }
    let obs = std::fs::read_to_string(ws.join("benchmark_inputs/current_observation/observation.json")).unwrap();
    for private in ["segmentation", "object", "mass", "bddl", "success", "stage", "reward"] {
        assert!(!obs.contains(private), "observation.json mentions {private}");
    }
}

#[test]
fn python_sdk_drives_a_level1_episode_through_the_stdio_relay() {
    let tmp = tempfile::tempdir().unwrap();
    let server = Server::start(&tmp.path().join("data"));
    let prepared = prepare(&server, &tmp.path().join("ws"), 1);
    let report = run_client(&prepared, 1, &["--stdio", bin(), "--mode", "legacy"]);
    assert_eq!(report["ok"], true, "{report}");
}

#[test]
fn malformed_traffic_gets_errors_and_never_stops_the_server() {
    let tmp = tempfile::tempdir().unwrap();
    let server = Server::start(&tmp.path().join("data"));
    let prepared = prepare(&server, &tmp.path().join("ws"), 2);
    let script = repo_root().join("tests/mcp/fuzz_endpoint.py");
    let out = Command::new(python())
        .arg(script)
        .args(["--url", prepared["mcp_url"].as_str().unwrap(), "--token", &token(&prepared)])
        .args(["--health", &format!("{}/api/health", server.url)])
        .output()
        .expect("run the fuzz client");
    assert!(
        out.status.success(),
        "fuzz client failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn a_killed_server_leaves_its_open_episode_invalid_with_a_reason_on_restart_and_the_store_agrees() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let mut server = Server::start(&data);
    // One episode runs to its end before the kill...
    let ended = prepare(&server, &tmp.path().join("ws-ended"), 1);
    let ended_id = ended["episode_id"].as_str().unwrap().to_owned();
    assert_eq!(run_client(&ended, 1, &[])["ok"], true);
    let ended_run = PathBuf::from(ended["run_dir"].as_str().unwrap());
    let ended_result: Value =
        serde_json::from_str(&std::fs::read_to_string(ended_run.join("result.json")).unwrap()).unwrap();
    let expected_outcome = match (ended_result["status"].as_str(), ended_result["success"].as_bool()) {
        (Some("finished"), Some(true)) => "SUCCESS",
        (Some("finished"), _) => "FAIL",
        _ => "INVALID",
    };
    let (status, row) = http_get_json(&format!("{}/api/episodes/{ended_id}", server.url));
    assert_eq!(status, 200, "{row}");
    assert_eq!(row["outcome"], expected_outcome, "the store has the end before any restart: {row}");
    assert!(row["started_at"].is_string() && row["finished_at"].is_string(), "{row}");
    // ...one is left open.
    let prepared = prepare(&server, &tmp.path().join("ws"), 3);
    let open_id = prepared["episode_id"].as_str().unwrap().to_owned();
    let (_, row) = http_get_json(&format!("{}/api/episodes/{open_id}", server.url));
    assert_eq!((row["outcome"].clone(), row["level"].clone(), row["seed"].clone()), (Value::Null, 3.into(), 100.into()));
    let run = PathBuf::from(prepared["run_dir"].as_str().unwrap());
    server.kill(); // SIGKILL: no chance to write anything
    // Whether or not the background worker had finished the ended episode's video, it is as if it had not: the
    // restarted server rebuilds it from the state record.
    for name in ["continuous_video.mp4", "continuous_video.mp4.partial"] {
        let _ = std::fs::remove_file(ended_run.join(name));
    }
    assert!(!run.join("result.json").exists());
    assert!(data.join("episodes.sqlite").is_file());
    let restarted = Server::start(&data);
    let result: Value = serde_json::from_str(&std::fs::read_to_string(run.join("result.json")).unwrap()).unwrap();
    assert_eq!(result["status"], "aborted");
    assert!(result["reason"].as_str().unwrap().starts_with("server_stopped_before_finish"));
    let (status, list) = http_get_json(&format!("{}/api/episodes", restarted.url));
    assert_eq!(status, 200);
    let rows = list["episodes"].as_array().expect("episodes array");
    assert_eq!(rows.len(), 2, "{list}");
    let row_of = |id: &str| rows.iter().find(|r| r["id"] == id).unwrap_or_else(|| panic!("no row {id}: {list}")).clone();
    let open_row = row_of(&open_id);
    assert_eq!(open_row["outcome"], "INVALID");
    assert_eq!(open_row["reason"], result["reason"], "the store gives the run directory's reason");
    assert_eq!(open_row["task_ref"], TASK);
    let ended_row = row_of(&ended_id);
    assert_eq!(ended_row["outcome"], expected_outcome, "the finished row survived the kill");
    assert_eq!(ended_row["reason"], ended_result["reason"]);
    let text = list.to_string();
    for secret in [token(&prepared), token(&ended), data.display().to_string()] {
        assert!(!text.contains(&secret), "the episode list leaks {secret}");
    }
    let (status, _) = http_get_json(&format!("{}/api/episodes/ep-nonexistent", restarted.url));
    assert_eq!(status, 404);

    // The review API says how far the rebuilt video is until it is there; the never-started episode has none.
    let (_, open_video) = http_get_json(&format!("{}/api/episodes/{open_id}/review?part=video", restarted.url));
    assert_eq!((open_video["video"].clone(), open_video["video_status"].clone()), (Value::Bool(false), Value::Null), "{open_video}");
    let started = std::time::Instant::now();
    let mut states = Vec::new();
    loop {
        let (status, v) = http_get_json(&format!("{}/api/episodes/{ended_id}/review?part=video", restarted.url));
        assert_eq!(status, 200, "{v}");
        let state = v["video_status"]["state"].as_str().unwrap_or_default().to_owned();
        assert!(["queued", "rendering", "ready"].contains(&state.as_str()), "{v}");
        assert!(v["video_status"]["percent"].as_u64().is_some_and(|p| p <= 100), "{v}");
        if states.last() != Some(&state) {
            states.push(state.clone());
        }
        if v["video"] == true {
            assert_eq!(state, "ready");
            break;
        }
        assert!(started.elapsed() < std::time::Duration::from_secs(300), "the video was not rebuilt: {states:?}");
        std::thread::sleep(std::time::Duration::from_millis(200));
    }
    assert!(std::fs::metadata(ended_run.join("state_record.bin")).unwrap().len() > 32, "frames were recorded");
    assert!(std::fs::metadata(ended_run.join("continuous_video.mp4")).unwrap().len() > 1000, "{states:?}");
}

#[test]
fn bench_mcp_prints_latency_percentiles_and_overhead_for_each_concurrency() {
    let tmp = tempfile::tempdir().unwrap();
    let out = Command::new(bin())
        .args(["bench", "mcp", "--json", "--episodes", "1,2", "--calls", "2", "--actions", "5", "--data"])
        .arg(tmp.path().join("data"))
        .output()
        .expect("run bench mcp");
    assert!(out.status.success(), "bench mcp failed: {}", String::from_utf8_lossy(&out.stderr));
    let v: Value = serde_json::from_slice(&out.stdout).expect("bench mcp --json prints one JSON object");
    assert_eq!((v["actions_per_call"].clone(), v["calls_per_episode"].clone()), (5.into(), 2.into()));
    let reference = v["sim_plus_render"]["sim_plus_render_ms_p50"].as_f64().expect("baseline p50");
    assert!(reference > 0.0);
    assert!(v["sim_plus_render"]["video_render_encode_ms_per_call"].as_f64().expect("video cost") > 0.0);
    let runs = v["mcp"].as_array().expect("mcp runs");
    assert_eq!(runs.len(), 2);
    for (run, n) in runs.iter().zip([1u64, 2]) {
        assert_eq!(run["concurrent_episodes"], n);
        assert_eq!(run["calls"], 2 * n, "every timed call of every episode is counted");
        let (p50, p95) = (run["mcp_p50_ms"].as_f64().unwrap(), run["mcp_p95_ms"].as_f64().unwrap());
        assert!(0.0 < p50 && p50 <= p95, "{run}");
        let ratio = run["overhead_ratio"].as_f64().unwrap();
        assert!((ratio - p50 / reference).abs() < 1e-9, "{run}");
        // The peer at the same concurrency: n worlds side by side without the server, every call timed.
        let (peer50, peer95) =
            (run["peer_same_concurrency_p50_ms"].as_f64().unwrap(), run["peer_same_concurrency_p95_ms"].as_f64().unwrap());
        assert!(0.0 < peer50 && peer50 <= peer95, "{run}");
        let vs_peer = run["overhead_ratio_vs_same_concurrency_peer"].as_f64().unwrap();
        assert!((vs_peer - p50 / peer50).abs() < 1e-9, "{run}");
    }
}
