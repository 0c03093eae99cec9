//! The router: which route is whose (the operator's API and console behind the operator guard, `/mcp/{id}`
//! behind its episode token, health and login open), compression, and the host check over everything.
use axum::Router;
use axum::http::{HeaderMap, StatusCode};
use axum::routing::{any, get};

use crate::app::AppState;
use crate::mcp_gate::mcp_endpoint;
use crate::{api, auth};

/// Gzip for successful responses only: error bodies are short, and a console can still read them to answer a
/// browser with a page (`Console::browser_errors`).
fn compression() -> tower_http::compression::CompressionLayer<impl tower_http::compression::Predicate> {
    use tower_http::compression::predicate::{DefaultPredicate, Predicate};
    let success = |status: StatusCode, _: axum::http::Version, _: &HeaderMap, _: &axum::http::Extensions| status.is_success();
    tower_http::compression::CompressionLayer::new().compress_when(DefaultPredicate::new().and(success))
}

pub fn router(state: AppState) -> Router {
    // The operator's side: the operator API and the console's pages, live streams and private media. Episode
    // tokens open none of it.
    let mut compressed = api::operator_routes();
    let mut raw = Router::new();
    let mut public = Router::new();
    if let Some(console) = state.console {
        compressed = compressed.merge((console.operator_compressed)());
        raw = raw.merge((console.operator_raw)());
        public = public.merge((console.public)());
    }
    let operator = compressed
        .layer(compression())
        .merge(raw)
        .layer(axum::middleware::from_fn_with_state(state.operator.clone(), auth::require_operator));
    let mut all = Router::new()
        .route("/api/health", get(api::health))
        .route("/mcp/{id}", any(mcp_endpoint))
        .merge(
            Router::new()
                .route("/login", get(auth::login_form).post(auth::login))
                .with_state(state.operator.clone()),
        )
        .merge(public.layer(compression()))
        .merge(operator);
    if let Some(console) = state.console {
        all = (console.browser_errors)(all);
    }
    all.layer(axum::middleware::from_fn_with_state(state.hosts.clone(), auth::check_host))
        .layer(tower_http::trace::TraceLayer::new_for_http())
        .with_state(state)
}
