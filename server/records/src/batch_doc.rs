//! A batch's records as their readers see them (the report, the Results page, a queued batch's follower): the
//! batch document (`batch.json` of a batch directory, the same document in a shared store) and the fields of a
//! rollout record (a line of `rollouts.jsonl`) that hold even for a record the queue wrote for a lost worker. The
//! runner writes both; see [`crate::typed`] for how the fields named here and the others survive a read.
use std::collections::BTreeMap;

use crate::typed::record;

record! {
    /// `batch.json`: the batch's settings, harness and sandbox, its status and progress.
    pub struct BatchDoc {
        pub schema_version: Option<String>,
        /// A queued batch's name (a batch directory's is its directory's).
        pub name: Option<String>,
        pub created_at: Option<String>,
        pub updated_at: Option<String>,
        /// `queued`, `running`, `finished`, `interrupted`.
        pub status: Option<String>,
        pub settings: Option<BatchSettingsDoc>,
        /// What `--resume` compares: the settings' canonical hash.
        pub settings_sha256: Option<String>,
        pub harness: Option<HarnessDoc>,
        /// Null for a batch run without the sandbox (or queued, before a worker reports one).
        pub sandbox: Option<SandboxDoc>,
        /// The agent's Python in the sandbox; null without one.
        pub toolbox: Option<ToolboxDoc>,
        pub rollout_count: Option<u64>,
        pub counts: Option<BatchCounts>,
        /// Rollout ids running now.
        pub running: Option<Vec<String>>,
        /// A queued batch's running rollouts and where they run.
        pub running_on: Option<Vec<RunningRollout>>,
        /// Ended rollouts per outcome class.
        pub outcomes: Option<BTreeMap<String, u64>>,
    }
}

record! {
    /// The settings a batch's rollouts share (the runner's `BatchSettings`), as far as readers name them.
    pub struct BatchSettingsDoc {
        pub experiment: Option<String>,
        pub harness: Option<String>,
        pub model: Option<String>,
        pub effort: Option<String>,
        /// The stable rule's repetitions (`--reps`).
        pub reps: Option<u64>,
        pub sandbox: Option<bool>,
    }
}

record! {
    /// The agent harness and the version it reported.
    pub struct HarnessDoc {
        pub name: Option<String>,
        pub version: Option<HarnessVersion>,
    }
}

record! {
    /// What the harness's version probe asked and saw.
    pub struct HarnessVersion {
        pub requested: Option<String>,
        pub observed: Option<String>,
        pub probe_output: Option<String>,
    }
}

record! {
    /// The sandbox the batch ran in.
    pub struct SandboxDoc {
        pub kind: Option<String>,
        pub version: Option<String>,
    }
}

record! {
    /// The toolbox the sandbox showed the agent (`Toolbox::describe`).
    pub struct ToolboxDoc {
        pub name: Option<String>,
        /// Where it came from (the project's lock, or `--toolbox PATH`).
        pub source: Option<String>,
        /// Its Python's version.
        pub python: Option<String>,
        pub packages: Option<Vec<ToolboxPackage>>,
    }
}

record! {
    /// One package of the toolbox.
    pub struct ToolboxPackage {
        pub name: Option<String>,
        pub version: Option<String>,
    }
}

record! {
    /// Rollouts ended, running and left.
    pub struct BatchCounts {
        pub done: Option<u64>,
        pub running: Option<u64>,
        pub left: Option<u64>,
    }
}

record! {
    /// A running rollout of a queued batch.
    pub struct RunningRollout {
        pub rollout_id: Option<String>,
        pub worker: Option<String>,
        /// The machine its worker runs on.
        pub host: Option<String>,
        /// Its episode's live view.
        pub live_url: Option<String>,
    }
}

record! {
    /// The fields of a rollout record that every stored record has, a lost worker's included (the runner's
    /// `RolloutRecord` is the whole record).
    pub struct RolloutSummary {
        pub rollout_id: Option<String>,
        /// The outcome class (§4.8).
        pub outcome: Option<String>,
        pub task: Option<String>,
        pub level: Option<u64>,
        pub episode_id: Option<String>,
        pub termination_reason: Option<String>,
        pub infrastructure_error: Option<String>,
        pub accepted_agent_steps: Option<u64>,
        pub wall_time_s: Option<f64>,
        /// Where a queued rollout's run directory is in the artifact store.
        pub artifacts: Option<String>,
    }
}

impl BatchDoc {
    pub fn experiment(&self) -> Option<&str> {
        self.settings.as_ref()?.experiment.as_deref()
    }

    /// The harness the settings name.
    pub fn harness_setting(&self) -> Option<&str> {
        self.settings.as_ref()?.harness.as_deref()
    }

    pub fn model(&self) -> Option<&str> {
        self.settings.as_ref()?.model.as_deref()
    }

    /// Ended rollouts of `outcome` (0 when none are counted).
    pub fn outcome_count(&self, outcome: &str) -> u64 {
        self.outcomes.as_ref().and_then(|o| o.get(outcome)).copied().unwrap_or(0)
    }
}

impl RolloutSummary {
    /// Why the rollout did not count: its infrastructure error, else its termination reason (the first non-empty).
    pub fn reason(&self) -> Option<&str> {
        [&self.infrastructure_error, &self.termination_reason].into_iter().find_map(|r| r.as_deref().filter(|s| !s.is_empty()))
    }
}

#[cfg(test)]
mod tests {
    use serde_json::{Value, json};

    use super::*;
    use crate::json::pretty_sorted;

    #[test]
    fn a_batch_document_round_trips_and_reads() {
        let doc = json!({
            "schema_version": "libero_agent.batch.v1", "created_at": "a", "updated_at": "b", "status": "running",
            "settings": {"experiment": "main_table", "harness": "codex", "model": "m", "effort": "high", "reps": 3,
                "tasks": [], "seed": 1, "wall_time_s": 1800.0, "max_agent_steps": 400, "agent_cmd": null, "sandbox": true},
            "settings_sha256": "00", "harness": {"name": "codex", "version": {"requested": "codex --version", "observed": null, "probe_output": null}},
            "sandbox": {"kind": "bubblewrap", "version": "0.9"}, "toolbox": null, "server_url": "http://s", "workspace_root": "/w",
            "max_outer_retries": 0, "rollout_count": 12, "skipped_unimplemented_tasks": [],
            "counts": {"done": 6, "running": 3, "left": 3}, "running": ["r1"],
            "running_on": [{"rollout_id": "r1", "worker": "w", "host": null, "live_url": null}],
            "outcomes": {"INVALID": 1, "SUCCESS": 5},
        });
        let text = pretty_sorted(&doc);
        let b: BatchDoc = serde_json::from_str(&text).unwrap();
        assert_eq!(pretty_sorted(&b.to_value()), text);
        assert_eq!((b.experiment(), b.harness_setting(), b.model()), (Some("main_table"), Some("codex"), Some("m")));
        assert_eq!((b.outcome_count("SUCCESS"), b.outcome_count("FAIL")), (5, 0));
        assert_eq!(b.counts.as_ref().and_then(|c| c.done), Some(6));
        assert_eq!(b.toolbox, None);
        assert_eq!(json!(b.toolbox), Value::Null, "passed on as the null it was");
        let running = &b.running_on.as_ref().unwrap()[0];
        assert_eq!((running.worker.as_deref(), running.host.as_deref()), (Some("w"), None));
        assert_eq!(b.harness.as_ref().and_then(|h| h.version.as_ref()).and_then(|v| v.observed.as_deref()), None);
    }

    #[test]
    fn a_lost_workers_record_has_its_reason() {
        let r = RolloutSummary::from_value(json!({"rollout_id": "x", "outcome": "INVALID", "termination_reason": "worker_lost"})).unwrap();
        assert_eq!((r.rollout_id.as_deref(), r.outcome.as_deref(), r.reason()), (Some("x"), Some("INVALID"), Some("worker_lost")));
        let r = RolloutSummary::from_value(json!({"infrastructure_error": "", "termination_reason": null})).unwrap();
        assert_eq!(r.reason(), None);
    }
}
