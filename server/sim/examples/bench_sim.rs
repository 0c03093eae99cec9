//! Quick release-mode run of `libero_sim::benchmark` without building the whole app
//! (`cargo run --release -p libero-sim --example bench_sim [STEPS]`); `libero-agent bench sim` is the
//! user-facing command.
use std::sync::Arc;

use libero_sim::benchmark::{BenchConfig, measure};
use libero_sim::model_overrides::compile_with_overrides;
use libero_sim::{AssetPaths, InitStates};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let scene = "libero_90__KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet";
    let steps = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(200);
    let golden = std::env::var_os("LIBERO_GOLDEN_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/reference/golden"));
    let paths = AssetPaths::discover()?;
    let xml = paths.substitute_placeholders(&std::fs::read_to_string(golden.join(format!("{scene}.mjcf_input.xml")))?);
    let model = Arc::new(compile_with_overrides(&xml, None)?);
    let init = InitStates::read(&paths.stock_init("libero_90", "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet"))?;
    let r = measure(scene, model, init.get(0)?, BenchConfig { steps, rounds: 5 })?;
    println!("{}", serde_json::to_string_pretty(&r)?);
    Ok(())
}
