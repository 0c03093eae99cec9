//! `private_ordered_physical_pour` (T20 pour_wine_into_mug; task catalog §4 T20): lift the wine bottle, then tilt it
//! over the mug. Stages `01_Lift_Wine_Bottle` (lift seen) then `02_Pour_Wine_Into_Mug` (≥ 1 pour event), counted by
//! the shared pour counter ([`crate::judge::pouring`]); substeps are counted but ignored.
//!
//! Success ⇔ both stages completed AND a lift observed AND ≥ 1 pour. Nothing is required of the final state.
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::Deserialize;

use crate::TasksError;
use crate::judge::commitment::CommitmentTracker;
use crate::judge::evaluator::{
    EvaluationRecord, EventKind, Evaluator, FailureReason, PrivateEvent, StageSpec, StageTracker, TerminalCheck, Tick,
};
use crate::judge::goal::GoalChecker;
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::pouring::{PourCounterConfig, PourTracker};
use crate::judge::support::{fill_history, scene_goal_and_commitment};
use crate::judge::predicates::SceneIndex;

pub const CHECKER: &str = "private_ordered_physical_pour";
pub const STAGES: [&str; 2] = ["01_Lift_Wine_Bottle", "02_Pour_Wine_Into_Mug"];

/// T20's parameters (manifest `checker.params`, every field from there).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PourParams {
    pub bottle: String,
    pub target_site: String,
    #[serde(flatten)]
    pub counter: PourCounterConfig,
    #[serde(deserialize_with = "crate::judge::stage_types::stage_names")]
    pub stages: Vec<String>,
}

/// The kind's table row.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind::plain(CHECKER, check::<PourParams>, |checker, scene, model| {
    let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
    Ok(Box::new(PourWine::new(checker.parse()?, goal, commitment, model, checker.task_id_owned())?))
});

pub struct PourWine {
    params: PourParams,
    index: std::sync::Arc<SceneIndex>,
    goal: GoalChecker,
    commitment: CommitmentTracker,
    task_id: Option<String>,
    bottle_body: usize,
    target_site: usize,
    tracker: PourTracker,
    stages: StageTracker,
    events: Vec<PrivateEvent>,
    control_steps: u64,
    substeps: u64,
}

impl PourWine {
    pub fn new(
        params: PourParams,
        goal: GoalChecker,
        commitment: CommitmentTracker,
        model: &MjModel,
        task_id: Option<String>,
    ) -> Result<Self, TasksError> {
        let index = goal.index().clone();
        let bottle = index.instance(&params.bottle).ok_or_else(|| TasksError::Scene(format!("no object {}", params.bottle)))?;
        let target_site = model
            .name_to_id(MjtObjBase::mjOBJ_SITE, &params.target_site)
            .ok_or_else(|| TasksError::Scene(format!("model has no site {:?}", params.target_site)))?;
        let bottle_body = index.instances[bottle].body;
        let tracker = PourTracker::new(&params.counter, bottle_body, target_site, 0.0);
        let stages = StageTracker::new(params.stages.iter().map(StageSpec::required).collect());
        Ok(Self {
            bottle_body,
            params,
            index,
            goal,
            commitment,
            task_id,
            target_site,
            tracker,
            stages,
            events: Vec::new(),
            control_steps: 0,
            substeps: 0,
        })
    }
}

impl Evaluator for PourWine {
    fn private_events(&self) -> Vec<PrivateEvent> {
        crate::judge::evaluator::merged_events(&self.stages, &self.events)
    }

    fn stage_progress(&self) -> (usize, usize) {
        (self.stages.completed_required_count(), self.stages.required_count())
    }

    fn checker(&self) -> &str {
        CHECKER
    }

    fn samples_substeps(&self) -> bool {
        true
    }

    fn reset(&mut self, data: &SimData, _tick: Tick) {
        let z0_m = data.xpos()[self.bottle_body][2];
        self.tracker = PourTracker::new(&self.params.counter, self.bottle_body, self.target_site, z0_m);
        self.stages = StageTracker::new(self.params.stages.iter().map(StageSpec::required).collect());
        self.events.clear();
        self.control_steps = 0;
        self.substeps = 0;
        self.commitment.reset(&self.index, data);
    }

    fn observe_substep(&mut self, _data: &SimData, _tick: Tick) {
        self.substeps += 1;
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.control_steps += 1;
        if self.tracker.update(data, tick.control_step).is_some() {
            let event = PrivateEvent { subject: Some(self.params.bottle.clone()), ..PrivateEvent::new(EventKind::PourDetected, tick) };
            self.events.push(event);
        }
        let (lift_seen, pours) = (self.tracker.lift_seen(), self.tracker.pours().len());
        self.stages.advance(tick, |i| if i == 0 { lift_seen } else { pours >= 1 });
        self.events.extend(self.commitment.observe_event(&self.index, data, tick));
    }

    fn finish(&mut self, data: &SimData, _tick: Tick) -> EvaluationRecord {
        let mut record = EvaluationRecord::new(CHECKER);
        self.stages.write_into(&mut record);
        record.task_id = self.task_id.clone();
        let (lift, pours) = (self.tracker.lift_seen(), self.tracker.pours().len());
        // nothing beyond the latched events is checked on the final state (catalog §1.4a); reported for the trace
        record.terminal_state_checks = vec![
            TerminalCheck { name: "lift_observed".into(), passed: lift },
            TerminalCheck {
                name: format!("pour_events >= 1 (count {pours}, max tilt {:.3} rad)", self.tracker.max_tilt_rad()),
                passed: pours >= 1,
            },
        ];
        record.terminal_state_success = true;
        record.success = self.stages.all_required_completed() && lift && pours >= 1;
        let counts = (self.control_steps, self.substeps);
        fill_history(&mut record, counts, &self.events, &self.commitment, &self.goal, data);
        record.failure_reason = (!record.success).then_some(FailureReason::IncompleteStage);
        record
    }
}
