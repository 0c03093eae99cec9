//! Task-pool results (issue 22): rollouts of `run --experiment pool` summarized per suite (libero_90,
//! robomemarena, …) under the paper's stable rule, beside and never inside the 30-task Score. A pool task has
//! no paper split, so each suite reports both numbers: stable success (every rollout succeeds) and stable stage
//! completion (the minimum `c / K`), with the ordinary success rate and its Wilson interval.
use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::{Outcome, Proportion, StableCounts, Trial, mean, rate, stable_counts};

/// What the pool summary needs of one rollout.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoolRollout {
    /// The pool suite (`libero_90`, `robomemarena`, …; `release` for a T-id scheduled in a pool batch).
    pub suite: String,
    /// The address the rollout ran (`libero_90/35`, `T11`).
    pub task: String,
    pub repetition: u32,
    pub outcome: Outcome,
    #[serde(default)]
    pub judgment_correct: Option<bool>,
    #[serde(default)]
    pub completed_stages: Option<u32>,
    pub stage_count: u32,
    #[serde(default)]
    pub wall_time_s: Option<f64>,
}

impl Trial for PoolRollout {
    fn repetition(&self) -> u32 {
        self.repetition
    }
    fn outcome(&self) -> Outcome {
        self.outcome
    }
    fn stage_fraction(&self) -> f64 {
        crate::stage_fraction(self.completed_stages, self.stage_count, self.outcome == Outcome::Success)
    }
    fn judgment_correct(&self) -> Option<bool> {
        self.judgment_correct
    }
}

/// One pool task under the stable rule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoolTaskSummary {
    pub suite: String,
    pub task: String,
    pub stage_count: u32,
    #[serde(flatten)]
    pub counts: StableCounts,
}

/// One suite of the pool.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoolSuiteSummary {
    pub suite: String,
    /// Tasks of the suite with at least one rollout.
    pub tasks: usize,
    /// Tasks with a stable value (`reps` valid rollouts).
    pub tasks_scored: usize,
    /// Fraction of the scored tasks whose every rollout succeeded.
    pub stable_success: Option<f64>,
    /// Mean over the scored tasks of the minimum `c / K`.
    pub stable_stage_completion: Option<f64>,
    /// Mean `c / K` over every valid rollout.
    pub mean_stage_completion: Option<f64>,
    /// SUCCESS / valid rollouts with its Wilson interval.
    pub ordinary: Proportion,
    pub outcome_counts: BTreeMap<Outcome, usize>,
    /// Mean episode time over every episode of the suite, INVALID included (as [`crate::SuiteSummary`]).
    pub avg_wall_time_min: Option<f64>,
    /// INVALID episodes inside that mean.
    #[serde(default)]
    pub averaged_invalid: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoolSummary {
    pub reps: usize,
    pub rollouts: usize,
    pub suites: Vec<PoolSuiteSummary>,
    pub tasks: Vec<PoolTaskSummary>,
}

/// Summarizes one agent's pool rollouts per suite (suites and tasks in name order).
pub fn summarize_pool(rollouts: &[PoolRollout], reps: usize) -> PoolSummary {
    let mut by_task: BTreeMap<(&str, &str), Vec<&PoolRollout>> = BTreeMap::new();
    for r in rollouts {
        by_task.entry((r.suite.as_str(), r.task.as_str())).or_default().push(r);
    }
    let tasks: Vec<PoolTaskSummary> = by_task
        .iter()
        .map(|(&(suite, task), rs)| PoolTaskSummary {
            suite: suite.to_owned(),
            task: task.to_owned(),
            stage_count: rs.iter().map(|r| r.stage_count).max().unwrap_or(1),
            counts: stable_counts(rs, reps),
        })
        .collect();
    let mut suite_names: Vec<&str> = rollouts.iter().map(|r| r.suite.as_str()).collect();
    suite_names.sort_unstable();
    suite_names.dedup();
    let suites = suite_names
        .into_iter()
        .map(|suite| {
            let ts: Vec<&PoolTaskSummary> = tasks.iter().filter(|t| t.suite == suite).collect();
            let valid: Vec<&PoolRollout> = rollouts.iter().filter(|r| r.suite == suite && r.outcome.is_valid()).collect();
            let episodes: Vec<&PoolRollout> = rollouts.iter().filter(|r| r.suite == suite && crate::is_episode(r.outcome)).collect();
            let mut outcome_counts = BTreeMap::new();
            for r in rollouts.iter().filter(|r| r.suite == suite) {
                *outcome_counts.entry(r.outcome).or_insert(0) += 1;
            }
            PoolSuiteSummary {
                suite: suite.to_owned(),
                tasks: ts.len(),
                tasks_scored: ts.iter().filter(|t| t.counts.stable_success.is_some()).count(),
                stable_success: rate(ts.iter().filter_map(|t| t.counts.stable_success)),
                stable_stage_completion: mean(ts.iter().filter_map(|t| t.counts.stable_stage_fraction)),
                mean_stage_completion: mean(valid.iter().map(|r| r.stage_fraction())),
                ordinary: Proportion::new(valid.iter().filter(|r| r.outcome == Outcome::Success).count() as u64, valid.len() as u64),
                outcome_counts,
                avg_wall_time_min: mean(episodes.iter().filter_map(|r| r.wall_time_s).map(|s| s / 60.0)),
                averaged_invalid: episodes.iter().filter(|r| r.outcome == Outcome::Invalid).count(),
            }
        })
        .collect();
    PoolSummary { reps, rollouts: rollouts.len(), suites, tasks }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn r(suite: &str, task: &str, rep: u32, outcome: Outcome, c: Option<u32>, k: u32) -> PoolRollout {
        PoolRollout {
            suite: suite.into(),
            task: task.into(),
            repetition: rep,
            outcome,
            judgment_correct: None,
            completed_stages: c,
            stage_count: k,
            wall_time_s: Some(120.0),
        }
    }

    #[test]
    fn each_suite_gets_stable_success_and_stage_completion_over_its_own_tasks() {
        let rs = [
            r("libero_90", "libero_90/35", 1, Outcome::Success, None, 1),
            r("libero_90", "libero_90/35", 2, Outcome::Success, None, 1),
            r("libero_90", "libero_90/0", 1, Outcome::Success, None, 1),
            r("libero_90", "libero_90/0", 2, Outcome::Fail, None, 1),
            r("robomemarena", "robomemarena/18", 1, Outcome::Fail, Some(1), 2),
            r("robomemarena", "robomemarena/18", 2, Outcome::SimTimeout, Some(2), 2),
            r("robomemarena", "robomemarena/25", 1, Outcome::Invalid, None, 2),
        ];
        let s = summarize_pool(&rs, 2);
        assert_eq!(s.suites.iter().map(|x| x.suite.as_str()).collect::<Vec<_>>(), ["libero_90", "robomemarena"]);
        let l90 = &s.suites[0];
        assert_eq!((l90.tasks, l90.tasks_scored, l90.stable_success), (2, 2, Some(0.5)));
        assert_eq!((l90.ordinary.successes, l90.ordinary.trials), (3, 4));
        let rma = &s.suites[1];
        // robomemarena/25 has no valid rollout: listed, not scored, not counted as a failure.
        assert_eq!((rma.tasks, rma.tasks_scored, rma.stable_success), (2, 1, Some(0.0)));
        assert_eq!(rma.stable_stage_completion, Some(0.5));
        assert_eq!(rma.mean_stage_completion, Some(0.75));
        assert_eq!((rma.ordinary.successes, rma.ordinary.trials), (0, 2));
        assert_eq!(rma.outcome_counts[&Outcome::Invalid], 1);
        // the INVALID rollout's time is in the mean, and said to be
        assert_eq!((rma.avg_wall_time_min, rma.averaged_invalid), (Some(2.0), 1));
        let t = s.tasks.iter().find(|t| t.task == "robomemarena/25").unwrap();
        assert_eq!((t.counts.valid_rollouts, t.counts.excluded_rollouts, t.counts.stable_success), (0, 1, None));
    }
}
