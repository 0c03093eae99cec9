//! Helpers every private evaluator family builds on: the diagnostic BDDL goal and first-commitment tracker of a
//! scene, the one error a lookup of a named model element gives, and the private masses written into the model.
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};

use crate::TasksError;
use crate::judge::commitment::CommitmentTracker;
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

/// The bodies of instance `instance`'s subtree (its root body is `<instance>_main`, as the composer names it).
fn instance_bodies(checker: &str, model: &MjModel, instance: &str) -> Result<Vec<usize>, TasksError> {
    let root_name = format!("{instance}_main");
    let root = model.name_to_id(MjtObjBase::mjOBJ_BODY, &root_name).ok_or_else(|| missing_in_model(checker, "body", &root_name))?;
    let parents = model.body_parentid();
    Ok((0..model.ffi().nbody as usize).filter(|&b| crate::judge::predicates::in_subtree(parents, b, root)).collect())
}

/// Sets each named instance's mass (kg), scaling every body of its subtree, inertia with it, so the shape's density
/// stays uniform: a task's private masses reach the physics, never a file (T08's mugs, the pool's seesaw weights).
pub(crate) fn set_instance_masses<'a>(
    checker: &str,
    masses_kg: impl IntoIterator<Item = (&'a String, &'a f64)>,
    model: &mut MjModel,
) -> Result<(), TasksError> {
    for (instance, &mass) in masses_kg {
        let bodies = instance_bodies(checker, model, instance)?;
        let total: f64 = bodies.iter().map(|&b| model.body_mass()[b]).sum();
        if total <= 0.0 || !(mass > 0.0 && mass.is_finite()) {
            return Err(TasksError::Scene(format!("{checker}: cannot give {instance} (mass {total} kg) a mass of {mass} kg")));
        }
        let k = mass / total;
        for &b in &bodies {
            model.body_mass_mut()[b] *= k;
            for v in &mut model.body_inertia_mut()[b] {
                *v *= k;
            }
        }
    }
    Ok(())
}

/// The mass (kg) of an instance's body subtree in the compiled model.
pub(crate) fn instance_mass(checker: &str, model: &MjModel, instance: &str) -> Result<f64, TasksError> {
    Ok(instance_bodies(checker, model, instance)?.iter().map(|&b| model.body_mass()[b]).sum())
}
