//! Errors of browser routes as pages. A person who follows a stale link, mistypes an episode id or sends a bad
//! query gets a page with the console's navigation and a plain sentence, not a JSON object or an empty 404.
//! `/api/`, `/ws/` and `/mcp/` keep answering JSON: scripts read those.
//!
//! The handlers keep answering errors as they always did (`libero_server::ApiError`, axum's rejections); one middleware around
//! the whole router turns an error answer of a browser route into [`render`]'s page with the same status and
//! message, and a fallback answers unknown routes. So a new page is covered without doing anything.
use askama::Template;
use axum::Router;
use axum::extract::Request;
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use libero_server::{ApiError, AppState};

/// Longest error body read to find its message; longer ones are not read and get the status's own words.
const MAX_ERROR_BODY: usize = 64 * 1024;
/// Longest message shown on the page.
const MAX_MESSAGE_CHARS: usize = 2000;

#[derive(Template)]
#[template(path = "error.html")]
struct ErrorPage<'a> {
    status: u16,
    title: &'a str,
    message: &'a str,
    path: &'a str,
    /// Whether the answer was "sign in first": the page then links to the login form.
    sign_in: bool,
}

/// Routes whose answers are for scripts (JSON or a WebSocket), never pages.
pub fn is_browser_path(path: &str) -> bool {
    !["/api/", "/ws/", "/mcp/"].iter().any(|p| path.starts_with(p)) && !matches!(path, "/api" | "/ws" | "/mcp")
}

/// The error page for `status` at `path`, saying `message`.
pub fn render(status: StatusCode, message: &str, path: &str) -> Response {
    let title = status.canonical_reason().unwrap_or("Error");
    let message: String = message.chars().take(MAX_MESSAGE_CHARS).collect();
    let path: String = path.chars().take(300).collect();
    let page = ErrorPage { status: status.as_u16(), title, message: &message, path: &path, sign_in: status == StatusCode::UNAUTHORIZED };
    match page.render() {
        Ok(html) => (status, Html(html)).into_response(),
        Err(e) => ApiError::new(status, format!("{message} (and the error page failed: {e})")).into_response(),
    }
}

/// Adds the console's error pages to the server's whole router (see the module doc).
pub fn browser_errors(router: Router<AppState>) -> Router<AppState> {
    router.fallback(unknown_route).layer(axum::middleware::from_fn(html_errors))
}

/// Routes open to everyone, like the static files: the icon a browser asks for on every page, login included.
pub fn public_routes() -> Router<AppState> {
    Router::new().route("/favicon.ico", get(favicon))
}

async fn favicon() -> Response {
    const ICON: &[u8] = include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/../../web/static/favicon.ico"));
    ([(header::CONTENT_TYPE, "image/x-icon"), (header::CACHE_CONTROL, "max-age=86400")], ICON).into_response()
}

async fn unknown_route(req: Request) -> Response {
    let path = req.uri().path();
    if is_browser_path(path) {
        return render(StatusCode::NOT_FOUND, "There is no page at this address. The console's pages are linked above.", path);
    }
    ApiError::not_found(format!("no route {} {path}", req.method())).into_response()
}

/// Middleware: an error answer (4xx, 5xx) of a browser route that is not a page already becomes the error page,
/// keeping its status, its message (the `error` of a JSON body, or a text body) and its `WWW-Authenticate`.
async fn html_errors(req: Request, next: Next) -> Response {
    let path = req.uri().path().to_owned();
    let resp = next.run(req).await;
    let status = resp.status();
    // 416 belongs to range requests of media players, which read no body.
    if !is_browser_path(&path) || !(status.is_client_error() || status.is_server_error()) || status == StatusCode::RANGE_NOT_SATISFIABLE {
        return resp;
    }
    let headers = resp.headers();
    let is_html = headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).is_some_and(|v| v.starts_with("text/html"));
    if is_html {
        return resp;
    }
    let encoded = headers.contains_key(header::CONTENT_ENCODING);
    let authenticate = headers.get(header::WWW_AUTHENTICATE).cloned();
    let body = if encoded { Vec::new() } else { axum::body::to_bytes(resp.into_body(), MAX_ERROR_BODY).await.map(|b| b.to_vec()).unwrap_or_default() };
    let message = message_of(&body).unwrap_or_else(|| default_message(status).to_owned());
    let mut page = render(status, &message, &path);
    if let Some(v) = authenticate {
        page.headers_mut().insert(header::WWW_AUTHENTICATE, v);
    }
    page.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    page
}

/// The message of an error body: `{"error": "…"}` or plain text.
fn message_of(body: &[u8]) -> Option<String> {
    if serde_json::from_slice::<serde_json::Value>(body).is_ok() {
        return ApiError::message_in(body);
    }
    let text = String::from_utf8_lossy(body).trim().to_owned();
    (!text.is_empty()).then_some(text)
}

fn default_message(status: StatusCode) -> &'static str {
    match status {
        StatusCode::NOT_FOUND => "There is nothing at this address.",
        StatusCode::UNAUTHORIZED => "Sign in with the operator token first.",
        StatusCode::FORBIDDEN => "This request is refused.",
        StatusCode::BAD_REQUEST => "The request's parameters are not valid.",
        _ if status.is_server_error() => "The server failed to answer; its log says why.",
        _ => "The request failed.",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_script_routes_keep_their_json() {
        for p in ["/", "/tasks", "/episodes/x/review", "/nowhere", "/apis", "/favicon.ico"] {
            assert!(is_browser_path(p), "{p}");
        }
        for p in ["/api/episodes", "/ws/episodes", "/mcp/ep-1", "/api"] {
            assert!(!is_browser_path(p), "{p}");
        }
    }

    #[test]
    fn the_message_comes_from_json_or_text_bodies() {
        assert_eq!(message_of(br#"{"ok":false,"error":"no episode ep-1"}"#).as_deref(), Some("no episode ep-1"));
        assert_eq!(message_of(b"Failed to deserialize query string\n").as_deref(), Some("Failed to deserialize query string"));
        assert_eq!(message_of(b""), None);
    }

    #[test]
    fn the_page_escapes_the_message_and_carries_the_navigation() {
        let resp = render(StatusCode::NOT_FOUND, "no episode <script>", "/episodes/<x>/review");
        assert_eq!(resp.status(), StatusCode::NOT_FOUND);
        let body = futures_body(resp);
        assert!(body.contains("no episode &#60;script&#62;") && !body.contains("<script>"), "{body}");
        assert!(body.contains("href=\"/tasks\"") && body.contains("href=\"/results\""), "{body}");
    }

    fn futures_body(resp: Response) -> String {
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        let bytes = rt.block_on(axum::body::to_bytes(resp.into_body(), 1 << 20)).unwrap();
        String::from_utf8(bytes.to_vec()).unwrap()
    }
}
