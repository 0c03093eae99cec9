//! The paper's ablation tables, built from the same [`SuiteSummary`] as Table 1 so that their level-3 and
//! no-demonstration rows are Table 1's own numbers (the paper takes them from the main-table run):
//!
//! * Table 2, observation ablation: short-horizon stable SR (T11–T20) at observation levels 1, 2 and 3;
//! * Table 3, demonstration ablation: long-horizon stable SC (T21–T30) with no demonstration, a video, and a video
//!   with its trajectory.
//!
//! Overall is the mean of the easy and hard subsets (five tasks each, equal weight), and exists only when both do.
use serde::{Deserialize, Serialize};

use crate::{Split, SuiteSummary, overall};

/// Which ablation a table shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AblationKind {
    /// Table 2: levels 1/2/3 on the short-horizon tasks.
    Observation,
    /// Table 3: none / video / video + trajectory on the long-horizon tasks.
    Demonstration,
}

impl AblationKind {
    /// The (easy, hard) subsets the table reports.
    pub fn splits(self) -> (Split, Split) {
        match self {
            AblationKind::Observation => (Split::ShortHorizonEasy, Split::ShortHorizonHard),
            AblationKind::Demonstration => (Split::LongHorizonEasy, Split::LongHorizonHard),
        }
    }

    /// The metric the table's cells hold.
    pub fn metric(self) -> &'static str {
        match self {
            AblationKind::Observation => "stable SR",
            AblationKind::Demonstration => "stable SC",
        }
    }

    pub fn title(self) -> &'static str {
        match self {
            AblationKind::Observation => "Observation ablation (Table 2; short-horizon tasks T11–T20, stable SR)",
            AblationKind::Demonstration => "Demonstration ablation (Table 3; long-horizon tasks T21–T30, stable SC)",
        }
    }
}

/// One line of an ablation table: one agent under one condition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AblationRow {
    /// `L1`/`L2`/`L3`, or `none`/`video`/`video_traj`.
    pub condition: String,
    /// Stable value of the easy subset in [0, 1] over its scored tasks.
    pub easy: Option<f64>,
    pub hard: Option<f64>,
    /// Mean of `easy` and `hard`, when both exist.
    pub overall: Option<f64>,
    pub easy_tasks_scored: usize,
    pub hard_tasks_scored: usize,
    /// Tasks per subset (5): a row with fewer scored tasks is partial.
    pub member_count: usize,
}

impl AblationRow {
    /// The row of `summary` (one agent under `condition`) for the table `kind`.
    pub fn of(kind: AblationKind, condition: impl Into<String>, summary: &SuiteSummary) -> Self {
        let (easy_split, hard_split) = kind.splits();
        let easy = summary.split(easy_split);
        let hard = summary.split(hard_split);
        let value = |s: Option<&crate::SplitSummary>| s.and_then(|s| s.stable);
        let (e, h) = (value(easy), value(hard));
        Self {
            condition: condition.into(),
            easy: e,
            hard: h,
            overall: e.zip(h).map(|(e, h)| overall(e, h)),
            easy_tasks_scored: easy.map_or(0, |s| s.tasks_scored),
            hard_tasks_scored: hard.map_or(0, |s| s.tasks_scored),
            member_count: easy_split.members().len(),
        }
    }

    /// Both subsets have every task scored, so the row compares with the paper's.
    pub fn complete(&self) -> bool {
        self.easy_tasks_scored == self.member_count && self.hard_tasks_scored == self.member_count
    }
}
