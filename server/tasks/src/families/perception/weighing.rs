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
use crate::judge::evaluator::{EvaluationRecord, FailureReason, StageSpec, StageTracker, Tick};
use crate::judge::family::{History, StagedFamily, build, terminal_check};
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::predicates::{EntityRef, region_contains};
use crate::judge::support::missing_in_model;

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
        build(checker, scene, model, |h| PhysicalWeighing::new(checker.parse()?, h))
    })
};

/// The kind's stage logic on the simulation (the shared skeleton: [`crate::judge::family`]). The stages are
/// unordered latches: every one not yet completed is tested at every sample.
pub struct PhysicalWeighing {
    params: WeighingParams,
    /// (mug name, instance) in stage order.
    mugs: Vec<(String, usize)>,
    target: usize,
    region: usize,
    z0: Vec<f64>,
    /// `Weigh_<mug>` per mug, then the placement.
    stages: StageTracker,
}

impl PhysicalWeighing {
    pub fn new(params: WeighingParams, history: &History) -> Result<Self, TasksError> {
        let index = &history.index;
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
        let stages = Self::fresh_stages(&mugs);
        Ok(Self { params, mugs, target, region, z0: vec![0.0; n], stages })
    }

    fn fresh_stages(mugs: &[(String, usize)]) -> StageTracker {
        StageTracker::new(mugs.iter().map(|(m, _)| format!("Weigh_{m}")).chain([PLACE_STAGE.to_owned()]).map(StageSpec::required).collect())
    }

    fn pos(&self, h: &History, data: &SimData, m: usize) -> [f64; 3] {
        data.xpos()[h.index.instances[self.mugs[m].1].body]
    }

    fn in_bin(&self, h: &History, data: &SimData, m: usize) -> bool {
        region_contains(&h.index, data, self.region, self.pos(h, data, m))
    }

    fn released_and_clear(&self, h: &History, data: &SimData, m: usize) -> bool {
        h.commitment.released_and_clear(&h.index, data, self.mugs[m].1, self.params.release_clear_distance_m)
    }

    fn all_weighed(&self) -> bool {
        (0..self.mugs.len()).all(|m| self.stages.is_completed(m))
    }
}

impl StagedFamily for PhysicalWeighing {
    fn checker(&self) -> &str {
        CHECKER
    }

    fn samples_substeps(&self) -> bool {
        true
    }

    fn reset(&mut self, h: &History, data: &SimData) {
        self.z0 = (0..self.mugs.len()).map(|m| self.pos(h, data, m)[2]).collect();
        self.stages = Self::fresh_stages(&self.mugs);
    }

    /// Weigh events (one per mug, latched), then the place event, which needs every mug weighed (this sample's
    /// weighings included).
    fn sample(&mut self, h: &mut History, data: &SimData, tick: Tick, _control: bool) {
        let n = self.mugs.len();
        let weighed: Vec<bool> = (0..n)
            .map(|m| {
                self.stages.is_completed(m)
                    || (self.pos(h, data, m)[2] >= self.z0[m] + self.params.weigh_lift_m
                        && h.commitment.grasped(&h.index, data, self.mugs[m].1))
            })
            .collect();
        let placed = weighed.iter().all(|&w| w)
            && self.in_bin(h, data, self.target)
            && self.released_and_clear(h, data, self.target);
        self.stages.complete_where(tick, |i| if i < n { weighed[i] } else { placed });
    }

    fn stages(&self) -> &StageTracker {
        &self.stages
    }

    fn judge(&self, h: &History, data: &SimData, record: &mut EvaluationRecord) {
        let all_weighed = self.all_weighed();
        let target_in = self.in_bin(h, data, self.target);
        let released = self.released_and_clear(h, data, self.target);
        let target_name = &self.mugs[self.target].0;
        record.terminal_state_checks = vec![
            terminal_check("all_mugs_weighed", all_weighed),
            terminal_check(format!("in {target_name} {}", self.params.receptacle_region), target_in),
            terminal_check(format!("released_and_clear {target_name}"), released),
        ];
        record.terminal_state_success = target_in && released;
        record.success = all_weighed && target_in && released;
        let others_in = (0..self.mugs.len()).any(|m| m != self.target && self.in_bin(h, data, m));
        record.judgment_correct = Some(target_in && !others_in);
        record.failure_reason = FailureReason::of_staged(record.success, all_weighed);
        let weighing: Vec<serde_json::Value> = self
            .mugs
            .iter()
            .enumerate()
            .map(|(m, (name, _))| serde_json::json!({"mug": name, "weighed_at": self.stages.completed_at(m)}))
            .collect();
        record.details = Some(serde_json::json!({
            "weighing_interactions": weighing,
            "target": target_name,
            "other_mug_in_bin": others_in,
        }));
    }
}
