//! Live evaluator progress for every evaluator kind of the registry (issue 33): while a scripted expert plays an
//! episode, each stage's completion and regression reaches the live stream at the control step it happens (a
//! `stage` message right after that step's `step` message, never only at finish), `progress` follows every stage
//! event, and the stream ends on the record's figures: the live stage events are exactly the record's
//! `stage_events`, the last `progress` is its `completed / K`.
//!
//! * In process, for every kind in `EVALUATOR_KINDS`: the episode reports to a dashboard hub (`LiveHubs`) and the
//!   test reads the hub's event channel, the very texts the episode socket sends. A kind without a play in
//!   [`PLAYS`] fails the test, so a new evaluator cannot ship without live progress.
//! * Over a real socket: `libero-agent serve`, a T28 episode driven over MCP while `/ws/episodes/{id}` is open.
use std::collections::HashSet;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use libero_episode::expert_run::{ToolPort, run_expert};
use libero_records::records::{RunDir, read_result_value};
use libero_episode::task::resolve_task;
use libero_episode::tools::MAX_AGENT_STEPS_CAP;
use libero_episode::world::{LiberoWorld, WorldSpec};
use libero_episode::{EpisodeConfig, EpisodeError, Level, spawn_episode_live};
use libero_render::Renderer;
use libero_server::live::{LiveHubs, Subscription};
use libero_sim::AssetPaths;
use libero_tasks::expert_behaviours;
use libero_tasks::registry::EVALUATOR_KINDS;
use serde_json::{Value, json};
use tokio::sync::broadcast::error::RecvError;

mod common;

/// How an evaluator kind is proven: a task it judges and the expert behaviour played on it.
struct Play {
    kind: &'static str,
    task: &'static str,
    behaviour: &'static str,
    /// The behaviour makes a completed stage regress (an `undo`, or a release after a grasp stage): the live
    /// stream must show it.
    regresses: bool,
    /// No task is judged by this kind: the task's checker is swapped for it (same scene, same expert).
    stand_in: bool,
}

/// One play per evaluator kind, chosen short (the whole test stays within a few minutes of a debug build).
const PLAYS: &[Play] = &[
    Play { kind: "bddl_terminal", task: "T14", behaviour: "solve", regresses: false, stand_in: false },
    // `bddl_terminal_open` (the release's K = 1 checker of T28) judges no task of this build: T14 under it.
    Play { kind: "bddl_terminal_open", task: "T14", behaviour: "solve", regresses: false, stand_in: true },
    Play { kind: "private_button_press", task: "T13", behaviour: "solve", regresses: false, stand_in: false },
    Play { kind: "private_contact_gated_button", task: "T06", behaviour: "solve", regresses: false, stand_in: false },
    // two tubes: two terminal stages
    Play { kind: "private_tube_insertion", task: "vlabench_tube_precision/1", behaviour: "solve", regresses: false, stand_in: false },
    // the grasp stage regresses when the sponge is let go on its rest area
    Play { kind: "private_ordered_physical_wipe", task: "T19", behaviour: "solve", regresses: true, stand_in: false },
    Play { kind: "private_ordered_physical_pour", task: "T20", behaviour: "solve", regresses: false, stand_in: false },
    Play { kind: "private_ordered_stages", task: "T28", behaviour: "undo", regresses: true, stand_in: false },
    Play { kind: "private_unordered_goal_predicates", task: "T21", behaviour: "undo", regresses: true, stand_in: false },
    Play {
        kind: "private_ordered_buffer_rotation_and_tabletop_avoidance",
        task: "T25",
        behaviour: "undo",
        regresses: true,
        stand_in: false,
    },
    Play { kind: "private_ordered_coffee_brewing", task: "long_horizon_v2/2", behaviour: "solve", regresses: false, stand_in: false },
    Play { kind: "private_physical_weighing", task: "T08", behaviour: "solve", regresses: false, stand_in: false },
    Play { kind: "private_ordered_hammer_contact", task: "T29", behaviour: "undo", regresses: true, stand_in: false },
    Play { kind: "private_ordered_physical_seesaw", task: "T30", behaviour: "undo", regresses: true, stand_in: false },
];

/// Most actions one play may send (the longest play above needs about 800).
const MAX_ACTIONS: u64 = 3000;

/// Stage events the record keeps in `stage_events` (the others — commitment, goal changes, pours — are live too,
/// but belong to the record's `events`).
const STAGE_KINDS: [&str; 3] = ["stage_completed", "stage_regressed", "order_violation"];

/// The task (its checker swapped for a stand-in) and the id its expert is registered under.
fn task_for(play: &Play, paths: &AssetPaths) -> Result<(libero_episode::task::TaskSource, String), String> {
    let mut task = resolve_task(play.task, paths).map_err(|e| format!("{}: {e}", play.task))?;
    let suite = task.suite.as_mut().ok_or_else(|| format!("{} is not a suite task", play.task))?;
    if suite.checker.kind != play.kind {
        if !play.stand_in {
            return Err(format!("{} is judged by {}, not {}", play.task, suite.checker.kind, play.kind));
        }
        suite.checker.kind = play.kind.to_owned();
    }
    let expert = if expert_behaviours(play.task).is_some() { play.task.to_owned() } else { suite.id.clone() };
    Ok((task, expert))
}

/// What a live stream showed, checked against the episode's record. Returns a one-line summary.
fn check_live(texts: &[Value], record: &Value, regresses: bool) -> Result<String, String> {
    let finish_call = texts
        .iter()
        .position(|t| t["type"] == "call_received" && t["tool"] == "finish_episode")
        .ok_or("the stream has no finish_episode call")?;
    let required: HashSet<&str> =
        record["ordered_stage_names"].as_array().ok_or("record without ordered_stage_names")?.iter().filter_map(Value::as_str).collect();
    let unordered = record["details"]["order"] == "unordered";
    let mut step: Option<u64> = None;
    let mut live_stage_events: Vec<Value> = Vec::new();
    let mut progress: Option<(u64, u64)> = None;
    let mut progress_messages = 0;
    // The required stages the live events say are done: latched ones once completed; unordered goals while holding
    // (counted from the count at the reset, as goals holding then are no event).
    let mut latched: HashSet<String> = HashSet::new();
    let mut unordered_count: Option<i64> = None;
    let mut check_progress = false;
    let verify = |progress: Option<(u64, u64)>, latched: &HashSet<String>, unordered_count: Option<i64>, at: &str| {
        let expected = if unordered { unordered_count.unwrap_or(0) } else { latched.len() as i64 };
        match progress {
            Some((c, _)) if c as i64 == expected => Ok(()),
            other => Err(format!("after the stage events of {at}: live progress {other:?}, the live stage events say {expected} done")),
        }
    };
    for (i, t) in texts.iter().enumerate() {
        let at_verdict = i > finish_call;
        match t["type"].as_str() {
            Some("step") => {
                if std::mem::take(&mut check_progress) {
                    verify(progress, &latched, unordered_count, &format!("control step {step:?}"))?;
                }
                step = t["control_step"].as_u64();
            }
            Some("progress") => {
                let (c, k) = (t["completed"].as_u64(), t["required"].as_u64());
                progress = c.zip(k);
                progress_messages += 1;
                if step == Some(0) && unordered_count.is_none() {
                    unordered_count = c.map(|c| c as i64);
                }
            }
            Some("stage") if STAGE_KINDS.contains(&t["event"]["kind"].as_str().unwrap_or_default()) => {
                let e = &t["event"];
                // As it happens: right after the step it happened at (stages judged on the final state at finish).
                if e["control_step"].as_u64() != step {
                    return Err(format!(
                        "{e} arrived after control step {step:?}{}: not as it happened",
                        if at_verdict { " (at the verdict)" } else { "" }
                    ));
                }
                let name = e["stage_name"].as_str().unwrap_or_default();
                if required.contains(name) {
                    match e["kind"].as_str() {
                        Some("stage_completed") => {
                            latched.insert(name.to_owned());
                            unordered_count = Some(unordered_count.unwrap_or(0) + 1);
                        }
                        Some("stage_regressed") => unordered_count = Some(unordered_count.unwrap_or(0) - 1),
                        _ => {}
                    }
                }
                live_stage_events.push(e.clone());
                check_progress = true;
            }
            _ => {}
        }
    }
    if check_progress {
        verify(progress, &latched, unordered_count, "the verdict")?;
    }
    let recorded = record["stage_events"].as_array().ok_or("record without stage_events")?;
    if &live_stage_events != recorded {
        return Err(format!("live stage events differ from the record's:\n live   {live_stage_events:?}\n record {recorded:?}"));
    }
    let k = record["required_stage_count"].as_u64();
    let c = record["completed_required_stage_count"].as_u64();
    if progress != c.zip(k) {
        return Err(format!("the live progress ends at {progress:?}, the record says {c:?} of {k:?}"));
    }
    let regressed = live_stage_events.iter().filter(|e| e["kind"] == "stage_regressed").count();
    if regresses && regressed == 0 {
        return Err("the play regresses a stage, the live stream showed no regression".into());
    }
    let finished = texts.iter().rev().find(|t| t["type"] == "finished").ok_or("the end was not reported")?;
    if (finished["outcome"] == "SUCCESS") != (record["success"] == true) {
        return Err(format!("live outcome {} for a record with success {}", finished["outcome"], record["success"]));
    }
    Ok(format!(
        "{} stage events live ({regressed} regressions), {progress_messages} progress messages, ending {}/{} as the record",
        live_stage_events.len(),
        c.unwrap_or(0),
        k.unwrap_or(0)
    ))
}

/// Plays `play` in process with its live events going to a hub of `hubs`; checks what the hub broadcast.
fn play_in_process(play: &Play, paths: &AssetPaths, renderer: &Renderer, hubs: &Arc<LiveHubs>, dir: &Path) -> Result<String, String> {
    let (task, expert) = task_for(play, paths)?;
    let spec = WorldSpec { task, level: Level::L1, seed: 100, init_index: 0, paths: paths.clone() };
    let id = format!("live-{}", play.kind);
    let cfg = EpisodeConfig {
        episode_id: id.clone(),
        instruction: spec.task.instruction.clone(),
        level: Level::L1,
        max_agent_steps: MAX_AGENT_STEPS_CAP,
        max_wall_time_s: 1800.0,
        workspace: dir.join(&id).join("ws"),
        run_dir: dir.join(&id).join("run"),
    };
    std::fs::create_dir_all(cfg.workspace.join("benchmark_inputs")).map_err(|e| e.to_string())?;
    let (sink, viewers) = hubs.open(&id, cfg.agent_step_limit(), cfg.max_wall_time_s);
    let Subscription { mut events, viewer, .. } = hubs.get(&id).and_then(|hub| hub.subscribe()).ok_or("no hub")?;
    // Only the text events are checked: no viewer of frames, so the live renderer stays idle.
    drop(viewer);
    let reader = std::thread::spawn(move || {
        let mut texts: Vec<Value> = Vec::new();
        loop {
            match events.blocking_recv() {
                Ok(text) => {
                    let v: Value = serde_json::from_str(&text).map_err(|e| format!("{e}: {text}"))?;
                    let end = v["type"] == "finished";
                    texts.push(v);
                    if end {
                        return Ok(texts);
                    }
                }
                Err(RecvError::Lagged(n)) => return Err(format!("the reader fell {n} events behind")),
                Err(RecvError::Closed) => return Ok(texts),
            }
        }
    });
    let (world_spec, world_sink, world_renderer) = (spec.clone(), sink.clone(), renderer.clone());
    let handle = spawn_episode_live(cfg.clone(), Some(sink), move || {
        let mut w = LiberoWorld::new(&world_spec, world_renderer)?;
        w.set_live(world_sink, viewers, None)?;
        Ok(w)
    })
    .map_err(|e| e.to_string())?;
    let mut port = handle.clone();
    let played = run_expert(&mut port, &spec, &expert, play.behaviour, MAX_ACTIONS, |_| {});
    handle.stop("test over");
    hubs.close(&id);
    let texts = reader.join().map_err(|_| "the reader panicked".to_owned())??;
    let played = played.map_err(|e| format!("the expert: {e}"))?;
    let result = read_result_value(&RunDir::new(&cfg.run_dir)).ok_or("no result.json")?;
    let summary = check_live(&texts, &result["private_evaluation"], play.regresses)?;
    Ok(format!("{summary}; {} actions", played.actions))
}

#[test]
fn every_evaluator_kind_reports_each_stage_live_as_it_happens() {
    let unplayed: Vec<&&str> = EVALUATOR_KINDS.iter().filter(|k| !PLAYS.iter().any(|p| p.kind == **k)).collect();
    assert!(unplayed.is_empty(), "evaluator kinds without a live-progress play: {unplayed:?}: add one to PLAYS");
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let renderer = Renderer::new().expect("a renderer");
    let hubs = Arc::new(LiveHubs::default());
    let dir = tempfile::tempdir().expect("tempdir");
    let queue: Mutex<Vec<&Play>> =
        Mutex::new(EVALUATOR_KINDS.iter().rev().filter_map(|k| PLAYS.iter().find(|p| p.kind == *k)).collect());
    let failures: Mutex<Vec<String>> = Mutex::default();
    let workers = std::thread::available_parallelism().map_or(2, |n| n.get()).clamp(1, 4);
    let t0 = Instant::now();
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| {
                while let Some(play) = queue.lock().unwrap().pop() {
                    let started = Instant::now();
                    let what = format!("{} ({} {})", play.kind, play.task, play.behaviour);
                    match play_in_process(play, &paths, &renderer, &hubs, dir.path()) {
                        Ok(summary) => eprintln!("{what}: {summary} [{:.1} s]", started.elapsed().as_secs_f64()),
                        Err(e) => failures.lock().unwrap().push(format!("{what}: {e}")),
                    }
                }
            });
        }
    });
    eprintln!("{} kinds in {:.1} s", EVALUATOR_KINDS.len(), t0.elapsed().as_secs_f64());
    let failures = failures.into_inner().unwrap();
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

// ------------------------------------------------------------------------------------------- a real socket

struct McpPort(libero_server::client::McpClient);

impl ToolPort for McpPort {
    fn call_tool(&mut self, tool: &str, arguments: Value) -> Result<Value, EpisodeError> {
        self.0.call_tool_payload(tool, arguments).map_err(|e| EpisodeError::Task(format!("{e:#}")))
    }
}

#[test]
fn a_long_horizon_episode_streams_every_stage_over_the_real_socket() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    let server = common::Server::start(&data);
    let req = json!({"task": "T28", "level": 1, "seed": 100, "video": false, "workspace": tmp.path().join("ws")});
    let op = format!("Bearer {}", server.token);
    let headers = [("Content-Type", "application/json"), ("Authorization", op.as_str())];
    let (status, _, body) = common::http("POST", &format!("{}/api/episodes", server.url), &headers, req.to_string().as_bytes());
    let prepared: Value = serde_json::from_slice(&body).expect("JSON");
    assert_eq!(status, 201, "{prepared}");
    let id = prepared["episode_id"].as_str().expect("episode id");
    let token = prepared["mcp_headers"]["Authorization"].as_str().expect("token").trim_start_matches("Bearer ");
    // Watching before the agent starts: everything arrives as it happens.
    let socket = common::read_socket(&format!("{}/ws/episodes/{id}", server.url), &server.token);
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let spec = WorldSpec { task: resolve_task("T28", &paths).expect("T28"), level: Level::L1, seed: 100, init_index: 0, paths };
    let client = libero_server::client::McpClient::connect_with_token(prepared["mcp_url"].as_str().expect("mcp url"), token, "live-stages-test")
        .expect("MCP session");
    let played = run_expert(&mut McpPort(client), &spec, "T28", "solve", MAX_ACTIONS, |_| {}).expect("the T28 expert");
    assert_eq!(played.finish["success"], true, "{}", played.finish);
    let texts = socket.join().expect("socket reader").expect("the socket stream");
    assert_eq!(texts.first().map(|t| t["type"].clone()), Some(json!("hello")), "{texts:?}");
    let result = read_result_value(&RunDir::new(data.join("runs").join(id))).expect("result.json");
    let record = &result["private_evaluation"];
    let summary = check_live(&texts, record, false).unwrap_or_else(|e| panic!("{e}"));
    eprintln!("T28 over the socket: {summary}");
    // What the live page shows: both stages completed, one after the other, and "stages 2/2".
    let completed: Vec<&Value> = texts.iter().filter(|t| t["type"] == "stage" && t["event"]["kind"] == "stage_completed").collect();
    let names: Vec<&str> = completed.iter().filter_map(|t| t["event"]["stage_name"].as_str()).collect();
    assert_eq!(names, ["01_Unlatch_Door", "02_Open_Door"], "{completed:?}");
    assert!(completed[0]["event"]["control_step"].as_u64() < completed[1]["event"]["control_step"].as_u64());
    let counts: Vec<(u64, u64)> = texts
        .iter()
        .filter(|t| t["type"] == "progress")
        .filter_map(|t| t["completed"].as_u64().zip(t["required"].as_u64()))
        .collect();
    assert_eq!(counts, [(0, 2), (1, 2), (2, 2)], "progress as the stages complete");
}
