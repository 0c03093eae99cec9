//! mujoco_adapted_v2: tasks adapted from robosuite, MetaWorld, RoboCasa and RoboMemArena onto LIBERO scenes: spill
//! wiping (T19), wine pouring (T20), the locked door (T28, judged by the staged evaluator) and hammer-on-nail
//! (T29), with their experts.
pub mod hammer_contact;
pub mod pour_wine;
pub mod wipe;
mod expert;
mod door_expert;
mod hammer_expert;

use crate::expert::ExpertEntry;
use crate::judge::kind::EvaluatorKind;

/// This family's experts, a row per task.
pub fn experts() -> impl Iterator<Item = ExpertEntry> {
    [expert::EXPERTS, door_expert::EXPERTS, hammer_expert::EXPERTS].into_iter().flatten().copied()
}

/// The checker kinds this family judges.
pub const EVALUATORS: &[EvaluatorKind] = &[wipe::EVALUATOR, pour_wine::EVALUATOR, hammer_contact::EVALUATOR];
