//! `libero-agent bench mcp`: latency of `osc_sequence` (50 micro-actions per call) over real MCP JSON-RPC
//! on streamable HTTP, with 1, 4 and 8 episodes driven concurrently against an in-process server, beside
//! what the same call costs without the server: the 50 simulator steps plus one observation render (both
//! cameras, same scene and level) on this machine, in the same run. `overhead_ratio = mcp_p50 / (sim +
//! render)_p50` says what the protocol, publishing, records and the private video add; the video's own
//! cost per call (render + encode, on the recorder thread) is measured beside it.
use std::path::PathBuf;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use libero_episode::World;
use libero_episode::task::resolve_task;
use libero_episode::video::{VideoCameras, VideoRecorder};
use libero_episode::world::{HEAD_CAMERA, LiberoWorld, RESOLUTION_PX, WRIST_CAMERA, WorldSpec};
use libero_episode::{Level, MicroAction};
use libero_render::{FrameState, Renderer};
use serde_json::{Value, json};

use crate::cmd_mcp_stdio::messages_of;
use crate::serve::http_client::{HttpUrl, request};
use crate::serve::{ServeArgs, serve_until};

pub const DEFAULT_TASK: &str = "libero_90/KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet";
/// Per-request timeout of the benchmark's client (a debug build under load can take seconds per call).
const CALL_TIMEOUT: Duration = Duration::from_secs(600);

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

/// One MCP client session over streamable HTTP (what the Python SDK does in legacy mode).
struct McpClient {
    url: HttpUrl,
    headers: Vec<(String, String)>,
    next_id: u64,
}

impl McpClient {
    fn connect(mcp_url: &str, token: &str) -> anyhow::Result<Self> {
        let headers = vec![
            ("Authorization".to_owned(), format!("Bearer {token}")),
            ("Content-Type".to_owned(), "application/json".to_owned()),
            ("Accept".to_owned(), "application/json, text/event-stream".to_owned()),
        ];
        let mut c = Self { url: HttpUrl::parse(mcp_url)?, headers, next_id: 1 };
        let init = json!({"protocolVersion": "2025-06-18", "capabilities": {},
            "clientInfo": {"name": "libero-agent-bench", "version": env!("CARGO_PKG_VERSION")}});
        let (reply, session) = c.post("initialize", init)?;
        if reply.get("result").is_none() {
            bail!("initialize failed: {reply}");
        }
        if let Some(s) = session {
            c.headers.push(("Mcp-Session-Id".to_owned(), s));
        }
        if let Some(v) = reply.pointer("/result/protocolVersion").and_then(Value::as_str) {
            c.headers.push(("Mcp-Protocol-Version".to_owned(), v.to_owned()));
        }
        let note = json!({"jsonrpc": "2.0", "method": "notifications/initialized"});
        let resp = request("POST", &c.url, &c.headers, note.to_string().as_bytes(), CALL_TIMEOUT)?;
        if resp.status >= 400 {
            bail!("notifications/initialized: HTTP {}", resp.status);
        }
        Ok(c)
    }

    fn post(&mut self, method: &str, params: Value) -> anyhow::Result<(Value, Option<String>)> {
        let id = self.next_id;
        self.next_id += 1;
        let body = json!({"jsonrpc": "2.0", "id": id, "method": method, "params": params});
        let resp = request("POST", &self.url, &self.headers, body.to_string().as_bytes(), CALL_TIMEOUT)?;
        if resp.status >= 400 {
            bail!("{method}: HTTP {}: {}", resp.status, String::from_utf8_lossy(&resp.body));
        }
        let session = resp.header("mcp-session-id").map(str::to_owned);
        let reply = messages_of(&resp)
            .into_iter()
            .find(|m| m.get("id") == Some(&json!(id)))
            .with_context(|| format!("{method}: no JSON-RPC reply with id {id}"))?;
        Ok((reply, session))
    }

    /// `tools/call`; the tool's payload (`structuredContent`), which must say `ok: true`.
    fn call_tool(&mut self, name: &str, arguments: Value) -> anyhow::Result<Value> {
        let (reply, _) = self.post("tools/call", json!({"name": name, "arguments": arguments}))?;
        let payload = reply.pointer("/result/structuredContent").cloned().with_context(|| format!("{name}: {reply}"))?;
        if payload["ok"] != true {
            bail!("{name} failed: {payload}");
        }
        Ok(payload)
    }
}

/// Prepares one episode on the server; returns (mcp_url, token).
fn prepare(base: &str, task: &str, level: u8, seed: u64) -> anyhow::Result<(String, String)> {
    let url = HttpUrl::parse(&format!("{base}/api/episodes"))?;
    let body = json!({"task": task, "level": level, "seed": seed});
    let headers = [("Content-Type".to_owned(), "application/json".to_owned())];
    let resp = request("POST", &url, &headers, body.to_string().as_bytes(), CALL_TIMEOUT)?;
    let v: Value = serde_json::from_slice(&resp.body).context("prepare reply is not JSON")?;
    if resp.status != 201 {
        bail!("prepare: HTTP {}: {v}", resp.status);
    }
    let token = v.pointer("/mcp_headers/Authorization").and_then(Value::as_str).context("no token")?;
    let mcp_url = v["mcp_url"].as_str().context("no mcp_url")?;
    Ok((mcp_url.to_owned(), token.trim_start_matches("Bearer ").to_owned()))
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
                let mut client = McpClient::connect(&url, &token)?;
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

/// The same calls without the server: 50 simulator steps, then one observation frame (both cameras).
fn baseline(args: &BenchMcpArgs, renderer: &Renderer) -> anyhow::Result<Value> {
    let paths = libero_sim::AssetPaths::discover()?;
    let level = Level::from_number(args.level).with_context(|| format!("level must be 1, 2 or 3 (got {})", args.level))?;
    let spec = WorldSpec { task: resolve_task(&args.task, &paths)?, level, seed: 100, init_index: 0, paths };
    let mut world = LiberoWorld::new(&spec, renderer.clone())?;
    world.start()?;
    world.frame(0)?; // first render pays pipeline/texture setup, as the server's start_episode does
    let (mut sim_ms, mut render_ms, mut total_ms) = (Vec::new(), Vec::new(), Vec::new());
    for call in 0..args.calls.max(1) {
        let a = bench_actions(args.actions, call);
        let t = Instant::now();
        for action in &a {
            world.step(action)?;
        }
        let stepped = t.elapsed();
        world.frame(call as u64 + 1)?;
        let all = t.elapsed();
        sim_ms.push(ms(stepped));
        render_ms.push(ms(all - stepped));
        total_ms.push(ms(all));
    }
    let video_ms = video_cost_ms(&mut world, renderer, args.actions)?;
    Ok(json!({
        "calls": total_ms.len(),
        "video_render_encode_ms_per_call": video_ms,
        "sim_steps_ms_p50": percentile_ms(&mut sim_ms, 50.0),
        "render_ms_p50": percentile_ms(&mut render_ms, 50.0),
        "sim_plus_render_ms_p50": percentile_ms(&mut total_ms.clone(), 50.0),
        "sim_plus_render_ms_p95": percentile_ms(&mut total_ms, 95.0),
    }))
}

/// What the private video costs per call off the reply path: `actions` frames (both cameras rendered,
/// side by side, H.264, MP4) through the recorder, timed from the first frame to the finished file.
fn video_cost_ms(world: &mut LiberoWorld, renderer: &Renderer, actions: usize) -> anyhow::Result<f64> {
    let mut states = Vec::with_capacity(actions);
    for action in bench_actions(actions, 0) {
        world.step(&action)?;
        let sim = world.simulation();
        states.push(FrameState::from_mujoco(sim.model(), sim.data()));
    }
    let dir = std::env::temp_dir().join(format!("libero-agent-bench-video-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let model = renderer.prepare_model(world.simulation().model())?;
    let cameras = VideoCameras { head: HEAD_CAMERA.into(), wrist: WRIST_CAMERA.into(), size_px: RESOLUTION_PX };
    let t = Instant::now();
    let mut recorder = VideoRecorder::spawn(&dir.join("video.mp4"), renderer.clone(), model, cameras)?;
    for s in states {
        recorder.record(s);
    }
    let summary = recorder.finish()?;
    let elapsed = ms(t.elapsed());
    let _ = std::fs::remove_dir_all(&dir);
    match summary {
        Some(v) if v.frames == actions as u64 => Ok(elapsed),
        other => bail!("the video benchmark wrote {other:?}, expected {actions} frames"),
    }
}

/// Starts the server on a free loopback port in a runtime of its own; returns its URL and a stopper.
fn start_server(data: PathBuf) -> anyhow::Result<(String, mpsc::Sender<()>, std::thread::JoinHandle<anyhow::Result<()>>)> {
    let (url_tx, url_rx) = mpsc::channel::<String>();
    let (stop_tx, stop_rx) = mpsc::channel::<()>();
    let thread = std::thread::spawn(move || -> anyhow::Result<()> {
        let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
        runtime.block_on(async move {
            let args = ServeArgs { addr: "127.0.0.1:0".parse()?, data: Some(data), operator_token_file: None };
            let stop = async move {
                let _ = tokio::task::spawn_blocking(move || stop_rx.recv()).await;
                "bench_finished_before_finish".to_owned()
            };
            let listening = move |v: Value| {
                let _ = url_tx.send(v["url"].as_str().unwrap_or_default().to_owned());
            };
            serve_until(args, listening, stop).await
        })
    });
    match url_rx.recv() {
        Ok(url) if !url.is_empty() => Ok((url, stop_tx, thread)),
        _ => match thread.join() {
            Ok(Err(e)) => Err(e.context("the server did not start")),
            _ => bail!("the server did not start"),
        },
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
    drop(renderer);
    let reference_ms = base["sim_plus_render_ms_p50"].as_f64().unwrap_or(f64::NAN);
    let (url, stop, server) = start_server(data.clone())?;
    let mut runs = Vec::new();
    let mut failure = None;
    for &n in &args.episodes {
        match run_concurrent(&url, args, n) {
            Ok(mut lat) => {
                let p50 = percentile_ms(&mut lat, 50.0);
                let p95 = percentile_ms(&mut lat, 95.0);
                runs.push(json!({"concurrent_episodes": n, "calls": lat.len(), "mcp_p50_ms": p50, "mcp_p95_ms": p95,
                    "overhead_ratio": p50 / reference_ms}));
                if !args.json {
                    eprintln!("{n} concurrent episode(s): p50 {p50:.1} ms, p95 {p95:.1} ms, {:.2}x sim+render", p50 / reference_ms);
                }
            }
            Err(e) => {
                failure = Some(e.context(format!("{n} concurrent episodes")));
                break;
            }
        }
    }
    let _ = stop.send(());
    let served = server.join().map_err(|_| anyhow::anyhow!("the server thread panicked"))?;
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
        "video": "continuous_video.mp4 recorded for every served episode",
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
