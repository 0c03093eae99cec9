//! perception_v2 (T01–T10), the pool's `vlabench_button` questions (tasks 0–6) and its `vlabench_world_knowledge`
//! selections: the weighing evaluator (T08) and the perception experts; the bin tasks are judged by the BDDL goal
//! with a judgment target, the buttons by the button press.
pub mod weighing;
mod expert;

use crate::expert::ExpertEntry;
use crate::judge::kind::EvaluatorKind;

/// This family's experts, a row per task.
pub fn experts() -> impl Iterator<Item = ExpertEntry> {
    expert::experts()
}

/// The checker kinds this family judges.
pub const EVALUATORS: &[EvaluatorKind] = &[weighing::EVALUATOR];

/// T08: the phase at whose end a weighed mug has hung still in the hand (tests read the wrist force there).
pub fn weigh_hold_phase() -> &'static str {
    expert::WEIGH_HOLD_PHASE
}
