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
//!
//! `private_contact_gated_button` (T06, T09, T10; catalog §3.1) is the same sampling over three buttons: a press of the
//! target needs the 11-sample run, a single pressed sample on any other button latches `wrong_button_pressed` (a
//! failure). There the first pressed sample of any button is the first commitment (catalog §8.6: "the first button
//! reaching a contact press"), and `judgment_correct` ⇔ that button is the private target.
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::{Deserialize, Serialize};

use crate::TasksError;
use crate::judge::evaluator::{EvaluationRecord, StageSpec, StageTracker, Tick};
use crate::judge::family::{History, Judged, StagedFamily, judge_history};
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::support::missing_in_model;

pub const CHECKER: &str = "private_button_press";
pub const GATED_CHECKER: &str = "private_contact_gated_button";

/// The two kinds' table rows.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind::plain(CHECKER, check::<ButtonPressParams>, |checker, scene, model| {
    Ok(Box::new(ButtonPress::new(checker.parse()?, scene, model, checker.task_id_owned())?))
});
pub const GATED_EVALUATOR: EvaluatorKind = EvaluatorKind::plain(GATED_CHECKER, check::<GatedButtonParams>, |checker, scene, model| {
    Ok(Box::new(ButtonPress::gated(checker.parse()?, scene, model, checker.task_id_owned())?))
});
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
    pub touch_sensor_min: f64,
    pub contact_normal_force_min_n: f64,
    pub min_press_streak_substeps: u32,
}

/// The manifest's `checker.params` of `private_contact_gated_button`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GatedButtonParams {
    /// Private: the button the agent must press.
    pub target_button: String,
    /// Every button instance (touch sensor `<b>_button_touch`, cap `<b>_button_cap`).
    pub buttons: Vec<String>,
    pub touch_sensor_min: f64,
    pub contact_normal_force_min_n: f64,
    pub min_press_streak_substeps: u32,
    pub wrong_press_fails: bool,
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

/// One watched button.
struct Watched {
    sensor_adr: usize,
    cap_geom: usize,
    history: ButtonHistory,
}

/// The kinds' stage logic on the simulation (the shared skeleton: [`crate::judge::family`]).
pub struct Buttons {
    checker: &'static str,
    params: ButtonPressParams,
    /// All watched buttons; `target` indexes the one to press.
    buttons: Vec<Watched>,
    target: usize,
    /// Contact-gated family: pressing another button fails, the first pressed sample commits, judgment is reported.
    gated: bool,
    wrong_press_fails: bool,
    wrong_button_pressed: bool,
    /// `is_gripper_geom[g]`: g is a gripper collision geom.
    is_gripper_geom: Vec<bool>,
    stages: StageTracker,
}

/// Either kind's evaluator.
pub type ButtonPress = Judged<Buttons>;

impl Judged<Buttons> {
    /// T13: one button, `params.button`.
    pub fn new(
        params: ButtonPressParams,
        scene: &ComposedScene,
        model: &MjModel,
        task_id: Option<String>,
    ) -> Result<Self, TasksError> {
        let sensor = params.touch_sensor.clone();
        let button = params.button.clone();
        Buttons::build(CHECKER, params, &[(button, sensor)], 0, false, false, scene, model, task_id)
    }

    /// T06, T09, T10: several buttons, one target; a press of another one fails.
    pub fn gated(
        params: GatedButtonParams,
        scene: &ComposedScene,
        model: &MjModel,
        task_id: Option<String>,
    ) -> Result<Self, TasksError> {
        let target = params.buttons.iter().position(|b| *b == params.target_button).ok_or_else(|| {
            TasksError::Scene(format!("{GATED_CHECKER}: target {:?} is not among the buttons", params.target_button))
        })?;
        let named: Vec<(String, String)> = params.buttons.iter().map(|b| (b.clone(), format!("{b}_button_touch"))).collect();
        let single = ButtonPressParams {
            button: params.target_button.clone(),
            touch_sensor: named[target].1.clone(),
            touch_sensor_min: params.touch_sensor_min,
            contact_normal_force_min_n: params.contact_normal_force_min_n,
            min_press_streak_substeps: params.min_press_streak_substeps,
        };
        Buttons::build(GATED_CHECKER, single, &named, target, true, params.wrong_press_fails, scene, model, task_id)
    }
}

impl Buttons {
    #[allow(clippy::too_many_arguments)]
    fn build(
        checker: &'static str,
        params: ButtonPressParams,
        named: &[(String, String)],
        target: usize,
        gated: bool,
        wrong_press_fails: bool,
        scene: &ComposedScene,
        model: &MjModel,
        task_id: Option<String>,
    ) -> Result<ButtonPress, TasksError> {
        let history = History::for_scene(scene, model, task_id)?;
        let missing = |kind: &str, name: &str| missing_in_model(checker, kind, name);
        let mut buttons = Vec::new();
        for (button, sensor_name) in named {
            let sensor = model.name_to_id(MjtObjBase::mjOBJ_SENSOR, sensor_name).ok_or_else(|| missing("sensor", sensor_name))?;
            let cap_name = format!("{button}_button_cap");
            let cap_geom = model.name_to_id(MjtObjBase::mjOBJ_GEOM, &cap_name).ok_or_else(|| missing("geom", &cap_name))?;
            let history = ButtonHistory { button: button.clone(), ..Default::default() };
            buttons.push(Watched { sensor_adr: model.sensor_adr()[sensor] as usize, cap_geom, history });
        }
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
        let family = Self {
            checker,
            buttons,
            target,
            gated,
            wrong_press_fails,
            wrong_button_pressed: false,
            is_gripper_geom,
            stages: StageTracker::new(vec![StageSpec::required(STAGE_NAME)]),
            params,
        };
        Ok(Judged::with(history, family))
    }

    fn gripper_pushes(&self, data: &SimData, cap_geom: usize) -> bool {
        data.contact().iter().enumerate().any(|(i, c)| {
            let (g1, g2) = (c.geom[0] as usize, c.geom[1] as usize);
            let pair = (g1 == cap_geom && self.is_gripper_geom[g2]) || (g2 == cap_geom && self.is_gripper_geom[g1]);
            // contact frame: the first component is the normal force
            pair && data.contact_force(i)[0] >= self.params.contact_normal_force_min_n
        })
    }

    /// The target button's history.
    pub fn history(&self) -> &ButtonHistory {
        &self.buttons[self.target].history
    }
}

impl StagedFamily for Buttons {
    fn checker(&self) -> &str {
        self.checker
    }

    fn samples_substeps(&self) -> bool {
        true
    }

    fn reset(&mut self, _history: &History, data: &SimData) {
        for b in &mut self.buttons {
            b.history = ButtonHistory { button: b.history.button.clone(), ..Default::default() };
            b.history.touching_now = data.sensordata()[b.sensor_adr] >= self.params.touch_sensor_min;
        }
        self.wrong_button_pressed = false;
        self.stages = StageTracker::new(vec![StageSpec::required(STAGE_NAME)]);
    }

    fn sample(&mut self, h: &mut History, data: &SimData, tick: Tick, _control: bool) {
        for b in 0..self.buttons.len() {
            let touching = data.sensordata()[self.buttons[b].sensor_adr] >= self.params.touch_sensor_min;
            let pressed = touching && self.gripper_pushes(data, self.buttons[b].cap_geom);
            let bh = &mut self.buttons[b].history;
            bh.touching_now = touching;
            bh.touch_observed_private |= touching;
            if pressed {
                bh.pressed_steps_private += 1;
                bh.streak += 1;
                bh.max_pressed_streak_private = bh.max_pressed_streak_private.max(bh.streak);
            } else {
                bh.streak = 0;
            }
            if pressed && self.gated {
                if b != self.target {
                    self.wrong_button_pressed = true;
                }
                let name = self.buttons[b].history.button.clone();
                h.events.extend(h.commitment.commit_press_event(&name, tick));
            }
        }
        let done = self.buttons[self.target].history.max_pressed_streak_private >= self.params.min_press_streak_substeps;
        if self.stages.advance(tick, |_| done).is_some() {
            h.events.extend(h.commitment.commit_press_event(&self.params.button, tick));
        }
    }

    fn stages(&self) -> &StageTracker {
        &self.stages
    }

    /// The press history decides; nothing has to hold on the final state (catalog §1.4a).
    fn judge(&self, _history: &History, _data: &SimData, record: &mut EvaluationRecord) {
        let target_pressed = self.stages.all_required_completed();
        let wrong_fails = self.wrong_press_fails && self.wrong_button_pressed;
        judge_history(record, target_pressed && !wrong_fails, Vec::new());
        if self.gated {
            let target = &self.buttons[self.target].history.button;
            record.judgment_correct = Some(crate::judge::evaluator::judged_target(record.first_commitment.as_ref(), target));
        }
        let histories: Vec<&ButtonHistory> = self.buttons.iter().map(|b| &b.history).collect();
        record.details = Some(serde_json::json!({
            "buttons": histories,
            "target_button": &self.params.button,
            "target_button_pressed": target_pressed,
            "wrong_button_pressed": self.wrong_button_pressed,
            "min_press_streak_substeps": self.params.min_press_streak_substeps,
        }));
    }

    fn geom_rgba_overrides(&self) -> Vec<(usize, [f32; 4])> {
        self.buttons.iter().filter(|b| b.history.touching_now).map(|b| (b.cap_geom, PRESSED_CAP_RGBA)).collect()
    }
}
