//! `libero-agent bench sim`: cost of the OSC_POSE loop on top of MuJoCo (see `libero_sim::benchmark`).
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;
use libero_sim::benchmark::{BenchConfig, measure};
use libero_sim::scene_setup::PreparedScene;
use libero_sim::{AssetPaths, InitStates};

const SUITE: &str = "libero_90";
const TASK: &str = "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet";

#[derive(clap::Args, Debug, Clone)]
pub struct BenchSimArgs {
    /// Print the result as one line of JSON.
    #[arg(long)]
    pub json: bool,
    /// Control steps per measurement round.
    #[arg(long, default_value_t = 200)]
    pub steps: usize,
    /// Measurement rounds (the best is reported).
    #[arg(long, default_value_t = 5)]
    pub rounds: usize,
    /// Scene MJCF instead of the default LIBERO kitchen scene 10 composed from its stock BDDL.
    #[arg(long)]
    pub xml: Option<PathBuf>,
    /// Python of the reference LIBERO stack (`scripts/reference_stack/setup.sh`) whose `env.step` is measured
    /// as the peer in the same run; default: `<cache>/refstack/bin/python` when it exists.
    #[arg(long)]
    pub libero_python: Option<PathBuf>,
    /// Skip the LIBERO `env.step` peer.
    #[arg(long)]
    pub no_libero: bool,
}

pub fn run(args: &BenchSimArgs) -> anyhow::Result<()> {
    let ours = measure_cli(args)?;
    let mut result = serde_json::to_value(&ours)?;
    if args.xml.is_none() && !args.no_libero {
        let peer = libero_peer(args);
        if let Some(rate) = peer.get("env_step_per_s").and_then(serde_json::Value::as_f64) {
            result["speedup_vs_libero_env_step"] = serde_json::json!(ours.control_steps_per_s / rate);
        }
        result["libero_env_step"] = peer;
    }
    if args.json {
        println!("{}", serde_json::to_string(&result)?);
    } else {
        println!("{}", serde_json::to_string_pretty(&result)?);
    }
    Ok(())
}

fn measure_cli(args: &BenchSimArgs) -> anyhow::Result<libero_sim::benchmark::BenchSimResult> {
    let paths = AssetPaths::discover()?;
    let init_file = paths.stock_init(SUITE, TASK);
    let (name, model, start_row) = match &args.xml {
        Some(xml) => {
            let init = InitStates::read(&init_file)?;
            (xml.display().to_string(), crate::cmd_sim::load_scene(xml, None)?, init.get(0)?.to_vec())
        }
        None => {
            let bddl = paths.stock_bddl(SUITE, TASK);
            let prepared = PreparedScene::prepare(&bddl, &paths, 0, Some((&init_file, 0)))
                .with_context(|| format!("setting up {}", bddl.display()))?;
            (format!("{SUITE}/{TASK}"), Arc::new(prepared.model), prepared.start_row)
        }
    };
    let cfg = BenchConfig { steps: args.steps, rounds: args.rounds };
    Ok(measure(&name, model, &start_row, cfg)?)
}

/// LIBERO's own `env.step` rate on the same scene, measured now by `scripts/reference_stack/bench_env_step.py`
/// under the reference venv; an object with `skipped` when the stack is not installed or the run fails.
fn libero_peer(args: &BenchSimArgs) -> serde_json::Value {
    let python = args.libero_python.clone().unwrap_or_else(|| libero_sim::paths::cache_dir().join("refstack/bin/python"));
    if !python.is_file() {
        return serde_json::json!({"skipped": format!(
            "{} not found; install the reference stack with scripts/reference_stack/setup.sh", python.display())});
    }
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../scripts/reference_stack/bench_env_step.py");
    eprintln!("measuring LIBERO's env.step with {} …", python.display());
    let out = std::process::Command::new(&python)
        .arg(&script)
        .args(["--suite", SUITE, "--task", TASK, "--steps", &args.steps.to_string(), "--rounds", &args.rounds.min(3).to_string()])
        .output();
    match out {
        Ok(o) if o.status.success() => {
            let text = String::from_utf8_lossy(&o.stdout);
            text.lines()
                .rev()
                .find_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
                .unwrap_or_else(|| serde_json::json!({"skipped": "the reference script printed no JSON"}))
        }
        Ok(o) => serde_json::json!({"skipped": format!("reference script failed ({}): {}", o.status,
            String::from_utf8_lossy(&o.stderr).lines().last().unwrap_or(""))}),
        Err(e) => serde_json::json!({"skipped": format!("cannot run {}: {e}", python.display())}),
    }
}
