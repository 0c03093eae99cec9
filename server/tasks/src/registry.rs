//! The one place that knows every kind: which evaluator judges each checker type of the manifest, and which
//! family's scripted expert plays each task. Adding a task family touches its folder under `families/`, this
//! registry and the manifest; nothing else names a family.
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;

use crate::TasksError;
use crate::catalog::CheckerSpec;
use crate::expert::{Expert, SOLVE, SceneRefs};
use crate::families::adapted::hammer_contact::{self, HammerContact};
use crate::families::adapted::pour_wine::{self as pour, PourWine};
use crate::families::adapted::wipe::{self, SpillWipe};
use crate::families::libero::bddl_terminal::{self, BddlTerminal};
use crate::families::long_horizon::coffee::{self, CoffeeBrewing};
use crate::families::long_horizon::staged::{self, StagedEvaluator};
use crate::families::perception::weighing::{self, PhysicalWeighing};
use crate::families::vlabench::button_press::{self, ButtonPress};
use crate::families::vlabench::seesaw::{self, PhysicalSeesaw};
use crate::families::vlabench::seesaw_adaptive::{self, AdaptiveSeesaw};
use crate::families::vlabench::seesaw_comparison::{self, WeightComparison};
use crate::families::vlabench::tube_insertion::{self, TubeInsertion};
use crate::families::{adapted, libero, long_horizon, perception, vlabench};
use crate::judge::annotated::Annotated;
use crate::judge::evaluator::Evaluator;
use crate::judge::support::scene_goal_and_commitment;

/// The checker types this build can judge (defined beside the catalog, which refuses an implemented task whose
/// checker is not among them).
pub use crate::checkers::EVALUATOR_KINDS;

/// The manifest's `checker.params` for `kind` (missing fields take the catalog's defaults where the type has them).
fn params<T: serde::de::DeserializeOwned>(checker: Option<&CheckerSpec>, kind: &str, task_id: Option<&str>) -> Result<T, TasksError> {
    let value = checker.map(|c| c.params.clone()).filter(|v| !v.is_null()).unwrap_or_else(|| serde_json::json!({}));
    serde_json::from_value(value).map_err(|e| TasksError::Catalog {
        path: task_id.unwrap_or("task").to_owned(),
        message: format!("checker {kind}: bad params: {e}"),
    })
}

/// The seesaw checker's variant (`params.variant`): `None` is T30's basic seesaw.
fn seesaw_variant(checker: Option<&CheckerSpec>) -> Option<&str> {
    checker.and_then(|c| c.params.get("variant")).and_then(|v| v.as_str())
}

/// Edits a task's private checker parameters make to the compiled model before the episode starts (T08: each
/// mug's mass; the pool's seesaw weights: each weight's mass). Call before [`build_evaluator`] and before the model
/// is frozen; a no-op for other checkers.
pub fn apply_private_model_edits(checker: Option<&CheckerSpec>, task_id: Option<&str>, model: &mut MjModel) -> Result<(), TasksError> {
    let masses = |m: &std::collections::BTreeMap<String, f64>, model: &mut MjModel| {
        crate::judge::support::set_instance_masses(seesaw::CHECKER, m, model)
    };
    match (checker.map(|c| c.kind.as_str()), seesaw_variant(checker)) {
        (Some(weighing::CHECKER), _) => weighing::apply_mug_masses(&params(checker, weighing::CHECKER, task_id)?, model),
        (Some(seesaw::CHECKER), Some(seesaw_adaptive::VARIANT)) => {
            let p: seesaw_adaptive::AdaptiveParams = params(checker, seesaw::CHECKER, task_id)?;
            masses(&p.masses_kg, model)
        }
        (Some(seesaw::CHECKER), Some(seesaw_comparison::VARIANT)) => {
            let p: seesaw_comparison::ComparisonParams = params(checker, seesaw::CHECKER, task_id)?;
            masses(&p.masses_kg, model)
        }
        _ => Ok(()),
    }
}

/// The evaluator for `checker` on `scene` (compiled as `model`). `None` — a stock LIBERO task without a suite
/// entry — is judged like `bddl_terminal`: the scene's own BDDL goal on the final state. Every evaluator comes
/// with the catalog's annotations ([`Annotated`]): the declared stage types, and the opening operations of the goal
/// for kinds that do not delimit operations by stage themselves.
pub fn build_evaluator(
    checker: Option<&CheckerSpec>,
    task_id: Option<&str>,
    scene: &ComposedScene,
    model: &MjModel,
) -> Result<Box<dyn Evaluator>, TasksError> {
    let kind = checker.map_or(bddl_terminal::CHECKER, |c| c.kind.as_str());
    let stage_types = match checker {
        Some(c) => c.stage_types().map_err(|message| TasksError::Catalog { path: task_id.unwrap_or("task").to_owned(), message })?,
        None => Vec::new(),
    };
    let typed = stage_types.into_iter().filter_map(|(name, t)| t.map(|t| (name, t))).collect();
    let staged = matches!(kind, staged::CHECKER_ORDERED | staged::CHECKER_UNORDERED | staged::CHECKER_BUFFER_ROTATION);
    let inner = build_kind(kind, checker, task_id, scene, model)?;
    Ok(Box::new(Annotated::new(inner, typed, !staged, scene, model)?))
}

/// The evaluator of checker type `kind`, unannotated.
fn build_kind(
    kind: &str,
    checker: Option<&CheckerSpec>,
    task_id: Option<&str>,
    scene: &ComposedScene,
    model: &MjModel,
) -> Result<Box<dyn Evaluator>, TasksError> {
    match kind {
        "bddl_terminal" | "bddl_terminal_open" => {
            let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
            let p: bddl_terminal::BddlTerminalParams = params(checker, kind, task_id)?;
            if let Some(t) = &p.judgment_target
                && goal.index().instance(t).is_none()
            {
                return Err(crate::judge::support::missing_in_model(kind, "instance", t));
            }
            let e = BddlTerminal::new(kind, goal, commitment, task_id.map(str::to_owned));
            Ok(Box::new(e.with_judgment_target(p.judgment_target)))
        }
        button_press::CHECKER => {
            let p = params(checker, kind, task_id)?;
            Ok(Box::new(ButtonPress::new(p, scene, model, task_id.map(str::to_owned))?))
        }
        button_press::GATED_CHECKER => {
            let p = params(checker, kind, task_id)?;
            Ok(Box::new(ButtonPress::gated(p, scene, model, task_id.map(str::to_owned))?))
        }
        tube_insertion::CHECKER => {
            let p = params(checker, kind, task_id)?;
            Ok(Box::new(TubeInsertion::new(p, scene, model, task_id.map(str::to_owned))?))
        }
        wipe::CHECKER => {
            let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
            let p = params(checker, kind, task_id)?;
            Ok(Box::new(SpillWipe::new(p, goal, commitment, model, task_id.map(str::to_owned))?))
        }
        pour::CHECKER => {
            let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
            let p = params(checker, kind, task_id)?;
            Ok(Box::new(PourWine::new(p, goal, commitment, model, task_id.map(str::to_owned))?))
        }
        staged::CHECKER_ORDERED | staged::CHECKER_UNORDERED | staged::CHECKER_BUFFER_ROTATION => {
            let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
            let p = params(checker, kind, task_id)?;
            Ok(Box::new(StagedEvaluator::new(kind, p, goal, commitment, model, task_id.map(str::to_owned))?))
        }
        coffee::CHECKER => {
            let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
            let p = params(checker, kind, task_id)?;
            Ok(Box::new(CoffeeBrewing::new(p, goal, commitment, model, task_id.map(str::to_owned))?))
        }
        weighing::CHECKER => {
            let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
            let p = params(checker, kind, task_id)?;
            Ok(Box::new(PhysicalWeighing::new(p, goal, commitment, task_id.map(str::to_owned))?))
        }
        hammer_contact::CHECKER => {
            let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
            let p = params(checker, kind, task_id)?;
            Ok(Box::new(HammerContact::new(p, goal, commitment, model, task_id.map(str::to_owned))?))
        }
        seesaw::CHECKER => {
            let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
            let id = task_id.map(str::to_owned);
            match seesaw_variant(checker) {
                None => Ok(Box::new(PhysicalSeesaw::new(params(checker, kind, task_id)?, goal, commitment, model, id)?)),
                Some(seesaw_adaptive::VARIANT) => {
                    Ok(Box::new(AdaptiveSeesaw::new(params(checker, kind, task_id)?, goal, commitment, model, id)?))
                }
                Some(seesaw_comparison::VARIANT) => {
                    Ok(Box::new(WeightComparison::new(params(checker, kind, task_id)?, goal, commitment, model, id)?))
                }
                Some(other) => Err(TasksError::Catalog {
                    path: task_id.unwrap_or("task").to_owned(),
                    message: format!("checker {kind}: no variant {other:?} in this build"),
                }),
            }
        }
        other => Err(TasksError::Catalog {
            path: task_id.unwrap_or("task").to_owned(),
            message: format!("no evaluator of type {other} in this build"),
        }),
    }
}

/// One family's experts: the tasks it scripts (with their near-miss behaviours) and how to build one.
struct ExpertFamily {
    behaviours: fn(&str) -> Option<&'static [&'static str]>,
    build: fn(&str, &str, &SceneRefs) -> Result<Box<dyn Expert>, TasksError>,
}

/// Every family with scripted experts. A task id belongs to at most one family.
const EXPERT_FAMILIES: &[ExpertFamily] = &[
    ExpertFamily { behaviours: libero::behaviours, build: libero::build_expert },
    ExpertFamily { behaviours: perception::behaviours, build: perception::build_expert },
    ExpertFamily { behaviours: vlabench::behaviours, build: vlabench::build_expert },
    ExpertFamily { behaviours: adapted::behaviours, build: adapted::build_expert },
    ExpertFamily { behaviours: long_horizon::behaviours, build: long_horizon::build_expert },
];

/// The tasks that have an expert, with their near-miss behaviours.
pub fn expert_behaviours(task_id: &str) -> Option<&'static [&'static str]> {
    EXPERT_FAMILIES.iter().find_map(|f| (f.behaviours)(task_id))
}

/// The expert for `task_id` playing `behaviour` ([`SOLVE`] or one of [`expert_behaviours`]) on this scene.
pub fn expert_for(
    task_id: &str,
    behaviour: &str,
    scene: &ComposedScene,
    model: &MjModel,
) -> Result<Box<dyn Expert>, TasksError> {
    let refs = SceneRefs::new(scene, model)?;
    let (family, known) = EXPERT_FAMILIES
        .iter()
        .find_map(|f| (f.behaviours)(task_id).map(|known| (f, known)))
        .ok_or_else(|| TasksError::Scene(format!("no scripted expert for task {task_id}")))?;
    if behaviour != SOLVE && !known.contains(&behaviour) {
        return Err(TasksError::Scene(format!(
            "task {task_id} has no expert behaviour {behaviour:?}; known: {SOLVE}, {}",
            known.join(", ")
        )));
    }
    (family.build)(task_id, behaviour, &refs)
}

/// Whether the expert of `task_id` can plan this scene's goal: `Ok(steps)` for a scripted task (the generic stock
/// expert's plan, one line per step; empty for a hand-written script), or why not (which goal atom has no skill).
pub fn expert_plan(task_id: &str, scene: &ComposedScene, model: &MjModel) -> Result<Vec<String>, TasksError> {
    if libero::stock::is_stock_id(task_id) {
        return libero::stock::plan_check(&SceneRefs::new(scene, model)?);
    }
    expert_behaviours(task_id).map(|_| Vec::new()).ok_or_else(|| TasksError::Scene(format!("no scripted expert for task {task_id}")))
}

/// The stock LIBERO suites the generic expert plays (`suite/NAME` ids).
pub use crate::pool::STOCK_SUITES;

