//! The paper's metrics over benchmark rollouts, with no simulator dependency so reports, the dashboard and
//! tests can compute them from records alone (paper_results.md "Metrics", protocol §10):
//!
//! * stable success rate: a task counts only if all of its `reps` rollouts succeed;
//! * stable stage completion: per task the minimum over rollouts of `c / K`;
//! * perception judgment accuracy: the stable rule applied to correct target identification;
//! * the Performance Score `5J + 10P + 5M_easy + 10M_hard + 20L_easy + 50L_hard`;
//! * ordinary success rates (SUCCESS / valid rollouts) with 95 % Wilson intervals, kept beside the stable
//!   numbers, and average episode time and tokens.
//!
//! INVALID and INTERRUPTED rollouts are excluded from every rate's denominator (§4.8); a task whose valid rollouts
//! number fewer than `reps` has no stable value and is listed as incomplete rather than guessed. Time, tokens and
//! steps are averaged over every episode, INVALID ones included, as the paper averages over all episodes of a table
//! (only INTERRUPTED rollouts, cut off by a stopped batch, are left out); how many INVALID ones are in is reported.
//!
//! The paper's other tables and its figure: the ablations (Tables 2 and 3, [`ablation`]), the stage-level diagnosis
//! (Table 4, [`diagnosis`]) and the sustained-contact ratio of opening operations (Figure 3, [`contact`]).
use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

pub mod ablation;
pub mod contact;
pub mod diagnosis;
mod pool;
mod wilson;
pub use ablation::{AblationKind, AblationRow};
pub use contact::{
    AgentScr, ContactSummary, Figure3, OpeningOperation, SUSTAINED_RUN_STEPS, ScrBin, ScrBinSummary, figure3, pearson, summarize_contact,
    sustained_contact_ratio_percent, sustained_steps,
};
pub use diagnosis::{
    ExecutionRate, FailureMode, LabelSource, PaperStageDiagnosis, StageAnnotation, StageAnnotations, StageDiagnosis, StageEvidence,
    StageKey, StageLabel, StageOpportunity, StageType, TaskFacts, TypeExecution, diagnose, diagnose_paper, in_paper_table4,
};
pub use pool::{PoolRollout, PoolSuiteSummary, PoolSummary, PoolTaskSummary, summarize_pool};
pub use wilson::{Proportion, wilson_interval};

/// Rollouts per task in the paper's protocol.
pub const PAPER_REPS: usize = 3;

#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    #[error("unknown split {0:?}")]
    UnknownSplit(String),
}

/// The paper's reporting subsets (five tasks each outside perception, equal weight).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    Perception,
    ShortHorizonEasy,
    ShortHorizonHard,
    LongHorizonEasy,
    LongHorizonHard,
}

impl Split {
    pub const ALL: [Split; 5] =
        [Split::Perception, Split::ShortHorizonEasy, Split::ShortHorizonHard, Split::LongHorizonEasy, Split::LongHorizonHard];

    /// The task numbers of each subset (paper_results.md "Splits").
    pub fn members(self) -> &'static [u32] {
        match self {
            Split::Perception => &[1, 2, 3, 4, 5, 6, 7, 8, 9, 10],
            Split::ShortHorizonEasy => &[11, 13, 14, 15, 20],
            Split::ShortHorizonHard => &[12, 16, 17, 18, 19],
            Split::LongHorizonEasy => &[23, 24, 26, 27, 29],
            Split::LongHorizonHard => &[21, 22, 25, 28, 30],
        }
    }

    /// The split of a suite task number (1–30).
    pub fn of_task(number: u32) -> Option<Split> {
        Split::ALL.into_iter().find(|s| s.members().contains(&number))
    }

    /// Long-horizon subsets are scored by stage completion, the others by full-task success.
    pub fn is_long_horizon(self) -> bool {
        matches!(self, Split::LongHorizonEasy | Split::LongHorizonHard)
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Split::Perception => "perception",
            Split::ShortHorizonEasy => "short_horizon_easy",
            Split::ShortHorizonHard => "short_horizon_hard",
            Split::LongHorizonEasy => "long_horizon_easy",
            Split::LongHorizonHard => "long_horizon_hard",
        }
    }

    /// Column heading as in the paper's Table 1.
    pub fn label(self) -> &'static str {
        match self {
            Split::Perception => "Perc. Task SR",
            Split::ShortHorizonEasy => "Short Easy SR",
            Split::ShortHorizonHard => "Short Hard SR",
            Split::LongHorizonEasy => "Long Easy SC",
            Split::LongHorizonHard => "Long Hard SC",
        }
    }
}

impl std::str::FromStr for Split {
    type Err = MetricsError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Split::ALL.into_iter().find(|x| x.as_str() == s).ok_or_else(|| MetricsError::UnknownSplit(s.to_owned()))
    }
}

/// Batch outcome of one rollout (protocol §4.8): defined once, with the records.
pub use libero_records::records::{Outcome, UnknownOutcome};

/// What the metrics need of one rollout.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Rollout {
    pub task_number: u32,
    pub split: Split,
    /// 1-based repetition (wave); rollouts are taken in this order when more than `reps` are valid.
    pub repetition: u32,
    pub outcome: Outcome,
    /// Correct target identification (perception tasks; `None` when the evaluator does not judge it).
    #[serde(default)]
    pub judgment_correct: Option<bool>,
    /// Completed required stages `c` (falls back to success when absent).
    #[serde(default)]
    pub completed_stages: Option<u32>,
    /// Required stages `K` (1 for single-stage tasks).
    pub stage_count: u32,
    /// Episode time (`result.wall_time_seconds`).
    #[serde(default)]
    pub wall_time_s: Option<f64>,
    #[serde(default)]
    pub total_tokens: Option<u64>,
    #[serde(default)]
    pub accepted_agent_steps: Option<u64>,
}

impl Rollout {
    pub fn success(&self) -> bool {
        self.outcome == Outcome::Success
    }

    /// `c / K` in [0, 1].
    pub fn stage_fraction(&self) -> f64 {
        stage_fraction(self.completed_stages, self.stage_count, self.success())
    }
}

/// `c / K` in [0, 1]; a rollout without a stage count has all stages when it succeeded and none otherwise.
pub fn stage_fraction(completed_stages: Option<u32>, stage_count: u32, success: bool) -> f64 {
    let k = stage_count.max(1);
    let c = completed_stages.unwrap_or(if success { k } else { 0 }).min(k);
    f64::from(c) / f64::from(k)
}

/// One task's numbers under the stable rule (the counts read through as `t.stable_success`, …).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskSummary {
    pub task_number: u32,
    pub split: Split,
    #[serde(flatten)]
    pub counts: StableCounts,
}

impl std::ops::Deref for TaskSummary {
    type Target = StableCounts;
    fn deref(&self) -> &StableCounts {
        &self.counts
    }
}

/// What the stable rule reads of one rollout: the paper's release rollouts ([`Rollout`]) and task-pool rollouts
/// ([`PoolRollout`]) are judged by the same rule.
pub trait Trial {
    fn repetition(&self) -> u32;
    fn outcome(&self) -> Outcome;
    /// `c / K` in [0, 1].
    fn stage_fraction(&self) -> f64;
    fn judgment_correct(&self) -> Option<bool>;
}

impl Trial for Rollout {
    fn repetition(&self) -> u32 {
        self.repetition
    }
    fn outcome(&self) -> Outcome {
        self.outcome
    }
    fn stage_fraction(&self) -> f64 {
        Rollout::stage_fraction(self)
    }
    fn judgment_correct(&self) -> Option<bool> {
        self.judgment_correct
    }
}

/// The stable rule over one task's rollouts (the task-independent part of [`TaskSummary`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StableCounts {
    pub valid_rollouts: usize,
    pub excluded_rollouts: usize,
    /// Successes among all valid rollouts.
    pub successes: usize,
    /// Successes among the first `reps` valid rollouts (the per-task "x/3" of the paper's Appendix E); `None` with
    /// fewer than `reps` valid rollouts.
    #[serde(default)]
    pub stable_successes: Option<usize>,
    /// All of the first `reps` valid rollouts succeeded; `None` with fewer than `reps` valid rollouts.
    pub stable_success: Option<bool>,
    /// Minimum of `c / K` over the first `reps` valid rollouts.
    pub stable_stage_fraction: Option<f64>,
    /// Sum of `c / K` over the first `reps` valid rollouts (the paper's long-horizon per-task table).
    pub stage_fraction_sum: Option<f64>,
    /// All of the first `reps` valid rollouts judged correctly; `None` if any judgment is unknown.
    pub stable_judgment: Option<bool>,
}

/// Applies the stable rule: the first `reps` valid rollouts (by repetition) decide; fewer than `reps` valid
/// rollouts give no stable value.
pub fn stable_counts<T: Trial>(rollouts: &[&T], reps: usize) -> StableCounts {
    let mut valid: Vec<&T> = rollouts.iter().copied().filter(|r| r.outcome().is_valid()).collect();
    valid.sort_by_key(|r| r.repetition());
    let successes = valid.iter().filter(|r| r.outcome() == Outcome::Success).count();
    let used = (valid.len() >= reps && reps > 0).then(|| &valid[..reps]);
    StableCounts {
        valid_rollouts: valid.len(),
        excluded_rollouts: rollouts.len() - valid.len(),
        successes,
        stable_successes: used.map(|u| u.iter().filter(|r| r.outcome() == Outcome::Success).count()),
        stable_success: used.map(|u| u.iter().all(|r| r.outcome() == Outcome::Success)),
        stable_stage_fraction: used.map(|u| u.iter().map(|r| r.stage_fraction()).fold(f64::INFINITY, f64::min)),
        stage_fraction_sum: used.map(|u| u.iter().map(|r| r.stage_fraction()).sum()),
        stable_judgment: used.and_then(|u| {
            u.iter().map(|r| r.judgment_correct()).collect::<Option<Vec<bool>>>().map(|j| j.iter().all(|&x| x))
        }),
    }
}

/// Applies the stable rule to one task's rollouts.
pub fn summarize_task(task_number: u32, split: Split, rollouts: &[&Rollout], reps: usize) -> TaskSummary {
    TaskSummary { task_number, split, counts: stable_counts(rollouts, reps) }
}

/// One reporting subset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SplitSummary {
    pub split: Split,
    /// Tasks of the subset in the paper's suite (5 or 10).
    pub member_count: usize,
    /// Tasks with a stable value (enough valid rollouts).
    pub tasks_scored: usize,
    /// Stable SR (short horizon, perception) or stable SC (long horizon) in [0, 1] over the scored tasks.
    pub stable: Option<f64>,
    /// Stable success over the scored tasks, also for long-horizon subsets (full-task success).
    pub stable_success: Option<f64>,
    /// SUCCESS / valid rollouts with its Wilson interval.
    pub ordinary: Proportion,
}

impl SplitSummary {
    /// Every member task has a stable value, so the number is comparable to the paper's.
    pub fn complete(&self) -> bool {
        self.tasks_scored == self.member_count
    }
}

/// The six fractions the Performance Score weighs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScoreComponents {
    pub j: f64,
    pub p: f64,
    pub m_easy: f64,
    pub m_hard: f64,
    pub l_easy: f64,
    pub l_hard: f64,
}

/// Weights of J, P, M_easy, M_hard, L_easy, L_hard (sum 100).
pub const SCORE_WEIGHTS: [f64; 6] = [5.0, 10.0, 5.0, 10.0, 20.0, 50.0];

impl ScoreComponents {
    /// The Performance Score in [0, 100].
    pub fn score(&self) -> f64 {
        let c = [self.j, self.p, self.m_easy, self.m_hard, self.l_easy, self.l_hard];
        c.iter().zip(SCORE_WEIGHTS).map(|(x, w)| x * w).sum()
    }
}

/// Mean of an easy and a hard subset (the ablation tables' "Overall": equal-size subsets, equal weight).
pub fn overall(easy: f64, hard: f64) -> f64 {
    (easy + hard) / 2.0
}

/// Everything a results table shows for one agent and condition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SuiteSummary {
    pub reps: usize,
    pub rollouts: usize,
    pub outcome_counts: BTreeMap<Outcome, usize>,
    pub tasks: Vec<TaskSummary>,
    pub splits: Vec<SplitSummary>,
    /// Stable judgment accuracy over perception tasks whose judgments are all known.
    pub judgment: Option<f64>,
    pub judgment_tasks_scored: usize,
    /// The components where every one could be computed (over the scored tasks).
    pub components: Option<ScoreComponents>,
    /// The Score only when every subset is complete (all 30 tasks with `reps` valid rollouts).
    pub score: Option<f64>,
    /// The Score with every missing component and unscored task counted as 0: a lower bound for partial suites.
    pub score_lower_bound: f64,
    /// Means over every episode (all rollouts but INTERRUPTED ones, INVALID included; see the module docs).
    pub avg_wall_time_min: Option<f64>,
    pub avg_tokens_millions: Option<f64>,
    pub avg_accepted_agent_steps: Option<f64>,
    /// Episodes the means are over, and the INVALID ones among them.
    #[serde(default)]
    pub averaged_episodes: usize,
    #[serde(default)]
    pub averaged_invalid: usize,
    /// SUCCESS / valid rollouts over everything.
    pub ordinary: Proportion,
}

impl SuiteSummary {
    pub fn split(&self, split: Split) -> Option<&SplitSummary> {
        self.splits.iter().find(|s| s.split == split)
    }
}

/// Counted in the time, token and step averages: every episode, INVALID included (the paper averages over all
/// episodes of a table); an INTERRUPTED rollout was cut off by a stopped batch and is no episode of it.
pub fn is_episode(outcome: Outcome) -> bool {
    outcome != Outcome::Interrupted
}

pub(crate) fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

pub(crate) fn rate(values: impl Iterator<Item = bool>) -> Option<f64> {
    mean(values.map(|b| if b { 1.0 } else { 0.0 }))
}

/// Summarizes rollouts of one agent under one condition (same level and demonstration condition).
pub fn summarize(rollouts: &[Rollout], reps: usize) -> SuiteSummary {
    let mut by_task: BTreeMap<(u32, Split), Vec<&Rollout>> = BTreeMap::new();
    for r in rollouts {
        by_task.entry((r.task_number, r.split)).or_default().push(r);
    }
    let tasks: Vec<TaskSummary> =
        by_task.iter().map(|(&(n, split), rs)| summarize_task(n, split, rs, reps)).collect();
    let mut outcome_counts = BTreeMap::new();
    for r in rollouts {
        *outcome_counts.entry(r.outcome).or_insert(0) += 1;
    }
    let ordinary_of = |rs: &mut dyn Iterator<Item = &Rollout>| {
        let valid: Vec<&Rollout> = rs.filter(|r| r.outcome.is_valid()).collect();
        Proportion::new(valid.iter().filter(|r| r.success()).count() as u64, valid.len() as u64)
    };
    let splits: Vec<SplitSummary> = Split::ALL
        .into_iter()
        .map(|split| {
            let ts: Vec<&TaskSummary> = tasks.iter().filter(|t| t.split == split).collect();
            let stable_success = rate(ts.iter().filter_map(|t| t.stable_success));
            let stable =
                if split.is_long_horizon() { mean(ts.iter().filter_map(|t| t.stable_stage_fraction)) } else { stable_success };
            SplitSummary {
                split,
                member_count: split.members().len(),
                tasks_scored: ts.iter().filter(|t| t.stable_success.is_some()).count(),
                stable,
                stable_success,
                ordinary: ordinary_of(&mut rollouts.iter().filter(|r| r.split == split)),
            }
        })
        .collect();
    let judgments: Vec<bool> =
        tasks.iter().filter(|t| t.split == Split::Perception).filter_map(|t| t.stable_judgment).collect();
    let judgment = rate(judgments.iter().copied());
    let get = |s: Split| splits.iter().find(|x| x.split == s).and_then(|x| x.stable);
    let components = (|| {
        Some(ScoreComponents {
            j: judgment?,
            p: get(Split::Perception)?,
            m_easy: get(Split::ShortHorizonEasy)?,
            m_hard: get(Split::ShortHorizonHard)?,
            l_easy: get(Split::LongHorizonEasy)?,
            l_hard: get(Split::LongHorizonHard)?,
        })
    })();
    let complete = splits.iter().all(SplitSummary::complete) && judgments.len() == Split::Perception.members().len();
    let score = if complete { components.map(|c| c.score()) } else { None };
    // Lower bound: sum over scored tasks only, each divided by the full member count.
    let scaled = |s: Split, f: &dyn Fn(&TaskSummary) -> Option<f64>| {
        // `+ 0.0`: an empty f64 sum is -0.0, which would print as "-0.0".
        (tasks.iter().filter(|t| t.split == s).filter_map(f).sum::<f64>() + 0.0) / s.members().len() as f64
    };
    let as_f = |b: Option<bool>| b.map(|x| if x { 1.0 } else { 0.0 });
    let lower = ScoreComponents {
        j: scaled(Split::Perception, &|t| as_f(t.stable_judgment)),
        p: scaled(Split::Perception, &|t| as_f(t.stable_success)),
        m_easy: scaled(Split::ShortHorizonEasy, &|t| as_f(t.stable_success)),
        m_hard: scaled(Split::ShortHorizonHard, &|t| as_f(t.stable_success)),
        l_easy: scaled(Split::LongHorizonEasy, &|t| t.stable_stage_fraction),
        l_hard: scaled(Split::LongHorizonHard, &|t| t.stable_stage_fraction),
    };
    let episodes = || rollouts.iter().filter(|r| is_episode(r.outcome));
    SuiteSummary {
        reps,
        rollouts: rollouts.len(),
        outcome_counts,
        judgment,
        judgment_tasks_scored: judgments.len(),
        components,
        score,
        score_lower_bound: lower.score(),
        avg_wall_time_min: mean(episodes().filter_map(|r| r.wall_time_s).map(|s| s / 60.0)),
        avg_tokens_millions: mean(episodes().filter_map(|r| r.total_tokens).map(|t| t as f64 / 1e6)),
        avg_accepted_agent_steps: mean(episodes().filter_map(|r| r.accepted_agent_steps).map(|n| n as f64)),
        averaged_episodes: episodes().count(),
        averaged_invalid: episodes().filter(|r| r.outcome == Outcome::Invalid).count(),
        ordinary: ordinary_of(&mut rollouts.iter()),
        tasks,
        splits,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rollout(task: u32, rep: u32, outcome: Outcome, c: Option<u32>, k: u32) -> Rollout {
        Rollout {
            task_number: task,
            split: Split::of_task(task).unwrap(),
            repetition: rep,
            outcome,
            judgment_correct: None,
            completed_stages: c,
            stage_count: k,
            wall_time_s: Some(600.0),
            total_tokens: Some(1_000_000),
            accepted_agent_steps: Some(10),
        }
    }

    #[test]
    fn a_task_is_stable_only_when_every_rollout_succeeds() {
        let rs = [
            rollout(11, 1, Outcome::Success, None, 1),
            rollout(11, 2, Outcome::Success, None, 1),
            rollout(11, 3, Outcome::Fail, None, 1),
            rollout(13, 1, Outcome::Success, None, 1),
            rollout(13, 2, Outcome::Success, None, 1),
            rollout(13, 3, Outcome::Success, None, 1),
        ];
        let s = summarize(&rs, 3);
        let easy = s.split(Split::ShortHorizonEasy).unwrap();
        assert_eq!((easy.tasks_scored, easy.stable), (2, Some(0.5)));
        assert_eq!((easy.ordinary.successes, easy.ordinary.trials), (5, 6));
        assert!(!easy.complete() && s.score.is_none());
        // Lower bound: one stable task of five in M_easy, weight 5 → 1.0.
        assert!((s.score_lower_bound - 1.0).abs() < 1e-12);
    }

    #[test]
    fn stage_completion_takes_the_minimum_over_rollouts() {
        let rs = [
            rollout(23, 1, Outcome::Fail, Some(8), 8),
            rollout(23, 2, Outcome::Fail, Some(4), 8),
            rollout(23, 3, Outcome::SimTimeout, Some(6), 8),
        ];
        let t = &summarize(&rs, 3).tasks[0];
        assert_eq!(t.stable_stage_fraction, Some(0.5));
        assert_eq!(t.stage_fraction_sum, Some(2.25));
        assert_eq!(t.stable_success, Some(false));
    }

    #[test]
    fn invalid_rollouts_leave_a_task_unscored_and_are_not_counted_as_failures() {
        let rs = [
            rollout(14, 1, Outcome::Success, None, 1),
            rollout(14, 2, Outcome::Invalid, None, 1),
            rollout(14, 3, Outcome::Success, None, 1),
        ];
        let s = summarize(&rs, 3);
        assert_eq!(s.tasks[0].stable_success, None);
        assert_eq!((s.tasks[0].valid_rollouts, s.tasks[0].excluded_rollouts), (2, 1));
        assert_eq!((s.ordinary.successes, s.ordinary.trials), (2, 2));
        assert_eq!(s.outcome_counts[&Outcome::Invalid], 1);
        // A re-run (repetition 4) completes the task.
        let mut more = rs.to_vec();
        more.push(rollout(14, 4, Outcome::Success, None, 1));
        assert_eq!(summarize(&more, 3).tasks[0].stable_success, Some(true));
    }

    #[test]
    fn time_and_tokens_average_every_episode_invalid_included() {
        let mut rs = vec![
            rollout(14, 1, Outcome::Success, None, 1),
            rollout(14, 2, Outcome::Invalid, None, 1),
            rollout(14, 3, Outcome::Fail, None, 1),
            rollout(14, 4, Outcome::Interrupted, None, 1),
        ];
        rs[1].wall_time_s = Some(30.0);
        rs[1].total_tokens = Some(4_000_000);
        rs[3].wall_time_s = Some(6000.0);
        let s = summarize(&rs, 3);
        // (600 + 30 + 600) / 3 s = 410 s; (1 + 4 + 1) / 3 M tokens; the INTERRUPTED rollout is no episode
        assert_eq!(s.avg_wall_time_min, Some(1230.0 / 3.0 / 60.0));
        assert_eq!(s.avg_tokens_millions, Some(2.0));
        assert_eq!((s.averaged_episodes, s.averaged_invalid), (3, 1));
        // the rates still leave INVALID out
        assert_eq!((s.ordinary.successes, s.ordinary.trials), (1, 2));
    }

    #[test]
    fn stable_successes_count_the_first_reps_valid_rollouts_only() {
        let rs: Vec<Rollout> = [Outcome::Success, Outcome::Fail, Outcome::Success, Outcome::Success]
            .into_iter()
            .enumerate()
            .map(|(i, o)| rollout(11, i as u32 + 1, o, None, 1))
            .collect();
        let t = &summarize(&rs, 3).tasks[0];
        assert_eq!((t.successes, t.stable_successes), (3, Some(2)));
        assert_eq!(summarize(&rs[..2], 3).tasks[0].stable_successes, None);
    }

    #[test]
    fn judgment_needs_every_rollout_judged() {
        let mut rs: Vec<Rollout> = (1..=3).map(|r| rollout(3, r, Outcome::Fail, None, 1)).collect();
        rs.iter_mut().for_each(|r| r.judgment_correct = Some(true));
        assert_eq!(summarize(&rs, 3).judgment, Some(1.0));
        rs[1].judgment_correct = None;
        assert_eq!(summarize(&rs, 3).judgment, None);
    }

    #[test]
    fn names_round_trip() {
        for o in Outcome::ALL {
            assert_eq!(o.as_str().parse::<Outcome>().unwrap(), o);
            assert_eq!(serde_json::to_value(o).unwrap(), o.as_str());
        }
        for s in Split::ALL {
            assert_eq!(s.as_str().parse::<Split>().unwrap(), s);
            assert_eq!(serde_json::to_value(s).unwrap(), s.as_str());
        }
        assert_eq!(Split::of_task(18), Some(Split::ShortHorizonHard));
        assert_eq!(Split::of_task(31), None);
    }
}
