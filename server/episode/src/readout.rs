//! The public robot state of a frame (§3.6, §3.8) read from the real simulation: joint and finger values
//! as robosuite's observables sampled them, the OSC controller's end-effector pose and twist, all turned
//! from the world frame into the robot base frame.
use libero_sim::Simulation;
use libero_sim::mujoco_rs::prelude::MjtObjBase;
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

use crate::EpisodeError;
use crate::observation::RobotReadout;

/// robosuite's robot root body.
pub const ROBOT_BASE_BODY: &str = "robot0_base";

/// `R_world_from_base` and `p_base_in_world` of the robot root body.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BasePose {
    pub r_world_from_base: Matrix3<f64>,
    pub p_base_in_world_m: Vector3<f64>,
}

impl BasePose {
    pub fn of(sim: &Simulation, base_body: usize) -> Self {
        let d = sim.data();
        let p = d.xpos()[base_body];
        let q = d.xquat()[base_body]; // w, x, y, z
        let rot = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]));
        Self { r_world_from_base: *rot.to_rotation_matrix().matrix(), p_base_in_world_m: Vector3::new(p[0], p[1], p[2]) }
    }

    /// Homogeneous `T_world_from_base`.
    pub fn t_world_from_base(&self) -> [[f64; 4]; 4] {
        let (r, p) = (&self.r_world_from_base, &self.p_base_in_world_m);
        [
            [r[(0, 0)], r[(0, 1)], r[(0, 2)], p[0]],
            [r[(1, 0)], r[(1, 1)], r[(1, 2)], p[1]],
            [r[(2, 0)], r[(2, 1)], r[(2, 2)], p[2]],
            [0.0, 0.0, 0.0, 1.0],
        ]
    }
}

/// Body id of the robot base in `sim`'s model.
pub fn robot_base_body(sim: &Simulation) -> Result<usize, EpisodeError> {
    sim.model()
        .name_to_id(MjtObjBase::mjOBJ_BODY, ROBOT_BASE_BODY)
        .ok_or_else(|| EpisodeError::Task(format!("the model has no body {ROBOT_BASE_BODY:?}")))
}

/// Unit quaternion `[x, y, z, w]` with `w ≥ 0` of a rotation matrix.
pub fn quat_xyzw_w_nonneg(r: &Matrix3<f64>) -> [f64; 4] {
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(r));
    let s = if q.w < 0.0 { -1.0 } else { 1.0 };
    [s * q.i, s * q.j, s * q.k, s * q.w]
}

/// The frame's robot readout.
pub fn robot_readout(sim: &Simulation, base: &BasePose) -> RobotReadout {
    let sampled = &sim.observation().robot;
    let arm = sim.controller_state();
    let rt = base.r_world_from_base.transpose();
    let p = rt * (arm.ee_pos_in_world_m - base.p_base_in_world_m);
    let q = quat_xyzw_w_nonneg(&(rt * arm.r_world_from_site));
    let v = rt * arm.ee_lin_vel_in_world_m_s;
    let w = rt * arm.ee_ang_vel_in_world_rad_s;
    RobotReadout {
        sim_time_s: sim.time_s(),
        arm_joint_position_rad: sampled.joint_pos_rad,
        gripper_finger_joint_position_m: sampled.gripper_qpos_m,
        eef_pose_robot_base_xyzw: [p[0], p[1], p[2], q[0], q[1], q[2], q[3]],
        arm_joint_velocity_rad_s: sampled.joint_vel_rad_s,
        gripper_finger_joint_velocity_m_s: sampled.gripper_qvel_m_s,
        commanded_arm_joint_torque_nm: Some(sim.arm_torques_nm()),
        eef_force_sensor_n: sampled.wrist_force_n,
        eef_torque_sensor_nm: sampled.wrist_torque_nm,
        eef_twist_robot_base: [v[0], v[1], v[2], w[0], w[1], w[2]],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quaternions_are_unit_with_nonnegative_w() {
        let r = Rotation3::from_axis_angle(&Vector3::z_axis(), 3.0); // w = cos(1.5) > 0
        let q = quat_xyzw_w_nonneg(r.matrix());
        assert!(q[3] >= 0.0);
        let r2 = Rotation3::from_axis_angle(&Vector3::x_axis(), -3.5); // would give w < 0 one way or the other
        let q2 = quat_xyzw_w_nonneg(r2.matrix());
        assert!(q2[3] >= 0.0);
        assert!(((q2.iter().map(|x| x * x).sum::<f64>()) - 1.0).abs() < 1e-12);
    }
}
