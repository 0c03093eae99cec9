//! The MCP half of the server's episodes: each prepared episode's rmcp service and its session manager, and the
//! token check of `/mcp/<id>`. Everything else an episode goes through (preparation, the end, release, videos,
//! demonstrations) is the lifecycle of `libero_episode::lifecycle`, which [`Episodes`] wraps and hands out as
//! [`Episodes::lifecycle`].
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, RwLock};

use anyhow::Context;
use libero_episode::EpisodeHandle;
use libero_episode::lifecycle::EpisodeSet;
use rmcp::transport::streamable_http_server::session::SessionManager;
use rmcp::transport::streamable_http_server::session::local::LocalSessionManager;
use rmcp::transport::streamable_http_server::{StreamableHttpServerConfig, StreamableHttpService};
use sha2::{Digest, Sha256};

use crate::mcp::EpisodeMcp;

/// The request and reply types of `POST /api/episodes` live with the lifecycle; here under their old paths.
pub use libero_episode::lifecycle::{
    BranchError, BranchRequest, MAX_WALL_TIME_S, PrepareRequest, Prepared, RELEASE_GRACE, random_hex, valid_episode_id,
};

pub type McpService = StreamableHttpService<EpisodeMcp, LocalSessionManager>;

/// Largest accepted MCP request body (the original's 1 MiB protocol limit).
const MAX_REQUEST_BYTES: usize = 1 << 20;
/// Most MCP sessions one episode keeps open at once (an agent needs one; a relay or a reconnect a few more).
pub const MAX_SESSIONS_PER_EPISODE: usize = 8;

/// One running episode's MCP service, with what its session cap needs.
#[derive(Clone)]
pub struct LiveMcp {
    pub service: McpService,
    sessions: Arc<LocalSessionManager>,
    /// Held from a session count to the `initialize` it admits, so concurrent ones cannot pass the cap together.
    admitting: Arc<tokio::sync::Mutex<()>>,
}

impl LiveMcp {
    fn new(mcp: EpisodeMcp) -> Self {
        let config = StreamableHttpServerConfig::default()
            .disable_allowed_hosts() // the per-episode token is the guard; hosts vary behind proxies
            .with_max_request_body_bytes(MAX_REQUEST_BYTES);
        let sessions = Arc::new(LocalSessionManager::default());
        let service = StreamableHttpService::new(move || Ok(mcp.clone()), sessions.clone(), config);
        Self { service, sessions, admitting: Arc::default() }
    }

    /// Waits for the right to admit one new session; holding the guard, count with [`Self::open_sessions`].
    pub async fn admit(&self) -> tokio::sync::OwnedMutexGuard<()> {
        self.admitting.clone().lock_owned().await
    }

    pub async fn open_sessions(&self) -> usize {
        self.sessions.sessions.read().await.len()
    }

    /// Closes every session: their workers end and let go of the episode's handler. Dropping the service alone
    /// would not do it, as each session worker holds the session manager until its 5-minute idle timeout.
    async fn close_all(&self) {
        let ids: Vec<_> = self.sessions.sessions.read().await.keys().cloned().collect();
        for id in ids {
            if let Err(e) = self.sessions.close_session(&id).await {
                log::warn!("closing MCP session {id}: {e}");
            }
        }
    }
}

/// What `/mcp/{id}` serves to a caller holding the episode's token.
pub enum McpAccess {
    Live(LiveMcp),
    /// The episode ended and its sessions were released; the handle answers from the episode's end record.
    Ended(EpisodeHandle),
}

/// An episode's endpoint: the token's digest (the token itself never outlives the prepare reply) and, until the
/// episode is released, its service.
struct Endpoint {
    token_sha256: [u8; 32],
    handle: EpisodeHandle,
    mcp: Option<LiveMcp>,
}

/// The server's episodes: the lifecycle ([`EpisodeSet`], through [`Episodes::lifecycle`]), and an MCP endpoint for
/// each episode prepared through [`Episodes::prepare`].
pub struct Episodes {
    set: EpisodeSet,
    endpoints: RwLock<HashMap<String, Endpoint>>,
}

impl Episodes {
    /// The lifecycle of every episode (prepare, stop, recover, release, videos, demos): `libero_episode`'s API.
    pub fn lifecycle(&self) -> &EpisodeSet {
        &self.set
    }
}

impl From<EpisodeSet> for Episodes {
    fn from(set: EpisodeSet) -> Self {
        Self { set, endpoints: RwLock::new(HashMap::new()) }
    }
}

/// Equal-time comparison, so response timing does not leak how much of a token was right.
pub(crate) fn tokens_equal(a: &str, b: &str) -> bool {
    bytes_equal(a.as_bytes(), b.as_bytes())
}

fn bytes_equal(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

fn token_digest(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

impl Episodes {
    /// The lifecycle's [`EpisodeSet::new`] with MCP endpoints (no live views, no events: in-process tools).
    pub fn new(data: PathBuf, base_url: String) -> anyhow::Result<Self> {
        Ok(EpisodeSet::new(data, base_url)?.into())
    }

    /// [`EpisodeSet::prepare`], then the episode's MCP endpoint.
    pub fn prepare(&self, req: PrepareRequest) -> anyhow::Result<Prepared> {
        self.prepare_with_parent(req, None)
    }

    /// [`EpisodeSet::prepare_with_parent`], then the episode's MCP endpoint.
    pub fn prepare_with_parent(&self, req: PrepareRequest, parent_run: Option<PathBuf>) -> anyhow::Result<Prepared> {
        let prepared = self.set.prepare_with_parent(req, parent_run)?;
        if let Err(e) = self.open_endpoint(&prepared) {
            // Nobody could ever call this episode: end it now, so its thread and world go.
            self.set.stop(&prepared.episode_id, &format!("its MCP endpoint could not be opened: {e:#}"));
            return Err(e);
        }
        Ok(prepared)
    }

    fn open_endpoint(&self, prepared: &Prepared) -> anyhow::Result<()> {
        let id = &prepared.episode_id;
        let token = prepared.bearer_token().context("the prepared episode has no bearer token")?;
        let handle = self.set.handle(id).context("the prepared episode vanished")?;
        let mcp = LiveMcp::new(EpisodeMcp { handle: handle.clone() });
        let endpoint = Endpoint { token_sha256: token_digest(token), handle, mcp: Some(mcp) };
        self.endpoints
            .write()
            .map_err(|_| anyhow::anyhow!("episode registry lock poisoned"))?
            .insert(id.clone(), endpoint);
        Ok(())
    }

    /// What the episode's MCP endpoint serves if `token` is its token.
    pub fn mcp_access(&self, id: &str, token: Option<&str>) -> Option<McpAccess> {
        let digest = token_digest(token?);
        let map = self.endpoints.read().ok()?;
        let endpoint = map.get(id)?;
        if !bytes_equal(&endpoint.token_sha256, &digest) {
            return None;
        }
        Some(match &endpoint.mcp {
            Some(live) => McpAccess::Live(live.clone()),
            None => McpAccess::Ended(endpoint.handle.clone()),
        })
    }

    /// [`EpisodeSet::release_ended`], then closes the released episodes' MCP sessions (their endpoints answer
    /// from the end record from now on) and trims the freed memory on a blocking thread. Only a release uses a
    /// blocking thread: a periodic one would keep tokio's idle blocking threads from ever timing out (each wake-up
    /// goes to another of them). Returns the ids released.
    pub async fn release_ended(self: &Arc<Self>) -> Vec<String> {
        let due = self.set.release_ended();
        for id in &due {
            let live = self.endpoints.write().ok().and_then(|mut m| m.get_mut(id).and_then(|e| e.mcp.take()));
            if let Some(live) = live {
                live.close_all().await;
            }
        }
        if !due.is_empty() {
            let _ = tokio::task::spawn_blocking(libero_episode::memory::return_freed_memory).await;
        }
        due
    }
}
