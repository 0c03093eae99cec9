//! `POST /api/episodes/{id}/agent/events`: a runner whose agent ran on another machine than this server (`run
//! --server URL` against a remote server) adds its agent's transcript events to the episode's run directory here,
//! where the review and the live page read them (`agent_events.jsonl`, docs/agent_transcript.md). Operator-only
//! like the rest of the operator API; every event is bounded again here and the file stays within its limit.
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::response::IntoResponse;
use libero_episode::RunDir;
use libero_records::agent_events::{AgentEvent, TranscriptFile};
use serde_json::json;

use crate::{ApiError, ApiResult, AppState};

/// Most events one request may add.
pub const MAX_EVENTS_PER_POST: usize = 1000;
/// Most bytes of one request's body (axum's default body limit; the runner posts at most 1 MiB at a time).
pub const MAX_POST_BYTES: usize = 2 << 20;

#[derive(serde::Deserialize)]
struct Posted {
    events: Vec<AgentEvent>,
}

/// Episode ids are `ep-<utc>-<hex>`; anything else never reaches the filesystem.
fn plain_id(id: &str) -> bool {
    !id.is_empty() && id.len() <= 96 && id.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
}

pub async fn ingest(State(app): State<AppState>, Path(id): Path<String>, body: Bytes) -> ApiResult {
    if body.len() > MAX_POST_BYTES {
        return Err(ApiError::too_large(format!("at most {MAX_POST_BYTES} bytes per request")));
    }
    let posted: Posted = serde_json::from_slice(&body)
        .map_err(|e| ApiError::bad_request(format!("body must be {{\"events\": [agent events]}}: {e}")))?;
    if posted.events.len() > MAX_EVENTS_PER_POST {
        return Err(ApiError::too_large(format!("at most {MAX_EVENTS_PER_POST} events per request")));
    }
    if !plain_id(&id) {
        return Err(ApiError::not_found("no such episode"));
    }
    let row = app.store.get(&id).await?.ok_or_else(|| ApiError::not_found(format!("no episode {id}")))?;
    let run = RunDir::new(row.episode.run_dir);
    let written = tokio::task::spawn_blocking(move || -> std::io::Result<(u64, bool)> {
        if !run.root.is_dir() {
            return Err(std::io::Error::new(std::io::ErrorKind::NotFound, "the episode's run directory is not on this server"));
        }
        let mut file = TranscriptFile::open(&run.agent_events_jsonl())?;
        file.append(posted.events)?;
        file.sync()?;
        Ok((file.written().events, file.is_full()))
    })
    .await
    .map_err(|e| ApiError::internal(format!("transcript: {e}")))?;
    match written {
        Ok((accepted, full)) => Ok(axum::Json(json!({"ok": true, "accepted": accepted, "full": full})).into_response()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(ApiError::conflict(e.to_string())),
        Err(e) => Err(ApiError::internal(format!("cannot write the transcript: {e}"))),
    }
}
