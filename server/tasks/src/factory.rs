//! Builds the evaluator a task is judged by.
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;

use crate::TasksError;
use crate::bddl_terminal::{self, BddlTerminal};
use crate::catalog::CheckerSpec;
use crate::commitment::CommitmentTracker;
use crate::evaluator::Evaluator;
use crate::goal::GoalChecker;

/// Whether this build has an evaluator of type `kind` (the catalog refuses implemented tasks without one).
pub fn has_evaluator(kind: &str) -> bool {
    matches!(kind, "bddl_terminal" | "bddl_terminal_open" | crate::wipe::CHECKER | crate::pour::CHECKER)
}

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
        crate::wipe::CHECKER => {
            let goal = GoalChecker::for_scene(scene, model)?;
            let commitment = CommitmentTracker::new(goal.index(), model)?;
            let params = params::<crate::wipe::WipeParams>(checker, task_id)?;
            Ok(Box::new(crate::wipe::SpillWipe::new(params, goal, commitment, model, task_id.map(str::to_owned))?))
        }
        crate::pour::CHECKER => {
            let goal = GoalChecker::for_scene(scene, model)?;
            let commitment = CommitmentTracker::new(goal.index(), model)?;
            let params = params::<crate::pour::PourParams>(checker, task_id)?;
            Ok(Box::new(crate::pour::PourWine::new(params, goal, commitment, model, task_id.map(str::to_owned))?))
        }
        other => Err(TasksError::Catalog {
            path: task_id.unwrap_or("task").to_owned(),
            message: format!("no evaluator of type {other} in this build"),
        }),
    }
}

/// The checker's manifest `params` as `T` (missing fields take the catalog's defaults).
fn params<T: serde::de::DeserializeOwned + Default>(checker: Option<&CheckerSpec>, task_id: Option<&str>) -> Result<T, TasksError> {
    match checker.map(|c| &c.params) {
        None | Some(serde_json::Value::Null) => Ok(T::default()),
        Some(v) => serde_json::from_value(v.clone()).map_err(|e| TasksError::Catalog {
            path: task_id.unwrap_or("task").to_owned(),
            message: format!("checker params: {e}"),
        }),
    }
}
