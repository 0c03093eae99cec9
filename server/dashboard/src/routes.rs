//! The console's routes of the episode pages, the Tasks and Results pages and the static files, each handler in
//! the module of its page (named like its template and script): [`home`], [`live`], [`review`], [`tasks`],
//! [`results`]; the teleop, demos and task pages have their own routers. Every route here but the static files is
//! behind the operator guard; nothing here is reachable with an episode token.
use axum::Router;
use axum::routing::get;
use libero_server::AppState;

use crate::{common, home, live, results, review, tasks};

/// Pages, static files and JSON: small responses worth compressing.
pub fn compressed_routes() -> Router<AppState> {
    Router::new()
        .route("/", get(home::home))
        .route("/tasks", get(tasks::tasks_page))
        .route("/episodes/{id}", get(live::live_page))
        .route("/episodes/{id}/review", get(review::review_page))
        .route("/api/episodes/{id}/review", get(review::review_data))
        .route("/api/episodes/{id}/agent", get(review::agent_data))
        .route("/api/tasks", get(tasks::tasks_json))
        .route("/results", get(results::results_page))
        .route("/api/results", get(results::results_api))
        .route("/results/report/{format}", get(results::results_download))
}

/// Streams and media: never compressed (range requests, WebSocket upgrades, JPEG/PNG/MP4).
pub fn raw_routes() -> Router<AppState> {
    Router::new()
        .route("/ws/episodes", get(home::list_socket))
        .route("/ws/episodes/{id}", get(live::episode_socket))
        .route("/episodes/{id}/video.mp4", get(review::video))
        .route("/episodes/{id}/observations/{*path}", get(review::observation_file))
        .route("/api/episodes/{id}/moment", get(review::moment))
        .route("/tasks/{id}/thumbnail.png", get(tasks::thumbnail))
        .route("/tasks/{suite}/{task_id}/thumbnail.png", get(tasks::pool_thumbnail))
}

/// Static files, open to everyone (no data in them; the login page needs them).
pub fn static_routes() -> Router<AppState> {
    Router::new().route("/static/{file}", get(common::static_file))
}
