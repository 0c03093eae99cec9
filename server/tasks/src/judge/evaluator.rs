//! Private evaluators: the contract between an episode and the code that judges it, and the machinery shared by
//! all of them (time-stamped events, ordered latched stages with regression tracking, terminal checks, the result
//! record of protocol §4.9, first-commitment tracking for judgment).
//!
//! Life cycle (task catalog §1.3): the episode restores the init state, settles 10 control steps, then calls
//! [`Evaluator::reset`] (baselines are captured here), then [`Evaluator::observe_control_step`] after every control
//! step and, for evaluators whose [`Evaluator::samples_substeps`] is true, [`Evaluator::observe_substep`] after every
//! physics substep (25 per control step, before the control-step call). [`Evaluator::finish`] judges the final state.
use libero_sim::simulation::SimData;
use serde::{Deserialize, Serialize};

pub use crate::judge::events::{EventKind, PrivateEvent, Tick};
use crate::judge::goal::GoalReport;

pub const RECORD_SCHEMA: &str = "libero_agent.private_evaluation.v1";

/// One stage of an evaluator.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StageSpec {
    pub name: String,
    /// Optional stages are reported but do not count toward K.
    pub required: bool,
}

impl StageSpec {
    pub fn required(name: impl Into<String>) -> Self {
        Self { name: name.into(), required: true }
    }
}

/// Ordered, latched stages. At most one stage completes per tick and completed stages never un-complete
/// (task catalog §1.4); regressions of completed stages are recorded as events and counted.
#[derive(Debug, Clone)]
pub struct StageTracker {
    specs: Vec<StageSpec>,
    completed_at: Vec<Option<Tick>>,
    /// Whether each completed stage's condition held at its last re-test.
    holding: Vec<bool>,
    regressions: Vec<u32>,
    /// When, and the (later, current) stages of the violation.
    order_violation: Option<(Tick, usize, usize)>,
    events: Vec<PrivateEvent>,
}

impl StageTracker {
    pub fn new(specs: Vec<StageSpec>) -> Self {
        let n = specs.len();
        Self {
            specs,
            completed_at: vec![None; n],
            holding: vec![false; n],
            regressions: vec![0; n],
            order_violation: None,
            events: Vec::new(),
        }
    }

    /// The first stage not yet completed, unless a strict-order violation froze progress.
    pub fn current(&self) -> Option<usize> {
        if self.order_violation.is_some() {
            return None;
        }
        self.completed_at.iter().position(Option::is_none)
    }

    fn stage_event(&self, kind: EventKind, tick: Tick, i: usize) -> PrivateEvent {
        PrivateEvent { stage_index: Some(i), stage_name: Some(self.specs[i].name.clone()), ..PrivateEvent::new(kind, tick) }
    }

    fn complete(&mut self, tick: Tick, i: usize) {
        self.completed_at[i] = Some(tick);
        self.holding[i] = true;
        self.events.push(self.stage_event(EventKind::StageCompleted, tick, i));
    }

    /// Tests only the current stage and completes it if `holds` (RoboMemArena ordered evaluator: a later stage
    /// that already holds simply completes once it becomes current). Returns the stage completed at this tick.
    pub fn advance(&mut self, tick: Tick, holds: impl FnOnce(usize) -> bool) -> Option<usize> {
        let i = self.current()?;
        holds(i).then(|| {
            self.complete(tick, i);
            i
        })
    }

    /// Strict order (`_StrictPredicateSequence`): before testing the current stage, every later stage is tested;
    /// if one already holds, the run is latched as an ordering violation and makes no further progress.
    pub fn advance_strict(&mut self, tick: Tick, mut holds: impl FnMut(usize) -> bool) -> Option<usize> {
        let i = self.current()?;
        if let Some(later) = (i + 1..self.specs.len()).find(|&j| holds(j)) {
            self.order_violation = Some((tick, later, i));
            let subject = Some(format!("{}_before_{}", self.specs[later].name, self.specs[i].name));
            self.events.push(PrivateEvent { subject, ..self.stage_event(EventKind::OrderViolation, tick, i) });
            return None;
        }
        holds(i).then(|| {
            self.complete(tick, i);
            i
        })
    }

    /// Completes every not yet completed stage that `holds`, in no order (terminal-only judging, where the stages
    /// are independent checks on one final state).
    pub fn complete_where(&mut self, tick: Tick, mut holds: impl FnMut(usize) -> bool) {
        for i in 0..self.specs.len() {
            if self.completed_at[i].is_none() && holds(i) {
                self.complete(tick, i);
            }
        }
    }

    /// Re-tests completed stages: a stage whose condition stops holding is recorded once per drop (event +
    /// count); it stays completed.
    pub fn track_regressions(&mut self, tick: Tick, mut holds: impl FnMut(usize) -> bool) {
        for i in 0..self.specs.len() {
            if self.completed_at[i].is_none() {
                continue;
            }
            let now = holds(i);
            if self.holding[i] && !now {
                self.regressions[i] += 1;
                self.events.push(self.stage_event(EventKind::StageRegressed, tick, i));
            }
            self.holding[i] = now;
        }
    }

    /// When stage `i` completed (`None` while it has not).
    pub fn completed_at(&self, i: usize) -> Option<Tick> {
        self.completed_at.get(i).copied().flatten()
    }

    /// Whether stage `i` has completed.
    pub fn is_completed(&self, i: usize) -> bool {
        self.completed_at.get(i).is_some_and(Option::is_some)
    }

    pub fn order_violated(&self) -> bool {
        self.order_violation.is_some()
    }

    /// `<later>_before_<current>` of a strict-order violation, as the original evaluator names the latch.
    pub fn order_violation_label(&self) -> Option<String> {
        self.order_violation.map(|(_, later, current)| format!("{}_before_{}", self.specs[later].name, self.specs[current].name))
    }

    pub fn required_count(&self) -> usize {
        self.specs.iter().filter(|s| s.required).count()
    }

    pub fn completed_required_count(&self) -> usize {
        self.specs.iter().zip(&self.completed_at).filter(|(s, c)| s.required && c.is_some()).count()
    }

    pub fn all_required_completed(&self) -> bool {
        self.completed_required_count() == self.required_count()
    }

    pub fn events(&self) -> &[PrivateEvent] {
        &self.events
    }

    /// Fills the stage fields of `record`.
    pub fn write_into(&self, record: &mut EvaluationRecord) {
        let names = |f: &dyn Fn(usize) -> bool| -> Vec<String> {
            (0..self.specs.len()).filter(|&i| f(i)).map(|i| self.specs[i].name.clone()).collect()
        };
        record.required_stage_count = self.required_count();
        record.completed_required_stage_count = self.completed_required_count();
        record.stage_score_percent = score_percent(record.completed_required_stage_count, record.required_stage_count);
        record.ordered_stage_names = names(&|i| self.specs[i].required);
        record.optional_stage_names = names(&|i| !self.specs[i].required);
        record.completed_stage_names = names(&|i| self.completed_at[i].is_some());
        record.stage_regressions = (0..self.specs.len())
            .filter(|&i| self.regressions[i] > 0)
            .map(|i| StageRegressions { stage_name: self.specs[i].name.clone(), count: self.regressions[i] })
            .collect();
        record.stage_events = self.events.clone();
    }
}

/// A tracker's stage events and an evaluator's other events in one time-ordered list (stable: at equal ticks,
/// stage events first), for [`Evaluator::private_events`].
pub fn merged_events(stages: &StageTracker, others: &[PrivateEvent]) -> Vec<PrivateEvent> {
    merge_events(stages.events(), others)
}

/// As [`merged_events`], for an evaluator that keeps its stage events itself (no [`StageTracker`]).
pub fn merge_events(stage_events: &[PrivateEvent], others: &[PrivateEvent]) -> Vec<PrivateEvent> {
    let mut all: Vec<PrivateEvent> = stage_events.iter().chain(others).cloned().collect();
    all.sort_by(|a, b| {
        let key = |e: &PrivateEvent| (e.tick.control_step, e.tick.substep.unwrap_or(u32::MAX));
        key(a).cmp(&key(b))
    });
    all
}

/// `100 × completed / K` (0 when K = 0).
pub fn score_percent(completed: usize, required: usize) -> f64 {
    if required == 0 { 0.0 } else { 100.0 * completed as f64 / required as f64 }
}

/// A check made on the final state at finish.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TerminalCheck {
    pub name: String,
    pub passed: bool,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StageRegressions {
    pub stage_name: String,
    pub count: u32,
}

/// Why an episode failed, in the vocabulary of protocol §4.9 (plus `order_violation`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FailureReason {
    IncompleteStage,
    TerminalStateInvalid,
    OrderViolation,
    ExtraPour,
    /// A forbidden contact was seen (T25: a bowl touched the tabletop).
    ForbiddenContact,
    /// T30: the target rose with the board tilted before both counterweights were placed.
    PrematureLiftDetected,
}

impl FailureReason {
    /// The usual verdict of a staged evaluator: none on success, else an incomplete stage before a bad final state.
    pub fn of_staged(success: bool, stages_done: bool) -> Option<Self> {
        if success {
            None
        } else if !stages_done {
            Some(Self::IncompleteStage)
        } else {
            Some(Self::TerminalStateInvalid)
        }
    }
}

/// The private evaluation of one episode (`result.json` → `private_evaluation`; protocol §4.9).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EvaluationRecord {
    pub schema_version: &'static str,
    /// Evaluator type, e.g. `bddl_terminal`.
    pub checker: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub task_id: Option<String>,
    pub success: bool,
    pub required_stage_count: usize,
    pub completed_required_stage_count: usize,
    pub stage_score_percent: f64,
    pub ordered_stage_names: Vec<String>,
    pub completed_stage_names: Vec<String>,
    pub optional_stage_names: Vec<String>,
    pub stage_regressions: Vec<StageRegressions>,
    pub terminal_state_success: bool,
    pub terminal_state_checks: Vec<TerminalCheck>,
    pub control_steps_observed: u64,
    pub substeps_observed: u64,
    /// Stage events (`private_stage_events.jsonl`).
    pub stage_events: Vec<PrivateEvent>,
    /// Other private events (commitment, diagnostic goal changes).
    pub events: Vec<PrivateEvent>,
    pub first_commitment: Option<Commitment>,
    /// The BDDL goal on the final state, per predicate (the success rule of `bddl_terminal`, a diagnostic for
    /// private evaluators: `bddl_final_goal_success`).
    pub bddl_goal: Option<GoalReport>,
    pub bddl_final_goal_success: Option<bool>,
    pub failure_reason: Option<FailureReason>,
    /// Perception tasks: whether the agent's first commitment (see [`CommitmentTracker`]) was the private target
    /// (task catalog §1.5/§8.6; per-task definitions in tasks/README.md). `None` for tasks that judge no target.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub judgment_correct: Option<bool>,
    /// Evaluator-specific private diagnostics (per-button press history, measured insertion values, …).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub details: Option<serde_json::Value>,
    /// Per-stage reached / succeeded / regressions / sustained-contact ratio, derived from the fields above by
    /// [`EvaluationRecord::with_stage_diagnostics`] (never filled by evaluators themselves).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub stage_diagnostics: Vec<StageDiagnostic>,
    /// The stage types the catalog declares, by stage name (set by the registry's [`crate::judge::annotated`]
    /// wrapper, read by the diagnostics; not part of the record's JSON).
    #[serde(skip)]
    pub stage_types: Vec<(String, crate::judge::stage_types::StageType)>,
    /// Every stage is available from the start (the unordered cooking goals) instead of one after another; read by
    /// the diagnostics, set by the evaluator that knows (not part of the record's JSON).
    #[serde(skip)]
    pub stages_unordered: bool,
}

/// One stage's diagnostics in the record (computed by [`crate::judge::diagnostics`], which documents each field).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StageDiagnostic {
    pub stage_name: String,
    #[serde(rename = "type", skip_serializing_if = "Option::is_none")]
    pub stage_type: Option<crate::judge::stage_types::StageType>,
    pub required: bool,
    pub reached: bool,
    pub succeeded: bool,
    /// Control step at which the stage first completed.
    pub completed_control_step: Option<u64>,
    pub regressions: u32,
    pub regressed_during_later_stage: bool,
    /// Share of the operation's control steps inside gripper–mechanism contact runs of ≥ 5 steps (stages with a
    /// monitored mechanism operation; `None` elsewhere).
    pub sustained_contact_ratio_percent: Option<f64>,
    pub contact_exec_steps: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub operation: Option<crate::judge::mechanism::OperationKind>,
    pub failure_reason: Option<String>,
}

impl EvaluationRecord {
    pub fn new(checker: impl Into<String>) -> Self {
        Self {
            schema_version: RECORD_SCHEMA,
            checker: checker.into(),
            task_id: None,
            success: false,
            required_stage_count: 0,
            completed_required_stage_count: 0,
            stage_score_percent: 0.0,
            ordered_stage_names: Vec::new(),
            completed_stage_names: Vec::new(),
            optional_stage_names: Vec::new(),
            stage_regressions: Vec::new(),
            terminal_state_success: false,
            terminal_state_checks: Vec::new(),
            control_steps_observed: 0,
            substeps_observed: 0,
            stage_events: Vec::new(),
            events: Vec::new(),
            first_commitment: None,
            bddl_goal: None,
            bddl_final_goal_success: None,
            failure_reason: None,
            judgment_correct: None,
            details: None,
            stage_diagnostics: Vec::new(),
            stage_types: Vec::new(),
            stages_unordered: false,
        }
    }

}

/// A private evaluator. Implementations own whatever scene index they need; they only read the data.
pub trait Evaluator: Send {
    /// The checker type (`bddl_terminal`, `private_button_press`, …).
    fn checker(&self) -> &str;
    /// Whether the episode must call [`Evaluator::observe_substep`] after every physics substep.
    fn samples_substeps(&self) -> bool {
        false
    }
    /// Captures baselines on the settled start state; clears all history.
    fn reset(&mut self, data: &SimData, tick: Tick);
    fn observe_control_step(&mut self, data: &SimData, tick: Tick);
    fn observe_substep(&mut self, _data: &SimData, _tick: Tick) {}
    /// Judges the final state (terminal checks) together with the history observed so far.
    fn finish(&mut self, data: &SimData, tick: Tick) -> EvaluationRecord;
    /// Visible feedback the original evaluators gave by editing `geom_rgba` (a pressed button's cap turns green, a
    /// wiped spill marker vanishes): `(geom id, rgba)` to draw instead of the model's colour. The model is shared
    /// read-only, so the episode applies these to each rendered frame.
    fn geom_rgba_overrides(&self) -> Vec<(usize, [f32; 4])> {
        Vec::new()
    }
    /// Private events recorded since the reset (every stage completion and regression included, as it happens), in
    /// time order, for the operator's live dashboard (never the agent). Called after every control step of an
    /// episode with a live view; an event once listed stays listed, in place (the live view sends only the new
    /// tail). Required of every evaluator: a default would leave a kind's live view silently empty.
    fn private_events(&self) -> Vec<PrivateEvent>;
    /// Live `(completed, K)` for the operator's dashboard: the required stages [`Evaluator::finish`] would count
    /// completed on the current state (so the last value before finish is the record's). Required, as above.
    fn stage_progress(&self) -> (usize, usize);
}

pub use crate::judge::commitment::{Commitment, CommitmentKind, CommitmentTracker};

/// Judgment for a perception task whose target is the instance `target`: the first commitment exists and is that
/// instance (no commitment at all is not a correct judgment).
pub fn judged_target(first: Option<&Commitment>, target: &str) -> bool {
    first.is_some_and(|c| c.subject == target)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tick(step: u64) -> Tick {
        Tick::at_control_step(step, step as f64 * 0.05)
    }

    fn tracker() -> StageTracker {
        StageTracker::new(vec![
            StageSpec::required("01_a"),
            StageSpec::required("02_b"),
            StageSpec { name: "03_optional".into(), required: false },
        ])
    }

    #[test]
    fn stages_complete_in_order_at_most_one_per_tick_and_stay_latched() {
        let mut t = tracker();
        // every condition holds: still only stage 0 completes at the first tick
        assert_eq!(t.advance(tick(1), |_| true), Some(0));
        assert_eq!(t.advance(tick(2), |i| i == 0), None, "stage 1 does not hold; completed stage 0 is not re-tested");
        assert_eq!(t.advance(tick(3), |i| i == 1), Some(1));
        assert_eq!(t.completed_required_count(), 2);
        assert!(t.all_required_completed(), "the optional stage does not count toward K");
        let mut r = EvaluationRecord::new("x");
        t.write_into(&mut r);
        assert_eq!((r.required_stage_count, r.completed_required_stage_count, r.stage_score_percent), (2, 2, 100.0));
        assert_eq!(r.ordered_stage_names, ["01_a", "02_b"]);
        assert_eq!(r.optional_stage_names, ["03_optional"]);
        assert_eq!(r.stage_events.iter().map(|e| e.tick.control_step).collect::<Vec<_>>(), [1, 3]);
    }

    #[test]
    fn terminal_stages_complete_wherever_they_hold_in_any_order() {
        let mut t = tracker();
        // the second stage holds, the first does not: an ordered advance would complete nothing
        t.complete_where(tick(9), |i| i == 1);
        assert!(!t.is_completed(0) && t.is_completed(1));
        assert_eq!(t.completed_required_count(), 1);
    }

    #[test]
    fn regressions_are_counted_once_per_drop_and_never_uncomplete_a_stage() {
        let mut t = tracker();
        t.advance(tick(1), |_| true);
        t.track_regressions(tick(2), |_| false);
        t.track_regressions(tick(3), |_| false); // still down: not a new drop
        t.track_regressions(tick(4), |_| true);
        t.track_regressions(tick(5), |_| false);
        assert_eq!(t.completed_required_count(), 1);
        let mut r = EvaluationRecord::new("x");
        t.write_into(&mut r);
        assert_eq!(r.stage_regressions, [StageRegressions { stage_name: "01_a".into(), count: 2 }]);
        let kinds: Vec<_> = r.stage_events.iter().map(|e| (e.kind, e.tick.control_step)).collect();
        assert_eq!(kinds, [(EventKind::StageCompleted, 1), (EventKind::StageRegressed, 2), (EventKind::StageRegressed, 5)]);
    }

    #[test]
    fn strict_order_latches_a_violation_when_a_later_stage_holds_first() {
        let mut t = tracker();
        assert_eq!(t.advance_strict(tick(1), |i| i == 1), None);
        assert!(t.order_violated());
        assert_eq!(t.advance_strict(tick(2), |_| true), None, "no progress after a violation");
        assert_eq!(t.completed_required_count(), 0);
        assert_eq!(t.events()[0].kind, EventKind::OrderViolation);
        assert_eq!(t.order_violation_label().as_deref(), Some("02_b_before_01_a"));
        assert_eq!(t.events()[0].subject.as_deref(), Some("02_b_before_01_a"));
    }

    #[test]
    fn staged_failure_reason_blames_a_missing_stage_before_the_final_state() {
        assert_eq!(FailureReason::of_staged(true, true), None);
        assert_eq!(FailureReason::of_staged(false, false), Some(FailureReason::IncompleteStage));
        assert_eq!(FailureReason::of_staged(false, true), Some(FailureReason::TerminalStateInvalid));
    }

    #[test]
    fn score_percent_is_completed_over_k() {
        assert_eq!(score_percent(3, 8), 37.5);
        assert_eq!(score_percent(0, 0), 0.0);
    }
}
