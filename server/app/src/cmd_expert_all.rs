//! `libero-agent expert --all [--suite S] [--filter PART] [--runs N] [--no-video] [--json]`: the solvability table. Every release task
//! with a scripted expert, every stock LIBERO task (the generic expert, planned from its BDDL goal) and every pool
//! entry with a definition of its own and an expert (RoboMemArena tasks, …) runs its
//! solving expert `--runs` times in this process; one JSON line per task, then a table and the summary line
//! "N of M solved k/k". A stock task whose goal the generic expert cannot plan is listed as "no expert" with the atom
//! it could not plan.
use std::time::Instant;

use anyhow::{Context, bail};
use libero_episode::Level;
use libero_episode::physics::WorldSpec;
use libero_episode::task::resolve_task;
use libero_sim::AssetPaths;
use libero_tasks::expert;
use serde_json::{Value, json};

use crate::cmd_expert::{ExpertArgs, prepare_request, run_local};
use libero_server::default_data_dir;
use libero_server::episodes::Episodes;

/// The suite name `--suite release` selects (the 30 release tasks).
const RELEASE: &str = "release";

/// `(suite, task id)` of every task `--suite` selects: release tasks first, then stock tasks by suite in task
/// order, then the pool's own definitions with an expert, by suite.
fn selected_tasks(suites: &[String]) -> anyhow::Result<Vec<(String, String)>> {
    let stock = |s: &str| libero_tasks::STOCK_SUITES.contains(&s);
    let wanted = |s: &str| suites.is_empty() || suites.iter().any(|w| w == s || (w == "stock" && stock(s)));
    let registered = |s: &str| libero_tasks::pool::REGISTERED_SUITES.iter().any(|(r, _)| *r == s);
    for w in suites {
        if w != RELEASE && w != "stock" && !registered(w) {
            bail!(
                "unknown suite {w:?}: expected {RELEASE}, stock or one of {}",
                libero_tasks::pool::REGISTERED_SUITES.map(|(s, _)| s).join(", ")
            );
        }
    }
    let mut tasks = Vec::new();
    if wanted(RELEASE) {
        let catalog = libero_tasks::Catalog::discover()?;
        for entry in catalog.tasks() {
            if libero_tasks::expert_behaviours(&entry.id).is_some() {
                tasks.push((RELEASE.to_owned(), entry.id.clone()));
            }
        }
    }
    // the stock entries of the pool, in the original's task order
    let pool = libero_tasks::Pool::discover()?;
    for suite in libero_tasks::STOCK_SUITES.iter().filter(|s| wanted(s)) {
        tasks.extend(pool.select(suite, None).map(|e| (suite.to_string(), e.reference())));
    }
    // entries that run on a definition of their own (not a release task's, not a stock file) and have an expert
    for e in pool.entries().iter().filter(|e| !stock(&e.suite) && wanted(&e.suite)) {
        let own = e.definition.is_some() && e.status() == libero_tasks::pool::EntryStatus::Runs;
        if own && libero_tasks::expert_behaviours(&e.reference()).is_some() {
            tasks.push((e.suite.clone(), e.reference()));
        }
    }
    Ok(tasks)
}

/// Whether the task's expert can plan its goal; `Err` says which atom it could not.
fn plan(spec: &WorldSpec, task_id: &str) -> anyhow::Result<Vec<String>> {
    let scene = libero_sim::compose::compose_file(&spec.task.bddl, &spec.paths)?;
    let model = scene.compile()?;
    Ok(libero_tasks::expert_plan(task_id, &scene, &model)?)
}

/// The goal atoms a record's final state failed (or its stage names where it has no terminal checks).
fn failed_checks(record: &Value) -> Vec<String> {
    let checks = record["terminal_state_checks"].as_array().cloned().unwrap_or_default();
    let failed: Vec<String> =
        checks.iter().filter(|c| c["passed"] == false).filter_map(|c| c["name"].as_str().map(str::to_owned)).collect();
    if !failed.is_empty() || !checks.is_empty() {
        return failed;
    }
    let done = record["completed_stage_names"].as_array().map_or(0, Vec::len);
    vec![format!("{done} of {} stages", record["required_stage_count"])]
}

pub fn run_all(args: &ExpertArgs) -> anyhow::Result<()> {
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    let level = Level::from_number(args.level).with_context(|| format!("--level must be 1, 2 or 3 (got {})", args.level))?;
    let paths = AssetPaths::discover().context("assets are missing; run `python3 scripts/setup.py`")?;
    let mut tasks = selected_tasks(&args.suite)?;
    if !args.filter.is_empty() {
        tasks.retain(|(_, id)| args.filter.iter().any(|f| id.contains(f.as_str())));
    }
    if tasks.is_empty() {
        bail!("no task with an expert matches --suite {:?} --filter {:?}", args.suite, args.filter);
    }
    let episodes = Episodes::new(args.data.clone().unwrap_or_else(default_data_dir), "http://127.0.0.1:0".into())?;
    let mut rows = Vec::with_capacity(tasks.len());
    for (k, (suite, task_id)) in tasks.iter().enumerate() {
        let started = Instant::now();
        let spec = WorldSpec { task: resolve_task(task_id, &paths)?, level, seed: args.seed, init_index: 0, paths: paths.clone() };
        let mut row = json!({"task": task_id, "suite": suite, "runs": args.runs, "successes": 0, "expert": true});
        match plan(&spec, task_id) {
            Err(e) => {
                row["expert"] = json!(false);
                row["runs"] = json!(0);
                row["no_expert"] = json!(format!("{e:#}"));
            }
            Ok(steps) => {
                if !steps.is_empty() {
                    row["plan"] = json!(steps);
                }
                let request = prepare_request(args, task_id);
                let (mut successes, mut failures, mut actions) = (0u32, Vec::new(), Vec::new());
                for run_index in 1..=args.runs {
                    let progress = |line: &str| {
                        if line.starts_with("waiting") || line.starts_with("video") {
                            eprintln!("[{}/{} {task_id} run {run_index}/{}] {line}", k + 1, tasks.len(), args.runs);
                        }
                    };
                    let r = run_local(&episodes, &request, &spec, task_id, expert::SOLVE, args.max_actions, args.pace, &progress)?;
                    match r.outcome {
                        Ok(run) => {
                            let record = r.record.unwrap_or(run.replica_record);
                            actions.push(run.actions);
                            if record["success"] == true {
                                successes += 1;
                            } else {
                                failures.push(json!({"run": run_index, "episode_id": r.episode_id, "failed": failed_checks(&record)}));
                            }
                        }
                        Err(e) => failures.push(json!({"run": run_index, "episode_id": r.episode_id, "error": e.to_string()})),
                    }
                }
                row["successes"] = json!(successes);
                row["actions"] = json!(actions);
                if !failures.is_empty() {
                    row["failures"] = json!(failures);
                }
            }
        }
        row["wall_time_s"] = json!((started.elapsed().as_secs_f64() * 10.0).round() / 10.0);
        eprintln!("[{}/{}] {task_id}: {}", k + 1, tasks.len(), verdict(&row));
        println!("{row}");
        rows.push(row);
    }
    let solved = rows.iter().filter(|r| r["expert"] == true && r["successes"] == args.runs).count();
    let summary = format!("{solved} of {} solved {}/{}", rows.len(), args.runs, args.runs);
    if args.json {
        println!("{}", json!({"summary": summary, "solved": solved, "tasks": rows.len(), "runs": args.runs}));
    } else {
        print_table(&rows);
        println!("{summary}");
    }
    Ok(())
}

/// `3/3`, `1/3 failed: (on a b)`, `no expert: …`.
fn verdict(row: &Value) -> String {
    if row["expert"] == false {
        return format!("no expert: {}", row["no_expert"].as_str().unwrap_or(""));
    }
    let mut v = format!("{}/{}", row["successes"], row["runs"]);
    if let Some(f) = row["failures"].as_array().and_then(|f| f.first()) {
        let why = f["failed"].as_array().map_or_else(
            || f["error"].as_str().unwrap_or("").to_owned(),
            |c| format!("failed {}", c.iter().filter_map(Value::as_str).collect::<Vec<_>>().join(" ")),
        );
        v.push_str(&format!(" ({why})"));
    }
    v
}

fn print_table(rows: &[Value]) {
    let width = rows.iter().filter_map(|r| r["task"].as_str()).map(str::len).max().unwrap_or(4).max(4);
    println!("{:<width$}  {:>7}  {:>8}  result", "task", "solved", "wall_s");
    for r in rows {
        let solved = if r["expert"] == true { format!("{}/{}", r["successes"], r["runs"]) } else { "-".into() };
        let task = r["task"].as_str().unwrap_or("");
        let wall_s = r["wall_time_s"].as_f64().unwrap_or(0.0);
        println!("{task:<width$}  {solved:>7}  {wall_s:>8.1}  {}", verdict(r));
    }
}
