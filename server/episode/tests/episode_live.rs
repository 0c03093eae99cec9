//! The operator's live view of a real episode: the actor reports calls and the end, the world reports every
//! control step and its telemetry, and the video recorder's own frames reach the sink rate-limited, labelled
//! with the control step they show, the last one always delivered. Nothing of it lands in the workspace.
use std::sync::{Arc, Mutex};

use libero_episode::records::RunDir;
use libero_episode::task::resolve_task;
use libero_episode::world::{LiberoWorld, SETTLE_STEPS, WorldSpec};
use libero_episode::{EpisodeConfig, Level, LiveEvent, LiveSink, spawn_episode_live};
use libero_render::Renderer;
use libero_sim::AssetPaths;
use serde_json::{Value, json};

const TASK: &str = "libero_90/KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet";

#[test]
fn a_live_episode_reports_calls_steps_frames_telemetry_and_its_end() {
    let dir = tempfile::tempdir().unwrap();
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let spec = WorldSpec { task: resolve_task(TASK, &paths).unwrap(), level: Level::L1, seed: 100, init_index: 0, paths };
    let cfg = EpisodeConfig {
        episode_id: "live".into(),
        instruction: "close the top drawer of the cabinet".into(),
        level: Level::L1,
        max_agent_steps: 100,
        max_wall_time_s: 600.0,
        workspace: dir.path().join("ws"),
        run_dir: dir.path().join("run"),
    };
    std::fs::create_dir_all(cfg.workspace.join("benchmark_inputs")).unwrap();
    let run = RunDir::new(&cfg.run_dir);
    let (video, telemetry) = (run.continuous_video(), run.telemetry_jsonl());
    let seen: Arc<Mutex<Vec<LiveEvent>>> = Arc::default();
    let sink: LiveSink = {
        let seen = seen.clone();
        Arc::new(move |e| seen.lock().unwrap().push(e))
    };
    let world_sink = sink.clone();
    let renderer = Renderer::new().expect("a renderer");
    let handle = spawn_episode_live(cfg.clone(), Some(sink), move || {
        let mut w = LiberoWorld::new(&spec, renderer)?;
        w.set_live(world_sink, Some(&telemetry))?;
        w.record_video(&video)?;
        Ok(w)
    })
    .expect("episode");
    assert_eq!(handle.call("start_episode", None)["ok"], true);
    let actions = json!({"actions": vec![[0.3, 0.0, -0.2, 0.0, 0.0, 0.0, -1.0]; 25]});
    assert_eq!(handle.call("osc_sequence", actions.as_object().cloned())["ok"], true);
    let bad = json!({"actions": [[3, 0, 0, 0, 0, 0, 0]]});
    assert_eq!(handle.call("osc_sequence", bad.as_object().cloned())["ok"], false);
    assert_eq!(handle.call("finish_episode", None)["ok"], true);
    handle.stop("test over"); // waits until the world (and its video recorder) is gone

    let events = seen.lock().unwrap();
    let kinds: Vec<Value> = events.iter().filter(|e| !matches!(e, LiveEvent::Frame(_))).map(|e| json!(e)).collect();
    let calls: Vec<(String, bool)> = kinds
        .iter()
        .filter(|e| e["type"] == "call_answered")
        .map(|e| (e["tool"].as_str().unwrap().to_owned(), e["ok"].as_bool().unwrap()))
        .collect();
    let expected = [("start_episode", true), ("osc_sequence", true), ("osc_sequence", false), ("finish_episode", true)];
    assert_eq!(calls, expected.map(|(t, ok)| (t.to_owned(), ok)));
    assert_eq!(kinds.iter().filter(|e| e["type"] == "call_received").count(), 4);
    let rejected = kinds.iter().filter(|e| e["type"] == "call_answered").nth(2).unwrap();
    assert_eq!((rejected["error_type"].as_str(), rejected["actions"].as_u64()), (Some("ValueError"), Some(1)));
    let steps: Vec<u64> = kinds.iter().filter(|e| e["type"] == "step").map(|e| e["control_step"].as_u64().unwrap()).collect();
    assert_eq!(steps, (0..=25).collect::<Vec<_>>());
    assert!(kinds.iter().any(|e| e["type"] == "progress" && e["required"] == 1), "live progress c/K");
    let finished: Vec<&Value> = kinds.iter().filter(|e| e["type"] == "finished").collect();
    assert_eq!(finished.len(), 1, "the end is reported once");
    assert_eq!(finished[0]["outcome"], "FAIL");

    let frames: Vec<(Option<u64>, u64)> = events
        .iter()
        .filter_map(|e| match e {
            LiveEvent::Frame(f) => Some((f.control_step, f.video_frame)),
            _ => None,
        })
        .collect();
    assert!(!frames.is_empty(), "frames reach the sink");
    assert!(frames.windows(2).all(|w| w[0].1 < w[1].1), "frames in video order: {frames:?}");
    let last_video_frame = (SETTLE_STEPS + 25 - 1) as u64;
    assert_eq!(frames.last(), Some(&(Some(25), last_video_frame)), "the newest frame is always delivered");
    for (step, video_frame) in &frames {
        if let Some(c) = step {
            assert_eq!(*video_frame, c + SETTLE_STEPS as u64 - 1, "label matches the video frame");
        }
    }

    let rows: Vec<Value> = std::fs::read_to_string(run.telemetry_jsonl())
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(rows.len(), 26, "one telemetry row per control step 0..=25");
    assert_eq!(rows[0]["video_frame"], SETTLE_STEPS as u64 - 1);
    assert_eq!(rows[25]["video_frame"], last_video_frame);
    let z = |r: &Value| r["eef_pos_in_base_m"][2].as_f64().unwrap();
    assert!(z(&rows[25]) < z(&rows[0]) - 0.02, "the commanded descent shows in the telemetry");
    assert!(rows.iter().all(|r| r["wrist_force_n"].as_array().is_some_and(|f| f.len() == 3)));
    let workspace_files: Vec<String> = walk(&cfg.workspace);
    assert!(!workspace_files.iter().any(|f| f.contains("telemetry")), "{workspace_files:?}");
}

fn walk(dir: &std::path::Path) -> Vec<String> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        out.push(e.path().display().to_string());
        if e.path().is_dir() {
            out.extend(walk(&e.path()));
        }
    }
    out
}
