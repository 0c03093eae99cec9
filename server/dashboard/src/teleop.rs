//! Teleoperation and the demonstration library in the dashboard (issue 8). The operator drives an episode of
//! their own in-process (`EpisodeHandle::call`, never the agent-token MCP path) from a WebSocket that carries
//! batches of normalized OSC actions; the live view is the ordinary live frame stream. "Save demonstration"
//! finishes the episode and records a bundle into `<data>/demos/<task>/<episode>/` with the demo library, which
//! verifies it by replay. The Demos page lists, plays, verifies, deletes and exports bundles. Everything here
//! sits behind the operator guard (token and cross-site check).
//!
//! Lifecycle (issue 49): the page makes its episode on the first action (opening it makes none); an episode no
//! teleop page is connected to for `serve --teleop-abandon-s` is ended as abandoned; "Finish and judge"
//! (`POST /api/episodes/{id}/finish`, any episode of this server, the live page too) asks the evaluator's verdict;
//! saving over the control socket reports the verifying replay's progress before its result.
use std::path::{Path as FsPath, PathBuf};
use std::time::{Duration, Instant};

use askama::Template;
use axum::Router;
use axum::body::{Body, Bytes};
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, Request, State};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use libero_episode::EpisodeHandle;
use libero_episode::demo::lerobot::export_lerobot;
use libero_episode::demo::record::RecordOptions;
use libero_episode::demo::{MANIFEST, TRAJECTORY, VIDEO_HEAD_WRIST, library, read_manifest, validate_bundle};
use libero_episode::tools::MAX_MICRO_ACTIONS_PER_CALL;
use libero_records::records::ToolReply;
use serde::Deserialize;
use serde_json::{Map, Value, json};

use crate::common::{page, serve_file, valid_id};
use libero_server::episodes::{BranchRequest, PrepareRequest, random_hex};
use libero_server::{ApiError, ApiQuery, ApiResult, AppState, TeleopEpisode};
use tokio::sync::mpsc;

/// Wall-clock budget of an operator episode: long enough for unhurried driving.
const TELEOP_WALL_TIME_S: f64 = 3600.0;
/// Seed of a teleop episode unless the page asks for another (the dashboard test's and thumbnails' seed).
const DEFAULT_SEED: u64 = 100;

/// Pages and JSON.
pub fn compressed_routes() -> Router<AppState> {
    Router::new()
        .route("/teleop/{task}", get(teleop_page))
        .route("/teleop/{suite}/{task_id}", get(pool_teleop_page))
        .route("/api/teleop", post(create))
        .route("/api/teleop/{id}/save", post(save))
        .route("/api/episodes/{id}/finish", post(finish))
        .route("/demos", get(demos_page))
        .route("/api/demos", get(demos_json))
        .route("/api/demos/export", post(export))
        .route("/api/demos/{task}/{bundle}/verify", post(verify))
        .route("/api/demos/{task}/{bundle}/delete", post(delete))
}

/// The control socket and bundle videos (never compressed).
pub fn raw_routes() -> Router<AppState> {
    Router::new()
        .route("/ws/teleop/{id}", get(control_socket))
        .route("/demos/{task}/{bundle}/video.mp4", get(bundle_video))
}

fn ok_json(v: Value) -> Response {
    axum::Json(v).into_response()
}

/// An implemented catalog task's or runnable pool entry's (`libero_90/35`) `(id, instruction, K)`, or why it
/// cannot be driven.
fn implemented_task(id: &str) -> Result<(String, String, usize), String> {
    if id.contains('/') {
        let pool = libero_tasks::Pool::discover().map_err(|e| format!("{e:#}"))?;
        let e = pool.lookup(id)?;
        if let Some(why) = e.why_not() {
            return Err(format!("{} is {why}", e.id()));
        }
        // the reference its episodes record (`suite/name`, or the release task it is), so demonstrations of
        // `libero_90/35` and of `libero_90/KITCHEN_SCENE7_open_the_microwave` are one task's
        let paths = libero_sim::AssetPaths::discover().map_err(|e| format!("{e:#}"))?;
        let source = libero_episode::task::resolve_task(&e.id(), &paths).map_err(|e| format!("{e:#}"))?;
        return Ok((source.task_ref, source.instruction, e.stage_count));
    }
    let catalog = libero_tasks::Catalog::discover().map_err(|e| format!("{e:#}"))?;
    let t = catalog.tasks().iter().find(|t| t.id == id).ok_or_else(|| format!("no task {id} in the catalog"))?;
    if !t.implemented {
        return Err(format!("{id} is not implemented: {}", t.not_implemented_reason.clone().unwrap_or_default()));
    }
    Ok((t.id.clone(), t.agent_instruction().to_owned(), t.stage_count))
}

// ---------------------------------------------------------------------------------------------- teleop page

#[derive(Template)]
#[template(path = "teleop.html")]
struct TeleopPage {
    task: String,
    instruction: String,
    k: usize,
    seed: u64,
    /// Drive a branch of this episode at this control step (`?branch=ID&step=N`, the review's "Continue from
    /// here"): every episode the page makes (Reset too) starts from that state.
    branch: Option<(String, u64)>,
    /// The gripper command the page starts with: a branch's parent's last one, so a held object stays held.
    gripper: f64,
}

/// `?branch=ID&step=N` of a teleop page.
#[derive(Deserialize, Default)]
struct BranchQuery {
    branch: Option<String>,
    step: Option<u64>,
}

impl BranchQuery {
    fn origin(self) -> Result<Option<(String, u64)>, String> {
        match (self.branch, self.step) {
            (None, None) => Ok(None),
            (Some(parent), Some(step)) if libero_server::episodes::valid_episode_id(&parent) => Ok(Some((parent, step))),
            _ => Err("a branch needs ?branch=<episode id>&step=<control step>".into()),
        }
    }
}

async fn teleop_page(State(app): State<AppState>, Path(task): Path<String>, ApiQuery(q): ApiQuery<BranchQuery>) -> Response {
    teleop_page_of(&app, &task, q).await
}

/// `/teleop/{suite}/{task_id}`: a pool entry.
async fn pool_teleop_page(State(app): State<AppState>, Path((suite, task_id)): Path<(String, String)>, ApiQuery(q): ApiQuery<BranchQuery>) -> Response {
    teleop_page_of(&app, &format!("{suite}/{task_id}"), q).await
}

async fn teleop_page_of(app: &AppState, task: &str, q: BranchQuery) -> Response {
    let branch = match q.origin() {
        Ok(b) => b,
        Err(e) => return ApiError::bad_request(e).into_response(),
    };
    let (task, instruction, k) = match implemented_task(task) {
        Ok(t) => t,
        Err(e) => return ApiError::not_found(e).into_response(),
    };
    // A branch the page could not start is an error page now, not a page whose controls fail later.
    let gripper = match &branch {
        Some((parent, step)) => match branch_point(app, &task, parent, *step).await {
            Ok(g) => g,
            Err(e) => return e.into_response(),
        },
        None => GRIPPER_OPEN,
    };
    page(TeleopPage { task, instruction, k, seed: DEFAULT_SEED, branch, gripper })
}

/// The gripper command of a fresh start (robosuite: −1 opens, +1 closes).
const GRIPPER_OPEN: f64 = -1.0;

/// Whether episode `parent` of `task` can be continued from control step `step` (its action log holds that many),
/// and the gripper command in force there: the last executed action's (open before any), which the branch's
/// first actions repeat instead of opening the gripper on what it holds.
async fn branch_point(app: &AppState, task: &str, parent: &str, step: u64) -> Result<f64, ApiError> {
    let Some(run) = crate::rows::run_dir_of(app, parent).await else {
        return Err(ApiError::not_found(format!("no episode {parent} to branch from")));
    };
    let source = tokio::task::spawn_blocking(move || libero_episode::demo::record::SourceEpisode::read(&run))
        .await
        .map_err(|e| ApiError::internal(format!("branch: {e}")))?
        .map_err(|e| ApiError::unprocessable(format!("episode {parent} cannot be continued: {e}")))?;
    if source.task_ref != task {
        return Err(ApiError::bad_request(format!("episode {parent} is an episode of {}, not {task}: open /teleop/{}?branch={parent}&step={step}", source.task_ref, source.task_ref)));
    }
    let available = source.actions.len() as u64;
    if step > available {
        return Err(ApiError::bad_request(format!("step {step} is beyond episode {parent}'s action log ({available} control steps were executed)")));
    }
    Ok(source.actions[..step as usize].last().map_or(GRIPPER_OPEN, |(_, a)| a[6]))
}

#[derive(Deserialize)]
struct CreateRequest {
    /// The task; a branch runs its parent's (leave it out or name that one).
    #[serde(default)]
    task: String,
    #[serde(default = "default_seed")]
    seed: u64,
    /// Drive the task in another layout, so the saved demonstration can be shown in release episodes (whose own
    /// configuration a demonstration never comes from).
    #[serde(default)]
    layout: Option<libero_episode::demo::LayoutVariant>,
    /// Continue another episode from one of its control steps (its task, seed, init state and layout; the
    /// parent's actions replayed), as `POST /api/episodes` does.
    #[serde(default)]
    branch: Option<BranchRequest>,
}

fn default_seed() -> u64 {
    DEFAULT_SEED
}

/// Prepares and starts an operator episode (level 1, private video on for the bundle; live frames are rendered
/// on demand while the page watches); a reset is
/// simply a new one of the same task and seed, which starts from the same init state.
async fn create(State(app): State<AppState>, body: Bytes) -> ApiResult {
    let req: CreateRequest = serde_json::from_slice(&body)
        .map_err(|e| ApiError::bad_request(format!("body must be {{\"task\": \"T14\", \"seed\": 100}}: {e}")))?;
    // A branch's task is its parent's: prepare resolves it (and says 404/400 for a parent or step it cannot use).
    let task = if req.branch.is_some() && req.task.is_empty() {
        String::new()
    } else {
        implemented_task(&req.task).map_err(ApiError::unprocessable)?.0
    };
    let prepare = PrepareRequest {
        level: 1,
        seed: req.seed,
        wall_time_s: TELEOP_WALL_TIME_S,
        video: true,
        harness: Some("teleop".into()),
        model: Some("human".into()),
        // Teleop episodes are one batch on the home page's filter.
        batch: Some("teleop".into()),
        layout: req.layout,
        branch: req.branch.clone(),
        ..PrepareRequest::new(task.clone())
    };
    let prepared = app.prepare_stored(prepare).await?;
    let task = prepared.task.clone();
    let eps = app.episodes.clone();
    let id = prepared.episode_id.clone();
    let started = tokio::task::spawn_blocking(move || -> anyhow::Result<()> {
        let handle = eps.lifecycle().handle(&id).ok_or_else(|| anyhow::anyhow!("the episode vanished"))?;
        let answer = ToolReply::of(&handle.call("start_episode", None));
        if !answer.is_ok() {
            handle.stop("teleop start failed");
            anyhow::bail!("start_episode failed: {}", answer.error_text());
        }
        Ok(())
    })
    .await
    .map_err(|e| ApiError::internal(format!("teleop start: {e}")))?;
    started.map_err(|e| ApiError::unprocessable(format!("{e:#}")))?;
    if let Ok(mut m) = app.teleop.lock() {
        m.insert(prepared.episode_id.clone(), TeleopEpisode::new(task.clone()));
    }
    watch_abandonment(app.clone(), prepared.episode_id.clone());
    app.sync(&prepared.episode_id).await;
    Ok(ok_json(json!({"ok": true, "episode_id": prepared.episode_id, "task": task, "seed": req.seed, "branch": prepared.branch})))
}

/// The handle and task of an operator episode; agents' episodes are never returned.
fn teleop_episode(app: &libero_server::App, id: &str) -> Option<(EpisodeHandle, String)> {
    let task = app.teleop.lock().ok()?.get(id)?.task.clone();
    Some((app.episodes.lifecycle().handle(id)?, task))
}

/// Why an episode nobody drives was ended (what the live page, review and API show as its reason).
fn abandoned_reason(after: Duration) -> String {
    format!("abandoned: no teleop page was connected to it for {} s (serve --teleop-abandon-s)", after.as_secs())
}

/// Ends teleop episode `id` as abandoned once no teleop page has been connected to it for
/// [`libero_server::App::teleop_abandon_after`] (a page closed or navigated away from, or one that never
/// connected). Stops watching when the episode ends otherwise or leaves the teleop map.
fn watch_abandonment(app: AppState, id: String) {
    let after = app.teleop_abandon_after;
    let period = (after / 4).clamp(Duration::from_millis(200), Duration::from_secs(5));
    tokio::spawn(async move {
        loop {
            tokio::time::sleep(period).await;
            let (due, sockets) = match app.teleop.lock().ok().and_then(|m| m.get(&id).cloned()) {
                Some(t) => (!t.saving && t.sockets == 0 && t.unattended_since.elapsed() >= after, t.sockets),
                None => return,
            };
            let open = app.episodes.lifecycle().status(&id).is_some_and(|s| s.outcome.is_none());
            if !open {
                // Ended some other way (finished, aborted, saved): forget it once no page holds it any more.
                if sockets == 0 {
                    forget(&app, &id);
                    return;
                }
                continue;
            }
            if due {
                let (eps, episode) = (app.episodes.clone(), id.clone());
                // A join error leaves the episode to the wall-time budget; nothing else can end it here.
                let _ = tokio::task::spawn_blocking(move || eps.lifecycle().stop(&episode, &abandoned_reason(after))).await;
                app.sync(&id).await;
                forget(&app, &id);
                return;
            }
        }
    });
}

fn forget(app: &libero_server::App, id: &str) {
    if let Ok(mut m) = app.teleop.lock() {
        m.remove(id);
    }
}

/// Counts a teleop socket as connected for the abandonment watch while it lives.
struct Attended {
    app: AppState,
    id: String,
}

impl Attended {
    fn new(app: AppState, id: String) -> Self {
        if let Ok(mut m) = app.teleop.lock()
            && let Some(t) = m.get_mut(&id)
        {
            t.sockets += 1;
        }
        Self { app, id }
    }
}

impl Drop for Attended {
    fn drop(&mut self) {
        if let Ok(mut m) = self.app.teleop.lock()
            && let Some(t) = m.get_mut(&self.id)
        {
            t.sockets = t.sockets.saturating_sub(1);
            if t.sockets == 0 {
                t.unattended_since = Instant::now();
            }
        }
    }
}

async fn control_socket(ws: WebSocketUpgrade, State(app): State<AppState>, Path(id): Path<String>) -> Response {
    let Some((handle, _)) = teleop_episode(&app, &id) else {
        return ApiError::not_found(format!("{id} is not an operator episode of this server")).into_response();
    };
    ws.on_upgrade(move |socket| control_stream(socket, app, id, handle))
}

/// A message of the control socket that is not an action batch: `{"type": "save"}` saves the demonstration,
/// answering with `save_progress` messages and then `saved` (or `save_failed`).
#[derive(Deserialize)]
struct ControlRequest {
    #[serde(rename = "type")]
    kind: String,
}

/// One batch from the page: `seq` echoes back so the page can pair answers and measure the achieved rate.
#[derive(Deserialize)]
struct ActionBatch {
    seq: u64,
    actions: Vec<[f64; 7]>,
}

/// Runs the page's batches one after another as `osc_sequence` calls and answers each. Batches are executed
/// in order; the page keeps at most a couple in flight, so the queue here stays short.
async fn control_stream(mut socket: WebSocket, app: AppState, id: String, handle: EpisodeHandle) {
    let _attended = Attended::new(app.clone(), id.clone());
    while let Some(Ok(message)) = socket.recv().await {
        let text = match message {
            Message::Text(t) => t,
            Message::Close(_) => return,
            _ => continue,
        };
        if let Ok(ControlRequest { kind }) = serde_json::from_str::<ControlRequest>(&text) {
            if kind != "save" {
                let reply = json!({"type": "error", "error": format!("unknown request {kind:?}: an action batch or {{\"type\": \"save\"}}")});
                if socket.send(Message::Text(reply.to_string().into())).await.is_err() {
                    return;
                }
                continue;
            }
            if !save_over_socket(&mut socket, &app, &id).await {
                return;
            }
            continue;
        }
        let reply = match serde_json::from_str::<ActionBatch>(&text) {
            Ok(batch) if (1..=MAX_MICRO_ACTIONS_PER_CALL).contains(&batch.actions.len()) => run_batch(&handle, batch).await,
            Ok(batch) => json!({"type": "ack", "seq": batch.seq, "ok": false,
                "error": format!("a batch holds 1 to {MAX_MICRO_ACTIONS_PER_CALL} actions")}),
            Err(e) => json!({"type": "ack", "ok": false, "error": format!("not an action batch: {e}")}),
        };
        app.sync(&id).await;
        if socket.send(Message::Text(reply.to_string().into())).await.is_err() {
            return;
        }
    }
}

async fn run_batch(handle: &EpisodeHandle, batch: ActionBatch) -> Value {
    let n = batch.actions.len();
    let mut args = Map::new();
    args.insert("actions".into(), json!(batch.actions));
    let h = handle.clone();
    let started = Instant::now();
    let answer = tokio::task::spawn_blocking(move || h.call("osc_sequence", Some(args))).await;
    let exec_ms = started.elapsed().as_secs_f64() * 1000.0;
    match answer {
        Ok(a) => {
            let a = ToolReply::of(&a);
            json!({"type": "ack", "seq": batch.seq, "ok": a.is_ok(), "actions": n, "exec_ms": exec_ms,
            "error_type": a.error_type, "error": a.error,
            "accepted_agent_steps": handle.status().accepted_agent_steps})
        }
        Err(e) => json!({"type": "ack", "seq": batch.seq, "ok": false, "error": format!("episode call: {e}")}),
    }
}

/// Finishes the operator episode, records its bundle (replayed, hence verified or not) and reports why it is
/// not verified when it is not.
async fn save(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    match save_demo(&app, &id, None).await {
        Ok(v) => ok_json(v),
        Err(e) => e.into_response(),
    }
}

/// "Save demonstration" over the control socket: `save_progress` messages while the replay renders and verifies
/// (10–40 s), then `saved` with [`save_demo`]'s answer or `save_failed`. False when the page has gone.
async fn save_over_socket(socket: &mut WebSocket, app: &AppState, id: &str) -> bool {
    let (tx, mut rx) = mpsc::unbounded_channel::<(usize, usize)>();
    let started = Instant::now();
    let send = |v: Value| Message::Text(v.to_string().into());
    if socket.send(send(json!({"type": "save_progress", "phase": "finishing", "elapsed_s": 0.0}))).await.is_err() {
        return false;
    }
    let work = save_demo(app, id, Some(tx));
    tokio::pin!(work);
    let mut gone = false;
    let result = loop {
        tokio::select! {
            r = &mut work => break r,
            Some((done, total)) = rx.recv() => {
                // Only the latest of a burst: the page needs where it is, not every frame.
                let (mut done, mut total) = (done, total);
                while let Ok((d, t)) = rx.try_recv() {
                    (done, total) = (d, t);
                }
                let msg = json!({"type": "save_progress", "phase": "replaying", "done": done, "total": total,
                    "elapsed_s": started.elapsed().as_secs_f64()});
                // A page that went away does not stop the save: it goes on and the bundle is kept.
                gone = gone || socket.send(send(msg)).await.is_err();
            }
        }
    };
    let reply = match result {
        Ok(mut v) => {
            v["type"] = json!("saved");
            v["elapsed_s"] = json!(started.elapsed().as_secs_f64());
            v
        }
        Err(e) => json!({"type": "save_failed", "ok": false, "error": e.message()}),
    };
    !gone && socket.send(send(reply)).await.is_ok()
}

/// Finishes teleop episode `id` (if it is still open), records its bundle with the verifying replay, telling
/// `progress` each rendered frame, and answers what the page shows.
async fn save_demo(app: &AppState, id: &str, progress: Option<mpsc::UnboundedSender<(usize, usize)>>) -> Result<Value, ApiError> {
    let Some((handle, task)) = teleop_episode(app, id) else {
        return Err(ApiError::not_found(format!("{id} is not an operator episode of this server")));
    };
    if let Ok(mut m) = app.teleop.lock()
        && let Some(t) = m.get_mut(id)
    {
        t.saving = true;
    }
    let eps = app.episodes.clone();
    let episode = id.to_owned();
    let saved = tokio::task::spawn_blocking(move || -> anyhow::Result<Value> {
        let finish = handle.call("finish_episode", None);
        let options = RecordOptions { source_type: "human_teleop".into(), source_desc: teleop_desc(&eps, &episode) };
        let mut tell = |done: usize, total: usize| {
            if let Some(tx) = &progress {
                let _ = tx.send((done, total));
            }
        };
        let s = eps.lifecycle().record_demo_with_progress(&episode, &options, &mut tell)?;
        let violations: Vec<String> = validate_bundle(&s.dir).iter().map(ToString::to_string).collect();
        let reason = if !violations.is_empty() {
            Some(format!("the bundle breaks {} rule(s) of §7.7", violations.len()))
        } else if s.source_success != Some(true) {
            Some("the episode did not succeed (the evaluator's verdict at finish_episode), so it cannot verify".into())
        } else if !s.replay_success {
            Some("replaying the actions did not reproduce the evaluator's success".into())
        } else {
            None
        };
        Ok(json!({
            "ok": true, "verified": s.verified && violations.is_empty(), "reason": reason, "violations": violations,
            "bundle": format!("{}/{}", library::task_dir_name(&task), library::task_dir_name(&episode)),
            "frame_count": s.frame_count, "transition_count": s.transition_count,
            "source_success": s.source_success, "replay_success": s.replay_success, "finish": finish,
            "branch": libero_episode::demo::read_manifest(&s.dir.join(MANIFEST)).ok().and_then(|m| m.branch().cloned()),
        }))
    })
    .await;
    app.sync(id).await;
    forget(app, id);
    match saved {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(ApiError::unprocessable(format!("{e:#}"))),
        Err(e) => Err(ApiError::internal(format!("save: {e}"))),
    }
}

/// The bundle's `source_desc`: who drove, and for a branch where it continued from.
fn teleop_desc(eps: &libero_server::episodes::Episodes, episode: &str) -> String {
    let base = "libero-agent dashboard teleop (keyboard / gamepad)";
    let run = libero_episode::RunDir::new(eps.lifecycle().runs_dir().join(episode));
    match libero_episode::demo::SourceEpisode::read(&run).ok().and_then(|s| s.branch) {
        Some(b) => format!("{base}, continuing {} from control step {} (its {} actions replayed first)", b.parent_episode_id, b.parent_control_step, b.replayed_actions),
        None => base.to_owned(),
    }
}

/// `POST /api/episodes/{id}/finish`: "Finish and judge" on the live and teleop pages. Calls the episode's own
/// `finish_episode` (in-process, as the teleop socket drives it) and answers the evaluator's verdict from
/// `result.json`. 404 for an episode this server does not hold; an episode that already ended answers its
/// verdict as it stands.
async fn finish(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult {
    let Some(handle) = app.episodes.lifecycle().handle(&id) else {
        return Err(ApiError::not_found(format!("no open episode {id} on this server")));
    };
    let answer = tokio::task::spawn_blocking(move || handle.call("finish_episode", None))
        .await
        .map_err(|e| ApiError::internal(format!("finish: {e}")))?;
    app.sync(&id).await;
    let status = app.episodes.lifecycle().status(&id);
    let run = crate::rows::run_dir_of(&app, &id).await;
    let result = run.as_ref().and_then(libero_records::records::read_result);
    let evaluation = result.as_ref().and_then(|r| r.private_evaluation.clone()).unwrap_or_default();
    Ok(ok_json(json!({
        "ok": ToolReply::of(&answer).is_ok(), "episode_id": id, "answer": answer,
        "state": status.as_ref().map(|s| json!(s.state)), "outcome": status.as_ref().and_then(|s| s.outcome),
        "reason": status.and_then(|s| s.reason),
        "success": result.as_ref().and_then(|r| r.success),
        "completed_required_stage_count": evaluation.completed_required_stage_count,
        "required_stage_count": evaluation.required_stage_count,
    })))
}

// ---------------------------------------------------------------------------------------------- demos page

#[derive(Template)]
#[template(path = "demos.html")]
struct DemosPage {}

async fn demos_page() -> Response {
    page(DemosPage {})
}

/// `<library>/<task>/<bundle>` for names that are plain directory names (never a path trick) and exist.
fn bundle_path(app: &libero_server::App, task: &str, bundle: &str) -> Option<PathBuf> {
    let plain = |s: &str| valid_id(s) && library::task_dir_name(s) == s;
    if !(plain(task) && plain(bundle)) {
        return None;
    }
    let dir = app.episodes.lifecycle().demo_library().join(task).join(bundle);
    dir.join(MANIFEST).is_file().then_some(dir)
}

/// Every bundle of the library with what the table shows (newest first).
fn list_bundles(root: &FsPath) -> Vec<BundleSummary> {
    newest_first(std::fs::read_dir(root).into_iter().flatten().flatten().flat_map(|d| bundle_rows(&d.path())).collect())
}

/// The bundles of one task's library folder (`<library>/<task>`), as [`list_bundles`] shows them, newest first.
pub(crate) fn task_bundles(task_dir: &FsPath) -> Vec<BundleSummary> {
    newest_first(bundle_rows(task_dir))
}

/// A bundle's row of the table, and when the bundle was recorded (what the rows are ordered by).
struct BundleRow {
    modified_unix_s: Option<f64>,
    row: BundleSummary,
}

/// One bundle as `/api/demos` lists it and the task page shows it (typed, so the page reads what the list writes).
#[derive(Debug, serde::Serialize)]
pub(crate) struct BundleSummary {
    /// `<task folder>/<bundle folder>`.
    pub key: String,
    pub task: Option<String>,
    pub instruction: Option<String>,
    pub verified: Option<bool>,
    pub replay_success: Option<bool>,
    pub actions: Option<u64>,
    pub source_type: Option<String>,
    pub episode_id: Option<String>,
    pub modified_unix_s: Option<f64>,
    pub branch: Option<libero_records::demo_manifest::DemoBranch>,
    /// Whether the bundle passes [`validate_bundle`], and its first violation if not.
    pub valid: bool,
    pub first_violation: Option<String>,
    pub replay_checks: Vec<String>,
}

/// The rows of one task's library folder, in directory order.
fn bundle_rows(task_dir: &FsPath) -> Vec<BundleRow> {
    let mut rows = Vec::new();
    let task_name = task_dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    for b in std::fs::read_dir(task_dir).into_iter().flatten().flatten() {
        let dir = b.path();
        let name = b.file_name().to_string_lossy().into_owned();
        if !dir.is_dir() || name.ends_with(".partial") {
            continue;
        }
        let Ok(m) = read_manifest(&dir.join(MANIFEST)) else { continue };
        // When it was recorded: the trajectory is written once (integrity-protected); the manifest is rewritten by
        // every verification and replay check, so its time is not the bundle's date.
        let modified = std::fs::metadata(dir.join(TRAJECTORY))
            .or_else(|_| std::fs::metadata(dir.join(MANIFEST)))
            .and_then(|md| md.modified())
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map(|d| d.as_secs_f64());
        let violations = validate_bundle(&dir);
        rows.push(BundleRow { modified_unix_s: modified, row: BundleSummary {
            key: format!("{task_name}/{name}"),
            task: m.task_id().map(str::to_owned), instruction: m.instruction().map(str::to_owned),
            verified: m.verification.as_ref().and_then(|v| v.verified),
            replay_success: m.verification.as_ref().and_then(|v| v.replay_success),
            actions: m.transition_count, source_type: m.source.as_ref().and_then(|s| s.source_type.clone()),
            episode_id: m.source.as_ref().and_then(|s| s.episode_id.clone()), modified_unix_s: modified,
            branch: m.branch().cloned(),
            valid: violations.is_empty(), first_violation: violations.first().map(ToString::to_string),
            replay_checks: m.replay_checks.iter().flatten().map(|c| c.summary()).collect(),
        }});
    }
    rows
}

/// The rows, the most recently recorded first.
fn newest_first(mut rows: Vec<BundleRow>) -> Vec<BundleSummary> {
    rows.sort_by(|a, b| b.modified_unix_s.partial_cmp(&a.modified_unix_s).unwrap_or(std::cmp::Ordering::Equal));
    rows.into_iter().map(|r| r.row).collect()
}

async fn demos_json(State(app): State<AppState>) -> Response {
    let root = app.episodes.lifecycle().demo_library();
    match tokio::task::spawn_blocking(move || list_bundles(&root)).await {
        Ok(rows) => ok_json(json!({"ok": true, "bundles": rows})),
        Err(e) => ApiError::internal(format!("demos: {e}")).into_response(),
    }
}

async fn bundle_video(State(app): State<AppState>, Path((task, bundle)): Path<(String, String)>, req: Request<Body>) -> Response {
    match bundle_path(&app, &task, &bundle) {
        Some(dir) => serve_file(dir.join(VIDEO_HEAD_WRIST), req).await,
        None => ApiError::not_found("no such bundle").into_response(),
    }
}

/// Validates, then replays; the manifest's verification is rewritten by the library.
async fn verify(State(app): State<AppState>, Path((task, bundle)): Path<(String, String)>) -> Response {
    let Some(dir) = bundle_path(&app, &task, &bundle) else { return ApiError::not_found("no such bundle").into_response() };
    let eps = app.episodes.clone();
    let result = tokio::task::spawn_blocking(move || -> anyhow::Result<Value> {
        let violations: Vec<String> = validate_bundle(&dir).iter().map(ToString::to_string).collect();
        if !violations.is_empty() {
            return Ok(json!({"ok": true, "verified": false, "reason": "invalid bundle, not replayed", "violations": violations}));
        }
        let verified = eps.lifecycle().verify_demo(&dir)?;
        let reason = (!verified).then_some("the source episode did not succeed or the replay did not reproduce its success");
        Ok(json!({"ok": true, "verified": verified, "reason": reason, "violations": []}))
    })
    .await;
    match result {
        Ok(Ok(v)) => ok_json(v),
        Ok(Err(e)) => ApiError::unprocessable(format!("{e:#}")).into_response(),
        Err(e) => ApiError::internal(format!("verify: {e}")).into_response(),
    }
}

async fn delete(State(app): State<AppState>, Path((task, bundle)): Path<(String, String)>) -> Response {
    let Some(dir) = bundle_path(&app, &task, &bundle) else { return ApiError::not_found("no such bundle").into_response() };
    match std::fs::remove_dir_all(&dir) {
        Ok(()) => ok_json(json!({"ok": true, "deleted": format!("{task}/{bundle}")})),
        Err(e) => ApiError::internal(format!("delete {task}/{bundle}: {e}")).into_response(),
    }
}

#[derive(Deserialize)]
struct ExportRequest {
    /// `task/bundle` keys as the list gives them.
    bundles: Vec<String>,
}

/// Exports the chosen bundles to a new LeRobot v3 dataset under `<data>/exports/`.
async fn export(State(app): State<AppState>, body: Bytes) -> Response {
    let req: ExportRequest = match serde_json::from_slice(&body) {
        Ok(r) => r,
        Err(e) => return ApiError::bad_request(format!("body must be {{\"bundles\": [\"T14/ep-…\"]}}: {e}")).into_response(),
    };
    let mut dirs = Vec::new();
    for key in &req.bundles {
        match key.split_once('/').and_then(|(t, b)| bundle_path(&app, t, b)) {
            Some(d) => dirs.push(d),
            None => return ApiError::not_found(format!("no bundle {key}")).into_response(),
        }
    }
    if dirs.is_empty() {
        return ApiError::bad_request("choose at least one bundle").into_response();
    }
    let suffix = match random_hex(3) {
        Ok(s) => s,
        Err(e) => return ApiError::internal(format!("{e}")).into_response(),
    };
    let stamp = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    let out = app.episodes.lifecycle().data_dir().join("exports").join(format!("lerobot-{stamp}-{suffix}"));
    let result = tokio::task::spawn_blocking(move || {
        std::fs::create_dir_all(out.parent().unwrap_or(&out))?;
        export_lerobot(&dirs, &out).map_err(anyhow::Error::from)
    })
    .await;
    match result {
        Ok(Ok(s)) => ok_json(json!({"ok": true, "out": s.out, "episodes": s.episodes, "frames": s.frames, "tasks": s.tasks})),
        Ok(Err(e)) => ApiError::unprocessable(format!("{e:#}")).into_response(),
        Err(e) => ApiError::internal(format!("export: {e}")).into_response(),
    }
}
