//! The operator API's own routes (`/api/…` but the batches and transcripts): preparing, listing, reading,
//! aborting and forfeiting episodes, their videos, health and thumbnails. Reads never write the store: they ask
//! the store writer to catch up first ([`App::sync`]).
use axum::Router;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use libero_episode::RunDir;
use libero_episode::lifecycle::EpisodeSet;
use libero_episode::video_queue::VideoProgress;
use libero_records::episode_view::{EpisodeList, EpisodeResultReply, EpisodeVideo, EpisodeView, VideoState, VideoStatus};
use serde_json::{Value, json};

use crate::api_error::{ApiError, ApiQuery, ApiResult};
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
        .route("/api/episodes/{id}/result", get(episode_result))
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
pub fn episode_json(app: &App, row: &libero_store::EpisodeRow) -> EpisodeView {
    let mut view = row.view();
    if let Some(live) = app.episodes.lifecycle().status(&row.episode.id) {
        view.state = Some(live.state);
        view.accepted_agent_steps = Some(live.accepted_agent_steps);
        view.latest_observation_id = Some(live.latest_observation_id);
    }
    view
}

#[derive(serde::Deserialize)]
struct ListQuery {
    limit: Option<i64>,
}

/// Largest page of `GET /api/episodes`.
const MAX_LIST_LIMIT: i64 = 10_000;

async fn list_episodes(State(app): State<AppState>, ApiQuery(q): ApiQuery<ListQuery>) -> ApiResult {
    app.sync_all().await;
    let limit = q.limit.unwrap_or(1000).clamp(1, MAX_LIST_LIMIT);
    let rows = app.store.list(limit).await?;
    let episodes = rows.iter().map(|r| episode_json(&app, r)).collect();
    Ok(axum::Json(EpisodeList::new(episodes)).into_response())
}

async fn episode_status(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult {
    app.sync(&id).await;
    let row = app.store.get(&id).await?.ok_or_else(|| ApiError::not_found(format!("no episode {id}")))?;
    Ok(axum::Json(episode_json(&app, &row)).into_response())
}

/// Whether the private video is there (`video`), and where its rendering stands (`video_status`: `state`
/// queued, rendering, ready or failed, `percent`, frames); `video_status` is null for an episode without one.
pub fn episode_video_view(episodes: &EpisodeSet, run: &RunDir) -> EpisodeVideo {
    let progress = episodes.video_progress(run);
    EpisodeVideo { video: progress == Some(VideoProgress::Ready), video_status: progress.as_ref().map(video_status) }
}

/// [`episode_video_view`] as JSON, for replies that merge it with other parts (the review page's data).
pub fn video_part(episodes: &EpisodeSet, run: &RunDir) -> Value {
    serde_json::to_value(episode_video_view(episodes, run)).unwrap_or(Value::Null)
}

/// The video queue's progress as the API shows it.
fn video_status(p: &VideoProgress) -> VideoStatus {
    let (state, frames, error) = match p {
        VideoProgress::Queued => (VideoState::Queued, None, None),
        VideoProgress::Rendering { frames_done, frames_total } => (VideoState::Rendering, Some((*frames_done, *frames_total)), None),
        VideoProgress::Ready => (VideoState::Ready, None, None),
        VideoProgress::Failed { error } => (VideoState::Failed, None, Some(error.clone())),
    };
    VideoStatus { error, frames_done: frames.map(|f| f.0), frames_total: frames.map(|f| f.1), percent: p.percent(), state }
}

/// `GET /api/episodes/{id}/video`: [`episode_video_view`] of a stored episode (what a worker waits on before
/// uploading).
async fn episode_video(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult {
    let row = app.store.get(&id).await?.ok_or_else(|| ApiError::not_found(format!("no episode {id}")))?;
    let run = RunDir::new(row.episode.run_dir);
    let episodes = app.episodes.clone();
    let v = tokio::task::spawn_blocking(move || episode_video_view(episodes.lifecycle(), &run))
        .await
        .map_err(|e| ApiError::internal(format!("video: {e}")))?;
    Ok(axum::Json(v).into_response())
}

/// `GET /api/episodes/{id}/result`: the episode's `result.json` from this server's run directory (null while the
/// episode is open): the verdict a runner on another machine classifies (§4.8) without reading that directory.
async fn episode_result(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult {
    let row = app.store.get(&id).await?.ok_or_else(|| ApiError::not_found(format!("no episode {id}")))?;
    let run = RunDir::new(row.episode.run_dir);
    let result = tokio::task::spawn_blocking(move || libero_records::records::try_read_result(&run))
        .await
        .map_err(|e| ApiError::internal(format!("result: {e}")))?
        .map_err(|e| ApiError::internal(format!("episode {id}: {e}")))?;
    Ok(axum::Json(EpisodeResultReply { ok: true, result }).into_response())
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The typed video status is the reply as it was before it was typed: the queue's progress with its percent,
    /// keys sorted.
    #[test]
    fn a_typed_video_status_is_the_queue_s_progress_with_its_percent() {
        let progress = [
            VideoProgress::Queued,
            VideoProgress::Rendering { frames_done: 30, frames_total: 120 },
            VideoProgress::Ready,
            VideoProgress::Failed { error: "ffmpeg exited 1".into() },
        ];
        for p in progress {
            let mut old = serde_json::to_value(&p).unwrap();
            old.as_object_mut().unwrap().insert("percent".into(), json!(p.percent()));
            let typed = video_status(&p);
            assert_eq!(serde_json::to_value(&typed).unwrap(), old, "{p:?}");
            assert_eq!(serde_json::to_string(&typed).unwrap(), old.to_string(), "{p:?}: the keys in the old order");
        }
    }
}
