//! long_horizon_v2 and RoboMemArena: the coffee-brewing evaluator of the pool's `long_horizon_v2/2`, and the experts
//! of T21–T27 and of the pool's long-horizon entries (VLABench find_unseen_object's staged search among them). Their
//! other tasks are judged by the staged evaluator (`judge::staged`), shared with other families.
pub mod coffee;
mod expert;
mod robomem_expert;
mod bowls_expert;
mod cooking_expert;
mod coffee_expert;
mod robomem_containers;
mod robomem_pour_microwave;
mod find_unseen_expert;

use crate::expert::ExpertEntry;
use crate::judge::kind::EvaluatorKind;

/// This family's experts, a row per task.
pub fn experts() -> impl Iterator<Item = ExpertEntry> {
    [expert::EXPERTS, robomem_expert::EXPERTS, bowls_expert::EXPERTS, cooking_expert::EXPERTS]
        .concat()
        .into_iter()
        .chain(robomem_containers::experts())
        .chain(robomem_pour_microwave::experts())
        .chain([find_unseen_expert::EXPERTS, coffee_expert::EXPERTS].concat())
}

/// The checker kinds this family judges.
pub const EVALUATORS: &[EvaluatorKind] = &[coffee::EVALUATOR];
