//! A BDDL `:goal` bound to a composed scene: LIBERO's `_check_success`, with every atom's value reported.
use std::sync::Arc;

use libero_bddl::Problem;
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::simulation::SimData;
use serde::Serialize;

use crate::TasksError;
use crate::predicates::{CompiledAtom, SceneIndex};

/// One goal atom and its value.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PredicateValue {
    pub predicate: String,
    pub value: bool,
}

/// The goal's value on one state.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GoalReport {
    /// Conjunction of all atoms (true for an empty goal, as LIBERO's loop starts from `True`).
    pub success: bool,
    pub predicates: Vec<PredicateValue>,
}

/// Evaluates a conjunctive goal. Every atom is evaluated (no short-circuit), as LIBERO does.
#[derive(Debug, Clone)]
pub struct GoalChecker {
    index: Arc<SceneIndex>,
    atoms: Vec<CompiledAtom>,
}

impl GoalChecker {
    /// The scene's own BDDL goal.
    pub fn for_scene(scene: &ComposedScene, model: &MjModel) -> Result<Self, TasksError> {
        Self::new(Arc::new(SceneIndex::new(scene, model)?), &scene.problem)
    }

    /// `problem`'s goal on an already indexed scene (the goal may come from another BDDL over the same scene).
    pub fn new(index: Arc<SceneIndex>, problem: &Problem) -> Result<Self, TasksError> {
        let atoms = problem.goal_atoms().ok_or_else(|| {
            TasksError::goal("(:goal ...)", "LIBERO evaluates only a conjunction of atoms; this goal uses or/not")
        })?;
        let atoms = atoms.into_iter().map(|a| CompiledAtom::compile(&index, a)).collect::<Result<Vec<_>, _>>()?;
        Ok(Self { index, atoms })
    }

    pub fn index(&self) -> &Arc<SceneIndex> {
        &self.index
    }

    pub fn atoms(&self) -> &[CompiledAtom] {
        &self.atoms
    }

    pub fn evaluate(&self, data: &SimData) -> GoalReport {
        let predicates: Vec<PredicateValue> = self
            .atoms
            .iter()
            .map(|a| PredicateValue { predicate: a.text.clone(), value: a.evaluate(&self.index, data) })
            .collect();
        GoalReport { success: predicates.iter().all(|p| p.value), predicates }
    }

    /// The conjunction alone (no allocation), for per-step sampling. Short-circuits: our atoms have no side
    /// effects (LIBERO's only one, the stove burner flag, is cosmetic and handled by the simulation).
    pub fn holds(&self, data: &SimData) -> bool {
        self.atoms.iter().all(|a| a.evaluate(&self.index, data))
    }
}
