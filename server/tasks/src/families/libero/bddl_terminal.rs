//! `bddl_terminal` (and `bddl_terminal_open`): success is the BDDL goal conjunction on the final state; nothing
//! is latched (task catalog §1.3 step 5, §1.4: K = 1, completed = success). The goal is also sampled at every control
//! step, only to record diagnostic "goal became true/false" events and the first commitment.
//!
//! Perception tasks judged by the terminal goal (the bin family T01–T05, T07) name their private target in the
//! manifest (`params.judgment_target`); the record then carries `judgment_correct`: the first object grasped and
//! lifted ≥ 0.04 m is the target (task catalog §8.6).
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::simulation::SimData;

use crate::TasksError;
use crate::judge::kind::{CheckerParams, EvaluatorKind, check};
use crate::judge::support::{missing_in_model, scene_goal_and_commitment};

use crate::judge::commitment::CommitmentTracker;
use crate::judge::evaluator::{
    EvaluationRecord, EventKind, Evaluator, FailureReason, PrivateEvent, StageSpec, StageTracker, TerminalCheck, Tick,
};
use crate::judge::family::History;
use crate::judge::goal::GoalChecker;

pub const CHECKER: &str = "bddl_terminal";
/// The same rule under the name the open-vocabulary tasks use.
pub const OPEN_CHECKER: &str = "bddl_terminal_open";

/// Both names' table rows.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind::plain(CHECKER, check::<BddlTerminalParams>, build);
pub const OPEN_EVALUATOR: EvaluatorKind = EvaluatorKind::plain(OPEN_CHECKER, check::<BddlTerminalParams>, build);

fn build(checker: &CheckerParams, scene: &ComposedScene, model: &MjModel) -> Result<Box<dyn Evaluator>, TasksError> {
    let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
    let p: BddlTerminalParams = checker.parse()?;
    if let Some(t) = &p.judgment_target
        && goal.index().instance(t).is_none()
    {
        return Err(missing_in_model(checker.kind, "instance", t));
    }
    let e = BddlTerminal::new(checker.kind, goal, commitment, checker.task_id_owned());
    Ok(Box::new(e.with_judgment_target(p.judgment_target)))
}
/// The single stage of a terminal task.
pub const STAGE_NAME: &str = "01_BDDL_Goal_At_Finish";

/// The manifest's `checker.params` (all optional).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BddlTerminalParams {
    /// Perception tasks: the instance the agent must identify (private).
    #[serde(default)]
    pub judgment_target: Option<String>,
}

pub struct BddlTerminal {
    checker: String,
    judgment_target: Option<String>,
    /// The shared bookkeeping ([`crate::judge::family`]); terminal judging keeps no stages during the episode.
    history: History,
    last_goal: Option<bool>,
}

impl BddlTerminal {
    /// `checker` is the manifest's checker name (`bddl_terminal` or `bddl_terminal_open`; same rule).
    pub fn new(checker: impl Into<String>, goal: GoalChecker, commitment: CommitmentTracker, task_id: Option<String>) -> Self {
        Self { checker: checker.into(), judgment_target: None, history: History::new(goal, commitment, task_id), last_goal: None }
    }

    /// Judges target identification against `target` (an instance of the scene).
    pub fn with_judgment_target(mut self, target: Option<String>) -> Self {
        self.judgment_target = target;
        self
    }

    fn note_goal(&mut self, data: &SimData, tick: Tick) {
        let now = self.history.goal.holds(data);
        if self.last_goal.is_some_and(|was| was != now) {
            let kind = if now { EventKind::GoalSatisfied } else { EventKind::GoalUnsatisfied };
            self.history.events.push(PrivateEvent::new(kind, tick));
        }
        self.last_goal = Some(now);
    }
}

impl Evaluator for BddlTerminal {
    fn checker(&self) -> &str {
        &self.checker
    }

    fn reset(&mut self, data: &SimData, tick: Tick) {
        self.history.reset(data);
        self.last_goal = None;
        self.note_goal(data, tick);
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.history.control_steps += 1;
        self.note_goal(data, tick);
        self.history.observe_commitment(data, tick);
    }

    fn finish(&mut self, data: &SimData, tick: Tick) -> EvaluationRecord {
        let report = self.history.goal.evaluate(data);
        let mut stages = StageTracker::new(vec![StageSpec::required(STAGE_NAME)]);
        stages.advance(tick, |_| report.success);
        let mut record = EvaluationRecord::new(self.checker.clone());
        stages.write_into(&mut record);
        self.history.write_into(&mut record, data);
        record.success = report.success;
        record.terminal_state_success = report.success;
        record.terminal_state_checks =
            report.predicates.iter().map(|p| TerminalCheck { name: p.predicate.clone(), passed: p.value }).collect();
        record.judgment_correct =
            self.judgment_target.as_deref().map(|t| crate::judge::evaluator::judged_target(record.first_commitment.as_ref(), t));
        record.failure_reason = (!record.success).then_some(FailureReason::TerminalStateInvalid);
        record
    }

    fn private_events(&self) -> Vec<PrivateEvent> {
        self.history.events.clone()
    }

    /// K = 1: the goal holding now is the stage that finish would complete.
    fn stage_progress(&self) -> (usize, usize) {
        (usize::from(self.last_goal == Some(true)), 1)
    }
}
