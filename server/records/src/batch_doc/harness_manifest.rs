//! A rollout's `harness_manifest.json` (`rollouts/<rollout_id>/` of a batch directory): what the runner launched,
//! in what sandbox and network, and what became of it. The runner writes it three times: at the launch (before the
//! agent starts), once the sandbox reported itself, and when the rollout ended; a field known only at a later
//! write is absent before it. Typed as the other records are ([`crate::typed`]): every key a reader does not name,
//! and every value of an unexpected type, survives a read and a write, so manifests of older runners still read.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde_json::Value;

use super::{HarnessVersion, ResourceLimitsDoc, ToolboxDoc};
use crate::records::Outcome;
use crate::typed::{RecordError, read_record, record};

/// The file's name in a rollout directory.
pub const HARNESS_MANIFEST_FILE: &str = "harness_manifest.json";

/// `schema_version` of the manifests this runner writes.
pub const HARNESS_MANIFEST_SCHEMA: &str = "libero.multi_agent_harness_run.v1";

/// `credential_material`: the API key itself is never in a manifest, only the file it came from.
pub const CREDENTIAL_MATERIAL_NEVER_RECORDED: &str = "never_recorded";

record! {
    /// `harness_manifest.json`. The first block is written at the launch, `sandbox_report` and `relay_dir` once
    /// the agent started, the rest when the rollout ended.
    pub struct HarnessManifest {
        /// [`HARNESS_MANIFEST_SCHEMA`].
        pub schema_version: Option<String>,
        pub rollout_id: Option<String>,
        /// When the launch was written (UTC, ISO 8601).
        pub created_at: Option<String>,
        /// The harness's name (`codex`, `claude`, `command`, …).
        pub harness: Option<String>,
        /// The model the batch asked for (what the harness's CLI was told, not what answered).
        pub model_requested: Option<String>,
        /// The reasoning effort the batch asked for.
        pub effort: Option<String>,
        /// `--version` of the executable this rollout launched (else the batch's probe).
        pub harness_version: Option<HarnessVersion>,
        /// The wire protocol the harness speaks to its model (§6.7).
        pub api_protocol: Option<String>,
        /// The credentials file the key came from; null without credentials.
        pub credential_source: Option<Option<PathBuf>>,
        /// Always [`CREDENTIAL_MATERIAL_NEVER_RECORDED`].
        pub credential_material: Option<String>,
        /// How the sandbox isolates the agent; null for a run without the sandbox.
        pub sandbox: Option<Option<SandboxDescription>>,
        /// The agent's Python in the sandbox; null: the system's python3 alone (results compare only with the
        /// same toolbox).
        pub toolbox: Option<Option<ToolboxDoc>>,
        /// The agent's network plan; null without the sandbox.
        pub network: Option<Option<NetworkPlanDoc>>,
        pub episode_id: Option<String>,
        /// The agent's workspace (its cwd).
        pub workspace: Option<PathBuf>,
        /// The episode's private run directory (the agent never sees it).
        pub private_run: Option<PathBuf>,
        /// The agent's `$HOME` for the rollout.
        pub session_home: Option<PathBuf>,
        /// The argv launched, the prompt replaced by `<task-prompt>`.
        pub command: Option<Vec<String>>,
        pub task: Option<String>,
        /// The task's instruction level (1–3).
        pub level: Option<u64>,
        /// The demonstration condition: `none`, `video`, `video_traj`.
        pub demo: Option<String>,
        pub seed: Option<u64>,
        /// The episode's wall-time budget, seconds.
        pub max_wall_time_seconds: Option<f64>,
        pub max_agent_steps: Option<u64>,
        /// What the sandbox is, as its first process saw it before the agent started; null when it did not say
        /// (no sandbox, or it did not start).
        pub sandbox_report: Option<Option<SandboxReport>>,
        /// The runner's relay sockets' directory (removed after the rollout); null without the sandbox.
        pub relay_dir: Option<Option<PathBuf>>,
        /// When the rollout ended (UTC, ISO 8601).
        pub finished_at: Option<String>,
        /// From the agent's start to its stop, seconds.
        pub elapsed_seconds: Option<f64>,
        /// The agent's exit code (-1: killed by a signal); null when it could not be read.
        pub agent_exit_code: Option<Option<i32>>,
        /// Why the rollout does not count, when the infrastructure failed it.
        pub infrastructure_error: Option<Option<String>>,
        /// The episode's `result.json` status (`finished`, `aborted`); null without a result.
        pub result_status: Option<Option<String>>,
        /// The private evaluation's verdict; null without one.
        pub task_success: Option<Option<bool>>,
        /// The rollout's outcome class (§4.8).
        pub outcome: Option<Outcome>,
        /// What became of each log (by file name): kept scrubbed and bounded, or why not.
        pub logs: Option<BTreeMap<String, LogRecordDoc>>,
        /// Where the token usage came from (`model_api_gateway`, `stdout`); null: nowhere.
        pub usage_source: Option<Option<String>>,
        /// What the transcript follower wrote.
        pub agent_events: Option<AgentEventsDoc>,
        /// What the runner's gateway saw of the agent's model traffic; null without the gateway.
        pub model_api: Option<Option<ModelApiDoc>>,
        /// What the agent used and met of its caps; null without a cage.
        pub resources_used: Option<Option<ResourcesUsedDoc>>,
    }
}

record! {
    /// How the sandbox isolates the agent (`Sandbox::describe`).
    pub struct SandboxDescription {
        /// The bubblewrap version.
        pub bubblewrap: Option<String>,
        pub namespaces: Option<Vec<String>>,
        pub identity: Option<SandboxIdentity>,
        /// The seccomp allow-list, described.
        pub seccomp: Option<Value>,
        /// The per-rollout caps; null when unconfined.
        pub resources: Option<Option<ResourceLimitsDoc>>,
        pub network: Option<String>,
    }
}

record! {
    /// Whose ids the agent runs with.
    pub struct SandboxIdentity {
        /// `root` or `unprivileged`: the runner's.
        pub runner: Option<String>,
        /// The agent's host uid and gid (a runner as root only).
        pub agent_uid: Option<u64>,
        pub agent_gid: Option<u64>,
        /// Each rollout has its own uid (`--agent-uids`).
        pub uid_per_rollout: Option<bool>,
        pub how: Option<String>,
    }
}

record! {
    /// The agent's network plan (`NetPlan::describe`): only its endpoint and its model API, through the runner's
    /// relays.
    pub struct NetworkPlanDoc {
        pub model_api: Option<ModelApiRouteDoc>,
        /// `host:port` the proxy lets through (tunnels the gateway cannot meter).
        pub proxy_allow_list: Option<Vec<String>>,
        pub everything_else: Option<String>,
    }
}

record! {
    /// Where the agent's model API goes.
    pub struct ModelApiRouteDoc {
        /// `127.0.0.1:<port>` inside the sandbox.
        pub inside: Option<String>,
        /// The real API base; null when the credentials name none.
        pub upstream: Option<Option<String>>,
        /// The API base the agent is given.
        pub agent_base: Option<String>,
        /// `METHOD /path` the gateway passes on.
        pub routes: Option<Vec<String>>,
    }
}

record! {
    /// What the sandbox's first process saw of itself (`sandbox_report`, `libero.sandbox_report.v1`).
    pub struct SandboxReport {
        pub schema_version: Option<String>,
        /// `/proc/self/status` `Uid:` (real, effective, saved, filesystem).
        pub uid: Option<Option<Vec<String>>>,
        pub gid: Option<Option<Vec<String>>>,
        pub capabilities: Option<CapabilitySets>,
        pub no_new_privs: Option<Option<bool>>,
        /// `/proc/self/status` `Seccomp:` (`2`: a filter).
        pub seccomp: Option<Option<String>>,
        pub network_interfaces: Option<Vec<String>>,
        pub mounts: Option<Vec<MountDoc>>,
    }
}

record! {
    /// The capability sets as hex masks (all zeros: none).
    pub struct CapabilitySets {
        pub inheritable: Option<Option<String>>,
        pub permitted: Option<Option<String>>,
        pub effective: Option<Option<String>>,
        pub bounding: Option<Option<String>>,
        pub ambient: Option<Option<String>>,
    }
}

record! {
    /// One mount the agent sees.
    pub struct MountDoc {
        pub mountpoint: Option<String>,
        pub root: Option<String>,
        /// Mount options (`ro,…`).
        pub options: Option<String>,
        pub fstype: Option<String>,
    }
}

record! {
    /// What became of one log (`LogRecord`), or why it was not scrubbed.
    pub struct LogRecordDoc {
        /// The log's size as the agent's process left it, bytes.
        pub size_bytes: Option<u64>,
        /// The scrubbed copy's size, bytes.
        pub kept_bytes: Option<u64>,
        /// Secrets replaced.
        pub redactions: Option<u64>,
        /// The bytes left out of a log longer than its head and tail; null: none.
        pub omitted: Option<Option<Value>>,
        /// Why it was not scrubbed.
        pub error: Option<String>,
    }
}

record! {
    /// What the transcript follower wrote (`transcript::Summary`).
    pub struct AgentEventsDoc {
        /// The transcript file.
        pub path: Option<Option<PathBuf>>,
        pub events: Option<u64>,
        pub bytes: Option<u64>,
        /// Events past the transcript's size cap.
        pub omitted_events: Option<u64>,
        /// Events over their stream's quota, by stream (absent: none).
        pub over_quota: Option<BTreeMap<String, u64>>,
        /// Events the remote server accepted, when posting.
        pub posted: Option<u64>,
        pub errors: Option<Vec<String>>,
    }
}

record! {
    /// The gateway's records added up (`netgate::UsageSummary`).
    pub struct ModelApiDoc {
        pub requests: Option<u64>,
        /// Requests the gateway refused.
        pub refused: Option<u64>,
        pub failed: Option<u64>,
        /// Responses that carried token usage.
        pub responses_with_usage: Option<u64>,
        pub input_tokens: Option<u64>,
        pub output_tokens: Option<u64>,
        pub total_tokens: Option<u64>,
        /// The sums are every token the traffic cost (else a lower bound).
        pub complete: Option<bool>,
    }
}

record! {
    /// What the agent used and met of its caps (`RolloutCage::usage`); null where the cgroup did not say.
    pub struct ResourcesUsedDoc {
        pub memory_peak_bytes: Option<Option<u64>>,
        pub oom_kills: Option<Option<u64>>,
        /// Memory-limit hits (cgroup v1's `memory.failcnt`).
        pub memory_limit_hits: Option<Option<u64>>,
        pub processes_peak: Option<Option<u64>>,
        /// Forks refused at the process cap.
        pub forks_refused: Option<Option<u64>>,
        pub disk_used_bytes: Option<Option<u64>>,
    }
}

impl HarnessManifest {
    /// The manifest of the rollout directory `rollout_dir`; `Ok(None)` when it has none.
    pub fn read(rollout_dir: &Path) -> Result<Option<Self>, RecordError> {
        read_record(&rollout_dir.join(HARNESS_MANIFEST_FILE))
    }

    /// Writes the manifest into `rollout_dir` (sorted, pretty, atomically).
    pub fn write(&self, rollout_dir: &Path) -> std::io::Result<()> {
        crate::json::write_json_file(&rollout_dir.join(HARNESS_MANIFEST_FILE), &self.to_value())
    }

    /// The sandbox's description; `None` without one (null or absent).
    pub fn sandbox(&self) -> Option<&SandboxDescription> {
        self.sandbox.as_ref()?.as_ref()
    }

    /// The sandbox's report; `None` when it did not say (null or absent).
    pub fn sandbox_report(&self) -> Option<&SandboxReport> {
        self.sandbox_report.as_ref()?.as_ref()
    }

    /// The network plan; `None` without the sandbox.
    pub fn network(&self) -> Option<&NetworkPlanDoc> {
        self.network.as_ref()?.as_ref()
    }

    /// The gateway's summary; `None` without the gateway.
    pub fn model_api(&self) -> Option<&ModelApiDoc> {
        self.model_api.as_ref()?.as_ref()
    }

    /// What the agent used of its caps; `None` without a cage.
    pub fn resources_used(&self) -> Option<&ResourcesUsedDoc> {
        self.resources_used.as_ref()?.as_ref()
    }

    /// The relay sockets' directory; `None` without the sandbox.
    pub fn relay_dir(&self) -> Option<&Path> {
        self.relay_dir.as_ref()?.as_deref()
    }

    /// Model requests that went through the gateway and were not refused (0 without the gateway).
    pub fn model_requests_passed(&self) -> u64 {
        self.model_api().map_or(0, |m| m.requests.unwrap_or(0).saturating_sub(m.refused.unwrap_or(0)))
    }
}
