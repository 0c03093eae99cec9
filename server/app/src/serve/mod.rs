//! `libero-agent serve`: every prepared episode at its own MCP endpoint `/mcp/<episode_id>` (rmcp streamable
//! HTTP), guarded by a per-episode bearer token checked before anything reaches rmcp; `GET /api/health`;
//! `POST /api/episodes` to prepare an episode (the CLI's `episode prepare` and the dashboard use it).
pub mod episodes;
pub mod http_client;
pub mod mcp;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;
use axum::Router;
use axum::body::Body;
use axum::extract::{Path, Request, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{any, get, post};
use serde_json::json;

use episodes::{Episodes, PrepareRequest};

#[derive(clap::Args, Debug, Clone)]
pub struct ServeArgs {
    /// Address to listen on (port 0 picks a free port; the chosen URL is printed as JSON on stdout).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Data directory for run records and default workspaces (default: $LIBERO_AGENT_DATA or
    /// ~/.local/share/libero-agent).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

pub fn default_data_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("LIBERO_AGENT_DATA") {
        return PathBuf::from(d);
    }
    let home = std::env::var_os("HOME").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("."));
    home.join(".local/share/libero-agent")
}

type AppState = Arc<Episodes>;

/// Runs the server until SIGINT/SIGTERM; unfinished episodes are then recorded as aborted (INVALID).
pub fn run_serve(args: ServeArgs) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    runtime.block_on(serve(args))
}

pub async fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let data = args.data.clone().unwrap_or_else(default_data_dir);
    std::fs::create_dir_all(&data).with_context(|| format!("cannot create data directory {}", data.display()))?;
    let listener = tokio::net::TcpListener::bind(args.addr).await.with_context(|| format!("cannot bind {}", args.addr))?;
    let local = listener.local_addr()?;
    let base_url = format!("http://{local}");
    let episodes = Arc::new(Episodes::new(data.clone(), base_url.clone())?);
    let recovered = episodes.recover_interrupted();
    let app = router(episodes.clone());
    println!(
        "{}",
        json!({"event": "listening", "url": base_url, "data": data, "recovered_invalid_episodes": recovered})
    );
    let shutdown = {
        let episodes = episodes.clone();
        async move {
            let reason = shutdown_signal().await;
            let episodes = episodes.clone();
            let _ = tokio::task::spawn_blocking(move || episodes.stop_all(&reason)).await;
        }
    };
    axum::serve(listener, app).with_graceful_shutdown(shutdown).await?;
    Ok(())
}

async fn shutdown_signal() -> String {
    use tokio::signal::unix::{SignalKind, signal};
    let mut term = match signal(SignalKind::terminate()) {
        Ok(s) => s,
        Err(_) => {
            let _ = tokio::signal::ctrl_c().await;
            return "server_received_signal_2_before_finish".into();
        }
    };
    tokio::select! {
        _ = tokio::signal::ctrl_c() => "server_received_signal_2_before_finish".into(),
        _ = term.recv() => "server_received_signal_15_before_finish".into(),
    }
}

pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/api/health", get(health))
        .route("/api/episodes", post(prepare))
        .route("/api/episodes/{id}", get(episode_status))
        .route("/mcp/{id}", any(mcp_endpoint))
        .with_state(state)
}

async fn health(State(eps): State<AppState>) -> Response {
    axum::Json(json!({"ok": true, "episodes": eps.count(), "version": env!("CARGO_PKG_VERSION")})).into_response()
}

fn json_error(status: StatusCode, message: impl Into<String>) -> Response {
    (status, axum::Json(json!({"ok": false, "error": message.into()}))).into_response()
}

async fn prepare(State(eps): State<AppState>, body: axum::body::Bytes) -> Response {
    let req: PrepareRequest = match serde_json::from_slice(&body) {
        Ok(r) => r,
        Err(e) => return json_error(StatusCode::BAD_REQUEST, format!("invalid prepare request: {e}")),
    };
    match tokio::task::spawn_blocking(move || eps.prepare(req)).await {
        Ok(Ok(prepared)) => (StatusCode::CREATED, axum::Json(prepared)).into_response(),
        Ok(Err(e)) => json_error(StatusCode::UNPROCESSABLE_ENTITY, format!("{e:#}")),
        Err(e) => json_error(StatusCode::INTERNAL_SERVER_ERROR, format!("prepare failed: {e}")),
    }
}

async fn episode_status(State(eps): State<AppState>, Path(id): Path<String>) -> Response {
    match eps.status(&id) {
        Some(s) => axum::Json(s).into_response(),
        None => json_error(StatusCode::NOT_FOUND, format!("no episode {id}")),
    }
}

/// `Authorization: Bearer <token>`, if present.
fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers.get(header::AUTHORIZATION)?.to_str().ok()?.strip_prefix("Bearer ").map(str::trim)
}

/// The token check happens here, before rmcp sees any byte; unknown episode and wrong token look the same.
async fn mcp_endpoint(State(eps): State<AppState>, Path(id): Path<String>, req: Request<Body>) -> Response {
    let Some(service) = eps.authorize(&id, bearer(req.headers())) else {
        return (
            StatusCode::UNAUTHORIZED,
            [(header::WWW_AUTHENTICATE, "Bearer")],
            axum::Json(json!({"ok": false, "error": "missing or invalid episode token"})),
        )
            .into_response();
    };
    use tower_service::Service;
    let mut service = service;
    match service.call(req).await {
        Ok(resp) => resp.into_response(),
        Err(never) => match never {},
    }
}
