//! `libero-agent bench review`: what a watcher and a reviewer of an episode wait for (issue 49). An in-process server
//! with the console runs a task's scripted expert at the control rate (`--pace realtime`, 50-action calls, no video)
//! while the bench watches its live view as the page does, counting the frames and the distinct control steps they
//! show per second of motion (one frame per call would be 0.4 a second). The finished episode, which has no video,
//! is then reviewed through the moment route: the first moment (the replay of its action log), uncached moments
//! (one render each) and cached ones.
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use futures_util::StreamExt;
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

use crate::bench_mcp::percentile_ms;
use crate::bench_teleop::{frame_step, open_socket, with_console_server};
use crate::cmd_expert::{McpPort, Pace, Paced};
use libero_episode::Level;
use libero_episode::task::resolve_task;
use libero_episode::world::WorldSpec;
use libero_server::client::{McpClient, prepare_episode};
use libero_server::episodes::PrepareRequest;
use libero_sim::AssetPaths;

/// Arguments of `bench review`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchReviewArgs {
    /// Print only the JSON result.
    #[arg(long)]
    pub json: bool,
    /// Release task whose solving expert is watched and reviewed (T28: 249 actions, about 12 s of motion).
    #[arg(long, default_value = "T28")]
    pub task: String,
    /// Uncached moments rendered after the first (spread over the episode).
    #[arg(long, default_value_t = 20)]
    pub moments: usize,
    /// Data directory of the in-process server (default: a new temporary directory, removed afterwards).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

pub fn run(args: &BenchReviewArgs) -> anyhow::Result<()> {
    if args.moments == 0 || args.moments > 500 {
        bail!("--moments must be 1 to 500");
    }
    with_console_server("review", args.data.as_ref(), args.json, |url| bench(url, args))
}

fn bench(base_url: &str, args: &BenchReviewArgs) -> anyhow::Result<Value> {
    let paths = AssetPaths::discover().context("assets are missing; run `python3 scripts/setup.py`")?;
    let task = args.task.trim().to_ascii_uppercase();
    let spec = WorldSpec { task: resolve_task(&task, &paths)?, level: Level::L1, seed: 100, init_index: 0, paths };
    let request = PrepareRequest { video: false, max_agent_steps: libero_episode::tools::MAX_AGENT_STEPS_CAP, ..PrepareRequest::new(task.clone()) };
    let prepared = prepare_episode(base_url, &request)?;
    let id = prepared.episode_id.clone();
    let token = prepared.mcp_headers.get("Authorization").context("no token in the server's reply")?.trim_start_matches("Bearer ").to_owned();

    // Watch the live view while the expert runs at the control rate.
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let frames: Arc<Mutex<Vec<(Instant, Option<u64>)>>> = Arc::default();
    let socket = runtime.block_on(open_socket(base_url, &format!("/ws/episodes/{id}")))?;
    let reader = {
        let frames = frames.clone();
        runtime.spawn(async move {
            let mut socket = socket;
            while let Some(Ok(message)) = socket.next().await {
                if let Message::Binary(bytes) = message
                    && let Some(step) = frame_step(&bytes)
                    && let Ok(mut f) = frames.lock()
                {
                    f.push((Instant::now(), step));
                }
            }
        })
    };
    let mut port = McpPort(McpClient::connect_with_token(&prepared.mcp_url, &token, "libero-agent-bench-review")?);
    let started = Instant::now();
    let run = libero_episode::expert_run::run_expert(&mut Paced::new(&mut port, Pace::Realtime), &spec, &task, "solve", 2000, |_| {})
        .with_context(|| format!("the {task} expert"))?;
    let motion_s = started.elapsed().as_secs_f64();
    // The playback trails the simulation by at most a few seconds: let it finish.
    std::thread::sleep(Duration::from_secs(4));
    reader.abort();
    let frames = frames.lock().map(|f| f.clone()).unwrap_or_default();
    let live = live_summary(&frames, started, motion_s, run.actions);

    // Review the finished episode (no video) through its moments.
    let steps = run.actions;
    let timed = |step: u64| -> anyhow::Result<f64> {
        let t0 = Instant::now();
        let (status, bytes) = get_bytes(base_url, &format!("/api/episodes/{id}/moment?step={step}"))?;
        if status != 200 || !bytes.starts_with(&[0xFF, 0xD8]) {
            bail!("moment {step}: HTTP {status}: {}", String::from_utf8_lossy(&bytes[..bytes.len().min(300)]));
        }
        Ok(t0.elapsed().as_secs_f64() * 1000.0)
    };
    let first_ms = timed(steps / 3)?;
    let spread: Vec<u64> = (0..args.moments as u64).map(|k| (k * 7919 + 1) % (steps + 1)).filter(|&s| s != steps / 3).collect();
    let mut uncached = spread.iter().map(|&s| timed(s)).collect::<anyhow::Result<Vec<f64>>>()?;
    let mut cached = spread.iter().map(|&s| timed(s)).collect::<anyhow::Result<Vec<f64>>>()?;
    Ok(json!({
        "bench": "review",
        "task": task,
        "episode_id": id,
        "actions": run.actions,
        "osc_sequence_calls": run.osc_calls,
        "live": live,
        "moments": {
            "first_ms": first_ms,
            "uncached_ms": {"p50": percentile_ms(&mut uncached, 50.0), "p95": percentile_ms(&mut uncached, 95.0), "n": uncached.len()},
            "cached_ms": {"p50": percentile_ms(&mut cached, 50.0), "n": cached.len()},
        },
        "build": if cfg!(debug_assertions) { "debug" } else { "release" },
    }))
}

/// Frames the watcher got during the expert's motion: how many, of how many distinct control steps, per second.
fn live_summary(frames: &[(Instant, Option<u64>)], started: Instant, motion_s: f64, actions: u64) -> Value {
    let moving: Vec<(f64, u64)> = frames.iter().filter_map(|&(at, step)| Some((at.duration_since(started).as_secs_f64(), step?))).filter(|&(_, s)| s > 0).collect();
    let mut distinct: Vec<u64> = moving.iter().map(|&(_, s)| s).collect();
    distinct.dedup();
    let (first_s, last_s) = (moving.first().map_or(0.0, |f| f.0), moving.last().map_or(0.0, |f| f.0));
    let shown_s = (last_s - first_s).max(1e-9);
    let mut gaps_ms: Vec<f64> = moving.windows(2).map(|w| (w[1].0 - w[0].0) * 1000.0).collect();
    json!({
        "motion_s": motion_s,
        "calls_per_s": (actions as f64 / 50.0).ceil() / motion_s,
        "frames": moving.len(),
        "distinct_control_steps": distinct.len(),
        "distinct_frames_per_s": distinct.len() as f64 / shown_s,
        "shown_over_s": shown_s,
        "last_step_shown": distinct.last(),
        "frame_gap_ms": {"p50": percentile_ms(&mut gaps_ms, 50.0), "p95": percentile_ms(&mut gaps_ms, 95.0)},
    })
}

/// `GET` with the operator's credential: (status, body).
fn get_bytes(base_url: &str, path: &str) -> anyhow::Result<(u16, Vec<u8>)> {
    let response = libero_server::client::operator_request("GET", base_url, path, b"", Duration::from_secs(300))?;
    Ok((response.status, response.body))
}
