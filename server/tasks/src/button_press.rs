//! `private_button_press` (T13; VLABench press-button evaluator, task catalog §4 T13, §6.4). Physics-substep
//! sampled. A sample is a *pressed* sample when
//! * the button's touch sensor (`<button>_button_touch`, MuJoCo touch on the cap volume) reads ≥ 0.001, and
//! * some active contact pairs a gripper collision geom (`gripper0_*`, group ≠ 1: robosuite's gripper
//!   `contact_geoms`) with the cap geom `<button>_button_cap`, with a normal force (`mj_contactForce`) ≥ 1e-3 N.
//!
//! Success ⇔ the longest uninterrupted run of pressed samples is ≥ 11. As in the original (catalog §2.4), the
//! evaluator is sampled 26 times per control step: after each of the 25 substeps and once more at control rate.
//! The press is latched (K = 1, stage `01_Press_Button`); nothing must still hold at finish. The press is the
//! episode's first commitment unless something came before it. The cap is drawn green whenever the sensor reads
//! ≥ 0.001 (the original edited `geom_rgba`).
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::{Deserialize, Serialize};

use crate::TasksError;
use crate::commitment::CommitmentTracker;
use crate::evaluator::{EvaluationRecord, Evaluator, FailureReason, PrivateEvent, StageSpec, StageTracker, Tick};
use crate::factory::{missing_in_model, scene_goal_and_commitment};
use crate::goal::GoalChecker;

pub const CHECKER: &str = "private_button_press";
pub const STAGE_NAME: &str = "01_Press_Button";
/// The colour a touched cap is drawn in.
pub const PRESSED_CAP_RGBA: [f32; 4] = [0.12, 0.85, 0.18, 1.0];
/// Prefix of the gripper's geoms after robosuite's merge.
pub const GRIPPER_GEOM_PREFIX: &str = "gripper0_";

/// The manifest's `checker.params`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ButtonPressParams {
    pub button: String,
    pub touch_sensor: String,
    #[serde(default = "default_touch_min")]
    pub touch_sensor_min: f64,
    #[serde(default = "default_force_min")]
    pub contact_normal_force_min_n: f64,
    #[serde(default = "default_streak")]
    pub min_press_streak_substeps: u32,
}

fn default_touch_min() -> f64 {
    0.001
}
fn default_force_min() -> f64 {
    1e-3
}
fn default_streak() -> u32 {
    11
}

/// Per-button press history (catalog §1.5 names).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ButtonHistory {
    pub button: String,
    pub touch_observed_private: bool,
    pub pressed_steps_private: u64,
    pub max_pressed_streak_private: u32,
    #[serde(skip)]
    streak: u32,
    /// The sensor reading of the last sample (drives the green cap).
    #[serde(skip)]
    touching_now: bool,
}

pub struct ButtonPress {
    params: ButtonPressParams,
    task_id: Option<String>,
    goal: GoalChecker,
    commitment: CommitmentTracker,
    sensor_adr: usize,
    cap_geom: usize,
    /// `is_gripper_geom[g]`: g is a gripper collision geom.
    is_gripper_geom: Vec<bool>,
    history: ButtonHistory,
    stages: StageTracker,
    events: Vec<PrivateEvent>,
    control_steps: u64,
    substeps: u64,
}

impl ButtonPress {
    pub fn new(
        params: ButtonPressParams,
        scene: &ComposedScene,
        model: &MjModel,
        task_id: Option<String>,
    ) -> Result<Self, TasksError> {
        let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
        let missing = |kind: &str, name: &str| missing_in_model(CHECKER, kind, name);
        let sensor = model
            .name_to_id(MjtObjBase::mjOBJ_SENSOR, &params.touch_sensor)
            .ok_or_else(|| missing("sensor", &params.touch_sensor))?;
        let cap_name = format!("{}_button_cap", params.button);
        let cap_geom = model.name_to_id(MjtObjBase::mjOBJ_GEOM, &cap_name).ok_or_else(|| missing("geom", &cap_name))?;
        let ngeom = model.ffi().ngeom as usize;
        let is_gripper_geom: Vec<bool> = (0..ngeom)
            .map(|g| {
                model.geom_group()[g] != 1
                    && model.id_to_name(MjtObjBase::mjOBJ_GEOM, g).is_some_and(|n| n.starts_with(GRIPPER_GEOM_PREFIX))
            })
            .collect();
        if !is_gripper_geom.iter().any(|&b| b) {
            return Err(missing("gripper collision geoms", GRIPPER_GEOM_PREFIX));
        }
        let history = ButtonHistory { button: params.button.clone(), ..Default::default() };
        Ok(Self {
            sensor_adr: model.sensor_adr()[sensor] as usize,
            cap_geom,
            is_gripper_geom,
            history,
            stages: StageTracker::new(vec![StageSpec::required(STAGE_NAME)]),
            params,
            task_id,
            goal,
            commitment,
            events: Vec::new(),
            control_steps: 0,
            substeps: 0,
        })
    }

    /// The touch sensor's reading.
    pub fn touch(&self, data: &SimData) -> f64 {
        data.sensordata()[self.sensor_adr]
    }

    /// Whether a gripper collision geom pushes on the cap with at least the minimum normal force.
    pub fn gripper_pushes_cap(&self, data: &SimData) -> bool {
        data.contact().iter().enumerate().any(|(i, c)| {
            let (g1, g2) = (c.geom[0] as usize, c.geom[1] as usize);
            let pair = (g1 == self.cap_geom && self.is_gripper_geom[g2]) || (g2 == self.cap_geom && self.is_gripper_geom[g1]);
            // contact frame: the first component is the normal force
            pair && data.contact_force(i)[0] >= self.params.contact_normal_force_min_n
        })
    }

    fn sample(&mut self, data: &SimData, tick: Tick) {
        let touching = self.touch(data) >= self.params.touch_sensor_min;
        let pressed = touching && self.gripper_pushes_cap(data);
        let h = &mut self.history;
        h.touching_now = touching;
        h.touch_observed_private |= touching;
        if pressed {
            h.pressed_steps_private += 1;
            h.streak += 1;
            h.max_pressed_streak_private = h.max_pressed_streak_private.max(h.streak);
        } else {
            h.streak = 0;
        }
        let done = h.max_pressed_streak_private >= self.params.min_press_streak_substeps;
        if self.stages.advance(tick, |_| done).is_some() {
            self.events.extend(self.commitment.commit_press_event(&self.params.button, tick));
        }
    }

    pub fn history(&self) -> &ButtonHistory {
        &self.history
    }
}

impl Evaluator for ButtonPress {
    fn private_events(&self) -> Vec<PrivateEvent> {
        crate::evaluator::merged_events(&self.stages, &self.events)
    }

    fn stage_progress(&self) -> Option<(usize, usize)> {
        Some((self.stages.completed_required_count(), self.stages.required_count()))
    }

    fn checker(&self) -> &str {
        CHECKER
    }

    fn samples_substeps(&self) -> bool {
        true
    }

    fn reset(&mut self, data: &SimData, _tick: Tick) {
        self.history = ButtonHistory { button: self.params.button.clone(), ..Default::default() };
        self.stages = StageTracker::new(vec![StageSpec::required(STAGE_NAME)]);
        self.events.clear();
        self.control_steps = 0;
        self.substeps = 0;
        self.commitment.reset(self.goal.index(), data);
        self.history.touching_now = self.touch(data) >= self.params.touch_sensor_min;
    }

    fn observe_substep(&mut self, data: &SimData, tick: Tick) {
        self.substeps += 1;
        self.sample(data, tick);
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.control_steps += 1;
        self.sample(data, tick);
        self.events.extend(self.commitment.observe_event(self.goal.index(), data, tick));
    }

    fn finish(&mut self, data: &SimData, _tick: Tick) -> EvaluationRecord {
        let mut record = EvaluationRecord::new(CHECKER);
        self.stages.write_into(&mut record);
        record.task_id = self.task_id.clone();
        record.success = self.stages.all_required_completed();
        // the press history decides; nothing has to hold on the final state (catalog §1.4a)
        record.terminal_state_success = true;
        record.control_steps_observed = self.control_steps;
        record.substeps_observed = self.substeps;
        record.events = self.events.clone();
        record.first_commitment = self.commitment.first().cloned();
        let report = self.goal.evaluate(data);
        record.bddl_final_goal_success = Some(report.success);
        record.bddl_goal = Some(report);
        record.failure_reason = (!record.success).then_some(FailureReason::IncompleteStage);
        record.details = Some(serde_json::json!({
            "buttons": [&self.history],
            "target_button": &self.params.button,
            "target_button_pressed": record.success,
            "wrong_button_pressed": false,
            "min_press_streak_substeps": self.params.min_press_streak_substeps,
        }));
        record
    }

    fn geom_rgba_overrides(&self) -> Vec<(usize, [f32; 4])> {
        if self.history.touching_now { vec![(self.cap_geom, PRESSED_CAP_RGBA)] } else { Vec::new() }
    }
}
