//! `libero-agent demo …`: demonstration bundles (protocol §7). `record` turns a finished episode's run directory
//! into a bundle, `verify` replays one and marks it verified only if the evaluator's success is reproduced,
//! `validate` applies §7.7's rules, `export-lerobot` writes a LeRobot v3 dataset.
use std::path::PathBuf;

use anyhow::{Context, bail};
use libero_episode::demo::lerobot::export_lerobot;
use libero_episode::demo::project::validate_projection;
use libero_episode::demo::record::RecordOptions;
use libero_episode::demo::{DemoCondition, record_bundle, validate_bundle, verify_bundle};
use libero_sim::AssetPaths;
use serde_json::json;

#[derive(clap::Args, Debug)]
pub struct DemoArgs {
    #[command(subcommand)]
    pub command: DemoCommand,
}

#[derive(clap::Subcommand, Debug)]
pub enum DemoCommand {
    /// Record a bundle from a finished episode's private run directory (replayed and rendered, then verified).
    Record {
        /// The episode's run directory (`<data>/runs/<episode id>`).
        #[arg(long)]
        run_dir: PathBuf,
        /// The bundle directory to create.
        #[arg(long)]
        out: PathBuf,
        /// Who produced the actions: scripted_expert, human_teleop, agent.
        #[arg(long, default_value = "agent")]
        source_type: String,
        #[arg(long, default_value = "")]
        source_desc: String,
    },
    /// Replay a bundle's actions from its init state; mark it verified only if the evaluator's success is reproduced.
    Verify { dir: PathBuf },
    /// Check a bundle against the §7.7 rules; every failure names its file and rule. `--agent video|video+traj`
    /// checks an agent-visible copy (`benchmark_inputs/expert_demo/`) instead.
    Validate {
        dir: PathBuf,
        #[arg(long)]
        agent: Option<String>,
    },
    /// Play the agent that only replays its demonstration, on demonstration-conditioned episodes of each task;
    /// fails if a replay solves its episode (the paper: direct replay must not solve the evaluation episode).
    ReplayAttack(crate::cmd_demo_replay::ReplayAttackArgs),
    /// Export bundles to a LeRobot v3 dataset.
    ExportLerobot {
        #[arg(required = true)]
        dirs: Vec<PathBuf>,
        #[arg(long)]
        out: PathBuf,
    },
}

fn paths() -> anyhow::Result<AssetPaths> {
    AssetPaths::discover().context("assets are missing; run `python3 scripts/setup.py`")
}

pub fn run(args: DemoArgs) -> anyhow::Result<()> {
    match args.command {
        DemoCommand::Record { run_dir, out, source_type, source_desc } => {
            let renderer = libero_render::Renderer::new().context("cannot open a GPU for rendering")?;
            let s = record_bundle(&run_dir, &out, &RecordOptions { source_type, source_desc }, renderer, &paths()?)?;
            println!(
                "{}",
                json!({"dir": s.dir, "frame_count": s.frame_count, "transition_count": s.transition_count,
                       "source_success": s.source_success, "replay_success": s.replay_success, "verified": s.verified})
            );
            if !s.verified {
                bail!("{} was recorded but is not verified (source success {:?}, replay success {})", out.display(), s.source_success, s.replay_success);
            }
        }
        DemoCommand::Verify { dir } => {
            let violations = validate_bundle(&dir);
            if !violations.is_empty() {
                bail!("{} is not a valid bundle, so it is not replayed:\n{}", dir.display(), lines(&violations));
            }
            let success = verify_bundle(&dir, &paths()?)?;
            println!("{}", json!({"dir": dir, "replay_success": success, "verified": success}));
            if !success {
                bail!("the replay of {} does not reproduce success; the bundle is marked unverified", dir.display());
            }
        }
        DemoCommand::Validate { dir, agent } => {
            let violations = match agent.as_deref() {
                None => validate_bundle(&dir),
                Some(c) => match DemoCondition::parse(c) {
                    Some(c @ (DemoCondition::Video | DemoCondition::VideoTraj)) => validate_projection(&dir, c),
                    _ => bail!("--agent must be video or video+traj"),
                },
            };
            if !violations.is_empty() {
                bail!("{} breaks {} rule(s):\n{}", dir.display(), violations.len(), lines(&violations));
            }
            println!("{}", json!({"dir": dir, "valid": true}));
        }
        DemoCommand::ReplayAttack(a) => crate::cmd_demo_replay::run(&a)?,
        DemoCommand::ExportLerobot { dirs, out } => {
            let s = export_lerobot(&dirs, &out)?;
            println!("{}", json!({"out": s.out, "episodes": s.episodes, "frames": s.frames, "tasks": s.tasks}));
        }
    }
    Ok(())
}

fn lines(v: &[libero_episode::demo::Violation]) -> String {
    v.iter().map(|v| format!("  {v}")).collect::<Vec<_>>().join("\n")
}
