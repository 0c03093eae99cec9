//! Determinism contract: the same model, init state and actions give bit-identical states, also when
//! several simulations run on several threads at once.
mod common;

use std::sync::Arc;

use common::*;
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::{Simulation, replay};

const NAME: &str = "libero_90__KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet";
const STEPS: usize = 40;

fn run(model: &Arc<MjModel>, init: &[f64], actions: &[[f64; 7]]) -> Vec<Vec<u64>> {
    let mut sim = Simulation::new(model.clone()).expect("simulation");
    let t = replay(&mut sim, init, actions).expect("replay");
    t.qpos.iter().zip(&t.qvel).map(|(q, v)| q.iter().chain(v).map(|x| x.to_bits()).collect()).collect()
}

#[test]
fn repeated_and_concurrent_runs_are_bit_identical() {
    let g = load_golden(NAME);
    let model = golden_model(NAME, &g);
    let actions: Vec<[f64; 7]> = g.actions[..STEPS].to_vec();
    // Per-thread variations (different sign of the motion) so threads do not do identical work.
    let variants: Vec<Vec<[f64; 7]>> = (0..4)
        .map(|k| actions.iter().map(|a| { let mut b = *a; b[0] *= if k % 2 == 0 { 1.0 } else { -1.0 }; b[1] *= 1.0 - 0.1 * k as f64; b }).collect())
        .collect();
    let reference: Vec<_> = variants.iter().map(|v| run(&model, &g.init_state, v)).collect();
    assert_eq!(run(&model, &g.init_state, &variants[0]), reference[0], "two sequential runs differ");
    let handles: Vec<_> = variants
        .iter()
        .cloned()
        .map(|v| {
            let (model, init) = (model.clone(), g.init_state.clone());
            std::thread::spawn(move || run(&model, &init, &v))
        })
        .collect();
    for (k, h) in handles.into_iter().enumerate() {
        assert_eq!(h.join().expect("thread"), reference[k], "thread {k} differs from the single-thread run");
    }
}

/// Re-running on the same `Simulation` after `reset` gives the same states as a fresh one.
#[test]
fn reset_restores_a_fresh_simulation() {
    let g = load_golden(NAME);
    let model = golden_model(NAME, &g);
    let mut sim = Simulation::new(model.clone()).expect("simulation");
    let first = replay(&mut sim, &g.init_state, &g.actions[..10]).expect("replay");
    let second = replay(&mut sim, &g.init_state, &g.actions[..10]).expect("replay");
    assert_eq!(first, second);
}
