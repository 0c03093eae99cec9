//! `private_physical_weighing` (T08 weigh_and_place_heaviest_mug; catalog §3 T08, PhysicalWeighingEvaluator).
//! Sampled at control steps and physics substeps.
//!
//! * At reset each mug's root height is stored.
//! * Weigh event for mug m (latched once): Grasped(m) AND z_m ≥ z_m(reset) + `weigh_lift_m` at the same sample.
//! * Place event (latched once): all mugs weighed AND `In(target, receptacle_region)` AND Released-and-clear(target)
//!   (not grasped, root ≥ `release_clear_distance_m` from the grip site).
//! * Success at finish ⇔ every mug weighed (ever) AND the target In the region AND released-and-clear, at finish.
//! * Stages (K = mugs + 1): `Weigh_<mug>` per mug (unordered) and `Place_Heaviest_Mug_In_Green_Bin`.
//!
//! The masses (and so which mug is the target) are private: they live in the manifest's params and are written into
//! the compiled model by [`apply_mug_masses`] before the episode starts; every mug is the same asset.
//!
//! Judgment (catalog §8.6, stricter): `judgment_correct` ⇔ at finish the target is In the bin region and no other mug
//! is — the mug the agent chose is the heaviest. (The first grasp-and-lift, the usual first commitment, is here only
//! the first weighing, so it judges nothing.)
use std::collections::BTreeMap;

use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::simulation::SimData;
use serde::{Deserialize, Serialize};

use crate::TasksError;
use crate::judge::commitment::CommitmentTracker;
use crate::judge::evaluator::{
    EvaluationRecord, EventKind, Evaluator, FailureReason, PrivateEvent, TerminalCheck, Tick, score_percent,
};
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::support::{missing_in_model, scene_goal_and_commitment};
use crate::judge::goal::GoalChecker;
use crate::judge::predicates::{EntityRef, SceneIndex, region_contains};

pub const CHECKER: &str = "private_physical_weighing";
pub const PLACE_STAGE: &str = "Place_Heaviest_Mug_In_Green_Bin";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WeighingParams {
    /// Private: mug instance → mass (kg).
    pub mugs: BTreeMap<String, f64>,
    pub weigh_lift_m: f64,
    /// Private: the heaviest mug.
    pub target: String,
    pub receptacle_region: String,
    pub release_clear_distance_m: f64,
}

/// Sets each mug instance's mass (scaling every body of its subtree, inertia with it, so the shape's density is
/// uniform): the private masses of the manifest reach the physics, never a file.
pub fn apply_mug_masses(params: &WeighingParams, model: &mut MjModel) -> Result<(), TasksError> {
    crate::judge::support::set_instance_masses(CHECKER, &params.mugs, model)
}

/// The kind's table row: the mug masses are written into the model before the episode.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind {
    model_edits: Some(|checker, model| apply_mug_masses(&checker.parse()?, model)),
    ..EvaluatorKind::plain(CHECKER, check::<WeighingParams>, |checker, scene, model| {
        let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
        Ok(Box::new(PhysicalWeighing::new(checker.parse()?, goal, commitment, checker.task_id_owned())?))
    })
};

pub struct PhysicalWeighing {
    params: WeighingParams,
    task_id: Option<String>,
    goal: GoalChecker,
    index: std::sync::Arc<SceneIndex>,
    commitment: CommitmentTracker,
    /// (mug name, instance) in stage order.
    mugs: Vec<(String, usize)>,
    target: usize,
    region: usize,
    z0: Vec<f64>,
    weighed: Vec<Option<Tick>>,
    placed: Option<Tick>,
    stage_events: Vec<PrivateEvent>,
    events: Vec<PrivateEvent>,
    control_steps: u64,
    substeps: u64,
}

impl PhysicalWeighing {
    pub fn new(
        params: WeighingParams,
        goal: GoalChecker,
        commitment: CommitmentTracker,
        task_id: Option<String>,
    ) -> Result<Self, TasksError> {
        let index = goal.index().clone();
        let instance = |n: &str| index.instance(n).ok_or_else(|| missing_in_model(CHECKER, "instance", n));
        let mugs = params.mugs.keys().map(|m| Ok((m.clone(), instance(m)?))).collect::<Result<Vec<_>, TasksError>>()?;
        let target = mugs
            .iter()
            .position(|(m, _)| *m == params.target)
            .ok_or_else(|| TasksError::Scene(format!("{CHECKER}: target {:?} is not among the mugs", params.target)))?;
        let region = match index.resolve(&params.receptacle_region) {
            Some(EntityRef::Region(r)) => r,
            _ => return Err(missing_in_model(CHECKER, "region", &params.receptacle_region)),
        };
        let n = mugs.len();
        Ok(Self {
            params,
            task_id,
            goal,
            index,
            commitment,
            mugs,
            target,
            region,
            z0: vec![0.0; n],
            weighed: vec![None; n],
            placed: None,
            stage_events: Vec::new(),
            events: Vec::new(),
            control_steps: 0,
            substeps: 0,
        })
    }

    fn stage_names(&self) -> Vec<String> {
        self.mugs.iter().map(|(m, _)| format!("Weigh_{m}")).chain([PLACE_STAGE.to_owned()]).collect()
    }

    fn pos(&self, data: &SimData, m: usize) -> [f64; 3] {
        data.xpos()[self.index.instances[self.mugs[m].1].body]
    }

    fn in_bin(&self, data: &SimData, m: usize) -> bool {
        region_contains(&self.index, data, self.region, self.pos(data, m))
    }

    fn released_and_clear(&self, data: &SimData, m: usize) -> bool {
        self.commitment.released_and_clear(&self.index, data, self.mugs[m].1, self.params.release_clear_distance_m)
    }

    fn stage_event(&mut self, i: usize, tick: Tick) {
        let names = self.stage_names();
        self.stage_events.push(PrivateEvent {
            stage_index: Some(i),
            stage_name: Some(names[i].clone()),
            ..PrivateEvent::new(EventKind::StageCompleted, tick)
        });
    }

    fn sample(&mut self, data: &SimData, tick: Tick) {
        for m in 0..self.mugs.len() {
            if self.weighed[m].is_none()
                && self.pos(data, m)[2] >= self.z0[m] + self.params.weigh_lift_m
                && self.commitment.grasped(&self.index, data, self.mugs[m].1)
            {
                self.weighed[m] = Some(tick);
                self.stage_event(m, tick);
            }
        }
        if self.placed.is_none()
            && self.weighed.iter().all(Option::is_some)
            && self.in_bin(data, self.target)
            && self.released_and_clear(data, self.target)
        {
            self.placed = Some(tick);
            self.stage_event(self.mugs.len(), tick);
        }
    }
}

impl Evaluator for PhysicalWeighing {
    fn checker(&self) -> &str {
        CHECKER
    }

    fn samples_substeps(&self) -> bool {
        true
    }

    fn reset(&mut self, data: &SimData, _tick: Tick) {
        self.z0 = (0..self.mugs.len()).map(|m| self.pos(data, m)[2]).collect();
        self.weighed = vec![None; self.mugs.len()];
        self.placed = None;
        self.stage_events.clear();
        self.events.clear();
        self.control_steps = 0;
        self.substeps = 0;
        self.commitment.reset(&self.index, data);
    }

    fn observe_substep(&mut self, data: &SimData, tick: Tick) {
        self.substeps += 1;
        self.sample(data, tick);
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.control_steps += 1;
        self.sample(data, tick);
        self.events.extend(self.commitment.observe_event(&self.index, data, tick));
    }

    fn private_events(&self) -> Vec<PrivateEvent> {
        crate::judge::evaluator::merge_events(&self.stage_events, &self.events)
    }

    /// Every weighed mug and the placement, latched as they happen (K = mugs + 1).
    fn stage_progress(&self) -> (usize, usize) {
        let done = self.weighed.iter().filter(|w| w.is_some()).count() + usize::from(self.placed.is_some());
        (done, self.mugs.len() + 1)
    }

    fn finish(&mut self, data: &SimData, _tick: Tick) -> EvaluationRecord {
        let mut record = EvaluationRecord::new(CHECKER);
        record.task_id = self.task_id.clone();
        let names = self.stage_names();
        let done: Vec<bool> = self.weighed.iter().map(Option::is_some).chain([self.placed.is_some()]).collect();
        record.required_stage_count = names.len();
        record.completed_required_stage_count = done.iter().filter(|&&d| d).count();
        record.stage_score_percent = score_percent(record.completed_required_stage_count, record.required_stage_count);
        record.completed_stage_names = names.iter().zip(&done).filter(|(_, d)| **d).map(|(n, _)| n.clone()).collect();
        record.ordered_stage_names = names;
        record.stage_events = self.stage_events.clone();
        let all_weighed = self.weighed.iter().all(Option::is_some);
        let target_in = self.in_bin(data, self.target);
        let released = self.released_and_clear(data, self.target);
        let target_name = &self.mugs[self.target].0;
        record.terminal_state_checks = vec![
            TerminalCheck { name: "all_mugs_weighed".into(), passed: all_weighed },
            TerminalCheck { name: format!("in {target_name} {}", self.params.receptacle_region), passed: target_in },
            TerminalCheck { name: format!("released_and_clear {target_name}"), passed: released },
        ];
        record.terminal_state_success = target_in && released;
        record.success = all_weighed && target_in && released;
        record.control_steps_observed = self.control_steps;
        record.substeps_observed = self.substeps;
        record.events = self.events.clone();
        record.first_commitment = self.commitment.first().cloned();
        let others_in = (0..self.mugs.len()).any(|m| m != self.target && self.in_bin(data, m));
        record.judgment_correct = Some(target_in && !others_in);
        let report = self.goal.evaluate(data);
        record.bddl_final_goal_success = Some(report.success);
        record.bddl_goal = Some(report);
        record.failure_reason = FailureReason::of_staged(record.success, all_weighed);
        let weighing: Vec<serde_json::Value> = self
            .mugs
            .iter()
            .zip(&self.weighed)
            .map(|((m, _), w)| serde_json::json!({"mug": m, "weighed_at": w}))
            .collect();
        record.details = Some(serde_json::json!({
            "weighing_interactions": weighing,
            "target": target_name,
            "other_mug_in_bin": others_in,
        }));
        record
    }
}
