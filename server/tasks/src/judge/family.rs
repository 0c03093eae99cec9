//! The skeleton every staged family evaluator shares, written once: a family states its stage logic (a
//! [`StagedFamily`]) and [`Judged`] makes it an [`Evaluator`].
//!
//! What the skeleton does, the same for every family ([`History`]): it keeps the scene index, the diagnostic BDDL
//! goal, the first-commitment tracker, the task id, the private events and the sample counts; counts each sample and,
//! after the family's control-step sample, records the first commitment; at finish writes the stage fields from the
//! family's [`StageTracker`], the task id and the history (counts, events, first commitment, BDDL goal on the final
//! state) before the family adds its verdict; lists the stage events merged with the others for the live view; and
//! reports the latched required stages as the live progress.
//!
//! What a family writes: its baselines at reset, one sample (control step or physics substep), its stage tracker,
//! and its verdict on the final state ([`StagedFamily::judge`], usually [`judge_checks`]). Adding a task kind
//! is that and the kind's table row ([`build`]); docs/ARCHITECTURE.md, "Where to start". The evaluators that keep
//! no latched stages during the episode (terminal judging: `bddl_terminal`, tube insertion) and the staged
//! evaluator, with its own order modes and monitors, implement [`Evaluator`] themselves on the same [`History`].
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::simulation::SimData;

use crate::TasksError;
use crate::judge::commitment::CommitmentTracker;
use crate::judge::evaluator::{EvaluationRecord, Evaluator, FailureReason, PrivateEvent, StageTracker, TerminalCheck, Tick};
use crate::judge::goal::GoalChecker;
use crate::judge::kind::CheckerParams;
use crate::judge::predicates::SceneIndex;
use crate::judge::support::scene_goal_and_commitment;

/// What every evaluator keeps of an episode besides its stage logic: the scene index, the diagnostic BDDL goal, the
/// first commitment, the private events (the family's own, such as pours or covered markers, and the commitment) and
/// the samples seen.
pub struct History {
    pub index: std::sync::Arc<SceneIndex>,
    pub goal: GoalChecker,
    pub commitment: CommitmentTracker,
    pub task_id: Option<String>,
    /// Private events other than stage events, in the order they happened.
    pub events: Vec<PrivateEvent>,
    pub control_steps: u64,
    pub substeps: u64,
}

impl History {
    pub fn new(goal: GoalChecker, commitment: CommitmentTracker, task_id: Option<String>) -> Self {
        Self { index: goal.index().clone(), goal, commitment, task_id, events: Vec::new(), control_steps: 0, substeps: 0 }
    }

    /// The scene's BDDL goal and first-commitment tracker, for the task `task_id`.
    pub fn for_scene(scene: &ComposedScene, model: &MjModel, task_id: Option<String>) -> Result<Self, TasksError> {
        let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
        Ok(Self::new(goal, commitment, task_id))
    }

    /// Clears the events and counts and captures the commitment baselines on the settled start state.
    pub fn reset(&mut self, data: &SimData) {
        self.events.clear();
        self.control_steps = 0;
        self.substeps = 0;
        self.commitment.reset(&self.index, data);
    }

    /// After a control step's sample: the first commitment, if it happened now.
    pub fn observe_commitment(&mut self, data: &SimData, tick: Tick) {
        self.events.extend(self.commitment.observe_event(&self.index, data, tick));
    }

    /// The fields every evaluator fills the same way: task id, sample counts, private events, first commitment and
    /// the diagnostic BDDL goal on the final state.
    pub fn write_into(&self, record: &mut EvaluationRecord, data: &SimData) {
        record.task_id = self.task_id.clone();
        record.control_steps_observed = self.control_steps;
        record.substeps_observed = self.substeps;
        record.events = self.events.clone();
        record.first_commitment = self.commitment.first().cloned();
        let report = self.goal.evaluate(data);
        record.bddl_final_goal_success = Some(report.success);
        record.bddl_goal = Some(report);
    }
}

/// A family's stage logic: what [`Judged`] needs besides the [`History`] it keeps for every family.
pub trait StagedFamily: Send {
    /// The checker type.
    fn checker(&self) -> &str;
    /// Whether the episode samples the family after every physics substep too (then [`Self::sample`] runs at both
    /// rates, `control` telling which).
    fn samples_substeps(&self) -> bool {
        false
    }
    /// Captures the baselines on the settled start state and starts fresh stages (the history is reset by the core).
    fn reset(&mut self, history: &History, data: &SimData);
    /// One sample: a control step (`control`) or a physics substep. Events of the family's own go to
    /// `history.events`; the first commitment is recorded by the core after a control step's sample.
    fn sample(&mut self, history: &mut History, data: &SimData, tick: Tick, control: bool);
    /// The stages, latched as they complete.
    fn stages(&self) -> &StageTracker;
    /// The verdict on the final state: terminal checks, success, failure reason, details, judgment. `record`
    /// already holds the stage fields and the history.
    fn judge(&self, history: &History, data: &SimData, record: &mut EvaluationRecord);
    /// See [`Evaluator::geom_rgba_overrides`].
    fn geom_rgba_overrides(&self) -> Vec<(usize, [f32; 4])> {
        Vec::new()
    }
}

/// A family's evaluator: its stage logic and the shared history.
pub struct Judged<F> {
    pub history: History,
    pub family: F,
}

impl<F: StagedFamily> Judged<F> {
    pub fn with(history: History, family: F) -> Self {
        Self { history, family }
    }
}

/// A kind's builder ([`crate::judge::kind::BuildEvaluator`]): the scene's history, then the family made from it.
pub fn build<F: StagedFamily + 'static>(
    checker: &CheckerParams,
    scene: &ComposedScene,
    model: &MjModel,
    family: impl FnOnce(&History) -> Result<F, TasksError>,
) -> Result<Box<dyn Evaluator>, TasksError> {
    let history = History::for_scene(scene, model, checker.task_id_owned())?;
    let family = family(&history)?;
    Ok(Box::new(Judged::with(history, family)))
}

impl<F: StagedFamily> Evaluator for Judged<F> {
    fn checker(&self) -> &str {
        self.family.checker()
    }

    fn samples_substeps(&self) -> bool {
        self.family.samples_substeps()
    }

    fn reset(&mut self, data: &SimData, _tick: Tick) {
        self.family.reset(&self.history, data);
        self.history.reset(data);
    }

    fn observe_substep(&mut self, data: &SimData, tick: Tick) {
        if self.family.samples_substeps() {
            self.history.substeps += 1;
            self.family.sample(&mut self.history, data, tick, false);
        }
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.history.control_steps += 1;
        self.family.sample(&mut self.history, data, tick, true);
        self.history.observe_commitment(data, tick);
    }

    fn finish(&mut self, data: &SimData, _tick: Tick) -> EvaluationRecord {
        let mut record = EvaluationRecord::new(self.family.checker());
        self.family.stages().write_into(&mut record);
        self.history.write_into(&mut record, data);
        self.family.judge(&self.history, data, &mut record);
        record
    }

    fn geom_rgba_overrides(&self) -> Vec<(usize, [f32; 4])> {
        self.family.geom_rgba_overrides()
    }

    fn private_events(&self) -> Vec<PrivateEvent> {
        crate::judge::evaluator::merged_events(self.family.stages(), &self.history.events)
    }

    fn stage_progress(&self) -> (usize, usize) {
        let s = self.family.stages();
        (s.completed_required_count(), s.required_count())
    }
}

/// The usual verdict of a staged family, into a record that holds the stage fields: success ⇔ every required stage
/// completed AND every terminal check passed; a failure blames a missing stage before a bad final state
/// ([`FailureReason::of_staged`]).
pub fn judge_checks(record: &mut EvaluationRecord, stages: &StageTracker, checks: Vec<TerminalCheck>) {
    let stages_done = stages.all_required_completed();
    record.terminal_state_success = checks.iter().all(|c| c.passed);
    record.terminal_state_checks = checks;
    record.success = stages_done && record.terminal_state_success;
    record.failure_reason = FailureReason::of_staged(record.success, stages_done);
}

/// A verdict on the latched history alone (nothing must hold on the final state, catalog §1.4a): the checks are
/// reported for the trace, the final state counts as valid, and a failure is an incomplete stage.
pub fn judge_history(record: &mut EvaluationRecord, success: bool, checks: Vec<TerminalCheck>) {
    record.terminal_state_checks = checks;
    record.terminal_state_success = true;
    record.success = success;
    record.failure_reason = (!success).then_some(FailureReason::IncompleteStage);
}

/// A terminal check named `name`.
pub fn terminal_check(name: impl Into<String>, passed: bool) -> TerminalCheck {
    TerminalCheck { name: name.into(), passed }
}
