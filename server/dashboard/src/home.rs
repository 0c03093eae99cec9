//! The home page, `/` (`web/templates/home.html`, `web/static/home.js`): the episode table with its filters and
//! the getting-started commands, kept current by the episode-list WebSocket `/ws/episodes`.
use askama::Template;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use libero_store::EpisodeFilter;
use libero_episode::Outcome;
use libero_records::episode_view::EpisodeView;
use libero_server::{ApiError, ApiQuery, App, AppState, episode_json};
use serde_json::json;

use crate::common::page;
use crate::rows::{Wake, next_wake};

/// Largest episode list the home page shows.
const HOME_LIST_LIMIT: i64 = 500;

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
    /// The filters in words when any is set (an empty list then says no episode matches them, not "no episodes").
    filters_text: String,
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
    /// When it started (prepared, while it has not started), `2026-12-07 14:08 UTC`, and the record's timestamp.
    started: String,
    started_iso: String,
    /// The home page filtered on this row's batch.
    batch_href: String,
    /// Why the episode ended as it did (abandoned, aborted, the runner's word), in full for the hover.
    reason: String,
    /// [`Self::reason`] cut to one line.
    reason_short: String,
}

/// Longest reason shown under an outcome (`home.js` cuts the same way).
const REASON_CHARS: usize = 80;

/// `reason` cut to [`REASON_CHARS`] characters, an ellipsis marking the cut.
fn short_reason(reason: &str) -> String {
    if reason.chars().count() > REASON_CHARS {
        let mut cut: String = reason.chars().take(REASON_CHARS - 1).collect();
        cut.push('…');
        cut
    } else {
        reason.to_owned()
    }
}

/// `2026-12-07T14:08:28.38+00:00` → `2026-12-07 14:08 UTC` (as `home.js` writes it).
pub(crate) fn short_utc(iso: &str) -> String {
    match (iso.get(..10), iso.get(11..16)) {
        (Some(day), Some(time)) if iso.as_bytes().get(10) == Some(&b'T') => format!("{day} {time} UTC"),
        _ => iso.to_owned(),
    }
}

impl HomeRow {
    fn of(v: &EpisodeView) -> Self {
        let text = |t: &Option<String>| t.clone().unwrap_or_default();
        let progress = match (v.completed_stage_count, v.required_stage_count) {
            (Some(c), Some(k)) => format!("{c}/{k}"),
            _ => "–".into(),
        };
        let started = v.started_at.as_deref().unwrap_or(&v.created_at);
        let reason = text(&v.reason);
        Self {
            id: v.id.clone(),
            task: v.task_ref.clone(),
            harness: text(&v.harness),
            model: text(&v.model),
            batch: text(&v.batch),
            level: v.level,
            outcome: v.outcome.map_or(RUNNING, Outcome::as_str).to_owned(),
            progress,
            wall_time: v.wall_time_s.map(|s| format!("{s:.1} s")).unwrap_or_else(|| "–".into()),
            submissions: v.accepted_agent_steps.map(|n| n.to_string()).unwrap_or_else(|| "–".into()),
            branch: v.branch_parent.clone().zip(v.branch_step),
            started: short_utc(started),
            started_iso: started.to_owned(),
            batch_href: format!("/?batch={}", crate::results::percent_encode(v.batch.as_deref().unwrap_or(""))),
            reason_short: short_reason(&reason),
            reason,
        }
    }
}

/// The outcome column of an open episode (`home.js` shows a null outcome the same way).
const RUNNING: &str = "RUNNING";

/// The stored rows with the live figures of episodes this process is running (an open episode's outcome is null,
/// as in the operator API).
async fn episode_list(app: &App, filter: &EpisodeFilter) -> anyhow::Result<Vec<EpisodeView>> {
    app.sync_all().await;
    let rows = app.store.list_filtered(filter, HOME_LIST_LIMIT).await?;
    Ok(rows
        .iter()
        .map(|r| {
            let mut v = episode_json(app, r);
            if let Some(live) = app.hubs.get(&r.episode.id).and_then(|hub| hub.summary()) {
                v.completed_stage_count = v.completed_stage_count.or(live.completed_stage_count);
                v.required_stage_count = v.required_stage_count.or(live.required_stage_count);
                v.wall_time_s = v.wall_time_s.or(live.wall_time_s);
            }
            v
        })
        .collect())
}

/// The outcome filter's choices: open episodes and every outcome an episode can end with.
fn outcome_choices() -> Vec<String> {
    std::iter::once(RUNNING).chain(libero_episode::Outcome::ALL.map(libero_episode::Outcome::as_str)).map(String::from).collect()
}

/// A filter on an outcome no episode can have would show an empty table under "any": refused, naming the choices.
fn known_outcome(filter: &EpisodeFilter) -> Result<(), String> {
    match &filter.outcome {
        Some(o) if !outcome_choices().contains(o) => Err(format!("outcome must be one of {}, not {o:?}", outcome_choices().join(", "))),
        _ => Ok(()),
    }
}

pub(crate) async fn home(State(app): State<AppState>, headers: axum::http::HeaderMap, ApiQuery(filter): ApiQuery<EpisodeFilter>) -> Response {
    let filter = filter.normalized();
    if let Err(why) = known_outcome(&filter) {
        return ApiError::bad_request(why).into_response();
    }
    let list = match episode_list(&app, &filter).await {
        Ok(l) => l,
        Err(e) => return ApiError::internal(format!("{e:#}")).into_response(),
    };
    let tasks = libero_tasks::Catalog::discover().map(|c| c.tasks().iter().map(|t| t.id.clone()).collect()).unwrap_or_default();
    // The Host header passed the allow-list, so it names this server.
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok()).unwrap_or("127.0.0.1:8080");
    let exe = std::env::current_exe().map(|p| p.display().to_string()).unwrap_or_else(|_| "libero-agent".into());
    let filters_text = [("task", &filter.task), ("outcome", &filter.outcome), ("batch", &filter.batch), ("harness", &filter.harness)]
        .iter()
        .filter_map(|(name, v)| v.as_ref().map(|v| format!("{name} “{}”", v.chars().take(80).collect::<String>())))
        .collect::<Vec<_>>()
        .join(", ");
    page(HomePage {
        filters_text,
        base_url: format!("http://{host}"),
        exe,
        rows: list.iter().map(HomeRow::of).collect(),
        filter_task: filter.task.unwrap_or_default(),
        filter_outcome: filter.outcome.unwrap_or_default(),
        filter_batch: filter.batch.unwrap_or_default(),
        filter_harness: filter.harness.unwrap_or_default(),
        harnesses: vec!["expert", "teleop", "command", "codex", "claude_code", "kimi_code", "qwen_code", "deepseek"],
        outcomes: outcome_choices(),
        tasks,
    })
}

pub(crate) async fn list_socket(ws: WebSocketUpgrade, State(app): State<AppState>, ApiQuery(filter): ApiQuery<EpisodeFilter>) -> Response {
    let filter = filter.normalized();
    if let Err(why) = known_outcome(&filter) {
        return ApiError::bad_request(why).into_response();
    }
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

#[cfg(test)]
mod tests {
    #[test]
    fn timestamps_read_as_minutes_in_utc() {
        assert_eq!(super::short_utc("2026-12-07T14:08:28.383004+00:00"), "2026-12-07 14:08 UTC");
        assert_eq!(super::short_utc("yesterday"), "yesterday");
        assert_eq!(super::short_utc(""), "");
    }

    #[test]
    fn a_long_end_reason_is_cut_to_one_line_at_a_character_boundary() {
        assert_eq!(super::short_reason("abandoned"), "abandoned");
        let long = "é".repeat(200);
        let cut = super::short_reason(&long);
        assert_eq!(cut.chars().count(), super::REASON_CHARS);
        assert!(cut.ends_with('…'));
    }
}
