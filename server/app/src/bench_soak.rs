//! `libero-agent bench soak`: many short episodes through the real MCP path against an in-process server, to show
//! that what an episode holds (thread, simulation, renderer uploads, state record, MCP sessions, live view) is
//! released when it ends (its private video, rendered after it from its state record, included). Resident memory, threads and open files of this process are read from `/proc/self` at
//! the start, after the first episode, half way, at the peak and after the last episode, each "after" once the
//! episodes' threads are gone and `--settle-s` more have passed (release grace, tokio's idle blocking threads).
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use serde::Serialize;
use serde_json::{Value, json};

use crate::bench_mcp::percentile_ms;
use libero_records::records::ToolReply;
use libero_server::client::{InProcessServer, McpClient, prepare_episode, wait_for_video};

/// The longest one episode's video may take (a software renderer behind several episodes).
const VIDEO_TIMEOUT: Duration = Duration::from_secs(900);
use libero_server::episodes::PrepareRequest;

/// Arguments of `bench soak`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchSoakArgs {
    /// Print only the JSON result.
    #[arg(long)]
    pub json: bool,
    /// Episodes in all (the first runs alone, to take the baseline).
    #[arg(long, default_value_t = 60)]
    pub episodes: usize,
    /// Episodes driven at the same time.
    #[arg(long, default_value_t = 8)]
    pub concurrent: usize,
    #[arg(long, default_value = "T14")]
    pub task: String,
    #[arg(long, default_value_t = 3)]
    pub level: u8,
    /// `osc_sequence` calls per episode.
    #[arg(long, default_value_t = 2)]
    pub calls: usize,
    /// Micro-actions per call.
    #[arg(long, default_value_t = 10)]
    pub actions: usize,
    /// Do not record the private video (by default every episode records it, as a served episode does).
    #[arg(long)]
    pub no_video: bool,
    /// Seconds waited after the episodes' threads are gone before sampling (covers the MCP release grace and
    /// tokio's 10 s idle timeout of blocking threads).
    #[arg(long, default_value_t = 12.0)]
    pub settle_s: f64,
    /// Data directory of the in-process server (default: a new directory under the system temp dir, removed
    /// afterwards).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

/// How long the episodes' threads may take to end after their last call before the run counts as leaking.
const THREAD_EXIT_TIMEOUT: Duration = Duration::from_secs(120);
/// How often the peak sampler reads `/proc/self`.
const PEAK_SAMPLE_PERIOD: Duration = Duration::from_millis(100);

/// Resources of this process at one moment.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Sample {
    pub rss_mb: f64,
    pub threads: u64,
    pub open_files: u64,
    /// What the allocator has handed out and what it holds free (all arenas): tells a leak from fragmentation.
    pub malloc_in_use_mb: f64,
    pub malloc_free_mb: f64,
    /// Compiled scene models alive in the process (shared between episodes while any holds one; none once all
    /// ended and their videos are drawn).
    pub models_alive: usize,
}

impl Sample {
    /// Reads `/proc/self/status` (VmRSS, Threads) and counts `/proc/self/fd`.
    pub fn now() -> anyhow::Result<Self> {
        let status = std::fs::read_to_string("/proc/self/status").context("reading /proc/self/status")?;
        let field = |name: &str| -> anyhow::Result<u64> {
            let line = status.lines().find(|l| l.starts_with(name)).with_context(|| format!("no {name} in /proc/self/status"))?;
            let value = line[name.len()..].split_whitespace().next().unwrap_or_default();
            value.parse().with_context(|| format!("{name} is not a number: {line}"))
        };
        let open_files = std::fs::read_dir("/proc/self/fd").context("reading /proc/self/fd")?.count() as u64;
        // SAFETY: mallinfo2 only reads the allocator's counters.
        let m = unsafe { libc::mallinfo2() };
        let mb = |b: usize| b as f64 / (1024.0 * 1024.0);
        Ok(Self {
            rss_mb: field("VmRSS:")? as f64 / 1024.0,
            threads: field("Threads:")?,
            open_files,
            malloc_in_use_mb: mb(m.uordblks + m.hblkhd),
            malloc_free_mb: mb(m.fordblks),
            models_alive: libero_sim::shared_model::alive(),
        })
    }

    fn max(self, other: Self) -> Self {
        Self {
            rss_mb: self.rss_mb.max(other.rss_mb),
            threads: self.threads.max(other.threads),
            open_files: self.open_files.max(other.open_files),
            malloc_in_use_mb: self.malloc_in_use_mb.max(other.malloc_in_use_mb),
            malloc_free_mb: self.malloc_free_mb.max(other.malloc_free_mb),
            models_alive: self.models_alive.max(other.models_alive),
        }
    }
}

/// This process's threads by kind (name without its episode id or index).
pub fn threads_by_kind() -> BTreeMap<String, u64> {
    let mut kinds = BTreeMap::new();
    for task in std::fs::read_dir("/proc/self/task").into_iter().flatten().flatten() {
        let name = std::fs::read_to_string(task.path().join("comm")).unwrap_or_default();
        *kinds.entry(thread_kind(name.trim())).or_insert(0) += 1;
    }
    kinds
}

/// The kinds of an episode's own threads (`episode-…`, `video-…`): each ended episode must let go of them.
const EPISODE_THREAD_KINDS: [&str; 2] = ["episode", "video"];

fn thread_kind(name: &str) -> String {
    for kind in EPISODE_THREAD_KINDS {
        if name.strip_prefix(kind).is_some_and(|rest| rest.starts_with('-')) {
            return kind.to_owned();
        }
    }
    name.trim_end_matches(|c: char| c.is_ascii_digit() || c == '-' || c == ':').to_owned()
}

/// This process's open files by kind (socket, pipe, anon_inode:…, or the file's extension).
pub fn open_files_by_kind() -> BTreeMap<String, u64> {
    let mut kinds = BTreeMap::new();
    for fd in std::fs::read_dir("/proc/self/fd").into_iter().flatten().flatten() {
        let target = std::fs::read_link(fd.path()).map(|p| p.to_string_lossy().into_owned()).unwrap_or_default();
        *kinds.entry(file_kind(&target)).or_insert(0) += 1;
    }
    kinds
}

fn file_kind(target: &str) -> String {
    if let Some(rest) = target.strip_prefix("anon_inode:") {
        return format!("anon_inode:{}", rest.trim_matches(|c| c == '[' || c == ']'));
    }
    if let Some((kind, _)) = target.split_once(":[") {
        return kind.to_owned();
    }
    if target.starts_with("/dev/") {
        return target.to_owned();
    }
    match std::path::Path::new(target).extension() {
        Some(ext) => format!("*.{}", ext.to_string_lossy()),
        None => "file".to_owned(),
    }
}

/// Episode and video threads still alive (each ended episode must let go of both).
fn episode_threads() -> u64 {
    let kinds = threads_by_kind();
    EPISODE_THREAD_KINDS.iter().map(|k| kinds.get(*k).copied().unwrap_or(0)).sum()
}

/// Samples continuously on a thread of its own and keeps the maximum of each figure.
struct PeakSampler {
    stop: Arc<AtomicBool>,
    peak: Arc<Mutex<Sample>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl PeakSampler {
    fn start() -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let peak = Arc::new(Mutex::new(Sample::now().unwrap_or_default()));
        let (s, p) = (stop.clone(), peak.clone());
        let thread = std::thread::spawn(move || {
            while !s.load(Ordering::Relaxed) {
                if let (Ok(now), Ok(mut peak)) = (Sample::now(), p.lock()) {
                    *peak = peak.max(now);
                }
                std::thread::sleep(PEAK_SAMPLE_PERIOD);
            }
        });
        Self { stop, peak, thread: Some(thread) }
    }

    /// The peak, without the sampler's own thread.
    fn finish(mut self) -> Sample {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        let peak = self.peak.lock().map(|p| *p).unwrap_or_default();
        Sample { threads: peak.threads.saturating_sub(1), ..peak }
    }
}

/// One episode as an agent drives it: prepare, initialize, start, `calls` short `osc_sequence` calls, finish.
/// Returns how long preparing took (the world is built then: compose, compile, place, upload to the renderer).
pub(crate) fn one_episode(base: &str, args: &BenchSoakArgs, index: usize) -> anyhow::Result<f64> {
    let req = PrepareRequest { level: args.level, seed: 100 + index as u64, video: !args.no_video, ..PrepareRequest::new(&args.task) };
    let t = Instant::now();
    let prepared = prepare_episode(base, &req)?;
    let prepare_ms = t.elapsed().as_secs_f64() * 1e3;
    let token = prepared.mcp_headers.get("Authorization").context("no token")?.trim_start_matches("Bearer ").to_owned();
    let mut client = McpClient::connect_with_token(&prepared.mcp_url, &token, "libero-agent-soak")?;
    client.call_tool("start_episode", json!({}))?;
    for call in 0..args.calls {
        let sign = if call % 2 == 0 { 1.0 } else { -1.0 };
        let actions = vec![[0.1 * sign, 0.05 * sign, 0.0, 0.0, 0.0, 0.0, -1.0]; args.actions];
        client.call_tool("osc_sequence", json!({"actions": actions}))?;
    }
    let finished = client.call_tool("finish_episode", json!({}))?;
    if ToolReply::of(&finished).status.as_deref() != Some("finished") {
        bail!("episode {}: finish_episode answered {finished}", prepared.episode_id);
    }
    if req.video {
        wait_for_video(base, &prepared.episode_id, VIDEO_TIMEOUT)?;
    }
    Ok(prepare_ms)
}

/// Runs episodes `range` with `concurrent` client threads; returns each one's prepare time (ms).
fn run_episodes(base: &str, args: &BenchSoakArgs, range: std::ops::Range<usize>, concurrent: usize) -> anyhow::Result<Vec<f64>> {
    let next = Arc::new(AtomicUsize::new(range.start));
    let end = range.end;
    let workers: Vec<_> = (0..concurrent.min(range.len()).max(1))
        .map(|_| {
            let (next, base, args) = (next.clone(), base.to_owned(), args.clone());
            std::thread::spawn(move || -> anyhow::Result<Vec<f64>> {
                let mut prepare_ms = Vec::new();
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    if i >= end {
                        return Ok(prepare_ms);
                    }
                    prepare_ms.push(one_episode(&base, &args, i).with_context(|| format!("episode {}", i + 1))?);
                }
            })
        })
        .collect();
    let mut prepare_ms = Vec::new();
    for w in workers {
        prepare_ms.extend(w.join().map_err(|_| anyhow::anyhow!("a client thread panicked"))??);
    }
    Ok(prepare_ms)
}

/// Waits until the ended episodes' threads are gone, then `settle`; returns the sample and how long the
/// threads took to end.
fn sample_after_release(settle: Duration) -> anyhow::Result<(Sample, f64)> {
    let ended = Instant::now();
    while episode_threads() > 0 {
        if ended.elapsed() > THREAD_EXIT_TIMEOUT {
            bail!("episode threads still alive {} s after their episodes ended: {:?}", THREAD_EXIT_TIMEOUT.as_secs(), threads_by_kind());
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let threads_gone_s = ended.elapsed().as_secs_f64();
    std::thread::sleep(settle);
    Ok((Sample::now()?, threads_gone_s))
}

fn progress(args: &BenchSoakArgs, what: &str, s: &Sample) {
    if !args.json {
        eprintln!("{what}: {:.0} MB resident, {} threads, {} open files", s.rss_mb, s.threads, s.open_files);
    }
}

/// The measurement itself, against the server at `base`.
fn soak(base: &str, args: &BenchSoakArgs, start: Sample) -> anyhow::Result<Value> {
    let settle = Duration::from_secs_f64(args.settle_s.max(0.0));
    let half = (args.episodes / 2).max(1);
    let peak = PeakSampler::start();
    let t0 = Instant::now();
    let mut prepare_ms = run_episodes(base, args, 0..1, 1)?;
    let (first, first_gone_s) = sample_after_release(settle)?;
    progress(args, "after the first episode", &first);
    let (first_threads, first_files) = (threads_by_kind(), open_files_by_kind());
    let t1 = Instant::now();
    prepare_ms.extend(run_episodes(base, args, 1..half, args.concurrent)?);
    let (mid, _) = sample_after_release(settle)?;
    progress(args, &format!("after {half} episodes"), &mid);
    let t2 = Instant::now();
    prepare_ms.extend(run_episodes(base, args, half..args.episodes, args.concurrent)?);
    let driving_s = (t1.duration_since(t0) + t2.elapsed()).as_secs_f64();
    let (last, last_gone_s) = sample_after_release(settle)?;
    let (last_threads, last_files) = (threads_by_kind(), open_files_by_kind());
    let peak = peak.finish();
    progress(args, &format!("after {} episodes", args.episodes), &last);
    Ok(json!({
        "start": start,
        "after_first_episode": first,
        "after_half": {"episodes": half, "sample": mid},
        "peak": peak,
        "after_last_episode": last,
        "rss_growth_after_first_mb": last.rss_mb - first.rss_mb,
        "rss_growth_second_half_mb": last.rss_mb - mid.rss_mb,
        "threads_over_baseline": last.threads as i64 - first.threads as i64,
        "open_files_over_baseline": last.open_files as i64 - first.open_files as i64,
        "episode_threads_gone_after_s": {"first": first_gone_s, "last": last_gone_s},
        "threads_by_kind": {"after_first_episode": first_threads, "after_last_episode": last_threads},
        "open_files_by_kind": {"after_first_episode": first_files, "after_last_episode": last_files},
        "driving_s": driving_s,
        "prepare_ms": {"first": prepare_ms[0], "p50": percentile_ms(&mut prepare_ms.clone(), 50.0),
            "max": percentile_ms(&mut prepare_ms, 100.0)},
    }))
}

pub fn run(args: &BenchSoakArgs) -> anyhow::Result<()> {
    if args.episodes < 2 || args.concurrent == 0 || args.actions == 0 || args.actions > 50 {
        bail!("--episodes must be at least 2, --concurrent positive and --actions between 1 and 50");
    }
    let (data, remove_data) = match &args.data {
        Some(d) => (d.clone(), false),
        None => (std::env::temp_dir().join(format!("libero-agent-bench-soak-{}", std::process::id())), true),
    };
    let start = Sample::now()?;
    progress(args, "start", &start);
    let server = InProcessServer::start(data.clone(), "bench_finished_before_finish")?;
    let measured = soak(&server.url, args, start);
    let served = server.stop();
    if remove_data {
        let _ = std::fs::remove_dir_all(&data);
    }
    let mut out = json!({
        "benchmark": "soak",
        "build": if cfg!(debug_assertions) { "debug" } else { "release" },
        "task": args.task,
        "level": args.level,
        "episodes": args.episodes,
        "concurrent": args.concurrent,
        "calls_per_episode": args.calls,
        "actions_per_call": args.actions,
        "video": !args.no_video,
        "settle_s": args.settle_s,
    });
    let measured = measured?;
    served?;
    if let (Some(o), Some(m)) = (out.as_object_mut(), measured.as_object()) {
        o.extend(m.clone());
    }
    println!("{}", if args.json { out.to_string() } else { serde_json::to_string_pretty(&out)? });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn threads_and_files_are_grouped_without_their_ids() {
        assert_eq!(thread_kind("episode-ep-2026"), "episode");
        assert_eq!(thread_kind("video-ep-2026112"), "video");
        assert_eq!(thread_kind("llvmpipe-12"), "llvmpipe");
        assert_eq!(thread_kind("tokio-runtime-w"), "tokio-runtime-w");
        assert_eq!(file_kind("socket:[1234]"), "socket");
        assert_eq!(file_kind("anon_inode:[eventfd]"), "anon_inode:eventfd");
        assert_eq!(file_kind("/data/store.sqlite-wal"), "*.sqlite-wal");
        assert_eq!(file_kind("/dev/dri/renderD128"), "/dev/dri/renderD128");
    }

    #[test]
    fn this_process_can_be_sampled() {
        let s = Sample::now().unwrap();
        assert!(s.rss_mb > 0.0 && s.threads >= 1 && s.open_files >= 3, "{s:?}");
    }
}
