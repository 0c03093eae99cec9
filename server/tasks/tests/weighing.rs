//! T08 weigh_and_place_heaviest_mug on its real scene: the private masses reach the physics (and nothing else), and
//! the wrist force/torque sensor tells the mugs apart — the reading while a mug hangs still in the hand after the
//! expert's lift-and-hold orders the three mugs by mass.
use std::sync::Arc;

use libero_sim::compose::compose_file;
use libero_sim::placement::Placement;
use libero_sim::{AssetPaths, Simulation};
use libero_tasks::catalog::CheckerSpec;
use libero_tasks::families::perception::weighing::WeighingParams;
use libero_tasks::{Catalog, apply_private_model_edits, expert};

#[test]
fn the_wrist_force_after_lift_and_hold_orders_the_mugs_by_mass() {
    let catalog = Catalog::discover().unwrap();
    let t = catalog.get("T08").unwrap();
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let scene = compose_file(&catalog.dir.join(&t.bddl.path), &paths).unwrap();
    let mut model = scene.compile().unwrap();
    let placement = Placement::sample(&scene, 100, Some(&model)).unwrap();
    placement.apply(&mut model).unwrap();
    let checker: &CheckerSpec = &t.checker;
    apply_private_model_edits(Some(checker), Some("T08"), &mut model).unwrap();
    let params: WeighingParams = serde_json::from_value(checker.params.clone()).unwrap();
    let mut qpos = model.qpos0().to_vec();
    placement.write_qpos(&model, &mut qpos).unwrap();
    let mut sim = Simulation::new(Arc::new(model)).unwrap();
    let mut row = sim.state_row();
    row[1..1 + qpos.len()].copy_from_slice(&qpos);
    sim.set_init_state(&row).unwrap();
    for _ in 0..10 {
        sim.step([0.0; 7]).unwrap();
    }
    let norm = |f: [f64; 3]| (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt();
    let empty = sim.robot_state().wrist_force_n;

    let mut script = libero_tasks::expert_for("T08", expert::SOLVE, &scene, sim.model()).unwrap();
    let mut readings = Vec::new();
    let mut last_phase = script.phase();
    let mut steps = 0;
    while let Some(a) = script.act(&sim) {
        // the hold phase just ended: the mug has hung still in the hand for WEIGH_HOLD_STEPS
        if last_phase == Some(libero_tasks::families::perception::weigh_hold_phase()) && script.phase() != last_phase {
            let f = sim.robot_state().wrist_force_n;
            readings.push(norm([f[0] - empty[0], f[1] - empty[1], f[2] - empty[2]]));
        }
        last_phase = script.phase();
        sim.step(a).unwrap();
        steps += 1;
        assert!(steps < 3000, "the script ends");
        if readings.len() == 3 {
            break;
        }
    }
    assert_eq!(readings.len(), 3, "three mugs weighed");
    let masses: Vec<f64> = ["mug_1", "mug_2", "mug_3"].iter().map(|m| params.mugs[*m]).collect();
    for (i, (f, m)) in readings.iter().zip(&masses).enumerate() {
        eprintln!("mug_{}: {m} kg, wrist force change {f:.3} N (m·g = {:.3} N)", i + 1, m * 9.81);
    }
    let mut by_force: Vec<usize> = (0..3).collect();
    by_force.sort_by(|&a, &b| readings[a].total_cmp(&readings[b]));
    let mut by_mass: Vec<usize> = (0..3).collect();
    by_mass.sort_by(|&a, &b| masses[a].total_cmp(&masses[b]));
    assert_eq!(by_force, by_mass, "forces {readings:?} for masses {masses:?}");
    // and the reading is the weight, roughly
    for (f, m) in readings.iter().zip(&masses) {
        assert!((f - m * 9.81).abs() < 0.35 * m * 9.81 + 0.3, "force {f} N for {m} kg");
    }
}
