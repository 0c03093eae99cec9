//! Helpers shared by the tasks crate's scene tests.
use std::path::Path;
use std::sync::Arc;

use libero_sim::compose::{ComposedScene, compose_file};
use libero_sim::placement::Placement;
use libero_sim::{AssetPaths, Simulation};

/// A task scene composed from `bddl`, placed with LIBERO's seed-100 sampler (the seed the release tasks without
/// trusted init states use), and a simulation starting from that placement.
pub fn scene_and_sim(bddl: &Path) -> (ComposedScene, Simulation) {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let scene = compose_file(bddl, &paths).unwrap();
    let mut model = scene.compile().unwrap();
    let placement = Placement::sample(&scene, 100, Some(&model)).unwrap();
    placement.apply(&mut model).unwrap();
    let mut qpos = model.qpos0().to_vec();
    placement.write_qpos(&model, &mut qpos).unwrap();
    let mut sim = Simulation::new(Arc::new(model)).unwrap();
    let mut row = sim.state_row();
    row[1..1 + qpos.len()].copy_from_slice(&qpos);
    sim.set_init_state(&row).unwrap();
    (scene, sim)
}
