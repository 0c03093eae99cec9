//! The rollout queue: batches that `run` enqueues and `worker` processes on any number of machines claim, one
//! rollout at a time, with a lease that heartbeats renew. The same SQL on both backends, with one difference:
//! PostgreSQL claims with `FOR UPDATE SKIP LOCKED` (concurrent claimers never wait on each other's rows), SQLite
//! serialises its writers anyway. Time is the database's clock (milliseconds since the epoch), so the machines'
//! clocks need not agree.
//!
//! A job is `queued`, `running` (claimed by a worker, lease until `lease_until_ms`) or `done` (its record is in the
//! `rollouts` table, written in the same transaction). The protocol's rule stands: nothing is retried on its own.
//! A running job whose lease ran out (its worker died) is closed with the record the caller makes
//! ([`Store::expire_lost`]: INVALID, `worker_lost`); only [`Store::requeue_invalid`] (`run --resume`) queues the
//! INVALID ones again. A worker that finishes a job it no longer holds is told so and its record is dropped, so a
//! rollout ends exactly once.
use crate::error::{Context, Result, StoreError};
use libero_records::batch_doc::{BatchDoc, RolloutSummary, RunningRollout};
use libero_records::json::utc_now_iso;
use serde::Serialize;
use serde_json::Value;
use sqlx::Row;

use crate::{Backend, Store, StoredBatch};

pub(crate) const QUEUE_TABLES: [&str; 3] = [
    "CREATE TABLE IF NOT EXISTS queue (batch TEXT NOT NULL, rollout_id TEXT NOT NULL, seq BIGINT NOT NULL, \
     plan TEXT NOT NULL, state TEXT NOT NULL, worker TEXT, lease_until_ms BIGINT, claimed_at_ms BIGINT, \
     enqueued_ms BIGINT NOT NULL, attempts BIGINT NOT NULL, outcome TEXT, PRIMARY KEY (batch, rollout_id))",
    "CREATE INDEX IF NOT EXISTS queue_by_state ON queue (state, enqueued_ms, seq)",
    "CREATE TABLE IF NOT EXISTS workers (id TEXT PRIMARY KEY, host TEXT NOT NULL, slots BIGINT NOT NULL, \
     live_url TEXT, started_at TEXT NOT NULL, seen_ms BIGINT NOT NULL)",
];

/// The PostgreSQL channel a `NOTIFY` goes to after every queue transition; the payload is the batch's name.
pub const QUEUE_CHANNEL: &str = "libero_queue";
/// The channel of episode transitions (prepared, started, ended); the payload is the episode id.
pub const EPISODE_CHANNEL: &str = "libero_episodes";

/// A claimed rollout.
#[derive(Debug, Clone, PartialEq)]
pub struct Job {
    pub batch: String,
    pub rollout_id: String,
    /// The rollout's plan as `run` enqueued it (JSON of the runner's `PlannedRollout`).
    pub plan: Value,
    /// How many times it was claimed (2 or more only after `run --resume` re-queued it).
    pub attempts: i64,
}

/// Where a queued batch stands.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct QueueProgress {
    pub total: u64,
    pub queued: u64,
    pub running: u64,
    pub done: u64,
    /// The running rollouts and the worker that holds each.
    pub running_on: Vec<(String, String)>,
}

impl QueueProgress {
    pub fn finished(&self) -> bool {
        self.total > 0 && self.done == self.total
    }
}

/// A worker as it registered, with the last time it was heard of.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct WorkerRow {
    pub id: String,
    pub host: String,
    pub slots: i64,
    /// The worker's own server (its live views), if it is reachable from elsewhere.
    pub live_url: Option<String>,
    pub started_at: String,
    pub seen_ms: i64,
}

impl Store {
    /// The database's clock in milliseconds, as SQL.
    fn now_ms(&self) -> &'static str {
        match self.backend {
            Backend::Postgres => "CAST(EXTRACT(EPOCH FROM clock_timestamp()) * 1000 AS BIGINT)",
            Backend::Sqlite => "CAST(unixepoch('subsec') * 1000 AS BIGINT)",
        }
    }

    /// The database's clock (ms since the epoch).
    pub async fn clock_ms(&self) -> Result<i64> {
        let row = sqlx::query(&format!("SELECT {} AS now", self.now_ms())).fetch_one(&self.pool).await.context("store: cannot read the clock")?;
        Ok(row.try_get("now")?)
    }

    /// Writes a new batch and queues its rollouts (`(rollout_id, plan)` in schedule order), in one transaction.
    /// Refused when the store already has a batch of that name.
    pub async fn enqueue(&self, batch: &StoredBatch, jobs: &[(String, Value)]) -> Result<()> {
        let name = &batch.name;
        let mut tx = self.pool.begin().await.context("store: cannot begin")?;
        if crate::write_batch_row(&mut tx, batch, "DO NOTHING").await? == 0 {
            return Err(StoreError::BatchExists(name.clone()));
        }
        let sql = format!(
            "INSERT INTO queue (batch, rollout_id, seq, plan, state, enqueued_ms, attempts) VALUES ($1, $2, $3, $4, 'queued', {}, 0)",
            self.now_ms()
        );
        for (seq, (rollout_id, plan)) in jobs.iter().enumerate() {
            sqlx::query(&sql)
                .bind(name)
                .bind(rollout_id)
                .bind(seq as i64)
                .bind(plan.to_string())
                .execute(&mut *tx)
                .await
                .with_context(|| format!("store: cannot queue rollout {rollout_id} of batch {name}"))?;
        }
        self.notify(&mut tx, name).await?;
        tx.commit().await.with_context(|| format!("store: cannot commit batch {name}"))
    }

    /// Replaces a batch's document (its settings and status), keeping its rollouts and jobs.
    pub async fn put_batch_doc(&self, name: &str, doc: &Value) -> Result<()> {
        sqlx::query("UPDATE batches SET doc = $2, updated_at = $3 WHERE name = $1")
            .bind(name)
            .bind(doc.to_string())
            .bind(utc_now_iso())
            .execute(&self.pool)
            .await
            .with_context(|| format!("store: cannot update batch {name}"))?;
        Ok(())
    }

    /// Claims the oldest queued rollout of any batch for `worker`, with a lease of `lease_ms`; `None` when nothing
    /// is queued.
    pub async fn claim(&self, worker: &str, lease_ms: i64) -> Result<Option<Job>> {
        let lock = match self.backend {
            Backend::Postgres => " FOR UPDATE SKIP LOCKED",
            Backend::Sqlite => "",
        };
        let now = self.now_ms();
        let sql = format!(
            "UPDATE queue SET state = 'running', worker = $1, lease_until_ms = {now} + $2, claimed_at_ms = {now}, \
             attempts = attempts + 1 \
             WHERE (batch, rollout_id) = (SELECT batch, rollout_id FROM queue WHERE state = 'queued' \
                                          ORDER BY enqueued_ms, batch, seq LIMIT 1{lock}) \
             RETURNING batch, rollout_id, plan, attempts"
        );
        let mut tx = self.pool.begin().await.context("store: cannot begin")?;
        let Some(row) = sqlx::query(&sql).bind(worker).bind(lease_ms).fetch_optional(&mut *tx).await.context("store: cannot claim a rollout")? else {
            return Ok(None);
        };
        let batch: String = row.try_get("batch")?;
        let plan_text: String = row.try_get("plan")?;
        let job = Job {
            rollout_id: row.try_get("rollout_id")?,
            plan: serde_json::from_str(&plan_text).with_context(|| format!("store: a queued plan of batch {batch} is not JSON"))?,
            attempts: row.try_get("attempts")?,
            batch,
        };
        self.refresh_doc(&mut tx, &job.batch).await?;
        self.notify(&mut tx, &job.batch).await?;
        tx.commit().await.context("store: cannot commit a claim")?;
        Ok(Some(job))
    }

    /// Renews the lease of every rollout `worker` runs and notes that it is alive; returns the rollouts it still
    /// holds (one missing here was closed as lost: its lease had run out).
    pub async fn heartbeat(&self, worker: &str, lease_ms: i64) -> Result<Vec<(String, String)>> {
        let now = self.now_ms();
        sqlx::query(&format!("UPDATE workers SET seen_ms = {now} WHERE id = $1"))
            .bind(worker)
            .execute(&self.pool)
            .await
            .context("store: cannot record a heartbeat")?;
        let rows = sqlx::query(&format!(
            "UPDATE queue SET lease_until_ms = {now} + $2 WHERE worker = $1 AND state = 'running' RETURNING batch, rollout_id"
        ))
        .bind(worker)
        .bind(lease_ms)
        .fetch_all(&self.pool)
        .await
        .context("store: cannot renew leases")?;
        rows.iter().map(|r| Ok((r.try_get("batch")?, r.try_get("rollout_id")?))).collect()
    }

    /// Records the end of a rollout `worker` holds: its record appended to the batch, the job done, in one
    /// transaction. `false` (and nothing written) when the worker no longer holds it.
    pub async fn finish(&self, batch: &str, rollout_id: &str, worker: &str, record: &Value) -> Result<bool> {
        self.close_job(batch, rollout_id, Some(worker), record).await
    }

    async fn close_job(&self, batch: &str, rollout_id: &str, worker: Option<&str>, record: &Value) -> Result<bool> {
        let now = self.now_ms();
        let mut tx = self.pool.begin().await.context("store: cannot begin")?;
        // The holder's own finish, or (no worker) the close of a lost one: only while its lease has run out.
        let guard = match worker {
            Some(_) => "worker = $4".to_owned(),
            None => format!("lease_until_ms < {now}"),
        };
        let sql = format!(
            "UPDATE queue SET state = 'done', outcome = $3, lease_until_ms = NULL \
             WHERE batch = $1 AND rollout_id = $2 AND state = 'running' AND {guard} RETURNING seq"
        );
        let outcome = RolloutSummary::from_value(record.clone()).ok().and_then(|r| r.outcome).unwrap_or_else(|| "INVALID".into());
        let mut query = sqlx::query(&sql).bind(batch).bind(rollout_id).bind(outcome);
        if let Some(w) = worker {
            query = query.bind(w);
        }
        let closed = query
            .fetch_optional(&mut *tx)
            .await
            .with_context(|| format!("store: cannot close rollout {rollout_id} of batch {batch}"))?;
        let Some(closed) = closed else {
            return Ok(false);
        };
        let job_seq: i64 = closed.try_get("seq")?;
        // Records are read back in the order they ended: the database's clock, then the schedule's order.
        sqlx::query(&format!("INSERT INTO rollouts (batch, seq, rollout_id, doc) VALUES ($1, {now} * 100000 + $2, $3, $4)"))
            .bind(batch)
            .bind(job_seq)
            .bind(rollout_id)
            .bind(record.to_string())
            .execute(&mut *tx)
            .await
            .with_context(|| format!("store: cannot record rollout {rollout_id} of batch {batch}"))?;
        self.refresh_doc(&mut tx, batch).await?;
        self.notify(&mut tx, batch).await?;
        tx.commit().await.with_context(|| format!("store: cannot commit rollout {rollout_id} of batch {batch}"))?;
        Ok(true)
    }

    /// Closes every running rollout whose lease ran out (its worker died or lost the database) with the record
    /// `lost(plan)` makes; returns `(batch, rollout_id)` of each. Any worker or follower may call it: a rollout is
    /// closed once.
    pub async fn expire_lost(&self, lost: impl Fn(&Value) -> Value) -> Result<Vec<(String, String)>> {
        let rows = sqlx::query(&format!("SELECT batch, rollout_id, plan FROM queue WHERE state = 'running' AND lease_until_ms < {}", self.now_ms()))
            .fetch_all(&self.pool)
            .await
            .context("store: cannot look for lost rollouts")?;
        let mut closed = Vec::new();
        for r in rows {
            let (batch, rollout_id, plan): (String, String, String) = (r.try_get("batch")?, r.try_get("rollout_id")?, r.try_get("plan")?);
            let plan: Value = serde_json::from_str(&plan).unwrap_or(Value::Null);
            if self.close_job(&batch, &rollout_id, None, &lost(&plan)).await? {
                closed.push((batch, rollout_id));
            }
        }
        Ok(closed)
    }

    /// Queues a batch's INVALID rollouts again (`run --resume`): their records are removed, their jobs queued.
    /// Returns their ids.
    pub async fn requeue_invalid(&self, batch: &str) -> Result<Vec<String>> {
        let mut tx = self.pool.begin().await.context("store: cannot begin")?;
        let rows = sqlx::query("UPDATE queue SET state = 'queued', worker = NULL, outcome = NULL, lease_until_ms = NULL \
                                WHERE batch = $1 AND state = 'done' AND outcome = 'INVALID' RETURNING rollout_id")
            .bind(batch)
            .fetch_all(&mut *tx)
            .await
            .with_context(|| format!("store: cannot re-queue the INVALID rollouts of batch {batch}"))?;
        let ids: Vec<String> = rows.iter().map(|r| r.try_get("rollout_id")).collect::<Result<_, _>>()?;
        for id in &ids {
            sqlx::query("DELETE FROM rollouts WHERE batch = $1 AND rollout_id = $2")
                .bind(batch)
                .bind(id)
                .execute(&mut *tx)
                .await
                .with_context(|| format!("store: cannot remove the record of {id}"))?;
        }
        self.refresh_doc(&mut tx, batch).await?;
        self.notify(&mut tx, batch).await?;
        tx.commit().await.context("store: cannot commit the re-queue")?;
        Ok(ids)
    }

    /// Where a queued batch stands (all zero for a batch that was not queued).
    pub async fn queue_progress(&self, batch: &str) -> Result<QueueProgress> {
        let rows = sqlx::query("SELECT rollout_id, state, worker FROM queue WHERE batch = $1 ORDER BY seq")
            .bind(batch)
            .fetch_all(&self.pool)
            .await
            .with_context(|| format!("store: cannot read the queue of batch {batch}"))?;
        let mut p = QueueProgress::default();
        for r in rows {
            p.total += 1;
            match r.try_get::<String, _>("state")?.as_str() {
                "queued" => p.queued += 1,
                "running" => {
                    p.running += 1;
                    p.running_on.push((r.try_get("rollout_id")?, r.try_get::<Option<String>, _>("worker")?.unwrap_or_default()));
                }
                _ => p.done += 1,
            }
        }
        Ok(p)
    }

    /// Registers (or re-registers) a worker.
    pub async fn register_worker(&self, id: &str, host: &str, slots: i64, live_url: Option<&str>) -> Result<()> {
        sqlx::query(&format!(
            "INSERT INTO workers (id, host, slots, live_url, started_at, seen_ms) VALUES ($1, $2, $3, $4, $5, {}) \
             ON CONFLICT (id) DO UPDATE SET host = excluded.host, slots = excluded.slots, live_url = excluded.live_url, \
             started_at = excluded.started_at, seen_ms = excluded.seen_ms",
            self.now_ms()
        ))
        .bind(id)
        .bind(host)
        .bind(slots)
        .bind(live_url)
        .bind(utc_now_iso())
        .execute(&self.pool)
        .await
        .context("store: cannot register the worker")?;
        Ok(())
    }

    /// The registered workers, most recently heard of first.
    pub async fn workers(&self) -> Result<Vec<WorkerRow>> {
        let rows = sqlx::query("SELECT id, host, slots, live_url, started_at, seen_ms FROM workers ORDER BY seen_ms DESC")
            .fetch_all(&self.pool)
            .await
            .context("store: cannot list workers")?;
        rows.iter()
            .map(|r| {
                Ok(WorkerRow {
                    id: r.try_get("id")?,
                    host: r.try_get("host")?,
                    slots: r.try_get("slots")?,
                    live_url: r.try_get("live_url")?,
                    started_at: r.try_get("started_at")?,
                    seen_ms: r.try_get("seen_ms")?,
                })
            })
            .collect()
    }

    /// Rewrites the batch document's progress (`status`, `counts`, `running`, `outcomes`, as `batch.json` has them)
    /// from its jobs, inside the transaction that changed them: the document is current whoever changed the queue,
    /// with or without a follower. The batch row is locked first on PostgreSQL, so concurrent changes of one batch
    /// write their documents in turn.
    async fn refresh_doc(&self, tx: &mut sqlx::Transaction<'_, sqlx::Any>, batch: &str) -> Result<()> {
        let lock = if self.backend == Backend::Postgres { " FOR UPDATE" } else { "" };
        let Some(row) = sqlx::query(&format!("SELECT doc FROM batches WHERE name = $1{lock}"))
            .bind(batch)
            .fetch_optional(&mut **tx)
            .await
            .with_context(|| format!("store: cannot read batch {batch}"))?
        else {
            return Ok(());
        };
        // a document that is not an object is left as it is
        let Ok(mut doc) = serde_json::from_str::<BatchDoc>(&row.try_get::<String, _>("doc")?) else { return Ok(()) };
        let jobs = sqlx::query(
            "SELECT q.rollout_id, q.state, q.outcome, q.worker, w.host, w.live_url FROM queue q \
             LEFT JOIN workers w ON w.id = q.worker WHERE q.batch = $1 ORDER BY q.seq",
        )
            .bind(batch)
            .fetch_all(&mut **tx)
            .await
            .with_context(|| format!("store: cannot read the queue of batch {batch}"))?;
        let (mut ended, mut running, mut left) = (Vec::new(), Vec::new(), 0u64);
        for j in &jobs {
            match j.try_get::<String, _>("state")?.as_str() {
                "queued" => left += 1,
                // which worker runs what, and where its own live views are (`worker --public-url`)
                "running" => running.push(RunningRollout {
                    rollout_id: Some(j.try_get("rollout_id")?),
                    worker: Some(j.try_get("worker")?),
                    host: Some(j.try_get("host")?),
                    live_url: Some(j.try_get("live_url")?),
                    ..Default::default()
                }),
                _ => ended.push(j.try_get::<Option<String>, _>("outcome")?.unwrap_or_else(|| "INVALID".into())),
            }
        }
        doc.set_progress(ended.iter().map(String::as_str), running, left);
        doc.updated_at = Some(utc_now_iso());
        let doc = doc.to_value();
        sqlx::query("UPDATE batches SET doc = $2, updated_at = $3 WHERE name = $1")
            .bind(batch)
            .bind(doc.to_string())
            .bind(utc_now_iso())
            .execute(&mut **tx)
            .await
            .with_context(|| format!("store: cannot update batch {batch}"))?;
        Ok(())
    }

    /// Tells PostgreSQL listeners (`LISTEN libero_queue`) that `batch` changed, when the transaction commits.
    async fn notify(&self, tx: &mut sqlx::Transaction<'_, sqlx::Any>, batch: &str) -> Result<()> {
        if self.backend == Backend::Postgres {
            sqlx::query("SELECT pg_notify($1, $2)")
                .bind(QUEUE_CHANNEL)
                .bind(batch)
                .execute(&mut **tx)
                .await
                .context("store: cannot notify the queue's listeners")?;
        }
        Ok(())
    }
}

/// Waits for queue changes: PostgreSQL's `LISTEN libero_queue` (woken at once by any machine's change), or a
/// poll on SQLite. `wait` returns after a change or `timeout`, whichever comes first.
pub enum QueueListener {
    Postgres(sqlx::postgres::PgListener),
    Poll,
}

impl QueueListener {
    pub async fn connect(url: &str) -> Result<Self> {
        Self::connect_to(url, &[QUEUE_CHANNEL]).await
    }

    /// Listens on `channels` ([`QUEUE_CHANNEL`], [`EPISODE_CHANNEL`]).
    pub async fn connect_to(url: &str, channels: &[&str]) -> Result<Self> {
        match Backend::of_url(url)? {
            Backend::Postgres => {
                let mut l = sqlx::postgres::PgListener::connect(url)
                    .await
                    .with_context(|| format!("cannot listen on the store {}", crate::redact(url)))?;
                l.listen_all(channels.iter().copied()).await.context("store: cannot LISTEN")?;
                Ok(Self::Postgres(l))
            }
            Backend::Sqlite => Ok(Self::Poll),
        }
    }

    /// Returns the batch that changed, or `None` on timeout (or on SQLite, after the timeout).
    pub async fn wait(&mut self, timeout: std::time::Duration) -> Option<String> {
        match self {
            Self::Postgres(l) => match tokio::time::timeout(timeout, l.recv()).await {
                Ok(Ok(n)) => Some(n.payload().to_owned()),
                _ => None,
            },
            Self::Poll => {
                tokio::time::sleep(timeout).await;
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;
    use std::path::PathBuf;

    use serde_json::json;

    use crate::testing::TestPostgres;
    use crate::{STORE_FILE, Store, StoredBatch};

    fn batch(name: &str) -> StoredBatch {
        StoredBatch { name: name.into(), dir: PathBuf::new(), doc: json!({"status": "queued"}), records: Vec::new() }
    }

    fn jobs(n: usize) -> Vec<(String, serde_json::Value)> {
        (0..n).map(|i| (format!("r{i}"), json!({"rollout_id": format!("r{i}"), "task": "T14"}))).collect()
    }

    fn record(id: &str, outcome: &str) -> serde_json::Value {
        json!({"rollout_id": id, "outcome": outcome})
    }

    /// Four claimers at once take six rollouts: each exactly once, in schedule order per claimer, and nothing is
    /// left to claim.
    async fn concurrent_claims_take_each_rollout_once(store: Store) {
        store.enqueue(&batch("b"), &jobs(6)).await.unwrap();
        assert!(store.enqueue(&batch("b"), &jobs(1)).await.is_err(), "a batch name is enqueued once");
        let claimers: Vec<_> = (0..4)
            .map(|w| {
                let store = store.clone();
                tokio::spawn(async move {
                    let mut got = Vec::new();
                    while let Some(job) = store.claim(&format!("w{w}"), 60_000).await.unwrap() {
                        got.push(job.rollout_id);
                    }
                    got
                })
            })
            .collect();
        let mut all = Vec::new();
        for c in claimers {
            all.extend(c.await.unwrap());
        }
        all.sort();
        assert_eq!(all, ["r0", "r1", "r2", "r3", "r4", "r5"], "every rollout claimed exactly once");
        let p = store.queue_progress("b").await.unwrap();
        assert_eq!((p.total, p.queued, p.running, p.done), (6, 0, 6, 0));
    }

    /// A holder's finish records once; a lost lease is closed by anyone with the caller's record, the late holder's
    /// finish is then refused, and only `requeue_invalid` queues it again.
    async fn a_lost_lease_ends_the_rollout_once_and_resume_requeues_it(store: Store) {
        store.enqueue(&batch("b"), &jobs(3)).await.unwrap();
        let a = store.claim("alive", 60_000).await.unwrap().unwrap();
        let b = store.claim("dead", 1).await.unwrap().unwrap();
        assert_eq!((a.rollout_id.as_str(), b.rollout_id.as_str(), a.attempts), ("r0", "r1", 1));
        assert!(!store.finish("b", "r0", "dead", &record("r0", "SUCCESS")).await.unwrap(), "only the holder finishes");
        assert!(store.finish("b", "r0", "alive", &record("r0", "SUCCESS")).await.unwrap());
        assert!(!store.finish("b", "r0", "alive", &record("r0", "SUCCESS")).await.unwrap(), "a rollout ends once");
        tokio::time::sleep(std::time::Duration::from_millis(30)).await;
        assert_eq!(store.heartbeat("dead", 60_000).await.unwrap(), [("b".to_owned(), "r1".to_owned())], "a heartbeat renews");
        assert!(store.expire_lost(|_| unreachable!()).await.unwrap().is_empty(), "a renewed lease is not lost");
        sqlx::query("UPDATE queue SET lease_until_ms = 0 WHERE rollout_id = 'r1'").execute(&store.pool).await.unwrap();
        let lost = store.expire_lost(|plan| record(plan["rollout_id"].as_str().unwrap(), "INVALID")).await.unwrap();
        assert_eq!(lost, [("b".to_owned(), "r1".to_owned())]);
        assert!(store.expire_lost(|_| unreachable!()).await.unwrap().is_empty(), "closed once");
        assert!(!store.finish("b", "r1", "dead", &record("r1", "SUCCESS")).await.unwrap(), "the lost holder's late finish is dropped");
        assert!(store.heartbeat("dead", 60_000).await.unwrap().is_empty(), "the lost holder learns it holds nothing");
        let stored = store.batch("b").await.unwrap().unwrap();
        let ended: Vec<(&str, &str)> = stored.records.iter().map(|r| (r["rollout_id"].as_str().unwrap(), r["outcome"].as_str().unwrap())).collect();
        assert_eq!(ended, [("r0", "SUCCESS"), ("r1", "INVALID")]);
        let p = store.queue_progress("b").await.unwrap();
        assert_eq!((p.queued, p.running, p.done), (1, 0, 2));
        let doc = store.batch("b").await.unwrap().unwrap().doc;
        assert_eq!((doc["status"].as_str(), &doc["counts"]), (Some("running"), &json!({"done": 2, "running": 0, "left": 1})));
        assert_eq!(doc["outcomes"], json!({"SUCCESS": 1, "INVALID": 1}));

        assert_eq!(store.requeue_invalid("b").await.unwrap(), ["r1"]);
        assert!(store.requeue_invalid("b").await.unwrap().is_empty());
        let ids: BTreeSet<String> = store.batch("b").await.unwrap().unwrap().records.iter().map(|r| r["rollout_id"].as_str().unwrap().to_owned()).collect();
        assert_eq!(ids, BTreeSet::from(["r0".to_owned()]), "the INVALID record is gone with the re-queue");
        let again = store.claim("alive", 60_000).await.unwrap().unwrap();
        assert_eq!((again.rollout_id.as_str(), again.attempts), ("r1", 2), "a re-queued rollout comes first again");
        let last = store.claim("alive", 60_000).await.unwrap().unwrap();
        assert_eq!(last.rollout_id, "r2");
        assert!(store.claim("alive", 60_000).await.unwrap().is_none());
        for id in ["r1", "r2"] {
            assert!(store.finish("b", id, "alive", &record(id, "FAIL")).await.unwrap());
        }
        assert!(store.queue_progress("b").await.unwrap().finished());
        let b = store.batch("b").await.unwrap().unwrap();
        assert_eq!(b.records.len(), 3);
        assert_eq!(b.doc["status"], "finished", "the document follows the queue");
        assert_eq!(b.doc["counts"], json!({"done": 3, "running": 0, "left": 0}));
        assert_eq!(b.doc["outcomes"], json!({"SUCCESS": 1, "FAIL": 2}));
    }

    async fn workers_register_and_are_listed(store: Store) {
        store.register_worker("w1", "host-a", 2, Some("http://10.0.0.5:8080")).await.unwrap();
        store.register_worker("w1", "host-a", 3, None).await.unwrap();
        let w = store.workers().await.unwrap();
        assert_eq!(w.len(), 1);
        assert_eq!((w[0].slots, w[0].live_url.as_deref()), (3, None));
        assert!((w[0].seen_ms - store.clock_ms().await.unwrap()).abs() < 60_000);
    }

    async fn sqlite() -> (tempfile::TempDir, Store) {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&dir.path().join(STORE_FILE)).await.unwrap();
        (dir, store)
    }

    #[tokio::test]
    async fn sqlite_concurrent_claims_take_each_rollout_once() {
        let (_d, store) = sqlite().await;
        concurrent_claims_take_each_rollout_once(store).await;
    }

    #[tokio::test]
    async fn postgres_concurrent_claims_take_each_rollout_once() {
        let pg = TestPostgres::start();
        concurrent_claims_take_each_rollout_once(Store::connect(&pg.url).await.unwrap()).await;
    }

    #[tokio::test]
    async fn sqlite_a_lost_lease_ends_the_rollout_once_and_resume_requeues_it() {
        let (_d, store) = sqlite().await;
        a_lost_lease_ends_the_rollout_once_and_resume_requeues_it(store.clone()).await;
        workers_register_and_are_listed(store).await;
    }

    #[tokio::test]
    async fn postgres_a_lost_lease_ends_the_rollout_once_and_resume_requeues_it() {
        let pg = TestPostgres::start();
        let store = Store::connect(&pg.url).await.unwrap();
        a_lost_lease_ends_the_rollout_once_and_resume_requeues_it(store.clone()).await;
        workers_register_and_are_listed(store).await;
    }

    /// A change on one connection wakes a listener on another at once (PostgreSQL's LISTEN/NOTIFY).
    #[tokio::test]
    async fn postgres_listeners_hear_of_every_queue_change() {
        let pg = TestPostgres::start();
        let store = Store::connect(&pg.url).await.unwrap();
        let mut listener = super::QueueListener::connect(&pg.url).await.unwrap();
        store.enqueue(&batch("heard"), &jobs(1)).await.unwrap();
        let t = std::time::Instant::now();
        assert_eq!(listener.wait(std::time::Duration::from_secs(10)).await.as_deref(), Some("heard"));
        assert!(t.elapsed() < std::time::Duration::from_secs(9), "woken by the notification, not the timeout");
        store.claim("w", 1000).await.unwrap().unwrap();
        assert_eq!(listener.wait(std::time::Duration::from_secs(10)).await.as_deref(), Some("heard"));
    }
}
