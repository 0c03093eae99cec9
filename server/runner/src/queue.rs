//! `run --store postgres://…`: the batch goes to the store's queue instead of running here. `run` enqueues it and
//! follows its progress (a bar on stderr, woken by the store's notifications) until every rollout ended, or
//! returns at once with `--detach`; `libero-agent worker` processes on any machine run the rollouts. `--resume`
//! queues the batch's INVALID rollouts again (a lost worker's among them) and follows; changed settings are
//! refused, as for a batch directory.
use std::time::Duration;

use anyhow::{Context, bail};
use libero_records::batch_doc::{BatchCounts, BatchDoc, HarnessDoc, QueueRef, RolloutSummary};
use libero_records::json::utc_now_iso;
use libero_metrics::Outcome;
use libero_store::{QueueListener, Store, StoredBatch};
use serde::Deserialize;
use serde_json::{Value, json};

use libero_report::batch::{BATCH_SCHEMA, RolloutRecord};

use super::batch::BatchSettings;
use super::schedule::PlannedRollout;
use super::{INTERRUPTED, RunArgs};

/// Why a rollout whose worker stopped renewing its lease ended (its record's `termination_reason`).
pub const WORKER_LOST: &str = "worker_lost";

/// A queue row that is no [`PlannedRollout`] as far as its record can still name it (null where it cannot).
#[derive(Deserialize)]
struct PlanId {
    #[serde(default)]
    rollout_id: Value,
}

/// The record of a rollout whose worker was lost (its lease ran out): INVALID, `worker_lost`.
pub fn worker_lost_record(plan: &Value) -> Value {
    let Ok(plan) = serde_json::from_value::<PlannedRollout>(plan.clone()) else {
        let rollout_id = PlanId::deserialize(plan).map(|p| p.rollout_id).unwrap_or_default();
        return json!({"rollout_id": rollout_id, "outcome": Outcome::Invalid.as_str(), "termination_reason": WORKER_LOST});
    };
    let mut rec = RolloutRecord::from(&plan);
    rec.outcome = Outcome::Invalid;
    rec.termination_reason = Some(WORKER_LOST.into());
    rec.infrastructure_error = Some(format!("{WORKER_LOST}: the worker running it stopped renewing its lease (its machine or process died)"));
    serde_json::to_value(&rec).unwrap_or(Value::Null)
}

/// A batch name: it names the batch in the store and its prefix in the artifact store.
pub fn batch_name(args: &RunArgs) -> anyhow::Result<String> {
    let name = match &args.batch {
        Some(b) => b.to_string_lossy().into_owned(),
        None => super::default_batch_dir().file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
    };
    libero_artifacts::check_name(&name).map(str::to_owned).with_context(|| "with a queue store, --batch is the batch's name, not a directory")
}

/// The queued batch's document: `batch.json`'s shape; the store keeps its progress current.
fn batch_doc(name: &str, settings: &BatchSettings, schedule: &[PlannedRollout], skipped: &[String], store_url: &str) -> Value {
    BatchDoc {
        schema_version: Some(BATCH_SCHEMA.into()),
        name: Some(name.into()),
        created_at: Some(utc_now_iso()),
        updated_at: Some(utc_now_iso()),
        status: Some("queued".into()),
        settings: Some(settings.doc()),
        settings_sha256: Some(settings.sha256()),
        // each worker probes its own harness and runs its own sandbox and server
        harness: Some(HarnessDoc { name: Some(settings.harness.clone()), version: Some(None), ..Default::default() }),
        sandbox: Some(None),
        server_url: Some(None),
        workspace_root: Some(None),
        max_outer_retries: Some(0),
        rollout_count: Some(schedule.len() as u64),
        skipped_unimplemented_tasks: Some(skipped.to_vec()),
        counts: Some(BatchCounts { done: Some(0), running: Some(0), left: Some(schedule.len() as u64), ..Default::default() }),
        running: Some(Vec::new()),
        outcomes: Some(Default::default()),
        queue: Some(QueueRef { store: Some(libero_store::redact(store_url)), ..Default::default() }),
        ..Default::default()
    }
    .to_value()
}

/// Writes a new batch `name` and queues its rollouts.
pub async fn enqueue(store: &Store, url: &str, name: &str, settings: &BatchSettings, schedule: &[PlannedRollout], skipped: &[String]) -> anyhow::Result<()> {
    let doc = batch_doc(name, settings, schedule, skipped, url);
    let jobs = schedule.iter().map(|r| Ok((r.rollout_id.clone(), serde_json::to_value(r)?))).collect::<anyhow::Result<Vec<_>>>()?;
    store.enqueue(&StoredBatch { name: name.to_owned(), dir: name.into(), doc, records: Vec::new() }, &jobs).await?;
    Ok(())
}

/// Enqueues (or with `--resume` re-queues the INVALID rollouts of) the batch, then follows it unless `--detach`.
pub fn enqueue_and_follow(
    args: &RunArgs,
    url: &str,
    schedule: &[PlannedRollout],
    skipped: &[String],
    settings: &BatchSettings,
) -> anyhow::Result<()> {
    for (given, flag) in [(args.server.is_some(), "--server"), (args.data.is_some(), "--data"), (args.paths.workspace_root.is_some(), "--workspace-root"), (args.concurrency.is_some(), "--concurrency"), (args.paths.credentials_file.is_some(), "--credentials-file")] {
        if given {
            bail!("{flag} belongs to a local run: a queued batch runs on `libero-agent worker`s (give it to them), or pass --local");
        }
    }
    let name = batch_name(args)?;
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    runtime.block_on(async {
        let store = Store::connect(url).await?;
        match store.batch(&name).await? {
            Some(existing) if args.resume => {
                let doc = BatchDoc::from_value(existing.doc).unwrap_or_default();
                if doc.settings_sha256 != Some(settings.sha256()) {
                    bail!(
                        "--resume refuses changed settings: the batch was started with {}, now {}",
                        json!(doc.settings),
                        serde_json::to_value(settings)?
                    );
                }
                let requeued = store.requeue_invalid(&name).await?;
                eprintln!("batch {name}: {} INVALID rollout(s) queued again{}", requeued.len(), if requeued.is_empty() { String::new() } else { format!(": {}", requeued.join(", ")) });
            }
            Some(_) => bail!("the store already has a batch {name:?}; pass --resume to continue it"),
            None if args.resume => bail!("--resume: the store {} has no batch {name:?}", libero_store::redact(url)),
            None => {
                enqueue(&store, url, &name, settings, schedule, skipped).await?;
                eprintln!("batch {name}: {} rollouts queued in {}", schedule.len(), libero_store::redact(url));
            }
        }
        if args.detach {
            eprintln!("detached: workers (`libero-agent worker --store URL --artifacts URL`) run it; `libero-agent report --store URL {name}` reads it");
            println!("{}", json!({"batch": name, "queued": true}));
            return Ok(());
        }
        follow(&store, url, &name).await
    })
}

/// Follows a queued batch until every rollout ended: a progress bar on stderr, redrawn on each change the store
/// notifies; lost workers' rollouts are closed as they are found. Ctrl-C stops following, not the batch.
async fn follow(store: &Store, url: &str, name: &str) -> anyhow::Result<()> {
    super::install_signal_handlers();
    let mut listener = QueueListener::connect(url).await?;
    let mut last = String::new();
    loop {
        for (batch, id) in store.expire_lost(worker_lost_record).await? {
            eprintln!("{batch}/{id}: INVALID ({WORKER_LOST}: its worker stopped renewing the lease)");
        }
        let Some(b) = store.batch(name).await? else { bail!("batch {name} left the store") };
        let doc = BatchDoc::from_value(b.doc).unwrap_or_default();
        let line = progress_line(&doc);
        if line != last {
            eprintln!("{line}");
            last = line;
        }
        if doc.status.as_deref() == Some("finished") {
            let invalid = doc.outcome_count(Outcome::Invalid.as_str());
            eprintln!("batch {name}: finished{}", if invalid > 0 { format!("; {invalid} INVALID (`run --resume` queues them again)") } else { String::new() });
            // A lost worker's record is partial: only the fields every record has are read.
            let records: Vec<RolloutSummary> = b.records.into_iter().map(|r| RolloutSummary::from_value(r).unwrap_or_default()).collect();
            for r in records.iter().filter(|r| r.outcome.as_deref() == Some(Outcome::Invalid.as_str())).take(10) {
                eprintln!("  {} INVALID: {}", r.rollout_id.as_deref().unwrap_or("?"), record_reason(r));
            }
            println!("{}", json!({"batch": name, "status": "finished", "counts": doc.counts, "outcomes": doc.outcomes}));
            // Every dashboard on this store lists it (`serve --store URL`); `report` reads it from the store.
            eprintln!("results: the Results page of any `libero-agent serve --store {}`", libero_store::redact(url));
            eprintln!("report: libero-agent report --store {} {name}", libero_store::redact(url));
            let rollouts = records.iter().map(|r| (r.rollout_id.as_deref().unwrap_or("?"), r.outcome.as_deref().unwrap_or("?"), Some(record_reason(r))));
            if let Some(msg) = super::batch::all_invalid_message(name, rollouts) {
                bail!("{msg}");
            }
            return Ok(());
        }
        if INTERRUPTED.load(std::sync::atomic::Ordering::SeqCst) {
            eprintln!("stopped following batch {name}; it goes on on the workers (`run --resume` with the same settings follows it again)");
            return Ok(());
        }
        // A notification wakes this at once; the timeout bounds how late a lost lease is noticed.
        listener.wait(Duration::from_secs(2)).await;
    }
}

/// Why a stored record did not count: its infrastructure error, else its termination reason.
fn record_reason(r: &RolloutSummary) -> String {
    r.reason().unwrap_or("no reason recorded").to_owned()
}

/// `[########------------] 5/12 ended · 3 running · 4 queued · SUCCESS 4, INVALID 1`
pub fn progress_line(doc: &BatchDoc) -> String {
    const WIDTH: u64 = 24;
    let total = doc.rollout_count.unwrap_or(0);
    let c = doc.counts.clone().unwrap_or_default();
    let (done, running, left) = (c.done.unwrap_or(0), c.running.unwrap_or(0), c.left.unwrap_or(0));
    let filled = (done * WIDTH).checked_div(total).unwrap_or(0).min(WIDTH);
    let outcomes: Vec<String> = doc.outcomes.iter().flatten().map(|(k, v)| format!("{k} {v}")).collect();
    format!(
        "[{}{}] {done}/{total} ended · {running} running · {left} queued · {}",
        "#".repeat(filled as usize),
        "-".repeat((WIDTH - filled) as usize),
        if outcomes.is_empty() { "no outcomes yet".to_owned() } else { outcomes.join(", ") }
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_progress_bar_fills_with_ended_rollouts() {
        let doc = json!({"rollout_count": 12, "counts": {"done": 6, "running": 3, "left": 3}, "outcomes": {"SUCCESS": 5, "INVALID": 1}});
        let doc = BatchDoc::from_value(doc).unwrap();
        assert_eq!(progress_line(&doc), format!("[{}{}] 6/12 ended · 3 running · 3 queued · INVALID 1, SUCCESS 5", "#".repeat(12), "-".repeat(12)));
        assert!(progress_line(&BatchDoc::default()).starts_with("[------------------------] 0/0 ended"));
    }

    #[test]
    fn a_queued_batch_document_has_every_key_its_readers_and_workers_expect() {
        let settings = BatchSettings {
            experiment: "main_table".into(), harness: "codex".into(), harness_version: None, model: "m".into(), effort: "high".into(), reps: 3,
            tasks: vec![14], pool_tasks: vec![], seed: 100, wall_time_s: 1800.0, max_agent_steps: 400, agent_cmd: None, sandbox: true,
        };
        let plan: PlannedRollout = serde_json::from_value(json!({"rollout_id": "w1_t14_level3", "task": "T14", "task_number": 14,
            "task_name": "close", "split": "short_horizon_easy", "stage_count": 1, "repetition": 1, "level": 3, "demo": "none"})).unwrap();
        let mut doc = batch_doc("b1", &settings, &[plan.clone(), plan], &["T99".into()], "postgres://u:secret@db/q");
        for stamp in ["created_at", "updated_at"] {
            assert!(doc[stamp].as_str().is_some_and(|t| t.ends_with('Z') || t.contains('+')), "{stamp}: {doc}");
            doc.as_object_mut().unwrap().remove(stamp);
        }
        assert_eq!(doc, json!({
            "schema_version": BATCH_SCHEMA, "name": "b1", "status": "queued", "settings": settings,
            "settings_sha256": settings.sha256(), "harness": {"name": "codex", "version": null}, "sandbox": null,
            "server_url": null, "workspace_root": null, "max_outer_retries": 0, "rollout_count": 2,
            "skipped_unimplemented_tasks": ["T99"], "counts": {"done": 0, "running": 0, "left": 2}, "running": [],
            "outcomes": {}, "queue": {"store": libero_store::redact("postgres://u:secret@db/q")},
        }));
        assert!(!doc.to_string().contains("secret"), "the store's password stays out of the document");
    }

    #[test]
    fn a_lost_rollout_is_invalid_with_reason_worker_lost() {
        let plan = json!({"rollout_id": "w1_t14_level3", "task": "T14", "task_number": 14, "task_name": "close", "split": "short_horizon_easy",
            "stage_count": 1, "repetition": 1, "level": 3, "demo": "none"});
        let rec: RolloutRecord = serde_json::from_value(worker_lost_record(&plan)).unwrap();
        assert_eq!((rec.outcome, rec.termination_reason.as_deref()), (Outcome::Invalid, Some(WORKER_LOST)));
        assert_eq!(rec.rollout_id, "w1_t14_level3");
        assert_eq!(worker_lost_record(&json!({"rollout_id": "x"}))["termination_reason"], WORKER_LOST);
    }
}
