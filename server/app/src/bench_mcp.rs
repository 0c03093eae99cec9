//! `libero-agent bench mcp`: latency of `osc_sequence` (50 micro-actions per call) over real MCP JSON-RPC
//! on streamable HTTP, with 1, 4 and 8 episodes driven concurrently against an in-process server, beside
//! what the same call costs without the server: the 50 simulator steps plus one observation render (both
//! cameras, same scene and level) on this machine, in the same run. `overhead_ratio = mcp_p50 / (sim +
//! render)_p50` says what the protocol, publishing and records (the private video's state record included)
//! add; the video's own cost per call (render + encode from the record, on the background worker) is measured
//! beside it, and the same steps with the state record on (`sim_steps_with_state_record_ms`).
//!
//! With n episodes the n clients call back to back, so the episodes share this machine's cores and no server
//! could answer faster than n worlds stepping and rendering side by side. That peer is measured too, in the
//! same run: n threads, each with its own world, doing the same calls without the server
//! (`peer_same_concurrency_p50_ms`, `overhead_ratio_vs_same_concurrency_peer`).
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use libero_episode::World;
use libero_episode::task::resolve_task;
use libero_episode::state_record::StateRecordReader;
use libero_episode::video_queue::{VideoProgress, VideoQueue};
use libero_episode::world::{LiberoWorld, WorldSpec, head_wrist_cameras};
use libero_episode::{Level, MicroAction};
use libero_render::Renderer;
use serde_json::json;

use libero_episode::tools::MAX_AGENT_STEPS_CAP;

use libero_server::client::{InProcessServer, McpClient, prepare_episode};
use libero_server::episodes::PrepareRequest;

pub const DEFAULT_TASK: &str = "libero_90/KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet";

/// Arguments of `bench mcp`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchMcpArgs {
    /// Print only the JSON result.
    #[arg(long)]
    pub json: bool,
    #[arg(long, default_value = DEFAULT_TASK)]
    pub task: String,
    #[arg(long, default_value_t = 3)]
    pub level: u8,
    /// Concurrent episode counts to measure, one run each.
    #[arg(long, value_delimiter = ',', default_values_t = [1usize, 4, 8])]
    pub episodes: Vec<usize>,
    /// Timed `osc_sequence` calls per episode.
    #[arg(long, default_value_t = 10)]
    pub calls: usize,
    /// Micro-actions per call.
    #[arg(long, default_value_t = 50)]
    pub actions: usize,
    /// Data directory of the in-process server (default: a new directory under the system temp dir,
    /// removed afterwards).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

/// The micro-action every timed call repeats: a gentle motion that keeps the arm in its workspace.
fn bench_actions(n: usize, call: usize) -> Vec<MicroAction> {
    let sign = if call % 2 == 0 { 1.0 } else { -1.0 };
    vec![[0.1 * sign, 0.05 * sign, 0.0, 0.0, 0.0, 0.02 * sign, -1.0]; n]
}

/// Nearest-rank percentile of `ms` (sorted in place).
pub fn percentile_ms(ms: &mut [f64], p: f64) -> f64 {
    if ms.is_empty() {
        return f64::NAN;
    }
    ms.sort_by(f64::total_cmp);
    let rank = ((p / 100.0) * ms.len() as f64).ceil() as usize;
    ms[rank.clamp(1, ms.len()) - 1]
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// Prepares one episode on the server; returns (mcp_url, token).
fn prepare(base: &str, task: &str, level: u8, seed: u64) -> anyhow::Result<(String, String)> {
    let req = PrepareRequest { level, seed, max_agent_steps: MAX_AGENT_STEPS_CAP, ..PrepareRequest::new(task) };
    let p = prepare_episode(base, &req)?;
    let token = p.mcp_headers.get("Authorization").context("no token")?;
    Ok((p.mcp_url, token.trim_start_matches("Bearer ").to_owned()))
}

/// Drives `episodes` episodes concurrently (one client thread each) and returns every timed call's latency.
fn run_concurrent(base: &str, args: &BenchMcpArgs, episodes: usize) -> anyhow::Result<Vec<f64>> {
    let mut endpoints = Vec::new();
    for i in 0..episodes {
        endpoints.push(prepare(base, &args.task, args.level, 100 + i as u64)?);
    }
    let (calls, actions) = (args.calls, args.actions);
    let barrier = std::sync::Arc::new(std::sync::Barrier::new(episodes));
    let threads: Vec<_> = endpoints
        .into_iter()
        .map(|(url, token)| {
            let barrier = barrier.clone();
            std::thread::spawn(move || -> anyhow::Result<Vec<f64>> {
                let mut client = McpClient::connect_with_token(&url, &token, "libero-agent-bench")?;
                client.call_tool("start_episode", json!({}))?;
                barrier.wait(); // all episodes step at the same time
                let mut latencies = Vec::with_capacity(calls);
                for call in 0..calls {
                    let a = bench_actions(actions, call);
                    let t = Instant::now();
                    client.call_tool("osc_sequence", json!({"actions": a}))?;
                    latencies.push(ms(t.elapsed()));
                }
                // Untimed: ends the episode (whatever the verdict) so it releases its world and video.
                let _ = client.post("tools/call", json!({"name": "finish_episode", "arguments": {}}));
                Ok(latencies)
            })
        })
        .collect();
    let mut all = Vec::new();
    for t in threads {
        let lat = t.join().map_err(|_| anyhow::anyhow!("a client thread panicked"))??;
        all.extend(lat);
    }
    Ok(all)
}

/// The world a peer thread drives: the bench's task and level, one seed per thread (as the served episodes).
fn peer_world(args: &BenchMcpArgs, renderer: &Renderer, seed: u64) -> anyhow::Result<LiberoWorld> {
    let paths = libero_sim::AssetPaths::discover()?;
    let level = Level::from_number(args.level).with_context(|| format!("level must be 1, 2 or 3 (got {})", args.level))?;
    let spec = WorldSpec { task: resolve_task(&args.task, &paths)?, level, seed, init_index: 0, paths };
    let mut world = LiberoWorld::new(&spec, renderer.clone())?;
    world.start()?;
    world.frame(0)?; // first render pays pipeline/texture setup, as the server's start_episode does
    Ok(world)
}

/// The timed calls without the server: per call (sim steps, render, both) in ms.
fn peer_calls(world: &mut LiberoWorld, args: &BenchMcpArgs) -> anyhow::Result<Vec<(f64, f64, f64)>> {
    let mut out = Vec::with_capacity(args.calls);
    for call in 0..args.calls.max(1) {
        let a = bench_actions(args.actions, call);
        let t = Instant::now();
        for action in &a {
            world.step(action)?;
        }
        let stepped = t.elapsed();
        world.frame(call as u64 + 1)?;
        let all = t.elapsed();
        out.push((ms(stepped), ms(all - stepped), ms(all)));
    }
    Ok(out)
}

/// `episodes` worlds doing the timed calls side by side, one thread each, starting together: what n
/// concurrent episodes cost on this machine with no server at all. Returns every call's total latency.
fn concurrent_peer(args: &BenchMcpArgs, renderer: &Renderer, episodes: usize) -> anyhow::Result<Vec<f64>> {
    let barrier = std::sync::Barrier::new(episodes);
    std::thread::scope(|scope| {
        let threads: Vec<_> = (0..episodes)
            .map(|i| {
                let barrier = &barrier;
                scope.spawn(move || -> anyhow::Result<Vec<f64>> {
                    // Every thread reaches the barrier, even when its world failed, so none waits forever.
                    let world = peer_world(args, renderer, 100 + i as u64);
                    barrier.wait();
                    Ok(peer_calls(&mut world?, args)?.into_iter().map(|(_, _, total)| total).collect())
                })
            })
            .collect();
        let mut all = Vec::new();
        for t in threads {
            all.extend(t.join().map_err(|_| anyhow::anyhow!("a peer thread panicked"))??);
        }
        Ok(all)
    })
}

/// The same calls without the server: 50 simulator steps, then one observation frame (both cameras).
/// The in-process peer's figures (no MCP, no server): what each served call is compared with.
#[derive(serde::Serialize)]
struct Baseline {
    calls: usize,
    sim_steps_with_state_record_ms: f64,
    video_render_encode_ms_per_call: f64,
    sim_steps_ms_p50: f64,
    render_ms_p50: f64,
    sim_plus_render_ms_p50: f64,
    sim_plus_render_ms_p95: f64,
}

fn baseline(args: &BenchMcpArgs, renderer: &Renderer) -> anyhow::Result<Baseline> {
    let mut world = peer_world(args, renderer, 100)?;
    let (mut sim_ms, mut render_ms, mut total_ms) = (Vec::new(), Vec::new(), Vec::new());
    for (sim, render, total) in peer_calls(&mut world, args)? {
        sim_ms.push(sim);
        render_ms.push(render);
        total_ms.push(total);
    }
    let (record_ms, video_ms) = video_cost_ms(&mut world, args.actions)?;
    Ok(Baseline {
        calls: total_ms.len(),
        sim_steps_with_state_record_ms: record_ms,
        video_render_encode_ms_per_call: video_ms,
        sim_steps_ms_p50: percentile_ms(&mut sim_ms, 50.0),
        render_ms_p50: percentile_ms(&mut render_ms, 50.0),
        sim_plus_render_ms_p50: percentile_ms(&mut total_ms.clone(), 50.0),
        sim_plus_render_ms_p95: percentile_ms(&mut total_ms, 95.0),
    })
}

/// What the private video costs per call off the reply path: `actions` control steps recorded as state by
/// the episode thread (timed on its own: what a reply carries), then rendered from the record by the
/// background worker's function (both cameras, side by side, H.264, MP4), timed to the finished file.
fn video_cost_ms(world: &mut LiberoWorld, actions: usize) -> anyhow::Result<(f64, f64)> {
    let dir = std::env::temp_dir().join(format!("libero-agent-bench-video-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let (record, video) = (dir.join("state_record.bin"), dir.join("video.mp4"));
    let queue = VideoQueue::start(head_wrist_cameras())?;
    let t = Instant::now();
    world.record_video(&video, &record, queue.clone(), None)?;
    for action in bench_actions(actions, 0) {
        world.step(&action)?;
    }
    let record_ms = ms(t.elapsed());
    let t = Instant::now();
    world.end_video();
    let state = queue.wait(&video, Duration::from_secs(600));
    let render_ms = ms(t.elapsed());
    let frames = StateRecordReader::open(&record).map(|r| r.frames()).unwrap_or(0);
    let _ = std::fs::remove_dir_all(&dir);
    match state {
        Some(VideoProgress::Ready) if frames == actions as u64 => Ok((record_ms, render_ms)),
        other => bail!("the video benchmark ended {other:?} with {frames} recorded frames, expected {actions}"),
    }
}

pub fn run(args: &BenchMcpArgs) -> anyhow::Result<()> {
    if args.calls == 0 || args.actions == 0 || args.actions > 50 || args.episodes.iter().any(|&n| n == 0) {
        bail!("--calls and --episodes must be positive and --actions between 1 and 50");
    }
    let (data, remove_data) = match &args.data {
        Some(d) => (d.clone(), false),
        None => (std::env::temp_dir().join(format!("libero-agent-bench-mcp-{}", std::process::id())), true),
    };
    let renderer = Renderer::new().context("cannot open a GPU for rendering")?;
    let base = baseline(args, &renderer)?;
    let reference_ms = base.sim_plus_render_ms_p50;
    let cores = std::thread::available_parallelism().map_or(1, std::num::NonZeroUsize::get);
    let server = InProcessServer::start(data.clone(), "bench_finished_before_finish")?;
    let url = server.url.clone();
    let mut runs = Vec::new();
    let mut failure = None;
    for &n in &args.episodes {
        // The peer runs before the served episodes of the same count, never beside them.
        let measured = concurrent_peer(args, &renderer, n)
            .context("the peer without the server")
            .and_then(|peer| Ok((peer, run_concurrent(&url, args, n)?)));
        match measured {
            Ok((mut peer, mut lat)) => {
                let p50 = percentile_ms(&mut lat, 50.0);
                let p95 = percentile_ms(&mut lat, 95.0);
                let peer_p50 = percentile_ms(&mut peer, 50.0);
                // Clients call back to back, so n episodes share this machine's cores: even with no overhead at
                // all a call could not come back faster than n / cores of the one-episode figure.
                let saturation_floor = (n as f64 / cores as f64).max(1.0);
                runs.push(json!({"concurrent_episodes": n, "calls": lat.len(), "mcp_p50_ms": p50, "mcp_p95_ms": p95,
                    "overhead_ratio": p50 / reference_ms, "cpu_saturation_floor_ratio": saturation_floor,
                    "overhead_over_floor": p50 / reference_ms / saturation_floor,
                    "peer_same_concurrency_p50_ms": peer_p50,
                    "peer_same_concurrency_p95_ms": percentile_ms(&mut peer, 95.0),
                    "overhead_ratio_vs_same_concurrency_peer": p50 / peer_p50}));
                if !args.json {
                    eprintln!(
                        "{n} concurrent episode(s): p50 {p50:.1} ms, p95 {p95:.1} ms, {:.2}x sim+render of one episode, \
                         {:.2}x {n} worlds side by side without the server ({peer_p50:.1} ms)",
                        p50 / reference_ms,
                        p50 / peer_p50
                    );
                }
            }
            Err(e) => {
                failure = Some(e.context(format!("{n} concurrent episodes")));
                break;
            }
        }
    }
    drop(renderer);
    // The served episodes' videos are rendering in the background; they are not what is measured here.
    let served = server.stop_now();
    if remove_data {
        let _ = std::fs::remove_dir_all(&data);
    }
    if let Some(e) = failure {
        return Err(e);
    }
    served?;
    let out = json!({
        "benchmark": "mcp_osc_sequence_latency",
        "build": if cfg!(debug_assertions) { "debug" } else { "release" },
        "task": args.task,
        "level": args.level,
        "actions_per_call": args.actions,
        "calls_per_episode": args.calls,
        "video": "every served episode records its state; continuous_video.mp4 is rendered from it in the background",
        "cpu_cores": cores,
        "sim_plus_render": base,
        "mcp": runs,
    });
    println!("{}", if args.json { out.to_string() } else { serde_json::to_string_pretty(&out)? });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_use_the_nearest_rank() {
        let mut v = vec![5.0, 1.0, 4.0, 2.0, 3.0];
        assert_eq!(percentile_ms(&mut v, 50.0), 3.0);
        assert_eq!(percentile_ms(&mut v, 95.0), 5.0);
        assert_eq!(percentile_ms(&mut [7.0], 95.0), 7.0);
        assert!(percentile_ms(&mut [], 50.0).is_nan());
    }
}
