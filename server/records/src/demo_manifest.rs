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
        pub replay_solves: Option<bool>,
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

    /// The stored verdict of replaying the bundle in `target`, if one is stored.
    pub fn replay_check(&self, target: &Value) -> Option<bool> {
        self.replay_checks.iter().flatten().find(|c| c.target.as_ref() == Some(target))?.replay_solves
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
        assert_eq!(m.replay_check(&target), Some(false));
        assert_eq!(m.replay_check(&json!({"task": "T14"})), None);
    }
}
