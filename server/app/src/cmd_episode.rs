//! `libero-agent episode prepare`: asks a running server to prepare an episode and prints its JSON
//! (episode_id, mcp_url, mcp_headers, workspace, prompt_file, …).
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, bail};

use libero_episode::demo::DemoCondition;

use crate::serve::episodes::PrepareRequest;
use crate::serve::http_client::{HttpUrl, request};

#[derive(clap::Args, Debug)]
pub struct EpisodeArgs {
    #[command(subcommand)]
    pub command: EpisodeCommand,
}

#[derive(clap::Subcommand, Debug)]
pub enum EpisodeCommand {
    /// Prepare an episode on a running server: workspace, private run directory, MCP endpoint.
    Prepare(PrepareArgs),
}

#[derive(clap::Args, Debug)]
pub struct PrepareArgs {
    /// The server started with `libero-agent serve`.
    #[arg(long, default_value = "http://127.0.0.1:8080")]
    pub server: String,
    /// Suite task (T11), stock LIBERO task (<suite>/<name>) or a .bddl path.
    #[arg(long)]
    pub task: String,
    /// Observation level 1, 2 or 3.
    #[arg(long, default_value_t = 3)]
    pub level: u8,
    #[arg(long, default_value_t = 100)]
    pub seed: u64,
    /// Index into the task's init-state file.
    #[arg(long, default_value_t = 0)]
    pub init_index: usize,
    /// Workspace directory to create (default: under the server's data directory).
    #[arg(long)]
    pub workspace: Option<PathBuf>,
    #[arg(long, default_value_t = 1800.0)]
    pub wall_time_s: f64,
    #[arg(long, default_value_t = 1_000_000)]
    pub max_agent_steps: u64,
    /// Agent harness driving the episode (shown and filterable on the dashboard).
    #[arg(long)]
    pub harness: Option<String>,
    /// Model behind the harness.
    #[arg(long)]
    pub model: Option<String>,
    /// Batch the episode belongs to.
    #[arg(long)]
    pub batch: Option<String>,
    /// File holding the server's operator token (needed when the server listens beyond loopback).
    #[arg(long)]
    pub operator_token_file: Option<PathBuf>,
    /// Demonstration at `benchmark_inputs/expert_demo/`: none, video (§7.4 video_only) or video+traj (video plus
    /// the actions and measured end-effector states).
    #[arg(long, default_value = "none", value_parser = parse_demo)]
    pub demo: DemoCondition,
}

fn parse_demo(s: &str) -> Result<DemoCondition, String> {
    DemoCondition::parse(s).ok_or_else(|| format!("{s:?} is not none, video or video+traj"))
}

pub fn run_episode(args: EpisodeArgs) -> anyhow::Result<()> {
    match args.command {
        EpisodeCommand::Prepare(p) => prepare(p),
    }
}

fn prepare(p: PrepareArgs) -> anyhow::Result<()> {
    let workspace = match p.workspace {
        Some(w) if w.is_relative() => Some(std::env::current_dir()?.join(w)),
        other => other,
    };
    let task = match std::path::Path::new(&p.task) {
        t if p.task.ends_with(".bddl") && t.is_relative() && t.is_file() => {
            std::env::current_dir()?.join(t).to_string_lossy().into_owned()
        }
        _ => p.task.clone(),
    };
    let req = PrepareRequest {
        task,
        level: p.level,
        seed: p.seed,
        init_index: p.init_index,
        workspace,
        wall_time_s: p.wall_time_s,
        max_agent_steps: p.max_agent_steps,
        video: true,
        harness: p.harness,
        model: p.model,
        batch: p.batch,
        demo: p.demo,
    };
    let base = p.server.trim_end_matches('/');
    let url = HttpUrl::parse(&format!("{base}/api/episodes"))?;
    let body = serde_json::to_vec(&req)?;
    let mut headers = vec![("Content-Type".to_owned(), "application/json".to_owned())];
    if let Some(file) = &p.operator_token_file {
        let token = std::fs::read_to_string(file).with_context(|| format!("cannot read {}", file.display()))?;
        headers.push(("Authorization".to_owned(), format!("Bearer {}", token.trim())));
    }
    let resp = request("POST", &url, &headers, &body, Duration::from_secs(300))
        .with_context(|| format!("is `libero-agent serve` running at {base}?"))?;
    let text = String::from_utf8_lossy(&resp.body);
    if resp.status != 201 {
        let msg = serde_json::from_str::<serde_json::Value>(&text)
            .ok()
            .and_then(|v| v["error"].as_str().map(str::to_owned))
            .unwrap_or_else(|| text.into_owned());
        bail!("the server refused to prepare the episode (HTTP {}): {msg}", resp.status);
    }
    let v: serde_json::Value = serde_json::from_str(&text).context("server sent invalid JSON")?;
    println!("{}", serde_json::to_string_pretty(&v)?);
    Ok(())
}
