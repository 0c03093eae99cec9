//! The review page of an episode, `/episodes/{id}/review` (`web/templates/review.html`, `web/static/review.js`
//! and `web/static/branch.js`), and its data, all from the episode's private run directory: `/api/episodes/{id}/review`
//! (stage events, result, video state, and the calls and telemetry in pages), `/api/episodes/{id}/agent` (the
//! agent's transcript on the calls' timeline), the private video with HTTP range support and the private
//! observation copies.
use std::path::{Component, Path as FsPath};

use askama::Template;
use axum::body::Body;
use axum::extract::{Path, Request, State};
use axum::response::{IntoResponse, Response};
use libero_episode::RunDir;
use libero_episode::lifecycle::MomentError;
use libero_records::records::{ActionEvent, PrivateEvent, read_result};
use libero_episode::video_queue::VideoProgress;
use libero_server::{ApiError, ApiQuery, ApiResult, AppState};
use serde::Serialize;
use serde::de::DeserializeOwned;
use serde_json::{Value, json};

use crate::common::{page, serve_file, valid_id};
use crate::rows::{run_dir_of, stored_row};
use crate::task_page::task_link;

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
    /// The batch the episode ran in, and its Results page.
    batch: Option<(String, String)>,
    /// This server's binary, as "prepare for an agent" prints the command (it may not be on PATH).
    exe: String,
    /// The episode's harness and model: a branch prepared for an agent is recorded with them unless changed.
    harness: String,
    model: String,
}

pub(crate) async fn review_page(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    if valid_id(&id) {
        app.sync(&id).await;
    }
    match stored_row(&app, &id).await {
        Ok(row) => page(ReviewPage {
            id,
            task_href: task_link(&row.episode.task_ref).0,
            instruction: task_link(&row.episode.task_ref).1,
            branch: row.episode.branch_parent.clone().zip(row.episode.branch_step),
            exe: std::env::current_exe().map(|p| p.display().to_string()).unwrap_or_else(|_| "libero-agent".into()),
            batch: row.episode.batch.clone().filter(|b| !b.is_empty()).map(|b| (format!("/results?batch={}", crate::results::percent_encode(&b)), b)),
            harness: row.episode.harness.clone().unwrap_or_default(),
            model: row.episode.model.clone().unwrap_or_default(),
            task: row.episode.task_ref,
            level: row.episode.level,
            outcome: row.outcome.unwrap_or_else(|| "RUNNING".into()),
        }),
        Err(e) => e.into_response(),
    }
}


fn read_jsonl<T: DeserializeOwned>(path: &FsPath) -> Vec<T> {
    read_jsonl_page(path, 0, usize::MAX).0
}

/// Up to `limit` parsed lines of a JSON-lines file from line `from` on, read as a stream (a long episode's file is
/// never held whole), and the index of the next line if the file goes on.
fn read_jsonl_page<T: DeserializeOwned>(path: &FsPath, from: u64, limit: usize) -> (Vec<T>, Option<u64>) {
    let (lines, next) = read_jsonl_indexed(path, from, limit);
    (lines.into_iter().map(|(_, v)| v).collect(), next)
}

/// [`read_jsonl_page`] with each value's line index (lines that do not parse are skipped, not counted).
fn read_jsonl_indexed<T: DeserializeOwned>(path: &FsPath, from: u64, limit: usize) -> (Vec<(u64, T)>, Option<u64>) {
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

/// One call of the review's timeline: an `actions.jsonl` event with the control steps it covered.
#[derive(Debug, Clone, Serialize)]
struct TimelineCall {
    event_index: Option<u64>,
    recorded_at: Option<String>,
    tool: Option<String>,
    /// Micro-actions the call sent.
    actions: Option<usize>,
    ok: bool,
    error_type: Value,
    error: Value,
    observation_id: Value,
    control_step_begin: u64,
    control_step_end: u64,
}

impl TimelineCall {
    /// The call as the agent timeline lists it (`kind: robot_call`, `t` its `recorded_at`).
    fn robot_call(&self) -> Value {
        let mut v = json!(self);
        if let Some(obj) = v.as_object_mut() {
            obj.insert("kind".into(), json!("robot_call"));
            obj.insert("t".into(), json!(self.recorded_at));
        }
        v
    }
}

/// The calls of `actions.jsonl`, each with the control steps it covered (start = step 0; an accepted
/// `osc_sequence` of n actions advances n steps), counting on from `control_step` (where the previous page ended).
fn timeline_calls<'a>(actions: impl IntoIterator<Item = &'a ActionEvent>, mut control_step: u64) -> (Vec<TimelineCall>, u64) {
    let calls = actions
        .into_iter()
        .map(|e| {
            let steps = if e.actions_executed() { e.control_steps() } else { 0 };
            let begin = control_step;
            control_step = control_step.saturating_add(steps);
            let answered = |key: &str| e.response().get(key).cloned().unwrap_or(Value::Null);
            TimelineCall {
                event_index: e.event_index,
                recorded_at: e.recorded_at.clone(),
                tool: e.tool().or(e.command()).map(str::to_owned),
                actions: e.actions().map(Vec::len),
                ok: e.ok(),
                error_type: answered("error_type"),
                error: answered("error"),
                observation_id: answered("observation_id"),
                control_step_begin: begin,
                control_step_end: control_step,
            }
        })
        .collect();
    (calls, control_step)
}

/// Lines per page of the review API's long parts (calls, telemetry).
const REVIEW_PAGE_LINES: usize = 5000;

/// `?part=calls&from=N&control_step=S` or `?part=telemetry&from=N`: the next page of a long part.
#[derive(serde::Deserialize, Default)]
pub(crate) struct ReviewQuery {
    part: Option<String>,
    #[serde(default)]
    from: u64,
    #[serde(default)]
    control_step: u64,
}

/// One page of calls: the calls, and where the next page starts (line and control step), if any.
fn calls_page(run: &RunDir, from: u64, control_step: u64) -> Value {
    let (lines, next) = read_jsonl_page::<ActionEvent>(&run.actions_jsonl(), from, REVIEW_PAGE_LINES);
    let (calls, step) = timeline_calls(&lines, control_step);
    json!({"calls": calls, "calls_next": next.map(|n| json!({"from": n, "control_step": step}))})
}

fn telemetry_page(run: &RunDir, from: u64) -> Value {
    // Passed on as written (the review page plots them).
    let (lines, next) = read_jsonl_page::<Value>(&run.telemetry_jsonl(), from, REVIEW_PAGE_LINES);
    json!({"telemetry": lines, "telemetry_next": next.map(|n| json!({"from": n}))})
}

/// Everything the review page shows, from the private run directory, with the long parts (calls, telemetry)
/// in pages the page follows through `calls_next` / `telemetry_next`. Operator-only.
pub(crate) async fn review_data(State(app): State<AppState>, Path(id): Path<String>, ApiQuery(q): ApiQuery<ReviewQuery>) -> ApiResult {
    let run = RunDir::new(stored_row(&app, &id).await?.episode.run_dir);
    let episodes = app.episodes.clone();
    let data = tokio::task::spawn_blocking(move || match q.part.as_deref() {
        Some("calls") => Ok(calls_page(&run, q.from, q.control_step)),
        Some("telemetry") => Ok(telemetry_page(&run, q.from)),
        Some("video") => Ok(libero_server::video_part(episodes.lifecycle(), &run)),
        Some(other) => Err(format!("part must be calls, telemetry or video (got {other:?})")),
        None => {
            let result = read_result(&run);
            let mut stage_events: Vec<PrivateEvent> = read_jsonl(&run.stage_events_jsonl());
            if let Some(events) = result.as_ref().and_then(|r| r.private_evaluation.as_ref()?.events.as_ref()) {
                stage_events.extend(events.iter().cloned());
            }
            stage_events.sort_by_key(|e| e.control_step.unwrap_or(0));
            let mut v = json!({
                "ok": true,
                "stage_events": stage_events,
                "result": result,
                "video_fps": 20.0,
            });
            for part in [libero_server::video_part(episodes.lifecycle(), &run), calls_page(&run, 0, 0), telemetry_page(&run, 0)] {
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
pub(crate) struct AgentQuery {
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

/// What the merge reads of a transcript event (a line the runner wrote as `AgentEvent`); the event itself is
/// passed on as it is. A line that does not read so has none of them.
#[derive(serde::Deserialize, Default)]
struct EventKeys {
    t: Option<String>,
    kind: Option<String>,
    robot_tool: Option<String>,
    observation_file: Option<String>,
}

impl EventKeys {
    fn of(event: &Value) -> Self {
        <Self as serde::Deserialize>::deserialize(event).unwrap_or_default()
    }

    /// A tool call the runner tied to one of the episode's robot tools.
    fn robot_call(&self) -> bool {
        self.kind.as_deref() == Some("tool_call") && self.robot_tool.is_some()
    }
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
    // The transcript is the agent's CLI output, normalised: its events are passed on as they are.
    let (events, events_next) = read_jsonl_indexed::<Value>(&transcript, q.from, AGENT_PAGE_ITEMS);
    let (lines, calls_next) = read_jsonl_indexed::<ActionEvent>(&run.actions_jsonl(), q.calls_from, AGENT_PAGE_ITEMS);
    let (calls, _) = timeline_calls(lines.iter().map(|(_, v)| v), q.control_step);
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
                let k = EventKeys::of(e);
                let before = k.t.as_deref().unwrap_or("") <= c.recorded_at.as_deref().unwrap_or("");
                let its_call = k.robot_call() && k.robot_tool == c.tool && !cursor.claimed;
                before || its_call
            }
        };
        if take_event {
            let (line, mut e) = events[i].clone();
            let k = EventKeys::of(&e);
            if k.robot_call() {
                cursor.claimed = true;
            }
            if matches!(k.kind.as_deref(), Some("image_view" | "file_read"))
                && let Some((obs, url)) = observation_copy(run, id, cursor.observation.as_deref(), k.observation_file.as_deref())
                && let Some(obj) = e.as_object_mut()
            {
                obj.insert("observation_id".into(), json!(obs));
                obj.insert("observation_url".into(), json!(url));
            }
            out.push(e);
            cursor.from = line + 1;
            i += 1;
        } else {
            let c = &calls[j];
            if c.ok
                && let Some(obs) = c.observation_id.as_str()
            {
                cursor.observation = Some(obs.to_owned());
            }
            cursor.claimed = false;
            cursor.calls_from = lines[j].0 + 1;
            cursor.control_step = c.control_step_end;
            out.push(c.robot_call());
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
pub(crate) async fn agent_data(State(app): State<AppState>, Path(id): Path<String>, ApiQuery(q): ApiQuery<AgentQuery>) -> ApiResult {
    let run = RunDir::new(stored_row(&app, &id).await?.episode.run_dir);
    let v = tokio::task::spawn_blocking(move || agent_timeline(&run, &id, &q))
        .await
        .map_err(|e| ApiError::internal(format!("agent transcript: {e}")))?;
    Ok(axum::Json(v).into_response())
}


pub(crate) async fn video(State(app): State<AppState>, Path(id): Path<String>, req: Request<Body>) -> Response {
    match run_dir_of(&app, &id).await {
        Some(run) if run.continuous_video().is_file() => serve_file(run.continuous_video(), req).await,
        Some(run) => {
            let message = match app.episodes.lifecycle().video_progress(&run) {
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

/// `?step=N`: the control step of a moment.
#[derive(serde::Deserialize)]
pub(crate) struct MomentQuery {
    step: Option<String>,
}

/// `GET /api/episodes/{id}/moment?step=N`: head | wrist of the state after control step N as a JPEG, rendered from
/// the episode's recorded actions (the review of an episode without its video). Operator-only, as the review.
/// The answer names its control step and the episode's count in `X-Control-Step` / `X-Control-Steps`.
pub(crate) async fn moment(State(app): State<AppState>, Path(id): Path<String>, ApiQuery(q): ApiQuery<MomentQuery>) -> Response {
    let Some(step) = q.step.as_deref().and_then(|s| s.trim().parse::<u64>().ok()) else {
        let got = q.step.as_deref().map_or("nothing".to_owned(), |s| format!("{:?}", s.chars().take(40).collect::<String>()));
        return ApiError::bad_request(format!("step must be a control step number: 0, 1, 2, … (got {got})")).into_response();
    };
    let Some(run) = run_dir_of(&app, &id).await else {
        return ApiError::not_found(format!("no episode {id}")).into_response();
    };
    if !run.episode_record().is_file() {
        return ApiError::not_found(format!("the run directory of {id} is not on this machine (it ran on another worker)")).into_response();
    }
    let episodes = app.episodes.clone();
    let rendered = tokio::task::spawn_blocking(move || episodes.lifecycle().moment(&run, step)).await;
    match rendered {
        Ok(Ok(m)) => (
            [
                (axum::http::header::CONTENT_TYPE, "image/jpeg".to_owned()),
                (axum::http::header::CACHE_CONTROL, "private, max-age=600".to_owned()),
                (axum::http::HeaderName::from_static("x-control-step"), m.control_step.to_string()),
                (axum::http::HeaderName::from_static("x-control-steps"), m.control_steps.to_string()),
            ],
            Body::from(m.jpeg.to_vec()),
        )
            .into_response(),
        Ok(Err(e @ MomentError::OutOfRange { .. })) => ApiError::bad_request(e.to_string()).into_response(),
        Ok(Err(e @ MomentError::NotReplayable(_))) => ApiError::unprocessable(e.to_string()).into_response(),
        Ok(Err(e)) => ApiError::internal(e.to_string()).into_response(),
        Err(e) => ApiError::internal(format!("moment: {e}")).into_response(),
    }
}

/// A plain relative path of the private observation copies: normal components of `[A-Za-z0-9-_.]` only.
fn plain_relative(rel: &str) -> bool {
    !rel.is_empty()
        && FsPath::new(rel).components().all(|c| matches!(c, Component::Normal(_)))
        && rel.chars().all(|c| c.is_ascii_alphanumeric() || "-_./".contains(c))
}

/// `observations/<obs_id>/<file>`: only plain relative names inside the private copy.
pub(crate) async fn observation_file(State(app): State<AppState>, Path((id, rel)): Path<(String, String)>, req: Request<Body>) -> Response {
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
