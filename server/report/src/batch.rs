//! Reading a batch directory: `batch.json` (settings, their hash, harness version, status and counts),
//! `rollouts.jsonl` (one [`RolloutRecord`] per ended rollout) and `rollouts/<rollout_id>/` (logs, harness manifest,
//! usage). The runner writes them; `report`, the Results page and the annotation page read them through
//! [`load_batch`] (or [`LoadedBatch::from_stored`] for a batch in the store) and [`metrics_rollouts`].
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use libero_metrics::{Outcome, PoolRollout, Rollout, Split};
use libero_records::batch_doc::{BatchDoc, HarnessVersion};
use libero_records::records::RunResult;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::usage::Usage;

pub const BATCH_SCHEMA: &str = "libero_agent.batch.v1";
pub const ROLLOUT_SCHEMA: &str = "libero_agent.rollout.v1";

/// Why a batch could not be read.
#[derive(Debug, thiserror::Error)]
pub enum BatchError {
    #[error("{} is not a batch directory: {error}", dir.display())]
    NotABatch { dir: PathBuf, error: std::io::Error },
    #[error("{} is not JSON: {error}", path.display())]
    NotJson { path: PathBuf, error: serde_json::Error },
    #[error("cannot read {}: {error}", path.display())]
    Read { path: PathBuf, error: std::io::Error },
    /// `batch.json` (or the store's batch document) of another schema.
    #[error("{what}: schema_version {found}, expected {BATCH_SCHEMA}")]
    Schema { what: String, found: String },
    #[error("batch {batch} in the store: a rollout record is not one: {error}")]
    StoredRecord { batch: String, error: serde_json::Error },
}

/// Demonstration condition of a rollout (protocol §7.1; paper: None / Video / Video + Traj.).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Demo {
    None,
    Video,
    VideoTraj,
}

impl Demo {
    pub fn as_str(self) -> &'static str {
        match self {
            Demo::None => "none",
            Demo::Video => "video",
            Demo::VideoTraj => "video_traj",
        }
    }
}

/// One ended rollout (a line of `rollouts.jsonl`). Never holds a credential or an episode token.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RolloutRecord {
    pub schema_version: String,
    pub rollout_id: String,
    pub task: String,
    pub task_number: u32,
    /// The paper's split; `None` for a pool task that is not a release task.
    pub split: Option<Split>,
    /// The pool suite of a `pool` experiment's rollout; such rollouts are reported per suite, never in the
    /// paper's tables.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub suite: Option<String>,
    pub stage_count: u32,
    pub repetition: u32,
    pub level: u8,
    pub demo: Demo,
    pub outcome: Outcome,
    pub episode_id: Option<String>,
    pub workspace: Option<PathBuf>,
    pub run_dir: Option<PathBuf>,
    pub result_status: Option<String>,
    pub success: Option<bool>,
    pub termination_reason: Option<String>,
    /// Why the rollout is INVALID/WATCHDOG_TIMEOUT (harness exit, API failure, supervision timeout, …).
    pub infrastructure_error: Option<String>,
    /// Episode time from `start_episode` (`result.wall_time_seconds`).
    pub wall_time_s: Option<f64>,
    /// The whole agent process, launch to exit.
    pub harness_elapsed_s: Option<f64>,
    pub accepted_agent_steps: Option<u64>,
    pub completed_stages: Option<u32>,
    pub judgment_correct: Option<bool>,
    pub agent_exit_code: Option<i32>,
    pub usage: Option<Usage>,
    pub started_at: String,
    pub finished_at: String,
    /// The `libero-agent worker` that ran a queued rollout.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub worker: Option<String>,
    /// Where a queued rollout's run directory is in the artifact store (`<artifacts URL>/runs/<episode id>`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub artifacts: Option<String>,
    /// `--version` of the harness CLI this rollout launched, probed just before its launch (absent for `command`,
    /// for a rollout that ended before its launch, and in records written before rollouts were probed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub harness_version: Option<HarnessVersion>,
}

impl RolloutRecord {
    /// Why the rollout did not count (INVALID, INTERRUPTED) or was stopped by the watchdog: the runner's
    /// infrastructure error, else the episode's termination reason, else what is known. `None` for the other
    /// outcomes.
    pub fn reason(&self) -> Option<String> {
        if !matches!(self.outcome, Outcome::Invalid | Outcome::Interrupted | Outcome::WatchdogTimeout) {
            return None;
        }
        Some(match (&self.infrastructure_error, &self.termination_reason, &self.result_status) {
            (Some(e), _, _) => e.clone(),
            (None, Some(t), _) => format!("the episode ended: {t}"),
            (None, None, Some(s)) => format!("the episode's result is {s:?}, with no reason given"),
            (None, None, None) => "no reason recorded".to_owned(),
        })
    }

    /// Gives an INVALID rollout that names no reason (no infrastructure error, no termination reason) one: the
    /// reason its episode's result records (the private run directory, written by the server), else what is
    /// missing. Every INVALID record then says why, in `rollouts.jsonl`, the store, `report` and the Results page.
    pub fn ensure_reason(&mut self) {
        if self.outcome != Outcome::Invalid || self.infrastructure_error.is_some() || self.termination_reason.is_some() {
            return;
        }
        let recorded = self.run_dir.as_deref().and_then(result_reason);
        self.infrastructure_error = Some(recorded.unwrap_or_else(|| match (&self.episode_id, &self.result_status) {
            (None, _) => "no episode was prepared for this rollout".to_owned(),
            (Some(id), None) => format!("no result was found for episode {id}"),
            (Some(id), Some(s)) => format!("episode {id} ended {s:?} without a reason"),
        }));
    }

    /// The rollout as the paper's metrics see it; `None` for a pool rollout.
    pub fn to_metrics(&self) -> Option<Rollout> {
        if self.suite.is_some() {
            return None;
        }
        Some(Rollout {
            task_number: self.task_number,
            split: self.split?,
            repetition: self.repetition,
            outcome: self.outcome,
            judgment_correct: self.judgment_correct,
            completed_stages: self.completed_stages,
            stage_count: self.stage_count,
            wall_time_s: self.wall_time_s,
            total_tokens: self.usage.as_ref().and_then(|u| u.total_tokens),
            accepted_agent_steps: self.accepted_agent_steps,
        })
    }

    /// The rollout as the pool summary sees it; `None` outside the pool experiment.
    pub fn to_pool(&self) -> Option<PoolRollout> {
        Some(PoolRollout {
            suite: self.suite.clone()?,
            task: self.task.clone(),
            repetition: self.repetition,
            outcome: self.outcome,
            judgment_correct: self.judgment_correct,
            completed_stages: self.completed_stages,
            stage_count: self.stage_count,
            wall_time_s: self.wall_time_s,
        })
    }
}

/// The reason an episode's `result.json` gives for not counting (its infrastructure error, its abort reason).
fn result_reason(run_dir: &Path) -> Option<String> {
    use std::io::Read;
    let mut text = String::new();
    std::fs::File::open(run_dir.join("result.json")).ok()?.take(1 << 20).read_to_string(&mut text).ok()?;
    let result: RunResult = serde_json::from_str(&text).ok()?;
    fn given(s: Option<&str>) -> Option<&str> {
        s.filter(|s| !s.is_empty())
    }
    given(result.infrastructure_error())
        .map(|e| format!("the episode recorded an infrastructure error: {e}"))
        .or_else(|| given(result.reason.as_deref()).map(|r| format!("the episode ended: {r}")))
        .or_else(|| given(result.status.as_deref()).map(|s| format!("the episode's result is {s:?}, with no reason given")))
}

pub fn batch_json(dir: &Path) -> PathBuf {
    dir.join("batch.json")
}
pub fn rollouts_jsonl(dir: &Path) -> PathBuf {
    dir.join("rollouts.jsonl")
}

/// The harnesses a batch can name (the runner's `Harness`), for the names of their rollouts' logs.
pub const HARNESSES: [&str; 6] = ["codex", "claude_code", "kimi_code", "qwen_code", "deepseek", "command"];

/// The name of a rollout's stdout log in `rollouts/<rollout_id>/` (JSON lines where the harness's CLI streams
/// JSON); `None` for a harness not in [`HARNESSES`], whose name is never made into a path.
pub fn stdout_file(harness: &str) -> Option<String> {
    let ext = match harness {
        "claude_code" | "kimi_code" | "qwen_code" | "codex" => "jsonl",
        h if HARNESSES.contains(&h) => "log",
        _ => return None,
    };
    Some(format!("{harness}_stdout.{ext}"))
}

/// The name of a rollout's stderr log in `rollouts/<rollout_id>/`; `None` as for [`stdout_file`].
pub fn stderr_file(harness: &str) -> Option<String> {
    HARNESSES.contains(&harness).then(|| format!("{harness}_stderr.log"))
}

/// Every record of `rollouts.jsonl` (a torn last line from a crash is skipped).
pub fn read_records(dir: &Path) -> Result<Vec<RolloutRecord>, BatchError> {
    let path = rollouts_jsonl(dir);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(error) => return Err(BatchError::Read { path, error }),
    };
    Ok(text.lines().filter_map(|l| serde_json::from_str(l).ok()).collect())
}

/// A batch as the report and the dashboard see it.
#[derive(Debug, Clone, Serialize)]
pub struct LoadedBatch {
    pub dir: PathBuf,
    pub batch: BatchDoc,
    pub records: Vec<RolloutRecord>,
}

impl LoadedBatch {
    pub fn name(&self) -> String {
        self.dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
    }

    /// A batch as the store holds it (`run --store` wrote `batch.json`'s document and the records there), in the
    /// shape [`load_batch`] gives.
    pub fn from_stored(name: &str, dir: PathBuf, doc: Value, records: Vec<Value>) -> Result<Self, BatchError> {
        let batch = BatchDoc::from_value(doc).unwrap_or_default();
        check_schema(&batch, || format!("batch {name} in the store"))?;
        let records = records
            .into_iter()
            .map(serde_json::from_value)
            .collect::<Result<Vec<RolloutRecord>, _>>()
            .map_err(|error| BatchError::StoredRecord { batch: name.to_owned(), error })?;
        Ok(Self { dir, batch, records })
    }
}

fn check_schema(batch: &BatchDoc, what: impl FnOnce() -> String) -> Result<(), BatchError> {
    if batch.schema_version.as_deref() == Some(BATCH_SCHEMA) {
        return Ok(());
    }
    Err(BatchError::Schema { what: what(), found: json!(batch.schema_version).to_string() })
}

/// Reads `batch.json` and `rollouts.jsonl`.
pub fn load_batch(dir: &Path) -> Result<LoadedBatch, BatchError> {
    let path = batch_json(dir);
    let text = std::fs::read_to_string(&path).map_err(|error| BatchError::NotABatch { dir: dir.to_path_buf(), error })?;
    let batch: Value = serde_json::from_str(&text).map_err(|error| BatchError::NotJson { path: path.clone(), error })?;
    // JSON that is no object has no schema_version, and is refused as such.
    let batch = BatchDoc::from_value(batch).unwrap_or_default();
    check_schema(&batch, || path.display().to_string())?;
    Ok(LoadedBatch { dir: dir.to_path_buf(), batch, records: read_records(dir)? })
}

/// A reporting condition: one observation level and demonstration condition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
pub struct Condition {
    pub level: u8,
    pub demo: Demo,
}

/// The batches' rollouts for the metrics, grouped by (agent, condition); the agent is `harness/model`.
pub fn metrics_rollouts(batches: &[LoadedBatch]) -> BTreeMap<(String, Condition), Vec<Rollout>> {
    let mut out: BTreeMap<(String, Condition), Vec<Rollout>> = BTreeMap::new();
    for b in batches {
        let agent = agent_of(b);
        for r in &b.records {
            if let Some(m) = r.to_metrics() {
                out.entry((agent.clone(), Condition { level: r.level, demo: r.demo })).or_default().push(m);
            }
        }
    }
    out
}

/// The batches' pool rollouts, grouped by agent (`harness/model`).
pub fn pool_rollouts(batches: &[LoadedBatch]) -> BTreeMap<String, Vec<PoolRollout>> {
    let mut out: BTreeMap<String, Vec<PoolRollout>> = BTreeMap::new();
    for b in batches {
        for r in b.records.iter().filter_map(RolloutRecord::to_pool) {
            out.entry(agent_of(b)).or_default().push(r);
        }
    }
    out
}

/// `harness/model` of a batch.
pub fn agent_of(b: &LoadedBatch) -> String {
    format!("{}/{}", b.batch.harness_setting().unwrap_or("?"), b.batch.model().unwrap_or("?"))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A T14 record with nothing known yet, as the runner writes it before supervision says otherwise.
    fn t14_invalid() -> RolloutRecord {
        serde_json::from_value(json!({"schema_version": ROLLOUT_SCHEMA, "rollout_id": "w1_t14_level3", "task": "T14",
            "task_number": 14, "split": "short_horizon_easy", "stage_count": 1, "repetition": 1, "level": 3, "demo": "none",
            "outcome": "INVALID", "episode_id": null, "workspace": null, "run_dir": null, "result_status": null, "success": null,
            "termination_reason": null, "infrastructure_error": null, "wall_time_s": null, "harness_elapsed_s": null,
            "accepted_agent_steps": null, "completed_stages": null, "judgment_correct": null, "agent_exit_code": null,
            "usage": null, "started_at": "x", "finished_at": "y"}))
        .unwrap()
    }

    #[test]
    fn a_record_written_before_the_pool_reads_back_as_a_release_rollout() {
        let line = r#"{"schema_version":"libero_agent.rollout.v1","rollout_id":"w1_t14_level3","task":"T14","task_number":14,
            "split":"short_horizon_easy","stage_count":1,"repetition":1,"level":3,"demo":"none","outcome":"SUCCESS",
            "episode_id":null,"workspace":null,"run_dir":null,"result_status":null,"success":true,"termination_reason":null,
            "infrastructure_error":null,"wall_time_s":1.0,"harness_elapsed_s":null,"accepted_agent_steps":4,
            "completed_stages":1,"judgment_correct":null,"agent_exit_code":0,"usage":null,"started_at":"x","finished_at":"y"}"#;
        let r: RolloutRecord = serde_json::from_str(line).unwrap();
        assert_eq!((r.suite.as_ref(), r.harness_version.as_ref()), (None, None));
        assert_eq!(r.to_metrics().unwrap().split, libero_metrics::Split::ShortHorizonEasy);
        assert!(r.to_pool().is_none());
    }

    #[test]
    fn every_invalid_rollout_names_a_reason() {
        let mut r = t14_invalid();
        r.ensure_reason();
        assert_eq!(r.reason().as_deref(), Some("no episode was prepared for this rollout"));
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("result.json"), r#"{"status": "aborted", "reason": "harness_process_exited_before_finish"}"#).unwrap();
        let mut r = t14_invalid();
        (r.episode_id, r.run_dir) = (Some("ep1".into()), Some(dir.path().to_path_buf()));
        r.ensure_reason();
        assert_eq!(r.reason().as_deref(), Some("the episode ended: harness_process_exited_before_finish"));
        let mut ok = t14_invalid();
        ok.outcome = Outcome::Success;
        ok.ensure_reason();
        assert_eq!((ok.reason(), ok.infrastructure_error), (None, None));
    }

    #[test]
    fn a_batch_of_another_schema_or_a_torn_last_line_is_read_as_such() {
        let dir = tempfile::tempdir().unwrap();
        assert!(matches!(load_batch(dir.path()), Err(BatchError::NotABatch { .. })));
        std::fs::write(batch_json(dir.path()), r#"{"schema_version": "libero_agent.batch.v0"}"#).unwrap();
        let e = load_batch(dir.path()).unwrap_err().to_string();
        assert!(e.ends_with("schema_version \"libero_agent.batch.v0\", expected libero_agent.batch.v1"), "{e}");
        std::fs::write(batch_json(dir.path()), json!({"schema_version": BATCH_SCHEMA}).to_string()).unwrap();
        let line = serde_json::to_string(&t14_invalid()).unwrap();
        std::fs::write(rollouts_jsonl(dir.path()), format!("{line}\n{{\"rollout_id\": \"w2_t1")).unwrap();
        let b = load_batch(dir.path()).unwrap();
        assert_eq!(b.records, vec![t14_invalid()], "the torn line is skipped");
        let stored = LoadedBatch::from_stored("b", "/x/b".into(), json!({"schema_version": BATCH_SCHEMA}), vec![json!(t14_invalid())]).unwrap();
        assert_eq!((stored.name(), stored.records.len()), ("b".to_owned(), 1));
        assert!(LoadedBatch::from_stored("b", "/x/b".into(), json!({}), vec![]).unwrap_err().to_string().starts_with("batch b in the store"));
    }

    #[test]
    fn only_a_known_harness_names_a_log_file() {
        assert_eq!(stdout_file("codex").as_deref(), Some("codex_stdout.jsonl"));
        assert_eq!(stdout_file("command").as_deref(), Some("command_stdout.log"));
        assert_eq!(stderr_file("deepseek").as_deref(), Some("deepseek_stderr.log"));
        assert_eq!((stdout_file("../x"), stderr_file("../x")), (None, None));
    }
}
