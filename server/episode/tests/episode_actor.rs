//! The episode actor on the real LIBERO world (MuJoCo simulation + wgpu renderer): budgets, wall-clock
//! expiry while idle, fault isolation between concurrent episodes, private records.
use std::path::Path;
use std::time::{Duration, Instant};

use libero_records::records::{Outcome, RunDir, classify, read_result, read_result_value};
use libero_episode::task::resolve_task;
use libero_episode::world::{LiberoWorld, WorldSpec};
use libero_episode::{EpisodeConfig, EpisodeHandle, EpisodeState, Level, spawn_episode};
use libero_render::Renderer;
use libero_sim::AssetPaths;
use serde_json::{Map, Value, json};

const TASK: &str = "libero_object/pick_up_the_ketchup_and_place_it_in_the_basket";

fn spec(level: Level) -> WorldSpec {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    WorldSpec { task: resolve_task(TASK, &paths).unwrap(), level, seed: 100, init_index: 0, paths }
}

fn config(dir: &Path, name: &str, level: Level, max_agent_steps: u64, wall_s: f64) -> EpisodeConfig {
    EpisodeConfig {
        episode_id: name.into(),
        instruction: "pick up the ketchup and place it in the basket".into(),
        level,
        max_agent_steps,
        max_wall_time_s: wall_s,
        workspace: dir.join(name).join("ws"),
        run_dir: dir.join(name).join("run"),
    }
}

fn episode(dir: &Path, name: &str, level: Level, steps: u64, wall_s: f64, renderer: &Renderer) -> Joined {
    let cfg = config(dir, name, level, steps, wall_s);
    std::fs::create_dir_all(cfg.workspace.join("benchmark_inputs")).unwrap();
    let (s, r) = (spec(level), renderer.clone());
    Joined(spawn_episode(cfg, move || LiberoWorld::new(&s, r)).expect("episode"))
}

/// An episode the test waits for when it lets go of it: stopped (if still open) and its thread gone, world and
/// renderer released. A test process that exits while an episode thread still drops its world into the
/// software renderer can crash in the renderer's exit handlers (SIGSEGV after "test result: ok").
struct Joined(EpisodeHandle);

impl std::ops::Deref for Joined {
    type Target = EpisodeHandle;
    fn deref(&self) -> &EpisodeHandle {
        &self.0
    }
}

impl Drop for Joined {
    fn drop(&mut self) {
        self.0.stop("the test ended");
    }
}

/// Compares a result record with its golden fixture, volatile fields (time stamps, durations) masked.
fn assert_matches_result_fixture(result: &Value, name: &str) {
    let mut masked = result.clone();
    for key in ["finished_at", "wall_time_seconds"] {
        assert!(masked.get(key).is_some(), "result lacks {key}");
        masked[key] = json!(format!("<{key}>"));
    }
    let path = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name);
    if std::env::var_os("UPDATE_GOLDEN").is_some() {
        let mut text = libero_records::json::pretty_sorted(&masked);
        text.push('\n');
        std::fs::write(&path, text).unwrap();
    }
    let golden: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    assert_eq!(masked, golden, "result.json wire format changed");
}

fn args(v: Value) -> Option<Map<String, Value>> {
    v.as_object().cloned()
}

fn obs_id(ws: &Path) -> String {
    let text = std::fs::read_to_string(ws.join("benchmark_inputs/current_observation/observation.json")).unwrap();
    serde_json::from_str::<Value>(&text).unwrap()["observation_id"].as_str().unwrap().to_owned()
}

/// §3.1: the call that spends the agent-step budget ends the episode, judged as the wall time's end is
/// (SIM_TIMEOUT, `agent_step_budget_exhausted`); the agent gets that call's observation and the word that the
/// episode is over, and every later call the ended episode's payload, without simulating.
#[test]
fn the_call_that_spends_the_step_budget_ends_the_episode_as_sim_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let renderer = Renderer::new().expect("renderer");
    let h = episode(dir.path(), "steps", Level::L2, 2, 300.0, &renderer);
    let ws = h.config().workspace.clone();
    assert_eq!(h.call("start_episode", None)["max_agent_steps"], 2);
    let step = args(json!({"actions": [[0, 0, 0.2, 0, 0, 0, 0]]}));
    let first = h.call("osc_sequence", step.clone());
    assert_eq!((first["observation_id"].clone(), first.get("episode_ended").cloned()), (json!("obs_000001"), None));
    let last = h.call("osc_sequence", step.clone());
    assert_eq!(last["observation_id"], "obs_000002", "{last}");
    assert_eq!((last["episode_ended"].clone(), last["termination_reason"].clone()), (json!(true), json!("agent_step_budget_exhausted")));
    let run = RunDir::new(&h.config().run_dir);
    let result = read_result(&run).expect("result.json written by the budget's end");
    assert_eq!(classify(Some(&result)), Outcome::SimTimeout);
    assert_eq!(result.termination_reason.as_deref(), Some("agent_step_budget_exhausted"));
    assert_eq!(result.accepted_agent_steps, Some(2));
    assert_eq!(h.status().outcome, Some(Outcome::SimTimeout));
    let late = h.call("osc_sequence", step);
    assert_eq!((late["ok"].clone(), late["success"].clone(), late["termination_reason"].clone()), (json!(true), json!(false), json!("agent_step_budget_exhausted")));
    assert_eq!(obs_id(&ws), "obs_000002", "a call after the end publishes nothing");
    assert_eq!(h.status().accepted_agent_steps, 2);
    let log = std::fs::read_to_string(run.actions_jsonl()).unwrap();
    let commands: Vec<String> = log.lines().map(|l| serde_json::from_str::<Value>(l).unwrap()["request"]["command"].as_str().unwrap_or("").to_owned()).collect();
    let end = commands.iter().position(|c| c == "agent_step_budget_exhausted").expect("the budget's end is logged");
    assert_eq!(commands[end - 1], "osc_sequence", "logged after the call that spent it: {commands:?}");
}

#[test]
fn idle_wall_clock_ends_as_sim_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let renderer = Renderer::new().expect("renderer");
    let budget_s = 8.0;
    let h = episode(dir.path(), "budget", Level::L2, 100, budget_s, &renderer);
    assert_eq!(h.call("start_episode", None)["max_agent_steps"], 100);
    let started = std::time::Instant::now(); // the wall clock starts just before start_episode returns
    let step = args(json!({"actions": [[0, 0, 0.2, 0, 0, 0, 0]]}));
    for expected in ["obs_000001", "obs_000002"] {
        assert_eq!(h.call("osc_sequence", step.clone())["observation_id"], expected);
    }
    assert!(started.elapsed().as_secs_f64() < budget_s, "machine too slow for this test's budget");
    assert!(read_result(&RunDir::new(&h.config().run_dir)).is_none(), "still open before the deadline");
    // Idle: nobody calls; the actor itself ends the episode at the deadline.
    std::thread::sleep(Duration::from_secs_f64(budget_s + 1.5).saturating_sub(started.elapsed()));
    let run = RunDir::new(&h.config().run_dir);
    let result = read_result(&run).expect("result.json written without any call");
    assert_eq!(classify(Some(&result)), Outcome::SimTimeout);
    assert_eq!(result.termination_reason.as_deref(), Some("episode_wall_time_budget_exhausted"));
    assert_eq!(h.status().outcome, Some(Outcome::SimTimeout));
    assert_matches_result_fixture(&read_result_value(&run).unwrap(), "result_sim_timeout.json");
    // The next call, whatever it is, gets the expiry payload (ok, not an error).
    let late = h.call("finish_episode", None);
    assert_eq!((late["ok"].clone(), late["success"].clone()), (json!(true), json!(false)));
    assert_eq!(late["accepted_agent_steps"], 2);
    let log = std::fs::read_to_string(run.actions_jsonl()).unwrap();
    assert!(log.contains(r#""request":{"command":"wall_time_budget_expired"}"#));
}

#[test]
fn a_mujoco_fault_ends_only_its_own_episode_as_invalid() {
    let dir = tempfile::tempdir().unwrap();
    let renderer = Renderer::new().expect("renderer");
    let healthy = episode(dir.path(), "healthy", Level::L1, 100, 600.0, &renderer);
    let cfg = config(dir.path(), "faulty", Level::L1, 100, 600.0);
    std::fs::create_dir_all(cfg.workspace.join("benchmark_inputs")).unwrap();
    let (s, r) = (spec(Level::L1), renderer.clone());
    let faulty = Joined(spawn_episode(cfg, move || {
        let mut w = LiberoWorld::new(&s, r)?;
        // An absurd joint velocity in the restored state: MuJoCo's integrator blows up during settling.
        w.edit_start_state(|row| {
            let n = row.len();
            row[n - 1] = 1e30;
        });
        Ok(w)
    })
    .unwrap());
    assert_eq!(healthy.call("start_episode", None)["ok"], true);
    let failed = faulty.call("start_episode", None);
    assert_eq!(failed["error_type"], "EnvironmentCommandError", "{failed}");
    assert_eq!(failed["error"], "the LIBERO server could not execute this command");
    let status = faulty.status();
    assert_eq!((status.state, status.outcome), (EpisodeState::Aborted, Some(Outcome::Invalid)));
    let result = read_result(&RunDir::new(&faulty.config().run_dir)).unwrap();
    assert_eq!(result.status.as_deref(), Some("aborted"));
    assert!(result.reason.as_deref().unwrap().contains("simulator fault"), "{result}");
    assert!(!faulty.config().workspace.join("benchmark_inputs/current_observation").exists());
    // The other episode keeps going.
    let ok = healthy.call("osc_sequence", args(json!({"actions": [[0.3, 0, 0, 0, 0, 0, 1]]})));
    assert_eq!(ok["observation_id"], "obs_000001", "{ok}");
    assert_eq!(faulty.call("osc_sequence", args(json!({"actions": [[0, 0, 0, 0, 0, 0, 0]]})))["error_type"], "RuntimeError");
}

#[test]
fn stopping_an_open_episode_records_it_as_aborted_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let renderer = Renderer::new().expect("renderer");
    let t = Instant::now();
    let h = episode(dir.path(), "stopped", Level::L3, 100, 600.0, &renderer);
    assert_eq!(h.call("start_episode", None)["ok"], true);
    h.stop("server_received_signal_15_before_finish");
    let lived_s = t.elapsed().as_secs_f64();
    let result = read_result(&RunDir::new(&h.config().run_dir)).unwrap();
    assert_eq!(result.reason.as_deref(), Some("server_received_signal_15_before_finish"));
    // Started, so it has a wall time: the stretch from its start to the stop, inside this test's own.
    let wall = result.wall_time_s().expect("a started episode's wall time");
    assert!(wall > 0.0 && wall <= lived_s, "{wall} s within {lived_s} s");
    assert_eq!(classify(Some(&result)), Outcome::Invalid);
}

fn files_under(root: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap().flatten() {
            let p = e.path();
            out.push(p.strip_prefix(root).unwrap().to_string_lossy().into_owned());
            if p.is_dir() {
                stack.push(p);
            }
        }
    }
    out.sort();
    out
}

#[test]
fn a_real_level3_episode_publishes_the_observation_files_and_nothing_private() {
    use libero_episode::workspace::{WorkspaceContract, WorkspaceLayout, create_workspace};
    let dir = tempfile::tempdir().unwrap();
    let renderer = Renderer::new().expect("renderer");
    let cfg = config(dir.path(), "l3", Level::L3, 100, 600.0);
    let contract = WorkspaceContract {
        instruction: cfg.instruction.clone(),
        max_agent_steps: 100,
        max_wall_time_s: 600.0,
        mcp_url: "http://127.0.0.1:1/mcp/l3".into(),
        mcp_headers: Default::default(),
        demo: None,
    };
    create_workspace(&WorkspaceLayout::new(&cfg.workspace), &contract).unwrap();
    let (ws, run) = (cfg.workspace.clone(), RunDir::new(&cfg.run_dir));
    let (s, r) = (spec(Level::L3), renderer.clone());
    let h = Joined(spawn_episode(cfg, move || LiberoWorld::new(&s, r)).unwrap());
    let start = h.call("start_episode", None);
    assert_eq!(start["task_instruction"], "pick up the ketchup and place it in the basket");
    let read = |ws: &Path| -> Value {
        serde_json::from_str(&std::fs::read_to_string(ws.join("benchmark_inputs/current_observation/observation.json")).unwrap())
            .unwrap()
    };
    let o0 = read(&ws);
    let moved = h.call("osc_sequence", args(json!({"actions": vec![[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]; 5]})));
    assert_eq!(moved["execution"]["micro_step_count"], 5, "{moved}");
    let o1 = read(&ws);
    let dt = o1["sim_time_s"].as_f64().unwrap() - o0["sim_time_s"].as_f64().unwrap();
    assert!((dt - 0.25).abs() < 1e-9, "5 micro-actions are 0.25 s of simulated time, got {dt}");
    let x = |o: &Value| o["state"]["eef_pose_robot_base_xyzw_7d"][0].as_f64().unwrap();
    assert!(x(&o1) - x(&o0) > 0.01, "full +x actions move the end effector along +x of the base frame");
    assert!(o0["sim_time_s"].as_f64().unwrap() > 0.0, "10 settle steps ran before the first frame");
    // Files of the level matrix, depth in metres with a 64-byte-aligned .npy header.
    let cur = ws.join("benchmark_inputs/current_observation");
    for cam in ["head", "wrist"] {
        let npy = std::fs::read(cur.join(cam).join("depth_m.npy")).unwrap();
        assert_eq!(npy.len(), 128 + 256 * 256 * 4, "{cam}: header + 256×256 float32");
        let depth = o1["cameras"][cam]["depth"].clone();
        assert_eq!(depth["shape"], json!([256, 256]));
        let (near, far) = (depth["preview_near_m"].as_f64().unwrap(), depth["preview_far_m"].as_f64().unwrap());
        assert!(0.0 < near && near < far && far < 10.0, "{cam}: preview range {near}..{far} m");
        let t = &o1["cameras"][cam]["matrix_T_robot_base_from_camera_opencv_4x4"];
        assert_eq!(t[3], json!([0.0, 0.0, 0.0, 1.0]));
    }
    // The workspace holds only public files; the private records are in the run directory.
    let allowed = ["TASK_PROMPT.txt", ".libero", "benchmark_inputs", "scratch"];
    for f in files_under(&ws) {
        assert!(allowed.iter().any(|a| f.starts_with(a)), "unexpected workspace file {f}");
        for private in ["actions", "result", "private", "segmentation", "bddl", "init", "mask_instance"] {
            assert!(!f.contains(private), "private-looking file {f} in the workspace");
        }
    }
    let text = std::fs::read_to_string(cur.join("observation.json")).unwrap();
    for private in ["object", "segmentation", "mass", "success", "stage", "reward", "bddl", "ketchup"] {
        assert!(!text.contains(private), "observation.json mentions {private}");
    }
    assert_eq!(std::fs::read_to_string(run.actions_jsonl()).unwrap().lines().count(), 2);
    assert!(run.private_observations().join("obs_000001/head/depth_m.npy").is_file());
}

/// Starts `task` at `level` and returns the first observation's JSON and the directory it was published in.
fn first_observation(dir: &Path, task: &str, level: Level, renderer: &Renderer) -> (Value, std::path::PathBuf) {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let s = WorldSpec { task: resolve_task(task, &paths).unwrap(), level, seed: 100, init_index: 0, paths };
    let name = format!("{task}_{level:?}");
    let cfg = config(dir, &name, level, 10, 600.0);
    std::fs::create_dir_all(cfg.workspace.join("benchmark_inputs")).unwrap();
    let cur = cfg.workspace.join("benchmark_inputs/current_observation");
    let r = renderer.clone();
    let h = Joined(spawn_episode(cfg, move || LiberoWorld::new(&s, r)).expect("episode"));
    h.call("start_episode", None);
    let obs = serde_json::from_str(&std::fs::read_to_string(cur.join("observation.json")).unwrap()).unwrap();
    h.call("finish_episode", None);
    (obs, cur)
}

/// Protocol §3.9: every observation of T22 (goal image) carries the task reference and its file, at every level;
/// T21 (same scene, text goal) gets no such key.
#[test]
fn the_goal_image_task_publishes_its_task_reference_and_the_text_goal_task_does_not() {
    let dir = tempfile::tempdir().unwrap();
    let renderer = Renderer::new().expect("renderer");
    for level in [Level::L1, Level::L3] {
        let (obs, cur) = first_observation(dir.path(), "T22", level, &renderer);
        let reference = &obs["task_reference"];
        assert_eq!(
            *reference,
            json!({"semantics": "desired_object_arrangement",
                   "rgb": {"file": "task_reference/rgb.png", "media_type": "image/png", "shape": [256, 256, 3]}}),
            "{level:?}"
        );
        let image = libero_episode::observation::RgbImage::read_png(&cur.join("task_reference/rgb.png"))
            .unwrap_or_else(|e| panic!("{level:?}: the reference file is not an 8-bit RGB PNG: {e}"));
        assert_eq!((image.height, image.width, image.rgb.len()), (256, 256, 256 * 256 * 3), "{level:?}");
    }
    let (obs, cur) = first_observation(dir.path(), "T21", Level::L1, &renderer);
    assert!(obs.get("task_reference").is_none(), "T21 has no reference image: {}", obs["task_reference"]);
    assert!(!cur.join("task_reference").exists());
}
