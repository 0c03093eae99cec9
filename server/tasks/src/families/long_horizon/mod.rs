//! long_horizon_v2 and RoboMemArena: the staged evaluator (ordered, unordered and buffer-rotation stages, pour
//! counters, drawers, cabinets), the coffee-brewing evaluator of the pool's `long_horizon_v2/2`, and the experts of
//! T21–T27 and of the pool's long-horizon entries (VLABench find_unseen_object's staged search among them).
pub mod staged;
pub mod coffee;
mod expert;
mod robomem_expert;
mod bowls_expert;
mod cooking_expert;
mod coffee_expert;
mod robomem_containers;
mod robomem_pour_microwave;
mod find_unseen_expert;

use crate::TasksError;
use crate::expert::{Expert, SceneRefs};

/// The tasks this family scripts, with their near-miss behaviours.
pub fn behaviours(task_id: &str) -> Option<&'static [&'static str]> {
    expert::behaviours(task_id).or_else(|| robomem_expert::behaviours(task_id)).or_else(|| bowls_expert::behaviours(task_id)).or_else(|| cooking_expert::behaviours(task_id))
        .or_else(|| robomem_containers::behaviours(task_id))
        .or_else(|| robomem_pour_microwave::behaviours(task_id))
        .or_else(|| find_unseen_expert::behaviours(task_id))
        .or_else(|| coffee_expert::behaviours(task_id))
}

/// This family's expert for `task_id` (one of [`behaviours`]).
pub fn build_expert(task_id: &str, behaviour: &str, refs: &SceneRefs) -> Result<Box<dyn Expert>, TasksError> {
    if robomem_expert::behaviours(task_id).is_some() {
        robomem_expert::build(task_id, behaviour, refs)
    } else if bowls_expert::behaviours(task_id).is_some() {
        bowls_expert::build(task_id, behaviour, refs)
    } else if cooking_expert::behaviours(task_id).is_some() {
        cooking_expert::build(task_id, behaviour, refs)
    } else if robomem_containers::behaviours(task_id).is_some() {
        robomem_containers::build(task_id, behaviour, refs)
    } else if robomem_pour_microwave::behaviours(task_id).is_some() {
        robomem_pour_microwave::build(task_id, behaviour, refs)
    } else if find_unseen_expert::behaviours(task_id).is_some() {
        find_unseen_expert::build(task_id, behaviour, refs)
    } else if coffee_expert::behaviours(task_id).is_some() {
        coffee_expert::build(task_id, behaviour, refs)
    } else {
        expert::build(task_id, behaviour, refs)
    }
}
