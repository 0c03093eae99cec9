//! Which rollouts an experiment means (protocol §8.8, paper_results.md "Ablations"):
//!
//! | experiment | tasks | levels | demonstrations | rollouts per task |
//! |---|---|---|---|---|
//! | `main_table` | T01–T30 | 3 | none | 3 |
//! | `manip_observation` | T11–T20 (short horizon) | 1, 2 (level 3 is the main table's) | none | 3 |
//! | `context` | T21–T30 (long horizon) | 3 | video, video + trajectory (none is the main table's) | 3 |
//!
//! Seed 100 for every repetition, the task's own init state, 1800 s, 1,000,000 submissions, no resets, no
//! retries. Repetitions (waves) are labels and ordering only, never barriers. Tasks the catalog does not mark
//! implemented are left out of the schedule and named on stderr.
use anyhow::bail;
use libero_metrics::Split;
use libero_tasks::catalog::{Category, TaskEntry};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
#[value(rename_all = "snake_case")]
pub enum Experiment {
    MainTable,
    ManipObservation,
    Context,
}

/// Demonstration condition of a rollout (protocol §7.1; paper: None / Video / Video + Traj.).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Demo {
    None,
    Video,
    VideoTraj,
}

impl Demo {
    pub fn as_str(self) -> &'static str {
        match self {
            Demo::None => "none",
            Demo::Video => "video",
            Demo::VideoTraj => "video_traj",
        }
    }
}

impl Experiment {
    pub fn as_str(self) -> &'static str {
        match self {
            Experiment::MainTable => "main_table",
            Experiment::ManipObservation => "manip_observation",
            Experiment::Context => "context",
        }
    }

    fn includes(self, task: &TaskEntry) -> bool {
        match self {
            Experiment::MainTable => true,
            Experiment::ManipObservation => task.category == Category::Manipulation,
            Experiment::Context => task.category == Category::LongHorizon,
        }
    }

    pub fn levels(self) -> &'static [u8] {
        match self {
            Experiment::ManipObservation => &[1, 2],
            _ => &[3],
        }
    }

    pub fn demos(self) -> &'static [Demo] {
        match self {
            Experiment::Context => &[Demo::Video, Demo::VideoTraj],
            _ => &[Demo::None],
        }
    }
}

/// One scheduled rollout: a fresh workspace, episode and agent process.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlannedRollout {
    /// `w<rep>_t<NN>_level<L>[_<demo>]` (the original's job id plus the demonstration condition).
    pub rollout_id: String,
    pub task: String,
    pub task_number: u32,
    pub task_name: String,
    pub split: Split,
    pub stage_count: u32,
    pub repetition: u32,
    pub level: u8,
    pub demo: Demo,
}

/// The rollouts of `experiment` over `catalog` (optionally only `only` task numbers), `reps` each; and the
/// catalog tasks left out because they are not implemented in this build.
pub fn plan(
    experiment: Experiment,
    catalog: &[TaskEntry],
    only: Option<&[u32]>,
    reps: u32,
) -> anyhow::Result<(Vec<PlannedRollout>, Vec<String>)> {
    if reps == 0 {
        bail!("--reps must be at least 1");
    }
    if let Some(only) = only {
        for n in only {
            let Some(t) = catalog.iter().find(|t| t.number == *n) else { bail!("no task T{n:02} in the catalog") };
            if !experiment.includes(t) {
                bail!("{} ({:?}) is not part of the {} experiment", t.id, t.category, experiment.as_str());
            }
            if !t.implemented {
                let why = t.not_implemented_reason.as_deref().unwrap_or("no reason given");
                bail!("{} is not implemented in this build: {why}", t.id);
            }
        }
    }
    let selected: Vec<&TaskEntry> = catalog
        .iter()
        .filter(|t| experiment.includes(t) && only.is_none_or(|o| o.contains(&t.number)))
        .collect();
    let skipped = selected.iter().filter(|t| !t.implemented).map(|t| t.id.clone()).collect();
    let mut out = Vec::new();
    for rep in 1..=reps {
        for t in selected.iter().filter(|t| t.implemented) {
            for &level in experiment.levels() {
                for &demo in experiment.demos() {
                    let suffix = if demo == Demo::None { String::new() } else { format!("_{}", demo.as_str()) };
                    out.push(PlannedRollout {
                        rollout_id: format!("w{rep}_t{:02}_level{level}{suffix}", t.number),
                        task: t.id.clone(),
                        task_number: t.number,
                        task_name: t.name.clone(),
                        split: t.split,
                        stage_count: u32::try_from(t.stage_count).unwrap_or(u32::MAX),
                        repetition: rep,
                        level,
                        demo,
                    });
                }
            }
        }
    }
    Ok((out, skipped))
}

#[cfg(test)]
mod tests {
    use super::*;
    use libero_tasks::catalog::Catalog;

    /// The catalog with every task marked implemented, to count the paper's full schedules.
    fn all_implemented() -> Vec<TaskEntry> {
        let mut tasks = Catalog::discover().unwrap().tasks().to_vec();
        tasks.iter_mut().for_each(|t| t.implemented = true);
        tasks
    }

    #[test]
    fn experiments_have_the_papers_sizes() {
        let tasks = all_implemented();
        let count = |e| plan(e, &tasks, None, 3).unwrap().0.len();
        assert_eq!(count(Experiment::MainTable), 90);
        assert_eq!(count(Experiment::ManipObservation), 60);
        assert_eq!(count(Experiment::Context), 60);
        let (ctx, _) = plan(Experiment::Context, &tasks, None, 3).unwrap();
        assert!(ctx.iter().all(|r| (21..=30).contains(&r.task_number) && r.level == 3 && r.demo != Demo::None));
        let (obs, _) = plan(Experiment::ManipObservation, &tasks, None, 1).unwrap();
        assert_eq!(obs[0].rollout_id, "w1_t11_level1");
        assert_eq!(obs[1].rollout_id, "w1_t11_level2");
    }

    #[test]
    fn unimplemented_tasks_are_skipped_or_refused() {
        let catalog = Catalog::discover().unwrap();
        let tasks = catalog.tasks();
        let (rs, skipped) = plan(Experiment::MainTable, tasks, None, 1).unwrap();
        let implemented = tasks.iter().filter(|t| t.implemented).count();
        assert_eq!((rs.len(), skipped.len()), (implemented, 30 - implemented));
        if let Some(t) = tasks.iter().find(|t| !t.implemented) {
            assert!(plan(Experiment::MainTable, tasks, Some(&[t.number]), 1).is_err());
        }
        assert!(plan(Experiment::ManipObservation, tasks, Some(&[1]), 1).is_err(), "T01 is not manipulation");
    }
}
