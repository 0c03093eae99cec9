//! Stock LIBERO tasks (libero_spatial, _object, _goal, _10, _90), judged on their BDDL goal: the goal evaluator, the
//! experts of the release tasks on stock scenes (T11, T12, T14–T17) and the generic expert of the 130 stock tasks
//! (`suite/NAME`, planned from the goal).
pub mod bddl_terminal;
mod expert;
mod objects;
pub mod stock;

use crate::TasksError;
use crate::expert::{Expert, SceneRefs};

/// The tasks this family scripts, with their near-miss behaviours.
pub fn behaviours(task_id: &str) -> Option<&'static [&'static str]> {
    expert::behaviours(task_id).or_else(|| stock::behaviours(task_id))
}

/// This family's expert for `task_id` (one of [`behaviours`]).
pub fn build_expert(task_id: &str, behaviour: &str, refs: &SceneRefs) -> Result<Box<dyn Expert>, TasksError> {
    if stock::is_stock_id(task_id) {
        return stock::build(behaviour, refs);
    }
    expert::build(task_id, behaviour, refs)
}
