//! `libero-agent bench scale`: what open episodes cost a real `libero-agent serve` process, read from outside it
//! (`/proc/<pid>`), as an independent client sees it. The bench starts `serve` (this same binary) on a free
//! loopback port with a fresh data directory and, over the HTTP API and MCP, opens `--episodes` episodes spread
//! round-robin over `--scenes` distinct tasks (the first `--scenes` episodes are each the first of their scene,
//! the rest are additional episodes of a loaded scene). Each episode is prepared, started and given one short
//! `osc_sequence` call, and is left open (not finished). No private video (`video: false`), so an episode costs
//! its world and nothing rendered after it.
//!
//! Measured: resident memory (`VmRSS`) and threads of `serve` idle, with 1 and with N open episodes, and after
//! they are finished; each episode's increment (sampled, settled, before and after it opens); how long an episode
//! takes to open (prepare + `start_episode`), cold (first of its scene) and warm (another episode of a loaded
//! scene); `osc_sequence` p50/p95 (`--actions` per call, level `--level`) on the first episode with only it open
//! and again with all N open (the others idle), with the server's CPU time per call; and the server's CPU use
//! while N episodes sit idle. `sizing` turns the increments into a main-table batch (30 tasks × 3 rollouts) held
//! open at once: its resident memory and episodes per GB.
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use libero_records::records::{STATUS_FINISHED, ToolReply};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::bench_mcp::percentile_ms;
use libero_episode::tools::MAX_AGENT_STEPS_CAP;
use libero_server::client::{McpClient, get_json, prepare_episode};
use libero_server::episodes::PrepareRequest;

/// The scenes in the order they are opened: distinct tasks on distinct scenes (kitchens, a living-room table,
/// a tabletop), each a world of its own.
pub const DEFAULT_SCENES: [&str; 8] = ["T14", "T11", "T16", "T15", "T17", "T12", "T20", "T13"];

/// The main table's batch (docs/commands.md, "Experiments"): T01–T30 at level 3, 3 rollouts each.
const MAIN_TABLE_TASKS: usize = 30;
const MAIN_TABLE_ROLLOUTS: usize = 90;

/// How long `serve` may take to stop once told to (SIGTERM), before it is killed.
const STOP_TIMEOUT: Duration = Duration::from_secs(60);
/// How long finished episodes' threads may take to exit.
const THREAD_EXIT_TIMEOUT: Duration = Duration::from_secs(120);
/// After their threads exit, ended episodes are released within the server's release grace (2 s) and its next
/// one-second tick; the sample after finishing waits this long more.
const RELEASE_WAIT: Duration = Duration::from_secs(4);

/// Arguments of `bench scale`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchScaleArgs {
    /// Print only the JSON result.
    #[arg(long)]
    pub json: bool,
    /// Episodes held open at the same time.
    #[arg(long, default_value_t = 8)]
    pub episodes: usize,
    /// Distinct scenes (tasks) the episodes are spread over, round-robin.
    #[arg(long, default_value_t = 2)]
    pub scenes: usize,
    /// The tasks the scenes are taken from, in order (the first `--scenes` of them are used): a task selection
    /// (docs/commands.md, "Selecting tasks"), e.g. `T14,T11` or `libero_goal`; entries that do not run are left out.
    #[arg(long, value_delimiter = ',', default_values_t = DEFAULT_SCENES.map(str::to_owned))]
    pub tasks: Vec<String>,
    #[arg(long, default_value_t = 3)]
    pub level: u8,
    /// Timed `osc_sequence` calls on the driven episode, with 1 and with N episodes open.
    #[arg(long, default_value_t = 10)]
    pub calls: usize,
    /// Micro-actions per timed call.
    #[arg(long, default_value_t = 50)]
    pub actions: usize,
    /// Milliseconds waited before each memory sample (lets the server's allocator and threads settle); also the
    /// window over which the CPU use of idle open episodes is read.
    #[arg(long, default_value_t = 2000)]
    pub settle_ms: u64,
    /// Data directory of the `serve` process (default: a new directory under the system temp dir, removed
    /// afterwards).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

/// One reading of a process: resident memory, threads and CPU time so far (all threads, user + system).
#[derive(Debug, Clone, Copy, Serialize)]
pub(crate) struct ProcSample {
    pub(crate) rss_mb: f64,
    pub(crate) threads: u64,
    #[serde(skip)]
    cpu_s: f64,
}

impl ProcSample {
    /// Reads `/proc/<pid>/status` (VmRSS, Threads) and `/proc/<pid>/stat` (utime, stime).
    pub(crate) fn of(pid: u32) -> anyhow::Result<Self> {
        let status = std::fs::read_to_string(format!("/proc/{pid}/status")).with_context(|| format!("is process {pid} gone?"))?;
        let field = |name: &str| -> anyhow::Result<u64> {
            let line = status.lines().find_map(|l| l.strip_prefix(name)).with_context(|| format!("no {name} in /proc/{pid}/status"))?;
            line.split_whitespace().next().unwrap_or_default().parse().with_context(|| format!("{name} is not a number: {line}"))
        };
        let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
        // After the command name (which may hold spaces) come field 3 (state) onward; utime and stime are 14 and 15.
        let after_name = stat.rsplit_once(") ").map(|(_, rest)| rest).context("/proc/<pid>/stat has no command name")?;
        let fields: Vec<&str> = after_name.split_whitespace().collect();
        let ticks = |i: usize| fields.get(i).and_then(|f| f.parse::<u64>().ok()).context("short /proc/<pid>/stat");
        // SAFETY: sysconf only reads a system constant.
        let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64;
        Ok(Self { rss_mb: field("VmRSS:")? as f64 / 1024.0, threads: field("Threads:")?, cpu_s: (ticks(11)? + ticks(12)?) as f64 / hz })
    }
}

/// The line `serve` announces itself with (`"event": "listening"`), as far as the bench reads it.
#[derive(Deserialize)]
struct Listening {
    url: Option<String>,
}

/// A `libero-agent serve` child on a free loopback port; stopped (SIGTERM, then killed) on drop.
pub(crate) struct ServeProcess {
    child: Child,
    pub(crate) url: String,
    log: PathBuf,
}

impl ServeProcess {
    fn start(data: &Path) -> anyhow::Result<Self> {
        // Thumbnails rendered ahead at start would be counted as the idle server's memory and CPU.
        Self::start_with(data, &["--thumbnails-ahead".into(), "off".into()])
    }

    /// `serve` with `extra` arguments (`bench thumbnails` asks for the background pass).
    pub(crate) fn start_with(data: &Path, extra: &[String]) -> anyhow::Result<Self> {
        std::fs::create_dir_all(data).with_context(|| format!("creating {}", data.display()))?;
        let log = data.join("serve.log");
        let mut child = Command::new(std::env::current_exe().context("which binary is this?")?)
            .args(["serve", "--addr", "127.0.0.1:0"])
            .args(extra)
            .arg("--data")
            .arg(data)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&log)?)
            .spawn()
            .context("starting libero-agent serve")?;
        let mut line = String::new();
        let read = BufReader::new(child.stdout.take().context("serve's stdout")?).read_line(&mut line);
        let url = serde_json::from_str::<Listening>(&line).ok().and_then(|l| l.url);
        let mut serve = Self { child, url: url.unwrap_or_default(), log };
        if read.is_err() || serve.url.is_empty() {
            bail!("serve did not announce its URL ({line:?}): {}", serve.log_tail());
        }
        // The operator token `serve` keeps in its data directory, for this process's client calls.
        libero_server::credential::use_token_file(&data.join(libero_server::credential::TOKEN_FILE));
        let (status, _) = get_json(&serve.url, "/api/health").map_err(|e| e.context(serve.log_tail()))?;
        if status != 200 {
            let _ = serve.child.kill();
            bail!("serve answered /api/health with HTTP {status}: {}", serve.log_tail());
        }
        Ok(serve)
    }

    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The end of serve's stderr, for error messages.
    fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let tail: Vec<&str> = text.lines().rev().take(20).collect();
        format!("serve's log ends:\n{}", tail.into_iter().rev().collect::<Vec<_>>().join("\n"))
    }

    /// SIGTERM, then waits for it to exit (killed after [`STOP_TIMEOUT`]).
    fn stop(&mut self) -> anyhow::Result<()> {
        if self.child.try_wait()?.is_some() {
            return Ok(());
        }
        // SAFETY: kill only sends a signal to our own child.
        unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGTERM) };
        let t = Instant::now();
        while self.child.try_wait()?.is_none() {
            if t.elapsed() > STOP_TIMEOUT {
                let _ = self.child.kill();
                let _ = self.child.wait();
                bail!("serve did not stop within {} s of SIGTERM", STOP_TIMEOUT.as_secs());
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        Ok(())
    }
}

impl Drop for ServeProcess {
    fn drop(&mut self) {
        let _ = self.stop();
    }
}

/// An episode held open by this bench: its MCP session, its scene and what opening it cost.
struct OpenEpisode {
    client: McpClient,
    record: OpenRecord,
}

/// What opening one episode cost (the output's `per_episode`).
#[derive(Debug, Clone, Serialize)]
struct OpenRecord {
    index: usize,
    task: String,
    episode_id: String,
    first_of_scene: bool,
    prepare_ms: f64,
    start_episode_ms: f64,
    open_ms: f64,
    rss_mb: f64,
    threads: u64,
    rss_increment_mb: f64,
    thread_increment: i64,
}

/// Count, mean, median, min and max of a measure over some episodes.
#[derive(Debug, Clone, Copy, Serialize)]
struct Summary {
    count: usize,
    mean: f64,
    p50: f64,
    min: f64,
    max: f64,
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// The timed calls' actions: a gentle back-and-forth that keeps the arm in its workspace.
fn actions(n: usize, call: usize) -> Value {
    let sign = if call % 2 == 0 { 1.0 } else { -1.0 };
    json!(vec![[0.1 * sign, 0.05 * sign, 0.0, 0.0, 0.0, 0.02 * sign, -1.0]; n])
}

struct Bench<'a> {
    args: &'a BenchScaleArgs,
    serve: ServeProcess,
    settle: Duration,
}

impl Bench<'_> {
    /// The server, once `--settle-ms` have passed.
    fn settled(&self) -> anyhow::Result<ProcSample> {
        std::thread::sleep(self.settle);
        ProcSample::of(self.serve.pid())
    }

    /// Prepares, starts and calls once (5 micro-actions) episode `index` of `task`; samples the server before
    /// (settled) and after (settled).
    fn open(&self, index: usize, task: &str, first_of_scene: bool) -> anyhow::Result<OpenEpisode> {
        let before = self.settled()?;
        let req = PrepareRequest {
            level: self.args.level,
            seed: 100 + index as u64,
            video: false,
            max_agent_steps: MAX_AGENT_STEPS_CAP,
            ..PrepareRequest::new(task)
        };
        let t = Instant::now();
        let prepared = prepare_episode(&self.serve.url, &req).with_context(|| format!("preparing episode {} ({task})", index + 1))?;
        let prepare_ms = ms(t.elapsed());
        let token = prepared.mcp_headers.get("Authorization").context("no MCP token")?.trim_start_matches("Bearer ");
        let mut client = McpClient::connect_with_token(&prepared.mcp_url, token, "libero-agent-bench-scale")?;
        let t = Instant::now();
        client.call_tool("start_episode", json!({}))?;
        let start_ms = ms(t.elapsed());
        client.call_tool("osc_sequence", json!({"actions": actions(5, 0)}))?;
        let after = self.settled()?;
        let record = OpenRecord {
            index,
            task: task.to_owned(),
            episode_id: prepared.episode_id,
            first_of_scene,
            prepare_ms,
            start_episode_ms: start_ms,
            open_ms: prepare_ms + start_ms,
            rss_mb: after.rss_mb,
            threads: after.threads,
            rss_increment_mb: after.rss_mb - before.rss_mb,
            thread_increment: after.threads as i64 - before.threads as i64,
        };
        if !self.args.json {
            eprintln!(
                "episode {} ({task}, {}): open {:.0} ms, +{:.0} MB, +{} threads -> {:.0} MB, {} threads",
                index + 1,
                if first_of_scene { "first of its scene" } else { "scene loaded" },
                prepare_ms + start_ms,
                after.rss_mb - before.rss_mb,
                after.threads as i64 - before.threads as i64,
                after.rss_mb,
                after.threads
            );
        }
        Ok(OpenEpisode { client, record })
    }

    /// `--calls` timed `osc_sequence` calls on `episode`, with `open` episodes open; p50/p95 and the server's CPU
    /// time per call.
    fn drive(&self, episode: &mut OpenEpisode, open: usize) -> anyhow::Result<Value> {
        let cpu0 = ProcSample::of(self.serve.pid())?.cpu_s;
        let mut latencies = Vec::with_capacity(self.args.calls);
        for call in 0..self.args.calls {
            let a = actions(self.args.actions, call);
            let t = Instant::now();
            episode.client.call_tool("osc_sequence", json!({"actions": a}))?;
            latencies.push(ms(t.elapsed()));
        }
        let cpu_ms_per_call = (ProcSample::of(self.serve.pid())?.cpu_s - cpu0) * 1e3 / self.args.calls as f64;
        let (p50, p95) = (percentile_ms(&mut latencies, 50.0), percentile_ms(&mut latencies, 95.0));
        if !self.args.json {
            eprintln!("osc_sequence with {open} open episode(s), one driven: p50 {p50:.1} ms, p95 {p95:.1} ms, server CPU {cpu_ms_per_call:.0} ms per call");
        }
        Ok(json!({"open_episodes": open, "calls": latencies.len(), "p50_ms": p50, "p95_ms": p95, "server_cpu_ms_per_call": cpu_ms_per_call}))
    }

    /// The server's CPU use (percent of one core) over `--settle-ms` while nothing is driven.
    fn idle_cpu_percent(&self) -> anyhow::Result<f64> {
        let (s0, t) = (ProcSample::of(self.serve.pid())?, Instant::now());
        let s1 = self.settled()?;
        Ok((s1.cpu_s - s0.cpu_s) / t.elapsed().as_secs_f64() * 100.0)
    }
}

/// Count, mean, min and max of `measure` over the episode records that pass `pick` (`None`, printed null, when
/// none does). A value JSON cannot hold (NaN) is left out, as it is printed null in the records.
fn summary(records: &[OpenRecord], pick: &dyn Fn(&OpenRecord) -> bool, measure: &dyn Fn(&OpenRecord) -> f64) -> Option<Summary> {
    let mut v: Vec<f64> = records.iter().filter(|r| pick(r)).map(measure).filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    let p50 = percentile_ms(&mut v, 50.0);
    Some(Summary { count: v.len(), mean, p50, min: v[0], max: v[v.len() - 1] })
}

/// A main-table batch held open at once, as [`sizing`] estimates it (the output's `sizing`).
#[derive(Debug, Clone, Serialize)]
struct Sizing {
    main_table_rollouts: usize,
    main_table_scenes: usize,
    main_table_all_open_rss_gb: f64,
    episodes_per_gb: f64,
    later_first_of_scene_measured: bool,
    additional_measured: bool,
}

/// A main-table batch (90 rollouts over 30 scenes) held open at once, from the measured increments over the idle
/// server: the server's first episode (it also opens the renderer), 29 more first episodes of a scene (the
/// first episode's increment where no later scene was measured) and 60 additional episodes of a loaded scene
/// (the first-of-scene figure where none was measured).
fn sizing(idle_mb: f64, first_episode_mb: f64, later_first_mb: Option<f64>, additional_mb: Option<f64>) -> Sizing {
    let later_first = later_first_mb.unwrap_or(first_episode_mb);
    let additional = additional_mb.unwrap_or(later_first);
    let batch_mb = idle_mb
        + first_episode_mb
        + (MAIN_TABLE_TASKS - 1) as f64 * later_first
        + (MAIN_TABLE_ROLLOUTS - MAIN_TABLE_TASKS) as f64 * additional;
    Sizing {
        main_table_rollouts: MAIN_TABLE_ROLLOUTS,
        main_table_scenes: MAIN_TABLE_TASKS,
        main_table_all_open_rss_gb: batch_mb / 1024.0,
        episodes_per_gb: MAIN_TABLE_ROLLOUTS as f64 / (batch_mb / 1024.0),
        later_first_of_scene_measured: later_first_mb.is_some(),
        additional_measured: additional_mb.is_some(),
    }
}

/// Waits until `serve` has no episode thread left (at most [`THREAD_EXIT_TIMEOUT`]); returns how long it took.
pub(crate) fn wait_episode_threads_gone(pid: u32) -> anyhow::Result<f64> {
    let t = Instant::now();
    loop {
        let alive = std::fs::read_dir(format!("/proc/{pid}/task"))?
            .flatten()
            .filter(|task| std::fs::read_to_string(task.path().join("comm")).is_ok_and(|n| n.starts_with("episode-")))
            .count();
        if alive == 0 {
            return Ok(t.elapsed().as_secs_f64());
        }
        if t.elapsed() > THREAD_EXIT_TIMEOUT {
            bail!("{alive} episode thread(s) still alive {} s after finish_episode", THREAD_EXIT_TIMEOUT.as_secs());
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn measure(bench: &Bench, tasks: &[String]) -> anyhow::Result<Value> {
    let args = bench.args;
    let idle = bench.settled()?;
    let idle_cpu = bench.idle_cpu_percent()?;
    if !args.json {
        eprintln!("serve idle: {:.0} MB resident, {} threads", idle.rss_mb, idle.threads);
    }
    let mut open: Vec<OpenEpisode> = Vec::with_capacity(args.episodes);
    open.push(bench.open(0, &tasks[0], true)?);
    let one_open = ProcSample::of(bench.serve.pid())?;
    let drive_one = bench.drive(&mut open[0], 1)?;
    for i in 1..args.episodes {
        open.push(bench.open(i, &tasks[i % tasks.len()], i < tasks.len())?);
    }
    let n_open = bench.settled()?;
    let n_idle_cpu = bench.idle_cpu_percent()?;
    let drive_n = bench.drive(&mut open[0], args.episodes)?;
    let records: Vec<OpenRecord> = open.iter().map(|e| e.record.clone()).collect();
    for mut e in open {
        let finished = e.client.call_tool("finish_episode", json!({}))?;
        if ToolReply::of(&finished).status.as_deref() != Some(STATUS_FINISHED) {
            bail!("episode {:?}: finish_episode answered {finished}", e.record.episode_id);
        }
    }
    let threads_gone_s = wait_episode_threads_gone(bench.serve.pid())?;
    std::thread::sleep(RELEASE_WAIT);
    let after_finish = bench.settled()?;
    let first = |r: &OpenRecord| r.first_of_scene;
    let later_first = |r: &OpenRecord| r.first_of_scene && r.index != 0;
    let additional = |r: &OpenRecord| !r.first_of_scene;
    let rss = |r: &OpenRecord| r.rss_increment_mb;
    let threads = |r: &OpenRecord| r.thread_increment as f64;
    let both = |pick: &dyn Fn(&OpenRecord) -> bool| json!({"rss_mb": summary(&records, pick, &rss), "threads": summary(&records, pick, &threads)});
    let increments = json!({
        "what": "resident memory (MB) and threads an episode adds to serve, each sampled settled before and after it opens",
        "first_of_scene": both(&first),
        "first_of_scene_after_the_first": both(&later_first),
        "additional": both(&additional),
        "first_episode_of_the_server": {"rss_mb": records[0].rss_increment_mb, "threads": records[0].thread_increment,
            "note": "includes opening the process's renderer (one GPU device for all episodes)"},
    });
    let mean_rss = |pick: &dyn Fn(&OpenRecord) -> bool| summary(&records, pick, &rss).map(|s| s.mean);
    let sizing = sizing(idle.rss_mb, records[0].rss_increment_mb, mean_rss(&later_first), mean_rss(&additional));
    Ok(json!({
        "idle": idle,
        "one_open": one_open,
        "n_open": {"episodes": args.episodes, "rss_mb": n_open.rss_mb, "threads": n_open.threads},
        "after_finish": {"rss_mb": after_finish.rss_mb, "threads": after_finish.threads, "episode_threads_gone_after_s": threads_gone_s},
        "per_open_episode_mb": (n_open.rss_mb - idle.rss_mb) / args.episodes as f64,
        "increments": increments,
        "open_ms": {
            "what": "prepare (POST /api/episodes) + start_episode, as a client waits for them",
            "cold": summary(&records, &first, &|r| r.open_ms),
            "warm": summary(&records, &additional, &|r| r.open_ms),
            "cold_prepare": summary(&records, &first, &|r| r.prepare_ms),
            "warm_prepare": summary(&records, &additional, &|r| r.prepare_ms),
        },
        "osc_sequence": {"actions_per_call": args.actions, "one_open": drive_one, "n_open": drive_n},
        "server_cpu_idle_percent": {"no_episode": idle_cpu, "n_open": n_idle_cpu,
            "per_open_episode": (n_idle_cpu - idle_cpu) / args.episodes as f64},
        "sizing": sizing,
        "per_episode": records,
    }))
}

/// The tasks a `--tasks` selection names that can open an episode, each once, in order.
fn scene_tasks(parts: &[String]) -> anyhow::Result<Vec<String>> {
    let catalog = libero_tasks::Catalog::discover()?;
    let pool = libero_tasks::Pool::discover()?;
    let picks = libero_tasks::Selection::from_parts(parts)?.runnable(catalog.tasks(), &pool)?;
    let ids = picks.iter().map(|p| p.member.id()).collect();
    Ok(ids)
}

pub fn run(args: &BenchScaleArgs) -> anyhow::Result<()> {
    if args.episodes == 0 || args.scenes == 0 || args.calls == 0 || args.actions == 0 || args.actions > 50 {
        bail!("--episodes, --scenes and --calls must be positive and --actions between 1 and 50");
    }
    let selected = scene_tasks(&args.tasks)?;
    if args.scenes > args.episodes || args.scenes > selected.len() {
        bail!("--scenes ({}) must be at most --episodes ({}) and the number of --tasks ({})", args.scenes, args.episodes, selected.len());
    }
    let tasks = &selected[..args.scenes];
    let (data, remove_data) = match &args.data {
        Some(d) => (d.clone(), false),
        None => (std::env::temp_dir().join(format!("libero-agent-bench-scale-{}", std::process::id())), true),
    };
    // The adapter this machine's wgpu picks with this environment: the server's own renderer picks the same way.
    let adapter = libero_render::Renderer::new().map(|r| r.adapter_description()).unwrap_or_else(|e| format!("none: {e}"));
    let measured = ServeProcess::start(&data).and_then(|serve| {
        let mut bench = Bench { args, serve, settle: Duration::from_millis(args.settle_ms) };
        let m = measure(&bench, tasks).map_err(|e| e.context(bench.serve.log_tail()));
        bench.serve.stop()?;
        m
    });
    if remove_data {
        let _ = std::fs::remove_dir_all(&data);
    }
    let measured = measured?;
    let cores = std::thread::available_parallelism().map_or(1, std::num::NonZeroUsize::get);
    let mut out = json!({
        "benchmark": "scale",
        "build": if cfg!(debug_assertions) { "debug" } else { "release" },
        "server": "a separate `libero-agent serve` process, read from /proc/<pid>",
        "renderer_adapter": adapter,
        "cpu_cores": cores,
        "mem_total_gb": mem_total_gb(),
        "episodes": args.episodes,
        "scenes": tasks,
        "level": args.level,
        "video": false,
        "settle_ms": args.settle_ms,
    });
    if let (Some(o), Some(m)) = (out.as_object_mut(), measured.as_object()) {
        o.extend(m.clone());
    }
    println!("{}", if args.json { out.to_string() } else { serde_json::to_string_pretty(&out)? });
    Ok(())
}

/// `MemTotal` of `/proc/meminfo` in GB (null when unreadable).
fn mem_total_gb() -> Value {
    let text = std::fs::read_to_string("/proc/meminfo").unwrap_or_default();
    let kb = text.lines().find_map(|l| l.strip_prefix("MemTotal:")).and_then(|v| v.split_whitespace().next()?.parse::<f64>().ok());
    kb.map_or(Value::Null, |kb| json!(kb / (1024.0 * 1024.0)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn this_process_can_be_read_from_proc() {
        let s = ProcSample::of(std::process::id()).unwrap();
        assert!(s.rss_mb > 0.0 && s.threads >= 1, "{s:?}");
        // CPU time is whole clock ticks, and it grows while this thread works (10 s is a bound, not a measure).
        // SAFETY: sysconf only reads a system constant.
        let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64;
        assert!(((s.cpu_s * hz) - (s.cpu_s * hz).round()).abs() < 1e-6, "{s:?}");
        let t = Instant::now();
        let mut spin = 0u64;
        while ProcSample::of(std::process::id()).unwrap().cpu_s <= s.cpu_s {
            spin = std::hint::black_box(spin.wrapping_add(1));
            assert!(t.elapsed() < Duration::from_secs(10), "this process's CPU time did not grow: {s:?}");
        }
    }

    #[test]
    fn summaries_pick_their_records_and_say_null_when_none() {
        let record = |first_of_scene, open_ms| OpenRecord {
            index: 0,
            task: "T14".into(),
            episode_id: "e".into(),
            first_of_scene,
            prepare_ms: 0.0,
            start_episode_ms: 0.0,
            open_ms,
            rss_mb: 0.0,
            threads: 0,
            rss_increment_mb: 0.0,
            thread_increment: 0,
        };
        let r = vec![record(true, 3.0), record(false, 1.0), record(true, 1.0), record(true, f64::NAN)];
        let s = summary(&r, &|r| r.first_of_scene, &|r| r.open_ms).unwrap();
        assert_eq!((s.count, s.mean, s.min, s.max), (2, 2.0, 1.0, 3.0), "NaN, printed null, is left out");
        assert_eq!(serde_json::to_value(summary(&r, &|_| false, &|r| r.open_ms)).unwrap(), Value::Null);
    }

    #[test]
    fn a_main_table_batch_is_thirty_first_and_sixty_additional_episodes() {
        let gb = |s: Sizing| s.main_table_all_open_rss_gb;
        let mb = 24.0 + 500.0 + 29.0 * 400.0 + 60.0 * 100.0;
        assert!((gb(sizing(24.0, 500.0, Some(400.0), Some(100.0))) - mb / 1024.0).abs() < 1e-9);
        // Unmeasured kinds take the nearest measured figure.
        assert!((gb(sizing(24.0, 500.0, None, Some(100.0))) - (24.0 + 30.0 * 500.0 + 60.0 * 100.0) / 1024.0).abs() < 1e-9);
        assert!((gb(sizing(24.0, 500.0, None, None)) - (24.0 + 90.0 * 500.0) / 1024.0).abs() < 1e-9);
    }
}
