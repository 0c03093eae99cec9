//! What every evaluator family shares, and nothing family-specific: the evaluator trait and its record, the
//! skeleton every staged family's evaluator is built on (`family`), stage tracking and per-stage diagnostics, the
//! first-commitment tracker, LIBERO's goal predicates, the pour counter, the staged-evaluator language (ordered,
//! unordered and buffer-rotation stages, used by several families) and small helpers. Nothing here imports a family
//! or the registry, so a family can depend on all of it.
pub mod annotated;
pub mod commitment;
pub mod diagnostics;
pub mod evaluator;
pub mod events;
pub mod family;
pub mod goal;
pub mod kind;
pub mod mechanism;
pub mod pouring;
pub mod predicates;
pub mod stage_types;
pub mod staged;
pub(crate) mod support;
#[cfg(test)]
pub(crate) mod test_params;
