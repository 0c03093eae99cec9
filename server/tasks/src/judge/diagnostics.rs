//! Per-stage diagnostics the paper annotates by hand (paper_results: stage reached / succeeded, failure mode; for
//! opening operations the sustained-contact ratio), computed from any evaluator's record so every staged task gets
//! them without evaluator-specific code.
//!
//! * **reached** — the agent could work on the stage: in ordered evaluators every earlier required stage completed
//!   (the stage became current); in the unordered cooking evaluator every goal is available from the start.
//! * **succeeded** — the stage latched as completed (unordered: the goal holds on the final state).
//! * **regressed_during_later_stage** — a completed stage whose condition stopped holding while a later stage was
//!   being worked on: the paper's cross-stage interference (an action in one stage undoing another's state).
//! * **failure_reason** — on the first reached stage that did not succeed, why the episode failed.
//! * **type** — the stage type the catalog declares (Object Manipulation / Mechanism Interaction), for Table 4.
//! * **operation** — for a stage with a monitored mechanism operation, which way it moves the mechanism, with the
//!   operation's sustained-contact ratio (see [`crate::judge::mechanism`]).
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
    let operations = record.details.as_ref().and_then(|d| d["opening_operations"].as_array());
    let failure =
        record.failure_reason.and_then(|r| serde_json::to_value(r).ok()).and_then(|v| v.as_str().map(str::to_owned));
    let mut out: Vec<StageDiagnostic> = Vec::with_capacity(names.len());
    let mut failure_given = false;
    for (i, &(name, required)) in names.iter().enumerate() {
        let done = succeeded(name);
        // Ordered: stage i is current once stage i−1 completed; optional stages follow the last required one.
        let reached = unordered || i == 0 || succeeded(names[i - 1].0);
        let regressions = record.stage_regressions.iter().find(|r| &r.stage_name == name).map_or(0, |r| r.count);
        // Once a stage completes the next one is current, so a regression of any but the last stage happens while
        // later work is under way.
        let regressed_during_later_stage = !unordered && regressions > 0 && i + 1 < names.len();
        let op = operations.and_then(|ops| ops.iter().rev().find(|o| o["stage_name"].as_str() == Some(name.as_str())));
        let failure_reason = if reached && !done && required && !failure_given {
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
            sustained_contact_ratio_percent: op.and_then(|o| o["sustained_contact_ratio_percent"].as_f64()),
            contact_exec_steps: op.and_then(|o| o["exec_steps"].as_u64()),
            operation: op.and_then(|o| operation_kind(&o["operation"])),
            stage_type: record.stage_types.iter().find(|(n, _)| n == name).map(|&(_, t)| t),
            failure_reason,
        });
    }
    out
}

fn operation_kind(v: &Value) -> Option<OperationKind> {
    match v.as_str()? {
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
    fn the_failure_reason_lands_on_the_first_reached_stage_that_failed() {
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
    fn records_without_stages_have_no_diagnostics() {
        assert!(stage_diagnostics(&EvaluationRecord::new("bddl_terminal")).is_empty());
    }
}
