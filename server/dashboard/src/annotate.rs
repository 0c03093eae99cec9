//! Stage annotation in the review (issue 48; the paper annotated its stage analysis by hand): for every required
//! stage of a batch's long-horizon rollout, the automatic label (reached, succeeded, failure modes) and the
//! person's annotation where one was saved. `GET /api/episodes/{id}/stages` reads them with the batch's previous
//! and next long-horizon episodes (to annotate a batch in a row); `POST` saves one stage's annotation: appended to
//! the batch's `stage_annotations.jsonl` (which travels with the batch and which Table 4 reads), then written to
//! the store (the latest per stage and the whole history). The page is `review.html`'s annotation panel
//! (`annotate.js`).
use std::path::PathBuf;

use axum::Router;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::response::IntoResponse;
use axum::routing::get;
use libero_records::json::utc_now_iso;
use libero_metrics::{FailureMode, Split, StageAnnotation, StageAnnotations, StageKey, StageOpportunity, in_paper_table4};
use libero_report::annotations::{AnnotationLine, append_annotation, invalid_annotation, read_annotations, rollout_stages};
use libero_report::batch::{RolloutRecord, read_records};
use libero_server::{ApiError, ApiResult, AppState};
use serde::Deserialize;
use serde_json::{Value, json};

use crate::common::valid_id;
use crate::results;

pub fn compressed_routes() -> Router<AppState> {
    Router::new().route("/api/episodes/{id}/stages", get(stages).post(save))
}

/// A batch rollout found by its episode id: its batch, its record, and the batch's long-horizon episodes in order.
struct Found {
    batch: String,
    batch_dir: PathBuf,
    record: RolloutRecord,
    long_horizon: Vec<String>,
}

fn find(roots: &[PathBuf], id: &str) -> Option<Found> {
    results::discover(roots).into_iter().find_map(|(batch, batch_dir)| {
        let records = read_records(&batch_dir).ok()?;
        let record = records.iter().find(|r| r.episode_id.as_deref() == Some(id))?.clone();
        let long_horizon = records
            .iter()
            .filter(|r| r.split.is_some_and(Split::is_long_horizon))
            .filter_map(|r| r.episode_id.clone())
            .collect();
        Some(Found { batch, batch_dir, record, long_horizon })
    })
}

/// The rollout of episode `id` and its stages, or the error a user sees.
async fn rollout(app: &AppState, id: &str) -> ApiResult<(Found, Vec<StageOpportunity>)> {
    if !valid_id(id) {
        return Err(ApiError::not_found("no such episode"));
    }
    let (roots, owned) = (app.batch_roots.clone(), id.to_owned());
    let found = tokio::task::spawn_blocking(move || {
        let found = find(&roots, &owned)?;
        let stages = rollout_stages(&found.record, libero_tasks::catalog::task_facts());
        Some((found, stages))
    })
    .await
    .map_err(|e| ApiError::internal(format!("annotation: {e}")))?;
    let Some((found, stages)) = found else {
        return Err(ApiError::not_found(format!(
            "episode {id} is no rollout of a batch this console reads: stages are annotated on batch rollouts, which Table 4 counts"
        )));
    };
    if stages.is_empty() {
        return Err(ApiError::unprocessable(format!(
            "episode {id} has no stage record to annotate (a {} rollout; stages are annotated on long-horizon rollouts that finished)",
            found.record.task
        )));
    }
    Ok((found, stages))
}

/// The annotations of the episode: the store's, and the batch file's where the store has none (a batch copied in).
async fn annotations_of(app: &AppState, id: &str, found: &Found) -> ApiResult<StageAnnotations> {
    let mut out: StageAnnotations = read_annotations(&found.batch_dir).into_iter().filter(|(k, _)| k.episode_id == id).collect();
    for (stage_name, doc) in app.store.stage_annotations(id).await? {
        if let Ok(a) = serde_json::from_value::<StageAnnotation>(doc) {
            out.insert(StageKey { episode_id: id.to_owned(), stage_name }, a);
        }
    }
    Ok(out)
}

async fn stages(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult {
    let (found, stages) = rollout(&app, &id).await?;
    let annotations = annotations_of(&app, &id, &found).await?;
    let position = found.long_horizon.iter().position(|e| *e == id);
    let neighbour = |d: isize| position.and_then(|p| p.checked_add_signed(d)).and_then(|p| found.long_horizon.get(p)).cloned();
    let annotation_of = |s: &StageOpportunity| annotations.get(&StageKey { episode_id: id.clone(), stage_name: s.stage_name.clone() });
    let rows: Vec<Value> = stages
        .iter()
        .map(|s| {
            let auto = s.automatic();
            let annotation = annotation_of(s);
            json!({
                "stage_name": s.stage_name,
                "stage_type": s.stage_type,
                "automatic": {"reached": auto.reached, "succeeded": auto.succeeded, "failure_modes": auto.failure_modes},
                "annotation": annotation,
                "counted": s.label(Some(&annotations)),
            })
        })
        .collect();
    Ok(axum::Json(json!({
        "ok": true,
        "episode_id": id,
        "task": found.record.task,
        "batch": found.batch,
        "in_table4": in_paper_table4(found.record.task_number),
        "stages": rows,
        "annotated": stages.iter().filter(|s| annotation_of(s).is_some()).count(),
        "position": position.map(|p| p + 1),
        "episodes": found.long_horizon.len(),
        "previous": neighbour(-1),
        "next": neighbour(1),
        "modes": libero_report::annotations::MODES.map(|m| json!({"key": m, "label": m.label()})),
    }))
    .into_response())
}

/// What the page sends for one stage.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SaveRequest {
    stage_name: String,
    reached: bool,
    succeeded: bool,
    #[serde(default)]
    failure_modes: Vec<FailureMode>,
    #[serde(default)]
    note: String,
    annotator: String,
}

async fn save(State(app): State<AppState>, Path(id): Path<String>, body: Bytes) -> ApiResult {
    let req: SaveRequest = serde_json::from_slice(&body).map_err(|e| {
        ApiError::bad_request(format!(
            "body must be {{\"stage_name\", \"reached\", \"succeeded\", \"failure_modes\": [local_execution|cross_stage_interference|geometric_error|other], \"note\", \"annotator\"}}: {e}"
        ))
    })?;
    let (found, stages) = rollout(&app, &id).await?;
    let mut failure_modes = req.failure_modes;
    failure_modes.sort_unstable();
    failure_modes.dedup();
    let annotation = StageAnnotation {
        reached: req.reached || req.succeeded,
        succeeded: req.succeeded,
        failure_modes,
        note: req.note,
        annotator: req.annotator.trim().to_owned(),
        annotated_at: utc_now_iso(),
    };
    if let Some(why) = invalid_annotation(&stages, &req.stage_name, &annotation) {
        return Err(ApiError::unprocessable(why));
    }
    let line = AnnotationLine { episode_id: id.clone(), stage_name: req.stage_name.clone(), annotation: annotation.clone() };
    // The batch's file first (what travels with the batch and what Table 4 reads), then the store.
    let dir = found.batch_dir.clone();
    tokio::task::spawn_blocking(move || append_annotation(&dir, &line))
        .await
        .map_err(|e| ApiError::internal(format!("annotation: {e}")))?
        .map_err(|e| ApiError::internal(format!("cannot append to {}: {e}", found.batch_dir.display())))?;
    let doc = serde_json::to_value(&annotation).map_err(|e| ApiError::internal(format!("annotation: {e}")))?;
    app.store.put_stage_annotation(&id, &req.stage_name, &annotation.annotator, &annotation.annotated_at, &doc).await?;
    Ok(axum::Json(json!({"ok": true, "episode_id": id, "stage_name": req.stage_name, "annotation": annotation, "label": annotation.label()})).into_response())
}
