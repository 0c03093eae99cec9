//! The background video worker (issue 19): private videos are rendered from their state records after the
//! episode, one at a time, on a thread with a lower CPU priority than the episodes, so no observation render
//! and no agent reply ever waits for a video. Each video's progress is kept while it is queued, rendering or
//! failed; a finished video is simply its file. A stopped worker leaves the rest for the next server start,
//! which rebuilds them from their records.
use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use libero_render::{ModelHandle, Renderer};
use libero_sim::mujoco_rs::prelude::MjModel;
use serde::Serialize;

use crate::video::{VideoCameras, VideoError, render_video_from_record};

/// What a video is drawn with: the simulation model, the renderer and that renderer's upload of the model.
pub type VideoModels = (Arc<MjModel>, Renderer, ModelHandle);

/// Builds the models a job renders with (the episode's own when it just ended; rebuilt from the episode's record
/// after a restart). The upload travels with the renderer that made it: a handle is only valid on its device.
pub type ModelSource = Box<dyn FnOnce() -> Result<VideoModels, String> + Send>;

/// How much the worker thread's nice value is raised above the server's.
const WORKER_NICENESS: i32 = 10;
/// The longest a video frame waits for episodes' calls to end.
const MAX_YIELD: Duration = Duration::from_secs(2);
/// Failed videos remembered for the API (oldest forgotten first).
const MAX_REMEMBERED_FAILURES: usize = 1024;

pub struct VideoJob {
    pub record: PathBuf,
    pub video: PathBuf,
    /// The models to draw with; with [`Self::rebuild`] given, these are models held in memory (the ended
    /// episode's own compiled model and upload).
    pub source: ModelSource,
    /// Builds the models anew from the episode's settings: taken instead of [`Self::source`] (whose models are
    /// then dropped) when the job queues behind [`QUEUED_WITH_MODELS`] others that still hold theirs.
    pub rebuild: Option<ModelSource>,
}

/// Queued videos that may keep their episode's models in memory. A backlog (a loaded machine, a stream of short
/// episodes) held every ended episode's compiled model until its video was drawn, tens of MB each; beyond these
/// the later jobs rebuild their models when their turn comes, so a backlog costs seconds, not memory.
pub const QUEUED_WITH_MODELS: usize = 2;

/// Where one video stands.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum VideoProgress {
    Queued,
    Rendering { frames_done: u64, frames_total: u64 },
    Ready,
    Failed { error: String },
}

impl VideoProgress {
    /// Whole percent rendered (0 while queued, 100 when ready); `None` for a failure.
    pub fn percent(&self) -> Option<u64> {
        match self {
            VideoProgress::Queued => Some(0),
            VideoProgress::Rendering { frames_done, frames_total } => Some(frames_done * 100 / (*frames_total).max(1)),
            VideoProgress::Ready => Some(100),
            VideoProgress::Failed { .. } => None,
        }
    }

    pub fn is_settled(&self) -> bool {
        matches!(self, VideoProgress::Ready | VideoProgress::Failed { .. })
    }
}

/// A handle on the worker; clones share it.
#[derive(Clone)]
pub struct VideoQueue {
    shared: Arc<Shared>,
}

struct Shared {
    state: Mutex<QueueState>,
    changed: Condvar,
}

#[derive(Default)]
struct QueueState {
    jobs: VecDeque<VideoJob>,
    /// Queued, rendering and failed videos by path.
    progress: HashMap<PathBuf, VideoProgress>,
    failures: VecDeque<PathBuf>,
    busy: bool,
    stopping: bool,
    frames_rendered: u64,
    render_seconds: f64,
}

impl VideoQueue {
    /// Starts the worker thread, which renders `cameras` of each job with the job's renderer.
    pub fn start(cameras: VideoCameras) -> std::io::Result<Self> {
        let shared = Arc::new(Shared { state: Mutex::new(QueueState::default()), changed: Condvar::new() });
        let weak = Arc::downgrade(&shared);
        std::thread::Builder::new().name("videos".into()).spawn(move || {
            lower_this_threads_priority();
            worker(weak, cameras)
        })?;
        Ok(Self { shared })
    }

    fn lock(&self) -> MutexGuard<'_, QueueState> {
        self.shared.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Queues a video (a job for a video already queued or rendering is ignored).
    pub fn submit(&self, mut job: VideoJob) {
        let mut s = self.lock();
        if s.stopping || matches!(s.progress.get(&job.video), Some(VideoProgress::Queued | VideoProgress::Rendering { .. })) {
            return;
        }
        let holding = s.jobs.iter().filter(|j| j.rebuild.is_some()).count();
        if holding >= QUEUED_WITH_MODELS
            && let Some(rebuild) = job.rebuild.take()
        {
            // the held models go with the replaced source
            job.source = rebuild;
        }
        s.progress.insert(job.video.clone(), VideoProgress::Queued);
        s.jobs.push_back(job);
        self.shared.changed.notify_all();
    }

    /// Where `video` stands: its queue entry, or `Ready` when the file exists, or `None` when this worker
    /// never heard of it and it does not exist.
    pub fn progress(&self, video: &Path) -> Option<VideoProgress> {
        standing(&self.lock(), video)
    }

    /// Waits until `video` is ready or failed, at most `timeout`; returns where it stands then.
    pub fn wait(&self, video: &Path, timeout: Duration) -> Option<VideoProgress> {
        let s = self.wait_while(timeout, |s| standing(s, video).is_some_and(|p| !p.is_settled()));
        standing(&s, video)
    }

    /// Waits until nothing is queued or rendering, at most `timeout`; whether it got there.
    pub fn wait_idle(&self, timeout: Duration) -> bool {
        let s = self.wait_while(timeout, |s| !s.jobs.is_empty() || s.busy);
        s.jobs.is_empty() && !s.busy
    }

    /// The state once `busy` is false, the worker stops or `timeout` has passed.
    fn wait_while(&self, timeout: Duration, mut busy: impl FnMut(&QueueState) -> bool) -> MutexGuard<'_, QueueState> {
        let guard = self.lock();
        self.shared
            .changed
            .wait_timeout_while(guard, timeout, |s| !s.stopping && busy(s))
            .map(|r| r.0)
            .unwrap_or_else(|p| p.into_inner().0)
    }

    /// Videos queued or rendering.
    pub fn pending(&self) -> usize {
        let s = self.lock();
        s.jobs.len() + usize::from(s.busy)
    }

    /// Frames rendered per second of rendering so far (`None` before the first video).
    pub fn render_rate_fps(&self) -> Option<f64> {
        let s = self.lock();
        (s.render_seconds > 0.0).then(|| s.frames_rendered as f64 / s.render_seconds)
    }

    /// Stops after the frame being rendered; what is left stays for the next start (rebuilt from the records).
    pub fn stop(&self) {
        let mut s = self.lock();
        s.stopping = true;
        s.jobs.clear();
        self.shared.changed.notify_all();
    }
}

/// Where `video` stands in `s`, or `Ready` when its file exists.
fn standing(s: &QueueState, video: &Path) -> Option<VideoProgress> {
    match s.progress.get(video) {
        Some(p) => Some(p.clone()),
        None => video.is_file().then_some(VideoProgress::Ready),
    }
}

/// Waits while an episode handles a tool call (at most [`MAX_YIELD`] at a time, so a stream of calls slows
/// videos down without starving them). A lower nice value alone is not enough: a software renderer draws on its
/// own pool of threads, which the video shares with the episodes' observations.
fn yield_to_episodes(shared: &Shared) {
    let start = Instant::now();
    while crate::actor::calls_in_flight() > 0 && start.elapsed() < MAX_YIELD {
        if shared.state.lock().map(|s| s.stopping).unwrap_or(true) {
            return;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

fn lower_this_threads_priority() {
    let tid = rustix::thread::gettid();
    let now = rustix::process::getpriority_process(Some(tid)).unwrap_or(0);
    if let Err(e) = rustix::process::setpriority_process(Some(tid), now + WORKER_NICENESS) {
        log::warn!("video worker: cannot lower its priority: {e}");
    }
}

fn worker(weak: std::sync::Weak<Shared>, cameras: VideoCameras) {
    loop {
        let Some(shared) = weak.upgrade() else { return };
        let job = {
            let mut s = shared.state.lock().unwrap_or_else(|p| p.into_inner());
            if s.stopping {
                return;
            }
            match s.jobs.pop_front() {
                Some(job) => {
                    s.busy = true;
                    Some(job)
                }
                None => {
                    // Idle: wait a little, then let go of the queue so that dropping every handle ends the thread.
                    drop(shared.changed.wait_timeout(s, Duration::from_secs(1)));
                    None
                }
            }
        };
        let Some(job) = job else { continue };
        let started = Instant::now();
        let video = job.video.clone();
        let result = (job.source)().map_err(VideoError::Source).and_then(|(model, renderer, gpu_model)| {
            render_video_from_record(&job.record, &job.video, &model, &renderer, &gpu_model, &cameras, |done, total| {
                yield_to_episodes(&shared);
                let mut s = shared.state.lock().unwrap_or_else(|p| p.into_inner());
                s.progress.insert(video.clone(), VideoProgress::Rendering { frames_done: done, frames_total: total });
                shared.changed.notify_all();
                !s.stopping
            })
        });
        // The job's models went with it. An episode retired while its video waited here could not let go of the
        // base model its own read from, and a rebuilt model made a base of its own: release both now, or they
        // stay until some later episode ends (an idle server kept a scene's hundreds of MB).
        libero_sim::shared_model::release_unused();
        crate::memory::return_freed_memory();
        let mut s = shared.state.lock().unwrap_or_else(|p| p.into_inner());
        s.busy = false;
        match result {
            Ok(summary) => {
                s.progress.remove(&video);
                if let Some(v) = summary {
                    s.frames_rendered += v.frames;
                    s.render_seconds += started.elapsed().as_secs_f64();
                    log::info!("video {}: {} frames in {:.1} s", video.display(), v.frames, started.elapsed().as_secs_f64());
                }
            }
            Err(VideoError::Stopped) => {
                s.progress.remove(&video);
            }
            Err(e) => {
                log::error!("video {}: {e}", video.display());
                s.progress.insert(video.clone(), VideoProgress::Failed { error: e.to_string() });
                s.failures.push_back(video);
                if s.failures.len() > MAX_REMEMBERED_FAILURES
                    && let Some(old) = s.failures.pop_front()
                {
                    s.progress.remove(&old);
                }
            }
        }
        shared.changed.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use std::sync::mpsc;

    use super::*;

    /// A job whose held "models" are `token` (alive while the job's source is) and whose rebuild holds nothing.
    fn job(dir: &Path, n: usize, token: Arc<()>) -> VideoJob {
        VideoJob {
            record: dir.join(format!("record-{n}.bin")),
            video: dir.join(format!("video-{n}.mp4")),
            source: Box::new(move || {
                drop(token);
                Err("held models (test)".into())
            }),
            rebuild: Some(Box::new(|| Err("rebuilt models (test)".into()))),
        }
    }

    /// Behind a video being drawn, only [`QUEUED_WITH_MODELS`] queued videos keep their episode's models; the
    /// later ones let go of them at once and rebuild when their turn comes, so a backlog of ended episodes does not
    /// hold every one's compiled model in memory. A queue that kept every job's models leaves all tokens alive.
    #[test]
    fn a_video_backlog_holds_the_models_of_only_the_first_queued_videos() {
        let dir = tempfile::tempdir().unwrap();
        let queue = VideoQueue::start(VideoCameras { head: "agentview".into(), wrist: "robot0_eye_in_hand".into(), size_px: 8 }).unwrap();
        // The first job blocks the worker until released, so the others queue behind it.
        let (release, blocked) = mpsc::channel::<()>();
        queue.submit(VideoJob {
            record: dir.path().join("record-0.bin"),
            video: dir.path().join("video-0.mp4"),
            source: Box::new(move || {
                let _ = blocked.recv();
                Err("first (test)".into())
            }),
            rebuild: None,
        });
        while !queue.lock().busy {
            std::thread::sleep(Duration::from_millis(5));
        }
        let tokens: Vec<Arc<()>> = (0..6).map(|_| Arc::new(())).collect();
        for (n, token) in tokens.iter().enumerate() {
            queue.submit(job(dir.path(), n + 1, token.clone()));
        }
        let held: Vec<bool> = tokens.iter().map(|t| Arc::strong_count(t) > 1).collect();
        assert_eq!(held, [true, true, false, false, false, false], "which queued videos still hold their models");
        // Each job still runs (with the models it holds or rebuilds), and every one is accounted for.
        release.send(()).unwrap();
        assert!(queue.wait_idle(Duration::from_secs(30)), "the queue drains");
        for n in 1..=6 {
            let video = dir.path().join(format!("video-{n}.mp4"));
            let expected = if n <= QUEUED_WITH_MODELS { "held models (test)" } else { "rebuilt models (test)" };
            match queue.progress(&video) {
                Some(VideoProgress::Failed { error }) => assert!(error.contains(expected), "video {n}: {error}"),
                other => panic!("video {n}: {other:?}"),
            }
        }
        assert!(tokens.iter().all(|t| Arc::strong_count(t) == 1), "no job keeps models after it ran");
    }
}
