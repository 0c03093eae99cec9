//! `episode_record.json`: an episode's private configuration, written when it is prepared (before anything else in
//! its run directory) and read back by the store, branches, demonstrations and the live view.
use std::path::PathBuf;

use serde_json::Value;

use crate::typed::record;

pub const EPISODE_RECORD_SCHEMA: &str = "libero.agent_episode_record.v1";

record! {
    /// The episode's task, level, seed, init state, budgets and who runs it.
    pub struct EpisodeRecord {
        pub schema_version: Option<String>,
        pub episode_id: Option<String>,
        pub created_at: Option<String>,
        pub task: Option<RecordedTask>,
        pub level: Option<u64>,
        pub seed: Option<u64>,
        /// The init state the request asked for (a suite task fixes its own: `task.suite.init_index`).
        pub init_state_index: Option<u64>,
        pub max_agent_steps: Option<u64>,
        pub max_wall_time_seconds: Option<f64>,
        /// The demonstration condition (`none`, `fixed_demo`, …).
        pub demo: Option<String>,
        pub workspace: Option<PathBuf>,
        pub mcp_url: Option<String>,
        /// Agent harness, model and batch where the preparer said; null otherwise.
        pub harness: Option<Option<String>>,
        pub model: Option<Option<String>>,
        pub batch: Option<Option<String>>,
        /// Set for a branch of another episode (issue 33).
        pub branch: Option<BranchRecord>,
    }
}

record! {
    /// The task as the episode resolved it (the episode crate's `TaskSource`).
    pub struct RecordedTask {
        /// What the user asked for, e.g. `libero_object/pick_up_the_ketchup_and_place_it_in_the_basket`.
        pub task_ref: Option<String>,
        pub instruction: Option<String>,
        /// Set for release tasks; null for stock tasks.
        pub suite: Option<Option<RecordedSuite>>,
        /// A demonstration source's layout variant (absent otherwise).
        pub layout: Option<Value>,
    }
}

record! {
    /// The release-task part of a recorded task.
    pub struct RecordedSuite {
        /// The init state the task fixes.
        pub init_index: Option<u64>,
    }
}

record! {
    /// Where a branch comes from.
    pub struct BranchRecord {
        pub parent_episode_id: Option<String>,
        pub parent_control_step: Option<u64>,
        pub replayed_actions: Option<u64>,
        pub prefix_file: Option<String>,
        pub counts_toward_max_agent_steps: Option<bool>,
    }
}

impl EpisodeRecord {
    /// The recorded task's `task_ref`.
    pub fn task_ref(&self) -> Option<&str> {
        self.task.as_ref()?.task_ref.as_deref()
    }

    /// The init state the episode ran: the suite task's own, else the requested one.
    pub fn init_index(&self) -> Option<u64> {
        self.task.as_ref().and_then(|t| t.suite.clone().flatten()).and_then(|s| s.init_index).or(self.init_state_index)
    }

    /// The recorded layout variant's JSON (null without one).
    pub fn layout(&self) -> &Value {
        self.task.as_ref().and_then(|t| t.layout.as_ref()).unwrap_or(&Value::Null)
    }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;
    use crate::json::pretty_sorted;

    /// What `prepare` writes, for a branch of a release task.
    fn written() -> Value {
        json!({
            "schema_version": EPISODE_RECORD_SCHEMA,
            "episode_id": "ep-20260101T000000Z-0a1b2c3d",
            "created_at": "2026-01-01T00:00:00.000001+00:00",
            "task": {"task_ref": "T11", "bddl": "/a/b.bddl", "init_states": null, "instruction": "open the drawer",
                "suite": {"init_index": 3, "number": 11}, "task_reference": null},
            "level": 2, "seed": 7, "init_state_index": 0, "max_agent_steps": 400, "max_wall_time_seconds": 1800.0,
            "demo": "none", "workspace": "/data/workspaces/ep", "mcp_url": "http://127.0.0.1:8787/mcp/ep",
            "harness": null, "model": "m", "batch": null,
            "branch": {"parent_episode_id": "ep-p", "parent_control_step": 12, "replayed_actions": 2,
                "prefix_file": "branch_prefix.json", "counts_toward_max_agent_steps": false},
        })
    }

    #[test]
    fn the_record_round_trips_and_reads_as_before() {
        let text = pretty_sorted(&written());
        let r: EpisodeRecord = serde_json::from_str(&text).unwrap();
        assert_eq!(pretty_sorted(&r.to_value()), text);
        assert_eq!((r.task_ref(), r.level, r.seed, r.init_index()), (Some("T11"), Some(2), Some(7), Some(3)));
        assert_eq!((r.harness.clone(), r.model.clone()), (Some(None), Some(Some("m".to_owned()))));
        let b = r.branch.as_ref().unwrap();
        assert_eq!((b.parent_episode_id.as_deref(), b.parent_control_step), (Some("ep-p"), Some(12)));
        assert_eq!(r.layout(), &Value::Null);
    }

    /// `prepare` builds the record typed; its bytes are those of the `json!` literal it replaced.
    #[test]
    fn the_typed_record_writes_what_the_literal_wrote() {
        let task = json!({"task_ref": "T11", "bddl": "/a/b.bddl", "init_states": null, "instruction": "open the drawer",
            "suite": null, "task_reference": null});
        let (harness, model, batch): (Option<String>, Option<String>, Option<String>) = (None, Some("m".into()), None);
        let literal = json!({
            "schema_version": EPISODE_RECORD_SCHEMA, "episode_id": "ep-1", "created_at": "t", "task": task, "level": 1u8,
            "seed": 7u64, "init_state_index": 0usize, "max_agent_steps": 400u64, "max_wall_time_seconds": 1800.0,
            "demo": "none", "workspace": PathBuf::from("/w"), "mcp_url": "u", "harness": harness, "model": model, "batch": batch,
        });
        let typed = EpisodeRecord {
            schema_version: Some(EPISODE_RECORD_SCHEMA.to_owned()),
            episode_id: Some("ep-1".into()),
            created_at: Some("t".into()),
            task: Some(RecordedTask::from_value(task).unwrap()),
            level: Some(1),
            seed: Some(7),
            init_state_index: Some(0),
            max_agent_steps: Some(400),
            max_wall_time_seconds: Some(1800.0),
            demo: Some("none".into()),
            workspace: Some(PathBuf::from("/w")),
            mcp_url: Some("u".into()),
            harness: Some(harness),
            model: Some(model),
            batch: Some(batch),
            branch: None,
            rest: serde_json::Map::new(),
        };
        assert_eq!(pretty_sorted(&typed.to_value()), pretty_sorted(&literal));
    }

    #[test]
    fn a_stock_task_uses_the_requested_init_state() {
        let r = EpisodeRecord::from_value(json!({"task": {"task_ref": "x", "suite": null, "layout": {"placement_seed": 1}}, "init_state_index": 5}))
            .unwrap();
        assert_eq!(r.init_index(), Some(5));
        assert_eq!(r.layout(), &json!({"placement_seed": 1}));
    }
}
