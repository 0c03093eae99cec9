//! Evaluator-private records in the run directory (§4.9): the append-only action log (one fsync per
//! line, so a killed server loses nothing it answered) and `result.json`, plus the outcome rule of §4.8.
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use serde_json::{Value, json};

pub use crate::action_event::{ACTION_EVENT_SCHEMA, ActionEvent, Execution, ToolReply, actions_executed};
pub use crate::episode_record::{BranchRecord, EPISODE_RECORD_SCHEMA, EpisodeRecord, RecordedSuite, RecordedTask};
use crate::json::{compact_sorted, open_jsonl_for_append, sha256_hex, utc_now_iso, write_json_file};
pub use crate::result::{
    EvaluationDetails, MechanismOperation, PrivateEvaluation, PrivateEvent, RESULT_SCHEMA, RunResult, STATUS_ABORTED,
    STATUS_FINISHED, StageDiagnostic, StageRegressions, TerminalCheck, WALL_TIME_BUDGET_SCOPE, WALL_TIME_EXHAUSTED, STEP_BUDGET_EXHAUSTED,
};
pub use crate::typed::RecordError;
use crate::typed::read_record;

/// `telemetry.jsonl` beside the other private records: one line per control step.
pub const TELEMETRY_FILE: &str = "telemetry.jsonl";

/// Files of one episode's private run directory.
#[derive(Debug, Clone)]
pub struct RunDir {
    pub root: PathBuf,
}

impl RunDir {
    pub fn new(root: impl Into<PathBuf>) -> Self {
        Self { root: root.into() }
    }
    pub fn actions_jsonl(&self) -> PathBuf {
        self.root.join("actions.jsonl")
    }
    pub fn result_json(&self) -> PathBuf {
        self.root.join("result.json")
    }
    pub fn stage_events_jsonl(&self) -> PathBuf {
        self.root.join("private_stage_events.jsonl")
    }
    pub fn private_observations(&self) -> PathBuf {
        self.root.join("private_observations")
    }
    /// The episode's private configuration (task, init state, level, seed, budgets, token digest).
    pub fn episode_record(&self) -> PathBuf {
        self.root.join("episode_record.json")
    }
    /// The private video (§6.1); `continuous_video.mp4.partial` while it is being written.
    pub fn continuous_video(&self) -> PathBuf {
        self.root.join("continuous_video.mp4")
    }
    /// What the private video is rendered from (see `state_record`).
    pub fn state_record(&self) -> PathBuf {
        self.root.join("state_record.bin")
    }
    pub fn agent_prompt(&self) -> PathBuf {
        self.root.join("agent_prompt.txt")
    }
    /// Per-control-step end-effector, gripper and wrist-force series for the review page.
    pub fn telemetry_jsonl(&self) -> PathBuf {
        self.root.join(TELEMETRY_FILE)
    }
    /// The agent's transcript, written by the runner ([`crate::agent_events`]).
    pub fn agent_events_jsonl(&self) -> PathBuf {
        self.root.join(crate::agent_events::AGENT_EVENTS_FILE)
    }
}

/// Serialized size above which a logged field is recorded as a digest and a prefix (see [`bounded_for_log`]).
/// The largest valid call, 50 micro-actions of 7 numbers of at most 24 characters each, serializes to about
/// 9 KiB, so accepted calls keep their full arguments (demonstration recording and replay read them back);
/// only rejected calls can exceed it.
pub const MAX_LOGGED_FIELD_BYTES: usize = 16 * 1024;
/// How much of an oversized field's serialized JSON the log keeps.
pub const LOGGED_PREFIX_BYTES: usize = 1024;

/// `value` as the action log records it: unchanged up to [`MAX_LOGGED_FIELD_BYTES`] serialized, otherwise
/// `{"truncated": true, "size_bytes", "sha256", "prefix"}` of its compact sorted JSON, so that an agent
/// sending megabytes of rejected arguments cannot fill the disk with fsync'd copies.
pub fn bounded_for_log(value: &Value) -> Value {
    let text = compact_sorted(value);
    if text.len() <= MAX_LOGGED_FIELD_BYTES {
        return value.clone();
    }
    let mut end = LOGGED_PREFIX_BYTES;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    json!({"truncated": true, "size_bytes": text.len(), "sha256": sha256_hex(text.as_bytes()), "prefix": &text[..end]})
}

/// Each field of an object bounded on its own (so `tool` and `command` stay readable beside huge
/// `arguments`); any other value bounded whole.
fn bounded_fields(value: &Value) -> Value {
    match value {
        Value::Object(map) => Value::Object(map.iter().map(|(k, v)| (k.clone(), bounded_for_log(v))).collect()),
        other => bounded_for_log(other),
    }
}

/// `actions.jsonl`: every request and its response, errors included.
pub struct ActionLog {
    file: File,
    next_index: u64,
}

impl ActionLog {
    /// Opens (creating or appending to) the log; `event_index` continues after existing lines. A line torn
    /// by a crash keeps its index and is ended, so the next event starts on a line of its own.
    pub fn open(path: &Path) -> std::io::Result<Self> {
        let (file, lines) = open_jsonl_for_append(path)?;
        Ok(Self { file, next_index: lines })
    }

    /// Appends one event and fsyncs it before returning. Oversized request fields and responses are
    /// recorded truncated ([`bounded_for_log`]).
    pub fn append(&mut self, request: &Value, response: &Value, attempt_index: u32) -> std::io::Result<()> {
        let event = ActionEvent {
            schema_version: Some(ACTION_EVENT_SCHEMA.to_owned()),
            event_index: Some(self.next_index),
            recorded_at: Some(utc_now_iso()),
            request: Some(bounded_fields(request)),
            response: Some(bounded_for_log(response)),
            attempt_index: Some(u64::from(attempt_index)),
            rest: serde_json::Map::new(),
        };
        let mut line = compact_sorted(&event.to_value());
        line.push('\n');
        self.file.write_all(line.as_bytes())?;
        self.file.sync_data()?;
        self.next_index += 1;
        Ok(())
    }

    pub fn events_written(&self) -> u64 {
        self.next_index
    }
}

/// Writes `result.json` atomically.
pub fn write_result(run: &RunDir, result: &RunResult) -> std::io::Result<()> {
    write_json_file(&run.result_json(), &result.to_value())
}

/// The aborted result of §4.7, finished now.
pub fn aborted_result(reason: &str, max_wall_time_s: f64, wall_time_s: Option<f64>) -> RunResult {
    RunResult::aborted(reason, max_wall_time_s, wall_time_s, utc_now_iso())
}

/// The outcome class of one episode or rollout (§4.8): the one definition the episode, the runner, the store and
/// the metrics share. An episode alone ends SUCCESS, FAIL, SIM_TIMEOUT or INVALID ([`classify`]); the harness adds
/// WATCHDOG_TIMEOUT and INTERRUPTED ([`classify_rollout`], and a batch interrupted before its rollout ran).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum Outcome {
    Success,
    Fail,
    SimTimeout,
    WatchdogTimeout,
    Invalid,
    Interrupted,
}

impl Outcome {
    pub const ALL: [Outcome; 6] =
        [Outcome::Success, Outcome::Fail, Outcome::SimTimeout, Outcome::WatchdogTimeout, Outcome::Invalid, Outcome::Interrupted];

    pub fn as_str(self) -> &'static str {
        match self {
            Outcome::Success => "SUCCESS",
            Outcome::Fail => "FAIL",
            Outcome::SimTimeout => "SIM_TIMEOUT",
            Outcome::WatchdogTimeout => "WATCHDOG_TIMEOUT",
            Outcome::Invalid => "INVALID",
            Outcome::Interrupted => "INTERRUPTED",
        }
    }

    /// Counted in success-rate denominators: timeouts are failures, INVALID/INTERRUPTED are excluded.
    pub fn is_valid(self) -> bool {
        !matches!(self, Outcome::Invalid | Outcome::Interrupted)
    }
}

/// A string that names no outcome class.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownOutcome(pub String);

impl std::fmt::Display for UnknownOutcome {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "unknown outcome {:?} (one of SUCCESS, FAIL, SIM_TIMEOUT, WATCHDOG_TIMEOUT, INVALID, INTERRUPTED)", self.0)
    }
}

impl std::error::Error for UnknownOutcome {}

impl std::str::FromStr for Outcome {
    type Err = UnknownOutcome;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Outcome::ALL.into_iter().find(|x| x.as_str() == s).ok_or_else(|| UnknownOutcome(s.to_owned()))
    }
}

/// An episode's outcome from its `result.json` (§4.8): a missing, unfinished or infrastructure-failed result is
/// INVALID; a success SUCCESS; an exhausted wall-time or agent-step budget SIM_TIMEOUT; anything else FAIL.
pub fn classify(result: Option<&RunResult>) -> Outcome {
    let Some(r) = result else { return Outcome::Invalid };
    if !r.is_finished() || r.has_infrastructure_error() {
        return Outcome::Invalid;
    }
    if r.success == Some(true) {
        Outcome::Success
    } else if matches!(r.termination_reason.as_deref(), Some(WALL_TIME_EXHAUSTED | STEP_BUDGET_EXHAUSTED)) {
        Outcome::SimTimeout
    } else {
        Outcome::Fail
    }
}

/// The harness's watchdog error text (§8.4), which [`classify_rollout`] reads as WATCHDOG_TIMEOUT once the episode
/// has used its whole wall budget.
pub const WATCHDOG_ERROR: &str = "multi-agent rollout wall-clock supervision timeout";

/// A rollout's outcome (§4.8 with the harness): the watchdog's kill of an agent past a spent `budget_s` is
/// WATCHDOG_TIMEOUT; any other harness infrastructure error INVALID; else the episode's own [`classify`].
pub fn classify_rollout(result: Option<&RunResult>, infra: Option<&str>, budget_s: f64) -> Outcome {
    if let (Some(r), Some(e)) = (result, infra)
        && e.contains("wall-clock supervision timeout")
        && r.wall_time_s().is_some_and(|w| w >= budget_s)
    {
        return Outcome::WatchdogTimeout;
    }
    if infra.is_some() {
        return Outcome::Invalid;
    }
    classify(result)
}

/// Reads `result.json` if present and parseable.
pub fn read_result(run: &RunDir) -> Option<RunResult> {
    try_read_result(run).ok().flatten()
}

/// Reads `result.json`: `Ok(None)` while there is none, an error saying why when it cannot be read.
pub fn try_read_result(run: &RunDir) -> Result<Option<RunResult>, RecordError> {
    read_record(&run.result_json())
}

/// `result.json` as it is, for a caller that hands the whole record on (an API response).
pub fn read_result_value(run: &RunDir) -> Option<Value> {
    let text = std::fs::read_to_string(run.result_json()).ok()?;
    serde_json::from_str(&text).ok()
}

/// Reads `episode_record.json`: `Ok(None)` when there is none (the episode was never prepared here).
pub fn read_episode_record(run: &RunDir) -> Result<Option<EpisodeRecord>, RecordError> {
    read_record(&run.episode_record())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A closed log holding one `start` event.
    fn log_with_a_start_event(dir: &Path) -> PathBuf {
        let path = dir.join("actions.jsonl");
        let mut log = ActionLog::open(&path).unwrap();
        log.append(&json!({"command": "start"}), &json!({"ok": true}), 1).unwrap();
        path
    }

    #[test]
    fn action_log_lines_are_sorted_compact_and_indexed_across_reopen() {
        let dir = tempfile::tempdir().unwrap();
        let path = log_with_a_start_event(dir.path());
        let mut log = ActionLog::open(&path).unwrap();
        log.append(&Value::Null, &json!({"ok": false, "error": "x"}), 1).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        assert_eq!(lines.len(), 2);
        assert_eq!(lines[1]["event_index"], 1);
        assert_eq!(lines[1]["request"], Value::Null);
        assert!(text.lines().next().unwrap().starts_with(r#"{"attempt_index":1,"event_index":0,"#));
    }

    #[test]
    fn action_log_lines_are_the_bytes_the_json_literal_wrote() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("actions.jsonl");
        let mut log = ActionLog::open(&path).unwrap();
        let request = json!({"tool": "osc_sequence", "command": "osc_sequence", "arguments": {"actions": [[0.5, 0, 0, 0, 0, 0, -1]]}});
        let response = json!({"ok": true, "observation_id": "obs_000001", "execution": {"control_steps": 1}});
        log.append(&request, &response, 1).unwrap();
        log.append(&Value::Null, &json!({"ok": false, "error": "x"}), 2).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        for (i, (line, (req, resp, attempt))) in
            text.lines().zip([(request, response, 1), (Value::Null, json!({"ok": false, "error": "x"}), 2)]).enumerate()
        {
            let written: ActionEvent = serde_json::from_str(line).unwrap();
            let literal = json!({
                "schema_version": ACTION_EVENT_SCHEMA,
                "event_index": i,
                "recorded_at": written.recorded_at,
                "request": req,
                "response": resp,
                "attempt_index": attempt,
            });
            assert_eq!(line, compact_sorted(&literal));
            assert_eq!(compact_sorted(&written.to_value()), line, "read and written back unchanged");
        }
    }

    #[test]
    fn append_after_a_torn_line_starts_a_new_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = log_with_a_start_event(dir.path());
        // A crash in the middle of the second event's write.
        let mut f = std::fs::OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(br#"{"attempt_index":1,"event_index":1,"req"#).unwrap();
        drop(f);
        let mut log = ActionLog::open(&path).unwrap();
        assert_eq!(log.events_written(), 2, "the torn event keeps its index");
        log.append(&json!({"command": "finish"}), &json!({"ok": true}), 1).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 3);
        assert!(serde_json::from_str::<Value>(lines[1]).is_err(), "the torn line stays as it was");
        let last: Value = serde_json::from_str(lines[2]).expect("the next event is a whole line");
        assert_eq!(last["event_index"], 2);
    }

    #[test]
    fn oversized_rejected_arguments_are_logged_truncated_with_sha256() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("actions.jsonl");
        let mut log = ActionLog::open(&path).unwrap();
        // 4 MiB of junk, with a multi-byte character straddling the prefix's end.
        let junk = format!("{}é{}", "x".repeat(LOGGED_PREFIX_BYTES - 13), "y".repeat(4 << 20));
        let arguments = json!({"actions": junk});
        let request = json!({"tool": "osc_sequence", "command": "osc_sequence", "arguments": arguments});
        let rejected = json!({"ok": false, "error_type": "ValueError", "error": "actions must be a rectangular numeric array"});
        log.append(&request, &rejected, 1).unwrap();
        let size = std::fs::metadata(&path).unwrap().len();
        assert!(size < 4096, "the line is {size} bytes");
        let line: Value = serde_json::from_str(std::fs::read_to_string(&path).unwrap().trim_end()).unwrap();
        let logged = &line["request"]["arguments"];
        let full = compact_sorted(&arguments);
        assert_eq!(logged["truncated"], true);
        assert_eq!(logged["size_bytes"], full.len());
        assert_eq!(logged["sha256"], sha256_hex(full.as_bytes()));
        let prefix = logged["prefix"].as_str().unwrap();
        assert!(full.starts_with(prefix) && prefix.len() <= LOGGED_PREFIX_BYTES && prefix.len() > LOGGED_PREFIX_BYTES - 4);
        assert_eq!(line["request"]["tool"], "osc_sequence", "small fields stay whole");
        assert_eq!(line["response"], rejected);
    }

    #[test]
    fn outcomes_follow_the_batch_rule() {
        let finished = |success: bool, reason: Option<&str>| {
            let mut v = json!({"status": "finished", "success": success});
            if let Some(r) = reason {
                v["termination_reason"] = json!(r);
            }
            v
        };
        let classify_value = |v: Value| classify(Some(&RunResult::from_value(v).unwrap()));
        assert_eq!(classify_value(finished(true, None)), Outcome::Success);
        assert_eq!(classify_value(finished(false, None)), Outcome::Fail);
        assert_eq!(classify_value(finished(false, Some("episode_wall_time_budget_exhausted"))), Outcome::SimTimeout);
        assert_eq!(classify(Some(&aborted_result("server_stopped_before_finish", 1800.0, None))), Outcome::Invalid);
        let mut infra = finished(true, None);
        infra["infrastructure_error"] = json!("boom");
        assert_eq!(classify_value(infra), Outcome::Invalid);
        assert_eq!(classify(None), Outcome::Invalid);
    }

    #[test]
    fn a_written_aborted_result_reads_back_and_classifies_invalid() {
        let dir = tempfile::tempdir().unwrap();
        let run = RunDir::new(dir.path());
        assert!(read_result(&run).is_none() && try_read_result(&run).unwrap().is_none(), "none yet");
        write_result(&run, &aborted_result("server_stopped_before_finish", 1800.0, Some(3.5))).unwrap();
        let text = std::fs::read_to_string(run.result_json()).unwrap();
        let r = read_result(&run).expect("the aborted result");
        assert_eq!((r.status.as_deref(), r.reason.as_deref(), r.wall_time_s()), (Some("aborted"), Some("server_stopped_before_finish"), Some(3.5)));
        assert_eq!(classify(Some(&r)), Outcome::Invalid);
        assert_eq!(classify_rollout(Some(&r), Some(WATCHDOG_ERROR), 1800.0), Outcome::Invalid, "3.5 s is not the budget");
        assert_eq!(classify_rollout(Some(&r), Some(WATCHDOG_ERROR), 3.0), Outcome::WatchdogTimeout);
        // Read and written back: the same bytes.
        write_result(&run, &r).unwrap();
        assert_eq!(std::fs::read_to_string(run.result_json()).unwrap(), text);
        assert_eq!(read_result_value(&run), Some(serde_json::from_str::<Value>(&text).unwrap()));
    }

    #[test]
    fn a_torn_or_foreign_result_is_none_with_a_reason() {
        let dir = tempfile::tempdir().unwrap();
        let run = RunDir::new(dir.path());
        std::fs::write(run.result_json(), r#"{"status": "finis"#).unwrap();
        assert!(read_result(&run).is_none());
        let why = try_read_result(&run).unwrap_err().to_string();
        assert!(why.contains("result.json is not a JSON object"), "{why}");
        std::fs::write(run.result_json(), "[1, 2]").unwrap();
        assert!(read_result(&run).is_none(), "a result is an object");
        // A partial result reads; what it lacks is None, and it is INVALID.
        std::fs::write(run.result_json(), r#"{"status": "finished", "success": "yes"}"#).unwrap();
        let r = read_result(&run).unwrap();
        assert_eq!((r.success, r.rest.get("success")), (None, Some(&json!("yes"))));
        assert_eq!(classify(Some(&r)), Outcome::Fail, "as r[\"success\"].as_bool() read it");
    }
}
