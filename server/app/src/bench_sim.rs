//! `libero-agent bench sim`: cost of the OSC_POSE loop on top of MuJoCo (see `libero_sim::benchmark`).
use std::path::PathBuf;

use anyhow::Context;
use libero_sim::benchmark::{BenchConfig, measure};
use libero_sim::{AssetPaths, InitStates};

const SCENE: &str = "libero_90__KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet";

#[derive(clap::Args, Debug, Clone)]
pub struct BenchSimArgs {
    /// Print the result as JSON only.
    #[arg(long)]
    pub json: bool,
    /// Control steps per measurement round.
    #[arg(long, default_value_t = 200)]
    pub steps: usize,
    /// Measurement rounds (the best is reported).
    #[arg(long, default_value_t = 5)]
    pub rounds: usize,
    /// Scene MJCF; default: the golden KITCHEN_SCENE10 `.mjcf_input.xml` of shared/reference/golden.
    #[arg(long)]
    pub xml: Option<PathBuf>,
}

fn default_scene_xml() -> anyhow::Result<PathBuf> {
    let file = format!("{SCENE}.mjcf_input.xml");
    let mut candidates = Vec::new();
    if let Some(d) = std::env::var_os("LIBERO_GOLDEN_DIR") {
        candidates.push(PathBuf::from(d).join(&file));
    }
    candidates.push(PathBuf::from("shared/reference/golden").join(&file));
    candidates.push(PathBuf::from("../shared/reference/golden").join(&file));
    candidates.push(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/reference/golden").join(&file));
    candidates
        .into_iter()
        .find(|p| p.is_file())
        .with_context(|| format!("cannot find {file}; pass --xml or set LIBERO_GOLDEN_DIR"))
}

pub fn run(args: &BenchSimArgs) -> anyhow::Result<()> {
    let result = measure_cli(args)?;
    if args.json {
        println!("{}", serde_json::to_string(&result)?);
    } else {
        println!("{}", serde_json::to_string_pretty(&result)?);
    }
    Ok(())
}

fn measure_cli(args: &BenchSimArgs) -> anyhow::Result<libero_sim::benchmark::BenchSimResult> {
    let xml_path = match &args.xml {
        Some(p) => p.clone(),
        None => default_scene_xml()?,
    };
    let model = crate::cmd_sim::load_scene(&xml_path, None)?;
    let paths = AssetPaths::discover()?;
    let init = InitStates::read(&paths.stock_init("libero_90", "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet"))?;
    let cfg = BenchConfig { steps: args.steps, rounds: args.rounds };
    Ok(measure(SCENE, model, init.get(0)?, cfg)?)
}
