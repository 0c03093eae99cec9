//! Per-stage diagnostics the paper annotates by hand (paper_results: stage reached / succeeded, failure mode; for
//! opening operations the sustained-contact ratio), computed from any evaluator's record so every staged task gets
//! them without evaluator-specific code.
//!
//! * **reached** — the record shows the agent got to the stage ([`libero_metrics::StageEvidence::reached`], the
//!   rule Table 4 uses): its goal held at some point; or, for an ordered stage after the first, the stage before it
//!   completed; or the gripper touched the stage's mechanism during its operation (a contact run); or a strict-order
//!   violation or a forbidden contact latched while it was current. Never merely because it comes first or because
//!   the unordered cooking goals are all available from the start.
//! * **succeeded** — the stage latched as completed (unordered: the goal holds on the final state).
//! * **regressed_during_later_stage** — a completed stage whose condition stopped holding while a later stage was
//!   being worked on: the paper's cross-stage interference (an action in one stage undoing another's state).
//! * **failure_reason** — on the first required stage that did not succeed, why the episode failed.
//! * **type** — the stage type the catalog declares (Object Manipulation / Mechanism Interaction), for Table 4.
//! * **operation** — for a stage with a monitored mechanism operation, which way it moves the mechanism, with the
//!   operation's sustained-contact ratio (see [`crate::judge::mechanism`]).
use libero_metrics::StageEvidence;
use serde::Deserialize;
use serde_json::Value;

pub use crate::judge::evaluator::StageDiagnostic;
use crate::judge::evaluator::{EvaluationRecord, EventKind};
use crate::judge::mechanism::OperationKind;

impl EvaluationRecord {
    /// The record with its per-stage diagnostics filled in (see [`stage_diagnostics`]).
    pub fn with_stage_diagnostics(mut self) -> Self {
        self.stage_diagnostics = stage_diagnostics(&self);
        self
    }
}

/// The part of an evaluator's `details` the diagnostics read: its monitored mechanism operations.
#[derive(Deserialize)]
struct MonitoredDetails {
    #[serde(default)]
    opening_operations: Option<Vec<MonitoredOperation>>,
}

/// One entry of `details.opening_operations`, as [`crate::judge::mechanism`] writes it (fields of another type
/// read as absent, as before it was typed).
#[derive(Deserialize)]
struct MonitoredOperation {
    #[serde(default, deserialize_with = "lenient")]
    stage_name: Option<String>,
    #[serde(default, deserialize_with = "lenient")]
    operation: Option<String>,
    #[serde(default, deserialize_with = "lenient")]
    exec_steps: Option<u64>,
    /// Only whether it holds any run matters here.
    #[serde(default, deserialize_with = "lenient")]
    contact_runs: Option<Vec<Value>>,
    #[serde(default, deserialize_with = "lenient")]
    sustained_steps: Option<u64>,
    #[serde(default, deserialize_with = "lenient")]
    sustained_contact_ratio_percent: Option<f64>,
}

/// A field of the type asked for, else none.
fn lenient<'de, D: serde::Deserializer<'de>, T: serde::de::DeserializeOwned>(d: D) -> Result<Option<T>, D::Error> {
    Ok(serde_json::from_value(Value::deserialize(d)?).ok())
}

/// The diagnostics of every stage (required ones first, then optional), empty for records without named stages.
pub fn stage_diagnostics(record: &EvaluationRecord) -> Vec<StageDiagnostic> {
    let names: Vec<(&String, bool)> = record
        .ordered_stage_names
        .iter()
        .map(|n| (n, true))
        .chain(record.optional_stage_names.iter().map(|n| (n, false)))
        .collect();
    let unordered = record.stages_unordered;
    let succeeded = |n: &str| record.completed_stage_names.iter().any(|c| c == n);
    let first_step = |n: &str, kind: EventKind| {
        record
            .stage_events
            .iter()
            .find(|e| e.kind == kind && e.stage_name.as_deref() == Some(n))
            .map(|e| e.tick.control_step)
    };
    let details = record.details.as_ref().and_then(|d| MonitoredDetails::deserialize(d).ok());
    let operations = details.as_ref().and_then(|d| d.opening_operations.as_deref());
    // The gripper touched the stage's mechanism during its operation: a contact run of its monitored operation.
    let touched = |n: &str| {
        operations.into_iter().flatten().filter(|o| o.stage_name.as_deref() == Some(n)).any(|o| {
            o.contact_runs.as_ref().is_some_and(|runs| !runs.is_empty()) || o.sustained_steps.is_some_and(|s| s > 0)
        })
    };
    // Ordered stages: the required stage current at a control step (the first not completed by then).
    let required: Vec<&String> = names.iter().filter(|(_, r)| *r).map(|(n, _)| *n).collect();
    let current_at = |step: u64| {
        (!unordered)
            .then(|| required.iter().find(|n| first_step(n, EventKind::StageCompleted).is_none_or(|c| c > step)))
            .flatten()
            .map(|n| n.as_str())
    };
    let all_events = || record.stage_events.iter().chain(&record.events);
    let violated_while_current =
        |n: &str| all_events().any(|e| e.kind == EventKind::OrderViolation && e.stage_name.as_deref() == Some(n));
    let forbidden_while_current = |n: &str| {
        all_events().any(|e| e.kind == EventKind::ForbiddenContact && current_at(e.tick.control_step) == Some(n))
    };
    let failure =
        record.failure_reason.and_then(|r| serde_json::to_value(r).ok()).and_then(|v| v.as_str().map(str::to_owned));
    let mut out: Vec<StageDiagnostic> = Vec::with_capacity(names.len());
    let mut failure_given = false;
    for (i, &(name, required)) in names.iter().enumerate() {
        let done = succeeded(name);
        let regressions = record.stage_regressions.iter().find(|r| &r.stage_name == name).map_or(0, |r| r.count);
        // Once a stage completes the next one is current, so a regression of any but the last stage happens while
        // later work is under way.
        let regressed_during_later_stage = !unordered && regressions > 0 && i + 1 < names.len();
        let blocked = violated_while_current(name);
        let evidence = StageEvidence {
            succeeded: done,
            completed_at_some_point: done || first_step(name, EventKind::StageCompleted).is_some(),
            // Ordered: stage i is current once stage i−1 completed; optional stages follow the last required one.
            preconditions_established: !unordered && i > 0 && succeeded(names[i - 1].0),
            touched_mechanism: touched(name),
            acted_while_current: blocked || forbidden_while_current(name),
            regressions,
            regressed_during_later_stage,
            blocked_by_other_stage: blocked,
        };
        let reached = evidence.reached();
        let op = operations.and_then(|ops| ops.iter().rev().find(|o| o.stage_name.as_deref() == Some(name.as_str())));
        let failure_reason = if !done && required && !failure_given {
            failure_given = true;
            failure.clone()
        } else {
            None
        };
        out.push(StageDiagnostic {
            stage_name: name.clone(),
            required,
            reached,
            succeeded: done,
            completed_control_step: first_step(name, EventKind::StageCompleted),
            regressions,
            regressed_during_later_stage,
            sustained_contact_ratio_percent: op.and_then(|o| o.sustained_contact_ratio_percent),
            contact_exec_steps: op.and_then(|o| o.exec_steps),
            operation: op.and_then(|o| operation_kind(o.operation.as_deref()?)),
            stage_type: record.stage_types.iter().find(|(n, _)| n == name).map(|&(_, t)| t),
            failure_reason,
        });
    }
    out
}

fn operation_kind(v: &str) -> Option<OperationKind> {
    match v {
        "open" => Some(OperationKind::Open),
        "close" => Some(OperationKind::Close),
        "operate" => Some(OperationKind::Operate),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;
    use crate::judge::evaluator::FailureReason;
    use crate::judge::stage_types::StageType;
    use crate::judge::evaluator::{PrivateEvent, StageRegressions, Tick};

    fn event(kind: EventKind, step: u64, name: &str) -> PrivateEvent {
        PrivateEvent { stage_name: Some(name.into()), ..PrivateEvent::new(kind, Tick::at_control_step(step, 0.0)) }
    }

    fn ordered_record() -> EvaluationRecord {
        let mut r = EvaluationRecord::new("private_ordered_stages");
        r.ordered_stage_names = vec!["01_Open".into(), "02_Place".into(), "03_Close".into()];
        r.optional_stage_names = vec!["04_Extra".into()];
        r.completed_stage_names = vec!["01_Open".into(), "02_Place".into()];
        r.stage_events = vec![
            event(EventKind::StageCompleted, 40, "01_Open"),
            event(EventKind::StageCompleted, 90, "02_Place"),
            event(EventKind::StageRegressed, 120, "01_Open"),
        ];
        r.stage_regressions = vec![StageRegressions { stage_name: "01_Open".into(), count: 1 }];
        r.failure_reason = Some(FailureReason::IncompleteStage);
        r.details = Some(json!({"opening_operations": [
            {"stage_name": "01_Open", "operation": "open", "exec_steps": 40, "sustained_contact_ratio_percent": 62.5}
        ]}));
        r.stage_types = vec![("01_Open".into(), StageType::MechanismInteraction), ("02_Place".into(), StageType::ObjectManipulation)];
        r
    }

    #[test]
    fn each_stage_carries_the_type_the_catalog_declares() {
        let d = stage_diagnostics(&ordered_record());
        let types: Vec<Option<StageType>> = d.iter().map(|s| s.stage_type).collect();
        assert_eq!(types, [Some(StageType::MechanismInteraction), Some(StageType::ObjectManipulation), None, None]);
        assert_eq!(serde_json::to_value(&d[0]).unwrap()["type"], "mechanism_interaction");
        assert!(serde_json::to_value(&d[2]).unwrap().get("type").is_none());
        assert_eq!((d[0].operation, d[1].operation), (Some(OperationKind::Open), None));
    }

    #[test]
    fn ordered_stages_are_reached_only_after_the_previous_one_completed() {
        let d = stage_diagnostics(&ordered_record());
        let reached: Vec<bool> = d.iter().map(|s| s.reached).collect();
        let succeeded: Vec<bool> = d.iter().map(|s| s.succeeded).collect();
        assert_eq!(reached, [true, true, true, false]);
        assert_eq!(succeeded, [true, true, false, false]);
        assert_eq!(d[1].completed_control_step, Some(90));
        assert!(!d[3].required);
    }

    #[test]
    fn the_failure_reason_lands_on_the_first_required_stage_that_failed() {
        let d = stage_diagnostics(&ordered_record());
        let reasons: Vec<Option<&str>> = d.iter().map(|s| s.failure_reason.as_deref()).collect();
        assert_eq!(reasons, [None, None, Some("incomplete_stage"), None]);
    }

    #[test]
    fn a_regression_while_a_later_stage_runs_is_cross_stage_interference() {
        let d = stage_diagnostics(&ordered_record());
        assert_eq!(d[0].regressions, 1);
        assert!(d[0].regressed_during_later_stage);
        assert!(!d[1].regressed_during_later_stage);
    }

    #[test]
    fn the_sustained_contact_ratio_comes_from_the_stage_s_opening_operation() {
        let d = stage_diagnostics(&ordered_record());
        assert_eq!(d[0].sustained_contact_ratio_percent, Some(62.5));
        assert_eq!(d[0].contact_exec_steps, Some(40));
        assert_eq!(d[1].sustained_contact_ratio_percent, None);
    }

    #[test]
    fn unordered_goals_are_all_reached_and_succeed_when_they_hold_at_the_end() {
        let mut r = EvaluationRecord::new("private_unordered_goal_predicates");
        r.stages_unordered = true;
        r.ordered_stage_names = vec!["G1".into(), "G2".into()];
        r.completed_stage_names = vec!["G2".into()];
        r.stage_events = vec![event(EventKind::StageCompleted, 5, "G1"), event(EventKind::StageRegressed, 9, "G1")];
        r.stage_regressions = vec![StageRegressions { stage_name: "G1".into(), count: 1 }];
        let d = stage_diagnostics(&r);
        assert!(d.iter().all(|s| s.reached));
        assert_eq!(d.iter().map(|s| s.succeeded).collect::<Vec<_>>(), [false, true]);
        assert_eq!(d[0].regressions, 1);
        assert!(!d[0].regressed_during_later_stage);
    }

    #[test]
    fn a_task_never_touched_has_no_reached_stage() {
        // T28 as an agent that never acted: nothing completed, the unlatch operation without a contact run.
        let mut r = EvaluationRecord::new("private_ordered_stages");
        r.ordered_stage_names = vec!["01_Unlatch_Door".into(), "02_Open_Door".into()];
        r.failure_reason = Some(FailureReason::IncompleteStage);
        r.details = Some(json!({"opening_operations": [
            {"stage_name": "01_Unlatch_Door", "operation": "open", "exec_steps": 300, "contact_runs": [], "sustained_steps": 0,
             "sustained_contact_ratio_percent": 0.0}
        ]}));
        let d = stage_diagnostics(&r);
        assert_eq!(d.iter().map(|s| s.reached).collect::<Vec<_>>(), [false, false]);
        assert_eq!(d[0].failure_reason.as_deref(), Some("incomplete_stage"), "the reason still lands on the stage due");
        // A touch of the latch handle reaches the first stage (and no further).
        r.details = Some(json!({"opening_operations": [
            {"stage_name": "01_Unlatch_Door", "operation": "open", "exec_steps": 300, "contact_runs": [3, 12], "sustained_steps": 12}
        ]}));
        assert_eq!(stage_diagnostics(&r).iter().map(|s| s.reached).collect::<Vec<_>>(), [true, false]);
        // Unordered goals nobody touched are not reached either.
        let mut u = EvaluationRecord::new("private_unordered_goal_predicates");
        u.stages_unordered = true;
        u.ordered_stage_names = vec!["G1".into(), "G2".into()];
        assert!(stage_diagnostics(&u).iter().all(|s| !s.reached));
    }

    #[test]
    fn an_order_violation_or_a_forbidden_contact_reaches_the_stage_then_current() {
        let mut r = EvaluationRecord::new("private_ordered_buffer_rotation_and_tabletop_avoidance");
        r.ordered_stage_names = vec!["01_a".into(), "02_b".into(), "03_c".into()];
        r.completed_stage_names = vec!["01_a".into()];
        r.stage_events = vec![
            event(EventKind::StageCompleted, 10, "01_a"),
            PrivateEvent { subject: Some("03_c_before_02_b".into()), ..event(EventKind::OrderViolation, 20, "02_b") },
        ];
        let d = stage_diagnostics(&r);
        assert_eq!(d.iter().map(|s| s.reached).collect::<Vec<_>>(), [true, true, false]);
        // A bowl dropped on the table at step 5, while the first stage was current.
        let mut f = EvaluationRecord::new("private_ordered_buffer_rotation_and_tabletop_avoidance");
        f.ordered_stage_names = vec!["01_a".into(), "02_b".into()];
        f.events = vec![PrivateEvent { subject: Some("bowl_touched_table".into()), ..PrivateEvent::new(EventKind::ForbiddenContact, Tick::at_control_step(5, 0.25)) }];
        assert_eq!(stage_diagnostics(&f).iter().map(|s| s.reached).collect::<Vec<_>>(), [true, false]);
    }

    #[test]
    fn records_without_stages_have_no_diagnostics() {
        assert!(stage_diagnostics(&EvaluationRecord::new("bddl_terminal")).is_empty());
    }
}
