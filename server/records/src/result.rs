//! `result.json` (protocol §4.9, §6.4) and the evaluator's `private_evaluation` inside it, typed for their readers
//! (see [`crate::typed`] for how fields they do not name survive).
use serde_json::Value;

use crate::typed::record;

pub const RESULT_SCHEMA: &str = "libero.agent_run_result.v1";
/// `status` of an episode that ended by `finish_episode`, the wall-time expiry or a forfeit.
pub const STATUS_FINISHED: &str = "finished";
/// `status` of an episode that ended any other way (§4.7).
pub const STATUS_ABORTED: &str = "aborted";
/// `termination_reason` of the wall-time expiry (§4.6), which §4.8 classifies SIM_TIMEOUT.
pub const WALL_TIME_EXHAUSTED: &str = "episode_wall_time_budget_exhausted";
/// `termination_reason` of an episode whose last allowed `osc_sequence` spent the agent-step budget (the paper's
/// §3.1: an episode ends when the agent finishes or exhausts the interaction or time budget); judged as the wall
/// time's end is: SIM_TIMEOUT.
pub const STEP_BUDGET_EXHAUSTED: &str = "agent_step_budget_exhausted";
/// `wall_time_budget_scope` of every result: one budget for the episode, whatever its resets.
pub const WALL_TIME_BUDGET_SCOPE: &str = "per_episode_across_resets";

record! {
    /// An episode's `result.json`: the `finish_episode` payload (§2.9) with `schema_version`, `finished_at` and the
    /// evaluator's record; or the aborted result of §4.7.
    pub struct RunResult {
        pub schema_version: Option<String>,
        /// `finished` or `aborted` (the original's launcher also wrote `infrastructure_error`).
        pub status: Option<String>,
        /// The tool payload's `ok`, kept in finished results.
        pub ok: Option<bool>,
        /// The evaluator's verdict (§4.5); absent from an aborted result.
        pub success: Option<bool>,
        /// Why a finished episode ended other than by `finish_episode` (expiry, forfeit).
        pub termination_reason: Option<String>,
        /// Why an aborted episode ended.
        pub reason: Option<String>,
        /// The launcher's infrastructure error (§6.4): a string, or null.
        pub infrastructure_error: Option<Option<String>>,
        pub finished_at: Option<String>,
        /// From `start_episode` to the end; null in an aborted result of an episode that never started.
        pub wall_time_seconds: Option<Option<f64>>,
        pub max_wall_time_seconds: Option<f64>,
        pub wall_time_budget_scope: Option<String>,
        pub accepted_agent_steps: Option<u64>,
        pub accepted_agent_steps_current_attempt: Option<u64>,
        pub attempt_index: Option<u64>,
        pub reset_count: Option<u64>,
        pub remaining_resets: Option<u64>,
        pub private_evaluation: Option<PrivateEvaluation>,
    }
}

impl RunResult {
    /// The aborted result of §4.7 (`wall_time_seconds` null for an episode that never started).
    pub fn aborted(reason: &str, max_wall_time_s: f64, wall_time_s: Option<f64>, finished_at: String) -> Self {
        Self {
            schema_version: Some(RESULT_SCHEMA.to_owned()),
            status: Some(STATUS_ABORTED.to_owned()),
            reason: Some(reason.to_owned()),
            finished_at: Some(finished_at),
            max_wall_time_seconds: Some(max_wall_time_s),
            wall_time_budget_scope: Some(WALL_TIME_BUDGET_SCOPE.to_owned()),
            wall_time_seconds: Some(wall_time_s),
            ..Self::default()
        }
    }

    /// Sets `private_evaluation` to the evaluator's output as it gave it (typed when it is an object, as records
    /// are; any other value kept as it is).
    pub fn set_private_evaluation(&mut self, evaluation: Value) {
        self.rest.remove("private_evaluation");
        match PrivateEvaluation::from_value(evaluation.clone()) {
            Ok(e) => self.private_evaluation = Some(e),
            Err(_) => {
                self.private_evaluation = None;
                self.rest.insert("private_evaluation".to_owned(), evaluation);
            }
        }
    }

    pub fn is_finished(&self) -> bool {
        self.status.as_deref() == Some(STATUS_FINISHED)
    }

    /// The infrastructure error, when it is a string.
    pub fn infrastructure_error(&self) -> Option<&str> {
        self.infrastructure_error.as_ref().and_then(Option::as_deref)
    }

    /// Whether the result records an infrastructure error: any value but null counts (§4.8's `infra`), a string
    /// or not.
    pub fn has_infrastructure_error(&self) -> bool {
        self.infrastructure_error().is_some() || self.rest.get("infrastructure_error").is_some_and(|v| !v.is_null())
    }

    /// Episode wall time (from `start_episode`), where the result has it.
    pub fn wall_time_s(&self) -> Option<f64> {
        self.wall_time_seconds.flatten()
    }
}

record! {
    /// The evaluator's record (`result.json` → `private_evaluation`, §4.9), as `libero_tasks`' `EvaluationRecord`
    /// writes it.
    pub struct PrivateEvaluation {
        pub schema_version: Option<String>,
        /// Evaluator type, e.g. `bddl_terminal`.
        pub checker: Option<String>,
        pub task_id: Option<String>,
        pub success: Option<bool>,
        pub required_stage_count: Option<u64>,
        pub completed_required_stage_count: Option<u64>,
        pub stage_score_percent: Option<f64>,
        pub ordered_stage_names: Option<Vec<String>>,
        pub completed_stage_names: Option<Vec<String>>,
        pub optional_stage_names: Option<Vec<String>>,
        pub stage_regressions: Option<Vec<StageRegressions>>,
        pub terminal_state_success: Option<bool>,
        pub terminal_state_checks: Option<Vec<TerminalCheck>>,
        pub control_steps_observed: Option<u64>,
        pub substeps_observed: Option<u64>,
        /// The stage events (also in `private_stage_events.jsonl`).
        pub stage_events: Option<Vec<PrivateEvent>>,
        /// Other private events (commitment, diagnostic goal changes).
        pub events: Option<Vec<PrivateEvent>>,
        /// The agent's first commitment (perception tasks), null when it made none.
        pub first_commitment: Option<Value>,
        pub bddl_final_goal_success: Option<Option<bool>>,
        /// `extra_pour`, `incomplete_stage`, `terminal_state_invalid`, `order_violation`; null on success.
        pub failure_reason: Option<Option<String>>,
        /// Perception tasks: whether the first commitment was the private target.
        pub judgment_correct: Option<bool>,
        /// Evaluator-specific diagnostics.
        pub details: Option<EvaluationDetails>,
        pub stage_diagnostics: Option<Vec<StageDiagnostic>>,
    }
}

record! {
    /// One check of the final state.
    pub struct TerminalCheck {
        pub name: Option<String>,
        pub passed: Option<bool>,
    }
}

record! {
    /// How often one stage regressed.
    pub struct StageRegressions {
        pub stage_name: Option<String>,
        pub count: Option<u64>,
    }
}

record! {
    /// One private event (a stage completed, a commitment, …) at its control step.
    pub struct PrivateEvent {
        pub kind: Option<String>,
        pub control_step: Option<u64>,
        pub sim_time_s: Option<f64>,
        pub stage_index: Option<u64>,
        pub stage_name: Option<String>,
        pub subject: Option<String>,
    }
}

record! {
    /// One stage's diagnostics (`libero_tasks::judge::diagnostics` documents each field).
    pub struct StageDiagnostic {
        pub stage_name: Option<String>,
        /// The stage type the catalog declares (`libero_tasks`' `StageType`).
        pub stage_type as "type": Option<Value>,
        pub required: Option<bool>,
        pub reached: Option<bool>,
        pub succeeded: Option<bool>,
        pub completed_control_step: Option<Option<u64>>,
        pub regressions: Option<u64>,
        pub regressed_during_later_stage: Option<bool>,
        pub sustained_contact_ratio_percent: Option<Option<f64>>,
        pub contact_exec_steps: Option<Option<u64>>,
        pub operation: Option<String>,
        pub failure_reason: Option<Option<String>>,
    }
}

record! {
    /// The evaluator-specific part of the record, as far as the reports read it.
    pub struct EvaluationDetails {
        /// Monitored mechanism operations (Figure 3's sustained-contact ratio).
        pub opening_operations: Option<Vec<MechanismOperation>>,
        /// The stage order the checker enforced (`ordered`, `unordered`), where its parameters name one.
        pub order: Option<String>,
    }
}

record! {
    /// One monitored mechanism operation of `details.opening_operations`.
    pub struct MechanismOperation {
        pub stage_name: Option<String>,
        /// `open`, `close`, …; absent in records from before operations carried a direction.
        pub operation: Option<String>,
        pub exec_steps: Option<u64>,
        /// Runs of gripper contact with any part of the mechanism (control steps, in order).
        pub contact_runs: Option<Vec<u64>>,
        /// Runs of gripper contact with the mechanism's declared handle: the runs Figure 3's SCR counts. Absent in
        /// records from before handle contact was told apart.
        pub handle_contact_runs: Option<Vec<u64>>,
        pub sustained_steps: Option<u64>,
        pub sustained_contact_ratio_percent: Option<f64>,
        pub completed: Option<bool>,
    }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;
    use crate::json::pretty_sorted;

    /// A finished result as the episode writes it, with a launcher's fields this crate does not name.
    fn finished() -> Value {
        json!({
            "accepted_agent_steps": 3, "accepted_agent_steps_current_attempt": 3, "attempt_index": 1,
            "finished_at": "2026-01-01T00:00:00.000001+00:00", "max_wall_time_seconds": 1800.0, "ok": true,
            "private_evaluation": {
                "checker": "staged", "completed_required_stage_count": 1, "completed_stage_names": ["a"],
                "control_steps_observed": 40, "events": [{"control_step": 3, "kind": "stage_completed", "sim_time_s": 0.15, "substep": null}],
                "failure_reason": "incomplete_stage", "first_commitment": null, "bddl_final_goal_success": null,
                "required_stage_count": 2, "stage_score_percent": 50.0,
                "terminal_state_checks": [{"name": "drawer_closed", "passed": false}],
                "stage_diagnostics": [{"stage_name": "a", "type": "grasp", "required": true, "reached": true, "succeeded": true,
                    "completed_control_step": 3, "regressions": 0, "regressed_during_later_stage": false,
                    "sustained_contact_ratio_percent": null, "contact_exec_steps": null, "failure_reason": null}],
                "details": {"opening_operations": [{"stage_name": "a", "operation": "open", "exec_steps": 4,
                    "contact_runs": [4], "handle_contact_runs": [3], "sustained_steps": 0,
                    "sustained_contact_ratio_percent": 0.0, "completed": true, "window": "first_contact"}]},
                "new_evaluator_field": {"x": [1, 2.5]}
            },
            "remaining_resets": 0, "reset_count": 0, "schema_version": RESULT_SCHEMA, "status": "finished", "success": false,
            "wall_time_budget_scope": "per_episode_across_resets", "wall_time_seconds": 12.5,
            "codex_exit_code": null, "agent_harness": "codex", "session_archive_error": null
        })
    }

    #[test]
    fn a_result_round_trips_byte_identically_with_unknown_fields() {
        let v = finished();
        let text = pretty_sorted(&v);
        let r: RunResult = serde_json::from_str(&text).unwrap();
        assert_eq!(pretty_sorted(&r.to_value()), text);
        assert!(r.is_finished() && !r.has_infrastructure_error());
        assert_eq!((r.success, r.wall_time_s(), r.accepted_agent_steps), (Some(false), Some(12.5), Some(3)));
        let pe = r.private_evaluation.as_ref().unwrap();
        assert_eq!((pe.required_stage_count, pe.completed_required_stage_count, pe.stage_score_percent), (Some(2), Some(1), Some(50.0)));
        assert_eq!(pe.failure_reason, Some(Some("incomplete_stage".to_owned())));
        let check = &pe.terminal_state_checks.as_ref().unwrap()[0];
        assert_eq!((check.name.as_deref(), check.passed), (Some("drawer_closed"), Some(false)));
        let d = &pe.stage_diagnostics.as_ref().unwrap()[0];
        assert_eq!((d.stage_type.clone(), d.succeeded, d.sustained_contact_ratio_percent), (Some(json!("grasp")), Some(true), Some(None)));
        let op = &pe.details.as_ref().unwrap().opening_operations.as_ref().unwrap()[0];
        assert_eq!((op.operation.as_deref(), op.exec_steps, op.rest["window"].clone()), (Some("open"), Some(4), json!("first_contact")));
        assert_eq!((op.contact_runs.as_deref(), op.handle_contact_runs.as_deref()), (Some(&[4][..]), Some(&[3][..])));
        assert_eq!(r.rest["agent_harness"], "codex");
    }

    #[test]
    fn an_aborted_result_is_what_section_4_7_writes() {
        let at = "2026-01-01T00:00:00.000001+00:00".to_owned();
        let old = |wall: Option<f64>| {
            json!({
                "schema_version": RESULT_SCHEMA, "status": "aborted", "reason": "server_stopped_before_finish",
                "finished_at": at, "max_wall_time_seconds": 1800.0, "wall_time_budget_scope": "per_episode_across_resets",
                "wall_time_seconds": wall,
            })
        };
        for wall in [None, Some(12.25)] {
            let r = RunResult::aborted("server_stopped_before_finish", 1800.0, wall, at.clone());
            assert_eq!(pretty_sorted(&r.to_value()), pretty_sorted(&old(wall)), "the aborted result's bytes");
            let read: RunResult = serde_json::from_str(&pretty_sorted(&old(wall))).unwrap();
            assert_eq!(read, r);
            assert_eq!(read.wall_time_s(), wall);
        }
    }

    #[test]
    fn any_infrastructure_error_but_null_counts() {
        let r = |e: Value| RunResult::from_value(json!({"status": "finished", "infrastructure_error": e})).unwrap();
        assert!(!r(Value::Null).has_infrastructure_error());
        assert!(r(json!("boom")).has_infrastructure_error());
        assert_eq!(r(json!("boom")).infrastructure_error(), Some("boom"));
        assert!(r(json!({"code": 1})).has_infrastructure_error(), "a non-string error is still one");
        assert!(!RunResult::default().has_infrastructure_error());
    }
}
