//! The agent's workspace (§3.1–§3.3) and the episode prompt (§5.1). Only public files live here: the
//! prompt, the public contract, the MCP client config and published observations.
use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

use serde_json::{Value, json};

use libero_records::json::{format_g, write_atomic, write_json_file};
use crate::tools::{MAX_MICRO_ACTIONS_PER_CALL, MCP_SERVER_KEY, ToolName};

/// Workspace-relative path of the published observation file.
pub const OBSERVATION_FILE: &str = "benchmark_inputs/current_observation/observation.json";

/// Paths inside one workspace.
#[derive(Debug, Clone)]
pub struct WorkspaceLayout {
    pub root: PathBuf,
}

impl WorkspaceLayout {
    pub fn new(root: impl Into<PathBuf>) -> Self {
        Self { root: root.into() }
    }
    pub fn prompt_file(&self) -> PathBuf {
        self.root.join("TASK_PROMPT.txt")
    }
    pub fn private_dir(&self) -> PathBuf {
        self.root.join(".libero")
    }
    pub fn episode_json(&self) -> PathBuf {
        self.private_dir().join("episode.json")
    }
    pub fn mcp_json(&self) -> PathBuf {
        self.private_dir().join("mcp.json")
    }
    pub fn benchmark_inputs(&self) -> PathBuf {
        self.root.join("benchmark_inputs")
    }
    pub fn current_observation(&self) -> PathBuf {
        self.benchmark_inputs().join("current_observation")
    }
    pub fn scratch(&self) -> PathBuf {
        self.root.join("scratch")
    }
    pub fn expert_demo(&self) -> PathBuf {
        self.root.join(EXPERT_DEMO_DIR)
    }
}

/// What the public workspace files state about an episode.
#[derive(Debug, Clone)]
pub struct WorkspaceContract {
    /// Task instruction shown to the agent (whitespace collapsed by [`normalize_instruction`]).
    pub instruction: String,
    pub max_agent_steps: u64,
    pub max_wall_time_s: f64,
    /// The episode's MCP endpoint, e.g. `http://127.0.0.1:8080/mcp/<episode_id>`.
    pub mcp_url: String,
    /// HTTP headers a client must send (the per-episode bearer token).
    pub mcp_headers: BTreeMap<String, String>,
    /// Demonstration placed at `benchmark_inputs/expert_demo/`: its `icl_condition` and the §5.2 notice
    /// (None in the release condition).
    pub demo: Option<DemoNotice>,
}

/// What the workspace says about a placed demonstration.
#[derive(Debug, Clone, PartialEq)]
pub struct DemoNotice {
    /// `video_only` or `video_plus_trajectory`.
    pub icl_condition: String,
    /// Inserted after the instruction, surrounded by newlines (§5.2).
    pub notice: String,
}

/// Workspace-relative directory of a placed demonstration (§7.3/§7.4).
pub const EXPERT_DEMO_DIR: &str = "benchmark_inputs/expert_demo";

/// Collapses internal whitespace to single spaces (the original's instruction normalisation).
pub fn normalize_instruction(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// The release prompt (§5.1): MCP transport, no resets, no demonstration notice.
pub fn task_prompt(instruction: &str, max_wall_time_s: f64, max_agent_steps: u64) -> String {
    task_prompt_with_notice(instruction, None, max_wall_time_s, max_agent_steps)
}

/// The paper's shared execution prompt (Appendix C; the original launcher's MCP wording, word for word), with a
/// demonstration notice on the line after the instruction; without one that line is empty. Golden files:
/// `tests/fixtures/prompt/`.
pub fn task_prompt_with_notice(instruction: &str, notice: Option<&str>, max_wall_time_s: f64, max_agent_steps: u64) -> String {
    let instruction = normalize_instruction(instruction);
    let notice = notice.map(normalize_instruction).unwrap_or_default();
    let t = format_g(max_wall_time_s);
    format!(
        "{instruction}\n\
{notice}\n\
\n\
A LIBERO episode has been prepared for you.\n\
\n\
This query has a {t}-second evaluator wall-clock budget shared by all reset attempts. Exceeding it ends the query \
as an official task failure.\n\
\n\
1. Call the `start_episode` robot tool exactly once to begin and receive the initial observation and \
`max_agent_steps` budget.\n\
2. Control the robot with the `osc_sequence` robot tool. Its `actions` argument is an array of 1 to \
{MAX_MICRO_ACTIONS_PER_CALL} normalized 7D OSC_POSE micro actions in `[dx, dy, dz, rx, ry, rz, gripper]` order. \
Every component must be within [-1, 1]. Each vector executes one LIBERO policy interval; translation 1.0 corresponds \
to 0.05 m, rotation 1.0 to a 0.5 rad rotation-vector component, gripper -1 opens, and +1 closes. One sequence call \
counts as one Agent action, with at most {max_agent_steps} accepted calls.\n\
3. Wait for each action to complete, then inspect `{obs}` and any referenced files before issuing another command.\n\
4. When you have completed the task, call the `finish_episode` robot tool exactly once. Only finish reports official \
task success.\n",
        obs = OBSERVATION_FILE,
    )
}

/// `.libero/episode.json`, schema `libero.agent_workspace.v1` (§3.2), release values except the demonstration.
pub fn episode_contract(max_wall_time_s: f64, demo: Option<&DemoNotice>) -> Value {
    json!({
        "schema_version": "libero.agent_workspace.v1",
        "episode_resumable": false,
        "operations": ToolName::ALL.iter().map(|t| t.as_str()).collect::<Vec<_>>(),
        "action_interface": "native_osc_sequence",
        "control_transport": "mcp",
        "max_native_osc_micro_steps_per_submission": MAX_MICRO_ACTIONS_PER_CALL,
        "observation_retention": "current_only",
        "max_resets": 0,
        "max_attempts": 1,
        "agent_step_budget_scope": "per_attempt",
        "max_wall_time_seconds": max_wall_time_s,
        "wall_time_budget_scope": "per_episode_across_resets",
        "icl_condition": demo.map_or("none", |d| d.icl_condition.as_str()),
        "expert_demo": demo.map(|_| EXPERT_DEMO_DIR),
        "experience_context": null,
    })
}

/// `.libero/mcp.json`: the client-neutral config, here an HTTP server entry (Claude Code / Kimi style).
pub fn mcp_config(url: &str, headers: &BTreeMap<String, String>) -> Value {
    let mut entry = json!({"type": "http", "url": url});
    if !headers.is_empty() {
        entry["headers"] = json!(headers);
    }
    json!({"mcpServers": {MCP_SERVER_KEY: entry}})
}

/// Creates the workspace files. `root` may exist but must not already hold a prepared episode.
pub fn create_workspace(layout: &WorkspaceLayout, contract: &WorkspaceContract) -> std::io::Result<()> {
    fs::create_dir_all(&layout.root)?;
    if layout.episode_json().exists() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::AlreadyExists,
            format!("{} already holds a prepared episode", layout.root.display()),
        ));
    }
    fs::create_dir_all(layout.scratch())?;
    fs::create_dir_all(layout.benchmark_inputs())?;
    fs::create_dir_all(layout.private_dir())?;
    set_mode(&layout.private_dir(), 0o700)?;
    let notice = contract.demo.as_ref().map(|d| d.notice.as_str());
    let prompt = task_prompt_with_notice(&contract.instruction, notice, contract.max_wall_time_s, contract.max_agent_steps);
    write_atomic(&layout.prompt_file(), prompt.as_bytes())?;
    write_json_file(&layout.episode_json(), &episode_contract(contract.max_wall_time_s, contract.demo.as_ref()))?;
    write_json_file(&layout.mcp_json(), &mcp_config(&contract.mcp_url, &contract.mcp_headers))?;
    set_mode(&layout.mcp_json(), 0o600)
}

fn set_mode(path: &Path, mode: u32) -> std::io::Result<()> {
    use std::os::unix::fs::PermissionsExt;
    fs::set_permissions(path, fs::Permissions::from_mode(mode))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prompt_has_the_release_layout() {
        let p = task_prompt("  put the  bowl\n on the plate ", 1800.0, 1_000_000);
        let lines: Vec<&str> = p.lines().collect();
        assert_eq!(lines[0], "put the bowl on the plate");
        assert_eq!((lines[1], lines[2]), ("", ""), "two empty lines when there is no ICL notice");
        assert_eq!(lines[3], "A LIBERO episode has been prepared for you.");
        assert!(lines[5].starts_with("This query has a 1800-second evaluator wall-clock budget"), "{}", lines[5]);
        assert!(lines[7].starts_with("1. Call the `start_episode`"));
        assert!(lines[8].starts_with("2. ") && lines[8].contains("at most 1000000 accepted calls"));
        assert!(lines[9].starts_with("3. ") && lines[9].contains(OBSERVATION_FILE));
        assert!(lines[10].starts_with("4. Only") || lines[10].starts_with("4. When"));
        assert_eq!(lines.len(), 11);
        assert!(p.ends_with(".\n"));
    }

    /// The paper's shared execution prompt, without and with the demonstration notice, byte for byte against
    /// `tests/fixtures/prompt/` (`UPDATE_GOLDEN=1` rewrites them after a deliberate change).
    #[test]
    fn prompts_match_the_papers_text() {
        let dir = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/prompt"));
        let notice = fs::read_to_string(dir.join("demo_notice.txt")).unwrap();
        for (file, prompt) in [
            ("prompt_release.txt", task_prompt("close the top drawer of the cabinet", 1800.0, 1_000_000)),
            ("prompt_demo.txt", task_prompt_with_notice("close the top drawer of the cabinet", Some(notice.trim_end()), 1800.0, 1_000_000)),
        ] {
            if std::env::var_os("UPDATE_GOLDEN").is_some() {
                fs::write(dir.join(file), &prompt).unwrap();
            }
            let want = fs::read_to_string(dir.join(file)).unwrap_or_else(|e| panic!("{file}: {e} (UPDATE_GOLDEN=1 writes it)"));
            assert_eq!(prompt, want, "{file}");
        }
    }

    #[test]
    fn a_demo_notice_sits_on_the_line_after_the_instruction() {
        let p = task_prompt_with_notice("open the drawer", Some("A demo is at `benchmark_inputs/expert_demo/`."), 1800.0, 10);
        let lines: Vec<&str> = p.lines().collect();
        assert_eq!(lines[..4], ["open the drawer", "A demo is at `benchmark_inputs/expert_demo/`.", "", "A LIBERO episode has been prepared for you."]);
        assert_eq!(p.lines().count(), 11);
    }

    #[test]
    fn workspace_files_follow_the_contract() {
        let dir = tempfile::tempdir().unwrap();
        let layout = WorkspaceLayout::new(dir.path().join("ws"));
        let mut headers = BTreeMap::new();
        headers.insert("Authorization".to_owned(), "Bearer tok".to_owned());
        let contract = WorkspaceContract {
            instruction: "open the drawer".into(),
            max_agent_steps: 1_000_000,
            max_wall_time_s: 1800.0,
            mcp_url: "http://127.0.0.1:9/mcp/ep1".into(),
            mcp_headers: headers,
            demo: None,
        };
        create_workspace(&layout, &contract).unwrap();
        let episode: Value = serde_json::from_str(&fs::read_to_string(layout.episode_json()).unwrap()).unwrap();
        assert_eq!(episode["operations"], json!(["start_episode", "osc_sequence", "finish_episode"]));
        assert_eq!(episode["max_wall_time_seconds"], json!(1800.0));
        let mcp: Value = serde_json::from_str(&fs::read_to_string(layout.mcp_json()).unwrap()).unwrap();
        assert_eq!(mcp["mcpServers"]["libero"]["url"], "http://127.0.0.1:9/mcp/ep1");
        assert_eq!(mcp["mcpServers"]["libero"]["headers"]["Authorization"], "Bearer tok");
        assert!(layout.scratch().is_dir() && layout.benchmark_inputs().is_dir());
        assert!(!layout.current_observation().exists(), "appears only at start_episode");
        use std::os::unix::fs::PermissionsExt;
        assert_eq!(fs::metadata(layout.private_dir()).unwrap().permissions().mode() & 0o777, 0o700);
        assert!(create_workspace(&layout, &contract).is_err(), "a workspace is never prepared twice");
    }
}
