//! `libero-agent worker`: runs queued rollouts on this machine. It claims rollouts from the store's queue
//! (`--slots` at a time), holds each with a lease its heartbeat renews, and runs each as `run` does locally: a
//! fresh workspace, an episode on this worker's own server (recorded in the shared store, so every dashboard
//! lists it) and the agent in its sandbox. When the rollout ended and the episode's video is written, the run
//! directory and the runner's files go to the artifact store, then the record to the store. A worker that dies
//! loses its leases: the next worker or follower to look closes those rollouts INVALID (`worker_lost`); nothing is
//! retried unless `run --resume` asks. SIGINT/SIGTERM: claim nothing more, end the running rollouts INTERRUPTED.
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use libero_artifacts::Artifacts;
use libero_records::batch_doc::{BatchDoc, RolloutSummary};
use libero_store::{QueueListener, Store};
use serde_json::{Value, json};

use libero_report::batch::RolloutRecord;

use super::batch::BatchSettings;
use super::harness::{Credentials, Harness, pinned_npm_cli_installed};
use super::queue::{WORKER_LOST, worker_lost_record};
use libero_sandbox::sandbox::Sandbox;
use super::schedule::PlannedRollout;
use super::{INTERRUPTED, RunContext};
use libero_server::{ServeArgs, ServerFlags, StoreFlags};
use libero_server::client::{InProcessServer, wait_for_video};

/// How long a rollout's video may take to be written before its files are uploaded without it.
const VIDEO_WAIT: Duration = Duration::from_secs(600);

/// The store, artifact and server flags are `serve`'s own ([`StoreFlags`], [`ServerFlags`]); a worker needs
/// both stores, and its server takes any free port unless told one.
#[derive(clap::Args, Debug, Clone)]
#[command(mut_arg("store", |a| a.required(true)), mut_arg("artifacts", |a| a.required(true)))]
#[command(mut_arg("addr", |a| a.default_value("127.0.0.1:0")))]
pub struct WorkerArgs {
    #[command(flatten)]
    pub stores: StoreFlags,
    /// Rollouts this machine runs at once.
    #[arg(long, default_value_t = 1)]
    pub slots: usize,
    #[command(flatten)]
    pub server: ServerFlags,
    #[command(flatten)]
    pub paths: super::LocalPaths,
    #[command(flatten)]
    pub resources: libero_sandbox::resources::ResourceArgs,
    /// The lease on a claimed rollout, renewed every third of it: a worker silent for this long is lost.
    #[arg(long, default_value_t = 60.0)]
    pub lease_s: f64,
    /// Exit once nothing is queued and this worker's rollouts ended (default: wait for more work).
    #[arg(long)]
    pub exit_when_idle: bool,
    /// The browser console the worker's server serves (set by the binary; never from the command line).
    #[arg(skip)]
    pub console: Option<libero_server::Console>,
}

/// What every slot of the worker shares.
struct Worker {
    id: String,
    store: Store,
    artifacts: Artifacts,
    runtime: tokio::runtime::Handle,
    server_url: String,
    data: PathBuf,
    workspace_root: PathBuf,
    credentials_file: PathBuf,
    /// Per-rollout caps, detected once (`None`: `--unconfined-resources` where they cannot be enforced).
    resources: Option<libero_sandbox::resources::Resources>,
    lease_ms: i64,
    /// The run context of each (batch, attempt): settings, harness, sandbox, credentials.
    contexts: Mutex<HashMap<(String, i64), Arc<RunContext>>>,
    busy: AtomicUsize,
}

pub fn run(args: WorkerArgs) -> anyhow::Result<()> {
    if args.slots == 0 || args.slots > 64 {
        bail!("--slots must be 1 to 64");
    }
    if !(2.0..=3600.0).contains(&args.lease_s) {
        bail!("--lease-s must be 2 to 3600 seconds");
    }
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname").map(|h| h.trim().to_owned()).unwrap_or_else(|_| "unknown".into());
    let id = format!("{host}-{}-{}", std::process::id(), &libero_records::json::random_name("")?[..6]);
    // Both are required on the command line; a caller building the arguments itself is told the same.
    let store_url = args.stores.store.clone().context("a worker needs --store (or $LIBERO_AGENT_STORE)")?;
    let artifacts_url = args.stores.artifacts.as_deref().context("a worker needs --artifacts (or $LIBERO_AGENT_ARTIFACTS)")?;
    // Before anything is registered: a worker that cannot cap its agents says so and starts nothing.
    let resources = libero_sandbox::resources::Resources::detect(&args.resources)?;
    let data = match &args.server.data {
        Some(d) => super::absolute(d)?,
        None => default_worker_dir(&id)?,
    };
    std::fs::create_dir_all(&data).with_context(|| format!("cannot create the worker's directory {}", data.display()))?;
    let artifacts = Artifacts::open(artifacts_url)?;
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let store = runtime.block_on(Store::connect(&store_url))?;
    let serve_args = ServeArgs {
        server: ServerFlags { data: Some(data.join("server")), ..args.server.clone() },
        rotate_token: false,
        batches: vec![],
        // The worker uploads to the artifact store itself; its server reads run directories from its own disk.
        stores: StoreFlags { store: Some(store_url.clone()), artifacts: None },
        limits: libero_server::listener::ConnLimits::default(),
        console: args.console,
        thumbnails: libero_server::ThumbnailArgs::off(),
        teleop_abandon_s: libero_server::args::DEFAULT_TELEOP_ABANDON_S,
    };
    let has_console = serve_args.console.is_some();
    let server = InProcessServer::start_args(serve_args, "worker_stopped_before_finish")?;
    // Without a console (`libero-worker`) there is no live view to link to.
    let live_url = has_console.then(|| args.server.public_url.clone().unwrap_or_else(|| server.url.clone()));
    runtime.block_on(store.register_worker(&id, &host, args.slots as i64, live_url.as_deref()))?;
    let workspace_base = args.paths.workspace_base()?;
    eprintln!(
        "worker {id}: {} slot(s), store {}, artifacts {}, server {}, data {}, workspaces {}",
        args.slots,
        libero_store::redact(&store_url),
        artifacts.url(),
        server.url,
        data.display(),
        workspace_base.display()
    );
    tracing::info!(
        worker = id,
        slots = args.slots,
        store = libero_store::redact(&store_url),
        artifacts = artifacts.url(),
        server = server.url,
        data = %data.display(),
        workspaces = %workspace_base.display(),
        "worker registered"
    );
    super::install_signal_handlers();
    let worker = Arc::new(Worker {
        id,
        store,
        artifacts,
        runtime: runtime.handle().clone(),
        server_url: server.url.clone(),
        workspace_root: workspace_base,
        data,
        credentials_file: args.paths.credentials_file(),
        resources,
        lease_ms: (args.lease_s * 1000.0) as i64,
        contexts: Mutex::new(HashMap::new()),
        busy: AtomicUsize::new(0),
    });
    let stop = Arc::new(AtomicBool::new(false));
    let heartbeat = {
        let (w, stop) = (worker.clone(), stop.clone());
        std::thread::spawn(move || {
            let period = Duration::from_millis((w.lease_ms / 3).max(500) as u64);
            while !stop.load(Ordering::SeqCst) {
                if let Err(e) = w.runtime.block_on(w.store.heartbeat(&w.id, w.lease_ms)) {
                    tracing::warn!(worker = w.id, error = format!("{e:#}"), "heartbeat failed (the leases run out if this lasts)");
                }
                let t = Instant::now();
                while t.elapsed() < period && !stop.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(100));
                }
            }
        })
    };
    let slots: Vec<_> = (0..args.slots)
        .map(|_| {
            let (w, url, exit_when_idle) = (worker.clone(), store_url.clone(), args.exit_when_idle);
            std::thread::spawn(move || w.slot(&url, exit_when_idle))
        })
        .collect();
    let mut failure = None;
    for s in slots {
        match s.join() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => failure = Some(e),
            Err(_) => failure = Some(anyhow::anyhow!("a worker slot panicked")),
        }
    }
    stop.store(true, Ordering::SeqCst);
    let _ = heartbeat.join();
    if INTERRUPTED.load(Ordering::SeqCst) { server.stop_now()? } else { server.stop()? };
    eprintln!("worker {}: stopped", worker.id);
    tracing::info!(worker = worker.id, error = failure.as_ref().map(|e| format!("{e:#}")), "worker stopped");
    failure.map_or(Ok(()), Err)
}

impl Worker {
    /// One slot: close lost rollouts, claim one, run it; wait for work when the queue is empty.
    fn slot(&self, url: &str, exit_when_idle: bool) -> anyhow::Result<()> {
        // In the runtime's context until the listener is dropped: its connection is closed by a task it spawns.
        let _in_runtime = self.runtime.enter();
        let mut listener = self.runtime.block_on(QueueListener::connect(url))?;
        loop {
            if INTERRUPTED.load(Ordering::SeqCst) {
                return Ok(());
            }
            for (batch, id) in self.runtime.block_on(self.store.expire_lost(worker_lost_record))? {
                eprintln!("{batch}/{id}: INVALID ({WORKER_LOST})");
                tracing::warn!(worker = self.id, batch, rollout_id = id, outcome = "INVALID", reason = WORKER_LOST, "rollout closed: its worker was lost");
            }
            let Some(job) = self.runtime.block_on(self.store.claim(&self.id, self.lease_ms))? else {
                if exit_when_idle && self.busy.load(Ordering::SeqCst) == 0 {
                    return Ok(());
                }
                self.runtime.block_on(listener.wait(Duration::from_secs(2)));
                continue;
            };
            tracing::info!(worker = self.id, batch = job.batch, rollout_id = job.rollout_id, attempt = job.attempts, "rollout claimed");
            self.busy.fetch_add(1, Ordering::SeqCst);
            let ended = self.run_job(&job);
            self.busy.fetch_sub(1, Ordering::SeqCst);
            if let Err(e) = ended {
                tracing::error!(worker = self.id, batch = job.batch, rollout_id = job.rollout_id, error = format!("{e:#}"), "rollout not finished");
            }
        }
    }

    fn run_job(&self, job: &libero_store::Job) -> anyhow::Result<()> {
        eprintln!("{}/{}: started on {}", job.batch, job.rollout_id, self.id);
        let mut rec = match serde_json::from_value::<PlannedRollout>(job.plan.clone()).context("the queued plan is not a rollout") {
            Ok(plan) => match self.context(&job.batch, job.attempts) {
                Ok(ctx) => {
                    let mut rec = super::rollout::run_rollout(&ctx, &plan);
                    rec.ensure_reason();
                    self.upload(&ctx, job, &mut rec);
                    self.clean_up(&ctx, job, &rec);
                    rec
                }
                Err(e) => failed(&plan, format!("the worker cannot run this batch: {e:#}")),
            },
            Err(e) => {
                let mut v = worker_lost_record(&job.plan);
                v["termination_reason"] = Value::Null;
                v["infrastructure_error"] = json!(format!("{e:#}"));
                return self.finish(job, &v);
            }
        };
        rec.worker = Some(self.id.clone());
        self.finish(job, &serde_json::to_value(&rec)?)
    }

    fn finish(&self, job: &libero_store::Job, record: &Value) -> anyhow::Result<()> {
        if self.runtime.block_on(self.store.finish(&job.batch, &job.rollout_id, &self.id, record))? {
            // A lost worker's record is partial: only the fields every record has are read.
            let r = RolloutSummary::from_value(record.clone()).unwrap_or_default();
            let why = r.infrastructure_error.as_deref().or(r.termination_reason.as_deref());
            let outcome = r.outcome.as_deref().unwrap_or("?");
            match why {
                Some(why) if outcome != "SUCCESS" && outcome != "FAIL" => eprintln!("{}/{}: {outcome} ({why})", job.batch, job.rollout_id),
                _ => eprintln!("{}/{}: {outcome}", job.batch, job.rollout_id),
            }
            let reason = why.filter(|_| !matches!(outcome, "SUCCESS" | "FAIL" | "SIM_TIMEOUT"));
            macro_rules! line {
                ($level:ident) => {
                    tracing::$level!(
                        worker = self.id,
                        batch = job.batch,
                        rollout_id = job.rollout_id,
                        task = r.task.as_deref(),
                        level = r.level,
                        outcome,
                        reason,
                        episode_id = r.episode_id.as_deref(),
                        steps = r.accepted_agent_steps,
                        wall_time_s = r.wall_time_s.map(|s| (s * 1000.0).round() / 1000.0),
                        artifacts = r.artifacts.as_deref(),
                        "rollout ended"
                    )
                };
            }
            if reason.is_some() {
                line!(warn);
            } else {
                line!(info);
            }
        } else {
            eprintln!("{}/{}: this worker lost its lease meanwhile; the rollout was closed as {WORKER_LOST} and this record is dropped", job.batch, job.rollout_id);
            tracing::warn!(worker = self.id, batch = job.batch, rollout_id = job.rollout_id, "lease lost meanwhile: the rollout was closed as {WORKER_LOST} and this record is dropped");
        }
        Ok(())
    }

    /// The run context of a batch's attempt: its settings from the store, this machine's sandbox and
    /// credentials. Each attempt gets directories of its own, fresh in this process (`a<N>-<random>`), so a
    /// re-queued rollout never meets the files of its first attempt, nor a batch those of an earlier batch of the
    /// same name (a fresh database numbers attempts from 1 again).
    fn context(&self, batch: &str, attempt: i64) -> anyhow::Result<Arc<RunContext>> {
        let key = (batch.to_owned(), attempt);
        if let Some(ctx) = self.contexts.lock().map_err(|_| anyhow::anyhow!("poisoned"))?.get(&key) {
            return Ok(ctx.clone());
        }
        let stored = self.runtime.block_on(self.store.batch(batch))?.with_context(|| format!("no batch {batch} in the store"))?;
        let doc = BatchDoc::from_value(stored.doc).unwrap_or_default();
        let settings: BatchSettings = serde_json::from_value(json!(doc.settings)).context("the batch's settings")?;
        let harness: Harness = serde_json::from_value(json!(settings.harness)).context("the batch's harness")?;
        let credentials = if harness.needs_credentials() { Some(Credentials::load(&self.credentials_file)?) } else { None };
        // the project's toolbox, as `run` gives its agents by default (installed on first use)
        let sandbox = match settings.sandbox {
            true => Some(Sandbox::detect()?.with_toolbox(Some(libero_sandbox::toolbox::ensure_project()?)).with_resources(self.resources.clone())),
            false => None,
        };
        let npm_cli_installed = pinned_npm_cli_installed(harness);
        // The batch's `--harness-version`, installed on this machine (else each of its rollouts here is INVALID, why said).
        let cli_path = super::cli_path_of(harness, settings.harness_version.as_deref())?;
        let name = libero_artifacts::check_name(batch)?;
        let attempt_dir = super::fresh_dir(&self.data.join("batches").join(name), &format!("a{attempt}"))?;
        let unique = attempt_dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| format!("a{attempt}"));
        let ctx = Arc::new(RunContext {
            batch_dir: attempt_dir,
            workspace_root: self.workspace_root.join(name).join(&unique),
            server_url: self.server_url.clone(),
            harness_version: super::probe_version(harness, npm_cli_installed, cli_path.as_deref()),
            settings,
            harness,
            credentials,
            sandbox,
            self_exe: super::agent_exe()?,
            npm_cli_installed,
            cli_path,
            store: None,
            // The batch is in the shared store already (every dashboard on it lists it); episodes carry its name.
            batch_name: batch.to_owned(),
            server_mirror: None,
        });
        std::fs::create_dir_all(&ctx.workspace_root)?;
        std::fs::create_dir_all(ctx.batch_dir.join("rollouts"))?;
        self.contexts.lock().map_err(|_| anyhow::anyhow!("poisoned"))?.insert(key, ctx.clone());
        Ok(ctx)
    }

    /// The episode's run directory (once its video is written) and the runner's own files of the rollout (not the
    /// agent's session home) to the artifact store; the record says where, or why not.
    fn upload(&self, ctx: &RunContext, job: &libero_store::Job, rec: &mut RolloutRecord) {
        let (Some(episode), Some(run_dir)) = (rec.episode_id.clone(), rec.run_dir.clone()) else { return };
        if !INTERRUPTED.load(Ordering::SeqCst)
            && let Err(e) = wait_for_video(&self.server_url, &episode, VIDEO_WAIT)
        {
            tracing::warn!(batch = job.batch, rollout_id = job.rollout_id, episode_id = episode, error = format!("{e:#}"), "uploading without a finished video");
        }
        let rollout_dir = ctx.batch_dir.join("rollouts").join(&job.rollout_id);
        let uploaded = self.runtime.block_on(async {
            let run_prefix = libero_artifacts::run_prefix(&episode)?;
            self.artifacts.put_run(&run_dir, &run_prefix, |_| true).await?;
            let files_prefix = libero_artifacts::rollout_prefix(&job.batch, &job.rollout_id)?;
            self.artifacts.put_run(&rollout_dir, &files_prefix, |rel| rel.parent() == Some(Path::new("")) && rel != Path::new("home")).await?;
            Ok::<_, libero_artifacts::ArtifactError>(run_prefix)
        });
        match uploaded {
            Ok(prefix) => rec.artifacts = Some(format!("{}/{prefix}", self.artifacts.url().trim_end_matches('/'))),
            Err(e) => tracing::error!(
                batch = job.batch,
                rollout_id = job.rollout_id,
                run_dir = %run_dir.display(),
                error = %e,
                "upload failed: the rollout's files stay on this worker"
            ),
        }
    }
}

impl Worker {
    /// Removes what the agent left on this machine once its files are uploaded: the workspace and the session
    /// home (never uploaded), however deep, following no link ([`libero_episode::dirfd::remove_at`]). Only paths inside this
    /// worker's own directories are touched.
    fn clean_up(&self, ctx: &RunContext, job: &libero_store::Job, rec: &RolloutRecord) {
        let home = ctx.batch_dir.join("rollouts").join(&job.rollout_id).join("home");
        let workspace = rec.workspace.clone().filter(|w| w.starts_with(&ctx.workspace_root) && w != &ctx.workspace_root);
        for path in [Some(home), workspace].into_iter().flatten() {
            // A capped rollout's home and workspace went with its disk.
            if let Err(e) = remove_path(&path).or_else(|e| if e.kind() == std::io::ErrorKind::NotFound { Ok(()) } else { Err(e) }) {
                tracing::warn!(batch = job.batch, rollout_id = job.rollout_id, path = %path.display(), error = %e, "cannot remove the rollout's files");
            }
        }
    }
}

/// Removes `path` and everything below it through its parent's directory handle, following no link.
fn remove_path(path: &Path) -> std::io::Result<()> {
    use std::os::fd::AsFd;
    let (Some(parent), Some(name)) = (path.parent(), path.file_name().and_then(|n| n.to_str())) else {
        return Err(std::io::Error::other(format!("{}: no parent or no UTF-8 name", path.display())));
    };
    let dir = libero_episode::dirfd::open_dir_path(parent)?;
    libero_episode::dirfd::remove_at(dir.as_fd(), name)
}

/// `<data dir>/workers/<worker id>`: a directory of this worker's own (`~/.local/share/libero-agent/workers/…`).
fn default_worker_dir(id: &str) -> anyhow::Result<PathBuf> {
    let name: String = id.chars().map(|c| if c.is_ascii_alphanumeric() || "-_.".contains(c) { c } else { '_' }).collect();
    super::absolute(&libero_server::default_data_dir().join("workers").join(name))
}

/// A rollout the worker could not start (INVALID, with why).
fn failed(plan: &PlannedRollout, why: String) -> RolloutRecord {
    let mut rec = RolloutRecord::from(plan);
    rec.infrastructure_error = Some(why);
    rec
}
