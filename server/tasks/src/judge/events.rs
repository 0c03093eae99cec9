//! The vocabulary of private events: when something was observed ([`Tick`]) and what ([`EventKind`],
//! [`PrivateEvent`]). The lowest module of `judge/`: the evaluator contract, the first-commitment tracker and the
//! stage diagnostics all speak it, and it imports none of them.
use serde::Serialize;

/// When something was observed. `control_step` counts control steps since the evaluator reset (0 = the reset
/// state); `substep` is 1…25 inside the control step for substep samples, `None` for control-rate samples.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Tick {
    pub control_step: u64,
    pub substep: Option<u32>,
    pub sim_time_s: f64,
}

impl Tick {
    pub fn at_control_step(control_step: u64, sim_time_s: f64) -> Self {
        Self { control_step, substep: None, sim_time_s }
    }
}

/// What a private event records.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EventKind {
    /// A stage latched as completed.
    StageCompleted,
    /// A completed stage's condition stopped holding (the stage stays completed).
    StageRegressed,
    /// A later stage held before the current one (strict-order evaluators; latches failure; `subject` names it
    /// `<later>_before_<current>`).
    OrderViolation,
    /// A forbidden contact was seen (T25: a bowl touched the tabletop; latches failure; `subject` names it
    /// `<object>_touched_<label>`).
    ForbiddenContact,
    /// The first commitment of the episode (see [`crate::judge::commitment::CommitmentTracker`]).
    FirstCommitment,
    /// Diagnostic: the BDDL goal conjunction became true / false at this tick (never scored).
    GoalSatisfied,
    GoalUnsatisfied,
    /// A spill marker was wiped (T19; `subject` = the marker geom).
    SpillMarkerCovered,
    /// The pour counter registered a pour (T20, T24; the pour began 2 control steps before this tick).
    PourDetected,
    /// A failure monitor latched a permanent failure (T24 `extra_pour`; `subject` = the monitor's name).
    FailureLatched,
}

/// A time-stamped private event (never shown to the agent).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PrivateEvent {
    pub kind: EventKind,
    #[serde(flatten)]
    pub tick: Tick,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stage_index: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stage_name: Option<String>,
    /// The object or fixture concerned, where there is one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub subject: Option<String>,
}

impl PrivateEvent {
    pub fn new(kind: EventKind, tick: Tick) -> Self {
        Self { kind, tick, stage_index: None, stage_name: None, subject: None }
    }
}
