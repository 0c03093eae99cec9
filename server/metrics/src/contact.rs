//! Figure 3, the sustained-contact ratio of opening operations. For each control step `t` of an operation, `l_t`
//! is the length of the gripper–handle contact run containing `t` (0 without contact); `N_sustained = #{t : l_t ≥ 5}`
//! and `SCR = N_sustained / N_exec × 100 %`. The evaluators record it per operation; here the operations of one agent
//! are summarized: the mean SCR, the local opening success (the opening completed) per SCR bin with 95 % Wilson
//! intervals, and Pearson's r between SCR and local success over operations.
use serde::{Deserialize, Serialize};

use crate::{Proportion, mean};

/// One opening operation as its evaluator recorded it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OpeningOperation {
    /// `T21`, `libero_90/35`, …
    pub task: String,
    pub stage_name: Option<String>,
    /// Sustained-contact ratio in percent, [0, 100].
    pub scr_percent: f64,
    /// `N_exec`, control steps.
    pub exec_steps: u64,
    /// Local opening success: the opening completed, whatever the rest of the task did.
    pub opened: bool,
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

/// Figure 3's numbers for one agent.
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

/// Summarizes one agent's opening operations (every bin is listed, empty ones with no rate).
pub fn summarize_contact(operations: &[OpeningOperation]) -> ContactSummary {
    let proportion = |ops: &mut dyn Iterator<Item = &OpeningOperation>| {
        let (opened, n) = ops.fold((0u64, 0u64), |(k, n), o| (k + u64::from(o.opened), n + 1));
        Proportion::new(opened, n)
    };
    let bins = ScrBin::ALL
        .into_iter()
        .map(|bin| ScrBinSummary {
            bin,
            label: bin.label().to_owned(),
            local_success: proportion(&mut operations.iter().filter(|o| ScrBin::of(o.scr_percent) == bin)),
        })
        .collect();
    let pairs: Vec<(f64, f64)> =
        operations.iter().map(|o| (o.scr_percent, if o.opened { 1.0 } else { 0.0 })).collect();
    ContactSummary {
        operations: operations.len(),
        mean_scr_percent: mean(operations.iter().map(|o| o.scr_percent)),
        local_success: proportion(&mut operations.iter()),
        bins,
        pearson_r: pearson(&pairs),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn op(scr: f64, opened: bool) -> OpeningOperation {
        OpeningOperation { task: "T16".into(), stage_name: None, scr_percent: scr, exec_steps: 100, opened }
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
        let s = summarize_contact(&[op(0.0, false), op(0.0, true), op(20.0, true), op(40.0, true)]);
        assert_eq!(s.operations, 4);
        assert_eq!(s.mean_scr_percent, Some(15.0));
        let counts: Vec<(u64, u64)> = s.bins.iter().map(|b| (b.local_success.successes, b.local_success.trials)).collect();
        assert_eq!(counts, [(1, 2), (0, 0), (1, 1), (1, 1)]);
        assert_eq!(s.bins[1].local_success.rate, None, "an empty bin has no rate");
        assert!(s.bins[0].local_success.wilson_low.unwrap() < 0.5 && s.bins[0].local_success.wilson_high.unwrap() > 0.5);
        assert!((s.pearson_r.unwrap() - 0.52223).abs() < 1e-5);
    }
}
