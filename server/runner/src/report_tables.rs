//! The paper's tables after Table 1 and its Figure 3, across the batches of one agent (`report`, the Results page):
//!
//! * Table 2, observation ablation (T11–T20 stable SR at levels 1/2/3): levels 1 and 2 from the agent's
//!   `manip_observation` batch, level 3 from its `main_table` batch (level 3, no demonstration);
//! * Table 3, demonstration ablation (T21–T30 stable SC with None / Video / Video + Traj.): the demonstrations from its
//!   `context` batch, None from its `main_table` batch;
//! * Table 4, the stage-level diagnosis of the long-horizon tasks, from each rollout's private stage diagnostics
//!   (`result.json` → `private_evaluation.stage_diagnostics`, with the stage types the catalog declares);
//! * Figure 3, the sustained-contact ratio of every opening operation (`private_evaluation.details.opening_operations`);
//! * Appendix E, the per-task tables in wide format.
//!
//! Rollouts are grouped by agent (`harness/model`) and condition exactly as Table 1's rows, whichever batch they came
//! from; Tables 4 and Figure 3 read the rollouts the stable rule reads (per task, the first `reps` valid ones) through
//! their run directories, and count those whose record cannot be read.
use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::Path;
use std::sync::OnceLock;

use libero_metrics::{
    AblationKind, AblationRow, ContactSummary, OpeningOperation, Proportion, Split, StageDiagnosis, StageOpportunity, StageType,
    diagnose, summarize, summarize_contact,
};
use libero_episode::records::{PrivateEvaluation, RunDir, read_result};
use serde::Serialize;

use crate::batch::{Condition, LoadedBatch, RolloutRecord, agent_of};
use crate::report::{Row, cell, pct, wilson};
use crate::schedule::Demo;

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

/// Table 4 for one agent under one condition.
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

/// Figure 3's numbers for one agent under one condition (`pool`: its task-pool rollouts).
#[derive(Debug, Clone, Serialize)]
pub struct ContactLine {
    pub agent: String,
    /// `L3, none`, `L3, video`, …, or `pool`.
    pub condition: String,
    #[serde(flatten)]
    pub summary: ContactSummary,
    pub opening_operations: Vec<OpeningOperation>,
    pub rollouts_without_record: usize,
}

impl ContactLine {
    pub fn label(&self) -> String {
        format!("{} ({})", self.agent, self.condition)
    }
}

/// One task of an Appendix E row: successes (perception, short horizon) or the sum of `c/K` (long horizon).
#[derive(Debug, Clone, Serialize)]
pub struct AppendixCell {
    pub task: String,
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
    pub rows: Vec<AppendixLine>,
}

/// Tables 2–4, Figure 3's data and Appendix E.
#[derive(Debug, Clone, Serialize)]
pub struct PaperTables {
    pub observation_ablation: Vec<AblationTable>,
    pub demonstration_ablation: Vec<AblationTable>,
    pub stage_diagnosis: Vec<DiagnosisLine>,
    pub sustained_contact: Vec<ContactLine>,
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

/// The rollout's private evaluation (`<run_dir>/result.json` → `private_evaluation`), if it can be read here.
fn private_evaluation(r: &RolloutRecord) -> Option<PrivateEvaluation> {
    read_result(&RunDir::new(r.run_dir.as_deref()?))?.private_evaluation
}

/// Stage types the catalog declares, per task number: for records written before the evaluator reported them.
fn catalog_stage_types() -> &'static BTreeMap<u32, Vec<(String, Option<StageType>)>> {
    static TYPES: OnceLock<BTreeMap<u32, Vec<(String, Option<StageType>)>>> = OnceLock::new();
    TYPES.get_or_init(|| {
        let Ok(catalog) = libero_tasks::Catalog::discover() else { return BTreeMap::new() };
        catalog.tasks().iter().filter_map(|t| Some((t.number, t.checker.stage_types().ok()?))).collect()
    })
}

/// The required stages of one long-horizon rollout's record as Table 4's opportunities.
fn opportunities(r: &RolloutRecord, pe: &PrivateEvaluation) -> Vec<StageOpportunity> {
    let declared = catalog_stage_types().get(&r.task_number);
    let stages = pe.stage_diagnostics.as_deref().unwrap_or_default();
    stages
        .iter()
        .filter(|d| d.required == Some(true))
        .map(|d| {
            let name = d.stage_name.clone().unwrap_or_default();
            let recorded = d.stage_type.clone().and_then(|t| serde_json::from_value::<StageType>(t).ok());
            let from_catalog = || declared.and_then(|ts| ts.iter().find(|(n, _)| *n == name)).and_then(|(_, t)| *t);
            StageOpportunity {
                task_number: r.task_number,
                stage_type: recorded.or_else(from_catalog),
                reached: d.reached == Some(true),
                succeeded: d.succeeded == Some(true),
                regressions: d.regressions.map_or(0, |n| n as u32),
                regressed_during_later_stage: d.regressed_during_later_stage == Some(true),
                // A strict order latched by a later stage's state made early: that state blocked this stage.
                blocked_by_other_stage: d.failure_reason.as_ref().and_then(Option::as_deref) == Some("order_violation"),
                stage_name: name,
            }
        })
        .collect()
}

/// The opening operations of one rollout's record (Figure 3). Records from before operations carried a direction
/// name their opening stages `…Open…`/`…Unlatch…`.
fn opening_operations(r: &RolloutRecord, pe: &PrivateEvaluation) -> Vec<OpeningOperation> {
    let ops = pe.details.as_ref().and_then(|d| d.opening_operations.as_deref()).unwrap_or_default();
    let succeeded = |stage: &str| {
        pe.stage_diagnostics.iter().flatten().any(|d| d.stage_name.as_deref() == Some(stage) && d.succeeded == Some(true))
    };
    ops.iter()
        .filter(|o| match o.operation.as_deref() {
            Some(kind) => kind == "open",
            None => o.stage_name.as_deref().is_some_and(|s| {
                let s = s.to_ascii_lowercase();
                s.contains("open") || s.contains("unlatch")
            }),
        })
        .filter(|o| o.exec_steps.is_some_and(|n| n > 0))
        .map(|o| {
            let stage = o.stage_name.clone();
            OpeningOperation {
                task: r.task.clone(),
                opened: o.completed.unwrap_or_else(|| stage.as_deref().is_some_and(succeeded)),
                stage_name: stage,
                scr_percent: o.sustained_contact_ratio_percent.unwrap_or(0.0),
                exec_steps: o.exec_steps.unwrap_or(0),
            }
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

/// The three wide tables of Appendix E over Table 1's rows.
fn appendix(rows: &[Row]) -> Vec<AppendixTable> {
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
                            value: t.and_then(|t| if long { t.stage_fraction_sum } else { Some(t.successes as f64) }),
                            valid_rollouts: t.map_or(0, |t| t.valid_rollouts),
                        }
                    })
                    .collect(),
            })
            .collect();
        AppendixTable { name, title, rows: lines }
    };
    vec![
        table("perception", "Perception tasks", &[Split::Perception], false),
        table("short_horizon", "Short-horizon tasks", &[Split::ShortHorizonEasy, Split::ShortHorizonHard], false),
        table("long_horizon", "Long-horizon tasks: stage fractions", &[Split::LongHorizonEasy, Split::LongHorizonHard], true),
    ]
}

/// Everything after Table 1, from the batches and Table 1's rows over them.
pub fn paper_tables(batches: &[LoadedBatch], rows: &[Row], reps: usize) -> PaperTables {
    let names = batch_names(batches);
    let mut diagnosis: BTreeMap<(String, Condition), (Vec<StageOpportunity>, usize, usize)> = BTreeMap::new();
    let mut contact: BTreeMap<(String, String), (Vec<OpeningOperation>, usize)> = BTreeMap::new();
    let mut by_agent: BTreeMap<String, Vec<&RolloutRecord>> = BTreeMap::new();
    for b in batches {
        by_agent.entry(agent_of(b)).or_default().extend(&b.records);
    }
    for (agent, records) in &by_agent {
        for r in counted(records.iter().copied(), reps) {
            let condition = Condition { level: r.level, demo: r.demo };
            let group = if r.suite.is_some() { "pool".to_owned() } else { condition_label(condition) };
            let pe = private_evaluation(r);
            let c = contact.entry((agent.clone(), group)).or_default();
            match &pe {
                Some(pe) => c.0.extend(opening_operations(r, pe)),
                None => c.1 += 1,
            }
            if r.suite.is_none() && r.split.is_some_and(Split::is_long_horizon) {
                let d = diagnosis.entry((agent.clone(), condition)).or_default();
                d.1 += 1;
                match &pe {
                    Some(pe) => d.0.extend(opportunities(r, pe)),
                    None => d.2 += 1,
                }
            }
        }
    }
    PaperTables {
        observation_ablation: ablations(AblationKind::Observation, rows, &names, reps),
        demonstration_ablation: ablations(AblationKind::Demonstration, rows, &names, reps),
        stage_diagnosis: diagnosis
            .into_iter()
            .map(|((agent, c), (ops, rollouts, missing))| DiagnosisLine {
                agent,
                level: c.level,
                demo: c.demo,
                diagnosis: diagnose(&ops, rollouts - missing),
                rollouts_without_record: missing,
            })
            .collect(),
        sustained_contact: contact
            .into_iter()
            .filter(|(_, (ops, missing))| !ops.is_empty() || *missing > 0)
            .map(|((agent, condition), (ops, missing))| ContactLine {
                agent,
                condition,
                summary: summarize_contact(&ops),
                opening_operations: ops,
                rollouts_without_record: missing,
            })
            .collect(),
        appendix_e: appendix(rows),
    }
}

// --------------------------------------------------------------------------------------------- cells

/// A stable percentage, with (scored/member) when partial.
fn partial(value: Option<f64>, scored: usize, member: usize) -> String {
    if scored == member { pct(value) } else { format!("{} ({scored}/{member})", pct(value)) }
}

/// `k/n = p%`.
fn share(p: &Proportion) -> String {
    match p.rate {
        Some(r) => format!("{}/{} = {:.1}%", p.successes, p.trials, 100.0 * r),
        None => "—".into(),
    }
}

fn of_type(d: &StageDiagnosis, t: StageType) -> Option<&libero_metrics::TypeExecution> {
    d.by_type.iter().find(|x| x.stage_type == t)
}

/// An Appendix E cell: successes (`x/valid` when fewer than `reps` are valid), or the `c/K` sum to 2 decimals.
fn appendix_text(cell: &AppendixCell, long: bool, reps: usize) -> String {
    match (cell.value, long) {
        (None, _) => "—".into(),
        (Some(v), true) => format!("{v:.2}"),
        (Some(v), false) if cell.valid_rollouts == reps => format!("{v:.0}"),
        (Some(v), false) => format!("{v:.0}/{}", cell.valid_rollouts),
    }
}

fn r_text(r: Option<f64>) -> String {
    r.map(|r| format!("{r:.3}")).unwrap_or_else(|| "—".into())
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

/// One table as text cells: what Markdown, LaTeX and the Results page show.
#[derive(Debug, Clone, PartialEq)]
pub struct DisplayTable {
    /// `table-2`, `figure-3`, `appendix-e-short-horizon`, … (the page's element id).
    pub id: String,
    pub title: String,
    /// What the numbers mean and where they come from (the whole body when `rows` is empty).
    pub note: String,
    pub heads: Vec<String>,
    pub rows: Vec<Vec<String>>,
}

fn strings<const N: usize>(heads: [&str; N]) -> Vec<String> {
    heads.map(str::to_owned).to_vec()
}

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
        id: "table-4".into(),
        title: "Stage-level diagnosis (Table 4; long-horizon tasks T21–T30)".into(),
        note: if lines.is_empty() {
            "No long-horizon rollout in the report.".into()
        } else {
            "Automatic labels from each rollout's private stage record, not the paper's manual annotation (docs/reports.md): a \
             stage opportunity is one required stage of one counted rollout; execution success = successes / reached stages \
             of that type [95% Wilson]; a failure is a reached stage that did not succeed or a completed stage a later stage \
             undid, counted as cross-stage interference when a completed stage regressed or an order violation blocked it, \
             else local execution."
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

fn contact_display(lines: &[ContactLine]) -> [DisplayTable; 2] {
    let mut heads = strings(["Agent", "Condition", "Opening operations", "Mean SCR", "Local opening success", "Pearson r (SCR, success)"]);
    heads.extend(libero_metrics::ScrBin::ALL.iter().map(|b| format!("SCR {} [95% Wilson]", b.label())));
    let rows = lines
        .iter()
        .map(|l| {
            let s = &l.summary;
            let mut row = vec![
                l.agent.clone(),
                l.condition.clone(),
                format!("{}{}", s.operations, without_record(l.rollouts_without_record)),
                s.mean_scr_percent.map(|m| format!("{m:.1}%")).unwrap_or_else(|| "—".into()),
                share(&s.local_success),
                r_text(s.pearson_r),
            ];
            row.extend(s.bins.iter().map(|b| wilson(&b.local_success)));
            row
        })
        .collect();
    let operations = lines
        .iter()
        .flat_map(|l| {
            l.opening_operations.iter().map(move |op| {
                vec![
                    l.agent.clone(),
                    l.condition.clone(),
                    op.task.clone(),
                    op.stage_name.clone().unwrap_or_else(|| "—".into()),
                    format!("{:.1}%", op.scr_percent),
                    op.exec_steps.to_string(),
                    if op.opened { "yes" } else { "no" }.into(),
                ]
            })
        })
        .collect();
    [
        DisplayTable {
            id: "figure-3".into(),
            title: "Sustained-contact ratio of opening operations (Figure 3)".into(),
            note: if lines.is_empty() {
                "No opening operation in the report.".into()
            } else {
                "SCR = N_sustained / N_exec × 100%: the share of an operation's control steps inside gripper–mechanism contact \
                 runs of ≥ 5 steps. Local opening success: the opening completed, whatever the rest of the task did; per SCR \
                 bin with 95% Wilson intervals; Pearson r over operations. `report --figures DIR` draws these as SVG."
                    .into()
            },
            heads,
            rows,
        },
        DisplayTable {
            id: "figure-3-operations".into(),
            title: "Opening operations (Figure 3's data)".into(),
            note: String::new(),
            heads: strings(["Agent", "Condition", "Task", "Stage", "SCR", "N_exec", "Opened"]),
            rows: operations,
        },
    ]
}

fn appendix_display(t: &AppendixTable, reps: usize) -> DisplayTable {
    let long = t.name == "long_horizon";
    let unit = if long { format!("sum of c/K over {reps} rollouts") } else { format!("successes out of {reps}") };
    let mut heads = strings(["Agent", "Condition"]);
    heads.extend(t.rows.first().into_iter().flat_map(|r| r.cells.iter().map(|c| c.task.clone())));
    let rows = t
        .rows
        .iter()
        .map(|r| {
            let mut row = vec![r.agent.clone(), condition_label(Condition { level: r.level, demo: r.demo })];
            row.extend(r.cells.iter().map(|c| appendix_text(c, long, reps)));
            row
        })
        .collect();
    DisplayTable { id: format!("appendix-e-{}", t.name.replace('_', "-")), title: format!("Appendix E: {} ({unit})", t.title), note: String::new(), heads, rows }
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
        out.push(diagnosis_display(&t.stage_diagnosis));
    }
    if choice.wants(TableChoice::Figure3) {
        out.extend(contact_display(&t.sustained_contact));
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

/// A CSV field, quoted where it needs to be.
fn field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) { format!("\"{}\"", s.replace('"', "\"\"")) } else { s.to_owned() }
}

/// A fraction in [0, 1] as a percentage with 4 decimals, empty when unknown.
fn p4(x: Option<f64>) -> String {
    x.map(|v| format!("{:.4}", 100.0 * v)).unwrap_or_default()
}

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

fn csv_contact(o: &mut String, lines: &[ContactLine]) {
    let _ = writeln!(o, "agent,condition,scr_bin,operations,opened,local_success_percent,wilson_low_percent,wilson_high_percent,mean_scr_percent,pearson_r");
    for l in lines {
        let s = &l.summary;
        let mean = s.mean_scr_percent.map(|m| format!("{m:.4}")).unwrap_or_default();
        let r = s.pearson_r.map(|r| format!("{r:.6}")).unwrap_or_default();
        for b in s.bins.iter().map(|b| (b.label.as_str(), &b.local_success)).chain([("all", &s.local_success)]) {
            let (label, p) = b;
            let _ = writeln!(
                o,
                "{},{},{},{},{},{},{},{},{mean},{r}",
                field(&l.agent), field(&l.condition), field(label), p.trials, p.successes, p4(p.rate), p4(p.wilson_low), p4(p.wilson_high)
            );
        }
    }
}

fn csv_operations(o: &mut String, lines: &[ContactLine]) {
    let _ = writeln!(o, "agent,condition,task,stage,scr_percent,exec_steps,opened");
    for l in lines {
        for op in &l.opening_operations {
            let _ = writeln!(
                o,
                "{},{},{},{},{:.4},{},{}",
                field(&l.agent), field(&l.condition), field(&op.task), field(op.stage_name.as_deref().unwrap_or("")), op.scr_percent,
                op.exec_steps, op.opened
            );
        }
    }
}

fn csv_appendix(o: &mut String, t: &AppendixTable, reps: usize) {
    let Some(first) = t.rows.first() else { return };
    let heads: Vec<&str> = first.cells.iter().map(|c| c.task.as_str()).collect();
    let _ = writeln!(o, "agent,level,demo,{}", heads.join(","));
    let long = t.name == "long_horizon";
    for r in &t.rows {
        let cells: Vec<String> = r.cells.iter().map(|c| if c.value.is_none() { String::new() } else { appendix_text(c, long, reps) }).collect();
        let _ = writeln!(o, "{},{},{},{}", field(&r.agent), r.level, r.demo.as_str(), cells.join(","));
    }
}

/// One `(name, CSV)` block per table `choice` selects (Figure 3: its bins and its operations; Appendix E: three).
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
        block("table_4_stage_diagnosis", &|o| csv_diagnosis(o, &t.stage_diagnosis));
    }
    if choice.wants(TableChoice::Figure3) {
        block("figure_3_scr_bins", &|o| csv_contact(o, &t.sustained_contact));
        block("figure_3_opening_operations", &|o| csv_operations(o, &t.sustained_contact));
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

/// Figure 3 as files in `dir`: the two SVG plots and the data behind them (CSV, JSON). Returns the paths written.
pub fn write_figures(t: &PaperTables, dir: &Path) -> std::io::Result<Vec<std::path::PathBuf>> {
    std::fs::create_dir_all(dir)?;
    let mut data = String::new();
    csv_contact(&mut data, &t.sustained_contact);
    let mut ops = String::new();
    csv_operations(&mut ops, &t.sustained_contact);
    let json = serde_json::to_string_pretty(&t.sustained_contact).map_err(std::io::Error::other)? + "\n";
    let files = [
        ("figure3_success_by_scr_bin.svg", crate::report::svg::success_by_bin(&t.sustained_contact)),
        ("figure3_mean_scr.svg", crate::report::svg::mean_scr(&t.sustained_contact)),
        ("figure3_scr_bins.csv", data),
        ("figure3_opening_operations.csv", ops),
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
