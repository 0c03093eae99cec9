//! `libero-agent demo replay-attack --task T21 [--task …] [--server URL | --data DIR]`: plays the agent that only
//! replays its demonstration. For each task it prepares a demonstration-conditioned episode (video + trajectory),
//! reads `benchmark_inputs/expert_demo/trajectory.jsonl` from the agent's workspace, sends every action through
//! `osc_sequence` (50 per call, as an agent would), finishes, and prints the verdict with the stages the replay
//! earned. The paper: "Direct replay of this trajectory does not solve the evaluation episode"; issue 48: nor may
//! it earn more than half the stages. The command exits non-zero if a replay succeeds or earns more than half.
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use libero_episode::demo::{DemoCondition, parse_action, read_json};
use libero_records::demo_manifest::{DemoManifest, ReplayCheck};
use libero_records::records::{PrivateEvaluation, RunDir, RunResult, ToolReply};
use libero_episode::expert_run::ToolPort;
use libero_episode::tools::MAX_MICRO_ACTIONS_PER_CALL;
use serde::Deserialize;
use serde_json::{Value, json};

use libero_server::client::{McpClient, prepare_episode};
use libero_server::default_data_dir;

use crate::cmd_expert::McpPort;
use libero_server::episodes::{Episodes, PrepareRequest};

#[derive(clap::Args, Debug)]
pub struct ReplayAttackArgs {
    /// Tasks to attack (repeatable, or comma-separated): `T21`, pool entries such as `libero_90/35`.
    #[arg(long, value_delimiter = ',', required = true)]
    pub task: Vec<String>,
    /// A running `libero-agent serve` on this machine (the workspace is read from its disk); otherwise the episodes
    /// run in this process under `--data`.
    #[arg(long)]
    pub server: Option<String>,
    #[arg(long)]
    pub data: Option<PathBuf>,
    #[arg(long, default_value_t = 100)]
    pub seed: u64,
    #[arg(long, default_value_t = 0)]
    pub init_index: usize,
}

/// A line of the trajectory the projection places in the workspace: only its action is read here.
#[derive(serde::Deserialize)]
struct TrajectoryRow {
    /// Null when the line has none (refused by [`parse_action`]).
    #[serde(default)]
    action: Value,
}

/// The projection receipt's bundle (the receipt is written by `libero_episode::demo::ProjectionReceipt`).
#[derive(serde::Deserialize)]
struct Receipt {
    source_bundle: PathBuf,
}

/// A stored replay check's target: the configuration it was replayed in.
#[derive(serde::Deserialize, Default)]
struct CheckTarget {
    #[serde(default)]
    effective_layout: Value,
}

impl CheckTarget {
    fn of(check: &ReplayCheck) -> Self {
        check.target.as_ref().and_then(|t| Self::deserialize(t).ok()).unwrap_or_default()
    }
}

/// The actions of an agent-visible trajectory, in order.
pub fn workspace_trajectory(workspace: &Path) -> anyhow::Result<Vec<[f64; 7]>> {
    let path = workspace.join("benchmark_inputs/expert_demo/trajectory.jsonl");
    let text = std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))?;
    text.lines()
        .enumerate()
        .map(|(n, line)| {
            let row: TrajectoryRow = serde_json::from_str(line).with_context(|| format!("{} line {}", path.display(), n + 1))?;
            parse_action(&row.action).with_context(|| format!("{} line {}: no 7-D action", path.display(), n + 1))
        })
        .collect()
}

/// Starts, sends `actions` in calls of at most 50, finishes; returns the finish payload.
pub fn replay(port: &mut dyn ToolPort, actions: &[[f64; 7]]) -> anyhow::Result<Value> {
    let start = port.call_tool("start_episode", json!({}))?;
    if !ToolReply::of(&start).is_ok() {
        bail!("start_episode refused: {start}");
    }
    for chunk in actions.chunks(MAX_MICRO_ACTIONS_PER_CALL) {
        let r = port.call_tool("osc_sequence", json!({"actions": chunk}))?;
        let reply = ToolReply::of(&r);
        // A refusal after the actions ran (no observation published) still says what ran: the replay goes on.
        if !reply.is_ok() && reply.execution.is_none() {
            bail!("osc_sequence refused: {r}");
        }
    }
    let finish = port.call_tool("finish_episode", json!({}))?;
    if !ToolReply::of(&finish).is_ok() {
        bail!("finish_episode refused: {finish}");
    }
    Ok(finish)
}

pub fn run(args: &ReplayAttackArgs) -> anyhow::Result<()> {
    let local = match &args.server {
        Some(_) => None,
        None => Some(Episodes::new(args.data.clone().unwrap_or_else(default_data_dir), "http://127.0.0.1:0".into())?),
    };
    let (mut solved, mut failed) = (Vec::new(), Vec::new());
    for task in &args.task {
        let t0 = Instant::now();
        match attack(args, local.as_ref(), task) {
            Ok(a) => {
                let (c, k) = (a.evaluation.completed_required_stage_count, a.evaluation.required_stage_count);
                let over_half = matches!((c, k), (Some(c), Some(k)) if 2 * c > k);
                println!(
                    "{}",
                    json!({
                        "task": task, "episode_id": a.episode_id, "replayed_actions": a.actions, "success": a.success,
                        "completed_required_stage_count": c, "required_stage_count": k,
                        "bundle": a.bundle, "stored_replay_check": a.check, "seconds": t0.elapsed().as_secs_f64(),
                    })
                );
                if a.success || over_half {
                    solved.push(task.clone());
                }
            }
            Err(e) => {
                println!("{}", json!({"task": task, "error": format!("{e:#}"), "seconds": t0.elapsed().as_secs_f64()}));
                failed.push(task.clone());
            }
        }
    }
    match (solved.is_empty(), failed.is_empty()) {
        (true, true) => Ok(()),
        (false, _) => bail!("direct replay of the demonstration solved or earned more than half the stages of {}", solved.join(", ")),
        (true, false) => bail!("no demonstration-conditioned episode could be replayed for {}", failed.join(", ")),
    }
}

/// What one attack got.
struct Attack {
    episode_id: String,
    actions: usize,
    success: bool,
    /// The evaluator's record of the replayed episode (its stages).
    evaluation: PrivateEvaluation,
    /// The library bundle the episode was shown, and the replay check stored in it for this episode.
    bundle: Option<String>,
    check: Option<Value>,
}

/// One task: prepare, replay the placed trajectory, finish, read the stages from the run directory.
fn attack(args: &ReplayAttackArgs, local: Option<&Episodes>, task: &str) -> anyhow::Result<Attack> {
    let request = PrepareRequest {
        level: 1,
        seed: args.seed,
        init_index: args.init_index,
        video: false,
        demo: DemoCondition::VideoTraj,
        ..PrepareRequest::new(task.to_owned())
    };
    eprintln!("[{task}] preparing a video+traj episode (the first one records a demonstration in another layout)");
    let (episode_id, run_dir, actions, finish) = match (local, &args.server) {
        (Some(episodes), _) => {
            let prepared = episodes.prepare(request)?;
            let mut handle = episodes.lifecycle().handle(&prepared.episode_id).context("the episode vanished")?;
            let actions = workspace_trajectory(&prepared.workspace)?;
            eprintln!("[{task}] replaying {} actions", actions.len());
            let finish = replay(&mut handle, &actions);
            (prepared.episode_id, prepared.run_dir, actions.len(), finish)
        }
        (None, Some(server)) => {
            let prepared = prepare_episode(server, &request)?;
            let token = prepared.mcp_headers.get("Authorization").context("no token in the server's reply")?;
            let mut port = McpPort(McpClient::connect_with_token(&prepared.mcp_url, token.trim_start_matches("Bearer "), "libero-agent-replay-attack")?);
            let actions = workspace_trajectory(&prepared.workspace)?;
            eprintln!("[{task}] replaying {} actions over MCP", actions.len());
            let finish = replay(&mut port, &actions);
            (prepared.episode_id, prepared.run_dir, actions.len(), finish)
        }
        (None, None) => unreachable!("either local or remote"),
    };
    let finish = finish.with_context(|| format!("replay in {episode_id}"))?;
    let success = ToolReply::of(&finish).success.context("finish_episode reported no success")?;
    let run = RunDir::new(&run_dir);
    let result = RunResult::from_value(read_json(&run.result_json())?).map_err(|e| anyhow::anyhow!("result.json: {e}"))?;
    let evaluation = result.private_evaluation.context("result.json has no private_evaluation")?;
    let (bundle, check) = shown_bundle(&run_dir, task, args).unwrap_or_default();
    Ok(Attack { episode_id, actions, success, evaluation, bundle, check })
}

/// The bundle the episode was shown (its projection receipt) and the replay check stored in it for the episode's
/// configuration.
fn shown_bundle(run_dir: &Path, task: &str, args: &ReplayAttackArgs) -> Option<(Option<String>, Option<Value>)> {
    let receipt: Receipt = serde_json::from_value(read_json(&run_dir.join("icl_projection_receipt.json")).ok()?).ok()?;
    let bundle = receipt.source_bundle;
    let manifest = DemoManifest::from_value(read_json(&bundle.join("manifest.json")).ok()?).ok()?;
    let paths = libero_sim::AssetPaths::discover().ok()?;
    let layout = libero_episode::task::resolve_task(task, &paths).ok()?.effective_layout(args.seed, args.init_index).ok()?;
    let layout = serde_json::to_value(layout).ok()?;
    let check = manifest.replay_checks?.iter().find(|c| CheckTarget::of(c).effective_layout == layout).map(ReplayCheck::to_value);
    Some((Some(bundle.display().to_string()), check))
}
