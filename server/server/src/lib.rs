//! The episode server (`libero-agent serve`, and the in-process server of `run` and `worker`): every prepared
//! episode at its own MCP endpoint `/mcp/<episode_id>` (rmcp streamable HTTP), guarded by a per-episode bearer
//! token checked before anything reaches rmcp; `GET /api/health`; `POST /api/episodes` to prepare an episode
//! (the CLI's `episode prepare` and the dashboard use it); `GET /api/episodes[/{id}[/video]]` from the episode
//! store (operator-facing; no tokens, no paths), behind the operator guard (`auth`). The browser console is not
//! here: a [`Console`] (the `libero-dashboard` crate's) adds its pages, so a worker's server can run without it.
//! Every listener (the address asked for and its loopback twin) serves through [`listener`]: connection caps per
//! peer address and in total, header, idle and body timeouts, and a file-descriptor reserve for the episodes.
//! Every error answer, the console's included, is an [`ApiError`] (`api_error`: the one place its JSON shape lives).
pub mod api_error;
pub mod auth;
pub mod batches;
pub mod client;
pub mod credential;
pub mod episodes;
pub mod http_client;
pub mod listener;
pub mod live;
pub mod mcp;
pub mod mcp_gate;
pub mod memory;
pub mod store;
pub mod thumbnails;
pub mod transcript;

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{Context, bail};
use axum::Router;
use axum::body::Body;
use axum::extract::{Path, Query, Request, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{any, get, post};
use libero_episode::json::utc_now_iso;
use libero_episode::{EpisodeState, EpisodeStatus, RunDir};
use serde_json::{Value, json};
use tokio::sync::mpsc::{UnboundedReceiver, unbounded_channel};

pub use api_error::{ApiError, ApiResult};
use episodes::{Episodes, PrepareRequest};
use store::{EpisodeEnd, NewEpisode, STORE_FILE, Store};

/// Where a server listens, under which names it is reached and whose token opens it: the flags `serve` and
/// `worker` share, defined once here so their names, defaults and help cannot drift apart. A worker changes
/// only `--addr`'s default (its server is for its own agents first, so any free port will do).
#[derive(clap::Args, Debug, Clone)]
pub struct ServerFlags {
    /// Address to listen on (port 0 picks a free port). `serve` prints the chosen URL as JSON on stdout; a
    /// worker's server answers its agents' MCP calls and, with a console, the live views other dashboards link to.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Data directory for run records and default workspaces (default: $LIBERO_AGENT_DATA or
    /// ~/.local/share/libero-agent). A worker's default is `workers/<worker id>` in there, a directory of its
    /// own, so any number of workers run on one machine without flags (printed at start): its server's data in
    /// `server/`, the runner's files per batch beside it.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// File holding the operator token for the dashboard and operator API (at least 16 characters). Without
    /// it, the token kept in `<data>/operator_token` (0600) is used again, or a random one is made at the first
    /// start. Either way it is kept there and registered for this user's client commands; a one-time login link is
    /// printed to stderr at each start.
    #[arg(long)]
    pub operator_token_file: Option<PathBuf>,
    /// A host name (or `name:port`) besides the loopback names under which this server is reached, e.g. behind
    /// a reverse proxy; requests naming any other `Host` are refused with 421. Repeatable.
    #[arg(long = "public-host", value_name = "NAME")]
    pub public_hosts: Vec<String>,
    /// The URL under which other machines reach this server (e.g. `http://worker-3.lab:8080`): stored with each
    /// episode it runs, so a dashboard elsewhere on the same store links to the episode's live view here
    /// (default: the address it listens on).
    #[arg(long, value_name = "URL")]
    pub public_url: Option<String>,
}

/// The stores a server shares with other machines: `serve` and `worker` take the same two flags (a worker
/// requires both: it claims from the queue in the one and uploads to the other).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct StoreFlags {
    /// The episode store: `sqlite://PATH` (default `<data>/episodes.sqlite`, embedded) or
    /// `postgres://USER@HOST:PORT/DB`, one store several servers can share (the password may come from
    /// `PGPASSWORD` or `~/.pgpass` instead of the URL). A worker needs one: its queue is there. Also
    /// $LIBERO_AGENT_STORE.
    #[arg(long, value_name = "URL", env = "LIBERO_AGENT_STORE")]
    pub store: Option<String>,
    /// The artifact store workers upload run directories to (`/shared/dir`, `file:///…` or `s3://BUCKET[/PREFIX]`
    /// with the `AWS_*` environment): reviews and videos of episodes run on other machines are fetched from there
    /// on first view and kept under `<data>/artifact_cache/`. A worker needs one. Also $LIBERO_AGENT_ARTIFACTS.
    #[arg(long, value_name = "URL", env = "LIBERO_AGENT_ARTIFACTS")]
    pub artifacts: Option<String>,
}

#[derive(clap::Args, Debug, Clone)]
pub struct ServeArgs {
    #[command(flatten)]
    pub server: ServerFlags,
    /// Replace the kept operator token with a new random one: every browser session, unused login link and
    /// client holding the old token is refused from now on.
    #[arg(long, conflicts_with = "operator_token_file")]
    pub rotate_token: bool,
    /// More batch directories for the Results page, besides `<data>/batches/`: a batch directory itself or a
    /// folder of them (e.g. `./agent_runs`, where `run` puts batches by default). Repeatable.
    #[arg(long = "batches", value_name = "DIR")]
    pub batches: Vec<PathBuf>,
    #[command(flatten)]
    pub stores: StoreFlags,
    /// Connection limits and timeouts of every listener (see [`listener`]).
    #[command(flatten)]
    pub limits: listener::ConnLimits,
    /// The browser console this server serves, if any (set by the binary, never from the command line).
    #[arg(skip)]
    pub console: Option<Console>,
    /// Which task thumbnails a server with a console renders ahead, at start.
    #[command(flatten)]
    pub thumbnails: ThumbnailArgs,
}

/// Task thumbnails rendered ahead at start by a server with a console ([`thumbnails`]).
#[derive(clap::Args, Debug, Clone)]
pub struct ThumbnailArgs {
    /// Task thumbnails a server with a console renders at start, in the background at low priority (cached under
    /// `<data>/thumbnails/`, reused across restarts): `all` (every release task, then every runnable pool entry),
    /// `off`, or a comma-separated list of `release`, pool suites and task ids (`T14,libero_90/35`).
    #[arg(long = "thumbnails-ahead", value_name = "SET", default_value = "all", env = "LIBERO_AGENT_THUMBNAILS_AHEAD")]
    pub ahead: String,
    /// How many thumbnails render at once in that background pass (default: a quarter of the CPUs, at least 1).
    #[arg(long = "thumbnail-threads", value_name = "N", value_parser = clap::value_parser!(u16).range(1..=64))]
    pub threads: Option<u16>,
}

impl ThumbnailArgs {
    /// None ahead (in-process servers of `run` and workers: nobody browses their Tasks page first).
    pub fn off() -> Self {
        Self { ahead: "off".into(), threads: None }
    }

    fn threads(&self) -> usize {
        self.threads.map(usize::from).unwrap_or_else(|| {
            std::thread::available_parallelism().map(|n| n.get() / 4).unwrap_or(1).clamp(1, 4)
        })
    }
}

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

/// A `--public-url` other machines can follow: `http(s)://` and at most 512 printable characters without spaces
/// or quotes (it is stored with every episode and shown as a link).
pub fn check_public_url(url: &str) -> anyhow::Result<()> {
    let ok = (url.starts_with("http://") || url.starts_with("https://"))
        && url.len() <= 512
        && url.chars().all(|c| c.is_ascii_graphic() && !matches!(c, '"' | '\'' | '<' | '>' | '\\'));
    if !ok {
        bail!("--public-url must be an http:// or https:// URL of at most 512 characters without spaces or quotes (got {url:?})");
    }
    Ok(())
}

/// Where the server looks for batches: `<data>/batches/` first, then the `--batches` directories.
pub fn batch_roots(data: &std::path::Path, extra: &[PathBuf]) -> Vec<PathBuf> {
    std::iter::once(data.join("batches")).chain(extra.iter().cloned()).collect()
}

pub fn default_data_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("LIBERO_AGENT_DATA") {
        return PathBuf::from(d);
    }
    let home = std::env::var_os("HOME").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("."));
    home.join(".local/share/libero-agent")
}

/// The server's shared state: the live episodes and the store that outlives them.
pub struct App {
    pub episodes: Arc<Episodes>,
    pub store: Store,
    /// The last state written to the store per episode, so only transitions cost a write.
    synced: Mutex<HashMap<String, EpisodeState>>,
    /// The progress last written to the store per open episode, so only changes cost a write.
    progressed: Mutex<HashMap<String, (u64, Option<(usize, usize)>)>>,
    /// Live events of the episodes this process runs, for the dashboard.
    pub hubs: Arc<live::LiveHubs>,
    pub operator: auth::Operator,
    /// The `Host` names this server answers to.
    pub hosts: auth::AllowedHosts,
    /// The task thumbnail cache (rendered ahead at start, or on demand).
    pub thumbnails: Arc<thumbnails::Thumbnails>,
    /// Where the Results page looks for batch directories ([`batch_roots`]).
    pub batch_roots: Vec<PathBuf>,
    /// Episodes the operator drives from the teleop page; only these accept actions from the operator's socket,
    /// so an agent's benchmark episode can never be steered from the dashboard.
    pub teleop: Mutex<HashMap<String, String>>,
    /// `--artifacts`: where run directories recorded on other machines are fetched from.
    pub artifacts: Option<libero_artifacts::Artifacts>,
    /// The browser console's routes, when this server has one.
    pub console: Option<Console>,
    /// Where other machines reach this server (`--public-url`, else its listening address), stored with every
    /// episode it prepares when it has a console (its live view).
    pub public_url: String,
}

pub type AppState = Arc<App>;

/// How often open episodes are checked for changes no call reports (wall-clock expiry while idle).
const STORE_SYNC_PERIOD: Duration = Duration::from_secs(1);

impl App {
    /// Writes `id`'s transition (started, ended) to the store if its state changed since the last write.
    pub async fn sync(&self, id: &str) {
        let Some(status) = self.episodes.status(id) else { return };
        let previous = self.synced.lock().ok().and_then(|m| m.get(id).copied());
        if previous != Some(status.state) {
            match self.write_transition(id, previous, &status).await {
                Ok(()) => {
                    if let Ok(mut m) = self.synced.lock() {
                        m.insert(id.to_owned(), status.state);
                    }
                    self.hubs.notify();
                }
                Err(e) => eprintln!("warning: {e:#}"),
            }
        }
        match status.state {
            EpisodeState::Active => self.sync_progress(id).await,
            EpisodeState::Finished | EpisodeState::Aborted => {
                if let Ok(mut m) = self.progressed.lock() {
                    m.remove(id);
                }
            }
            EpisodeState::Prepared => {}
        }
    }

    /// Writes an open episode's steps and stages to the store when they changed, for dashboards elsewhere.
    async fn sync_progress(&self, id: &str) {
        let Some(now) = self.hubs.get(id).and_then(|hub| hub.progress()) else { return };
        if self.progressed.lock().ok().and_then(|m| m.get(id).copied()) == Some(now) {
            return;
        }
        let stages = now.1.map(|(completed, required)| (completed as i64, required as i64));
        match self.store.record_progress(id, now.0 as i64, stages).await {
            Ok(()) => {
                if let Ok(mut m) = self.progressed.lock() {
                    m.insert(id.to_owned(), now);
                }
            }
            Err(e) => eprintln!("warning: {e}"),
        }
    }

    async fn write_transition(&self, id: &str, previous: Option<EpisodeState>, status: &EpisodeStatus) -> anyhow::Result<()> {
        // The initial observation exists exactly when start_episode succeeded.
        if status.latest_observation_id.is_some() && previous != Some(EpisodeState::Active) {
            self.store.mark_started(id, &utc_now_iso()).await?;
        }
        if matches!(status.state, EpisodeState::Finished | EpisodeState::Aborted) {
            let run = RunDir::new(self.episodes.runs_dir().join(id));
            if let Some(end) = EpisodeEnd::from_run(&run) {
                self.store.record_end(id, &end).await?;
            }
        }
        Ok(())
    }

    /// Stores a prepared episode's row. The run directory's record is written first; a row that cannot be
    /// stored is a failure of the preparation (the caller ends the episode), never a log line.
    pub async fn insert_prepared(&self, prepared: &episodes::Prepared) -> anyhow::Result<()> {
        let mut new = NewEpisode::from_record(&RunDir::new(&prepared.run_dir))
            .with_context(|| format!("episode {} has no readable episode record", prepared.episode_id))?;
        // Only a server with a console has a live view for other dashboards to link to.
        new.server_url = self.console.is_some().then(|| self.public_url.clone());
        self.store.insert_prepared(&new).await?;
        self.hubs.notify();
        Ok(())
    }

    /// Prepares an episode and stores its row; an episode whose row cannot be stored is stopped again.
    pub async fn prepare_stored(&self, req: PrepareRequest) -> ApiResult<episodes::Prepared> {
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
                    .downcast_ref::<episodes::BranchError>()
                    .and_then(|b| StatusCode::from_u16(b.http_status()).ok())
                    .unwrap_or(StatusCode::UNPROCESSABLE_ENTITY);
                return Err(ApiError::new(status, format!("{e:#}")));
            }
            Err(e) => return Err(ApiError::internal(format!("prepare failed: {e}"))),
        };
        if let Err(e) = self.insert_prepared(&prepared).await {
            let eps = self.episodes.clone();
            let id = prepared.episode_id.clone();
            let _ = tokio::task::spawn_blocking(move || eps.stop(&id, "the episode store refused its row")).await;
            return Err(ApiError::internal(format!("cannot store the episode: {e:#}")));
        }
        Ok(prepared)
    }

    /// Syncs every episode whose last stored state is not final.
    pub async fn sync_all(&self) {
        let open: Vec<String> = {
            let synced = self.synced.lock().map(|m| m.clone()).unwrap_or_default();
            self.episodes
                .ids()
                .into_iter()
                .filter(|id| !matches!(synced.get(id), Some(EpisodeState::Finished | EpisodeState::Aborted)))
                .collect()
        };
        for id in open {
            self.sync(&id).await;
        }
    }
}

/// Keeps the store in step: after every tool call (reported by the MCP handlers) and once a period.
async fn store_sync(app: Arc<App>, mut calls: UnboundedReceiver<String>) {
    let mut tick = tokio::time::interval(STORE_SYNC_PERIOD);
    loop {
        tokio::select! {
            id = calls.recv() => match id {
                Some(id) => app.sync(&id).await,
                None => return,
            },
            _ = tick.tick() => {
                app.sync_all().await;
                app.episodes.release_ended().await;
            }
        }
    }
}

/// How long a shutdown by signal waits for episode threads to record their end (and, after that, for open
/// connections): a stuck episode must not keep the process alive.
pub const SIGNAL_GRACE: Duration = Duration::from_secs(5);
/// How long a planned stop (a batch or bench that is done) waits for episode threads to finish their records
/// and private videos, which take tens of seconds to drain on a CPU renderer.
pub const DRAIN_GRACE: Duration = Duration::from_secs(600);

/// Runs the server until SIGINT/SIGTERM; unfinished episodes are then recorded as aborted (INVALID).
pub fn run_serve(args: ServeArgs) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    let result = runtime.block_on(serve(args));
    // A request still waiting on a stuck episode thread must not keep the process alive.
    runtime.shutdown_timeout(Duration::from_secs(1));
    result
}

pub async fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let shutdown = async { (shutdown_signal().await, SIGNAL_GRACE) };
    serve_until(args, |listening| println!("{listening}"), shutdown).await
}

/// An exclusive lock on a data directory, held while a server uses it: a second `serve` on the same
/// directory would otherwise record the first one's live episodes as interrupted.
pub struct DataLock {
    _file: std::fs::File,
}

impl DataLock {
    pub fn acquire(data: &std::path::Path) -> anyhow::Result<Self> {
        use std::io::{Read, Seek, Write};
        use std::os::unix::fs::OpenOptionsExt;
        let path = data.join("serve.lock");
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .mode(0o600)
            .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
            .open(&path)
            .with_context(|| format!("cannot open {}", path.display()))?;
        // SAFETY: flock on a descriptor this function owns.
        if unsafe { libc::flock(std::os::fd::AsRawFd::as_raw_fd(&file), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
            let mut holder = String::new();
            let _ = file.read_to_string(&mut holder);
            bail!(
                "another libero-agent server (pid {}) is using the data directory {}; stop it or pass another --data",
                holder.trim().parse::<u32>().map(|p| p.to_string()).unwrap_or_else(|_| "unknown".into()),
                data.display()
            );
        }
        file.set_len(0)?;
        file.seek(std::io::SeekFrom::Start(0))?;
        write!(file, "{}", std::process::id())?;
        Ok(Self { _file: file })
    }
}

/// The server: locks the data directory, binds, recovers interrupted episodes (files, then the store),
/// reports `listening` (the JSON line `serve` prints), serves until `shutdown` yields a stop reason and how long
/// to wait for the episodes, then records every open episode as aborted with it.
pub async fn serve_until(
    args: ServeArgs,
    listening: impl FnOnce(Value),
    shutdown: impl Future<Output = (String, Duration)> + Send + 'static,
) -> anyhow::Result<()> {
    let running = start(&args).await?;
    running.serve(listening, shutdown).await
}

/// A bound server, before it serves: its URL and operator token are known.
pub struct Bound {
    app: Arc<App>,
    /// The listener on the address asked for first, then its loopback twin ([`listener::bind`]).
    listeners: Vec<tokio::net::TcpListener>,
    limits: listener::Limits,
    base_url: String,
    recovered: usize,
    reconciled: u64,
    /// Tool-call reports for the store sync, which starts when serving begins.
    calls_rx: UnboundedReceiver<String>,
    /// Thumbnails to render in the background once serving begins, and how many at once.
    ahead: (Vec<String>, usize),
    _lock: DataLock,
    _registration: Option<credential::Registration>,
}

/// Locks the data directory, binds and opens everything a server needs.
pub async fn start(args: &ServeArgs) -> anyhow::Result<Bound> {
    let (flags, stores) = (&args.server, &args.stores);
    if let Some(url) = &flags.public_url {
        check_public_url(url)?;
    }
    // Descriptors for a flood of connections and for the episodes' own files, renders and store.
    let nofile = listener::raise_nofile_limit();
    let limits = args.limits.resolve(nofile)?;
    if limits.max_total < args.limits.max_connections {
        eprintln!(
            "libero-agent serve: at most {} connections (not {}): the file-descriptor limit is {nofile}, and a reserve stays \
             for the episodes",
            limits.max_total, args.limits.max_connections
        );
    }
    let data = flags.data.clone().unwrap_or_else(default_data_dir);
    std::fs::create_dir_all(&data).with_context(|| format!("cannot create data directory {}", data.display()))?;
    let lock = DataLock::acquire(&data)?;
    let mut operator = auth::Operator::for_server(&data, flags.operator_token_file.as_deref(), args.rotate_token)?;
    if let Some(console) = args.console {
        operator = operator.with_login_page(console.login_page);
    }
    let listeners = listener::bind(flags.addr).await?;
    let local = listeners.first().context("no listener")?.local_addr()?;
    let operator = operator.listening_on(local, Some(data.join(credential::TOKEN_FILE)));
    let base_url = format!("http://{local}");
    let registration = credential::Registration::register(local, operator.token());
    let (calls_tx, calls_rx) = unbounded_channel();
    let hubs = Arc::new(live::LiveHubs::default());
    let episodes = Arc::new(Episodes::new(data.clone(), base_url.clone())?.with_call_reports(calls_tx).with_live(hubs.clone()));
    let recovered = episodes.recover_interrupted();
    let rebuilding = episodes.rebuild_missing_videos();
    if rebuilding > 0 {
        eprintln!("libero-agent serve: rebuilding {rebuilding} private video(s) from their state records in the background");
    }
    let store = match &stores.store {
        Some(url) => Store::connect(url).await?,
        None => Store::open(&episodes.data_dir().join(STORE_FILE)).await?,
    };
    if store.backend() == store::Backend::Postgres {
        eprintln!("libero-agent serve: episode store {}", store::redact(stores.store.as_deref().unwrap_or_default()));
    }
    let reconciled = store.reconcile(&episodes.runs_dir()).await?;
    let artifacts = stores.artifacts.as_deref().map(libero_artifacts::Artifacts::open).transpose()?;
    if let Some(url) = stores.store.as_deref().filter(|_| store.backend() == store::Backend::Postgres) {
        follow_store_changes(url, hubs.clone()).await?;
    }
    // A bad `--thumbnails-ahead` stops the start; a server without a console renders none ahead.
    let ahead = match args.console {
        Some(_) => thumbnails::ahead_ids(&args.thumbnails.ahead).map_err(|e| anyhow::anyhow!("--thumbnails-ahead: {e}"))?,
        None => Vec::new(),
    };
    let ahead = (ahead, args.thumbnails.threads());
    let thumbnails = Arc::new(thumbnails::Thumbnails::new(episodes.clone()));
    let app = Arc::new(App {
        episodes,
        store,
        synced: Mutex::new(HashMap::new()),
        progressed: Mutex::new(HashMap::new()),
        hubs,
        operator,
        hosts: auth::AllowedHosts::new(local, &flags.public_hosts),
        thumbnails,
        batch_roots: batch_roots(&data, &args.batches),
        teleop: Mutex::new(HashMap::new()),
        artifacts,
        console: args.console,
        public_url: flags.public_url.as_deref().map(|u| u.trim_end_matches('/').to_owned()).unwrap_or_else(|| base_url.clone()),
    });
    Ok(Bound { app, listeners, limits, base_url, recovered, reconciled, calls_rx, ahead, _lock: lock, _registration: registration })
}

/// On a shared PostgreSQL store, every episode and queue change any machine makes (`LISTEN libero_episodes,
/// libero_queue`) refreshes this dashboard's episode list at once, as its own episodes' changes do.
async fn follow_store_changes(url: &str, hubs: Arc<live::LiveHubs>) -> anyhow::Result<()> {
    let mut listener = store::QueueListener::connect_to(url, &[store::EPISODE_CHANNEL, store::QUEUE_CHANNEL]).await?;
    tokio::spawn(async move {
        loop {
            if listener.wait(Duration::from_secs(60)).await.is_some() {
                hubs.notify();
            }
        }
    });
    Ok(())
}

impl Bound {
    pub fn url(&self) -> &str {
        &self.base_url
    }

    pub fn operator_token(&self) -> &str {
        self.app.operator.token()
    }

    /// Serves until `shutdown` yields a stop reason (see [`serve_until`]).
    pub async fn serve(self, listening: impl FnOnce(Value), shutdown: impl Future<Output = (String, Duration)> + Send + 'static) -> anyhow::Result<()> {
        let Bound { app, listeners, limits, base_url, recovered, reconciled, calls_rx, ahead, _lock, _registration } = self;
        let sync_task = tokio::spawn(store_sync(app.clone(), calls_rx));
        // started before `listening`, so whoever reads the line and asks /api/thumbnails sees the pass running
        let (ahead_ids, ahead_threads) = ahead;
        if !ahead_ids.is_empty() {
            tracing::info!(thumbnails = ahead_ids.len(), threads = ahead_threads, "rendering task thumbnails ahead in the background (low priority; cached ones are reused)");
            app.thumbnails.render_ahead(ahead_ids, ahead_threads);
        }
        let data = app.episodes.data_dir().to_path_buf();
        listening(json!({
            "event": "listening", "url": base_url, "data": data,
            "recovered_invalid_episodes": recovered, "store_rows_closed_at_start": reconciled,
            "dashboard": format!("{base_url}/"), "batch_roots": app.batch_roots,
            "operator_token_file": data.join(credential::TOKEN_FILE),
        }));
        let token_file = std::path::absolute(data.join(credential::TOKEN_FILE)).unwrap_or_else(|_| data.join(credential::TOKEN_FILE));
        match app.operator.new_login_code() {
            Ok(code) => eprintln!(
                "libero-agent serve: open the dashboard with this one-time login link (it works once; the operator token \
                 itself is in {}, and client commands of this user find it themselves):\n  {base_url}/?token={code}",
                token_file.display()
            ),
            Err(e) => eprintln!(
                "libero-agent serve: no login link this time ({e:#}); sign in at {base_url}/login with the token in {}",
                token_file.display()
            ),
        }
        let (stopped_tx, stopped_rx) = tokio::sync::oneshot::channel::<()>();
        let stop = {
            let app = app.clone();
            async move {
                let (reason, grace) = shutdown.await;
                let episodes = app.episodes.clone();
                let stuck = tokio::task::spawn_blocking(move || {
                    let stuck = episodes.stop_all(&reason, grace);
                    // The ended episodes' videos get the same grace; what is left is rebuilt at the next start.
                    let mut said: Option<(usize, std::time::Instant)> = None;
                    let done = episodes.wait_for_videos(grace, |pending, rate| {
                        if said.is_some_and(|(n, at)| n == pending && at.elapsed() < Duration::from_secs(10)) {
                            return;
                        }
                        said = Some((pending, std::time::Instant::now()));
                        let rate = rate.map(|r| format!(" at {r:.1} frames/s")).unwrap_or_default();
                        eprintln!("libero-agent serve: waiting for {pending} private video(s) to finish rendering{rate}");
                    });
                    if !done {
                        eprintln!("libero-agent serve: unfinished private videos will be rebuilt from their state records at the next start");
                    }
                    episodes.stop_videos();
                    stuck
                })
                .await
                .unwrap_or(0);
                if stuck > 0 {
                    eprintln!("warning: {stuck} episode thread(s) did not end within {grace:?}; stopping anyway");
                }
                let _ = stopped_tx.send(());
            }
        };
        let server = listener::serve(listeners, router(app.clone()), limits, stop);
        let grace_over = async {
            let _ = stopped_rx.await;
            tokio::time::sleep(SIGNAL_GRACE).await;
        };
        tokio::select! {
            () = server => {}
            () = grace_over => eprintln!("warning: requests still open {SIGNAL_GRACE:?} after the stop; closing them"),
        }
        sync_task.abort();
        app.sync_all().await;
        app.store.close().await;
        Ok(())
    }
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
    let mut compressed = Router::new()
        .route("/api/episodes", post(prepare).get(list_episodes))
        .route("/api/episodes/{id}", get(episode_status))
        .route("/api/episodes/{id}/video", get(episode_video))
        .route("/api/episodes/{id}/abort", post(abort_episode))
        .route("/api/episodes/{id}/forfeit", post(forfeit_episode))
        .route("/api/thumbnails", get(thumbnail_stats))
        .route("/api/episodes/{id}/agent/events", post(transcript::ingest))
        .route("/api/batches", post(batches::register));
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
        .route("/api/health", get(health))
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

/// `GET /api/thumbnails`: what the thumbnail cache rendered, reused and has left to render ahead.
async fn thumbnail_stats(State(app): State<AppState>) -> Response {
    axum::Json(json!({"ok": true, "thumbnails": app.thumbnails.stats()})).into_response()
}

async fn health(State(app): State<AppState>) -> Response {
    axum::Json(json!({"ok": true, "episodes": app.episodes.count(), "version": env!("CARGO_PKG_VERSION")})).into_response()
}

async fn prepare(State(app): State<AppState>, body: axum::body::Bytes) -> ApiResult {
    let req: PrepareRequest =
        serde_json::from_slice(&body).map_err(|e| ApiError::bad_request(format!("invalid prepare request: {e}")))?;
    let prepared = app.prepare_stored(req).await?;
    Ok((StatusCode::CREATED, axum::Json(prepared)).into_response())
}

/// A stored row for the API: no paths, plus the live state while this process serves the episode.
pub fn episode_json(app: &App, row: &store::EpisodeRow) -> Value {
    let mut v = row.public();
    if let (Some(live), Some(obj)) = (app.episodes.status(&row.episode.id), v.as_object_mut()) {
        obj.insert("state".into(), json!(live.state));
        obj.insert("accepted_agent_steps".into(), json!(live.accepted_agent_steps));
        obj.insert("latest_observation_id".into(), json!(live.latest_observation_id));
    }
    v
}

#[derive(serde::Deserialize)]
struct ListQuery {
    limit: Option<i64>,
}

/// Largest page of `GET /api/episodes`.
const MAX_LIST_LIMIT: i64 = 10_000;

async fn list_episodes(State(app): State<AppState>, Query(q): Query<ListQuery>) -> ApiResult {
    app.sync_all().await;
    let limit = q.limit.unwrap_or(1000).clamp(1, MAX_LIST_LIMIT);
    let rows = app.store.list(limit).await?;
    let episodes: Vec<Value> = rows.iter().map(|r| episode_json(&app, r)).collect();
    Ok(axum::Json(json!({"ok": true, "episodes": episodes})).into_response())
}

async fn episode_status(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult {
    app.sync(&id).await;
    let row = app.store.get(&id).await?.ok_or_else(|| ApiError::not_found(format!("no episode {id}")))?;
    Ok(axum::Json(episode_json(&app, &row)).into_response())
}

/// Whether the private video is there (`video`), and where its rendering stands (`video_status`: `state`
/// queued, rendering, ready or failed, `percent`, frames); `video_status` is null for an episode without one.
pub fn video_part(episodes: &Episodes, run: &RunDir) -> Value {
    let status = episodes.video_progress(run);
    let mut st = serde_json::to_value(&status).unwrap_or(Value::Null);
    if let (Some(obj), Some(p)) = (st.as_object_mut(), status.as_ref()) {
        obj.insert("percent".into(), json!(p.percent()));
    }
    json!({"video": status == Some(libero_episode::video_queue::VideoProgress::Ready), "video_status": st})
}

/// `GET /api/episodes/{id}/video`: [`video_part`] of a stored episode (what a worker waits on before uploading).
async fn episode_video(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult {
    let row = app.store.get(&id).await?.ok_or_else(|| ApiError::not_found(format!("no episode {id}")))?;
    let run = RunDir::new(row.episode.run_dir);
    let episodes = app.episodes.clone();
    let v = tokio::task::spawn_blocking(move || video_part(&episodes, &run))
        .await
        .map_err(|e| ApiError::internal(format!("video: {e}")))?;
    Ok(axum::Json(v).into_response())
}

#[derive(serde::Deserialize)]
struct AbortRequest {
    reason: String,
}

/// Ends an open episode as aborted (INVALID) with the caller's reason: the batch runner's answer to an agent
/// that exited or was killed before `finish_episode` without the sandbox (the original launcher killed its
/// server instead). A finished episode is left as it is.
async fn abort_episode(State(app): State<AppState>, Path(id): Path<String>, body: axum::body::Bytes) -> ApiResult {
    end_episode(app, id, body, false).await
}

/// `POST /api/episodes/{id}/forfeit {"reason": "…"}`: the runner's word that the agent's harness ended without
/// `finish_episode`. The episode ends as the agent's FAIL (never INVALID: nothing an agent does may earn it a
/// rerun); an episode that already ended is left as it is. Operator-only, as abort.
async fn forfeit_episode(State(app): State<AppState>, Path(id): Path<String>, body: axum::body::Bytes) -> ApiResult {
    end_episode(app, id, body, true).await
}

/// Abort or forfeit: the reason (at most 1000 characters kept), the ending on a blocking thread, the store synced.
async fn end_episode(app: AppState, id: String, body: axum::body::Bytes, forfeit: bool) -> ApiResult {
    let reason = match serde_json::from_slice::<AbortRequest>(&body) {
        Ok(r) if !r.reason.trim().is_empty() => r.reason.chars().take(1000).collect::<String>(),
        _ => return Err(ApiError::bad_request("body must be {\"reason\": \"…\"}")),
    };
    let eps = app.episodes.clone();
    let id2 = id.clone();
    let ended = tokio::task::spawn_blocking(move || if forfeit { eps.forfeit(&id2, &reason) } else { eps.stop(&id2, &reason) })
        .await
        .map_err(|e| ApiError::internal(format!("ending the episode failed: {e}")))?;
    if !ended {
        return Err(ApiError::not_found(format!("no open episode {id} on this server")));
    }
    app.sync(&id).await;
    episode_status(State(app), Path(id)).await
}

/// `Authorization: Bearer <token>`, if present.
pub fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers.get(header::AUTHORIZATION)?.to_str().ok()?.strip_prefix("Bearer ").map(str::trim)
}

/// The token check happens here, before rmcp sees any byte; unknown episode and wrong token look the same.
async fn mcp_endpoint(State(app): State<AppState>, Path(id): Path<String>, req: Request<Body>) -> Response {
    let Some(access) = app.episodes.mcp_access(&id, bearer(req.headers())) else {
        // The body is not read: close the connection so a keep-alive client never reuses it mid-body.
        return ApiError::unauthorized("missing or invalid episode token")
            .with_header(header::WWW_AUTHENTICATE, "Bearer")
            .with_header(header::CONNECTION, "close")
            .into_response();
    };
    mcp_gate::serve(access, &id, req).await
}
