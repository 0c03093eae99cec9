//! The last expert sweep of the pool (`libero-agent expert --all`: `tasks/results/expert_sweep.jsonl`
//! and its `expert_sweep.meta.json`), as the Tasks page and the task pages show it: "expert: solved 3/3 on
//! 2026-11-27 at b63b099". Read on demand and kept until either file's modification time changes, so a new sweep
//! shows without a restart; a missing or unreadable file shows nothing (it is a note, not a page's reason to fail).
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use libero_records::expert_sweep::{ExpertSweepMeta, ExpertSweepRow};

/// The sweep file under the tasks folder (`$LIBERO_AGENT_TASKS_DIR`, else the repository's `tasks/`).
fn sweep_path() -> PathBuf {
    libero_tasks::catalog::tasks_dir().join("results").join("expert_sweep.jsonl")
}

/// `expert_sweep.jsonl` → `expert_sweep.meta.json` (as `expert --all` writes it).
fn meta_path(sweep: &Path) -> PathBuf {
    sweep.with_file_name("expert_sweep.meta.json")
}

fn modified(path: &Path) -> Option<SystemTime> {
    std::fs::metadata(path).and_then(|m| m.modified()).ok()
}

/// The files' identity a cached reading stands for.
type Stamp = (PathBuf, Option<SystemTime>, Option<SystemTime>);

/// The line per task: keyed by the expert's task id (`T14`, `libero_90/<NAME>`) and by the pool address.
type Lines = Arc<HashMap<String, String>>;

/// The last reading and the files' identity it stands for.
static CACHE: Mutex<Option<(Stamp, Lines)>> = Mutex::new(None);

/// "solved 3/3 on 2026-11-27 at b63b099" for a sweep row (no expert, an error, or a failure say so instead).
fn line_of(row: &ExpertSweepRow, date: &str, commit: &str) -> String {
    let runs = row.runs.unwrap_or(0);
    let what = if row.expert == Some(false) {
        "no plan for its goal".to_owned()
    } else if row.has_error() {
        "the run failed with an error".to_owned()
    } else {
        format!("solved {}/{runs}", row.successes.unwrap_or(0))
    };
    let mut line = what;
    if !date.is_empty() {
        line.push_str(&format!(" on {date}"));
    }
    if !commit.is_empty() {
        line.push_str(&format!(" at {commit}"));
    }
    line
}

/// Reads the sweep and its metadata; `None` when there is no readable sweep.
fn read(sweep: &Path) -> Option<HashMap<String, String>> {
    let text = std::fs::read_to_string(sweep).ok()?;
    let meta: ExpertSweepMeta =
        std::fs::read_to_string(meta_path(sweep)).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or_default();
    let date: String = meta.date_utc.as_deref().unwrap_or("").chars().take(10).collect();
    let commit = meta.commit.as_deref().unwrap_or("");
    let mut lines = HashMap::new();
    for row in text.lines().filter_map(|l| serde_json::from_str::<ExpertSweepRow>(l).ok()) {
        // a row re-run by `expert --tasks … --update` carries its own date and commit
        let row_date: String = row.date_utc.as_deref().map_or_else(|| date.clone(), |d| d.chars().take(10).collect());
        let line = line_of(&row, &row_date, row.commit.as_deref().unwrap_or(commit));
        for key in [&row.task, &row.entry].into_iter().flatten() {
            lines.insert(key.clone(), line.clone());
        }
    }
    Some(lines)
}

/// The sweep's lines as of now (re-read when the files changed).
fn current() -> Lines {
    let sweep = sweep_path();
    let stamp = (sweep.clone(), modified(&sweep), modified(&meta_path(&sweep)));
    let Ok(mut cache) = CACHE.lock() else { return Arc::default() };
    if let Some((_, lines)) = cache.as_ref().filter(|(s, _)| *s == stamp) {
        return lines.clone();
    }
    let lines = Arc::new(read(&sweep).unwrap_or_default());
    *cache = Some((stamp, lines.clone()));
    lines
}

/// What the last sweep says of the first of `ids` it has (a task id, a pool address, a task reference), or "".
pub fn expert_line(ids: &[&str]) -> String {
    let lines = current();
    ids.iter().find_map(|id| lines.get(*id).cloned()).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn row(v: serde_json::Value) -> ExpertSweepRow {
        ExpertSweepRow::from_value(v).unwrap()
    }

    #[test]
    fn rows_read_as_solved_counts_with_the_sweeps_date_and_commit() {
        assert_eq!(line_of(&row(json!({"runs": 3, "successes": 2, "expert": true})), "2026-11-27", "b63b099"), "solved 2/3 on 2026-11-27 at b63b099");
        assert_eq!(line_of(&row(json!({"runs": 0, "expert": false})), "", ""), "no plan for its goal");
        assert_eq!(line_of(&row(json!({"runs": 3, "expert": true, "error": "boom"})), "2026-11-27", ""), "the run failed with an error on 2026-11-27");
        assert_eq!(line_of(&row(json!({"runs": 3, "successes": 3, "expert": true, "error": null})), "", ""), "solved 3/3", "a null error is none");
    }

    #[test]
    fn a_row_re_run_by_an_update_shows_its_own_date_and_commit() {
        let dir = tempfile::tempdir().unwrap();
        let sweep = dir.path().join("expert_sweep.jsonl");
        let rows = [
            json!({"task": "T06", "entry": "vlabench_button/1", "runs": 3, "successes": 3, "expert": true}),
            json!({"task": "T10", "runs": 3, "successes": 3, "expert": true, "date_utc": "2026-11-29T01:02:03Z", "commit": "abc1234"}),
        ];
        std::fs::write(&sweep, rows.iter().map(|r| format!("{r}\n")).collect::<String>()).unwrap();
        std::fs::write(meta_path(&sweep), r#"{"date_utc": "2026-11-28T04:09:45Z", "commit": "95cdfa6", "runs": 3}"#).unwrap();
        let lines = read(&sweep).unwrap();
        assert_eq!(lines["T06"], "solved 3/3 on 2026-11-28 at 95cdfa6");
        assert_eq!(lines["vlabench_button/1"], lines["T06"]);
        assert_eq!(lines["T10"], "solved 3/3 on 2026-11-29 at abc1234");
    }

    /// The golden sweep (every row shape the sweep writes, an older row with `wall_time_s` and an older table's
    /// summary line) reads as one line per task and per pool entry; the summary line is no task.
    #[test]
    fn the_golden_sweep_reads_as_one_line_per_task_and_entry() {
        let fixtures = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/expert_sweep");
        let dir = tempfile::tempdir().unwrap();
        let sweep = dir.path().join("expert_sweep.jsonl");
        std::fs::copy(fixtures.join("expert_sweep.jsonl"), &sweep).unwrap();
        std::fs::copy(fixtures.join("expert_sweep.meta.json"), meta_path(&sweep)).unwrap();
        let lines = read(&sweep).unwrap();
        assert_eq!(lines["T01"], "solved 3/3 on 2026-11-29 at bfc58d2");
        assert_eq!(lines["libero_90/89"], "solved 0/1 on 2026-11-29 at bfc58d2");
        assert_eq!(lines["T03"], "solved 1/2 on 2026-11-29 at bfc58d2");
        assert_eq!(lines["libero_90/3"], "no plan for its goal on 2026-11-29 at bfc58d2");
        assert_eq!(lines["T07"], "the run failed with an error on 2026-11-29 at bfc58d2");
        assert_eq!(lines["long_horizon_v2/place_mug_and_brew_coffee"], "solved 3/3 on 2026-11-29 at bfc58d2");
        assert_eq!(lines.len(), 8, "six tasks and two pool entries: {lines:?}");
    }
}
