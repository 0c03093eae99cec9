//! Replaying an action sequence from an init state and recording what the golden files record.
use serde::{Deserialize, Serialize};

use crate::SimError;
use crate::simulation::Simulation;

/// Per-step records; field names follow the golden files (`steps.*`).
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct Trajectory {
    pub action: Vec<[f64; 7]>,
    pub qpos: Vec<Vec<f64>>,
    pub qvel: Vec<Vec<f64>>,
    pub time: Vec<f64>,
    /// Observation returned by the step (robosuite's sampling phase): grip-site position.
    pub obs_eef_pos: Vec<[f64; 3]>,
    /// Observation: `robot0_right_hand` quaternion (x, y, z, w).
    pub obs_eef_quat: Vec<[f64; 4]>,
    pub obs_joint_pos: Vec<[f64; 7]>,
    pub obs_gripper_qpos: Vec<[f64; 2]>,
    /// Grip site after `mj_forward` at the end of the step.
    pub site_grip_xpos_end: Vec<[f64; 3]>,
    /// Arm joint positions at the end of the step.
    pub joint_pos: Vec<[f64; 7]>,
    /// Finger joint positions at the end of the step.
    pub gripper_qpos: Vec<[f64; 2]>,
    /// Arm torques of the last substep.
    pub torques: Vec<[f64; 7]>,
    pub goal_pos: Vec<[f64; 3]>,
    pub gripper_current_action: Vec<[f64; 2]>,
}

/// LIBERO's evaluation flow: `reset` → `set_init_state(init_row)` → `step(action)` for each action,
/// recording every step. Stops at the first error (a fault poisons `sim`).
pub fn replay(sim: &mut Simulation, init_row: &[f64], actions: &[[f64; 7]]) -> Result<Trajectory, SimError> {
    sim.reset()?;
    sim.set_init_state(init_row)?;
    let mut t = Trajectory::default();
    for a in actions {
        sim.step(*a)?;
        let obs = sim.observation().robot;
        t.action.push(*a);
        t.obs_eef_pos.push(obs.eef_pos_in_world_m);
        t.obs_eef_quat.push(obs.eef_quat_xyzw);
        t.obs_joint_pos.push(obs.joint_pos_rad);
        t.obs_gripper_qpos.push(obs.gripper_qpos_m);
        t.torques.push(sim.arm_torques_nm());
        t.goal_pos.push(sim.controller().goal_pos_in_world_m.into());
        t.gripper_current_action.push(sim.gripper().current_action);
        sim.forward()?;
        let end = sim.robot_state();
        t.qpos.push(sim.data().qpos().to_vec());
        t.qvel.push(sim.data().qvel().to_vec());
        t.time.push(end.time_s);
        t.site_grip_xpos_end.push(end.eef_pos_in_world_m);
        t.joint_pos.push(end.joint_pos_rad);
        t.gripper_qpos.push(end.gripper_qpos_m);
    }
    Ok(t)
}
