//! A batch's records as their readers see them (the report, the Results page, a queued batch's follower): the
//! batch document (`batch.json` of a batch directory, the same document in a shared store) and the fields of a
//! rollout record (a line of `rollouts.jsonl`) that hold even for a record the queue wrote for a lost worker. The
//! runner writes both; see [`crate::typed`] for how the fields named here and the others survive a read. A
//! rollout's `harness_manifest.json` is in [`harness_manifest`].
use std::collections::BTreeMap;

pub mod harness_manifest;

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
        pub sandbox: Option<Option<SandboxDoc>>,
        /// The agent's Python in the sandbox; null without one.
        pub toolbox: Option<Option<ToolboxDoc>>,
        /// The episode server the rollouts ran on (null for a queued batch: each worker has its own).
        pub server_url: Option<Option<String>>,
        /// Where the rollouts' workspaces are (null for a queued batch).
        pub workspace_root: Option<Option<String>>,
        /// Outer retries of an INVALID rollout within the batch (always 0: `--resume` re-runs them).
        pub max_outer_retries: Option<u64>,
        pub rollout_count: Option<u64>,
        /// Tasks the selection named that have no implementation (left out of the schedule).
        pub skipped_unimplemented_tasks: Option<Vec<String>>,
        pub counts: Option<BatchCounts>,
        /// Rollout ids running now.
        pub running: Option<Vec<String>>,
        /// A queued batch's running rollouts and where they run.
        pub running_on: Option<Vec<RunningRollout>>,
        /// Ended rollouts per outcome class.
        pub outcomes: Option<BTreeMap<String, u64>>,
        /// A queued batch's store (its URL without credentials).
        pub queue: Option<QueueRef>,
    }
}

record! {
    /// Where a queued batch's rollouts wait.
    pub struct QueueRef {
        pub store: Option<String>,
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
        /// Null until a version probe ran (a queued batch's, before its workers report).
        pub version: Option<Option<HarnessVersion>>,
    }
}

record! {
    /// What the harness's version probe asked and saw: the batch's (`batch.json`), and each rollout's, probed on the
    /// executable that rollout launched (a line of `rollouts.jsonl`).
    pub struct HarnessVersion {
        /// The command probed, without `--version` (`codex`, a pinned install's path, `npx --yes <package>`).
        pub requested: Option<String>,
        /// The first version-looking word it printed (`0.154.0`).
        pub observed: Option<String>,
        pub probe_output: Option<String>,
        /// The file the command resolved to on the runner's PATH (absent in records written before it was kept).
        pub executable: Option<String>,
    }
}

record! {
    /// The sandbox the batch ran in.
    pub struct SandboxDoc {
        pub kind: Option<String>,
        pub version: Option<String>,
        /// The per-rollout caps in force; null when the batch ran with `--unconfined-resources`.
        pub resources: Option<Option<ResourceLimitsDoc>>,
    }
}

record! {
    /// What one rollout's agent could take of the machine (`Resources::describe`).
    pub struct ResourceLimitsDoc {
        pub max_processes: Option<u64>,
        pub memory_bytes: Option<u64>,
        /// A CPU quota; null: every CPU of the machine (at half the server's weight).
        pub cpus: Option<Option<f64>>,
        pub disk_bytes: Option<u64>,
        pub enforced_by: Option<String>,
        pub agent_uids: Option<Option<String>>,
    }
}

impl ResourceLimitsDoc {
    /// `1,024 processes, 4.0 GiB memory, 2.0 GiB disk, all CPUs`.
    pub fn summary(&self) -> String {
        let gib = |b: Option<u64>| match b {
            Some(b) if b >= 1 << 30 => format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64),
            Some(b) => format!("{} MiB", b >> 20),
            None => "?".into(),
        };
        let cpus = match self.cpus.flatten() {
            Some(c) => format!("{c} CPUs"),
            None => "all CPUs".into(),
        };
        format!(
            "{} processes, {} memory, {} disk, {cpus}",
            self.max_processes.map(|n| n.to_string()).unwrap_or_else(|| "?".into()),
            gib(self.memory_bytes),
            gib(self.disk_bytes)
        )
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
        /// Where the agent sees it in the sandbox.
        pub inside: Option<String>,
        /// Its size on disk, bytes.
        pub size_bytes: Option<u64>,
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
        pub worker: Option<Option<String>>,
        /// The machine its worker runs on.
        pub host: Option<Option<String>>,
        /// Its episode's live view.
        pub live_url: Option<Option<String>>,
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
    /// The sandbox the batch ran in; `None` without one (null or absent).
    pub fn sandbox(&self) -> Option<&SandboxDoc> {
        self.sandbox.as_ref()?.as_ref()
    }

    /// The toolbox the sandbox showed the agent; `None` without one.
    pub fn toolbox(&self) -> Option<&ToolboxDoc> {
        self.toolbox.as_ref()?.as_ref()
    }

    /// The counts and outcomes of `ended` rollouts (by outcome class), `running` ones and `left` ones, and the
    /// status they make (`queued` before any started, `finished` when none is running or left).
    pub fn set_progress<'a>(&mut self, ended: impl IntoIterator<Item = &'a str>, running: Vec<RunningRollout>, left: u64) {
        let mut outcomes = BTreeMap::new();
        for outcome in ended {
            *outcomes.entry(outcome.to_owned()).or_insert(0) += 1;
        }
        let done = outcomes.values().sum::<u64>();
        self.status = Some(
            match (done, running.len(), left) {
                (_, 0, 0) => "finished",
                (0, 0, _) => "queued",
                _ => "running",
            }
            .to_owned(),
        );
        self.counts = Some(BatchCounts { done: Some(done), running: Some(running.len() as u64), left: Some(left), ..Default::default() });
        self.running = Some(running.iter().filter_map(|r| r.rollout_id.clone()).collect());
        self.running_on = Some(running);
        self.outcomes = Some(outcomes);
    }

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
        assert_eq!((b.toolbox.clone(), b.toolbox()), (Some(None), None), "a null toolbox is no toolbox");
        assert_eq!(json!(b.toolbox), Value::Null, "passed on as the null it was");
        assert_eq!(b.sandbox().and_then(|s| s.version.as_deref()), Some("0.9"));
        let running = &b.running_on.as_ref().unwrap()[0];
        assert_eq!((running.worker.clone(), running.host.clone()), (Some(Some("w".into())), Some(None)));
        assert_eq!(b.harness.as_ref().and_then(|h| h.version.clone().flatten()).and_then(|v| v.observed), None);
    }

    #[test]
    fn progress_counts_outcomes_and_says_the_status_they_make() {
        let mut d = BatchDoc::default();
        d.set_progress([], Vec::new(), 3);
        assert_eq!((d.status.as_deref(), d.outcome_count("SUCCESS")), (Some("queued"), 0));
        let r1 = RunningRollout { rollout_id: Some("r1".into()), worker: Some(Some("w".into())), host: Some(None), ..Default::default() };
        d.set_progress(["SUCCESS", "INVALID", "SUCCESS"], vec![r1], 2);
        assert_eq!(d.status.as_deref(), Some("running"));
        let c = d.counts.clone().unwrap();
        assert_eq!((c.done, c.running, c.left), (Some(3), Some(1), Some(2)));
        assert_eq!((d.outcome_count("SUCCESS"), d.outcome_count("INVALID")), (2, 1));
        assert_eq!(d.to_value()["running"], json!(["r1"]));
        assert_eq!(d.to_value()["running_on"], json!([{"rollout_id": "r1", "worker": "w", "host": null}]), "null kept, absent left out");
        d.set_progress(["FAIL"], Vec::new(), 0);
        assert_eq!(d.status.as_deref(), Some("finished"));
        d.set_progress([], Vec::new(), 0);
        assert_eq!(d.status.as_deref(), Some("finished"), "an empty batch has nothing left to run");
    }

    #[test]
    fn a_lost_workers_record_has_its_reason() {
        let r = RolloutSummary::from_value(json!({"rollout_id": "x", "outcome": "INVALID", "termination_reason": "worker_lost"})).unwrap();
        assert_eq!((r.rollout_id.as_deref(), r.outcome.as_deref(), r.reason()), (Some("x"), Some("INVALID"), Some("worker_lost")));
        let r = RolloutSummary::from_value(json!({"infrastructure_error": "", "termination_reason": null})).unwrap();
        assert_eq!(r.reason(), None);
    }
    #[test]
    fn resource_limits_read_as_a_person_would_say_them() {
        let r = ResourceLimitsDoc::from_value(json!({"max_processes": 1024, "memory_bytes": 4u64 << 30, "cpus": null, "disk_bytes": 256u64 << 20})).unwrap();
        assert_eq!(r.summary(), "1024 processes, 4.0 GiB memory, 256 MiB disk, all CPUs");
        let r = ResourceLimitsDoc::from_value(json!({"max_processes": 64, "memory_bytes": 512u64 << 20, "cpus": 0.5, "disk_bytes": 2u64 << 30})).unwrap();
        assert_eq!(r.summary(), "64 processes, 512 MiB memory, 2.0 GiB disk, 0.5 CPUs");
    }

}
