//! Stock LIBERO tasks (libero_spatial, _object, _goal, _10, _90), judged on their BDDL goal: the goal evaluator and
//! the experts of the release tasks on stock scenes (T11, T12, T14–T17).
pub mod bddl_terminal;
mod expert;
mod objects;

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
