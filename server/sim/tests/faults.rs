//! Faults are values: MuJoCo errors and numerical blow-ups end one simulation, never the process.
mod common;

use std::sync::Arc;

use common::*;
use libero_sim::fault::{ffi, guarded};
use libero_sim::mujoco_rs::prelude::*;
use libero_sim::{SimError, Simulation};

const NAME: &str = "libero_90__KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet";

fn sim_and_init() -> (Simulation, Vec<f64>, Arc<MjModel>) {
    let g = load_golden(NAME);
    let model = golden_model(NAME, &g);
    (Simulation::new(model.clone()).expect("simulation"), g.init_state, model)
}

/// An invalid state signature is checked by MuJoCo with `mju_error` (its default handler would exit).
fn provoke_mujoco_error(data: &libero_sim::simulation::SimData) {
    let mut buf = vec![0.0; 4096];
    unsafe { ffi::mj_getState(data.model().ffi(), data.ffi(), buf.as_mut_ptr(), 1 << 30) };
}

/// Two successive MuJoCo errors raised on the same thread are both caught (MuJoCo keeps no recursion
/// guard that would swallow or escalate the second one).
#[test]
fn two_successive_mujoco_errors_are_both_caught() {
    let (sim, _, _) = sim_and_init();
    for attempt in 0..2 {
        let err = guarded(|| provoke_mujoco_error(sim.data())).expect_err("MuJoCo must raise an error");
        assert!(err.contains("mj_getState") || err.to_lowercase().contains("sig"), "attempt {attempt}: {err}");
    }
}

/// A MuJoCo error inside a control step becomes `SimError::Fault`, poisons that simulation (every
/// later call returns the same fault), and a new simulation on the same model works normally.
#[test]
fn mujoco_error_during_step_poisons_only_that_simulation() {
    let (mut sim, init, model) = sim_and_init();
    sim.set_init_state(&init).expect("init state");
    sim.step([0.0; 7]).expect("a normal step");
    let err = sim
        .step_with([0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], |k, data| {
            if k == 3 {
                provoke_mujoco_error(data);
            }
        })
        .expect_err("the provoked error must surface");
    let SimError::Fault(msg) = &err else { panic!("expected a fault, got {err:?}") };
    assert!(sim.fault().is_some());
    for later in [sim.step([0.0; 7]).unwrap_err(), sim.reset().unwrap_err(), sim.forward().unwrap_err()] {
        assert!(matches!(&later, SimError::Fault(m) if m == msg), "later call must repeat the fault: {later:?}");
    }
    // A second fault in a second simulation is caught as well, and a third simulation still steps.
    let mut second = Simulation::new(model.clone()).expect("second simulation");
    assert!(second.step_with([0.0; 7], |_, d| provoke_mujoco_error(d)).is_err());
    let mut fresh = Simulation::new(model).expect("fresh simulation");
    fresh.set_init_state(&init).expect("init state");
    for _ in 0..3 {
        fresh.step([0.2, 0.0, -0.1, 0.0, 0.0, 0.0, -1.0]).expect("healthy simulation keeps working");
    }
}

/// A non-finite velocity (MuJoCo would silently reset the state with a warning) is reported as a fault.
#[test]
fn nan_state_is_reported_as_fault() {
    let (mut sim, init, _) = sim_and_init();
    sim.set_init_state(&init).expect("init state");
    sim.step([0.0; 7]).expect("a normal step");
    sim.inject_qvel(2, f64::NAN);
    let err = sim.step([0.0; 7]).expect_err("NaN must be detected");
    assert!(matches!(err, SimError::Fault(_)), "{err:?}");
    assert!(sim.step([0.0; 7]).is_err(), "poisoned after the fault");
}

/// A model whose arena is far too small overflows MuJoCo's stack in the first `mj_forward`: the
/// simulation cannot be created, and the error says why instead of ending the process.
#[test]
fn arena_overflow_is_a_fault_not_an_exit() {
    let path = golden_dir().join(format!("{NAME}.mjcf_input.xml"));
    let xml = assets().substitute_placeholders(&std::fs::read_to_string(path).unwrap());
    let xml = xml.replace("<size nconmax=\"5000\" njmax=\"5000\" />", "<size memory=\"20K\" />");
    assert!(xml.contains("memory=\"20K\""), "size element not found in the golden MJCF");
    let model = Arc::new(libero_sim::model_overrides::compile_with_overrides(&xml, None).expect("compiles"));
    match Simulation::new(model) {
        Err(SimError::Fault(msg)) => println!("caught: {msg}"),
        Err(other) => panic!("expected a fault, got {other:?}"),
        Ok(mut sim) => {
            let err = sim.step([0.0; 7]).expect_err("a 20 KiB arena cannot hold a step");
            println!("caught: {err}");
        }
    }
}

/// Non-finite actions and wrong-length init states are input errors, not faults.
#[test]
fn bad_inputs_are_input_errors() {
    let (mut sim, init, _) = sim_and_init();
    assert!(matches!(sim.set_init_state(&init[1..]), Err(SimError::Input(_))));
    assert!(matches!(sim.step([f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]), Err(SimError::Input(_))));
    sim.step([0.0; 7]).expect("still usable after input errors");
}

/// The step observer (the private video's hook) sees every completed control step, after its last
/// substep, and never a step that faulted.
#[test]
fn the_step_observer_sees_each_completed_step_and_no_faulted_one() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let (mut sim, init, _) = sim_and_init();
    sim.set_init_state(&init).expect("init state");
    let seen = Arc::new(AtomicUsize::new(0));
    let times = Arc::new(std::sync::Mutex::new(Vec::new()));
    let (s, t) = (seen.clone(), times.clone());
    let poses = Arc::new(std::sync::Mutex::new(Vec::new()));
    let p = poses.clone();
    sim.set_step_observer(Some(Box::new(move |_, data, pose_qpos: &[f64]| {
        s.fetch_add(1, Ordering::SeqCst);
        t.lock().unwrap().push(data.ffi().time);
        // The poses in data come from the qpos before the last substep's integration, not from data's qpos.
        assert_eq!(pose_qpos.len(), data.qpos().len());
        p.lock().unwrap().push((pose_qpos.to_vec(), data.qpos().to_vec(), data.xpos().to_vec()));
    })));
    for _ in 0..3 {
        let outcome = sim.step([0.1, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]).expect("a normal step");
        assert_eq!(times.lock().unwrap().last().copied(), Some(outcome.time_s), "observed after the last substep");
    }
    assert_eq!(seen.load(Ordering::SeqCst), 3);
    let mut replay = libero_sim::PoseReplay::new(sim.model().clone());
    for (pose_qpos, qpos, xpos) in poses.lock().unwrap().iter() {
        assert_ne!(pose_qpos, qpos, "a moving arm's qpos changes in the last substep");
        let again = replay.pose(pose_qpos, &[]).expect("replayed pose");
        assert_eq!(again.xpos().iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>(), xpos.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>(), "the poses are recomputed bit for bit");
    }
    assert!(replay.pose(&[0.0; 3], &[]).is_err(), "a pose of the wrong size is refused");
    sim.inject_qvel(2, f64::NAN);
    assert!(sim.step([0.0; 7]).is_err());
    assert_eq!(seen.load(Ordering::SeqCst), 3, "a faulted step is not observed");
    sim.set_step_observer(None);
}
