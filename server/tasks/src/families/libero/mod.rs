//! Stock LIBERO tasks (libero_spatial, _object, _goal, _10, _90), judged on their BDDL goal: the goal evaluator, the
//! experts of the release tasks on stock scenes (T11, T12, T14–T17) and the generic expert of the 130 stock tasks
//! (`suite/NAME`, planned from the goal).
pub mod bddl_terminal;
mod expert;
mod objects;
pub mod stock;

use crate::expert::ExpertEntry;
use crate::judge::kind::EvaluatorKind;

/// This family's per-task experts (the stock suites' generic one is [`stock::SUITE_EXPERT`]).
pub fn experts() -> impl Iterator<Item = ExpertEntry> {
    expert::EXPERTS.iter().copied()
}

/// The checker kinds this family judges.
pub const EVALUATORS: &[EvaluatorKind] = &[bddl_terminal::EVALUATOR, bddl_terminal::OPEN_EVALUATOR];
