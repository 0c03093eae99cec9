//! The launches of [`build_launch`] read by the real agent CLIs, without any model: each check builds the
//! launch `run` would build for a live T14 episode of an in-process server (session home, environment, the CLI's
//! configuration files), starts the CLI's own MCP command inside the bubblewrap sandbox exactly as `run` starts
//! the agent, and reads what the CLI says about the episode's server. The CLIs are the pinned ones that
//! `scripts/setup.py --test` installs under the cache's `node/node_modules/.bin`; a missing one fails the test
//! with the command that installs it. Whole episodes driven by Claude Code and Codex are `tests/real_clis.rs`.
use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};

use serde_json::{Value, json};

use super::harness::{
    Credentials, Harness, Launch, LaunchContext, QWEN_PACKAGE, agent_credentials, build_launch, claude_mcp_config, net_plan, qwen_mcp_config,
};
use libero_sandbox::agent_net::{NetPlan, contain};
use super::rollout::write_launch_files;
use libero_sandbox::sandbox::Sandbox;
use libero_server::client::{InProcessServer, prepare_episode};
use libero_server::episodes::{PrepareRequest, Prepared};

const SETUP_HINT: &str = "run `python3 scripts/setup.py --test`, which installs the pinned agent CLIs with npm into \
                          ~/.cache/libero-agent/node (and the paper's versions into ~/.cache/libero-agent/harnesses)";

/// Where `scripts/setup.py --test` puts the CLIs' commands (and the Node 22 they run on).
fn cli_dir() -> PathBuf {
    let cache = std::env::var_os("LIBERO_AGENT_CACHE")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cache/libero-agent"));
    cache.join("node/node_modules/.bin")
}

/// The `libero-agent` binary whose `sandbox-net` starts every sandboxed process (built beside the test binaries
/// by `cargo test --workspace`).
fn libero_agent_exe() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let p = exe.parent().and_then(Path::parent).map(|d| d.join("libero-agent")).unwrap();
    assert!(p.is_file(), "{} is missing: cargo build -p libero-agent", p.display());
    p
}

fn require_cli(name: &str) -> PathBuf {
    let p = cli_dir().join(name);
    assert!(p.is_file(), "{} is missing: {SETUP_HINT}", p.display());
    p
}

/// A live episode of its own server; the session home is the one `run` would give its agent.
struct Episode {
    server: Option<InProcessServer>,
    prepared: Prepared,
    token: String,
    home: PathBuf,
    _dir: tempfile::TempDir,
}

impl Episode {
    fn start() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let server = InProcessServer::start(dir.path().join("data"), "test_finished").unwrap();
        let req = PrepareRequest {
            level: 3,
            workspace: Some(dir.path().join("ws")),
            wall_time_s: 120.0,
            max_agent_steps: 10,
            ..PrepareRequest::new("T14")
        };
        let prepared = prepare_episode(&server.url, &req).unwrap();
        let token = prepared.mcp_headers["Authorization"].trim_start_matches("Bearer ").to_owned();
        let home = dir.path().join("home");
        std::fs::create_dir(&home).unwrap();
        Self { server: Some(server), prepared, token, home, _dir: dir }
    }

    /// The launch `run` builds for `harness`, with the cache's CLIs first on the child's PATH. The model API is
    /// a closed loopback port: nothing here talks to a model, and nothing waits on a name lookup.
    fn launch(&self, harness: Harness) -> Launch {
        let creds = Credentials { api_base: Some("http://127.0.0.1:9".into()), api_key: "sk-config-check-0123".into(), source: "/c".into() };
        let creds = agent_credentials(&self.plan(harness), &creds);
        let prompt_file = self.prepared.prompt_file.clone();
        let ctx = LaunchContext {
            harness,
            model: "scripted",
            effort: "high",
            workspace: &self.prepared.workspace,
            session_home: &self.home,
            prompt: "check the configuration",
            prompt_file: &prompt_file,
            mcp_url: &self.prepared.mcp_url,
            mcp_token: &self.token,
            credentials: Some(&creds),
            agent_cmd: None,
            self_exe: Path::new("/nonexistent/libero-agent"),
            sandboxed: true,
            npm_cli_installed: true,
            cli_path: None,
        };
        let mut launch = build_launch(&ctx).unwrap();
        for (k, v) in &mut launch.env {
            if k == "PATH" {
                *v = format!("{}:{v}", cli_dir().display());
            }
        }
        write_launch_files(&launch).unwrap();
        launch
    }

    /// The agent's network as `run` plans it: the model API is the launch's closed loopback port.
    fn plan(&self, harness: Harness) -> NetPlan {
        let creds = Credentials { api_base: Some("http://127.0.0.1:9".into()), api_key: "sk-config-check-0123".into(), source: "/c".into() };
        net_plan(harness, &self.prepared.mcp_url, Some(&creds), false).unwrap()
    }

    /// Runs `argv` as `run` runs the agent: sandboxed in its own network namespace behind the runner's relays, in
    /// the workspace, with exactly the launch's environment.
    fn run_contained(&self, harness: Harness, launch: &Launch, argv: &[&str]) -> Output {
        let argv: Vec<String> = argv.iter().map(|a| (*a).to_owned()).collect();
        let sandbox = Sandbox::detect().unwrap();
        let this = Launch { argv, env: launch.env.clone(), files: Vec::new() };
        let private = self._dir.path().join(format!("private-{}", harness.as_str()));
        let mut contained =
            contain(Some(&sandbox), Some(&self.plan(harness)), &this.argv, &this.env, &self.prepared.workspace, &self.home, &libero_agent_exe(), &private).unwrap();
        assert!(contained.argv.iter().all(|a| !a.contains(&self.token)), "the episode token is on a command line: {:?}", contained.argv);
        let mut cmd = contained.command();
        let out = cmd.current_dir(&self.prepared.workspace).stdin(Stdio::null()).output().unwrap();
        contained.spawned();
        let argv = this.argv;
        eprintln!("$ {}\n{}{}", argv.join(" "), String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        out
    }
}

impl Drop for Episode {
    fn drop(&mut self) {
        if let Some(s) = self.server.take() {
            let _ = s.stop();
        }
    }
}

fn text(out: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

/// The launch's file named `name` in the session home, as JSON.
fn launch_file(launch: &Launch, name: &str) -> Value {
    let (_, content, mode) = launch.files.iter().find(|f| f.0.ends_with(name)).unwrap_or_else(|| panic!("no {name} in the launch"));
    assert_eq!(*mode, 0o600, "{name} holds the episode token");
    serde_json::from_str(content).unwrap()
}

/// The paper's CLI versions (App. A: Codex 0.154.0, Claude Code 2.1.139), installed apart by `scripts/setup.py
/// --harnesses` (part of `--test`), and the tests' versions are what `run --harness-version` resolves them to: each
/// executable found prints exactly the version asked for.
#[test]
fn the_papers_and_the_tests_cli_versions_resolve_to_executables_that_print_them() {
    use super::harness_versions::{install_dir, probe, resolve};
    let cache = libero_sandbox::host_paths::cache_dir();
    let path = std::ffi::OsString::from(format!("{}:/usr/bin:/bin", cli_dir().display()));
    for (harness, version) in [(Harness::Codex, "0.154.0"), (Harness::ClaudeCode, "2.1.139"), (Harness::Codex, "0.169.0"), (Harness::ClaudeCode, "2.1.330")] {
        let exe = resolve(harness, version, &cache, &path).unwrap_or_else(|e| panic!("{e:#}\n({SETUP_HINT})"));
        let v = probe(&[exe.to_string_lossy().into_owned(), "--version".into()], &path);
        assert_eq!(v.observed.as_deref(), Some(version), "{} --version: {v:?}", exe.display());
        if version == "0.154.0" || version == "2.1.139" {
            assert!(exe.starts_with(install_dir(&cache, harness, version)), "the paper's version installed apart: {}", exe.display());
        }
    }
}

/// `claude mcp list` health-checks every server of its configured scopes (it ignores `--mcp-config`), so the
/// server entry of the launch's `--mcp-config` file goes, unchanged, into the user scope of the launch's
/// CLAUDE_CONFIG_DIR. From inside the sandbox Claude Code reaches the episode with its token; with a wrong token
/// it does not, so "Connected" is the endpoint's answer, not the CLI's assumption.
#[test]
fn claude_code_health_check_connects_to_the_episode_from_inside_the_sandbox() {
    require_cli("claude");
    let ep = Episode::start();
    let h = Harness::ClaudeCode;
    let launch = ep.launch(h);
    let cfg = launch_file(&launch, "mcp.json");
    let config_arg = launch.argv.iter().position(|a| a == "--mcp-config").map(|i| &launch.argv[i + 1]);
    assert_eq!(config_arg.map(PathBuf::from), Some(ep.home.join("mcp.json")), "{:?}", launch.argv);
    let user_scope = |servers: &Value| std::fs::write(ep.home.join(".claude.json"), json!({"mcpServers": servers}).to_string()).unwrap();
    user_scope(&cfg["mcpServers"]);
    let out = ep.run_contained(h, &launch, &["claude", "mcp", "list"]);
    let said = text(&out);
    assert!(out.status.success(), "claude mcp list: {said}");
    let line = said.lines().find(|l| l.starts_with("libero:")).unwrap_or_else(|| panic!("no libero server listed: {said}"));
    assert!(line.contains(&ep.prepared.mcp_url) && line.contains("Connected"), "claude mcp list: {line}");
    user_scope(&claude_mcp_config(&ep.prepared.mcp_url, "wrong-token")["mcpServers"]);
    let said = text(&ep.run_contained(h, &launch, &["claude", "mcp", "list"]));
    assert!(said.contains("libero:") && !said.contains("Connected"), "a wrong token must not connect: {said}");
}

/// Codex shows the server the launch's `--config` overrides define: streamable HTTP at the episode's URL, the
/// token named by its environment variable (set in the launch's environment, never written into the config),
/// the episode's tools and timeouts. Run in the sandbox with the launch's CODEX_HOME and environment.
#[test]
fn codex_shows_the_launch_s_server_with_its_token_variable() {
    require_cli("codex");
    let ep = Episode::start();
    let h = Harness::Codex;
    let launch = ep.launch(h);
    let overrides: Vec<&str> = launch.argv.windows(2).filter(|w| w[0] == "--config").map(|w| w[1].as_str()).collect();
    assert!(overrides.iter().any(|o| o.starts_with("openai_base_url=")), "{overrides:?}");
    let mut argv = vec!["codex"];
    for o in &overrides {
        argv.extend(["--config", o]);
    }
    argv.extend(["mcp", "get", "libero", "--json"]);
    let out = ep.run_contained(h, &launch, &argv);
    assert!(out.status.success(), "codex mcp get: {}", text(&out));
    let v: Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("codex mcp get --json: {e}: {}", text(&out)));
    let t = &v["transport"];
    assert_eq!((t["type"].as_str(), t["url"].as_str()), (Some("streamable_http"), Some(ep.prepared.mcp_url.as_str())), "{v}");
    assert_eq!(t["bearer_token_env_var"], "LIBERO_MCP_TOKEN", "{v}");
    assert!(t["http_headers"].is_null(), "no token in the configuration: {v}");
    assert_eq!(v["enabled_tools"], json!(["start_episode", "osc_sequence", "finish_episode"]), "{v}");
    assert_eq!((v["startup_timeout_sec"].as_f64(), v["tool_timeout_sec"].as_f64()), (Some(30.0), Some(600.0)), "{v}");
    assert!(launch.env.iter().any(|(k, val)| k == "LIBERO_MCP_TOKEN" && *val == ep.token), "the variable holds the token");
}

/// Qwen Code (the version the launch's `npx` names) reads the launch's settings from QWEN_HOME and its own
/// `qwen mcp list` connects to the episode's server from inside the sandbox; a wrong token does not connect.
#[test]
fn qwen_code_health_check_connects_to_the_episode_from_inside_the_sandbox() {
    require_cli("qwen");
    let ep = Episode::start();
    let h = Harness::QwenCode;
    let launch = ep.launch(h);
    assert_eq!(launch.argv[0], "qwen", "the installed pinned CLI, not npx");
    let version = ep.run_contained(h, &launch, &["qwen", "--version"]);
    let pinned = QWEN_PACKAGE.rsplit('@').next().unwrap_or_default();
    assert_eq!(String::from_utf8_lossy(&version.stdout).trim(), pinned, "the installed Qwen Code is the one the launch names");
    let settings = launch_file(&launch, "settings.json");
    assert_eq!(settings["mcpServers"], qwen_mcp_config(&ep.prepared.mcp_url, &ep.token)["mcpServers"]);
    let out = ep.run_contained(h, &launch, &["qwen", "mcp", "list"]);
    let said = text(&out);
    assert!(out.status.success(), "qwen mcp list: {said}");
    let line = said.lines().find(|l| l.contains("libero:")).unwrap_or_else(|| panic!("no libero server listed: {said}"));
    assert!(line.contains(&ep.prepared.mcp_url) && line.contains("Connected") && !line.contains("Disconnected"), "{line}");
    let mut wrong = settings.clone();
    wrong["mcpServers"] = qwen_mcp_config(&ep.prepared.mcp_url, "wrong-token")["mcpServers"].clone();
    std::fs::write(ep.home.join("settings.json"), wrong.to_string()).unwrap();
    let said = text(&ep.run_contained(h, &launch, &["qwen", "mcp", "list"]));
    assert!(said.contains("libero:") && said.contains("Disconnected"), "a wrong token must not connect: {said}");
}
