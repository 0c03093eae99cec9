//! The operator's live view of an episode: events the actor and the world emit while the episode runs (calls,
//! control steps, private stage events, frames, the end), handed to a [`LiveSink`] the server installs. The
//! sink must return at once (the server fans out through a broadcast channel); the episode thread never waits
//! for a viewer. Nothing here reaches the agent's workspace: private evaluator progress is for operators only.
//!
//! With the `world` feature: [`WorldTap`] (per control step: `telemetry.jsonl` in the run directory, step and
//! stage events) and [`FrameTap`] (the video recorder's head | wrist frames, throttled to
//! [`LIVE_FRAME_MIN_INTERVAL`] and JPEG-encoded once per emitted frame).
use std::sync::Arc;

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
    /// Index of this frame in `continuous_video.mp4`.
    pub video_frame: u64,
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

/// `telemetry.jsonl` beside the other private records: one line per control step.
pub const TELEMETRY_FILE: &str = "telemetry.jsonl";

#[cfg(feature = "world")]
pub use world_taps::{FrameTap, LIVE_FRAME_MIN_INTERVAL, TelemetryRow, WorldTap, encode_jpeg};

#[cfg(feature = "world")]
mod world_taps {
    use std::fs::File;
    use std::io::{BufWriter, Write};
    use std::path::Path;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::time::{Duration, Instant};

    use libero_tasks::evaluator::PrivateEvent;
    use serde::Serialize;

    use super::{LiveEvent, LiveFrame, LiveSink};
    use crate::observation::RobotReadout;

    /// At most 20 frames a second reach viewers; the video keeps every control step.
    pub const LIVE_FRAME_MIN_INTERVAL: Duration = Duration::from_millis(50);
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
        events_sent: usize,
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
                events_sent: 0,
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

        /// The frame tap for the video recorder, sharing this tap's control-step origin.
        pub fn frame_tap(&self) -> FrameTap {
            FrameTap { sink: self.sink.clone(), origin: self.origin.clone(), last_sent: None, pending: None }
        }

        fn video_frame(&self, control_step: u64) -> Option<u64> {
            let origin = self.origin.load(Ordering::Acquire);
            (origin != NOT_STARTED && self.video_frames.load(Ordering::Acquire) > 0)
                .then(|| (origin + control_step).saturating_sub(1))
        }

        /// At the evaluator reset (after settling): control step 0.
        pub fn on_reset(&mut self, robot: &RobotReadout, events: &[PrivateEvent], progress: Option<(usize, usize)>) {
            self.origin.store(self.video_frames.load(Ordering::Acquire), Ordering::Release);
            self.events_sent = 0;
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
            for e in events.iter().skip(self.events_sent) {
                if let Ok(event) = serde_json::to_value(e) {
                    (self.sink)(LiveEvent::Stage { event });
                }
            }
            self.events_sent = events.len();
            if progress != self.progress_sent {
                if let Some((completed, required)) = progress {
                    (self.sink)(LiveEvent::Progress { completed, required });
                }
                self.progress_sent = progress;
            }
        }
    }

    /// A frame waiting for its turn under the rate limit.
    struct Pending {
        rgb: Vec<u8>,
        width_px: u32,
        height_px: u32,
        video_frame: u64,
        sim_time_s: f64,
    }

    /// The video recorder's side: keeps the newest rendered frame and sends it at most every
    /// [`LIVE_FRAME_MIN_INTERVAL`]; only frames actually sent are JPEG-encoded.
    pub struct FrameTap {
        sink: LiveSink,
        origin: Arc<AtomicU64>,
        last_sent: Option<Instant>,
        pending: Option<Pending>,
    }

    impl FrameTap {
        /// Offers the frame just rendered (`rgb` is `width × height × 3`, rows top to bottom).
        pub fn offer(&mut self, rgb: &[u8], width_px: u32, height_px: u32, video_frame: u64, sim_time_s: f64) {
            let mut buf = self.pending.take().map(|p| p.rgb).unwrap_or_default();
            buf.clear();
            buf.extend_from_slice(rgb);
            self.pending = Some(Pending { rgb: buf, width_px, height_px, video_frame, sim_time_s });
            if self.due().is_none() {
                self.flush();
            }
        }

        /// How long until the pending frame may be sent (`None`: now, or nothing pending).
        pub fn due(&self) -> Option<Duration> {
            self.pending.as_ref()?;
            let wait = LIVE_FRAME_MIN_INTERVAL.saturating_sub(self.last_sent?.elapsed());
            (!wait.is_zero()).then_some(wait)
        }

        pub fn has_pending(&self) -> bool {
            self.pending.is_some()
        }

        /// Sends the pending frame now.
        pub fn flush(&mut self) {
            let Some(p) = self.pending.take() else { return };
            self.last_sent = Some(Instant::now());
            let origin = self.origin.load(Ordering::Acquire);
            // Frame f shows the state after video step f + 1; control step c was frame origin + c - 1.
            let control_step = (origin != NOT_STARTED && p.video_frame + 1 >= origin).then(|| p.video_frame + 1 - origin);
            match encode_jpeg(&p.rgb, p.width_px, p.height_px) {
                Ok(jpeg) => (self.sink)(LiveEvent::Frame(LiveFrame {
                    control_step,
                    sim_time_s: p.sim_time_s,
                    video_frame: p.video_frame,
                    width_px: p.width_px,
                    height_px: p.height_px,
                    jpeg: jpeg.into(),
                })),
                Err(e) => log::warn!("live frame {}: {e}", p.video_frame),
            }
            self.pending = None;
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

        use super::*;

        fn collecting() -> (LiveSink, Arc<Mutex<Vec<LiveEvent>>>) {
            let seen = Arc::new(Mutex::new(Vec::new()));
            let s = seen.clone();
            (Arc::new(move |e| s.lock().unwrap().push(e)), seen)
        }

        #[test]
        fn frames_are_rate_limited_keep_the_newest_and_carry_control_steps_after_the_reset() {
            let (sink, seen) = collecting();
            let tap = WorldTap::new(sink, None).unwrap();
            let mut frames = tap.frame_tap();
            let rgb = vec![128u8; 16 * 8 * 3];
            frames.offer(&rgb, 16, 8, 0, 0.05); // a settle step, sent at once
            tap.origin.store(10, Ordering::Release); // the reset after 10 settle frames
            frames.offer(&rgb, 16, 8, 10, 0.55);
            frames.offer(&rgb, 16, 8, 11, 0.60); // replaces frame 10 while rate-limited
            assert!(frames.due().is_some_and(|d| d <= LIVE_FRAME_MIN_INTERVAL));
            frames.flush();
            let got: Vec<(Option<u64>, u64)> = seen
                .lock()
                .unwrap()
                .iter()
                .filter_map(|e| match e {
                    LiveEvent::Frame(f) => Some((f.control_step, f.video_frame)),
                    _ => None,
                })
                .collect();
            assert_eq!(got, [(None, 0), (Some(2), 11)]);
            let jpeg = match &seen.lock().unwrap()[0] {
                LiveEvent::Frame(f) => f.jpeg.clone(),
                _ => unreachable!(),
            };
            assert_eq!(&jpeg[..2], [0xFF, 0xD8], "a JPEG");
        }
    }
}
