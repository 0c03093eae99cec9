//! `libero-agent bench thumbnails`: what the background thumbnail pass (`serve --thumbnails-ahead`) costs a real
//! `libero-agent serve` process, read from outside it (`/proc/<pid>`), and whether episodes run beside the pass
//! leave the server where they found it.
//!
//! 1. **The pass alone.** `serve` starts on a fresh data directory with `--thumbnails-ahead <--tasks>`; its resident
//!    memory is read as it announces itself (`before`), continuously while the pass runs (`during_max`, the
//!    kernel's high-water mark `VmHWM`), and `--settle-ms` after the pass reported done (`after`).
//! 2. **A soak beside the pass** (`--soak-episodes`, 0 to skip): `serve` again, its thumbnail cache emptied, with
//!    `--thumbnails-ahead <--soak-tasks>` (more scenes than the soak takes, so the pass runs throughout), and
//!    `--soak-episodes` short episodes one after another as `bench soak` drives them (prepare, start, two
//!    10-action calls, finish, its video). The pass renders between episodes (it waits while one is open). Memory
//!    is read after the first and after the last episode, each once the episodes' threads are gone, `--settle-ms`
//!    have passed and the pass has just finished a scene (so no scene is half built at the reading).
//!    `--soak-without-pass` runs the same soak once more on a server with the pass off, for comparison.
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::bench_scale::{ProcSample, ServeProcess, wait_episode_threads_gone};
use crate::bench_soak::{BenchSoakArgs, one_episode};
use libero_server::client::get_json;

/// How often the pass's progress and the server's memory are read.
const SAMPLE_PERIOD: Duration = Duration::from_millis(100);
/// How long the bench waits for the pass to finish a scene before it reads memory anyway.
const SCENE_WAIT: Duration = Duration::from_secs(300);

/// Arguments of `bench thumbnails`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchThumbnailsArgs {
    /// Print only the JSON result.
    #[arg(long)]
    pub json: bool,
    /// The pass measured alone (`--thumbnails-ahead`; `release,all` is the server's default, ~240 scenes).
    #[arg(long, default_value = "release")]
    pub tasks: String,
    /// `--thumbnail-threads` of the server (its default when not given).
    #[arg(long)]
    pub threads: Option<u16>,
    /// Episodes of the soak beside the pass (0: no soak).
    #[arg(long, default_value_t = 16)]
    pub soak_episodes: usize,
    /// The pass running beside the soak (more scenes than the soak lasts).
    #[arg(long, default_value = "release,all")]
    pub soak_tasks: String,
    /// Task of the soak's episodes.
    #[arg(long, default_value = "T14")]
    pub soak_task: String,
    /// The soak's episodes record no private video.
    #[arg(long)]
    pub no_video: bool,
    /// Also run the soak on a server with the pass off.
    #[arg(long)]
    pub soak_without_pass: bool,
    /// Milliseconds waited before each reading after the pass or an episode (release grace, allocator).
    #[arg(long, default_value_t = 5000)]
    pub settle_ms: u64,
    /// Data directory of the `serve` processes (default: a new directory under the system temp dir, removed
    /// afterwards). Its thumbnail cache is emptied before each server starts.
    #[arg(long)]
    pub data: Option<PathBuf>,
}

/// The pass's progress as `/api/thumbnails` reports it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Pass {
    /// Scenes looked at: rendered, reused or failed.
    scenes: u64,
    rendered: u64,
    failed: u64,
    done: bool,
}

/// `GET /api/thumbnails`'s answer (the server's `ThumbnailStats`), as far as the bench reads it; a count the
/// server leaves out reads 0.
#[derive(Deserialize)]
struct ThumbnailsReply {
    #[serde(default)]
    thumbnails: ThumbnailCounts,
}

#[derive(Deserialize, Default)]
#[serde(default)]
struct ThumbnailCounts {
    rendered: u64,
    reused: u64,
    failed: u64,
    ahead_done: bool,
}

/// Memory after a soak episode, and where the pass was then.
#[derive(Serialize)]
struct Reading {
    episodes: usize,
    rss_mb: f64,
    pass_scenes: Option<u64>,
    pass_done: Option<bool>,
}

/// How long `/api/thumbnails` may fail to answer (a server busy building a scene on a loaded machine) before the
/// bench gives up.
const API_PATIENCE: Duration = Duration::from_secs(60);

impl Pass {
    /// The pass's progress, asked again while the server does not answer (at most [`API_PATIENCE`]).
    fn of(serve: &ServeProcess) -> anyhow::Result<Self> {
        let t = Instant::now();
        loop {
            match Self::ask(serve) {
                Err(e) if t.elapsed() < API_PATIENCE => {
                    log::debug!("GET /api/thumbnails: {e:#}; asking again");
                    std::thread::sleep(Duration::from_millis(500));
                }
                answer => return answer,
            }
        }
    }

    fn ask(serve: &ServeProcess) -> anyhow::Result<Self> {
        let (status, v) = get_json(&serve.url, "/api/thumbnails")?;
        if status != 200 {
            bail!("GET /api/thumbnails answered HTTP {status}: {v}");
        }
        let t = ThumbnailsReply::deserialize(&v).with_context(|| format!("GET /api/thumbnails answered {v}"))?.thumbnails;
        Ok(Self { scenes: t.rendered + t.reused + t.failed, rendered: t.rendered, failed: t.failed, done: t.ahead_done })
    }
}

/// The kernel's high-water mark of the process's resident memory (`VmHWM`), MB.
fn peak_rss_mb(pid: u32) -> anyhow::Result<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).with_context(|| format!("is process {pid} gone?"))?;
    let kb = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse::<f64>().ok())
        .context("no VmHWM in /proc/<pid>/status")?;
    Ok(kb / 1024.0)
}

/// Starts `serve` on `data` (its thumbnail cache emptied) with the pass over `ahead`.
fn start(data: &std::path::Path, ahead: &str, threads: Option<u16>) -> anyhow::Result<ServeProcess> {
    let cache = data.join("thumbnails");
    if cache.exists() {
        std::fs::remove_dir_all(&cache).with_context(|| format!("emptying {}", cache.display()))?;
    }
    let mut extra = vec!["--thumbnails-ahead".to_owned(), ahead.to_owned()];
    if let Some(n) = threads {
        extra.extend(["--thumbnail-threads".to_owned(), n.to_string()]);
    }
    ServeProcess::start_with(data, &extra)
}

/// The server's resident memory once the pass has just finished a scene (or is done, or has not moved for
/// [`SCENE_WAIT`]): a reading with no scene half built. Also what the pass had done then.
fn between_scenes(serve: &ServeProcess) -> anyhow::Result<(f64, Pass)> {
    let start = Pass::of(serve)?;
    let t = Instant::now();
    loop {
        let now = Pass::of(serve)?;
        if now.done || now.scenes != start.scenes || t.elapsed() > SCENE_WAIT {
            return Ok((ProcSample::of(serve.pid())?.rss_mb, now));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn progress(args: &BenchThumbnailsArgs, line: String) {
    if !args.json {
        eprintln!("{line}");
    }
}

/// Phase 1: the pass alone, from a fresh server to its end.
fn pass_alone(args: &BenchThumbnailsArgs, data: &std::path::Path) -> anyhow::Result<Value> {
    let t0 = Instant::now();
    let serve = start(data, &args.tasks, args.threads)?;
    let before = ProcSample::of(serve.pid())?;
    progress(args, format!("pass over {}: fresh server {:.0} MB", args.tasks, before.rss_mb));
    let mut last = Pass::of(&serve)?;
    let mut printed = Instant::now();
    while !last.done {
        std::thread::sleep(SAMPLE_PERIOD);
        last = Pass::of(&serve)?;
        if printed.elapsed() > Duration::from_secs(10) {
            printed = Instant::now();
            let (rss, peak) = (ProcSample::of(serve.pid())?.rss_mb, peak_rss_mb(serve.pid())?);
            progress(args, format!("  {} scenes ({} rendered): {rss:.0} MB now, {peak:.0} MB at most", last.scenes, last.rendered));
        }
    }
    let pass_s = t0.elapsed().as_secs_f64();
    let during_max = peak_rss_mb(serve.pid())?;
    std::thread::sleep(Duration::from_millis(args.settle_ms));
    let after = ProcSample::of(serve.pid())?;
    progress(args, format!("pass done in {pass_s:.0} s: {:.0} MB at most, {:.0} MB after", during_max, after.rss_mb));
    Ok(json!({
        "tasks": args.tasks, "scenes": last.scenes, "rendered": last.rendered, "failed": last.failed,
        "pass_s": pass_s,
        "rss_mb": {"before": before.rss_mb, "during_max": during_max, "after": after.rss_mb},
        "after_minus_before_mb": after.rss_mb - before.rss_mb,
        "during_max_minus_before_mb": during_max - before.rss_mb,
        "threads": {"before": before.threads, "after": after.threads},
    }))
}

/// Phase 2: `--soak-episodes` episodes one after another on a server whose pass over `ahead` runs beside them.
fn soak(args: &BenchThumbnailsArgs, data: &std::path::Path, ahead: &str) -> anyhow::Result<Value> {
    let serve = start(data, ahead, args.threads)?;
    let fresh = ProcSample::of(serve.pid())?;
    let soak_args = BenchSoakArgs {
        json: true,
        episodes: args.soak_episodes,
        concurrent: 1,
        task: args.soak_task.clone(),
        level: 3,
        calls: 2,
        actions: 10,
        no_video: args.no_video,
        settle_s: 0.0,
        data: None,
    };
    let settle = Duration::from_millis(args.settle_ms);
    let mut readings = Vec::new();
    let t0 = Instant::now();
    for i in 0..args.soak_episodes {
        one_episode(&serve.url, &soak_args, i).with_context(|| format!("soak episode {}", i + 1))?;
        if i == 0 || i + 1 == args.soak_episodes {
            wait_episode_threads_gone(serve.pid())?;
            std::thread::sleep(settle);
            let (rss, pass) = if ahead == "off" { (ProcSample::of(serve.pid())?.rss_mb, None) } else { between_scenes(&serve).map(|(r, p)| (r, Some(p)))? };
            progress(args, format!("  pass {ahead}: after episode {}: {rss:.0} MB (pass: {pass:?})", i + 1));
            readings.push(Reading { episodes: i + 1, rss_mb: rss, pass_scenes: pass.map(|p| p.scenes), pass_done: pass.map(|p| p.done) });
        }
    }
    let first = readings.first().map(|r| r.rss_mb).unwrap_or_default();
    let last = readings.last().map(|r| r.rss_mb).unwrap_or_default();
    Ok(json!({
        "pass": ahead, "episodes": args.soak_episodes, "task": args.soak_task, "video": !args.no_video,
        "fresh_server_rss_mb": fresh.rss_mb, "readings": readings,
        "rss_growth_first_to_last_mb": last - first,
        "peak_rss_mb": peak_rss_mb(serve.pid())?,
        "driving_s": t0.elapsed().as_secs_f64(),
    }))
}

pub fn run(args: &BenchThumbnailsArgs) -> anyhow::Result<()> {
    if args.soak_episodes == 1 {
        bail!("--soak-episodes must be 0 (no soak) or at least 2");
    }
    let (data, remove_data) = match &args.data {
        Some(d) => (d.clone(), false),
        None => (std::env::temp_dir().join(format!("libero-agent-bench-thumbnails-{}", std::process::id())), true),
    };
    // One data directory for every server: `serve` keeps its operator token there, and this process's client
    // calls read the first token file they are given.
    let measured = (|| -> anyhow::Result<Value> {
        let alone = pass_alone(args, &data)?;
        let beside = if args.soak_episodes > 0 { soak(args, &data, &args.soak_tasks)? } else { Value::Null };
        let without = if args.soak_episodes > 0 && args.soak_without_pass { soak(args, &data, "off")? } else { Value::Null };
        Ok(json!({"pass_alone": alone, "soak_beside_pass": beside, "soak_without_pass": without}))
    })();
    if remove_data {
        let _ = std::fs::remove_dir_all(&data);
    }
    let mut out = json!({
        "benchmark": "thumbnails",
        "build": if cfg!(debug_assertions) { "debug" } else { "release" },
        "settle_ms": args.settle_ms,
    });
    if let (Some(o), Some(m)) = (out.as_object_mut(), measured?.as_object()) {
        o.extend(m.clone());
    }
    println!("{}", if args.json { out.to_string() } else { serde_json::to_string_pretty(&out)? });
    Ok(())
}
