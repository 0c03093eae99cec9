//! What every evaluator's record gets whatever its kind, added around it by the registry: the stage types the
//! catalog declares (for the stage diagnostics), and, for evaluators that do not delimit opening operations of their
//! own (single-goal BDDL tasks such as T15/T16 and the pool's stock LIBERO tasks, the adapted evaluators), every
//! `Open` atom of the scene's BDDL goal as an opening operation with its sustained-contact ratio
//! ([`crate::judge::mechanism`]). The staged evaluators delimit theirs by stage and are wrapped for the types only.
use std::sync::Arc;

use libero_bddl::{Atom, Expr};
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::simulation::SimData;
use serde_json::Value;

use crate::TasksError;
use crate::judge::evaluator::{EvaluationRecord, Evaluator, PrivateEvent, Tick};
use crate::judge::mechanism::{GripperContact, PendingOpening, Watched, body_names, moving_bodies};
use crate::judge::predicates::{CompiledAtom, PredicateKind, SceneIndex};
use crate::judge::stage_types::StageType;

/// The `Open` atoms of a scene's BDDL goal, each a pending opening watched from the first gripper contact.
struct GoalOpenings {
    index: Arc<SceneIndex>,
    gripper: GripperContact,
    openings: Vec<(CompiledAtom, PendingOpening)>,
}

/// The goal's atoms that must hold (not under a `Not`) and whose predicate is `open`.
fn open_atoms<'a>(e: &'a Expr, out: &mut Vec<&'a Atom>) {
    match e {
        Expr::And(items) | Expr::Or(items) => items.iter().for_each(|i| open_atoms(i, out)),
        Expr::Not(_) => {}
        Expr::Atom(a) if a.predicate.eq_ignore_ascii_case("open") => out.push(a),
        Expr::Atom(_) => {}
    }
}

impl GoalOpenings {
    /// `None` when the goal opens nothing with joints.
    fn of_scene(scene: &ComposedScene, model: &MjModel) -> Result<Option<Self>, TasksError> {
        let mut atoms = Vec::new();
        if let Some(goal) = &scene.problem.goal {
            open_atoms(goal, &mut atoms);
        }
        if atoms.is_empty() {
            return Ok(None);
        }
        let index = Arc::new(SceneIndex::new(scene, model)?);
        let gripper = GripperContact::new(&index, model)?;
        let mut openings = Vec::new();
        for atom in atoms {
            let compiled = CompiledAtom::compile(&index, atom)?;
            let bodies = compiled.args.first().map(|&e| moving_bodies(&index, model, e)).unwrap_or_default();
            if compiled.kind == PredicateKind::Open && !bodies.is_empty() {
                let handle_geoms = gripper.require_handle(&bodies, model, &format!("goal {}", compiled.text))?;
                let watched = Watched { bodies: body_names(model, &bodies), handle_geoms };
                let opening = PendingOpening::new(compiled.text.clone(), bodies, watched);
                openings.push((compiled, opening));
            }
        }
        Ok((!openings.is_empty()).then(|| Self { index, gripper, openings }))
    }
}

/// An evaluator with the catalog's annotations (see the module documentation).
pub struct Annotated {
    inner: Box<dyn Evaluator>,
    stage_types: Vec<(String, StageType)>,
    goal_openings: Option<GoalOpenings>,
}

impl Annotated {
    /// `inner` with `stage_types`; with `watch_goal_openings`, also the opening operations of `scene`'s goal.
    pub fn new(
        inner: Box<dyn Evaluator>,
        stage_types: Vec<(String, StageType)>,
        watch_goal_openings: bool,
        scene: &ComposedScene,
        model: &MjModel,
    ) -> Result<Self, TasksError> {
        let goal_openings = if watch_goal_openings { GoalOpenings::of_scene(scene, model)? } else { None };
        Ok(Self { inner, stage_types, goal_openings })
    }
}

impl Evaluator for Annotated {
    fn checker(&self) -> &str {
        self.inner.checker()
    }

    fn samples_substeps(&self) -> bool {
        self.inner.samples_substeps()
    }

    fn reset(&mut self, data: &SimData, tick: Tick) {
        self.inner.reset(data, tick);
        if let Some(g) = &mut self.goal_openings {
            for (atom, opening) in &mut g.openings {
                opening.reset(atom.evaluate(&g.index, data));
            }
        }
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.inner.observe_control_step(data, tick);
        if let Some(g) = &mut self.goal_openings {
            for (atom, opening) in &mut g.openings {
                let touch = g.gripper.touches(data, &opening.bodies);
                opening.step(touch, atom.evaluate(&g.index, data));
            }
        }
    }

    fn observe_substep(&mut self, data: &SimData, tick: Tick) {
        self.inner.observe_substep(data, tick);
    }

    fn finish(&mut self, data: &SimData, tick: Tick) -> EvaluationRecord {
        let mut record = self.inner.finish(data, tick);
        record.stage_types = self.stage_types.clone();
        let Some(g) = &self.goal_openings else { return record };
        // A single-stage record's one stage is the operation's stage; otherwise the operation names its goal atom.
        let only_stage = (record.ordered_stage_names.len() == 1).then(|| record.ordered_stage_names[0].clone());
        let ops: Vec<Value> = g.openings.iter().filter_map(|(_, o)| o.to_json(only_stage.as_deref())).collect();
        if ops.is_empty() {
            return record;
        }
        let mut details = match record.details.take() {
            Some(Value::Object(map)) => map,
            Some(other) => serde_json::Map::from_iter([("evaluator".to_owned(), other)]),
            None => serde_json::Map::new(),
        };
        let list = details.entry("opening_operations").or_insert_with(|| Value::Array(Vec::new()));
        if let Value::Array(existing) = list {
            existing.extend(ops);
        }
        record.details = Some(Value::Object(details));
        record
    }

    fn geom_rgba_overrides(&self) -> Vec<(usize, [f32; 4])> {
        self.inner.geom_rgba_overrides()
    }

    fn private_events(&self) -> Vec<PrivateEvent> {
        self.inner.private_events()
    }

    fn stage_progress(&self) -> (usize, usize) {
        self.inner.stage_progress()
    }
}
