//! An episode's stored row, wherever it lives, for the live and review pages: the store (with the run directory
//! fetched from the artifact store when another machine ran the episode) or a batch directory's records (a
//! batch's own in-process server); and the wait of a WebSocket that follows the store (the home page's episode
//! list, the live page of an episode another server runs).
use std::time::Duration;

use axum::extract::ws::{Message, WebSocket};
use libero_episode::RunDir;
use libero_server::{ApiError, ApiResult, App};

use crate::common::valid_id;
use crate::results;

/// Coalesces bursts of list changes into one refresh per viewer.
const LIST_REFRESH_MIN_INTERVAL: Duration = Duration::from_millis(250);

/// The stored row of episode `id`, or the response saying why there is none.
pub(crate) async fn stored_row(app: &App, id: &str) -> ApiResult<libero_store::EpisodeRow> {
    row_and_source(app, id).await.map(|(row, _)| row)
}

/// Where an episode's row came from.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum RowSource {
    /// The store: every server of a shared store writes there.
    Store,
    /// A batch directory's records (a batch's own in-process server).
    BatchDir,
}

pub(crate) async fn row_and_source(app: &App, id: &str) -> ApiResult<(libero_store::EpisodeRow, RowSource)> {
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
async fn fetched_if_elsewhere(app: &App, mut row: libero_store::EpisodeRow) -> libero_store::EpisodeRow {
    let Some(artifacts) = app.artifacts.as_ref() else { return row };
    if tokio::fs::metadata(&row.episode.run_dir).await.is_ok_and(|m| m.is_dir()) {
        return row;
    }
    let id = row.episode.id.clone();
    let cache = app.episodes.lifecycle().data_dir().join("artifact_cache");
    let dest = cache.join(&id);
    if tokio::fs::metadata(dest.join(libero_artifacts::COMPLETE_MARKER)).await.is_ok() {
        row.episode.run_dir = dest;
        return row;
    }
    let Ok(prefix) = libero_artifacts::run_prefix(&id) else { return row };
    // Fetched beside the destination and renamed into place: a concurrent view never sees half a directory.
    let Ok(staging_name) = libero_records::json::random_name(&format!(".{id}.")) else { return row };
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
async fn batch_episode(app: &App, id: &str) -> Option<libero_store::EpisodeRow> {
    let roots = app.batch_roots.clone();
    let id = id.to_owned();
    tokio::task::spawn_blocking(move || {
        let run_dir = results::discover(&roots).into_iter().find_map(|(_, dir)| {
            libero_report::batch::read_records(&dir)
                .ok()?
                .into_iter()
                .find(|r| r.episode_id.as_deref() == Some(id.as_str()))
                .and_then(|r| r.run_dir)
        })?;
        let run = RunDir::new(run_dir);
        let episode = libero_store::NewEpisode::from_record(&run).filter(|e| e.id == id)?;
        let end = libero_store::EpisodeEnd::from_run(&run);
        Some(libero_store::EpisodeRow {
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

pub(crate) async fn run_dir_of(app: &App, id: &str) -> Option<RunDir> {
    stored_row(app, id).await.ok().map(|r| RunDir::new(r.episode.run_dir))
}

/// What woke a socket that follows the store.
pub(crate) enum Wake {
    /// The store changed (or, with a re-read period, that period passed): read it again.
    Changed,
    /// The viewer sent a text, ping or pong: nothing to re-read.
    Viewer,
    /// The viewer or the server went away.
    Gone,
}

/// Waits for a change of the store (a burst coalesced into one, at most every 250 ms), a message of the viewer,
/// or `reread` without either (for stores without notifications).
pub(crate) async fn next_wake(socket: &mut WebSocket, changes: &mut tokio::sync::broadcast::Receiver<()>, reread: Option<Duration>) -> Wake {
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
