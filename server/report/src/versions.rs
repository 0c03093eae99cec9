//! The harness versions rollouts ran, for `report` and the Results page. Each rollout's record keeps what `--version`
//! of the CLI it launched printed (`harness_version.observed`, the runner's `harness_versions::probe`); a batch recorded
//! before rollouts were probed has only its own probe (`batch.json`'s `harness.version`), which then stands for each
//! of its rollouts. Rollouts of one batch, or of one agent's row across batches, that ran different versions are
//! flagged as mixed: their numbers pool different CLIs.
use std::cmp::Ordering;

use serde::Serialize;

use crate::batch::{LoadedBatch, RolloutRecord};

/// One version and how many of the rollouts ran it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct VersionCount {
    pub version: String,
    pub rollouts: usize,
}

/// The versions of a harness a set of rollouts ran.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct HarnessVersions {
    pub harness: String,
    /// Oldest first.
    pub versions: Vec<VersionCount>,
    /// Rollouts with no version: ended before their launch, or agents of `--harness command`.
    pub unknown: usize,
    /// More than one version ran.
    pub mixed: bool,
    /// `codex 0.154.0`, `codex 0.154.0 / 0.169.0 (mixed versions)`, `codex (version unknown)`.
    pub text: String,
}

impl HarnessVersions {
    /// Over the rollouts of `batches` that `keep` keeps.
    pub fn of<'a>(batches: impl IntoIterator<Item = &'a LoadedBatch>, keep: impl Fn(&RolloutRecord) -> bool) -> Self {
        let mut harness = None;
        let mut versions: Vec<VersionCount> = Vec::new();
        let mut unknown = 0;
        for b in batches {
            harness = harness.or_else(|| b.batch.harness_setting().map(str::to_owned));
            // A batch none of whose records has a version was recorded before rollouts were probed: its own probe.
            let probed = b.records.iter().any(|r| r.harness_version.is_some());
            for r in b.records.iter().filter(|r| keep(r)) {
                let version = if probed { observed_of(r) } else { batch_observed(b) };
                match version {
                    Some(v) => add(&mut versions, v, 1),
                    None => unknown += 1,
                }
            }
        }
        Self::new(harness.unwrap_or_else(|| "?".into()), versions, unknown)
    }

    /// Over every rollout of `b`; a batch with none recorded yet shows its own probe.
    pub fn of_batch(b: &LoadedBatch) -> Self {
        let mut v = Self::of([b], |_| true);
        if b.records.is_empty()
            && let Some(observed) = batch_observed(b)
        {
            v = Self::new(v.harness, vec![VersionCount { version: observed.to_owned(), rollouts: 0 }], 0);
        }
        v
    }

    fn new(harness: String, mut versions: Vec<VersionCount>, unknown: usize) -> Self {
        versions.sort_by(|a, b| compare_versions(&a.version, &b.version));
        let mixed = versions.len() > 1;
        let mut v = Self { harness, versions, unknown, mixed, text: String::new() };
        v.text = match v.versions_text() {
            Some(t) => format!("{} {t}", v.harness),
            None if v.harness == "command" => v.harness.clone(),
            None => format!("{} (version unknown)", v.harness),
        };
        v
    }

    /// The versions alone (`0.154.0 / 0.169.0 (mixed versions)`); `None` when none is known.
    pub fn versions_text(&self) -> Option<String> {
        if self.versions.is_empty() {
            return None;
        }
        let list: Vec<&str> = self.versions.iter().map(|v| v.version.as_str()).collect();
        Some(format!("{}{}", list.join(" / "), if self.mixed { " (mixed versions)" } else { "" }))
    }
}

fn observed_of(r: &RolloutRecord) -> Option<&str> {
    r.harness_version.as_ref()?.observed.as_deref()
}

fn batch_observed(b: &LoadedBatch) -> Option<&str> {
    b.batch.harness.as_ref()?.version.as_ref()?.as_ref()?.observed.as_deref()
}

fn add(versions: &mut Vec<VersionCount>, version: &str, n: usize) {
    match versions.iter_mut().find(|v| v.version == version) {
        Some(v) => v.rollouts += n,
        None => versions.push(VersionCount { version: version.to_owned(), rollouts: n }),
    }
}

/// `0.9.0 < 0.10.0 < 0.154.0`: numeric parts as numbers, others as text.
fn compare_versions(a: &str, b: &str) -> Ordering {
    let parts = |s: &str| -> Vec<(u64, String)> {
        s.split(['.', '-', '+']).map(|p| (p.parse::<u64>().unwrap_or(u64::MAX), p.to_owned())).collect()
    };
    parts(a).cmp(&parts(b))
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;

    fn record(id: &str, level: u8, observed: Option<&str>) -> RolloutRecord {
        let mut r: RolloutRecord = serde_json::from_value(json!({
            "schema_version": "libero_agent.rollout.v1", "rollout_id": id, "task": "T14", "task_number": 14,
            "split": "short_horizon_easy", "stage_count": 1, "repetition": 1, "level": level, "demo": "none",
            "outcome": "SUCCESS", "episode_id": null, "workspace": null, "run_dir": null, "result_status": null,
            "success": true, "termination_reason": null, "infrastructure_error": null, "wall_time_s": 1.0,
            "harness_elapsed_s": null, "accepted_agent_steps": 2, "completed_stages": 1, "judgment_correct": null,
            "agent_exit_code": 0, "usage": null, "started_at": "x", "finished_at": "y"}))
        .unwrap();
        r.harness_version = observed.map(|o| {
            libero_records::batch_doc::HarnessVersion::from_value(json!({"requested": "codex", "observed": o})).unwrap()
        });
        r
    }

    fn batch(name: &str, batch_observed: Option<&str>, records: Vec<RolloutRecord>) -> LoadedBatch {
        let doc = json!({"schema_version": "libero_agent.batch.v1", "settings": {"harness": "codex", "model": "m"},
            "harness": {"name": "codex", "version": {"requested": "codex", "observed": batch_observed, "probe_output": null}}});
        LoadedBatch { dir: format!("/b/{name}").into(), batch: libero_records::batch_doc::BatchDoc::from_value(doc).unwrap(), records }
    }

    #[test]
    fn rollouts_of_one_version_say_it() {
        let b = batch("a", Some("0.169.0"), vec![record("r1", 3, Some("0.154.0")), record("r2", 3, Some("0.154.0"))]);
        let v = HarnessVersions::of_batch(&b);
        assert_eq!((v.text.as_str(), v.mixed, v.unknown), ("codex 0.154.0", false, 0), "the rollouts' own, not the batch's first look");
        assert_eq!(v.versions, [VersionCount { version: "0.154.0".into(), rollouts: 2 }]);
    }

    #[test]
    fn rollouts_that_ran_different_versions_are_flagged_mixed() {
        let b = batch("a", Some("0.154.0"), vec![record("r1", 3, Some("0.169.0")), record("r2", 3, Some("0.154.0")), record("r3", 3, None)]);
        let v = HarnessVersions::of_batch(&b);
        assert!(v.mixed);
        assert_eq!(v.text, "codex 0.154.0 / 0.169.0 (mixed versions)");
        assert_eq!(v.versions_text().as_deref(), Some("0.154.0 / 0.169.0 (mixed versions)"));
        assert_eq!(v.unknown, 1, "a rollout that ended before its launch ran no version");
        // Across batches of one agent: the row's rollouts only.
        let other = batch("b", Some("0.9.0"), vec![record("r1", 1, Some("0.9.0"))]);
        let same = batch("c", None, vec![record("r1", 3, Some("0.154.0"))]);
        let l3 = |r: &RolloutRecord| r.level == 3;
        assert!(!HarnessVersions::of([&same, &other], l3).mixed, "batch b has no level-3 rollout");
        let all = HarnessVersions::of([&same, &other], |_| true);
        assert_eq!(all.text, "codex 0.9.0 / 0.154.0 (mixed versions)", "numeric order");
    }

    #[test]
    fn a_batch_recorded_before_rollouts_were_probed_uses_its_own_probe() {
        let old = batch("old", Some("0.169.0"), vec![record("r1", 3, None), record("r2", 3, None)]);
        let v = HarnessVersions::of_batch(&old);
        assert_eq!((v.text.as_str(), v.versions[0].rollouts, v.unknown), ("codex 0.169.0", 2, 0));
        let queued = batch("q", Some("0.154.0"), Vec::new());
        assert_eq!(HarnessVersions::of_batch(&queued).text, "codex 0.154.0", "nothing ran yet: the batch's probe");
        let unknown = batch("u", None, vec![record("r1", 3, None)]);
        assert_eq!(HarnessVersions::of_batch(&unknown).text, "codex (version unknown)");
    }
}
