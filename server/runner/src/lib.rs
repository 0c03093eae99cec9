//! `libero-agent run`: a benchmark batch. One fresh workspace, episode and agent process per rollout, run by
//! `--concurrency` workers against one server (in-process on 127.0.0.1:0 unless `--server`), each agent in a
//! bubblewrap sandbox, supervised against the episode's wall budget, classified per §4.8, with no automatic
//! retries. Progress goes to stderr; `batch.json` and `rollouts.jsonl` in the batch directory are what the
//! report and the dashboard read.
pub mod batch;
#[cfg(test)]
mod cli_checks;
pub mod harness;
pub mod harness_versions;
pub mod lines;
pub mod queue;
pub mod report;
pub mod rollout;
pub mod schedule;
pub mod transcript;
pub mod usage;
pub mod worker;

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{Context, bail};
use libero_records::batch_doc::{BatchCounts, BatchDoc, HarnessDoc, HarnessVersion, SandboxDoc, ToolboxDoc};
use libero_records::json::utc_now_iso;
use libero_episode::tools::{DEFAULT_WALL_TIME_S, MAX_AGENT_STEPS_CAP};
use libero_metrics::Outcome;
use libero_tasks::catalog::Catalog;
use libero_tasks::selector::{Member, Selection, Term};
use serde_json::{Value, json};

use batch::{BatchSettings, append_record, write_batch_json};
use libero_report::batch::{BATCH_SCHEMA, RolloutRecord, read_records};
use harness::{Credentials, Harness, default_credentials_file};
use schedule::{Experiment, PlannedRollout, plan, plan_pool};

use libero_sandbox::resources;
use libero_sandbox::sandbox::Sandbox;
use libero_sandbox::toolbox::{self, Toolbox, ToolboxChoice};
use libero_server::client::InProcessServer;

/// Set by SIGINT/SIGTERM: stop scheduling, stop running agents, record them INTERRUPTED.
pub static INTERRUPTED: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_: libc::c_int) {
    INTERRUPTED.store(true, Ordering::SeqCst);
}

#[derive(clap::Args, Debug, Clone)]
pub struct RunArgs {
    /// main_table: T01–T30 at level 3; manip_observation: T11–T20 at levels 1 and 2; context: T21–T30 with
    /// video and video+trajectory demonstrations; pool: any tasks of the pool at level 3, reported per suite.
    #[arg(long, value_enum)]
    pub experiment: Experiment,
    #[arg(long, value_enum)]
    pub harness: Harness,
    /// Run this version of the harness's CLI (e.g. `0.154.0` for Codex, `2.1.139` for Claude Code: the paper's), found
    /// installed apart in the cache (`python3 scripts/setup.py --harnesses`), in the tests' install or on PATH; an
    /// error lists the installed versions when it is not there. Default: the command on PATH. Each rollout records
    /// the version it ran.
    #[arg(long, value_name = "VERSION")]
    pub harness_version: Option<String>,
    /// The model id, always explicit (for `command` it labels the agent in reports).
    #[arg(long)]
    pub model: String,
    /// Reasoning effort where the harness supports it.
    #[arg(long, default_value = "high", value_parser = ["low", "medium", "high"])]
    pub effort: String,
    /// Rollouts at once in a local run (default 1).
    #[arg(long)]
    pub concurrency: Option<usize>,
    /// Only these tasks, a task selection (docs/commands.md, "Selecting tasks"): `T11,T13`, `release`, `match:TEXT`
    /// (default: every implemented task of the experiment). With `--experiment pool` also `all`, `stock`, a suite
    /// (`robomemarena`), `group:long_horizon` and pool entries (`libero_90/35`, `libero_90/<name>`; see `tasks list
    /// --tasks all`); default every entry that runs.
    #[arg(long, value_delimiter = ',')]
    pub tasks: Vec<String>,
    /// Rollouts per task and condition.
    #[arg(long, default_value_t = 3)]
    pub reps: u32,
    /// Batch directory (default: ./agent_runs/batch_<UTC time>).
    #[arg(long)]
    pub batch: Option<PathBuf>,
    /// Print the schedule and launch nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// With --dry-run: one JSON object per rollout on stdout.
    #[arg(long, requires = "dry_run")]
    pub json: bool,
    /// Continue an existing batch: finished rollouts are skipped, changed settings refused.
    #[arg(long)]
    pub resume: bool,
    /// The agent of `--harness command`; `{workspace}`, `{prompt_file}`, `{mcp_config}`, `{mcp_url}`, `{model}`
    /// and `{libero_agent}` expand to shell-quoted words; run by /bin/sh in the workspace.
    #[arg(long)]
    pub agent_cmd: Option<String>,
    /// A running `libero-agent serve` (default: a server in this process on 127.0.0.1:0).
    #[arg(long)]
    pub server: Option<String>,
    /// Data directory of the in-process server (default: <batch>/server).
    #[arg(long)]
    pub data: Option<PathBuf>,
    #[command(flatten)]
    pub paths: LocalPaths,
    #[arg(long, default_value_t = 100)]
    pub seed: u64,
    #[arg(long, default_value_t = DEFAULT_WALL_TIME_S)]
    pub wall_time_s: f64,
    #[arg(long, default_value_t = MAX_AGENT_STEPS_CAP)]
    pub max_agent_steps: u64,
    /// Run agents without the bubblewrap sandbox (they can then read everything this user can), and without
    /// per-rollout resource caps.
    #[arg(long)]
    pub no_sandbox: bool,
    #[command(flatten)]
    pub resources: resources::ResourceArgs,
    /// The agent's Python, shown read-only in the sandbox at /opt/libero-toolbox and first on its PATH as
    /// python3/python/pip: a directory laid out as a venv over a python3 the sandbox shows (`bin/python3`,
    /// `lib/python3.X/site-packages`), or `none` for the system's python3 alone. Default: the project's (numpy,
    /// scipy, Pillow, OpenCV, imageio; assets/third_party.lock.json), installed into the cache on first use.
    #[arg(long, value_name = "PATH|none")]
    pub toolbox: Option<ToolboxChoice>,
    /// The store. `postgres://…`: the batch is queued there (`--batch` is then its name) and run by
    /// `libero-agent worker`s on any machine, while this command follows its progress. `sqlite://PATH` (or
    /// `--local`): the batch runs here and is also written to the store as it changes, for `report --store URL
    /// NAME` on any machine (named by its directory's name).
    #[arg(long, value_name = "URL")]
    pub store: Option<String>,
    /// With a queue store: enqueue and return (workers run it; `report --store` reads it).
    #[arg(long)]
    pub detach: bool,
    /// With a PostgreSQL store: run here, mirroring the batch to the store, instead of queueing it.
    #[arg(long)]
    pub local: bool,
}

impl RunArgs {
    /// The store URL of a queued batch: a PostgreSQL store without `--local`.
    fn queue_store(&self) -> anyhow::Result<Option<&str>> {
        let Some(url) = self.store.as_deref() else { return Ok(None) };
        Ok((libero_store::Backend::of_url(url)? == libero_store::Backend::Postgres && !self.local).then_some(url))
    }
}

/// SIGINT/SIGTERM set [`INTERRUPTED`].
pub(crate) fn install_signal_handlers() {
    // SAFETY: installing an async-signal-safe handler that only stores to an atomic.
    unsafe {
        libc::signal(libc::SIGINT, on_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_signal as *const () as libc::sighandler_t);
    }
}

/// Where this machine puts agent workspaces and keeps API credentials (`run` and `worker`).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct LocalPaths {
    /// Where workspaces are created. `run`: this directory, or a fresh `<batch name>-<random>` in it when a
    /// workspace of an earlier batch is in the way (default: a fresh `$TMPDIR/libero-agent-workspaces/<batch
    /// name>-<random>`). `worker`: a fresh `<batch>/a<attempt>-<random>` in it per batch attempt (default
    /// `$TMPDIR/libero-agent-workspaces`).
    #[arg(long)]
    pub workspace_root: Option<PathBuf>,
    /// API credentials (APIKEY=…, APIURL=…), outside every workspace (default ~/.config/libero-agent/credentials).
    #[arg(long)]
    pub credentials_file: Option<PathBuf>,
}

impl LocalPaths {
    /// The directory workspaces go under (absolute; `<TMPDIR>/libero-agent-workspaces` by default).
    pub fn workspace_base(&self) -> anyhow::Result<PathBuf> {
        match &self.workspace_root {
            Some(w) => absolute(w),
            None => absolute(&std::env::temp_dir().join("libero-agent-workspaces")),
        }
    }

    pub fn credentials_file(&self) -> PathBuf {
        self.credentials_file.clone().unwrap_or_else(default_credentials_file)
    }
}

/// What every rollout of a batch shares.
pub struct RunContext {
    pub batch_dir: PathBuf,
    pub workspace_root: PathBuf,
    pub server_url: String,
    pub settings: BatchSettings,
    pub harness: Harness,
    pub credentials: Option<Credentials>,
    pub sandbox: Option<Sandbox>,
    pub harness_version: Value,
    pub self_exe: PathBuf,
    /// The harness's pinned npm CLI is installed: launched directly, not through `npx`.
    pub npm_cli_installed: bool,
    /// `--harness-version`'s executable ([`harness_versions::resolve`]), launched instead of the command on PATH.
    pub cli_path: Option<PathBuf>,
    /// `--store`: the batch is written there after every change too.
    pub store: Option<batch::StoreMirror>,
    /// The batch's name, as its episodes carry it on the server (a queued batch's name, else its directory's).
    pub batch_name: String,
    /// `--server`: the batch is registered with that server after every change, for its Results page.
    pub server_mirror: Option<Mutex<batch::ServerMirror>>,
}

impl RunContext {
    /// The batch directory's `batch.json` rewritten (and the store updated, with `--store`).
    fn write_batch(&self, v: &Value) -> anyhow::Result<()> {
        write_batch_json(&self.batch_dir, v)?;
        self.sync_store()
    }

    /// One ended rollout appended (and the store updated, with `--store`).
    fn append(&self, rec: &RolloutRecord) -> anyhow::Result<()> {
        append_record(&self.batch_dir, rec)?;
        self.sync_store()
    }

    fn sync_store(&self) -> anyhow::Result<()> {
        if let Some(m) = &self.store {
            m.sync(&self.batch_dir).context("writing the batch to --store")?;
        }
        if let Some(m) = &self.server_mirror {
            m.lock().map_err(|_| anyhow::anyhow!("server mirror poisoned"))?.sync(&self.batch_dir)?;
        }
        Ok(())
    }
}

fn parse_tasks(tasks: &[String], catalog: &Catalog) -> anyhow::Result<Vec<u32>> {
    if tasks.iter().all(|t| t.trim().is_empty()) {
        return Ok(Vec::new());
    }
    let selection = Selection::from_parts(tasks)?;
    if let Some(t) = selection.terms().iter().find(|t| !matches!(t, Term::Release | Term::ReleaseTask(_) | Term::Match(_))) {
        bail!("{:?} is a pool selector: pool tasks run with --experiment pool", t.to_string());
    }
    let pool = libero_tasks::pool::Pool::discover()?;
    let picks = selection.resolve(catalog.tasks(), &pool)?;
    // A set leaves out what is not implemented (as the default does); a task named alone is checked by `plan`.
    let numbers = picks.iter().filter_map(|p| match p.member {
        Member::Release(t) if p.named || t.implemented => Some(t.number),
        _ => None,
    });
    Ok(numbers.collect())
}

/// The schedule of `args`, the tasks left out, and the `--tasks` as the settings record them.
fn schedule_of(args: &RunArgs, catalog: &Catalog) -> anyhow::Result<(Vec<PlannedRollout>, Vec<String>, Vec<u32>, Vec<String>)> {
    if args.experiment == Experiment::Pool {
        let selectors: Vec<String> = args.tasks.iter().map(|t| t.trim().to_owned()).filter(|t| !t.is_empty()).collect();
        if let Some(long) = selectors.iter().find(|t| t.len() > 200) {
            bail!("--tasks entry of {} bytes: at most 200", long.len());
        }
        let pool = libero_tasks::pool::Pool::discover()?;
        let (schedule, skipped) = plan_pool(&pool, catalog.tasks(), &selectors, args.reps)?;
        return Ok((schedule, skipped, Vec::new(), selectors));
    }
    let only = parse_tasks(&args.tasks, catalog)?;
    let (schedule, skipped) = plan(args.experiment, catalog.tasks(), (!only.is_empty()).then_some(&only[..]), args.reps)?;
    Ok((schedule, skipped, only, Vec::new()))
}

fn settings_of(args: &RunArgs, tasks: &[u32], pool_tasks: &[String]) -> BatchSettings {
    BatchSettings {
        experiment: args.experiment.as_str().to_owned(),
        harness: args.harness.as_str().to_owned(),
        harness_version: args.harness_version.clone(),
        model: args.model.clone(),
        effort: args.effort.clone(),
        reps: args.reps,
        tasks: tasks.to_vec(),
        pool_tasks: pool_tasks.to_vec(),
        seed: args.seed,
        wall_time_s: args.wall_time_s,
        max_agent_steps: args.max_agent_steps,
        agent_cmd: args.agent_cmd.clone(),
        sandbox: !args.no_sandbox,
    }
}

/// The batch's `harness.version`: `<program> --version` of the CLI its rollouts launch ([`harness_versions::probe_cli`]),
/// all null for `command`.
pub(crate) fn probe_version(harness: Harness, npm_cli_installed: bool, cli_path: Option<&Path>) -> Value {
    match harness_versions::probe_cli(harness, npm_cli_installed, cli_path) {
        Some(v) => v.to_value(),
        None => json!({"requested": null, "observed": null, "probe_output": null}),
    }
}

/// `--harness-version`'s executable, resolved on this machine (`None` without the flag), said on stderr.
pub(crate) fn cli_path_of(harness: Harness, version: Option<&str>) -> anyhow::Result<Option<PathBuf>> {
    let Some(version) = version else { return Ok(None) };
    let path = harness_versions::resolve_here(harness, version)?;
    eprintln!("{} {version}: {}", harness.as_str(), path.display());
    Ok(Some(path))
}

/// `numpy 1.26.4, scipy 1.14.1, …` for the progress line.
fn package_list(t: &Toolbox) -> String {
    t.packages.iter().map(|p| format!("{} {}", p.name, p.version)).collect::<Vec<_>>().join(", ")
}

pub(crate) fn default_batch_dir() -> PathBuf {
    let stamp: String = utc_now_iso()[..19].chars().filter(|c| c.is_ascii_digit() || *c == 'T').collect();
    PathBuf::from("agent_runs").join(format!("batch_{stamp}Z"))
}

pub(crate) fn absolute(p: &Path) -> anyhow::Result<PathBuf> {
    Ok(if p.is_absolute() { p.to_path_buf() } else { std::env::current_dir()?.join(p) })
}

/// A new directory `<base>/<stem>-<random>` (created here, so no other run or worker has it).
pub(crate) fn fresh_dir(base: &Path, stem: &str) -> anyhow::Result<PathBuf> {
    std::fs::create_dir_all(base).with_context(|| format!("cannot create {}", base.display()))?;
    loop {
        let dir = base.join(format!("{stem}-{}", &libero_records::json::random_name("")?[..8]));
        match std::fs::create_dir(&dir) {
            Ok(()) => return Ok(dir),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e).with_context(|| format!("cannot create {}", dir.display())),
        }
    }
}

/// Where a local run's workspaces go (`<root>/<rollout id>` each): `--workspace-root` itself unless a workspace
/// of a rollout to run is already there (left by an earlier batch of the same name), else a fresh
/// `<batch name>-<random>` directory in it (always, without `--workspace-root`). A batch never fails on what an
/// earlier one left.
fn run_workspace_root(paths: &LocalPaths, batch: &str, todo: &VecDeque<PlannedRollout>) -> anyhow::Result<PathBuf> {
    let base = paths.workspace_base()?;
    if paths.workspace_root.is_some() {
        let leftover = todo.iter().find(|r| std::fs::symlink_metadata(base.join(&r.rollout_id)).is_ok());
        let Some(leftover) = leftover else {
            std::fs::create_dir_all(&base).with_context(|| format!("cannot create {}", base.display()))?;
            return Ok(base);
        };
        let dir = fresh_dir(&base, batch)?;
        eprintln!(
            "{} already holds {} (an earlier batch's workspace): this batch's workspaces go to {}",
            base.display(),
            leftover.rollout_id,
            dir.display()
        );
        return Ok(dir);
    }
    fresh_dir(&base, batch)
}

/// `GET /api/health` of `--server`, answered within seconds, before anything is scheduled: a batch never starts
/// against a server that is not there (each rollout would end INVALID).
pub(crate) fn check_server(url: &str) -> anyhow::Result<()> {
    use libero_server::http_client::{HttpUrl, request};
    use std::net::{TcpStream, ToSocketAddrs};
    let base = url.trim_end_matches('/');
    let health = HttpUrl::parse(&format!("{base}/api/health")).with_context(|| format!("--server {url}"))?;
    let addrs: Vec<std::net::SocketAddr> = health
        .host_port
        .to_socket_addrs()
        .with_context(|| format!("--server {url}: cannot resolve {}", health.host_port))?
        .collect();
    if !addrs.iter().any(|a| TcpStream::connect_timeout(a, Duration::from_secs(5)).is_ok()) {
        bail!(
            "--server {url}: nothing answers at {} (is `libero-agent serve` running there? without --server the batch \
             runs its own server)",
            health.host_port
        );
    }
    let resp = request("GET", &health, &[], b"", Duration::from_secs(15))
        .with_context(|| format!("--server {url}: GET /api/health failed"))?;
    let v: Value = serde_json::from_slice(&resp.body).unwrap_or(Value::Null);
    if resp.status != 200 || v["ok"] != true {
        bail!("--server {url} is not a libero-agent server: GET /api/health answered HTTP {} {}", resp.status,
            String::from_utf8_lossy(&resp.body).chars().take(200).collect::<String>());
    }
    Ok(())
}

/// Live counts for the terminal and `batch.json`.
struct Progress {
    total: usize,
    done: usize,
    running: BTreeSet<String>,
    outcomes: BTreeMap<Outcome, usize>,
}

impl Progress {
    fn line(&self) -> String {
        let o: Vec<String> = self.outcomes.iter().map(|(k, v)| format!("{} {v}", k.as_str())).collect();
        format!(
            "[{} done, {} running, {} left] {}",
            self.done,
            self.running.len(),
            self.total - self.done - self.running.len(),
            if o.is_empty() { "no outcomes yet".to_owned() } else { o.join(", ") }
        )
    }
}

/// `batch.json` of the batch now.
fn batch_value(ctx: &RunContext, status: &str, created_at: &str, p: &Progress, skipped: &[String]) -> Value {
    let toolbox = ctx.sandbox.as_ref().and_then(|s| s.toolbox.as_ref()).map(|t| ToolboxDoc::from_value(t.describe()).unwrap_or_default());
    BatchDoc {
        schema_version: Some(BATCH_SCHEMA.into()),
        created_at: Some(created_at.into()),
        updated_at: Some(utc_now_iso()),
        status: Some(status.into()),
        settings: Some(ctx.settings.doc()),
        settings_sha256: Some(ctx.settings.sha256()),
        harness: Some(HarnessDoc {
            name: Some(ctx.harness.as_str().into()),
            version: Some(HarnessVersion::from_value(ctx.harness_version.clone()).ok()),
            ..Default::default()
        }),
        sandbox: Some(ctx.sandbox.as_ref().map(|s| SandboxDoc {
            kind: Some("bubblewrap".into()),
            version: Some(s.version.clone()),
            resources: Some(s.resources.as_ref().and_then(|r| serde_json::from_value(r.describe()).ok())),
            ..Default::default()
        })),
        toolbox: Some(toolbox),
        server_url: Some(Some(ctx.server_url.clone())),
        workspace_root: Some(Some(ctx.workspace_root.to_string_lossy().into_owned())),
        max_outer_retries: Some(0),
        rollout_count: Some(p.total as u64),
        skipped_unimplemented_tasks: Some(skipped.to_vec()),
        counts: Some(BatchCounts {
            done: Some(p.done as u64),
            running: Some(p.running.len() as u64),
            left: Some((p.total - p.done - p.running.len()) as u64),
            ..Default::default()
        }),
        running: Some(p.running.iter().cloned().collect()),
        outcomes: Some(p.outcomes.iter().map(|(k, v)| (k.as_str().to_owned(), *v as u64)).collect()),
        ..Default::default()
    }
    .to_value()
}

/// The `libero-agent` binary a rollout's `{libero_agent}` and the `mcp-stdio` relay run (and the sandbox shows):
/// this executable, or for `libero-worker` (which has neither the reference agent nor the relay) the
/// `libero-agent` installed beside it.
pub fn agent_exe() -> anyhow::Result<PathBuf> {
    let me = std::env::current_exe().context("cannot find this executable")?;
    if me.file_name().is_some_and(|n| n == "libero-agent") {
        return Ok(me);
    }
    let beside = me.with_file_name("libero-agent");
    if beside.is_file() {
        return Ok(beside);
    }
    bail!("{} runs agents through libero-agent ({{libero_agent}}, the mcp-stdio relay), expected at {}", me.display(), beside.display())
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let queue_store = check_args(&args)?;
    let catalog = Catalog::discover()?;
    let (schedule, skipped, only, pool_tasks) = schedule_of(&args, &catalog)?;
    if !skipped.is_empty() {
        eprintln!(
            "left out, {} tasks that do not run in this build (`libero-agent tasks show <task>` says why): {}",
            skipped.len(),
            skipped.join(", ")
        );
    }
    if args.dry_run {
        return print_dry_run(&args, &schedule);
    }
    if schedule.is_empty() {
        bail!("nothing to run");
    }
    let settings = settings_of(&args, &only, &pool_tasks);
    if let Some(url) = queue_store {
        return queue::enqueue_and_follow(&args, url, &schedule, &skipped, &settings);
    }
    // The CLI version asked for is installed here, or nothing starts (a queued batch's workers resolve it each).
    let cli_path = cli_path_of(args.harness, args.harness_version.as_deref())?;
    if let Some(url) = &args.server {
        check_server(url)?;
    }
    // A store that cannot be opened stops the run before anything is written or launched.
    let store = args.store.as_deref().map(batch::StoreMirror::connect).transpose()?;
    let batch_dir = absolute(&args.batch.clone().unwrap_or_else(default_batch_dir))?;
    let (created_at, done_records) = open_batch_dir(&args, &batch_dir, &settings)?;
    let credentials = credentials_of(&args)?;
    let sandbox = sandbox_of(&args)?;
    let batch_name = batch_dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "batch".into());
    if let Some(c) = &credentials
        && (c.source.starts_with(args.paths.workspace_base()?) || c.source.starts_with(&batch_dir))
    {
        bail!("the credentials file must lie outside the workspaces and the batch directory");
    }
    let self_exe = agent_exe()?;
    let npm_cli_installed = harness::pinned_npm_cli_installed(args.harness);
    let harness_version = probe_version(args.harness, npm_cli_installed, cli_path.as_deref());
    let (todo, progress) = rollouts_to_run(&batch_dir, &schedule, &done_records)?;
    let workspace_root = run_workspace_root(&args.paths, &batch_name, &todo)?;
    // The in-process server lives as long as the batch.
    let (server, server_url) = start_server(&args, &batch_dir)?;
    let ctx = Arc::new(RunContext {
        batch_dir: batch_dir.clone(),
        workspace_root,
        server_url,
        settings,
        harness: args.harness,
        credentials,
        sandbox,
        harness_version,
        self_exe,
        npm_cli_installed,
        cli_path,
        store,
        batch_name: batch_name.clone(),
        server_mirror: args.server.as_deref().map(|url| Mutex::new(batch::ServerMirror::new(url))),
    });
    install_signal_handlers();
    let skipped = Arc::new(skipped);
    ctx.write_batch(&batch_value(&ctx, "running", &created_at, &progress, &skipped))?;
    eprintln!("batch {} — {}", batch_dir.display(), progress.line());
    if let Some(url) = args.server.as_deref() {
        eprintln!("registered with {url}: its Results page lists the batch as it runs");
    }
    tracing::info!(
        batch = batch_name,
        dir = %batch_dir.display(),
        experiment = ctx.settings.experiment,
        harness = ctx.settings.harness,
        model = ctx.settings.model,
        rollouts = progress.total,
        to_run = progress.total - progress.done,
        concurrency = args.concurrency.unwrap_or(1),
        server = ctx.server_url,
        "batch started"
    );
    let batch = Batch { ctx, created_at, skipped, state: Arc::new(Mutex::new(progress)) };
    let failure = batch.run_workers(todo, args.concurrency.unwrap_or(1));
    if let Some(s) = server {
        // Give the store a moment to record the last transitions, then stop.
        std::thread::sleep(Duration::from_millis(200));
        // Interrupted: exit within seconds; done: wait for every episode's records and video.
        if INTERRUPTED.load(Ordering::SeqCst) { s.stop_now()? } else { s.stop()? };
    }
    batch.finish(failure, &schedule)
}

/// The arguments' own checks, before anything is read; returns the queue store of a queued batch.
fn check_args(args: &RunArgs) -> anyhow::Result<Option<&str>> {
    if args.concurrency == Some(0) {
        bail!("--concurrency must be at least 1");
    }
    let queue_store = args.queue_store()?;
    if args.detach && queue_store.is_none() {
        bail!("--detach needs a queue store (--store postgres://… without --local)");
    }
    if args.model.trim().is_empty() {
        bail!("--model must name the model");
    }
    if args.harness.runs_agent_cmd() != args.agent_cmd.is_some() {
        bail!("--agent-cmd is required with --harness command and only allowed with it");
    }
    if args.harness_version.is_some() && args.harness.command().is_none() {
        bail!("--harness-version picks a version of an agent CLI; --harness command runs --agent-cmd, which has none");
    }
    Ok(queue_store)
}

/// `--dry-run`: the schedule on stdout (JSON lines with `--json`), nothing launched.
fn print_dry_run(args: &RunArgs, schedule: &[PlannedRollout]) -> anyhow::Result<()> {
    for r in schedule {
        if args.json {
            println!("{}", serde_json::to_string(r)?);
        } else {
            println!("{:<30} {:<18} {:<40} level {} demo {}", r.rollout_id, r.task, r.task_name, r.level, r.demo.as_str());
        }
    }
    if !args.json {
        eprintln!("{} rollouts ({} experiment, {} × {} reps); nothing launched", schedule.len(), args.experiment.as_str(),
            args.harness.as_str(), args.reps);
    }
    Ok(())
}

/// The batch directory made, or with `--resume` the batch there continued (its settings unchanged): when the
/// batch was created, and the records of its ended rollouts.
fn open_batch_dir(args: &RunArgs, batch_dir: &Path, settings: &BatchSettings) -> anyhow::Result<(String, Vec<RolloutRecord>)> {
    let existing = libero_report::batch::batch_json(batch_dir);
    if !existing.is_file() {
        std::fs::create_dir_all(batch_dir)?;
        return Ok((utc_now_iso(), Vec::new()));
    }
    if !args.resume {
        bail!("{} already holds a batch; pass --resume to continue it", batch_dir.display());
    }
    let old: Value = serde_json::from_str(&std::fs::read_to_string(&existing)?)?;
    let old = BatchDoc::from_value(old).unwrap_or_default();
    if old.settings_sha256 != Some(settings.sha256()) {
        bail!(
            "--resume refuses changed settings: the batch was started with {}, now {}",
            json!(old.settings),
            serde_json::to_value(settings)?
        );
    }
    Ok((old.created_at.unwrap_or_default(), read_records(batch_dir)?))
}

/// The API credentials: the credentials file's for a harness that needs them, and for a `command` agent that talks
/// to a model (its API through the runner's gateway, like every harness) when a file is given.
fn credentials_of(args: &RunArgs) -> anyhow::Result<Option<Credentials>> {
    if args.harness.needs_credentials() {
        let path = args.paths.credentials_file();
        Ok(Some(Credentials::load(&path)?))
    } else if let Some(path) = &args.paths.credentials_file {
        Ok(Some(Credentials::load(path)?))
    } else {
        Ok(None)
    }
}

/// The agents' sandbox with its resources and toolbox (said on stderr); none with `--no-sandbox`.
fn sandbox_of(args: &RunArgs) -> anyhow::Result<Option<Sandbox>> {
    if args.no_sandbox {
        eprintln!("warning: --no-sandbox: agents run without isolation and can read every file this user can");
        if matches!(args.toolbox, Some(ToolboxChoice::Path(_))) {
            bail!("--toolbox is shown inside the sandbox; with --no-sandbox the agent runs the host's own python3");
        }
        return Ok(None);
    }
    let sandbox = Sandbox::detect()?.with_resources(resources::Resources::detect(&args.resources)?);
    let toolbox = toolbox::resolve(args.toolbox.as_ref())?;
    match &toolbox {
        Some(t) => eprintln!("the agents' toolbox: {} at {} ({})", t.name, toolbox::INSIDE, package_list(t)),
        None => eprintln!("no toolbox: agents run the system's python3 alone"),
    }
    Ok(Some(sandbox.with_toolbox(toolbox)))
}

/// The rollouts of `schedule` still to run and the progress so far. Rollouts with a directory but no record were
/// running when an earlier runner died: recorded INTERRUPTED here, never retried.
fn rollouts_to_run(batch_dir: &Path, schedule: &[PlannedRollout], done_records: &[RolloutRecord]) -> anyhow::Result<(VecDeque<PlannedRollout>, Progress)> {
    let mut finished: BTreeSet<String> = done_records.iter().map(|r| r.rollout_id.clone()).collect();
    for r in schedule {
        if !finished.contains(&r.rollout_id) && batch_dir.join("rollouts").join(&r.rollout_id).exists() {
            let rec = interrupted_record(r);
            append_record(batch_dir, &rec)?;
            finished.insert(r.rollout_id.clone());
        }
    }
    let records_so_far = read_records(batch_dir)?;
    let mut outcomes = BTreeMap::new();
    for r in records_so_far.iter().filter(|r| schedule.iter().any(|s| s.rollout_id == r.rollout_id)) {
        *outcomes.entry(r.outcome).or_insert(0) += 1;
    }
    let todo: VecDeque<PlannedRollout> = schedule.iter().filter(|r| !finished.contains(&r.rollout_id)).cloned().collect();
    let progress = Progress { total: schedule.len(), done: schedule.len() - todo.len(), running: BTreeSet::new(), outcomes };
    Ok((todo, progress))
}

/// The server the batch's episodes run on: `--server`, else one in this process (stopped with the batch) with
/// its data in `--data` or the batch directory.
fn start_server(args: &RunArgs, batch_dir: &Path) -> anyhow::Result<(Option<InProcessServer>, String)> {
    Ok(match &args.server {
        Some(url) => (None, url.trim_end_matches('/').to_owned()),
        None => {
            let data = absolute(&args.data.clone().unwrap_or_else(|| batch_dir.join("server")))?;
            let s = InProcessServer::start(data, "batch_runner_stopped_before_finish")?;
            let url = s.url.clone();
            (Some(s), url)
        }
    })
}

/// A running batch: its context, when it was created, what was left out, and its progress.
struct Batch {
    ctx: Arc<RunContext>,
    created_at: String,
    skipped: Arc<Vec<String>>,
    state: Arc<Mutex<Progress>>,
}

impl Batch {
    /// `concurrency` workers take rollouts off `todo` until it is empty or the runner is interrupted, each rollout's
    /// record appended and `batch.json` rewritten as it starts and ends. Returns the first worker's failure.
    fn run_workers(&self, todo: VecDeque<PlannedRollout>, concurrency: usize) -> Option<anyhow::Error> {
        let queue = Arc::new(Mutex::new(todo));
        let workers: Vec<_> = (0..concurrency)
            .map(|_| {
                let (ctx, queue, state, skipped, created_at) =
                    (self.ctx.clone(), queue.clone(), self.state.clone(), self.skipped.clone(), self.created_at.clone());
                let batch_name = self.ctx.batch_name.clone();
                std::thread::spawn(move || -> anyhow::Result<()> {
                    loop {
                        if INTERRUPTED.load(Ordering::SeqCst) {
                            return Ok(());
                        }
                        let Some(next) = queue.lock().map_err(|_| anyhow::anyhow!("queue poisoned"))?.pop_front() else {
                            return Ok(());
                        };
                        {
                            let mut p = state.lock().map_err(|_| anyhow::anyhow!("progress poisoned"))?;
                            p.running.insert(next.rollout_id.clone());
                            ctx.write_batch(&batch_value(&ctx, "running", &created_at, &p, &skipped))?;
                            eprintln!("{}: started — {}", next.rollout_id, p.line());
                        }
                        let mut rec = rollout::run_rollout(&ctx, &next);
                        rec.ensure_reason();
                        let mut p = state.lock().map_err(|_| anyhow::anyhow!("progress poisoned"))?;
                        ctx.append(&rec)?;
                        p.running.remove(&rec.rollout_id);
                        p.done += 1;
                        *p.outcomes.entry(rec.outcome).or_insert(0) += 1;
                        ctx.write_batch(&batch_value(&ctx, "running", &created_at, &p, &skipped))?;
                        let why = rec.reason().map(|e| format!(" ({e})")).unwrap_or_default();
                        eprintln!("{}: {}{why} — {}", rec.rollout_id, rec.outcome.as_str(), p.line());
                        log_rollout_end(&ctx.settings.model, &batch_name, &rec);
                    }
                })
            })
            .collect();
        let mut failure = None;
        for w in workers {
            match w.join() {
                Ok(Ok(())) => {}
                Ok(Err(e)) => failure = Some(e),
                Err(_) => failure = Some(anyhow::anyhow!("a worker panicked")),
            }
        }
        failure
    }

    /// `batch.json`'s last state (stopped or finished), said on stderr and in the log; then the run's error if it
    /// failed, was interrupted, or none of its rollouts ran (a failure of the run, not a result), else where to look.
    fn finish(&self, failure: Option<anyhow::Error>, schedule: &[PlannedRollout]) -> anyhow::Result<()> {
        let ctx = &self.ctx;
        let batch_name = &ctx.batch_name;
        let p = self.state.lock().map_err(|_| anyhow::anyhow!("progress poisoned"))?;
        let stopped = INTERRUPTED.load(Ordering::SeqCst) || failure.is_some();
        ctx.write_batch(&batch_value(ctx, if stopped { "stopped" } else { "finished" }, &self.created_at, &p, &self.skipped))?;
        eprintln!("batch {}: {}", if stopped { "stopped" } else { "finished" }, p.line());
        let outcomes: Vec<String> = p.outcomes.iter().map(|(k, v)| format!("{}={v}", k.as_str())).collect();
        tracing::info!(
            batch = batch_name,
            status = if stopped { "stopped" } else { "finished" },
            done = p.done,
            rollouts = p.total,
            outcomes = outcomes.join(" "),
            error = failure.as_ref().map(|e| format!("{e:#}")),
            "batch ended"
        );
        if let Some(e) = failure {
            return Err(e);
        }
        if stopped {
            bail!("interrupted; `--resume` continues the batch (interrupted rollouts are not retried)");
        }
        // A batch none of whose rollouts ran is a failure of the run, not a result.
        print_where_to_look(ctx, &ctx.batch_dir);
        let records = read_records(&ctx.batch_dir)?;
        let ours = records.iter().filter(|r| schedule.iter().any(|s| s.rollout_id == r.rollout_id));
        if let Some(msg) = batch::all_invalid_message(batch_name, ours.map(|r| (r.rollout_id.as_str(), r.outcome.as_str(), r.reason()))) {
            bail!("{msg}");
        }
        Ok(())
    }
}

/// Where the ended batch can be seen: the Results page of `--server` (which has it registered), else how to
/// show it on one, and the `report` command. Printed on stderr with the progress.
fn print_where_to_look(ctx: &RunContext, batch_dir: &Path) {
    let dir = harness::shell_quote(&batch_dir.to_string_lossy());
    match &ctx.server_mirror {
        Some(m) => {
            if let Ok(m) = m.lock() {
                eprintln!("results: {}", m.results_url(&ctx.batch_name));
            }
        }
        None => {
            let parent = batch_dir.parent().map(|p| harness::shell_quote(&p.to_string_lossy())).unwrap_or_else(|| dir.clone());
            eprintln!("results: not on any server yet (run it with --server URL, or `libero-agent serve --batches {parent}`)");
        }
    }
    eprintln!("report: libero-agent report {dir}");
}

/// The log line of an ended rollout (`run` and workers): info for an outcome of the agent's, a warning with its
/// reason for an INVALID, WATCHDOG_TIMEOUT or INTERRUPTED one.
pub(crate) fn log_rollout_end(model: &str, batch: &str, rec: &RolloutRecord) {
    let reason = rec.reason();
    macro_rules! line {
        ($level:ident) => {
            tracing::$level!(
                batch,
                rollout_id = rec.rollout_id,
                task = rec.task,
                level = rec.level,
                model,
                outcome = rec.outcome.as_str(),
                reason = reason.as_deref(),
                episode_id = rec.episode_id.as_deref(),
                steps = rec.accepted_agent_steps,
                wall_time_s = rec.wall_time_s.map(|s| (s * 1000.0).round() / 1000.0),
                worker = rec.worker.as_deref(),
                "rollout ended"
            )
        };
    }
    if reason.is_some() {
        line!(warn);
    } else {
        line!(info);
    }
}

fn interrupted_record(r: &PlannedRollout) -> RolloutRecord {
    let mut rec = RolloutRecord::from(r);
    rec.outcome = Outcome::Interrupted;
    rec.infrastructure_error = Some("an earlier runner stopped while this rollout ran (found at --resume)".into());
    rec
}
