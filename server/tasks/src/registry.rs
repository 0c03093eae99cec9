//! The one place that knows every kind: which evaluator judges each checker type of the manifest, and which
//! family's scripted expert plays each task. Both are tables: each family exports its rows (`EVALUATORS`, built
//! once into [`crate::checkers::KINDS`]; `experts()`, concatenated here), so a task's expert and a kind's builder are
//! written once, in their row. Adding a task family touches its folder under `families/`, its line here and in
//! `checkers`, and the manifest; nothing else names a family.
use std::collections::HashMap;
use std::sync::LazyLock;

use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;

use crate::TasksError;
use crate::catalog::CheckerSpec;
use crate::checkers::kind_of;
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs, SuiteExpert};
use crate::families::libero::bddl_terminal;
use crate::families::libero::stock::SUITE_EXPERT;
use crate::families::{adapted, libero, long_horizon, perception, vlabench};
use crate::judge::annotated::Annotated;
use crate::judge::evaluator::Evaluator;
use crate::judge::kind::CheckerParams;

/// The checker types this build can judge (defined beside the catalog, which refuses an implemented task whose
/// checker is not among them).
pub use crate::checkers::EVALUATOR_KINDS;

/// `checker` as its kind's builder sees it; `None` (a stock task without a suite entry) is `bddl_terminal` with
/// no params.
fn with_params<R>(checker: Option<&CheckerSpec>, task_id: Option<&str>, f: impl FnOnce(&CheckerParams) -> R) -> R {
    let kind = checker.map_or(bddl_terminal::CHECKER, |c| c.kind.as_str());
    f(&CheckerParams::new(kind, checker.map_or(&serde_json::Value::Null, |c| &c.params), task_id))
}

/// Edits a task's private checker parameters make to the compiled model before the episode starts (T08: each
/// mug's mass; the pool's seesaw weights: each weight's mass). Call before [`build_evaluator`] and before the model
/// is frozen; a no-op for other checkers (and for a kind this build lacks: [`build_evaluator`] says so).
pub fn apply_private_model_edits(checker: Option<&CheckerSpec>, task_id: Option<&str>, model: &mut MjModel) -> Result<(), TasksError> {
    if checker.is_none() {
        return Ok(());
    }
    with_params(checker, task_id, |c| match kind_of(c).ok().and_then(|k| k.model_edits) {
        Some(edit) => edit(c, model),
        None => Ok(()),
    })
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
    let stage_types = match checker {
        Some(c) => c.stage_types().map_err(|message| TasksError::Catalog { path: task_id.unwrap_or("task").to_owned(), message })?,
        None => Vec::new(),
    };
    let typed = stage_types.into_iter().filter_map(|(name, t)| t.map(|t| (name, t))).collect();
    let (inner, own_operations) = with_params(checker, task_id, |c| {
        let kind = kind_of(c)?;
        Ok::<_, TasksError>(((kind.build)(c, scene, model)?, kind.stages_delimit_operations))
    })?;
    Ok(Box::new(Annotated::new(inner, typed, !own_operations, scene, model)?))
}

/// Every task with a scripted expert of its own: the families' tables, concatenated.
static EXPERTS: LazyLock<Vec<ExpertEntry>> = LazyLock::new(|| {
    libero::experts()
        .chain(perception::experts())
        .chain(vlabench::experts())
        .chain(adapted::experts())
        .chain(long_horizon::experts())
        .collect()
});

/// [`EXPERTS`] by task id.
static EXPERT_INDEX: LazyLock<HashMap<&'static str, &'static ExpertEntry>> =
    LazyLock::new(|| EXPERTS.iter().map(|e| (e.task, e)).collect());

/// Experts that play whole suites (the generic stock expert), asked when no row names the task.
const SUITE_EXPERTS: &[SuiteExpert] = &[SUITE_EXPERT];

/// The behaviours and builder of `task_id`'s expert.
fn expert_entry(task_id: &str) -> Option<(&'static [&'static str], crate::expert::BuildExpert)> {
    if let Some(e) = EXPERT_INDEX.get(task_id) {
        return Some((e.behaviours, e.build));
    }
    SUITE_EXPERTS.iter().find(|s| s.plays(task_id)).map(|s| (s.behaviours, s.build))
}

/// The tasks that have an expert, with their near-miss behaviours.
pub fn expert_behaviours(task_id: &str) -> Option<&'static [&'static str]> {
    expert_entry(task_id).map(|(behaviours, _)| behaviours)
}

/// The expert for `task_id` playing `behaviour` ([`SOLVE`] or one of [`expert_behaviours`]) on this scene.
pub fn expert_for(
    task_id: &str,
    behaviour: &str,
    scene: &ComposedScene,
    model: &MjModel,
) -> Result<Box<dyn Expert>, TasksError> {
    let refs = SceneRefs::new(scene, model)?;
    let (known, build) = expert_entry(task_id).ok_or_else(|| TasksError::Scene(format!("no scripted expert for task {task_id}")))?;
    if behaviour != SOLVE && !known.contains(&behaviour) {
        return Err(TasksError::Scene(format!(
            "task {task_id} has no expert behaviour {behaviour:?}; known: {SOLVE}, {}",
            known.join(", ")
        )));
    }
    build(&refs, behaviour, task_id)
}

/// Whether the expert of `task_id` can plan this scene's goal: `Ok(steps)` for a scripted task (the generic stock
/// expert's plan, one line per step; empty for a hand-written script), or why not (which goal atom has no skill).
pub fn expert_plan(task_id: &str, scene: &ComposedScene, model: &MjModel) -> Result<Vec<String>, TasksError> {
    if SUITE_EXPERT.plays(task_id) {
        return libero::stock::plan_check(&SceneRefs::new(scene, model)?);
    }
    expert_behaviours(task_id).map(|_| Vec::new()).ok_or_else(|| TasksError::Scene(format!("no scripted expert for task {task_id}")))
}

/// The stock LIBERO suites the generic expert plays (`suite/NAME` ids).
pub use crate::pool::STOCK_SUITES;


#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_task_has_two_expert_rows() {
        let mut seen = std::collections::BTreeSet::new();
        let twice: Vec<&str> = EXPERTS.iter().map(|e| e.task).filter(|t| !seen.insert(*t)).collect();
        assert!(twice.is_empty(), "tasks with two expert rows: {twice:?}");
        let shadowed: Vec<&str> = EXPERTS.iter().map(|e| e.task).filter(|t| SUITE_EXPERTS.iter().any(|s| s.plays(t))).collect();
        assert!(shadowed.is_empty(), "rows inside a suite a suite expert plays: {shadowed:?}");
    }

    #[test]
    fn every_release_task_with_an_expert_keeps_its_behaviours() {
        assert_eq!(expert_behaviours("T23").map(<[&str]>::len), Some(8));
        assert_eq!(expert_behaviours("T21"), expert_behaviours("T22"));
        assert_eq!(expert_behaviours("libero_10/anything"), Some(&["stop_short"][..]));
        assert_eq!(expert_behaviours("libero_10/a/b"), None);
        assert_eq!(expert_behaviours("T31"), None);
    }
}
