//! What every page of the console shares: rendering an askama template into a response, the episode-id check,
//! serving a file with range support (the review's video and observation images, thumbnails, demonstrations), and
//! the static files of `web/static/` (`style.css`, `common.js` and each page's script), compiled into the binary
//! so an installed server needs no web folder. The static files are open to everyone (no data in them; the login
//! page needs them).
use askama::Template;
use axum::body::Body;
use axum::extract::{Path, Request};
use axum::http::header;
use axum::response::{Html, IntoResponse, Response};
use libero_server::ApiError;
use tower::ServiceExt;
use tower_http::services::ServeFile;

pub(crate) fn page(t: impl Template) -> Response {
    match t.render() {
        Ok(html) => Html(html).into_response(),
        Err(e) => ApiError::internal(format!("template: {e}")).into_response(),
    }
}

/// Episode ids are `ep-<utc>-<hex>`; anything else never reaches the filesystem.
pub(crate) fn valid_id(id: &str) -> bool {
    !id.is_empty() && id.len() <= 96 && id.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
}

/// A file served with range support (the video, observation images).
pub(crate) async fn serve_file(path: std::path::PathBuf, req: Request<Body>) -> Response {
    match ServeFile::new(path).oneshot(req).await {
        Ok(resp) => resp.map(Body::new).into_response(),
        Err(e) => ApiError::internal(format!("file: {e}")).into_response(),
    }
}

macro_rules! web_static {
    ($name:literal) => {
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/../../web/static/", $name))
    };
}

pub(crate) async fn static_file(Path(file): Path<String>) -> Response {
    let (body, kind) = match file.as_str() {
        "style.css" => (web_static!("style.css"), "text/css; charset=utf-8"),
        "common.js" => (web_static!("common.js"), "text/javascript; charset=utf-8"),
        "home.js" => (web_static!("home.js"), "text/javascript; charset=utf-8"),
        "live.js" => (web_static!("live.js"), "text/javascript; charset=utf-8"),
        "review.js" => (web_static!("review.js"), "text/javascript; charset=utf-8"),
        "teleop.js" => (web_static!("teleop.js"), "text/javascript; charset=utf-8"),
        "demos.js" => (web_static!("demos.js"), "text/javascript; charset=utf-8"),
        "elsewhere.js" => (web_static!("elsewhere.js"), "text/javascript; charset=utf-8"),
        "branch.js" => (web_static!("branch.js"), "text/javascript; charset=utf-8"),
        "annotate.js" => (web_static!("annotate.js"), "text/javascript; charset=utf-8"),
        "thumbs.js" => (web_static!("thumbs.js"), "text/javascript; charset=utf-8"),
        _ => return ApiError::not_found("no such file").into_response(),
    };
    ([(header::CONTENT_TYPE, kind), (header::CACHE_CONTROL, "no-cache")], body).into_response()
}
