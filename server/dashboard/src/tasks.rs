//! The Tasks page, `/tasks` (`web/templates/tasks.html`): the release tasks or a pool suite as cards, with
//! filters; `/api/tasks`, the release tasks as JSON; and the tasks' start thumbnails from the thumbnail cache
//! (`/tasks/{id}/thumbnail.png`, `/tasks/{suite}/{task_id}/thumbnail.png`), which the task and teleop pages show too.
use askama::Template;
use axum::body::Body;
use axum::extract::{Path, Request, State};
use axum::response::{IntoResponse, Response};
use libero_server::{ApiError, ApiQuery, AppState};
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

fn task_cards(catalog: &libero_tasks::Catalog) -> Vec<TaskCard> {
    catalog
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
        .collect()
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

/// `/tasks?tasks=…&group=…&q=…`: the tasks of a task selection (docs/commands.md, "Selecting tasks": `release`,
/// the default; `all`; a suite; `group:G`; `T11,libero_90/35`; `match:TEXT`), narrowed by a group and a search.
/// `suite=` is read as `tasks=` (older links).
#[derive(serde::Deserialize, Default)]
pub(crate) struct TasksQuery {
    tasks: Option<String>,
    suite: Option<String>,
    group: Option<String>,
    q: Option<String>,
}

impl TasksQuery {
    /// The selection as written, `release` when none is given.
    fn selection_text(&self) -> &str {
        [&self.tasks, &self.suite].into_iter().flatten().map(|s| s.trim()).find(|s| !s.is_empty()).unwrap_or(RELEASE_SUITE)
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

/// One suggestion of the selection field.
struct SuiteOption {
    value: String,
    label: String,
}

#[derive(Template)]
#[template(path = "tasks.html")]
struct TasksPage {
    tasks: Vec<TaskCard>,
    pool: Vec<PoolCard>,
    /// The selection as it reads back (`T14,libero_90/35`), in the field.
    selection: String,
    suites: Vec<SuiteOption>,
    groups: Vec<(String, bool)>,
    q: String,
    summary: String,
    /// Why the selection in the field selects nothing (a typo, an unknown suite), shown above the cards.
    error: String,
}

fn tasks_view(query: &TasksQuery) -> anyhow::Result<TasksPage> {
    let catalog = libero_tasks::Catalog::discover()?;
    let pool = libero_tasks::Pool::discover()?;
    let text = query.selection_text();
    let picks = text.parse::<libero_tasks::Selection>().and_then(|s| Ok((s.resolve(catalog.tasks(), &pool)?, s.to_string())));
    let (picks, selection, mut error) = match picks {
        Ok((picks, shown)) => (picks, shown, String::new()),
        Err(e) => (Vec::new(), text.chars().take(200).collect(), e.to_string()),
    };
    if let Some(g) = query.group().filter(|g| !libero_tasks::pool::GROUPS.contains(g)) {
        let g: String = g.chars().take(60).collect();
        error = format!("group must be one of {}, not {g:?}", libero_tasks::pool::GROUPS.join(", "));
    }
    let counts = pool.suite_counts();
    let mut suites = vec![SuiteOption { value: RELEASE_SUITE.into(), label: "release (T01–T30)".into() }];
    let (runs, total): (usize, usize) = counts.iter().fold((0, 0), |(r, t), c| (r + c.runs, t + c.registered));
    suites.push(SuiteOption { value: "all".into(), label: format!("all registered ({runs} of {total} run)") });
    suites.push(SuiteOption { value: "stock".into(), label: "stock LIBERO (130 entries)".into() });
    for c in &counts {
        suites.push(SuiteOption { value: c.suite.clone(), label: format!("{} ({} of {} run)", c.suite, c.runs, c.registered) });
    }
    for g in libero_tasks::pool::GROUPS {
        suites.push(SuiteOption { value: format!("group:{g}"), label: format!("every {g} entry") });
    }
    let groups = libero_tasks::pool::GROUPS.iter().map(|g| ((*g).to_owned(), query.group() == Some(*g))).collect();
    let q = query.query();
    let mut release_cards = task_cards(&catalog);
    let mut tasks = Vec::new();
    let mut pool_cards = Vec::new();
    for pick in picks {
        match pick.member {
            libero_tasks::Member::Release(t) => {
                if let Some(i) = release_cards.iter().position(|c| c.id == t.id) {
                    let card = release_cards.swap_remove(i);
                    if query.keeps(&q, &card.group, [&card.id, &card.name, &card.instruction]) {
                        tasks.push(card);
                    }
                }
            }
            libero_tasks::Member::Entry(e) => {
                if query.keeps(&q, &e.group, [&e.id(), &e.name, &e.instruction]) {
                    pool_cards.push(pool_card(e));
                }
            }
        }
    }
    let running = pool_cards.iter().filter(|c: &&PoolCard| c.runs).count();
    let summary = match (tasks.len(), pool_cards.len()) {
        _ if !error.is_empty() => String::new(),
        (n, 0) => format!("{n} of the 30 release tasks"),
        (0, n) => format!("{n} registered entries, {running} of them run here"),
        (n, m) => format!("{n} of the 30 release tasks and {m} registered entries, {running} of them run here"),
    };
    Ok(TasksPage { tasks, pool: pool_cards, selection, suites, groups, q: query.q.clone().unwrap_or_default(), summary, error })
}

pub(crate) async fn tasks_page(ApiQuery(query): ApiQuery<TasksQuery>) -> Response {
    match tasks_view(&query) {
        // a selection that cannot be read still gets the page, with the reason and the field to fix it
        Ok(view) if !view.error.is_empty() => (axum::http::StatusCode::BAD_REQUEST, page(view)).into_response(),
        Ok(view) => page(view),
        Err(e) => ApiError::bad_request(format!("{e:#}")).into_response(),
    }
}

pub(crate) async fn tasks_json() -> Response {
    match libero_tasks::Catalog::discover() {
        Ok(catalog) => axum::Json(json!({"ok": true, "tasks": task_cards(&catalog)})).into_response(),
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
pub(crate) async fn thumbnail(State(app): State<AppState>, Path(id): Path<String>, ApiQuery(q): ApiQuery<ThumbnailQuery>, req: Request<Body>) -> Response {
    thumbnail_of(app, id, q, req).await
}

/// `/tasks/{suite}/{task_id}/thumbnail.png`: a runnable pool entry.
pub(crate) async fn pool_thumbnail(
    State(app): State<AppState>,
    Path((suite, task_id)): Path<(String, String)>,
    ApiQuery(q): ApiQuery<ThumbnailQuery>,
    req: Request<Body>,
) -> Response {
    thumbnail_of(app, format!("{suite}/{task_id}"), q, req).await
}

async fn thumbnail_of(app: AppState, id: String, q: ThumbnailQuery, req: Request<Body>) -> Response {
    use libero_server::thumbnails::{Camera, ThumbnailError};
    let Some(camera) = Camera::parse(q.camera.as_deref()) else {
        return ApiError::bad_request("camera must be head or wrist").into_response();
    };
    // a page left before its turn drops this future, which takes its render out of the queue
    match app.thumbnails.get(id, camera).await {
        Ok(path) => serve_file(path, req).await,
        Err(e @ ThumbnailError::NoSuchTask(_)) => ApiError::not_found(e.to_string()).into_response(),
        Err(e) => ApiError::internal(e.to_string()).into_response(),
    }
}
