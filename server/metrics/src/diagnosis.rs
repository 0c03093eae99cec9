//! Table 4, the stage-level diagnosis of the long-horizon tasks, computed from the evaluators' private stage
//! records instead of the paper's manual annotation of rollouts:
//!
//! * a *stage opportunity* is one required stage of one valid rollout;
//! * **reached** — the agent could work on the stage (ordered stages: every earlier one completed; unordered
//!   goals: always); **success** — the stage completed (unordered goals: held at the end);
//! * **execution success** per stage type (Object Manipulation / Mechanism Interaction, declared per stage in the
//!   task catalog) — successes over reached opportunities of that type;
//! * **failure modes** — a *failure* is a reached stage that did not succeed, or a completed stage that a later
//!   stage undid. It is *cross-stage interference* when a completed stage later regressed, or when the stage was
//!   blocked by a state another stage created (the evaluator latched an order violation: a later stage's state
//!   made before its turn); every other failure is *local execution*.
use serde::{Deserialize, Serialize};

use crate::Proportion;

/// What a stage asks of the agent (declared per stage in `tasks/manifest.json` and `tasks/pool.json`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StageType {
    /// Grasp, move, place, pour, insert, wipe an object.
    ObjectManipulation,
    /// Operate an articulated or actuated mechanism: drawers, doors, latches, knobs, buttons, a seesaw.
    MechanismInteraction,
}

impl StageType {
    pub const ALL: [StageType; 2] = [StageType::ObjectManipulation, StageType::MechanismInteraction];

    /// The paper's name.
    pub fn label(self) -> &'static str {
        match self {
            StageType::ObjectManipulation => "Object Manipulation",
            StageType::MechanismInteraction => "Mechanism Interaction",
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            StageType::ObjectManipulation => "object_manipulation",
            StageType::MechanismInteraction => "mechanism_interaction",
        }
    }
}

/// Why a stage failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FailureMode {
    LocalExecution,
    CrossStageInterference,
}

/// One required stage of one valid rollout, as its evaluator recorded it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageOpportunity {
    pub task_number: u32,
    pub stage_name: String,
    /// `None` when neither the record nor the catalog declares it (counted, but in no per-type row).
    pub stage_type: Option<StageType>,
    pub reached: bool,
    pub succeeded: bool,
    /// Times a completed stage stopped holding.
    pub regressions: u32,
    /// A completed stage stopped holding while a later stage was worked on.
    pub regressed_during_later_stage: bool,
    /// The stage could not complete because another stage's state was made before its turn (order violation).
    pub blocked_by_other_stage: bool,
}

impl StageOpportunity {
    /// The failure this opportunity counts as, if any (see the module documentation).
    pub fn failure(&self) -> Option<FailureMode> {
        if self.reached && !self.succeeded {
            // An unordered goal that is not held at the end but completed before was undone by other work.
            let interfered = self.regressions > 0 || self.blocked_by_other_stage;
            Some(if interfered { FailureMode::CrossStageInterference } else { FailureMode::LocalExecution })
        } else if self.succeeded && self.regressed_during_later_stage {
            Some(FailureMode::CrossStageInterference)
        } else {
            None
        }
    }
}

/// Execution success of one stage type.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TypeExecution {
    pub stage_type: StageType,
    pub opportunities: usize,
    pub reached: usize,
    /// Successes over reached opportunities of this type, with its Wilson interval.
    pub execution_success: Proportion,
}

/// Table 4 for one agent under one condition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageDiagnosis {
    pub rollouts: usize,
    pub opportunities: usize,
    /// Reached opportunities over all opportunities.
    pub reached: Proportion,
    /// Successful opportunities over all opportunities.
    pub success: Proportion,
    pub by_type: Vec<TypeExecution>,
    /// Opportunities whose stage type is declared nowhere.
    pub untyped_opportunities: usize,
    pub failures: usize,
    pub local_execution: usize,
    pub cross_stage_interference: usize,
    /// Cross-stage interference over all failures.
    pub interference_share: Option<f64>,
}

/// Table 4 over the stage opportunities of `rollouts` valid rollouts.
pub fn diagnose(opportunities: &[StageOpportunity], rollouts: usize) -> StageDiagnosis {
    let count = |f: &dyn Fn(&StageOpportunity) -> bool| opportunities.iter().filter(|o| f(o)).count() as u64;
    let n = opportunities.len() as u64;
    let by_type = StageType::ALL
        .into_iter()
        .filter_map(|t| {
            let of_type: Vec<&StageOpportunity> = opportunities.iter().filter(|o| o.stage_type == Some(t)).collect();
            let reached = of_type.iter().filter(|o| o.reached).count();
            let succeeded = of_type.iter().filter(|o| o.reached && o.succeeded).count();
            (!of_type.is_empty()).then(|| TypeExecution {
                stage_type: t,
                opportunities: of_type.len(),
                reached,
                execution_success: Proportion::new(succeeded as u64, reached as u64),
            })
        })
        .collect();
    let failures: Vec<FailureMode> = opportunities.iter().filter_map(StageOpportunity::failure).collect();
    let interference = failures.iter().filter(|&&f| f == FailureMode::CrossStageInterference).count();
    StageDiagnosis {
        rollouts,
        opportunities: opportunities.len(),
        reached: Proportion::new(count(&|o| o.reached), n),
        success: Proportion::new(count(&|o| o.succeeded), n),
        by_type,
        untyped_opportunities: opportunities.iter().filter(|o| o.stage_type.is_none()).count(),
        failures: failures.len(),
        local_execution: failures.len() - interference,
        cross_stage_interference: interference,
        interference_share: (!failures.is_empty()).then(|| interference as f64 / failures.len() as f64),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn op(t: StageType, reached: bool, succeeded: bool) -> StageOpportunity {
        StageOpportunity {
            task_number: 27,
            stage_name: "s".into(),
            stage_type: Some(t),
            reached,
            succeeded,
            regressions: 0,
            regressed_during_later_stage: false,
            blocked_by_other_stage: false,
        }
    }

    #[test]
    fn execution_success_divides_by_reached_and_failures_split_by_cause() {
        use StageType::*;
        let mut regressed = op(ObjectManipulation, true, true);
        regressed.regressions = 1;
        regressed.regressed_during_later_stage = true;
        let mut blocked = op(ObjectManipulation, true, false);
        blocked.blocked_by_other_stage = true;
        let ops = [
            op(MechanismInteraction, true, true),
            op(MechanismInteraction, true, false), // local
            op(MechanismInteraction, false, false), // not reached: no failure
            regressed,                              // success, and interference
            blocked,                                // interference
        ];
        let d = diagnose(&ops, 2);
        assert_eq!((d.opportunities, d.reached.successes, d.success.successes), (5, 4, 2));
        let mech = d.by_type.iter().find(|t| t.stage_type == MechanismInteraction).unwrap();
        assert_eq!((mech.opportunities, mech.reached, mech.execution_success.successes, mech.execution_success.trials), (3, 2, 1, 2));
        let obj = d.by_type.iter().find(|t| t.stage_type == ObjectManipulation).unwrap();
        assert_eq!((obj.execution_success.successes, obj.execution_success.trials), (1, 2));
        assert_eq!((d.failures, d.local_execution, d.cross_stage_interference), (3, 1, 2));
        assert_eq!(d.interference_share, Some(2.0 / 3.0));
    }

    #[test]
    fn an_unordered_goal_lost_after_completing_is_interference() {
        let mut lost = op(StageType::MechanismInteraction, true, false);
        lost.regressions = 2;
        assert_eq!(lost.failure(), Some(FailureMode::CrossStageInterference));
        assert_eq!(op(StageType::MechanismInteraction, true, false).failure(), Some(FailureMode::LocalExecution));
    }
}
