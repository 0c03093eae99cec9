//! The operator's log lines of one episode (prepared, started, ended), each written once by whoever sees the
//! transition first.
use std::path::Path;
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::Instant;

use super::request::PrepareRequest;
use crate::{EpisodeState, EpisodeStatus};

/// The operator's log of one episode: a line when it is prepared, when `start_episode` succeeds and when it ends,
/// each with the episode's id, task, level and labels (never its token). Whoever sees a transition first (the
/// server's store writer after a tool call or on its tick, an abort, the shutdown) writes its line; each is written
/// once.
pub(super) struct EpisodeLog {
    task: String,
    level: u8,
    harness: Option<String>,
    model: Option<String>,
    batch: Option<String>,
    prepared_at: Instant,
    /// [`Self::PREPARED`], [`Self::STARTED`] or [`Self::ENDED`]: the last line written.
    phase: AtomicU8,
}

impl EpisodeLog {
    const PREPARED: u8 = 0;
    const STARTED: u8 = 1;
    const ENDED: u8 = 2;

    pub(super) fn prepared(id: &str, req: &PrepareRequest, task: &str, workspace: &Path) -> Self {
        let log = Self {
            task: task.to_owned(),
            level: req.level,
            harness: req.harness.clone(),
            model: req.model.clone(),
            batch: req.batch.clone(),
            prepared_at: Instant::now(),
            phase: AtomicU8::new(Self::PREPARED),
        };
        tracing::info!(
            episode_id = id,
            task = log.task,
            level = log.level,
            harness = log.harness.as_deref(),
            model = log.model.as_deref(),
            batch = log.batch.as_deref(),
            seed = req.seed,
            video = req.video,
            demo = req.demo.as_str(),
            workspace = %workspace.display(),
            "episode prepared"
        );
        log
    }

    /// Writes the lines of the transitions `status` shows that were not written yet.
    pub(super) fn follow(&self, id: &str, status: &EpisodeStatus) {
        // The initial observation exists exactly when start_episode succeeded.
        if status.latest_observation_id.is_some()
            && self.phase.compare_exchange(Self::PREPARED, Self::STARTED, Ordering::AcqRel, Ordering::Acquire).is_ok()
        {
            tracing::info!(
                episode_id = id,
                task = self.task,
                level = self.level,
                harness = self.harness.as_deref(),
                model = self.model.as_deref(),
                batch = self.batch.as_deref(),
                "episode started"
            );
        }
        let state = match status.state {
            EpisodeState::Finished => "finished",
            EpisodeState::Aborted => "aborted",
            EpisodeState::Prepared | EpisodeState::Active => return,
        };
        if self.phase.swap(Self::ENDED, Ordering::AcqRel) == Self::ENDED {
            return;
        }
        tracing::info!(
            episode_id = id,
            task = self.task,
            level = self.level,
            harness = self.harness.as_deref(),
            model = self.model.as_deref(),
            batch = self.batch.as_deref(),
            state,
            outcome = status.outcome.map(|o| o.as_str()),
            steps = status.accepted_agent_steps,
            reason = status.reason.as_deref(),
            since_prepared_s = (self.prepared_at.elapsed().as_secs_f64() * 10.0).round() / 10.0,
            "episode ended"
        );
    }
}
