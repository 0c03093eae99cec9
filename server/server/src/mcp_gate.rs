//! `/mcp/{id}`: the token check ([`mcp_endpoint`]), then the episode's answer. A running episode's requests go to its rmcp service, a new session only
//! while the episode has fewer than [`MAX_SESSIONS_PER_EPISODE`] open. An ended episode keeps no sessions: its
//! requests are answered here from its end record. Tool calls get exactly what the episode would have answered
//! (the protocol's "already finished" error, the expiry payload, …); anything else (a new `initialize`,
//! `tools/list`, …) gets HTTP 410 with a JSON-RPC error saying the episode has ended, which MCP clients show
//! as the error's message.
use axum::body::{Body, Bytes};
use axum::extract::{Path, Request, State};
use axum::http::{HeaderMap, Method, StatusCode, header};
use axum::response::{IntoResponse, Response};
use libero_episode::actor::Ended;
use libero_episode::{EpisodeHandle, Outcome};
use serde_json::{Map, Value, json};

use crate::api_error::{ApiError, ApiResult};
use crate::app::AppState;
use crate::episodes::{LiveMcp, MAX_SESSIONS_PER_EPISODE, McpAccess};
use crate::mcp::envelope;

/// Largest MCP request body read; a 50-action `osc_sequence` is a few kilobytes.
const MAX_MCP_BODY_BYTES: usize = 4 << 20;
/// JSON-RPC error code of "this episode has ended" and "too many sessions" (implementation-defined range).
const EPISODE_ERROR_CODE: i64 = -32000;

/// `Authorization: Bearer <token>`, if present.
pub fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers.get(header::AUTHORIZATION)?.to_str().ok()?.strip_prefix("Bearer ").map(str::trim)
}

/// The token check happens here, before rmcp sees any byte; unknown episode and wrong token look the same.
pub(crate) async fn mcp_endpoint(State(app): State<AppState>, Path(id): Path<String>, req: Request<Body>) -> Response {
    let Some(access) = app.episodes.mcp_access(&id, bearer(req.headers())) else {
        // The body is not read: close the connection so a keep-alive client never reuses it mid-body.
        return ApiError::unauthorized("missing or invalid episode token")
            .with_header(header::WWW_AUTHENTICATE, "Bearer")
            .with_header(header::CONNECTION, "close")
            .into_response();
    };
    serve(access, &id, req).await
}

/// Serves one authorised request to episode `id`.
pub async fn serve(access: McpAccess, id: &str, req: Request<Body>) -> Response {
    match access {
        McpAccess::Live(live) => serve_live(live, id, req).await,
        McpAccess::Ended(handle) => serve_ended(&handle, id, req).await,
    }
}

/// The whole body, read before anything answers: a service that answers early (415, 413) without reading it
/// would leave the rest on a kept-alive connection and break the client's next request.
async fn read_body(body: Body) -> ApiResult<Bytes> {
    axum::body::to_bytes(body, MAX_MCP_BODY_BYTES)
        .await
        .map_err(|_| ApiError::too_large(format!("request body over {MAX_MCP_BODY_BYTES} bytes")).with_header(header::CONNECTION, "close"))
}

async fn serve_live(live: LiveMcp, id: &str, req: Request<Body>) -> Response {
    let (parts, body) = req.into_parts();
    let bytes = match read_body(body).await {
        Ok(b) => b,
        Err(e) => return e.into_response(),
    };
    let message: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
    // A new session is admitted only under the cap; the guard is held until rmcp has registered it.
    let _admitting = if opens_session(&parts.method, &parts.headers, &message) {
        let guard = live.admit().await;
        if live.open_sessions().await >= MAX_SESSIONS_PER_EPISODE {
            let text = format!(
                "episode {id} already has {MAX_SESSIONS_PER_EPISODE} open MCP sessions, the most one episode keeps; reuse \
                 one, or close one (HTTP DELETE with its Mcp-Session-Id header) before opening another"
            );
            return rpc_error(StatusCode::TOO_MANY_REQUESTS, &message["id"], &text, json!({"episode_id": id}));
        }
        Some(guard)
    } else {
        None
    };
    use tower_service::Service;
    let mut service = live.service;
    match service.call(Request::from_parts(parts, Body::from(bytes))).await {
        Ok(resp) => resp.into_response(),
        Err(never) => match never {},
    }
}

/// A POST of `initialize` without a session id: what creates an rmcp session.
fn opens_session(method: &Method, headers: &HeaderMap, message: &Value) -> bool {
    method == Method::POST && !headers.contains_key("mcp-session-id") && message["method"] == "initialize"
}

async fn serve_ended(handle: &EpisodeHandle, id: &str, req: Request<Body>) -> Response {
    let ended = EndedText::of(handle, id);
    let (parts, body) = req.into_parts();
    match parts.method {
        Method::POST => {}
        // The session is already closed on this side.
        Method::DELETE => return StatusCode::NO_CONTENT.into_response(),
        // No event stream to open: MCP clients take 405 as "this server offers none" and stop asking.
        _ => {
            return ApiError::new(StatusCode::METHOD_NOT_ALLOWED, ended.message).with_header(header::ALLOW, "POST, DELETE").into_response();
        }
    }
    let bytes = match read_body(body).await {
        Ok(b) => b,
        Err(e) => return e.into_response(),
    };
    let message: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
    let Some(request_id) = message.get("id").filter(|_| message.get("method").is_some()) else {
        // A notification or a response: nothing to answer.
        return StatusCode::ACCEPTED.into_response();
    };
    if message["method"] == "tools/call" {
        return tool_result(handle, request_id, &message["params"]);
    }
    rpc_error(StatusCode::GONE, request_id, &ended.message, ended.data)
}

/// What the episode answers to a tool call after its end, in the tool-result envelope.
fn tool_result(handle: &EpisodeHandle, request_id: &Value, params: &Value) -> Response {
    let name = params["name"].as_str().unwrap_or_default();
    let arguments: Option<Map<String, Value>> = params["arguments"].as_object().cloned();
    let payload = handle.call(name, arguments);
    let result = serde_json::to_value(envelope(payload)).unwrap_or(Value::Null);
    axum::Json(json!({"jsonrpc": "2.0", "id": request_id, "result": result})).into_response()
}

fn rpc_error(status: StatusCode, request_id: &Value, message: &str, data: Value) -> Response {
    let body = json!({"jsonrpc": "2.0", "id": request_id, "error": {"code": EPISODE_ERROR_CODE, "message": message, "data": data}});
    (status, axum::Json(body)).into_response()
}

/// "episode … has ended (finished); …" and the same facts as data.
struct EndedText {
    message: String,
    data: Value,
}

impl EndedText {
    fn of(handle: &EpisodeHandle, id: &str) -> Self {
        let state = match handle.ended() {
            Some(Ended::Finished) => "finished",
            Some(Ended::Expired { .. }) => "expired",
            Some(Ended::Aborted) | None => "aborted",
        };
        let outcome = handle.status().outcome.map(Outcome::as_str);
        Self {
            message: format!("episode {id} has ended ({state}); its MCP endpoint accepts no further calls"),
            data: json!({"episode_id": id, "state": state, "outcome": outcome}),
        }
    }
}
