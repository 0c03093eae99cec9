//! A long-horizon rollout's required stages as stage opportunities, read from its private record (`result.json` →
//! `private_evaluation`): the evidence Table 4, Figure 3 and the annotation page share. Stage types the record lacks
//! come from the task facts ([`TaskFacts`]).
use libero_metrics::{StageEvidence, StageOpportunity, StageType, TaskFacts};
use libero_records::records::{MechanismOperation, PrivateEvaluation, PrivateEvent, RunDir, StageDiagnostic, read_result};

use crate::batch::RolloutRecord;

/// The rollout's private evaluation (`<run_dir>/result.json` → `private_evaluation`), if it can be read here.
pub(crate) fn private_evaluation(r: &RolloutRecord) -> Option<PrivateEvaluation> {
    read_result(&RunDir::new(r.run_dir.as_deref()?))?.private_evaluation
}

/// The checker whose goals are all available at once (T21, T22): no stage comes first.
const UNORDERED_CHECKER: &str = "private_unordered_goal_predicates";

/// The gripper touched the mechanism of this operation (anywhere on it): a contact run (`contact_runs`), or sustained
/// steps or a positive SCR in records without the runs.
pub(crate) fn touched(o: &MechanismOperation) -> bool {
    let runs = o.contact_runs.as_ref().is_some_and(|r| !r.is_empty());
    runs || o.sustained_steps.is_some_and(|n| n > 0) || o.sustained_contact_ratio_percent.is_some_and(|p| p > 0.0)
}

/// The required stages of one long-horizon rollout's record as stage opportunities, each with the evidence its
/// record holds ([`StageEvidence`]: reached only on evidence of the agent, never because a stage comes first).
pub(crate) fn opportunities(r: &RolloutRecord, pe: &PrivateEvaluation, facts: &TaskFacts) -> Vec<StageOpportunity> {
    let declared = facts.stage_types.get(&r.task_number);
    let stages: Vec<&StageDiagnostic> = pe.stage_diagnostics.iter().flatten().filter(|d| d.required == Some(true)).collect();
    let name = |d: &StageDiagnostic| d.stage_name.clone().unwrap_or_default();
    let order = pe.details.as_ref().and_then(|d| d.order.as_deref());
    let unordered = pe.checker.as_deref() == Some(UNORDERED_CHECKER) || order == Some("unordered");
    let events: Vec<&PrivateEvent> = pe.stage_events.iter().flatten().chain(pe.events.iter().flatten()).collect();
    let of_kind = |kind: &'static str| events.iter().copied().filter(move |e| e.kind.as_deref() == Some(kind));
    // The control step a stage first completed at (its diagnostic's, else its first completion event).
    let completed_at = |d: &StageDiagnostic| {
        let n = name(d);
        d.completed_control_step.flatten().or_else(|| {
            of_kind("stage_completed").filter(|e| e.stage_name.as_deref() == Some(n.as_str())).filter_map(|e| e.control_step).min()
        })
    };
    let ever_completed = |d: &StageDiagnostic| d.succeeded == Some(true) || completed_at(d).is_some() || d.regressions.unwrap_or(0) > 0;
    // Ordered stages: the required stage current at a control step (the first not completed by then).
    let current_at = |step: u64| {
        (!unordered).then(|| stages.iter().find(|d| completed_at(d).is_none_or(|c| c > step))).flatten().map(|d| name(d))
    };
    let ops: &[MechanismOperation] = pe.details.as_ref().and_then(|d| d.opening_operations.as_deref()).unwrap_or_default();
    stages
        .iter()
        .enumerate()
        .map(|(i, d)| {
            let n = name(d);
            let recorded = d.stage_type.clone().and_then(|t| serde_json::from_value::<StageType>(t).ok());
            let from_catalog = || declared.and_then(|ts| ts.iter().find(|(s, _)| *s == n)).and_then(|(_, t)| *t);
            // A strict order latched by a later stage's state made early, while this stage was current: that state
            // blocked it (records from before the event named its stage carry the reason on the stage instead).
            let blocked = of_kind("order_violation").any(|e| e.stage_name.as_deref() == Some(n.as_str()))
                || d.failure_reason.as_ref().and_then(Option::as_deref) == Some("order_violation");
            let forbidden = of_kind("forbidden_contact").any(|e| e.control_step.and_then(current_at).as_deref() == Some(n.as_str()));
            StageOpportunity {
                episode_id: r.episode_id.clone(),
                task_number: r.task_number,
                stage_type: recorded.or_else(from_catalog),
                evidence: StageEvidence {
                    succeeded: d.succeeded == Some(true),
                    completed_at_some_point: ever_completed(d),
                    preconditions_established: !unordered && i > 0 && ever_completed(stages[i - 1]),
                    touched_mechanism: ops.iter().any(|o| o.stage_name.as_deref() == Some(n.as_str()) && touched(o)),
                    acted_while_current: blocked || forbidden,
                    regressions: d.regressions.map_or(0, |n| n as u32),
                    regressed_during_later_stage: d.regressed_during_later_stage == Some(true),
                    blocked_by_other_stage: blocked,
                },
                stage_name: n,
            }
        })
        .collect()
}

/// The required stages of one rollout with their evidence, read from its private record (empty without one).
pub fn rollout_opportunities(r: &RolloutRecord, facts: &TaskFacts) -> Vec<StageOpportunity> {
    private_evaluation(r).map(|pe| opportunities(r, &pe, facts)).unwrap_or_default()
}
