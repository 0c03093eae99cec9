//! The live page of an episode, `/episodes/{id}` (`web/templates/live.html`, `web/static/live.js`), and its
//! WebSocket `/ws/episodes/{id}`: events, frames and the agent's transcript of an episode this server runs; for an
//! open episode another server of the shared store runs, the page `web/templates/live_elsewhere.html`
//! (`web/static/elsewhere.js`) and the store's row as it changes; for an ended one, the final state (the page then
//! opens the review).
use std::path::Path as FsPath;
use std::sync::Arc;
use std::time::Duration;

use askama::Template;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, State};
use axum::response::{IntoResponse, Redirect, Response};
use libero_episode::RunDir;
use libero_records::records::read_episode_record;
use libero_server::live::Hub;
use libero_server::{App, AppState};
use serde_json::{Value, json};

use crate::common::page;
use crate::rows::{RowSource, Wake, next_wake, row_and_source};
use crate::task_page::task_link;

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

pub(crate) async fn live_page(State(app): State<AppState>, Path(id): Path<String>) -> Response {
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
fn runs_elsewhere(app: &App, row: &libero_store::EpisodeRow, source: RowSource) -> Option<Option<String>> {
    if row.outcome.is_some() || source != RowSource::Store {
        return None;
    }
    match row.episode.server_url.as_deref() {
        None => Some(None),
        Some(url) if url != app.public_url && (url.starts_with("http://") || url.starts_with("https://")) => Some(Some(url.to_owned())),
        Some(_) => None,
    }
}

pub(crate) async fn episode_socket(ws: WebSocketUpgrade, State(app): State<AppState>, Path(id): Path<String>) -> Response {
    if let Some(hub) = app.hubs.get(&id) {
        let transcript = RunDir::new(app.episodes.lifecycle().runs_dir().join(&id)).agent_events_jsonl();
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
fn elsewhere_state(row: &libero_store::EpisodeRow) -> &'static str {
    if row.started_at.is_some() { "running" } else { "prepared" }
}

fn elsewhere_steps(row: &libero_store::EpisodeRow) -> String {
    row.accepted_agent_steps.map_or_else(|| "none yet".into(), |n| n.to_string())
}

fn elsewhere_stages(row: &libero_store::EpisodeRow) -> String {
    match (row.completed_stage_count, row.required_stage_count) {
        (Some(c), Some(r)) => format!("{c} / {r}"),
        _ => "not reported yet".into(),
    }
}

/// What a viewer of an episode another server runs gets: the store's row as an `elsewhere` message at once and
/// again whenever the store changes (a PostgreSQL store's `NOTIFY`, which the running server sends with every
/// change of steps and stages, wakes it; otherwise every few seconds), until the row has its outcome: then an
/// `ended` message and the socket closes, and the page opens the review.
async fn elsewhere_stream(mut socket: WebSocket, app: AppState, mut row: libero_store::EpisodeRow) {
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
async fn ended_stream(mut socket: WebSocket, row: libero_store::EpisodeRow) {
    let record = read_episode_record(&RunDir::new(&row.episode.run_dir)).ok().flatten().unwrap_or_default();
    let hello = json!({"type": "hello", "max_agent_steps": record.max_agent_steps, "max_wall_time_s": record.max_wall_time_seconds});
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
    if let Some(frame) = newest
        && socket.send(Message::Binary(frame)).await.is_err()
    {
        return;
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
                if let Some(frame) = frame
                    && socket.send(Message::Binary(frame)).await.is_err()
                {
                    return;
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
