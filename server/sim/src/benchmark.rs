//! Cost of the OSC_POSE control loop relative to MuJoCo itself (`libero-agent bench sim`).
//!
//! On one scene it times (a) our control loop (25 × controller + physics per control step) on a fixed
//! action sequence, (b) raw `mj_step` replaying the exact per-substep controls (a) produced — the same
//! trajectory, so the same contacts and solver work — and (c) raw `mj_step` from the same initial state
//! with the controls held. `cost_ratio` = time per control step of (a) ÷ time of 25 raw steps of (b).
//! Times are the thread's on-CPU time when Linux provides it (machines may be shared), else wall time;
//! each figure is the best of several interleaved rounds.
use std::sync::Arc;
use std::time::Instant;

use mujoco_rs::prelude::*;
use serde::Serialize;

use crate::controller::{ArmStateReader, OscPose, Vector7};
use crate::robot::SUBSTEPS_PER_ACTION;
use crate::simulation::SimData;
use crate::{SimError, Simulation};

#[derive(Debug, Serialize)]
pub struct BenchSimResult {
    pub scene: String,
    pub nq: i64,
    pub nv: i64,
    pub control_steps: usize,
    pub clock: &'static str,
    pub build: &'static str,
    /// Our loop: control steps per second.
    pub control_steps_per_s: f64,
    pub us_per_control_step: f64,
    /// Raw mj_step on the same trajectory (recorded controls), per second and ÷ 25.
    pub raw_mj_step_per_s: f64,
    pub raw_control_equiv_per_s: f64,
    pub us_per_25_raw_steps: f64,
    /// Our time per control step ÷ time of 25 raw mj_step calls on the same trajectory.
    pub cost_ratio: f64,
    /// Raw mj_step from the same initial state with the controls held (a different trajectory).
    pub raw_held_ctrl_mj_step_per_s: f64,
    pub cost_ratio_vs_held_ctrl: f64,
    /// The controller alone (state read from mjData + OSC torque law), per substep: the deterministic
    /// part of the overhead, unaffected by how noisy the end-to-end timings are on a shared machine.
    pub controller_us_per_substep: f64,
    /// `controller_us_per_substep` ÷ raw µs per `mj_step`.
    pub controller_share_of_raw_step: f64,
}

/// How many control steps per round and how many rounds.
#[derive(Debug, Clone, Copy)]
pub struct BenchConfig {
    pub steps: usize,
    pub rounds: usize,
}

/// On-CPU nanoseconds of this thread (Linux), if available.
fn thread_cpu_ns() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse().ok()
}

struct Clock {
    cpu: bool,
}

impl Clock {
    fn time<R>(&self, f: impl FnOnce() -> R) -> (f64, R) {
        if self.cpu {
            let a = thread_cpu_ns().unwrap_or(0);
            let r = f();
            let b = thread_cpu_ns().unwrap_or(0);
            ((b - a) as f64 * 1e-9, r)
        } else {
            let t = Instant::now();
            let r = f();
            (t.elapsed().as_secs_f64(), r)
        }
    }
}

/// The golden generator's sequence A (smooth sinusoids, gripper toggling every 15 steps).
pub fn sequence_a_action(t: usize) -> [f64; 7] {
    if t < 5 {
        return [0.0; 7];
    }
    let k = (t - 5) as f64;
    let grip = if ((t - 5) / 15) % 2 == 0 { 1.0 } else { -1.0 };
    [
        0.6 * (k / 5.0).sin(),
        0.5 * (k / 7.0).cos(),
        -0.4 + 0.3 * (k / 11.0).sin(),
        0.3 * (k / 9.0).sin(),
        0.2 * (k / 6.0).cos(),
        -0.25 * (k / 4.0).sin(),
        grip,
    ]
}

pub fn measure(scene: &str, model: Arc<MjModel>, init_row: &[f64], cfg: BenchConfig) -> Result<BenchSimResult, SimError> {
    let steps = cfg.steps.max(1);
    let actions: Vec<[f64; 7]> = (0..steps).map(sequence_a_action).collect();
    let clock = Clock { cpu: thread_cpu_ns().is_some() };
    let nu = model.ffi().nu as usize;
    let substeps = SUBSTEPS_PER_ACTION;

    let mut sim = Simulation::new(model.clone())?;
    // Record the per-substep controls of our loop once (untimed) for the same-trajectory raw replay.
    let mut recorded_ctrl: Vec<f64> = Vec::with_capacity(steps * substeps * nu);
    let mut held_ctrl = vec![0.0; nu];
    sim.set_init_state(init_row)?;
    for (i, a) in actions.iter().enumerate() {
        sim.step_with(*a, |_, d| recorded_ctrl.extend_from_slice(d.ctrl()))?;
        if i == 0 {
            held_ctrl.copy_from_slice(sim.data().ctrl());
        }
    }
    let mut raw_data = SimData::new(model.clone());
    let (mut best_ours, mut best_raw, mut best_held) = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
    for _ in 0..cfg.rounds.max(1) {
        // (a) our loop
        sim.reset()?;
        sim.set_init_state(init_row)?;
        let (t, r) = clock.time(|| -> Result<(), SimError> {
            for a in &actions {
                sim.step(*a)?;
            }
            Ok(())
        });
        r?;
        best_ours = best_ours.min(t);
        // (b) raw mj_step on the recorded controls (same trajectory)
        load_state(&mut raw_data, init_row);
        let (t, _) = clock.time(|| {
            for c in recorded_ctrl.chunks_exact(nu) {
                raw_data.ctrl_mut().copy_from_slice(c);
                raw_data.step();
            }
        });
        best_raw = best_raw.min(t);
        // (c) raw mj_step, controls held
        load_state(&mut raw_data, init_row);
        raw_data.ctrl_mut().copy_from_slice(&held_ctrl);
        let (t, _) = clock.time(|| {
            for _ in 0..steps * substeps {
                raw_data.step();
            }
        });
        best_held = best_held.min(t);
    }
    // (d) the controller alone, on the final state of the last round
    let ids = sim.ids().clone();
    let mut reader = ArmStateReader::new(&model, &ids);
    let mut osc = OscPose::new(reader.read(sim.data(), &ids), &ids);
    let bias = Vector7::from_fn(|i, _| sim.data().qfrc_bias()[ids.arm_dof_adr[i]]);
    let reps = 20_000;
    let mut best_ctrl = f64::INFINITY;
    for _ in 0..cfg.rounds.max(1) {
        let (t, _) = clock.time(|| {
            let mut acc = 0.0;
            for _ in 0..reps {
                osc.needs_refresh = true;
                osc.update_with(|| reader.read(sim.data(), &ids));
                acc += std::hint::black_box(osc.run(&bias))[0];
            }
            acc
        });
        best_ctrl = best_ctrl.min(t);
    }
    let controller_s = best_ctrl / reps as f64;
    let raw_steps = (steps * substeps) as f64;
    let per_control = best_ours / steps as f64;
    let per_25_raw = best_raw / raw_steps * substeps as f64;
    let per_25_held = best_held / raw_steps * substeps as f64;
    Ok(BenchSimResult {
        scene: scene.to_string(),
        nq: model.ffi().nq,
        nv: model.ffi().nv,
        control_steps: steps,
        clock: if clock.cpu { "thread_cpu" } else { "wall" },
        build: if cfg!(debug_assertions) { "debug" } else { "release" },
        control_steps_per_s: 1.0 / per_control,
        us_per_control_step: per_control * 1e6,
        raw_mj_step_per_s: raw_steps / best_raw,
        raw_control_equiv_per_s: raw_steps / best_raw / substeps as f64,
        us_per_25_raw_steps: per_25_raw * 1e6,
        cost_ratio: per_control / per_25_raw,
        raw_held_ctrl_mj_step_per_s: raw_steps / best_held,
        cost_ratio_vs_held_ctrl: per_control / per_25_held,
        controller_us_per_substep: controller_s * 1e6,
        controller_share_of_raw_step: controller_s / (best_raw / raw_steps),
    })
}

fn load_state(data: &mut SimData, row: &[f64]) {
    let nq = data.qpos().len();
    // SAFETY: plain field writes on owned data.
    unsafe {
        let d = data.ffi_mut();
        d.time = row[0];
    }
    data.qpos_mut().copy_from_slice(&row[1..1 + nq]);
    data.qvel_mut().copy_from_slice(&row[1 + nq..]);
    data.qacc_warmstart_mut().fill(0.0);
}
