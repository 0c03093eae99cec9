//! The Results page, `/results` (`web/templates/results.html`), and `/api/results`: the paper's tables over the
//! batch directories `libero-agent run` writes. The server finds batches under `<data>/batches/` and under every
//! `serve --batches DIR` (a batch directory itself or a folder of them); each is read afresh per request, so a
//! running batch's progress shows on refresh. Numbers come from [`report_json`] (the same code as `libero-agent
//! report --format json`): Table 1, progress and per-task cells one batch at a time with the batch's own `--reps`
//! unless `?reps=N`; Tables 2–4, Figure 3 (SVG drawn here, on the server) and Appendix E across the selected
//! batches of each agent, as `report` merges them, so the level-3 and no-demonstration rows come from the agent's
//! main-table batch.
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use askama::Template;
use axum::extract::{Path as UrlPath, RawQuery, State};
use axum::http::header;
use axum::response::IntoResponse;
use libero_records::batch_doc::ToolboxDoc;
use libero_metrics::{PAPER_REPS, Split, TaskFacts};
use libero_tasks::catalog::task_facts;
use libero_server::{ApiError, ApiResult, App, AppState};
use serde_json::{Value, json};

use libero_report::batch::{LoadedBatch, RolloutRecord, load_batch};
use libero_report::display::DisplayTable;
use libero_report::tables::{TableChoice, display_tables, paper_tables};
use libero_report::tokens::{self, RolloutTokens, TokenSummary};
use libero_report::versions::HarnessVersions;
use libero_report::{
    Row, coverage, default_reps, pct, pool_rows, report_json, row_records, row_versions, rows, suite_records, svg, time_text, toolbox_text,
    wilson,
};

use crate::common::page;

/// Batch and rollout names as the runner makes them (directory names): letters, digits, `-`, `_`, `.`, not
/// starting with a dot. Anything else never reaches the filesystem.
pub fn plain_name(s: &str) -> bool {
    !s.is_empty() && s.len() <= 160 && !s.starts_with('.') && s.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
}

/// The rollout logs page of `r` in batch `b` (`batch_logs`), when the batch's rollout directories are on this machine.
pub fn logs_href(b: &LoadedBatch, r: &RolloutRecord) -> String {
    let name = b.name();
    if plain_name(&name) && plain_name(&r.rollout_id) {
        format!("/results/logs/{}/{}", percent_encode(&name), percent_encode(&r.rollout_id))
    } else {
        String::new()
    }
}

/// Where the server looks for batches: `<data>/batches/` first, then the `--batches` directories.
pub fn batch_roots(data: &Path, extra: &[PathBuf]) -> Vec<PathBuf> {
    std::iter::once(data.join("batches")).chain(extra.iter().cloned()).collect()
}

/// Every batch directory under `roots` as (name, dir), sorted by name; a name seen twice keeps the first.
pub fn discover(roots: &[PathBuf]) -> Vec<(String, PathBuf)> {
    let mut found: Vec<(String, PathBuf)> = Vec::new();
    let mut names = BTreeSet::new();
    for root in roots {
        let dirs: Vec<PathBuf> = if root.join("batch.json").is_file() {
            vec![root.clone()]
        } else {
            let mut ds: Vec<PathBuf> = std::fs::read_dir(root)
                .map(|rd| rd.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.join("batch.json").is_file()).collect())
                .unwrap_or_default();
            ds.sort();
            ds
        };
        for d in dirs {
            let name = d.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            if !name.is_empty() && names.insert(name.clone()) {
                found.push((name, d));
            }
        }
    }
    found.sort();
    found
}

/// What a request selected: batch names (none: all) and an optional stable-rule repetition count.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct Selection {
    pub batches: Vec<String>,
    pub reps: Option<usize>,
}

fn percent_decode(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = bytes.get(i + 1..i + 3).and_then(|h| std::str::from_utf8(h).ok()).and_then(|h| u8::from_str_radix(h, 16).ok());
        match (bytes[i], hex) {
            (b'+', _) => out.push(b' '),
            (b'%', Some(b)) => {
                out.push(b);
                i += 2;
            }
            (b, _) => out.push(b),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

impl Selection {
    /// `batch=A&batch=B&reps=3` (repeated keys, which axum's `Query` cannot collect). A `reps` that is no whole
    /// number from 1 to [`MAX_REPS`] is an error the page shows, never a silent default; an empty one means the
    /// batch's own.
    pub fn parse(query: Option<&str>) -> Result<Self, String> {
        let mut s = Self::default();
        for pair in query.unwrap_or("").split('&').filter(|p| !p.is_empty()) {
            let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
            let v = percent_decode(v);
            match k {
                "batch" if !v.trim().is_empty() && !s.batches.contains(&v) => s.batches.push(v),
                "reps" if v.trim().is_empty() => s.reps = None,
                "reps" => match v.trim().parse::<usize>() {
                    Ok(n) if (1..=MAX_REPS).contains(&n) => s.reps = Some(n),
                    _ => return Err(format!("reps must be a whole number from 1 to {MAX_REPS} (or empty for each batch's own), not {v:?}")),
                },
                _ => {}
            }
        }
        Ok(s)
    }

    /// The query that selects the same (`batch=…&reps=…`, percent-encoded), for links and downloads.
    pub fn query(&self) -> String {
        let mut parts: Vec<String> = self.batches.iter().map(|b| format!("batch={}", percent_encode(b))).collect();
        if let Some(n) = self.reps {
            parts.push(format!("reps={n}"));
        }
        parts.join("&")
    }
}

/// Percent-encodes everything but unreserved characters (RFC 3986).
pub fn percent_encode(s: &str) -> String {
    s.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => (b as char).to_string(),
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// Largest `?reps=` the Results page accepts (the paper uses 3).
const MAX_REPS: usize = 100;

/// The rule's repetition count for `b`: the request's, else the batch's `--reps` (as `report` defaults), else the
/// paper's 3.
fn reps_of(b: &LoadedBatch, sel: &Selection) -> usize {
    sel.reps.unwrap_or_else(|| default_reps(std::slice::from_ref(b)))
}

/// A selected batch: read from its directory, or one only the store holds (`run --store`), to be read from there.
pub enum Selected {
    /// Boxed: a loaded batch's typed document is large beside a name.
    Loaded(Box<LoadedBatch>),
    InStore(String),
}

/// The selected batches (all known ones when none is named), in name order: batch directories under `roots`, and
/// the batches only the store holds (`stored`, by name; a directory of the same name wins). An unknown name is an
/// error naming the known ones.
pub fn load_selected(roots: &[PathBuf], stored: &[String], sel: &Selection) -> Result<(Vec<String>, Vec<Selected>), String> {
    let mut all: Vec<(String, Option<PathBuf>)> = discover(roots).into_iter().map(|(n, d)| (n, Some(d))).collect();
    for name in stored {
        if !all.iter().any(|(n, _)| n == name) {
            all.push((name.clone(), None));
        }
    }
    all.sort();
    let names: Vec<String> = all.iter().map(|(n, _)| n.clone()).collect();
    let wanted: Vec<&(String, Option<PathBuf>)> = if sel.batches.is_empty() {
        all.iter().collect()
    } else {
        let mut w = Vec::new();
        for name in &sel.batches {
            match all.iter().find(|(n, _)| n == name) {
                Some(x) => w.push(x),
                None => return Err(format!("no batch {name:?} (known: {})", names.join(", "))),
            }
        }
        w
    };
    let mut selected = Vec::new();
    for (name, dir) in wanted {
        selected.push(match dir {
            Some(dir) => Selected::Loaded(Box::new(load_batch(dir).map_err(|e| format!("{e:#}"))?)),
            None => Selected::InStore(name.clone()),
        });
    }
    Ok((names, selected))
}

fn episode_json(b: &LoadedBatch, r: &RolloutRecord) -> Value {
    json!({
        "rollout_id": r.rollout_id, "task": r.task, "task_number": r.task_number, "split": r.split, "suite": r.suite,
        "repetition": r.repetition, "level": r.level, "demo": r.demo, "outcome": r.outcome,
        "completed_stages": r.completed_stages, "stage_count": r.stage_count, "episode_id": r.episode_id,
        "review": r.episode_id.as_ref().map(|id| format!("/episodes/{id}/review")),
        "logs": Some(logs_href(b, r)).filter(|h| !h.is_empty()),
        "wall_time_s": r.wall_time_s, "judgment_correct": r.judgment_correct,
        "reason": (!r.outcome.is_valid()).then(|| r.reason()).flatten(), "worker": r.worker,
        "tokens": RolloutTokens::of(r),
    })
}

/// The stable rule's repetition count across the selection: the request's, else the first batch's `--reps`.
fn selection_reps(batches: &[LoadedBatch], sel: &Selection) -> usize {
    batches.first().map_or(sel.reps.unwrap_or(PAPER_REPS), |b| reps_of(b, sel))
}

/// `/api/results`: per batch its settings, progress, the report (as `report --format json` of that batch
/// alone) and every recorded rollout with its review link; and `across_batches`, the report over the whole
/// selection (`report` of every selected batch at once: Tables 2–4, Figure 3 and Appendix E per agent).
pub fn results_json(names: &[String], batches: &[LoadedBatch], sel: &Selection) -> Value {
    let list: Vec<Value> = batches
        .iter()
        .map(|b| {
            let reps = reps_of(b, sel);
            let d = &b.batch;
            json!({
                "name": b.name(),
                "dir": b.dir,
                "status": d.status,
                "experiment": d.experiment(),
                "harness": d.harness_setting(),
                "harness_versions": HarnessVersions::of_batch(b),
                "model": d.model(),
                "reps": reps,
                "toolbox": d.toolbox,
                "progress": {"rollout_count": d.rollout_count, "counts": d.counts,
                    "running": d.running, "outcomes": d.outcomes, "updated_at": d.updated_at},
                "report": report_json(std::slice::from_ref(b), reps, task_facts()),
                "episodes": b.records.iter().map(|r| episode_json(b, r)).collect::<Vec<_>>(),
            })
        })
        .collect();
    let reps = selection_reps(batches, sel);
    // the paper's tables across the selection, as `report` computes them (not the rest of its report)
    let across = libero_report::tables::paper_tables(batches, &rows(batches, reps), reps, task_facts());
    json!({"ok": true, "schema_version": "libero_agent.results.v1", "available": names, "batches": list,
        "across_batches": {"reps": reps, "observation_ablation": across.observation_ablation,
            "demonstration_ablation": across.demonstration_ablation, "stage_diagnosis": across.stage_diagnosis,
            "stage_diagnosis_extension": across.stage_diagnosis_extension, "sustained_contact": across.sustained_contact, "appendix_e": across.appendix_e}})
}

// ------------------------------------------------------------------------------------------- page view

fn condition_label(r: &Row) -> String {
    format!("L{}, demo {}", r.condition.level, r.condition.demo.as_str())
}

/// One line of the main table.
pub struct MainRow {
    pub batch: String,
    pub agent: String,
    /// The harness versions the row's rollouts ran, flagged when they differ.
    pub version: VersionCell,
    pub condition: String,
    pub reps: usize,
    pub j: String,
    pub p: String,
    pub m_easy: String,
    pub m_hard: String,
    pub l_easy: String,
    pub l_hard: String,
    pub score: String,
    /// The suite is incomplete: the Score shown is the metrics crate's lower bound.
    pub score_is_bound: bool,
    pub time: String,
    /// Mean total tokens with where the figures came from (`8,610 (gateway 2/2)`, `– (no usage: 2 rollouts)`).
    pub tokens: String,
    pub ordinary: Vec<String>,
}

/// The agent toolbox a batch ran with: results are comparable only with the same toolbox.
pub struct ToolboxRow {
    pub batch: String,
    pub name: String,
    /// `numpy 1.26.4, scipy 1.14.1, …`
    pub packages: String,
    pub python: String,
    pub source: String,
    /// The per-rollout caps (`1024 processes, 4.0 GiB memory, 2.0 GiB disk, all CPUs`), or why there were none.
    pub limits: String,
}

/// The harness versions a batch's (or a row's) rollouts ran: `codex 0.154.0`, or with `mixed` set,
/// `codex 0.154.0 / 0.169.0 (mixed versions)`, shown as a warning.
pub struct VersionCell {
    pub text: String,
    pub mixed: bool,
    /// Each version with how many rollouts ran it.
    pub title: String,
}

impl From<HarnessVersions> for VersionCell {
    fn from(v: HarnessVersions) -> Self {
        let mut counts: Vec<String> = v.versions.iter().map(|c| format!("{}: {} rollouts", c.version, c.rollouts)).collect();
        if v.unknown > 0 {
            counts.push(format!("no version: {} rollouts (never launched)", v.unknown));
        }
        Self { text: v.text, mixed: v.mixed, title: counts.join(", ") }
    }
}

/// A batch's progress line (done/running/left, outcomes so far).
pub struct ProgressRow {
    pub batch: String,
    /// The Results page of this batch alone.
    pub href: String,
    pub status: String,
    pub experiment: String,
    pub agent: String,
    pub version: VersionCell,
    pub done: String,
    pub running: String,
    pub left: String,
    pub outcomes: String,
    /// A queued batch's running rollouts: (rollout id, worker, the worker's live view if it gave one).
    pub running_on: Vec<(String, String, Option<String>)>,
}

/// One rollout in a per-task cell.
#[derive(Clone)]
pub struct EpisodeLink {
    pub href: String,
    pub label: String,
    pub outcome: String,
    pub title: String,
    /// Why an INVALID or INTERRUPTED rollout does not count, shortened (the title has all of it); empty otherwise.
    pub reason: String,
    /// The rollout's logs (stdout, stderr, manifest, transcript) for operators; empty when it has no plain name.
    pub logs: String,
}

/// One rollout of a shown batch, with its review and its logs.
pub struct RolloutRow {
    pub batch: String,
    pub rollout: String,
    pub task: String,
    pub repetition: u32,
    pub condition: String,
    pub outcome: String,
    /// `c/K`.
    pub stages: String,
    pub review: String,
    pub logs: String,
    /// Why an INVALID or INTERRUPTED rollout does not count, shortened; empty otherwise.
    pub reason: String,
}

/// A rollout that does not count (INVALID, INTERRUPTED), with why.
pub struct ExcludedRow {
    pub batch: String,
    pub rollout: String,
    pub task: String,
    pub outcome: String,
    pub worker: String,
    pub reason: String,
    pub href: String,
    pub logs: String,
}

pub struct TaskCell {
    /// `successes/valid` (plus excluded), empty when the column has no rollout of the task.
    pub summary: String,
    pub stable: String,
    /// Each valid rollout's total tokens with its source mark (`8,610 G · 9,020 G`).
    pub tokens: String,
    pub links: Vec<EpisodeLink>,
}

pub struct TaskRow {
    pub task: String,
    pub split: String,
    pub cells: Vec<TaskCell>,
}


/// One suite of a pool batch (`run --experiment pool`).
pub struct PoolSuiteRow {
    pub batch: String,
    pub agent: String,
    pub suite: String,
    pub tasks: String,
    pub stable_sr: String,
    pub stable_sc: String,
    pub mean_sc: String,
    pub ordinary: String,
    pub time: String,
    pub tokens: String,
}

/// One pool task of a batch with its rollouts.
pub struct PoolTaskRow {
    pub batch: String,
    pub task: String,
    pub suite: String,
    pub summary: String,
    pub stable: String,
    pub tokens: String,
    pub links: Vec<EpisodeLink>,
}

pub struct View {
    pub main: Vec<MainRow>,
    pub pool: Vec<PoolSuiteRow>,
    pub pool_tasks: Vec<PoolTaskRow>,
    pub progress: Vec<ProgressRow>,
    pub columns: Vec<String>,
    pub tasks: Vec<TaskRow>,
    /// Tables 2–4, Figure 3's numbers and Appendix E, across the selected batches of each agent (those with rows).
    pub paper: Vec<DisplayTable>,
    /// Figure 3 as inline SVG (its two panels in one), drawn by the server (the same as `report --figures`).
    pub figures: Vec<String>,
    /// Every rollout that does not count, with its reason.
    pub excluded: Vec<ExcludedRow>,
    /// Every recorded rollout of the shown batches, in the order they ended, each with its review and logs.
    pub rollouts: Vec<RolloutRow>,
    /// Each shown batch's agent toolbox.
    pub toolboxes: Vec<ToolboxRow>,
    /// [`tokens::LEGEND`].
    pub token_legend: &'static str,
    pub any_running: bool,
}

/// `harness + model`, as the page heads it.
fn agent_of(b: &LoadedBatch) -> String {
    format!("{} + {}", b.batch.harness_setting().unwrap_or("?"), b.batch.model().unwrap_or("?"))
}

fn count(n: Option<u64>) -> String {
    n.map(|n| n.to_string()).unwrap_or_else(|| "—".into())
}

/// Everything the page shows, from the same rows the JSON carries.
pub fn view(batches: &[LoadedBatch], sel: &Selection) -> View {
    let mut v = View {
        main: vec![],
        pool: vec![],
        pool_tasks: vec![],
        progress: vec![],
        columns: vec![],
        tasks: vec![],
        paper: vec![],
        figures: vec![],
        excluded: vec![],
        rollouts: vec![],
        toolboxes: vec![],
        token_legend: tokens::LEGEND,
        any_running: false,
    };
    // (column index, batch, condition row) for the per-task table.
    let mut task_numbers = BTreeSet::new();
    let mut cols: Vec<(&LoadedBatch, Row)> = Vec::new();
    for b in batches {
        let reps = reps_of(b, sel);
        let d = &b.batch;
        let status = d.status.clone().unwrap_or_else(|| "?".into());
        v.any_running |= status == "running" || status == "queued";
        let outcomes = d
            .outcomes
            .as_ref()
            .map(|o| o.iter().map(|(k, n)| format!("{k} {n}")).collect::<Vec<_>>().join(", "))
            .filter(|s| !s.is_empty())
            .unwrap_or_else(|| "none yet".into());
        let experiment = d.experiment().unwrap_or("?").to_owned();
        let counts = d.counts.clone().unwrap_or_default();
        v.toolboxes.push(toolbox_row(b));
        v.progress.push(ProgressRow {
            href: format!("/results?batch={}", percent_encode(&b.name())),
            batch: b.name(),
            status,
            experiment: experiment.clone(),
            agent: agent_of(b),
            version: HarnessVersions::of_batch(b).into(),
            done: count(counts.done),
            running: count(counts.running),
            left: count(counts.left),
            outcomes,
            running_on: d
                .running_on
                .iter()
                .flatten()
                .map(|r| {
                    let live = r.live_url.clone().flatten().filter(|u| u.starts_with("http://") || u.starts_with("https://"));
                    let on = r.host.clone().flatten().or_else(|| r.worker.clone().flatten()).unwrap_or_default();
                    (r.rollout_id.clone().unwrap_or_default(), on, live)
                })
                .collect(),
        });
        let batch_rows = rows(std::slice::from_ref(b), reps);
        for r in &batch_rows {
            let s = &r.summary;
            v.main.push(MainRow {
                batch: b.name(),
                agent: agent_of(b),
                version: row_versions(std::slice::from_ref(b), &r.agent, r.condition).into(),
                condition: condition_label(r),
                reps,
                j: if s.judgment_tasks_scored == 0 {
                    "—".into()
                } else {
                    format!("{} ({}/10)", pct(s.judgment), s.judgment_tasks_scored)
                },
                p: coverage(s, Split::Perception),
                m_easy: coverage(s, Split::ShortHorizonEasy),
                m_hard: coverage(s, Split::ShortHorizonHard),
                l_easy: coverage(s, Split::LongHorizonEasy),
                l_hard: coverage(s, Split::LongHorizonHard),
                score: match s.score {
                    Some(x) => format!("{x:.1}"),
                    None => format!("≥ {:.1}", s.score_lower_bound),
                },
                score_is_bound: s.score.is_none(),
                time: time_text(s.avg_wall_time_min, s.averaged_invalid),
                tokens: TokenSummary::of(row_records(std::slice::from_ref(b), &r.agent, r.condition)).text(),
                ordinary: Split::ALL
                    .iter()
                    .map(|sp| s.split(*sp).map(|x| wilson(&x.ordinary)).unwrap_or_default())
                    .chain(std::iter::once(wilson(&s.ordinary)))
                    .collect(),
            });
            task_numbers.extend(s.tasks.iter().map(|t| t.task_number));
        }
        for r in b.records.iter().filter(|r| !r.outcome.is_valid()) {
            v.excluded.push(ExcludedRow {
                batch: b.name(),
                rollout: r.rollout_id.clone(),
                task: r.task.clone(),
                outcome: r.outcome.as_str().to_owned(),
                worker: r.worker.clone().unwrap_or_default(),
                reason: r.reason().unwrap_or_else(|| "no reason recorded".into()),
                href: r.episode_id.as_ref().map(|id| format!("/episodes/{id}/review")).unwrap_or_default(),
                logs: logs_href(b, r),
            });
        }
        for r in &b.records {
            let link = episode_link(b, r);
            v.rollouts.push(RolloutRow {
                batch: b.name(),
                rollout: r.rollout_id.clone(),
                task: r.task.clone(),
                repetition: r.repetition,
                condition: format!("L{}, demo {}", r.level, r.demo.as_str()),
                outcome: link.outcome,
                stages: link.label,
                review: link.href,
                logs: link.logs,
                reason: link.reason,
            });
        }
        pool_view(&mut v, b, reps);
        cols.extend(batch_rows.into_iter().map(|r| (b, r)));
    }
    v.columns = cols.iter().map(|(b, r)| format!("{} · {} ({})", b.name(), agent_of(b), condition_label(r))).collect();
    for n in task_numbers {
        let cells = cols
            .iter()
            .map(|(b, r)| {
                let recs: Vec<&RolloutRecord> = b
                    .records
                    .iter()
                    .filter(|x| x.task_number == n && x.level == r.condition.level && x.demo == r.condition.demo)
                    .collect();
                let t = r.summary.tasks.iter().find(|t| t.task_number == n);
                let mut recs = recs;
                recs.sort_by_key(|x| x.repetition);
                TaskCell {
                    tokens: tokens::per_rollout_text(recs.iter().copied().filter(|x| x.outcome.is_valid())),
                    summary: t
                        .map(|t| {
                            let excluded = if t.excluded_rollouts > 0 { format!(" (+{} excluded)", t.excluded_rollouts) } else { String::new() };
                            format!("{}/{}{excluded}", t.successes, t.valid_rollouts)
                        })
                        .unwrap_or_default(),
                    stable: t
                        .map(|t| {
                            if t.split.is_long_horizon() {
                                format!("min c/K {}", t.stable_stage_fraction.map(|f| format!("{f:.2}")).unwrap_or_else(|| "—".into()))
                            } else {
                                match t.stable_success {
                                    Some(true) => "stable".into(),
                                    Some(false) => "not stable".into(),
                                    None => "incomplete".into(),
                                }
                            }
                        })
                        .unwrap_or_default(),
                    links: recs.iter().map(|x| episode_link(b, x)).collect(),
                }
            })
            .collect();
        v.tasks.push(TaskRow {
            task: format!("T{n:02}"),
            split: Split::of_task(n).map(|s| s.as_str().to_owned()).unwrap_or_default(),
            cells,
        });
    }
    let reps = selection_reps(batches, sel);
    let paper = paper_tables(batches, &rows(batches, reps), reps, task_facts());
    v.paper = display_tables(&paper, TableChoice::All, reps).into_iter().filter(|t| !t.rows.is_empty()).collect();
    if !paper.sustained_contact.is_empty() {
        v.figures = vec![svg::figure3(&paper.sustained_contact)];
    }
    v
}

/// The toolbox line of a batch (`batch.json`'s `toolbox`, as `Toolbox::describe` wrote it).
fn toolbox_row(b: &LoadedBatch) -> ToolboxRow {
    let t = b.batch.toolbox();
    let described = toolbox_text(t);
    let (name, packages) = match described.split_once(" (") {
        Some((name, rest)) => (name.to_owned(), rest.trim_end_matches(')').to_owned()),
        None => (described, String::new()),
    };
    let name = if t.is_some() {
        name
    } else if b.batch.settings.as_ref().and_then(|s| s.sandbox) == Some(false) {
        "none (run without the sandbox: the host's python3)".into()
    } else {
        "none".into()
    };
    let text = |f: fn(&ToolboxDoc) -> Option<&String>| t.and_then(f).cloned().unwrap_or_default();
    let limits = match b.batch.sandbox() {
        Some(sb) => match sb.resources.as_ref() {
            Some(Some(r)) => r.summary(),
            Some(None) => "unconfined (--unconfined-resources)".into(),
            None => "not recorded".into(),
        },
        None if b.batch.settings.as_ref().and_then(|s| s.sandbox) == Some(false) => "none (run without the sandbox)".into(),
        None => "not recorded".into(),
    };
    ToolboxRow { batch: b.name(), name, packages, python: text(|t| t.python.as_ref()), source: text(|t| t.source.as_ref()), limits }
}

/// A rollout of batch `b` as `c/K`, linked to its review and its logs.
fn episode_link(b: &LoadedBatch, x: &RolloutRecord) -> EpisodeLink {
    let c = x.completed_stages.map(|c| c.to_string()).unwrap_or_else(|| "?".into());
    let reason = if x.outcome.is_valid() { None } else { x.reason() };
    EpisodeLink {
        href: x.episode_id.as_ref().map(|id| format!("/episodes/{id}/review")).unwrap_or_default(),
        label: format!("{c}/{}", x.stage_count),
        outcome: x.outcome.as_str().to_owned(),
        title: match &reason {
            Some(why) => format!("repetition {}: {} ({}): {why}", x.repetition, x.outcome.as_str(), x.rollout_id),
            None => format!("repetition {}: {} ({}), tokens {}", x.repetition, x.outcome.as_str(), x.rollout_id, RolloutTokens::of(x).short()),
        },
        reason: reason.map(|why| shorten(&why, 80)).unwrap_or_default(),
        logs: logs_href(b, x),
    }
}

/// At most `max` characters of `text`, with `…` where it was cut.
fn shorten(text: &str, max: usize) -> String {
    if text.chars().count() <= max {
        return text.to_owned();
    }
    let mut s: String = text.chars().take(max.saturating_sub(1)).collect();
    s.push('…');
    s
}

/// A pool batch's per-suite lines and per-task rows (the same summary as `report`'s pool section).
fn pool_view(v: &mut View, b: &LoadedBatch, reps: usize) {
    for (_, p) in pool_rows(std::slice::from_ref(b), reps) {
        for s in &p.suites {
            v.pool.push(PoolSuiteRow {
                batch: b.name(),
                agent: agent_of(b),
                suite: s.suite.clone(),
                tasks: format!("{} ({} scored)", s.tasks, s.tasks_scored),
                stable_sr: pct(s.stable_success),
                stable_sc: pct(s.stable_stage_completion),
                mean_sc: pct(s.mean_stage_completion),
                ordinary: wilson(&s.ordinary),
                time: time_text(s.avg_wall_time_min, s.averaged_invalid),
                tokens: TokenSummary::of(suite_records(std::slice::from_ref(b), &libero_report::batch::agent_of(b), &s.suite)).text(),
            });
        }
        for t in &p.tasks {
            let mut recs: Vec<&RolloutRecord> =
                b.records.iter().filter(|x| x.suite.as_deref() == Some(t.suite.as_str()) && x.task == t.task).collect();
            recs.sort_by_key(|x| x.repetition);
            let c = &t.counts;
            let excluded = if c.excluded_rollouts > 0 { format!(" (+{} excluded)", c.excluded_rollouts) } else { String::new() };
            v.pool_tasks.push(PoolTaskRow {
                batch: b.name(),
                task: t.task.clone(),
                suite: t.suite.clone(),
                summary: format!("{}/{}{excluded}", c.successes, c.valid_rollouts),
                tokens: tokens::per_rollout_text(recs.iter().copied().filter(|x| x.outcome.is_valid())),
                stable: match (c.stable_success, c.stable_stage_fraction) {
                    (Some(true), _) => "stable".into(),
                    (Some(false), Some(f)) if t.stage_count > 1 => format!("not stable, min c/K {f:.2}"),
                    (Some(false), _) => "not stable".into(),
                    (None, _) => "incomplete".into(),
                },
                links: recs.iter().map(|x| episode_link(b, x)).collect(),
            });
        }
    }
}

// ---------------------------------------------------------------------------------------------- the page and /api/results

#[derive(Template)]
#[template(path = "results.html")]
struct ResultsPage {
    available: Vec<(String, bool)>,
    reps: String,
    /// The selection's query (for the download links).
    query: String,
    view: View,
}

/// Loads the selected batches: batch directories off the async workers (they are files of any size), and the
/// batches only the store holds (`run --store`) from the store.
pub(crate) async fn selected(app: &App, sel: &Selection) -> ApiResult<(Vec<String>, Vec<LoadedBatch>)> {
    let internal = |e: String| ApiError::internal(format!("results: {e}"));
    let stored = app.store.batch_names().await.map_err(|e| internal(format!("{e:#}")))?;
    let (roots, sel) = (app.batch_roots.clone(), sel.clone());
    let (names, picked) = match tokio::task::spawn_blocking(move || load_selected(&roots, &stored, &sel)).await {
        Ok(Ok(x)) => x,
        Ok(Err(e)) => return Err(ApiError::not_found(e)),
        Err(e) => return Err(internal(e.to_string())),
    };
    let mut batches = Vec::with_capacity(picked.len());
    for p in picked {
        batches.push(match p {
            Selected::Loaded(b) => *b,
            Selected::InStore(name) => {
                let b = app.store.batch(&name).await.map_err(|e| internal(format!("{e:#}")))?;
                let b = b.ok_or_else(|| internal(format!("batch {name} left the store")))?;
                LoadedBatch::from_stored(&b.name, b.dir, b.doc, b.records).map_err(|e| internal(e.to_string()))?
            }
        });
    }
    Ok((names, batches))
}

pub(crate) async fn results_page(State(app): State<AppState>, RawQuery(query): RawQuery) -> ApiResult {
    let sel = Selection::parse(query.as_deref()).map_err(ApiError::bad_request)?;
    let (names, batches) = selected(&app, &sel).await?;
    let view = view(&batches, &sel);
    Ok(page(ResultsPage {
        available: names.into_iter().map(|n| (n.clone(), sel.batches.contains(&n))).collect(),
        reps: sel.reps.map(|n| n.to_string()).unwrap_or_default(),
        query: sel.query(),
        view,
    }))
}

pub(crate) async fn results_api(State(app): State<AppState>, RawQuery(query): RawQuery) -> ApiResult {
    let sel = Selection::parse(query.as_deref()).map_err(ApiError::bad_request)?;
    let (names, batches) = selected(&app, &sel).await?;
    Ok(axum::Json(results_json(&names, &batches, &sel)).into_response())
}

/// `/results/report/{csv|markdown|latex}?batch=…&reps=…`: what `libero-agent report --format F` prints for the
/// selected batches (every table), as a download.
pub(crate) async fn results_download(State(app): State<AppState>, UrlPath(format): UrlPath<String>, RawQuery(query): RawQuery) -> ApiResult {
    let sel = Selection::parse(query.as_deref()).map_err(ApiError::bad_request)?;
    let (render, kind, ext): (fn(&[LoadedBatch], usize, TableChoice, &TaskFacts) -> String, &str, &str) = match format.as_str() {
        "csv" => (libero_report::csv, "text/csv; charset=utf-8", "csv"),
        "markdown" | "md" => (libero_report::markdown, "text/markdown; charset=utf-8", "md"),
        "latex" | "tex" => (libero_report::latex, "application/x-latex; charset=utf-8", "tex"),
        other => return Err(ApiError::bad_request(format!("the report downloads as csv, markdown or latex, not {other:?}"))),
    };
    let (_, batches) = selected(&app, &sel).await?;
    let reps = sel.reps.unwrap_or_else(|| default_reps(&batches));
    let body = tokio::task::spawn_blocking(move || render(&batches, reps, TableChoice::All, task_facts()))
        .await
        .map_err(|e| ApiError::internal(format!("report: {e}")))?;
    let file = format!("attachment; filename=\"libero-agent-results.{ext}\"");
    Ok(([(header::CONTENT_TYPE, kind.to_owned()), (header::CONTENT_DISPOSITION, file)], body).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn repeated_batch_keys_are_all_kept() {
        let s = Selection::parse(Some("batch=a&batch=b%2Dc&reps=3&batch=a&x=1")).unwrap();
        assert_eq!(s, Selection { batches: vec!["a".into(), "b-c".into()], reps: Some(3) });
        assert_eq!(s.query(), "batch=a&batch=b-c&reps=3");
        assert_eq!(Selection::parse(None).unwrap(), Selection::default());
        assert_eq!(Selection::parse(Some("reps=&batch=")).unwrap().reps, None, "an empty reps is each batch's own");
        for bad in ["reps=0", "reps=abc", "reps=101", "reps=-1", "reps=2.5"] {
            let e = Selection::parse(Some(bad)).unwrap_err();
            assert!(e.contains("from 1 to 100"), "{bad}: {e}");
        }
        assert_eq!(Selection { batches: vec!["a b/ü".into()], reps: None }.query(), "batch=a%20b%2F%C3%BC");
        assert_eq!(percent_decode("100%"), "100%");
    }
}
