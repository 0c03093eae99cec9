//! Helpers every private evaluator family builds on: the diagnostic BDDL goal and first-commitment tracker of a
//! scene, the one error a lookup of a named model element gives, and the history fields every physical evaluator
//! fills the same way.
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::simulation::SimData;

use crate::TasksError;
use crate::judge::commitment::CommitmentTracker;
use crate::judge::evaluator::{EvaluationRecord, PrivateEvent};
use crate::judge::goal::GoalChecker;

/// The scene's BDDL goal (a diagnostic for private evaluators) and its first-commitment tracker.
pub(crate) fn scene_goal_and_commitment(
    scene: &ComposedScene,
    model: &MjModel,
) -> Result<(GoalChecker, CommitmentTracker), TasksError> {
    let goal = GoalChecker::for_scene(scene, model)?;
    let commitment = CommitmentTracker::new(goal.index(), model)?;
    Ok((goal, commitment))
}

/// A private evaluator's lookup error: the model lacks what its parameters name.
pub(crate) fn missing_in_model(checker: &str, kind: &str, name: &str) -> TasksError {
    TasksError::Scene(format!("{checker}: the model has no {kind} {name:?}"))
}

/// The fields every private physical evaluator fills the same way: sample counts, private events, first commitment
/// and the diagnostic BDDL goal on the final state.
pub(crate) fn fill_history(
    record: &mut EvaluationRecord,
    (control_steps, substeps): (u64, u64),
    events: &[PrivateEvent],
    commitment: &CommitmentTracker,
    goal: &GoalChecker,
    data: &SimData,
) {
    record.control_steps_observed = control_steps;
    record.substeps_observed = substeps;
    record.events = events.to_vec();
    record.first_commitment = commitment.first().cloned();
    let report = goal.evaluate(data);
    record.bddl_final_goal_success = Some(report.success);
    record.bddl_goal = Some(report);
}

