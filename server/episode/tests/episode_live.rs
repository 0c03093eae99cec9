//! The operator's live view of a real episode: the actor reports calls and the end, the world reports every
//! control step and its telemetry, and live frames are rendered on demand: none while nobody watches, the
//! newest state (never a backlog) while someone does, labelled with the control step they show, the last one
//! always delivered. Nothing of it lands in the workspace.
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use libero_records::records::RunDir;
use libero_episode::task::resolve_task;
use libero_episode::video_queue::VideoQueue;
use libero_episode::world::{LiberoWorld, SETTLE_STEPS, WorldSpec, head_wrist_cameras};
use libero_episode::live::{LIVE_FRAME_MIN_INTERVAL, LiveViewers};
use libero_episode::{EpisodeConfig, EpisodeHandle, Level, LiveEvent, LiveSink, spawn_episode_live};
use libero_render::Renderer;
use libero_sim::AssetPaths;
use serde_json::{Value, json};

const TASK: &str = "libero_90/KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet";

/// The world and episode configuration of a level-1 episode of [`TASK`] under `dir` (workspace made).
fn level1_episode(dir: &std::path::Path, episode_id: &str, max_agent_steps: u64) -> (WorldSpec, EpisodeConfig) {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let spec = WorldSpec { task: resolve_task(TASK, &paths).unwrap(), level: Level::L1, seed: 100, init_index: 0, paths };
    let cfg = EpisodeConfig {
        episode_id: episode_id.into(),
        instruction: "close the top drawer of the cabinet".into(),
        level: Level::L1,
        max_agent_steps,
        max_wall_time_s: 600.0,
        workspace: dir.join("ws"),
        run_dir: dir.join("run"),
    };
    std::fs::create_dir_all(cfg.workspace.join("benchmark_inputs")).unwrap();
    (spec, cfg)
}

#[test]
fn a_live_episode_reports_calls_steps_frames_telemetry_and_its_end() {
    let dir = tempfile::tempdir().unwrap();
    let (spec, cfg) = level1_episode(dir.path(), "live", 100);
    let run = RunDir::new(&cfg.run_dir);
    let (video, telemetry) = (run.continuous_video(), run.telemetry_jsonl());
    let seen: Arc<Mutex<Vec<LiveEvent>>> = Arc::default();
    let sink: LiveSink = {
        let seen = seen.clone();
        Arc::new(move |e| seen.lock().unwrap().push(e))
    };
    let world_sink = sink.clone();
    let viewers = LiveViewers::new();
    let _viewer = viewers.watch();
    let renderer = Renderer::new().expect("a renderer");
    let handle = spawn_episode_live(cfg.clone(), Some(sink), move || {
        let mut w = LiberoWorld::new(&spec, renderer)?;
        w.set_live(world_sink, viewers, Some(&telemetry))?;
        w.record_video(&video, &video.with_file_name("state_record.bin"), VideoQueue::start(head_wrist_cameras()).expect("video worker"), None)?;
        Ok(w)
    })
    .expect("episode");
    assert_eq!(handle.call("start_episode", None)["ok"], true);
    let actions = json!({"actions": vec![[0.3, 0.0, -0.2, 0.0, 0.0, 0.0, -1.0]; 25]});
    assert_eq!(handle.call("osc_sequence", actions.as_object().cloned())["ok"], true);
    let bad = json!({"actions": [[3, 0, 0, 0, 0, 0, 0]]});
    assert_eq!(handle.call("osc_sequence", bad.as_object().cloned())["ok"], false);
    assert_eq!(handle.call("finish_episode", None)["ok"], true);
    handle.stop("test over"); // waits until the world is gone

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

    let frames: Vec<(Option<u64>, Option<u64>)> = events
        .iter()
        .filter_map(|e| match e {
            LiveEvent::Frame(f) => Some((f.control_step, f.video_frame)),
            _ => None,
        })
        .collect();
    assert!(!frames.is_empty(), "frames reach the sink");
    assert!(frames.windows(2).all(|w| w[0].0 < w[1].0), "frames in step order: {frames:?}");
    let last_video_frame = (SETTLE_STEPS + 25 - 1) as u64;
    assert_eq!(frames.last(), Some(&(Some(25), Some(last_video_frame))), "the newest frame is always delivered");
    for (step, video_frame) in &frames {
        if let Some(c) = step {
            assert_eq!(*video_frame, Some(c + SETTLE_STEPS as u64 - 1), "label matches the video frame");
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

/// A live episode of [`TASK`] with its video on, whose sink collects events (frame events take `frame_delay`
/// each, as a slow viewer would) and whose live renderer counts its renders.
struct Watched {
    handle: EpisodeHandle,
    seen: Arc<Mutex<Vec<LiveEvent>>>,
    viewers: LiveViewers,
    renders: Arc<AtomicU64>,
    _dir: tempfile::TempDir,
}

fn watched_episode(frame_delay: Duration) -> Watched {
    let dir = tempfile::tempdir().unwrap();
    let (spec, cfg) = level1_episode(dir.path(), "on-demand", 1000);
    let video = RunDir::new(&cfg.run_dir).continuous_video();
    let seen: Arc<Mutex<Vec<LiveEvent>>> = Arc::default();
    let sink: LiveSink = {
        let seen = seen.clone();
        Arc::new(move |e| {
            if matches!(e, LiveEvent::Frame(_)) {
                std::thread::sleep(frame_delay);
            }
            seen.lock().unwrap().push(e)
        })
    };
    let viewers = LiveViewers::new();
    let (world_viewers, world_sink) = (viewers.clone(), sink.clone());
    let counter: Arc<Mutex<Option<Arc<AtomicU64>>>> = Arc::default();
    let world_counter = counter.clone();
    let renderer = Renderer::new().expect("a renderer");
    let handle = spawn_episode_live(cfg, Some(sink), move || {
        let mut w = LiberoWorld::new(&spec, renderer)?;
        w.set_live(world_sink, world_viewers, None)?;
        w.record_video(&video, &video.with_file_name("state_record.bin"), VideoQueue::start(head_wrist_cameras()).expect("video worker"), None)?;
        *world_counter.lock().unwrap() = w.live_render_counter();
        Ok(w)
    })
    .expect("episode");
    assert_eq!(handle.call("start_episode", None)["ok"], true);
    let renders = counter.lock().unwrap().clone().expect("the live renderer's counter");
    Watched { handle, seen, viewers, renders, _dir: dir }
}

impl Watched {
    fn act(&self, n: usize) {
        let actions = json!({"actions": vec![[0.2, 0.0, -0.1, 0.0, 0.0, 0.0, -1.0]; n]});
        assert_eq!(self.handle.call("osc_sequence", actions.as_object().cloned())["ok"], true);
    }

    fn frame_steps(&self) -> Vec<Option<u64>> {
        let seen = self.seen.lock().unwrap();
        seen.iter()
            .filter_map(|e| match e {
                LiveEvent::Frame(f) => Some(f.control_step),
                _ => None,
            })
            .collect()
    }

    /// Waits (up to `limit`) for a frame of control step `step`; how long it took.
    fn wait_for_frame(&self, step: u64, limit: Duration) -> Option<Duration> {
        let t0 = Instant::now();
        while t0.elapsed() < limit {
            if self.frame_steps().contains(&Some(step)) {
                return Some(t0.elapsed());
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        None
    }
}

#[test]
fn no_live_frame_is_rendered_while_nobody_watches() {
    let ep = watched_episode(Duration::ZERO);
    ep.act(20);
    ep.act(20);
    assert_eq!(ep.handle.call("finish_episode", None)["ok"], true);
    ep.handle.stop("test over");
    assert_eq!(ep.renders.load(Ordering::Acquire), 0, "no viewer, no render (the video does not feed the live view)");
    assert!(ep.frame_steps().is_empty());
}

#[test]
fn a_viewer_arriving_mid_episode_gets_the_newest_state_in_its_first_frame() {
    let ep = watched_episode(Duration::ZERO);
    ep.act(10);
    std::thread::sleep(LIVE_FRAME_MIN_INTERVAL * 2);
    assert_eq!(ep.renders.load(Ordering::Acquire), 0);
    let viewer = ep.viewers.watch();
    let waited = ep.wait_for_frame(10, Duration::from_secs(20)).expect("a frame of the newest state");
    eprintln!("first frame for a new viewer after {waited:?}");
    assert_eq!(ep.frame_steps(), [Some(10)], "one frame, of the newest state (not an older one first)");
    // The newest state is the one the call's observation showed: its images are reused, nothing is rendered.
    assert_eq!(ep.renders.load(Ordering::Acquire), 0);
    // Idle simulation, one viewer: nothing newer to show, so no frame.
    std::thread::sleep(LIVE_FRAME_MIN_INTERVAL * 4);
    assert_eq!(ep.frame_steps().len(), 1);
    drop(viewer);
    ep.act(5);
    std::thread::sleep(LIVE_FRAME_MIN_INTERVAL * 4);
    assert_eq!(ep.frame_steps().len(), 1, "the viewer left: no more frames");
    assert_eq!(ep.renders.load(Ordering::Acquire), 0, "the viewer left: no render");
    ep.handle.stop("test over");
}

#[test]
fn a_slow_viewer_gets_far_fewer_renders_than_steps_and_always_the_newest_state() {
    let ep = watched_episode(Duration::from_millis(150));
    let _viewer = ep.viewers.watch();
    let steps = 200;
    for _ in 0..4 {
        ep.act(50);
    }
    ep.wait_for_frame(steps, Duration::from_secs(20)).expect("the final state is rendered");
    let renders = ep.renders.load(Ordering::Acquire);
    let frames = ep.frame_steps();
    eprintln!("{steps} control steps, {renders} renders: {frames:?}");
    assert!(frames.len() as u64 * 4 < steps, "skip to the latest: {} frames ({renders} rendered) for {steps} steps", frames.len());
    assert!(renders as usize <= frames.len(), "each render is delivered");
    assert!(frames.windows(2).all(|w| w[0] < w[1]), "never an older state after a newer one: {frames:?}");
    ep.handle.stop("test over");
}

/// A watched episode's frame after each call comes from the observation the call rendered (same state, same
/// cameras, same size), not from a second render: more frames arrive than the live renderer renders, and the
/// call's last control step is always among them.
#[test]
fn the_frame_after_a_call_reuses_the_observation_it_rendered() {
    let ep = watched_episode(Duration::ZERO);
    let _viewer = ep.viewers.watch();
    for call in 1..=6u64 {
        ep.act(1);
        assert!(ep.wait_for_frame(call, Duration::from_secs(30)).is_some(), "a frame of control step {call}");
    }
    let frames = ep.frame_steps().len() as u64;
    let renders = ep.renders.load(Ordering::Acquire);
    assert!(frames > renders, "{frames} frames from {renders} renders: the observations' images were not reused");
    ep.handle.stop("test over");
}

/// A 50-action call (2.5 s of motion) is shown to a watcher as motion played back at the control rate, not as one
/// jump to its end: frames of several control steps inside the call, in order, spread over about the call's
/// simulated duration, ending on its last step.
#[test]
fn a_long_call_is_watched_as_motion_at_the_control_rate() {
    let ep = watched_episode(Duration::ZERO);
    let _viewer = ep.viewers.watch();
    let t0 = Instant::now();
    ep.act(50);
    let answered = t0.elapsed();
    ep.wait_for_frame(50, Duration::from_secs(30)).expect("the call's last state is shown");
    let took = t0.elapsed();
    let frames: Vec<u64> = ep.frame_steps().into_iter().flatten().filter(|&c| c > 0).collect();
    eprintln!("call answered after {answered:?}; frames {frames:?}, the last after {took:?}");
    assert!(frames.windows(2).all(|w| w[0] < w[1]), "in order: {frames:?}");
    let inside = frames.iter().filter(|&&c| c < 50).count();
    assert!(inside >= 3, "motion inside the call is shown, not only its end: {frames:?}");
    // Played back, not jumped: the last frame cannot come before most of the call's 2.5 s of motion has been shown
    // (however fast the simulation ran the call).
    assert!(took >= Duration::from_millis(2000), "the call's motion was shown in {took:?}");
    ep.handle.stop("test over");
}

/// Minor page faults of this process so far.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn minor_faults() -> u64 {
    // SAFETY: getrusage writes only into the struct it is given.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    assert_eq!(unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) }, 0);
    usage.ru_minflt as u64
}

/// Frames rendered one after another (a watched or teleoperated episode) fault in no fresh pages: the renderer's
/// per-frame buffers stay with the allocator between frames (`libero_episode::memory`'s trim threshold). With
/// glibc's default trim threshold every frame gave them back and faulted them in again, about 14,000 pages a frame.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[test]
fn frames_rendered_one_after_another_do_not_fault_their_buffers_in_again() {
    use libero_episode::World;
    libero_episode::memory::tune_for_long_runs();
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let spec = WorldSpec { task: resolve_task("T14", &paths).unwrap(), level: Level::L1, seed: 100, init_index: 0, paths };
    let mut world = LiberoWorld::new(&spec, Renderer::new().unwrap()).unwrap();
    world.start().unwrap();
    for i in 0..5 {
        world.frame(i).unwrap();
    }
    const FRAMES: u64 = 20;
    let before = minor_faults();
    for i in 0..FRAMES {
        world.frame(5 + i).unwrap();
    }
    let per_frame = (minor_faults() - before) / FRAMES;
    assert!(per_frame < 1_000, "{per_frame} minor page faults per rendered frame");
}
