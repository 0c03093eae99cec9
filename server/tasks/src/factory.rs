//! Builds the evaluator a task is judged by.
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;

use crate::TasksError;
use crate::bddl_terminal::{self, BddlTerminal};
use crate::catalog::CheckerSpec;
use crate::commitment::CommitmentTracker;
use crate::evaluator::Evaluator;
use crate::goal::GoalChecker;

/// The evaluator for `checker` on `scene` (compiled as `model`). `None` — a stock LIBERO task without a suite
/// entry — is judged like `bddl_terminal`: the scene's own BDDL goal on the final state.
pub fn build_evaluator(
    checker: Option<&CheckerSpec>,
    task_id: Option<&str>,
    scene: &ComposedScene,
    model: &MjModel,
) -> Result<Box<dyn Evaluator>, TasksError> {
    let kind = checker.map_or(bddl_terminal::CHECKER, |c| c.kind.as_str());
    match kind {
        "bddl_terminal" | "bddl_terminal_open" => {
            let goal = GoalChecker::for_scene(scene, model)?;
            let commitment = CommitmentTracker::new(goal.index(), model)?;
            Ok(Box::new(BddlTerminal::new(kind, goal, commitment, task_id.map(str::to_owned))))
        }
        other => Err(TasksError::Catalog {
            path: task_id.unwrap_or("task").to_owned(),
            message: format!("no evaluator of type {other} in this build"),
        }),
    }
}
