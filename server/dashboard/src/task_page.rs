//! A page per task: `/tasks/{id}` for a release task (`T14`) and `/tasks/{suite}/{task_id}` for a pool entry
//! (`libero_90/35`). It gathers what the console knows of one task: the instruction, split, K and the stage names,
//! the settled start from both cameras (the thumbnail cache), what the checker judges in public words (stage names
//! and types from the catalog, never the evaluator's parameters, poses or thresholds), the task's demonstrations,
//! a teleop link, every stored episode of the task and its cells of the batches the Results page shows (computed
//! there, by [`results::view`]).
use askama::Template;
use axum::Router;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::Response;
use axum::routing::get;
use libero_store::EpisodeFilter;
use libero_server::{App, AppState};
use libero_tasks::catalog::CheckerSpec;
use serde::Deserialize;
use serde_json::Value;

use crate::teleop::BundleSummary;

use crate::common::page;
use crate::error_page;
use crate::results::{self, EpisodeLink, Selection};

/// Most episodes a task page lists (newest first).
const EPISODE_LIMIT: i64 = 500;
/// Longest task address the routes accept (`vlabench_tube_precision/12` and the like).
const MAX_ADDRESS_LEN: usize = 80;

pub fn compressed_routes() -> Router<AppState> {
    Router::new().route("/tasks/{id}", get(release_task)).route("/tasks/{suite}/{task_id}", get(pool_task))
}

#[derive(Debug, thiserror::Error)]
enum TaskPageError {
    /// The address names no release task or registered pool entry: 404.
    #[error("{0}")]
    Unknown(String),
    /// The catalog, pool or store could not be read: 500.
    #[error("{0}")]
    Internal(String),
}

/// One stage as the page lists it: its catalog name, declared type, and whether success needs it.
struct StageLine {
    number: usize,
    name: String,
    kind: String,
    required: bool,
}

/// A stored episode of the task.
struct EpisodeLine {
    id: String,
    href: String,
    created_at: String,
    level: i64,
    outcome: String,
    stages: String,
    steps: String,
    wall_time: String,
    /// `harness + model`, or the batch, or empty for an operator's episode.
    agent: String,
    batch: String,
}

/// A demonstration bundle of the task's library folder.
struct DemoLine {
    key: String,
    source: String,
    verified: String,
    actions: String,
    video: String,
    /// One line per episode configuration the bundle was replayed in (`ReplayCheck::summary`).
    replay_checks: Vec<String>,
    /// The source episode's id (empty when the manifest names none).
    episode: String,
    /// Its review, when the store knows the episode; empty otherwise.
    review: String,
}

/// One batch column's cell of this task (the Results page's per-task table).
struct BatchCell {
    column: String,
    summary: String,
    stable: String,
    links: Vec<EpisodeLink>,
}

/// One pool batch's row of this task (the Results page's Pool tasks table).
struct PoolCell {
    batch: String,
    summary: String,
    stable: String,
    links: Vec<EpisodeLink>,
}

#[derive(Template)]
#[template(path = "task.html")]
struct TaskPage {
    /// `T14` or `libero_90/35`.
    id: String,
    /// The Tasks page showing this task's card (its suite's, for a pool entry).
    back: String,
    name: String,
    instruction: String,
    /// (label, value) facts: split, group, source…
    facts: Vec<(String, String)>,
    k: usize,
    judged: String,
    stages: Vec<StageLine>,
    /// Empty when the task does not run here.
    why_not: String,
    head: String,
    wrist: String,
    teleop: String,
    /// The task reference its episodes and demonstrations are recorded under.
    task_ref: String,
    /// What the last expert sweep says of it ("solved 3/3 on DATE at COMMIT"), or empty.
    expert: String,
    /// (label, href) of related task pages: the release task a pool entry runs as, pool entries of a release task.
    related: Vec<(String, String)>,
    demos: Vec<DemoLine>,
    episodes: Vec<EpisodeLine>,
    batch_cells: Vec<BatchCell>,
    pool_cells: Vec<PoolCell>,
}

/// What the page needs from the catalog or the pool, before the store and batches are read.
struct TaskFacts {
    id: String,
    name: String,
    instruction: String,
    facts: Vec<(String, String)>,
    k: usize,
    checker: CheckerSpec,
    why_not: Option<String>,
    task_ref: String,
    related: Vec<(String, String)>,
}

async fn release_task(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    task_page(&app, id).await
}

async fn pool_task(State(app): State<AppState>, Path((suite, task_id)): Path<(String, String)>) -> Response {
    task_page(&app, format!("{suite}/{task_id}")).await
}

async fn task_page(app: &App, address: String) -> Response {
    let path = format!("/tasks/{address}");
    let facts = match tokio::task::spawn_blocking(move || facts_of(&address)).await {
        Ok(Ok(f)) => f,
        Ok(Err(TaskPageError::Unknown(why))) => return error_page::render(StatusCode::NOT_FOUND, &why, &path),
        Ok(Err(TaskPageError::Internal(why))) => return error_page::render(StatusCode::INTERNAL_SERVER_ERROR, &why, &path),
        Err(e) => return error_page::render(StatusCode::INTERNAL_SERVER_ERROR, &format!("task page: {e}"), &path),
    };
    match gather(app, facts).await {
        Ok(view) => page(view),
        Err(e) => error_page::render(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string(), &path),
    }
}

/// A plain task address: `T14` or `suite/task_id` (task names too), short, without path tricks.
fn plain_address(address: &str) -> bool {
    let plain = |s: &str| !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    address.len() <= MAX_ADDRESS_LEN
        && match address.split_once('/') {
            Some((suite, task)) => plain(suite) && plain(task),
            None => plain(address),
        }
}

fn facts_of(address: &str) -> Result<TaskFacts, TaskPageError> {
    if !plain_address(address) {
        return Err(TaskPageError::Unknown(format!("{address:?} is not a task address: T01–T30 or <suite>/<task id>")));
    }
    let internal = |e: libero_tasks::TasksError| TaskPageError::Internal(e.to_string());
    let catalog = libero_tasks::Catalog::discover().map_err(internal)?;
    let pool = libero_tasks::Pool::discover().map_err(internal)?;
    if !address.contains('/') {
        let t = catalog
            .get(address)
            .ok_or_else(|| TaskPageError::Unknown(format!("There is no release task {address}: the release tasks are T01–T30.")))?;
        let related = pool
            .entries()
            .iter()
            .filter(|e| e.runs_as.as_deref() == Some(t.id.as_str()) || e.release_task.as_deref() == Some(t.id.as_str()))
            .map(|e| (format!("{} ({})", e.id(), e.name), format!("/tasks/{}", e.id())))
            .collect();
        return Ok(TaskFacts {
            id: t.id.clone(),
            name: t.name.clone(),
            instruction: t.agent_instruction().to_owned(),
            facts: vec![
                ("split".into(), text_of(&t.split)),
                ("group".into(), format!("{} ({})", t.group, text_of(&t.difficulty))),
                ("capability".into(), t.capability.clone()),
                ("source".into(), format!("{}/{}", t.source.suite, t.source.task_id)),
            ],
            k: t.stage_count,
            checker: t.checker.clone(),
            why_not: (!t.implemented).then(|| t.not_implemented_reason.clone().unwrap_or_else(|| "not implemented".into())),
            task_ref: t.id.clone(),
            related,
        });
    }
    let e = pool.lookup(address).map_err(|why| TaskPageError::Unknown(format!("There is no such task: {why}")))?;
    let checker = match (&e.runs_as, &e.definition) {
        (Some(release), _) => catalog.get(release).map(|t| t.checker.clone()),
        (None, Some(d)) => Some(CheckerSpec { kind: e.checker.clone(), params: d.checker_params.clone() }),
        (None, None) => None,
    }
    .unwrap_or_else(|| CheckerSpec { kind: e.checker.clone(), params: Value::Null });
    // the reference its episodes record: the release task it runs as when it keeps that task's language,
    // else `suite/name` (as `resolve_task` names it)
    let task_ref = match e.runs_as.as_deref().and_then(|r| catalog.get(r)) {
        Some(t) if t.agent_instruction() == e.instruction => t.id.clone(),
        _ => e.reference(),
    };
    let mut related = Vec::new();
    for release in [e.runs_as.as_deref(), e.release_task.as_deref()].into_iter().flatten() {
        if let Some(t) = catalog.get(release).filter(|_| !related.iter().any(|(_, h): &(String, String)| h.ends_with(release))) {
            related.push((format!("{} ({})", t.id, t.name), format!("/tasks/{}", t.id)));
        }
    }
    let mut facts = vec![("suite".into(), e.suite.clone()), ("group".into(), e.group.clone()), ("source".into(), e.source.clone())];
    if let Some(r) = &e.runs_as {
        facts.push(("runs as".into(), r.clone()));
    }
    Ok(TaskFacts {
        id: e.id(),
        name: e.name.clone(),
        instruction: e.instruction.clone(),
        facts,
        k: e.stage_count,
        checker,
        why_not: e.why_not(),
        task_ref,
        related,
    })
}

fn text_of<T: serde::Serialize>(v: &T) -> String {
    serde_json::to_value(v).ok().and_then(|v| v.as_str().map(str::to_owned)).unwrap_or_default()
}

/// The checker parameters the page describes (never shows): its stage order and how many stages it requires.
/// Kept as JSON values so that any other shape reads as absent, as each kind's own parameters decide.
#[derive(Deserialize, Default)]
struct DescribedParams {
    #[serde(default)]
    order: Value,
    #[serde(default)]
    stages: Value,
}

impl DescribedParams {
    fn of(checker: &CheckerSpec) -> Self {
        Self::deserialize(&checker.params).unwrap_or_default()
    }
}

/// What the checker judges, in public words: its kind and K, never its parameters.
fn judged_words(checker: &CheckerSpec, k: usize) -> String {
    let plural = if k == 1 { "" } else { "s" };
    if checker.is_bddl_terminal() {
        return "Success when the task's BDDL goal holds on the final state, judged when the agent calls finish_episode."
            .into();
    }
    let kind = checker.kind.trim_start_matches("private_").replace('_', " ");
    let params = DescribedParams::of(checker);
    if params.order == "unordered" {
        return format!(
            "{k} goal{plural} in any order ({kind}), judged by a private evaluator: success needs all of them to hold at the end."
        );
    }
    if checker.kind.starts_with("private_ordered") || params.order == "ordered" {
        return format!(
            "{k} ordered stage{plural} ({kind}), judged by a private evaluator: a stage counts only after the ones before it; \
             success needs all {k}."
        );
    }
    format!("{k} stage{plural} ({kind}), judged by a private evaluator: success needs all of them.")
}

/// The catalog's stage names and declared types; a BDDL-terminal task has its goal as its one stage.
fn stage_lines(checker: &CheckerSpec) -> Vec<StageLine> {
    let required = DescribedParams::of(checker).stages.as_array().map_or(0, Vec::len);
    let listed = checker.stage_types().unwrap_or_default();
    if listed.is_empty() {
        return vec![StageLine { number: 1, name: "goal".into(), kind: "the BDDL goal on the final state".into(), required: true }];
    }
    listed
        .into_iter()
        .enumerate()
        .map(|(i, (name, kind))| StageLine {
            number: i + 1,
            name,
            kind: kind.map(|k| text_of(&k).replace('_', " ")).unwrap_or_else(|| "—".into()),
            required: i < required,
        })
        .collect()
}

/// The page: the facts, then the store's episodes, the library's bundles and the batches' cells of the task.
async fn gather(app: &App, f: TaskFacts) -> anyhow::Result<TaskPage> {
    let filter = EpisodeFilter { task: Some(f.task_ref.clone()), ..Default::default() };
    app.sync_all().await;
    let rows = app.store.list_filtered(&filter, EPISODE_LIMIT).await?;
    let episodes = rows.iter().map(episode_line).collect();
    let library = libero_episode::demo::library::task_dir(&app.episodes.lifecycle().demo_library(), &f.task_ref);
    let mut demos: Vec<DemoLine> = tokio::task::spawn_blocking(move || crate::teleop::task_bundles(&library)).await?.iter().map(demo_line).collect();
    for d in demos.iter_mut().filter(|d| crate::common::valid_id(&d.episode)) {
        if app.store.get(&d.episode).await?.is_some() {
            d.review = format!("/episodes/{}/review", d.episode);
        }
    }
    let (batch_cells, pool_cells) = match results::selected(app, &Selection::default()).await {
        Ok((_, batches)) => batch_cells(&results::view(&batches, &Selection::default()), &f.id),
        // a batch that cannot be read is the Results page's error to show; the task page still opens
        Err(_) => (Vec::new(), Vec::new()),
    };
    let runs = f.why_not.is_none();
    let thumb = |camera: &str| if runs { format!("/tasks/{}/thumbnail.png?camera={camera}", f.id) } else { String::new() };
    Ok(TaskPage {
        head: thumb("head"),
        wrist: thumb("wrist"),
        teleop: if runs { format!("/teleop/{}", f.id) } else { String::new() },
        judged: judged_words(&f.checker, f.k),
        stages: stage_lines(&f.checker),
        why_not: f.why_not.unwrap_or_default(),
        back: match f.id.split_once('/') {
            Some((suite, _)) => format!("/tasks?tasks={suite}#{}", f.id),
            None => format!("/tasks#{}", f.id),
        },
        expert: crate::expert_sweep::expert_line(&[&f.id, &f.task_ref]),
        id: f.id,
        name: f.name,
        instruction: f.instruction,
        facts: f.facts,
        k: f.k,
        task_ref: f.task_ref,
        related: f.related,
        demos,
        episodes,
        batch_cells,
        pool_cells,
    })
}

fn episode_line(r: &libero_store::EpisodeRow) -> EpisodeLine {
    let id = r.episode.id.clone();
    let agent = match (&r.episode.harness, &r.episode.model) {
        (Some(h), Some(m)) => format!("{h} + {m}"),
        (Some(h), None) => h.clone(),
        _ => String::new(),
    };
    EpisodeLine {
        href: if r.outcome.is_some() { format!("/episodes/{id}/review") } else { format!("/episodes/{id}") },
        created_at: r.episode.created_at.clone(),
        level: r.episode.level,
        outcome: r.outcome.clone().unwrap_or_else(|| "RUNNING".into()),
        stages: match (r.completed_stage_count, r.required_stage_count) {
            (Some(c), Some(k)) => format!("{c}/{k}"),
            _ => "–".into(),
        },
        steps: r.accepted_agent_steps.map(|n| n.to_string()).unwrap_or_else(|| "–".into()),
        wall_time: r.wall_time_s.map(|s| format!("{s:.1} s")).unwrap_or_else(|| "–".into()),
        agent,
        batch: r.episode.batch.clone().unwrap_or_default(),
        id,
    }
}

fn demo_line(b: &BundleSummary) -> DemoLine {
    let key = b.key.clone();
    let verified = match (b.verified, b.valid) {
        (_, false) => format!("invalid: {}", b.first_violation.as_deref().unwrap_or("?")),
        (Some(true), _) => "verified".into(),
        (Some(false), _) => "not verified".into(),
        (None, _) => "–".into(),
    };
    DemoLine {
        video: format!("/demos/{key}/video.mp4"),
        source: b.source_type.as_deref().unwrap_or("?").to_owned(),
        actions: b.actions.map(|n| n.to_string()).unwrap_or_else(|| "–".into()),
        verified,
        replay_checks: b.replay_checks.clone(),
        episode: b.episode_id.clone().unwrap_or_default(),
        review: String::new(),
        key,
    }
}

/// This task's cells of the Results page's per-task table (one per batch column that has rollouts of it) and its
/// rows of the Pool tasks table.
fn batch_cells(view: &results::View, id: &str) -> (Vec<BatchCell>, Vec<PoolCell>) {
    let mut cells = Vec::new();
    if let Some(row) = view.tasks.iter().find(|r| r.task == id) {
        for (column, c) in view.columns.iter().zip(&row.cells) {
            if c.summary.is_empty() && c.links.is_empty() {
                continue;
            }
            cells.push(BatchCell { column: column.clone(), summary: c.summary.clone(), stable: c.stable.clone(), links: c.links.clone() });
        }
    }
    let pool = view
        .pool_tasks
        .iter()
        .filter(|r| r.task == id)
        .map(|r| PoolCell { batch: r.batch.clone(), summary: r.summary.clone(), stable: r.stable.clone(), links: r.links.clone() })
        .collect();
    (cells, pool)
}

/// The task page of an episode's task reference (`T14`, `libero_90/35`, `libero_90/<name>`) and the instruction
/// it has, for the live and review pages; `None` for a task outside the catalog and pool (a BDDL path).
pub fn task_of_ref(task_ref: &str) -> Option<(String, String)> {
    if !plain_address(task_ref) {
        return None;
    }
    if !task_ref.contains('/') {
        let catalog = libero_tasks::Catalog::discover().ok()?;
        let t = catalog.get(task_ref)?;
        return Some((format!("/tasks/{}", t.id), t.agent_instruction().to_owned()));
    }
    let pool = libero_tasks::Pool::discover().ok()?;
    let e = pool.lookup(task_ref).ok()?;
    Some((format!("/tasks/{}", e.id()), e.instruction.clone()))
}

/// The task page and instruction of an episode's task reference, or empty strings.
pub(crate) fn task_link(task_ref: &str) -> (String, String) {
    task_of_ref(task_ref).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_with_path_tricks_are_unknown_tasks() {
        for bad in ["..", "T14/../x", "a/b/c", "", "T 14", "libero_90/"] {
            assert!(matches!(facts_of(bad), Err(TaskPageError::Unknown(_))), "{bad:?}");
        }
        assert!(matches!(facts_of("T99"), Err(TaskPageError::Unknown(_))));
        assert!(matches!(facts_of("libero_90/9999"), Err(TaskPageError::Unknown(_))));
    }

    #[test]
    fn checker_words_name_the_stages_but_no_parameter() {
        let catalog = libero_tasks::Catalog::discover().unwrap();
        let t28 = catalog.get("T28").unwrap();
        let words = judged_words(&t28.checker, t28.stage_count);
        assert!(words.contains("ordered"), "{words}");
        let stages = stage_lines(&t28.checker);
        assert_eq!(stages.iter().filter(|s| s.required).count(), t28.stage_count);
        let shown = format!("{words} {}", stages.iter().map(|s| format!("{} {}", s.name, s.kind)).collect::<Vec<_>>().join(" "));
        for private in ["latch_joint", "1.23", "contact_body", "hinge"] {
            assert!(!shown.contains(private), "{private:?} leaked into {shown}");
        }
    }

    #[test]
    fn episode_refs_lead_to_their_task_pages() {
        assert_eq!(task_of_ref("T14").map(|(h, _)| h), Some("/tasks/T14".into()));
        assert_eq!(task_of_ref("libero_90/35").map(|(h, _)| h), Some("/tasks/libero_90/35".into()));
        assert_eq!(task_of_ref("/tmp/x.bddl"), None);
    }
}
