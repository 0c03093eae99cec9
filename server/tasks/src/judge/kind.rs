//! A checker kind as a table row: its name in the manifest, how to build its evaluator and which private edits it
//! makes to the model. Each family lists the kinds it judges this way; the registry concatenates the tables, so the
//! list of kinds a build can judge lives in one place.
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;
use serde::Deserialize;
use serde::de::DeserializeOwned;

use crate::TasksError;
use crate::judge::evaluator::Evaluator;

/// A manifest checker as a kind's builder sees it.
#[derive(Debug, Clone, Copy)]
pub struct CheckerParams<'a> {
    /// The checker type (`bddl_terminal_open` shares its builder with `bddl_terminal`).
    pub kind: &'a str,
    /// `checker.params` (`{}` where the task has none).
    pub params: &'a serde_json::Value,
    pub task_id: Option<&'a str>,
}

/// The params of a checker that has none.
static NO_PARAMS: std::sync::LazyLock<serde_json::Value> = std::sync::LazyLock::new(|| serde_json::json!({}));

impl<'a> CheckerParams<'a> {
    /// A checker's params as its builder sees them: `null` (no `params` in the manifest) reads as `{}`.
    pub fn new(kind: &'a str, params: &'a serde_json::Value, task_id: Option<&'a str>) -> Self {
        let params = if params.is_null() { &*NO_PARAMS } else { params };
        Self { kind, params, task_id }
    }
}

impl<'a> CheckerParams<'a> {
    /// The params as the kind's typed struct. Every field comes from the manifest (the structs have no defaults and
    /// refuse unknown fields), so the error names the field.
    pub fn parse<T: DeserializeOwned>(&self) -> Result<T, TasksError> {
        T::deserialize(self.params).map_err(|e| self.error(format!("checker {}: bad params: {e}", self.kind)))
    }

    /// `params.variant`: which form of a kind with several (the seesaw's).
    pub fn variant(&self) -> Option<&'a str> {
        /// The one param every kind may read before its own struct: which form of it.
        #[derive(serde::Deserialize)]
        struct Variant<'v> {
            #[serde(borrow, default)]
            variant: Option<&'v str>,
        }
        Variant::deserialize(self.params).ok()?.variant
    }

    /// A catalog error about this task's checker.
    pub fn error(&self, message: String) -> TasksError {
        TasksError::Catalog { path: self.task_id.unwrap_or("task").to_owned(), message }
    }

    pub fn task_id_owned(&self) -> Option<String> {
        self.task_id.map(str::to_owned)
    }
}

/// Whether the params parse as `T`: a kind's [`EvaluatorKind::check_params`] (`check::<TheParams>`), so the catalog
/// and the pool refuse a malformed checker when they load, not when an episode starts.
pub fn check<T: DeserializeOwned>(checker: &CheckerParams) -> Result<(), TasksError> {
    checker.parse::<T>().map(drop)
}

/// Checks a checker's params without a scene.
pub type CheckParams = fn(&CheckerParams) -> Result<(), TasksError>;
/// Builds a kind's evaluator (unannotated) for a scene compiled as the model.
pub type BuildEvaluator = fn(&CheckerParams, &ComposedScene, &MjModel) -> Result<Box<dyn Evaluator>, TasksError>;
/// Writes a task's private parameters into the compiled model before the episode starts (T08's mug masses).
pub type ModelEdits = fn(&CheckerParams, &mut MjModel) -> Result<(), TasksError>;

/// One checker kind (or one variant of it).
#[derive(Debug, Clone, Copy)]
pub struct EvaluatorKind {
    /// The manifest's `checker.type`.
    pub name: &'static str,
    /// The `params.variant` this row judges; `None` is the kind's plain form.
    pub variant: Option<&'static str>,
    /// The evaluator delimits operations by its own stages (the staged kinds), so the catalog's annotation adds the
    /// declared stage types only, not the goal's opening operations.
    pub stages_delimit_operations: bool,
    /// Parses the params alone ([`check`]`::<TheParams>`).
    pub check_params: CheckParams,
    pub build: BuildEvaluator,
    pub model_edits: Option<ModelEdits>,
}

impl EvaluatorKind {
    /// A kind in its plain form, without model edits, judged with the goal's opening operations.
    pub const fn plain(name: &'static str, check_params: CheckParams, build: BuildEvaluator) -> Self {
        Self { name, variant: None, stages_delimit_operations: false, check_params, build, model_edits: None }
    }
}

/// The row of `kinds` that judges `checker`: its kind, and among a kind's variants the one `params.variant` names (a
/// kind without variants ignores the field: its params struct refuses it).
pub fn find<'k>(kinds: &'k [EvaluatorKind], checker: &CheckerParams) -> Result<&'k EvaluatorKind, TasksError> {
    let rows: Vec<&EvaluatorKind> = kinds.iter().filter(|k| k.name == checker.kind).collect();
    let variant = checker.variant();
    match (rows.iter().find(|k| k.variant == variant), rows.as_slice()) {
        (Some(row), _) => Ok(row),
        (None, []) => Err(checker.error(format!("no evaluator of type {} in this build", checker.kind))),
        (None, [only]) if only.variant.is_none() => Ok(only),
        (None, _) => Err(checker.error(format!("checker {}: no variant {:?} in this build", checker.kind, variant.unwrap_or_default()))),
    }
}
