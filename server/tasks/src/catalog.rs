//! The catalog of the 30 release tasks (`tasks/manifest.json`): loaded, validated, and resolved to files.
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use libero_sim::AssetPaths;
use serde::{Deserialize, Serialize};

use crate::TasksError;

pub const MANIFEST_SCHEMA: &str = "libero_agent.task_manifest.v1";
pub const TASK_COUNT: usize = 30;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Category {
    Perception,
    Manipulation,
    LongHorizon,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Difficulty {
    Easy,
    Hard,
}

/// The paper's reporting subsets, defined once beside the metrics that score them.
pub use libero_metrics::Split;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Source {
    pub suite: String,
    /// Index inside the source suite.
    pub task_id: u32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BddlOrigin {
    /// hf-libero `bddl_files/<path>`.
    Stock,
    /// This repository's `tasks/<path>`.
    Repository,
    /// A file of the original release that is not available here.
    ReleaseOnly,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BddlRef {
    pub origin: BddlOrigin,
    pub path: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InitKind {
    /// hf-libero `init_files/<path>`, row `index`.
    StockFile,
    /// No trusted state: LIBERO's reset placement with the episode seed (or `seed` when fixed).
    SeededPlacement,
    /// The release's trusted state file, not available here.
    ReleaseFileUnavailable,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InitRef {
    pub kind: InitKind,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path: Option<String>,
    pub index: usize,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u32>,
    /// Seeded placement only: the start state is the placement after this many zero-action control steps (a stand-in
    /// for a trusted state captured on a settled scene, where objects rest on tilted or moving parts).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub settle_control_steps: Option<u32>,
    /// Seeded placement only: objects moved, after the placement and before settling, to a fixed pose in a body's
    /// frame (a documented stand-in for where an unavailable trusted state put them).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub poses_in_body: Vec<PoseInBody>,
    /// How this start differs from the release, where it does.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// An object's start pose given in the frame of a body of the placed scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseInBody {
    /// Object instance (moved by its free joint).
    pub object: String,
    /// MuJoCo body whose frame `pos_m` / `quat_wxyz` are given in.
    pub body: String,
    pub pos_m: [f64; 3],
    pub quat_wxyz: [f64; 4],
}

/// Evaluator type and its private parameters (operator-visible only; never sent to agents).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CheckerSpec {
    #[serde(rename = "type")]
    pub kind: String,
    #[serde(default)]
    pub params: serde_json::Value,
}

impl CheckerSpec {
    /// Whether the task is judged by the BDDL goal on the final state alone.
    pub fn is_bddl_terminal(&self) -> bool {
        matches!(self.kind.as_str(), "bddl_terminal" | "bddl_terminal_open")
    }

    /// Every stage its parameters list (`stages`, then `optional_stages`) with the type it declares (paper Table 4:
    /// Object Manipulation / Mechanism Interaction); `None` where a stage declares none.
    pub fn stage_types(&self) -> Result<Vec<(String, Option<crate::judge::stage_types::StageType>)>, String> {
        crate::judge::stage_types::declared_stage_types(&self.params)
    }
}

/// An input the agent receives besides the instruction (protocol §3.9: T22's goal image).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskReference {
    /// RGB PNG under the repository's `assets/` folder (`AssetPaths::project_assets`).
    pub path: String,
    /// What the image specifies (`desired_object_arrangement`: the goal's object arrangement; the robot pose is
    /// not part of it).
    pub semantics: String,
}

/// One release task.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskEntry {
    pub number: u32,
    /// `T01`…`T30`.
    pub id: String,
    pub name: String,
    pub category: Category,
    /// perception / short_horizon / long_horizon.
    pub group: String,
    pub difficulty: Difficulty,
    pub split: Split,
    pub capability: String,
    /// The release manifest's sentence.
    pub instruction: String,
    /// The suite registry's `language` where it differs (lower-case, filename-derived for stock LIBERO tasks).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub registry_instruction: Option<String>,
    pub source: Source,
    pub bddl: BddlRef,
    pub init: InitRef,
    pub checker: CheckerSpec,
    /// K.
    pub stage_count: usize,
    /// True only when the task runs end to end in this build.
    pub implemented: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub not_implemented_reason: Option<String>,
    /// Published with every observation of the task's episodes (protocol §3.9).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub task_reference: Option<TaskReference>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notes: Option<String>,
}

impl TaskEntry {
    /// The text the agent receives: the registry's `language` (protocol §9.3: the original release shows the
    /// registry text, lower-case for stock LIBERO tasks), else the manifest sentence.
    pub fn agent_instruction(&self) -> &str {
        self.registry_instruction.as_deref().unwrap_or(&self.instruction)
    }
}

/// Files an implemented task runs from.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskFiles {
    pub bddl: PathBuf,
    /// `None` when the task starts from the seeded placement.
    pub init_states: Option<PathBuf>,
    pub init_index: usize,
    /// Fixed placement seed, if the task has one (otherwise the episode seed).
    pub placement_seed: Option<u32>,
    /// The task's reference image and its semantics (protocol §3.9), checked to exist.
    pub task_reference: Option<(PathBuf, String)>,
    /// Zero-action control steps that turn the seeded placement into the start state (0: the placement itself).
    pub init_settle_steps: u32,
    /// Object poses set after the placement, before the settle steps.
    pub init_poses_in_body: Vec<PoseInBody>,
    /// `vlabench_physical` (protocol §4.2): the settle steps run on the ordinary reset *before* the start state is
    /// restored, and none after it (so an object resting on the seesaw board is not disturbed).
    pub settle_before_restore: bool,
}

/// The one source suite whose episodes settle before restoring the init state (protocol §4.1/§4.2).
pub const SETTLE_BEFORE_RESTORE_SUITE: &str = "vlabench_physical";

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub schema_version: String,
    pub name: String,
    #[serde(default)]
    pub description: String,
    #[serde(default)]
    pub evaluation_policy: serde_json::Value,
    pub tasks: Vec<TaskEntry>,
}

/// The validated manifest plus the folder its repository paths are relative to.
#[derive(Debug, Clone)]
pub struct Catalog {
    pub manifest: Manifest,
    pub dir: PathBuf,
}

/// `$LIBERO_AGENT_TASKS_DIR`, else the repository's `tasks/` folder this crate was built from.
pub fn tasks_dir() -> PathBuf {
    std::env::var_os("LIBERO_AGENT_TASKS_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tasks"))
}

/// The release tasks' facts the report reads beside the records (their stage types and K), from the discovered
/// catalog once per process; empty where there is no catalog (the report then takes what the records say).
pub fn task_facts() -> &'static libero_metrics::TaskFacts {
    static FACTS: std::sync::OnceLock<libero_metrics::TaskFacts> = std::sync::OnceLock::new();
    FACTS.get_or_init(|| Catalog::discover().map(|c| c.task_facts()).unwrap_or_default())
}

impl Catalog {
    /// Loads and validates `<tasks_dir()>/manifest.json`.
    pub fn discover() -> Result<Self, TasksError> {
        Self::load(&tasks_dir())
    }

    pub fn load(dir: &Path) -> Result<Self, TasksError> {
        let path = dir.join("manifest.json");
        let err = |message: String| TasksError::Catalog { path: path.display().to_string(), message };
        let bytes = std::fs::read(&path).map_err(|e| err(format!("cannot read: {e}")))?;
        let manifest: Manifest = serde_json::from_slice(&bytes).map_err(|e| err(e.to_string()))?;
        validate(&manifest).map_err(err)?;
        Ok(Self { manifest, dir: dir.to_path_buf() })
    }

    pub fn tasks(&self) -> &[TaskEntry] {
        &self.manifest.tasks
    }

    /// The tasks' facts the report reads beside the records ([`task_facts`]).
    pub fn task_facts(&self) -> libero_metrics::TaskFacts {
        libero_metrics::TaskFacts {
            stage_types: self.tasks().iter().filter_map(|t| Some((t.number, t.checker.stage_types().ok()?))).collect(),
            stage_counts: self.tasks().iter().map(|t| (t.number, t.stage_count as u32)).collect(),
        }
    }

    /// `T16`, `t16` or `16`.
    pub fn get(&self, id: &str) -> Option<&TaskEntry> {
        let digits = id.trim().trim_start_matches(['T', 't']);
        let number: u32 = digits.parse().ok()?;
        self.manifest.tasks.iter().find(|t| t.number == number)
    }

    /// The BDDL and init files of an implemented task; a clear error naming why otherwise.
    pub fn files(&self, task: &TaskEntry, paths: &AssetPaths) -> Result<TaskFiles, TasksError> {
        if !task.implemented {
            let why = task.not_implemented_reason.as_deref().unwrap_or("no reason given");
            return Err(TasksError::Catalog {
                path: task.id.clone(),
                message: format!("{} ({}) is not implemented in this build: {why}", task.id, task.name),
            });
        }
        let definition = Definition {
            id: &task.id,
            suite: &task.source.suite,
            bddl: &task.bddl,
            init: &task.init,
            task_reference: task.task_reference.as_ref(),
        };
        definition.files(&self.dir, paths)
    }
}

/// Where a runnable task's scene and start come from: a release task's, or a pool entry's own.
pub(crate) struct Definition<'a> {
    pub id: &'a str,
    /// The source suite (decides the settle order of `vlabench_physical`).
    pub suite: &'a str,
    pub bddl: &'a BddlRef,
    pub init: &'a InitRef,
    pub task_reference: Option<&'a TaskReference>,
}

impl Definition<'_> {
    /// The files, checked to exist; repository paths are relative to `dir` (`tasks/`).
    pub fn files(&self, dir: &Path, paths: &AssetPaths) -> Result<TaskFiles, TasksError> {
        let fail = |message: String| TasksError::Catalog { path: self.id.to_owned(), message };
        let bddl = match self.bddl.origin {
            BddlOrigin::Stock => paths.libero_root.join("bddl_files").join(&self.bddl.path),
            BddlOrigin::Repository => dir.join(&self.bddl.path),
            BddlOrigin::ReleaseOnly => return Err(fail(format!("{} needs a release-only BDDL file", self.id))),
        };
        let init_states = match (self.init.kind, &self.init.path) {
            (InitKind::StockFile, Some(p)) => Some(paths.libero_root.join("init_files").join(p)),
            (InitKind::SeededPlacement, _) => None,
            _ => return Err(fail(format!("{} has no usable init state", self.id))),
        };
        let reference = self.task_reference.map(|r| paths.project_assets.join(&r.path));
        for p in std::iter::once(&bddl).chain(&init_states).chain(&reference) {
            if !p.is_file() {
                return Err(fail(format!("{} is missing", p.display())));
            }
        }
        let task_reference = reference.zip(self.task_reference.map(|r| r.semantics.clone()));
        Ok(TaskFiles {
            bddl,
            init_states,
            init_index: self.init.index,
            placement_seed: self.init.seed,
            init_settle_steps: self.init.settle_control_steps.unwrap_or(0),
            init_poses_in_body: self.init.poses_in_body.clone(),
            settle_before_restore: self.suite == SETTLE_BEFORE_RESTORE_SUITE,
            task_reference,
        })
    }
}

fn validate(m: &Manifest) -> Result<(), String> {
    if m.schema_version != MANIFEST_SCHEMA {
        return Err(format!("schema_version {:?}, expected {MANIFEST_SCHEMA:?}", m.schema_version));
    }
    if m.tasks.len() != TASK_COUNT {
        return Err(format!("{} tasks, expected {TASK_COUNT}", m.tasks.len()));
    }
    let numbers: BTreeSet<u32> = m.tasks.iter().map(|t| t.number).collect();
    if numbers != (1..=TASK_COUNT as u32).collect() {
        return Err("task numbers must be exactly 1..=30, each once".into());
    }
    for t in &m.tasks {
        let at = |msg: String| format!("{}: {msg}", t.id);
        if t.id != format!("T{:02}", t.number) {
            return Err(at(format!("id does not match number {}", t.number)));
        }
        if !t.split.members().contains(&t.number) {
            return Err(at(format!("split {:?} does not list task {}", t.split, t.number)));
        }
        if t.stage_count == 0 || (t.checker.is_bddl_terminal() && t.stage_count != 1) {
            return Err(at(format!("stage_count {} does not fit checker {}", t.stage_count, t.checker.kind)));
        }
        if t.implemented == t.not_implemented_reason.is_some() {
            return Err(at("exactly the unimplemented tasks carry a not_implemented_reason".into()));
        }
        if t.implemented && !crate::checkers::EVALUATOR_KINDS.contains(&t.checker.kind.as_str()) {
            return Err(at(format!("checker {} has no evaluator in this build", t.checker.kind)));
        }
        if t.implemented {
            crate::checkers::check_params(&t.checker.kind, &t.checker.params, &t.id).map_err(at)?;
        }
        t.checker.stage_types().map_err(at)?;
    }
    Ok(())
}
