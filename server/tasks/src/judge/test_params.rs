//! Test fixtures: a task's checker params as the manifest (or the pool's own definitions) gives them, the one source
//! of every threshold, so unit tests judge with the values the tasks run with instead of restating them.
use std::path::PathBuf;

fn tasks_dir() -> PathBuf {
    std::env::var_os("LIBERO_AGENT_TASKS_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tasks"))
}

fn read<T: serde::de::DeserializeOwned>(file: &str) -> T {
    let path = tasks_dir().join(file);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("read {}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("parse {}: {e}", path.display()))
}

/// What these fixtures read of `manifest.json` and `pool.json`: the few keys of their own (the crate's full types live
/// in `catalog` and `pool`, which the checkers this module serves are below: reading through them closed an import
/// circle).
#[derive(serde::Deserialize)]
struct Manifest {
    tasks: Vec<ManifestTask>,
}

#[derive(serde::Deserialize)]
struct ManifestTask {
    id: String,
    checker: Checker,
}

#[derive(serde::Deserialize)]
struct Checker {
    #[serde(default)]
    params: serde_json::Value,
}

#[derive(serde::Deserialize)]
struct PoolEntries {
    entries: Vec<PoolEntry>,
}

#[derive(serde::Deserialize)]
struct PoolEntry {
    suite: String,
    name: String,
    definition: Option<Definition>,
}

#[derive(serde::Deserialize)]
struct Definition {
    #[serde(default)]
    checker_params: serde_json::Value,
}

/// `checker.params` of release task `task` (`T20`), or `definition.checker_params` of pool entry `suite/name`.
pub(crate) fn checker_params(task: &str) -> serde_json::Value {
    let found = match task.split_once('/') {
        None => read::<Manifest>("manifest.json").tasks.into_iter().find(|t| t.id == task).map(|t| t.checker.params),
        Some((suite, name)) => read::<PoolEntries>("pool.json")
            .entries
            .into_iter()
            .find(|e| e.suite == suite && e.name == name)
            .map(|e| e.definition.map(|d| d.checker_params).unwrap_or_default()),
    };
    found.unwrap_or_else(|| panic!("no checker params for {task}"))
}

/// [`checker_params`] as the kind's typed struct.
pub(crate) fn parsed<T: serde::de::DeserializeOwned>(task: &str) -> T {
    serde_json::from_value(checker_params(task)).unwrap_or_else(|e| panic!("{task}'s checker params: {e}"))
}
