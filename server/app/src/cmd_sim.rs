//! `libero-agent sim replay`: run an action sequence on a LIBERO scene from an init state and write
//! the per-step trajectory as JSON (golden-file field names), for parity checks and debugging.
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Deserialize;
use anyhow::{Context, bail};
use libero_sim::model_overrides::{RuntimeOverrides, compile_with_overrides};
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::scene_setup::PreparedScene;
use libero_sim::{AssetPaths, InitStates, Simulation, replay};

#[derive(clap::Args, Debug, Clone)]
#[command(group(clap::ArgGroup::new("scene").required(true).args(["bddl", "xml"])))]
pub struct ReplayArgs {
    /// LIBERO BDDL problem file: composed, compiled and placed as LIBERO's `env.reset()` does.
    #[arg(long)]
    pub bddl: Option<PathBuf>,
    /// LIBERO's `env.seed` for the reset-time fixture placement with `--bddl` (the golden files use 0;
    /// served episodes use the seed they were prepared with, 100 by default).
    #[arg(long, default_value_t = 0)]
    pub seed: u32,
    /// Compiled scene MJCF instead of a BDDL file (e.g. a golden `.mjcf_input.xml`);
    /// `${ROBOSUITE_ASSETS}`/`${LIBERO_ASSETS}` are substituted.
    #[arg(long)]
    pub xml: Option<PathBuf>,
    /// Golden JSON whose `runtime_model_overrides` (fixture poses, site colours) are applied to an `--xml`
    /// model; also supplies the init state when `--init-file` is absent.
    #[arg(long)]
    pub golden: Option<PathBuf>,
    /// LIBERO `.pruned_init` file. Without it a `--bddl` replay starts from the seeded placement.
    #[arg(long)]
    pub init_file: Option<PathBuf>,
    /// Row of the init file.
    #[arg(long, default_value_t = 0)]
    pub init_index: usize,
    /// JSON array of 7-vectors, or a golden JSON (its `actions`).
    #[arg(long)]
    pub actions: PathBuf,
    /// Output trajectory JSON (`steps` holds the golden files' per-step fields).
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(clap::Subcommand, Debug, Clone)]
pub enum SimCommand {
    /// Replay actions from an init state and write the trajectory.
    Replay(ReplayArgs),
    /// Print the composed scene (bodies, joints, geoms, cameras, sites, masses) as JSON.
    Inspect(crate::cmd_inspect::InspectArgs),
}

pub fn run_sim(cmd: &SimCommand) -> anyhow::Result<()> {
    match cmd {
        SimCommand::Replay(a) => run_replay(a),
        SimCommand::Inspect(a) => crate::cmd_inspect::run(a),
    }
}

fn read_json(path: &Path) -> anyhow::Result<serde_json::Value> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_slice(&bytes).with_context(|| format!("{} is not valid JSON", path.display()))
}

/// Actions from a plain array or from a golden file's `actions`.
pub fn parse_actions(v: &serde_json::Value) -> anyhow::Result<Vec<[f64; 7]>> {
    let list = v.get("actions").unwrap_or(v);
    let arr = list.as_array().context("actions must be a JSON array of 7-element arrays")?;
    arr.iter()
        .enumerate()
        .map(|(i, a)| {
            let xs = a.as_array().with_context(|| format!("action {i} is not an array"))?;
            if xs.len() != 7 {
                bail!("action {i} has {} components, OSC_POSE needs 7", xs.len());
            }
            let mut out = [0.0; 7];
            for (k, x) in xs.iter().enumerate() {
                out[k] = x.as_f64().with_context(|| format!("action {i} component {k} is not a number"))?;
            }
            Ok(out)
        })
        .collect()
}

/// Reads and compiles a scene MJCF, substituting asset placeholders when present.
pub fn load_scene(xml_path: &Path, overrides: Option<&RuntimeOverrides>) -> anyhow::Result<Arc<libero_sim::mujoco_rs::prelude::MjModel>> {
    let mut xml = std::fs::read_to_string(xml_path).with_context(|| format!("reading {}", xml_path.display()))?;
    if xml.contains("${ROBOSUITE_ASSETS}") || xml.contains("${LIBERO_ASSETS}") {
        xml = AssetPaths::discover()?.substitute_placeholders(&xml);
    }
    Ok(Arc::new(compile_with_overrides(&xml, overrides).with_context(|| format!("compiling {}", xml_path.display()))?))
}

/// A golden file of `tests/reference` as far as a replay reads it: the recording's model overrides and start state
/// (kept as JSON here, so that each is parsed with its own error; a file of another shape has neither).
#[derive(serde::Deserialize, Default)]
struct Golden {
    #[serde(default)]
    runtime_model_overrides: Option<serde_json::Value>,
    #[serde(default)]
    init_state: Option<serde_json::Value>,
}

/// The model and start row of a replay, from `--bddl` or from `--xml` (+ `--golden`).
fn replay_scene(args: &ReplayArgs, golden: Option<&Golden>) -> anyhow::Result<(Arc<MjModel>, Vec<f64>)> {
    if let Some(bddl) = &args.bddl {
        if args.golden.is_some() && args.init_file.is_none() {
            bail!("with --bddl give the init state as --init-file (a golden file is only read for --actions)");
        }
        let paths = AssetPaths::discover()?;
        let init = args.init_file.as_deref().map(|f| (f, args.init_index));
        let prepared = PreparedScene::prepare(bddl, &paths, args.seed, init)
            .with_context(|| format!("setting up {}", bddl.display()))?;
        return Ok((Arc::new(prepared.model), prepared.start_row));
    }
    let xml = args.xml.as_deref().context("give --bddl FILE or --xml FILE")?;
    let overrides: Option<RuntimeOverrides> = match golden.and_then(|g| g.runtime_model_overrides.as_ref()) {
        Some(o) => Some(serde_json::from_value(o.clone()).context("golden runtime_model_overrides")?),
        None => None,
    };
    let model = load_scene(xml, overrides.as_ref())?;
    let init_row: Vec<f64> = match (&args.init_file, golden) {
        (Some(f), _) => InitStates::read(f)?.get(args.init_index)?.to_vec(),
        (None, Some(g)) => serde_json::from_value(g.init_state.clone().context("golden has no init_state")?)
            .context("golden init_state")?,
        (None, None) => bail!("give --init-file (or --golden with an init_state)"),
    };
    Ok((model, init_row))
}

pub fn run_replay(args: &ReplayArgs) -> anyhow::Result<()> {
    let golden = args.golden.as_deref().map(read_json).transpose()?.map(|g| Golden::deserialize(g).unwrap_or_default());
    // Parse the actions before the (slow) scene set-up so a bad file fails at once.
    let actions = parse_actions(&read_json(&args.actions)?)?;
    let (model, init_row) = replay_scene(args, golden.as_ref())?;
    let mut sim = Simulation::new(model)?;
    let traj = replay(&mut sim, &init_row, &actions)?;
    let doc = serde_json::json!({
        "format": "libero-agent.trajectory.v1",
        "bddl": args.bddl,
        "xml": args.xml,
        "seed": args.bddl.as_ref().map(|_| args.seed),
        "init_file": args.init_file,
        "init_state_index": args.init_file.as_ref().map(|_| args.init_index),
        "init_state": init_row,
        "actions": actions,
        "steps": traj,
    });
    let json = serde_json::to_vec(&doc)?;
    std::fs::write(&args.out, json).with_context(|| format!("writing {}", args.out.display()))?;
    eprintln!("replayed {} steps → {}", actions.len(), args.out.display());
    Ok(())
}
