//! The paper's reports: Table 1 here, Tables 2–4, Figure 3's data and Appendix E in [`tables`] (which operations
//! Figure 3 counts: [`figure3`]), its plot in [`svg`], in Markdown, CSV, LaTeX and JSON ([`report_json`], what the
//! dashboard's Results page reads), from batches read by [`batch`]. Rollouts are grouped by agent (`harness/model`)
//! and condition (level, demonstration); several batches of the same agent combine (a re-run of INVALID rollouts,
//! and the main table, observation and context batches whose conditions Tables 2 and 3 put side by side).
//!
//! Why a crate of its own: reports compute from records alone (`batch.json`, `rollouts.jsonl`, run directories'
//! `result.json`, stage annotations), so this crate links neither the simulator nor the runner's sandbox, and the
//! console reads batches and prints tables through it without linking either. What the report needs of the task
//! catalog beyond the records comes in as plain data ([`TaskFacts`], filled by the caller).
pub mod annotations;
pub mod batch;
pub mod display;
pub mod figure3;
pub mod stages;
pub mod svg;
pub mod tables;
pub mod tokens;
pub mod usage;
pub mod versions;

use std::fmt::Write as _;

use tables::TableChoice;
use tokens::{RolloutTokens, TokenSummary};
use versions::HarnessVersions;

use libero_metrics::TaskFacts;
use libero_metrics::{PoolSummary, Proportion, Split, SuiteSummary, summarize, summarize_pool};
use libero_records::batch_doc::ToolboxDoc;
use serde_json::{Value, json};

use crate::batch::{Condition, LoadedBatch, RolloutRecord, agent_of, metrics_rollouts, pool_rollouts};

/// One agent under one condition.
pub struct Row {
    pub agent: String,
    pub condition: Condition,
    pub summary: SuiteSummary,
}

/// The stable rule's repetitions a batch was run with (its `--reps`), if its settings say.
pub fn batch_reps(b: &LoadedBatch) -> Option<usize> {
    b.batch.settings.as_ref()?.reps.map(|n| n as usize).filter(|&n| n > 0)
}

/// The repetitions `report` and the Results page use unless told otherwise: the first batch's own `--reps` (so a
/// 1-rep batch is judged on 1 rollout per task in both), else the paper's 3.
pub fn default_reps(batches: &[LoadedBatch]) -> usize {
    batches.first().and_then(batch_reps).unwrap_or(libero_metrics::PAPER_REPS)
}

/// The records of a Table 1 row: the agent's rollouts under the row's condition, from every batch (pool rollouts
/// are not in the paper's rows).
pub fn row_records<'a>(batches: &'a [LoadedBatch], agent: &str, condition: Condition) -> Vec<&'a RolloutRecord> {
    batches
        .iter()
        .filter(|b| agent_of(b) == agent)
        .flat_map(|b| b.records.iter())
        .filter(|r| r.suite.is_none() && r.level == condition.level && r.demo == condition.demo)
        .collect()
}

/// The harness versions a Table 1 row's rollouts ran ([`row_records`]' rollouts, each batch's own).
pub fn row_versions(batches: &[LoadedBatch], agent: &str, condition: Condition) -> HarnessVersions {
    let of_agent = batches.iter().filter(|b| agent_of(b) == agent);
    HarnessVersions::of(of_agent, |r| r.suite.is_none() && r.level == condition.level && r.demo == condition.demo)
}

/// The records of one pool suite of an agent.
pub fn suite_records<'a>(batches: &'a [LoadedBatch], agent: &str, suite: &str) -> Vec<&'a RolloutRecord> {
    batches.iter().filter(|b| agent_of(b) == agent).flat_map(|b| b.records.iter()).filter(|r| r.suite.as_deref() == Some(suite)).collect()
}

/// The tokens of a row's rollouts with their sources: the summary, and every rollout's figures.
fn tokens_json(records: &[&RolloutRecord]) -> (Value, Value) {
    let per_rollout: Vec<Value> = records
        .iter()
        .map(|r| json!({"rollout_id": r.rollout_id, "task": r.task, "repetition": r.repetition, "outcome": r.outcome,
            "tokens": RolloutTokens::of(r)}))
        .collect();
    (json!(TokenSummary::of(records.iter().copied())), Value::Array(per_rollout))
}

/// Computes every (agent, condition) summary of the batches.
pub fn rows(batches: &[LoadedBatch], reps: usize) -> Vec<Row> {
    metrics_rollouts(batches)
        .into_iter()
        .map(|((agent, condition), rollouts)| Row { agent, condition, summary: summarize(&rollouts, reps) })
        .collect()
}

/// Every agent's pool summary (rollouts of `run --experiment pool`), per suite; never part of the Score.
pub fn pool_rows(batches: &[LoadedBatch], reps: usize) -> Vec<(String, PoolSummary)> {
    pool_rollouts(batches).into_iter().map(|(agent, rs)| (agent, summarize_pool(&rs, reps))).collect()
}

/// The report as JSON: batches (settings, harness version, counts), per-row summaries (Table 1), and Tables 2–4,
/// Figure 3's data and Appendix E across the batches of each agent.
pub fn report_json(batches: &[LoadedBatch], reps: usize, facts: &TaskFacts) -> Value {
    let table1 = rows(batches, reps);
    let paper = tables::paper_tables(batches, &table1, reps, facts);
    let rows: Vec<Value> = table1
        .into_iter()
        .map(|r| {
            let (tokens, per_rollout) = tokens_json(&row_records(batches, &r.agent, r.condition));
            json!({"agent": r.agent, "level": r.condition.level, "demo": r.condition.demo, "summary": r.summary,
                "tokens": tokens, "rollout_tokens": per_rollout, "harness_versions": row_versions(batches, &r.agent, r.condition)})
        })
        .collect();
    let meta: Vec<Value> = batches
        .iter()
        .map(|b| {
            let d = &b.batch;
            json!({"name": b.name(), "dir": b.dir, "status": d.status, "settings": d.settings, "harness": d.harness,
                "harness_versions": HarnessVersions::of_batch(b), "sandbox": d.sandbox, "toolbox": d.toolbox, "counts": d.counts, "outcomes": d.outcomes,
                "rollouts_recorded": b.records.len()})
        })
        .collect();
    let pool: Vec<Value> = pool_rows(batches, reps)
        .into_iter()
        .map(|(agent, summary)| {
            let tokens: serde_json::Map<String, Value> = summary
                .suites
                .iter()
                .map(|s| (s.suite.clone(), json!(TokenSummary::of(suite_records(batches, &agent, &s.suite)))))
                .collect();
            json!({"agent": agent, "summary": summary, "tokens": tokens})
        })
        .collect();
    let excluded: Vec<Value> = excluded(batches)
        .into_iter()
        .map(|(b, r, why)| json!({"batch": b.name(), "rollout_id": r.rollout_id, "task": r.task, "outcome": r.outcome,
            "reason": why, "worker": r.worker, "episode_id": r.episode_id}))
        .collect();
    json!({"schema_version": "libero_agent.report.v1", "reps": reps, "batches": meta, "rows": rows, "pool": pool,
        "excluded": excluded, "observation_ablation": paper.observation_ablation,
        "demonstration_ablation": paper.demonstration_ablation, "stage_diagnosis": paper.stage_diagnosis,
        "stage_diagnosis_extension": paper.stage_diagnosis_extension, "sustained_contact": paper.sustained_contact, "appendix_e": paper.appendix_e})
}

/// The batches' rollouts that do not count (INVALID, INTERRUPTED), each with its reason, in batch order.
pub fn excluded(batches: &[LoadedBatch]) -> Vec<(&LoadedBatch, &RolloutRecord, String)> {
    batches
        .iter()
        .flat_map(|b| b.records.iter().map(move |r| (b, r)))
        .filter(|(_, r)| !r.outcome.is_valid())
        .map(|(b, r)| (b, r, r.reason().unwrap_or_else(|| "no reason recorded".into())))
        .collect()
}

/// `text` as one Markdown table cell.
pub(crate) fn cell(text: &str) -> String {
    text.replace('|', "\\|").replace(['\n', '\r'], " ")
}

pub fn pct(x: Option<f64>) -> String {
    x.map(|v| format!("{:.1}", 100.0 * v)).unwrap_or_else(|| "—".into())
}

/// A stable split value, with (scored/member) when the subset is partial.
pub fn coverage(s: &SuiteSummary, split: Split) -> String {
    match s.split(split) {
        Some(sp) if sp.complete() => pct(sp.stable),
        Some(sp) => format!("{} ({}/{})", pct(sp.stable), sp.tasks_scored, sp.member_count),
        None => "—".into(),
    }
}

/// `successes/trials = rate [low, high]` in percent.
pub fn wilson(p: &Proportion) -> String {
    match (p.rate, p.wilson_low, p.wilson_high) {
        (Some(r), Some(lo), Some(hi)) => {
            format!("{}/{} = {:.1} [{:.1}, {:.1}]", p.successes, p.trials, 100.0 * r, 100.0 * lo, 100.0 * hi)
        }
        _ => "—".into(),
    }
}

/// `INVALID incl.` beside an average over every episode: ` (2 INVALID incl.)`, empty without any.
pub fn invalid_included(n: usize) -> String {
    if n > 0 { format!(" ({n} INVALID incl.)") } else { String::new() }
}

/// Average episode time over every episode: `11.5 min`, `11.5 min (2 INVALID incl.)`, `—`.
pub fn time_text(minutes: Option<f64>, invalid: usize) -> String {
    match minutes {
        Some(m) => format!("{m:.1} min{}", invalid_included(invalid)),
        None => "—".into(),
    }
}

fn opt(x: Option<f64>, digits: usize) -> String {
    x.map(|v| format!("{v:.digits$}")).unwrap_or_else(|| "—".into())
}

fn label(r: &Row) -> String {
    format!("{} (L{}, demo {})", r.agent, r.condition.level, r.condition.demo.as_str())
}

fn score(s: &SuiteSummary) -> String {
    match s.score {
        Some(x) => format!("{x:.1}"),
        None => format!("≥ {:.1}", s.score_lower_bound),
    }
}

/// The whole report as Markdown (with `choice`, one table of it).
pub fn markdown(batches: &[LoadedBatch], reps: usize, choice: TableChoice, facts: &TaskFacts) -> String {
    let rows = rows(batches, reps);
    let mut o = String::new();
    let _ = writeln!(o, "# LIBERO-Agent results\n");
    for b in batches {
        let (d, h) = (&b.batch, b.batch.harness.as_ref());
        let _ = writeln!(
            o,
            "- batch `{}`: {} {} `{}` effort {}, harness version {}, sandbox {}, toolbox {}, status {}, {} rollouts recorded, outcomes {}",
            b.name(),
            d.experiment().unwrap_or("?"),
            h.and_then(|h| h.name.as_deref()).unwrap_or("?"),
            d.model().unwrap_or("?"),
            d.settings.as_ref().and_then(|s| s.effort.as_deref()).unwrap_or("?"),
            HarnessVersions::of_batch(b).versions_text().unwrap_or_else(|| "unknown".into()),
            d.sandbox().and_then(|s| s.version.as_deref()).unwrap_or("none"),
            toolbox_text(d.toolbox()),
            d.status.as_deref().unwrap_or("?"),
            b.records.len(),
            json!(d.outcomes),
        );
    }
    let paper = tables::paper_tables(batches, &rows, reps, facts);
    if choice != TableChoice::All && choice != TableChoice::Table1 {
        o.push_str(&tables::markdown(&paper, choice, reps));
        return o;
    }
    let _ = writeln!(o, "\n## Stable performance (Table 1; {reps} rollouts per task; INVALID excluded from the rates, included in time and tokens)\n");
    let _ = writeln!(o, "Partial subsets show (scored/member tasks); a Score over a partial suite is a lower bound (≥). Avg. time and \
        Avg. tokens are over every episode of the row, INVALID ones included as the paper averages over all episodes (how many \
        are said beside them); only INTERRUPTED rollouts are left out.\n");
    let _ = writeln!(o, "| Agent | Judg. Acc. | Perc. Task SR | Short Easy SR | Short Hard SR | Long Easy SC | Long Hard SC | Score | Avg. time | Avg. tokens |");
    let _ = writeln!(o, "|---|---|---|---|---|---|---|---|---|---|");
    for r in &rows {
        let s = &r.summary;
        let j = if s.judgment_tasks_scored == 0 { "—".into() } else { format!("{} ({}/10)", pct(s.judgment), s.judgment_tasks_scored) };
        let _ = writeln!(
            o,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            label(r),
            j,
            coverage(s, Split::Perception),
            coverage(s, Split::ShortHorizonEasy),
            coverage(s, Split::ShortHorizonHard),
            coverage(s, Split::LongHorizonEasy),
            coverage(s, Split::LongHorizonHard),
            score(s),
            time_text(s.avg_wall_time_min, s.averaged_invalid),
            cell(&TokenSummary::of(row_records(batches, &r.agent, r.condition)).millions_text()),
        );
    }
    let _ = writeln!(o, "\n{}", tokens::LEGEND);
    for r in &rows {
        let v = row_versions(batches, &r.agent, r.condition);
        if v.mixed {
            let _ = writeln!(o, "\n**Warning: {} pools rollouts of different harness versions: {}.**", label(r), v.text);
        }
    }
    let _ = writeln!(o, "\n## Ordinary success rates (SUCCESS / valid rollouts, 95% Wilson interval)\n");
    let _ = writeln!(o, "| Agent | Perception | Short Easy | Short Hard | Long Easy | Long Hard | All |");
    let _ = writeln!(o, "|---|---|---|---|---|---|---|");
    for r in &rows {
        let s = &r.summary;
        let cells: Vec<String> = Split::ALL.iter().map(|sp| s.split(*sp).map(|x| wilson(&x.ordinary)).unwrap_or_default()).collect();
        let _ = writeln!(o, "| {} | {} | {} |", label(r), cells.join(" | "), wilson(&s.ordinary));
    }
    let _ = writeln!(o, "\n## Per task\n");
    let _ = writeln!(o, "| Agent | Task | Split | Valid | Excluded | Successes | Stable | Stage fraction (min / sum) | Tokens per rollout (source) |");
    let _ = writeln!(o, "|---|---|---|---|---|---|---|---|---|");
    for r in &rows {
        let recs = row_records(batches, &r.agent, r.condition);
        for t in &r.summary.tasks {
            let stable = stable_word(t.stable_success);
            let task_tokens = tokens::per_rollout_text(recs.iter().copied().filter(|x| x.task_number == t.task_number && x.outcome.is_valid()));
            let _ = writeln!(
                o,
                "| {} | T{:02} | {} | {} | {} | {} | {} | {} / {} | {} |",
                label(r),
                t.task_number,
                t.split.as_str(),
                t.valid_rollouts,
                t.excluded_rollouts,
                t.successes,
                stable,
                opt(t.stable_stage_fraction, 2),
                opt(t.stage_fraction_sum, 2),
                cell(&task_tokens),
            );
        }
    }
    let excluded = excluded(batches);
    if !excluded.is_empty() {
        let _ = writeln!(o, "\n## Excluded rollouts (INVALID, INTERRUPTED) and why\n");
        let _ = writeln!(o, "| Batch | Rollout | Task | Outcome | Worker | Reason |");
        let _ = writeln!(o, "|---|---|---|---|---|---|");
        for (b, r, why) in &excluded {
            let _ = writeln!(
                o,
                "| {} | {} | {} | {} | {} | {} |",
                cell(&b.name()),
                cell(&r.rollout_id),
                cell(&r.task),
                r.outcome.as_str(),
                cell(r.worker.as_deref().unwrap_or("—")),
                cell(why),
            );
        }
    }
    let pool = pool_rows(batches, reps);
    if !pool.is_empty() {
        let _ = writeln!(o, "\n## Task pool, per suite (`run --experiment pool`; not part of the Score)\n");
        let _ = writeln!(o, "Stable SR: every one of the {reps} rollouts succeeded; stable SC: the minimum c/K, averaged over the suite's scored tasks.\n");
        let _ = writeln!(o, "| Agent | Suite | Tasks (scored) | Stable SR | Stable SC | Mean c/K | Ordinary SR [95% Wilson] | Avg. time | Avg. tokens (source) |");
        let _ = writeln!(o, "|---|---|---|---|---|---|---|---|---|");
        for (agent, p) in &pool {
            for s in &p.suites {
                let _ = writeln!(
                    o,
                    "| {agent} | {} | {} ({}) | {} | {} | {} | {} | {} | {} |",
                    s.suite, s.tasks, s.tasks_scored, pct(s.stable_success), pct(s.stable_stage_completion),
                    pct(s.mean_stage_completion), wilson(&s.ordinary), time_text(s.avg_wall_time_min, s.averaged_invalid),
                    cell(&TokenSummary::of(suite_records(batches, agent, &s.suite)).text()),
                );
            }
        }
        let _ = writeln!(o, "\n### Pool tasks\n");
        let _ = writeln!(o, "| Agent | Task | Suite | Valid | Excluded | Successes | Stable | Stage fraction (min / sum) |");
        let _ = writeln!(o, "|---|---|---|---|---|---|---|---|");
        for (agent, p) in &pool {
            for t in &p.tasks {
                let c = &t.counts;
                let _ = writeln!(
                    o,
                    "| {agent} | {} | {} | {} | {} | {} | {} | {} / {} |",
                    t.task, t.suite, c.valid_rollouts, c.excluded_rollouts, c.successes, stable_word(c.stable_success),
                    opt(c.stable_stage_fraction, 2), opt(c.stage_fraction_sum, 2),
                );
            }
        }
    }
    if choice == TableChoice::All {
        o.push_str(&tables::markdown(&paper, choice, reps));
    }
    o
}

pub(crate) fn stable_word(s: Option<bool>) -> &'static str {
    match s {
        Some(true) => "yes",
        Some(false) => "no",
        None => "incomplete",
    }
}

/// The report as CSV, one block per table (`choice`: all, or one table). A single block prints as plain CSV; several
/// are each headed by a `# name` line and separated by a blank line.
pub fn csv(batches: &[LoadedBatch], reps: usize, choice: TableChoice, facts: &TaskFacts) -> String {
    let table1 = rows(batches, reps);
    let paper = tables::paper_tables(batches, &table1, reps, facts);
    let mut blocks = Vec::new();
    if choice.wants(TableChoice::Table1) {
        blocks.push(("table_1_stable_performance".to_owned(), csv_table1(&table1, batches, reps)));
    }
    if choice == TableChoice::All {
        blocks.push(("tokens_per_rollout".to_owned(), csv_rollout_tokens(&table1, batches)));
    }
    blocks.extend(tables::csv_blocks(&paper, choice, reps));
    match blocks.as_slice() {
        [(_, only)] => only.clone(),
        _ => blocks.iter().map(|(name, body)| format!("# {name}\n{body}")).collect::<Vec<_>>().join("\n"),
    }
}

/// Table 1 (and the pool's per-suite lines) as CSV.
fn csv_table1(table1: &[Row], batches: &[LoadedBatch], reps: usize) -> String {
    let mut o = String::from("agent,level,demo,split,member_tasks,scored_tasks,stable_percent,ordinary_successes,valid_rollouts,wilson_low_percent,wilson_high_percent,mean_total_tokens,rollouts_with_usage,tokens_sources,stdout_disagrees\n");
    let f = |x: Option<f64>| x.map(|v| format!("{:.4}", 100.0 * v)).unwrap_or_default();
    // Every line carries its row's tokens and where they came from (empty mean: no usage, never 0).
    let t = |tk: &TokenSummary| {
        format!("{},{},{},{}", tk.mean_total.map(|m| format!("{m:.1}")).unwrap_or_default(), tk.rollouts_with_usage, tk.sources_field(), tk.stdout_disagrees.len())
    };
    for r in table1 {
        let tk = t(&TokenSummary::of(row_records(batches, &r.agent, r.condition)));
        for sp in &r.summary.splits {
            let _ = writeln!(
                o,
                "{},{},{},{},{},{},{},{},{},{},{},{tk}",
                r.agent, r.condition.level, r.condition.demo.as_str(), sp.split.as_str(), sp.member_count, sp.tasks_scored,
                f(sp.stable), sp.ordinary.successes, sp.ordinary.trials, f(sp.ordinary.wilson_low), f(sp.ordinary.wilson_high)
            );
        }
        let s = &r.summary;
        let _ = writeln!(
            o,
            "{},{},{},score,30,,{},,,,,{tk}",
            r.agent, r.condition.level, r.condition.demo.as_str(),
            s.score.map(|x| format!("{x:.4}")).unwrap_or_default()
        );
    }
    // Pool suites: `split` is `pool:<suite>`, member tasks are the suite's tasks in the batches.
    for (agent, p) in pool_rows(batches, reps) {
        for s in &p.suites {
            let tk = t(&TokenSummary::of(suite_records(batches, &agent, &s.suite)));
            let _ = writeln!(
                o,
                "{agent},3,none,pool:{},{},{},{},{},{},{},{},{tk}",
                s.suite, s.tasks, s.tasks_scored, f(s.stable_success), s.ordinary.successes, s.ordinary.trials,
                f(s.ordinary.wilson_low), f(s.ordinary.wilson_high)
            );
        }
    }
    o
}

/// Every counted row's rollouts with their tokens and source, one line each (pool rollouts as `pool:<suite>`).
fn csv_rollout_tokens(table1: &[Row], batches: &[LoadedBatch]) -> String {
    let mut o = String::from("agent,level,demo,rollout_id,task,repetition,outcome,total_tokens,input_tokens,cached_input_tokens,output_tokens,tokens_source\n");
    let n = |x: Option<u64>| x.map(|v| v.to_string()).unwrap_or_default();
    let mut line = |agent: &str, level: String, demo: &str, r: &RolloutRecord| {
        let t = RolloutTokens::of(r);
        let _ = writeln!(
            o,
            "{agent},{level},{demo},{},{},{},{},{},{},{},{},{}",
            r.rollout_id, r.task, r.repetition, r.outcome.as_str(), n(t.total), n(t.input), n(t.cached), n(t.output), t.source
        );
    };
    for r in table1 {
        for x in row_records(batches, &r.agent, r.condition) {
            line(&r.agent, r.condition.level.to_string(), r.condition.demo.as_str(), x);
        }
    }
    for b in batches {
        for x in b.records.iter().filter(|x| x.suite.is_some()) {
            line(&agent_of(b), x.level.to_string(), &format!("pool:{}", x.suite.as_deref().unwrap_or("?")), x);
        }
    }
    o
}

/// A batch's toolbox as `libero-toolbox (numpy 1.26.4, scipy 1.14.1, …)`; `none` when the batch ran without one.
pub fn toolbox_text(t: Option<&ToolboxDoc>) -> String {
    match t.and_then(|t| t.name.as_deref()) {
        Some(name) => {
            let packages: Vec<String> = t
                .and_then(|t| t.packages.as_ref())
                .map(|ps| {
                    ps.iter()
                        .map(|p| format!("{} {}", p.name.as_deref().unwrap_or("?"), p.version.as_deref().unwrap_or("?")))
                        .collect()
                })
                .unwrap_or_default();
            if packages.is_empty() { name.to_owned() } else { format!("{name} ({})", packages.join(", ")) }
        }
        None => "none".into(),
    }
}

/// The report as LaTeX tabulars (booktabs): Table 1, then (with `choice` `all`) the others, each after a `% caption`.
pub fn latex(batches: &[LoadedBatch], reps: usize, choice: TableChoice, facts: &TaskFacts) -> String {
    let table1 = rows(batches, reps);
    let paper = tables::paper_tables(batches, &table1, reps, facts);
    let mut o = String::new();
    if choice.wants(TableChoice::Table1) {
        o.push_str(&latex_table1(&table1, batches));
    }
    o.push_str(&tables::latex(&paper, choice, reps));
    o
}

fn latex_table1(table1: &[Row], batches: &[LoadedBatch]) -> String {
    let mut o = String::from(
        "\\begin{tabular}{lrrrrrrrrrl}\n\\toprule\nAgent & Judg. Acc. & Perc. SR & Short Easy & Short Hard & Long Easy SC & Long Hard SC & Score & Time (min) & Tokens (M) & Token source \\\\\n\\midrule\n",
    );
    let esc = tables::tex;
    for r in table1 {
        let s = &r.summary;
        let c = |sp| s.split(sp).and_then(|x| x.stable);
        let tk = TokenSummary::of(row_records(batches, &r.agent, r.condition));
        let _ = writeln!(
            o,
            "{} & {} & {} & {} & {} & {} & {} & {} & {} & {} & {} \\\\",
            esc(&label(r)), pct(s.judgment), pct(c(Split::Perception)), pct(c(Split::ShortHorizonEasy)),
            pct(c(Split::ShortHorizonHard)), pct(c(Split::LongHorizonEasy)), pct(c(Split::LongHorizonHard)),
            esc(&score(s)), format!("{}{}", opt(s.avg_wall_time_min, 1), invalid_included(s.averaged_invalid)),
            opt(tk.mean_total.map(|t| t / 1e6), 2), esc(&tk.sources_text())
        );
    }
    o.push_str("\\bottomrule\n\\end{tabular}\n");
    o.replace('—', "--")
}
