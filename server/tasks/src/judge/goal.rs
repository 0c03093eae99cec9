//! A BDDL `:goal` bound to a composed scene: LIBERO's `_check_success`, with every atom's value reported.
use std::sync::Arc;

use libero_bddl::{Expr, Problem};
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::simulation::SimData;
use serde::Serialize;

use crate::TasksError;
use crate::judge::predicates::{CompiledAtom, SceneIndex};

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

/// Evaluates a conjunctive goal. Every atom is evaluated (no short-circuit), as LIBERO does. The coffee-table
/// problem class (Libero-Agent's, task catalog §2.1) also evaluates nested `Or` / `And` / `Not` (T24's drainer goal);
/// then `atoms` lists every atom in document order and `success` is the expression's value.
#[derive(Debug, Clone)]
pub struct GoalChecker {
    index: Arc<SceneIndex>,
    atoms: Vec<CompiledAtom>,
    /// `None`: the conjunction of `atoms`.
    expr: Option<GoalExpr>,
}

/// A goal expression over `GoalChecker::atoms` (indices).
#[derive(Debug, Clone)]
enum GoalExpr {
    And(Vec<GoalExpr>),
    Or(Vec<GoalExpr>),
    Not(Box<GoalExpr>),
    Atom(usize),
}

impl GoalExpr {
    fn compile(e: &Expr, index: &SceneIndex, atoms: &mut Vec<CompiledAtom>) -> Result<Self, TasksError> {
        let list = |items: &[Expr], atoms: &mut Vec<CompiledAtom>| {
            items.iter().map(|i| Self::compile(i, index, atoms)).collect::<Result<Vec<_>, _>>()
        };
        Ok(match e {
            Expr::And(items) => GoalExpr::And(list(items, atoms)?),
            Expr::Or(items) => GoalExpr::Or(list(items, atoms)?),
            Expr::Not(inner) => GoalExpr::Not(Box::new(Self::compile(inner, index, atoms)?)),
            Expr::Atom(a) => {
                atoms.push(CompiledAtom::compile(index, a)?);
                GoalExpr::Atom(atoms.len() - 1)
            }
        })
    }

    fn value(&self, atom: &dyn Fn(usize) -> bool) -> bool {
        match self {
            GoalExpr::And(items) => items.iter().all(|i| i.value(atom)),
            GoalExpr::Or(items) => items.iter().any(|i| i.value(atom)),
            GoalExpr::Not(inner) => !inner.value(atom),
            GoalExpr::Atom(i) => atom(*i),
        }
    }
}

/// The problem class whose goals may use `Or` / `Not`.
const NESTED_GOAL_PROBLEM: &str = "LIBERO_Coffee_Table_Manipulation";

impl GoalChecker {
    /// The scene's own BDDL goal.
    pub fn for_scene(scene: &ComposedScene, model: &MjModel) -> Result<Self, TasksError> {
        Self::new(Arc::new(SceneIndex::new(scene, model)?), &scene.problem)
    }

    /// `problem`'s goal on an already indexed scene (the goal may come from another BDDL over the same scene).
    pub fn new(index: Arc<SceneIndex>, problem: &Problem) -> Result<Self, TasksError> {
        if let (None, Some(goal)) = (problem.goal_atoms(), &problem.goal)
            && problem.problem_name.eq_ignore_ascii_case(NESTED_GOAL_PROBLEM)
        {
            let mut atoms = Vec::new();
            let expr = GoalExpr::compile(goal, &index, &mut atoms)?;
            return Ok(Self { index, atoms, expr: Some(expr) });
        }
        let atoms = problem.goal_atoms().ok_or_else(|| {
            TasksError::goal("(:goal ...)", "LIBERO evaluates only a conjunction of atoms; this goal uses or/not")
        })?;
        let atoms = atoms.into_iter().map(|a| CompiledAtom::compile(&index, a)).collect::<Result<Vec<_>, _>>()?;
        Ok(Self { index, atoms, expr: None })
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
        let success = match &self.expr {
            Some(e) => e.value(&|i| predicates[i].value),
            None => predicates.iter().all(|p| p.value),
        };
        GoalReport { success, predicates }
    }

    /// The conjunction alone (no allocation), for per-step sampling. Short-circuits: our atoms have no side
    /// effects (LIBERO's only one, the stove burner flag, is cosmetic and handled by the simulation).
    pub fn holds(&self, data: &SimData) -> bool {
        match &self.expr {
            Some(e) => e.value(&|i| self.atoms[i].evaluate(&self.index, data)),
            None => self.atoms.iter().all(|a| a.evaluate(&self.index, data)),
        }
    }
}
