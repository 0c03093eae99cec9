//! Figure 3, the sustained-contact ratio (SCR) of opening operations, as the paper (§5.3) computes it. For each
//! control step `t` of an operation, `l_t` is the length of the gripper–**handle** contact run containing `t` (0
//! without contact); `N_sustained = #{t : l_t ≥ 5}` and `SCR = N_sustained / N_exec × 100 %`. The evaluators record
//! each operation's contact runs (`libero_tasks::judge::mechanism`); here:
//!
//! * [`sustained_steps`] and [`sustained_contact_ratio_percent`]: the definition itself, which the evaluators use
//!   too, so the record and the report cannot disagree;
//! * [`figure3`]: over the *entered* opening operations of the stage analysis (the report decides which those are),
//!   (a) each agent's mean SCR, and (b) the local opening success (the opening completed) per SCR bin — 0,
//!   (0, 10 %], (10, 25 %], > 25 % — with 95 % Wilson intervals and Pearson's r between SCR and local success, both
//!   pooled over every agent's operations.
use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::{Proportion, mean};

/// Minimum contact run (control steps) that counts as sustained: `l_t ≥ 5`.
pub const SUSTAINED_RUN_STEPS: u64 = 5;

/// `N_sustained` of an operation whose contact runs are `runs`: every step of a run of length `r` has `l_t = r`, so the
/// steps with `l_t ≥ 5` are exactly those of the runs of 5 or more.
pub fn sustained_steps(runs: &[u64]) -> u64 {
    runs.iter().filter(|&&r| r >= SUSTAINED_RUN_STEPS).sum()
}

/// `SCR = N_sustained / N_exec × 100 %` (0 for an operation of no step).
pub fn sustained_contact_ratio_percent(runs: &[u64], exec_steps: u64) -> f64 {
    if exec_steps == 0 { 0.0 } else { 100.0 * sustained_steps(runs) as f64 / exec_steps as f64 }
}

/// One opening operation as the report read it from a rollout's record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OpeningOperation {
    /// `harness/model`.
    pub agent: String,
    /// `T21`, …
    pub task: String,
    pub episode_id: Option<String>,
    pub stage_name: Option<String>,
    /// `N_exec`, control steps.
    pub exec_steps: u64,
    /// Runs of gripper–handle contact, in control steps, in order; `None` in records from before the evaluators
    /// told handle contact from contact anywhere on the mechanism (such an operation is left out).
    pub handle_contact_runs: Option<Vec<u64>>,
    /// SCR in percent from the handle runs; `None` without them.
    pub scr_percent: Option<f64>,
    /// The operation was entered (the report's rule: its stage was reached in the stage analysis).
    pub entered: bool,
    /// Local opening success: the opening completed, whatever the rest of the task did.
    pub opened: bool,
}

impl OpeningOperation {
    /// An operation with its SCR computed from its handle runs.
    pub fn new(agent: &str, task: &str, stage_name: Option<String>, exec_steps: u64, handle_contact_runs: Option<Vec<u64>>) -> Self {
        let scr_percent = handle_contact_runs.as_deref().map(|runs| sustained_contact_ratio_percent(runs, exec_steps));
        Self {
            agent: agent.to_owned(),
            task: task.to_owned(),
            episode_id: None,
            stage_name,
            exec_steps,
            handle_contact_runs,
            scr_percent,
            entered: false,
            opened: false,
        }
    }

    /// In Figure 3: entered, and recorded with its handle runs.
    pub fn counted(&self) -> Option<f64> {
        self.scr_percent.filter(|_| self.entered)
    }
}

/// The paper's SCR bins.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScrBin {
    /// SCR = 0: no contact run of 5 steps.
    Zero,
    /// (0, 10 %]
    UpTo10,
    /// (10, 25 %]
    UpTo25,
    /// > 25 %
    Above25,
}

impl ScrBin {
    pub const ALL: [ScrBin; 4] = [ScrBin::Zero, ScrBin::UpTo10, ScrBin::UpTo25, ScrBin::Above25];

    pub fn of(scr_percent: f64) -> Self {
        if scr_percent <= 0.0 {
            ScrBin::Zero
        } else if scr_percent <= 10.0 {
            ScrBin::UpTo10
        } else if scr_percent <= 25.0 {
            ScrBin::UpTo25
        } else {
            ScrBin::Above25
        }
    }

    pub fn label(self) -> &'static str {
        match self {
            ScrBin::Zero => "0",
            ScrBin::UpTo10 => "(0,10%]",
            ScrBin::UpTo25 => "(10,25%]",
            ScrBin::Above25 => ">25%",
        }
    }
}

/// Local opening success of the operations in one bin.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScrBinSummary {
    pub bin: ScrBin,
    pub label: String,
    /// Opened operations over the bin's operations, with the 95 % Wilson interval.
    pub local_success: Proportion,
}

/// Figure 3(b): the pooled operations' SCR bins and correlation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContactSummary {
    pub operations: usize,
    pub mean_scr_percent: Option<f64>,
    /// Opened operations over all operations.
    pub local_success: Proportion,
    pub bins: Vec<ScrBinSummary>,
    /// Pearson's r between SCR and local success (0/1) over operations; `None` when either is constant.
    pub pearson_r: Option<f64>,
}

/// Figure 3(a): one agent's entered operations.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AgentScr {
    pub agent: String,
    pub operations: usize,
    pub mean_scr_percent: Option<f64>,
    pub local_success: Proportion,
}

/// Figure 3 over a set of opening operations.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Figure3 {
    /// (a) Mean SCR per agent (by agent name), over its entered operations.
    pub agents: Vec<AgentScr>,
    /// (b) Local opening success per SCR bin and Pearson's r, pooled over every agent's entered operations.
    pub pooled: ContactSummary,
    /// Operations read that were never entered (left out).
    pub not_entered: usize,
    /// Entered operations recorded without handle contact runs (left out: their ratio is not the paper's).
    pub without_handle_runs: usize,
}

/// Pearson's correlation coefficient; `None` for fewer than two pairs or a constant variable.
pub fn pearson(pairs: &[(f64, f64)]) -> Option<f64> {
    let n = pairs.len();
    if n < 2 {
        return None;
    }
    let mx = pairs.iter().map(|p| p.0).sum::<f64>() / n as f64;
    let my = pairs.iter().map(|p| p.1).sum::<f64>() / n as f64;
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for &(x, y) in pairs {
        sxy += (x - mx) * (y - my);
        sxx += (x - mx) * (x - mx);
        syy += (y - my) * (y - my);
    }
    (sxx > 0.0 && syy > 0.0).then(|| sxy / (sxx * syy).sqrt())
}

/// Opened over all of `(scr, opened)` points.
fn opened_share<'a>(points: impl Iterator<Item = &'a (f64, bool)>) -> Proportion {
    let (opened, n) = points.fold((0u64, 0u64), |(k, n), &(_, o)| (k + u64::from(o), n + 1));
    Proportion::new(opened, n)
}

/// Summarizes `(SCR %, opened)` points: every bin is listed, empty ones with no rate.
pub fn summarize_contact(points: &[(f64, bool)]) -> ContactSummary {
    let bins = ScrBin::ALL
        .into_iter()
        .map(|bin| ScrBinSummary {
            bin,
            label: bin.label().to_owned(),
            local_success: opened_share(points.iter().filter(|p| ScrBin::of(p.0) == bin)),
        })
        .collect();
    let pairs: Vec<(f64, f64)> = points.iter().map(|&(scr, opened)| (scr, if opened { 1.0 } else { 0.0 })).collect();
    ContactSummary {
        operations: points.len(),
        mean_scr_percent: mean(points.iter().map(|p| p.0)),
        local_success: opened_share(points.iter()),
        bins,
        pearson_r: pearson(&pairs),
    }
}

/// Figure 3 over `operations`: the entered ones with handle runs count; the others are counted as left out.
pub fn figure3(operations: &[OpeningOperation]) -> Figure3 {
    let mut by_agent: BTreeMap<&str, Vec<(f64, bool)>> = BTreeMap::new();
    let mut pooled = Vec::new();
    for o in operations {
        if let Some(scr) = o.counted() {
            by_agent.entry(&o.agent).or_default().push((scr, o.opened));
            pooled.push((scr, o.opened));
        }
    }
    let agents = by_agent
        .into_iter()
        .map(|(agent, points)| AgentScr {
            agent: agent.to_owned(),
            operations: points.len(),
            mean_scr_percent: mean(points.iter().map(|p| p.0)),
            local_success: opened_share(points.iter()),
        })
        .collect();
    Figure3 {
        agents,
        pooled: summarize_contact(&pooled),
        not_entered: operations.iter().filter(|o| !o.entered).count(),
        without_handle_runs: operations.iter().filter(|o| o.entered && o.scr_percent.is_none()).count(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_of_four_steps_is_not_sustained_and_one_of_five_is() {
        assert_eq!(sustained_steps(&[4, 5, 1, 12]), 17);
        assert_eq!(sustained_steps(&[4, 4, 4]), 0);
        assert!((sustained_contact_ratio_percent(&[4, 5], 20) - 25.0).abs() < 1e-12);
        assert_eq!(sustained_contact_ratio_percent(&[5], 0), 0.0);
    }

    #[test]
    fn bins_are_closed_on_the_right() {
        let got: Vec<ScrBin> = [0.0, 0.1, 10.0, 10.01, 25.0, 25.5, 100.0].into_iter().map(ScrBin::of).collect();
        use ScrBin::*;
        assert_eq!(got, [Zero, UpTo10, UpTo10, UpTo25, UpTo25, Above25, Above25]);
    }

    #[test]
    fn pearson_r_matches_a_hand_computed_point_biserial_value() {
        // x = 0, 0, 20, 40; y = 0, 1, 1, 1: mx = 15, my = 0.75; sxy = 15·0.75 + 15·(−0.25) + 5·0.25 + 25·0.25 = 15,
        // sxx = 225 + 225 + 25 + 625 = 1100, syy = 0.75 → r = 15 / √825 = 0.52223.
        let r = pearson(&[(0.0, 0.0), (0.0, 1.0), (20.0, 1.0), (40.0, 1.0)]).unwrap();
        assert!((r - 15.0 / 825f64.sqrt()).abs() < 1e-12, "{r}");
        assert_eq!(pearson(&[(1.0, 1.0), (2.0, 1.0)]), None, "constant y");
        assert_eq!(pearson(&[(1.0, 1.0)]), None);
    }

    #[test]
    fn every_bin_is_listed_with_its_wilson_interval() {
        let s = summarize_contact(&[(0.0, false), (0.0, true), (20.0, true), (40.0, true)]);
        assert_eq!(s.operations, 4);
        assert_eq!(s.mean_scr_percent, Some(15.0));
        let counts: Vec<(u64, u64)> = s.bins.iter().map(|b| (b.local_success.successes, b.local_success.trials)).collect();
        assert_eq!(counts, [(1, 2), (0, 0), (1, 1), (1, 1)]);
        assert_eq!(s.bins[1].local_success.rate, None, "an empty bin has no rate");
        assert!(s.bins[0].local_success.wilson_low.unwrap() < 0.5 && s.bins[0].local_success.wilson_high.unwrap() > 0.5);
        assert!((s.pearson_r.unwrap() - 0.52223).abs() < 1e-5);
    }

    #[test]
    fn only_entered_operations_with_handle_runs_count() {
        let op = |agent: &str, runs: Option<Vec<u64>>, entered: bool, opened: bool| OpeningOperation {
            entered,
            opened,
            ..OpeningOperation::new(agent, "T21", None, 20, runs)
        };
        let f = figure3(&[
            op("a", Some(vec![5]), true, true),
            op("a", Some(vec![]), false, false),
            op("b", Some(vec![4, 10]), true, false),
            op("b", None, true, true),
        ]);
        assert_eq!(f.agents.iter().map(|a| (a.agent.as_str(), a.operations, a.mean_scr_percent)).collect::<Vec<_>>(), [("a", 1, Some(25.0)), ("b", 1, Some(50.0))]);
        assert_eq!((f.pooled.operations, f.not_entered, f.without_handle_runs), (2, 1, 1));
    }
}
