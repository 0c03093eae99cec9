//! The private videos' side of the lifecycle: the one background worker that renders them from state records,
//! where each stands, waiting for them, and rebuilding those a stopped server left unfinished.
use std::fs;
use std::time::{Duration, Instant};

use anyhow::Context;

use super::EpisodeSet;
use super::prepare::spec_from_record;
use crate::RunDir;
use crate::video_queue::{VideoJob, VideoProgress, VideoQueue};
use crate::world::{LiberoWorld, head_wrist_cameras};

impl EpisodeSet {
    /// The video worker, started at first use.
    pub(super) fn video_queue(&self) -> anyhow::Result<VideoQueue> {
        let mut slot = self.videos.lock().map_err(|_| anyhow::anyhow!("video queue lock poisoned"))?;
        if let Some(q) = slot.as_ref() {
            return Ok(q.clone());
        }
        let q = VideoQueue::start(head_wrist_cameras()).context("cannot start the video worker")?;
        *slot = Some(q.clone());
        Ok(q)
    }

    fn started_video_queue(&self) -> Option<VideoQueue> {
        self.videos.lock().ok().and_then(|q| q.clone())
    }

    /// Where the private video of `run` stands: `None` when the episode records none.
    pub fn video_progress(&self, run: &RunDir) -> Option<VideoProgress> {
        let video = run.continuous_video();
        if let Some(p) = self.started_video_queue().and_then(|q| q.progress(&video)) {
            return Some(p);
        }
        if video.is_file() {
            Some(VideoProgress::Ready)
        } else if recorded_frames(run) > 0 {
            // Recorded, not yet handed to the worker (the episode is running, or the server restarted).
            Some(VideoProgress::Queued)
        } else {
            None
        }
    }

    /// Waits until every queued video is rendered, at most `timeout`; `progress` hears about each waiting second.
    /// Whether they all were.
    pub fn wait_for_videos(&self, timeout: Duration, mut progress: impl FnMut(usize, Option<f64>)) -> bool {
        let Some(q) = self.started_video_queue() else { return true };
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if q.wait_idle(left.min(Duration::from_secs(1))) {
                return true;
            }
            if left.is_zero() {
                return false;
            }
            progress(q.pending(), q.render_rate_fps());
        }
    }

    /// Waits until the private video of `run` is ready or failed, at most `timeout`; where it stands then.
    pub fn wait_for_video(&self, run: &RunDir, timeout: Duration) -> Option<VideoProgress> {
        match self.started_video_queue() {
            Some(q) => q.wait(&run.continuous_video(), timeout),
            None => self.video_progress(run),
        }
    }

    /// Stops the video worker after its current frame; unfinished videos are rebuilt at the next start.
    pub fn stop_videos(&self) {
        if let Some(q) = self.started_video_queue() {
            q.stop();
        }
    }

    /// After a restart: queues every private video that has a state record but no file (the server stopped
    /// before the worker finished it). Each job rebuilds the episode's model from its record when its turn
    /// comes. Returns how many.
    pub fn rebuild_missing_videos(&self) -> usize {
        let Ok(dirs) = fs::read_dir(self.runs_dir()) else { return 0 };
        let held: std::collections::HashSet<String> = self.ids().into_iter().collect();
        let mut n = 0;
        for d in dirs.flatten() {
            let run = RunDir::new(d.path());
            let id = d.file_name().to_string_lossy().into_owned();
            if held.contains(&id) || recorded_frames(&run) == 0 || run.continuous_video().is_file() {
                continue;
            }
            let (Some(paths), Ok(queue)) = (self.paths.clone(), self.video_queue()) else { return n };
            let Ok(renderer) = self.renderer() else { return n };
            let record = run.episode_record();
            let source = Box::new(move || -> Result<_, String> {
                let spec = spec_from_record(&record, paths).map_err(|e| format!("{e:#}"))?;
                let world = LiberoWorld::new(&spec, renderer).map_err(|e| e.to_string())?;
                Ok(world.video_models())
            });
            queue.submit(VideoJob { record: run.state_record(), video: run.continuous_video(), source, rebuild: None });
            n += 1;
        }
        n
    }

}

/// Control steps in the state record of `run` (0 without one: an episode never started records no frame).
fn recorded_frames(run: &RunDir) -> u64 {
    crate::state_record::StateRecordReader::open(&run.state_record()).map(|r| r.frames()).unwrap_or(0)
}
