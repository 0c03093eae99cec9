//! mujoco_adapted_v2: tasks adapted from robosuite, MetaWorld, RoboCasa and RoboMemArena onto LIBERO scenes: spill
//! wiping (T19), wine pouring (T20), the locked door (T28, judged by the staged evaluator) and hammer-on-nail
//! (T29), with their experts.
pub mod hammer_contact;
pub mod pour_wine;
pub mod wipe;
mod expert;
mod door_expert;
mod hammer_expert;

use crate::TasksError;
use crate::expert::{Expert, SceneRefs};

/// The tasks this family scripts, with their near-miss behaviours.
pub fn behaviours(task_id: &str) -> Option<&'static [&'static str]> {
    expert::behaviours(task_id).or_else(|| door_expert::behaviours(task_id)).or_else(|| hammer_expert::behaviours(task_id))
}

/// This family's expert for `task_id` (one of [`behaviours`]).
pub fn build_expert(task_id: &str, behaviour: &str, refs: &SceneRefs) -> Result<Box<dyn Expert>, TasksError> {
    if door_expert::behaviours(task_id).is_some() {
        door_expert::build(task_id, behaviour, refs)
    } else if hammer_expert::behaviours(task_id).is_some() {
        hammer_expert::build(task_id, behaviour, refs)
    } else {
        expert::build(task_id, behaviour, refs)
    }
}
