//! `libero-agent expert --task T14 [--runs 3] [--behaviour solve] [--server URL]`: runs a task's scripted
//! privileged expert as ordinary episodes (recorded like any other: action log, result, video) and prints each
//! run's result record as one JSON object per line. With `--server`, the episodes are prepared on that server and
//! driven over MCP, so they show in its dashboard; otherwise they run in this process under `--data`.
//!
//! `--behaviour solve,idle,push_half` or `--behaviour all` plays several behaviours in one process (one renderer,
//! one data directory), one record per run as for a single behaviour.
//!
//! `expert --all | --tasks SELECTION [--runs N] [--jobs N]`: every entry with an expert (the release tasks, the 130 stock
//! LIBERO tasks of the generic expert and the pool's own definitions), one JSON line per task, then a table and the
//! line "N of M solved k/k"; see `cmd_expert_all`.
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use libero_episode::demo::record::RecordOptions;
use libero_episode::demo::{LayoutVariant, library, record_bundle};
use libero_episode::expert_run::{IDLE, ToolPort, run_expert, run_replica_only};
use libero_episode::physics::WorldSpec;
use libero_records::records::{PrivateEvaluation, RunResult, read_result};
use libero_episode::task::resolve_task;
use libero_episode::video_queue::VideoProgress;
use libero_episode::{EpisodeError, Level, RunDir};
use libero_sim::AssetPaths;
use libero_tasks::expert;
use serde::Deserialize;
use serde_json::{Value, json};

use libero_server::default_data_dir;
use libero_server::episodes::{Episodes, PrepareRequest};
use libero_server::client::{McpClient, prepare_episode};

/// The longest `expert` waits for an episode's private video (a long episode on a software renderer).
const VIDEO_WAIT: Duration = Duration::from_secs(3600);

#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("sweep").args(["all", "tasks"]).multiple(false)))]
pub struct ExpertArgs {
    /// Release task (`T14`, …), stock LIBERO task (`libero_90/KITCHEN_SCENE3_turn_on_the_stove`) or pool entry
    /// (`libero_90/35`, `robomemarena/18`).
    #[arg(long, required_unless_present_any = ["list", "all", "tasks"])]
    pub task: Option<String>,
    /// Run the solving expert of every task that has one and print a table: `--tasks all`.
    #[arg(long, conflicts_with_all = ["task", "list", "server", "trace", "demo_out", "tasks"])]
    pub all: bool,
    /// Run the solving expert of every task of this selection that has one and print a table (docs/commands.md,
    /// "Selecting tasks"): `release`, `stock`, a suite (`libero_90`, `robomemarena`), `group:G`, tasks (`T14`,
    /// `libero_90/35`, `libero_90/<name>`), `match:TEXT`, comma-separated or repeated. A pool entry that runs a
    /// release task's definition runs as that task.
    #[arg(long, value_delimiter = ',', conflicts_with_all = ["task", "list", "server", "trace", "demo_out"])]
    pub tasks: Vec<String>,
    /// With `--all` or `--tasks`: print only the JSON lines (the summary as a last JSON line), no table.
    #[arg(long)]
    pub json: bool,
    /// With `--all` or `--tasks`: run this many tasks at a time, each on its own thread (the rows are the same as with 1).
    #[arg(long, default_value_t = 1, requires = "sweep")]
    pub jobs: usize,
    /// With `--all` or `--tasks`: write the sweep table here (one JSON row per entry) and its metadata beside it
    /// (`<name>.meta.json`). Default: `tasks/results/expert_sweep.jsonl` for `--all`, else none.
    #[arg(long, requires = "sweep")]
    pub out: Option<PathBuf>,
    /// With `--all` or `--tasks`: run nothing; print the sweep file (`--out`, or the default) as a Markdown table per suite.
    #[arg(long, requires = "sweep")]
    pub markdown: bool,
    /// With `--tasks`: re-run just this selection and replace its rows in the sweep file (`--out`, or the
    /// default), each replaced row stamped with its own date and commit and the update listed in the metadata;
    /// the rest of the table stays as its run left it. `--runs` must be the table's.
    #[arg(long, requires = "sweep", conflicts_with = "markdown")]
    pub update: bool,
    /// With `--all` or `--tasks` and a sweep file: keep the rows a stopped run of the same command already finished
    /// (its journal, `<name>.journal.jsonl` beside the sweep file, each row with its date and commit) and run only
    /// the rest. Without it a sweep starts its journal afresh.
    #[arg(long, requires = "sweep", conflicts_with = "markdown")]
    pub resume: bool,
    /// How many episodes to run (of each behaviour; with `--behaviour all`, of `solve`).
    #[arg(long, default_value_t = 1)]
    pub runs: u32,
    /// `solve`, `idle` (start, then finish), or one of the task's near-miss behaviours (see `--list`); several
    /// comma-separated, or `all`: `solve` `--runs` times, then `idle` and every near-miss once each.
    #[arg(long, default_value = expert::SOLVE)]
    pub behaviour: String,
    /// List every entry with an expert (release, stock and pool) and its behaviours, one JSON line each, then exit.
    #[arg(long)]
    pub list: bool,
    /// A running `libero-agent serve` to run the episodes on (watchable in its dashboard).
    #[arg(long)]
    pub server: Option<String>,
    /// Data directory for in-process runs (default: as `serve`).
    #[arg(long)]
    pub data: Option<PathBuf>,
    #[arg(long, default_value_t = 1)]
    pub level: u8,
    #[arg(long, default_value_t = 100)]
    pub seed: u64,
    /// Tuning aid: run the script on a bare replica (no episode, no rendering) and print every step as JSON
    /// (phase, action, end-effector, fingers, and the joints named by `--watch-joint`), then the record.
    #[arg(long)]
    pub trace: bool,
    /// Joint whose qpos `--trace` prints (repeatable).
    #[arg(long = "watch-joint")]
    pub watch_joints: Vec<String>,
    /// Body whose world position `--trace` prints (repeatable).
    #[arg(long = "watch-body")]
    pub watch_bodies: Vec<String>,
    /// Do not record the private continuous video (faster; verdicts and action logs are unaffected).
    #[arg(long)]
    pub no_video: bool,
    /// Upper bound on the actions one run may send.
    #[arg(long, default_value_t = 3000)]
    pub max_actions: u64,
    /// `fast` (default): every call as soon as the last one is answered. `realtime`: 20 actions per second of wall
    /// time, the control rate, so a person can watch the expert live in the dashboard (an `osc_sequence` of n
    /// actions takes at least n/20 s).
    #[arg(long, value_enum, default_value_t = Pace::Fast)]
    pub pace: Pace,
    /// Record every successful run as a demonstration bundle into this library directory
    /// (`DIR/<task>/<episode id>/`, replayed, rendered and verified). In-process runs only.
    #[arg(long)]
    pub demo_out: Option<PathBuf>,
    /// Run the task in another layout, as a demonstration's source episode must (issue 31): this placement seed
    /// instead of the task's own …
    #[arg(long)]
    pub layout_seed: Option<u32>,
    /// … this row of the task's init-state file (tasks with trusted init states) …
    #[arg(long, default_value_t = 0, requires = "layout_seed")]
    pub layout_init: usize,
    /// … and table regions widened by this much on every side, metres (at most 0.1).
    #[arg(long, default_value_t = 0.0, requires = "layout_seed")]
    pub region_margin_m: f64,
    /// … and the whole table scene moved by `X,Y` metres (at most 0.1 each).
    #[arg(long, value_delimiter = ',', num_args = 2, requires = "layout_seed", allow_hyphen_values = true)]
    pub scene_shift_m: Vec<f64>,
    /// … and every table region's yaw interval widened by this much at both ends, radians (at most 0.8).
    #[arg(long, default_value_t = 0.0, requires = "layout_seed")]
    pub yaw_margin_rad: f64,
}

impl ExpertArgs {
    /// What a sweep runs: `--tasks`, or everything with `--all`.
    pub fn selection(&self) -> anyhow::Result<libero_tasks::Selection> {
        if self.all { Ok(libero_tasks::Selection::all()) } else { Ok(libero_tasks::Selection::from_parts(&self.tasks)?) }
    }

    /// The layout variant the flags ask for.
    pub(crate) fn layout(&self) -> anyhow::Result<Option<LayoutVariant>> {
        let Some(placement_seed) = self.layout_seed else { return Ok(None) };
        let scene_shift_m = match self.scene_shift_m.as_slice() {
            [] => [0.0; 2],
            [x, y] => [*x, *y],
            other => bail!("--scene-shift-m takes X,Y (got {other:?})"),
        };
        let v = LayoutVariant { placement_seed, init_index: self.layout_init, region_margin_m: self.region_margin_m, scene_shift_m, yaw_margin_rad: self.yaw_margin_rad };
        v.validate()?;
        Ok(Some(v))
    }
}

/// How fast an expert sends its actions.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Pace {
    /// As fast as the server answers.
    Fast,
    /// 20 actions per second of wall time (the 20 Hz control rate).
    Realtime,
}

/// Actions per second of wall time at [`Pace::Realtime`].
const REALTIME_ACTIONS_PER_S: f64 = 20.0;

/// A port that holds each `osc_sequence` of n actions to at least n/20 s of wall time at [`Pace::Realtime`]
/// (the call itself counts: only what is left of the n/20 s is slept).
pub(crate) struct Paced<'a> {
    inner: &'a mut dyn ToolPort,
    pace: Pace,
}

impl<'a> Paced<'a> {
    pub(crate) fn new(inner: &'a mut dyn ToolPort, pace: Pace) -> Self {
        Self { inner, pace }
    }
}

/// The `osc_sequence` arguments an expert builds (`{"actions": [[7 numbers], …]}`), as far as pacing counts them;
/// the episode validates them (kept as JSON, so that what it refuses still paces as before).
#[derive(serde::Deserialize, Default)]
struct OscArguments {
    #[serde(default)]
    actions: Value,
}

impl ToolPort for Paced<'_> {
    fn call_tool(&mut self, tool: &str, arguments: Value) -> Result<Value, EpisodeError> {
        let actions = match (self.pace, tool) {
            (Pace::Realtime, "osc_sequence") => OscArguments::deserialize(&arguments).unwrap_or_default().actions.as_array().map_or(0, Vec::len),
            _ => 0,
        };
        let started = Instant::now();
        let answer = self.inner.call_tool(tool, arguments);
        let due = Duration::from_secs_f64(actions as f64 / REALTIME_ACTIONS_PER_S);
        if let Some(left) = due.checked_sub(started.elapsed()) {
            std::thread::sleep(left);
        }
        answer
    }
}

/// An expert (or any scripted client) driving a server's episode over MCP.
pub(crate) struct McpPort(pub(crate) McpClient);

impl ToolPort for McpPort {
    fn call_tool(&mut self, tool: &str, arguments: Value) -> Result<Value, EpisodeError> {
        self.0.call_tool_payload(tool, arguments).map_err(|e| EpisodeError::Task(format!("{e:#}")))
    }
}

/// The `(behaviour, runs)` that `--behaviour` asks of `task_id`, checked against its expert before anything runs.
fn behaviour_plan(task_id: &str, asked: &str, runs: u32) -> anyhow::Result<Vec<(String, u32)>> {
    let known = libero_tasks::expert_behaviours(task_id).unwrap_or_default();
    if asked.trim() == "all" {
        let rest = [IDLE].into_iter().chain(known.iter().copied()).map(|b| (b.to_owned(), 1));
        return Ok([(expert::SOLVE.to_owned(), runs)].into_iter().chain(rest).collect());
    }
    let mut plan = Vec::new();
    for b in asked.split(',').map(str::trim).filter(|b| !b.is_empty()) {
        if b != expert::SOLVE && b != IDLE && !known.contains(&b) {
            bail!("task {task_id} has no expert behaviour {b:?}; known: {}, {IDLE}, {}", expert::SOLVE, known.join(", "));
        }
        plan.push((b.to_owned(), runs));
    }
    if plan.is_empty() {
        bail!("--behaviour names no behaviour");
    }
    Ok(plan)
}

/// `t14` → `T14`; stock ids (`suite/NAME`) and paths as given.
fn normalize_task_id(id: &str) -> String {
    let id = id.trim();
    if id.contains('/') || id.ends_with(".bddl") { id.to_owned() } else { id.to_ascii_uppercase() }
}

/// The expert's id and the task for `asked`: a task with an expert as given (`T14`, `libero_90/NAME`), or a pool
/// address (`libero_90/35`, `robomemarena/18`) played by the expert of the definition it resolves to.
fn expert_task(asked: &str, paths: &AssetPaths) -> anyhow::Result<(String, libero_episode::task::TaskSource)> {
    if libero_tasks::expert_behaviours(asked).is_some() {
        return Ok((asked.to_owned(), resolve_task(asked, paths)?));
    }
    // a pool entry that does not run says why (excluded, or what it still needs)
    let task = resolve_task(asked, paths)
        .map_err(|e| anyhow::anyhow!("task {asked} has no scripted expert (see `libero-agent expert --list`): {e:#}"))?;
    let id = task.suite.as_ref().map_or_else(|| task.task_ref.clone(), |s| s.id.clone());
    if libero_tasks::expert_behaviours(&id).is_none() {
        bail!("task {asked} has no scripted expert (see `libero-agent expert --list`)");
    }
    Ok((id, task))
}

pub fn run(args: &ExpertArgs) -> anyhow::Result<()> {
    // `--list` and `--all` are `cmd_expert_all`'s, dispatched by main.
    let asked = normalize_task_id(args.task.as_deref().unwrap_or_default());
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    let level = Level::from_number(args.level).with_context(|| format!("--level must be 1, 2 or 3 (got {})", args.level))?;
    let paths = AssetPaths::discover().context("assets are missing; run `python3 scripts/setup.py`")?;
    let (task_id, mut task) = expert_task(&asked, &paths)?;
    task.layout = args.layout()?;
    let spec = WorldSpec { task, level, seed: args.seed, init_index: 0, paths };
    if args.trace {
        return trace(args, &spec, &task_id);
    }
    let behaviours = behaviour_plan(&task_id, &args.behaviour, args.runs)?;
    if args.demo_out.is_some() && args.server.is_some() {
        bail!("--demo-out needs the run directories here: run without --server");
    }
    let renderer = match &args.demo_out {
        Some(_) => Some(libero_render::Renderer::new().context("cannot open a GPU to render the demonstration")?),
        None => None,
    };
    let local = match &args.server {
        Some(_) => None,
        None => Some(Episodes::new(args.data.clone().unwrap_or_else(default_data_dir), "http://127.0.0.1:0".into())?),
    };
    let (mut failures, mut solves) = (0, 0);
    for (behaviour, runs) in &behaviours {
        // the episode is the address's (a pool entry keeps its own instruction); the expert is its definition's
        let request = PrepareRequest { layout: spec.task.layout, ..prepare_request(args, &spec.task.task_ref, behaviour) };
        solves += if behaviour == expert::SOLVE { *runs } else { 0 };
        for run_index in 1..=*runs {
            let outcome = run_once(args, &spec, &task_id, behaviour, (run_index, *runs), &request, local.as_ref(), renderer.as_ref())?;
            failures += u32::from(!outcome && behaviour == expert::SOLVE);
        }
    }
    if failures > 0 {
        bail!("the {task_id} expert failed {failures} of {solves} runs");
    }
    Ok(())
}

/// One run of `behaviour` (number `run_index` of `runs`): plays it, prints its record, records its demonstration
/// when asked; whether it succeeded.
#[allow(clippy::too_many_arguments)] // the run's own settings, passed as given
fn run_once(
    args: &ExpertArgs,
    spec: &WorldSpec,
    task_id: &str,
    behaviour: &str,
    (run_index, runs): (u32, u32),
    request: &PrepareRequest,
    local: Option<&Episodes>,
    renderer: Option<&libero_render::Renderer>,
) -> anyhow::Result<bool> {
    let progress = |line: &str| eprintln!("[{task_id} {behaviour} run {run_index}/{runs}] {line}");
    let (mut episode_wall_time_s, mut video_ready_s) = (None, None);
    let (episode_id, outcome, record, run_dir) = match (local, &args.server) {
        (Some(episodes), _) => {
            let r = run_local(episodes, request, spec, task_id, behaviour, args.max_actions, args.pace, &progress)?;
            (episode_wall_time_s, video_ready_s) = (r.episode_wall_time_s, r.video_ready_s);
            (r.episode_id, r.outcome, r.record, Some(r.run_dir))
        }
        (None, Some(server)) => {
            let prepared = prepare_episode(server, request)?;
            let token = prepared.mcp_headers.get("Authorization").context("no token in the server's reply")?;
            let token = token.trim_start_matches("Bearer ");
            let mut port = McpPort(McpClient::connect_with_token(&prepared.mcp_url, token, "libero-agent-expert")?);
            let episode_id = prepared.episode_id;
            let outcome = run_expert(&mut Paced::new(&mut port, args.pace), spec, task_id, behaviour, args.max_actions, progress);
            (episode_id, outcome, None, None)
        }
        (None, None) => unreachable!("either local or remote"),
    };
    let run = outcome.with_context(|| format!("{task_id} run {run_index} ({episode_id})"))?;
    let record = PrivateEvaluation::from_value(record.unwrap_or_else(|| run.replica_record.clone())).unwrap_or_default();
    let success = record.success.unwrap_or(false);
    let demo = match (&args.demo_out, renderer, &run_dir) {
        (Some(lib), Some(renderer), Some(run_dir)) if success => {
            let out = library::bundle_dir(lib, &spec.task.task_ref, &episode_id);
            let options = RecordOptions {
                source_type: "scripted_expert".into(),
                source_desc: format!("libero-agent expert --behaviour {}", behaviour),
            };
            let s = record_bundle(run_dir, &out, &options, renderer.clone(), &spec.paths)
                .with_context(|| format!("recording the demonstration of {episode_id}"))?;
            progress(&format!("demonstration {} ({} frames, verified {})", out.display(), s.frame_count, s.verified));
            json!({"dir": out, "frame_count": s.frame_count, "verified": s.verified})
        }
        _ => Value::Null,
    };
    let line = json!({
        "task": task_id,
        "behaviour": behaviour,
        "pace": args.pace,
        "run": run_index,
        "episode_id": episode_id,
        "success": success,
        "completed_stage_count": record.completed_required_stage_count,
        "required_stage_count": record.required_stage_count,
        "completed_stage_names": record.completed_stage_names,
        "stage_regressions": record.stage_regressions,
        "stage_diagnostics": record.stage_diagnostics,
        "failure_reason": record.failure_reason.flatten(),
        "first_commitment": record.first_commitment,
        "judgment_correct": record.judgment_correct,
        "osc_sequence_calls": run.osc_calls,
        "actions": run.actions,
        "demo": demo,
        "episode_wall_time_s": episode_wall_time_s,
        "video_ready_s": video_ready_s,
    });
    println!("{line}");
    Ok(success)
}

/// The episode an expert run of `task_id` prepares (the agent step cap, so that budgets never end a run early).
/// The dashboard's table shows and filters it as harness `expert`, model = the behaviour, batch = this command.
pub(crate) fn prepare_request(args: &ExpertArgs, task_id: &str, behaviour: &str) -> PrepareRequest {
    PrepareRequest {
        level: args.level,
        seed: args.seed,
        max_agent_steps: libero_episode::tools::MAX_AGENT_STEPS_CAP,
        video: !args.no_video,
        harness: Some("expert".into()),
        model: Some(behaviour.to_owned()),
        batch: Some(expert_batch().to_owned()),
        ..PrepareRequest::new(task_id.to_owned())
    }
}

/// `expert_<UTC time>`: one batch name for every episode of this command.
fn expert_batch() -> &'static str {
    static NAME: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    NAME.get_or_init(|| {
        let stamp: String = libero_records::json::utc_now_iso().chars().take(19).filter(|c| c.is_ascii_digit() || *c == 'T').collect();
        format!("expert_{stamp}Z")
    })
}

/// One in-process expert episode.
pub(crate) struct LocalRun {
    pub episode_id: String,
    pub outcome: Result<libero_episode::expert_run::ExpertRun, EpisodeError>,
    /// The episode's own evaluation record (`private_evaluation` of its result).
    pub record: Option<Value>,
    pub run_dir: PathBuf,
    pub episode_wall_time_s: Option<f64>,
    pub video_ready_s: Option<f64>,
}

/// Prepares an episode on `episodes`, plays `behaviour` on it at `pace`, and waits for its private video when it
/// records one.
#[allow(clippy::too_many_arguments)] // each is one of the run's own settings, passed as given
pub(crate) fn run_local(
    episodes: &Episodes,
    request: &PrepareRequest,
    spec: &WorldSpec,
    task_id: &str,
    behaviour: &str,
    max_actions: u64,
    pace: Pace,
    progress: &dyn Fn(&str),
) -> anyhow::Result<LocalRun> {
    let prepared = episodes.prepare(request.clone())?;
    let mut handle = episodes.lifecycle().handle(&prepared.episode_id).context("prepared episode vanished")?;
    let outcome = run_expert(&mut Paced::new(&mut handle, pace), spec, task_id, behaviour, max_actions, progress);
    handle.stop("expert run over");
    let run = RunDir::new(&prepared.run_dir);
    let ended = Instant::now();
    let result = read_result(&run);
    let episode_wall_time_s = result.as_ref().and_then(RunResult::wall_time_s);
    let mut video_ready_s = None;
    if request.video {
        let frames = libero_episode::state_record::StateRecordReader::open(&run.state_record()).map(|r| r.frames()).unwrap_or(0);
        progress(&format!("waiting for the private video ({frames} frames, rendered in the background)"));
        match episodes.lifecycle().wait_for_video(&run, VIDEO_WAIT) {
            Some(VideoProgress::Ready) => {
                let ready_s = ended.elapsed().as_secs_f64();
                video_ready_s = Some(ready_s);
                progress(&format!("video ready {ready_s:.1} s after the episode"));
            }
            other => bail!("the private video of {} did not complete: {other:?}", prepared.episode_id),
        }
    }
    let record = result.and_then(|r| r.private_evaluation).map(|e| e.to_value());
    Ok(LocalRun { episode_id: prepared.episode_id, outcome, record, run_dir: prepared.run_dir, episode_wall_time_s, video_ready_s })
}

/// `(name, id)` of each named model object of `kind` (warning about names the model lacks).
fn named_ids(
    model: &libero_sim::mujoco_rs::prelude::MjModel,
    kind: libero_sim::mujoco_rs::prelude::MjtObjBase,
    names: &[String],
) -> Vec<(String, usize)> {
    names
        .iter()
        .filter_map(|n| {
            let id = model.name_to_id(kind, n);
            if id.is_none() {
                eprintln!("warning: the model has no {kind:?} {n:?}");
            }
            id.map(|id| (n.clone(), id))
        })
        .collect()
}

fn trace(args: &ExpertArgs, spec: &WorldSpec, task_id: &str) -> anyhow::Result<()> {
    use libero_sim::mujoco_rs::prelude::MjtObjBase;
    let mut watch: Option<Vec<(String, usize)>> = None;
    let mut bodies: Option<Vec<(String, usize)>> = None;
    let record = run_replica_only(spec, task_id, &args.behaviour, args.max_actions, |t, sim| {
        let watch = watch.get_or_insert_with(|| {
            let model = sim.model();
            let joints = named_ids(model, MjtObjBase::mjOBJ_JOINT, &args.watch_joints);
            joints.into_iter().map(|(n, j)| (n, model.jnt_qposadr()[j] as usize)).collect()
        });
        let bodies = bodies.get_or_insert_with(|| named_ids(sim.model(), MjtObjBase::mjOBJ_BODY, &args.watch_bodies));
        let mut line = json!(t);
        for (name, b) in bodies.iter() {
            let p = sim.data().xpos()[*b];
            line[name.as_str()] = json!([(p[0] * 1e4).round() / 1e4, (p[1] * 1e4).round() / 1e4, (p[2] * 1e4).round() / 1e4]);
        }
        for (name, adr) in watch.iter() {
            line[name.as_str()] = json!(sim.data().qpos()[*adr]);
        }
        for (name, b) in bodies.iter() {
            line[name.as_str()] = json!(sim.data().xpos()[*b]);
        }
        println!("{line}");
    })?;
    println!("{}", json!({"record": record}));
    Ok(())
}
