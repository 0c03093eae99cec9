//! The episode store: one row per prepared episode (task, level, seed, init state, times, outcome of §4.8,
//! reason, stage counts, run directory), written when an episode is prepared, when it starts and when it
//! ends. SQLite through sqlx; the SQL is plain (`$n` placeholders, `BIGINT`/`BOOLEAN`/`TEXT`, `ON CONFLICT
//! DO NOTHING`) so the same statements run on PostgreSQL. The run directories stay the source of truth:
//! at startup [`Store::reconcile`] rebuilds any row the files know better (a crash between `result.json`
//! and the store write loses nothing).
use std::path::{Path, PathBuf};
use std::str::FromStr;

use anyhow::Context;
use libero_episode::json::utc_now_iso;
use libero_episode::records::{Outcome, RunDir, classify, read_result};
use serde::Serialize;
use serde_json::Value;
use sqlx::Row;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteRow};

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

/// Nullable columns added after the first schema (the dashboard's filters and wall time); added in place to an
/// older store by [`Store::open`].
const ADDED_COLUMNS: [(&str, &str); 4] =
    [("harness", "TEXT"), ("model", "TEXT"), ("batch", "TEXT"), ("wall_time_s", "DOUBLE PRECISION")];

const COLUMNS: &str = "id, task_ref, level, seed, init_index, created_at, started_at, finished_at, outcome, reason, \
    success, accepted_agent_steps, completed_stage_count, required_stage_count, run_dir, harness, model, batch, \
    wall_time_s";

/// The dashboard's episode filters (`None`: any). Outcome `RUNNING` selects episodes without an outcome yet.
#[derive(Debug, Clone, Default, PartialEq, serde::Deserialize)]
pub struct EpisodeFilter {
    pub task: Option<String>,
    pub outcome: Option<String>,
    pub batch: Option<String>,
}

impl EpisodeFilter {
    /// Empty strings (an empty form field) mean no filter.
    pub fn normalized(self) -> Self {
        let keep = |v: Option<String>| v.map(|s| s.trim().to_owned()).filter(|s| !s.is_empty());
        Self { task: keep(self.task), outcome: keep(self.outcome).map(|o| o.to_uppercase()), batch: keep(self.batch) }
    }
}

/// One stored episode. The run directory is private: the HTTP API leaves it out (see [`EpisodeRow::public`]).
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
    /// The row as the operator API shows it: everything but filesystem paths.
    pub fn public(&self) -> Value {
        let mut v = serde_json::to_value(self).unwrap_or(Value::Null);
        if let Some(o) = v.as_object_mut() {
            o.remove("run_dir");
        }
        v
    }

    fn from_row(r: &SqliteRow) -> Result<Self, sqlx::Error> {
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
        };
        Ok(Self {
            episode,
            started_at: r.try_get("started_at")?,
            finished_at: r.try_get("finished_at")?,
            outcome: r.try_get("outcome")?,
            reason: r.try_get("reason")?,
            success: r.try_get("success")?,
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

    pub fn from_result(result: &Value) -> Self {
        let outcome = classify(Some(result));
        let text = |k: &str| result.get(k).and_then(Value::as_str).map(str::to_owned);
        let eval = result.get("private_evaluation");
        let eval_count = |k: &str| eval.and_then(|e| e.get(k)).and_then(Value::as_i64);
        Self {
            finished_at: text("finished_at").unwrap_or_else(utc_now_iso),
            outcome,
            reason: text("reason").or_else(|| text("termination_reason")),
            success: outcome == Outcome::Success,
            accepted_agent_steps: result.get("accepted_agent_steps").and_then(Value::as_i64),
            completed_stage_count: eval_count("completed_required_stage_count"),
            required_stage_count: eval_count("required_stage_count"),
            wall_time_s: result.get("wall_time_seconds").and_then(Value::as_f64),
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
}

impl NewEpisode {
    /// From a run directory's `episode_record.json` (written by `prepare` before anything else).
    pub fn from_record(run: &RunDir) -> Option<Self> {
        let text = std::fs::read_to_string(run.episode_record()).ok()?;
        let r: Value = serde_json::from_str(&text).ok()?;
        Some(Self {
            id: r["episode_id"].as_str()?.to_owned(),
            task_ref: r["task"]["task_ref"].as_str()?.to_owned(),
            level: r["level"].as_i64()?,
            seed: r["seed"].as_i64()?,
            init_index: r["init_state_index"].as_i64()?,
            created_at: r["created_at"].as_str()?.to_owned(),
            run_dir: run.root.clone(),
            harness: r["harness"].as_str().map(str::to_owned),
            model: r["model"].as_str().map(str::to_owned),
            batch: r["batch"].as_str().map(str::to_owned),
        })
    }
}

/// SQLite connections of the store.
const STORE_CONNECTIONS: u32 = 4;

#[derive(Clone)]
pub struct Store {
    pool: SqlitePool,
}

impl Store {
    /// Opens (creating) the SQLite store at `path` and its table.
    pub async fn open(path: &Path) -> anyhow::Result<Self> {
        let url = format!("sqlite://{}", path.display());
        let options = SqliteConnectOptions::from_str(&url)
            .with_context(|| format!("store path {}", path.display()))?
            .create_if_missing(true)
            // WAL: readers (the API) never block the writer; a killed process loses no committed row.
            .journal_mode(SqliteJournalMode::Wal);
        let pool = SqlitePoolOptions::new()
            .max_connections(STORE_CONNECTIONS)
            // All open from the start: a connection is a thread and three files, and a pool that grew under
            // load would keep them for its 10-minute idle timeout, so the server's baseline depended on past load.
            .min_connections(STORE_CONNECTIONS)
            .connect_with(options)
            .await
            .with_context(|| format!("cannot open the episode store {}", path.display()))?;
        sqlx::query(SCHEMA).execute(&pool).await.context("cannot create the episodes table")?;
        for (name, kind) in ADDED_COLUMNS {
            // A store written by this version has the column already; any other failure is one.
            if let Err(e) = sqlx::query(&format!("ALTER TABLE episodes ADD COLUMN {name} {kind}")).execute(&pool).await
                && !e.to_string().to_ascii_lowercase().contains("duplicate column")
            {
                return Err(anyhow::Error::from(e).context(format!("cannot add column {name} to the episode store {}", path.display())));
            }
        }
        Ok(Self { pool })
    }

    /// The row of a newly prepared episode (kept as is if it already exists).
    pub async fn insert_prepared(&self, e: &NewEpisode) -> anyhow::Result<()> {
        sqlx::query(
            "INSERT INTO episodes (id, task_ref, level, seed, init_index, created_at, run_dir, harness, model, batch) \
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10) ON CONFLICT (id) DO NOTHING",
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
        .execute(&self.pool)
        .await
        .with_context(|| format!("store: cannot insert episode {}", e.id))?;
        Ok(())
    }

    pub async fn mark_started(&self, id: &str, started_at: &str) -> anyhow::Result<()> {
        sqlx::query("UPDATE episodes SET started_at = $1 WHERE id = $2 AND started_at IS NULL")
            .bind(started_at)
            .bind(id)
            .execute(&self.pool)
            .await
            .with_context(|| format!("store: cannot mark episode {id} started"))?;
        Ok(())
    }

    /// Records the end once; a row that already has an outcome keeps it.
    pub async fn record_end(&self, id: &str, end: &EpisodeEnd) -> anyhow::Result<()> {
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
        Ok(())
    }

    /// At startup, after the run directories were recovered: every run directory has its row, every ended
    /// episode its outcome; rows still open without a run directory become INVALID. Returns how many rows
    /// were closed.
    pub async fn reconcile(&self, runs_dir: &Path) -> anyhow::Result<u64> {
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
        let orphans = sqlx::query(
            "UPDATE episodes SET finished_at = $1, outcome = $2, reason = $3, success = $4 WHERE outcome IS NULL",
        )
        .bind(utc_now_iso())
        .bind(Outcome::Invalid.as_str())
        .bind(MISSING_RUN_REASON)
        .bind(false)
        .execute(&self.pool)
        .await
        .context("store: cannot close orphaned rows")?;
        Ok(closed + orphans.rows_affected())
    }

    pub async fn get(&self, id: &str) -> anyhow::Result<Option<EpisodeRow>> {
        let row = sqlx::query(&format!("SELECT {COLUMNS} FROM episodes WHERE id = $1"))
            .bind(id)
            .fetch_optional(&self.pool)
            .await
            .with_context(|| format!("store: cannot read episode {id}"))?;
        Ok(row.as_ref().map(EpisodeRow::from_row).transpose()?)
    }

    /// Newest first.
    pub async fn list(&self, limit: i64) -> anyhow::Result<Vec<EpisodeRow>> {
        self.list_filtered(&EpisodeFilter::default(), limit).await
    }

    /// Newest first, those matching `filter`.
    pub async fn list_filtered(&self, filter: &EpisodeFilter, limit: i64) -> anyhow::Result<Vec<EpisodeRow>> {
        let sql = format!(
            "SELECT {COLUMNS} FROM episodes WHERE ($1 IS NULL OR task_ref = $1) \
             AND ($2 IS NULL OR outcome = $2 OR ($2 = 'RUNNING' AND outcome IS NULL)) AND ($3 IS NULL OR batch = $3) \
             ORDER BY created_at DESC, id DESC LIMIT $4"
        );
        let rows = sqlx::query(&sql)
            .bind(&filter.task)
            .bind(&filter.outcome)
            .bind(&filter.batch)
            .bind(limit)
            .fetch_all(&self.pool)
            .await
            .context("store: cannot list episodes")?;
        Ok(rows.iter().map(EpisodeRow::from_row).collect::<Result<_, _>>()?)
    }

    pub async fn close(&self) {
        self.pool.close().await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

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
        }
    }

    #[tokio::test]
    async fn rows_follow_an_episode_from_prepare_to_its_end_and_keep_the_first_outcome() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&dir.path().join(STORE_FILE)).await.unwrap();
        store.insert_prepared(&new_episode("ep-a", dir.path())).await.unwrap();
        let row = store.get("ep-a").await.unwrap().unwrap();
        assert_eq!((row.episode.level, row.episode.seed, row.episode.init_index), (3, 100, 2));
        assert_eq!(row.outcome, None);
        store.mark_started("ep-a", "2026-01-01T00:00:00+00:00").await.unwrap();
        let result = json!({"status": "finished", "success": false, "accepted_agent_steps": 7,
            "termination_reason": "episode_wall_time_budget_exhausted", "finished_at": "2026-01-01T00:30:00+00:00",
            "private_evaluation": {"completed_required_stage_count": 1, "required_stage_count": 3}});
        store.record_end("ep-a", &EpisodeEnd::from_result(&result)).await.unwrap();
        let aborted = json!({"status": "aborted", "reason": "late"});
        store.record_end("ep-a", &EpisodeEnd::from_result(&aborted)).await.unwrap();
        let row = store.get("ep-a").await.unwrap().unwrap();
        assert_eq!(row.outcome.as_deref(), Some("SIM_TIMEOUT"));
        assert_eq!(row.reason.as_deref(), Some("episode_wall_time_budget_exhausted"));
        assert_eq!((row.success, row.accepted_agent_steps), (Some(false), Some(7)));
        assert_eq!((row.completed_stage_count, row.required_stage_count), (Some(1), Some(3)));
        assert_eq!(row.started_at.as_deref(), Some("2026-01-01T00:00:00+00:00"));
        assert!(row.public().get("run_dir").is_none(), "paths stay out of the API");
        assert_eq!(store.list(10).await.unwrap(), vec![row.clone()]);
        let filter = |task: &str, outcome: &str, batch: &str| {
            EpisodeFilter { task: Some(task.into()), outcome: Some(outcome.into()), batch: Some(batch.into()) }.normalized()
        };
        let task = row.episode.task_ref.clone();
        assert_eq!(store.list_filtered(&filter(&task, "sim_timeout", "b1"), 10).await.unwrap(), vec![row.clone()]);
        assert!(store.list_filtered(&filter(&task, "RUNNING", ""), 10).await.unwrap().is_empty());
        assert!(store.list_filtered(&filter("", "", "b2"), 10).await.unwrap().is_empty());
        assert_eq!(row.episode.harness.as_deref(), Some("codex"));
    }

    #[tokio::test]
    async fn reconcile_restores_ended_episodes_from_run_directories_and_closes_orphans() {
        let dir = tempfile::tempdir().unwrap();
        let runs = dir.path().join("runs");
        let run = RunDir::new(runs.join("ep-files"));
        std::fs::create_dir_all(&run.root).unwrap();
        let record = json!({"episode_id": "ep-files", "created_at": "2026-01-01T00:00:00+00:00",
            "task": {"task_ref": "libero_object/x"}, "level": 1, "seed": 5, "init_state_index": 0});
        std::fs::write(run.episode_record(), record.to_string()).unwrap();
        std::fs::write(run.result_json(), json!({"status": "finished", "success": true}).to_string()).unwrap();
        let store = Store::open(&dir.path().join(STORE_FILE)).await.unwrap();
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
