//! The browser console: server-rendered pages (askama templates in `web/templates/`), vanilla ES modules and
//! CSS from `web/static/` (compiled into the binary, so an installed server needs no web folder), the live
//! WebSockets (episode list, one episode's events, frames and agent transcript), and the review page's data: the
//! private video with HTTP range support, the private observation copies, telemetry, calls, stage events and the
//! agent's transcript on the calls' timeline. Every route here is behind the operator guard; nothing here is
//! reachable with an episode token.
use std::path::{Component, Path as FsPath};
use std::sync::Arc;
use std::time::Duration;

use askama::Template;
use libero_episode::video_queue::VideoProgress;
use axum::Router;
use axum::body::Body;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, Query, RawQuery, Request, State};
use axum::http::header;
use axum::response::{Html, IntoResponse, Redirect, Response};
use axum::routing::get;
use libero_episode::RunDir;
use libero_episode::records::read_result;
use serde_json::{Value, json};
use tower::ServiceExt;
use tower_http::services::ServeFile;

use libero_server::live::Hub;
use crate::results::{self, Selection};
use libero_server::store::EpisodeFilter;
use libero_server::{ApiError, ApiResult, App, AppState, episode_json};

/// Largest episode list the home page shows.
const HOME_LIST_LIMIT: i64 = 500;
/// Coalesces bursts of list changes into one refresh per viewer.
const LIST_REFRESH_MIN_INTERVAL: Duration = Duration::from_millis(250);

/// Pages, static files and JSON: small responses worth compressing.
pub fn compressed_routes() -> Router<AppState> {
    Router::new()
        .route("/", get(home))
        .route("/tasks", get(tasks_page))
        .route("/episodes/{id}", get(live_page))
        .route("/episodes/{id}/review", get(review_page))
        .route("/api/episodes/{id}/review", get(review_data))
        .route("/api/episodes/{id}/agent", get(agent_data))
        .route("/api/tasks", get(tasks_json))
        .route("/results", get(results_page))
        .route("/api/results", get(results_api))
}

/// Streams and media: never compressed (range requests, WebSocket upgrades, JPEG/PNG/MP4).
pub fn raw_routes() -> Router<AppState> {
    Router::new()
        .route("/ws/episodes", get(list_socket))
        .route("/ws/episodes/{id}", get(episode_socket))
        .route("/episodes/{id}/video.mp4", get(video))
        .route("/episodes/{id}/observations/{*path}", get(observation_file))
        .route("/tasks/{id}/thumbnail.png", get(thumbnail))
        .route("/tasks/{suite}/{task_id}/thumbnail.png", get(pool_thumbnail))
}

/// Static files, open to everyone (no data in them; the login page needs them).
pub fn static_routes() -> Router<AppState> {
    Router::new().route("/static/{file}", get(static_file))
}

pub(crate) fn page(t: impl Template) -> Response {
    match t.render() {
        Ok(html) => Html(html).into_response(),
        Err(e) => ApiError::internal(format!("template: {e}")).into_response(),
    }
}

/// Episode ids are `ep-<utc>-<hex>`; anything else never reaches the filesystem.
pub(crate) fn valid_id(id: &str) -> bool {
    !id.is_empty() && id.len() <= 96 && id.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
}

/// The stored row of episode `id`, or the response saying why there is none.
async fn stored_row(app: &App, id: &str) -> ApiResult<libero_server::store::EpisodeRow> {
    row_and_source(app, id).await.map(|(row, _)| row)
}

/// Where an episode's row came from.
#[derive(Clone, Copy, PartialEq, Eq)]
enum RowSource {
    /// The store: every server of a shared store writes there.
    Store,
    /// A batch directory's records (a batch's own in-process server).
    BatchDir,
}

async fn row_and_source(app: &App, id: &str) -> ApiResult<(libero_server::store::EpisodeRow, RowSource)> {
    if !valid_id(id) {
        return Err(ApiError::not_found("no such episode"));
    }
    match app.store.get(id).await? {
        Some(row) => Ok((fetched_if_elsewhere(app, row).await, RowSource::Store)),
        None => batch_episode(app, id)
            .await
            .map(|row| (row, RowSource::BatchDir))
            .ok_or_else(|| ApiError::not_found(format!("no episode {id}"))),
    }
}

/// A stored episode whose run directory is not on this machine (a worker elsewhere ran it): with `--artifacts`,
/// its run directory is fetched from the artifact store once its upload is complete, kept under
/// `<data>/artifact_cache/<id>`, and the row points there. Otherwise the row is returned as it is.
async fn fetched_if_elsewhere(app: &App, mut row: libero_server::store::EpisodeRow) -> libero_server::store::EpisodeRow {
    let Some(artifacts) = app.artifacts.as_ref() else { return row };
    if tokio::fs::metadata(&row.episode.run_dir).await.is_ok_and(|m| m.is_dir()) {
        return row;
    }
    let id = row.episode.id.clone();
    let cache = app.episodes.data_dir().join("artifact_cache");
    let dest = cache.join(&id);
    if tokio::fs::metadata(dest.join(libero_artifacts::COMPLETE_MARKER)).await.is_ok() {
        row.episode.run_dir = dest;
        return row;
    }
    let Ok(prefix) = libero_artifacts::run_prefix(&id) else { return row };
    // Fetched beside the destination and renamed into place: a concurrent view never sees half a directory.
    let Ok(staging_name) = libero_episode::json::random_name(&format!(".{id}.")) else { return row };
    let staging = cache.join(staging_name);
    match artifacts.fetch_run(&prefix, &staging).await {
        Ok(Some(_)) => match tokio::fs::rename(&staging, &dest).await {
            Ok(()) => row.episode.run_dir = dest,
            Err(_) if tokio::fs::metadata(dest.join(libero_artifacts::COMPLETE_MARKER)).await.is_ok() => row.episode.run_dir = dest,
            Err(e) => eprintln!("artifact cache: cannot keep episode {id}: {e}"),
        },
        Ok(None) => {}
        Err(e) => eprintln!("artifact store: cannot fetch episode {id}: {e}"),
    }
    let _ = tokio::fs::remove_dir_all(&staging).await;
    row
}

/// An episode a batch ran on its own in-process server (`<batch>/server`, not this server's store): found
/// through the batch's `rollouts.jsonl`, read from its run directory, so Results links open its review.
async fn batch_episode(app: &App, id: &str) -> Option<libero_server::store::EpisodeRow> {
    let roots = app.batch_roots.clone();
    let id = id.to_owned();
    tokio::task::spawn_blocking(move || {
        let run_dir = results::discover(&roots).into_iter().find_map(|(_, dir)| {
            libero_runner::batch::read_records(&dir)
                .ok()?
                .into_iter()
                .find(|r| r.episode_id.as_deref() == Some(id.as_str()))
                .and_then(|r| r.run_dir)
        })?;
        let run = RunDir::new(run_dir);
        let episode = libero_server::store::NewEpisode::from_record(&run).filter(|e| e.id == id)?;
        let end = libero_server::store::EpisodeEnd::from_run(&run);
        Some(libero_server::store::EpisodeRow {
            episode,
            started_at: None,
            finished_at: end.as_ref().map(|e| e.finished_at.clone()),
            outcome: end.as_ref().map(|e| e.outcome.as_str().to_owned()),
            reason: end.as_ref().and_then(|e| e.reason.clone()),
            success: end.as_ref().map(|e| e.success),
            accepted_agent_steps: end.as_ref().and_then(|e| e.accepted_agent_steps),
            completed_stage_count: end.as_ref().and_then(|e| e.completed_stage_count),
            required_stage_count: end.as_ref().and_then(|e| e.required_stage_count),
            wall_time_s: end.as_ref().and_then(|e| e.wall_time_s),
        })
    })
    .await
    .ok()
    .flatten()
}

// ---------------------------------------------------------------------------------------------- results page

#[derive(Template)]
#[template(path = "results.html")]
struct ResultsPage {
    available: Vec<(String, bool)>,
    reps: String,
    view: results::View,
}

/// Loads the selected batches: batch directories off the async workers (they are files of any size), and the
/// batches only the store holds (`run --store`) from the store.
pub(crate) async fn selected(app: &App, sel: &Selection) -> ApiResult<(Vec<String>, Vec<libero_runner::batch::LoadedBatch>)> {
    let internal = |e: String| ApiError::internal(format!("results: {e}"));
    let stored = app.store.batch_names().await.map_err(|e| internal(format!("{e:#}")))?;
    let (roots, sel) = (app.batch_roots.clone(), sel.clone());
    let (names, picked) = match tokio::task::spawn_blocking(move || results::load_selected(&roots, &stored, &sel)).await {
        Ok(Ok(x)) => x,
        Ok(Err(e)) => return Err(ApiError::not_found(e)),
        Err(e) => return Err(internal(e.to_string())),
    };
    let mut batches = Vec::with_capacity(picked.len());
    for p in picked {
        batches.push(match p {
            results::Selected::Loaded(b) => b,
            results::Selected::InStore(name) => {
                let b = app.store.batch(&name).await.map_err(|e| internal(format!("{e:#}")))?;
                let b = b.ok_or_else(|| internal(format!("batch {name} left the store")))?;
                libero_runner::batch::from_stored(b).map_err(|e| internal(format!("{e:#}")))?
            }
        });
    }
    Ok((names, batches))
}

async fn results_page(State(app): State<AppState>, RawQuery(query): RawQuery) -> ApiResult {
    let sel = Selection::parse(query.as_deref());
    let (names, batches) = selected(&app, &sel).await?;
    let view = results::view(&batches, &sel);
    Ok(page(ResultsPage {
        available: names.into_iter().map(|n| (n.clone(), sel.batches.contains(&n))).collect(),
        reps: sel.reps.map(|n| n.to_string()).unwrap_or_default(),
        view,
    }))
}

async fn results_api(State(app): State<AppState>, RawQuery(query): RawQuery) -> ApiResult {
    let sel = Selection::parse(query.as_deref());
    let (names, batches) = selected(&app, &sel).await?;
    Ok(axum::Json(results::results_json(&names, &batches, &sel)).into_response())
}

// ---------------------------------------------------------------------------------------------- home page

#[derive(Template)]
#[template(path = "home.html")]
struct HomePage {
    /// This server as the browser reached it, and this binary: the getting-started commands are copied as is.
    base_url: String,
    exe: String,
    filter_task: String,
    filter_outcome: String,
    filter_batch: String,
    filter_harness: String,
    /// Suggestions for the harness filter: the runner's harnesses and the operator's own kinds of episode.
    harnesses: Vec<&'static str>,
    outcomes: Vec<String>,
    rows: Vec<HomeRow>,
    tasks: Vec<String>,
}

/// One line of the episode table (the same fields the live list sends as JSON).
struct HomeRow {
    id: String,
    task: String,
    harness: String,
    model: String,
    batch: String,
    level: i64,
    outcome: String,
    progress: String,
    wall_time: String,
    submissions: String,
    /// A branch's parent episode and control step (issue 33).
    branch: Option<(String, i64)>,
}

impl HomeRow {
    fn of(v: &Value) -> Self {
        let text = |k: &str| v[k].as_str().unwrap_or("").to_owned();
        let progress = match (v["completed_stage_count"].as_i64(), v["required_stage_count"].as_i64()) {
            (Some(c), Some(k)) => format!("{c}/{k}"),
            _ => "–".into(),
        };
        Self {
            id: text("id"),
            task: text("task_ref"),
            harness: text("harness"),
            model: text("model"),
            batch: text("batch"),
            level: v["level"].as_i64().unwrap_or(0),
            outcome: v["outcome"].as_str().unwrap_or("RUNNING").to_owned(),
            progress,
            wall_time: v["wall_time_s"].as_f64().map(|s| format!("{s:.1} s")).unwrap_or_else(|| "–".into()),
            submissions: v["accepted_agent_steps"].as_i64().map(|n| n.to_string()).unwrap_or_else(|| "–".into()),
            branch: branch_of(v),
        }
    }
}

/// The parent episode and control step of a stored row that is a branch.
fn branch_of(v: &Value) -> Option<(String, i64)> {
    Some((v["branch_parent"].as_str()?.to_owned(), v["branch_step"].as_i64()?))
}

/// The stored rows with the live figures of episodes this process is running.
async fn episode_list(app: &App, filter: &EpisodeFilter) -> anyhow::Result<Vec<Value>> {
    app.sync_all().await;
    let rows = app.store.list_filtered(filter, HOME_LIST_LIMIT).await?;
    Ok(rows
        .iter()
        .map(|r| {
            let mut v = episode_json(app, r);
            if let (Some(hub), Some(obj)) = (app.hubs.get(&r.episode.id), v.as_object_mut()) {
                let live = hub.summary();
                for k in ["completed_stage_count", "required_stage_count", "wall_time_s"] {
                    if obj.get(k).is_none_or(Value::is_null) && !live[k].is_null() {
                        obj.insert(k.into(), live[k].clone());
                    }
                }
            }
            if let Some(obj) = v.as_object_mut() {
                obj.entry("outcome").and_modify(|o| {
                    if o.is_null() {
                        *o = json!("RUNNING");
                    }
                });
            }
            v
        })
        .collect())
}

async fn home(State(app): State<AppState>, headers: axum::http::HeaderMap, Query(filter): Query<EpisodeFilter>) -> Response {
    let filter = filter.normalized();
    let list = match episode_list(&app, &filter).await {
        Ok(l) => l,
        Err(e) => return ApiError::internal(format!("{e:#}")).into_response(),
    };
    let tasks = libero_tasks::Catalog::discover().map(|c| c.tasks().iter().map(|t| t.id.clone()).collect()).unwrap_or_default();
    // The Host header passed the allow-list, so it names this server.
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok()).unwrap_or("127.0.0.1:8080");
    let exe = std::env::current_exe().map(|p| p.display().to_string()).unwrap_or_else(|_| "libero-agent".into());
    page(HomePage {
        base_url: format!("http://{host}"),
        exe,
        rows: list.iter().map(HomeRow::of).collect(),
        filter_task: filter.task.unwrap_or_default(),
        filter_outcome: filter.outcome.unwrap_or_default(),
        filter_batch: filter.batch.unwrap_or_default(),
        filter_harness: filter.harness.unwrap_or_default(),
        harnesses: vec!["expert", "teleop", "command", "codex", "claude_code", "kimi_code", "qwen_code", "deepseek"],
        outcomes: ["RUNNING", "SUCCESS", "FAIL", "SIM_TIMEOUT", "INVALID"].map(String::from).to_vec(),
        tasks,
    })
}

async fn list_socket(ws: WebSocketUpgrade, State(app): State<AppState>, Query(filter): Query<EpisodeFilter>) -> Response {
    let filter = filter.normalized();
    ws.on_upgrade(move |socket| list_stream(socket, app, filter))
}

/// Sends the filtered list at once and again after every change (at most every 250 ms).
async fn list_stream(mut socket: WebSocket, app: AppState, filter: EpisodeFilter) {
    let mut changes = app.hubs.changes();
    loop {
        let message = match episode_list(&app, &filter).await {
            Ok(list) => json!({"type": "episodes", "episodes": list}),
            Err(e) => json!({"type": "error", "error": format!("{e:#}")}),
        };
        if socket.send(Message::Text(message.to_string().into())).await.is_err() {
            return;
        }
        if matches!(next_wake(&mut socket, &mut changes, None).await, Wake::Gone) {
            return;
        }
    }
}

/// What woke a socket that follows the store.
enum Wake {
    /// The store changed (or, with a re-read period, that period passed): read it again.
    Changed,
    /// The viewer sent a text, ping or pong: nothing to re-read.
    Viewer,
    /// The viewer or the server went away.
    Gone,
}

/// Waits for a change of the store (a burst coalesced into one, at most every 250 ms), a message of the viewer,
/// or `reread` without either (for stores without notifications).
async fn next_wake(socket: &mut WebSocket, changes: &mut tokio::sync::broadcast::Receiver<()>, reread: Option<Duration>) -> Wake {
    let period = async {
        match reread {
            Some(d) => tokio::time::sleep(d).await,
            None => std::future::pending().await,
        }
    };
    tokio::select! {
        changed = changes.recv() => {
            if matches!(changed, Err(tokio::sync::broadcast::error::RecvError::Closed)) {
                return Wake::Gone;
            }
            tokio::time::sleep(LIST_REFRESH_MIN_INTERVAL).await;
            *changes = changes.resubscribe(); // drop what piled up meanwhile: one re-read covers it
            Wake::Changed
        }
        _ = period => Wake::Changed,
        incoming = socket.recv() => {
            if matches!(incoming, Some(Ok(Message::Ping(_) | Message::Pong(_) | Message::Text(_)))) { Wake::Viewer } else { Wake::Gone }
        }
    }
}

// ---------------------------------------------------------------------------------------------- live page

#[derive(Template)]
#[template(path = "live.html")]
struct LivePage {
    id: String,
    task: String,
    /// The task's page and instruction (empty for a task outside the catalog and pool).
    task_href: String,
    instruction: String,
    level: i64,
    max_agent_steps: u64,
    max_wall_time_s: f64,
    /// A branch's parent episode and control step.
    branch: Option<(String, i64)>,
}

/// An open episode another server of the shared store runs: what the store knows, and the link to its live view.
#[derive(Template)]
#[template(path = "live_elsewhere.html")]
struct LiveElsewherePage {
    id: String,
    task: String,
    level: i64,
    state: &'static str,
    /// The running server and its live view; `None` when it has no console.
    server_url: Option<String>,
    live_url: Option<String>,
    created_at: String,
    started_at: String,
    batch: Option<String>,
    /// `accepted of max` agent steps and `completed / required` stages, as the running server last stored them.
    steps: String,
    stages: String,
}

async fn live_page(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    let (row, source) = match row_and_source(&app, &id).await {
        Ok(r) => r,
        Err(e) => return e.into_response(),
    };
    let Some(hub) = app.hubs.get(&id) else {
        if let Some(server_url) = runs_elsewhere(&app, &row, source) {
            let (state, steps, stages) = (elsewhere_state(&row), elsewhere_steps(&row), elsewhere_stages(&row));
            return page(LiveElsewherePage {
                live_url: server_url.as_ref().map(|url| format!("{url}/episodes/{id}")),
                id,
                task: row.episode.task_ref,
                level: row.episode.level,
                state,
                server_url,
                created_at: row.episode.created_at,
                started_at: row.started_at.unwrap_or_else(|| "not yet".into()),
                batch: row.episode.batch,
                steps,
                stages,
            });
        }
        // Ended, or run by this server before a restart: only the review exists.
        return Redirect::to(&format!("/episodes/{id}/review")).into_response();
    };
    let (task_href, instruction) = task_link(&row.episode.task_ref);
    page(LivePage {
        id,
        task: row.episode.task_ref,
        task_href,
        instruction,
        level: row.episode.level,
        max_agent_steps: hub.max_agent_steps,
        max_wall_time_s: hub.max_wall_time_s,
        branch: row.episode.branch_parent.clone().zip(row.episode.branch_step),
    })
}

/// For a stored episode that is still open and that this server does not run (the caller checked it has no live
/// hub here): `Some(Some(url))`, the server whose live view shows it; `Some(None)`, a server without a console
/// (`libero-worker`, `run`'s in-process server) runs it, so only the store follows it. `None` otherwise.
fn runs_elsewhere(app: &App, row: &libero_server::store::EpisodeRow, source: RowSource) -> Option<Option<String>> {
    if row.outcome.is_some() || source != RowSource::Store {
        return None;
    }
    match row.episode.server_url.as_deref() {
        None => Some(None),
        Some(url) if url != app.public_url && (url.starts_with("http://") || url.starts_with("https://")) => Some(Some(url.to_owned())),
        Some(_) => None,
    }
}

async fn episode_socket(ws: WebSocketUpgrade, State(app): State<AppState>, Path(id): Path<String>) -> Response {
    if let Some(hub) = app.hubs.get(&id) {
        let transcript = RunDir::new(app.episodes.runs_dir().join(&id)).agent_events_jsonl();
        return ws.on_upgrade(move |socket| episode_stream(socket, hub, transcript));
    }
    let (row, source) = match row_and_source(&app, &id).await {
        Ok(r) => r,
        Err(e) => return e.into_response(),
    };
    if runs_elsewhere(&app, &row, source).is_some() {
        return ws.on_upgrade(move |socket| elsewhere_stream(socket, app, row));
    }
    // Ended and released (or run before a restart): the viewer gets the final state from the records.
    ws.on_upgrade(move |socket| ended_stream(socket, row))
}

/// How often the page of an episode running elsewhere re-reads the store without a notification: a SQLite
/// store shared by processes on one machine has no LISTEN/NOTIFY.
const ELSEWHERE_REREAD: Duration = Duration::from_secs(5);

/// The state of an open episode another server runs.
fn elsewhere_state(row: &libero_server::store::EpisodeRow) -> &'static str {
    if row.started_at.is_some() { "running" } else { "prepared" }
}

fn elsewhere_steps(row: &libero_server::store::EpisodeRow) -> String {
    row.accepted_agent_steps.map_or_else(|| "none yet".into(), |n| n.to_string())
}

fn elsewhere_stages(row: &libero_server::store::EpisodeRow) -> String {
    match (row.completed_stage_count, row.required_stage_count) {
        (Some(c), Some(r)) => format!("{c} / {r}"),
        _ => "not reported yet".into(),
    }
}

/// What a viewer of an episode another server runs gets: the store's row as an `elsewhere` message at once and
/// again whenever the store changes (a PostgreSQL store's `NOTIFY`, which the running server sends with every
/// change of steps and stages, wakes it; otherwise every few seconds), until the row has its outcome: then an
/// `ended` message and the socket closes, and the page opens the review.
async fn elsewhere_stream(mut socket: WebSocket, app: AppState, mut row: libero_server::store::EpisodeRow) {
    let id = row.episode.id.clone();
    let mut changes = app.hubs.changes();
    let mut last_sent = String::new();
    loop {
        let message = if row.outcome.is_some() {
            json!({"type": "ended", "outcome": row.outcome, "reason": row.reason, "review_url": format!("/episodes/{id}/review")})
        } else {
            json!({"type": "elsewhere", "state": elsewhere_state(&row), "started_at": row.started_at,
                "steps": elsewhere_steps(&row), "stages": elsewhere_stages(&row),
                "accepted_agent_steps": row.accepted_agent_steps, "completed_stage_count": row.completed_stage_count,
                "required_stage_count": row.required_stage_count})
        }
        .to_string();
        if message != last_sent {
            if !send_text(&mut socket, &message).await {
                return;
            }
            last_sent = message;
        }
        if row.outcome.is_some() {
            let _ = socket.send(Message::Close(None)).await;
            return;
        }
        match next_wake(&mut socket, &mut changes, Some(ELSEWHERE_REREAD)).await {
            Wake::Changed => {}
            Wake::Viewer => continue,
            Wake::Gone => return,
        }
        row = match app.store.get(&id).await {
            Ok(Some(fresh)) => fresh,
            // Gone from the store (or the store failed): the page falls back to reloading.
            Ok(None) | Err(_) => return,
        };
    }
}

/// What a viewer of an episode without a live hub gets: `hello` with the budgets, the final state as a
/// `finished` event (the live page then stops reconnecting), then the socket closes.
async fn ended_stream(mut socket: WebSocket, row: libero_server::store::EpisodeRow) {
    let record: Value = std::fs::read_to_string(RunDir::new(&row.episode.run_dir).episode_record())
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or(Value::Null);
    let hello = json!({"type": "hello", "max_agent_steps": record["max_agent_steps"], "max_wall_time_s": record["max_wall_time_seconds"]});
    let state = if row.outcome.is_some() { "ended" } else { "not live on this server" };
    let finished = json!({"type": "finished", "state": state, "outcome": row.outcome, "reason": row.reason});
    for message in [hello, finished] {
        if !send_text(&mut socket, &message.to_string()).await {
            return;
        }
    }
    let _ = socket.send(Message::Close(None)).await;
}

async fn send_text(socket: &mut WebSocket, text: &str) -> bool {
    socket.send(Message::Text(text.into())).await.is_ok()
}

/// New events of the agent's transcript since `offset` (`None`: the newest ones) as one `agent` message, if any.
async fn agent_message(path: &std::path::Path, offset: &mut Option<u64>) -> Option<String> {
    let (p, from) = (path.to_path_buf(), *offset);
    let max = if from.is_some() { LIVE_AGENT_TICK_BYTES } else { LIVE_AGENT_CATCH_UP_BYTES };
    let (events, next) = tokio::task::spawn_blocking(move || read_transcript_lines(&p, from, max)).await.ok()?;
    *offset = Some(next);
    (!events.is_empty()).then(|| json!({"type": "agent", "events": events}).to_string())
}

/// Catch-up (history, latest step, newest frame, the newest of the agent's transcript) then everything as it
/// happens. The episode never waits: frames come from a watch channel (a slow socket skips to the newest), events
/// from a broadcast channel (a viewer that falls behind is sent the whole history again, marked `reset`); the
/// transcript the runner appends to the run directory is read every half second.
async fn episode_stream(mut socket: WebSocket, hub: Arc<Hub>, transcript: std::path::PathBuf) {
    let Some(sub) = hub.subscribe() else { return };
    let branch = hub.branch().map(|(parent, step)| json!({"parent_episode_id": parent, "parent_control_step": step}));
    let hello = json!({"type": "hello", "max_agent_steps": hub.max_agent_steps, "max_wall_time_s": hub.max_wall_time_s, "branch": branch});
    if !send_text(&mut socket, &hello.to_string()).await {
        return;
    }
    for text in sub.history.iter().chain(&sub.latest_step) {
        if !send_text(&mut socket, text).await {
            return;
        }
    }
    let (mut events, mut frames, mut closed) = (sub.events, sub.frames, sub.closed);
    let newest = frames.borrow_and_update().clone();
    if let Some(frame) = newest {
        if socket.send(Message::Binary(frame)).await.is_err() {
            return;
        }
    }
    let mut agent_offset = None;
    if let Some(text) = agent_message(&transcript, &mut agent_offset).await
        && !send_text(&mut socket, &text).await
    {
        return;
    }
    // Closed while this viewer subscribed: the history it was sent ends with `finished`.
    if *closed.borrow_and_update() {
        return;
    }
    let mut agent_tick = tokio::time::interval(LIVE_AGENT_TICK);
    loop {
        tokio::select! {
            _ = agent_tick.tick() => {
                if let Some(text) = agent_message(&transcript, &mut agent_offset).await
                    && !send_text(&mut socket, &text).await
                {
                    return;
                }
            }
            event = events.recv() => match event {
                Ok(text) => if !send_text(&mut socket, &text).await { return },
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {
                    let Some((history, fresh)) = hub.resubscribe() else { return };
                    events = fresh;
                    if !send_text(&mut socket, r#"{"type":"reset"}"#).await { return }
                    for text in &history {
                        if !send_text(&mut socket, text).await { return }
                    }
                }
                Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
            },
            // The server let go of the hub (the episode ended a while ago): the page has its `finished` event.
            _ = closed.changed() => return,
            changed = frames.changed() => {
                if changed.is_err() { return }
                let frame = frames.borrow_and_update().clone();
                if let Some(frame) = frame {
                    if socket.send(Message::Binary(frame)).await.is_err() { return }
                }
            }
            incoming = socket.recv() => {
                if !matches!(incoming, Some(Ok(Message::Ping(_) | Message::Pong(_) | Message::Text(_)))) {
                    return;
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------- review page

#[derive(Template)]
#[template(path = "review.html")]
struct ReviewPage {
    id: String,
    task: String,
    /// The task's page and instruction (empty for a task outside the catalog and pool).
    task_href: String,
    instruction: String,
    level: i64,
    outcome: String,
    /// A branch's parent episode and control step.
    branch: Option<(String, i64)>,
}

async fn review_page(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    if valid_id(&id) {
        app.sync(&id).await;
    }
    match stored_row(&app, &id).await {
        Ok(row) => page(ReviewPage {
            id,
            task_href: task_link(&row.episode.task_ref).0,
            instruction: task_link(&row.episode.task_ref).1,
            branch: row.episode.branch_parent.clone().zip(row.episode.branch_step),
            task: row.episode.task_ref,
            level: row.episode.level,
            outcome: row.outcome.unwrap_or_else(|| "RUNNING".into()),
        }),
        Err(e) => e.into_response(),
    }
}

/// The task page and instruction of an episode's task reference, or empty strings.
fn task_link(task_ref: &str) -> (String, String) {
    crate::task_page::task_of_ref(task_ref).unwrap_or_default()
}

fn read_jsonl(path: &FsPath) -> Vec<Value> {
    read_jsonl_page(path, 0, usize::MAX).0
}

/// Up to `limit` parsed lines of a JSON-lines file from line `from` on, read as a stream (a long episode's file is
/// never held whole), and the index of the next line if the file goes on.
fn read_jsonl_page(path: &FsPath, from: u64, limit: usize) -> (Vec<Value>, Option<u64>) {
    let (lines, next) = read_jsonl_indexed(path, from, limit);
    (lines.into_iter().map(|(_, v)| v).collect(), next)
}

/// [`read_jsonl_page`] with each value's line index (lines that do not parse are skipped, not counted).
fn read_jsonl_indexed(path: &FsPath, from: u64, limit: usize) -> (Vec<(u64, Value)>, Option<u64>) {
    use std::io::BufRead;
    let Ok(file) = std::fs::File::open(path) else { return (Vec::new(), None) };
    let mut out = Vec::new();
    let mut lines = std::io::BufReader::new(file).lines().skip(usize::try_from(from).unwrap_or(usize::MAX));
    let mut index = from;
    for line in lines.by_ref() {
        let Ok(line) = line else { break };
        if let Ok(v) = serde_json::from_str(&line) {
            out.push((index, v));
        }
        index += 1;
        if out.len() >= limit {
            let more = lines.next().is_some();
            return (out, more.then_some(index));
        }
    }
    (out, None)
}

/// The calls of `actions.jsonl`, each with the control steps it covered (start = step 0; an accepted
/// `osc_sequence` of n actions advances n steps), counting on from `control_step` (where the previous page ended).
fn timeline_calls(actions: &[Value], mut control_step: u64) -> (Vec<Value>, u64) {
    let calls = actions
        .iter()
        .map(|e| {
            let (req, resp) = (&e["request"], &e["response"]);
            let ok = resp["ok"] == json!(true);
            let executed = libero_episode::tools::actions_executed(resp);
            let steps = if executed { resp["execution"]["control_steps"].as_u64().unwrap_or(0) } else { 0 };
            let begin = control_step;
            control_step = control_step.saturating_add(steps);
            json!({
                "event_index": e["event_index"],
                "recorded_at": e["recorded_at"],
                "tool": req["tool"].as_str().or(req["command"].as_str()),
                "actions": req["arguments"]["actions"].as_array().map(Vec::len),
                "ok": ok,
                "error_type": resp["error_type"],
                "error": resp["error"],
                "observation_id": resp["observation_id"],
                "control_step_begin": begin,
                "control_step_end": control_step,
            })
        })
        .collect();
    (calls, control_step)
}

/// Lines per page of the review API's long parts (calls, telemetry).
const REVIEW_PAGE_LINES: usize = 5000;

/// `?part=calls&from=N&control_step=S` or `?part=telemetry&from=N`: the next page of a long part.
#[derive(serde::Deserialize, Default)]
struct ReviewQuery {
    part: Option<String>,
    #[serde(default)]
    from: u64,
    #[serde(default)]
    control_step: u64,
}

/// One page of calls: the calls, and where the next page starts (line and control step), if any.
fn calls_page(run: &RunDir, from: u64, control_step: u64) -> Value {
    let (lines, next) = read_jsonl_page(&run.actions_jsonl(), from, REVIEW_PAGE_LINES);
    let (calls, step) = timeline_calls(&lines, control_step);
    json!({"calls": calls, "calls_next": next.map(|n| json!({"from": n, "control_step": step}))})
}

fn telemetry_page(run: &RunDir, from: u64) -> Value {
    let (lines, next) = read_jsonl_page(&run.telemetry_jsonl(), from, REVIEW_PAGE_LINES);
    json!({"telemetry": lines, "telemetry_next": next.map(|n| json!({"from": n}))})
}

/// Everything the review page shows, from the private run directory, with the long parts (calls, telemetry)
/// in pages the page follows through `calls_next` / `telemetry_next`. Operator-only.
async fn review_data(State(app): State<AppState>, Path(id): Path<String>, Query(q): Query<ReviewQuery>) -> ApiResult {
    let run = RunDir::new(stored_row(&app, &id).await?.episode.run_dir);
    let episodes = app.episodes.clone();
    let data = tokio::task::spawn_blocking(move || match q.part.as_deref() {
        Some("calls") => Ok(calls_page(&run, q.from, q.control_step)),
        Some("telemetry") => Ok(telemetry_page(&run, q.from)),
        Some("video") => Ok(libero_server::video_part(&episodes, &run)),
        Some(other) => Err(format!("part must be calls, telemetry or video (got {other:?})")),
        None => {
            let result = read_result(&run);
            let mut stage_events = read_jsonl(&run.stage_events_jsonl());
            if let Some(events) = result.as_ref().and_then(|r| r["private_evaluation"]["events"].as_array()) {
                stage_events.extend(events.iter().cloned());
            }
            stage_events.sort_by_key(|e| e["control_step"].as_u64().unwrap_or(0));
            let mut v = json!({
                "ok": true,
                "stage_events": stage_events,
                "result": result,
                "video_fps": 20.0,
            });
            for part in [libero_server::video_part(&episodes, &run), calls_page(&run, 0, 0), telemetry_page(&run, 0)] {
                if let (Some(obj), Value::Object(p)) = (v.as_object_mut(), part) {
                    obj.extend(p);
                }
            }
            Ok(v)
        }
    })
    .await;
    match data.map_err(|e| ApiError::internal(format!("review: {e}")))? {
        Ok(v) => Ok(axum::Json(v).into_response()),
        Err(msg) => Err(ApiError::bad_request(msg)),
    }
}

// ---------------------------------------------------------------------------------------------- agent transcript

/// Items per page of the agent timeline.
const AGENT_PAGE_ITEMS: usize = 2000;

/// Where a page of the agent timeline starts: the transcript's line, the action log's line and control step, the
/// observation current there, and whether a robot tool call of the transcript already stands before the next
/// robot call (all from the previous page's `timeline_next`).
#[derive(serde::Deserialize, serde::Serialize, Default, Clone)]
struct AgentQuery {
    #[serde(default)]
    from: u64,
    #[serde(default)]
    calls_from: u64,
    #[serde(default)]
    control_step: u64,
    observation: Option<String>,
    #[serde(default)]
    claimed: bool,
}

/// The served copy of an image or file the agent looked at: only a published observation file, from the
/// episode's private copy of the observation current at that moment; anything else stays a path.
fn observation_copy(run: &RunDir, id: &str, observation: Option<&str>, file: Option<&str>) -> Option<(String, String)> {
    let (obs, file) = (observation?, file?);
    let plain = plain_relative(obs) && !obs.contains('/') && plain_relative(file);
    (plain && run.private_observations().join(obs).join(file).is_file())
        .then(|| (obs.to_owned(), format!("/episodes/{id}/observations/{obs}/{file}")))
}

/// One page of the agent's transcript merged with the robot's calls by time (`kind: robot_call` items are the
/// calls as the review's timeline has them, `t` their `recorded_at`). A robot tool call of the transcript stands
/// before the robot call it made even when the runner captured it a little after the server recorded the call.
/// Images and files the agent viewed that are published observation files get `observation_url`.
fn agent_timeline(run: &RunDir, id: &str, q: &AgentQuery) -> Value {
    let transcript = run.agent_events_jsonl();
    let available = transcript.is_file();
    let (events, events_next) = read_jsonl_indexed(&transcript, q.from, AGENT_PAGE_ITEMS);
    let (lines, calls_next) = read_jsonl_indexed(&run.actions_jsonl(), q.calls_from, AGENT_PAGE_ITEMS);
    let call_lines: Vec<Value> = lines.iter().map(|(_, v)| v.clone()).collect();
    let (calls, _) = timeline_calls(&call_lines, q.control_step);
    let mut cursor = q.clone();
    let (mut i, mut j) = (0, 0);
    let mut out = Vec::new();
    while out.len() < AGENT_PAGE_ITEMS {
        let take_event = match (events.get(i), calls.get(j)) {
            (None, None) => break,
            // The other file goes on: the next page decides what comes first.
            (Some(_), None) if calls_next.is_some() => break,
            (None, Some(_)) if events_next.is_some() => break,
            (Some(_), None) => true,
            (None, Some(_)) => false,
            (Some((_, e)), Some(c)) => {
                let before = e["t"].as_str().unwrap_or("") <= c["recorded_at"].as_str().unwrap_or("");
                let its_call = e["kind"] == "tool_call" && !e["robot_tool"].is_null() && e["robot_tool"] == c["tool"] && !cursor.claimed;
                before || its_call
            }
        };
        if take_event {
            let (line, mut e) = events[i].clone();
            if e["kind"] == "tool_call" && !e["robot_tool"].is_null() {
                cursor.claimed = true;
            }
            if matches!(e["kind"].as_str(), Some("image_view" | "file_read"))
                && let Some((obs, url)) = observation_copy(run, id, cursor.observation.as_deref(), e["observation_file"].as_str())
                && let Some(obj) = e.as_object_mut()
            {
                obj.insert("observation_id".into(), json!(obs));
                obj.insert("observation_url".into(), json!(url));
            }
            out.push(e);
            cursor.from = line + 1;
            i += 1;
        } else {
            let mut c = calls[j].clone();
            if c["ok"] == true
                && let Some(obs) = c["observation_id"].as_str()
            {
                cursor.observation = Some(obs.to_owned());
            }
            cursor.claimed = false;
            cursor.calls_from = lines[j].0 + 1;
            cursor.control_step = c["control_step_end"].as_u64().unwrap_or(cursor.control_step);
            if let Some(obj) = c.as_object_mut() {
                obj.insert("kind".into(), json!("robot_call"));
                obj.insert("t".into(), obj.get("recorded_at").cloned().unwrap_or(Value::Null));
            }
            out.push(c);
            j += 1;
        }
    }
    let done = i == events.len() && j == calls.len() && events_next.is_none() && calls_next.is_none();
    // Unparsable lines at the end of a page are passed over with it.
    if i == events.len() && let Some(n) = events_next {
        cursor.from = cursor.from.max(n);
    }
    if j == calls.len() && let Some(n) = calls_next {
        cursor.calls_from = cursor.calls_from.max(n);
    }
    json!({"ok": true, "available": available, "timeline": out, "timeline_next": if done { Value::Null } else { json!(cursor) }})
}

/// `GET /api/episodes/{id}/agent`: the agent's transcript on the robot's timeline, in pages the caller follows
/// through `timeline_next` (its fields are the next request's query). Operator-only, as the review.
async fn agent_data(State(app): State<AppState>, Path(id): Path<String>, Query(q): Query<AgentQuery>) -> ApiResult {
    let run = RunDir::new(stored_row(&app, &id).await?.episode.run_dir);
    let v = tokio::task::spawn_blocking(move || agent_timeline(&run, &id, &q))
        .await
        .map_err(|e| ApiError::internal(format!("agent transcript: {e}")))?;
    Ok(axum::Json(v).into_response())
}

/// Most transcript events a live viewer is sent when it connects (the newest ones; the review has them all).
const LIVE_AGENT_CATCH_UP_BYTES: u64 = 256 << 10;
/// Most transcript bytes sent to a live viewer per tick.
const LIVE_AGENT_TICK_BYTES: u64 = 256 << 10;
/// How often a live viewer's transcript is read for new events.
const LIVE_AGENT_TICK: Duration = Duration::from_millis(500);

/// The complete lines of `path` from byte `offset` on (at most `max` bytes; from the last `max` bytes when
/// `offset` is None, beginning at a line start) as JSON, and the offset after them.
fn read_transcript_lines(path: &FsPath, offset: Option<u64>, max: u64) -> (Vec<Value>, u64) {
    use std::io::{Read, Seek};
    let Ok(mut f) = std::fs::File::open(path) else { return (Vec::new(), offset.unwrap_or(0)) };
    let size = f.metadata().map(|m| m.len()).unwrap_or(0);
    let start = offset.unwrap_or(size.saturating_sub(max)).min(size);
    let mut buf = Vec::new();
    if f.seek(std::io::SeekFrom::Start(start)).is_err() || f.take(max).read_to_end(&mut buf).is_err() {
        return (Vec::new(), start);
    }
    // Only whole lines; a tail catch-up starts after its first newline (unless it starts the file).
    let first = if offset.is_none() && start > 0 { buf.iter().position(|&b| b == b'\n').map_or(buf.len(), |p| p + 1) } else { 0 };
    let end = buf.iter().rposition(|&b| b == b'\n').map_or(first, |p| p + 1).max(first);
    let values = buf[first..end].split(|&b| b == b'\n').filter_map(|l| serde_json::from_slice(l).ok()).collect();
    (values, start + end as u64)
}

/// A file served with range support (the video, observation images).
pub(crate) async fn serve_file(path: std::path::PathBuf, req: Request<Body>) -> Response {
    match ServeFile::new(path).oneshot(req).await {
        Ok(resp) => resp.map(Body::new).into_response(),
        Err(e) => ApiError::internal(format!("file: {e}")).into_response(),
    }
}

async fn run_dir_of(app: &App, id: &str) -> Option<RunDir> {
    stored_row(app, id).await.ok().map(|r| RunDir::new(r.episode.run_dir))
}

async fn video(State(app): State<AppState>, Path(id): Path<String>, req: Request<Body>) -> Response {
    match run_dir_of(&app, &id).await {
        Some(run) if run.continuous_video().is_file() => serve_file(run.continuous_video(), req).await,
        Some(run) => {
            let message = match app.episodes.video_progress(&run) {
                Some(VideoProgress::Queued) => "the video is queued for rendering (video rendering, 0 %)".to_owned(),
                Some(VideoProgress::Failed { error }) => format!("the video could not be rendered: {error}"),
                Some(p) => format!("the video is not ready yet (video rendering, {} %)", p.percent().unwrap_or(0)),
                None => "this episode records no video".to_owned(),
            };
            ApiError::not_found(message).into_response()
        }
        None => ApiError::not_found(format!("no episode {id}")).into_response(),
    }
}

/// A plain relative path of the private observation copies: normal components of `[A-Za-z0-9-_.]` only.
fn plain_relative(rel: &str) -> bool {
    !rel.is_empty()
        && FsPath::new(rel).components().all(|c| matches!(c, Component::Normal(_)))
        && rel.chars().all(|c| c.is_ascii_alphanumeric() || "-_./".contains(c))
}

/// `observations/<obs_id>/<file>`: only plain relative names inside the private copy.
async fn observation_file(State(app): State<AppState>, Path((id, rel)): Path<(String, String)>, req: Request<Body>) -> Response {
    let rel_path = FsPath::new(&rel);
    let Some(run) = run_dir_of(&app, &id).await.filter(|_| plain_relative(&rel)) else {
        return ApiError::not_found("no such observation file").into_response();
    };
    let path = run.private_observations().join(rel_path);
    if !path.is_file() {
        return ApiError::not_found("no such observation file").into_response();
    }
    serve_file(path, req).await
}

// ---------------------------------------------------------------------------------------------- tasks page

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
struct TasksQuery {
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

async fn tasks_page(Query(query): Query<TasksQuery>) -> Response {
    match tasks_view(&query) {
        Ok(view) => page(view),
        Err(e) => ApiError::bad_request(format!("{e:#}")).into_response(),
    }
}

async fn tasks_json() -> Response {
    match task_cards() {
        Ok(tasks) => axum::Json(json!({"ok": true, "tasks": tasks})).into_response(),
        Err(e) => ApiError::internal(format!("{e:#}")).into_response(),
    }
}

/// `?camera=head` (default) or `?camera=wrist`.
#[derive(serde::Deserialize)]
struct ThumbnailQuery {
    camera: Option<String>,
}

/// `/tasks/{id}/thumbnail.png[?camera=wrist]`: from the thumbnail cache, which the server fills ahead at start;
/// one not rendered yet renders now (seconds).
async fn thumbnail(State(app): State<AppState>, Path(id): Path<String>, Query(q): Query<ThumbnailQuery>, req: Request<Body>) -> Response {
    thumbnail_of(app, id, q, req).await
}

/// `/tasks/{suite}/{task_id}/thumbnail.png`: a runnable pool entry.
async fn pool_thumbnail(
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

// ---------------------------------------------------------------------------------------------- static files

macro_rules! web_static {
    ($name:literal) => {
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/../../web/static/", $name))
    };
}

async fn static_file(Path(file): Path<String>) -> Response {
    let (body, kind) = match file.as_str() {
        "style.css" => (web_static!("style.css"), "text/css; charset=utf-8"),
        "common.js" => (web_static!("common.js"), "text/javascript; charset=utf-8"),
        "home.js" => (web_static!("home.js"), "text/javascript; charset=utf-8"),
        "live.js" => (web_static!("live.js"), "text/javascript; charset=utf-8"),
        "review.js" => (web_static!("review.js"), "text/javascript; charset=utf-8"),
        "teleop.js" => (web_static!("teleop.js"), "text/javascript; charset=utf-8"),
        "demos.js" => (web_static!("demos.js"), "text/javascript; charset=utf-8"),
        "elsewhere.js" => (web_static!("elsewhere.js"), "text/javascript; charset=utf-8"),
        "branch.js" => (web_static!("branch.js"), "text/javascript; charset=utf-8"),
        _ => return ApiError::not_found("no such file").into_response(),
    };
    ([(header::CONTENT_TYPE, kind), (header::CACHE_CONTROL, "no-cache")], body).into_response()
}
