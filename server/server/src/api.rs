//! The operator API's own routes (`/api/…` but the batches and transcripts): preparing, listing, reading,
//! aborting and forfeiting episodes, their videos, health and thumbnails. Reads never write the store: they ask
//! the store writer to catch up first ([`App::sync`]).
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use libero_episode::RunDir;
use libero_episode::lifecycle::EpisodeSet;
use serde_json::{Value, json};

use crate::api_error::{ApiError, ApiResult};
use crate::app::{App, AppState};
use crate::episodes::PrepareRequest;
use crate::{batches, transcript};

/// The operator API's routes (behind the operator guard, gzip-compressed: see [`crate::router`]).
pub(crate) fn operator_routes() -> Router<AppState> {
    use axum::routing::{get, post};
    Router::new()
        .route("/api/episodes", post(prepare).get(list_episodes))
        .route("/api/episodes/{id}", get(episode_status))
        .route("/api/episodes/{id}/video", get(episode_video))
        .route("/api/episodes/{id}/abort", post(abort_episode))
        .route("/api/episodes/{id}/forfeit", post(forfeit_episode))
        .route("/api/thumbnails", get(thumbnail_stats))
        .route("/api/episodes/{id}/agent/events", post(transcript::ingest))
        .route("/api/batches", post(batches::register))
}

/// `GET /api/thumbnails`: what the thumbnail cache rendered, reused and has left to render ahead.
async fn thumbnail_stats(State(app): State<AppState>) -> Response {
    axum::Json(json!({"ok": true, "thumbnails": app.thumbnails.stats()})).into_response()
}

pub(crate) async fn health(State(app): State<AppState>) -> Response {
    axum::Json(json!({"ok": true, "episodes": app.episodes.lifecycle().count(), "version": env!("CARGO_PKG_VERSION")})).into_response()
}

async fn prepare(State(app): State<AppState>, body: axum::body::Bytes) -> ApiResult {
    let req: PrepareRequest =
        serde_json::from_slice(&body).map_err(|e| ApiError::bad_request(format!("invalid prepare request: {e}")))?;
    let prepared = app.prepare_stored(req).await?;
    Ok((StatusCode::CREATED, axum::Json(prepared)).into_response())
}

/// A stored row for the API: no paths, plus the live state while this process serves the episode.
pub fn episode_json(app: &App, row: &libero_store::EpisodeRow) -> Value {
    let mut v = row.public();
    if let (Some(live), Some(obj)) = (app.episodes.lifecycle().status(&row.episode.id), v.as_object_mut()) {
        obj.insert("state".into(), json!(live.state));
        obj.insert("accepted_agent_steps".into(), json!(live.accepted_agent_steps));
        obj.insert("latest_observation_id".into(), json!(live.latest_observation_id));
    }
    v
}

#[derive(serde::Deserialize)]
struct ListQuery {
    limit: Option<i64>,
}

/// Largest page of `GET /api/episodes`.
const MAX_LIST_LIMIT: i64 = 10_000;

async fn list_episodes(State(app): State<AppState>, Query(q): Query<ListQuery>) -> ApiResult {
    app.sync_all().await;
    let limit = q.limit.unwrap_or(1000).clamp(1, MAX_LIST_LIMIT);
    let rows = app.store.list(limit).await?;
    let episodes: Vec<Value> = rows.iter().map(|r| episode_json(&app, r)).collect();
    Ok(axum::Json(json!({"ok": true, "episodes": episodes})).into_response())
}

async fn episode_status(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult {
    app.sync(&id).await;
    let row = app.store.get(&id).await?.ok_or_else(|| ApiError::not_found(format!("no episode {id}")))?;
    Ok(axum::Json(episode_json(&app, &row)).into_response())
}

/// Whether the private video is there (`video`), and where its rendering stands (`video_status`: `state`
/// queued, rendering, ready or failed, `percent`, frames); `video_status` is null for an episode without one.
pub fn video_part(episodes: &EpisodeSet, run: &RunDir) -> Value {
    let status = episodes.video_progress(run);
    let mut st = serde_json::to_value(&status).unwrap_or(Value::Null);
    if let (Some(obj), Some(p)) = (st.as_object_mut(), status.as_ref()) {
        obj.insert("percent".into(), json!(p.percent()));
    }
    json!({"video": status == Some(libero_episode::video_queue::VideoProgress::Ready), "video_status": st})
}

/// `GET /api/episodes/{id}/video`: [`video_part`] of a stored episode (what a worker waits on before uploading).
async fn episode_video(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult {
    let row = app.store.get(&id).await?.ok_or_else(|| ApiError::not_found(format!("no episode {id}")))?;
    let run = RunDir::new(row.episode.run_dir);
    let episodes = app.episodes.clone();
    let v = tokio::task::spawn_blocking(move || video_part(episodes.lifecycle(), &run))
        .await
        .map_err(|e| ApiError::internal(format!("video: {e}")))?;
    Ok(axum::Json(v).into_response())
}

#[derive(serde::Deserialize)]
struct AbortRequest {
    reason: String,
}

/// Ends an open episode as aborted (INVALID) with the caller's reason: the batch runner's answer to an agent
/// that exited or was killed before `finish_episode` without the sandbox (the original launcher killed its
/// server instead). A finished episode is left as it is.
async fn abort_episode(State(app): State<AppState>, Path(id): Path<String>, body: axum::body::Bytes) -> ApiResult {
    end_episode(app, id, body, false).await
}

/// `POST /api/episodes/{id}/forfeit {"reason": "…"}`: the runner's word that the agent's harness ended without
/// `finish_episode`. The episode ends as the agent's FAIL (never INVALID: nothing an agent does may earn it a
/// rerun); an episode that already ended is left as it is. Operator-only, as abort.
async fn forfeit_episode(State(app): State<AppState>, Path(id): Path<String>, body: axum::body::Bytes) -> ApiResult {
    end_episode(app, id, body, true).await
}

/// Abort or forfeit: the reason (at most 1000 characters kept), the ending on a blocking thread, then the row as
/// the store writer wrote it.
async fn end_episode(app: AppState, id: String, body: axum::body::Bytes, forfeit: bool) -> ApiResult {
    let reason = match serde_json::from_slice::<AbortRequest>(&body) {
        Ok(r) if !r.reason.trim().is_empty() => r.reason.chars().take(1000).collect::<String>(),
        _ => return Err(ApiError::bad_request("body must be {\"reason\": \"…\"}")),
    };
    let eps = app.episodes.clone();
    let id2 = id.clone();
    let ended = tokio::task::spawn_blocking(move || if forfeit { eps.lifecycle().forfeit(&id2, &reason) } else { eps.lifecycle().stop(&id2, &reason) })
        .await
        .map_err(|e| ApiError::internal(format!("ending the episode failed: {e}")))?;
    if !ended {
        return Err(ApiError::not_found(format!("no open episode {id} on this server")));
    }
    app.sync(&id).await;
    episode_status(State(app), Path(id)).await
}
