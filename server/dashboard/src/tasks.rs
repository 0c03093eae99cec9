//! The Tasks page, `/tasks` (`web/templates/tasks.html`): the release tasks or a pool suite as cards, with
//! filters; `/api/tasks`, the release tasks as JSON; and the tasks' start thumbnails from the thumbnail cache
//! (`/tasks/{id}/thumbnail.png`, `/tasks/{suite}/{task_id}/thumbnail.png`), which the task and teleop pages show too.
use askama::Template;
use axum::body::Body;
use axum::extract::{Path, Query, Request, State};
use axum::response::{IntoResponse, Response};
use libero_server::{ApiError, AppState};
use serde_json::json;

use crate::common::{page, serve_file};

/// A task as the dashboard shows it: public facts only (no checker parameters, poses, masses or init files).
#[derive(serde::Serialize)]
struct TaskCard {
    id: String,
    name: String,
    instruction: String,
    group: String,
    split: String,
    difficulty: String,
    capability: String,
    k: usize,
    checks: String,
    implemented: bool,
    not_implemented_reason: String,
    /// What the last expert sweep says of it ("solved 3/3 on DATE at COMMIT"), or empty.
    expert: String,
}

fn enum_text<T: serde::Serialize>(v: &T) -> String {
    serde_json::to_value(v).ok().and_then(|v| v.as_str().map(str::to_owned)).unwrap_or_default()
}

fn task_cards() -> anyhow::Result<Vec<TaskCard>> {
    let catalog = libero_tasks::Catalog::discover()?;
    Ok(catalog
        .tasks()
        .iter()
        .map(|t| TaskCard {
            id: t.id.clone(),
            name: t.name.clone(),
            instruction: t.agent_instruction().to_owned(),
            group: t.group.clone(),
            split: enum_text(&t.split),
            difficulty: enum_text(&t.difficulty),
            capability: t.capability.clone(),
            k: t.stage_count,
            checks: if t.checker.is_bddl_terminal() {
                "success when the task's BDDL goal holds on the final state at finish_episode".into()
            } else {
                format!("K = {} ordered stage(s) judged by a private evaluator; success needs all of them", t.stage_count)
            },
            implemented: t.implemented,
            not_implemented_reason: t.not_implemented_reason.clone().unwrap_or_default(),
            expert: crate::expert_sweep::expert_line(&[&t.id]),
        })
        .collect())
}

/// A registered pool entry as the Tasks page shows it.
#[derive(serde::Serialize)]
struct PoolCard {
    id: String,
    name: String,
    instruction: String,
    group: String,
    source: String,
    checker: String,
    k: usize,
    /// `runs`, `runs as T07`, or why not.
    status: String,
    runs: bool,
    /// Empty when the entry does not run.
    thumbnail: String,
    teleop: String,
    /// What the last expert sweep says of it, or empty.
    expert: String,
}

fn pool_card(e: &libero_tasks::PoolEntry) -> PoolCard {
    let why_not = e.why_not();
    let runs = why_not.is_none();
    let (thumbnail, status) = match (&e.runs_as, &why_not) {
        (_, Some(why)) => (String::new(), why.clone()),
        // the same scene at the same seed as its release task: one thumbnail
        (Some(t), None) => (format!("/tasks/{t}/thumbnail.png"), format!("runs as {t}")),
        (None, None) => (format!("/tasks/{}/thumbnail.png", e.id()), "runs".into()),
    };
    PoolCard {
        id: e.id(),
        name: e.name.clone(),
        instruction: e.instruction.clone(),
        group: e.group.clone(),
        source: e.source.clone(),
        checker: e.checker.clone(),
        k: e.stage_count,
        status,
        runs,
        thumbnail,
        teleop: if runs { format!("/teleop/{}", e.id()) } else { String::new() },
        expert: crate::expert_sweep::expert_line(&[&e.id(), &e.reference()]),
    }
}

/// `/tasks?suite=…&group=…&q=…`: the release tasks (default) or a pool suite (`all` for every entry).
#[derive(serde::Deserialize, Default)]
pub(crate) struct TasksQuery {
    suite: Option<String>,
    group: Option<String>,
    q: Option<String>,
}

impl TasksQuery {
    fn suite(&self) -> &str {
        self.suite.as_deref().filter(|s| !s.is_empty()).unwrap_or(RELEASE_SUITE)
    }

    fn group(&self) -> Option<&str> {
        self.group.as_deref().filter(|g| !g.is_empty())
    }

    /// The search, lower-cased once per request.
    fn query(&self) -> String {
        self.q.as_deref().unwrap_or_default().trim().to_lowercase()
    }

    /// Whether a task with these texts passes the group and the search `q` (from [`Self::query`]).
    fn keeps(&self, q: &str, group: &str, texts: [&str; 3]) -> bool {
        self.group().is_none_or(|g| g == group) && (q.is_empty() || texts.iter().any(|t| t.to_lowercase().contains(q)))
    }
}

/// The Tasks page's name for the 30 release tasks in the suite filter.
const RELEASE_SUITE: &str = "release";

/// One option of the suite filter.
struct SuiteOption {
    value: String,
    label: String,
    selected: bool,
}

#[derive(Template)]
#[template(path = "tasks.html")]
struct TasksPage {
    release: bool,
    tasks: Vec<TaskCard>,
    pool: Vec<PoolCard>,
    suites: Vec<SuiteOption>,
    groups: Vec<(String, bool)>,
    q: String,
    summary: String,
}

fn tasks_view(query: &TasksQuery) -> anyhow::Result<TasksPage> {
    let pool = libero_tasks::Pool::discover()?;
    let suite = query.suite();
    let counts = pool.suite_counts();
    let mut suites = vec![SuiteOption { value: RELEASE_SUITE.into(), label: "release (T01–T30)".into(), selected: suite == RELEASE_SUITE }];
    let (runs, total): (usize, usize) = counts.iter().fold((0, 0), |(r, t), c| (r + c.runs, t + c.registered));
    suites.push(SuiteOption { value: "all".into(), label: format!("all registered ({runs} of {total} run)"), selected: suite == "all" });
    for c in &counts {
        suites.push(SuiteOption {
            value: c.suite.clone(),
            label: format!("{} ({} of {} run)", c.suite, c.runs, c.registered),
            selected: suite == c.suite,
        });
    }
    if !suites.iter().any(|s| s.selected) {
        anyhow::bail!("no suite {suite:?}: release, all, or one of {}", counts.iter().map(|c| c.suite.as_str()).collect::<Vec<_>>().join(", "));
    }
    let groups = libero_tasks::pool::GROUPS.iter().map(|g| ((*g).to_owned(), query.group() == Some(*g))).collect();
    let release = suite == RELEASE_SUITE;
    let q = query.query();
    let (tasks, pool_cards) = if release {
        let tasks: Vec<TaskCard> =
            task_cards()?.into_iter().filter(|t| query.keeps(&q, &t.group, [&t.id, &t.name, &t.instruction])).collect();
        (tasks, Vec::new())
    } else {
        let cards = pool
            .select(suite, None)
            .filter(|e| query.keeps(&q, &e.group, [&e.id(), &e.name, &e.instruction]))
            .map(pool_card)
            .collect();
        (Vec::new(), cards)
    };
    let shown = tasks.len() + pool_cards.len();
    let summary = if release {
        format!("{shown} of the 30 release tasks")
    } else {
        let running = pool_cards.iter().filter(|c: &&PoolCard| c.runs).count();
        format!("{shown} registered entries, {running} of them run here")
    };
    Ok(TasksPage { release, tasks, pool: pool_cards, suites, groups, q: query.q.clone().unwrap_or_default(), summary })
}

pub(crate) async fn tasks_page(Query(query): Query<TasksQuery>) -> Response {
    match tasks_view(&query) {
        Ok(view) => page(view),
        Err(e) => ApiError::bad_request(format!("{e:#}")).into_response(),
    }
}

pub(crate) async fn tasks_json() -> Response {
    match task_cards() {
        Ok(tasks) => axum::Json(json!({"ok": true, "tasks": tasks})).into_response(),
        Err(e) => ApiError::internal(format!("{e:#}")).into_response(),
    }
}

/// `?camera=head` (default) or `?camera=wrist`.
#[derive(serde::Deserialize)]
pub(crate) struct ThumbnailQuery {
    camera: Option<String>,
}

/// `/tasks/{id}/thumbnail.png[?camera=wrist]`: from the thumbnail cache, which the server fills ahead at start;
/// one not rendered yet renders now (seconds).
pub(crate) async fn thumbnail(State(app): State<AppState>, Path(id): Path<String>, Query(q): Query<ThumbnailQuery>, req: Request<Body>) -> Response {
    thumbnail_of(app, id, q, req).await
}

/// `/tasks/{suite}/{task_id}/thumbnail.png`: a runnable pool entry.
pub(crate) async fn pool_thumbnail(
    State(app): State<AppState>,
    Path((suite, task_id)): Path<(String, String)>,
    Query(q): Query<ThumbnailQuery>,
    req: Request<Body>,
) -> Response {
    thumbnail_of(app, format!("{suite}/{task_id}"), q, req).await
}

async fn thumbnail_of(app: AppState, id: String, q: ThumbnailQuery, req: Request<Body>) -> Response {
    use libero_server::thumbnails::{Camera, ThumbnailError};
    let Some(camera) = Camera::parse(q.camera.as_deref()) else {
        return ApiError::bad_request("camera must be head or wrist").into_response();
    };
    let thumbnails = app.thumbnails.clone();
    match tokio::task::spawn_blocking(move || thumbnails.get(&id, camera)).await {
        Ok(Ok(path)) => serve_file(path, req).await,
        Ok(Err(e @ ThumbnailError::NoSuchTask(_))) => ApiError::not_found(e.to_string()).into_response(),
        Ok(Err(e)) => ApiError::internal(e.to_string()).into_response(),
        Err(e) => ApiError::internal(format!("thumbnail: {e}")).into_response(),
    }
}
