//! Figure 3 as the paper computes it (§5.3): the sustained-contact ratio of the opening operations of the long-horizon
//! stage analysis. [`libero_metrics::figure3`] does the arithmetic; here the report decides which operations enter:
//!
//! * **Rollouts**: those of the stage analysis — the main table's long-horizon rollouts (T21–T30 at level 3 without
//!   a demonstration, as the paper's stage analysis reads its main runs), per task the first `reps` valid ones (the
//!   stable rule's). The short-horizon T15/T16, the pool, and the ablation conditions are not read.
//! * **Operations**: each recorded opening (`details.opening_operations[]` with `operation: open`; older records name
//!   their opening stages `…Open…`/`…Unlatch…`) of at least one control step.
//! * **Entered**: the operation's stage was *reached* by the stage analysis's rule (Table 4's evidence,
//!   [`libero_metrics::StageEvidence::reached`]): its goal held at some point, or (ordered stages after the first) the
//!   stage before it completed so the agent was at it, or the gripper touched the mechanism anywhere during the
//!   operation, or the agent acted on the task while it was current. An opening the agent never got to — a pending
//!   unordered goal nobody touched, a first stage left alone — is no operation of the analysis and is left out (the
//!   paper's 64 operations are those its annotators saw the agent attempt). An operation whose stage has no diagnostic
//!   is entered when its mechanism was touched or it opened.
//! * **SCR**: from the record's `handle_contact_runs` (gripper–handle contact only) and `exec_steps`, by the
//!   paper's definition; an operation recorded before handle contact was told apart has none and is left out (counted).
//!
//! (a) is each agent's mean SCR over its entered operations; (b) the local opening success per SCR bin with 95 %
//! Wilson intervals and Pearson's r, pooled over every agent's entered operations.
use std::fmt::Write as _;

use libero_records::records::{MechanismOperation, PrivateEvaluation};
use libero_metrics::{Figure3, OpeningOperation, Split, StageOpportunity, figure3};
use serde::Serialize;

use crate::batch::{Demo, RolloutRecord};
use crate::display::{DisplayTable, field, p4, r_text, share, strings};
use crate::stages::touched;
use crate::wilson;

/// Figure 3 with the operations it was computed from.
#[derive(Debug, Clone, Serialize)]
pub struct Figure3Data {
    #[serde(flatten)]
    pub figure: Figure3,
    /// Every opening operation read, entered or not, in rollout order.
    pub operations: Vec<OpeningOperation>,
    /// Rollouts of the stage analysis read, and those whose record could not be read here.
    pub rollouts: usize,
    pub rollouts_without_record: usize,
}

impl Figure3Data {
    pub fn new(operations: Vec<OpeningOperation>, rollouts: usize, rollouts_without_record: usize) -> Self {
        Self { figure: figure3(&operations), operations, rollouts, rollouts_without_record }
    }

    /// Nothing to show: no operation read and no record missing.
    pub fn is_empty(&self) -> bool {
        self.operations.is_empty() && self.rollouts_without_record == 0
    }
}

/// A rollout of the stage analysis: the main table's long-horizon rollouts (level 3, no demonstration).
pub fn in_stage_analysis(r: &RolloutRecord) -> bool {
    r.suite.is_none() && r.split.is_some_and(Split::is_long_horizon) && r.level == 3 && r.demo == Demo::None
}

/// An opening, by its direction or (older records) its stage's name.
fn is_opening(o: &MechanismOperation) -> bool {
    match o.operation.as_deref() {
        Some(kind) => kind == "open",
        None => o.stage_name.as_deref().is_some_and(|s| {
            let s = s.to_ascii_lowercase();
            s.contains("open") || s.contains("unlatch")
        }),
    }
}

/// The opening operations of one rollout of `agent`, each marked entered by its stage's opportunity in `stages`.
pub fn operations(agent: &str, r: &RolloutRecord, pe: &PrivateEvaluation, stages: &[StageOpportunity]) -> Vec<OpeningOperation> {
    let ops = pe.details.as_ref().and_then(|d| d.opening_operations.as_deref()).unwrap_or_default();
    let succeeded = |stage: &str| {
        pe.stage_diagnostics.iter().flatten().any(|d| d.stage_name.as_deref() == Some(stage) && d.succeeded == Some(true))
    };
    ops.iter()
        .filter(|o| is_opening(o) && o.exec_steps.is_some_and(|n| n > 0))
        .map(|o| {
            let stage = o.stage_name.clone();
            let opened = o.completed.unwrap_or_else(|| stage.as_deref().is_some_and(succeeded));
            let reached = stages.iter().find(|s| Some(&s.stage_name) == stage.as_ref()).map(|s| s.evidence.reached());
            OpeningOperation {
                episode_id: r.episode_id.clone(),
                entered: reached.unwrap_or_else(|| touched(o) || opened),
                opened,
                ..OpeningOperation::new(agent, &r.task, stage, o.exec_steps.unwrap_or(0), o.handle_contact_runs.clone())
            }
        })
        .collect()
}

fn percent(x: Option<f64>) -> String {
    x.map(|m| format!("{m:.1}%")).unwrap_or_else(|| "—".into())
}

fn yes_no(b: bool) -> String {
    if b { "yes" } else { "no" }.into()
}

fn runs_text(runs: Option<&[u64]>, sep: &str) -> String {
    runs.map(|r| r.iter().map(u64::to_string).collect::<Vec<_>>().join(sep)).unwrap_or_default()
}

/// What the figure stands on, for the notes.
fn basis(d: &Figure3Data) -> String {
    let f = &d.figure;
    let mut left = vec![format!("{} not entered", f.not_entered)];
    if f.without_handle_runs > 0 {
        left.push(format!("{} recorded without handle contact runs (before handles were declared)", f.without_handle_runs));
    }
    if d.rollouts_without_record > 0 {
        left.push(format!("{} rollouts without record", d.rollouts_without_record));
    }
    format!(
        "{} opening operations of {} long-horizon rollouts (T21–T30, L3, no demonstration; the stable rule's) read, {} counted; left out: {}.",
        d.operations.len(),
        d.rollouts,
        f.pooled.operations,
        left.join(", ")
    )
}

/// Figure 3(a), 3(b) and the operations as display tables.
pub fn display(d: &Figure3Data) -> [DisplayTable; 3] {
    let f = &d.figure;
    let agents = f
        .agents
        .iter()
        .map(|a| vec![a.agent.clone(), a.operations.to_string(), percent(a.mean_scr_percent), share(&a.local_success)])
        .collect();
    let mut bins: Vec<Vec<String>> = f
        .pooled
        .bins
        .iter()
        .map(|b| {
            let p = &b.local_success;
            vec![format!("SCR {}", b.label), p.trials.to_string(), p.successes.to_string(), wilson(p), String::new()]
        })
        .collect();
    let all = &f.pooled.local_success;
    bins.push(vec!["all".into(), all.trials.to_string(), all.successes.to_string(), wilson(all), r_text(f.pooled.pearson_r)]);
    if d.is_empty() {
        bins.clear();
    }
    let operations = d
        .operations
        .iter()
        .map(|o| {
            vec![
                o.agent.clone(),
                o.task.clone(),
                o.stage_name.clone().unwrap_or_else(|| "—".into()),
                o.exec_steps.to_string(),
                o.handle_contact_runs.as_deref().map_or_else(|| "— (not recorded)".into(), |r| format!("[{}]", runs_text(Some(r), ", "))),
                percent(o.scr_percent),
                yes_no(o.entered),
                yes_no(o.opened),
                yes_no(o.counted().is_some()),
            ]
        })
        .collect();
    let definition = "SCR = N_sustained / N_exec × 100%, N_sustained the control steps inside gripper–handle contact runs of ≥ 5 steps \
                      (the handle geoms tasks/mechanism_handles.json declares; contact elsewhere on a door or drawer does not count). An \
                      operation counts when entered: its stage was reached in the stage analysis (Table 4's evidence).";
    [
        DisplayTable {
            id: "figure-3".into(),
            title: "Figure 3(a): mean sustained-contact ratio of opening operations, per agent".into(),
            note: if d.is_empty() {
                "No opening operation of the stage analysis (long-horizon main-table rollouts) in the report.".into()
            } else {
                format!("{definition} {} `report --figures DIR` draws (a) and (b) as one SVG.", basis(d))
            },
            heads: strings(["Agent", "Opening operations", "Mean SCR", "Local opening success"]),
            rows: agents,
        },
        DisplayTable {
            id: "figure-3-bins".into(),
            title: "Figure 3(b): local opening success by SCR bin, every agent's operations pooled".into(),
            note: if d.is_empty() {
                String::new()
            } else {
                format!(
                    "Local opening success: the opening completed, whatever the rest of the task did; 95% Wilson intervals. Pearson r \
                     between SCR and local success (0/1) over the {} pooled operations: {}.",
                    f.pooled.operations,
                    r_text(f.pooled.pearson_r)
                )
            },
            heads: strings(["SCR bin", "Operations", "Opened", "Local opening success [95% Wilson]", "Pearson r (SCR, success)"]),
            rows: bins,
        },
        DisplayTable {
            id: "figure-3-operations".into(),
            title: "Opening operations (Figure 3's data)".into(),
            note: String::new(),
            heads: strings(["Agent", "Task", "Stage", "N_exec", "Handle contact runs", "SCR", "Entered", "Opened", "Counted"]),
            rows: operations,
        },
    ]
}

/// Figure 3(a) as CSV: one line per agent.
pub fn csv_mean(o: &mut String, d: &Figure3Data) {
    let _ = writeln!(o, "agent,operations,mean_scr_percent,opened,local_success_percent,wilson_low_percent,wilson_high_percent");
    for a in &d.figure.agents {
        let p = &a.local_success;
        let mean = a.mean_scr_percent.map(|m| format!("{m:.4}")).unwrap_or_default();
        let _ = writeln!(o, "{},{},{mean},{},{},{},{}", field(&a.agent), a.operations, p.successes, p4(p.rate), p4(p.wilson_low), p4(p.wilson_high));
    }
}

/// Figure 3(b) as CSV: one line per bin and an `all` line with Pearson's r.
pub fn csv_bins(o: &mut String, d: &Figure3Data) {
    let _ = writeln!(o, "scr_bin,operations,opened,local_success_percent,wilson_low_percent,wilson_high_percent,pearson_r");
    let s = &d.figure.pooled;
    let r = s.pearson_r.map(|r| format!("{r:.6}")).unwrap_or_default();
    for (label, p, r) in s.bins.iter().map(|b| (b.label.as_str(), &b.local_success, "")).chain([("all", &s.local_success, r.as_str())]) {
        let _ = writeln!(o, "{},{},{},{},{},{},{r}", field(label), p.trials, p.successes, p4(p.rate), p4(p.wilson_low), p4(p.wilson_high));
    }
}

/// Every opening operation read, as CSV (`handle_contact_runs` space-separated; empty when not recorded).
pub fn csv_operations(o: &mut String, d: &Figure3Data) {
    let _ = writeln!(o, "agent,task,episode_id,stage,exec_steps,handle_contact_runs,scr_percent,entered,opened,counted");
    for op in &d.operations {
        let _ = writeln!(
            o,
            "{},{},{},{},{},{},{},{},{},{}",
            field(&op.agent),
            field(&op.task),
            field(op.episode_id.as_deref().unwrap_or("")),
            field(op.stage_name.as_deref().unwrap_or("")),
            op.exec_steps,
            runs_text(op.handle_contact_runs.as_deref(), " "),
            op.scr_percent.map(|s| format!("{s:.4}")).unwrap_or_default(),
            op.entered,
            op.opened,
            op.counted().is_some()
        );
    }
}
