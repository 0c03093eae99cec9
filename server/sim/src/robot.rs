//! The Panda as robosuite 1.4 + LIBERO name it in a compiled model, and its reset configuration.
use mujoco_rs::prelude::*;

use crate::SimError;

/// LIBERO's arm `init_qpos` (MountedPanda / OnTheGroundPanda; port notes §3.3), radians.
pub const ARM_INIT_QPOS_RAD: [f64; 7] =
    [0.0, -0.161037389, 0.0, -2.44459747, 0.0, 2.22675220, std::f64::consts::FRAC_PI_4];
/// PandaGripper `init_qpos` (metres, slide joints).
pub const FINGER_INIT_QPOS_M: [f64; 2] = [0.020833, -0.020833];
/// Physics substeps per control step: `int(0.05 / 0.002)`.
pub const SUBSTEPS_PER_ACTION: usize = 25;
/// robosuite's control period (20 Hz), seconds.
pub const CONTROL_PERIOD_S: f64 = 0.05;

const ARM_JOINTS: [&str; 7] = [
    "robot0_joint1",
    "robot0_joint2",
    "robot0_joint3",
    "robot0_joint4",
    "robot0_joint5",
    "robot0_joint6",
    "robot0_joint7",
];
const ARM_ACTUATORS: [&str; 7] = [
    "robot0_torq_j1",
    "robot0_torq_j2",
    "robot0_torq_j3",
    "robot0_torq_j4",
    "robot0_torq_j5",
    "robot0_torq_j6",
    "robot0_torq_j7",
];
const FINGER_JOINTS: [&str; 2] = ["gripper0_finger_joint1", "gripper0_finger_joint2"];
const FINGER_ACTUATORS: [&str; 2] = ["gripper0_gripper_finger_joint1", "gripper0_gripper_finger_joint2"];
/// Controller and observation EE position (`robot0_eef_pos`).
pub const GRIP_SITE: &str = "gripper0_grip_site";
/// Body whose orientation robosuite reports as `robot0_eef_quat`.
pub const RIGHT_HAND_BODY: &str = "robot0_right_hand";
const FORCE_SENSOR: &str = "gripper0_force_ee";
const TORQUE_SENSOR: &str = "gripper0_torque_ee";

/// Indices of the Panda's elements in one compiled model, looked up by robosuite name.
#[derive(Debug, Clone)]
pub struct PandaIds {
    pub arm_qpos_adr: [usize; 7],
    pub arm_dof_adr: [usize; 7],
    pub arm_actuator: [usize; 7],
    pub finger_qpos_adr: [usize; 2],
    pub finger_dof_adr: [usize; 2],
    pub finger_actuator: [usize; 2],
    pub grip_site: usize,
    pub right_hand_body: usize,
    /// `sensordata` addresses of the 3-D wrist force / torque sensors, if the model has them.
    pub force_sensor_adr: Option<usize>,
    pub torque_sensor_adr: Option<usize>,
    /// Arm actuator ctrlrange (robosuite's `torque_limits`), N·m.
    pub arm_torque_min: [f64; 7],
    pub arm_torque_max: [f64; 7],
    /// Finger actuator ctrlrange rows `[lo, hi]`, metres.
    pub finger_ctrlrange: [[f64; 2]; 2],
}

fn id(model: &MjModel, kind: MjtObjBase, name: &str, what: &str) -> Result<usize, SimError> {
    model
        .name_to_id(kind, name)
        .ok_or_else(|| SimError::Input(format!("model has no {what} named {name:?} (not a robosuite Panda scene?)")))
}

impl PandaIds {
    /// Looks every element up; a model without the robosuite Panda is an input error.
    pub fn lookup(model: &MjModel) -> Result<Self, SimError> {
        let jnt_qposadr = model.jnt_qposadr();
        let jnt_dofadr = model.jnt_dofadr();
        let ctrlrange = model.actuator_ctrlrange();
        let mut ids = PandaIds {
            arm_qpos_adr: [0; 7],
            arm_dof_adr: [0; 7],
            arm_actuator: [0; 7],
            finger_qpos_adr: [0; 2],
            finger_dof_adr: [0; 2],
            finger_actuator: [0; 2],
            grip_site: id(model, MjtObjBase::mjOBJ_SITE, GRIP_SITE, "site")?,
            right_hand_body: id(model, MjtObjBase::mjOBJ_BODY, RIGHT_HAND_BODY, "body")?,
            force_sensor_adr: None,
            torque_sensor_adr: None,
            arm_torque_min: [0.0; 7],
            arm_torque_max: [0.0; 7],
            finger_ctrlrange: [[0.0; 2]; 2],
        };
        for i in 0..7 {
            let j = id(model, MjtObjBase::mjOBJ_JOINT, ARM_JOINTS[i], "joint")?;
            ids.arm_qpos_adr[i] = jnt_qposadr[j] as usize;
            ids.arm_dof_adr[i] = jnt_dofadr[j] as usize;
            let a = id(model, MjtObjBase::mjOBJ_ACTUATOR, ARM_ACTUATORS[i], "actuator")?;
            ids.arm_actuator[i] = a;
            ids.arm_torque_min[i] = ctrlrange[a][0];
            ids.arm_torque_max[i] = ctrlrange[a][1];
        }
        for i in 0..2 {
            let j = id(model, MjtObjBase::mjOBJ_JOINT, FINGER_JOINTS[i], "joint")?;
            ids.finger_qpos_adr[i] = jnt_qposadr[j] as usize;
            ids.finger_dof_adr[i] = jnt_dofadr[j] as usize;
            let a = id(model, MjtObjBase::mjOBJ_ACTUATOR, FINGER_ACTUATORS[i], "actuator")?;
            ids.finger_actuator[i] = a;
            ids.finger_ctrlrange[i] = ctrlrange[a];
        }
        let sensor_adr = model.sensor_adr();
        ids.force_sensor_adr =
            model.name_to_id(MjtObjBase::mjOBJ_SENSOR, FORCE_SENSOR).map(|s| sensor_adr[s] as usize);
        ids.torque_sensor_adr =
            model.name_to_id(MjtObjBase::mjOBJ_SENSOR, TORQUE_SENSOR).map(|s| sensor_adr[s] as usize);
        Ok(ids)
    }
}
