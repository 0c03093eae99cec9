//! The demonstration library: `<root>/<task>/<source episode id>/`, one library bundle each. Episodes with a
//! demonstration condition take a valid, verified bundle of their task from here.
use std::path::{Path, PathBuf};

use super::*;

/// Directory name of a task in the library (`T14`; `suite/name` and paths become safe names).
pub fn task_dir_name(task_ref: &str) -> String {
    task_ref.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect()
}

pub fn task_dir(root: &Path, task_ref: &str) -> PathBuf {
    root.join(task_dir_name(task_ref))
}

/// Where a new bundle of `episode_id` goes.
pub fn bundle_dir(root: &Path, task_ref: &str, episode_id: &str) -> PathBuf {
    task_dir(root, task_ref).join(task_dir_name(episode_id))
}

/// The first (by name, i.e. oldest episode id) valid and verified bundle of `task_ref`, skipping bundles recorded
/// from `exclude_episode` (a demonstration must come from a separate episode). Invalid bundles are skipped with a
/// log line, never used.
pub fn find_verified(root: &Path, task_ref: &str, exclude_episode: Option<&str>) -> Option<PathBuf> {
    let dir = task_dir(root, task_ref);
    let mut entries: Vec<PathBuf> = std::fs::read_dir(&dir).ok()?.flatten().map(|e| e.path()).collect();
    entries.sort();
    entries.into_iter().filter(|p| p.is_dir() && !p.to_string_lossy().ends_with(".partial")).find(|p| {
        let violations = validate_bundle(p);
        if !violations.is_empty() {
            log::warn!("demo library: skipping {} ({} violations, first: {})", p.display(), violations.len(), violations[0]);
            return false;
        }
        let Ok(m) = read_json(&p.join(MANIFEST)) else { return false };
        m["verification"]["verified"] == true
            && m["task"]["id"] == task_ref
            && exclude_episode.is_none_or(|e| m["source"]["episode_id"] != e)
    })
}
