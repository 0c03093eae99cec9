//! Which rollouts an experiment means (protocol §8.8, paper_results.md "Ablations"):
//!
//! | experiment | tasks | levels | demonstrations | rollouts per task |
//! |---|---|---|---|---|
//! | `main_table` | T01–T30 | 3 | none | 3 |
//! | `manip_observation` | T11–T20 (short horizon) | 1, 2 (level 3 is the main table's) | none | 3 |
//! | `context` | T21–T30 (long horizon) | 3 | video, video + trajectory (none is the main table's) | 3 |
//! | `pool` | any subset of the task pool (`--tasks suite:robomemarena,T11,libero_90/35`; default every entry that runs) | 3 | none | 3 |
//!
//! Pool rollouts carry their suite and are reported per suite, never inside the paper's 30-task Score.
//!
//! Seed 100 for every repetition, the task's own init state, 1800 s, 1,000,000 submissions, no resets, no
//! retries. Repetitions (waves) are labels and ordering only, never barriers. Tasks the catalog does not mark
//! implemented are left out of the schedule and named on stderr.
use anyhow::bail;
use libero_metrics::Split;
use libero_report::batch::Demo;
use libero_tasks::catalog::{Category, TaskEntry};
use libero_tasks::pool::Pool;
use libero_tasks::selector::{Member, Selection};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
#[value(rename_all = "snake_case")]
pub enum Experiment {
    MainTable,
    ManipObservation,
    Context,
    Pool,
}

impl Experiment {
    pub fn as_str(self) -> &'static str {
        match self {
            Experiment::MainTable => "main_table",
            Experiment::ManipObservation => "manip_observation",
            Experiment::Context => "context",
            Experiment::Pool => "pool",
        }
    }

    fn includes(self, task: &TaskEntry) -> bool {
        match self {
            Experiment::MainTable | Experiment::Pool => true,
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
    /// The paper's split; `None` for a pool task that is not a release task.
    pub split: Option<Split>,
    /// The pool suite of a `pool` rollout (`release` for a T-id); `None` in the paper's experiments.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub suite: Option<String>,
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
    if experiment == Experiment::Pool {
        bail!("the pool experiment is planned by plan_pool");
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
                        split: Some(t.split),
                        suite: None,
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

/// The suite label of a release task scheduled in a pool batch.
pub const RELEASE_SUITE: &str = "release";

/// One selected pool task: the address the episode is prepared with and what the record carries.
struct PoolPick {
    address: String,
    rollout_key: String,
    name: String,
    suite: String,
    task_number: u32,
    split: Option<Split>,
    stage_count: usize,
}

fn release_pick(t: &TaskEntry) -> PoolPick {
    PoolPick {
        address: t.id.clone(),
        rollout_key: format!("t{:02}", t.number),
        name: t.name.clone(),
        suite: RELEASE_SUITE.into(),
        task_number: t.number,
        split: Some(t.split),
        stage_count: t.stage_count,
    }
}

/// The rollouts of `run --experiment pool`: `selectors` are a task selection (`libero_tasks::selector`: `all`,
/// `release`, `stock`, a suite, `group:G`, `T11`, `libero_90/35`, `libero_90/<name>`, `match:TEXT`; the old
/// `suite:S` spelling too); none means `all`, every registered entry. An entry named on its own that does not run is
/// refused with its reason; one inside a set is left out and returned in the second list. The same task named twice
/// runs once.
pub fn plan_pool(
    pool: &Pool,
    catalog: &[TaskEntry],
    selectors: &[String],
    reps: u32,
) -> anyhow::Result<(Vec<PlannedRollout>, Vec<String>)> {
    if reps == 0 {
        bail!("--reps must be at least 1");
    }
    let selection = if selectors.is_empty() { Selection::all() } else { Selection::from_parts(selectors)? };
    let mut picks: Vec<PoolPick> = Vec::new();
    let mut skipped: Vec<String> = Vec::new();
    let pool_pick = |e: &libero_tasks::pool::PoolEntry| PoolPick {
        address: e.id(),
        rollout_key: format!("{}_{:03}", e.suite, e.task_id),
        name: e.name.clone(),
        suite: e.suite.clone(),
        task_number: e.release_task.as_deref().and_then(|t| t.trim_start_matches('T').parse().ok()).unwrap_or(0),
        split: None,
        stage_count: e.stage_count,
    };
    for pick in selection.resolve(catalog, pool)? {
        match (pick.member, pick.member.why_not()) {
            (Member::Release(t), None) => picks.push(release_pick(t)),
            (Member::Entry(e), None) => picks.push(pool_pick(e)),
            (m, Some(why)) if pick.named => match m {
                Member::Entry(e) => bail!("{} ({}) {why}", e.id(), e.name),
                Member::Release(t) => bail!("{} is {why}", t.id),
            },
            (m, Some(_)) => skipped.push(m.id()),
        }
    }
    skipped.retain(|s| !picks.iter().any(|p| &p.address == s));
    skipped.dedup();
    let mut out = Vec::new();
    for rep in 1..=reps {
        for p in &picks {
            out.push(PlannedRollout {
                rollout_id: format!("w{rep}_{}_level3", p.rollout_key),
                task: p.address.clone(),
                task_number: p.task_number,
                task_name: p.name.clone(),
                split: p.split,
                suite: Some(p.suite.clone()),
                stage_count: u32::try_from(p.stage_count).unwrap_or(u32::MAX),
                repetition: rep,
                level: 3,
                demo: Demo::None,
            });
        }
    }
    Ok((out, skipped))
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    use super::*;
    use libero_tasks::catalog::Catalog;
    use libero_tasks::pool::EntryStatus;

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

    #[test]
    fn a_pool_plan_mixes_suites_release_ids_and_addresses_once_each() {
        let catalog = Catalog::discover().unwrap();
        let pool = Pool::discover().unwrap();
        let sel = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let (rs, skipped) =
            plan_pool(&pool, catalog.tasks(), &sel(&["suite:libero_object", "T11", "libero_90/35", "libero_object/3"]), 2).unwrap();
        assert_eq!(rs.len(), 2 * 12, "10 libero_object tasks, T11 and libero_90/35; libero_object/3 only once");
        assert!(skipped.is_empty());
        let first = &rs[0];
        assert_eq!((first.rollout_id.as_str(), first.task.as_str(), first.suite.as_deref()), ("w1_libero_object_000_level3", "libero_object/0", Some("libero_object")));
        let t11 = rs.iter().find(|r| r.task == "T11").unwrap();
        assert_eq!((t11.rollout_id.as_str(), t11.suite.as_deref(), t11.task_number), ("w1_t11_level3", Some(RELEASE_SUITE), 11));
        let l90 = rs.iter().find(|r| r.task == "libero_90/35").unwrap();
        assert_eq!((l90.task_number, l90.split, l90.level, l90.demo), (16, None, 3, Demo::None), "libero_90/35 is T16's task");
        assert_eq!(rs.iter().filter(|r| r.repetition == 2).count(), 12);
        let ids: BTreeSet<&str> = rs.iter().map(|r| r.rollout_id.as_str()).collect();
        assert_eq!(ids.len(), rs.len(), "rollout ids are unique");

        // A suite leaves out what does not run and says so; naming such an entry alone is refused with its reason.
        let (rma, skipped) = plan_pool(&pool, catalog.tasks(), &sel(&["suite:robomemarena"]), 1).unwrap();
        let runs = pool.select("robomemarena", None).filter(|e| e.status() == EntryStatus::Runs).count();
        assert_eq!((rma.len(), rma.len() + skipped.len()), (runs, 26));
        if let Some(e) = pool.select("robomemarena", None).find(|e| e.status() == EntryStatus::NotImplemented) {
            let err = plan_pool(&pool, catalog.tasks(), &[e.id()], 1).unwrap_err().to_string();
            assert!(err.contains("not implemented in this build"), "{err}");
        }
        let banana = pool.entries().iter().find(|e| e.status() == EntryStatus::Excluded).unwrap();
        let err = plan_pool(&pool, catalog.tasks(), &[banana.id()], 1).unwrap_err().to_string();
        assert!(err.contains("excluded"), "{err}");
        for bad in ["suite:nope", "group:medium", "libero_90/999", "T31"] {
            assert!(plan_pool(&pool, catalog.tasks(), &sel(&[bad]), 1).is_err(), "{bad} is refused");
        }
        // The default is every entry that runs.
        let (every, _) = plan_pool(&pool, catalog.tasks(), &[], 1).unwrap();
        assert_eq!(every.len(), pool.entries().iter().filter(|e| e.status() == EntryStatus::Runs).count());
    }
}
