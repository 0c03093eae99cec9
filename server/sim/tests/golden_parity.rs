//! Parity with golden trajectories recorded from the real robosuite 1.4.0 + LIBERO stack on MuJoCo
//! 3.17.0 (`tests/reference/golden/`).
mod common;

use common::*;
use libero_sim::Simulation;
use libero_sim::mujoco_rs::mujoco_c::{mj_step1, mj_step2};
use libero_sim::mujoco_rs::prelude::*;
use libero_sim::simulation::SimData;

fn load_state(data: &mut SimData, row: &[f64]) {
    let nq = data.qpos().len();
    unsafe { data.ffi_mut().time = row[0] };
    data.qpos_mut().copy_from_slice(&row[1..1 + nq]);
    data.qvel_mut().copy_from_slice(&row[1 + nq..]);
}

/// (a) The recorded per-substep controls, applied with plain `mj_step` (and with the `mj_step1` /
/// `mj_step2` split the simulation uses) to the exact recorded model, reproduce every recorded state
/// bit for bit: the model, the init state and the physics are identical to the reference stack.
#[test]
fn recorded_controls_reproduce_golden_states_bit_for_bit() {
    for name in golden_names() {
        let g = load_golden(&name);
        let model = golden_model(&name, &g);
        for split in [false, true] {
            let mut data = SimData::new(model.clone());
            load_state(&mut data, &g.init_state);
            let mut worst: f64 = 0.0;
            for (t, substeps) in g.ctrl_substeps.iter().enumerate() {
                for c in substeps {
                    if split {
                        unsafe { mj_step1(model.ffi(), data.ffi_mut()) };
                        data.ctrl_mut().copy_from_slice(c);
                        unsafe { mj_step2(model.ffi(), data.ffi_mut()) };
                    } else {
                        data.ctrl_mut().copy_from_slice(c);
                        data.step();
                    }
                }
                worst = worst
                    .max(max_abs_diff(data.qpos(), &g.steps.qpos[t]))
                    .max(max_abs_diff(data.qvel(), &g.steps.qvel[t]))
                    .max((data.ffi().time - g.steps.time[t]).abs());
            }
            println!("{name:90} split={split} max |Δ| = {worst:e}");
            assert_eq!(worst, 0.0, "{name}: physics replay (split={split}) is not bit-identical");
        }
    }
}

struct Errors {
    eef_m: f64,
    joint_rad: f64,
    object_m: f64,
    torque_nm: f64,
    obs_eef_m: f64,
}

/// (b) The full controller (reset → set_init_state → 80 actions) tracks every golden step within the
/// fair tolerances of golden/README.md: grip site max(1 mm, 10·eef_div), joints max(1e-3 rad,
/// 10·joint_div), objects max(2 mm, 10·object_div); and, stricter, within 100× the reference's own
/// round-off sensitivity (floor 1e-8).
#[test]
fn controller_replay_tracks_golden_trajectories() {
    let mut report = Vec::new();
    for name in golden_names() {
        let g = load_golden(&name);
        let sens = load_sensitivity(&name);
        let model = golden_model(&name, &g);
        let free_qpos: Vec<usize> = (0..model.ffi().njnt as usize)
            .filter(|&j| model.jnt_type()[j] == MjtJoint::mjJNT_FREE)
            .map(|j| model.jnt_qposadr()[j] as usize)
            .collect();
        let mut sim = Simulation::new(model.clone()).expect("simulation");
        let traj = libero_sim::replay(&mut sim, &g.init_state, &g.actions).expect("replay");
        let mut e = Errors { eef_m: 0.0, joint_rad: 0.0, object_m: 0.0, torque_nm: 0.0, obs_eef_m: 0.0 };
        let arm = sim.ids().arm_qpos_adr;
        for t in 0..g.actions.len() {
            let eef = max_abs_diff(&traj.site_grip_xpos_end[t], &g.steps.site_grip_xpos_end[t]);
            let joints = arm.iter().map(|&a| (traj.qpos[t][a] - g.steps.qpos[t][a]).abs()).fold(0.0, f64::max);
            let objects = free_qpos
                .iter()
                .map(|&a| max_abs_diff(&traj.qpos[t][a..a + 3], &g.steps.qpos[t][a..a + 3]))
                .fold(0.0, f64::max);
            let torque = max_abs_diff(&traj.torques[t], &g.steps.torques[t]);
            let obs = max_abs_diff(&traj.obs_eef_pos[t], &g.steps.obs_eef_pos[t]);
            let tol_eef = (10.0 * sens.eef_div_m[t]).max(1e-3);
            let tol_joint = (10.0 * sens.joint_div_rad[t]).max(1e-3);
            let tol_obj = (10.0 * sens.object_div_m[t]).max(2e-3);
            assert!(eef <= tol_eef, "{name} step {t}: grip site off by {eef:e} m (tolerance {tol_eef:e})");
            assert!(joints <= tol_joint, "{name} step {t}: joint off by {joints:e} rad (tolerance {tol_joint:e})");
            assert!(objects <= tol_obj, "{name} step {t}: object off by {objects:e} m (tolerance {tol_obj:e})");
            // Stricter bar: within 100× the reference stack's own 1e-12-perturbation divergence (floor
            // 1e-8), i.e. the port is as close as floating-point reassociation allows.
            let strict = |err: f64, div: f64| err <= (100.0 * div).max(1e-8);
            assert!(
                strict(eef, sens.eef_div_m[t]) && strict(joints, sens.joint_div_rad[t]) && strict(objects, sens.object_div_m[t]),
                "{name} step {t}: beyond the round-off bar (eef {eef:e}, joints {joints:e}, objects {objects:e})"
            );
            e.eef_m = e.eef_m.max(eef);
            e.joint_rad = e.joint_rad.max(joints);
            e.object_m = e.object_m.max(objects);
            e.torque_nm = e.torque_nm.max(torque);
            e.obs_eef_m = e.obs_eef_m.max(obs);
        }
        report.push(format!(
            "{name:90} eef {:9.2e} m  joints {:9.2e} rad  objects {:9.2e} m  torques {:9.2e} Nm  obs_eef {:9.2e} m",
            e.eef_m, e.joint_rad, e.object_m, e.torque_nm, e.obs_eef_m
        ));
    }
    for line in report {
        println!("{line}");
    }
}

/// The torque law alone: given the recorded state before each substep of the instrumented step and the
/// recorded goals, the controller reproduces the recorded torques (isolates OSC from trajectory drift);
/// the arm inertia block read from the sparse `d.M` equals `mj_fullM`'s bit for bit.
#[test]
fn torque_law_reproduces_recorded_substep_torques() {
    use libero_sim::controller::{ArmStateReader, OscPose, Vector7};
    use libero_sim::mujoco_rs::mujoco_c::mj_forward;
    use nalgebra::{Matrix3, Vector3};
    let mut worst_all: f64 = 0.0;
    for name in golden_names() {
        let g = load_golden(&name);
        let model = golden_model(&name, &g);
        let sim = Simulation::new(model.clone()).expect("simulation");
        let ids = sim.ids().clone();
        let s6 = g.instrumented_step;
        let mut data = SimData::new(model.clone());
        let mut reader = ArmStateReader::new(&model, &ids);
        let nv = model.ffi().nv as usize;
        let mut dense = vec![0.0; nv * nv];
        let mut worst: f64 = 0.0;
        for k in 1..25 {
            let nq = data.qpos().len();
            let mut row = vec![g.steps.time[s6]];
            row.extend_from_slice(&g.substeps_of_step6.qpos[k - 1][..nq]);
            row.extend_from_slice(&g.substeps_of_step6.qvel[k - 1]);
            load_state(&mut data, &row);
            unsafe { mj_forward(model.ffi(), data.ffi_mut()) };
            let state = reader.read(&data, &ids);
            data.full_m(&mut dense).expect("mj_fullM");
            for (i, &a) in ids.arm_dof_adr.iter().enumerate() {
                for (j, &b) in ids.arm_dof_adr.iter().enumerate() {
                    assert_eq!(state.mass[(i, j)].to_bits(), dense[a * nv + b].to_bits(), "arm inertia block ≠ mj_fullM");
                }
            }
            let mut osc = OscPose::new(state, &ids);
            osc.initial_joint_rad = Vector7::from_column_slice(&g.init.controller_initial_joint);
            osc.goal_pos_in_world_m = Vector3::from_column_slice(&g.steps.goal_pos[s6]);
            let go = &g.steps.goal_ori[s6];
            osc.goal_r_world_from_site = Matrix3::from_fn(|i, j| go[i][j]);
            let bias = Vector7::from_fn(|i, _| data.qfrc_bias()[ids.arm_dof_adr[i]]);
            let tau = osc.run(&bias);
            let d = max_abs_diff(tau.as_slice(), &g.substeps_of_step6.torques[k]);
            worst = worst.max(d);
        }
        println!("{name:90} torque law max |Δτ| = {worst:e} N·m");
        worst_all = worst_all.max(worst);
    }
    assert!(worst_all < 1e-9, "torque law differs from the recorded torques by {worst_all:e} N·m");
}
