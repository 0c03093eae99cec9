//! `libero-agent episode prepare`: asks a running server to prepare an episode and prints its JSON
//! (episode_id, mcp_url, mcp_headers, workspace, prompt_file, …).
use std::path::PathBuf;

use libero_episode::demo::DemoCondition;

use libero_server::episodes::PrepareRequest;
use libero_server::client::prepare_episode;

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
    /// Release task (T11), pool entry (`libero_90/35`, `robomemarena/18`, `suite/name`; see `tasks list --tasks all`)
    /// or a .bddl path.
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
    /// File holding the server's operator token (default: the token the server registered for this user).
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
        layout: None,
        branch: None,
    };
    if let Some(file) = &p.operator_token_file {
        libero_server::credential::use_token_file(file);
    }
    let prepared = prepare_episode(&p.server, &req)?;
    println!("{}", serde_json::to_string_pretty(&prepared)?);
    Ok(())
}
