//! `libero-agent sim replay`: run an action sequence on a LIBERO scene from an init state and write
//! the per-step trajectory as JSON (golden-file field names), for parity checks and debugging.
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, bail};
use libero_sim::model_overrides::{RuntimeOverrides, compile_with_overrides};
use libero_sim::{AssetPaths, InitStates, Simulation, replay};

#[derive(clap::Args, Debug, Clone)]
pub struct ReplayArgs {
    /// Scene MJCF (e.g. a golden `.mjcf_input.xml`); `${ROBOSUITE_ASSETS}`/`${LIBERO_ASSETS}` are substituted.
    #[arg(long)]
    pub xml: PathBuf,
    /// Golden JSON whose `runtime_model_overrides` (fixture poses, site colours) are applied to the model;
    /// also supplies the init state when `--init-file` is absent.
    #[arg(long)]
    pub golden: Option<PathBuf>,
    /// LIBERO `.pruned_init` file.
    #[arg(long)]
    pub init_file: Option<PathBuf>,
    /// Row of the init file.
    #[arg(long, default_value_t = 0)]
    pub init_index: usize,
    /// JSON array of 7-vectors, or a golden JSON (its `actions`).
    #[arg(long)]
    pub actions: PathBuf,
    /// Output trajectory JSON.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(clap::Subcommand, Debug, Clone)]
pub enum SimCommand {
    /// Replay actions from an init state and write the trajectory.
    Replay(ReplayArgs),
}

pub fn run_sim(cmd: &SimCommand) -> anyhow::Result<()> {
    match cmd {
        SimCommand::Replay(a) => run_replay(a),
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

pub fn run_replay(args: &ReplayArgs) -> anyhow::Result<()> {
    let golden = args.golden.as_deref().map(read_json).transpose()?;
    let overrides: Option<RuntimeOverrides> = match &golden {
        Some(g) => match g.get("runtime_model_overrides") {
            Some(o) => Some(serde_json::from_value(o.clone()).context("golden runtime_model_overrides")?),
            None => None,
        },
        None => None,
    };
    let model = load_scene(&args.xml, overrides.as_ref())?;
    let init_row: Vec<f64> = match (&args.init_file, &golden) {
        (Some(f), _) => InitStates::read(f)?.get(args.init_index)?.to_vec(),
        (None, Some(g)) => serde_json::from_value(g.get("init_state").cloned().context("golden has no init_state")?)
            .context("golden init_state")?,
        (None, None) => bail!("give --init-file (or --golden with an init_state)"),
    };
    let actions = parse_actions(&read_json(&args.actions)?)?;
    let mut sim = Simulation::new(model)?;
    let traj = replay(&mut sim, &init_row, &actions)?;
    let json = serde_json::to_vec(&traj)?;
    std::fs::write(&args.out, json).with_context(|| format!("writing {}", args.out.display()))?;
    eprintln!("replayed {} steps → {}", actions.len(), args.out.display());
    Ok(())
}
