//! The paper's tables after Table 1 and its Figure 3, across the batches of one agent (`report`, the Results page):
//!
//! * Table 2, observation ablation (T11–T20 stable SR at levels 1/2/3): levels 1 and 2 from the agent's
//!   `manip_observation` batch, level 3 from its `main_table` batch (level 3, no demonstration);
//! * Table 3, demonstration ablation (T21–T30 stable SC with None / Video / Video + Traj.): the demonstrations from its
//!   `context` batch, None from its `main_table` batch;
//! * Table 4, the paper's stage-level diagnosis of the hard long-horizon tasks (T21, T22, T25, T28, T30), and
//!   "Table 4+", this project's extension over every long-horizon task, from each rollout's private record
//!   (`result.json` → `private_evaluation`: its stage diagnostics, stage events and opening operations, with the stage
//!   types the catalog declares, [`TaskFacts`]) and, for Table 4, a person's stage annotations where there are any;
//! * Figure 3, the sustained-contact ratio of the stage analysis's opening operations (`private_evaluation.details.
//!   opening_operations`; which operations and how, [`crate::figure3`]);
//! * Appendix E, the per-task tables in wide format.
//!
//! Rollouts are grouped by agent (`harness/model`) and condition exactly as Table 1's rows, whichever batch they came
//! from; Tables 4 and Figure 3 read the rollouts the stable rule reads (per task, the first `reps` valid ones) through
//! their run directories, and count those whose record cannot be read.
use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::Path;

use libero_metrics::{
    AblationKind, AblationRow, PaperStageDiagnosis, Split, StageAnnotations, StageDiagnosis, StageOpportunity, StageType,
    TaskFacts, diagnose, diagnose_paper, in_paper_table4, summarize,
};
use libero_records::records::PrivateEvaluation;
use serde::Serialize;

use crate::batch::{Condition, Demo, LoadedBatch, RolloutRecord, agent_of};
use crate::display::{DisplayTable, field, p4, share, strings};
use crate::figure3::{self, Figure3Data};
use crate::stages::{opportunities, private_evaluation};
use crate::{Row, cell, pct, wilson};

/// One line of Table 2 or 3, with the batches its rollouts came from.
#[derive(Debug, Clone, Serialize)]
pub struct AblationLine {
    #[serde(flatten)]
    pub row: AblationRow,
    pub batches: Vec<String>,
}

/// Table 2 or 3 for one agent.
#[derive(Debug, Clone, Serialize)]
pub struct AblationTable {
    pub agent: String,
    pub rows: Vec<AblationLine>,
}

/// The paper's Table 4 for one agent under one condition (the hard long-horizon tasks).
#[derive(Debug, Clone, Serialize)]
pub struct PaperDiagnosisLine {
    pub agent: String,
    pub level: u8,
    pub demo: Demo,
    #[serde(flatten)]
    pub diagnosis: PaperStageDiagnosis,
    /// Counted rollouts whose record could not be read (no run directory here, or no `result.json`).
    pub rollouts_without_record: usize,
    /// The hard long-horizon tasks with a counted rollout (`T21`, …), and how many rollouts each.
    pub tasks: BTreeMap<String, usize>,
}

/// Table 4+ (the extension: every long-horizon task, automatic labels) for one agent under one condition.
#[derive(Debug, Clone, Serialize)]
pub struct DiagnosisLine {
    pub agent: String,
    pub level: u8,
    pub demo: Demo,
    #[serde(flatten)]
    pub diagnosis: StageDiagnosis,
    /// Counted rollouts whose record could not be read (no run directory here, or no `result.json`).
    pub rollouts_without_record: usize,
}

/// One task of an Appendix E row: successes (perception, short horizon) or the sum of `c/K` (long horizon) over
/// the first `reps` valid rollouts, printed `x/reps` and `sum/reps` as the paper does (`3/3`, `1.80/3`).
#[derive(Debug, Clone, Serialize)]
pub struct AppendixCell {
    pub task: String,
    /// Over the first `reps` valid rollouts; with fewer valid rollouts, short-horizon and perception cells hold the
    /// successes among those there are (`x/n valid`) and long-horizon cells none.
    pub value: Option<f64>,
    pub valid_rollouts: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct AppendixLine {
    pub agent: String,
    pub level: u8,
    pub demo: Demo,
    pub cells: Vec<AppendixCell>,
}

/// One wide per-task table of Appendix E.
#[derive(Debug, Clone, Serialize)]
pub struct AppendixTable {
    pub name: &'static str,
    pub title: &'static str,
    /// The long-horizon table's K row: each task's number of required stages (the catalog's, else the records'),
    /// in column order; empty for the other tables.
    pub stage_counts: Vec<Option<u32>>,
    pub rows: Vec<AppendixLine>,
}

/// Tables 2–4, Figure 3's data and Appendix E.
#[derive(Debug, Clone, Serialize)]
pub struct PaperTables {
    pub observation_ablation: Vec<AblationTable>,
    pub demonstration_ablation: Vec<AblationTable>,
    /// The paper's Table 4 (hard long-horizon tasks, annotations where given).
    pub stage_diagnosis: Vec<PaperDiagnosisLine>,
    /// Table 4+, the extension (every long-horizon task, automatic labels).
    pub stage_diagnosis_extension: Vec<DiagnosisLine>,
    /// Figure 3 over the stage analysis's opening operations (every agent's).
    pub sustained_contact: Figure3Data,
    pub appendix_e: Vec<AppendixTable>,
}

/// `L3, none`.
pub fn condition_label(c: Condition) -> String {
    format!("L{}, {}", c.level, c.demo.as_str())
}

/// The paper's name of a demonstration condition.
fn demo_label(d: Demo) -> &'static str {
    match d {
        Demo::None => "None",
        Demo::Video => "Video",
        Demo::VideoTraj => "Video + Traj.",
    }
}

/// Per task and condition, the first `reps` valid rollouts by repetition: the rollouts the stable rule reads.
fn counted<'a>(records: impl Iterator<Item = &'a RolloutRecord>, reps: usize) -> Vec<&'a RolloutRecord> {
    let mut by_task: BTreeMap<(Option<&str>, &str, u8, Demo), Vec<&RolloutRecord>> = BTreeMap::new();
    for r in records.filter(|r| r.outcome.is_valid()) {
        by_task.entry((r.suite.as_deref(), r.task.as_str(), r.level, r.demo)).or_default().push(r);
    }
    by_task
        .into_values()
        .flat_map(|mut rs| {
            rs.sort_by_key(|r| r.repetition);
            rs.truncate(reps);
            rs
        })
        .collect()
}

/// The batches whose rollouts fall in each (agent, condition), by name.
fn batch_names(batches: &[LoadedBatch]) -> BTreeMap<(String, Condition), BTreeSet<String>> {
    let mut out: BTreeMap<(String, Condition), BTreeSet<String>> = BTreeMap::new();
    for b in batches {
        for r in b.records.iter().filter(|r| r.suite.is_none()) {
            out.entry((agent_of(b), Condition { level: r.level, demo: r.demo })).or_default().insert(b.name());
        }
    }
    out
}

/// Table 2 or 3 for every agent with a condition of that ablation (levels 1/2, or a demonstration).
fn ablations(kind: AblationKind, rows: &[Row], batches: &BTreeMap<(String, Condition), BTreeSet<String>>, reps: usize) -> Vec<AblationTable> {
    let conditions: Vec<(Condition, String)> = match kind {
        AblationKind::Observation => (1..=3).map(|l| (Condition { level: l, demo: Demo::None }, format!("L{l}"))).collect(),
        AblationKind::Demonstration => {
            [Demo::None, Demo::Video, Demo::VideoTraj].into_iter().map(|d| (Condition { level: 3, demo: d }, d.as_str().to_owned())).collect()
        }
    };
    let ablated = |c: &Condition| match kind {
        AblationKind::Observation => c.demo == Demo::None && c.level < 3,
        AblationKind::Demonstration => c.level == 3 && c.demo != Demo::None,
    };
    let agents: BTreeSet<&str> = rows.iter().filter(|r| ablated(&r.condition)).map(|r| r.agent.as_str()).collect();
    let empty = summarize(&[], reps);
    agents
        .into_iter()
        .map(|agent| AblationTable {
            agent: agent.to_owned(),
            rows: conditions
                .iter()
                .map(|(c, label)| {
                    let summary = rows.iter().find(|r| r.agent == agent && r.condition == *c).map_or(&empty, |r| &r.summary);
                    AblationLine {
                        row: AblationRow::of(kind, label.clone(), summary),
                        batches: batches.get(&(agent.to_owned(), *c)).map(|s| s.iter().cloned().collect()).unwrap_or_default(),
                    }
                })
                .collect(),
        })
        .collect()
}

/// The three wide tables of Appendix E over Table 1's rows (`batches` for the K row where `facts` lack a task).
fn appendix(rows: &[Row], batches: &[LoadedBatch], facts: &TaskFacts) -> Vec<AppendixTable> {
    let k_of = |n: u32| {
        facts
            .stage_counts
            .get(&n)
            .copied()
            .or_else(|| batches.iter().flat_map(|b| &b.records).filter(|r| r.suite.is_none() && r.task_number == n).map(|r| r.stage_count).max())
    };
    let table = |name, title, splits: &[Split], long: bool| {
        let mut tasks: Vec<u32> = splits.iter().flat_map(|s| s.members().iter().copied()).collect();
        tasks.sort_unstable();
        let lines = rows
            .iter()
            .filter(|r| r.summary.tasks.iter().any(|t| splits.contains(&t.split)))
            .map(|r| AppendixLine {
                agent: r.agent.clone(),
                level: r.condition.level,
                demo: r.condition.demo,
                cells: tasks
                    .iter()
                    .map(|&n| {
                        let t = r.summary.tasks.iter().find(|t| t.task_number == n);
                        AppendixCell {
                            task: format!("T{n:02}"),
                            value: t.and_then(|t| {
                                if long {
                                    t.stage_fraction_sum
                                } else {
                                    Some(t.stable_successes.unwrap_or(t.successes) as f64)
                                }
                            }),
                            valid_rollouts: t.map_or(0, |t| t.valid_rollouts),
                        }
                    })
                    .collect(),
            })
            .collect();
        let stage_counts = if long { tasks.iter().map(|&n| k_of(n)).collect() } else { Vec::new() };
        AppendixTable { name, title, stage_counts, rows: lines }
    };
    vec![
        table("perception", "Perception tasks", &[Split::Perception], false),
        table("short_horizon", "Short-horizon tasks", &[Split::ShortHorizonEasy, Split::ShortHorizonHard], false),
        table("long_horizon", "Long-horizon tasks: stage fractions", &[Split::LongHorizonEasy, Split::LongHorizonHard], true),
    ]
}

/// Everything after Table 1, from the batches and Table 1's rows over them (Table 4 from the people's annotations
/// in the batches' `stage_annotations.jsonl` where there are any, automatic labels elsewhere).
pub fn paper_tables(batches: &[LoadedBatch], rows: &[Row], reps: usize, facts: &TaskFacts) -> PaperTables {
    let annotations = crate::annotations::batches_annotations(batches);
    paper_tables_annotated(batches, rows, reps, Some(&annotations), facts)
}

/// Stage opportunities of one (agent, condition): the opportunities, counted rollouts, those without a record, and
/// the rollouts per task.
#[derive(Default)]
struct Opportunities {
    stages: Vec<StageOpportunity>,
    rollouts: usize,
    without_record: usize,
    tasks: BTreeMap<String, usize>,
}

impl Opportunities {
    fn add(&mut self, r: &RolloutRecord, pe: Option<&PrivateEvaluation>, facts: &TaskFacts) {
        self.rollouts += 1;
        *self.tasks.entry(format!("T{:02}", r.task_number)).or_default() += 1;
        match pe {
            Some(pe) => self.stages.extend(opportunities(r, pe, facts)),
            None => self.without_record += 1,
        }
    }
}

/// Everything after Table 1, with the paper's Table 4 taking each stage's label from `annotations` where it has one
/// (keyed by the rollout's episode and the stage's name) and from the automatic diagnosis elsewhere.
pub fn paper_tables_annotated(
    batches: &[LoadedBatch],
    rows: &[Row],
    reps: usize,
    annotations: Option<&StageAnnotations>,
    facts: &TaskFacts,
) -> PaperTables {
    let names = batch_names(batches);
    let mut diagnosis: BTreeMap<(String, Condition), Opportunities> = BTreeMap::new();
    let mut paper4: BTreeMap<(String, Condition), Opportunities> = BTreeMap::new();
    let (mut openings, mut analysed, mut analysed_without_record) = (Vec::new(), 0, 0);
    let mut by_agent: BTreeMap<String, Vec<&RolloutRecord>> = BTreeMap::new();
    for b in batches {
        by_agent.entry(agent_of(b)).or_default().extend(&b.records);
    }
    for (agent, records) in &by_agent {
        for r in counted(records.iter().copied(), reps) {
            let condition = Condition { level: r.level, demo: r.demo };
            let pe = private_evaluation(r);
            if figure3::in_stage_analysis(r) {
                analysed += 1;
                match &pe {
                    Some(pe) => openings.extend(figure3::operations(agent, r, pe, &opportunities(r, pe, facts))),
                    None => analysed_without_record += 1,
                }
            }
            if r.suite.is_none() && r.split.is_some_and(Split::is_long_horizon) {
                diagnosis.entry((agent.clone(), condition)).or_default().add(r, pe.as_ref(), facts);
                if in_paper_table4(r.task_number) {
                    paper4.entry((agent.clone(), condition)).or_default().add(r, pe.as_ref(), facts);
                }
            }
        }
    }
    PaperTables {
        observation_ablation: ablations(AblationKind::Observation, rows, &names, reps),
        demonstration_ablation: ablations(AblationKind::Demonstration, rows, &names, reps),
        stage_diagnosis: paper4
            .into_iter()
            .map(|((agent, c), o)| PaperDiagnosisLine {
                agent,
                level: c.level,
                demo: c.demo,
                diagnosis: diagnose_paper(&o.stages, o.rollouts - o.without_record, annotations),
                rollouts_without_record: o.without_record,
                tasks: o.tasks,
            })
            .collect(),
        stage_diagnosis_extension: diagnosis
            .into_iter()
            .map(|((agent, c), o)| DiagnosisLine {
                agent,
                level: c.level,
                demo: c.demo,
                diagnosis: diagnose(&o.stages, o.rollouts - o.without_record),
                rollouts_without_record: o.without_record,
            })
            .collect(),
        sustained_contact: Figure3Data::new(openings, analysed, analysed_without_record),
        appendix_e: appendix(rows, batches, facts),
    }
}

// --------------------------------------------------------------------------------------------- cells

/// A stable percentage, with (scored/member) when partial.
fn partial(value: Option<f64>, scored: usize, member: usize) -> String {
    if scored == member { pct(value) } else { format!("{} ({scored}/{member})", pct(value)) }
}

fn of_type(d: &StageDiagnosis, t: StageType) -> Option<&libero_metrics::TypeExecution> {
    d.by_type.iter().find(|x| x.stage_type == t)
}

/// An Appendix E cell as the paper writes it: successes over the `reps` rollouts (`3/3`), or the sum of `c/K` over
/// them to 2 decimals (`1.80/3`); with fewer than `reps` valid rollouts, the successes among the valid ones
/// (`1/2 valid`), and no long-horizon sum (`—`).
fn appendix_text(cell: &AppendixCell, long: bool, reps: usize) -> String {
    match (cell.value, long) {
        (None, _) => "—".into(),
        (Some(v), true) => format!("{v:.2}/{reps}"),
        (Some(v), false) if cell.valid_rollouts >= reps => format!("{v:.0}/{reps}"),
        (Some(v), false) => format!("{v:.0}/{} valid", cell.valid_rollouts),
    }
}

/// A Table 2/3 row's condition as the paper names it (`L1`; `None`, `Video`, `Video + Traj.`).
fn ablation_label(kind: AblationKind, condition: &str) -> String {
    match kind {
        AblationKind::Observation => condition.to_owned(),
        AblationKind::Demonstration => match condition {
            "video" => demo_label(Demo::Video),
            "video_traj" => demo_label(Demo::VideoTraj),
            _ => demo_label(Demo::None),
        }
        .to_owned(),
    }
}

// --------------------------------------------------------------------------------------------- display tables

fn ablation_display(kind: AblationKind, tables: &[AblationTable]) -> DisplayTable {
    let (id, by, source) = match kind {
        AblationKind::Observation => ("table-2", "Level", "L1/L2 come from the agent's observation batch, L3 from its main-table batch (level 3, no demonstration)."),
        AblationKind::Demonstration => ("table-3", "Demonstration", "Video and Video + Traj. come from the agent's context batch, None from its main-table batch (level 3, no demonstration)."),
    };
    let note = if tables.is_empty() {
        "No batch of this ablation in the report.".to_owned()
    } else {
        format!("{source} Overall is the mean of Easy and Hard; a partial subset shows (scored/member tasks).")
    };
    let (easy, hard) = kind.splits();
    let rows = tables
        .iter()
        .flat_map(|t| {
            t.rows.iter().map(move |l| {
                let r = &l.row;
                vec![
                    t.agent.clone(),
                    ablation_label(kind, &r.condition),
                    partial(r.easy, r.easy_tasks_scored, r.member_count),
                    partial(r.hard, r.hard_tasks_scored, r.member_count),
                    pct(r.overall),
                    if l.batches.is_empty() { "(none)".to_owned() } else { l.batches.join(", ") },
                ]
            })
        })
        .collect();
    DisplayTable {
        id: id.into(),
        title: kind.title().into(),
        note,
        heads: vec!["Agent".into(), by.into(), easy.label().into(), hard.label().into(), "Overall".into(), "From batch(es)".into()],
        rows,
    }
}

/// `agent (L3, none)`: the paper's Table 4 has one Agent column, so the condition goes with it.
fn agent_condition(agent: &str, level: u8, demo: Demo) -> String {
    format!("{agent} ({})", condition_label(Condition { level, demo }))
}

/// What each paper Table 4 row stands on: its opportunities, rollouts, tasks, and labels (annotated / automatic).
fn paper_basis(l: &PaperDiagnosisLine) -> String {
    let d = &l.diagnosis;
    let tasks: Vec<String> = l.tasks.iter().map(|(t, n)| format!("{t} ×{n}")).collect();
    let mut o = format!(
        "{}: {} stage opportunities over {} rollouts{} ({}); {} annotated, {} automatic",
        agent_condition(&l.agent, l.level, l.demo),
        d.opportunities,
        d.rollouts,
        without_record(l.rollouts_without_record),
        tasks.join(", "),
        d.annotated,
        d.automatic
    );
    if d.geometric_error + d.other + d.unattributed > 0 {
        let _ = write!(o, "; failed stages also annotated geometric error {}, other {}, no mode {}", d.geometric_error, d.other, d.unattributed);
    }
    if d.untyped_opportunities > 0 {
        let _ = write!(o, "; {} without a stage type", d.untyped_opportunities);
    }
    o
}

/// The paper's Table 4: exactly its seven columns.
fn paper_diagnosis_display(lines: &[PaperDiagnosisLine]) -> DisplayTable {
    let rows = lines
        .iter()
        .map(|l| {
            let d = &l.diagnosis;
            vec![
                agent_condition(&l.agent, l.level, l.demo),
                share(&d.reached),
                share(&d.success),
                share(&d.object_manipulation.execution_success),
                share(&d.mechanism_interaction.execution_success),
                share(&d.local_execution),
                share(&d.cross_stage_interference),
            ]
        })
        .collect();
    let note = if lines.is_empty() {
        "No rollout of the hard long-horizon tasks (T21, T22, T25, T28, T30) in the report.".to_owned()
    } else {
        let basis: Vec<String> = lines.iter().map(paper_basis).collect();
        format!(
            "The hard long-horizon tasks T21, T22, T25, T28, T30 (20 stages per round of rollouts); a stage opportunity is one \
             required stage of one counted rollout. Reached and Success: over all stage opportunities. Execution SR: successes / \
             reached stages of that type, leaving out reached stages whose failure is attributed to cross-stage interference. \
             Local Execution and Cross-stage Interference: shares of the reached stages that did not succeed; a stage may have \
             both, so they need not sum to 100%. A stage is reached only on evidence in its record (docs/reports.md), and a \
             person's annotation of a stage replaces its automatic label. {}.",
            basis.join(" · ")
        )
    };
    DisplayTable {
        id: "table-4".into(),
        title: "Stage-level diagnosis (Table 4; hard long-horizon tasks)".into(),
        note,
        heads: strings([
            "Agent", "Reached", "Success", "Execution SR: Object Manipulation", "Execution SR: Mechanism Interaction",
            "Local Execution", "Cross-stage Interference",
        ]),
        rows,
    }
}

/// Table 4+, the extension over every long-horizon task.
fn diagnosis_display(lines: &[DiagnosisLine]) -> DisplayTable {
    let rows = lines
        .iter()
        .map(|l| {
            let d = &l.diagnosis;
            let exec = |t| of_type(d, t).map(|x| wilson(&x.execution_success)).unwrap_or_else(|| "—".into());
            let mode = |n: usize| if d.failures == 0 { n.to_string() } else { format!("{n} ({:.1}%)", 100.0 * n as f64 / d.failures as f64) };
            vec![
                l.agent.clone(),
                condition_label(Condition { level: l.level, demo: l.demo }),
                format!("{}{}", d.rollouts, without_record(l.rollouts_without_record)),
                d.opportunities.to_string(),
                share(&d.reached),
                share(&d.success),
                exec(StageType::ObjectManipulation),
                exec(StageType::MechanismInteraction),
                d.failures.to_string(),
                mode(d.local_execution),
                mode(d.cross_stage_interference),
            ]
        })
        .collect();
    DisplayTable {
        id: "table-4-extension".into(),
        title: "Table 4+ (all long-horizon tasks T21–T30; extension): stage-level diagnosis, automatic labels".into(),
        note: if lines.is_empty() {
            "No long-horizon rollout in the report.".into()
        } else {
            "Not a table of the paper: every long-horizon task, automatic labels only (annotations enter Table 4), reached on \
             the same evidence as Table 4. Execution success = successes / reached stages of that type, nothing left out [95% \
             Wilson]; a failure is a reached stage that did not succeed or a completed stage a later stage undid, counted once, \
             as cross-stage interference when a completed stage regressed or an order violation blocked it, else local execution."
                .into()
        },
        heads: strings([
            "Agent", "Condition", "Rollouts", "Stage opportunities", "Reached", "Success", "Exec. success, Object Manipulation",
            "Exec. success, Mechanism Interaction", "Failures", "Local execution", "Cross-stage interference",
        ]),
        rows,
    }
}

fn without_record(n: usize) -> String {
    if n > 0 { format!(" (+{n} without record)") } else { String::new() }
}

/// `5`, or `—` where the stage count is unknown.
fn k_text(k: Option<u32>) -> String {
    k.map(|k| k.to_string()).unwrap_or_else(|| "—".into())
}

fn appendix_display(t: &AppendixTable, reps: usize) -> DisplayTable {
    let long = t.name == "long_horizon";
    let unit = if long { format!("sum of c/K over {reps} rollouts, /{reps}") } else { format!("successes out of {reps}, /{reps}") };
    let mut heads = strings(["Agent", "Condition"]);
    heads.extend(t.rows.first().into_iter().flat_map(|r| r.cells.iter().map(|c| c.task.clone())));
    let mut rows: Vec<Vec<String>> = Vec::new();
    if long && !t.rows.is_empty() {
        let mut k = vec!["K (stages)".to_owned(), String::new()];
        k.extend(t.stage_counts.iter().map(|&c| k_text(c)));
        rows.push(k);
    }
    rows.extend(t.rows.iter().map(|r| {
        let mut row = vec![r.agent.clone(), condition_label(Condition { level: r.level, demo: r.demo })];
        row.extend(r.cells.iter().map(|c| appendix_text(c, long, reps)));
        row
    }));
    let note = if long {
        format!("Each cell is the sum over the {reps} rollouts of the completed-stage fraction c/K, written sum/{reps} as the paper \
                 does (1.80/{reps}: the fractions sum to 1.80); the K row gives each task's number of stages; — without {reps} valid rollouts.")
    } else {
        format!("Each cell is the full-task successes among the {reps} rollouts, written x/{reps} as the paper does; x/n valid where \
                 fewer than {reps} rollouts are valid.")
    };
    DisplayTable { id: format!("appendix-e-{}", t.name.replace('_', "-")), title: format!("Appendix E: {} ({unit})", t.title), note, heads, rows }
}

/// Tables 2–4, Figure 3's numbers and operations, and Appendix E (its non-empty tables) as `choice` selects them.
pub fn display_tables(t: &PaperTables, choice: TableChoice, reps: usize) -> Vec<DisplayTable> {
    let mut out = Vec::new();
    if choice.wants(TableChoice::Table2) {
        out.push(ablation_display(AblationKind::Observation, &t.observation_ablation));
    }
    if choice.wants(TableChoice::Table3) {
        out.push(ablation_display(AblationKind::Demonstration, &t.demonstration_ablation));
    }
    if choice.wants(TableChoice::Table4) {
        out.push(paper_diagnosis_display(&t.stage_diagnosis));
        out.push(diagnosis_display(&t.stage_diagnosis_extension));
    }
    if choice.wants(TableChoice::Figure3) {
        out.extend(figure3::display(&t.sustained_contact));
    }
    if choice.wants(TableChoice::Appendix) {
        out.extend(t.appendix_e.iter().filter(|a| !a.rows.is_empty()).map(|a| appendix_display(a, reps)));
    }
    out
}

/// Which tables a format prints (`report --table`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum TableChoice {
    All,
    #[value(name = "table1", alias = "1")]
    Table1,
    #[value(name = "table2", alias = "2")]
    Table2,
    #[value(name = "table3", alias = "3")]
    Table3,
    #[value(name = "table4", alias = "4")]
    Table4,
    #[value(name = "figure3", alias = "fig3")]
    Figure3,
    #[value(name = "appendix", alias = "appendix-e")]
    Appendix,
}

impl TableChoice {
    pub fn wants(self, t: TableChoice) -> bool {
        self == TableChoice::All || self == t
    }
}

/// Tables 2–4, Figure 3's data and Appendix E as Markdown (after Table 1's sections).
pub fn markdown(t: &PaperTables, choice: TableChoice, reps: usize) -> String {
    let mut o = String::new();
    for d in display_tables(t, choice, reps) {
        let _ = writeln!(o, "\n## {}\n", d.title);
        if !d.note.is_empty() {
            let _ = writeln!(o, "{}\n", d.note);
        }
        if d.rows.is_empty() {
            continue;
        }
        let _ = writeln!(o, "| {} |", d.heads.iter().map(|h| cell(h)).collect::<Vec<_>>().join(" | "));
        let _ = writeln!(o, "|{}", "---|".repeat(d.heads.len()));
        for r in &d.rows {
            let _ = writeln!(o, "| {} |", r.iter().map(|c| cell(c)).collect::<Vec<_>>().join(" | "));
        }
    }
    o
}

// --------------------------------------------------------------------------------------------- CSV

fn csv_ablation(o: &mut String, kind: AblationKind, tables: &[AblationTable]) {
    let by = if kind == AblationKind::Observation { "level" } else { "demo" };
    let _ = writeln!(o, "agent,{by},easy_percent,hard_percent,overall_percent,easy_tasks_scored,hard_tasks_scored,member_tasks,batches");
    for t in tables {
        for l in &t.rows {
            let r = &l.row;
            let _ = writeln!(
                o,
                "{},{},{},{},{},{},{},{},{}",
                field(&t.agent), r.condition, p4(r.easy), p4(r.hard), p4(r.overall), r.easy_tasks_scored, r.hard_tasks_scored,
                r.member_count, field(&l.batches.join(" "))
            );
        }
    }
}

/// The paper's Table 4 as CSV: the seven columns' counts and percentages, and what each row stands on.
fn csv_paper_diagnosis(o: &mut String, lines: &[PaperDiagnosisLine]) {
    let _ = writeln!(
        o,
        "agent,level,demo,rollouts,rollouts_without_record,stage_opportunities,annotated,automatic,reached,reached_percent,\
         succeeded,success_percent,om_succeeded,om_reached,om_excluded_interference,om_execution_sr_percent,mi_succeeded,mi_reached,\
         mi_excluded_interference,mi_execution_sr_percent,failed,local_execution,local_execution_percent,cross_stage_interference,\
         cross_stage_interference_percent,geometric_error,other,untyped_opportunities"
    );
    for l in lines {
        let d = &l.diagnosis;
        let (om, mi) = (&d.object_manipulation, &d.mechanism_interaction);
        let _ = writeln!(
            o,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            field(&l.agent), l.level, l.demo.as_str(), d.rollouts, l.rollouts_without_record, d.opportunities, d.annotated, d.automatic,
            d.reached.successes, p4(d.reached.rate), d.success.successes, p4(d.success.rate),
            om.execution_success.successes, om.reached, om.excluded_interference, p4(om.execution_success.rate),
            mi.execution_success.successes, mi.reached, mi.excluded_interference, p4(mi.execution_success.rate),
            d.failed, d.local_execution.successes, p4(d.local_execution.rate), d.cross_stage_interference.successes,
            p4(d.cross_stage_interference.rate), d.geometric_error, d.other, d.untyped_opportunities
        );
    }
}

fn csv_diagnosis(o: &mut String, lines: &[DiagnosisLine]) {
    let _ = writeln!(
        o,
        "agent,level,demo,rollouts,rollouts_without_record,stage_opportunities,reached,reached_percent,succeeded,success_percent,\
         stage_type,type_opportunities,type_reached,type_succeeded,execution_success_percent,wilson_low_percent,wilson_high_percent,\
         failures,local_execution,cross_stage_interference"
    );
    for l in lines {
        let d = &l.diagnosis;
        let head = format!(
            "{},{},{},{},{},{},{},{},{},{}",
            field(&l.agent), l.level, l.demo.as_str(), d.rollouts, l.rollouts_without_record, d.opportunities, d.reached.successes,
            p4(d.reached.rate), d.success.successes, p4(d.success.rate)
        );
        let tail = format!("{},{},{}", d.failures, d.local_execution, d.cross_stage_interference);
        // one line per stage type, and an `all` line with the totals
        for t in &d.by_type {
            let e = &t.execution_success;
            let _ = writeln!(
                o,
                "{head},{},{},{},{},{},{},{},{tail}",
                t.stage_type.as_str(), t.opportunities, t.reached, e.successes, p4(e.rate), p4(e.wilson_low), p4(e.wilson_high)
            );
        }
        let _ = writeln!(o, "{head},all,{},{},{},,,,{tail}", d.opportunities, d.reached.successes, d.success.successes);
    }
}

fn csv_appendix(o: &mut String, t: &AppendixTable, reps: usize) {
    let Some(first) = t.rows.first() else { return };
    let heads: Vec<&str> = first.cells.iter().map(|c| c.task.as_str()).collect();
    let _ = writeln!(o, "agent,level,demo,{}", heads.join(","));
    let long = t.name == "long_horizon";
    if long {
        let ks: Vec<String> = t.stage_counts.iter().map(|k| k.map(|k| k.to_string()).unwrap_or_default()).collect();
        let _ = writeln!(o, "K,,,{}", ks.join(","));
    }
    for r in &t.rows {
        let cells: Vec<String> = r.cells.iter().map(|c| if c.value.is_none() { String::new() } else { appendix_text(c, long, reps) }).collect();
        let _ = writeln!(o, "{},{},{},{}", field(&r.agent), r.level, r.demo.as_str(), cells.join(","));
    }
}

/// One `(name, CSV)` block per table `choice` selects (Table 4: the paper's and the extension; Figure 3: its two
/// panels and its operations; Appendix E: three).
pub fn csv_blocks(t: &PaperTables, choice: TableChoice, reps: usize) -> Vec<(String, String)> {
    let mut blocks = Vec::new();
    let mut block = |name: &str, body: &dyn Fn(&mut String)| {
        let mut o = String::new();
        body(&mut o);
        blocks.push((name.to_owned(), o));
    };
    if choice.wants(TableChoice::Table2) {
        block("table_2_observation_ablation", &|o| csv_ablation(o, AblationKind::Observation, &t.observation_ablation));
    }
    if choice.wants(TableChoice::Table3) {
        block("table_3_demonstration_ablation", &|o| csv_ablation(o, AblationKind::Demonstration, &t.demonstration_ablation));
    }
    if choice.wants(TableChoice::Table4) {
        block("table_4_stage_diagnosis", &|o| csv_paper_diagnosis(o, &t.stage_diagnosis));
        block("table_4_extension_all_long_horizon", &|o| csv_diagnosis(o, &t.stage_diagnosis_extension));
    }
    if choice.wants(TableChoice::Figure3) {
        block("figure_3a_mean_scr", &|o| figure3::csv_mean(o, &t.sustained_contact));
        block("figure_3b_scr_bins", &|o| figure3::csv_bins(o, &t.sustained_contact));
        block("figure_3_opening_operations", &|o| figure3::csv_operations(o, &t.sustained_contact));
    }
    if choice.wants(TableChoice::Appendix) {
        for a in t.appendix_e.iter().filter(|a| !a.rows.is_empty()) {
            block(&format!("appendix_e_{}", a.name), &|o| csv_appendix(o, a, reps));
        }
    }
    blocks
}

// --------------------------------------------------------------------------------------------- LaTeX

/// `text` safe in a LaTeX cell.
pub fn tex(text: &str) -> String {
    text.replace('\\', "\\textbackslash{}")
        .replace('_', "\\_")
        .replace('%', "\\%")
        .replace('&', "\\&")
        .replace('#', "\\#")
        .replace('≥', "$\\geq$")
        .replace('—', "--")
        .replace('×', "$\\times$")
}

fn tex_table(o: &mut String, caption: &str, heads: &[String], rows: &[Vec<String>]) {
    let _ = writeln!(o, "\n% {caption}");
    let _ = writeln!(o, "\\begin{{tabular}}{{l{}}}\n\\toprule", "r".repeat(heads.len().saturating_sub(1)));
    let _ = writeln!(o, "{} \\\\\n\\midrule", heads.iter().map(|h| tex(h)).collect::<Vec<_>>().join(" & "));
    for r in rows {
        let _ = writeln!(o, "{} \\\\", r.iter().map(|c| tex(c)).collect::<Vec<_>>().join(" & "));
    }
    o.push_str("\\bottomrule\n\\end{tabular}\n");
}

/// Tables 2–4, Figure 3's numbers and operations and Appendix E as LaTeX tabulars (booktabs), each after a
/// `% title` line; tables without rows are left out.
pub fn latex(t: &PaperTables, choice: TableChoice, reps: usize) -> String {
    let mut o = String::new();
    for d in display_tables(t, choice, reps).iter().filter(|d| !d.rows.is_empty()) {
        tex_table(&mut o, &d.title, &d.heads, &d.rows);
    }
    o
}

/// Figure 3 as files in `dir`: the two-panel SVG ([`crate::svg::figure3`]) and the data behind it (CSV, JSON).
/// Returns the paths written.
pub fn write_figures(t: &PaperTables, dir: &Path) -> std::io::Result<Vec<std::path::PathBuf>> {
    let d = &t.sustained_contact;
    std::fs::create_dir_all(dir)?;
    let csv = |f: fn(&mut String, &Figure3Data)| {
        let mut o = String::new();
        f(&mut o, d);
        o
    };
    let json = serde_json::to_string_pretty(d).map_err(std::io::Error::other)? + "\n";
    let files = [
        ("figure3.svg", crate::svg::figure3(d)),
        ("figure3_mean_scr.csv", csv(figure3::csv_mean)),
        ("figure3_scr_bins.csv", csv(figure3::csv_bins)),
        ("figure3_opening_operations.csv", csv(figure3::csv_operations)),
        ("figure3.json", json),
    ];
    let mut written = Vec::new();
    for (name, text) in files {
        let path = dir.join(name);
        std::fs::write(&path, text)?;
        written.push(path);
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    //! Golden tests: rollout records of the five hard long-horizon tasks written by hand, and Table 4's seven
    //! columns computed by hand from the paper's definitions (see each test's comment).
    use std::path::Path;

    use libero_metrics::{FailureMode, StageAnnotation, StageKey};
    use serde_json::{Value, json};

    use super::*;
    use crate::batch::load_batch;

    const OM: &str = "object_manipulation";
    const MI: &str = "mechanism_interaction";

    /// A stage diagnostic as a record holds it. `reached` is the value an older evaluator wrote (first stages and
    /// unordered goals always true): the tables must not read it.
    fn stage(name: &str, ty: Option<&str>, old_reached: bool, succeeded: bool) -> Value {
        let mut d = json!({"stage_name": name, "required": true, "reached": old_reached, "succeeded": succeeded, "regressions": 0,
            "regressed_during_later_stage": false, "completed_control_step": null, "failure_reason": null});
        if let Some(t) = ty {
            d["type"] = json!(t);
        }
        d
    }

    fn completed(name: &str, step: u64) -> Value {
        json!({"kind": "stage_completed", "control_step": step, "stage_name": name})
    }

    fn opening(name: &str, exec: u64, runs: &[u64], completed: bool) -> Value {
        json!({"stage_name": name, "operation": "open", "exec_steps": exec, "contact_runs": runs,
            "sustained_steps": runs.iter().filter(|&&r| r >= 5).sum::<u64>(), "sustained_contact_ratio_percent": 0.0, "completed": completed})
    }

    /// A batch of agent `command/golden` (L3, no demonstration, 1 repetition): `(task, K, c, private evaluation)`.
    fn write_batch(dir: &Path, rollouts: &[(u32, u32, u32, Value)]) -> LoadedBatch {
        std::fs::create_dir_all(dir).unwrap();
        let batch = json!({
            "schema_version": "libero_agent.batch.v1", "status": "finished",
            "settings": {"experiment": "main_table", "harness": "command", "model": "golden", "effort": "high", "reps": 1,
                "tasks": [], "seed": 100, "wall_time_s": 300.0, "max_agent_steps": 100, "agent_cmd": "true", "sandbox": false},
            "rollout_count": rollouts.len(), "counts": {"done": rollouts.len(), "running": 0, "left": 0}, "outcomes": {},
        });
        std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
        let mut lines = String::new();
        for (task, k, c, pe) in rollouts {
            let id = format!("w1_t{task}_level3_none");
            let run = dir.join("runs").join(&id);
            std::fs::create_dir_all(&run).unwrap();
            std::fs::write(run.join("result.json"), json!({"status": "finished", "private_evaluation": pe}).to_string()).unwrap();
            let record = json!({
                "schema_version": "libero_agent.rollout.v1", "rollout_id": id, "task": format!("T{task:02}"), "task_number": task,
                "split": Split::of_task(*task).unwrap().as_str(), "stage_count": k, "repetition": 1, "level": 3, "demo": "none",
                "outcome": if c == k { "SUCCESS" } else { "FAIL" }, "episode_id": format!("ep-t{task}"), "run_dir": run,
                "completed_stages": c, "wall_time_s": 60.0, "started_at": "2025-01-01T00:00:00Z", "finished_at": "2025-01-01T00:01:00Z",
            });
            lines.push_str(&format!("{record}\n"));
        }
        std::fs::write(dir.join("rollouts.jsonl"), lines).unwrap();
        load_batch(dir).unwrap()
    }

    /// T21 (unordered cooking goals): the moka pot placed and kept (success); the second stove turned on, then off
    /// again (completed, regressed: reached, failed, cross-stage interference); the microwave handle touched but not
    /// opened (reached, failed, local execution); the frying pan and the first stove never touched (not reached).
    fn t21() -> Value {
        let mut st = vec![
            stage("Moka_Pot_On_Second_Stove", Some(OM), true, true),
            stage("Second_Stove_On", Some(MI), true, false),
            stage("Frying_Pan_On_First_Stove", Some(OM), true, false),
            stage("First_Stove_On", Some(MI), true, false),
            stage("Microwave_Open", Some(MI), true, false),
        ];
        st[0]["completed_control_step"] = json!(120);
        st[1]["completed_control_step"] = json!(200);
        st[1]["regressions"] = json!(1);
        json!({"checker": "private_unordered_goal_predicates", "stage_diagnostics": st,
            "stage_events": [completed("Moka_Pot_On_Second_Stove", 120), completed("Second_Stove_On", 200),
                {"kind": "stage_regressed", "control_step": 260, "stage_name": "Second_Stove_On"}],
            "details": {"order": "unordered", "opening_operations": [opening("Microwave_Open", 80, &[2, 3], false)]}})
    }

    /// T22: the agent never touched the task (the microwave's pending opening spans the episode without contact).
    fn t22() -> Value {
        let st: Vec<Value> = [("Moka_Pot_On_Second_Stove", OM), ("Second_Stove_On", MI), ("Frying_Pan_On_First_Stove", OM), ("First_Stove_On", MI), ("Microwave_Open", MI)]
            .iter()
            .map(|(n, t)| stage(n, Some(t), true, false))
            .collect();
        json!({"checker": "private_unordered_goal_predicates", "stage_diagnostics": st, "stage_events": [],
            "details": {"order": "unordered", "opening_operations": [opening("Microwave_Open", 1500, &[], false)]}})
    }

    /// T25 (strict order): stage 01 done; the right bowl moved before the middle one latched the order violation
    /// while 02 was current (reached, failed, cross-stage interference); 03 and 04 not reached.
    fn t25() -> Value {
        let mut st = vec![
            stage("01_Move_Left_Bowl_To_Empty_Plate", Some(OM), true, true),
            stage("02_Move_Middle_Bowl_To_Left_Plate", Some(OM), true, false),
            stage("03_Move_Right_Bowl_To_Middle_Plate", Some(OM), false, false),
            stage("04_Move_Buffered_Bowl_To_Right_Plate", Some(OM), false, false),
        ];
        st[0]["completed_control_step"] = json!(300);
        st[1]["failure_reason"] = json!("order_violation");
        json!({"checker": "private_ordered_buffer_rotation_and_tabletop_avoidance", "stage_diagnostics": st,
            "stage_events": [completed("01_Move_Left_Bowl_To_Empty_Plate", 300),
                {"kind": "order_violation", "control_step": 410, "stage_name": "02_Move_Middle_Bowl_To_Left_Plate",
                 "subject": "03_Move_Right_Bowl_To_Middle_Plate_before_02_Move_Middle_Bowl_To_Left_Plate"}],
            "details": {"order": "strict", "opening_operations": []}})
    }

    /// T28: unlatched (success); the door handle touched, the door not opened (reached, failed, local execution).
    fn t28() -> Value {
        let mut st = vec![stage("01_Unlatch_Door", Some(MI), true, true), stage("02_Open_Door", Some(MI), true, false)];
        st[0]["completed_control_step"] = json!(150);
        json!({"checker": "private_ordered_stages", "stage_diagnostics": st, "stage_events": [completed("01_Unlatch_Door", 150)],
            "details": {"order": "ordered", "opening_operations": [opening("01_Unlatch_Door", 150, &[20], true), opening("02_Open_Door", 300, &[1, 1], false)]}})
    }

    /// T30 (seesaw; the record names no types: the task facts' are used): 01–03 done, 01 knocked off while 02 ran and
    /// still latched (a success in Table 4, an interference failure in the extension); 04 reached, failed, local.
    fn t30() -> Value {
        let mut st = vec![
            stage("01_Place_First_Counterweight", None, true, true),
            stage("02_Place_Second_Counterweight", None, true, true),
            stage("03_Physical_Lift_Of_Target", None, true, true),
            stage("04_Place_Target_In_Basket", None, true, false),
        ];
        st[0]["regressions"] = json!(1);
        st[0]["regressed_during_later_stage"] = json!(true);
        json!({"checker": "private_ordered_physical_seesaw", "stage_diagnostics": st,
            "stage_events": [completed("01_Place_First_Counterweight", 100), completed("02_Place_Second_Counterweight", 200),
                {"kind": "stage_regressed", "control_step": 180, "stage_name": "01_Place_First_Counterweight"},
                completed("03_Physical_Lift_Of_Target", 320)],
            "details": {"opening_operations": []}})
    }

    fn golden(dir: &Path) -> Vec<LoadedBatch> {
        vec![write_batch(dir, &[(21, 5, 1, t21()), (22, 5, 0, t22()), (25, 4, 1, t25()), (28, 2, 1, t28()), (30, 4, 3, t30())])]
    }

    /// The catalog's facts these tests read: the paper's K of T21–T30 and T30's declared stage types.
    pub(crate) fn facts() -> TaskFacts {
        use StageType::{MechanismInteraction as Mi, ObjectManipulation as Om};
        let t30 = [("01_Place_First_Counterweight", Om), ("02_Place_Second_Counterweight", Om), ("03_Physical_Lift_Of_Target", Mi), ("04_Place_Target_In_Basket", Om)];
        TaskFacts {
            stage_types: [(30, t30.iter().map(|(n, t)| (n.to_string(), Some(*t))).collect())].into(),
            stage_counts: (21..=30).zip([5, 5, 8, 4, 4, 3, 4, 2, 3, 4]).collect(),
        }
    }

    fn tables(batches: &[LoadedBatch], notes: Option<&StageAnnotations>) -> PaperTables {
        paper_tables_annotated(batches, &crate::rows(batches, 1), 1, notes, &facts())
    }

    fn table4_row(t: &PaperTables) -> Vec<String> {
        let d = display_tables(t, TableChoice::Table4, 1);
        assert_eq!(d[0].id, "table-4");
        assert_eq!(d[0].heads.len(), 7, "the paper's seven columns");
        assert_eq!(d[0].rows.len(), 1);
        d[0].rows[0].clone()
    }

    /// By hand, 20 stage opportunities (5 + 5 + 4 + 2 + 4):
    /// * reached 11: T21 moka, second stove, microwave (3); T22 none; T25 01, 02 (2); T28 both (2); T30 all four → 55.0%;
    /// * success 6: T21 moka; T25 01; T28 01; T30 01, 02, 03 → 30.0%;
    /// * Object Manipulation reached 6 (T21 moka; T25 01, 02; T30 01, 02, 04), T25 02 left out (interference),
    ///   successes 4 → 4/5 = 80.0%; Mechanism Interaction reached 5 (T21 second stove, microwave; T28 01, 02; T30 03),
    ///   T21 second stove left out, successes 2 → 2/4 = 50.0%;
    /// * failed 5: local execution T21 microwave, T28 02, T30 04 → 3/5 = 60.0%; interference T21 second stove, T25 02
    ///   → 2/5 = 40.0%.
    #[test]
    fn table_4_over_the_hard_long_horizon_records_is_the_hand_computed_one() {
        let dir = tempfile::tempdir().unwrap();
        let b = golden(dir.path());
        let t = tables(&b, None);
        let d = &t.stage_diagnosis[0].diagnosis;
        assert_eq!((d.rollouts, d.opportunities, d.annotated, d.automatic, d.failed), (5, 20, 0, 20, 5));
        assert_eq!(
            table4_row(&t),
            ["command/golden (L3, none)", "11/20 = 55.0%", "6/20 = 30.0%", "4/5 = 80.0%", "2/4 = 50.0%", "3/5 = 60.0%", "2/5 = 40.0%"]
        );
        assert_eq!((d.object_manipulation.reached, d.object_manipulation.excluded_interference), (6, 1));
        assert_eq!((d.mechanism_interaction.reached, d.mechanism_interaction.excluded_interference), (5, 1));
        // The extension over the same records: T30 01 undone while 02 ran is a failure there (interference), and
        // execution success leaves nothing out: OM 4/6, MI 2/5.
        let x = &t.stage_diagnosis_extension[0].diagnosis;
        assert_eq!((x.opportunities, x.reached.successes, x.success.successes), (20, 11, 6));
        assert_eq!((x.failures, x.local_execution, x.cross_stage_interference), (6, 3, 3));
        let exec: Vec<(u64, u64)> = x.by_type.iter().map(|e| (e.execution_success.successes, e.execution_success.trials)).collect();
        assert_eq!(exec, [(4, 6), (2, 5)]);
        let ext = &display_tables(&t, TableChoice::Table4, 1)[1];
        assert_eq!(ext.id, "table-4-extension");
        assert!(ext.title.starts_with("Table 4+ (all long-horizon tasks T21–T30; extension)"), "{}", ext.title);
        // Markdown and CSV carry the same numbers.
        let md = markdown(&t, TableChoice::Table4, 1);
        assert!(md.contains("| command/golden (L3, none) | 11/20 = 55.0% | 6/20 = 30.0% | 4/5 = 80.0% | 2/4 = 50.0% | 3/5 = 60.0% | 2/5 = 40.0% |"), "{md}");
        assert!(md.contains("20 stage opportunities over 5 rollouts (T21 ×1, T22 ×1, T25 ×1, T28 ×1, T30 ×1); 0 annotated, 20 automatic"), "{md}");
        let csv = csv_blocks(&t, TableChoice::Table4, 1);
        assert_eq!(csv[0].0, "table_4_stage_diagnosis");
        assert!(
            csv[0].1.contains("command/golden,3,none,5,0,20,0,20,11,55.0000,6,30.0000,4,6,1,80.0000,2,5,1,50.0000,5,3,60.0000,2,40.0000,0,0,0\n"),
            "{}",
            csv[0].1
        );
    }

    fn note(reached: bool, succeeded: bool, modes: &[FailureMode]) -> StageAnnotation {
        StageAnnotation {
            reached,
            succeeded,
            failure_modes: modes.to_vec(),
            note: String::new(),
            annotator: "reviewer".into(),
            annotated_at: "2026-01-02T00:00:00Z".into(),
        }
    }

    fn key(episode: &str, stage: &str) -> StageKey {
        StageKey { episode_id: episode.into(), stage_name: stage.into() }
    }

    /// A person sees the frying pan grasped and knocked over by the pot's move (reached, failed, both local execution
    /// and interference: the automatic label says not reached) and the door blocked by the open latch arm placed
    /// wrongly (interference and geometric error, where the automatic label says local execution). By hand:
    /// reached 12/20 = 60.0%; success 6/20 = 30.0%; Object Manipulation reached 7, two left out (the pan, T25 02) →
    /// 4/5 = 80.0%; Mechanism Interaction reached 5, two left out (second stove, door) → 2/3 = 66.7%; failed 6: local
    /// execution microwave, pan, T30 04 → 3/6 = 50.0%; interference second stove, pan, T25 02, door → 4/6 = 66.7%
    /// (the two overlap on the pan: 116.7% together).
    #[test]
    fn annotations_replace_the_automatic_labels_where_they_differ() {
        let dir = tempfile::tempdir().unwrap();
        let b = golden(dir.path());
        let mut notes = StageAnnotations::new();
        use FailureMode::*;
        notes.insert(key("ep-t21", "Frying_Pan_On_First_Stove"), note(true, false, &[LocalExecution, CrossStageInterference]));
        notes.insert(key("ep-t28", "02_Open_Door"), note(true, false, &[CrossStageInterference, GeometricError]));
        // an annotation of another episode's stage changes nothing here
        notes.insert(key("ep-elsewhere", "02_Open_Door"), note(false, false, &[]));
        let t = tables(&b, Some(&notes));
        assert_eq!(
            table4_row(&t),
            ["command/golden (L3, none)", "12/20 = 60.0%", "6/20 = 30.0%", "4/5 = 80.0%", "2/3 = 66.7%", "3/6 = 50.0%", "4/6 = 66.7%"]
        );
        let d = &t.stage_diagnosis[0].diagnosis;
        assert_eq!((d.annotated, d.automatic, d.geometric_error), (2, 18, 1));
        let md = markdown(&t, TableChoice::Table4, 1);
        assert!(md.contains("2 annotated, 18 automatic; failed stages also annotated geometric error 1, other 0, no mode 0"), "{md}");
        // the extension stays automatic
        assert_eq!(t.stage_diagnosis_extension[0].diagnosis.reached.successes, 11);
        assert_ne!(table4_row(&tables(&b, None)), table4_row(&t));
    }

    /// An agent that never touched T28 (nothing completed, the latch's operation without a contact run), whose
    /// record still says its first stage was reached (the old rule): 0 of 2 stages reached.
    #[test]
    fn an_agent_that_never_touched_a_task_reached_none_of_its_stages() {
        let dir = tempfile::tempdir().unwrap();
        let idle = json!({"checker": "private_ordered_stages",
            "stage_diagnostics": [stage("01_Unlatch_Door", Some(MI), true, false), stage("02_Open_Door", Some(MI), false, false)],
            "stage_events": [], "details": {"order": "ordered", "opening_operations": [opening("01_Unlatch_Door", 1200, &[], false)]}});
        let b = vec![write_batch(dir.path(), &[(28, 2, 0, idle)])];
        let t = tables(&b, None);
        assert_eq!(table4_row(&t), ["command/golden (L3, none)", "0/2 = 0.0%", "0/2 = 0.0%", "—", "—", "—", "—"]);
        assert_eq!(t.stage_diagnosis_extension[0].diagnosis.reached.successes, 0);
    }

    /// Cells as the paper writes them (`3/3`, `1.80/3`), and the long-horizon table's K row from the task facts.
    #[test]
    fn appendix_e_writes_x_over_reps_and_sum_over_reps_with_a_k_row() {
        let cell = |value: Option<f64>, valid: usize| AppendixCell { task: "T01".into(), value, valid_rollouts: valid };
        assert_eq!(appendix_text(&cell(Some(3.0), 3), false, 3), "3/3");
        assert_eq!(appendix_text(&cell(Some(0.0), 4), false, 3), "0/3");
        assert_eq!(appendix_text(&cell(Some(1.8), 3), true, 3), "1.80/3");
        assert_eq!(appendix_text(&cell(Some(0.0), 3), true, 3), "0.00/3");
        assert_eq!(appendix_text(&cell(Some(1.0), 2), false, 3), "1/2 valid");
        assert_eq!(appendix_text(&cell(None, 1), true, 3), "—");

        let dir = tempfile::tempdir().unwrap();
        let t = tables(&golden(dir.path()), None);
        let long = display_tables(&t, TableChoice::Appendix, 1).into_iter().find(|d| d.id == "appendix-e-long-horizon").unwrap();
        assert_eq!(long.heads[2..], ["T21", "T22", "T23", "T24", "T25", "T26", "T27", "T28", "T29", "T30"]);
        // The paper's K: T21 5, T22 5, T23 8, T24 4, T25 4, T26 3, T27 4, T28 2, T29 3, T30 4.
        assert_eq!(long.rows[0], ["K (stages)", "", "5", "5", "8", "4", "4", "3", "4", "2", "3", "4"]);
        // c/K of each rollout: T21 1/5, T22 0/5, T25 1/4, T28 1/2, T30 3/4, over 1 rollout.
        assert_eq!(long.rows[1][2..], ["0.20/1", "0.00/1", "—", "—", "0.25/1", "—", "—", "0.50/1", "—", "0.75/1"]);
        let csv = csv_blocks(&t, TableChoice::Appendix, 1);
        let (_, body) = csv.iter().find(|(n, _)| n == "appendix_e_long_horizon").unwrap();
        assert!(body.contains("\nK,,,5,5,8,4,4,3,4,2,3,4\n"), "{body}");
        assert!(body.contains("\ncommand/golden,3,none,0.20/1,0.00/1,,,0.25/1,,,0.50/1,,0.75/1\n"), "{body}");
    }
}
