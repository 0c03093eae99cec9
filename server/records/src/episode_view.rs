//! The operator API's episode, typed for every side of the wire: the server builds it (`GET /api/episodes`,
//! `GET /api/episodes/{id}`, the console's episode list), the API client, the batch runner and the console read
//! it. Also the list reply, the video reply of `GET /api/episodes/{id}/video` and the result reply of
//! `GET /api/episodes/{id}/result`, which carries `result.json` to a runner on another machine than the server's
//! run directory.
//!
//! The wire format is the one these replies had as untyped JSON maps: the keys in alphabetical order (a
//! `serde_json::Value` map sorts them, so the fields are declared sorted) and the same nulls. The live fields
//! (`state`, `latest_observation_id`) are absent, not null, for an episode the answering process does not run.
use serde::{Deserialize, Deserializer, Serialize};

use crate::records::Outcome;
use crate::result::{PrivateEvaluation, RunResult, STATUS_ABORTED, STATUS_FINISHED};

/// Lifecycle state of an episode the answering server runs (never shown to the agent beyond its tool results).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EpisodeState {
    Prepared,
    Active,
    Finished,
    Aborted,
}

impl EpisodeState {
    /// Finished or aborted: `result.json` is written before an episode enters either state.
    pub fn has_ended(self) -> bool {
        matches!(self, EpisodeState::Finished | EpisodeState::Aborted)
    }
}

/// One episode as the operator API shows it: its store row without the private run directory, plus the live
/// state while the answering process runs it. Fields in alphabetical order (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeView {
    /// Agent steps the episode accepted (`osc_sequence` calls within budget): the live count while the answering
    /// process runs the episode, else the stored one; null before the store has any.
    pub accepted_agent_steps: Option<u64>,
    /// The batch the episode belongs to, where its preparer said.
    pub batch: Option<String>,
    /// A branch's parent episode (issue 33); null for an ordinary episode.
    pub branch_parent: Option<String>,
    /// The parent's control step the branch starts from; null for an ordinary episode.
    pub branch_step: Option<i64>,
    /// Required stages the evaluator saw completed; null until it reported any.
    pub completed_stage_count: Option<u64>,
    /// When the episode was prepared (UTC, ISO 8601).
    pub created_at: String,
    /// When the episode ended (UTC, ISO 8601); null while it is open.
    pub finished_at: Option<String>,
    /// Agent harness driving the episode (`expert`, `teleop`, `command`, `codex`, …), where its preparer said.
    pub harness: Option<String>,
    /// Episode id (`ep-…`).
    pub id: String,
    /// Index of the task's initial state the episode starts from.
    pub init_index: i64,
    /// Live only: the id of the latest observation the agent was given (`Some(None)`: none yet); absent from the
    /// wire (`None`) for an episode the answering process does not run.
    #[serde(default, skip_serializing_if = "Option::is_none", deserialize_with = "present")]
    pub latest_observation_id: Option<Option<String>>,
    /// Difficulty level (1–3: what the agent observes).
    pub level: i64,
    /// The agent's model, where its preparer said.
    pub model: Option<String>,
    /// The episode's outcome class (§4.8: SUCCESS, FAIL, SIM_TIMEOUT or INVALID); null while it is open.
    pub outcome: Option<Outcome>,
    /// Why it ended: an aborted episode's reason, else a finished one's termination reason (wall time or step
    /// budget spent, forfeit); null for an episode ended by `finish_episode` or still open.
    pub reason: Option<String>,
    /// Required stages of the task (the evaluator's count); null until it reported it.
    pub required_stage_count: Option<u64>,
    /// Simulation seed.
    pub seed: i64,
    /// The URL of the server running the episode, where its live view is (only a server with a console has one).
    pub server_url: Option<String>,
    /// When the agent started the episode (UTC, ISO 8601); null while it is only prepared.
    pub started_at: Option<String>,
    /// Live only: the lifecycle state; absent from the wire (`None`) for an episode the answering process does
    /// not run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state: Option<EpisodeState>,
    /// The evaluator's verdict (outcome SUCCESS); null while the episode is open.
    pub success: Option<bool>,
    /// Task id (`T14`) or the path of a custom BDDL.
    pub task_ref: String,
    /// Episode wall time from `start_episode` to its end, in seconds; null while it is open.
    pub wall_time_s: Option<f64>,
}

/// A key that is there deserializes to `Some` (its value possibly null): `Option<Option<T>>`'s outer `None` is
/// the key's absence (with `#[serde(default)]`).
fn present<'de, D: Deserializer<'de>, T: Deserialize<'de>>(d: D) -> Result<Option<Option<T>>, D::Error> {
    Option::<T>::deserialize(d).map(Some)
}

impl EpisodeView {
    /// Whether the episode has ended, as the view tells: its live state, or (an episode the answering process
    /// does not run) an outcome in its row.
    pub fn has_ended(&self) -> bool {
        self.state.is_some_and(EpisodeState::has_ended) || self.outcome.is_some()
    }

    /// The episode's `result.json` as far as the row tells it, for a reader without the result itself (see
    /// [`EpisodeResultReply`]): status, verdict, reason, steps, wall time and completed stages, enough for §4.8's
    /// classification to give the row's outcome again. `None` while the episode is open.
    pub fn result_summary(&self) -> Option<RunResult> {
        let outcome = self.outcome?;
        let aborted = outcome == Outcome::Invalid;
        Some(RunResult {
            status: Some(if aborted { STATUS_ABORTED } else { STATUS_FINISHED }.to_owned()),
            success: self.success,
            // The row's reason is an aborted result's `reason`, else a finished one's `termination_reason`.
            reason: self.reason.clone().filter(|_| aborted),
            termination_reason: self.reason.clone().filter(|_| !aborted),
            wall_time_seconds: self.wall_time_s.map(Some),
            accepted_agent_steps: self.accepted_agent_steps,
            private_evaluation: Some(PrivateEvaluation {
                completed_required_stage_count: self.completed_stage_count,
                required_stage_count: self.required_stage_count,
                ..PrivateEvaluation::default()
            }),
            ..RunResult::default()
        })
    }
}

/// `GET /api/episodes`: the stored episodes, newest first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeList {
    pub episodes: Vec<EpisodeView>,
    /// Always true (a failure answers the API's error shape instead).
    pub ok: bool,
}

impl EpisodeList {
    pub fn new(episodes: Vec<EpisodeView>) -> Self {
        Self { episodes, ok: true }
    }
}

/// Where an episode's private video stands (the video queue's view of it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VideoState {
    Queued,
    Rendering,
    Ready,
    Failed,
}

/// The rendering of an episode's private video. Fields in alphabetical order (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VideoStatus {
    /// Why the rendering failed (state `failed` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Frames rendered so far (state `rendering` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames_done: Option<u64>,
    /// Frames the video will have (state `rendering` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames_total: Option<u64>,
    /// Whole percent rendered (0 while queued, 100 when ready); null for a failure.
    pub percent: Option<u64>,
    pub state: VideoState,
}

/// `GET /api/episodes/{id}/video` (and the review page's video part): whether the private video is written, and
/// where its rendering stands.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeVideo {
    /// The video file is complete.
    pub video: bool,
    /// Null for an episode without a video (none was asked for, or it was never queued on this server).
    pub video_status: Option<VideoStatus>,
}

impl EpisodeVideo {
    /// The rendering failed, or there is none to wait for: waiting longer would not bring a video.
    pub fn will_not_come(&self) -> bool {
        !self.video && self.video_status.as_ref().is_none_or(|s| s.state == VideoState::Failed)
    }
}

/// `GET /api/episodes/{id}/result`: the episode's `result.json` as its server's run directory holds it (the
/// operator's, private evaluation included), for a runner that does not see that directory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeResultReply {
    pub ok: bool,
    /// Null while the episode is open (or its run directory is not on the answering server).
    pub result: Option<RunResult>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::records::classify;

    fn ended(outcome: Outcome, reason: Option<&str>) -> EpisodeView {
        EpisodeView {
            accepted_agent_steps: Some(7),
            batch: None,
            branch_parent: None,
            branch_step: None,
            completed_stage_count: Some(1),
            created_at: "2026-12-07T14:08:28+00:00".into(),
            finished_at: Some("2026-12-07T14:10:00+00:00".into()),
            harness: None,
            id: "ep-1".into(),
            init_index: 0,
            latest_observation_id: None,
            level: 3,
            model: None,
            outcome: Some(outcome),
            reason: reason.map(str::to_owned),
            required_stage_count: Some(2),
            seed: 1,
            server_url: None,
            started_at: None,
            state: None,
            success: Some(outcome == Outcome::Success),
            task_ref: "T14".into(),
            wall_time_s: Some(1800.2),
        }
    }

    #[test]
    fn a_row_s_result_summary_classifies_as_the_row_s_outcome() {
        let cases = [
            (Outcome::Success, None),
            (Outcome::Fail, None),
            (Outcome::SimTimeout, Some(crate::result::WALL_TIME_EXHAUSTED)),
            (Outcome::SimTimeout, Some(crate::result::STEP_BUDGET_EXHAUSTED)),
            (Outcome::Invalid, Some("harness exited")),
        ];
        for (outcome, reason) in cases {
            let summary = ended(outcome, reason).result_summary().unwrap();
            assert_eq!(classify(Some(&summary)), outcome, "{summary:?}");
            assert_eq!(summary.wall_time_s(), Some(1800.2));
        }
    }

    #[test]
    fn an_open_episode_has_no_result_summary_and_has_not_ended() {
        let mut open = ended(Outcome::Fail, None);
        open.outcome = None;
        assert_eq!(open.result_summary(), None);
        assert!(!open.has_ended());
        open.state = Some(EpisodeState::Aborted);
        assert!(open.has_ended(), "the live state tells before the row does");
    }

    #[test]
    fn a_failed_or_missing_video_will_not_come() {
        let status = |state| Some(VideoStatus { error: None, frames_done: None, frames_total: None, percent: Some(0), state });
        assert!(EpisodeVideo { video: false, video_status: None }.will_not_come());
        assert!(EpisodeVideo { video: false, video_status: status(VideoState::Failed) }.will_not_come());
        assert!(!EpisodeVideo { video: false, video_status: status(VideoState::Rendering) }.will_not_come());
        assert!(!EpisodeVideo { video: true, video_status: status(VideoState::Ready) }.will_not_come());
    }
}
