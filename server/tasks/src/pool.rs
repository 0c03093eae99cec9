//! The task pool (`tasks/pool.json`): every `(suite, task_id)` the original registers, 213 entries in 15 suites
//! (task_catalog.md §7), addressable as `suite/task_id` or `suite/name`. An entry either runs here — as its stock
//! LIBERO BDDL, or on the scene, init state and evaluator of a release task (`runs_as`) — or says why not: excluded
//! as a known-buggy asset family, or not implemented yet. Operator data: entries name checker kinds, never reach
//! an agent beyond the instruction of the task it runs.
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use libero_sim::AssetPaths;

use crate::catalog::{BddlRef, Catalog, CheckerSpec, Definition, InitRef, TaskFiles, tasks_dir};
use crate::TasksError;

pub const POOL_SCHEMA: &str = "libero_agent.task_pool.v1";

/// The suites the original registers with their entry counts, in the order `tasks list --tasks all` shows them.
pub const REGISTERED_SUITES: [(&str, usize); 15] = [
    ("perception_v2", 10),
    ("long_horizon_v2", 6),
    ("mujoco_adapted_v2", 4),
    ("vlabench_physical", 3),
    ("vlabench_world_knowledge", 16),
    ("vlabench_perception", 6),
    ("vlabench_tube_precision", 2),
    ("vlabench_additional", 2),
    ("vlabench_button", 8),
    ("libero_spatial", 10),
    ("libero_object", 10),
    ("libero_goal", 10),
    ("libero_10", 10),
    ("libero_90", 90),
    ("robomemarena", 26),
];

/// Stock LIBERO suites: their entries run the stock BDDL and init file of the same name. Defined beside the generic
/// stock expert that plays them, so that family needs nothing of the pool.
pub use crate::families::libero::stock::STOCK_SUITES;

/// The one suite whose task ids start at 1 (RoboMemArena Tasks 1–26).
const ONE_BASED_SUITE: &str = "robomemarena";

/// The reporting groups of the paper.
pub const GROUPS: [&str; 3] = ["perception", "short_horizon", "long_horizon"];

/// One registered pool entry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoolEntry {
    pub suite: String,
    /// Index inside the suite as the original registers it.
    pub task_id: u32,
    pub name: String,
    /// The registered language the agent receives.
    pub instruction: String,
    /// Where the task comes from (`libero`, `robomemarena`, `vlabench`, `metaworld`, …).
    pub source: String,
    /// perception / short_horizon / long_horizon.
    pub group: String,
    /// K.
    pub stage_count: usize,
    /// Evaluator type (parameters live with the task that runs it).
    pub checker: String,
    /// True when the entry runs end to end in this build.
    pub implemented: bool,
    /// The release task whose scene, init state and evaluator this entry runs on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub runs_as: Option<String>,
    /// The release task derived from (or equal to) this entry.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub release_task: Option<String>,
    /// `suite/name` of the entry whose definition this one re-uses (the original registers some scenes twice).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub same_definition_as: Option<String>,
    /// Why the original leaves this entry out of the pool (a known-buggy asset family).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub excluded: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub not_implemented_reason: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notes: Option<String>,
    /// An entry defined here rather than by a release task: its scene, start and private checker parameters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub definition: Option<PoolDefinition>,
}

/// The scene, start state and checker parameters of a pool entry that runs on its own definition (operator-only:
/// the parameters are private like a release task's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoolDefinition {
    pub bddl: BddlRef,
    pub init: InitRef,
    #[serde(default)]
    pub checker_params: serde_json::Value,
}

/// What a runnable pool entry runs on.
#[derive(Debug, Clone, PartialEq)]
pub enum Runs<'a> {
    /// The stock LIBERO file `suite/name`.
    Stock,
    /// A release task (`T07`).
    Release(&'a str),
    /// Its own definition, resolved to files, with its checker.
    Own(TaskFiles, CheckerSpec),
}

/// Whether an entry can be run, and if not why.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EntryStatus {
    Runs,
    Excluded,
    NotImplemented,
}

impl PoolEntry {
    /// `suite/task_id`.
    pub fn id(&self) -> String {
        format!("{}/{}", self.suite, self.task_id)
    }

    /// `suite/name`: the canonical reference an episode records.
    pub fn reference(&self) -> String {
        format!("{}/{}", self.suite, self.name)
    }

    pub fn is_stock(&self) -> bool {
        STOCK_SUITES.contains(&self.suite.as_str())
    }

    pub fn status(&self) -> EntryStatus {
        if self.excluded.is_some() {
            EntryStatus::Excluded
        } else if self.implemented {
            EntryStatus::Runs
        } else {
            EntryStatus::NotImplemented
        }
    }

    /// Why this entry cannot run, if it cannot.
    pub fn why_not(&self) -> Option<String> {
        match self.status() {
            EntryStatus::Runs => None,
            EntryStatus::Excluded => Some(format!("excluded: {}", self.excluded.as_deref().unwrap_or_default())),
            EntryStatus::NotImplemented => Some(format!(
                "not implemented in this build: {}",
                self.not_implemented_reason.as_deref().unwrap_or("no reason given")
            )),
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct PoolFile {
    schema_version: String,
    #[serde(default)]
    description: String,
    excluded_families: Vec<String>,
    entries: Vec<PoolEntry>,
}

/// The validated pool.
#[derive(Debug, Clone)]
pub struct Pool {
    entries: Vec<PoolEntry>,
    excluded_families: Vec<String>,
    /// The folder `pool.json` came from: entries' own definitions are relative to it.
    dir: PathBuf,
}

/// Counts of one suite for `tasks list` and the Tasks page.
#[derive(Debug, Clone, Serialize, PartialEq, Eq)]
pub struct SuiteCounts {
    pub suite: String,
    pub registered: usize,
    pub runs: usize,
    pub excluded: usize,
    pub not_implemented: usize,
}

impl Pool {
    /// Loads `<tasks_dir()>/pool.json`, checked against the release catalog beside it.
    pub fn discover() -> Result<Self, TasksError> {
        let dir = tasks_dir();
        let catalog = Catalog::load(&dir)?;
        Self::load(&dir, &catalog)
    }

    pub fn load(dir: &Path, catalog: &Catalog) -> Result<Self, TasksError> {
        let path = dir.join("pool.json");
        let err = |message: String| TasksError::Catalog { path: path.display().to_string(), message };
        let bytes = std::fs::read(&path).map_err(|e| err(format!("cannot read: {e}")))?;
        let file: PoolFile = serde_json::from_slice(&bytes).map_err(|e| err(e.to_string()))?;
        validate(&file, catalog).map_err(err)?;
        Ok(Self { entries: file.entries, excluded_families: file.excluded_families, dir: dir.to_path_buf() })
    }

    pub fn entries(&self) -> &[PoolEntry] {
        &self.entries
    }

    pub fn excluded_families(&self) -> &[String] {
        &self.excluded_families
    }

    /// What entry `e` runs on, its files resolved (relative to this pool's folder) and checked; why not otherwise.
    pub fn runs<'a>(&self, e: &'a PoolEntry, paths: &AssetPaths) -> Result<Runs<'a>, TasksError> {
        if let Some(why) = e.why_not() {
            return Err(TasksError::Catalog { path: e.id(), message: format!("{} ({}) is {why}", e.id(), e.name) });
        }
        match (&e.runs_as, &e.definition) {
            _ if e.is_stock() => Ok(Runs::Stock),
            (Some(task), _) => Ok(Runs::Release(task)),
            (None, Some(d)) => {
                let id = e.reference();
                let definition = Definition { id: &id, suite: &e.suite, bddl: &d.bddl, init: &d.init, task_reference: None };
                let files = definition.files(&self.dir, paths)?;
                Ok(Runs::Own(files, CheckerSpec { kind: e.checker.clone(), params: d.checker_params.clone() }))
            }
            (None, None) => Err(TasksError::Catalog { path: e.id(), message: "names nothing to run".into() }),
        }
    }

    /// `suite/task_id` or `suite/name` (a trailing `.bddl` is ignored).
    pub fn get(&self, id: &str) -> Option<&PoolEntry> {
        let (suite, rest) = id.trim().split_once('/')?;
        let rest = rest.strip_suffix(".bddl").unwrap_or(rest);
        let number: Option<u32> = rest.parse().ok();
        self.entries
            .iter()
            .find(|e| e.suite == suite && (e.name == rest || number.is_some_and(|n| n == e.task_id)))
    }

    /// The entry an ambiguous-looking reference names, or a message listing what exists.
    pub fn lookup(&self, id: &str) -> Result<&PoolEntry, String> {
        self.get(id).ok_or_else(|| {
            let suite = id.split_once('/').map_or(id, |(s, _)| s);
            match REGISTERED_SUITES.iter().find(|(s, _)| *s == suite) {
                Some((s, n)) => {
                    let first = if *s == ONE_BASED_SUITE { 1 } else { 0 };
                    format!("no pool entry {id:?}: {s} has task ids {first}–{} (or use a task name)", first + n - 1)
                }
                None => format!(
                    "no pool suite {suite:?}; registered suites: {}",
                    REGISTERED_SUITES.map(|(s, _)| s).join(", ")
                ),
            }
        })
    }

    /// Entries of one suite (`all`: every entry), optionally of one group.
    pub fn select<'a>(&'a self, suite: &'a str, group: Option<&'a str>) -> impl Iterator<Item = &'a PoolEntry> + 'a {
        self.entries
            .iter()
            .filter(move |e| suite == "all" || e.suite == suite)
            .filter(move |e| group.is_none_or(|g| e.group == g))
    }

    /// Per-suite counts in registration order.
    pub fn suite_counts(&self) -> Vec<SuiteCounts> {
        REGISTERED_SUITES
            .iter()
            .map(|(suite, registered)| {
                let of = |s: EntryStatus| self.entries.iter().filter(|e| e.suite == *suite && e.status() == s).count();
                SuiteCounts {
                    suite: (*suite).to_owned(),
                    registered: *registered,
                    runs: of(EntryStatus::Runs),
                    excluded: of(EntryStatus::Excluded),
                    not_implemented: of(EntryStatus::NotImplemented),
                }
            })
            .collect()
    }
}

fn validate(file: &PoolFile, catalog: &Catalog) -> Result<(), String> {
    if file.schema_version != POOL_SCHEMA {
        return Err(format!("schema_version {:?}, expected {POOL_SCHEMA:?}", file.schema_version));
    }
    let mut by_suite: BTreeMap<&str, Vec<&PoolEntry>> = BTreeMap::new();
    for e in &file.entries {
        by_suite.entry(e.suite.as_str()).or_default().push(e);
    }
    for (suite, count) in REGISTERED_SUITES {
        let entries = by_suite.remove(suite).unwrap_or_default();
        let first = if suite == ONE_BASED_SUITE { 1 } else { 0 };
        let ids: Vec<u32> = entries.iter().map(|e| e.task_id).collect();
        if ids != (first..first + count as u32).collect::<Vec<_>>() {
            return Err(format!("{suite}: task ids {ids:?}, expected {first}..{} in order", first + count as u32));
        }
        let names: BTreeSet<&str> = entries.iter().map(|e| e.name.as_str()).collect();
        if names.len() != entries.len() {
            return Err(format!("{suite}: names must be unique within the suite"));
        }
    }
    if let Some(extra) = by_suite.keys().next() {
        return Err(format!("suite {extra:?} is not registered by the original"));
    }
    let names: BTreeSet<String> = file.entries.iter().map(PoolEntry::reference).collect();
    for e in &file.entries {
        validate_entry(e, catalog, &names, &file.excluded_families).map_err(|m| format!("{}: {m}", e.id()))?;
    }
    Ok(())
}

fn validate_entry(e: &PoolEntry, catalog: &Catalog, names: &BTreeSet<String>, families: &[String]) -> Result<(), String> {
    if e.instruction.trim().is_empty() || e.name.contains(['/', '.']) || e.name.is_empty() {
        return Err("needs a name without '/' or '.' and an instruction".into());
    }
    if !GROUPS.contains(&e.group.as_str()) || e.stage_count == 0 {
        return Err(format!("group {:?} / K {} invalid", e.group, e.stage_count));
    }
    match (e.implemented, e.excluded.is_some(), e.not_implemented_reason.is_some()) {
        (true, false, false) | (false, true, false) | (false, false, true) => {}
        _ => return Err("exactly one of: implemented, excluded (with reason), not_implemented_reason".into()),
    }
    if let Some(why) = &e.excluded
        && !families.iter().any(|f| why.contains(f.as_str()))
    {
        return Err(format!("excluded for {why:?}, which names none of the excluded families"));
    }
    if let Some(other) = &e.same_definition_as
        && (!names.contains(other) || *other == e.reference())
    {
        return Err(format!("same_definition_as {other:?} is not another pool entry"));
    }
    if e.is_stock() {
        if !e.implemented || e.runs_as.is_some() || e.checker != "bddl_terminal" || e.stage_count != 1 {
            return Err("a stock LIBERO entry runs its own BDDL: implemented, no runs_as, bddl_terminal, K = 1".into());
        }
    } else if e.implemented {
        match (&e.runs_as, &e.definition) {
            (Some(id), None) => {
                let task =
                    catalog.get(id).filter(|t| t.id == *id).ok_or_else(|| format!("runs_as {id:?} is no release task"))?;
                if task.checker.kind != e.checker || task.stage_count != e.stage_count {
                    return Err(format!(
                        "checker/K {}/{} differ from {id}'s {}/{}",
                        e.checker, e.stage_count, task.checker.kind, task.stage_count
                    ));
                }
            }
            (None, Some(d)) if crate::checkers::EVALUATOR_KINDS.contains(&e.checker.as_str()) => {
                crate::judge::stage_types::declared_stage_types(&d.checker_params)?;
                crate::checkers::check_params(&e.checker, &d.checker_params, &e.id())?;
            }
            (None, Some(_)) => return Err(format!("checker {} has no evaluator in this build", e.checker)),
            _ => return Err("an implemented entry outside stock LIBERO runs as a release task or on its own definition, not both".into()),
        }
    }
    for t in e.release_task.iter().chain(&e.runs_as) {
        if catalog.get(t).is_none_or(|task| task.id != *t) {
            return Err(format!("{t:?} is no release task"));
        }
    }
    Ok(())
}
