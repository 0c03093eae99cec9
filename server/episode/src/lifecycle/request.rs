//! What preparing an episode takes and gives: the `POST /api/episodes` body (also the CLI's and the runner's), its
//! range checks, a branch point and why a branch cannot be made, and the reply. Plain data, so a client of the
//! server's API needs nothing else of the lifecycle.
use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{Context, bail};
use serde::{Deserialize, Serialize};

use crate::Level;
use crate::demo::{DemoCondition, LayoutVariant};
use crate::tools::{DEFAULT_WALL_TIME_S, MAX_AGENT_STEPS_CAP};

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

impl Prepared {
    /// The episode's bearer token, from the headers the agent is told to send: the MCP endpoint keeps only its
    /// digest.
    pub fn bearer_token(&self) -> Option<&str> {
        self.mcp_headers.get("Authorization")?.strip_prefix("Bearer ")
    }
}
