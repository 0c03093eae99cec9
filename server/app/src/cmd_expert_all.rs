//! `libero-agent expert --all | --tasks SELECTION [--runs N] [--jobs N] [--no-video] [--json] [--out PATH]`:
//! the solvability table. Every release task with a scripted expert, every stock LIBERO task (the generic expert,
//! planned from its BDDL goal) and every pool entry with a definition of its own and an expert (RoboMemArena tasks,
//! …) runs its solving expert `--runs` times in this process, `--jobs` tasks at a time; one JSON line per task (in
//! task order whatever `--jobs`), then a table and the summary line "N of M solved k/k". A stock task whose goal the
//! generic expert cannot plan is listed as "no expert" with the atom it could not plan; a task that errors keeps its
//! row, with the error. Progress (done/total, failures so far, time left) goes to stderr.
//!
//! The table is written to `--out` (default `tasks/results/expert_sweep.jsonl` for `--all`, that is `--tasks all`)
//! with `<name>.meta.json` beside it (date, commit, command line, cores): the dashboard's task pages show it.
//! `--markdown` prints that file as the README's table per suite instead of running anything. `--tasks SEL --update`
//! re-runs a selection (after an expert changed) and replaces just its rows, each stamped with its own date and
//! commit, the update listed in the metadata.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use anyhow::{Context, bail};
use libero_episode::Level;
use libero_episode::physics::WorldSpec;
use libero_episode::task::resolve_task;
use libero_sim::AssetPaths;
use libero_tasks::expert;
use libero_tasks::pool::EntryStatus;
use libero_records::expert_sweep::{ExpertSweepMeta, ExpertSweepRow, META_SCHEMA, SweepFailure, SweepUpdate};
use libero_records::result::PrivateEvaluation;
use libero_tasks::selector::{Member, Selection, Term};
use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::cmd_expert::{ExpertArgs, prepare_request, run_local};
use libero_server::default_data_dir;
use libero_server::episodes::Episodes;

/// The suite label of the release tasks in a sweep's rows.
const RELEASE: &str = "release";

/// One entry a sweep runs.
#[derive(Debug, Clone)]
pub(crate) struct SweepTask {
    /// `release`, a stock suite or a pool suite.
    pub suite: String,
    /// The id the expert runs under: `T14`, `libero_90/<NAME>`, `robomemarena/<name>`.
    pub task: String,
    /// The pool address of a pool entry (`libero_90/35`): its dashboard page.
    pub entry: Option<String>,
}

/// Every task with an expert that `selection` names, in sweep order: release tasks first, then stock tasks by
/// suite in task order, then the pool's own definitions with an expert, by suite. A pool entry that runs a release
/// task's definition (its twin, `perception_v2/3` for T04) runs as that release task; a stock entry runs the generic
/// stock expert even where it is a release task's twin (`libero_90/35`, T16). A task named on its own that has no
/// expert is refused; the members of a set without one are left out. `all` is every release task and every entry.
pub(crate) fn selected_tasks(selection: &Selection) -> anyhow::Result<Vec<SweepTask>> {
    let catalog = libero_tasks::Catalog::discover()?;
    let pool = libero_tasks::Pool::discover()?;
    let has_expert = |id: &str| libero_tasks::expert_behaviours(id).is_some();
    // (bucket, suite order, place in its list): the sweep's order whatever the selection's
    let mut keyed: Vec<((usize, usize, usize), SweepTask)> = Vec::new();
    let release = |t: &libero_tasks::TaskEntry| ((0, 0, t.number as usize), SweepTask { suite: RELEASE.to_owned(), task: t.id.clone(), entry: None });
    // `all` takes every release task too: some release tasks' only pool twins are stock entries, which run the
    // generic stock expert rather than the release task's own
    let with_release: Selection;
    let selection = if selection.terms().contains(&Term::All) {
        with_release = selection.with_first(Term::Release);
        &with_release
    } else {
        selection
    };
    for (place, pick) in selection.resolve(catalog.tasks(), &pool)?.into_iter().enumerate() {
        let found = match pick.member {
            Member::Release(t) => has_expert(&t.id).then(|| release(t)),
            Member::Entry(e) if e.is_stock() => {
                let suite = libero_tasks::STOCK_SUITES.iter().position(|s| *s == e.suite).unwrap_or(0);
                Some(((1, suite, e.task_id as usize), SweepTask { suite: e.suite.clone(), task: e.reference(), entry: Some(e.id()) }))
            }
            Member::Entry(e) => match e.release_task.as_deref().and_then(|t| catalog.get(t)) {
                Some(t) if e.definition.is_none() => has_expert(&t.id).then(|| release(t)),
                _ => (e.definition.is_some() && e.status() == EntryStatus::Runs && has_expert(&e.reference()))
                    .then(|| ((2, 0, place), SweepTask { suite: e.suite.clone(), task: e.reference(), entry: Some(e.id()) })),
            },
        };
        match found {
            Some(k) if !keyed.iter().any(|(_, t)| t.task == k.1.task) => keyed.push(k),
            Some(_) => {}
            None if pick.named => bail!("{} has no scripted expert (`expert --list` lists those that do)", pick.member.id()),
            None => {}
        }
    }
    keyed.sort_by_key(|(k, _)| *k);
    Ok(keyed.into_iter().map(|(_, t)| t).collect())
}

/// Whether the task's expert can plan its goal; `Err` says which atom it could not.
fn plan(spec: &WorldSpec, task_id: &str) -> anyhow::Result<Vec<String>> {
    let scene = libero_sim::compose::compose_file(&spec.task.bddl, &spec.paths)?;
    let model = scene.compile()?;
    Ok(libero_tasks::expert_plan(task_id, &scene, &model)?)
}

/// The goal atoms a record's final state failed (or its stage names where it has no terminal checks).
fn failed_checks(record: &PrivateEvaluation) -> Vec<String> {
    let checks = record.terminal_state_checks.as_deref().unwrap_or_default();
    let failed: Vec<String> = checks.iter().filter(|c| c.passed == Some(false)).filter_map(|c| c.name.clone()).collect();
    if !failed.is_empty() || !checks.is_empty() {
        return failed;
    }
    let done = record.completed_stage_names.as_ref().map_or(0, Vec::len);
    let required = record.required_stage_count.map_or_else(|| "null".to_owned(), |n| n.to_string());
    vec![format!("{done} of {required} stages")]
}

/// The sweep file `--all` writes by default, where the dashboard reads it.
pub(crate) fn default_sweep_path() -> PathBuf {
    libero_tasks::catalog::tasks_dir().join("results").join("expert_sweep.jsonl")
}

/// `expert_sweep.jsonl` → `expert_sweep.meta.json`.
fn meta_path(out: &Path) -> PathBuf {
    let stem = out.file_stem().map_or_else(|| "expert_sweep".into(), |s| s.to_string_lossy().into_owned());
    out.with_file_name(format!("{stem}.meta.json"))
}

/// `expert_sweep.jsonl` → `expert_sweep.journal.jsonl`: the rows of a sweep in progress, one line as each task ends.
fn journal_path(out: &Path) -> PathBuf {
    let stem = out.file_stem().map_or_else(|| "expert_sweep".into(), |s| s.to_string_lossy().into_owned());
    out.with_file_name(format!("{stem}.journal.jsonl"))
}

/// The rows of a sweep as they finish, so that a stopped sweep (a killed process, a lost machine) loses only the
/// tasks it was running: its first line says what was swept, and `--resume` takes the rest only from a journal of
/// the same selection, runs, level and seed.
struct Journal {
    file: std::fs::File,
}

/// The journal's first line: `{"journal": {…}}`, what was swept.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct JournalHeader {
    journal: SweepKey,
}

/// What makes two sweeps the same one (a journal resumes only its own). Fields in key order: the line is written
/// with sorted keys, as before it was typed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct SweepKey {
    level: u8,
    runs: u32,
    seed: u64,
    selection: String,
}

impl Journal {
    /// Opens the journal at `path` for `header`'s sweep: with `resume`, its finished rows (refused when it swept
    /// something else); without, a fresh journal replacing any old one.
    fn open(path: &Path, header: &JournalHeader, resume: bool) -> anyhow::Result<(Self, Vec<ExpertSweepRow>)> {
        use std::io::Write as _;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        }
        let kept = if resume {
            let text = match std::fs::read_to_string(path) {
                Ok(text) => text,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    bail!("--resume: no journal at {} (nothing to resume)", path.display())
                }
                Err(e) => return Err(e).with_context(|| format!("cannot read the sweep journal {}", path.display())),
            };
            let mut lines = text.lines().filter(|l| !l.trim().is_empty());
            match lines.next() {
                Some(first) if serde_json::from_str::<JournalHeader>(first).ok().as_ref() == Some(header) => {
                    lines.map(|l| parse_row(path, l)).collect::<anyhow::Result<Vec<_>>>()?
                }
                Some(first) => bail!(
                    "--resume: the journal {} is of another sweep ({}), not this one ({}); run without --resume to start afresh",
                    path.display(),
                    serde_json::from_str::<JournalHeader>(first).map_or_else(|_| first.to_owned(), |h| compact(&h.journal)),
                    compact(&header.journal)
                ),
                None => Vec::new(),
            }
        } else {
            Vec::new()
        };
        let mut file = if resume && path.exists() {
            std::fs::OpenOptions::new().append(true).open(path)
        } else {
            std::fs::File::create(path)
        }
        .with_context(|| format!("cannot write the journal {}", path.display()))?;
        if !resume || kept.is_empty() && std::fs::metadata(path).map_or(0, |m| m.len()) == 0 {
            writeln!(file, "{}", compact(header)).with_context(|| format!("cannot write the journal {}", path.display()))?;
        }
        Ok((Self { file }, kept))
    }

    fn append(&mut self, row: &ExpertSweepRow) -> anyhow::Result<()> {
        use std::io::Write as _;
        writeln!(self.file, "{row}").context("cannot append to the sweep journal")?;
        self.file.sync_data().context("cannot sync the sweep journal")
    }
}

/// What the progress line needs from the tasks done so far.
#[derive(Default)]
struct Tally {
    done: usize,
    failed: usize,
    task_seconds: f64,
}

pub fn run_all(args: &ExpertArgs) -> anyhow::Result<()> {
    if args.markdown {
        let path = args.out.clone().unwrap_or_else(default_sweep_path);
        print!("{}", markdown(&read_rows(&path)?));
        return Ok(());
    }
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    if args.jobs == 0 {
        bail!("--jobs must be at least 1");
    }
    let level = Level::from_number(args.level).with_context(|| format!("--level must be 1, 2 or 3 (got {})", args.level))?;
    let paths = AssetPaths::discover().context("assets are missing; run `python3 scripts/setup.py`")?;
    let selection = args.selection()?;
    let tasks = selected_tasks(&selection)?;
    if tasks.is_empty() {
        bail!("no task with an expert in --tasks {selection}");
    }
    // a partial sweep never replaces the whole pool's table unless asked to
    let whole = selection.terms() == [Term::All];
    let out = args.out.clone().or_else(|| (whole || args.update).then(default_sweep_path));
    // an update checks the table it will change before it runs anything
    let base = match (&out, args.update) {
        (Some(out), true) => Some(SweepTable::read_for_update(out, args.runs)?),
        _ => None,
    };
    let header = JournalHeader { journal: SweepKey { level: args.level, runs: args.runs, seed: args.seed, selection: selection.to_string() } };
    let (journal, kept) = match &out {
        Some(out) => {
            let (journal, kept) = Journal::open(&journal_path(out), &header, args.resume)?;
            (Some(journal), kept)
        }
        None if args.resume => bail!("--resume needs a sweep file: --out, or --all / --update"),
        None => (None, Vec::new()),
    };
    let episodes = Episodes::new(args.data.clone().unwrap_or_else(default_data_dir), "http://127.0.0.1:0".into())?;
    let total = tasks.len();
    let mut done: Vec<Option<ExpertSweepRow>> =
        tasks.iter().map(|t| kept.iter().rev().find(|r| r.task.as_deref() == Some(t.task.as_str())).cloned()).collect();
    let resumed = done.iter().flatten().count();
    if resumed > 0 {
        eprintln!("resuming: {resumed} of {total} tasks done in the journal, {} to run", total - resumed);
    }
    let todo: Vec<usize> = (0..total).filter(|&k| done[k].is_none()).collect();
    let jobs = args.jobs.min(todo.len()).max(1);
    let started = Instant::now();
    let next = AtomicUsize::new(0);
    let journal = journal.map(Mutex::new);
    let tally = Mutex::new(Tally { done: resumed, failed: done.iter().flatten().filter(|r| !solved(r, args.runs)).count(), ..Tally::default() });
    let rows: Mutex<&mut Vec<Option<ExpertSweepRow>>> = Mutex::new(&mut done);
    let ran = AtomicUsize::new(0);
    std::thread::scope(|s| {
        for _ in 0..jobs {
            s.spawn(|| {
                loop {
                    let Some(&k) = todo.get(next.fetch_add(1, Ordering::SeqCst)) else { break };
                    let task = &tasks[k];
                    let t0 = Instant::now();
                    let run = std::panic::AssertUnwindSafe(|| sweep_task(args, &episodes, &paths, level, task));
                    let mut row = match std::panic::catch_unwind(run) {
                        Ok(Ok(row)) => row,
                        Ok(Err(e)) => error_row(args, task, format!("{e:#}")),
                        Err(panic) => error_row(args, task, format!("panicked: {}", panic_text(&*panic))),
                    };
                    let seconds = t0.elapsed().as_secs_f64();
                    row.seconds = Some(tenths(seconds));
                    if let Some(journal) = &journal {
                        row.date_utc = Some(now_utc());
                        row.commit = Some(git_commit());
                        let mut journal = journal.lock().unwrap_or_else(|e| e.into_inner());
                        if let Err(e) = journal.append(&row) {
                            eprintln!("warning: {e:#} (a --resume would run this task again)");
                        }
                    }
                    let line = {
                        let mut t = tally.lock().unwrap_or_else(|e| e.into_inner());
                        t.done += 1;
                        t.failed += usize::from(!solved(&row, args.runs));
                        t.task_seconds += seconds;
                        let n = ran.fetch_add(1, Ordering::SeqCst) + 1;
                        let left = t.task_seconds / n as f64 * (total - t.done) as f64 / jobs as f64;
                        format!(
                            "[{}/{total}] {}: {} in {seconds:.1} s; {} failed so far, {} elapsed, about {} left",
                            t.done,
                            task.task,
                            verdict(&row),
                            t.failed,
                            clock(started.elapsed().as_secs_f64()),
                            clock(left)
                        )
                    };
                    eprintln!("{line}");
                    rows.lock().unwrap_or_else(|e| e.into_inner())[k] = Some(row);
                }
            });
        }
    });
    drop(rows);
    let rows: Vec<ExpertSweepRow> = done.into_iter().flatten().collect();
    for row in &rows {
        println!("{row}");
    }
    let solved_count = rows.iter().filter(|r| solved(r, args.runs)).count();
    let summary = format!("{solved_count} of {} solved {}/{}", rows.len(), args.runs, args.runs);
    match (&out, base) {
        (Some(out), Some(base)) => {
            let whole_summary = base.update(out, &rows, args.runs, jobs, started.elapsed().as_secs_f64(), &summary)?;
            eprintln!("updated {} rows of {} and {}: {whole_summary}", rows.len(), out.display(), meta_path(out).display());
        }
        (Some(out), None) => {
            write_sweep(out, &rows, args, jobs, started.elapsed().as_secs_f64(), &summary)?;
            eprintln!("wrote {} and {}", out.display(), meta_path(out).display());
        }
        (None, _) => {}
    }
    if let Some(out) = &out {
        // the table holds every row now; a later --resume must not take this run's rows
        let _ = std::fs::remove_file(journal_path(out));
    }
    if args.json {
        println!("{}", json!({"summary": summary, "solved": solved_count, "tasks": rows.len(), "runs": args.runs}));
    } else {
        print_table(&rows);
        println!("{summary}");
    }
    Ok(())
}

/// Whether a row is an expert that solved every run.
fn solved(row: &ExpertSweepRow, runs: u32) -> bool {
    row.solved(u64::from(runs))
}

/// Seconds rounded to 0.1 s, as the sweep's files say them.
fn tenths(seconds: f64) -> f64 {
    (seconds * 10.0).round() / 10.0
}

/// Compact JSON of one of the sweep's own lines.
fn compact<T: Serialize>(line: &T) -> String {
    serde_json::to_string(line).unwrap_or_else(|_| "null".to_owned())
}

/// The row a task's sweep starts from: nothing run yet, nothing solved.
fn new_row(args: &ExpertArgs, task: &SweepTask) -> ExpertSweepRow {
    ExpertSweepRow {
        task: Some(task.task.clone()),
        suite: Some(task.suite.clone()),
        entry: task.entry.clone(),
        runs: Some(u64::from(args.runs)),
        successes: Some(0),
        expert: Some(true),
        ..ExpertSweepRow::default()
    }
}

/// The row of a task whose sweep could not run (it still counts, with the reason).
fn error_row(args: &ExpertArgs, task: &SweepTask, error: String) -> ExpertSweepRow {
    ExpertSweepRow { error: Some(error), ..new_row(args, task) }
}

fn panic_text(panic: &(dyn std::any::Any + Send)) -> String {
    panic.downcast_ref::<String>().cloned().or_else(|| panic.downcast_ref::<&str>().map(|s| (*s).to_owned())).unwrap_or_default()
}

/// `95 s`, `12 min`, `1 h 05 min`.
fn clock(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    match s {
        0..120 => format!("{s} s"),
        120..3600 => format!("{} min", (s + 30) / 60),
        _ => format!("{} h {:02} min", s / 3600, (s % 3600 + 30) / 60),
    }
}

/// Plans `task` and runs its solving expert `--runs` times: its row (a run that errors is a failure with the error).
fn sweep_task(args: &ExpertArgs, episodes: &Episodes, paths: &AssetPaths, level: Level, task: &SweepTask) -> anyhow::Result<ExpertSweepRow> {
    let task_id = task.task.as_str();
    let spec = WorldSpec { task: resolve_task(task_id, paths)?, level, seed: args.seed, init_index: 0, paths: paths.clone() };
    let mut row = new_row(args, task);
    let steps = match plan(&spec, task_id) {
        Ok(steps) => steps,
        Err(e) => {
            row.expert = Some(false);
            row.runs = Some(0);
            row.no_expert = Some(format!("{e:#}"));
            return Ok(row);
        }
    };
    if !steps.is_empty() {
        row.plan = Some(steps);
    }
    let request = prepare_request(args, task_id, expert::SOLVE);
    let (mut successes, mut failures, mut actions) = (0u32, Vec::new(), Vec::new());
    for run_index in 1..=args.runs {
        let progress = |line: &str| {
            if line.starts_with("waiting") || line.starts_with("video") {
                eprintln!("[{task_id} run {run_index}/{}] {line}", args.runs);
            }
        };
        let r = run_local(episodes, &request, &spec, task_id, expert::SOLVE, args.max_actions, args.pace, &progress)?;
        let failure = SweepFailure { run: Some(u64::from(run_index)), episode_id: Some(r.episode_id), ..SweepFailure::default() };
        match r.outcome {
            Ok(run) => {
                // the replica's record where the episode wrote none; a record that is no object reads as no success
                let record = PrivateEvaluation::from_value(r.record.unwrap_or(run.replica_record)).unwrap_or_default();
                actions.push(run.actions);
                if record.success == Some(true) {
                    successes += 1;
                } else {
                    failures.push(SweepFailure { failed: Some(failed_checks(&record)), ..failure });
                }
            }
            Err(e) => failures.push(SweepFailure { error: Some(e.to_string()), ..failure }),
        }
    }
    row.successes = Some(u64::from(successes));
    row.actions = Some(actions);
    if !failures.is_empty() {
        row.failures = Some(failures);
    }
    Ok(row)
}

/// `git rev-parse --short HEAD` of the working directory, or `unknown`.
fn git_commit() -> String {
    std::process::Command::new("git")
        .args(["rev-parse", "--short", "HEAD"])
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_owned())
        .filter(|c| !c.is_empty())
        .unwrap_or_else(|| "unknown".into())
}

/// Now, as the sweep files say it: `2026-11-28T04:09:45Z`.
fn now_utc() -> String {
    format!("{}Z", libero_records::json::utc_now_iso().chars().take(19).collect::<String>())
}

/// Writes `text` to a file beside `path` and renames it over `path`, so a reader (the dashboard) never sees half a
/// table and a failed write leaves the old one.
fn replace_file(path: &Path, text: &str) -> anyhow::Result<()> {
    let tmp = path.with_extension("partial");
    std::fs::write(&tmp, text).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("cannot replace {}", path.display()))
}

/// The solved summary of a whole table: "N of M solved k/k".
fn table_summary(rows: &[ExpertSweepRow], runs: u32) -> String {
    let entries: Vec<&ExpertSweepRow> = rows.iter().filter(|r| r.is_entry()).collect();
    let solved_count = entries.iter().filter(|r| solved(r, runs)).count();
    format!("{solved_count} of {} solved {runs}/{runs}", entries.len())
}

/// A sweep file and its metadata, read to be updated (`expert --tasks … --update`).
struct SweepTable {
    rows: Vec<ExpertSweepRow>,
    meta: ExpertSweepMeta,
}

impl SweepTable {
    /// The table at `out`; refused when it is missing, unreadable, or was run with another `--runs` (its rows would
    /// not be comparable).
    fn read_for_update(out: &Path, runs: u32) -> anyhow::Result<Self> {
        let rows = read_rows(out).context("--update changes an existing sweep table; run the whole sweep first")?;
        let meta_file = meta_path(out);
        let text = std::fs::read_to_string(&meta_file).with_context(|| format!("cannot read {} to update it", meta_file.display()))?;
        let meta: ExpertSweepMeta =
            serde_json::from_str(&text).with_context(|| format!("{} is not a JSON object", meta_file.display()))?;
        match meta.runs {
            Some(n) if n == u64::from(runs) => Ok(Self { rows, meta }),
            Some(n) => bail!("{} was run with --runs {n}; an update must use the same (got --runs {runs})", out.display()),
            None => bail!("{} says no `runs`; cannot tell whether an update's rows compare", meta_file.display()),
        }
    }

    /// Replaces the rows of the tasks in `fresh` (appending any the table lacked), stamps each with `date_utc` and
    /// `commit`, lists the update in the metadata with the whole table's new summary, and writes both files.
    fn update(mut self, out: &Path, fresh: &[ExpertSweepRow], runs: u32, jobs: usize, seconds: f64, summary: &str) -> anyhow::Result<String> {
        let (date, commit) = (now_utc(), git_commit());
        for row in fresh {
            let row = ExpertSweepRow { date_utc: Some(date.clone()), commit: Some(commit.clone()), ..row.clone() };
            match self.rows.iter_mut().find(|r| r.task == row.task) {
                Some(old) => *old = row,
                None => self.rows.push(row),
            }
        }
        let whole = table_summary(&self.rows, runs);
        let update = SweepUpdate {
            date_utc: Some(date),
            commit: Some(commit),
            command: Some(std::env::args().collect::<Vec<_>>().join(" ")),
            jobs: Some(jobs as u64),
            tasks: Some(fresh.len() as u64),
            summary: Some(summary.to_owned()),
            seconds: Some(tenths(seconds)),
            ..SweepUpdate::default()
        };
        self.meta.updates.get_or_insert_with(Vec::new).push(update);
        self.meta.tasks = Some(self.rows.len() as u64);
        self.meta.summary = Some(whole.clone());
        replace_file(out, &rows_text(&self.rows))?;
        replace_file(&meta_path(out), &format!("{:#}\n", self.meta.to_value()))?;
        Ok(whole)
    }
}

/// Writes the rows (one JSON line each, in task order) and the metadata beside them.
fn write_sweep(out: &Path, rows: &[ExpertSweepRow], args: &ExpertArgs, jobs: usize, seconds: f64, summary: &str) -> anyhow::Result<()> {
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    replace_file(out, &rows_text(rows))?;
    let meta = ExpertSweepMeta {
        schema_version: Some(META_SCHEMA.to_owned()),
        date_utc: Some(now_utc()),
        commit: Some(git_commit()),
        command: Some(std::env::args().collect::<Vec<_>>().join(" ")),
        cores: Some(std::thread::available_parallelism().map_or(1, |n| n.get()) as u64),
        jobs: Some(jobs as u64),
        runs: Some(u64::from(args.runs)),
        tasks: Some(rows.len() as u64),
        summary: Some(summary.to_owned()),
        seconds: Some(tenths(seconds)),
        ..ExpertSweepMeta::default()
    };
    replace_file(&meta_path(out), &format!("{:#}\n", meta.to_value()))
}

/// The table's text: one compact line per row (keys sorted), in order.
fn rows_text(rows: &[ExpertSweepRow]) -> String {
    rows.iter().map(|r| format!("{r}\n")).collect()
}

/// One line of a sweep file or journal.
fn parse_row(path: &Path, line: &str) -> anyhow::Result<ExpertSweepRow> {
    serde_json::from_str(line).with_context(|| format!("{}: not a JSON row: {line}", path.display()))
}

/// The rows of a sweep file.
fn read_rows(path: &Path) -> anyhow::Result<Vec<ExpertSweepRow>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read the sweep file {}", path.display()))?;
    text.lines().filter(|l| !l.trim().is_empty()).map(|l| parse_row(path, l)).collect()
}

/// The README's pool table: per suite, its entries, how many have an expert, and how many it solved every run.
fn markdown(rows: &[ExpertSweepRow]) -> String {
    let mut suites: BTreeMap<String, (usize, usize, usize)> = BTreeMap::new();
    let mut order = Vec::new();
    // summary lines (older tables end with one) are not entries
    for r in rows.iter().filter(|r| r.is_entry()) {
        let suite = r.suite.clone().unwrap_or_else(|| "?".to_owned());
        if !suites.contains_key(&suite) {
            order.push(suite.clone());
        }
        let e = suites.entry(suite).or_default();
        e.0 += 1;
        e.1 += usize::from(r.has_working_expert());
        e.2 += usize::from(r.solved_every_run());
    }
    let runs: std::collections::BTreeSet<u64> = rows.iter().filter_map(|r| r.runs).filter(|n| *n > 0).collect();
    let solved = match runs.iter().collect::<Vec<_>>()[..] {
        [n] => format!("solved {n}/{n}"),
        _ => "solved every run".to_owned(),
    };
    let mut text = format!("| suite | entries | with expert | {solved} |\n|---|---|---|---|\n");
    let mut all = (0, 0, 0);
    for suite in &order {
        let (n, e, s) = suites[suite];
        text.push_str(&format!("| {suite} | {n} | {e} | {s} |\n"));
        all = (all.0 + n, all.1 + e, all.2 + s);
    }
    text.push_str(&format!("| **all** | **{}** | **{}** | **{}** |\n", all.0, all.1, all.2));
    text
}

/// `3/3`, `1/3 failed: (on a b)`, `no expert: …`.
fn verdict(row: &ExpertSweepRow) -> String {
    if row.expert == Some(false) {
        return format!("no expert: {}", row.no_expert.as_deref().unwrap_or(""));
    }
    if let Some(e) = &row.error {
        return format!("error: {e}");
    }
    let mut v = solved_of(row);
    if let Some(f) = row.failures.as_ref().and_then(|f| f.first()) {
        let why = f.failed.as_ref().map_or_else(|| f.error.clone().unwrap_or_default(), |c| format!("failed {}", c.join(" ")));
        v.push_str(&format!(" ({why})"));
    }
    v
}

/// `2/3`: the row's successes of its runs (`null` for a count it lacks, as the untyped table printed it).
fn solved_of(row: &ExpertSweepRow) -> String {
    let n = |c: Option<u64>| c.map_or_else(|| "null".to_owned(), |c| c.to_string());
    format!("{}/{}", n(row.successes), n(row.runs))
}

fn print_table(rows: &[ExpertSweepRow]) {
    let width = rows.iter().filter_map(|r| r.task.as_deref()).map(str::len).max().unwrap_or(4).max(4);
    println!("{:<width$}  {:>7}  {:>8}  result", "task", "solved", "wall_s");
    for r in rows {
        let solved = if r.expert == Some(true) { solved_of(r) } else { "-".into() };
        let task = r.task.as_deref().unwrap_or("");
        let wall_s = r.seconds.unwrap_or(0.0);
        println!("{task:<width$}  {solved:>7}  {wall_s:>8.1}  {}", verdict(r));
    }
}

/// One line of `expert --list`; fields in key order, as the line was written before it was typed.
#[derive(Serialize)]
struct ListLine<'a> {
    /// `solve` and `idle` first, then the task's own.
    behaviours: Vec<&'a str>,
    /// The pool address (absent for a release task).
    #[serde(skip_serializing_if = "Option::is_none")]
    entry: Option<&'a str>,
    suite: &'a str,
    task: &'a str,
}

/// Every entry with an expert and its behaviours, one JSON line each: the release tasks first, then the stock
/// LIBERO tasks and the pool's own definitions, in the order `expert --all` runs them.
pub fn list() -> anyhow::Result<()> {
    for t in selected_tasks(&Selection::all())? {
        if let Some(b) = libero_tasks::expert_behaviours(&t.task) {
            let all: Vec<&str> = [expert::SOLVE, libero_episode::expert_run::IDLE].into_iter().chain(b.iter().copied()).collect();
            let line = ListLine { behaviours: all, entry: t.entry.as_deref(), suite: &t.suite, task: &t.task };
            println!("{}", compact(&line));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The journal's header and `--list`'s lines are what the untyped writer wrote (sorted keys, `entry` only for a
    /// pool entry), so a journal left by an older build still resumes.
    #[test]
    fn the_journal_header_and_list_lines_keep_their_wire_format() {
        let header = JournalHeader { journal: SweepKey { level: 3, runs: 3, seed: 7, selection: "T01,T02".into() } };
        let old = json!({"journal": {"selection": "T01,T02", "runs": 3, "level": 3, "seed": 7}});
        assert_eq!(compact(&header), old.to_string());
        assert_eq!(serde_json::from_str::<JournalHeader>(&old.to_string()).unwrap(), header);
        let line = ListLine { behaviours: vec!["solve", "idle"], entry: None, suite: "release", task: "T01" };
        assert_eq!(compact(&line), json!({"task": "T01", "suite": "release", "behaviours": ["solve", "idle"]}).to_string());
        let line = ListLine { entry: Some("libero_90/1"), ..line };
        assert_eq!(
            compact(&line),
            json!({"task": "T01", "suite": "release", "behaviours": ["solve", "idle"], "entry": "libero_90/1"}).to_string()
        );
    }

    /// A failed run names the goal atoms its final state failed, or, without terminal checks, the stages it reached.
    #[test]
    fn a_failed_run_names_its_failed_atoms_or_the_stages_it_reached() {
        let record = |v| PrivateEvaluation::from_value(v).unwrap();
        let checks = json!({"terminal_state_checks": [{"name": "(on a b)", "passed": false}, {"name": "(open c)", "passed": true}]});
        assert_eq!(failed_checks(&record(checks)), ["(on a b)"]);
        assert_eq!(failed_checks(&record(json!({"completed_stage_names": ["grasp"], "required_stage_count": 3}))), ["1 of 3 stages"]);
        assert_eq!(failed_checks(&record(json!({}))), ["0 of null stages"], "as the untyped reader printed a missing count");
    }

    /// The verdict column and the README's table read typed rows as they read the untyped ones.
    #[test]
    fn verdicts_and_the_markdown_table_read_every_row_shape() {
        let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/expert_sweep/expert_sweep.jsonl")).unwrap();
        let rows: Vec<ExpertSweepRow> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        let verdicts: Vec<String> = rows.iter().map(verdict).collect();
        assert_eq!(
            verdicts[..5],
            [
                "3/3".to_owned(),
                "0/1 (failed (in yellow_book_1 wooden_two_layer_shelf_1_bottom_region))".to_owned(),
                "1/2 (episode timed out)".to_owned(),
                "no expert: cannot plan (open microwave_1)".to_owned(),
                "error: panicked: boom".to_owned(),
            ]
        );
        let table = markdown(&rows);
        assert!(table.starts_with("| suite | entries | with expert | solved every run |"), "runs 3, 1 and 2: {table}");
        assert!(table.contains("| release | 3 | 2 | 1 |") && table.contains("| libero_90 | 2 | 1 | 0 |"), "{table}");
        assert!(table.contains("| long_horizon_v2 | 1 | 1 | 1 |") && table.contains("| **all** | **6** | **4** | **2** |"), "{table}");
        assert_eq!(table_summary(&rows, 3), "2 of 6 solved 3/3", "the summary line is no entry");
    }
}
