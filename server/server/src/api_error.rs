//! The one rule for error answers of the HTTP API, here and in the console's routes (`libero-dashboard`).
//!
//! Every error a handler or middleware answers is an [`ApiError`]: a status and a message, rendered as
//! `{"ok": false, "error": "<message>"}` with that status (plus, rarely, more fields such as a batch's `have`,
//! and headers such as `WWW-Authenticate`). Scripts (the CLI, the runner, tests) read `error`; the console's
//! error pages read the same field to answer a browser with a page instead. Handlers return
//! [`ApiResult`] and use `?`; nothing else builds an error body, so the shape cannot drift between routes.
use axum::http::{HeaderName, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde_json::{Map, Value};

/// A failed request: its status, the sentence the caller reads, and what a few answers carry besides.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{message}")]
pub struct ApiError {
    status: StatusCode,
    message: String,
    /// Fields beside `ok` and `error` (the batch API's `have`).
    extra: Map<String, Value>,
    headers: Vec<(HeaderName, HeaderValue)>,
}

/// What an API handler returns.
pub type ApiResult<T = Response> = Result<T, ApiError>;

impl ApiError {
    pub fn new(status: StatusCode, message: impl Into<String>) -> Self {
        Self { status, message: message.into(), extra: Map::new(), headers: Vec::new() }
    }

    /// 400: the request itself is malformed.
    pub fn bad_request(message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, message)
    }

    pub fn unauthorized(message: impl Into<String>) -> Self {
        Self::new(StatusCode::UNAUTHORIZED, message)
    }

    pub fn forbidden(message: impl Into<String>) -> Self {
        Self::new(StatusCode::FORBIDDEN, message)
    }

    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, message)
    }

    /// 409: the request is fine but the state it meets is not (a batch named twice, an ended run).
    pub fn conflict(message: impl Into<String>) -> Self {
        Self::new(StatusCode::CONFLICT, message)
    }

    pub fn too_large(message: impl Into<String>) -> Self {
        Self::new(StatusCode::PAYLOAD_TOO_LARGE, message)
    }

    /// 422: well-formed, but what it asks for cannot be done (an unknown task, a failed replay).
    pub fn unprocessable(message: impl Into<String>) -> Self {
        Self::new(StatusCode::UNPROCESSABLE_ENTITY, message)
    }

    /// 500: the server failed; the message says where.
    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, message)
    }

    /// One more field of the body besides `ok` and `error`.
    pub fn with_field(mut self, key: &str, value: impl Into<Value>) -> Self {
        self.extra.insert(key.to_owned(), value.into());
        self
    }

    /// One more header of the answer (`WWW-Authenticate`, `Connection: close`, `Allow`).
    pub fn with_header(mut self, name: HeaderName, value: &'static str) -> Self {
        self.headers.push((name, HeaderValue::from_static(value)));
        self
    }

    /// The message of an error answer's body (`{"ok": false, "error": "…"}`), for this server's own clients and
    /// error pages; `None` for any other body.
    pub fn message_in(body: &[u8]) -> Option<String> {
        #[derive(serde::Deserialize)]
        struct Body {
            error: String,
        }
        serde_json::from_slice::<Body>(body).ok().map(|b| b.error)
    }

    pub fn status(&self) -> StatusCode {
        self.status
    }

    pub fn message(&self) -> &str {
        &self.message
    }
}

/// A store that fails answers 500 with its own words (`{e:#}`, as every handler always wrote it).
impl From<libero_store::StoreError> for ApiError {
    fn from(e: libero_store::StoreError) -> Self {
        Self::internal(format!("{e:#}"))
    }
}

/// `Query<T>` whose rejection is an [`ApiError`]: a query string the route cannot read (`?limit=many`) is answered
/// `{"ok": false, "error": "…"}` with axum's words naming the field, as every other bad request, instead of axum's
/// plain-text 400 (which a script reading `error`, and the console's error pages, could not read).
#[derive(Debug, Clone, Copy, Default)]
pub struct ApiQuery<T>(pub T);

impl<T, S> axum::extract::FromRequestParts<S> for ApiQuery<T>
where
    T: serde::de::DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut axum::http::request::Parts, state: &S) -> Result<Self, ApiError> {
        match axum::extract::Query::<T>::from_request_parts(parts, state).await {
            Ok(axum::extract::Query(query)) => Ok(Self(query)),
            Err(rejection) => Err(ApiError::new(rejection.status(), rejection.body_text())),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut body = Map::new();
        body.insert("ok".into(), Value::Bool(false));
        body.extend(self.extra);
        body.insert("error".into(), Value::String(self.message));
        let mut resp = (self.status, axum::Json(Value::Object(body))).into_response();
        for (name, value) in self.headers {
            resp.headers_mut().insert(name, value);
        }
        resp
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rendered(e: ApiError) -> (StatusCode, Option<String>, Value) {
        let resp = e.into_response();
        let status = resp.status();
        let ctype = resp.headers().get(axum::http::header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).map(str::to_owned);
        let rt = tokio::runtime::Builder::new_current_thread().build().expect("runtime");
        let bytes = rt.block_on(axum::body::to_bytes(resp.into_body(), 1 << 20)).expect("body");
        (status, ctype, serde_json::from_slice(&bytes).expect("JSON body"))
    }

    #[test]
    fn the_body_is_ok_false_and_the_message() {
        let (status, ctype, body) = rendered(ApiError::not_found("no episode ep-1"));
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert_eq!(ctype.as_deref(), Some("application/json"));
        assert_eq!(body, serde_json::json!({"ok": false, "error": "no episode ep-1"}));
        let (_, _, body) = rendered(ApiError::conflict("gap").with_field("have", 3));
        assert_eq!(body, serde_json::json!({"ok": false, "have": 3, "error": "gap"}));
    }
}
