//! Branches (issue 33): an episode that starts from another episode's state at one of its control steps. The
//! parent's executed actions are replayed to that step on the same task, seed, init state and layout (the
//! determinism contract makes the state bit-identical, and the evaluator observes the replay, so stages reached
//! stay reached). The branch's run directory keeps the replayed actions (`branch_prefix.jsonl`, one action a
//! line), so a branch replays on its own, and a branch of a branch needs only its parent's directory; the
//! branch's `actions.jsonl` begins with a `branch_from` line saying where it branched, whose `execution`
//! covers the replayed control steps (the review's timeline shows them as one span).
use std::io::Write;
use std::path::PathBuf;

use serde_json::json;

use crate::call::MicroAction;
use libero_records::records::{ActionLog, RunDir};

/// The replayed actions of a branch, in its run directory.
pub const PREFIX_FILE: &str = "branch_prefix.jsonl";
/// The `command` of the first line of a branch's `actions.jsonl`.
pub const BRANCH_COMMAND: &str = "branch_from";

/// Where a branch's replayed actions are kept.
pub fn prefix_path(run: &RunDir) -> PathBuf {
    run.root.join(PREFIX_FILE)
}

/// Writes `actions` (the parent's first control steps) into the branch's run directory, one JSON array a line.
/// `serde_json` writes each `f64` so that it reads back bit for bit.
pub fn write_prefix(run: &RunDir, actions: &[MicroAction]) -> std::io::Result<()> {
    let path = prefix_path(run);
    let mut file = std::fs::OpenOptions::new().write(true).create_new(true).open(&path)?;
    file.write_all(prefix_text(actions)?.as_bytes())?;
    file.sync_data()
}

/// The prefix file's text: one JSON array a line (a demonstration bundle of a branch keeps the same file).
pub fn prefix_text(actions: &[MicroAction]) -> std::io::Result<String> {
    let mut text = String::with_capacity(actions.len() * 80);
    for a in actions {
        text.push_str(&serde_json::to_string(a).map_err(std::io::Error::other)?);
        text.push('\n');
    }
    Ok(text)
}

/// The replayed actions of the episode in `run` (none for an episode that is not a branch).
pub fn read_prefix(run: &RunDir) -> Result<Vec<MicroAction>, String> {
    read_prefix_file(&prefix_path(run))
}

/// The actions of a prefix file at `path` (none when there is no such file).
pub fn read_prefix_file(path: &std::path::Path) -> Result<Vec<MicroAction>, String> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(format!("{}: {e}", path.display())),
    };
    text.lines()
        .enumerate()
        .map(|(n, line)| {
            serde_json::from_str::<MicroAction>(line).map_err(|e| format!("{} line {}: not an action: {e}", path.display(), n + 1))
        })
        .collect()
}

/// Writes the first line of a branch's `actions.jsonl`: where it branched and the control steps replayed.
pub fn log_branch_point(run: &RunDir, parent: &str, step: u64) -> std::io::Result<()> {
    let mut log = ActionLog::open(&run.actions_jsonl())?;
    let request = json!({"command": BRANCH_COMMAND, "parent_episode_id": parent, "parent_control_step": step});
    let response = json!({
        "ok": true,
        "replayed_actions": step,
        "execution": {"command_completed": true, "termination_reason": "parent_actions_replayed", "control_steps": step},
    });
    log.append(&request, &response, 1)
}

/// The `branch` object of an episode record: `{"parent_episode_id", "parent_control_step"}` or null.
pub fn record_branch(record: &libero_records::records::EpisodeRecord) -> Option<(String, u64)> {
    let b = record.branch.as_ref()?;
    Some((b.parent_episode_id.clone()?, b.parent_control_step?))
}
