//! One rollout: prepare the episode (fresh workspace), launch the agent in its sandbox, supervise it against
//! the wall clock, end the episode if the agent did not, classify the outcome (§4.8), account time and tokens,
//! scrub logs. No retries: whatever happens is the rollout's record.
use std::fs;
use std::os::unix::fs::PermissionsExt;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use anyhow::Context;
use libero_records::batch_doc::HarnessVersion;
use libero_records::batch_doc::harness_manifest::{CREDENTIAL_MATERIAL_NEVER_RECORDED, HARNESS_MANIFEST_SCHEMA, HarnessManifest};
use libero_episode::demo::DemoCondition;
use libero_records::json::{utc_now_iso, write_json_file};
use libero_records::episode_view::{EpisodeState, EpisodeView};
use libero_records::records::RunResult;
use libero_metrics::Outcome;
use libero_report::batch::{Demo, RolloutRecord};
use libero_report::usage::Usage;
use serde_json::{Value, json};

use super::harness::{Harness, Launch, LaunchContext, agent_credentials, build_launch, net_plan};
use super::harness_versions::probe_cli;
use libero_sandbox::agent_net::{Contained, NetPlan, contain};
use libero_sandbox::resources::RolloutCage;
use libero_sandbox::sandbox::Sandbox;
use super::schedule::PlannedRollout;
use libero_sandbox::logs::{Limits, scrub_log, scrub_text};
use super::transcript::Follower;
use super::usage::UsageScanner;
use super::{INTERRUPTED, RunContext};
use libero_server::client::{episode, episode_result, post_json, prepare_episode};
use libero_server::episodes::{PrepareRequest, Prepared};

/// Supervision poll period.
const POLL: Duration = Duration::from_millis(250);
/// After the episode ended, how long the agent may keep running (to read the verdict) before it is stopped.
const AFTER_FINISH_GRACE: Duration = Duration::from_secs(5);
/// After the agent exited without finishing, how long the episode may still end (an in-flight call).
const AGENT_EXIT_GRACE: Duration = Duration::from_secs(15);
/// Beyond the episode's wall budget, how long the agent may run before the watchdog kills it (§8.4: 15 + 30 s).
pub const WATCHDOG_GRACE_S: f64 = 45.0;
/// SIGTERM → SIGKILL grace for the agent's process group.
const KILL_GRACE: Duration = Duration::from_secs(10);

/// The rollout's outcome rule and the watchdog's error text live with the records (one home for §4.8).
pub use libero_records::records::{WATCHDOG_ERROR, classify_rollout as classify};

/// Why an agent whose harness exited before `finish_episode` should not be judged, if anything but the agent
/// caused it: the sandbox never started, or the model API failed it (the gateway's records, which the agent cannot
/// write). Without a sandbox there is no gateway and no boundary, so every early exit stays the harness's error.
fn quit_cause(sandboxed: bool, sandbox_reported: bool, model_api_records: Option<&Path>) -> Option<String> {
    if !sandboxed {
        return Some("unsandboxed runs cannot tell an agent's exit from a harness failure".into());
    }
    if !sandbox_reported {
        return Some("the sandbox did not start".into());
    }
    model_api_records.and_then(libero_sandbox::netgate::last_model_api_failure)
}

/// An episode the agent left open (`what` happened): the infrastructure's failure when `cause` names one
/// (excluded and rescheduled, as the original does), else the agent's own doing, its FAIL through the server's
/// forfeit with `reason`, never a free rerun. Returns the infrastructure error, if any.
fn end_left_episode(ctx: &RunContext, episode_id: &str, what: &str, reason: &str, cause: Option<String>) -> Option<String> {
    if let Some(cause) = cause {
        return Some(format!("{what}: {cause}"));
    }
    let url = format!("/api/episodes/{episode_id}/forfeit");
    post_json(&ctx.server_url, &url, &json!({"reason": reason}))
        .err()
        .map(|e| format!("{what}, and the server could not record it as the agent's failure: {e}"))
}

/// Replaces the API key, `sk-…` tokens and `Bearer …` values with `<redacted>` (the same matcher as the logs'
/// streaming scrubber, [`libero_sandbox::logs`]).
pub fn scrub(text: &str, secrets: &[&str]) -> String {
    scrub_text(text, secrets)
}

/// The episode as the server's API shows it; None when the server cannot be asked. The runner learns about its
/// episode only here and from [`verdict`], never from the server's run directory: a queue's worker and the server
/// may be on different machines.
fn episode_view(ctx: &RunContext, episode_id: &str) -> Option<EpisodeView> {
    episode(&ctx.server_url, episode_id).ok()
}

/// Whether the episode has ended, as the server says (it writes `result.json` before it says so).
fn episode_ended(ctx: &RunContext, episode_id: &str) -> bool {
    episode_view(ctx, episode_id).is_some_and(|v| v.has_ended())
}

fn kill_group(child: &mut Child) {
    let pgid = child.id() as i32;
    // SAFETY: kill(2) on the process group we created for the agent; no memory is touched.
    unsafe { libc::kill(-pgid, libc::SIGTERM) };
    let t = Instant::now();
    while t.elapsed() < KILL_GRACE {
        if matches!(child.try_wait(), Ok(Some(_))) {
            // The leader is gone; make sure nothing of the group lingers.
            unsafe { libc::kill(-pgid, libc::SIGKILL) };
            return;
        }
        std::thread::sleep(POLL);
    }
    unsafe { libc::kill(-pgid, libc::SIGKILL) };
    let _ = child.wait();
}

/// Scrubs the agent's logs in place and reads the token usage from its stdout on the way, in one bounded pass
/// per log ([`scrub_log`]: the first and last 8 MiB kept, scrubbed, the size and SHA-256 of the rest recorded;
/// opened without following a link). The usage comes from what the harness itself printed on stdout, which the
/// runner captures into the rollout directory outside the sandbox: the one channel the agent cannot write to.
/// Session logs in the agent's home or workspace are never read (the agent could forge them, or plant links and
/// FIFOs there). Codex prints its events on stdout with `--json`, one `turn.completed` usage per turn. Returns the
/// usage and, per log file name, what was kept (or why the log could not be scrubbed).
fn scrub_logs(harness: Harness, stdout: &Path, stderr: &Path, secrets: &[&str]) -> (Usage, Value) {
    let mut usage = UsageScanner::new(harness.spec().usage);
    let mut logs = serde_json::Map::new();
    for (path, is_stdout) in [(stdout, true), (stderr, false)] {
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let scrubbed = scrub_log(path, secrets, &Limits::DEFAULT, |bytes| {
            if is_stdout {
                match bytes {
                    Some(b) => usage.push(b),
                    None => usage.gap(),
                }
            }
        });
        let entry = match scrubbed {
            Ok(r) => json!(r),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => {
                eprintln!("libero-agent: cannot scrub {}: {e}", path.display());
                json!({"error": format!("not scrubbed: {e}")})
            }
        };
        logs.insert(name, entry);
    }
    (usage.finish(), Value::Object(logs))
}

/// Writes the files a launch needs first (CLI configuration, 0600 where it holds a token or key).
pub fn write_launch_files(launch: &Launch) -> anyhow::Result<()> {
    for (path, content, mode) in &launch.files {
        if let Some(p) = path.parent() {
            fs::create_dir_all(p)?;
        }
        fs::write(path, content)?;
        fs::set_permissions(path, fs::Permissions::from_mode(*mode))?;
    }
    Ok(())
}

/// Replaces the launch's files in the session home with what the runner wrote there, secrets scrubbed. What is
/// there now is never read: the home is the agent's to write, and any entry in it may have become a link to a
/// host file or a FIFO. Entries are reached through directory handles that refuse links.
fn scrub_launch_files(home: &Path, launch: &Launch, secrets: &[&str]) {
    for (path, content, mode) in &launch.files {
        if let Err(e) = replace_file_under(home, path, scrub(content, secrets).as_bytes(), *mode) {
            eprintln!("libero-agent: cannot scrub {}: {e}", path.display());
        }
    }
}

/// Puts a new file with `bytes` at `path` (below `root`), whatever entry was there, following no link on the way.
pub fn replace_file_under(root: &Path, path: &Path, bytes: &[u8], mode: u32) -> std::io::Result<()> {
    use libero_episode::dirfd;
    use std::os::fd::AsFd;
    let outside = || std::io::Error::other(format!("{} is not a plain path below {}", path.display(), root.display()));
    let rel = path.strip_prefix(root).map_err(|_| outside())?;
    let mut names = Vec::new();
    for c in rel.components() {
        match c {
            std::path::Component::Normal(n) => names.push(n.to_str().ok_or_else(outside)?),
            _ => return Err(outside()),
        }
    }
    let name = names.pop().ok_or_else(outside)?;
    let mut dir = dirfd::open_dir_path(root)?;
    for n in names {
        dir = dirfd::open_dir_at(dir.as_fd(), n)?;
    }
    dirfd::remove_at(dir.as_fd(), name)?;
    dirfd::write_new_file_mode_at(dir.as_fd(), name, bytes, mode)
}

/// Copies a file the runner created (the CLI's log, opened without following a link), at most its scrubbed size.
fn copy_own_file(from: &Path, to: &Path) -> std::io::Result<u64> {
    use std::os::unix::fs::OpenOptionsExt;
    let mut src = fs::OpenOptions::new().read(true).custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK).open(from)?;
    if !src.metadata()?.is_file() {
        return Err(std::io::Error::other("not a plain file"));
    }
    let mut dst = fs::OpenOptions::new().write(true).create_new(true).custom_flags(libc::O_NOFOLLOW).open(to)?;
    std::io::copy(&mut std::io::Read::take(&mut src, 64 << 20), &mut dst)
}

/// Runs one rollout to its record.
pub fn run_rollout(ctx: &RunContext, plan: &PlannedRollout) -> RolloutRecord {
    let mut rec = RolloutRecord::from(plan);
    if let Err(e) = supervise(ctx, plan, &mut rec) {
        rec.infrastructure_error.get_or_insert_with(|| format!("{e:#}"));
        rec.outcome = if INTERRUPTED.load(Ordering::SeqCst) { Outcome::Interrupted } else { Outcome::Invalid };
    }
    rec.finished_at = utc_now_iso();
    rec
}

fn supervise(ctx: &RunContext, plan: &PlannedRollout, rec: &mut RolloutRecord) -> anyhow::Result<()> {
    let ready = prepare(ctx, plan, rec)?;
    let (agent, launched) = launch(ctx, plan, &ready, rec)?;
    let watched = watch(ctx, &ready, agent);
    collect(ctx, ready, launched, watched, rec)
}

/// A rollout ready to launch: its directory and cage, its sandbox, the agent's session home and log directory, and
/// the episode the server prepared for it (with its bearer token and prompt).
struct Ready {
    dir: PathBuf,
    cage: Option<RolloutCage>,
    sandbox: Option<Sandbox>,
    home: PathBuf,
    log_dir: PathBuf,
    prepared: Prepared,
    token: String,
    prompt: String,
}

/// The agent as it runs: what [`watch`] waits on and ends (fields in the order they are dropped).
struct Agent {
    transcript: Follower,
    child: Child,
    t0: Instant,
    contained: Contained,
}

/// What [`collect`] needs of the launch: the sandbox's own report, the manifest so far, the CLI's logs, and the
/// launch itself (its files are scrubbed at the end).
struct Launched {
    sandbox_report: Option<Value>,
    manifest: HarnessManifest,
    logs: AgentLogs,
    launch: Launch,
}

/// The CLI's stdout and stderr: their names in the rollout directory and where the agent writes them.
struct AgentLogs {
    stdout_name: String,
    stderr_name: String,
    stdout: PathBuf,
    stderr: PathBuf,
}

/// How the watch ended: the agent stopped, its relays gone.
struct Watched {
    /// The infrastructure's error so far (an interrupt).
    infra: Option<String>,
    exit_code: Option<i32>,
    /// The agent exited and the episode did not end within [`AGENT_EXIT_GRACE`].
    quit_before_finish: bool,
    /// The wall budget and [`WATCHDOG_GRACE_S`] passed.
    watchdog: bool,
    elapsed_s: f64,
    model_api_records: Option<PathBuf>,
    transcript: super::transcript::Summary,
}

/// The rollout's directory, its cage (cgroups, its own uid, a capped disk), and the episode prepared on the server
/// with the workspace the cage holds.
fn prepare(ctx: &RunContext, plan: &PlannedRollout, rec: &mut RolloutRecord) -> anyhow::Result<Ready> {
    let dir = ctx.batch_dir.join("rollouts").join(&plan.rollout_id);
    fs::create_dir_all(ctx.batch_dir.join("rollouts"))?;
    fs::create_dir(&dir).with_context(|| format!("{} already exists (an earlier attempt)", dir.display()))?;
    // The rollout's cage: its cgroups, its own uid, and its capped disk holding the workspace, the session home,
    // the sandbox's /tmp and the CLI's logs (`resources`); without caps, the home and logs lie in the rollout
    // directory and the workspace in the workspace root.
    let resources = ctx.sandbox.as_ref().and_then(|s| s.resources.as_ref());
    let cage = resources.map(|r| r.for_rollout(&plan.rollout_id, &ctx.workspace_root)).transpose().context("cannot make the rollout's cage")?;
    let sandbox = ctx.sandbox.as_ref().map(|s| s.for_cage(cage.as_ref()));
    let home = match cage.as_ref().and_then(|c| c.home()) {
        Some(h) => h,
        None => {
            let h = dir.join("home");
            fs::create_dir(&h)?;
            fs::set_permissions(&h, fs::Permissions::from_mode(0o700))?;
            h
        }
    };
    let workspace = cage.as_ref().and_then(|c| c.workspace()).unwrap_or_else(|| ctx.workspace_root.join(&plan.rollout_id));
    let log_dir = cage.as_ref().and_then(|c| c.logs()).unwrap_or_else(|| dir.clone());
    let req = PrepareRequest {
        level: plan.level,
        seed: ctx.settings.seed,
        workspace: Some(workspace.clone()),
        wall_time_s: ctx.settings.wall_time_s,
        max_agent_steps: ctx.settings.max_agent_steps,
        demo: match plan.demo {
            Demo::None => DemoCondition::None,
            Demo::Video => DemoCondition::Video,
            Demo::VideoTraj => DemoCondition::VideoTraj,
        },
        // The dashboard's episode table shows and filters by these.
        harness: Some(ctx.settings.harness.clone()),
        model: Some(ctx.settings.model.clone()),
        batch: Some(ctx.batch_name.clone()),
        ..PrepareRequest::new(plan.task.clone())
    };
    let prepared = prepare_episode(&ctx.server_url, &req).context("episode preparation failed")?;
    rec.episode_id = Some(prepared.episode_id.clone());
    rec.workspace = Some(prepared.workspace.clone());
    rec.run_dir = Some(prepared.run_dir.clone());
    let token = prepared.mcp_headers.get("Authorization").map(|t| t.trim_start_matches("Bearer ").to_owned()).unwrap_or_default();
    let prompt = fs::read_to_string(&prepared.prompt_file).context("cannot read the prepared prompt")?;
    Ok(Ready { dir, cage, sandbox, home, log_dir, prepared, token, prompt })
}

/// The harness's launch, contained in the sandbox with its network plan, started in its own process group in the
/// cage, its transcript followed and its manifest written.
fn launch(ctx: &RunContext, plan: &PlannedRollout, ready: &Ready, rec: &mut RolloutRecord) -> anyhow::Result<(Agent, Launched)> {
    let Ready { dir, cage, sandbox, home, log_dir, prepared, token, prompt } = ready;
    let (net, launch) = launch_of(ctx, ready)?;
    // The version this rollout runs: `--version` of the very executable launched next, not the batch's first look.
    rec.harness_version = probe_cli(ctx.harness, ctx.npm_cli_installed, ctx.cli_path.as_deref());
    write_launch_files(&launch)?;
    let mut contained = contain(sandbox.as_ref(), net.as_ref(), &launch.argv, &launch.env, &prepared.workspace, home, &ctx.self_exe, &dir.join("sandbox"))?;
    let stdout_name = ctx.harness.stdout_file();
    let stderr_name = format!("{}_stderr.log", ctx.harness.as_str());
    let logs = AgentLogs { stdout: log_dir.join(&stdout_name), stderr: log_dir.join(&stderr_name), stdout_name, stderr_name };
    let mut manifest = HarnessManifest {
        schema_version: Some(HARNESS_MANIFEST_SCHEMA.into()),
        rollout_id: Some(plan.rollout_id.clone()),
        created_at: Some(utc_now_iso()),
        harness: Some(ctx.harness.as_str().into()),
        model_requested: Some(ctx.settings.model.clone()),
        effort: Some(ctx.settings.effort.clone()),
        harness_version: rec.harness_version.clone().or_else(|| HarnessVersion::from_value(ctx.harness_version.clone()).ok()),
        api_protocol: Some(ctx.harness.api_protocol().into()),
        credential_source: Some(ctx.credentials.as_ref().map(|c| c.source.clone())),
        credential_material: Some(CREDENTIAL_MATERIAL_NEVER_RECORDED.into()),
        sandbox: Some(sandbox.as_ref().map(|s| doc(s.describe()))),
        // A result is only comparable with the same toolbox: null is the system's python3 alone.
        toolbox: Some(ctx.sandbox.as_ref().and_then(|s| s.toolbox.as_ref()).map(|t| doc(t.describe()))),
        network: Some(net.as_ref().map(|n| doc(n.describe()))),
        episode_id: Some(prepared.episode_id.clone()),
        workspace: Some(prepared.workspace.clone()),
        private_run: Some(prepared.run_dir.clone()),
        session_home: Some(home.clone()),
        command: Some(launch.public_argv(prompt)),
        task: Some(plan.task.clone()),
        level: Some(plan.level.into()),
        demo: Some(plan.demo.as_str().into()),
        seed: Some(ctx.settings.seed),
        max_wall_time_seconds: Some(ctx.settings.wall_time_s),
        max_agent_steps: Some(ctx.settings.max_agent_steps),
        ..HarnessManifest::default()
    };
    write_manifest(dir, &manifest)?;
    let mut cmd = contained.command();
    cmd.current_dir(&prepared.workspace)
        .stdin(Stdio::null())
        .stdout(fs::File::create(&logs.stdout)?)
        .stderr(fs::File::create(&logs.stderr)?)
        .process_group(0);
    if let Some(c) = cage {
        // SAFETY: the hook makes only async-signal-safe calls (open, write, close) on paths made beforehand.
        unsafe { cmd.pre_exec(c.attach_hook()) };
    }
    let t0 = Instant::now();
    let child = cmd.spawn().with_context(|| format!("cannot start {}", contained.argv[0]))?;
    contained.spawned();
    // The agent's transcript as it prints it, beside the robot's calls (docs/agent_transcript.md).
    let transcript = super::transcript::follow_rollout(super::transcript::RolloutTranscript {
        harness: ctx.harness,
        workspace: &prepared.workspace,
        secrets: &ctx.credentials.iter().map(|c| c.api_key.as_str()).chain([token.as_str()]).collect::<Vec<_>>(),
        streams: super::transcript::Streams { stdout: logs.stdout.clone(), stderr: logs.stderr.clone(), gateway: contained.model_api_records.clone() },
        server_url: &ctx.server_url,
        episode_id: &prepared.episode_id,
        run_dir: &prepared.run_dir,
        rollout_dir: dir,
    });
    // What the sandbox is, as its first process saw it before the agent started (ids, capabilities, mounts).
    let sandbox_report = if ctx.sandbox.is_some() { contained.report(Duration::from_secs(30)) } else { None };
    manifest.sandbox_report = Some(sandbox_report.clone().map(doc));
    manifest.relay_dir = Some(contained.relay_dir().map(Path::to_path_buf));
    write_manifest(dir, &manifest)?;
    Ok((Agent { transcript, child, t0, contained }, Launched { sandbox_report, manifest, logs, launch }))
}

/// Writes the rollout's `harness_manifest.json` as it stands (each of its three writes replaces the last).
fn write_manifest(rollout_dir: &Path, manifest: &HarnessManifest) -> anyhow::Result<()> {
    manifest.write(rollout_dir).with_context(|| format!("cannot write the harness manifest in {}", rollout_dir.display()))
}

/// A typed manifest part from what the sandbox crate and the runner describe as JSON. Every key is kept (the
/// records keep what they do not name); each description, and sandbox-net's report, is an object (anything else
/// would read as an empty part).
fn doc<T: serde::de::DeserializeOwned + Default>(described: Value) -> T {
    serde_json::from_value(described).unwrap_or_default()
}

/// The agent's network plan (its endpoint and its model API through the runner's relays, nothing else; none
/// without a sandbox) and the harness's launch, built with the credentials as the agent sees them.
fn launch_of(ctx: &RunContext, ready: &Ready) -> anyhow::Result<(Option<NetPlan>, Launch)> {
    let prepared = &ready.prepared;
    let via_npx = ctx.harness.npm_cli().is_some() && !ctx.npm_cli_installed && ctx.cli_path.is_none();
    let net = match ctx.sandbox {
        Some(_) => Some(net_plan(ctx.harness, &prepared.mcp_url, ctx.credentials.as_ref(), via_npx)?),
        None => None,
    };
    let agent_credentials = ctx.credentials.as_ref().map(|c| match &net {
        Some(p) => agent_credentials(p, c),
        None => c.clone(),
    });
    let lctx = LaunchContext {
        harness: ctx.harness,
        model: &ctx.settings.model,
        effort: &ctx.settings.effort,
        workspace: &prepared.workspace,
        session_home: &ready.home,
        prompt: &ready.prompt,
        prompt_file: &prepared.prompt_file,
        mcp_url: &prepared.mcp_url,
        mcp_token: &ready.token,
        credentials: agent_credentials.as_ref(),
        agent_cmd: ctx.settings.agent_cmd.as_deref(),
        self_exe: &ctx.self_exe,
        sandboxed: ctx.sandbox.is_some(),
        npm_cli_installed: ctx.npm_cli_installed,
        cli_path: ctx.cli_path.as_deref(),
    };
    let launch = build_launch(&lctx)?;
    Ok((net, launch))
}

/// Waits until the episode ended and the agent exited (or either's grace ran out), the wall budget and the
/// watchdog's grace passed, or the runner is interrupted; then stops the agent (its process group, and whatever
/// left it in the cage), its relays and gateway, and reads the transcript's last lines.
fn watch(ctx: &RunContext, ready: &Ready, agent: Agent) -> Watched {
    let Agent { transcript, mut child, t0, contained } = agent;
    let prepared = &ready.prepared;
    let deadline = Duration::from_secs_f64(ctx.settings.wall_time_s + WATCHDOG_GRACE_S);
    let mut infra: Option<String> = None;
    let mut ended_at: Option<Instant> = None;
    let mut exited_at: Option<Instant> = None;
    let mut exit_code = None;
    let mut quit_before_finish = false;
    let mut watchdog = false;
    loop {
        if exit_code.is_none()
            && let Ok(Some(st)) = child.try_wait()
        {
            exit_code = Some(st.code().unwrap_or(-1));
            exited_at = Some(Instant::now());
        }
        if ended_at.is_none() && episode_ended(ctx, &prepared.episode_id) {
            ended_at = Some(Instant::now());
        }
        if INTERRUPTED.load(Ordering::SeqCst) {
            infra = Some("the batch runner was interrupted (SIGINT/SIGTERM)".into());
            break;
        }
        match (ended_at, exited_at) {
            (Some(_), Some(_)) => break,
            (Some(e), None) if e.elapsed() >= AFTER_FINISH_GRACE => break,
            (None, Some(x)) if x.elapsed() >= AGENT_EXIT_GRACE => {
                quit_before_finish = true;
                break;
            }
            _ => {}
        }
        if t0.elapsed() >= deadline {
            // An agent that never started its episode, or sat on it past the budget without the server ending
            // it, has left it: its forfeit (below), unless the model API failed it.
            watchdog = true;
            break;
        }
        std::thread::sleep(POLL);
    }
    if exit_code.is_none() {
        kill_group(&mut child);
        exit_code = child.try_wait().ok().flatten().map(|s| s.code().unwrap_or(-1));
    }
    // Whatever left the process group (setsid, daemons) is still in the cage's cgroups.
    if let Some(c) = &ready.cage {
        c.kill_all();
    }
    let elapsed_s = t0.elapsed().as_secs_f64();
    // The agent is gone: its relays and gateway stop, their sockets go; the gateway's records stay.
    let model_api_records = contained.model_api_records.clone();
    drop(contained);
    // Before the logs are scrubbed in place: the last lines, and the gateway's last records.
    let transcript = transcript.finish();
    Watched { infra, exit_code, quit_before_finish, watchdog, elapsed_s, model_api_records, transcript }
}

/// The rollout's record: the episode the agent left ended (its forfeit, or an abort), its verdict and outcome, the
/// logs scrubbed and kept, the token usage, the launch's files scrubbed, and the manifest completed.
fn collect(ctx: &RunContext, ready: Ready, launched: Launched, watched: Watched, rec: &mut RolloutRecord) -> anyhow::Result<()> {
    let Ready { dir, cage, home, log_dir, prepared, token, .. } = ready;
    let Launched { sandbox_report, mut manifest, logs, launch } = launched;
    let cause = || quit_cause(ctx.sandbox.is_some(), sandbox_report.is_some(), watched.model_api_records.as_deref());
    let infra = settle_episode(ctx, &prepared, &watched, cause);
    let result = verdict(ctx, &prepared);
    if INTERRUPTED.load(Ordering::SeqCst) && infra.is_some() {
        rec.outcome = Outcome::Interrupted;
    } else {
        rec.outcome = classify(result.as_ref(), infra.as_deref(), ctx.settings.wall_time_s);
    }
    if let Some(r) = &result {
        rec.result_status = r.status.clone();
        rec.success = r.success;
        rec.termination_reason = r.termination_reason.clone().or_else(|| r.reason.clone());
        rec.wall_time_s = r.wall_time_s();
        rec.accepted_agent_steps = r.accepted_agent_steps;
        let pe = r.private_evaluation.as_ref();
        rec.completed_stages = pe.and_then(|pe| pe.completed_required_stage_count).and_then(|c| u32::try_from(c).ok());
        rec.judgment_correct = pe.and_then(|pe| pe.judgment_correct);
    }
    rec.infrastructure_error = infra;
    rec.harness_elapsed_s = Some(watched.elapsed_s);
    rec.agent_exit_code = watched.exit_code;
    // Scrub what the agent printed (the API key, sk-… keys, bearer tokens, ours included), bounded whatever its
    // size, and the launch's own files, which stay in the batch's session home: Kimi's config.toml holds the key,
    // the MCP configs the token.
    let secrets: Vec<&str> = ctx.credentials.iter().map(|c| c.api_key.as_str()).chain([token.as_str()]).collect();
    let (usage, scrubbed) = scrub_logs(ctx.harness, &logs.stdout, &logs.stderr, &secrets);
    // The scrubbed, bounded logs leave the cage's disk for the rollout directory (files the runner made and
    // the agent only wrote to); the rest of the disk goes with the cage.
    if log_dir != dir {
        for name in [&logs.stdout_name, &logs.stderr_name] {
            if let Err(e) = copy_own_file(&log_dir.join(name), &dir.join(name)) {
                eprintln!("libero-agent: cannot keep {name}: {e}");
            }
        }
    }
    // What the runner's gateway saw of the agent's model traffic (never a file the agent can write): its token
    // figures count whenever it has any, stdout's only without them (the agent can print into its CLI's stdout).
    let model_api = watched.model_api_records.as_deref().and_then(|p| libero_sandbox::netgate::summarize(p).ok());
    let usage = super::usage::choose(usage, model_api.as_ref());
    let usage_source = usage.source.clone();
    rec.usage = Some(usage);
    if cage.is_none() {
        scrub_launch_files(&home, &launch, &secrets);
    }
    manifest.finished_at = Some(utc_now_iso());
    manifest.elapsed_seconds = Some(watched.elapsed_s);
    manifest.agent_exit_code = Some(watched.exit_code);
    manifest.infrastructure_error = Some(rec.infrastructure_error.clone());
    manifest.result_status = Some(rec.result_status.clone());
    manifest.task_success = Some(rec.success);
    manifest.outcome = Some(rec.outcome);
    manifest.logs = Some(doc(scrubbed));
    manifest.usage_source = Some(usage_source);
    manifest.agent_events = serde_json::to_value(&watched.transcript).ok().map(doc);
    manifest.model_api = Some(model_api.as_ref().and_then(|m| serde_json::to_value(m).ok()).map(doc));
    manifest.resources_used = Some(cage.as_ref().map(|c| doc(c.usage())));
    // The cage goes: its cgroups removed, its disk (workspace, home, /tmp) unmounted.
    drop(cage);
    write_manifest(&dir, &manifest)?;
    write_json_file(&dir.join("harness_usage.json"), &serde_json::to_value(&rec.usage)?)?;
    Ok(())
}

/// Ends the episode the agent left open, if it did: past the budget, an episode never started is the agent's
/// forfeit like any other it leaves, one the server still runs stays the watchdog's (§8.4); an agent that exited
/// first forfeits it, unless `cause` names the infrastructure's failure; whatever is still open is aborted.
/// Returns the infrastructure's error, if any.
fn settle_episode(ctx: &RunContext, prepared: &Prepared, watched: &Watched, cause: impl Fn() -> Option<String>) -> Option<String> {
    let mut infra = watched.infra.clone();
    if watched.watchdog {
        // Still open past budget + grace: an episode never started (prepared) is the agent's forfeit like any
        // other it leaves; one the server still runs past its budget stays the watchdog's (§8.4).
        let never_started = episode_view(ctx, &prepared.episode_id).is_some_and(|v| v.state == Some(EpisodeState::Prepared));
        let reason = format!("the agent did not start its episode within the budget and {WATCHDOG_GRACE_S} s");
        infra = match (never_started, cause()) {
            (true, cause) => end_left_episode(ctx, &prepared.episode_id, WATCHDOG_ERROR, &reason, cause),
            (false, Some(cause)) => Some(format!("{WATCHDOG_ERROR}: {cause}")),
            (false, None) => Some(WATCHDOG_ERROR.into()),
        };
    }
    if watched.quit_before_finish {
        let exited = format!("harness exited before finish_episode (exit code {})", watched.exit_code.unwrap_or(-1));
        infra = end_left_episode(ctx, &prepared.episode_id, &exited, &format!("the agent's {exited}"), cause());
    }
    if !episode_ended(ctx, &prepared.episode_id) {
        let reason = infra.clone().unwrap_or_else(|| "harness_process_exited_before_finish".into());
        let _ = post_json(&ctx.server_url, &format!("/api/episodes/{}/abort", prepared.episode_id), &json!({"reason": reason}));
    }
    infra
}

/// The episode's result as the server's API gives it: its `result.json`, else (a server that cannot read the run
/// directory) what its row tells.
fn verdict(ctx: &RunContext, prepared: &Prepared) -> Option<RunResult> {
    let result = episode_result(&ctx.server_url, &prepared.episode_id).ok().flatten();
    verdict_of(result, || episode_view(ctx, &prepared.episode_id))
}

/// The result itself when the server sent it, else the row's summary of it (None while the episode is open: an
/// episode the runner could not end is no verdict of the agent).
fn verdict_of(result: Option<RunResult>, view: impl FnOnce() -> Option<EpisodeView>) -> Option<RunResult> {
    result.or_else(|| view().and_then(|v| v.result_summary()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scrubbing_the_session_home_replaces_planted_links_and_fifos_without_following_them() {
        let t = tempfile::tempdir().unwrap();
        let home = t.path().join("home");
        let host = t.path().join("host-file");
        fs::write(&host, "host secret Bearer abcdefghijkl\n").unwrap();
        fs::create_dir_all(home.join(".codex")).unwrap();
        std::os::unix::fs::symlink(&host, home.join("mcp.json")).unwrap();
        assert!(std::process::Command::new("mkfifo").arg(home.join(".codex/config.toml")).status().unwrap().success());
        // A directory replaced by a link to a host directory: nothing is written through it.
        fs::create_dir(t.path().join("host-dir")).unwrap();
        std::os::unix::fs::symlink(t.path().join("host-dir"), home.join("sub")).unwrap();
        let launch = Launch {
            files: vec![
                (home.join("mcp.json"), "{\"Authorization\": \"Bearer tok-123456789\"}".into(), 0o600),
                (home.join(".codex/config.toml"), "key = \"MYSECRETKEY\"".into(), 0o600),
                (home.join("sub/x.json"), "x".into(), 0o600),
            ],
            argv: vec![],
            env: vec![],
        };
        scrub_launch_files(&home, &launch, &["MYSECRETKEY"]);
        assert_eq!(fs::read_to_string(&host).unwrap(), "host secret Bearer abcdefghijkl\n", "the host file is untouched");
        assert!(fs::read_dir(t.path().join("host-dir")).unwrap().next().is_none(), "nothing written through the link");
        let meta = fs::symlink_metadata(home.join("mcp.json")).unwrap();
        assert!(meta.is_file());
        assert_eq!(meta.permissions().mode() & 0o777, 0o600);
        assert_eq!(fs::read_to_string(home.join("mcp.json")).unwrap(), "{\"Authorization\": \"Bearer <redacted>\"}");
        assert_eq!(fs::read_to_string(home.join(".codex/config.toml")).unwrap(), "key = \"<redacted>\"");
    }

    #[test]
    fn outcomes_follow_section_4_8() {
        let fin = |ok: bool| RunResult::from_value(json!({"status": "finished", "success": ok, "wall_time_seconds": 12.0})).unwrap();
        assert_eq!(classify(Some(&fin(true)), None, 1800.0), Outcome::Success);
        assert_eq!(classify(Some(&fin(false)), None, 1800.0), Outcome::Fail);
        let expired = RunResult::from_value(json!({"status": "finished", "success": false, "termination_reason": "episode_wall_time_budget_exhausted",
            "wall_time_seconds": 1800.2})).unwrap();
        assert_eq!(classify(Some(&expired), None, 1800.0), Outcome::SimTimeout);
        let aborted = |wall_time_s: f64| RunResult::from_value(json!({"status": "aborted", "wall_time_seconds": wall_time_s})).unwrap();
        assert_eq!(classify(Some(&aborted(1800.5)), Some(WATCHDOG_ERROR), 1800.0), Outcome::WatchdogTimeout);
        assert_eq!(classify(Some(&aborted(30.0)), Some(WATCHDOG_ERROR), 1800.0), Outcome::Invalid);
        assert_eq!(classify(Some(&fin(true)), Some("harness exited before finish_episode"), 1800.0), Outcome::Invalid);
        assert_eq!(classify(None, None, 1800.0), Outcome::Invalid);
    }

    /// A row as `GET /api/episodes/{id}` sends it, for an episode the answering server no longer runs.
    fn row(outcome: Option<&str>, reason: Option<&str>) -> EpisodeView {
        serde_json::from_value(json!({"accepted_agent_steps": 40, "batch": null, "branch_parent": null, "branch_step": null,
            "completed_stage_count": 1, "created_at": "2026-12-07T13:00:00+00:00", "finished_at": null, "harness": null,
            "id": "ep-1", "init_index": 0, "level": 1, "model": null, "outcome": outcome, "reason": reason,
            "required_stage_count": 2, "seed": 1, "server_url": null, "started_at": null, "success": outcome.map(|o| o == "SUCCESS"),
            "task_ref": "T03", "wall_time_s": 1800.2}))
        .unwrap()
    }

    #[test]
    fn the_verdict_is_the_server_s_result_else_its_row_s_summary_else_none() {
        let result = RunResult::from_value(json!({"status": "finished", "success": true, "wall_time_seconds": 12.0})).unwrap();
        let asked = std::cell::Cell::new(false);
        let from_result = verdict_of(Some(result.clone()), || {
            asked.set(true);
            None
        });
        assert_eq!((from_result, asked.get()), (Some(result), false), "the result itself wins, the row is not asked");
        let timed_out = verdict_of(None, || Some(row(Some("SIM_TIMEOUT"), Some("episode_wall_time_budget_exhausted")))).unwrap();
        assert_eq!(classify(Some(&timed_out), None, 1800.0), Outcome::SimTimeout, "{timed_out:?}");
        assert_eq!(classify(Some(&timed_out), Some(WATCHDOG_ERROR), 1800.0), Outcome::WatchdogTimeout, "the row's wall time counts");
        let aborted = verdict_of(None, || Some(row(Some("INVALID"), Some("harness exited")))).unwrap();
        assert_eq!((aborted.status.as_deref(), aborted.reason.as_deref()), (Some("aborted"), Some("harness exited")));
        assert_eq!(verdict_of(None, || Some(row(None, None))), None, "an open episode has no verdict");
        assert_eq!(verdict_of(None, || None), None);
    }

    #[test]
    fn scrubbing_removes_keys_and_tokens() {
        let t = "key=sk-abcdef123456 auth: Bearer 0123456789abcdef and MYSECRETKEY here; sk-no";
        let s = scrub(t, &["MYSECRETKEY"]);
        assert_eq!(s, "key=sk-<redacted> auth: Bearer <redacted> and <redacted> here; sk-no");
    }
}
