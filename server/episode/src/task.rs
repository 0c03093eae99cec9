//! Which task an episode runs: a stock LIBERO task (`suite/name` or a BDDL path) resolved to its BDDL file,
//! init-state file and the instruction LIBERO's benchmark shows (derived from the file name).
use std::path::{Path, PathBuf};

use libero_sim::AssetPaths;

use crate::EpisodeError;

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
}

/// Resolves `id`: `T01`…`T30` (suite tasks), `suite/name` (stock LIBERO) or a path to a `.bddl` file.
pub fn resolve_task(id: &str, paths: &AssetPaths) -> Result<TaskSource, EpisodeError> {
    let id = id.trim();
    if id.len() == 3 && id.starts_with(['T', 't']) && id[1..].chars().all(|c| c.is_ascii_digit()) {
        return Err(EpisodeError::Task(format!(
            "suite task {id} needs the task catalog (tasks/ manifest and server/tasks), which this build does not \
have yet; use a stock LIBERO task such as libero_object/pick_up_the_ketchup_and_place_it_in_the_basket"
        )));
    }
    let as_path = Path::new(id);
    if id.ends_with(".bddl") && as_path.is_file() {
        return Ok(from_bddl_path(id, as_path, paths));
    }
    let (suite, name) = id
        .split_once('/')
        .filter(|(s, n)| !s.is_empty() && !n.is_empty() && !n.contains('/') && !s.contains(".."))
        .ok_or_else(|| {
            EpisodeError::Task(format!("unknown task {id:?}: expected T01–T30, <suite>/<task name> or a .bddl path"))
        })?;
    let name = name.strip_suffix(".bddl").unwrap_or(name);
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
    })
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
        let err = resolve_task("T11", &paths).unwrap_err().to_string();
        assert!(err.contains("task catalog"), "{err}");
    }
}
