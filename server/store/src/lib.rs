//! The episode store: one row per prepared episode (task, level, seed, init state, times, outcome of §4.8,
//! reason, stage counts, run directory), written when an episode is prepared, when it starts and when it
//! ends. Two backends through sqlx's `Any` driver, chosen by URL (`--store`): `sqlite://PATH` (the embedded
//! default, `<data>/episodes.sqlite`) or `postgres://…` (one store shared by several servers). The SQL is
//! plain (`$n` placeholders, `BIGINT`/`BOOLEAN`/`TEXT`, `ON CONFLICT DO NOTHING`), the same statements on
//! both. The run directories stay the source of truth: at startup [`Store::reconcile`] rebuilds any row the
//! files know better (a crash between `result.json` and the store write loses nothing), and closes only the
//! open rows of its own run directories (another server's running episodes in a shared store stay open).
use std::path::{Path, PathBuf};

use libero_records::batch_doc::RolloutSummary;
use libero_records::episode_view::EpisodeView;
use libero_records::json::utc_now_iso;
use libero_records::records::{Outcome, RunDir, RunResult, classify, read_episode_record, read_result};
use serde::Serialize;
use serde_json::Value;
use sqlx::Row;
use sqlx::AnyPool;
use sqlx::any::{AnyPoolOptions, AnyRow};

mod error;
pub mod queue;
pub use error::{Result, StoreError};
use error::Context;
pub use queue::{EPISODE_CHANNEL, Job, QUEUE_CHANNEL, QueueListener, QueueProgress, WorkerRow};

/// File name of the store inside the data directory.
pub const STORE_FILE: &str = "episodes.sqlite";
/// Reason stored for a row whose episode was open when the server went away and whose run directory is gone.
pub const MISSING_RUN_REASON: &str = "server_stopped_before_finish: the run directory was missing at restart";

const SCHEMA: &str = "CREATE TABLE IF NOT EXISTS episodes (
    id TEXT PRIMARY KEY,
    task_ref TEXT NOT NULL,
    level BIGINT NOT NULL,
    seed BIGINT NOT NULL,
    init_index BIGINT NOT NULL,
    created_at TEXT NOT NULL,
    started_at TEXT,
    finished_at TEXT,
    outcome TEXT,
    reason TEXT,
    success BOOLEAN,
    accepted_agent_steps BIGINT,
    completed_stage_count BIGINT,
    required_stage_count BIGINT,
    run_dir TEXT NOT NULL
)";

/// Batches of `libero-agent run` and their ended rollouts, as the batch directory holds them (`batch.json`, the
/// lines of `rollouts.jsonl` in order): `run --store` writes them, `report --store` reads them back. `dir` is
/// where the batch's files are on the machine that ran it.
const BATCH_TABLES: [&str; 4] = [
    "CREATE TABLE IF NOT EXISTS batches (name TEXT PRIMARY KEY, dir TEXT NOT NULL, doc TEXT NOT NULL, updated_at TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS rollouts (batch TEXT NOT NULL, seq BIGINT NOT NULL, rollout_id TEXT NOT NULL, doc TEXT NOT NULL, \
     PRIMARY KEY (batch, seq))",
    // A person's judgment of one stage of one episode (the latest per stage) …
    "CREATE TABLE IF NOT EXISTS stage_annotations (episode_id TEXT NOT NULL, stage_name TEXT NOT NULL, doc TEXT NOT NULL, \
     annotator TEXT NOT NULL, annotated_at TEXT NOT NULL, PRIMARY KEY (episode_id, stage_name))",
    // … and every one ever saved, in order.
    "CREATE TABLE IF NOT EXISTS stage_annotation_history (episode_id TEXT NOT NULL, stage_name TEXT NOT NULL, doc TEXT NOT NULL, \
     annotator TEXT NOT NULL, annotated_at TEXT NOT NULL)",
];

/// Creates the tables and adds the columns later versions added (idempotent: every server and worker runs it).
async fn create_schema(conn: &mut sqlx::AnyConnection, backend: Backend, url: &str) -> Result<()> {
    sqlx::query(SCHEMA).execute(&mut *conn).await.context("cannot create the episodes table")?;
    for sql in BATCH_TABLES.iter().chain(queue::QUEUE_TABLES.iter()) {
        sqlx::query(sql).execute(&mut *conn).await.context("cannot create the batch and queue tables")?;
    }
    for (name, kind) in ADDED_COLUMNS {
        let sql = match backend {
            Backend::Postgres => format!("ALTER TABLE episodes ADD COLUMN IF NOT EXISTS {name} {kind}"),
            // SQLite has no IF NOT EXISTS here: a store written by this version has the column already
            Backend::Sqlite => format!("ALTER TABLE episodes ADD COLUMN {name} {kind}"),
        };
        if let Err(e) = sqlx::query(&sql).execute(&mut *conn).await
            && !e.to_string().to_ascii_lowercase().contains("duplicate column")
        {
            return Err(StoreError::Database { what: format!("cannot add column {name} to the episode store {}", redact(url)), cause: e });
        }
    }
    Ok(())
}

/// Inserts `batch`'s row (name, dir, document); `on_conflict` says what an existing row of that name gets
/// (`DO NOTHING`, `DO UPDATE SET …`). Returns the rows written.
async fn write_batch_row(tx: &mut sqlx::Transaction<'_, sqlx::Any>, batch: &StoredBatch, on_conflict: &str) -> Result<u64> {
    let written = sqlx::query(&format!("INSERT INTO batches (name, dir, doc, updated_at) VALUES ($1, $2, $3, $4) ON CONFLICT (name) {on_conflict}"))
        .bind(&batch.name)
        .bind(batch.dir.to_string_lossy().into_owned())
        .bind(batch.doc.to_string())
        .bind(utc_now_iso())
        .execute(&mut **tx)
        .await
        .with_context(|| format!("store: cannot write batch {}", batch.name))?;
    Ok(written.rows_affected())
}

/// A batch as the store holds it: `batch.json`'s document and the `rollouts.jsonl` records in order.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredBatch {
    pub name: String,
    pub dir: PathBuf,
    pub doc: Value,
    pub records: Vec<Value>,
}

/// The PostgreSQL advisory lock that serialises schema creation and upgrades across every process on the store
/// (an arbitrary constant: "libero" in ASCII).
const SCHEMA_LOCK_KEY: i64 = 0x6c_6962_6572_6f;

/// Nullable columns added after the first schema (the dashboard's filters and wall time); added in place to an
/// older store by [`Store::open`].
const ADDED_COLUMNS: [(&str, &str); 7] = [
    ("harness", "TEXT"),
    ("model", "TEXT"),
    ("batch", "TEXT"),
    ("wall_time_s", "DOUBLE PRECISION"),
    ("server_url", "TEXT"),
    ("branch_parent", "TEXT"),
    ("branch_step", "BIGINT"),
];

/// The columns of a row as read back. `success` is read as a number: sqlx's `Any` driver decodes PostgreSQL's
/// BOOLEAN but not SQLite's.
const COLUMNS: &str = "id, task_ref, level, seed, init_index, created_at, started_at, finished_at, outcome, reason, \
    CAST(CASE WHEN success THEN 1 WHEN NOT success THEN 0 END AS BIGINT) AS success, accepted_agent_steps, completed_stage_count, required_stage_count, run_dir, harness, model, batch, \
    wall_time_s, server_url, branch_parent, branch_step";

/// The dashboard's episode filters (`None`: any). Outcome `RUNNING` selects episodes without an outcome yet.
#[derive(Debug, Clone, Default, PartialEq, serde::Deserialize)]
pub struct EpisodeFilter {
    pub task: Option<String>,
    pub outcome: Option<String>,
    pub batch: Option<String>,
    /// `expert`, `teleop`, `command`, `codex`, …
    #[serde(default)]
    pub harness: Option<String>,
}

impl EpisodeFilter {
    /// Empty strings (an empty form field) mean no filter.
    pub fn normalized(self) -> Self {
        let keep = |v: Option<String>| v.map(|s| s.trim().to_owned()).filter(|s| !s.is_empty());
        Self {
            task: keep(self.task),
            outcome: keep(self.outcome).map(|o| o.to_uppercase()),
            batch: keep(self.batch),
            harness: keep(self.harness),
        }
    }
}

/// One stored episode. The run directory is private: the HTTP API leaves it out (see [`EpisodeRow::view`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EpisodeRow {
    #[serde(flatten)]
    pub episode: NewEpisode,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    /// `SUCCESS | FAIL | SIM_TIMEOUT | INVALID`, null while the episode is open.
    pub outcome: Option<String>,
    pub reason: Option<String>,
    pub success: Option<bool>,
    pub accepted_agent_steps: Option<i64>,
    pub completed_stage_count: Option<i64>,
    pub required_stage_count: Option<i64>,
    /// Episode wall time (`result.json`), once ended.
    pub wall_time_s: Option<f64>,
}

impl EpisodeRow {
    /// The row as the operator API shows it: everything but filesystem paths, without the live fields (the
    /// server adds those for an episode it runs).
    pub fn view(&self) -> EpisodeView {
        let e = &self.episode;
        let count = |n: Option<i64>| n.and_then(|n| u64::try_from(n).ok());
        EpisodeView {
            accepted_agent_steps: count(self.accepted_agent_steps),
            batch: e.batch.clone(),
            branch_parent: e.branch_parent.clone(),
            branch_step: e.branch_step,
            completed_stage_count: count(self.completed_stage_count),
            created_at: e.created_at.clone(),
            finished_at: self.finished_at.clone(),
            harness: e.harness.clone(),
            id: e.id.clone(),
            init_index: e.init_index,
            latest_observation_id: None,
            level: e.level,
            model: e.model.clone(),
            // Written by `Outcome::as_str` only.
            outcome: self.outcome.as_deref().and_then(|o| o.parse().ok()),
            reason: self.reason.clone(),
            required_stage_count: count(self.required_stage_count),
            seed: e.seed,
            server_url: e.server_url.clone(),
            started_at: self.started_at.clone(),
            state: None,
            success: self.success,
            task_ref: e.task_ref.clone(),
            wall_time_s: self.wall_time_s,
        }
    }

    fn from_row(r: &AnyRow) -> Result<Self, sqlx::Error> {
        let episode = NewEpisode {
            id: r.try_get("id")?,
            task_ref: r.try_get("task_ref")?,
            level: r.try_get("level")?,
            seed: r.try_get("seed")?,
            init_index: r.try_get("init_index")?,
            created_at: r.try_get("created_at")?,
            run_dir: PathBuf::from(r.try_get::<String, _>("run_dir")?),
            harness: r.try_get("harness")?,
            model: r.try_get("model")?,
            batch: r.try_get("batch")?,
            server_url: r.try_get("server_url")?,
            branch_parent: r.try_get("branch_parent")?,
            branch_step: r.try_get("branch_step")?,
        };
        Ok(Self {
            episode,
            started_at: r.try_get("started_at")?,
            finished_at: r.try_get("finished_at")?,
            outcome: r.try_get("outcome")?,
            reason: r.try_get("reason")?,
            success: r.try_get::<Option<i64>, _>("success")?.map(|v| v != 0),
            accepted_agent_steps: r.try_get("accepted_agent_steps")?,
            completed_stage_count: r.try_get("completed_stage_count")?,
            required_stage_count: r.try_get("required_stage_count")?,
            wall_time_s: r.try_get("wall_time_s")?,
        })
    }
}

/// How an episode ended, as `result.json` says.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeEnd {
    pub finished_at: String,
    pub outcome: Outcome,
    pub reason: Option<String>,
    pub success: bool,
    pub accepted_agent_steps: Option<i64>,
    pub completed_stage_count: Option<i64>,
    pub required_stage_count: Option<i64>,
    pub wall_time_s: Option<f64>,
}

impl EpisodeEnd {
    /// From a run directory's `result.json` (None while it has none).
    pub fn from_run(run: &RunDir) -> Option<Self> {
        let result = read_result(run)?;
        Some(Self::from_result(&result))
    }

    pub fn from_result(result: &RunResult) -> Self {
        let outcome = classify(Some(result));
        let eval = result.private_evaluation.as_ref();
        let count = |n: Option<u64>| n.and_then(|n| i64::try_from(n).ok());
        Self {
            finished_at: result.finished_at.clone().unwrap_or_else(utc_now_iso),
            outcome,
            reason: result.reason.clone().or_else(|| result.termination_reason.clone()),
            success: outcome == Outcome::Success,
            accepted_agent_steps: count(result.accepted_agent_steps),
            completed_stage_count: count(eval.and_then(|e| e.completed_required_stage_count)),
            required_stage_count: count(eval.and_then(|e| e.required_stage_count)),
            wall_time_s: result.wall_time_s(),
        }
    }
}

/// What is known when an episode is prepared.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NewEpisode {
    pub id: String,
    pub task_ref: String,
    pub level: i64,
    pub seed: i64,
    pub init_index: i64,
    pub created_at: String,
    pub run_dir: PathBuf,
    /// Agent harness and model driving the episode, and the batch it belongs to, where the preparer said.
    pub harness: Option<String>,
    pub model: Option<String>,
    pub batch: Option<String>,
    /// The URL of the server that runs the episode (its `--public-url`), where its live view is: a dashboard on
    /// another machine links there while the episode is open.
    pub server_url: Option<String>,
    /// A branch's parent episode and the control step it branched at (issue 33).
    pub branch_parent: Option<String>,
    pub branch_step: Option<i64>,
}

impl NewEpisode {
    /// From a run directory's `episode_record.json` (written by `prepare` before anything else).
    pub fn from_record(run: &RunDir) -> Option<Self> {
        let r = read_episode_record(run).ok()??;
        let int = |n: Option<u64>| n.and_then(|n| i64::try_from(n).ok());
        let branch = r.branch.as_ref();
        Some(Self {
            id: r.episode_id.clone()?,
            task_ref: r.task_ref()?.to_owned(),
            level: int(r.level)?,
            seed: int(r.seed)?,
            init_index: int(r.init_state_index)?,
            created_at: r.created_at.clone()?,
            run_dir: run.root.clone(),
            harness: r.harness.clone().flatten(),
            model: r.model.clone().flatten(),
            batch: r.batch.clone().flatten(),
            server_url: None,
            branch_parent: branch.and_then(|b| b.parent_episode_id.clone()),
            branch_step: int(branch.and_then(|b| b.parent_control_step)),
        })
    }
}

/// Connections of the store's pool.
const STORE_CONNECTIONS: u32 = 4;

/// Which engine a store URL names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    Sqlite,
    Postgres,
}

impl Backend {
    pub fn of_url(url: &str) -> Result<Self> {
        match url.split_once(':').map(|(scheme, _)| scheme) {
            Some("sqlite") => Ok(Backend::Sqlite),
            Some("postgres" | "postgresql") => Ok(Backend::Postgres),
            _ => Err(StoreError::BadUrl(redact(url))),
        }
    }
}

/// A store URL without its password, for messages.
pub fn redact(url: &str) -> String {
    match (url.find("://"), url.rfind('@')) {
        (Some(s), Some(at)) if at > s => match url[s + 3..at].split_once(':') {
            Some((user, _)) => format!("{}{user}:***{}", &url[..s + 3], &url[at..]),
            None => url.to_owned(),
        },
        _ => url.to_owned(),
    }
}

/// The URL of the embedded store at `path`, created when missing. The path is percent-encoded: a data directory
/// may be named anything (`?`, `#`, `%`, spaces), and sqlx decodes the path part of the URL.
pub fn sqlite_url(path: &Path) -> String {
    use std::os::unix::ffi::OsStrExt;
    let mut encoded = String::new();
    for &b in path.as_os_str().as_bytes() {
        if b.is_ascii_alphanumeric() || b"/-_.~".contains(&b) {
            encoded.push(char::from(b));
        } else {
            encoded.push_str(&format!("%{b:02X}"));
        }
    }
    format!("sqlite://{encoded}?mode=rwc")
}

/// Switches a SQLite store to WAL (kept in the file). Changing the journal mode needs the file to itself, and SQLite
/// answers "database is locked" at once, without its busy handler, while another opener of a fresh file holds it
/// (workers started together on one file): so the switch is retried for up to ten seconds before it is an error.
async fn switch_to_wal(pool: &AnyPool) -> Result<()> {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    let mut wait_ms = 5u64;
    loop {
        match sqlx::query("PRAGMA journal_mode=WAL").execute(pool).await {
            Ok(_) => return Ok(()),
            Err(e) if is_sqlite_busy(&e) && std::time::Instant::now() < deadline => {
                tokio::time::sleep(std::time::Duration::from_millis(wait_ms)).await;
                wait_ms = (wait_ms * 2).min(200);
            }
            Err(e) => return Err(e).context("cannot switch the store to WAL"),
        }
    }
}

/// SQLITE_BUSY (5) or SQLITE_LOCKED (6), possibly extended.
fn is_sqlite_busy(e: &sqlx::Error) -> bool {
    match e {
        sqlx::Error::Database(db) => db.code().and_then(|c| c.parse::<i64>().ok()).is_some_and(|c| matches!(c & 0xff, 5 | 6)),
        _ => false,
    }
}

#[derive(Clone)]
pub struct Store {
    pool: AnyPool,
    backend: Backend,
}

impl Store {
    /// Opens (creating) the embedded SQLite store at `path` and its table.
    pub async fn open(path: &Path) -> Result<Self> {
        Self::connect(&sqlite_url(path)).await
    }

    /// Opens the store a URL names (`sqlite://PATH?mode=rwc`, `postgres://…`) and creates or upgrades its table.
    pub async fn connect(url: &str) -> Result<Self> {
        let backend = Backend::of_url(url)?;
        sqlx::any::install_default_drivers();
        let pool = AnyPoolOptions::new()
            .max_connections(STORE_CONNECTIONS)
            // All open from the start: a connection is a thread and three files, and a pool that grew under
            // load would keep them for its 10-minute idle timeout, so the server's baseline depended on past load.
            .min_connections(STORE_CONNECTIONS)
            .connect(url)
            .await
            .with_context(|| format!("cannot open the episode store {}", redact(url)))?;
        if backend == Backend::Sqlite {
            // WAL (kept in the file): readers (the API) never block the writer; a killed process loses no
            // committed row.
            switch_to_wal(&pool).await?;
        }
        // On PostgreSQL the schema is created under a session advisory lock: `CREATE TABLE IF NOT EXISTS` is not
        // safe against itself, so workers and dashboards starting at once on a fresh database would fail on the
        // catalog's unique index. SQLite serialises writers itself (and a transaction there would fail on a stale
        // snapshot instead of waiting).
        let mut conn = pool.acquire().await.context("cannot start creating the store's tables")?;
        if backend == Backend::Postgres {
            sqlx::query("SELECT pg_advisory_lock($1)").bind(SCHEMA_LOCK_KEY).execute(&mut *conn).await.context("cannot lock the store's schema")?;
        }
        let created = create_schema(&mut conn, backend, url).await;
        if backend == Backend::Postgres {
            // Also released when the connection closes, should this fail.
            let _ = sqlx::query("SELECT pg_advisory_unlock($1)").bind(SCHEMA_LOCK_KEY).execute(&mut *conn).await;
        }
        created?;
        Ok(Self { pool, backend })
    }

    pub fn backend(&self) -> Backend {
        self.backend
    }

    /// Tells PostgreSQL listeners (every dashboard on the store) that episode `id` changed.
    async fn notify_episode(&self, id: &str) -> Result<()> {
        if self.backend == Backend::Postgres {
            sqlx::query("SELECT pg_notify($1, $2)")
                .bind(EPISODE_CHANNEL)
                .bind(id)
                .execute(&self.pool)
                .await
                .context("store: cannot notify the episode's listeners")?;
        }
        Ok(())
    }

    /// Writes a batch's `batch.json` document (replacing the stored one) and the `rollouts.jsonl` records the store
    /// does not have yet (by position: records are only ever appended). Idempotent: run it after every change.
    pub async fn put_batch(&self, batch: &StoredBatch) -> Result<()> {
        let name = &batch.name;
        let mut tx = self.pool.begin().await.context("store: cannot begin")?;
        write_batch_row(&mut tx, batch, "DO UPDATE SET dir = excluded.dir, doc = excluded.doc, updated_at = excluded.updated_at").await?;
        let have: i64 = sqlx::query("SELECT CAST(COUNT(*) AS BIGINT) AS n FROM rollouts WHERE batch = $1")
            .bind(name)
            .fetch_one(&mut *tx)
            .await
            .and_then(|r| r.try_get("n"))
            .with_context(|| format!("store: cannot count the rollouts of batch {name}"))?;
        for (seq, record) in batch.records.iter().enumerate().skip(usize::try_from(have).unwrap_or(0)) {
            sqlx::query("INSERT INTO rollouts (batch, seq, rollout_id, doc) VALUES ($1, $2, $3, $4) ON CONFLICT DO NOTHING")
                .bind(name)
                .bind(seq as i64)
                .bind(RolloutSummary::from_value(record.clone()).ok().and_then(|r| r.rollout_id).unwrap_or_default())
                .bind(record.to_string())
                .execute(&mut *tx)
                .await
                .with_context(|| format!("store: cannot write a rollout of batch {name}"))?;
        }
        tx.commit().await.with_context(|| format!("store: cannot commit batch {name}"))?;
        Ok(())
    }

    /// A stored batch, its records in the order they were recorded; `None` when the store has no such batch.
    pub async fn batch(&self, name: &str) -> Result<Option<StoredBatch>> {
        let Some(row) = sqlx::query("SELECT dir, doc FROM batches WHERE name = $1")
            .bind(name)
            .fetch_optional(&self.pool)
            .await
            .with_context(|| format!("store: cannot read batch {name}"))?
        else {
            return Ok(None);
        };
        let parse = |text: String| serde_json::from_str::<Value>(&text).with_context(|| format!("store: batch {name} holds bad JSON"));
        let doc = parse(row.try_get("doc")?)?;
        let dir = PathBuf::from(row.try_get::<String, _>("dir")?);
        let records = sqlx::query("SELECT doc FROM rollouts WHERE batch = $1 ORDER BY seq")
            .bind(name)
            .fetch_all(&self.pool)
            .await
            .with_context(|| format!("store: cannot read the rollouts of batch {name}"))?
            .into_iter()
            .map(|r| parse(r.try_get("doc")?))
            .collect::<Result<Vec<_>>>()?;
        Ok(Some(StoredBatch { name: name.to_owned(), dir, doc, records }))
    }

    /// Saves a person's annotation of one stage of one episode (`doc`: the annotation as JSON), replacing the one
    /// stored before and adding it to the history.
    pub async fn put_stage_annotation(&self, episode_id: &str, stage_name: &str, annotator: &str, annotated_at: &str, doc: &Value) -> Result<()> {
        let what = || format!("store: cannot save the annotation of {episode_id} stage {stage_name}");
        let mut tx = self.pool.begin().await.context("store: cannot begin")?;
        sqlx::query(
            "INSERT INTO stage_annotations (episode_id, stage_name, doc, annotator, annotated_at) VALUES ($1, $2, $3, $4, $5) \
             ON CONFLICT (episode_id, stage_name) DO UPDATE SET doc = excluded.doc, annotator = excluded.annotator, annotated_at = excluded.annotated_at",
        )
        .bind(episode_id)
        .bind(stage_name)
        .bind(doc.to_string())
        .bind(annotator)
        .bind(annotated_at)
        .execute(&mut *tx)
        .await
        .with_context(what)?;
        sqlx::query("INSERT INTO stage_annotation_history (episode_id, stage_name, doc, annotator, annotated_at) VALUES ($1, $2, $3, $4, $5)")
            .bind(episode_id)
            .bind(stage_name)
            .bind(doc.to_string())
            .bind(annotator)
            .bind(annotated_at)
            .execute(&mut *tx)
            .await
            .with_context(what)?;
        tx.commit().await.with_context(what)?;
        Ok(())
    }

    /// The latest annotation of each annotated stage of `episode_id`: `(stage name, annotation JSON)`, by name.
    pub async fn stage_annotations(&self, episode_id: &str) -> Result<Vec<(String, Value)>> {
        let rows = sqlx::query("SELECT stage_name, doc FROM stage_annotations WHERE episode_id = $1 ORDER BY stage_name")
            .bind(episode_id)
            .fetch_all(&self.pool)
            .await
            .with_context(|| format!("store: cannot read the annotations of {episode_id}"))?;
        rows.iter()
            .map(|r| {
                let doc: String = r.try_get("doc")?;
                let value = serde_json::from_str(&doc).with_context(|| format!("store: an annotation of {episode_id} holds bad JSON"))?;
                Ok((r.try_get("stage_name")?, value))
            })
            .collect()
    }

    /// How many annotations of `episode_id`'s stages were ever saved (the history's length).
    pub async fn stage_annotation_history_len(&self, episode_id: &str) -> Result<i64> {
        sqlx::query("SELECT CAST(COUNT(*) AS BIGINT) AS n FROM stage_annotation_history WHERE episode_id = $1")
            .bind(episode_id)
            .fetch_one(&self.pool)
            .await
            .and_then(|r| r.try_get("n"))
            .with_context(|| format!("store: cannot count the annotations of {episode_id}"))
    }

    /// The names of the stored batches, sorted.
    pub async fn batch_names(&self) -> Result<Vec<String>> {
        let rows = sqlx::query("SELECT name FROM batches ORDER BY name").fetch_all(&self.pool).await.context("store: cannot list batches")?;
        rows.iter().map(|r| r.try_get::<String, _>("name").map_err(StoreError::from)).collect()
    }

    /// The row of a newly prepared episode (kept as is if it already exists).
    pub async fn insert_prepared(&self, e: &NewEpisode) -> Result<()> {
        sqlx::query(
            "INSERT INTO episodes (id, task_ref, level, seed, init_index, created_at, run_dir, harness, model, batch, server_url, \
             branch_parent, branch_step) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13) ON CONFLICT (id) DO NOTHING",
        )
        .bind(&e.id)
        .bind(&e.task_ref)
        .bind(e.level)
        .bind(e.seed)
        .bind(e.init_index)
        .bind(&e.created_at)
        .bind(e.run_dir.to_string_lossy().into_owned())
        .bind(&e.harness)
        .bind(&e.model)
        .bind(&e.batch)
        .bind(&e.server_url)
        .bind(&e.branch_parent)
        .bind(e.branch_step)
        .execute(&self.pool)
        .await
        .with_context(|| format!("store: cannot insert episode {}", e.id))?;
        self.notify_episode(&e.id).await
    }

    pub async fn mark_started(&self, id: &str, started_at: &str) -> Result<()> {
        sqlx::query("UPDATE episodes SET started_at = $1 WHERE id = $2 AND started_at IS NULL")
            .bind(started_at)
            .bind(id)
            .execute(&self.pool)
            .await
            .with_context(|| format!("store: cannot mark episode {id} started"))?;
        self.notify_episode(id).await
    }

    /// An open episode's progress so far (agent steps accepted; stages completed of required, once the evaluator
    /// said), so dashboards on other machines can follow it; ignored once the episode has its outcome, whose
    /// record then holds the final figures.
    pub async fn record_progress(&self, id: &str, accepted_agent_steps: i64, stages: Option<(i64, i64)>) -> Result<()> {
        let updated = sqlx::query(
            "UPDATE episodes SET accepted_agent_steps = $1, completed_stage_count = COALESCE($2, completed_stage_count), \
             required_stage_count = COALESCE($3, required_stage_count) WHERE id = $4 AND outcome IS NULL",
        )
        .bind(accepted_agent_steps)
        .bind(stages.map(|s| s.0))
        .bind(stages.map(|s| s.1))
        .bind(id)
        .execute(&self.pool)
        .await
        .with_context(|| format!("store: cannot record the progress of episode {id}"))?;
        if updated.rows_affected() > 0 {
            self.notify_episode(id).await?;
        }
        Ok(())
    }

    /// Records the end once; a row that already has an outcome keeps it.
    pub async fn record_end(&self, id: &str, end: &EpisodeEnd) -> Result<()> {
        sqlx::query(
            "UPDATE episodes SET finished_at = $1, outcome = $2, reason = $3, success = $4, \
             accepted_agent_steps = $5, completed_stage_count = $6, required_stage_count = $7, wall_time_s = $8 \
             WHERE id = $9 AND outcome IS NULL",
        )
        .bind(&end.finished_at)
        .bind(end.outcome.as_str())
        .bind(&end.reason)
        .bind(end.success)
        .bind(end.accepted_agent_steps)
        .bind(end.completed_stage_count)
        .bind(end.required_stage_count)
        .bind(end.wall_time_s)
        .bind(id)
        .execute(&self.pool)
        .await
        .with_context(|| format!("store: cannot record the end of episode {id}"))?;
        self.notify_episode(id).await
    }

    /// At startup, after the run directories were recovered: every run directory has its row, every ended
    /// episode its outcome; rows still open without a run directory become INVALID. Returns how many rows
    /// were closed.
    pub async fn reconcile(&self, runs_dir: &Path) -> Result<u64> {
        let mut closed = 0;
        let mut dirs: Vec<PathBuf> = match std::fs::read_dir(runs_dir) {
            Ok(d) => d.flatten().map(|e| e.path()).collect(),
            Err(_) => Vec::new(),
        };
        dirs.sort();
        for dir in dirs {
            let run = RunDir::new(dir);
            let Some(new) = NewEpisode::from_record(&run) else { continue };
            self.insert_prepared(&new).await?;
            if let Some(end) = EpisodeEnd::from_run(&run) {
                let before = self.get(&new.id).await?.and_then(|r| r.outcome);
                self.record_end(&new.id, &end).await?;
                closed += u64::from(before.is_none());
            }
        }
        // Rows of this server's run directories still open without their directory: the episode was lost with
        // the server. Rows under other run directories (another server on a shared store) are not this one's.
        let open = sqlx::query("SELECT id, run_dir FROM episodes WHERE outcome IS NULL")
            .fetch_all(&self.pool)
            .await
            .context("store: cannot list open rows")?;
        let mut orphans = 0;
        for row in &open {
            let (id, run_dir): (String, String) = (row.try_get("id")?, row.try_get("run_dir")?);
            let run_dir = PathBuf::from(run_dir);
            let foreign = self.backend == Backend::Postgres && run_dir.parent() != Some(runs_dir);
            if foreign || run_dir.exists() {
                continue;
            }
            let closed_row = sqlx::query(
                "UPDATE episodes SET finished_at = $1, outcome = $2, reason = $3, success = $4 WHERE id = $5 AND outcome IS NULL",
            )
            .bind(utc_now_iso())
            .bind(Outcome::Invalid.as_str())
            .bind(MISSING_RUN_REASON)
            .bind(false)
            .bind(&id)
            .execute(&self.pool)
            .await
            .context("store: cannot close an orphaned row")?;
            orphans += closed_row.rows_affected();
        }
        Ok(closed + orphans)
    }

    pub async fn get(&self, id: &str) -> Result<Option<EpisodeRow>> {
        let row = sqlx::query(&format!("SELECT {COLUMNS} FROM episodes WHERE id = $1"))
            .bind(id)
            .fetch_optional(&self.pool)
            .await
            .with_context(|| format!("store: cannot read episode {id}"))?;
        Ok(row.as_ref().map(EpisodeRow::from_row).transpose()?)
    }

    /// Newest first.
    pub async fn list(&self, limit: i64) -> Result<Vec<EpisodeRow>> {
        self.list_filtered(&EpisodeFilter::default(), limit).await
    }

    /// Newest first, those matching `filter`.
    pub async fn list_filtered(&self, filter: &EpisodeFilter, limit: i64) -> Result<Vec<EpisodeRow>> {
        let sql = format!(
            "SELECT {COLUMNS} FROM episodes WHERE ($1 IS NULL OR task_ref = $1) \
             AND ($2 IS NULL OR outcome = $2 OR ($2 = 'RUNNING' AND outcome IS NULL)) AND ($3 IS NULL OR batch = $3) \
             AND ($5 IS NULL OR harness = $5) ORDER BY created_at DESC, id DESC LIMIT $4"
        );
        let rows = sqlx::query(&sql)
            .bind(&filter.task)
            .bind(&filter.outcome)
            .bind(&filter.batch)
            .bind(limit)
            .bind(&filter.harness)
            .fetch_all(&self.pool)
            .await
            .context("store: cannot list episodes")?;
        Ok(rows.iter().map(EpisodeRow::from_row).collect::<Result<_, _>>()?)
    }

    pub async fn close(&self) {
        self.pool.close().await;
    }
}

#[cfg(any(test, feature = "testing"))]
pub mod testing;

#[cfg(test)]
mod tests {
    use super::testing::TestPostgres;
    use super::*;
    use serde_json::json;

    /// The typed view is the wire format the API had when it sent the row's JSON minus `run_dir`: the same keys
    /// and values, in the same (sorted) order.
    fn assert_view_is_the_row_without_its_run_dir(row: &EpisodeRow) {
        let mut old = serde_json::to_value(row).unwrap();
        assert!(old.as_object_mut().unwrap().remove("run_dir").is_some());
        let view = serde_json::to_value(row.view()).unwrap();
        assert!(view.get("run_dir").is_none(), "paths stay out of the API");
        assert_eq!(view, old);
        assert_eq!(serde_json::to_string(&row.view()).unwrap(), old.to_string(), "the keys in the old order");
    }

    fn new_episode(id: &str, run_dir: &Path) -> NewEpisode {
        NewEpisode {
            id: id.into(),
            task_ref: "libero_90/KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet".into(),
            level: 3,
            seed: 100,
            init_index: 2,
            created_at: utc_now_iso(),
            run_dir: run_dir.to_path_buf(),
            harness: Some("codex".into()),
            model: None,
            batch: Some("b1".into()),
            server_url: Some("http://worker-1.lab:8080".into()),
            branch_parent: Some("ep-parent".into()),
            branch_step: Some(42),
        }
    }

    #[tokio::test]
    async fn errors_say_what_failed_and_keep_passwords_out() {
        let err = Store::connect("mysql://libero:hunter2@db:3306/x").await.err().expect("not a store URL");
        assert!(matches!(err, StoreError::BadUrl(_)), "{err:?}");
        assert!(err.to_string().contains("libero:***@db") && !err.to_string().contains("hunter2"), "{err}");
        let dir = tempfile::tempdir().unwrap();
        let store = sqlite_store(dir.path()).await;
        let batch = StoredBatch { name: "b1".into(), dir: PathBuf::new(), doc: serde_json::json!({}), records: vec![] };
        store.enqueue(&batch, &[]).await.unwrap();
        let again = store.enqueue(&batch, &[]).await.expect_err("the name is taken");
        assert!(matches!(&again, StoreError::BatchExists(name) if name == "b1"), "{again:?}");
    }

    async fn sqlite_store(dir: &Path) -> Store {
        Store::open(&dir.join(STORE_FILE)).await.unwrap()
    }

    /// A batch written as it grows (the document replaced, records appended) reads back exactly, in order, with no
    /// record twice however often it is written.
    async fn batches_round_trip(store: Store) {
        let record = |id: &str, outcome: &str| json!({"rollout_id": id, "outcome": outcome, "task": "T14"});
        let mut batch = StoredBatch {
            name: "b1".into(),
            dir: PathBuf::from("/runs/b1"),
            doc: json!({"status": "running", "counts": {"done": 1}}),
            records: vec![record("r1", "FAIL")],
        };
        store.put_batch(&batch).await.unwrap();
        store.put_batch(&batch).await.unwrap();
        batch.doc = json!({"status": "finished", "counts": {"done": 3}});
        batch.records.extend([record("r2", "SUCCESS"), record("r1", "INVALID")]);
        store.put_batch(&batch).await.unwrap();
        store.put_batch(&batch).await.unwrap();
        assert_eq!(store.batch("b1").await.unwrap(), Some(batch.clone()));
        assert_eq!(store.batch("b2").await.unwrap(), None);
        let other = StoredBatch { name: "a0".into(), records: Vec::new(), ..batch };
        store.put_batch(&other).await.unwrap();
        assert_eq!(store.batch_names().await.unwrap(), ["a0", "b1"]);
    }

    #[tokio::test]
    async fn sqlite_batches_round_trip_in_order_without_duplicates() {
        let dir = tempfile::tempdir().unwrap();
        batches_round_trip(sqlite_store(dir.path()).await).await;
    }

    #[tokio::test]
    async fn postgres_batches_round_trip_in_order_without_duplicates() {
        let pg = TestPostgres::start();
        let store = Store::connect(&pg.url).await.unwrap();
        batches_round_trip(store.clone()).await;
        store.close().await;
    }

    /// A stage annotated twice reads back as the second, the history keeps both, other episodes see none.
    async fn stage_annotations_round_trip(store: Store) {
        let first = json!({"reached": true, "succeeded": false, "failure_modes": ["local_execution"], "note": "slipped", "annotator": "ana"});
        let second = json!({"reached": true, "succeeded": false, "failure_modes": ["geometric_error", "other"], "note": "ünïcode ' \" ;", "annotator": "bo"});
        store.put_stage_annotation("ep-1", "02_open", "ana", "2026-12-07T10:00:00Z", &first).await.unwrap();
        store.put_stage_annotation("ep-1", "01_grasp", "ana", "2026-12-07T10:00:01Z", &first).await.unwrap();
        store.put_stage_annotation("ep-1", "02_open", "bo", "2026-12-07T10:00:02Z", &second).await.unwrap();
        let got = store.stage_annotations("ep-1").await.unwrap();
        assert_eq!(got, vec![("01_grasp".to_owned(), first), ("02_open".to_owned(), second)]);
        assert_eq!(store.stage_annotation_history_len("ep-1").await.unwrap(), 3);
        assert!(store.stage_annotations("ep-2").await.unwrap().is_empty());
    }

    #[tokio::test]
    async fn sqlite_stage_annotations_replace_the_last_and_keep_the_history() {
        let dir = tempfile::tempdir().unwrap();
        stage_annotations_round_trip(sqlite_store(dir.path()).await).await;
    }

    #[tokio::test]
    async fn postgres_stage_annotations_replace_the_last_and_keep_the_history() {
        let pg = TestPostgres::start();
        let store = Store::connect(&pg.url).await.unwrap();
        stage_annotations_round_trip(store.clone()).await;
        store.close().await;
    }

    #[tokio::test]
    async fn sqlite_rows_follow_an_episode_from_prepare_to_its_end_and_keep_the_first_outcome() {
        let dir = tempfile::tempdir().unwrap();
        rows_follow_an_episode(sqlite_store(dir.path()).await, dir.path()).await;
    }

    #[tokio::test]
    async fn postgres_rows_follow_an_episode_from_prepare_to_its_end_and_keep_the_first_outcome() {
        let pg = TestPostgres::start();
        let dir = tempfile::tempdir().unwrap();
        let store = Store::connect(&pg.url).await.unwrap();
        assert_eq!(store.backend(), Backend::Postgres);
        rows_follow_an_episode(store.clone(), dir.path()).await;
        store.close().await;
        // Opening an existing store again (a second server, a restart) keeps its rows and columns.
        let again = Store::connect(&pg.url).await.unwrap();
        assert_eq!(again.list(10).await.unwrap().len(), 1);
        again.close().await;
    }

    /// N workers and dashboards starting at once on a fresh database: PostgreSQL's `CREATE TABLE IF NOT EXISTS`
    /// is not safe against itself (both see no table, one fails on the catalog's unique index), so the schema is
    /// created under an advisory lock and every opener succeeds.
    #[tokio::test(flavor = "multi_thread", worker_threads = 4)]
    async fn postgres_stores_opened_at_once_on_a_fresh_database_all_open() {
        let pg = TestPostgres::start();
        for round in 0..3 {
            // A fresh database each round, so every round races on creating the tables.
            let db = format!("fresh{round}");
            let admin = Store::connect(&pg.url).await.unwrap();
            sqlx::query(&format!("CREATE DATABASE {db}")).execute(&admin.pool).await.unwrap();
            admin.close().await;
            let url = format!("{}/{db}", pg.url.rsplit_once('/').unwrap().0);
            open_at_once(&url, Backend::Postgres).await;
        }
    }

    /// Eight openers of `url` at once; each must open the store.
    async fn open_at_once(url: &str, expected: Backend) {
        let openers: Vec<_> = (0..8)
            .map(|_| {
                let url = url.to_owned();
                tokio::spawn(async move { Store::connect(&url).await })
            })
            .collect();
        for opener in openers {
            let store = opener.await.unwrap().unwrap_or_else(|e| panic!("{url}: {e}"));
            assert_eq!(store.backend(), expected);
            store.close().await;
        }
    }

    /// Several workers of one machine on one `sqlite://` file, started at once.
    #[tokio::test(flavor = "multi_thread", worker_threads = 4)]
    async fn sqlite_stores_opened_at_once_on_a_new_file_all_open() {
        let dir = tempfile::tempdir().unwrap();
        for round in 0..3 {
            open_at_once(&sqlite_url(&dir.path().join(format!("fresh{round}.sqlite"))), Backend::Sqlite).await;
        }
    }

    #[tokio::test]
    async fn sqlite_reconcile_restores_ended_episodes_from_run_directories_and_closes_orphans() {
        let dir = tempfile::tempdir().unwrap();
        reconcile_restores_and_closes_orphans(sqlite_store(dir.path()).await, dir.path()).await;
    }

    #[tokio::test]
    async fn postgres_reconcile_closes_only_its_own_orphans() {
        let pg = TestPostgres::start();
        let dir = tempfile::tempdir().unwrap();
        let store = Store::connect(&pg.url).await.unwrap();
        // Another server's open episode in the shared store: not this server's to close.
        let other = dir.path().join("other-server/runs/ep-elsewhere");
        store.insert_prepared(&new_episode("ep-elsewhere", &other)).await.unwrap();
        reconcile_restores_and_closes_orphans(store.clone(), dir.path()).await;
        let open = store.get("ep-elsewhere").await.unwrap().unwrap();
        assert_eq!(open.outcome, None, "another server's episode stays open");
        assert_view_is_the_row_without_its_run_dir(&open);
        store.close().await;
    }

    #[tokio::test]
    async fn the_embedded_store_opens_in_a_directory_whose_name_needs_quoting_in_a_url() {
        let dir = tempfile::tempdir().unwrap();
        let odd = dir.path().join("my data #1 ?x=y 100%");
        std::fs::create_dir_all(&odd).unwrap();
        let store = Store::open(&odd.join(STORE_FILE)).await.unwrap();
        store.insert_prepared(&new_episode("ep-odd", &odd)).await.unwrap();
        assert!(store.get("ep-odd").await.unwrap().is_some());
        store.close().await;
        assert!(odd.join(STORE_FILE).is_file(), "the file is where the path says, not at a truncated name");
    }

    #[test]
    fn store_urls_name_their_backend_and_messages_hide_the_password() {
        assert_eq!(Backend::of_url("sqlite:///tmp/x.sqlite").unwrap(), Backend::Sqlite);
        assert_eq!(Backend::of_url("postgres://u:secret@h:5432/db").unwrap(), Backend::Postgres);
        let err = Backend::of_url("mysql://u:secret@h/db").unwrap_err().to_string();
        assert!(err.contains("postgres://") && !err.contains("secret"), "{err}");
        assert_eq!(redact("postgres://u:secret@h:5432/db"), "postgres://u:***@h:5432/db");
        assert_eq!(redact("sqlite:///a/b"), "sqlite:///a/b");
    }

    async fn rows_follow_an_episode(store: Store, dir: &Path) {
        store.insert_prepared(&new_episode("ep-a", dir)).await.unwrap();
        let row = store.get("ep-a").await.unwrap().unwrap();
        assert_eq!((row.episode.level, row.episode.seed, row.episode.init_index), (3, 100, 2));
        assert_eq!(row.outcome, None);
        store.mark_started("ep-a", "2026-01-01T00:00:00+00:00").await.unwrap();
        // Progress while open: steps at once, stages once the evaluator reported them, kept when a later write
        // has none.
        let progress = |r: EpisodeRow| (r.outcome, r.accepted_agent_steps, r.completed_stage_count, r.required_stage_count);
        store.record_progress("ep-a", 2, None).await.unwrap();
        assert_eq!(progress(store.get("ep-a").await.unwrap().unwrap()), (None, Some(2), None, None));
        store.record_progress("ep-a", 3, Some((1, 3))).await.unwrap();
        store.record_progress("ep-a", 4, None).await.unwrap();
        assert_eq!(progress(store.get("ep-a").await.unwrap().unwrap()), (None, Some(4), Some(1), Some(3)));
        let result = json!({"status": "finished", "success": false, "accepted_agent_steps": 7,
            "termination_reason": "episode_wall_time_budget_exhausted", "finished_at": "2026-01-01T00:30:00+00:00",
            "private_evaluation": {"completed_required_stage_count": 1, "required_stage_count": 3}});
        let result = RunResult::from_value(result).unwrap();
        store.record_end("ep-a", &EpisodeEnd::from_result(&result)).await.unwrap();
        let aborted = RunResult::from_value(json!({"status": "aborted", "reason": "late"})).unwrap();
        store.record_end("ep-a", &EpisodeEnd::from_result(&aborted)).await.unwrap();
        store.record_progress("ep-a", 99, Some((3, 3))).await.unwrap();
        let row = store.get("ep-a").await.unwrap().unwrap();
        assert_eq!(row.outcome.as_deref(), Some("SIM_TIMEOUT"));
        assert_eq!(row.reason.as_deref(), Some("episode_wall_time_budget_exhausted"));
        assert_eq!((row.success, row.accepted_agent_steps), (Some(false), Some(7)));
        assert_eq!((row.completed_stage_count, row.required_stage_count), (Some(1), Some(3)));
        assert_eq!(row.started_at.as_deref(), Some("2026-01-01T00:00:00+00:00"));
        assert_view_is_the_row_without_its_run_dir(&row);
        assert_eq!(store.list(10).await.unwrap(), vec![row.clone()]);
        let filter = |task: &str, outcome: &str, batch: &str| {
            EpisodeFilter { task: Some(task.into()), outcome: Some(outcome.into()), batch: Some(batch.into()), harness: None }.normalized()
        };
        let task = row.episode.task_ref.clone();
        assert_eq!(store.list_filtered(&filter(&task, "sim_timeout", "b1"), 10).await.unwrap(), vec![row.clone()]);
        assert!(store.list_filtered(&filter(&task, "RUNNING", ""), 10).await.unwrap().is_empty());
        assert!(store.list_filtered(&filter("", "", "b2"), 10).await.unwrap().is_empty());
        assert_eq!(row.episode.harness.as_deref(), Some("codex"));
        let by_harness = |h: &str| EpisodeFilter { harness: Some(h.into()), ..Default::default() }.normalized();
        assert_eq!(store.list_filtered(&by_harness("codex"), 10).await.unwrap(), vec![row.clone()]);
        assert!(store.list_filtered(&by_harness("expert"), 10).await.unwrap().is_empty());
        assert_eq!(row.episode.server_url.as_deref(), Some("http://worker-1.lab:8080"), "where its live view is");
    }

    async fn reconcile_restores_and_closes_orphans(store: Store, dir: &Path) {
        let runs = dir.join("runs");
        let run = RunDir::new(runs.join("ep-files"));
        std::fs::create_dir_all(&run.root).unwrap();
        let record = json!({"episode_id": "ep-files", "created_at": "2026-01-01T00:00:00+00:00",
            "task": {"task_ref": "libero_object/x"}, "level": 1, "seed": 5, "init_state_index": 0});
        std::fs::write(run.episode_record(), record.to_string()).unwrap();
        std::fs::write(run.result_json(), json!({"status": "finished", "success": true}).to_string()).unwrap();
        // A row whose run directory vanished while it was open.
        store.insert_prepared(&new_episode("ep-gone", &runs.join("ep-gone"))).await.unwrap();
        assert_eq!(store.reconcile(&runs).await.unwrap(), 2);
        let files = store.get("ep-files").await.unwrap().expect("row rebuilt from the run directory");
        assert_eq!((files.outcome.as_deref(), files.success, files.episode.seed), (Some("SUCCESS"), Some(true), 5));
        let gone = store.get("ep-gone").await.unwrap().unwrap();
        assert_eq!((gone.outcome.as_deref(), gone.reason.as_deref()), (Some("INVALID"), Some(MISSING_RUN_REASON)));
        assert_eq!(store.reconcile(&runs).await.unwrap(), 0, "idempotent");
    }
}
