//! A demonstration bundle's `manifest.json` (protocol §7, the demo library), typed for the code that uses bundles:
//! the library, the projection into a workspace, replays and the console's list. Validating a bundle reads the
//! manifest as plain JSON instead: it reports each missing or ill-typed field. See [`crate::typed`] for how the
//! fields not named here (integrity, artifacts, action semantics) survive a read.
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
        pub replay_success: Option<bool>,
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
    }
}

record! {
    /// The bundle's overview (contact sheets and how their frames were sampled).
    pub struct DemoOverview {
        pub sampling: Option<FrameSampling>,
    }
}

record! {
    /// §7.6's frame sampling of the contact sheets.
    pub struct FrameSampling {
        pub sampled_frame_indices: Option<Vec<u64>>,
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

/// The rule a replay check is made under today (issue 48: direct and offset replays, stages counted); a stored
/// acceptance under another rule is checked again.
pub const REPLAY_CHECK_METHOD: &str = "direct_and_offset_replay_v2";

impl ReplayCheck {
    /// One line for people: which episode configuration, what the direct and the best offset replay earned of the
    /// target's stages, and whether the bundle may be shown there (`direct 0/2 · offset 2/2 (solves) · idle 0 ·
    /// at most 1 → shown, direct rule`).
    pub fn summary(&self) -> String {
        let target = self.target.as_ref();
        let layout = target.map(|t| &t["effective_layout"]);
        let seed = layout.and_then(|l| l["placement_seed"].as_u64()).map_or_else(|| "?".to_owned(), |s| s.to_string());
        let init = layout.and_then(|l| l["init_index"].as_u64()).map(|i| format!(", init {i}")).unwrap_or_default();
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
        let offsets = self.rest.get("offset_replays").and_then(|v| v.as_array()).map_or(0, Vec::len);
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
