//! The server's episodes: preparing one (ids, token, private run directory, workspace, actor thread),
//! looking one up for a request (token check), and the records' life across restarts.
use std::collections::{BTreeMap, HashMap};
use std::fs;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use libero_episode::demo::record::{BundleSummary, RecordOptions, SourceEpisode};
use libero_episode::demo::library::TargetEpisode;
use libero_episode::demo::{DemoCondition, LayoutVariant, layout_from_json, library, project_bundle, record_bundle, verify_bundle};
use libero_episode::expert_run::run_expert;
use libero_episode::json::{utc_now_iso, write_json_file};
use libero_episode::physics::WorldSpec as PhysicsSpec;
use libero_episode::records::{aborted_result, read_result, write_result};
use libero_episode::task::{TaskSource, resolve_task};
use libero_episode::tools::{DEFAULT_WALL_TIME_S, MAX_AGENT_STEPS_CAP};
use libero_episode::workspace::{DemoNotice, WorkspaceContract, WorkspaceLayout, create_workspace};
use libero_episode::video_queue::{VideoJob, VideoProgress, VideoQueue};
use libero_episode::world::{LiberoWorld, WorldSpec, head_wrist_cameras};
use libero_episode::{EpisodeConfig, EpisodeHandle, EpisodeState, EpisodeStatus, Level, RunDir, spawn_episode_live};
use libero_render::Renderer;
use libero_sim::AssetPaths;
use rmcp::transport::streamable_http_server::session::SessionManager;
use rmcp::transport::streamable_http_server::session::local::LocalSessionManager;
use rmcp::transport::streamable_http_server::{StreamableHttpServerConfig, StreamableHttpService};
use serde::{Deserialize, Serialize};
use serde_json::json;
use sha2::{Digest, Sha256};

use crate::live::LiveHubs;
use crate::mcp::EpisodeMcp;

pub type McpService = StreamableHttpService<EpisodeMcp, LocalSessionManager>;

/// Largest accepted MCP request body (the original's 1 MiB protocol limit).
const MAX_REQUEST_BYTES: usize = 1 << 20;
/// Most MCP sessions one episode keeps open at once (an agent needs one; a relay or a reconnect a few more).
pub const MAX_SESSIONS_PER_EPISODE: usize = 8;
/// How long an ended episode keeps its MCP sessions: long enough for its last reply to reach the client.
pub const RELEASE_GRACE: Duration = Duration::from_secs(2);

/// `POST /api/episodes` body and the CLI's `episode prepare` options.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrepareRequest {
    /// `T01`…`T30`, `<suite>/<task>` or a `.bddl` path. A branch runs its parent's task: leave it out (or name
    /// the parent's).
    #[serde(default)]
    pub task: String,
    #[serde(default = "default_level")]
    pub level: u8,
    #[serde(default = "default_seed")]
    pub seed: u64,
    #[serde(default)]
    pub init_index: usize,
    /// Where to create the workspace (default: `<data>/workspaces/<episode_id>`).
    #[serde(default)]
    pub workspace: Option<PathBuf>,
    #[serde(default = "default_wall_time_s")]
    pub wall_time_s: f64,
    #[serde(default = "default_max_agent_steps")]
    pub max_agent_steps: u64,
    /// Record the private continuous video (default true; tests that only need verdicts turn it off).
    #[serde(default = "default_video")]
    pub video: bool,
    /// Agent harness (`codex`, `claude`, …), model and batch name, for the dashboard's table and filters.
    #[serde(default)]
    pub harness: Option<String>,
    #[serde(default)]
    pub model: Option<String>,
    #[serde(default)]
    pub batch: Option<String>,
    /// Demonstration placed at `benchmark_inputs/expert_demo/` (`none`, `video`, `video+traj`), taken from the
    /// server's demo library (`<data>/demos/<task>/`), recorded with the task's expert when the library has none.
    #[serde(default)]
    pub demo: DemoCondition,
    /// Run the task in another layout (a demonstration's source episode: another placement seed or init row,
    /// regions widened); None for evaluation episodes.
    #[serde(default)]
    pub layout: Option<LayoutVariant>,
    /// Start from another episode's state at one of its control steps (issue 33): its task, seed, init state
    /// and layout, its first `step` executed actions replayed. The replayed steps do not count toward
    /// `max_agent_steps`: the agent gets a normal fresh start whose first observation shows the branch state.
    #[serde(default)]
    pub branch: Option<BranchRequest>,
}

/// Whether `id` has the shape of an episode id (what may name a run directory).
pub fn valid_episode_id(id: &str) -> bool {
    !id.is_empty() && id.len() <= 96 && id.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
}

/// Where a branch starts: episode `parent` after its control step `step` (0: its settled start).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BranchRequest {
    pub parent: String,
    pub step: u64,
}

/// Why a branch cannot be prepared; each maps to its own HTTP status ([`BranchError::http_status`]).
#[derive(Debug, thiserror::Error)]
pub enum BranchError {
    #[error("no episode {0:?} to branch from")]
    UnknownParent(String),
    #[error("step {step} is beyond the parent's action log ({available} control steps were executed)")]
    StepOutOfRange { step: u64, available: u64 },
    #[error("the parent episode {parent} cannot be replayed: {why}")]
    NotReplayable { parent: String, why: String },
    #[error("a branch runs its parent's task {parent_task}, not {asked}; leave task out")]
    OtherTask { parent_task: String, asked: String },
}

impl BranchError {
    /// 404 for an unknown parent, 400 for a step or task the parent cannot give, 422 for a parent whose record
    /// cannot be replayed.
    pub fn http_status(&self) -> u16 {
        match self {
            Self::UnknownParent(_) => 404,
            Self::StepOutOfRange { .. } | Self::OtherTask { .. } => 400,
            Self::NotReplayable { .. } => 422,
        }
    }
}

/// A resolved branch: the parent's world and the actions replayed to the branch point.
struct BranchSource {
    request: BranchRequest,
    spec: WorldSpec,
    prefix: Vec<[f64; 7]>,
}

fn default_video() -> bool {
    true
}

impl PrepareRequest {
    /// `task` with every default of the HTTP API.
    pub fn new(task: impl Into<String>) -> Self {
        Self {
            task: task.into(),
            level: default_level(),
            seed: default_seed(),
            init_index: 0,
            workspace: None,
            wall_time_s: default_wall_time_s(),
            max_agent_steps: default_max_agent_steps(),
            video: default_video(),
            harness: None,
            model: None,
            batch: None,
            demo: DemoCondition::None,
            layout: None,
            branch: None,
        }
    }
}

/// Longest wall-clock budget an episode may be given (a week; the protocol's default is 1800 s).
pub const MAX_WALL_TIME_S: f64 = 7.0 * 24.0 * 3600.0;
/// Longest task reference, harness, model or batch name accepted.
const MAX_NAME_CHARS: usize = 512;
/// Largest init-state index (LIBERO's init files hold 50 states).
const MAX_INIT_INDEX: usize = 100_000;

impl PrepareRequest {
    /// Range checks of every number and size from outside, before anything is built.
    pub fn validate(&self) -> anyhow::Result<()> {
        Level::from_number(self.level).with_context(|| format!("level must be 1, 2 or 3 (got {})", self.level))?;
        if !(self.wall_time_s.is_finite() && self.wall_time_s > 0.0 && self.wall_time_s <= MAX_WALL_TIME_S) {
            bail!("wall_time_s must be a number of seconds in (0, {MAX_WALL_TIME_S}] (got {})", self.wall_time_s);
        }
        if self.max_agent_steps == 0 || self.max_agent_steps > MAX_AGENT_STEPS_CAP {
            bail!("max_agent_steps must be between 1 and {MAX_AGENT_STEPS_CAP} (got {})", self.max_agent_steps);
        }
        if self.seed > u64::from(u32::MAX) {
            bail!("seed must be between 0 and {} (NumPy's seed range; got {})", u32::MAX, self.seed);
        }
        if self.init_index > MAX_INIT_INDEX {
            bail!("init_index must be at most {MAX_INIT_INDEX} (got {})", self.init_index);
        }
        if self.task.trim().is_empty() && self.branch.is_none() {
            bail!("task must name a task (T14, libero_90/<name> or a .bddl path)");
        }
        if let Some(branch) = &self.branch {
            if !valid_episode_id(&branch.parent) {
                bail!("branch.parent must be an episode id (got {:?})", branch.parent);
            }
            if self.layout.is_some() {
                bail!("a branch runs its parent's layout; leave layout out");
            }
        }
        if let Some(layout) = &self.layout {
            layout.validate()?;
            if self.demo != DemoCondition::None {
                bail!("an episode in a layout variant records demonstrations; it cannot be given one");
            }
        }
        let names = [("task", Some(&self.task)), ("harness", self.harness.as_ref()), ("model", self.model.as_ref()), ("batch", self.batch.as_ref())];
        for (field, value) in names {
            if let Some(v) = value
                && (v.chars().count() > MAX_NAME_CHARS || v.chars().any(char::is_control))
            {
                bail!("{field} must be at most {MAX_NAME_CHARS} characters without control characters");
            }
        }
        Ok(())
    }
}

fn default_level() -> u8 {
    3
}
fn default_seed() -> u64 {
    100
}
fn default_wall_time_s() -> f64 {
    DEFAULT_WALL_TIME_S
}
fn default_max_agent_steps() -> u64 {
    MAX_AGENT_STEPS_CAP
}

/// What preparing returns (printed by `episode prepare`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Prepared {
    pub episode_id: String,
    pub mcp_url: String,
    /// Headers the MCP client must send (the bearer token).
    pub mcp_headers: BTreeMap<String, String>,
    pub workspace: PathBuf,
    pub prompt_file: PathBuf,
    pub mcp_config_file: PathBuf,
    pub run_dir: PathBuf,
    pub task: String,
    pub instruction: String,
    pub level: u8,
    /// The episode and control step a branch started from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub branch: Option<BranchRequest>,
}

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

/// An episode this process served. Once it has ended and its MCP sessions are closed, only a tombstone is left:
/// the token's digest and the handle, whose thread and world are gone (about a kilobyte).
struct Entry {
    token_sha256: [u8; 32],
    handle: EpisodeHandle,
    /// `None` once released.
    mcp: Option<LiveMcp>,
    /// What the episode's log lines name, and how far they have followed it (kept by the tombstone).
    log: Arc<EpisodeLog>,
}

/// The operator's log of one episode: a line when it is prepared, when `start_episode` succeeds and when it ends,
/// each with the episode's id, task, level and labels (never its token). Whoever sees a transition first (the store
/// sync after a tool call or on its tick, an abort, the shutdown) writes its line; each is written once.
struct EpisodeLog {
    task: String,
    level: u8,
    harness: Option<String>,
    model: Option<String>,
    batch: Option<String>,
    prepared_at: Instant,
    /// [`Self::PREPARED`], [`Self::STARTED`] or [`Self::ENDED`]: the last line written.
    phase: AtomicU8,
}

impl EpisodeLog {
    const PREPARED: u8 = 0;
    const STARTED: u8 = 1;
    const ENDED: u8 = 2;

    fn prepared(id: &str, req: &PrepareRequest, task: &str, workspace: &Path) -> Self {
        let log = Self {
            task: task.to_owned(),
            level: req.level,
            harness: req.harness.clone(),
            model: req.model.clone(),
            batch: req.batch.clone(),
            prepared_at: Instant::now(),
            phase: AtomicU8::new(Self::PREPARED),
        };
        tracing::info!(
            episode_id = id,
            task = log.task,
            level = log.level,
            harness = log.harness.as_deref(),
            model = log.model.as_deref(),
            batch = log.batch.as_deref(),
            seed = req.seed,
            video = req.video,
            demo = req.demo.as_str(),
            workspace = %workspace.display(),
            "episode prepared"
        );
        log
    }

    /// Writes the lines of the transitions `status` shows that were not written yet.
    fn follow(&self, id: &str, status: &EpisodeStatus) {
        // The initial observation exists exactly when start_episode succeeded.
        if status.latest_observation_id.is_some()
            && self.phase.compare_exchange(Self::PREPARED, Self::STARTED, Ordering::AcqRel, Ordering::Acquire).is_ok()
        {
            tracing::info!(
                episode_id = id,
                task = self.task,
                level = self.level,
                harness = self.harness.as_deref(),
                model = self.model.as_deref(),
                batch = self.batch.as_deref(),
                "episode started"
            );
        }
        let state = match status.state {
            EpisodeState::Finished => "finished",
            EpisodeState::Aborted => "aborted",
            EpisodeState::Prepared | EpisodeState::Active => return,
        };
        if self.phase.swap(Self::ENDED, Ordering::AcqRel) == Self::ENDED {
            return;
        }
        tracing::info!(
            episode_id = id,
            task = self.task,
            level = self.level,
            harness = self.harness.as_deref(),
            model = self.model.as_deref(),
            batch = self.batch.as_deref(),
            state,
            outcome = status.outcome.map(|o| o.as_str()),
            steps = status.accepted_agent_steps,
            reason = status.reason.as_deref(),
            since_prepared_s = (self.prepared_at.elapsed().as_secs_f64() * 10.0).round() / 10.0,
            "episode ended"
        );
    }
}

pub struct Episodes {
    data: PathBuf,
    base_url: String,
    paths: Option<AssetPaths>,
    map: RwLock<HashMap<String, Arc<Entry>>>,
    /// One GPU device shared by every episode (opened at the first prepare).
    renderer: Mutex<Option<Renderer>>,
    /// Where each MCP handler reports the episode it just served (the store sync listens).
    calls: Option<tokio::sync::mpsc::UnboundedSender<String>>,
    /// Each episode's live view for the dashboard.
    live: Option<Arc<LiveHubs>>,
    /// Serialises recording missing demonstrations, so concurrent rollouts of one task record one bundle.
    demo_recording: Mutex<()>,
    /// When each ended episode was first seen with its thread gone, until it is released (see [`RELEASE_GRACE`]).
    ending: Mutex<HashMap<String, Instant>>,
    /// The background worker that renders private videos from state records (started with the renderer).
    videos: Mutex<Option<VideoQueue>>,
}

pub fn random_hex(bytes: usize) -> std::io::Result<String> {
    let mut buf = vec![0u8; bytes];
    fs::File::open("/dev/urandom")?.read_exact(&mut buf)?;
    Ok(buf.iter().map(|b| format!("{b:02x}")).collect())
}

/// Equal-time comparison, so response timing does not leak how much of a token was right.
pub(crate) fn tokens_equal(a: &str, b: &str) -> bool {
    bytes_equal(a.as_bytes(), b.as_bytes())
}

fn bytes_equal(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// What an entry keeps of its token: the token itself never outlives the prepare reply.
fn token_digest(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

fn is_within(child: &Path, parent: &Path) -> bool {
    child.starts_with(parent)
}

/// Absolute, lexically normalised path (the workspace may not exist yet).
fn absolute(p: &Path) -> std::io::Result<PathBuf> {
    let p = if p.is_absolute() { p.to_path_buf() } else { std::env::current_dir()?.join(p) };
    let mut out = PathBuf::new();
    for c in p.components() {
        match c {
            std::path::Component::ParentDir => {
                out.pop();
            }
            std::path::Component::CurDir => {}
            other => out.push(other),
        }
    }
    Ok(out)
}

impl Episodes {
    pub fn new(data: PathBuf, base_url: String) -> anyhow::Result<Self> {
        crate::memory::tune_for_long_runs();
        let data = absolute(&data)?;
        fs::create_dir_all(data.join("runs"))?;
        fs::create_dir_all(data.join("workspaces"))?;
        let paths = match AssetPaths::discover() {
            Ok(p) => Some(p),
            Err(e) => {
                tracing::warn!("{e}; episodes cannot be prepared until the assets are set up");
                None
            }
        };
        Ok(Self {
            data,
            base_url,
            paths,
            map: RwLock::new(HashMap::new()),
            renderer: Mutex::new(None),
            calls: None,
            live: None,
            demo_recording: Mutex::new(()),
            ending: Mutex::new(HashMap::new()),
            videos: Mutex::new(None),
        })
    }

    /// The video worker, started at first use.
    fn video_queue(&self) -> anyhow::Result<VideoQueue> {
        let mut slot = self.videos.lock().map_err(|_| anyhow::anyhow!("video queue lock poisoned"))?;
        if let Some(q) = slot.as_ref() {
            return Ok(q.clone());
        }
        let q = VideoQueue::start(head_wrist_cameras()).context("cannot start the video worker")?;
        *slot = Some(q.clone());
        Ok(q)
    }

    fn started_video_queue(&self) -> Option<VideoQueue> {
        self.videos.lock().ok().and_then(|q| q.clone())
    }

    /// Where the private video of `run` stands: `None` when the episode records none.
    pub fn video_progress(&self, run: &RunDir) -> Option<VideoProgress> {
        let video = run.continuous_video();
        if let Some(p) = self.started_video_queue().and_then(|q| q.progress(&video)) {
            return Some(p);
        }
        if video.is_file() {
            Some(VideoProgress::Ready)
        } else if recorded_frames(run) > 0 {
            // Recorded, not yet handed to the worker (the episode is running, or the server restarted).
            Some(VideoProgress::Queued)
        } else {
            None
        }
    }

    /// Waits until every queued video is rendered, at most `timeout`; `progress` hears about each waiting second.
    /// Whether they all were.
    pub fn wait_for_videos(&self, timeout: Duration, mut progress: impl FnMut(usize, Option<f64>)) -> bool {
        let Some(q) = self.started_video_queue() else { return true };
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if q.wait_idle(left.min(Duration::from_secs(1))) {
                return true;
            }
            if left.is_zero() {
                return false;
            }
            progress(q.pending(), q.render_rate_fps());
        }
    }

    /// Waits until the private video of `run` is ready or failed, at most `timeout`; where it stands then.
    pub fn wait_for_video(&self, run: &RunDir, timeout: Duration) -> Option<VideoProgress> {
        match self.started_video_queue() {
            Some(q) => q.wait(&run.continuous_video(), timeout),
            None => self.video_progress(run),
        }
    }

    /// Stops the video worker after its current frame; unfinished videos are rebuilt at the next start.
    pub fn stop_videos(&self) {
        if let Some(q) = self.started_video_queue() {
            q.stop();
        }
    }

    /// After a restart: queues every private video that has a state record but no file (the server stopped
    /// before the worker finished it). Each job rebuilds the episode's model from its record when its turn
    /// comes. Returns how many.
    pub fn rebuild_missing_videos(&self) -> usize {
        let Ok(dirs) = fs::read_dir(self.runs_dir()) else { return 0 };
        let held: std::collections::HashSet<String> = self.ids().into_iter().collect();
        let mut n = 0;
        for d in dirs.flatten() {
            let run = RunDir::new(d.path());
            let id = d.file_name().to_string_lossy().into_owned();
            if held.contains(&id) || recorded_frames(&run) == 0 || run.continuous_video().is_file() {
                continue;
            }
            let (Some(paths), Ok(queue)) = (self.paths.clone(), self.video_queue()) else { return n };
            let Ok(renderer) = self.renderer() else { return n };
            let record = run.episode_record();
            let source = Box::new(move || -> Result<_, String> {
                let spec = spec_from_record(&record, paths).map_err(|e| format!("{e:#}"))?;
                let world = LiberoWorld::new(&spec, renderer).map_err(|e| e.to_string())?;
                Ok(world.video_models())
            });
            queue.submit(VideoJob { record: run.state_record(), video: run.continuous_video(), source });
            n += 1;
        }
        n
    }

    /// Reports every served tool call's episode id on `calls`.
    pub fn with_call_reports(mut self, calls: tokio::sync::mpsc::UnboundedSender<String>) -> Self {
        self.calls = Some(calls);
        self
    }

    /// Feeds every later episode's live events to `hubs`.
    pub fn with_live(mut self, hubs: Arc<LiveHubs>) -> Self {
        self.live = Some(hubs);
        self
    }

    pub fn data_dir(&self) -> &Path {
        &self.data
    }

    /// Ids of the episodes this server process holds.
    pub fn ids(&self) -> Vec<String> {
        self.map.read().map(|m| m.keys().cloned().collect()).unwrap_or_default()
    }

    /// The asset set, when it is installed (thumbnails resolve tasks with it).
    pub(crate) fn asset_paths(&self) -> Option<&AssetPaths> {
        self.paths.as_ref()
    }

    pub(crate) fn renderer(&self) -> anyhow::Result<Renderer> {
        let mut slot = self.renderer.lock().map_err(|_| anyhow::anyhow!("renderer lock poisoned"))?;
        if let Some(r) = slot.as_ref() {
            return Ok(r.clone());
        }
        let r = Renderer::new().context("cannot open a GPU for rendering")?;
        *slot = Some(r.clone());
        Ok(r)
    }

    pub fn runs_dir(&self) -> PathBuf {
        self.data.join("runs")
    }

    /// The demonstration library: `<data>/demos/<task>/<source episode id>/`.
    pub fn demo_library(&self) -> PathBuf {
        self.data.join("demos")
    }

    /// A library bundle that may be shown in the episode (`task`, `seed`, `init_index`): valid, verified,
    /// recorded in another configuration, and not solving this episode by direct replay (issue 31). When the
    /// library has none, one is recorded now with the task's scripted expert from the next source layout
    /// ([`library::source_layout_candidate`]) until one qualifies.
    pub fn demo_bundle(&self, task: &TaskSource, seed: u64, init_index: usize) -> anyhow::Result<PathBuf> {
        let lib = self.demo_library();
        let paths = self.paths.clone().context("assets are missing")?;
        let target = TargetEpisode { task: task.clone(), seed, init_index };
        // replay checks write manifests: one selection or recording at a time
        let _one_at_a_time = self.demo_recording.lock().map_err(|_| anyhow::anyhow!("demo lock poisoned"))?;
        let mut passed_over = match library::select_for_target(&lib, &target, &paths)? {
            Ok(bundle) => return Ok(bundle),
            Err(skipped) => skipped.into_iter().map(|s| format!("{}: {}", s.bundle.display(), s.reason)).collect::<Vec<_>>(),
        };
        let task_ref = task.task_ref.as_str();
        if libero_tasks::expert_behaviours(task_ref).is_none() {
            bail!(
                "no usable demonstration of {task_ref} in {} ({}) and no scripted expert to record one (record one \
                 in another layout by teleoperation, or with `libero-agent expert --task {task_ref} --layout-seed N \
                 --demo-out {}`)",
                library::task_dir(&lib, task_ref).display(),
                if passed_over.is_empty() { "the library is empty".to_owned() } else { passed_over.join("; ") },
                lib.display()
            );
        }
        let init_rows = match &task.init_states {
            Some(path) => Some(libero_sim::InitStates::read(path)?.len()),
            None => None,
        };
        for attempt in 0..library::MAX_SOURCE_ATTEMPTS {
            let layout = library::source_layout_candidate(&target, attempt, init_rows)?;
            let what = format!("source layout {}", serde_json::to_string(&layout)?);
            match self.record_expert_demo(task, layout, &target) {
                Ok(dir) => {
                    tracing::info!(task = task_ref, attempt, bundle = %dir.display(), "demonstration recorded");
                    return Ok(dir);
                }
                Err(e) => {
                    tracing::info!(task = task_ref, attempt, why = format!("{e:#}"), "demonstration source passed over");
                    passed_over.push(format!("{what}: {e:#}"));
                }
            }
        }
        bail!(
            "no demonstration of {task_ref} could be recorded whose replay does not solve the episode (seed {seed}, \
             init {init_index}): {}",
            passed_over.join("; ")
        )
    }

    /// Records a scripted-expert demonstration of `task` in `layout` (a separate episode, level 1, no video) for
    /// `target`: the expert's actions are first replayed in the target (physics only), and only a source whose
    /// replay fails is rendered into a bundle, verified by replay, with that check stored in its manifest.
    fn record_expert_demo(&self, task: &TaskSource, layout: LayoutVariant, target: &TargetEpisode) -> anyhow::Result<PathBuf> {
        let task_ref = task.task_ref.as_str();
        let seed = u64::from(layout.placement_seed);
        let req = PrepareRequest { level: 1, seed, init_index: layout.init_index, video: false, layout: Some(layout), ..PrepareRequest::new(task_ref) };
        let prepared = self.prepare(req)?;
        let mut handle = self.handle(&prepared.episode_id).context("the demonstration episode vanished")?;
        let paths = self.paths.clone().context("assets are missing")?;
        let mut source_task = task.clone();
        source_task.layout = Some(layout);
        let spec = PhysicsSpec { task: source_task, level: Level::L1, seed, init_index: layout.init_index, paths: paths.clone() };
        let run = run_expert(&mut handle, &spec, task_ref, libero_tasks::expert::SOLVE, 3000, |_| {});
        handle.stop("demonstration recording over");
        let run = run.with_context(|| format!("the {task_ref} expert could not run"))?;
        let source = SourceEpisode::read(&RunDir::new(self.runs_dir().join(&prepared.episode_id)))?;
        if source.success != Some(true) {
            let record = &run.replica_record;
            bail!(
                "the {task_ref} expert did not solve this layout ({} of {} stages)",
                record["completed_required_stage_count"],
                record["required_stage_count"]
            );
        }
        let actions: Vec<[f64; 7]> = source.actions.iter().map(|(_, a)| *a).collect();
        let replay = library::replay_in_target(&actions, target, &paths)?;
        if replay.success {
            bail!("replaying its {} actions solves the target episode", actions.len());
        }
        let options = RecordOptions { source_type: "scripted_expert".into(), source_desc: "libero-agent expert solve".into() };
        let summary = self.record_demo(&prepared.episode_id, &options)?;
        if !summary.verified {
            bail!("the expert's demonstration did not verify by replay ({})", summary.dir.display());
        }
        library::store_replay_check(&summary.dir, target, &replay)?;
        Ok(summary.dir)
    }

    /// Records a finished episode of this server into the demo library (`<data>/demos/<task>/<episode id>/`):
    /// replayed, rendered, and verified if the episode succeeded and the replay reproduces it. What the teleop
    /// page's "save demonstration" calls.
    pub fn record_demo(&self, episode_id: &str, options: &RecordOptions) -> anyhow::Result<BundleSummary> {
        if episode_id.is_empty() || !episode_id.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_') {
            bail!("not an episode id: {episode_id:?}");
        }
        let paths = self.paths.clone().context("assets are missing; run `python3 scripts/setup.py`")?;
        let run_dir = self.runs_dir().join(episode_id);
        let source = SourceEpisode::read(&RunDir::new(&run_dir)).with_context(|| format!("episode {episode_id}"))?;
        let out = library::bundle_dir(&self.demo_library(), &source.task_ref, episode_id);
        Ok(record_bundle(&run_dir, &out, options, self.renderer()?, &paths)?)
    }

    /// Replays library bundle `dir` and rewrites its verification; true if the evaluator's success is reproduced.
    pub fn verify_demo(&self, dir: &Path) -> anyhow::Result<bool> {
        let paths = self.paths.clone().context("assets are missing; run `python3 scripts/setup.py`")?;
        Ok(verify_bundle(dir, &paths)?)
    }

    /// Episodes this process serves that have not ended.
    pub fn count(&self) -> usize {
        self.map.read().map(|m| m.values().filter(|e| e.handle.ended().is_none()).count()).unwrap_or(0)
    }

    /// What the episode's MCP endpoint serves if `token` is its token.
    pub fn mcp_access(&self, id: &str, token: Option<&str>) -> Option<McpAccess> {
        let digest = token_digest(token?);
        let map = self.map.read().ok()?;
        let entry = map.get(id)?;
        if !bytes_equal(&entry.token_sha256, &digest) {
            return None;
        }
        Some(match &entry.mcp {
            Some(live) => McpAccess::Live(live.clone()),
            None => McpAccess::Ended(entry.handle.clone()),
        })
    }

    /// Releases what episodes that ended at least [`RELEASE_GRACE`] ago, and whose threads have exited, still hold
    /// here: their MCP sessions and their live views; then hands the memory their worlds freed back to the OS.
    /// Returns the ids released. Called periodically.
    pub async fn release_ended(&self) -> Vec<String> {
        let due = self.retire_due(Instant::now());
        for (id, live) in &due {
            live.close_all().await;
            self.close_live(id);
        }
        if !due.is_empty() {
            // Models other episodes' models read their large arrays from, now that no such episode is left.
            libero_sim::shared_model::release_unused();
            let _ = tokio::task::spawn_blocking(crate::memory::return_freed_memory).await;
        }
        due.into_iter().map(|(id, _)| id).collect()
    }

    /// Drops `id`'s live view (an episode that will never be served).
    fn close_live(&self, id: &str) {
        if let Some(hubs) = &self.live {
            hubs.close(id);
        }
    }

    /// Turns the entries of episodes ended for [`RELEASE_GRACE`] into tombstones; returns their MCP services.
    fn retire_due(&self, now: Instant) -> Vec<(String, LiveMcp)> {
        let (Ok(mut map), Ok(mut ending)) = (self.map.write(), self.ending.lock()) else { return Vec::new() };
        let mut due = Vec::new();
        for (id, entry) in map.iter_mut() {
            let ended = entry.handle.ended().is_some() && entry.handle.is_released();
            let Some(live) = entry.mcp.as_ref().filter(|_| ended) else { continue };
            let since = *ending.entry(id.clone()).or_insert(now);
            if now.duration_since(since) >= RELEASE_GRACE {
                due.push((id.clone(), live.clone()));
                entry.log.follow(id, &entry.handle.status());
                *entry = Arc::new(Entry { token_sha256: entry.token_sha256, handle: entry.handle.clone(), mcp: None, log: entry.log.clone() });
                ending.remove(id);
            }
        }
        due
    }

    /// The in-process handle of an episode (for the CLI's own agents, never for requests).
    pub fn handle(&self, id: &str) -> Option<EpisodeHandle> {
        let map = self.map.read().ok()?;
        map.get(id).map(|e| e.handle.clone())
    }

    pub fn status(&self, id: &str) -> Option<EpisodeStatus> {
        let map = self.map.read().ok()?;
        let entry = map.get(id)?;
        let status = entry.handle.status();
        entry.log.follow(id, &status);
        Some(status)
    }

    /// Ends one episode (aborted with `reason` unless it already ended); false if this server does not hold it.
    pub fn stop(&self, id: &str, reason: &str) -> bool {
        self.end_with(id, |h| h.stop(reason))
    }

    /// Ends one unfinished episode as its agent's FAIL (the agent ended without `finish_episode`); false if this
    /// server does not hold it.
    pub fn forfeit(&self, id: &str, reason: &str) -> bool {
        self.end_with(id, |h| h.forfeit(reason))
    }

    /// Runs `end` on `id`'s handle and records the state it leaves; false if this server does not hold it.
    fn end_with(&self, id: &str, end: impl FnOnce(&EpisodeHandle)) -> bool {
        let Some(e) = self.map.read().ok().and_then(|m| m.get(id).cloned()) else { return false };
        end(&e.handle);
        e.log.follow(id, &e.handle.status());
        true
    }

    /// Records every unfinished episode as aborted with `reason` (server shutdown), waiting at most `timeout`
    /// in all: an episode thread stuck in the simulation is left behind (the process is ending) rather than
    /// holding the shutdown. Returns how many did not answer in time.
    pub fn stop_all(&self, reason: &str, timeout: std::time::Duration) -> usize {
        let entries: Vec<(String, Arc<Entry>)> =
            self.map.read().map(|m| m.iter().map(|(id, e)| (id.clone(), e.clone())).collect()).unwrap_or_default();
        let deadline = std::time::Instant::now() + timeout;
        let pending: Vec<_> = entries.iter().map(|(_, e)| e.handle.request_stop(reason)).collect();
        let stuck = pending.into_iter().filter(|p| !p.wait_until(deadline)).count();
        for (id, e) in &entries {
            e.log.follow(id, &e.handle.status());
        }
        stuck
    }

    /// After a crash or kill: every run directory with an episode record but no result becomes an aborted
    /// (INVALID) episode with its reason. Finished records are left untouched. Returns how many.
    pub fn recover_interrupted(&self) -> usize {
        let Ok(dirs) = fs::read_dir(self.runs_dir()) else { return 0 };
        let mut n = 0;
        for d in dirs.flatten() {
            let run = RunDir::new(d.path());
            if !run.episode_record().is_file() || read_result(&run).is_some() {
                continue;
            }
            let max_wall = fs::read_to_string(run.episode_record())
                .ok()
                .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
                .and_then(|v| v["max_wall_time_seconds"].as_f64())
                .unwrap_or(DEFAULT_WALL_TIME_S);
            let result = aborted_result("server_stopped_before_finish: the server exited while the episode was open", max_wall, None);
            if write_result(&run, &result).is_ok() {
                n += 1;
            }
        }
        n
    }

    /// Prepares an episode: resolves the task, builds its world on a new episode thread, writes the private
    /// run directory and the workspace, and registers the MCP endpoint. A branch's parent is looked for in this
    /// server's run directories.
    pub fn prepare(&self, req: PrepareRequest) -> anyhow::Result<Prepared> {
        self.prepare_with_parent(req, None)
    }

    /// [`Self::prepare`], a branch's parent read from `parent_run` (its run directory as the store knows it)
    /// when given. Errors about the branch are [`BranchError`]s.
    pub fn prepare_with_parent(&self, req: PrepareRequest, parent_run: Option<PathBuf>) -> anyhow::Result<Prepared> {
        let task = req.task.clone();
        let prepared = self.prepare_episode(req, parent_run).inspect_err(|e| tracing::warn!(task, error = format!("{e:#}"), "episode not prepared"));
        // Building a world allocates and frees hundreds of MB in small blocks (the MuJoCo compile of a model the
        // scene may already share, its upload): give them back now, so an open episode costs what it keeps.
        crate::memory::return_freed_memory();
        prepared
    }

    /// Reads the parent's record and action log and checks the branch point (nothing is replayed yet: the branch's
    /// world replays the prefix when it starts, and its live preview at preparation).
    fn branch_source(&self, branch: &BranchRequest, parent_run: Option<PathBuf>, paths: &AssetPaths) -> Result<BranchSource, BranchError> {
        let parent = branch.parent.clone();
        let run = RunDir::new(parent_run.unwrap_or_else(|| self.runs_dir().join(&parent)));
        if !valid_episode_id(&parent) || !run.episode_record().is_file() {
            return Err(BranchError::UnknownParent(parent));
        }
        let not_replayable = |why: String| BranchError::NotReplayable { parent: parent.clone(), why };
        let source = SourceEpisode::read(&run).map_err(|e| not_replayable(e.to_string()))?;
        let mut spec = spec_from_record(&run.episode_record(), paths.clone()).map_err(|e| not_replayable(format!("{e:#}")))?;
        // the parent's own init state (a suite task fixes its row; the record keeps what the episode used)
        spec.init_index = source.init_state_index;
        let available = source.actions.len() as u64;
        if branch.step > available {
            return Err(BranchError::StepOutOfRange { step: branch.step, available });
        }
        let prefix = source.actions.iter().take(branch.step as usize).map(|(_, a)| *a).collect();
        Ok(BranchSource { request: branch.clone(), spec, prefix })
    }

    fn prepare_episode(&self, mut req: PrepareRequest, parent_run: Option<PathBuf>) -> anyhow::Result<Prepared> {
        req.validate()?;
        let level = Level::from_number(req.level).context("level")?;
        let paths = self.paths.clone().context("assets are missing; run `python3 scripts/setup.py`")?;
        let branch = req.branch.as_ref().map(|b| self.branch_source(b, parent_run, &paths)).transpose()?;
        let mut task: TaskSource = match &branch {
            Some(b) => {
                let parent_task = b.spec.task.task_ref.clone();
                if !req.task.trim().is_empty() && req.task != parent_task {
                    return Err(BranchError::OtherTask { parent_task, asked: req.task.clone() }.into());
                }
                req.task = parent_task;
                req.seed = b.spec.seed;
                req.init_index = b.spec.init_index;
                req.layout = b.spec.task.layout;
                b.spec.task.clone()
            }
            None => resolve_task(&req.task, &paths)?,
        };
        task.layout = req.layout;
        let demo_source = match req.demo {
            DemoCondition::None => None,
            _ => Some(self.demo_bundle(&task, req.seed, req.init_index).context("no demonstration for this episode")?),
        };
        let episode_id = format!("ep-{}-{}", compact_utc(), random_hex(4)?);
        let token = random_hex(32)?;
        let run_dir = self.runs_dir().join(&episode_id);
        let workspace = match &req.workspace {
            Some(w) => absolute(w)?,
            None => self.data.join("workspaces").join(&episode_id),
        };
        if is_within(&workspace, &self.runs_dir()) || is_within(&self.runs_dir(), &workspace) {
            bail!("the workspace {} must not overlap the private run directories", workspace.display());
        }
        if WorkspaceLayout::new(&workspace).episode_json().exists() {
            bail!("{} already holds a prepared episode", workspace.display());
        }
        fs::create_dir_all(&run_dir)?;
        let mcp_url = format!("{}/mcp/{episode_id}", self.base_url);
        let mut headers = BTreeMap::new();
        headers.insert("Authorization".to_owned(), format!("Bearer {token}"));
        let record = json!({
            "schema_version": "libero.agent_episode_record.v1",
            "episode_id": episode_id,
            "created_at": utc_now_iso(),
            "task": task,
            "level": req.level,
            "seed": req.seed,
            "init_state_index": req.init_index,
            "max_agent_steps": req.max_agent_steps,
            "max_wall_time_seconds": req.wall_time_s,
            "demo": req.demo.as_str(),
            "workspace": workspace,
            "mcp_url": mcp_url,
            "harness": req.harness,
            "model": req.model,
            "batch": req.batch,
        });
        let mut record = record;
        if let Some(b) = &branch {
            record["branch"] = json!({
                "parent_episode_id": b.request.parent,
                "parent_control_step": b.request.step,
                "replayed_actions": b.prefix.len(),
                "prefix_file": libero_episode::branch::PREFIX_FILE,
                "counts_toward_max_agent_steps": false,
            });
        }
        let run = RunDir::new(&run_dir);
        write_json_file(&run.episode_record(), &record)?;
        if let Some(b) = &branch {
            libero_episode::branch::write_prefix(&run, &b.prefix).context("cannot keep the branch's replayed actions")?;
            libero_episode::branch::log_branch_point(&run, &b.request.parent, b.request.step).context("cannot start the branch's action log")?;
        }
        let prefix = branch.as_ref().map(|b| b.prefix.clone()).unwrap_or_default();
        let config = EpisodeConfig {
            episode_id: episode_id.clone(),
            instruction: task.instruction.clone(),
            level,
            max_agent_steps: req.max_agent_steps,
            max_wall_time_s: req.wall_time_s,
            workspace: workspace.clone(),
            run_dir: run_dir.clone(),
        };
        let spec = WorldSpec { task: task.clone(), level, seed: req.seed, init_index: req.init_index, paths };
        let renderer = self.renderer()?;
        let video_queue = if req.video { Some(self.video_queue()?) } else { None };
        let (video, state_record) = (run.continuous_video(), run.state_record());
        let telemetry = run.telemetry_jsonl();
        let live = self.live.as_ref().map(|hubs| hubs.open(&episode_id, config.agent_step_limit(), config.max_wall_time_s));
        if let (Some(hubs), Some(b)) = (&self.live, &branch) {
            hubs.mark_branch(&episode_id, &b.request.parent, b.request.step);
        }
        let world_live = live.clone();
        let make_world = move || {
            let mut world = LiberoWorld::new(&spec, renderer)?;
            world.set_start_prefix(prefix);
            if let Some((sink, viewers)) = world_live {
                world.set_live(sink, viewers, Some(&telemetry))?;
            }
            if let Some(queue) = video_queue {
                world.record_video(&video, &state_record, queue)?;
            }
            Ok(world)
        };
        let handle = match spawn_episode_live(config, live.map(|(sink, _)| sink), make_world) {
            Ok(h) => h,
            Err(e) => {
                self.close_live(&episode_id);
                return Err(e).with_context(|| format!("cannot build the simulation for {}", task.task_ref));
            }
        };
        let layout = WorkspaceLayout::new(&workspace);
        let contract = WorkspaceContract {
            instruction: task.instruction.clone(),
            max_agent_steps: req.max_agent_steps,
            max_wall_time_s: req.wall_time_s,
            mcp_url: mcp_url.clone(),
            mcp_headers: headers.clone(),
            demo: req.demo.prompt_notice().map(|notice| DemoNotice { icl_condition: req.demo.icl_condition().into(), notice }),
        };
        let demo = demo_source.as_deref().map(|source| (source, req.demo));
        if let Err(e) = place_workspace(&layout, &contract, demo, &run) {
            // Nobody will ever call this episode: end it now, so its thread and world go.
            handle.stop(&format!("workspace set-up failed: {e:#}"));
            self.close_live(&episode_id);
            return Err(e);
        }
        let mcp = LiveMcp::new(EpisodeMcp { handle: handle.clone(), calls: self.calls.clone() });
        let log = Arc::new(EpisodeLog::prepared(&episode_id, &req, &task.task_ref, &workspace));
        let entry = Arc::new(Entry { token_sha256: token_digest(&token), handle, mcp: Some(mcp), log });
        self.map
            .write()
            .map_err(|_| anyhow::anyhow!("episode registry lock poisoned"))?
            .insert(episode_id.clone(), entry);
        Ok(Prepared {
            episode_id,
            mcp_url,
            mcp_headers: headers,
            prompt_file: layout.prompt_file(),
            mcp_config_file: layout.mcp_json(),
            workspace,
            run_dir,
            task: task.task_ref,
            instruction: task.instruction,
            level: req.level,
            branch: branch.map(|b| b.request),
        })
    }
}

impl Drop for Episodes {
    /// The end lines of episodes nothing asked about since they ended (the in-process expert stops its episodes
    /// through their handles).
    fn drop(&mut self) {
        if let Ok(map) = self.map.read() {
            for (id, e) in map.iter() {
                e.log.follow(id, &e.handle.status());
            }
        }
    }
}

/// Control steps in the state record of `run` (0 without one: an episode never started records no frame).
fn recorded_frames(run: &RunDir) -> u64 {
    libero_episode::state_record::StateRecordReader::open(&run.state_record()).map(|r| r.frames()).unwrap_or(0)
}

/// The world an episode ran on, from its private record (`task.task_ref`, `level`, `seed`, `init_state_index`).
fn spec_from_record(record: &Path, paths: AssetPaths) -> anyhow::Result<WorldSpec> {
    let v: serde_json::Value = serde_json::from_slice(&fs::read(record).with_context(|| format!("cannot read {}", record.display()))?)?;
    let task_ref = v["task"]["task_ref"].as_str().context("the episode record names no task")?;
    let level = v["level"].as_u64().and_then(|l| Level::from_number(u8::try_from(l).ok()?)).context("the episode record has no level")?;
    let seed = v["seed"].as_u64().context("the episode record has no seed")?;
    let init_index = v["init_state_index"].as_u64().context("the episode record has no init state index")?;
    let mut task = resolve_task(task_ref, &paths)?;
    task.layout = layout_from_json(&v["task"]["layout"])?;
    Ok(WorldSpec { task, level, seed, init_index: usize::try_from(init_index)?, paths })
}

/// The agent's workspace (prompt, MCP config, the demonstration if any) and the prompt's private copy.
fn place_workspace(
    layout: &WorkspaceLayout,
    contract: &WorkspaceContract,
    demo: Option<(&Path, DemoCondition)>,
    run: &RunDir,
) -> anyhow::Result<()> {
    create_workspace(layout, contract).with_context(|| format!("cannot create the workspace {}", layout.root.display()))?;
    if let Some((source, condition)) = demo {
        let receipt = project_bundle(source, &layout.expert_demo(), condition, &contract.instruction)
            .context("cannot place the demonstration in the workspace")?;
        write_json_file(&run.root.join("icl_projection_receipt.json"), &serde_json::to_value(&receipt)?)?;
    }
    fs::copy(layout.prompt_file(), run.agent_prompt()).context("cannot keep a private copy of the prompt")?;
    Ok(())
}

/// `YYYYMMDDTHHMMSSZ` for episode ids (sortable by creation time).
fn compact_utc() -> String {
    let iso = utc_now_iso(); // 2026-11-21T17:03:04.123456+00:00
    let digits: String = iso[..19].chars().filter(|c| c.is_ascii_digit() || *c == 'T').collect();
    format!("{digits}Z")
}
