//! Starting and stopping a server: the data directory's lock, binding, recovering interrupted episodes, the
//! store writer and the housekeeping tasks, serving until a stop, and the drain that records every open episode.
use std::collections::HashMap;
use std::future::Future;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{Context, bail};
use libero_episode::lifecycle::EpisodeSet;

use crate::app::App;
use crate::args::{ServeArgs, batch_roots, check_public_url, default_data_dir};
use crate::episodes::Episodes;
use crate::router::router;
use libero_store::{STORE_FILE, Store};
use crate::{auth, credential, listener, live, store_writer, thumbnails};

/// How often ended episodes are looked at for release.
const RELEASE_PERIOD: Duration = Duration::from_secs(1);

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
    serve_until(args, |listening| println!("{}", serde_json::to_string(&listening).unwrap_or_default()), shutdown).await
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

/// The line `serve` prints once it listens (a JSON object; the keys in the order it always printed them), what
/// scripts and benches wait for and read the server's URL and data directory from.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Listening {
    pub batch_roots: Vec<PathBuf>,
    pub dashboard: String,
    pub data: PathBuf,
    /// Always `listening`.
    pub event: String,
    pub operator_token_file: PathBuf,
    /// Episodes found open in the run directories at start, recorded as aborted (INVALID).
    pub recovered_invalid_episodes: usize,
    /// Store rows still open at start, closed from their run directories.
    pub store_rows_closed_at_start: u64,
    pub url: String,
}

/// The server: locks the data directory, binds, recovers interrupted episodes (files, then the store),
/// reports `listening` (the JSON line `serve` prints), serves until `shutdown` yields a stop reason and how long
/// to wait for the episodes, then records every open episode as aborted with it.
pub async fn serve_until(
    args: ServeArgs,
    listening: impl FnOnce(Listening),
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
    /// The store writer's queue; the writer starts when serving begins.
    inbox: store_writer::Inbox,
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
    let (writer, inbox) = store_writer::channel();
    let hubs = Arc::new(live::LiveHubs::default());
    let set = EpisodeSet::new(data.clone(), base_url.clone())?.with_live(hubs.clone()).with_events(writer.events());
    let episodes = Arc::new(Episodes::from(set));
    let recovered = episodes.lifecycle().recover_interrupted();
    let rebuilding = episodes.lifecycle().rebuild_missing_videos();
    if rebuilding > 0 {
        eprintln!("libero-agent serve: rebuilding {rebuilding} private video(s) from their state records in the background");
    }
    let store = match &stores.store {
        Some(url) => Store::connect(url).await?,
        None => Store::open(&episodes.lifecycle().data_dir().join(STORE_FILE)).await?,
    };
    if store.backend() == libero_store::Backend::Postgres {
        eprintln!("libero-agent serve: episode store {}", libero_store::redact(stores.store.as_deref().unwrap_or_default()));
    }
    let reconciled = store.reconcile(&episodes.lifecycle().runs_dir()).await?;
    let artifacts = stores.artifacts.as_deref().map(libero_artifacts::Artifacts::open).transpose()?;
    if let Some(url) = stores.store.as_deref().filter(|_| store.backend() == libero_store::Backend::Postgres) {
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
        writer,
        hubs,
        operator,
        hosts: auth::AllowedHosts::new(local, &flags.public_hosts),
        thumbnails,
        batch_roots: batch_roots(&data, &args.batches),
        teleop: Mutex::new(HashMap::new()),
        teleop_abandon_after: Duration::from_secs(args.teleop_abandon_s),
        artifacts,
        console: args.console,
        public_url: flags.public_url.as_deref().map(|u| u.trim_end_matches('/').to_owned()).unwrap_or_else(|| base_url.clone()),
    });
    Ok(Bound { app, listeners, limits, base_url, recovered, reconciled, inbox, ahead, _lock: lock, _registration: registration })
}

/// Lets go of ended episodes' sessions, live views and memory, once a period.
async fn release_ended(episodes: Arc<Episodes>) {
    let mut tick = tokio::time::interval(RELEASE_PERIOD);
    loop {
        tick.tick().await;
        episodes.release_ended().await;
    }
}

/// On a shared PostgreSQL store, every episode and queue change any machine makes (`LISTEN libero_episodes,
/// libero_queue`) refreshes this dashboard's episode list at once, as its own episodes' changes do.
async fn follow_store_changes(url: &str, hubs: Arc<live::LiveHubs>) -> anyhow::Result<()> {
    let mut listener = libero_store::QueueListener::connect_to(url, &[libero_store::EPISODE_CHANNEL, libero_store::QUEUE_CHANNEL]).await?;
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

    /// The server without its listeners: the same [`router`] `serve` runs, over this server's state, with the store
    /// writer and the release of ended episodes running on the current runtime. Requests are answered by calling
    /// the router (`tower::ServiceExt::oneshot`: `libero-testkit`'s in-process client); they must name the bound
    /// address as their `Host`. No thumbnails are rendered ahead. The data directory stays locked, and the
    /// background tasks run, until the [`InProcess`] drops.
    pub fn in_process(self) -> InProcess {
        let Bound { app, listeners, base_url, inbox, _lock, _registration, .. } = self;
        drop(listeners);
        let tasks = vec![
            tokio::spawn(store_writer::run(inbox, app.store.clone(), app.episodes.clone(), app.hubs.clone())),
            tokio::spawn(release_ended(app.episodes.clone())),
        ];
        InProcess { router: router(app.clone()), app, base_url, tasks, _lock, _registration }
    }

    /// Serves until `shutdown` yields a stop reason (see [`serve_until`]).
    pub async fn serve(self, listening: impl FnOnce(Listening), shutdown: impl Future<Output = (String, Duration)> + Send + 'static) -> anyhow::Result<()> {
        let Bound { app, listeners, limits, base_url, recovered, reconciled, inbox, ahead, _lock, _registration } = self;
        let writer_task = tokio::spawn(store_writer::run(inbox, app.store.clone(), app.episodes.clone(), app.hubs.clone()));
        let release_task = tokio::spawn(release_ended(app.episodes.clone()));
        // started before `listening`, so whoever reads the line and asks /api/thumbnails sees the pass running
        let (ahead_ids, ahead_threads) = ahead;
        if !ahead_ids.is_empty() {
            tracing::info!(thumbnails = ahead_ids.len(), threads = ahead_threads, "rendering task thumbnails ahead in the background (low priority; cached ones are reused)");
            app.thumbnails.render_ahead(ahead_ids, ahead_threads);
        }
        let data = app.episodes.lifecycle().data_dir().to_path_buf();
        listening(Listening {
            batch_roots: app.batch_roots.clone(),
            dashboard: format!("{base_url}/"),
            operator_token_file: data.join(credential::TOKEN_FILE),
            data: data.clone(),
            event: "listening".into(),
            recovered_invalid_episodes: recovered,
            store_rows_closed_at_start: reconciled,
            url: base_url.clone(),
        });
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
                    let stuck = episodes.lifecycle().stop_all(&reason, grace);
                    // The ended episodes' videos get the same grace; what is left is rebuilt at the next start.
                    let mut said: Option<(usize, std::time::Instant)> = None;
                    let done = episodes.lifecycle().wait_for_videos(grace, |pending, rate| {
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
                    episodes.lifecycle().stop_videos();
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
        release_task.abort();
        app.sync_all().await;
        writer_task.abort();
        app.store.close().await;
        Ok(())
    }
}

/// A server answering in process ([`Bound::in_process`]).
pub struct InProcess {
    /// The full router, the console's routes included where the server has one.
    pub router: axum::Router,
    pub app: Arc<App>,
    /// The bound address's URL (`http://127.0.0.1:PORT`): requests name its host as their `Host`.
    pub base_url: String,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    _lock: DataLock,
    _registration: Option<credential::Registration>,
}

impl InProcess {
    /// Stops every open episode (recorded as aborted with `reason`) and writes their rows.
    pub async fn stop(&self, reason: &str) {
        let episodes = self.app.episodes.clone();
        let reason = reason.to_owned();
        let _ = tokio::task::spawn_blocking(move || episodes.lifecycle().stop_all(&reason, SIGNAL_GRACE)).await;
        self.app.sync_all().await;
    }
}

impl Drop for InProcess {
    fn drop(&mut self) {
        for task in &self.tasks {
            task.abort();
        }
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
