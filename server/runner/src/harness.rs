//! How each agent CLI is launched for one rollout (protocol §8.3–§8.5), adapted to our transport: the MCP
//! server is the episode's streamable-HTTP endpoint with its bearer token (stdio-only harnesses get the
//! `mcp-stdio` relay). Every launch has an explicit model, a private session home (HOME and the CLI's own
//! config directory, so session logs are ours to read and nothing leaks between rollouts), credentials only
//! in the child's environment (or a 0600 file in the session home where the CLI insists), and the prompt as
//! the last argument.
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use serde_json::{Value, json};

use libero_episode::tools::{MCP_SERVER_KEY, ToolName};
use libero_sandbox::agent_net::NetPlan;

use crate::usage::UsageFormat;

/// The agent CLIs the runner knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
#[value(rename_all = "snake_case")]
pub enum Harness {
    Codex,
    ClaudeCode,
    KimiCode,
    QwenCode,
    Deepseek,
    /// Any command (`--agent-cmd`), e.g. the built-in reference agent.
    Command,
}

/// npm packages of the harnesses launched through `npx` (the paper's versions).
pub const DSH_PACKAGE: &str = "@deepseek-ai/dsh@0.1.5-rc.2";
pub const KIMI_PACKAGE: &str = "@moonshot-ai/kimi-code@0.42.0";
pub const QWEN_PACKAGE: &str = "@qwen-code/qwen-code@0.24.0";

/// Everything the runner knows of one harness, as data and functions: one row per [`Harness`] ([`Harness::spec`]).
/// Adding a harness is a variant of [`Harness`] and its row here (with its launch functions below, and a parser in
/// `transcript` if it prints a shape none of the others does); the report crate names its logs
/// (`libero_report::batch::HARNESSES`), and the lock may list versions of its CLI (`harness_versions`).
pub struct HarnessSpec {
    /// The name in batch files, rollout directories, logs and manifests (the CLI's `--harness` value).
    pub name: &'static str,
    /// How its CLI is installed and started: what `--version` probes and `--harness-version` picks.
    pub cli: Cli,
    /// Whether it needs API credentials (a `command` agent gets them only when a credentials file is given).
    pub needs_credentials: bool,
    /// §6.7 `api_protocol` of its manifest.
    pub api_protocol: &'static str,
    /// The wire APIs its CLI calls its model with (what the gateway passes on).
    pub model_apis: &'static [ModelApi],
    /// Where its model traffic goes when the credentials name no base URL: its CLI's own default.
    pub default_api_base: Option<&'static str>,
    /// Its model APIs' endpoints are allowed below the API base as given too, not only as its CLI would make it
    /// (a `command` agent may use the base unchanged).
    pub endpoints_below_given_base: bool,
    /// The configuration files its launch writes first (MCP server, model provider, settings: path, content, mode).
    pub files: fn(&LaunchContext) -> anyhow::Result<Vec<LaunchFile>>,
    /// Its argv (the prompt last), given the environment every launch has, to which it adds its own variables.
    pub command: fn(&LaunchContext, &mut LaunchEnv) -> anyhow::Result<Vec<String>>,
    /// How its stdout reads as the agent's transcript (`crate::transcript`).
    pub transcript: TranscriptFormat,
    /// Where the rollout's token usage is read from on its stdout (`crate::usage`).
    pub usage: UsageFormat,
}

/// How a harness's CLI is installed and started.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cli {
    /// No CLI of its own: it runs `--agent-cmd` (the `command` harness).
    AgentCmd,
    /// The command its CLI installs on PATH (or a version installed apart, `run --harness-version`).
    OnPath(&'static str),
    /// A pinned npm package (`<package>@<version>`) and the command it installs: run by that command when exactly
    /// the pinned version is installed, else through `npx --yes <package>@<version>`.
    Npm { package: &'static str, command: &'static str },
}

/// How a harness's stdout reads as a transcript (docs/agent_transcript.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TranscriptFormat {
    /// Plain text the agent prints: every line is a message.
    Text,
    /// JSON lines of the CLIs' shapes (Codex `exec --json`, the `stream-json` of Claude Code, Qwen Code and Kimi
    /// Code); any other line is an `other` event.
    JsonLines,
    /// JSON lines, with plain text lines as the agent's answer (DeepSeek's headless profile prints it so).
    JsonLinesOrText,
}

const CODEX: HarnessSpec = HarnessSpec {
    name: "codex",
    cli: Cli::OnPath("codex"),
    needs_credentials: true,
    api_protocol: "openai_chat",
    model_apis: &[ModelApi::OpenaiResponses],
    default_api_base: Some("https://api.openai.com/v1"),
    endpoints_below_given_base: false,
    files: no_files,
    command: codex_command,
    transcript: TranscriptFormat::JsonLines,
    // `--json`: its events (token counts included) on stdout, one `turn.completed` usage per turn.
    usage: UsageFormat::CodexExec,
};

const CLAUDE_CODE: HarnessSpec = HarnessSpec {
    name: "claude_code",
    cli: Cli::OnPath("claude"),
    needs_credentials: true,
    api_protocol: "anthropic_messages",
    model_apis: &[ModelApi::AnthropicMessages],
    default_api_base: Some("https://api.anthropic.com"),
    endpoints_below_given_base: false,
    files: claude_files,
    command: claude_command,
    transcript: TranscriptFormat::JsonLines,
    usage: UsageFormat::Jsonl,
};

const KIMI_CODE: HarnessSpec = HarnessSpec {
    name: "kimi_code",
    cli: Cli::Npm { package: KIMI_PACKAGE, command: "kimi" },
    needs_credentials: true,
    api_protocol: "openai_chat",
    model_apis: &[ModelApi::OpenaiChat],
    default_api_base: None,
    endpoints_below_given_base: false,
    files: kimi_files,
    command: kimi_command,
    transcript: TranscriptFormat::JsonLines,
    usage: UsageFormat::Jsonl,
};

const QWEN_CODE: HarnessSpec = HarnessSpec {
    name: "qwen_code",
    cli: Cli::Npm { package: QWEN_PACKAGE, command: "qwen" },
    needs_credentials: true,
    api_protocol: "openai_chat",
    model_apis: &[ModelApi::OpenaiChat],
    default_api_base: Some("https://api.openai.com/v1"),
    endpoints_below_given_base: false,
    files: qwen_files,
    command: qwen_command,
    transcript: TranscriptFormat::JsonLines,
    usage: UsageFormat::Jsonl,
};

const DEEPSEEK: HarnessSpec = HarnessSpec {
    name: "deepseek",
    cli: Cli::Npm { package: DSH_PACKAGE, command: "dsh" },
    needs_credentials: true,
    api_protocol: "openai_chat",
    model_apis: &[ModelApi::OpenaiChat],
    default_api_base: None,
    endpoints_below_given_base: false,
    files: deepseek_files,
    command: deepseek_command,
    transcript: TranscriptFormat::JsonLinesOrText,
    usage: UsageFormat::Jsonl,
};

const COMMAND: HarnessSpec = HarnessSpec {
    name: "command",
    cli: Cli::AgentCmd,
    needs_credentials: false,
    api_protocol: "none",
    model_apis: &[ModelApi::OpenaiChat, ModelApi::OpenaiResponses, ModelApi::AnthropicMessages],
    default_api_base: None,
    endpoints_below_given_base: true,
    files: no_files,
    command: agent_cmd_command,
    transcript: TranscriptFormat::Text,
    usage: UsageFormat::None,
};

impl Harness {
    /// This harness's row: how it is launched and configured, how its stdout is read, where its usage comes from.
    pub fn spec(self) -> &'static HarnessSpec {
        match self {
            Harness::Codex => &CODEX,
            Harness::ClaudeCode => &CLAUDE_CODE,
            Harness::KimiCode => &KIMI_CODE,
            Harness::QwenCode => &QWEN_CODE,
            Harness::Deepseek => &DEEPSEEK,
            Harness::Command => &COMMAND,
        }
    }

    pub fn as_str(self) -> &'static str {
        self.spec().name
    }

    /// `<program> --version` argv (None for `command`): the program as [`cli_command`] starts it.
    pub fn version_probe(self, npm_cli_installed: bool, cli_path: Option<&Path>) -> Option<Vec<String>> {
        let mut a = cli_command(self, npm_cli_installed, cli_path);
        if a.is_empty() {
            return None;
        }
        a.push("--version".into());
        Some(a)
    }

    /// The command the harness's CLI installs (`codex`, `claude`, `qwen`, …); `None` for `command`.
    pub fn command(self) -> Option<&'static str> {
        match self.spec().cli {
            Cli::AgentCmd => None,
            Cli::OnPath(command) | Cli::Npm { command, .. } => Some(command),
        }
    }

    /// The pinned npm package and the command it installs, for the harnesses the paper ran through `npx`.
    pub fn npm_cli(self) -> Option<(&'static str, &'static str)> {
        match self.spec().cli {
            Cli::Npm { package, command } => Some((package, command)),
            _ => None,
        }
    }

    /// Whether the harness runs `--agent-cmd` (it has no CLI of its own).
    pub fn runs_agent_cmd(self) -> bool {
        self.spec().cli == Cli::AgentCmd
    }

    pub fn needs_credentials(self) -> bool {
        self.spec().needs_credentials
    }

    /// The stdout file name in the rollout directory (JSON lines where the CLI streams JSON).
    /// The batch directory's layout is the report crate's, which the console reads logs through too.
    pub fn stdout_file(self) -> String {
        libero_report::batch::stdout_file(self.as_str()).unwrap_or_else(|| format!("{}_stdout.log", self.as_str()))
    }

    /// Anthropic's protocol for Claude, OpenAI-compatible chat for the others (§6.7 `api_protocol`).
    pub fn api_protocol(self) -> &'static str {
        self.spec().api_protocol
    }

    /// The wire APIs the harness's CLI calls its model with (what the gateway passes on): Codex the Responses API,
    /// Claude Code Anthropic's Messages, the others OpenAI-compatible chat completions; a `command` agent may
    /// speak any of them.
    pub fn model_apis(self) -> &'static [ModelApi] {
        self.spec().model_apis
    }

    /// The model-API endpoints the harness's CLI calls, `(method, path)`, given the path of the API base URL it
    /// is handed (the gateway's, which has the upstream's path): each API's endpoints below the base the CLI
    /// makes of it ([`ModelApi::base_path`]). A `command` agent gets them below the base as given too, since it
    /// may use that unchanged. Nothing else (no files, batches or stored objects: memory that would outlive a
    /// rollout).
    pub fn model_api_endpoints(self, api_base_path: &str) -> Vec<(&'static str, String)> {
        let mut out: Vec<(&'static str, String)> = Vec::new();
        for api in self.model_apis() {
            let mut bases = vec![api.base_path(api_base_path)];
            if self.spec().endpoints_below_given_base {
                bases.push(api_base_path.trim_end_matches('/').to_owned());
            }
            for base in bases {
                for (method, below) in api.endpoints() {
                    let e = (*method, format!("{base}{below}"));
                    if !out.contains(&e) {
                        out.push(e);
                    }
                }
            }
        }
        out
    }

    /// Where the agent's model traffic goes when the credentials name no base URL: each CLI's own default.
    pub fn default_api_base(self) -> Option<&'static str> {
        self.spec().default_api_base
    }
}

/// A model API's wire protocol, as a client calls it below its API base.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelApi {
    /// `POST {base}/chat/completions` (Qwen Code, Kimi Code, DeepSeek's dsh).
    OpenaiChat,
    /// `POST {base}/responses` (Codex).
    OpenaiResponses,
    /// `POST {base}/messages` and `/messages/count_tokens` (Claude Code).
    AnthropicMessages,
}

impl ModelApi {
    /// `(method, path below the base)` of the calls its clients make; `GET /models` for the model list the CLIs
    /// read at start.
    pub fn endpoints(self) -> &'static [(&'static str, &'static str)] {
        match self {
            ModelApi::OpenaiChat => &[("POST", "/chat/completions"), ("GET", "/models")],
            ModelApi::OpenaiResponses => &[("POST", "/responses"), ("GET", "/models")],
            ModelApi::AnthropicMessages => &[("POST", "/messages"), ("POST", "/messages/count_tokens"), ("GET", "/models")],
        }
    }

    /// The path a client's endpoints hang below, made from the path of the API base URL it is handed as the
    /// launches make it: OpenAI clients get [`Credentials::openai_base`] (`/v1` appended if missing), Anthropic's
    /// get [`Credentials::anthropic_base`] (a trailing `/v1` removed) and add `/v1` themselves.
    pub fn base_path(self, api_base_path: &str) -> String {
        let b = api_base_path.trim_end_matches('/');
        match self {
            ModelApi::OpenaiChat | ModelApi::OpenaiResponses if b.ends_with("/v1") => b.to_owned(),
            ModelApi::OpenaiChat | ModelApi::OpenaiResponses => format!("{b}/v1"),
            ModelApi::AnthropicMessages => format!("{}/v1", b.trim_end_matches("/v1")),
        }
    }
}

/// Whether `harness`'s pinned npm CLI is installed on PATH at exactly the pinned version. Then the runner runs it
/// directly; otherwise `npx --yes <package>@<version>`, which downloads it into each rollout's fresh home.
pub fn pinned_npm_cli_installed(harness: Harness) -> bool {
    let Some((package, command)) = harness.npm_cli() else { return false };
    let Some(path) = libero_sandbox::host_paths::which(command) else { return false };
    let pinned = package.rsplit('@').next().unwrap_or_default();
    let out = std::process::Command::new(path).arg("--version").stdin(std::process::Stdio::null()).output();
    out.is_ok_and(|o| o.status.success() && String::from_utf8_lossy(&o.stdout).split_whitespace().any(|w| w.trim_start_matches('v') == pinned))
}

/// How the harness's CLI is started (empty for `command`): a version installed apart (`run --harness-version`) by
/// its executable's path; else Codex and Claude Code by the command on PATH, the other npm harnesses by their
/// installed command or `npx --yes <package>@<version>`.
pub fn cli_command(harness: Harness, npm_cli_installed: bool, cli_path: Option<&Path>) -> Vec<String> {
    if let (Some(path), Some(_)) = (cli_path, harness.command()) {
        return vec![path.to_string_lossy().into_owned()];
    }
    match harness.spec().cli {
        Cli::OnPath(command) => vec![command.to_owned()],
        Cli::Npm { command, .. } if npm_cli_installed => vec![command.to_owned()],
        Cli::Npm { package, .. } => vec!["npx".to_owned(), "--yes".to_owned(), package.to_owned()],
        Cli::AgentCmd => Vec::new(),
    }
}

/// API credentials read from a file outside every workspace; never logged, never in a manifest.
#[derive(Clone)]
pub struct Credentials {
    pub api_base: Option<String>,
    pub api_key: String,
    pub source: PathBuf,
}

impl std::fmt::Debug for Credentials {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Credentials").field("api_base", &self.api_base).field("source", &self.source).finish_non_exhaustive()
    }
}

/// Default credentials file: `~/.config/libero-agent/credentials`.
pub fn default_credentials_file() -> PathBuf {
    let home = std::env::var_os("HOME").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("/"));
    home.join(".config/libero-agent/credentials")
}

impl Credentials {
    /// `KEY = value` lines (`APIKEY|API_KEY|OPENAI_API_KEY`, `APIURL|API_BASE_URL|OPENAI_API_BASE|OPENAI_API_URL`),
    /// else a bare http(s) URL line and the first other non-comment line of at least 8 characters as the key.
    pub fn parse(text: &str, source: &Path) -> anyhow::Result<Self> {
        let (mut base, mut key, mut bare_key) = (None, None, None);
        for line in text.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')) {
            if let Some((k, v)) = line.split_once('=') {
                let v = v.trim().trim_matches(['"', '\'']).to_owned();
                match k.trim() {
                    "APIKEY" | "API_KEY" | "OPENAI_API_KEY" => key = Some(v),
                    "APIURL" | "API_BASE_URL" | "OPENAI_API_BASE" | "OPENAI_API_URL" => base = Some(v),
                    _ => {}
                }
            } else if line.starts_with("http://") || line.starts_with("https://") {
                base.get_or_insert_with(|| line.to_owned());
            } else if line.len() >= 8 && bare_key.is_none() {
                bare_key = Some(line.to_owned());
            }
        }
        let api_key = key.or(bare_key).with_context(|| format!("{} holds no API key (APIKEY=…)", source.display()))?;
        Ok(Self { api_base: base, api_key, source: source.to_path_buf() })
    }

    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read credentials file {}", path.display()))?;
        Self::parse(&text, path)
    }

    /// OpenAI-style base: `/v1` appended if missing.
    pub fn openai_base(&self) -> Option<String> {
        self.api_base.as_ref().map(|b| {
            let b = b.trim_end_matches('/');
            if b.ends_with("/v1") { b.to_owned() } else { format!("{b}/v1") }
        })
    }

    /// Anthropic-style base: a trailing `/v1` removed.
    pub fn anthropic_base(&self) -> Option<String> {
        self.api_base.as_ref().map(|b| b.trim_end_matches('/').trim_end_matches("/v1").to_owned())
    }
}

/// The network plan ([`NetPlan`]) of an agent of `harness` on the episode at `mcp_url`: its model traffic to the
/// credentials' base URL (else the CLI's default), through the harness's own endpoints only; `via_npx` when the
/// harness's CLI is fetched by `npx` at launch.
pub fn net_plan(harness: Harness, mcp_url: &str, credentials: Option<&Credentials>, via_npx: bool) -> anyhow::Result<NetPlan> {
    let base = credentials.and_then(|c| c.api_base.clone()).or_else(|| harness.default_api_base().map(str::to_owned));
    NetPlan::new(mcp_url, base.as_deref(), |path| harness.model_api_endpoints(path), via_npx)
}

/// The credentials the launch is built from: the key unchanged, the base URL the gateway's.
pub fn agent_credentials(plan: &NetPlan, c: &Credentials) -> Credentials {
    Credentials { api_base: plan.agent_api_base().or_else(|| c.api_base.clone()), api_key: c.api_key.clone(), source: c.source.clone() }
}

/// Everything a launch depends on.
pub struct LaunchContext<'a> {
    pub harness: Harness,
    pub model: &'a str,
    pub effort: &'a str,
    pub workspace: &'a Path,
    pub session_home: &'a Path,
    pub prompt: &'a str,
    pub prompt_file: &'a Path,
    pub mcp_url: &'a str,
    pub mcp_token: &'a str,
    pub credentials: Option<&'a Credentials>,
    pub agent_cmd: Option<&'a str>,
    /// This binary (for `mcp-stdio` and `{libero_agent}`).
    pub self_exe: &'a Path,
    /// Whether our sandbox isolates the agent (then Codex's own sandbox is not nested inside it).
    pub sandboxed: bool,
    /// Whether the harness's pinned npm CLI is installed ([`pinned_npm_cli_installed`]): run it without `npx`.
    pub npm_cli_installed: bool,
    /// The executable of a version asked for with `run --harness-version` (`crate::harness_versions::resolve`),
    /// run instead of the command on PATH.
    pub cli_path: Option<&'a Path>,
}

/// A launch's environment variables (the child's whole environment), in order.
pub type LaunchEnv = Vec<(String, String)>;

/// A file a launch writes first: path, content, mode (0600 where it holds a token or key).
pub type LaunchFile = (PathBuf, String, u32);

/// A launch: argv, the child's whole environment, files to write first.
pub struct Launch {
    pub argv: Vec<String>,
    pub env: LaunchEnv,
    pub files: Vec<LaunchFile>,
}

impl Launch {
    /// The argv for manifests: the prompt replaced by `<task-prompt>`.
    pub fn public_argv(&self, prompt: &str) -> Vec<String> {
        self.argv.iter().map(|a| if a == prompt { "<task-prompt>".to_owned() } else { a.clone() }).collect()
    }
}

/// Shell-quotes one word.
pub fn shell_quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

fn tool_names() -> Vec<&'static str> {
    ToolName::ALL.iter().map(|t| t.as_str()).collect()
}

/// `{"mcpServers": {"libero": {"type": "http", "url", "headers"}}}` (Claude Code; Kimi adds timeouts).
pub fn claude_mcp_config(url: &str, token: &str) -> Value {
    json!({"mcpServers": {MCP_SERVER_KEY: {"type": "http", "url": url, "headers": {"Authorization": format!("Bearer {token}")}}}})
}

/// Qwen Code (a Gemini CLI fork) names streamable HTTP servers by `httpUrl`.
pub fn qwen_mcp_config(url: &str, token: &str) -> Value {
    json!({"mcpServers": {MCP_SERVER_KEY: {"httpUrl": url, "headers": {"Authorization": format!("Bearer {token}")},
        "timeout": 600000, "trust": true, "includeTools": tool_names()}}})
}

/// Codex's `--config` overrides for the episode's MCP server (TOML values); the token comes from the
/// environment variable `LIBERO_MCP_TOKEN`, never from argv.
pub fn codex_mcp_args(url: &str) -> Vec<String> {
    let tools = tool_names().iter().map(|t| format!("\"{t}\"")).collect::<Vec<_>>().join(", ");
    [
        format!("mcp_servers.{MCP_SERVER_KEY}.url=\"{url}\""),
        format!("mcp_servers.{MCP_SERVER_KEY}.bearer_token_env_var=\"LIBERO_MCP_TOKEN\""),
        format!("mcp_servers.{MCP_SERVER_KEY}.required=true"),
        format!("mcp_servers.{MCP_SERVER_KEY}.startup_timeout_sec=30"),
        format!("mcp_servers.{MCP_SERVER_KEY}.tool_timeout_sec=600"),
        format!("mcp_servers.{MCP_SERVER_KEY}.enabled_tools=[{tools}]"),
    ]
    .into_iter()
    .flat_map(|c| ["--config".to_owned(), c])
    .collect()
}

fn s(x: &str) -> String {
    x.to_owned()
}

/// Builds the launch of `ctx.harness`: the environment every launch has, then the harness's files and command
/// ([`HarnessSpec::files`], [`HarnessSpec::command`]).
pub fn build_launch(ctx: &LaunchContext) -> anyhow::Result<Launch> {
    let spec = ctx.harness.spec();
    let mut env = common_env(ctx);
    let files = (spec.files)(ctx)?;
    let argv = (spec.command)(ctx, &mut env)?;
    Ok(Launch { argv, env, files })
}

/// The environment of every launch: the session home, the workspace and the episode's endpoint and token.
fn common_env(ctx: &LaunchContext) -> LaunchEnv {
    let path = std::env::var("PATH").unwrap_or_else(|_| s("/usr/local/bin:/usr/bin:/bin"));
    let mut env = vec![
        (s("PATH"), path),
        (s("HOME"), ctx.session_home.to_string_lossy().into_owned()),
        (s("LANG"), s("C.UTF-8")),
        (s("TERM"), s("dumb")),
        (s("NO_COLOR"), s("1")),
        (s("TMPDIR"), s("/tmp")),
        (s("LIBERO_AGENT_WORKSPACE"), ctx.workspace.to_string_lossy().into_owned()),
        (s("LIBERO_MCP_URL"), s(ctx.mcp_url)),
        (s("LIBERO_MCP_TOKEN"), s(ctx.mcp_token)),
    ];
    // A library path the operator started the runner with (libmujoco outside the binary's run path) holds for the
    // `libero-agent` processes of the sandbox too; the sandbox shows the libraries themselves.
    if let Some(v) = std::env::var_os("LD_LIBRARY_PATH") {
        env.push((s("LD_LIBRARY_PATH"), v.to_string_lossy().into_owned()));
    }
    env
}

/// The launch's credentials, which every CLI harness needs.
fn credentials<'a>(ctx: &LaunchContext<'a>) -> anyhow::Result<&'a Credentials> {
    ctx.credentials.with_context(|| format!("the {} harness needs API credentials", ctx.harness.as_str()))
}

fn home_s(ctx: &LaunchContext) -> String {
    ctx.session_home.to_string_lossy().into_owned()
}

fn no_files(_: &LaunchContext) -> anyhow::Result<Vec<LaunchFile>> {
    Ok(Vec::new())
}

fn codex_command(ctx: &LaunchContext, env: &mut LaunchEnv) -> anyhow::Result<Vec<String>> {
    let c = credentials(ctx)?;
    env.push((s("CODEX_HOME"), home_s(ctx)));
    env.push((s("OPENAI_API_KEY"), c.api_key.clone()));
    env.push((s("CODEX_API_KEY"), c.api_key.clone()));
    let mut a = cli_command(ctx.harness, ctx.npm_cli_installed, ctx.cli_path);
    a.push(s("exec"));
    if ctx.sandboxed {
        // Our bubblewrap sandbox is the isolation; Codex's own (landlock/bwrap) cannot nest inside it.
        a.push(s("--dangerously-bypass-approvals-and-sandbox"));
    } else {
        a.extend([s("--sandbox"), s("workspace-write"), s("--config"), s("approval_policy=\"never\"")]);
    }
    // `--json`: events (token counts included) on stdout, which the runner captures out of the agent's reach.
    a.extend([s("--skip-git-repo-check"), s("--color"), s("never"), s("--json"), s("--model"), s(ctx.model)]);
    a.extend([s("--config"), format!("model_reasoning_effort=\"{}\"", ctx.effort)]);
    if let Some(b) = c.openai_base() {
        a.extend([s("--config"), format!("openai_base_url=\"{b}\"")]);
    }
    a.extend(codex_mcp_args(ctx.mcp_url));
    a.push(s(ctx.prompt));
    Ok(a)
}

/// Claude Code's MCP configuration (`--mcp-config`), in the session home.
fn claude_config_file(ctx: &LaunchContext) -> PathBuf {
    ctx.session_home.join("mcp.json")
}

fn claude_files(ctx: &LaunchContext) -> anyhow::Result<Vec<LaunchFile>> {
    let config = serde_json::to_string_pretty(&claude_mcp_config(ctx.mcp_url, ctx.mcp_token))?;
    Ok(vec![(claude_config_file(ctx), config, 0o600)])
}

fn claude_command(ctx: &LaunchContext, env: &mut LaunchEnv) -> anyhow::Result<Vec<String>> {
    let c = credentials(ctx)?;
    if let Some(b) = c.anthropic_base() {
        env.push((s("ANTHROPIC_BASE_URL"), b));
    }
    env.push((s("ANTHROPIC_API_KEY"), c.api_key.clone()));
    env.push((s("CLAUDE_CONFIG_DIR"), home_s(ctx)));
    env.push((s("CLAUDE_CODE_DISABLE_NONESSENTIAL_TRAFFIC"), s("1")));
    if ctx.sandboxed {
        // Claude Code's own marker for "inside bubblewrap": without it, bypassPermissions is refused to
        // root (the uid a CI container runs as), although our sandbox is exactly the isolation it asks for.
        env.push((s("CLAUDE_CODE_BUBBLEWRAP"), s("1")));
    }
    let mut a = cli_command(ctx.harness, ctx.npm_cli_installed, ctx.cli_path);
    a.extend([
        s("--bare"), s("--strict-mcp-config"), s("--mcp-config"), claude_config_file(ctx).to_string_lossy().into_owned(),
        s("--print"), s("--output-format"), s("stream-json"), s("--verbose"), s("--model"), s(ctx.model),
        s("--effort"), s(ctx.effort), s("--permission-mode"), s("bypassPermissions"), s(ctx.prompt),
    ]);
    Ok(a)
}

/// Kimi Code's provider and model (the key among them), its MCP server, and an empty skills directory.
fn kimi_files(ctx: &LaunchContext) -> anyhow::Result<Vec<LaunchFile>> {
    let c = credentials(ctx)?;
    let home = ctx.session_home;
    let base = c.openai_base().context("Kimi Code needs an API base URL (APIURL=…) in the credentials file")?;
    let toml = format!(
        "default_model = \"libero-kimi\"\ndefault_permission_mode = \"auto\"\nmerge_all_available_skills = false\n\
         builtin_product_skills = false\ntelemetry = false\n\n[providers.libero]\ntype = \"openai\"\nbase_url = {}\n\
         api_key = {}\n\n[models.libero-kimi]\nprovider = \"libero\"\nmodel = {}\nmax_context_size = 200000\n\
         max_output_size = 8192\ncapabilities = [\"thinking\", \"image_in\", \"tool_use\"]\n\n[thinking]\n\
         enabled = true\neffort = {}\nkeep = \"all\"\n\n[loop_control]\nmax_attempts_per_step = 10\n",
        json!(base), json!(c.api_key), json!(ctx.model), json!(ctx.effort)
    );
    let mut mcp = claude_mcp_config(ctx.mcp_url, ctx.mcp_token);
    mcp["mcpServers"][MCP_SERVER_KEY]["startupTimeoutMs"] = json!(600000);
    mcp["mcpServers"][MCP_SERVER_KEY]["toolTimeoutMs"] = json!(600000);
    mcp["mcpServers"][MCP_SERVER_KEY]["enabledTools"] = json!(tool_names());
    Ok(vec![
        (home.join("config.toml"), toml, 0o600),
        (home.join("mcp.json"), serde_json::to_string_pretty(&mcp)?, 0o600),
        (home.join("empty-skills/.keep"), String::new(), 0o600),
    ])
}

fn kimi_command(ctx: &LaunchContext, env: &mut LaunchEnv) -> anyhow::Result<Vec<String>> {
    credentials(ctx)?;
    let home_s = home_s(ctx);
    for (k, v) in [("KIMI_CODE_NO_AUTO_UPDATE", "1"), ("KIMI_CLI_NO_AUTO_UPDATE", "1"), ("KIMI_DISABLE_TELEMETRY", "1"),
        ("KIMI_CODE_BUILTIN_PRODUCT_SKILLS", "0"), ("CHOKIDAR_USEPOLLING", "1"), ("CHOKIDAR_INTERVAL", "1000")]
    {
        env.push((s(k), s(v)));
    }
    env.push((s("KIMI_CODE_HOME"), home_s.clone()));
    let mut a = cli_command(ctx.harness, ctx.npm_cli_installed, ctx.cli_path);
    a.extend([
        s("--model"), s("libero-kimi"), s("--output-format"), s("stream-json"),
        s("--skills-dir"), format!("{home_s}/empty-skills"), s("--prompt"), s(ctx.prompt),
    ]);
    Ok(a)
}

/// QWEN_HOME is Qwen's settings directory itself: `<home>/settings.json` is its user settings, so the episode's
/// server lives there (not in `--mcp-config`), where `qwen mcp list` reads and checks it too.
fn qwen_files(ctx: &LaunchContext) -> anyhow::Result<Vec<LaunchFile>> {
    let settings = json!({"security": {"auth": {"selectedType": "openai"}},
        "model": {"name": ctx.model, "reasoningEffort": ctx.effort},
        "privacy": {"usageStatisticsEnabled": false},
        "telemetry": {"enabled": false, "logPrompts": false, "includeSensitiveSpanAttributes": false},
        "mcpServers": qwen_mcp_config(ctx.mcp_url, ctx.mcp_token)["mcpServers"]});
    Ok(vec![(ctx.session_home.join("settings.json"), serde_json::to_string_pretty(&settings)?, 0o600)])
}

fn qwen_command(ctx: &LaunchContext, env: &mut LaunchEnv) -> anyhow::Result<Vec<String>> {
    let c = credentials(ctx)?;
    let home_s = home_s(ctx);
    env.push((s("OPENAI_API_KEY"), c.api_key.clone()));
    if let Some(b) = c.openai_base() {
        env.push((s("OPENAI_BASE_URL"), b));
    }
    for (k, v) in [("OPENAI_MODEL", ctx.model), ("QWEN_MODEL", ctx.model), ("QWEN_HOME", &home_s),
        ("QWEN_RUNTIME_DIR", &home_s), ("QWEN_DISABLE_TELEMETRY", "1"), ("QWEN_DISABLE_USAGE_STATISTICS", "1")]
    {
        env.push((s(k), s(v)));
    }
    let mut a = cli_command(ctx.harness, ctx.npm_cli_installed, ctx.cli_path);
    a.extend([
        s("--auth-type"), s("openai"), s("--model"), s(ctx.model), s("--allowed-mcp-server-names"), s(MCP_SERVER_KEY),
        s("--approval-mode"), s("yolo"), s("--chat-recording"), s("--output-format"), s("stream-json"), s(ctx.prompt),
    ]);
    Ok(a)
}

/// DeepSeek's credentials and base URL: effort high only, a base URL required.
fn deepseek_base<'a>(ctx: &LaunchContext<'a>) -> anyhow::Result<(&'a Credentials, String)> {
    let c = credentials(ctx)?;
    if ctx.effort != "high" {
        bail!("the DeepSeek harness runs at reasoning effort high only (got {})", ctx.effort);
    }
    let base = c.openai_base().context("the DeepSeek harness needs an API base URL (APIURL=…)")?;
    Ok((c, base))
}

/// dsh's `--patch`: its provider, agent loop and the episode's server through the `mcp-stdio` relay.
fn deepseek_patch_file(ctx: &LaunchContext) -> PathBuf {
    ctx.session_home.join("dsh_mcp.patch.yml")
}

fn deepseek_files(ctx: &LaunchContext) -> anyhow::Result<Vec<LaunchFile>> {
    let (_, base) = deepseek_base(ctx)?;
    let relay = [
        s("mcp-stdio"), s("--url"), s(ctx.mcp_url), s("--bearer-env"), s("LIBERO_MCP_TOKEN"),
    ];
    let patch = format!(
        "- plugin: llm-deepseek\n  config:\n    apiKeyEnv: DEEPSEEK_API_KEY\n    baseURL: {base}\n    thinking: enabled\n    \
         reasoningEffort: high\n    maxTokens: 8192\n    models:\n      - id: {model}\n        contextWindow: 200000\n\
         - plugin: agent-loop\n  config:\n    agents:\n      - id: main\n        provider: deepseek-official\n        \
         model: {model}\n        cwd: {ws}\n- plugin: agent-default-model\n  config:\n    provider: deepseek-official\n    \
         model: {model}\n- plugin: session-persistence-jsonl\n  config:\n    root: {home}/sessions\n    compression: none\n\
         - plugin: '@deepseek-ai/dsh-mcp-client'\n  id: libero-mcp\n  config:\n    serverName: {key}\n    transport: stdio\n    \
         command: {exe}\n    args: {args}\n    cwd: {ws}\n    toolCallTimeoutMs: 600000\n    failOnStartupError: true\n",
        model = json!(ctx.model),
        ws = json!(ctx.workspace),
        home = home_s(ctx),
        key = MCP_SERVER_KEY,
        exe = json!(ctx.self_exe),
        args = json!(relay),
    );
    Ok(vec![(deepseek_patch_file(ctx), patch, 0o600)])
}

fn deepseek_command(ctx: &LaunchContext, env: &mut LaunchEnv) -> anyhow::Result<Vec<String>> {
    let (c, base) = deepseek_base(ctx)?;
    let home_s = home_s(ctx);
    env.push((s("DEEPSEEK_API_KEY"), c.api_key.clone()));
    env.push((s("DEEPSEEK_BASE_URL"), base));
    for (k, v) in [("DSH_HOME", home_s.as_str()), ("DSH_TELEMETRY_DISABLED", "1"), ("DSH_TELEMETRY_MODE", "DISABLED"),
        ("DSH_TOOLS_MODE", "native"), ("DSH_PERMISSION_MODE", "workspace-write")]
    {
        env.push((s(k), s(v)));
    }
    let mut a = cli_command(ctx.harness, ctx.npm_cli_installed, ctx.cli_path);
    a.extend([s("--profile"), s("headless"), s("--patch"), deepseek_patch_file(ctx).to_string_lossy().into_owned(), s(ctx.prompt)]);
    Ok(a)
}

/// `--agent-cmd` with its placeholders expanded to quoted words, run by `/bin/sh -c`.
fn agent_cmd_command(ctx: &LaunchContext, env: &mut LaunchEnv) -> anyhow::Result<Vec<String>> {
    let template = ctx.agent_cmd.context("--harness command needs --agent-cmd \"…\"")?;
    let mcp_config = ctx.workspace.join(".libero/mcp.json");
    let cmd = template
        .replace("{workspace}", &shell_quote(&ctx.workspace.to_string_lossy()))
        .replace("{prompt_file}", &shell_quote(&ctx.prompt_file.to_string_lossy()))
        .replace("{mcp_config}", &shell_quote(&mcp_config.to_string_lossy()))
        .replace("{mcp_url}", &shell_quote(ctx.mcp_url))
        .replace("{model}", &shell_quote(ctx.model))
        .replace("{libero_agent}", &shell_quote(&ctx.self_exe.to_string_lossy()));
    if let Some(c) = ctx.credentials {
        // Explicit credentials for a command agent: its key (the base URL is the gateway's, in the
        // sandbox's LIBERO_MODEL_API_BASE).
        env.push((s("LIBERO_MODEL_API_KEY"), c.api_key.clone()));
        if let Some(b) = &c.api_base {
            env.push((s("LIBERO_MODEL_API_BASE"), b.clone()));
        }
    }
    Ok(vec![s("/bin/sh"), s("-c"), cmd])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The report crate names every harness's logs (the console finds them by its names), so it knows them all.
    #[test]
    fn every_harness_has_its_log_names_in_the_report_crate() {
        use clap::ValueEnum;
        for h in Harness::value_variants() {
            assert_eq!(libero_report::batch::stdout_file(h.as_str()), Some(h.stdout_file()), "{h:?}");
            assert_eq!(libero_report::batch::stderr_file(h.as_str()), Some(format!("{}_stderr.log", h.as_str())), "{h:?}");
        }
    }

    /// A row's name is the harness's name everywhere: the CLI's `--harness` value and the batch files' (serde).
    #[test]
    fn each_row_is_named_as_the_cli_and_the_batch_files_name_its_harness() {
        use clap::ValueEnum;
        for h in Harness::value_variants() {
            let spec = h.spec();
            assert_eq!(h.to_possible_value().unwrap().get_name(), spec.name, "{h:?}");
            assert_eq!(serde_json::to_value(h).unwrap(), spec.name, "{h:?}");
            assert!(libero_report::batch::HARNESSES.contains(&spec.name), "{h:?}");
            assert_eq!(spec.cli == Cli::AgentCmd, !spec.needs_credentials, "{h:?}: only `command` runs without credentials");
            assert_eq!(h.runs_agent_cmd(), h.command().is_none(), "{h:?}");
        }
    }

    fn creds(base: Option<&str>) -> Credentials {
        Credentials { api_base: base.map(str::to_owned), api_key: "sk-test-000000".into(), source: "/c".into() }
    }

    /// The plan's harness-specific parts (the generic ones are `libero_sandbox::agent_net`'s tests): each CLI's
    /// own endpoints below the base, its default base without one, and the credentials the launch gets.
    #[test]
    fn the_agent_sees_the_gateway_s_base_and_only_its_harness_s_endpoints() {
        let c = creds(Some("https://api.example.com/v1/"));
        let p = net_plan(Harness::Codex, "http://127.0.0.1:41234/mcp/ep-1", Some(&c), false).unwrap();
        assert_eq!(agent_credentials(&p, &c).openai_base().as_deref(), Some("http://127.0.0.1:18790/v1"));
        assert_eq!(agent_credentials(&p, &c).api_key, "sk-test-000000");
        let routes: Vec<String> = p.routes.iter().map(ToString::to_string).collect();
        assert_eq!(routes, ["POST /v1/responses", "GET /v1/models"], "Codex's endpoints only");
        // Without a base: the CLI's default upstream.
        let q = net_plan(Harness::ClaudeCode, "http://localhost:18790/mcp/x", Some(&creds(None)), true).unwrap();
        assert_eq!(q.upstream.as_ref().map(|u| u.as_str()), Some("https://api.anthropic.com/"));
        let routes: Vec<String> = q.routes.iter().map(ToString::to_string).collect();
        assert_eq!(routes, ["POST /v1/messages", "POST /v1/messages/count_tokens", "GET /v1/models"]);
        let none = net_plan(Harness::Command, "http://127.0.0.1:8080/mcp/x", None, false).unwrap();
        assert!(none.upstream.is_none() && none.routes.is_empty() && agent_credentials(&none, &creds(None)).api_base.is_none());
        // A command agent with credentials: every API's endpoints below its base (the escape test's `/models` too).
        let cmd = net_plan(Harness::Command, "http://127.0.0.1:8080/mcp/x", Some(&creds(Some("http://127.0.0.1:9/v1"))), false).unwrap();
        let routes: Vec<String> = cmd.routes.iter().map(ToString::to_string).collect();
        for r in ["POST /v1/chat/completions", "POST /v1/responses", "POST /v1/messages", "GET /v1/models"] {
            assert!(routes.contains(&r.to_owned()), "{r}: {routes:?}");
        }
    }

    fn ctx<'a>(h: Harness, creds: Option<&'a Credentials>) -> LaunchContext<'a> {
        LaunchContext {
            harness: h,
            model: "m-1",
            effort: "high",
            workspace: Path::new("/tmp/ws/w1_t14_level3"),
            session_home: Path::new("/b/rollouts/w1/home"),
            prompt: "open the drawer\n\n\nA LIBERO episode…",
            prompt_file: Path::new("/tmp/ws/w1_t14_level3/TASK_PROMPT.txt"),
            mcp_url: "http://127.0.0.1:9/mcp/ep-1",
            mcp_token: "tok123",
            credentials: creds,
            agent_cmd: Some("run {workspace} {libero_agent}"),
            self_exe: Path::new("/opt/libero-agent"),
            sandboxed: true,
            npm_cli_installed: false,
            cli_path: None,
        }
    }

    #[test]
    fn credentials_parse_and_bases_normalise() {
        let c = Credentials::parse("# comment\nAPIURL = https://api.example.com\nAPIKEY=\"sk-abcdefgh\"\n", Path::new("/c")).unwrap();
        assert_eq!(c.api_key, "sk-abcdefgh");
        assert_eq!(c.openai_base().as_deref(), Some("https://api.example.com/v1"));
        let c = Credentials::parse("https://x.test/v1/\nsk-bare-key-1234\n", Path::new("/c")).unwrap();
        assert_eq!((c.api_key.as_str(), c.anthropic_base().as_deref()), ("sk-bare-key-1234", Some("https://x.test")));
        assert!(Credentials::parse("APIURL=https://x\n", Path::new("/c")).is_err());
        assert!(!format!("{c:?}").contains("sk-bare"), "Debug never prints the key");
    }

    /// Neither the API key nor the episode token is ever on a command line (where `/proc/<pid>/cmdline` shows it to
    /// every process of the machine): they travel in the environment or in 0600 files of the session home.
    #[test]
    fn every_launch_names_the_model_and_keeps_the_key_and_token_off_argv() {
        let c = Credentials { api_base: Some("https://api.test".into()), api_key: "sk-secret-key".into(), source: "/c".into() };
        for h in [Harness::Codex, Harness::ClaudeCode, Harness::KimiCode, Harness::QwenCode, Harness::Deepseek] {
            let l = build_launch(&ctx(h, Some(&c))).unwrap();
            assert!(l.argv.iter().all(|a| !a.contains("sk-secret-key") && !a.contains("tok123")), "{h:?}");
            assert!(l.files.iter().filter(|f| f.1.contains("tok123") || f.1.contains("sk-secret-key")).all(|f| f.2 == 0o600), "{h:?}");
            assert!(l.argv.iter().any(|a| a.contains("m-1")) || l.files.iter().any(|f| f.1.contains("m-1")), "{h:?}");
            assert_eq!(l.argv.last().unwrap(), "open the drawer\n\n\nA LIBERO episode…", "{h:?}: prompt last");
            assert!(l.public_argv(ctx(h, None).prompt).contains(&"<task-prompt>".to_owned()));
            assert!(build_launch(&ctx(h, None)).is_err(), "{h:?} without credentials");
        }
        let codex = build_launch(&ctx(Harness::Codex, Some(&c))).unwrap();
        let joined = codex.argv.join(" ");
        assert!(joined.contains("mcp_servers.libero.url=\"http://127.0.0.1:9/mcp/ep-1\""));
        assert!(joined.contains("bearer_token_env_var=\"LIBERO_MCP_TOKEN\"") && !joined.contains("tok123"));
        let qwen = build_launch(&ctx(Harness::QwenCode, Some(&c))).unwrap();
        assert_eq!(qwen.argv[..3], ["npx", "--yes", QWEN_PACKAGE], "the paper's launch through npx");
        let installed = build_launch(&LaunchContext { npm_cli_installed: true, ..ctx(Harness::QwenCode, Some(&c)) }).unwrap();
        assert_eq!((installed.argv[0].as_str(), &installed.argv[1..]), ("qwen", &qwen.argv[3..]), "or the installed pinned CLI");
        let claude = build_launch(&ctx(Harness::ClaudeCode, Some(&c))).unwrap();
        let cfg: Value = serde_json::from_str(&claude.files[0].1).unwrap();
        assert_eq!(cfg["mcpServers"]["libero"]["headers"]["Authorization"], "Bearer tok123");
        assert_eq!(claude.files[0].2, 0o600);
    }

    /// Each CLI's model-API endpoints below the base it makes of the gateway's (the real CLIs: Codex's Responses
    /// API, Claude Code's Messages and token counting, the others' chat completions), and nothing else.
    #[test]
    fn each_harness_calls_its_own_model_api_endpoints_only() {
        let e = |h: Harness, base: &str| h.model_api_endpoints(base).into_iter().map(|(m, p)| format!("{m} {p}")).collect::<Vec<_>>();
        assert_eq!(e(Harness::Codex, "/v1"), ["POST /v1/responses", "GET /v1/models"]);
        assert_eq!(e(Harness::Codex, ""), ["POST /v1/responses", "GET /v1/models"], "openai_base appends /v1");
        assert_eq!(e(Harness::QwenCode, "/api/v1/"), ["POST /api/v1/chat/completions", "GET /api/v1/models"]);
        assert_eq!(e(Harness::KimiCode, "/coding"), ["POST /coding/v1/chat/completions", "GET /coding/v1/models"]);
        assert_eq!(e(Harness::Deepseek, "/"), ["POST /v1/chat/completions", "GET /v1/models"]);
        let claude = ["POST /v1/messages", "POST /v1/messages/count_tokens", "GET /v1/models"];
        assert_eq!(e(Harness::ClaudeCode, "/v1"), claude, "anthropic_base drops /v1, the CLI adds it");
        assert_eq!(e(Harness::ClaudeCode, ""), claude);
        // The same paths the launches' base URLs lead to.
        let c = Credentials { api_base: Some("http://127.0.0.1:18790/api".into()), api_key: "k".into(), source: "/c".into() };
        assert!(e(Harness::Codex, "/api").contains(&format!("POST {}/responses", c.openai_base().unwrap().trim_start_matches("http://127.0.0.1:18790"))));
        assert!(e(Harness::ClaudeCode, "/api").contains(&format!("POST {}/v1/messages", c.anthropic_base().unwrap().trim_start_matches("http://127.0.0.1:18790"))));
        // A command agent: every API, below the base as given and as each CLI would make it.
        let cmd = e(Harness::Command, "/v1");
        assert_eq!(cmd, ["POST /v1/chat/completions", "GET /v1/models", "POST /v1/responses", "POST /v1/messages", "POST /v1/messages/count_tokens"]);
        let bare = e(Harness::Command, "");
        assert!(bare.contains(&"POST /chat/completions".to_owned()) && bare.contains(&"POST /v1/chat/completions".to_owned()), "{bare:?}");
        assert!(!cmd.iter().chain(&bare).any(|r| r.contains("files") || r.contains("batches")));
    }

    /// `run --harness-version`: the same launch, started by the executable of the version asked for.
    #[test]
    fn a_version_asked_for_is_launched_by_its_executable_with_the_same_arguments() {
        let c = Credentials { api_base: Some("https://api.test".into()), api_key: "sk-secret-key".into(), source: "/c".into() };
        for (h, command) in [(Harness::Codex, "codex"), (Harness::ClaudeCode, "claude"), (Harness::QwenCode, "qwen")] {
            let pinned = PathBuf::from(format!("/cache/harnesses/{}-1.2.3/node_modules/.bin/{command}", h.as_str()));
            let default = build_launch(&LaunchContext { npm_cli_installed: true, ..ctx(h, Some(&c)) }).unwrap();
            let chosen = build_launch(&LaunchContext { cli_path: Some(&pinned), ..ctx(h, Some(&c)) }).unwrap();
            assert_eq!(default.argv[0], command, "{h:?}: the command on PATH without --harness-version");
            assert_eq!((chosen.argv[0].as_str(), &chosen.argv[1..]), (pinned.to_str().unwrap(), &default.argv[1..]), "{h:?}");
            assert_eq!(h.version_probe(false, Some(&pinned)).unwrap(), [pinned.to_str().unwrap(), "--version"]);
        }
        assert_eq!(Harness::Codex.version_probe(false, None).unwrap(), ["codex", "--version"]);
        assert_eq!(Harness::KimiCode.version_probe(false, None).unwrap(), ["npx", "--yes", KIMI_PACKAGE, "--version"]);
        assert_eq!(Harness::Command.version_probe(false, Some(Path::new("/x"))), None);
    }

    #[test]
    fn command_placeholders_expand_to_quoted_words() {
        let l = build_launch(&ctx(Harness::Command, None)).unwrap();
        assert_eq!(l.argv[2], "run '/tmp/ws/w1_t14_level3' '/opt/libero-agent'");
        assert_eq!(shell_quote("a'b"), r"'a'\''b'");
    }
}
