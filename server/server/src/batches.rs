//! `POST /api/batches`: a runner playing its episodes on this server (`libero-agent run --server URL`, from this
//! machine or another) registers its batch here as it goes, so this server's Results page lists it wherever the
//! batch directory is. The body is the batch directory's state: `batch.json`'s document (replacing the stored one)
//! and the `rollouts.jsonl` records from position `from` on (records are only ever appended, so a runner sends each
//! once). Operator-only like the rest of the operator API; every size is bounded here.
use axum::body::Bytes;
use axum::extract::State;
use axum::response::IntoResponse;
use libero_records::batch_doc::BatchDoc;
use serde::Deserialize;
use serde_json::{Value, json};

use libero_store::StoredBatch;
use crate::{ApiError, ApiResult, AppState};

/// Most bytes of one request's body (the runner posts at most [`MAX_POST_RECORDS`] records and 1 MiB at a time).
pub const MAX_POST_BYTES: usize = 2 << 20;
/// Most records one request may add.
pub const MAX_POST_RECORDS: usize = 500;
/// Longest batch name (a directory name).
pub const MAX_NAME_LEN: usize = 128;
/// Longest `dir` (where the batch's files are on the runner's machine).
const MAX_DIR_LEN: usize = 4096;
/// The batch document's schema (`libero_report::batch::BATCH_SCHEMA`, which the runner writes and the report reads; this crate links neither).
const BATCH_SCHEMA: &str = "libero_agent.batch.v1";

#[derive(serde::Deserialize)]
struct Posted {
    /// The batch's name: its directory's name.
    name: String,
    /// The batch directory on the runner's machine.
    dir: String,
    /// `batch.json`.
    doc: Value,
    /// Position in `rollouts.jsonl` of `records[0]`.
    #[serde(default)]
    from: usize,
    #[serde(default)]
    records: Vec<Value>,
}

/// The keys every rollout record has (the runner's `RolloutRecord`): a record without them is refused.
#[derive(serde::Deserialize)]
struct RecordKeys {
    #[serde(rename = "rollout_id")]
    _rollout_id: String,
    #[serde(rename = "schema_version")]
    _schema_version: String,
}

/// The creation time of a batch document (null or absent: none).
fn created_at(doc: &Value) -> Option<String> {
    BatchDoc::deserialize(doc).ok()?.created_at
}

/// Names the Results page and URLs carry as they are: letters, digits, `-`, `_`, `.`, not starting with a dot.
fn plain_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= MAX_NAME_LEN
        && !name.starts_with('.')
        && name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
}

/// Checks a posted batch; the refusal says what is wrong.
fn check(p: &Posted) -> Result<(), String> {
    if !plain_name(&p.name) {
        return Err(format!("batch name must be 1 to {MAX_NAME_LEN} of letters, digits, '-', '_', '.' (not starting with '.')"));
    }
    if p.dir.len() > MAX_DIR_LEN || !p.dir.starts_with('/') {
        return Err(format!("dir must be an absolute path of at most {MAX_DIR_LEN} bytes"));
    }
    // The Results page names a batch after its directory: both must agree.
    if std::path::Path::new(&p.dir).file_name().and_then(|n| n.to_str()) != Some(p.name.as_str()) {
        return Err(format!("name {:?} is not the last component of dir {:?}", p.name, p.dir));
    }
    // Settings are typed only when they are an object.
    let doc = BatchDoc::deserialize(&p.doc).unwrap_or_default();
    if doc.schema_version.as_deref() != Some(BATCH_SCHEMA) || doc.settings.is_none() {
        return Err(format!("doc must be a batch.json of schema {BATCH_SCHEMA} with settings"));
    }
    if p.records.len() > MAX_POST_RECORDS {
        return Err(format!("at most {MAX_POST_RECORDS} records per request"));
    }
    if let Some(i) = p.records.iter().position(|r| RecordKeys::deserialize(r).is_err()) {
        return Err(format!("records[{i}] is not a rollout record (rollout_id, schema_version)"));
    }
    Ok(())
}

/// The same batch as the stored one: the same directory and creation time (a `--resume` keeps both). Another
/// batch of the same name is refused rather than mixed in.
fn same_batch(stored: &StoredBatch, p: &Posted) -> bool {
    stored.dir.to_str() == Some(p.dir.as_str()) && created_at(&stored.doc) == created_at(&p.doc)
}

pub async fn register(State(app): State<AppState>, body: Bytes) -> ApiResult {
    if body.len() > MAX_POST_BYTES {
        return Err(ApiError::too_large(format!("at most {MAX_POST_BYTES} bytes per request")));
    }
    let posted: Posted = serde_json::from_slice(&body).map_err(|e| {
        ApiError::bad_request(format!("body must be {{\"name\", \"dir\", \"doc\", \"from\", \"records\"}}: {e}"))
    })?;
    check(&posted).map_err(ApiError::bad_request)?;
    let stored = app.store.batch(&posted.name).await?;
    let have = stored.as_ref().map_or(0, |s| s.records.len());
    if let Some(s) = &stored
        && !same_batch(s, &posted)
    {
        return Err(ApiError::conflict(format!(
            "this server already has a batch named {:?} from {} (created {}): name the new batch's directory differently",
            posted.name,
            s.dir.display(),
            created_at(&s.doc).as_deref().unwrap_or("?")
        ))
        .with_field("have", have));
    }
    if posted.from > have {
        // Records are stored by position: a gap would misplace them. The runner sends again from `have`.
        return Err(ApiError::conflict(format!("records from {} posted, but the server has {have}", posted.from)).with_field("have", have));
    }
    let name = posted.name.clone();
    // `put_batch` keeps the records it has by position and appends the rest: positions before `from` are ones
    // it has already (from <= have), so they are placeholders here and never written.
    let mut records = vec![Value::Null; posted.from];
    records.extend(posted.records);
    let total = records.len();
    let batch = StoredBatch { name: posted.name, dir: posted.dir.into(), doc: posted.doc, records };
    app.store.put_batch(&batch).await?;
    tracing::debug!(batch = name, records = total.max(have), "batch registered");
    Ok(axum::Json(json!({"ok": true, "name": name, "have": total.max(have), "results": format!("/results?batch={name}")})).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn posted(name: &str, dir: &str) -> Posted {
        Posted {
            name: name.into(),
            dir: dir.into(),
            doc: json!({"schema_version": BATCH_SCHEMA, "settings": {}, "created_at": "t"}),
            from: 0,
            records: vec![json!({"rollout_id": "w1", "schema_version": "libero_agent.rollout.v1"})],
        }
    }

    #[test]
    fn only_plain_batches_named_after_their_directory_pass() {
        assert!(check(&posted("b1", "/tmp/runs/b1")).is_ok());
        assert!(check(&posted("b1", "/tmp/runs/b2")).is_err(), "name must be the directory's");
        assert!(check(&posted("../x", "/tmp/../x")).is_err());
        assert!(check(&posted(".hidden", "/tmp/.hidden")).is_err());
        assert!(check(&posted("b1", "relative/b1")).is_err());
        let mut p = posted("b1", "/tmp/b1");
        p.doc["schema_version"] = json!("other");
        assert!(check(&p).is_err());
        let mut p = posted("b1", "/tmp/b1");
        p.records = vec![json!({"rollout_id": 3})];
        assert!(check(&p).is_err());
        let mut p = posted("b1", "/tmp/b1");
        p.records = vec![p.records[0].clone(); MAX_POST_RECORDS + 1];
        assert!(check(&p).is_err());
    }
}
