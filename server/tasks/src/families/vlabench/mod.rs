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

use crate::expert::ExpertEntry;
use crate::judge::kind::EvaluatorKind;

/// This family's experts, a row per task.
pub fn experts() -> impl Iterator<Item = ExpertEntry> {
    [expert::EXPERTS, seesaw_expert::EXPERTS, seesaw_pool_expert::EXPERTS, cluster_expert::EXPERTS].into_iter().flatten().copied()
}

/// The checker kinds this family judges (the seesaw in its three variants).
pub const EVALUATORS: &[EvaluatorKind] = &[
    button_press::EVALUATOR,
    button_press::GATED_EVALUATOR,
    tube_insertion::EVALUATOR,
    seesaw::EVALUATOR,
    seesaw_adaptive::EVALUATOR,
    seesaw_comparison::EVALUATOR,
];
