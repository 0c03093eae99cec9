//! The operator's live view of an episode: events the actor and the world emit while the episode runs (calls,
//! control steps, private stage events, frames, the end), handed to a [`LiveSink`] the server installs. The
//! sink must return at once (the server fans out through a broadcast channel); the episode thread never waits
//! for a viewer. Nothing here reaches the agent's workspace: private evaluator progress is for operators only.
//!
//! Frames are rendered on demand: the server counts who watches ([`LiveViewers`]); with nobody watching no
//! frame is rendered, and with viewers the episode's live renderer (`world` feature: [`LiveRenderer`]) renders
//! the newest simulation state, skipping states it had no time for, so a viewer never sees a backlog.
//!
//! With the `world` feature: [`WorldTap`] (per control step: `telemetry.jsonl` in the run directory, step and
//! stage events) and [`LiveRenderer`] (head | wrist of the newest state, at most every
//! [`LIVE_FRAME_MIN_INTERVAL`], JPEG-encoded once per frame for all viewers).
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use serde::Serialize;
use serde_json::Value;

/// Where an episode's live events go. Called from the episode and video threads; must not block.
pub type LiveSink = Arc<dyn Fn(LiveEvent) + Send + Sync>;

/// One head | wrist frame, encoded once and shared by every viewer.
#[derive(Debug, Clone)]
pub struct LiveFrame {
    /// Control steps since the evaluator reset (0 = the settled start); `None` for settle steps.
    pub control_step: Option<u64>,
    pub sim_time_s: f64,
    /// Index of the same state's frame in `continuous_video.mp4` (`None` without a video or before the reset).
    pub video_frame: Option<u64>,
    pub width_px: u32,
    pub height_px: u32,
    pub jpeg: Arc<[u8]>,
}

/// What happened, in order, as the operator's dashboard shows it.
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum LiveEvent {
    /// A tool call reached the episode thread.
    CallReceived {
        tool: String,
        /// Number of micro-actions for `osc_sequence` (when the argument is an array).
        actions: Option<usize>,
        at_unix_s: f64,
    },
    /// Its answer left the episode thread.
    CallAnswered {
        tool: String,
        actions: Option<usize>,
        ok: bool,
        error_type: Option<String>,
        error: Option<String>,
        observation_id: Option<String>,
        accepted_agent_steps: u64,
        /// Budgets as they stand after this call.
        max_agent_steps: u64,
        wall_time_s: Option<f64>,
        max_wall_time_s: f64,
        at_unix_s: f64,
    },
    /// After every control step (0 = the settled start state).
    Step { control_step: u64, sim_time_s: f64 },
    /// A private evaluator event (stage completed/regressed, first commitment, goal changes) as it happens.
    Stage { event: Value },
    /// Live stage progress `completed / required` (K).
    Progress { completed: usize, required: usize },
    /// The episode ended (finished, expired or aborted).
    Finished { state: String, outcome: Option<String>, reason: Option<String> },
    /// A rendered frame; carried as binary, not JSON.
    #[serde(skip)]
    Frame(LiveFrame),
}

/// Wall-clock seconds since the Unix epoch (for event times shown to operators).
pub fn unix_now_s() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}

pub use libero_records::records::TELEMETRY_FILE;

/// Called when the number of viewers changes (the live renderer wakes up on it).
type ViewersChanged = Arc<dyn Fn() + Send + Sync>;

/// How many viewers watch an episode's frames: the server's hub holds one [`ViewerGuard`] per frame
/// subscriber, the episode's live renderer renders only while the count is above zero. Cloning shares it.
#[derive(Clone, Default)]
pub struct LiveViewers(Arc<ViewersInner>);

#[derive(Default)]
struct ViewersInner {
    count: AtomicUsize,
    on_change: Mutex<Option<ViewersChanged>>,
}

impl LiveViewers {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn count(&self) -> usize {
        self.0.count.load(Ordering::Acquire)
    }

    /// Counts one viewer until the guard is dropped.
    pub fn watch(&self) -> ViewerGuard {
        self.0.count.fetch_add(1, Ordering::AcqRel);
        self.changed();
        ViewerGuard(self.clone())
    }

    /// Installs the wake-up of the one renderer that serves these viewers (replacing any earlier one).
    pub fn on_change(&self, wake: ViewersChanged) {
        if let Ok(mut slot) = self.0.on_change.lock() {
            *slot = Some(wake);
        }
    }

    fn changed(&self) {
        let wake = self.0.on_change.lock().ok().and_then(|w| w.clone());
        if let Some(wake) = wake {
            wake();
        }
    }
}

/// One viewer, counted in its [`LiveViewers`] while it lives.
pub struct ViewerGuard(LiveViewers);

impl Drop for ViewerGuard {
    fn drop(&mut self) {
        self.0.0.count.fetch_sub(1, Ordering::AcqRel);
        self.0.changed();
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicUsize;

    use super::*;

    #[test]
    fn viewers_are_counted_while_their_guards_live_and_every_change_wakes_the_renderer() {
        let viewers = LiveViewers::new();
        let wakes = Arc::new(AtomicUsize::new(0));
        let w = wakes.clone();
        viewers.on_change(Arc::new(move || {
            w.fetch_add(1, Ordering::AcqRel);
        }));
        let (a, b) = (viewers.watch(), viewers.clone().watch());
        assert_eq!((viewers.count(), wakes.load(Ordering::Acquire)), (2, 2));
        drop(a);
        assert_eq!(viewers.count(), 1);
        drop(b);
        assert_eq!((viewers.count(), wakes.load(Ordering::Acquire)), (0, 4));
    }
}

#[cfg(feature = "world")]
pub use live_renderer::{LiveRenderer, LiveState};
#[cfg(feature = "world")]
pub use world_taps::{LIVE_FRAME_MIN_INTERVAL, LIVE_OBSERVATION_GRACE, TelemetryRow, WorldTap, encode_jpeg};

#[cfg(feature = "world")]
mod world_taps {
    use std::fs::File;
    use std::io::{BufWriter, Write};
    use std::path::Path;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::time::Duration;

    use libero_tasks::judge::evaluator::PrivateEvent;
    use serde::Serialize;

    use super::{LiveEvent, LiveSink};
    use crate::observation::RobotReadout;

    /// At most 20 live frames a second (the control rate) are rendered, however many viewers watch.
    pub const LIVE_FRAME_MIN_INTERVAL: Duration = Duration::from_millis(50);
    /// How long a state without images waits for an observation of a newer state before it is rendered. A call
    /// ends with an observation, whose images the live view reuses for nothing; rendering the steps inside a
    /// short call would only take the cores the call's own render needs and delay the frame after it (teleop's
    /// batches). A call longer than this still shows motion while it runs.
    pub const LIVE_OBSERVATION_GRACE: Duration = Duration::from_millis(150);
    /// JPEG quality of live frames: small enough for many viewers, sharp enough to read the scene.
    const JPEG_QUALITY: u8 = 80;
    /// `origin` before the evaluator reset: frames until then are settle steps.
    const NOT_STARTED: u64 = u64::MAX;

    /// One line of `telemetry.jsonl`: what the review page plots against the video.
    #[derive(Debug, Clone, Serialize)]
    pub struct TelemetryRow {
        pub control_step: u64,
        pub sim_time_s: f64,
        /// Index of this state's frame in `continuous_video.mp4` (its time there is `video_frame / 20` s).
        pub video_frame: Option<u64>,
        pub eef_pos_in_base_m: [f64; 3],
        pub gripper_qpos_m: [f64; 2],
        pub wrist_force_n: [f64; 3],
    }

    /// The world's side: counts recorded video frames, writes telemetry and emits step and stage events.
    pub struct WorldTap {
        sink: LiveSink,
        telemetry: Option<BufWriter<File>>,
        /// Video frames queued so far (one per physics control step, settle steps included).
        video_frames: Arc<AtomicU64>,
        /// Video frames queued at the evaluator reset (the frame of control step c is `origin + c - 1`).
        origin: Arc<AtomicU64>,
        /// How many of the evaluator's private events (an append-only list since the reset) were sent.
        events_listed: usize,
        /// Every private event sent since the reset, so the verdict's stage events are sent once.
        sent: Vec<PrivateEvent>,
        progress_sent: Option<(usize, usize)>,
    }

    impl WorldTap {
        /// `telemetry` is the run directory's `telemetry.jsonl` (created, truncated).
        pub fn new(sink: LiveSink, telemetry: Option<&Path>) -> std::io::Result<Self> {
            let telemetry = telemetry.map(File::create).transpose()?.map(BufWriter::new);
            Ok(Self {
                sink,
                telemetry,
                video_frames: Arc::new(AtomicU64::new(0)),
                origin: Arc::new(AtomicU64::new(NOT_STARTED)),
                events_listed: 0,
                sent: Vec::new(),
                progress_sent: None,
            })
        }

        pub fn sink(&self) -> &LiveSink {
            &self.sink
        }

        /// Counts one recorded video frame (call from the video step observer).
        pub fn frame_counter(&self) -> Arc<AtomicU64> {
            self.video_frames.clone()
        }

        /// Index of control step `control_step`'s frame in the video (`None` without one or before the reset).
        pub fn video_frame(&self, control_step: u64) -> Option<u64> {
            let origin = self.origin.load(Ordering::Acquire);
            (origin != NOT_STARTED && self.video_frames.load(Ordering::Acquire) > 0)
                .then(|| (origin + control_step).saturating_sub(1))
        }

        /// At the evaluator reset (after settling): control step 0.
        pub fn on_reset(&mut self, robot: &RobotReadout, events: &[PrivateEvent], progress: Option<(usize, usize)>) {
            self.origin.store(self.video_frames.load(Ordering::Acquire), Ordering::Release);
            self.events_listed = 0;
            self.sent.clear();
            self.progress_sent = None;
            self.after_step(0, robot, events, progress);
        }

        /// After control step `control_step`: a telemetry line, a step event, new private events, progress.
        pub fn after_step(
            &mut self,
            control_step: u64,
            robot: &RobotReadout,
            events: &[PrivateEvent],
            progress: Option<(usize, usize)>,
        ) {
            let p = robot.eef_pose_robot_base_xyzw;
            let row = TelemetryRow {
                control_step,
                sim_time_s: robot.sim_time_s,
                video_frame: self.video_frame(control_step),
                eef_pos_in_base_m: [p[0], p[1], p[2]],
                gripper_qpos_m: robot.gripper_finger_joint_position_m,
                wrist_force_n: robot.eef_force_sensor_n,
            };
            if let Some(w) = self.telemetry.as_mut() {
                let written = serde_json::to_writer(&mut *w, &row).map_err(std::io::Error::from).and_then(|()| {
                    w.write_all(b"\n")?;
                    w.flush()
                });
                if let Err(e) = written {
                    log::error!("telemetry.jsonl: {e}; telemetry stops here");
                    self.telemetry = None;
                }
            }
            (self.sink)(LiveEvent::Step { control_step, sim_time_s: robot.sim_time_s });
            for e in events.iter().skip(self.events_listed) {
                self.send_event(e);
            }
            self.events_listed = self.events_listed.max(events.len());
            self.send_progress(progress);
        }

        /// At the verdict (finish, or the wall-time expiry): the record's stage events not sent yet (stages judged on
        /// the final state complete at finish: `bddl_terminal`, tube insertion) and its `completed / K`, so the live
        /// view ends on the record's figures whatever the evaluator. Sends nothing twice.
        pub fn on_verdict(&mut self, stage_events: &[PrivateEvent], progress: (usize, usize)) {
            for e in stage_events {
                if !self.sent.contains(e) {
                    self.send_event(e);
                }
            }
            self.send_progress(Some(progress));
        }

        fn send_event(&mut self, e: &PrivateEvent) {
            if let Ok(event) = serde_json::to_value(e) {
                (self.sink)(LiveEvent::Stage { event });
            }
            self.sent.push(e.clone());
        }

        fn send_progress(&mut self, progress: Option<(usize, usize)>) {
            if progress != self.progress_sent {
                if let Some((completed, required)) = progress {
                    (self.sink)(LiveEvent::Progress { completed, required });
                }
                self.progress_sent = progress;
            }
        }
    }

    /// Baseline JPEG of an RGB image.
    pub fn encode_jpeg(rgb: &[u8], width_px: u32, height_px: u32) -> Result<Vec<u8>, String> {
        let (w, h) = (u16::try_from(width_px).map_err(|e| e.to_string())?, u16::try_from(height_px).map_err(|e| e.to_string())?);
        let mut out = Vec::with_capacity(rgb.len() / 8);
        jpeg_encoder::Encoder::new(&mut out, JPEG_QUALITY)
            .encode(rgb, w, h, jpeg_encoder::ColorType::Rgb)
            .map_err(|e| e.to_string())?;
        Ok(out)
    }

    #[cfg(test)]
    mod tests {
        use std::sync::Mutex;

        use libero_tasks::Tick;
        use libero_tasks::judge::evaluator::EventKind;

        use super::*;

        fn stage(kind: EventKind, step: u64, name: &str) -> PrivateEvent {
            let tick = Tick::at_control_step(step, step as f64 * 0.05);
            PrivateEvent { stage_index: Some(0), stage_name: Some(name.into()), ..PrivateEvent::new(kind, tick) }
        }

        #[test]
        fn stage_events_go_out_at_their_step_and_the_verdict_adds_only_what_finish_judged_with_the_records_count() {
            let seen: Arc<Mutex<Vec<serde_json::Value>>> = Arc::default();
            let sink: LiveSink = {
                let seen = seen.clone();
                Arc::new(move |e| seen.lock().unwrap().push(serde_json::to_value(&e).unwrap()))
            };
            let mut tap = WorldTap::new(sink, None).unwrap();
            let robot = RobotReadout::default();
            let done = stage(EventKind::StageCompleted, 3, "01_a");
            tap.on_reset(&robot, &[], Some((0, 2)));
            tap.after_step(3, &robot, std::slice::from_ref(&done), Some((1, 2)));
            tap.after_step(4, &robot, std::slice::from_ref(&done), Some((1, 2)));
            // The record repeats the live stage and adds one judged on the final state.
            let at_finish = stage(EventKind::StageCompleted, 4, "02_b");
            tap.on_verdict(&[done.clone(), at_finish.clone()], (2, 2));
            tap.on_verdict(&[done, at_finish], (2, 2));
            let seen = seen.lock().unwrap();
            let kinds: Vec<String> = seen
                .iter()
                .map(|e| match e["type"].as_str().unwrap() {
                    "step" => format!("step {}", e["control_step"]),
                    "stage" => format!("{} {}", e["event"]["stage_name"].as_str().unwrap(), e["event"]["control_step"]),
                    "progress" => format!("{}/{}", e["completed"], e["required"]),
                    other => other.to_owned(),
                })
                .collect();
            assert_eq!(kinds, ["step 0", "0/2", "step 3", "01_a 3", "1/2", "step 4", "02_b 4", "2/2"]);
        }
    }
}

#[cfg(feature = "world")]
mod live_renderer {
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::sync::{Arc, Condvar, Mutex};
    use std::thread::JoinHandle;
    use std::time::{Duration, Instant};

    use libero_render::{FrameState, ModelHandle, Renderer};

    use super::world_taps::{LIVE_FRAME_MIN_INTERVAL, LIVE_OBSERVATION_GRACE, encode_jpeg};
    use super::{LiveEvent, LiveFrame, LiveSink, LiveViewers};
    use crate::video::{Lane, VideoCameras, render_head_wrist, side_by_side};

    /// The newest simulation state as the world leaves it after a control step (poses only: no rendering).
    pub struct LiveState {
        pub state: FrameState,
        /// `None` before the evaluator reset (settling).
        pub control_step: Option<u64>,
        pub sim_time_s: f64,
        pub video_frame: Option<u64>,
        /// Head and wrist RGB of this state already rendered at the live size (an observation the episode made
        /// of it): the live frame reuses them instead of rendering the state again.
        pub rendered: Option<(Vec<u8>, Vec<u8>)>,
    }

    /// Motion of at most this much simulated time since the last shown frame is shown as its newest state at once
    /// (teleop's short calls feel immediate); a longer stretch (an agent's or an expert's 50-action call) is
    /// played back at the control rate's pace, so a watcher sees the robot move rather than jump.
    pub const PLAYBACK_SNAP_S: f64 = 0.25;
    /// The most a played-back frame trails the newest simulated state: past it, playback skips ahead.
    pub const MAX_PLAYBACK_LAG_S: f64 = 3.0;
    /// One control period (20 Hz): the first state of a played-back stretch is due this long after it starts.
    const CONTROL_PERIOD_S: f64 = 0.05;
    /// A stretch is played back only when the simulation ran it at least this much faster than real time (an
    /// agent's call executed in a fraction of its duration). A stream of states arriving in real time (teleop, or a
    /// simulation that is no faster than the clock) is already motion at its pace: its newest state is shown, so
    /// playback never adds latency there.
    const RAN_AHEAD_FACTOR: f64 = 1.5;

    /// The states waiting for the live renderer, oldest first, and the playback clock. While nobody watches only
    /// the newest is kept; while someone does, states older than [`MAX_PLAYBACK_LAG_S`] behind the newest are
    /// dropped, so the queue stays short (at most about 3 s of control steps).
    struct Slot {
        queue: std::collections::VecDeque<LiveState>,
        playback: Playback,
        /// When the queue last went from empty to holding a state: how long the pending frame has waited.
        pending_since: Option<Instant>,
        /// When the episode last published a state (the simulation stepped then).
        last_published: Option<Instant>,
        closed: bool,
    }

    /// Where playback stands: the simulated time last shown, and while a stretch is being played back, the
    /// wall-clock instant and simulated time it is anchored at (1 s of wall time shows 1 s of motion).
    #[derive(Debug, Clone, Copy, Default, PartialEq)]
    struct Playback {
        shown_sim_s: Option<f64>,
        anchor: Option<(Instant, f64)>,
    }

    /// What the renderer does next with the queued states (their simulated times and whether each carries its
    /// images).
    #[derive(Debug, Clone, Copy, PartialEq)]
    enum Next {
        /// Show the state at this index (the ones before it are skipped).
        Show(usize),
        Wait(Duration),
    }

    impl Playback {
        /// Decides the next frame. A short stretch (≤ [`PLAYBACK_SNAP_S`]), or one published no faster than real
        /// time ([`RAN_AHEAD_FACTOR`]; `pending_since` to `last_published`), shows its newest state: at once when it
        /// carries its images (an observation's), else once the render pace allows and it has waited
        /// [`LIVE_OBSERVATION_GRACE`] for an observation. A longer one the simulation ran ahead is played back: the
        /// newest state due by the clock, no sooner than the render pace allows, the clock moved on when it trails
        /// by more than [`MAX_PLAYBACK_LAG_S`].
        fn next(
            &mut self,
            now: Instant,
            queued: &[(f64, bool)],
            not_before: Option<Instant>,
            pending_since: Option<Instant>,
            last_published: Option<Instant>,
        ) -> Next {
            let (Some(&(first_s, _)), Some(&(newest_s, newest_rendered))) = (queued.first(), queued.last()) else {
                return Next::Wait(Duration::from_secs(3600));
            };
            let start_s = match self.shown_sim_s {
                Some(shown) if shown >= first_s - CONTROL_PERIOD_S && shown <= first_s => shown,
                _ => first_s - CONTROL_PERIOD_S,
            };
            let paced = not_before.map_or(Duration::ZERO, |t| t.saturating_duration_since(now));
            let published_over_s = match (pending_since, last_published) {
                (Some(a), Some(b)) => b.saturating_duration_since(a).as_secs_f64(),
                _ => 0.0,
            };
            let ran_ahead = newest_s - start_s > PLAYBACK_SNAP_S && newest_s - first_s > RAN_AHEAD_FACTOR * published_over_s;
            if self.anchor.is_none() && !ran_ahead {
                let wait = wait_before_showing(now, newest_rendered, not_before, pending_since);
                return if wait.is_zero() { Next::Show(queued.len() - 1) } else { Next::Wait(wait) };
            }
            let anchor = self.anchor.get_or_insert((now, start_s));
            let mut due_s = anchor.1 + now.saturating_duration_since(anchor.0).as_secs_f64();
            if newest_s - due_s > MAX_PLAYBACK_LAG_S {
                anchor.1 += newest_s - due_s - MAX_PLAYBACK_LAG_S;
                due_s = newest_s - MAX_PLAYBACK_LAG_S;
            }
            match queued.iter().rposition(|&(t, _)| t <= due_s + 1e-9) {
                None => Next::Wait(paced.max(Duration::from_secs_f64((first_s - due_s).clamp(0.001, 1.0)))),
                Some(i) if paced.is_zero() || queued[i].1 => Next::Show(i),
                Some(_) => Next::Wait(paced),
            }
        }

        /// After showing a state of simulated time `shown_s`; `drained` when nothing is left to play.
        fn shown(&mut self, shown_s: f64, drained: bool) {
            self.shown_sim_s = Some(shown_s);
            if drained {
                self.anchor = None;
            }
        }
    }

    struct Shared {
        slot: Mutex<Slot>,
        wake: Condvar,
    }

    impl Shared {
        /// Wakes the renderer; taking the lock first means a wake-up between its check and its wait is not lost.
        fn notify(&self) {
            let _slot = self.slot.lock();
            self.wake.notify_all();
        }
    }

    /// An episode's live renderer thread: while at least one viewer watches, renders head | wrist of the states
    /// the episode publishes, played back at the control rate's pace ([`Playback`]), at most every
    /// [`LIVE_FRAME_MIN_INTERVAL`] and leaving the simulation at least half a core, on the renderer's normal lane
    /// (the video keeps to its background lane), and hands the JPEG to the sink. Dropping it ends the thread;
    /// the newest state still waiting then is rendered first if someone watches, so viewers always end on the
    /// final state.
    pub struct LiveRenderer {
        shared: Arc<Shared>,
        viewers: LiveViewers,
        renders: Arc<AtomicU64>,
        thread: Option<JoinHandle<()>>,
    }

    impl LiveRenderer {
        pub fn spawn(
            renderer: Renderer,
            model: ModelHandle,
            cameras: VideoCameras,
            sink: LiveSink,
            viewers: LiveViewers,
        ) -> std::io::Result<Self> {
            let shared = Arc::new(Shared {
                slot: Mutex::new(Slot { queue: Default::default(), playback: Playback::default(), pending_since: None, last_published: None, closed: false }),
                wake: Condvar::new(),
            });
            let waker = shared.clone();
            viewers.on_change(Arc::new(move || waker.notify()));
            let renders = Arc::new(AtomicU64::new(0));
            let job = Job { shared: shared.clone(), viewers: viewers.clone(), renderer, model, cameras, sink, renders: renders.clone(), failed: false };
            let thread = std::thread::Builder::new().name("live-render".into()).spawn(move || job.run())?;
            Ok(Self { shared, viewers, renders, thread: Some(thread) })
        }

        /// Queues the newest state. The same control step again (its call's observation, with images) replaces
        /// the queued one; a state earlier in simulated time than the queue's newest (a restart) starts playback
        /// over; with nobody watching only the newest is kept. Never waits for a render.
        pub fn publish(&self, state: LiveState) {
            let Ok(mut slot) = self.shared.slot.lock() else { return };
            let newest_s = slot.queue.back().map(|s| s.sim_time_s);
            if slot.queue.back().is_some_and(|s| s.control_step.is_some() && s.control_step == state.control_step) {
                slot.queue.pop_back();
            }
            if newest_s.is_some_and(|t| state.sim_time_s < t) || self.viewers.count() == 0 {
                slot.queue.clear();
                slot.playback = Playback::default();
            }
            while slot.queue.front().is_some_and(|s| s.sim_time_s < state.sim_time_s - MAX_PLAYBACK_LAG_S - CONTROL_PERIOD_S) {
                slot.queue.pop_front();
            }
            let now = Instant::now();
            if slot.queue.is_empty() {
                slot.pending_since = Some(now);
            }
            slot.last_published = Some(now);
            slot.queue.push_back(state);
            self.shared.wake.notify_all();
        }

        /// Frames rendered so far (a test hook: zero while nobody watches).
        pub fn render_counter(&self) -> Arc<AtomicU64> {
            self.renders.clone()
        }
    }

    impl Drop for LiveRenderer {
        fn drop(&mut self) {
            if let Ok(mut slot) = self.shared.slot.lock() {
                slot.closed = true;
                self.shared.wake.notify_all();
            }
            if let Some(t) = self.thread.take()
                && t.join().is_err()
            {
                log::error!("the live renderer thread panicked");
            }
            // The hub's viewer count outlives the world and holds the wake-up: leave no pose snapshot there.
            if let Ok(mut slot) = self.shared.slot.lock() {
                slot.queue.clear();
            }
        }
    }

    /// The thread's side.
    struct Job {
        shared: Arc<Shared>,
        viewers: LiveViewers,
        renderer: Renderer,
        model: ModelHandle,
        cameras: VideoCameras,
        sink: LiveSink,
        renders: Arc<AtomicU64>,
        /// A render failure is logged once, not at frame rate.
        failed: bool,
    }

    /// When the next live render may start after one that ran from `started` to `ended`: at the rate cap, and
    /// after an idle time as long as the render took, so that watching never takes more than half a core from
    /// the simulation on a CPU renderer (a render there costs about as much as many control steps).
    /// While the simulation stands still (`simulating` false: no state was published during the render, as between
    /// an agent's calls or while a paced expert waits out its call), there is nothing to leave room for: only the
    /// rate cap holds, so a call played back after it ran is shown as smoothly as the renderer allows.
    fn next_render_at(started: Instant, ended: Instant, simulating: bool) -> Instant {
        let cost = ended.saturating_duration_since(started);
        let capped = started + LIVE_FRAME_MIN_INTERVAL;
        if simulating { capped.max(ended + cost) } else { capped }
    }

    /// How long the newest state of a short stretch must still wait before it is shown (see [`Playback::next`]).
    fn wait_before_showing(now: Instant, prerendered: bool, not_before: Option<Instant>, pending_since: Option<Instant>) -> Duration {
        if prerendered {
            return Duration::ZERO;
        }
        let paced = not_before.map_or(Duration::ZERO, |t| t.saturating_duration_since(now));
        let grace = pending_since.map_or(Duration::ZERO, |t| (t + LIVE_OBSERVATION_GRACE).saturating_duration_since(now));
        paced.max(grace)
    }

    impl Job {
        fn run(mut self) {
            let mut not_before: Option<Instant> = None;
            let mut shown: Option<(u64, u64)> = None;
            while let Some(state) = self.next(not_before) {
                // A step rendered live while its call's observation was late, then that observation: one frame.
                let label = state.control_step.zip(state.video_frame);
                if label.is_some() && label == shown {
                    continue;
                }
                shown = label.or(shown);
                let started = Instant::now();
                self.render(state);
                let simulating = self.shared.slot.lock().map_or(true, |slot| slot.last_published.is_some_and(|t| t >= started));
                not_before = Some(next_render_at(started, Instant::now(), simulating));
            }
        }

        /// Waits for the next state to show while someone watches ([`Playback::next`]); `None` once the world is
        /// gone and nothing is left to show (then the newest waiting state is the last one shown).
        fn next(&self, not_before: Option<Instant>) -> Option<LiveState> {
            let mut slot = self.shared.slot.lock().ok()?;
            loop {
                let wanted = !slot.queue.is_empty() && self.viewers.count() > 0;
                if slot.closed {
                    let last = if wanted { slot.queue.pop_back() } else { None };
                    slot.queue.clear();
                    return last;
                }
                if !wanted {
                    slot = self.shared.wake.wait(slot).ok()?;
                    continue;
                }
                let queued: Vec<(f64, bool)> = slot.queue.iter().map(|s| (s.sim_time_s, s.rendered.is_some())).collect();
                let (pending_since, last_published) = (slot.pending_since, slot.last_published);
                match slot.playback.next(Instant::now(), &queued, not_before, pending_since, last_published) {
                    Next::Show(i) => {
                        let state = slot.queue.drain(..=i).last()?;
                        let drained = slot.queue.is_empty();
                        slot.playback.shown(state.sim_time_s, drained);
                        slot.pending_since = if drained { None } else { Some(Instant::now()) };
                        return Some(state);
                    }
                    Next::Wait(wait) => slot = self.shared.wake.wait_timeout(slot, wait).ok()?.0,
                }
            }
        }

        fn render(&mut self, live: LiveState) {
            let size = self.cameras.size_px;
            let rgb = if let Some((head, wrist)) = &live.rendered {
                side_by_side(head, wrist, size as usize, size as usize)
            } else {
                self.renders.fetch_add(1, Ordering::AcqRel);
                render_head_wrist(&self.renderer, &self.model, &live.state, &self.cameras, Lane::Normal)
            };
            let jpeg = rgb.map_err(|e| e.to_string()).and_then(|rgb| encode_jpeg(&rgb, 2 * size, size));
            match jpeg {
                Ok(jpeg) => (self.sink)(LiveEvent::Frame(LiveFrame {
                    control_step: live.control_step,
                    sim_time_s: live.sim_time_s,
                    video_frame: live.video_frame,
                    width_px: 2 * size,
                    height_px: size,
                    jpeg: jpeg.into(),
                })),
                Err(e) if !self.failed => {
                    self.failed = true;
                    log::warn!("live frame at control step {:?}: {e} (later failures are not logged)", live.control_step);
                }
                Err(_) => {}
            }
        }
    }

    #[cfg(test)]
    mod tests {
        use std::time::Duration;

        use super::*;

        #[test]
        fn a_state_with_images_is_shown_at_once_and_one_without_waits_for_the_pace_and_an_observation() {
            let t0 = Instant::now();
            let ms = Duration::from_millis;
            // An observation's images: no render to pace, nothing to wait for.
            assert_eq!(wait_before_showing(t0, true, Some(t0 + ms(40)), Some(t0)), Duration::ZERO);
            // A step inside a call: it waits for the call's observation.
            assert_eq!(wait_before_showing(t0, false, None, Some(t0)), LIVE_OBSERVATION_GRACE);
            assert_eq!(wait_before_showing(t0 + ms(100), false, None, Some(t0)), LIVE_OBSERVATION_GRACE - ms(100));
            // A long call: once the grace is over, the newest step is rendered (motion while it runs)...
            assert_eq!(wait_before_showing(t0 + LIVE_OBSERVATION_GRACE, false, None, Some(t0)), Duration::ZERO);
            // ... at the pace renders earn.
            let paced = t0 + LIVE_OBSERVATION_GRACE + ms(30);
            assert_eq!(wait_before_showing(t0 + LIVE_OBSERVATION_GRACE, false, Some(paced), Some(t0)), ms(30));
            // A state left from before anyone watched waited long ago: shown at once to a new viewer.
            assert_eq!(wait_before_showing(t0 + ms(5000), false, None, Some(t0)), Duration::ZERO);
        }

        /// `n` control steps' simulated times from `from_s` on, the last one carrying its images if `observed`.
        fn stretch(from_s: f64, n: usize, observed: bool) -> Vec<(f64, bool)> {
            (1..=n).map(|k| (from_s + k as f64 * CONTROL_PERIOD_S, observed && k == n)).collect()
        }

        #[test]
        fn a_long_call_is_played_back_at_the_control_rate_not_jumped_to_its_end() {
            let t0 = Instant::now();
            let queued = stretch(0.0, 50, true);
            let mut playback = Playback::default();
            // The first state is due one control period after playback starts.
            assert_eq!(playback.next(t0, &queued, None, Some(t0), Some(t0)), Next::Wait(Duration::from_millis(50)));
            // One second of wall time later, the state one second into the call (not the call's last).
            let Next::Show(i) = playback.next(t0 + Duration::from_secs(1), &queued, None, Some(t0), Some(t0)) else { panic!("a frame is due") };
            assert!((queued[i].0 - 1.0).abs() < 1e-9, "showed {}", queued[i].0);
            playback.shown(queued[i].0, false);
            let rest = &queued[i + 1..];
            // The render pace holds a state that has no images...
            let paced = t0 + Duration::from_millis(1100);
            assert_eq!(playback.next(t0 + Duration::from_millis(1060), rest, Some(paced), None, None), Next::Wait(Duration::from_millis(40)));
            // ... and the call's observation is shown when its time comes: at 2.5 s.
            assert_eq!(playback.next(t0 + Duration::from_millis(2400), rest, None, None, None), Next::Show(rest.len() - 3));
            assert_eq!(playback.next(t0 + Duration::from_millis(2500), rest, Some(paced + Duration::from_secs(9)), None, None), Next::Show(rest.len() - 1));
            playback.shown(2.5, true);
            assert_eq!(playback.anchor, None, "caught up: the next stretch starts its own clock");
        }

        #[test]
        fn playback_never_trails_the_simulation_by_more_than_the_lag_bound() {
            let t0 = Instant::now();
            let queued = stretch(0.0, 200, false);
            let mut playback = Playback::default();
            let Next::Show(i) = playback.next(t0, &queued, None, Some(t0), Some(t0)) else { panic!("10 s queued: a frame is due at once") };
            assert!((queued[i].0 - (10.0 - MAX_PLAYBACK_LAG_S)).abs() < 1e-9, "showed {}", queued[i].0);
        }

        #[test]
        fn a_short_teleop_call_shows_its_observation_at_once() {
            let t0 = Instant::now();
            let mut playback = Playback { shown_sim_s: Some(1.0), anchor: None };
            let queued = stretch(1.0, 2, true);
            assert_eq!(playback.next(t0, &queued, Some(t0 + Duration::from_millis(80)), Some(t0), Some(t0)), Next::Show(1));
            // Without its observation yet, it waits for it (the grace), as before.
            let queued = stretch(1.0, 2, false);
            assert_eq!(playback.next(t0, &queued, None, Some(t0), Some(t0)), Next::Wait(LIVE_OBSERVATION_GRACE));
        }

        #[test]
        fn states_arriving_in_real_time_are_shown_newest_first_however_many_queued() {
            // A teleop stream the renderer fell behind on: 1 s of motion published over 1 s. Playing it back would
            // keep the picture a second behind the operator's keys for good; the newest state is shown instead.
            let t0 = Instant::now();
            let mut playback = Playback { shown_sim_s: Some(1.0), anchor: None };
            let queued = stretch(1.0, 20, true);
            let published = Some(t0 + Duration::from_secs(1));
            assert_eq!(playback.next(t0 + Duration::from_secs(1), &queued, None, Some(t0), published), Next::Show(19));
            // The same second of motion run in 0.2 s (an agent's call) is played back.
            let mut playback = Playback { shown_sim_s: Some(1.0), anchor: None };
            let ran = Some(t0 + Duration::from_millis(200));
            assert!(matches!(playback.next(t0 + Duration::from_millis(200), &queued, None, Some(t0), ran), Next::Wait(_)));
        }

        #[test]
        fn live_renders_leave_a_running_simulation_at_least_half_a_core() {
            let t0 = Instant::now();
            // A cheap render waits for the rate cap.
            assert_eq!(next_render_at(t0, t0 + Duration::from_millis(10), true), t0 + LIVE_FRAME_MIN_INTERVAL);
            // A costly one (a CPU renderer) idles as long as it took while the simulation runs...
            let ended = t0 + Duration::from_millis(200);
            assert_eq!(next_render_at(t0, ended, true), ended + Duration::from_millis(200));
            // ... and not while it stands still (playing a finished call back): only the rate cap then.
            assert_eq!(next_render_at(t0, ended, false), t0 + LIVE_FRAME_MIN_INTERVAL);
        }
    }
}
