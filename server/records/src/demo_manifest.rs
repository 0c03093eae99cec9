//! A demonstration bundle's `manifest.json` (protocol §7, the demo library), typed for the code that writes it (the
//! recorder, re-verification) and the code that uses bundles: the library, the projection into a workspace,
//! replays and the console's list. Validating a bundle reads the manifest as plain JSON instead: a bundle handed
//! in may be malformed, and the validator reports each missing or ill-typed field. See [`crate::typed`] for how
//! the fields not named here survive a read. The bundle's `trajectory.jsonl` rows are typed here too
//! ([`DemoTrajectoryRow`]).
use serde::Deserialize;
use serde_json::Value;

use crate::typed::record;

record! {
    /// A bundle's manifest.
    pub struct DemoManifest {
        pub schema_version: Option<String>,
        pub task: Option<DemoTask>,
        /// The episode the bundle was recorded from.
        pub source: Option<DemoSource>,
        pub verification: Option<DemoVerification>,
        /// Frames of the bundle (its actions + 1).
        pub frame_count: Option<u64>,
        pub transition_count: Option<u64>,
        /// Outcomes of replaying the bundle in other episodes' configurations (outside the integrity block).
        pub replay_checks: Option<Vec<ReplayCheck>>,
        pub overview: Option<DemoOverview>,
        /// §7.3's canonical action semantics object (the validator compares it whole with the canonical one).
        pub action_semantics: Option<Value>,
        /// `trajectory.jsonl`, as an artifact.
        pub trajectory: Option<DemoFile>,
        pub video: Option<DemoVideo>,
        /// Every file of the bundle but the manifest, sorted by path (§7.2).
        pub integrity: Option<DemoIntegrity>,
    }
}

record! {
    /// A file of the bundle (§7.2): an integrity record, or with its media type an artifact record.
    pub struct DemoFile {
        /// Bundle-relative POSIX path.
        pub path: Option<String>,
        /// `video/mp4`, `image/png`, `application/x-ndjson`; absent in the integrity block.
        pub media_type: Option<String>,
        pub size_bytes: Option<u64>,
        /// Lower-case hex SHA-256 of the file's bytes.
        pub sha256: Option<String>,
    }
}

record! {
    /// The integrity block.
    pub struct DemoIntegrity {
        /// `sha256`.
        pub algorithm: Option<String>,
        /// Every file except `manifest.json`, sorted by path.
        pub files: Option<Vec<DemoFile>>,
    }
}

record! {
    /// The bundle's videos: head | wrist side by side, and each camera alone.
    pub struct DemoVideo {
        /// Frames per second: one frame per 20 Hz control step.
        pub fps_hz: Option<f64>,
        /// Frames of each video (the bundle's actions + 1).
        pub frame_count: Option<u64>,
        /// `head_rgb_left__wrist_rgb_right`: how `file` places the cameras.
        pub layout: Option<String>,
        pub file: Option<DemoFile>,
        pub head_rgb: Option<DemoFile>,
        pub wrist_rgb: Option<DemoFile>,
    }
}

record! {
    /// One contact sheet per camera (§7.4).
    pub struct ContactSheets {
        pub head_rgb: Option<DemoFile>,
        pub wrist_rgb: Option<DemoFile>,
    }
}

record! {
    /// The demonstrated task.
    pub struct DemoTask {
        /// The task reference (`T14`, `suite/name`).
        pub id: Option<String>,
        /// The instruction, whitespace-normalised.
        pub instruction: Option<String>,
    }
}

record! {
    /// The source episode's identity.
    pub struct DemoSource {
        pub episode_id: Option<String>,
        pub level: Option<u64>,
        pub seed: Option<u64>,
        pub init_state_index: Option<u64>,
        /// The evaluator's verdict on the source episode; null when it never finished.
        pub episode_success: Option<bool>,
        /// The layout variant it ran (null: the task's own configuration).
        pub layout: Option<Value>,
        /// `scripted_expert`, `human_teleop`, `agent`.
        pub source_type: Option<String>,
        pub source_desc: Option<String>,
        /// Where the source episode branched from another one (absent: it started at the task's start).
        pub branch: Option<DemoBranch>,
        /// The configuration the source episode started from (placement seed, init index, margins), what a target
        /// episode must differ from; null where it is not known.
        pub effective_layout: Option<Value>,
        /// Physics steps run before the first frame.
        pub settle_steps: Option<u64>,
    }
}

record! {
    /// A demonstration recorded from a branch (issue 49): its trajectory and videos hold only the branch's own
    /// actions, from the branch point on; the parent's actions that led there are in `prefix_file`, replayed first.
    pub struct DemoBranch {
        pub parent_episode_id: Option<String>,
        pub parent_control_step: Option<u64>,
        /// Lines of `prefix_file`: the actions replayed before the trajectory's first row.
        pub replayed_actions: Option<u64>,
        /// The bundle-relative file of the replayed actions (`branch_prefix.jsonl`, one 7-number array a line).
        pub prefix_file: Option<String>,
    }
}

record! {
    /// Whether replaying the bundle reproduced the source's success.
    pub struct DemoVerification {
        pub verified: Option<bool>,
        /// The replay's verdict; written null when the bundle was never replayed (see [`Self::set_replay_success`]).
        pub replay_success: Option<bool>,
        /// `replay_on_world_physics`.
        pub method: Option<String>,
    }
}

record! {
    /// One replay of the bundle in another configuration.
    pub struct ReplayCheck {
        /// The target: its task and effective layout.
        pub target: Option<Value>,
        /// Whether any replay (direct or offset) solved the target.
        pub replay_solves: Option<bool>,
        /// The rule the check was made under (`direct_and_offset_replay_v2`).
        pub method: Option<String>,
        /// Whether the bundle may be shown in the target: every replay (direct and offset) within the rule …
        pub accepted: Option<bool>,
        /// … or the direct replay alone (what is asked where no source passes the offset replays).
        pub direct_accepted: Option<bool>,
        /// Stages the direct replay earned, of `required_stage_count`.
        pub completed_required_stage_count: Option<u64>,
        pub required_stage_count: Option<u64>,
        /// The most stages any replay (direct or offset) earned.
        pub best_completed_stage_count: Option<u64>,
        /// Stages the target's idle start earns, and the most a replay may earn.
        pub idle_completed_stage_count: Option<u64>,
        pub allowed_stage_count: Option<u64>,
        /// The replays after moving the end effector by an object's start displacement.
        pub offset_replays: Option<Vec<OffsetReplayCheck>>,
        /// When the check was made (ISO-8601 UTC).
        pub checked_at: Option<String>,
    }
}

record! {
    /// One offset replay of a [`ReplayCheck`].
    pub struct OffsetReplayCheck {
        /// The object whose start displacement the end effector was moved by.
        pub instance: Option<String>,
        /// The displacement, metres (x, y, z).
        pub offset_m: Option<Vec<f64>>,
        /// Whether the replay solved the target.
        pub success: Option<bool>,
        /// Stages it earned.
        pub completed_required_stage_count: Option<u64>,
    }
}

record! {
    /// The bundle's overview (contact sheets and how their frames were sampled).
    pub struct DemoOverview {
        pub sampling: Option<FrameSampling>,
        pub contact_sheets: Option<ContactSheets>,
    }
}

record! {
    /// §7.6's frame sampling of the contact sheets.
    pub struct FrameSampling {
        /// `uniform_endpoint_preserving_v1`.
        pub rule: Option<String>,
        /// Tiles per sheet at most.
        pub maximum_frames_per_sheet: Option<u64>,
        /// Frames sampled from (the bundle's frame count).
        pub source_frame_count: Option<u64>,
        pub sampled_frame_indices: Option<Vec<u64>>,
    }
}

record! {
    /// One line of a library bundle's `trajectory.jsonl`: an action and the measured robot state around it.
    pub struct DemoTrajectoryRow {
        /// 0-based, in execution order (after a branch's replayed prefix).
        pub action_index: Option<u64>,
        /// The `event_index` of the `osc_sequence` call in the source episode's `actions.jsonl`.
        pub call_index: Option<u64>,
        pub action: Option<DemoAction>,
        /// Video frame before the action (= `action_index`) and after it (+ 1).
        pub frame_before: Option<u64>,
        pub frame_after: Option<u64>,
        pub state_before: Option<DemoMeasuredState>,
        pub state_after: Option<DemoMeasuredState>,
    }
}

record! {
    /// One action (§7.3).
    pub struct DemoAction {
        /// `libero.normalized_osc_pose_action.v1`.
        pub schema_version: Option<String>,
        /// The 7 normalized OSC_POSE components, each within [-1, 1].
        pub normalized_vector_7d: Option<Vec<f64>>,
    }
}

record! {
    /// The measured robot state (observations, not actions).
    pub struct DemoMeasuredState {
        /// `[x, y, z, qx, qy, qz, qw]` of the end effector in the robot base frame, metres, `qw ≥ 0`.
        pub eef_pose_robot_base_xyzw: Option<Vec<f64>>,
        /// The two finger joints, metres.
        pub gripper_finger_joint_position_m: Option<Vec<f64>>,
    }
}

/// Sets a field whose key the writer always writes: `None` is written as null (kept in `rest`, where a read puts a
/// null), so a typed manifest has the key as the untyped writer had it.
fn set_nullable<T>(field: &mut Option<T>, rest: &mut serde_json::Map<String, Value>, key: &str, value: Option<T>) {
    match value {
        Some(v) => {
            rest.remove(key);
            *field = Some(v);
        }
        None => {
            rest.insert(key.to_owned(), Value::Null);
            *field = None;
        }
    }
}

impl DemoSource {
    /// Sets `episode_success`: null when the source episode never finished.
    pub fn set_episode_success(&mut self, success: Option<bool>) {
        set_nullable(&mut self.episode_success, &mut self.rest, "episode_success", success);
    }
}

impl DemoVerification {
    /// Sets `replay_success`: null when the bundle was not replayed.
    pub fn set_replay_success(&mut self, success: Option<bool>) {
        set_nullable(&mut self.replay_success, &mut self.rest, "replay_success", success);
    }
}

impl DemoManifest {
    /// Whether the bundle is verified (`verification.verified` is true).
    pub fn verified(&self) -> bool {
        self.verification.as_ref().and_then(|v| v.verified) == Some(true)
    }

    pub fn task_id(&self) -> Option<&str> {
        self.task.as_ref()?.id.as_deref()
    }

    pub fn instruction(&self) -> Option<&str> {
        self.task.as_ref()?.instruction.as_deref()
    }

    /// The branch the bundle's source episode was (None: it started at the task's start).
    pub fn branch(&self) -> Option<&DemoBranch> {
        self.source.as_ref()?.branch.as_ref()
    }

    /// The stored check of replaying the bundle in `target`, if one is stored.
    pub fn replay_check(&self, target: &Value) -> Option<&ReplayCheck> {
        self.replay_checks.iter().flatten().find(|c| c.target.as_ref() == Some(target))
    }
}

/// What a replay check's summary reads of its target: the configuration the target episode started from.
#[derive(serde::Deserialize)]
struct TargetLayout {
    effective_layout: Option<LayoutSeed>,
}

/// The placement seed and init row of an episode configuration (its other keys are not read here).
#[derive(serde::Deserialize, Default)]
struct LayoutSeed {
    placement_seed: Option<u64>,
    init_index: Option<u64>,
}

/// The rule a replay check is made under today (issue 48: direct and offset replays, stages counted); a stored
/// acceptance under another rule is checked again.
pub const REPLAY_CHECK_METHOD: &str = "direct_and_offset_replay_v2";

impl ReplayCheck {
    /// One line for people: which episode configuration, what the direct and the best offset replay earned of the
    /// target's stages, and whether the bundle may be shown there (`direct 0/2 · offset 2/2 (solves) · idle 0 ·
    /// at most 1 → shown, direct rule`).
    pub fn summary(&self) -> String {
        let layout = self.target.as_ref().and_then(|t| TargetLayout::deserialize(t).ok()).and_then(|t| t.effective_layout).unwrap_or_default();
        let seed = layout.placement_seed.map_or_else(|| "?".to_owned(), |s| s.to_string());
        let init = layout.init_index.map(|i| format!(", init {i}")).unwrap_or_default();
        let k = self.required_stage_count.map_or_else(|| "?".to_owned(), |k| k.to_string());
        let c = |n: Option<u64>| n.map_or_else(|| "?".to_owned(), |n| n.to_string());
        if self.method.as_deref() != Some(REPLAY_CHECK_METHOD) {
            let solves = match self.replay_solves {
                Some(true) => "solves",
                Some(false) => "does not solve",
                None => "?",
            };
            return format!("seed {seed}{init}: direct replay {solves} (stages not checked, older rule)");
        }
        let offsets = self.offset_replays.as_ref().map_or(0, Vec::len);
        let verdict = match (self.accepted, self.direct_accepted) {
            (Some(true), _) => "shown",
            (_, Some(true)) => "shown, direct rule (an offset replay earns more)",
            _ => "refused",
        };
        format!(
            "seed {seed}{init}: direct {}/{k} · best of {offsets} offsets {}/{k}{} · idle {} · at most {} → {verdict}",
            c(self.completed_required_stage_count),
            c(self.best_completed_stage_count),
            if self.replay_solves == Some(true) { " (solves)" } else { "" },
            c(self.idle_completed_stage_count),
            c(self.allowed_stage_count),
        )
    }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;
    use crate::json::pretty_sorted;

    #[test]
    fn the_golden_manifest_round_trips_and_reads() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/demo_bundle/manifest.json");
        let text = std::fs::read_to_string(path).unwrap();
        let m: DemoManifest = serde_json::from_str(&text).unwrap();
        assert_eq!(format!("{}\n", pretty_sorted(&m.to_value())), text);
        assert_eq!((m.task_id(), m.verified(), m.frame_count, m.transition_count), (Some("T14"), true, Some(3), Some(2)));
        let s = m.source.as_ref().unwrap();
        assert_eq!((s.episode_id.as_deref(), s.level, s.episode_success, s.layout.clone()), (Some("ep-20260101T000000Z-0000abcd"), Some(3), Some(true), Some(Value::Null)));
        assert_eq!(m.overview.as_ref().and_then(|o| o.sampling.as_ref()).and_then(|s| s.sampled_frame_indices.clone()), Some(vec![0, 1, 2]));
    }

    /// The fields the recorder writes read back typed from the golden manifest (artifacts, integrity, videos,
    /// sampling), and a null verdict is written as a null key, not left out.
    #[test]
    fn the_golden_manifest_reads_its_files_and_nullable_verdicts_stay_keys() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/demo_bundle/manifest.json");
        let m: DemoManifest = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        let video = m.video.as_ref().unwrap();
        assert_eq!((video.fps_hz, video.frame_count, video.layout.as_deref()), (Some(20.0), Some(3), Some("head_rgb_left__wrist_rgb_right")));
        assert_eq!(video.file.as_ref().and_then(|f| f.media_type.as_deref()), Some("video/mp4"));
        let integrity = m.integrity.as_ref().unwrap();
        assert_eq!(integrity.algorithm.as_deref(), Some("sha256"));
        let files = integrity.files.as_deref().unwrap();
        assert!(files.iter().all(|f| f.media_type.is_none() && f.sha256.as_ref().is_some_and(|h| h.len() == 64)), "{files:?}");
        assert_eq!(m.trajectory.as_ref().and_then(|t| t.path.as_deref()), Some("trajectory.jsonl"));
        let sampling = m.overview.as_ref().and_then(|o| o.sampling.as_ref()).unwrap();
        assert_eq!((sampling.rule.as_deref(), sampling.maximum_frames_per_sheet, sampling.source_frame_count), (Some("uniform_endpoint_preserving_v1"), Some(12), Some(3)));
        let s = m.source.as_ref().unwrap();
        assert_eq!(s.settle_steps, Some(10));
        assert_eq!(s.effective_layout.as_ref().and_then(|l| l["placement_seed"].as_u64()), Some(100));
        assert_eq!(m.verification.as_ref().and_then(|v| v.method.as_deref()), Some("replay_on_world_physics"));

        let mut v = DemoVerification { verified: Some(false), ..DemoVerification::default() };
        v.set_replay_success(None);
        assert_eq!(v.to_value(), json!({"verified": false, "replay_success": null}));
        v.set_replay_success(Some(true));
        assert_eq!(v.to_value(), json!({"verified": false, "replay_success": true}));
        let mut s = DemoSource::default();
        s.set_episode_success(None);
        assert_eq!(s.to_value(), json!({"episode_success": null}));
    }

    /// A golden trajectory row reads typed and writes back byte for byte (compact, keys sorted).
    #[test]
    fn golden_trajectory_rows_read_typed_and_write_back_byte_for_byte() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/demo_bundle/trajectory.jsonl");
        let text = std::fs::read_to_string(path).unwrap();
        for (n, line) in text.lines().enumerate() {
            let row: DemoTrajectoryRow = serde_json::from_str(line).unwrap();
            assert_eq!(row.to_string(), line);
            assert_eq!((row.action_index, row.frame_before, row.frame_after), (Some(n as u64), Some(n as u64), Some(n as u64 + 1)));
            let action = row.action.as_ref().unwrap();
            assert_eq!((action.schema_version.as_deref(), action.normalized_vector_7d.as_ref().map(Vec::len)), (Some("libero.normalized_osc_pose_action.v1"), Some(7)));
            let before = row.state_before.as_ref().unwrap();
            assert_eq!((before.eef_pose_robot_base_xyzw.as_ref().map(Vec::len), before.gripper_finger_joint_position_m.as_ref().map(Vec::len)), (Some(7), Some(2)));
        }
    }

    #[test]
    fn a_stored_replay_check_is_found_by_its_target() {
        let target = json!({"task": "T14", "effective_layout": {"init_index": 1}});
        let m = DemoManifest::from_value(json!({"replay_checks": [{"target": target, "replay_solves": false, "method": "x"}]})).unwrap();
        assert_eq!(m.replay_check(&target).and_then(|c| c.replay_solves), Some(false));
        assert_eq!(m.replay_check(&target).and_then(|c| c.method.as_deref()), Some("x"));
        assert!(m.replay_check(&json!({"task": "T14"})).is_none());
    }

    #[test]
    fn a_replay_check_reads_in_one_line_with_its_stage_counts() {
        let check = ReplayCheck::from_value(json!({
            "target": {"task": "T28", "effective_layout": {"placement_seed": 100, "init_index": null}},
            "method": "direct_and_offset_replay_v2", "replay_solves": true, "accepted": false, "direct_accepted": true,
            "completed_required_stage_count": 0, "required_stage_count": 2, "best_completed_stage_count": 2,
            "idle_completed_stage_count": 0, "allowed_stage_count": 1,
            "offset_replays": [{"instance": "latched_door_1", "offset_m": [0.01, 0.0, 0.0], "success": true, "completed_required_stage_count": 2}],
        }))
        .unwrap();
        assert_eq!(
            check.summary(),
            "seed 100: direct 0/2 · best of 1 offsets 2/2 (solves) · idle 0 · at most 1 → shown, direct rule (an offset replay earns more)"
        );
        let old = ReplayCheck::from_value(json!({"target": {"effective_layout": {"placement_seed": 7, "init_index": 3}}, "replay_solves": false})).unwrap();
        assert_eq!(old.summary(), "seed 7, init 3: direct replay does not solve (stages not checked, older rule)");
    }
}
