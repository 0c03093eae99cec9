//! The server's shared state ([`App`], what every handler gets) and what a browser console plugs into it
//! ([`Console`]); preparing an episode together with its store row.
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use axum::Router;
use axum::http::StatusCode;
use libero_episode::RunDir;

use crate::api_error::{ApiError, ApiResult};
use crate::episodes::{BranchError, Episodes, PrepareRequest, Prepared};
use libero_store::{NewEpisode, Store};
use crate::store_writer::StoreWriter;
use crate::{auth, live, thumbnails};

/// What a browser console adds to the server: its routes (each `fn` builds a fresh router) and its login page.
/// `operator_compressed` and `operator_raw` sit behind the operator guard (the first gzip-compressed);
/// `public` (static files) is open to anyone who may reach the server at all.
#[derive(Debug, Clone, Copy)]
pub struct Console {
    pub operator_compressed: fn() -> Router<AppState>,
    pub operator_raw: fn() -> Router<AppState>,
    pub public: fn() -> Router<AppState>,
    /// The login form's HTML (whether the token just given was wrong, where the server listens, the token file).
    pub login_page: fn(&auth::LoginInfo) -> String,
    /// Wraps the whole router so that browser routes answer errors, unknown routes included, as pages.
    pub browser_errors: fn(Router<AppState>) -> Router<AppState>,
}

/// The server's shared state: the live episodes and the store that outlives them.
pub struct App {
    pub episodes: Arc<Episodes>,
    pub store: Store,
    /// The one writer of episode rows ([`crate::store_writer`]).
    pub(crate) writer: StoreWriter,
    /// Live events of the episodes this process runs, for the dashboard.
    pub hubs: Arc<live::LiveHubs>,
    pub operator: auth::Operator,
    /// The `Host` names this server answers to.
    pub hosts: auth::AllowedHosts,
    /// The task thumbnail cache (rendered ahead at start, or on demand).
    pub thumbnails: Arc<thumbnails::Thumbnails>,
    /// Where the Results page looks for batch directories ([`crate::batch_roots`]).
    pub batch_roots: Vec<PathBuf>,
    /// Episodes the operator drives from the teleop page; only these accept actions from the operator's socket,
    /// so an agent's benchmark episode can never be steered from the dashboard.
    pub teleop: Mutex<HashMap<String, TeleopEpisode>>,
    /// How long a teleop episode may go without a connected teleop page before it is ended as abandoned.
    pub teleop_abandon_after: Duration,
    /// `--artifacts`: where run directories recorded on other machines are fetched from.
    pub artifacts: Option<libero_artifacts::Artifacts>,
    /// The browser console's routes, when this server has one.
    pub console: Option<Console>,
    /// Where other machines reach this server (`--public-url`, else its listening address), stored with every
    /// episode it prepares when it has a console (its live view).
    pub public_url: String,
}

pub type AppState = Arc<App>;

/// A teleop episode of [`App::teleop`]: its task, and whether a page is driving it (the console ends one nobody
/// drives after [`App::teleop_abandon_after`]).
#[derive(Debug, Clone)]
pub struct TeleopEpisode {
    pub task: String,
    /// Teleop sockets open on it now.
    pub sockets: usize,
    /// Since when no socket has been open (its creation, or its last socket's close).
    pub unattended_since: Instant,
    /// A demonstration is being saved from it: ending it then is the save's business.
    pub saving: bool,
}

impl TeleopEpisode {
    pub fn new(task: String) -> Self {
        Self { task, sockets: 0, unattended_since: Instant::now(), saving: false }
    }
}

impl App {
    /// Waits until the store writer has written what `id` shows now (the writer alone writes rows; a reader that
    /// must see the latest state asks it to catch up first).
    pub async fn sync(&self, id: &str) {
        self.writer.sync(Some(id)).await;
    }

    /// [`Self::sync`] of every episode whose last stored state is not final.
    pub async fn sync_all(&self) {
        self.writer.sync(None).await;
    }

    /// Stores a prepared episode's row. The run directory's record is written first; a row that cannot be
    /// stored is a failure of the preparation (the caller ends the episode), never a log line.
    pub async fn insert_prepared(&self, prepared: &Prepared) -> anyhow::Result<()> {
        let mut new = NewEpisode::from_record(&RunDir::new(&prepared.run_dir))
            .with_context(|| format!("episode {} has no readable episode record", prepared.episode_id))?;
        // Only a server with a console has a live view for other dashboards to link to.
        new.server_url = self.console.is_some().then(|| self.public_url.clone());
        self.writer.insert(new).await
    }

    /// Prepares an episode and stores its row; an episode whose row cannot be stored is stopped again.
    pub async fn prepare_stored(&self, req: PrepareRequest) -> ApiResult<Prepared> {
        req.validate().map_err(|e| ApiError::bad_request(format!("{e:#}")))?;
        // A branch's parent: its run directory as the store knows it (a run of another server on a shared store
        // whose directory this machine sees), else this server's own.
        let parent_run = match &req.branch {
            Some(b) => self.store.get(&b.parent).await.ok().flatten().map(|row| row.episode.run_dir).filter(|d| d.is_dir()),
            None => None,
        };
        let eps = self.episodes.clone();
        let prepared = match tokio::task::spawn_blocking(move || eps.prepare_with_parent(req, parent_run)).await {
            Ok(Ok(p)) => p,
            Ok(Err(e)) => {
                let status = e
                    .downcast_ref::<BranchError>()
                    .and_then(|b| StatusCode::from_u16(b.http_status()).ok())
                    .unwrap_or(StatusCode::UNPROCESSABLE_ENTITY);
                return Err(ApiError::new(status, format!("{e:#}")));
            }
            Err(e) => return Err(ApiError::internal(format!("prepare failed: {e}"))),
        };
        if let Err(e) = self.insert_prepared(&prepared).await {
            let eps = self.episodes.clone();
            let id = prepared.episode_id.clone();
            let _ = tokio::task::spawn_blocking(move || eps.lifecycle().stop(&id, "the episode store refused its row")).await;
            return Err(ApiError::internal(format!("cannot store the episode: {e:#}")));
        }
        Ok(prepared)
    }
}
