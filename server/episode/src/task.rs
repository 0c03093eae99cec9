//! Which task an episode runs: a release task (`T11`…`T30`, through the catalog in `tasks/manifest.json`), a pool
//! entry (`suite/task_id`, through `tasks/pool.json`) or a stock LIBERO task (`suite/name` or a BDDL path), resolved to its BDDL file, init-state file, the instruction
//! the agent sees and the evaluator that judges it.
use std::path::{Path, PathBuf};

use libero_sim::AssetPaths;
use libero_tasks::pool::Runs;
use libero_tasks::{Catalog, Pool};
use libero_tasks::catalog::CheckerSpec;

use crate::EpisodeError;

/// What the catalog fixes for a release task.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SuiteTask {
    /// `T16`.
    pub id: String,
    pub name: String,
    /// Evaluator type and private parameters.
    pub checker: CheckerSpec,
    /// Row of the init-state file the release uses (overrides the request's index).
    pub init_index: usize,
    /// Placement seed fixed by the task (RoboMemArena: 100), else the episode seed is used.
    pub placement_seed: Option<u32>,
    /// Zero-action control steps that turn the seeded placement into the start state (catalog `init`).
    pub init_settle_steps: u32,
    /// Object poses set on the placement before those settle steps (catalog `init.poses_in_body`).
    pub init_poses_in_body: Vec<libero_tasks::catalog::PoseInBody>,
    /// `vlabench_physical`: settle on the ordinary reset, then restore the start state, no settle after (§4.2).
    pub settle_before_restore: bool,
}

/// A resolved task. Private: the BDDL path and init file never reach the workspace.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TaskSource {
    /// What the user asked for, e.g. `libero_object/pick_up_the_ketchup_and_place_it_in_the_basket`.
    pub task_ref: String,
    pub bddl: PathBuf,
    /// `.pruned_init` file when the task has trusted init states.
    pub init_states: Option<PathBuf>,
    /// LIBERO benchmark `language` (filename-derived, §9.3), whitespace-normalised.
    pub instruction: String,
    /// Set for release tasks; stock tasks are judged by their BDDL goal on the final state (`bddl_terminal`).
    pub suite: Option<SuiteTask>,
    /// The reference image published with every observation (protocol §3.9; T22's goal image).
    pub task_reference: Option<PathBuf>,
    /// Set only for a demonstration's source episode: the same scene and evaluator drawn as a different layout, so
    /// a demonstration never comes from the configuration it is shown in (issue 31). Recorded in the episode
    /// record, so replays rebuild the same world.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub layout: Option<LayoutVariant>,
}

/// How a demonstration's source episode differs from the task's release configuration: another placement seed
/// (seeded-placement tasks), another row of the init-state file (tasks with trusted init states), and table
/// regions widened on every side (for tasks whose regions are so narrow that every seed gives the same layout).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayoutVariant {
    pub placement_seed: u32,
    pub init_index: usize,
    /// Added to every side of every table region before placement, metres (0 keeps the task's regions).
    #[serde(default)]
    pub region_margin_m: f64,
    /// Every table region moved by this `(x, y)`, metres: with the target's own seed, the whole sampled scene
    /// moves rigidly relative to the robot (its relative layout stays one the task's expert knows).
    #[serde(default)]
    pub scene_shift_m: [f64; 2],
    /// Added to both ends of every table region's yaw interval before placement, radians (0 keeps the task's):
    /// objects and fixtures turn as well as move, so no one offset lines a replayed path up with all of them.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub yaw_margin_rad: f64,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

/// Largest yaw widening a layout variant may ask for.
pub const MAX_YAW_MARGIN_RAD: f64 = 0.8;

/// Largest region widening a layout variant may ask for (beyond it objects leave the reachable table).
pub const MAX_REGION_MARGIN_M: f64 = 0.10;

impl LayoutVariant {
    /// A variant is usable only with a finite margin in `[0, MAX_REGION_MARGIN_M]` and a shift of at most that
    /// much per axis.
    pub fn validate(&self) -> Result<(), EpisodeError> {
        if !(self.region_margin_m.is_finite() && (0.0..=MAX_REGION_MARGIN_M).contains(&self.region_margin_m)) {
            return Err(EpisodeError::Task(format!(
                "layout region_margin_m must lie in [0, {MAX_REGION_MARGIN_M}] m, not {}",
                self.region_margin_m
            )));
        }
        if !self.scene_shift_m.iter().all(|d| d.is_finite() && d.abs() <= MAX_REGION_MARGIN_M) {
            return Err(EpisodeError::Task(format!(
                "layout scene_shift_m components must lie in [-{MAX_REGION_MARGIN_M}, {MAX_REGION_MARGIN_M}] m, not {:?}",
                self.scene_shift_m
            )));
        }
        if !(self.yaw_margin_rad.is_finite() && (0.0..=MAX_YAW_MARGIN_RAD).contains(&self.yaw_margin_rad)) {
            return Err(EpisodeError::Task(format!(
                "layout yaw_margin_rad must lie in [0, {MAX_YAW_MARGIN_RAD}] rad, not {}",
                self.yaw_margin_rad
            )));
        }
        Ok(())
    }
}

/// The physical configuration an episode starts from: what decides its layout, whatever the request said. Two
/// episodes of one task with equal layouts start from the same state (the level only changes what is published).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct EffectiveLayout {
    /// Seed of LIBERO's reset placement.
    pub placement_seed: u32,
    /// Row of the init-state file, `None` when the task starts from its placement.
    pub init_index: Option<usize>,
    pub region_margin_m: f64,
    pub scene_shift_m: [f64; 2],
    #[serde(skip_serializing_if = "is_zero")]
    pub yaw_margin_rad: f64,
}

impl TaskSource {
    /// The layout an episode of this task with request `seed` and `init_index` starts from: the task's fixed
    /// placement seed and init row where the catalog fixes them, a demonstration source's variant where set.
    pub fn effective_layout(&self, seed: u64, init_index: usize) -> Result<EffectiveLayout, EpisodeError> {
        let suite = self.suite.as_ref();
        if let Some(v) = &self.layout {
            v.validate()?;
            return Ok(EffectiveLayout {
                placement_seed: v.placement_seed,
                init_index: self.init_states.is_some().then_some(v.init_index),
                region_margin_m: v.region_margin_m,
                scene_shift_m: v.scene_shift_m,
                yaw_margin_rad: v.yaw_margin_rad,
            });
        }
        let placement_seed = match suite.and_then(|s| s.placement_seed) {
            Some(fixed) => fixed,
            None => u32::try_from(seed).map_err(|_| EpisodeError::Task("seed must fit in 32 bits".into()))?,
        };
        let init_index = suite.map_or(init_index, |s| s.init_index);
        let init_index = self.init_states.is_some().then_some(init_index);
        Ok(EffectiveLayout { placement_seed, init_index, region_margin_m: 0.0, scene_shift_m: [0.0; 2], yaw_margin_rad: 0.0 })
    }
}

/// Resolves `id`: `T01`…`T30` (suite tasks), `suite/name` (a stock LIBERO file), `suite/task_id` or `suite/name` of a
/// pool entry (`tasks/pool.json`), or a path to a `.bddl` file.
pub fn resolve_task(id: &str, paths: &AssetPaths) -> Result<TaskSource, EpisodeError> {
    let id = id.trim();
    if id.len() == 3 && id.starts_with(['T', 't']) && id[1..].chars().all(|c| c.is_ascii_digit()) {
        return resolve_suite_task(id, paths);
    }
    let as_path = Path::new(id);
    if id.ends_with(".bddl") && as_path.is_file() {
        return Ok(from_bddl_path(id, as_path, paths));
    }
    let (suite, name) = id
        .split_once('/')
        .filter(|(s, n)| !s.is_empty() && !n.is_empty() && !n.contains('/') && !s.contains(".."))
        .ok_or_else(|| {
            EpisodeError::Task(format!(
                "unknown task {id:?}: expected T01–T30, <suite>/<task id or name> (`tasks list --tasks all`) or a .bddl path"
            ))
        })?;
    let name = name.strip_suffix(".bddl").unwrap_or(name);
    let stock_suite = libero_tasks::pool::STOCK_SUITES.contains(&suite);
    if !stock_suite || name.chars().all(|c| c.is_ascii_digit()) {
        return resolve_pool_entry(&format!("{suite}/{name}"), paths);
    }
    let bddl = paths.stock_bddl(suite, name);
    if !bddl.is_file() {
        return Err(EpisodeError::Task(format!("no stock LIBERO task {suite}/{name} ({} is missing)", bddl.display())));
    }
    let init = paths.stock_init(suite, name);
    Ok(TaskSource {
        task_ref: format!("{suite}/{name}"),
        instruction: libero_bddl::language_from_filename(name),
        init_states: init.is_file().then_some(init),
        bddl,
        suite: None,
        task_reference: None,
        layout: None,
    })
}

/// A pool entry (`tasks/pool.json`): a stock entry runs its stock files (as `suite/name`); any other runs on the
/// release task it names, with its own registered instruction; excluded and unimplemented entries say why.
fn resolve_pool_entry(id: &str, paths: &AssetPaths) -> Result<TaskSource, EpisodeError> {
    let task_err = |e: libero_tasks::TasksError| EpisodeError::Task(e.to_string());
    let pool = Pool::discover().map_err(task_err)?;
    let entry = pool.lookup(id).map_err(EpisodeError::Task)?;
    match pool.runs(entry, paths).map_err(task_err)? {
        Runs::Stock => resolve_task(&entry.reference(), paths),
        Runs::Release(release) => {
            let mut source = resolve_suite_task(release, paths)?;
            if source.instruction != entry.instruction {
                // same scene and evaluator, the entry's own language: recorded under the entry's name
                source.task_ref = entry.reference();
                source.instruction = entry.instruction.clone();
            }
            Ok(source)
        }
        Runs::Own(files, checker) => {
            let id = entry.reference();
            Ok(source_from_files(&id, &entry.name, &entry.instruction, checker, files))
        }
    }
}

/// `T11`…`T30` through the catalog; unimplemented tasks fail with the catalog's reason.
fn resolve_suite_task(id: &str, paths: &AssetPaths) -> Result<TaskSource, EpisodeError> {
    let catalog = Catalog::discover().map_err(|e| EpisodeError::Task(e.to_string()))?;
    let entry = catalog.get(id).ok_or_else(|| EpisodeError::Task(format!("no release task {id}: expected T01–T30")))?;
    let files = catalog.files(entry, paths).map_err(|e| EpisodeError::Task(e.to_string()))?;
    Ok(suite_task_source(entry, files))
}

/// The source of a catalog task from its resolved files.
pub fn suite_task_source(entry: &libero_tasks::TaskEntry, files: libero_tasks::catalog::TaskFiles) -> TaskSource {
    source_from_files(&entry.id, &entry.name, entry.agent_instruction(), entry.checker.clone(), files)
}

/// A task judged by its own evaluator (a release task or a pool entry's own definition), recorded as `id`.
fn source_from_files(
    id: &str,
    name: &str,
    instruction: &str,
    checker: CheckerSpec,
    files: libero_tasks::catalog::TaskFiles,
) -> TaskSource {
    TaskSource {
        task_ref: id.to_owned(),
        bddl: files.bddl,
        init_states: files.init_states,
        instruction: instruction.to_owned(),
        suite: Some(SuiteTask {
            id: id.to_owned(),
            name: name.to_owned(),
            checker,
            init_index: files.init_index,
            placement_seed: files.placement_seed,
            init_settle_steps: files.init_settle_steps,
            init_poses_in_body: files.init_poses_in_body,
            settle_before_restore: files.settle_before_restore,
        }),
        task_reference: files.task_reference.map(|(path, _)| path),
        layout: None,
    }
}

fn from_bddl_path(id: &str, path: &Path, paths: &AssetPaths) -> TaskSource {
    let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    // A stock file given by path still gets its stock init states.
    let suite = path.parent().and_then(|p| p.file_name()).map(|s| s.to_string_lossy().into_owned());
    let init = suite.map(|s| paths.stock_init(&s, &stem)).filter(|p| p.is_file());
    TaskSource {
        task_ref: id.to_owned(),
        bddl: path.to_path_buf(),
        init_states: init,
        instruction: libero_bddl::language_from_filename(&stem),
        suite: None,
        task_reference: None,
        layout: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stock_tasks_resolve_to_bddl_init_and_filename_language() {
        let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
        let t = resolve_task("libero_90/KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet", &paths).unwrap();
        assert!(t.bddl.is_file());
        assert!(t.init_states.as_ref().is_some_and(|p| p.is_file()));
        assert_eq!(t.instruction, "close the top drawer of the cabinet");
        let by_path = resolve_task(t.bddl.to_str().unwrap(), &paths).unwrap();
        assert_eq!(by_path.init_states, t.init_states);
        assert!(resolve_task("libero_90/no_such_task", &paths).is_err());
        assert!(resolve_task("../etc/passwd", &paths).is_err());
    }

    #[test]
    fn release_tasks_resolve_through_the_catalog_and_unimplemented_entries_say_why() {
        let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
        let t16 = resolve_task("T16", &paths).unwrap();
        assert!(t16.bddl.ends_with("libero_90/KITCHEN_SCENE7_open_the_microwave.bddl"));
        assert!(t16.init_states.as_ref().is_some_and(|p| p.is_file()));
        assert_eq!(t16.instruction, "open the microwave");
        let suite = t16.suite.expect("catalog entry");
        assert_eq!((suite.id.as_str(), suite.checker.kind.as_str(), suite.init_index), ("T16", "bddl_terminal", 0));
        let t12 = resolve_task("t12", &paths).unwrap();
        assert!(t12.bddl.is_file() && t12.init_states.is_none(), "pruned T12 starts from the seeded placement");
        let catalog = Catalog::discover().unwrap();
        // every release task is implemented now: an entry marked otherwise must still refuse with its reason
        let mut missing = catalog.get("T30").expect("T30").clone();
        missing.implemented = false;
        missing.not_implemented_reason = Some("the seesaw is being rebuilt".into());
        let err = catalog.files(&missing, &paths).unwrap_err().to_string();
        assert!(err.contains("T30 (basic_seesaw_usage) is not implemented in this build: the seesaw is being rebuilt"), "{err}");
        assert!(resolve_task("T31", &paths).unwrap_err().to_string().contains("no release task T31"));
    }

    #[test]
    fn pool_entries_resolve_by_id_or_name_and_refuse_with_their_reason() {
        let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
        let by_id = resolve_task("libero_90/35", &paths).unwrap();
        assert_eq!(by_id, resolve_task("libero_90/KITCHEN_SCENE7_open_the_microwave", &paths).unwrap());
        assert_eq!((by_id.task_ref.as_str(), by_id.suite.is_none()), ("libero_90/KITCHEN_SCENE7_open_the_microwave", true));
        // the release entry itself runs as its release task
        let cola = resolve_task("perception_v2/6", &paths).unwrap();
        assert_eq!(cola, resolve_task("T07", &paths).unwrap());
        assert_eq!(resolve_task("vlabench_world_knowledge/select_cola_drink", &paths).unwrap(), cola);
        // a re-used scene with its own registered language keeps its name
        let marker = resolve_task("vlabench_perception/0", &paths).unwrap();
        let t01 = resolve_task("T01", &paths).unwrap();
        assert_eq!((marker.task_ref.as_str(), marker.bddl == t01.bddl), ("vlabench_perception/select_upright_marker", true));
        assert_eq!(marker.suite.as_ref().map(|s| s.id.as_str()), Some("T01"));
        assert!(marker.instruction.starts_with("Pick up the upright marker, rather than a fallen marker"));
        assert_eq!(resolve_task(&marker.task_ref, &paths).unwrap(), marker, "an episode record re-resolves");
        let err = resolve_task("vlabench_world_knowledge/8", &paths).unwrap_err().to_string();
        assert!(err.contains("select_banana_fruit") && err.contains("excluded") && err.contains("banana"), "{err}");
        assert!(resolve_task("long_horizon_v2/2", &paths).is_ok(), "the coffee machine runs on a definition of its own");
        let err = resolve_task("libero_90/90", &paths).unwrap_err().to_string();
        assert!(err.contains("0–89"), "{err}");
    }
}
