//! Writing a batch directory: `batch.json` (settings, their hash, harness version, status and counts; rewritten
//! atomically after every change), `rollouts.jsonl` (one record per ended rollout, appended), and
//! `rollouts/<rollout_id>/` (logs, harness manifest, usage, the agent's session home), mirrored to a store or a
//! server as it changes. What a batch holds and how it is read (the record, [`load_batch`]) is `libero_report::batch`,
//! which `report` and the dashboard read it through.
use std::io::Write;
use std::path::Path;

use anyhow::{Context, bail};
use libero_metrics::Outcome;
use libero_records::batch_doc::BatchSettingsDoc;
use libero_records::json::write_json_file;
use libero_report::batch::{LoadedBatch, ROLLOUT_SCHEMA, RolloutRecord, load_batch, rollouts_jsonl};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use sha2::{Digest, Sha256};

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
        let canonical = libero_records::json::compact_sorted(&v);
        Sha256::digest(canonical.as_bytes()).iter().map(|b| format!("{b:02x}")).collect()
    }
}

/// A record of `plan` with nothing known yet (INVALID until supervision says otherwise).
impl From<&super::schedule::PlannedRollout> for RolloutRecord {
    fn from(plan: &super::schedule::PlannedRollout) -> Self {
        let now = libero_records::json::utc_now_iso();
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

/// Appends one record and syncs it (a killed runner loses no ended rollout).
pub fn append_record(dir: &Path, record: &RolloutRecord) -> anyhow::Result<()> {
    // A torn last line (a runner killed mid-write) is ended first, so this record starts on its own line.
    let (mut f, _) = libero_records::json::open_jsonl_for_append(&rollouts_jsonl(dir))?;
    let mut line = serde_json::to_string(record)?;
    line.push('\n');
    f.write_all(line.as_bytes())?;
    f.sync_data()?;
    Ok(())
}

pub fn write_batch_json(dir: &Path, v: &Value) -> anyhow::Result<()> {
    let path = libero_report::batch::batch_json(dir);
    write_json_file(&path, v).with_context(|| format!("cannot write {}", path.display()))
}

/// The batch in a shared store (`run --store URL`): after every change to the batch directory the runner writes
/// `batch.json`'s document and the new `rollouts.jsonl` records there too, so that `report --store URL NAME` (on any
/// machine) reads the batch without its files. The directory stays the source of truth.
pub struct StoreMirror {
    runtime: tokio::runtime::Runtime,
    store: libero_store::Store,
}

impl StoreMirror {
    pub fn connect(url: &str) -> anyhow::Result<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
        let store = runtime.block_on(libero_store::Store::connect(url))?;
        Ok(Self { runtime, store })
    }

    /// Writes the batch directory's current state to the store.
    pub fn sync(&self, dir: &Path) -> anyhow::Result<()> {
        let b = load_batch(dir)?;
        let stored = libero_store::StoredBatch {
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

/// `POST /api/batches`'s answer (the server's `batches::register`), as far as the mirror reads it: how many records
/// the server has, or why it refused. An answer that does not read so (another server's page) has neither.
#[derive(Deserialize, Default)]
struct Registered {
    have: Option<u64>,
    error: Option<String>,
}

impl Registered {
    fn of(v: &Value) -> Self {
        Self::deserialize(v).unwrap_or_default()
    }

    /// The refusal of a post that would leave a gap: the server has fewer records than `from`.
    fn gap_below(&self, from: usize) -> bool {
        self.have.is_some_and(|n| (n as usize) < from) && self.error.as_deref().is_some_and(|e| e.starts_with("records from"))
    }
}

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
                    self.posted = Registered::of(&v).have.map_or(end, |n| n as usize);
                    if self.posted >= records.len() {
                        return Ok(());
                    }
                }
                // The server has fewer records than this runner thought (a fresh store): send them from there.
                Ok((409, v)) if Registered::of(&v).gap_below(from) => {
                    self.posted = Registered::of(&v).have.map_or(0, |n| n as usize);
                }
                Ok((404 | 405, _)) => {
                    eprintln!("warning: {} has no batch registration (an older server): its Results page will not list batch {name}", self.url);
                    self.unsupported = true;
                    return Ok(());
                }
                Ok((status, v)) => {
                    bail!("{} refused to register batch {name} (HTTP {status}): {}", self.url, Registered::of(&v).error.unwrap_or_else(|| v.to_string()))
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

/// Reads batches by name from a store (`report --store URL NAME…`), in the shape [`load_batch`] gives.
pub fn load_batches_from_store(url: &str, names: &[String]) -> anyhow::Result<Vec<LoadedBatch>> {
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    runtime.block_on(async {
        let store = libero_store::Store::connect(url).await?;
        let mut out = Vec::with_capacity(names.len());
        for name in names {
            let Some(b) = store.batch(name).await? else {
                let known = store.batch_names().await?;
                bail!("the store {} has no batch {name:?} (it has: {})", libero_store::redact(url), known.join(", "));
            };
            out.push(LoadedBatch::from_stored(&b.name, b.dir, b.doc, b.records)?);
        }
        store.close().await;
        Ok(out)
    })
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
        demo: libero_report::batch::Demo::None,
    }
    }

    #[test]
    fn a_planned_record_is_invalid_for_a_named_reason_until_supervised() {
        let mut r = RolloutRecord::from(&t14_plan());
        r.ensure_reason();
        assert_eq!(r.reason().as_deref(), Some("no episode was prepared for this rollout"));
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
        append_record(dir.path(), &RolloutRecord::from(&plan)).unwrap();
        let records = libero_report::batch::read_records(dir.path()).unwrap();
        assert_eq!(records.len(), 1, "the torn line is skipped, the new record is whole");
        assert_eq!(records[0].rollout_id, "w1_t14_level3");
    }
}
