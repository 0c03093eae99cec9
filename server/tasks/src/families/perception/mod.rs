//! perception_v2 (T01–T10), the pool's `vlabench_button` questions (tasks 0–6) and its `vlabench_world_knowledge`
//! selections: the weighing evaluator (T08) and the perception experts; the bin tasks are judged by the BDDL goal
//! with a judgment target, the buttons by the button press.
pub mod weighing;
mod expert;

use crate::TasksError;
use crate::expert::{Expert, SceneRefs};

/// The tasks this family scripts, with their near-miss behaviours.
pub fn behaviours(task_id: &str) -> Option<&'static [&'static str]> {
    expert::behaviours(task_id)
}

/// This family's expert for `task_id` (one of [`behaviours`]).
pub fn build_expert(task_id: &str, behaviour: &str, refs: &SceneRefs) -> Result<Box<dyn Expert>, TasksError> {
    expert::build(task_id, behaviour, refs)
}

/// T08: the phase at whose end a weighed mug has hung still in the hand (tests read the wrist force there).
pub fn weigh_hold_phase() -> &'static str {
    expert::WEIGH_HOLD_PHASE
}
