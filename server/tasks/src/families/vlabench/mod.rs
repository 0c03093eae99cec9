//! VLABench-derived tasks on this repository's assets: the button press (T13 and the property buttons), the
//! chemistry-tube insertion (T18) and the seesaw (T30, and the pool's `vlabench_physical` 1 and 2: the adaptive mass
//! selection and the active weight comparison), with their experts; and the expert of the pool's
//! `vlabench_additional/cluster_series` (judged by the staged evaluator from its own checker parameters).
pub mod button_press;
pub mod seesaw;
pub mod seesaw_adaptive;
pub mod seesaw_comparison;
pub mod tube_insertion;
mod cluster_expert;
mod expert;
mod seesaw_expert;
mod seesaw_pool_expert;

use crate::TasksError;
use crate::expert::{Expert, SceneRefs};

/// The tasks this family scripts, with their near-miss behaviours.
pub fn behaviours(task_id: &str) -> Option<&'static [&'static str]> {
    expert::behaviours(task_id)
        .or_else(|| seesaw_expert::behaviours(task_id))
        .or_else(|| seesaw_pool_expert::behaviours(task_id))
        .or_else(|| cluster_expert::behaviours(task_id))
}

/// This family's expert for `task_id` (one of [`behaviours`]).
pub fn build_expert(task_id: &str, behaviour: &str, refs: &SceneRefs) -> Result<Box<dyn Expert>, TasksError> {
    if seesaw_expert::behaviours(task_id).is_some() {
        seesaw_expert::build(task_id, behaviour, refs)
    } else if seesaw_pool_expert::behaviours(task_id).is_some() {
        seesaw_pool_expert::build(task_id, behaviour, refs)
    } else if cluster_expert::behaviours(task_id).is_some() {
        cluster_expert::build(task_id, behaviour, refs)
    } else {
        expert::build(task_id, behaviour, refs)
    }
}
