//! One simulated LIBERO episode's physics: the Panda under robosuite 1.4 `OSC_POSE` at 20 Hz with 25
//! physics substeps of 2 ms per action, faults returned as values.
//!
//! Substep schedule (port notes §1.6). robosuite runs `mj_forward`, computes the control, then
//! `mj_step`; the extra `mj_forward` calls are physics-neutral. We run `mj_step1` (position and
//! velocity stages — the same values robosuite's `mj_forward` produces), compute the control from
//! them and finish with `mj_step2`. The resulting states are bit-identical to `mj_step` with the same
//! controls, at the cost of one physics step per substep.
//!
//! What the data holds after [`Simulation::step`]: qpos/qvel/time are the end of the step; kinematic
//! fields (body/site poses, contacts, sensors) are those of the last substep's pre-integration state.
//! That is the view LIBERO's `_check_success` and observations use. Call [`Simulation::forward`] for
//! end-of-step kinematics (the golden files' `site_grip_xpos_end`).
use std::sync::Arc;

use mujoco_rs::mujoco_c::{mjData, mjModel, mjtWarning};
use mujoco_rs::prelude::*;

use crate::SimError;
use crate::controller::{ArmState, ArmStateReader, OscPose, Vector7};
use crate::fault::ffi::{mj_forward, mj_resetData, mj_step1, mj_step2};
use crate::fault::guarded;
use crate::gripper::GripperRamp;
use crate::robot::{ARM_INIT_QPOS_RAD, FINGER_INIT_QPOS_M, PandaIds, SUBSTEPS_PER_ACTION};

/// robosuite's `macros.SIMULATION_TIMESTEP`, used by the observable timers (not the model's timestep).
const OBSERVABLE_DT_S: f64 = 0.002;
/// Warnings after which the state is garbage: MuJoCo resets mjData itself on bad qpos/qvel/qacc.
const FATAL_WARNINGS: [mjtWarning; 6] = [
    mjtWarning::mjWARN_CONTACTFULL,
    mjtWarning::mjWARN_CNSTRFULL,
    mjtWarning::mjWARN_BADQPOS,
    mjtWarning::mjWARN_BADQVEL,
    mjtWarning::mjWARN_BADQACC,
    mjtWarning::mjWARN_BADCTRL,
];

pub type SimData = MjData<Arc<MjModel>>;

/// robosuite's observable timer (`Observable.update`, 20 Hz, no delay), float arithmetic kept as is so
/// the sampling phase matches (§4.5): after `set_init_state` observations are taken after substep 24.
#[derive(Debug, Clone, Copy)]
struct ObservationClock {
    t_since_s: f64,
    sampled: bool,
}

impl ObservationClock {
    const PERIOD_S: f64 = 1.0 / 20.0;

    /// Advances by `dt`; returns whether the observation is sampled now.
    fn update(&mut self, dt: f64, force: bool) -> bool {
        self.t_since_s += dt;
        let mut sample = false;
        if (!self.sampled && Self::PERIOD_S - 0.0 >= self.t_since_s) || force {
            sample = true;
            self.sampled = true;
        }
        if self.t_since_s >= Self::PERIOD_S {
            if !self.sampled {
                sample = true;
            }
            self.t_since_s %= Self::PERIOD_S;
            self.sampled = false;
        }
        sample
    }
}

/// Robot readout at one instant. Positions in the world frame, metres; quaternions (x, y, z, w).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RobotState {
    pub time_s: f64,
    /// `robot0_eef_pos`: `gripper0_grip_site` position.
    pub eef_pos_in_world_m: [f64; 3],
    /// `robot0_eef_quat`: `robot0_right_hand` body orientation, (x, y, z, w).
    pub eef_quat_xyzw: [f64; 4],
    pub joint_pos_rad: [f64; 7],
    pub joint_vel_rad_s: [f64; 7],
    /// `robot0_gripper_qpos`: finger slide joints (≈[0.04, −0.04] open, ≈[0, 0] closed).
    pub gripper_qpos_m: [f64; 2],
    pub gripper_qvel_m_s: [f64; 2],
    /// Wrist force/torque sensors on `gripper0_ft_frame` (site frame), zero if the model lacks them.
    pub wrist_force_n: [f64; 3],
    pub wrist_torque_nm: [f64; 3],
}

/// What robosuite's observables sampled: qpos-based values of the just-integrated state, pose-based
/// values (eef pose, body poses) from the kinematics of the same `mj_step`, i.e. one substep older.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ObservationSample {
    pub robot: RobotState,
    /// Every body's world position at the sampling instant (index = body id).
    pub body_pos_in_world_m: Vec<[f64; 3]>,
    /// Every body's world orientation (w, x, y, z, MuJoCo order) at the sampling instant.
    pub body_quat_wxyz: Vec<[f64; 4]>,
}

/// Result of one control step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepOutcome {
    pub time_s: f64,
    /// 1-based substep after which the observation was sampled, if it was during this step.
    pub observation_substep: Option<usize>,
}

/// A Panda episode simulation. Owns its `mjData`; the model is shared read-only. `Send`, so an
/// episode thread can own it.
pub struct Simulation {
    model: Arc<MjModel>,
    data: SimData,
    ids: PandaIds,
    reader: ArmStateReader,
    controller: OscPose,
    gripper: GripperRamp,
    clock: ObservationClock,
    observation: ObservationSample,
    arm_torques_nm: [f64; 7],
    warnings_seen: [i32; 7],
    poisoned: Option<String>,
    /// Called after every completed control step (the private video records each one, settle steps included).
    step_observer: Option<StepObserver>,
    /// `qpos` as the last substep's `mj_step1` saw it (kept only while a step observer is installed).
    pose_qpos: Vec<f64>,
}

/// A hook on every completed control step: model and data after the step's last substep, and the `qpos` that
/// data's poses (`xpos`, `geom_xpos`, cameras, lights) were computed from. `mj_step2` integrates `qpos` after
/// `mj_step1` computed the kinematics, so the two differ by one substep; [`crate::PoseReplay`] recomputes the
/// same poses, bit for bit, from this `qpos` alone.
pub type StepObserver = Box<dyn FnMut(&MjModel, &SimData, &[f64]) + Send>;

fn non_finite(xs: &[f64]) -> Option<usize> {
    xs.iter().position(|x| !x.is_finite())
}

impl Simulation {
    /// A simulation of `model`, already [`reset`](Self::reset).
    pub fn new(model: Arc<MjModel>) -> Result<Self, SimError> {
        let ids = PandaIds::lookup(&model)?;
        let data = guarded(|| SimData::try_new(model.clone()))
            .map_err(SimError::Fault)?
            .map_err(|e| SimError::Fault(format!("cannot allocate mjData: {e}")))?;
        let nbody = model.ffi().nbody as usize;
        let mut reader = ArmStateReader::new(&model, &ids);
        let initial = reader.read(&data, &ids);
        let mut sim = Self {
            controller: OscPose::new(initial, &ids),
            model,
            data,
            ids,
            reader,
            gripper: GripperRamp::default(),
            clock: ObservationClock { t_since_s: 0.0, sampled: false },
            observation: ObservationSample {
                robot: RobotState::default(),
                body_pos_in_world_m: vec![[0.0; 3]; nbody],
                body_quat_wxyz: vec![[1.0, 0.0, 0.0, 0.0]; nbody],
            },
            arm_torques_nm: [0.0; 7],
            warnings_seen: [0; 7],
            poisoned: None,
            step_observer: None,
            pose_qpos: Vec::new(),
        };
        sim.reset()?;
        Ok(sim)
    }

    fn check_poison(&self) -> Result<(), SimError> {
        match &self.poisoned {
            Some(msg) => Err(SimError::Fault(msg.clone())),
            None => Ok(()),
        }
    }

    fn poison(&mut self, msg: String) -> SimError {
        self.poisoned = Some(msg.clone());
        SimError::Fault(msg)
    }

    /// Runs one raw MuJoCo call under the fault guard.
    fn mj(&mut self, f: unsafe extern "C-unwind" fn(*const mjModel, *mut mjData)) -> Result<(), SimError> {
        self.check_poison()?;
        let model = self.model.clone();
        let data = &mut self.data;
        // SAFETY: model and data belong together; MuJoCo errors unwind out through `guarded`.
        match guarded(|| unsafe { f(model.ffi(), data.ffi_mut()) }) {
            Ok(()) => Ok(()),
            Err(msg) => Err(self.poison(msg)),
        }
    }

    /// robosuite's hard reset for the robot (§3.3, §6.4): fresh data, arm at LIBERO's `init_qpos`,
    /// controller created there (nullspace target, goals, cached state with the refresh flag cleared),
    /// then the fingers put at their `init_qpos` (after the controller, as robosuite does), gripper
    /// command [0, 0], observable timers restarted and force-sampled.
    pub fn reset(&mut self) -> Result<(), SimError> {
        self.check_poison()?;
        self.mj(mj_resetData)?;
        {
            let qpos = self.data.qpos_mut();
            for (i, &a) in self.ids.arm_qpos_adr.iter().enumerate() {
                qpos[a] = ARM_INIT_QPOS_RAD[i];
            }
        }
        self.mj(mj_forward)?;
        let initial = self.reader.read(&self.data, &self.ids);
        self.controller = OscPose::new(initial, &self.ids);
        {
            let qpos = self.data.qpos_mut();
            for (i, &a) in self.ids.finger_qpos_adr.iter().enumerate() {
                qpos[a] = FINGER_INIT_QPOS_M[i];
            }
        }
        self.mj(mj_forward)?;
        self.gripper = GripperRamp::default();
        self.arm_torques_nm = [0.0; 7];
        self.warnings_seen = self.warning_counts();
        self.clock = ObservationClock { t_since_s: 0.0, sampled: false };
        if self.clock.update(OBSERVABLE_DT_S, true) {
            self.sample_observation();
        }
        self.check_finite()
    }

    /// LIBERO's `set_init_state` (§6.2): time, qpos, qvel from `[time, qpos…, qvel…]`, then
    /// `mj_forward` and a forced observation sample. Controller and gripper state are untouched.
    pub fn set_init_state(&mut self, row: &[f64]) -> Result<(), SimError> {
        self.check_poison()?;
        let (nq, nv) = (self.model.ffi().nq as usize, self.model.ffi().nv as usize);
        if row.len() != 1 + nq + nv {
            return Err(SimError::Input(format!(
                "init state has {} values, this model needs 1 + nq + nv = {}",
                row.len(),
                1 + nq + nv
            )));
        }
        if let Some(i) = non_finite(row) {
            return Err(SimError::Input(format!("init state value {i} is not finite")));
        }
        // SAFETY: plain field write on owned data.
        unsafe { self.data.ffi_mut().time = row[0] };
        self.data.qpos_mut().copy_from_slice(&row[1..1 + nq]);
        self.data.qvel_mut().copy_from_slice(&row[1 + nq..]);
        self.mj(mj_forward)?;
        self.check_finite()?;
        if self.clock.update(OBSERVABLE_DT_S, true) {
            self.sample_observation();
        }
        Ok(())
    }

    /// One 20 Hz control step with a 7-D `OSC_POSE` action
    /// `[dx, dy, dz, ax, ay, az, gripper]` (each clipped to [−1, 1]; gripper: −1 open, +1 close).
    pub fn step(&mut self, action: [f64; 7]) -> Result<StepOutcome, SimError> {
        self.step_with(action, |_, _| {})
    }

    /// [`step`](Self::step) with a hook called after every substep (1-based index, data after `mj_step`).
    pub fn step_with(
        &mut self,
        action: [f64; 7],
        mut on_substep: impl FnMut(usize, &SimData),
    ) -> Result<StepOutcome, SimError> {
        self.check_poison()?;
        if let Some(i) = non_finite(&action) {
            return Err(SimError::Input(format!("action component {i} is not finite: {:?}", action)));
        }
        let arm_action = [action[0], action[1], action[2], action[3], action[4], action[5]];
        let model = self.model.clone();
        let mut observation_substep = None;
        let result = guarded(|| -> Result<(), String> {
            for k in 0..SUBSTEPS_PER_ACTION {
                // SAFETY: model and data belong together; errors unwind through `guarded`.
                unsafe { mj_step1(model.ffi(), self.data.ffi_mut()) };
                let (reader, data, ids) = (&mut self.reader, &self.data, &self.ids);
                self.controller.update_with(|| reader.read(data, ids));
                if k == 0 {
                    self.controller.set_goal(&arm_action);
                }
                let bias = {
                    let qfrc_bias = self.data.qfrc_bias();
                    Vector7::from_fn(|i, _| qfrc_bias[self.ids.arm_dof_adr[i]])
                };
                let tau = self.controller.run(&bias);
                self.gripper.advance(action[6]);
                let finger_ctrl = self.gripper.ctrl(&self.ids.finger_ctrlrange);
                {
                    let ctrl = self.data.ctrl_mut();
                    for (i, &a) in self.ids.arm_actuator.iter().enumerate() {
                        ctrl[a] = tau[i];
                    }
                    for (i, &a) in self.ids.finger_actuator.iter().enumerate() {
                        ctrl[a] = finger_ctrl[i];
                    }
                }
                self.arm_torques_nm = tau.into();
                if k + 1 == SUBSTEPS_PER_ACTION && self.step_observer.is_some() {
                    self.pose_qpos.clear();
                    self.pose_qpos.extend_from_slice(self.data.qpos());
                }
                // SAFETY: as above.
                unsafe { mj_step2(model.ffi(), self.data.ffi_mut()) };
                self.substep_checks()?;
                if self.clock.update(OBSERVABLE_DT_S, false) {
                    self.sample_observation();
                    observation_substep = Some(k + 1);
                }
                on_substep(k + 1, &self.data);
            }
            Ok(())
        });
        match result {
            Ok(Ok(())) => {
                if let Some(observe) = self.step_observer.as_mut() {
                    observe(&self.model, &self.data, &self.pose_qpos);
                }
                Ok(StepOutcome { time_s: self.data.ffi().time, observation_substep })
            }
            Ok(Err(msg)) | Err(msg) => Err(self.poison(msg)),
        }
    }

    /// Installs (or with `None` removes) the hook run after every completed control step; a step that
    /// faults is not observed.
    pub fn set_step_observer(&mut self, observer: Option<StepObserver>) {
        self.step_observer = observer;
    }

    /// Recomputes all derived quantities for the current qpos/qvel (`mj_forward`); physics-neutral.
    pub fn forward(&mut self) -> Result<(), SimError> {
        self.mj(mj_forward)
    }

    fn warning_counts(&self) -> [i32; 7] {
        let w = self.data.warning();
        std::array::from_fn(|i| w[i].number)
    }

    /// NaN/Inf and MuJoCo's instability warnings after a substep, as a fault message.
    fn substep_checks(&mut self) -> Result<(), String> {
        let counts = self.warning_counts();
        for w in FATAL_WARNINGS {
            let i = w as usize;
            if counts[i] > self.warnings_seen[i] {
                return Err(format!(
                    "MuJoCo warning {:?} at t = {:.3} s (simulation unstable; MuJoCo reset its state)",
                    w,
                    self.data.ffi().time
                ));
            }
        }
        self.warnings_seen = counts;
        self.check_finite().map_err(|e| match e {
            SimError::Fault(m) => m,
            other => other.to_string(),
        })
    }

    fn check_finite(&self) -> Result<(), SimError> {
        for (name, xs) in [("qpos", self.data.qpos()), ("qvel", self.data.qvel()), ("qacc", self.data.qacc())] {
            if let Some(i) = non_finite(xs) {
                return Err(SimError::Fault(format!(
                    "{name}[{i}] became {} at t = {:.3} s",
                    xs[i],
                    self.data.ffi().time
                )));
            }
        }
        Ok(())
    }

    fn sample_observation(&mut self) {
        self.observation.robot = self.robot_state();
        self.observation.body_pos_in_world_m.copy_from_slice(self.data.xpos());
        self.observation.body_quat_wxyz.copy_from_slice(self.data.xquat());
    }

    /// Robot readout from the data as it is now (see the module docs for what "now" means after a step).
    pub fn robot_state(&self) -> RobotState {
        let d = &self.data;
        let (qpos, qvel) = (d.qpos(), d.qvel());
        let site = d.site_xpos()[self.ids.grip_site];
        let q = d.xquat()[self.ids.right_hand_body];
        let sensor = d.sensordata();
        let read3 = |adr: Option<usize>| adr.map(|a| [sensor[a], sensor[a + 1], sensor[a + 2]]).unwrap_or_default();
        RobotState {
            time_s: d.ffi().time,
            eef_pos_in_world_m: site,
            eef_quat_xyzw: [q[1], q[2], q[3], q[0]],
            joint_pos_rad: std::array::from_fn(|i| qpos[self.ids.arm_qpos_adr[i]]),
            joint_vel_rad_s: std::array::from_fn(|i| qvel[self.ids.arm_dof_adr[i]]),
            gripper_qpos_m: std::array::from_fn(|i| qpos[self.ids.finger_qpos_adr[i]]),
            gripper_qvel_m_s: std::array::from_fn(|i| qvel[self.ids.finger_dof_adr[i]]),
            wrist_force_n: read3(self.ids.force_sensor_adr),
            wrist_torque_nm: read3(self.ids.torque_sensor_adr),
        }
    }

    /// The last observation robosuite would have returned (sampled at its observable phase).
    pub fn observation(&self) -> &ObservationSample {
        &self.observation
    }

    /// Arm torques applied in the last substep (clipped to the actuator range), N·m.
    pub fn arm_torques_nm(&self) -> [f64; 7] {
        self.arm_torques_nm
    }

    pub fn controller(&self) -> &OscPose {
        &self.controller
    }

    /// The controller's cached state (what its next stale substep would use).
    pub fn controller_state(&self) -> &ArmState {
        self.controller.cached_state()
    }

    pub fn gripper(&self) -> &GripperRamp {
        &self.gripper
    }

    pub fn ids(&self) -> &PandaIds {
        &self.ids
    }

    pub fn model(&self) -> &Arc<MjModel> {
        &self.model
    }

    /// Read-only access for evaluators, renderers and readouts.
    pub fn data(&self) -> &SimData {
        &self.data
    }

    pub fn time_s(&self) -> f64 {
        self.data.ffi().time
    }

    /// `[time, qpos…, qvel…]`, the init-state row layout.
    pub fn state_row(&self) -> Vec<f64> {
        let mut v = Vec::with_capacity(1 + self.data.qpos().len() + self.data.qvel().len());
        v.push(self.data.ffi().time);
        v.extend_from_slice(self.data.qpos());
        v.extend_from_slice(self.data.qvel());
        v
    }

    /// The fault that poisoned this simulation, if any.
    pub fn fault(&self) -> Option<&str> {
        self.poisoned.as_deref()
    }

    /// Test hook: writes `value` into qvel[dof] (used to prove NaN detection); not for episodes.
    #[doc(hidden)]
    pub fn inject_qvel(&mut self, dof: usize, value: f64) {
        if let Some(v) = self.data.qvel_mut().get_mut(dof) {
            *v = value;
        }
    }
}

/// Compile-time proof that an episode thread can own a simulation.
const _: fn() = || {
    fn is_send<T: Send>() {}
    is_send::<Simulation>();
};
