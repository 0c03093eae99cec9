//! A batch directory: `batch.json` (settings, their hash, harness version, status and counts; rewritten
//! atomically after every change), `rollouts.jsonl` (one record per ended rollout, appended), and
//! `rollouts/<rollout_id>/` (logs, harness manifest, usage, the agent's session home). The dashboard and
//! `report` read batches through [`load_batch`] and [`metrics_rollouts`].
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use libero_episode::json::write_json_file;
use libero_episode::batch_doc::{BatchDoc, BatchSettingsDoc, HarnessVersion};
use libero_episode::records::RunResult;
use libero_metrics::{Outcome, PoolRollout, Rollout, Split};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use sha2::{Digest, Sha256};

use super::schedule::Demo;

pub const BATCH_SCHEMA: &str = "libero_agent.batch.v1";
pub const ROLLOUT_SCHEMA: &str = "libero_agent.rollout.v1";

/// The settings a batch's rollouts must share; `--resume` refuses a batch whose hash differs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BatchSettings {
    pub experiment: String,
    pub harness: String,
    /// `--harness-version`: the CLI version every rollout runs (absent: the command on PATH). Left out of the JSON
    /// when absent, so the hash of a batch run without it is what it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub harness_version: Option<String>,
    pub model: String,
    pub effort: String,
    pub reps: u32,
    /// Task numbers given with `--tasks` (empty: every implemented task of the experiment).
    pub tasks: Vec<u32>,
    /// The `pool` experiment's `--tasks` selectors (`suite:robomemarena`, `T11`, `libero_90/35`). Left out of
    /// the JSON when empty, so the hash of every other experiment's settings is what it was.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub pool_tasks: Vec<String>,
    pub seed: u64,
    pub wall_time_s: f64,
    pub max_agent_steps: u64,
    /// The command of `--harness command` (it defines the agent).
    pub agent_cmd: Option<String>,
    pub sandbox: bool,
}

impl BatchSettings {
    /// The settings as `batch.json` holds them (every field; the typed ones its readers name).
    pub fn doc(&self) -> BatchSettingsDoc {
        serde_json::to_value(self).ok().and_then(|v| BatchSettingsDoc::from_value(v).ok()).unwrap_or_default()
    }

    /// SHA-256 of the canonical JSON (sorted keys, compact).
    pub fn sha256(&self) -> String {
        let v = serde_json::to_value(self).unwrap_or(Value::Null);
        let canonical = libero_episode::json::compact_sorted(&v);
        Sha256::digest(canonical.as_bytes()).iter().map(|b| format!("{b:02x}")).collect()
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
    pub usage: Option<super::usage::Usage>,
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
    /// A record of `plan` with nothing known yet (INVALID until supervision says otherwise).
    pub fn planned(plan: &super::schedule::PlannedRollout) -> Self {
        let now = libero_episode::json::utc_now_iso();
        Self {
            schema_version: ROLLOUT_SCHEMA.to_owned(),
            rollout_id: plan.rollout_id.clone(),
            task: plan.task.clone(),
            task_number: plan.task_number,
            split: plan.split,
            suite: plan.suite.clone(),
            stage_count: plan.stage_count,
            repetition: plan.repetition,
            level: plan.level,
            demo: plan.demo,
            outcome: Outcome::Invalid,
            episode_id: None,
            workspace: None,
            run_dir: None,
            result_status: None,
            success: None,
            termination_reason: None,
            infrastructure_error: None,
            wall_time_s: None,
            harness_elapsed_s: None,
            accepted_agent_steps: None,
            completed_stages: None,
            judgment_correct: None,
            agent_exit_code: None,
            usage: None,
            started_at: now.clone(),
            finished_at: now,
            worker: None,
            artifacts: None,
            harness_version: None,
        }
    }

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

/// When every rollout of `rollouts` (id, outcome, reason) is INVALID, the message saying so with the first
/// reasons; `None` when any is not (or there are none).
pub fn all_invalid_message<'a>(batch: &str, rollouts: impl IntoIterator<Item = (&'a str, &'a str, Option<String>)>) -> Option<String> {
    let rollouts: Vec<_> = rollouts.into_iter().collect();
    if rollouts.is_empty() || rollouts.iter().any(|(_, outcome, _)| *outcome != Outcome::Invalid.as_str()) {
        return None;
    }
    let first: Vec<String> = rollouts
        .iter()
        .take(3)
        .map(|(id, _, why)| format!("  {id}: {}", why.as_deref().unwrap_or("no reason recorded")))
        .collect();
    Some(format!(
        "every rollout of batch {batch} ended INVALID ({} of them); the first reasons:\n{}",
        rollouts.len(),
        first.join("\n")
    ))
}

pub fn batch_json(dir: &Path) -> PathBuf {
    dir.join("batch.json")
}
pub fn rollouts_jsonl(dir: &Path) -> PathBuf {
    dir.join("rollouts.jsonl")
}

/// Appends one record and syncs it (a killed runner loses no ended rollout).
pub fn append_record(dir: &Path, record: &RolloutRecord) -> anyhow::Result<()> {
    // A torn last line (a runner killed mid-write) is ended first, so this record starts on its own line.
    let (mut f, _) = libero_episode::json::open_jsonl_for_append(&rollouts_jsonl(dir))?;
    let mut line = serde_json::to_string(record)?;
    line.push('\n');
    f.write_all(line.as_bytes())?;
    f.sync_data()?;
    Ok(())
}

/// Every record of `rollouts.jsonl` (a torn last line from a crash is skipped).
pub fn read_records(dir: &Path) -> anyhow::Result<Vec<RolloutRecord>> {
    let path = rollouts_jsonl(dir);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e).with_context(|| format!("cannot read {}", path.display())),
    };
    Ok(text.lines().filter_map(|l| serde_json::from_str(l).ok()).collect())
}

pub fn write_batch_json(dir: &Path, v: &Value) -> anyhow::Result<()> {
    write_json_file(&batch_json(dir), v).with_context(|| format!("cannot write {}", batch_json(dir).display()))
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
}

/// Reads `batch.json` and `rollouts.jsonl`.
pub fn load_batch(dir: &Path) -> anyhow::Result<LoadedBatch> {
    let text = std::fs::read_to_string(batch_json(dir)).with_context(|| format!("{} is not a batch directory", dir.display()))?;
    let batch: Value = serde_json::from_str(&text).with_context(|| format!("{} is not JSON", batch_json(dir).display()))?;
    // JSON that is no object has no schema_version, and is refused as such.
    let batch = BatchDoc::from_value(batch).unwrap_or_default();
    if batch.schema_version.as_deref() != Some(BATCH_SCHEMA) {
        bail!("{}: schema_version {}, expected {BATCH_SCHEMA}", batch_json(dir).display(), json!(batch.schema_version));
    }
    Ok(LoadedBatch { dir: dir.to_path_buf(), batch, records: read_records(dir)? })
}

/// The batch in a shared store (`run --store URL`): after every change to the batch directory the runner writes
/// `batch.json`'s document and the new `rollouts.jsonl` records there too, so that `report --store URL NAME` (on any
/// machine) reads the batch without its files. The directory stays the source of truth.
pub struct StoreMirror {
    runtime: tokio::runtime::Runtime,
    store: libero_server::store::Store,
}

impl StoreMirror {
    pub fn connect(url: &str) -> anyhow::Result<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
        let store = runtime.block_on(libero_server::store::Store::connect(url))?;
        Ok(Self { runtime, store })
    }

    /// Writes the batch directory's current state to the store.
    pub fn sync(&self, dir: &Path) -> anyhow::Result<()> {
        let b = load_batch(dir)?;
        let stored = libero_server::store::StoredBatch {
            name: b.name(),
            dir: b.dir.clone(),
            doc: serde_json::to_value(&b.batch)?,
            records: b.records.iter().map(serde_json::to_value).collect::<Result<_, _>>()?,
        };
        Ok(self.runtime.block_on(self.store.put_batch(&stored))?)
    }
}

/// The batch registered with the server its episodes run on (`run --server URL`): after every change to the batch
/// directory the runner posts `batch.json`'s document and the records that server does not have yet to its
/// operator API (`POST /api/batches`), so that server's Results page lists the batch wherever its directory is.
/// The directory stays the source of truth: a server that cannot be reached is warned about and tried again at
/// the next change; one that refuses the batch (another batch of the same name, a wrong token) stops the run.
pub struct ServerMirror {
    url: String,
    /// Records of `rollouts.jsonl` the server has.
    posted: usize,
    /// Set once the server lacks the route (an older server): nothing more is posted.
    unsupported: bool,
    warned: bool,
}

/// Most records and bytes of records one registration request carries (the server takes up to 500 and 2 MiB).
const MIRROR_RECORDS: usize = 200;
const MIRROR_BYTES: usize = 1 << 20;
/// A registration must not hold a rollout's worker for long.
const MIRROR_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(20);

impl ServerMirror {
    pub fn new(url: &str) -> Self {
        Self { url: url.trim_end_matches('/').to_owned(), posted: 0, unsupported: false, warned: false }
    }

    /// The Results page of the batch named `name` on this server.
    pub fn results_url(&self, name: &str) -> String {
        format!("{}/results?batch={name}", self.url)
    }

    /// Posts the batch directory's current state; `Err` only when the server refuses the batch.
    pub fn sync(&mut self, dir: &Path) -> anyhow::Result<()> {
        if self.unsupported {
            return Ok(());
        }
        let b = load_batch(dir)?;
        let name = b.name();
        let records: Vec<Value> = b.records.iter().map(serde_json::to_value).collect::<Result<_, _>>()?;
        loop {
            let from = self.posted.min(records.len());
            let mut end = from;
            let mut bytes = 0;
            while end < records.len() && end - from < MIRROR_RECORDS {
                let size = records[end].to_string().len();
                if end > from && bytes + size > MIRROR_BYTES {
                    break;
                }
                bytes += size;
                end += 1;
            }
            let body = serde_json::json!({"name": name, "dir": b.dir, "doc": b.batch, "from": from, "records": &records[from..end]});
            match libero_server::client::post_json_within(&self.url, "/api/batches", &body, MIRROR_TIMEOUT) {
                Ok((200, v)) => {
                    self.posted = v["have"].as_u64().map_or(end, |n| n as usize);
                    if self.posted >= records.len() {
                        return Ok(());
                    }
                }
                // The server has fewer records than this runner thought (a fresh store): send them from there.
                Ok((409, v)) if v["have"].as_u64().is_some_and(|n| (n as usize) < from) && v["error"].as_str().is_some_and(|e| e.starts_with("records from")) => {
                    self.posted = v["have"].as_u64().map_or(0, |n| n as usize);
                }
                Ok((404 | 405, _)) => {
                    eprintln!("warning: {} has no batch registration (an older server): its Results page will not list batch {name}", self.url);
                    self.unsupported = true;
                    return Ok(());
                }
                Ok((status, v)) => {
                    bail!("{} refused to register batch {name} (HTTP {status}): {}", self.url, v["error"].as_str().map_or_else(|| v.to_string(), str::to_owned))
                }
                Err(e) => {
                    if !self.warned {
                        eprintln!("warning: cannot register batch {name} with {} (tried again at the next change): {e:#}", self.url);
                        self.warned = true;
                    }
                    return Ok(());
                }
            }
        }
    }
}

/// A batch read from the store, in the shape [`load_batch`] gives.
pub fn from_stored(b: libero_server::store::StoredBatch) -> anyhow::Result<LoadedBatch> {
    let doc = BatchDoc::from_value(b.doc).unwrap_or_default();
    if doc.schema_version.as_deref() != Some(BATCH_SCHEMA) {
        bail!("batch {} in the store: schema_version {}, expected {BATCH_SCHEMA}", b.name, json!(doc.schema_version));
    }
    let records = b.records.into_iter().map(serde_json::from_value).collect::<Result<Vec<RolloutRecord>, _>>()?;
    Ok(LoadedBatch { dir: b.dir, batch: doc, records })
}

/// Reads batches by name from a store (`report --store URL NAME…`), in the shape [`load_batch`] gives.
pub fn load_batches_from_store(url: &str, names: &[String]) -> anyhow::Result<Vec<LoadedBatch>> {
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    runtime.block_on(async {
        let store = libero_server::store::Store::connect(url).await?;
        let mut out = Vec::with_capacity(names.len());
        for name in names {
            let Some(b) = store.batch(name).await? else {
                let known = store.batch_names().await?;
                bail!("the store {} has no batch {name:?} (it has: {})", libero_server::store::redact(url), known.join(", "));
            };
            out.push(from_stored(b)?);
        }
        store.close().await;
        Ok(out)
    })
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

    #[test]
    fn the_settings_hash_changes_with_any_setting() {
        let s = BatchSettings {
            experiment: "main_table".into(),
            harness: "codex".into(),
            harness_version: None,
            model: "m".into(),
            effort: "high".into(),
            reps: 3,
            tasks: vec![],
            pool_tasks: vec![],
            seed: 100,
            wall_time_s: 1800.0,
            max_agent_steps: 1_000_000,
            agent_cmd: None,
            sandbox: true,
        };
        let mut t = s.clone();
        assert_eq!(s.sha256(), t.sha256());
        t.model = "other".into();
        assert_ne!(s.sha256(), t.sha256());
        assert_eq!(s.sha256().len(), 64);
        // Outside the pool experiment the settings JSON (and so an existing batch's hash) has no pool_tasks.
        assert!(!serde_json::to_string(&s).unwrap().contains("pool_tasks"));
        t.pool_tasks = vec!["suite:robomemarena".into()];
        assert_ne!(s.sha256(), t.sha256());
        // Without --harness-version too; with it, another batch (`--resume` refuses a changed version).
        assert!(!serde_json::to_string(&s).unwrap().contains("harness_version"));
        let mut v = s.clone();
        v.harness_version = Some("0.154.0".into());
        assert_ne!(s.sha256(), v.sha256());
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

    fn t14_plan() -> super::super::schedule::PlannedRollout {
        super::super::schedule::PlannedRollout {
        rollout_id: "w1_t14_level3".into(),
        task: "T14".into(),
        task_number: 14,
        task_name: "open_the_microwave".into(),
        split: Some(libero_metrics::Split::ShortHorizonEasy),
        suite: None,
        stage_count: 1,
        repetition: 1,
        level: 3,
        demo: super::super::schedule::Demo::None,
    }
    }

    #[test]
    fn every_invalid_rollout_names_a_reason() {
        let plan = t14_plan();
        let mut r = RolloutRecord::planned(&plan);
        r.ensure_reason();
        assert_eq!(r.reason().as_deref(), Some("no episode was prepared for this rollout"));
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("result.json"), r#"{"status": "aborted", "reason": "harness_process_exited_before_finish"}"#).unwrap();
        let mut r = RolloutRecord::planned(&plan);
        (r.episode_id, r.run_dir) = (Some("ep1".into()), Some(dir.path().to_path_buf()));
        r.ensure_reason();
        assert_eq!(r.reason().as_deref(), Some("the episode ended: harness_process_exited_before_finish"));
        let mut ok = RolloutRecord::planned(&plan);
        ok.outcome = Outcome::Success;
        ok.ensure_reason();
        assert_eq!((ok.reason(), ok.infrastructure_error), (None, None));
        let msg = all_invalid_message("b", [("a", "INVALID", Some("x".to_owned())), ("b", "INVALID", None)]).unwrap();
        assert!(msg.contains("(2 of them)") && msg.contains("a: x") && msg.contains("b: no reason recorded"), "{msg}");
        assert!(all_invalid_message("b", [("a", "INVALID", None), ("b", "FAIL", None)]).is_none());
        assert!(all_invalid_message("b", []).is_none());
    }

    #[test]
    fn a_record_appended_after_a_torn_line_is_read_back() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(rollouts_jsonl(dir.path()), b"{\"rollout_id\": \"w1_t14_le").unwrap();
        let plan = t14_plan();
        append_record(dir.path(), &RolloutRecord::planned(&plan)).unwrap();
        let records = read_records(dir.path()).unwrap();
        assert_eq!(records.len(), 1, "the torn line is skipped, the new record is whole");
        assert_eq!(records[0].rollout_id, "w1_t14_level3");
    }
}
