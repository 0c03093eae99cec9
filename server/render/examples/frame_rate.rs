//! Frames per second of both cameras × (RGB + depth) on one compiled scene (the renderer half of
//! `libero-agent bench render`): `cargo run -p libero-render --example frame_rate -- SCENE.xml [FRAMES]`.
use std::sync::Arc;
use std::time::Instant;

use libero_render::{CameraRequest, FrameState, Outputs, RenderOptions, Renderer};
use mujoco_rs::prelude::{MjData, MjModel};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let xml = std::env::args().nth(1).ok_or("usage: frame_rate SCENE.xml [FRAMES]")?;
    let frames: usize = std::env::args().nth(2).map(|s| s.parse()).transpose()?.unwrap_or(200);
    let cache = std::env::var_os("LIBERO_AGENT_CACHE")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::PathBuf::from(std::env::var("HOME").unwrap_or_default()).join(".cache/libero-agent"));
    let text = std::fs::read_to_string(&xml)?
        .replace("${ROBOSUITE_ASSETS}", &cache.join("robosuite-1.4.0/assets").to_string_lossy())
        .replace("${LIBERO_ASSETS}", &cache.join("libero-assets-0.1.0/assets").to_string_lossy());
    let mut model = MjModel::from_xml_string(&text)?;
    libero_render::scene::robosuite_hide_sites(&mut model);
    let model = Arc::new(model);
    let mut data = MjData::new(model.clone());
    data.forward();
    let renderer = Renderer::new()?;
    let handle = renderer.prepare_model(&model)?;
    let reqs: Vec<CameraRequest> = ["agentview", "robot0_eye_in_hand"]
        .iter()
        .map(|c| CameraRequest::named(c, 256, 256, Outputs::RGB_DEPTH))
        .collect();
    let opts = RenderOptions::default();
    for _ in 0..5 {
        renderer.render(&handle, &FrameState::from_mujoco(&model, &data), &reqs, &opts)?;
    }
    let t0 = Instant::now();
    for _ in 0..frames {
        let out = renderer.render(&handle, &FrameState::from_mujoco(&model, &data), &reqs, &opts)?;
        std::hint::black_box(out);
    }
    let wall = t0.elapsed().as_secs_f64();
    println!(
        "{{\"renderer\": \"{}\", \"frames\": {frames}, \"wall_s\": {wall:.3}, \"fps\": {:.2}}}",
        renderer.adapter_description(),
        frames as f64 / wall
    );
    Ok(())
}
