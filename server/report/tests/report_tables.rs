//! `report` over one agent's three batches — a main-table batch, an observation-ablation batch and a context batch,
//! written by hand with their rollouts' private records — prints Tables 1–4, Figure 3's data and Appendix E, each
//! checked against values computed by hand below, in Markdown, CSV, LaTeX and JSON, and `--figures DIR` writes
//! Figure 3's two-panel SVG with its data. Stable rule over 2 rollouts per task (`--reps 2`).
//!
//! Hand computation (agent `command/fixture`):
//! * main (L3, none): T11 S,S (stable) · T13 S,F · T12 S,S (stable) · T16 F,F → easy 1/2 scored = 50.0 (2/5), hard 50.0
//!   (2/5); T27 c/K 2/4, 1/4 → 0.25 · T28 2/2, 1/2 → 0.5 → long easy 25.0, hard 50.0; an INVALID T11 rollout counts
//!   nowhere.
//! * obs: L1 T11 S,F · T12 F,F → 0.0, 0.0, Overall 0.0; L2 T11 S,S · T12 S,F → 100.0, 0.0, Overall 50.0.
//! * ctx: video T27 4/4, 3/4 → 0.75 · T28 S,S → 1.0 (Overall 87.5); video+traj T27 2/4, 2/4 → 0.5 · T28 0/2, 1/2 → 0
//!   (Overall 25.0). The ablation batches' rollouts have no run directory: Table 4 and Figure 3 count them as without
//!   record.
//! * Table 4 (the paper's: hard long-horizon tasks only, here T28 ×2 × 2 stages = 4 opportunities, L3 none): reached
//!   4 (100.0%: r1 both completed; r2's door reached once the latch was open), success 3 (75.0%); Mechanism Interaction
//!   3 successes over 4 reached less 1 interference failure (r2's door, blocked by an order violation) = 3/3; failed 1:
//!   local execution 0/1, cross-stage interference 1/1. The video conditions' T28 rollouts have no record.
//! * Table 4+ (the extension, L3 none), 12 stage opportunities (T27 ×2 × 4 stages, T28 ×2 × 2): reached 9 (75.0%),
//!   success 6 (50.0%); Object Manipulation: reached 3, succeeded 1; Mechanism Interaction: reached 6, succeeded 5;
//!   failures 4: local 2 (T27 r1 stage 03, T27 r2 stage 02), interference 2 (T27 r2's drawer closed while a later
//!   stage ran; T28 r2's door blocked by an order violation). T27 r2's record has no stage types: the task facts' (the catalog's, [`facts`]) are used.
//! * Appendix E: x/2 and sum/2 (2 rollouts per task), the long-horizon table after its K row.
//! * Figure 3 (the main table's long-horizon rollouts; T16 and the ablation batches are not read): 6 opening
//!   operations (T28's closing is none), all entered; T27 r2's legacy record (no direction, no handle runs) is left out;
//!   the 5 counted have SCR 20, 40, 50, 12, 0 (T28 r2's door: contact on the panel only) with opened T, T, T, T, F →
//!   mean 24.4, success 4/5; bins 0: 0/1, (0,10]: 0/0, (10,25]: 2/2, >25: 2/2; Pearson r = 24.4 / √(1667.2 · 0.8) =
//!   0.66811. (The multi-agent golden test is `figure_3_pools_…` below.)
use std::path::Path;

use libero_metrics::{StageType, TaskFacts};
use libero_report::batch::{LoadedBatch, load_batch};
use libero_report::{self as report, tables::TableChoice};
use serde_json::{Value, json};

const REPS: usize = 2;

/// What the catalog says beside the records, as the runner and the console pass it: the paper's K of T21–T30 (Appendix
/// E's K row) and T27's stage types (its r2 record names none).
fn facts() -> TaskFacts {
    use StageType::{MechanismInteraction as Mi, ObjectManipulation as Om};
    let t27 = [("01_Open_Middle_Drawer", Mi), ("02_Place_Cookies_Middle_Drawer", Om), ("03_Place_Chocolate_Middle_Drawer", Om), ("04_Close_Middle_Drawer", Mi)];
    TaskFacts {
        stage_types: [(27, t27.iter().map(|(n, t)| (n.to_string(), Some(*t))).collect())].into(),
        stage_counts: (21..=30).zip([5, 5, 8, 4, 4, 3, 4, 2, 3, 4]).collect(),
    }
}

/// One rollout: (task, split, K, repetition, level, demo, outcome, completed stages, private evaluation if any).
struct Rollout {
    task: u32,
    k: u32,
    rep: u32,
    level: u8,
    demo: &'static str,
    outcome: &'static str,
    c: u32,
    private: Option<Value>,
}

fn split(task: u32) -> &'static str {
    libero_metrics::Split::of_task(task).unwrap().as_str()
}

fn r(task: u32, k: u32, rep: u32, level: u8, demo: &'static str, outcome: &'static str, c: u32) -> Rollout {
    Rollout { task, k, rep, level, demo, outcome, c, private: None }
}

fn with(mut x: Rollout, private: Value) -> Rollout {
    x.private = Some(private);
    x
}

fn write_batch(dir: &Path, experiment: &str, rollouts: &[Rollout]) {
    write_agent_batch(dir, experiment, "fixture", rollouts);
}

/// A batch of agent `command/<model>`.
fn write_agent_batch(dir: &Path, experiment: &str, model: &str, rollouts: &[Rollout]) {
    std::fs::create_dir_all(dir).unwrap();
    let batch = json!({
        "schema_version": "libero_agent.batch.v1", "status": "finished",
        "settings": {"experiment": experiment, "harness": "command", "model": model, "effort": "high", "reps": REPS,
            "tasks": [], "seed": 100, "wall_time_s": 300.0, "max_agent_steps": 100, "agent_cmd": "true", "sandbox": false},
        "rollout_count": rollouts.len(), "counts": {"done": rollouts.len(), "running": 0, "left": 0}, "outcomes": {},
    });
    std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
    let mut lines = String::new();
    for x in rollouts {
        let id = format!("w{}_t{}_level{}_{}", x.rep, x.task, x.level, x.demo);
        let run_dir = x.private.as_ref().map(|pe| {
            let d = dir.join("runs").join(&id);
            std::fs::create_dir_all(&d).unwrap();
            std::fs::write(d.join("result.json"), json!({"status": "finished", "private_evaluation": pe}).to_string()).unwrap();
            d
        });
        let record = json!({
            "schema_version": "libero_agent.rollout.v1", "rollout_id": id, "task": format!("T{:02}", x.task),
            "task_number": x.task, "split": split(x.task), "stage_count": x.k, "repetition": x.rep, "level": x.level,
            "demo": x.demo, "outcome": x.outcome, "episode_id": format!("ep-{id}"), "run_dir": run_dir,
            "completed_stages": x.c, "wall_time_s": 60.0, "started_at": "2025-01-01T00:00:00Z", "finished_at": "2025-01-01T00:01:00Z",
        });
        lines.push_str(&format!("{record}\n"));
    }
    std::fs::write(dir.join("rollouts.jsonl"), lines).unwrap();
}

/// A stage diagnostic; `ty` None leaves the type out (a record from before the evaluator reported it).
fn stage(name: &str, ty: Option<&str>, reached: bool, succeeded: bool) -> Value {
    let mut d = json!({"stage_name": name, "required": true, "reached": reached, "succeeded": succeeded, "regressions": 0,
        "regressed_during_later_stage": false, "failure_reason": null});
    if let Some(t) = ty {
        d["type"] = json!(t);
    }
    d
}

/// An opening operation record (`kind` None: a legacy record without direction or completion).
fn op(stage: &str, kind: Option<&str>, scr: f64, exec: u64, completed: bool) -> Value {
    let mut o = json!({"stage_name": stage, "exec_steps": exec, "sustained_contact_ratio_percent": scr});
    if let Some(k) = kind {
        o["operation"] = json!(k);
        o["completed"] = json!(completed);
    }
    o
}

fn pe(stages: Vec<Value>, ops: Vec<Value>) -> Value {
    json!({"stage_diagnostics": stages, "details": {"opening_operations": ops}})
}

const MI: Option<&str> = Some("mechanism_interaction");
const OM: Option<&str> = Some("object_manipulation");

fn batches(root: &Path) -> Vec<LoadedBatch> {
    let t16 = |scr: f64, exec: u64| pe(vec![stage("01_BDDL_Goal_At_Finish", None, true, false)], vec![op("01_BDDL_Goal_At_Finish", Some("open"), scr, exec, false)]);
    let mut t27_r2 = vec![
        stage("01_Open_Middle_Drawer", None, true, true),
        stage("02_Place_Cookies_Middle_Drawer", None, true, false),
        stage("03_Place_Chocolate_Middle_Drawer", None, false, false),
        stage("04_Close_Middle_Drawer", None, false, false),
    ];
    t27_r2[0]["regressions"] = json!(1);
    t27_r2[0]["regressed_during_later_stage"] = json!(true);
    let mut t28_r2 = vec![stage("01_Unlatch_Door", MI, true, true), stage("02_Open_Door", MI, true, false)];
    t28_r2[1]["failure_reason"] = json!("order_violation");
    let main = [
        r(11, 1, 1, 3, "none", "SUCCESS", 1),
        r(11, 1, 2, 3, "none", "SUCCESS", 1),
        r(11, 1, 3, 3, "none", "INVALID", 0),
        r(13, 1, 1, 3, "none", "SUCCESS", 1),
        r(13, 1, 2, 3, "none", "FAIL", 0),
        r(12, 1, 1, 3, "none", "SUCCESS", 1),
        r(12, 1, 2, 3, "none", "SUCCESS", 1),
        with(r(16, 1, 1, 3, "none", "FAIL", 0), t16(0.0, 40)),
        with(r(16, 1, 2, 3, "none", "FAIL", 0), t16(8.0, 50)),
        with(
            r(27, 4, 1, 3, "none", "FAIL", 2),
            pe(
                vec![
                    stage("01_Open_Middle_Drawer", MI, true, true),
                    stage("02_Place_Cookies_Middle_Drawer", OM, true, true),
                    stage("03_Place_Chocolate_Middle_Drawer", OM, true, false),
                    stage("04_Close_Middle_Drawer", MI, false, false),
                ],
                vec![opening("01_Open_Middle_Drawer", 100, &[20], &[20], true)],
            ),
        ),
        with(r(27, 4, 2, 3, "none", "FAIL", 1), pe(t27_r2, vec![op("01_Open_Middle_Drawer", None, 30.0, 90, false)])),
        with(
            r(28, 2, 1, 3, "none", "SUCCESS", 2),
            pe(
                vec![stage("01_Unlatch_Door", MI, true, true), stage("02_Open_Door", MI, true, true)],
                vec![
                    opening("01_Unlatch_Door", 110, &[44], &[44], true),
                    opening("02_Open_Door", 60, &[30], &[30], true),
                    op("03_Close_Door", Some("close"), 10.0, 60, true),
                ],
            ),
        ),
        with(
            r(28, 2, 2, 3, "none", "FAIL", 1),
            pe(t28_r2, vec![opening("01_Unlatch_Door", 100, &[12], &[12], true), opening("02_Open_Door", 80, &[6], &[], false)]),
        ),
    ];
    let obs = [
        r(11, 1, 1, 1, "none", "SUCCESS", 1),
        r(11, 1, 2, 1, "none", "FAIL", 0),
        r(12, 1, 1, 1, "none", "FAIL", 0),
        r(12, 1, 2, 1, "none", "FAIL", 0),
        r(11, 1, 1, 2, "none", "SUCCESS", 1),
        r(11, 1, 2, 2, "none", "SUCCESS", 1),
        r(12, 1, 1, 2, "none", "SUCCESS", 1),
        r(12, 1, 2, 2, "none", "FAIL", 0),
    ];
    let ctx = [
        r(27, 4, 1, 3, "video", "SUCCESS", 4),
        r(27, 4, 2, 3, "video", "FAIL", 3),
        r(28, 2, 1, 3, "video", "SUCCESS", 2),
        r(28, 2, 2, 3, "video", "SUCCESS", 2),
        r(27, 4, 1, 3, "video_traj", "FAIL", 2),
        r(27, 4, 2, 3, "video_traj", "FAIL", 2),
        r(28, 2, 1, 3, "video_traj", "FAIL", 0),
        r(28, 2, 2, 3, "video_traj", "FAIL", 1),
    ];
    // Every counted main-table rollout has its record; the ablation batches' rollouts have none (no run directory).
    let main: Vec<Rollout> = main
        .into_iter()
        .map(|x| match (&x.private, x.outcome) {
            (None, "SUCCESS" | "FAIL") => {
                let ok = x.outcome == "SUCCESS";
                with(x, pe(vec![stage("01_BDDL_Goal_At_Finish", None, true, ok)], vec![]))
            }
            _ => x,
        })
        .collect();
    write_batch(&root.join("main"), "main_table", &main);
    write_batch(&root.join("obs"), "manip_observation", &obs);
    write_batch(&root.join("ctx"), "context", &ctx);
    ["main", "obs", "ctx"].iter().map(|n| load_batch(&root.join(n)).unwrap()).collect()
}

fn has(text: &str, line: &str) {
    assert!(text.lines().any(|l| l == line), "missing line\n{line}\nin\n{text}");
}

#[test]
fn markdown_prints_tables_1_to_4_figure_3_and_appendix_e_with_the_hand_computed_values() {
    let dir = tempfile::tempdir().unwrap();
    let md = report::markdown(&batches(dir.path()), REPS, TableChoice::All, &facts());
    // Table 1: the three conditions of one agent, each from its own batch.
    assert!(md.contains("| command/fixture (L3, demo none) | — | — (0/10) | 50.0 (2/5) | 50.0 (2/5) | 25.0 (1/5) | 50.0 (1/5) |"), "{md}");
    // Table 2: L1/L2 from the observation batch, L3 from the main table.
    has(&md, "| command/fixture | L1 | 0.0 (1/5) | 0.0 (1/5) | 0.0 | obs |");
    has(&md, "| command/fixture | L2 | 100.0 (1/5) | 0.0 (1/5) | 50.0 | obs |");
    has(&md, "| command/fixture | L3 | 50.0 (2/5) | 50.0 (2/5) | 50.0 | main |");
    // Table 3: None from the main table, the demonstrations from the context batch.
    has(&md, "| command/fixture | None | 25.0 (1/5) | 50.0 (1/5) | 37.5 | main |");
    has(&md, "| command/fixture | Video | 75.0 (1/5) | 100.0 (1/5) | 87.5 | ctx |");
    has(&md, "| command/fixture | Video + Traj. | 50.0 (1/5) | 0.0 (1/5) | 25.0 | ctx |");
    // Table 4, the paper's seven columns.
    has(&md, "| command/fixture (L3, none) | 4/4 = 100.0% | 3/4 = 75.0% | — | 3/3 = 100.0% | 0/1 = 0.0% | 1/1 = 100.0% |");
    has(&md, "| command/fixture (L3, video) | — | — | — | — | — | — |");
    assert!(md.contains("command/fixture (L3, none): 4 stage opportunities over 2 rollouts (T28 ×2); 0 annotated, 4 automatic"), "{md}");
    assert!(md.contains("command/fixture (L3, video): 0 stage opportunities over 0 rollouts (+2 without record) (T28 ×2)"), "{md}");
    // Table 4+, the extension.
    assert!(md.contains("## Table 4+ (all long-horizon tasks T21–T30; extension)"), "{md}");
    has(
        &md,
        "| command/fixture | L3, none | 4 | 12 | 9/12 = 75.0% | 6/12 = 50.0% | 1/3 = 33.3 [6.1, 79.2] | 5/6 = 83.3 [43.6, 97.0] | 4 | 2 (50.0%) | 2 (50.0%) |",
    );
    has(&md, "| command/fixture | L3, video | 0 (+4 without record) | 0 | — | — | — | — | 0 | 0 | 0 |");
    // Figure 3: (a) the agent's mean, (b) the pooled bins, and every operation read.
    has(&md, "| command/fixture | 5 | 24.4% | 4/5 = 80.0% |");
    has(&md, "| SCR 0 | 1 | 0 | 0/1 = 0.0 [0.0, 79.3] |  |");
    has(&md, "| SCR (0,10%] | 0 | 0 | — |  |");
    has(&md, "| all | 5 | 4 | 4/5 = 80.0 [37.6, 96.4] | 0.668 |");
    assert!(md.contains("6 opening operations of 4 long-horizon rollouts (T21–T30, L3, no demonstration; the stable rule's) read, 5 counted; \
                         left out: 0 not entered, 1 recorded without handle contact runs"), "{md}");
    has(&md, "| command/fixture | T28 | 02_Open_Door | 80 | [] | 0.0% | yes | no | yes |");
    has(&md, "| command/fixture | T27 | 01_Open_Middle_Drawer | 90 | — (not recorded) | — | yes | yes | no |");
    let ops = md.split("## Opening operations (Figure 3's data)").nth(1).unwrap().split("\n## ").next().unwrap();
    assert!(!ops.contains("03_Close_Door") && !ops.contains("| T16 |"), "a closing and a short-horizon task are no operation of Figure 3");
    // Appendix E, wide.
    has(&md, "| command/fixture | L3, none | 2/2 | 2/2 | 1/2 | — | — | 0/2 | — | — | — | — |");
    has(&md, "| K (stages) |  | 5 | 5 | 8 | 4 | 4 | 3 | 4 | 2 | 3 | 4 |");
    has(&md, "| command/fixture | L3, none | — | — | — | — | — | — | 0.75/2 | 1.50/2 | — | — |");
    has(&md, "| command/fixture | L3, video | — | — | — | — | — | — | 1.75/2 | 2.00/2 | — | — |");
    // One table alone.
    let only = report::markdown(&batches(dir.path()), REPS, TableChoice::Table3, &facts());
    assert!(only.contains("Demonstration ablation") && !only.contains("Observation ablation") && !only.contains("## Stable performance"));
}

#[test]
fn csv_and_latex_hold_every_table_in_a_fixed_shape() {
    let dir = tempfile::tempdir().unwrap();
    let b = batches(dir.path());
    let csv = report::csv(&b, REPS, TableChoice::All, &facts());
    let blocks: Vec<&str> = csv.lines().filter(|l| l.starts_with("# ")).collect();
    assert_eq!(
        blocks,
        [
            "# table_1_stable_performance",
            "# tokens_per_rollout",
            "# table_2_observation_ablation",
            "# table_3_demonstration_ablation",
            "# table_4_stage_diagnosis",
            "# table_4_extension_all_long_horizon",
            "# figure_3a_mean_scr",
            "# figure_3b_scr_bins",
            "# figure_3_opening_operations",
            "# appendix_e_short_horizon",
            "# appendix_e_long_horizon"
        ]
    );
    let t2 = report::csv(&b, REPS, TableChoice::Table2, &facts());
    assert_eq!(
        t2,
        "agent,level,easy_percent,hard_percent,overall_percent,easy_tasks_scored,hard_tasks_scored,member_tasks,batches\n\
         command/fixture,L1,0.0000,0.0000,0.0000,1,1,5,obs\n\
         command/fixture,L2,100.0000,0.0000,50.0000,1,1,5,obs\n\
         command/fixture,L3,50.0000,50.0000,50.0000,2,2,5,main\n"
    );
    let t3 = report::csv(&b, REPS, TableChoice::Table3, &facts());
    assert_eq!(
        t3,
        "agent,demo,easy_percent,hard_percent,overall_percent,easy_tasks_scored,hard_tasks_scored,member_tasks,batches\n\
         command/fixture,none,25.0000,50.0000,37.5000,1,1,5,main\n\
         command/fixture,video,75.0000,100.0000,87.5000,1,1,5,ctx\n\
         command/fixture,video_traj,50.0000,0.0000,25.0000,1,1,5,ctx\n"
    );
    let t4 = report::csv(&b, REPS, TableChoice::Table4, &facts());
    has(&t4, "command/fixture,3,none,2,0,4,0,4,4,100.0000,3,75.0000,0,0,0,,3,4,1,100.0000,1,0,0.0000,1,100.0000,0,0,0");
    has(&t4, "command/fixture,3,video,0,2,0,0,0,0,,0,,0,0,0,,0,0,0,,0,0,,0,,0,0,0");
    has(&t4, "command/fixture,3,none,4,0,12,9,75.0000,6,50.0000,object_manipulation,4,3,1,33.3333,6.1492,79.2340,4,2,2");
    has(&t4, "command/fixture,3,none,4,0,12,9,75.0000,6,50.0000,mechanism_interaction,8,6,5,83.3333,43.6497,96.9947,4,2,2");
    has(&t4, "command/fixture,3,none,4,0,12,9,75.0000,6,50.0000,all,12,9,6,,,,4,2,2");
    has(&t4, "command/fixture,3,video,0,4,0,0,,0,,all,0,0,0,,,,0,0,0");
    let f3 = report::csv(&b, REPS, TableChoice::Figure3, &facts());
    has(&f3, "command/fixture,5,24.4000,4,80.0000,37.5535,96.3776");
    has(&f3, "\"(10,25%]\",2,2,100.0000,34.2380,100.0000,");
    has(&f3, "all,5,4,80.0000,37.5535,96.3776,0.668115");
    has(&f3, "command/fixture,T28,ep-w2_t28_level3_none,02_Open_Door,80,,0.0000,true,false,true");
    let appendix = report::csv(&b, REPS, TableChoice::Appendix, &facts());
    has(&appendix, "agent,level,demo,T11,T12,T13,T14,T15,T16,T17,T18,T19,T20");
    has(&appendix, "command/fixture,3,none,2/2,2/2,1/2,,,0/2,,,,");
    has(&appendix, "command/fixture,1,none,1/2,0/2,,,,,,,,");
    has(&appendix, "K,,,5,5,8,4,4,3,4,2,3,4");
    has(&appendix, "command/fixture,3,video_traj,,,,,,,1.00/2,0.50/2,,");

    let tex = report::latex(&b, REPS, TableChoice::All, &facts());
    assert_eq!(tex.matches("\\begin{tabular}").count(), 10, "Tables 1–4, Table 4+, Figure 3(a), 3(b) and its operations, two appendix tables:\n{tex}");
    assert_eq!(tex.matches("\\begin{tabular}").count(), tex.matches("\\end{tabular}").count());
    has(&tex, "command/fixture & L2 & 100.0 (1/5) & 0.0 (1/5) & 50.0 & obs \\\\");
    has(&tex, "command/fixture & Video + Traj. & 50.0 (1/5) & 0.0 (1/5) & 25.0 & ctx \\\\");
    has(
        &tex,
        "command/fixture & L3, none & 4 & 12 & 9/12 = 75.0\\% & 6/12 = 50.0\\% & 1/3 = 33.3 [6.1, 79.2] & 5/6 = 83.3 [43.6, 97.0] & 4 & 2 (50.0\\%) & 2 (50.0\\%) \\\\",
    );
    has(&tex, "command/fixture & T28 & 02\\_Open\\_Door & 80 & [] & 0.0\\% & yes & no & yes \\\\");
    assert!(tex.contains("% Figure 3(b): local opening success by SCR bin, every agent's operations pooled\n\\begin{tabular}{lrrrr}"), "{tex}");
    has(&tex, "command/fixture & L3, none & 2/2 & 2/2 & 1/2 & -- & -- & 0/2 & -- & -- & -- & -- \\\\");
    has(&tex, "command/fixture (L3, none) & 4/4 = 100.0\\% & 3/4 = 75.0\\% & -- & 3/3 = 100.0\\% & 0/1 = 0.0\\% & 1/1 = 100.0\\% \\\\");
    assert!(!tex.contains('—') && !tex.contains("_fix"), "LaTeX-safe cells");
}

#[test]
fn json_holds_the_same_numbers_and_figures_are_written_as_svg_with_their_data() {
    let dir = tempfile::tempdir().unwrap();
    let b = batches(dir.path());
    let v = report::report_json(&b, REPS, &facts());
    let obs = &v["observation_ablation"][0];
    assert_eq!(obs["agent"], "command/fixture");
    let l3 = &obs["rows"][2];
    assert_eq!((l3["condition"].as_str(), l3["easy"].as_f64(), l3["overall"].as_f64()), (Some("L3"), Some(0.5), Some(0.5)));
    assert_eq!(l3["batches"], json!(["main"]));
    let none = &v["demonstration_ablation"][0]["rows"][0];
    assert_eq!((none["easy"].as_f64(), none["hard"].as_f64(), none["overall"].as_f64()), (Some(0.25), Some(0.5), Some(0.375)));
    let t4 = v["stage_diagnosis"].as_array().unwrap().iter().find(|l| l["demo"] == "none").unwrap();
    assert_eq!((t4["opportunities"].as_u64(), t4["failed"].as_u64(), t4["cross_stage_interference"]["successes"].as_u64()), (Some(4), Some(1), Some(1)));
    assert_eq!((t4["annotated"].as_u64(), t4["automatic"].as_u64()), (Some(0), Some(4)));
    assert_eq!(t4["tasks"], json!({"T28": 2}));
    let t4 = v["stage_diagnosis_extension"].as_array().unwrap().iter().find(|l| l["demo"] == "none").unwrap();
    assert_eq!((t4["opportunities"].as_u64(), t4["failures"].as_u64(), t4["cross_stage_interference"].as_u64()), (Some(12), Some(4), Some(2)));
    assert_eq!(t4["untyped_opportunities"], 0, "T27 r2's stage types come from the task facts");
    let f3 = &v["sustained_contact"];
    assert!((f3["pooled"]["pearson_r"].as_f64().unwrap() - 24.4 / (1667.2f64 * 0.8).sqrt()).abs() < 1e-12);
    assert_eq!((f3["operations"].as_array().map(Vec::len), f3["without_handle_runs"].as_u64()), (Some(6), Some(1)));
    let bins: Vec<(u64, u64)> = f3["pooled"]["bins"].as_array().unwrap().iter().map(|b| (b["local_success"]["successes"].as_u64().unwrap(), b["local_success"]["trials"].as_u64().unwrap())).collect();
    assert_eq!(bins, [(0, 1), (0, 0), (2, 2), (2, 2)]);
    let appendix = v["appendix_e"].as_array().unwrap();
    assert_eq!(appendix.iter().map(|a| a["rows"].as_array().unwrap().len()).collect::<Vec<_>>(), [0, 3, 3]);

    // What `report … --figures DIR` writes: Figure 3 and its data.
    let figures = dir.path().join("figures");
    let paper = report::tables::paper_tables(&b, &report::rows(&b, REPS), REPS, &facts());
    report::tables::write_figures(&paper, &figures).unwrap();
    let svg = std::fs::read_to_string(figures.join("figure3.svg")).unwrap();
    assert!(svg.starts_with("<svg xmlns=\"http://www.w3.org/2000/svg\"") && svg.contains(">2/2<") && svg.contains(">0/1<"));
    assert!(svg.contains("24.4% (n = 5)") && svg.contains("pooled: n = 5, r = 0.67"), "{svg}");
    let csv = report::csv(&b, REPS, TableChoice::Figure3, &facts());
    let block = |name: &str| csv.split(&format!("# {name}\n")).nth(1).unwrap().split("\n# ").next().unwrap().to_owned();
    for (file, name) in [("figure3_mean_scr.csv", "figure_3a_mean_scr"), ("figure3_scr_bins.csv", "figure_3b_scr_bins"), ("figure3_opening_operations.csv", "figure_3_opening_operations")] {
        assert_eq!(std::fs::read_to_string(figures.join(file)).unwrap().trim_end(), block(name).trim_end(), "{file}");
    }
    let json: Value = serde_json::from_str(&std::fs::read_to_string(figures.join("figure3.json")).unwrap()).unwrap();
    assert_eq!(json, v["sustained_contact"]);
}

/// A 1-rep batch of agent `codex/tokens` whose five T11–T15 rollouts took their tokens from each source: the gateway
/// (harness stdout disagreeing), the harness's stdout, none, a record from before sources were recorded, and an
/// INVALID rollout (in the averages, as the paper averages over all episodes, and said to be).
fn write_token_batch(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    let batch = json!({
        "schema_version": "libero_agent.batch.v1", "status": "finished",
        "settings": {"experiment": "main_table", "harness": "codex", "model": "tokens", "effort": "high", "reps": 1,
            "tasks": [], "seed": 100, "wall_time_s": 300.0, "max_agent_steps": 100, "agent_cmd": null, "sandbox": true},
        "rollout_count": 5, "counts": {"done": 5, "running": 0, "left": 0}, "outcomes": {},
    });
    std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
    let u = |total: u64, source: Option<&str>| {
        let mut v = json!({"available": true, "requests_with_usage": 1, "lines_scanned": 1, "input_tokens": total - 100,
            "output_tokens": 100, "cache_read_input_tokens": 50, "total_tokens": total});
        if let Some(s) = source {
            v["source"] = json!(s);
        }
        v
    };
    let mut gateway = u(9000, Some("model_api_gateway"));
    gateway["harness_stdout"] = json!({"input_tokens": 1, "output_tokens": 1, "total_tokens": 2, "agrees": false});
    let none = json!({"available": false, "requests_with_usage": 0, "lines_scanned": 3, "source": "unavailable"});
    let rollouts = [(11, "SUCCESS", gateway), (12, "FAIL", u(3000, Some("harness_stdout"))), (13, "FAIL", none),
        (14, "SUCCESS", u(6000, None)), (15, "INVALID", u(100_000, Some("model_api_gateway")))];
    let mut lines = String::new();
    for (task, outcome, usage) in rollouts {
        let r = json!({
            "schema_version": "libero_agent.rollout.v1", "rollout_id": format!("w1_t{task}_level3"), "task": format!("T{task}"),
            "task_number": task, "split": split(task), "stage_count": 1, "repetition": 1, "level": 3, "demo": "none",
            "outcome": outcome, "completed_stages": u32::from(outcome == "SUCCESS"), "wall_time_s": 60.0, "usage": usage,
            "infrastructure_error": if outcome == "INVALID" { json!("harness exited") } else { Value::Null },
            "started_at": "2025-01-01T00:00:00Z", "finished_at": "2025-01-01T00:01:00Z",
        });
        lines.push_str(&format!("{r}\n"));
    }
    std::fs::write(dir.join("rollouts.jsonl"), lines).unwrap();
}

#[test]
fn every_row_carries_its_tokens_with_their_source_in_every_format() {
    let dir = tempfile::tempdir().unwrap();
    write_token_batch(&dir.path().join("tok"));
    let b = vec![load_batch(&dir.path().join("tok")).unwrap()];
    assert_eq!(report::default_reps(&b), 1, "the batch's own repetitions");
    let reps = report::default_reps(&b);
    let part = |text: &str, piece: &str| assert!(text.contains(piece), "missing\n{piece}\nin\n{text}");

    // JSON: the row's mean over every episode with usage, INVALID included (9000, 3000, 6000, 100000), the sources,
    // the disagreement.
    let v = report::report_json(&b, reps, &facts());
    let t = &v["rows"][0]["tokens"];
    assert_eq!(t["mean_total"], 29500.0, "{t}");
    assert_eq!((t["rollouts_with_usage"].as_u64(), t["rollouts"].as_u64(), t["invalid_included"].as_u64()), (Some(4), Some(5), Some(1)));
    assert_eq!(t["sources"], json!({"model_api_gateway": 2, "harness_stdout": 1, "unavailable": 1, "not_recorded": 1}));
    let s = &v["rows"][0]["summary"];
    assert_eq!((s["averaged_episodes"].as_u64(), s["averaged_invalid"].as_u64()), (Some(5), Some(1)));
    assert_eq!(t["stdout_disagrees"], json!([{"rollout_id": "w1_t11_level3", "gateway": {"input": 8900, "output": 100, "total": 9000},
        "harness_stdout": {"input": 1, "output": 1, "total": 2}}]));
    let per: Vec<(String, String)> = v["rows"][0]["rollout_tokens"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["rollout_id"].as_str().unwrap().to_owned(), r["tokens"]["source"].as_str().unwrap().to_owned()))
        .collect();
    assert_eq!(per.iter().map(|(_, s)| s.as_str()).collect::<Vec<_>>(),
        ["model_api_gateway", "harness_stdout", "unavailable", "not_recorded", "model_api_gateway"]);

    // Markdown: Table 1 with the sources, per-task cells with marks, and the legend.
    let md = report::markdown(&b, reps, TableChoice::All, &facts());
    part(&md, "| 1.0 min (1 INVALID incl.) | 0.03M (gateway 2, stdout 1, source not recorded 1; 1 without usage; stdout disagrees: 1; 1 INVALID incl.) |");
    part(&md, "| 9,000 G |");
    part(&md, "| 3,000 S |");
    part(&md, "| – |");
    part(&md, "| 6,000 ? |");
    part(&md, "Token sources: G the runner's model-API gateway");

    // CSV: every Table 1 line carries the row's tokens and sources; every rollout its figure and source.
    let csv = report::csv(&b, reps, TableChoice::All, &facts());
    part(&csv, "mean_total_tokens,rollouts_with_usage,tokens_sources,stdout_disagrees");
    part(&csv, "codex/tokens,3,none,score,30,,");
    part(&csv, ",29500.0,4,model_api_gateway=2 harness_stdout=1 unavailable=1 not_recorded=1,1\n");
    part(&csv, "codex/tokens,3,none,w1_t11_level3,T11,1,SUCCESS,9000,8900,50,100,model_api_gateway\n");
    part(&csv, "codex/tokens,3,none,w1_t13_level3,T13,1,FAIL,,,,,unavailable\n");
    part(&csv, "codex/tokens,3,none,w1_t14_level3,T14,1,SUCCESS,6000,5900,50,100,not_recorded\n");

    // LaTeX: the mean and its source column.
    let tex = report::latex(&b, reps, TableChoice::Table1, &facts());
    part(&tex, "& Tokens (M) & Token source \\\\");
    part(&tex, "& 1.0 (1 INVALID incl.) & 0.03 & gateway 2, stdout 1, source not recorded 1; 1 without usage; stdout disagrees: 1; 1 INVALID incl. \\\\");
}

/// An opening operation as the evaluators now record it: `contact` the runs of gripper contact anywhere on the
/// mechanism, `handle` those on its handle (no SCR given: the report computes it from the runs).
fn opening(stage: &str, exec: u64, contact: &[u64], handle: &[u64], completed: bool) -> Value {
    json!({"stage_name": stage, "operation": "open", "exec_steps": exec, "contact_runs": contact, "handle_contact_runs": handle,
        "completed": completed})
}

/// A record of the unordered cooking goals (T21, T22): only the microwave's goal is listed.
fn cooking(opened: bool, op: Value) -> Value {
    let mut v = pe(vec![stage("Microwave_Open", MI, false, opened)], vec![op]);
    v["details"]["order"] = json!("unordered");
    v
}

/// T28's two ordered stages with the operations the agent got to.
fn door(unlatched: bool, opened: bool, ops: Vec<Value>) -> Value {
    pe(vec![stage("01_Unlatch_Door", MI, false, unlatched), stage("02_Open_Door", MI, false, opened)], ops)
}

/// Figure 3 golden test, computed by hand from the paper's definitions (§5.3) over three agents' main-table rollouts
/// (`--reps 2`). SCR = N_sustained / N_exec × 100 with N_sustained = Σ handle runs ≥ 5; an operation counts when
/// entered (its stage reached in the stage analysis).
///
/// * command/a: T21 r1 microwave, 40 steps, handle runs 4, 5, 6 (inside one 30-step contact with the door) → 11/40 =
///   27.5 %, opened; T21 r2 never touched (1,500 pending steps) → not entered; T28 r1 unlatch 20/100 = 20 %, opened, and
///   its door (reached: the latch opened) 50 steps with contact runs 12, 30 on the panel and one handle run of 4 → 0 %,
///   not opened (the panel does not count, a run of 4 is not sustained); T28 r2 unlatch never touched (first stage) →
///   not entered. Mean (27.5 + 20 + 0) / 3 = 95/6.
/// * command/b: T27 r1 drawer 50/200 = 25 %, opened; T27 r2 drawer pushed on its front for 40 steps, no handle → 0 %,
///   entered (touched), not opened; T22 r1 one handle run of 5 in 60 steps → 25/3 %, not opened; T22 r2 one of 4 in 50
///   → 0 %, not opened; a T16 opening (short horizon, 100 %) is no operation of the stage analysis. Mean 25/3.
/// * command/c: T28 r1 unlatch 30/30 = 100 %, door 10/20 = 50 %, both opened; T28 r2 unlatch runs 5, 4 in 50 = 10 %,
///   opened, door never touched but reached (the latch opened) → 0 %, not opened; a video-condition T28 rollout is not
///   read. Mean 160/4 = 40.
/// * Pooled, 11 operations: SCR 0 → 0/4; (0, 10 %] → 1/2 (8.33 no, 10 yes); (10, 25 %] → 2/2 (20, 25); > 25 % → 3/3
///   (27.5, 100, 50); all 6/11. Pearson r = (n Σxy − Σx Σy) / √((n Σx² − (Σx)²)(n Σy² − (Σy)²)) with n = 11,
///   Σx = 1445/6, Σy = 6, Σxy = 232.5, Σx² = 14450 + 25/36 …: numerator 2225/2, x-term 1817225/18, y-term 30.
#[test]
fn figure_3_pools_the_entered_handle_openings_of_every_agent_as_computed_by_hand() {
    let dir = tempfile::tempdir().unwrap();
    let a = [
        with(r(21, 5, 1, 3, "none", "FAIL", 1), cooking(true, opening("Microwave_Open", 40, &[30], &[4, 5, 6], true))),
        with(r(21, 5, 2, 3, "none", "FAIL", 0), cooking(false, opening("Microwave_Open", 1500, &[], &[], false))),
        with(
            r(28, 2, 1, 3, "none", "FAIL", 1),
            door(true, false, vec![opening("01_Unlatch_Door", 100, &[20], &[20], true), opening("02_Open_Door", 50, &[12, 30], &[4], false)]),
        ),
        with(r(28, 2, 2, 3, "none", "FAIL", 0), door(false, false, vec![opening("01_Unlatch_Door", 80, &[], &[], false)])),
    ];
    let drawer = |opened: bool, op: Value| {
        pe(vec![stage("01_Open_Middle_Drawer", MI, false, opened), stage("02_Place_Cookies_Middle_Drawer", OM, false, false)], vec![op])
    };
    let b = [
        with(r(27, 4, 1, 3, "none", "FAIL", 1), drawer(true, opening("01_Open_Middle_Drawer", 200, &[50], &[50], true))),
        with(r(27, 4, 2, 3, "none", "FAIL", 0), drawer(false, opening("01_Open_Middle_Drawer", 100, &[40], &[], false))),
        with(r(22, 5, 1, 3, "none", "FAIL", 0), cooking(false, opening("Microwave_Open", 60, &[5], &[5], false))),
        with(r(22, 5, 2, 3, "none", "FAIL", 0), cooking(false, opening("Microwave_Open", 50, &[4], &[4], false))),
        with(
            r(16, 1, 1, 3, "none", "SUCCESS", 1),
            pe(vec![stage("01_BDDL_Goal_At_Finish", MI, true, true)], vec![opening("01_BDDL_Goal_At_Finish", 50, &[50], &[50], true)]),
        ),
    ];
    let c = [
        with(
            r(28, 2, 1, 3, "none", "SUCCESS", 2),
            door(true, true, vec![opening("01_Unlatch_Door", 30, &[30], &[30], true), opening("02_Open_Door", 20, &[10], &[10], true)]),
        ),
        with(
            r(28, 2, 2, 3, "none", "FAIL", 1),
            door(true, false, vec![opening("01_Unlatch_Door", 50, &[5, 4], &[5, 4], true), opening("02_Open_Door", 40, &[], &[], false)]),
        ),
        with(r(28, 2, 1, 3, "video", "SUCCESS", 2), door(true, true, vec![opening("01_Unlatch_Door", 10, &[10], &[10], true)])),
    ];
    for (name, rollouts) in [("a", &a[..]), ("b", &b[..]), ("c", &c[..])] {
        write_agent_batch(&dir.path().join(name), "main_table", name, rollouts);
    }
    let batches: Vec<LoadedBatch> = ["a", "b", "c"].iter().map(|n| load_batch(&dir.path().join(n)).unwrap()).collect();
    let v = report::report_json(&batches, REPS, &facts());
    let f = &v["sustained_contact"];
    let close = |got: &Value, want: f64, what: &str| {
        let got = got.as_f64().unwrap_or_else(|| panic!("{what}: {got}"));
        assert!((got - want).abs() < 1e-9, "{what}: {got} ≠ {want}");
    };

    // (a) mean SCR per agent over its entered operations
    let agents = f["agents"].as_array().unwrap();
    let names: Vec<(&str, u64)> = agents.iter().map(|a| (a["agent"].as_str().unwrap(), a["operations"].as_u64().unwrap())).collect();
    assert_eq!(names, [("command/a", 3), ("command/b", 4), ("command/c", 4)]);
    for (a, want) in agents.iter().zip([95.0 / 6.0, 25.0 / 3.0, 40.0]) {
        close(&a["mean_scr_percent"], want, a["agent"].as_str().unwrap());
    }
    // what was read and left out: 13 operations (not T16's, not the video rollout's), 2 never entered
    assert_eq!(f["operations"].as_array().map(Vec::len), Some(13));
    assert_eq!((f["not_entered"].as_u64(), f["without_handle_runs"].as_u64(), f["rollouts"].as_u64()), (Some(2), Some(0), Some(10)));
    let scr_of = |agent: &str, task: &str, stage: &str| {
        let op = f["operations"].as_array().unwrap().iter().find(|o| o["agent"] == agent && o["task"] == task && o["stage_name"] == stage).unwrap();
        (op["scr_percent"].as_f64(), op["entered"].as_bool())
    };
    assert_eq!(scr_of("command/a", "T28", "02_Open_Door"), (Some(0.0), Some(true)), "panel contact and a run of 4 count nothing");
    assert_eq!(scr_of("command/a", "T21", "Microwave_Open").1, Some(true));

    // (b) pooled over every agent: per-bin successes with their 95 % Wilson bounds, each from its closed form
    let z: f64 = 1.959_963_984_540_054;
    let z2 = z * z;
    let half = |n: f64| z / (1.0 + z2 / n) * (0.25 / n + z2 / (4.0 * n * n)).sqrt();
    let want: [(u64, u64, f64, f64); 4] = [
        (0, 4, 0.0, z2 / (4.0 + z2)),
        (1, 2, 0.5 - half(2.0), 0.5 + half(2.0)),
        (2, 2, 2.0 / (2.0 + z2), 1.0),
        (3, 3, 3.0 / (3.0 + z2), 1.0),
    ];
    let bins = f["pooled"]["bins"].as_array().unwrap();
    for (b, (k, n, lo, hi)) in bins.iter().zip(want) {
        let p = &b["local_success"];
        assert_eq!((p["successes"].as_u64(), p["trials"].as_u64()), (Some(k), Some(n)), "{b}");
        close(&p["wilson_low"], lo, b["label"].as_str().unwrap());
        close(&p["wilson_high"], hi, b["label"].as_str().unwrap());
    }
    let all = &f["pooled"]["local_success"];
    assert_eq!((all["successes"].as_u64(), all["trials"].as_u64()), (Some(6), Some(11)));
    close(&f["pooled"]["pearson_r"], (2225.0 / 2.0) / (1_817_225.0 / 18.0 * 30.0f64).sqrt(), "Pearson r");

    // the same in CSV and Markdown, and the two-panel SVG
    let csv = report::csv(&batches, REPS, TableChoice::Figure3, &facts());
    has(&csv, "command/b,4,8.3333,1,25.0000,4.5587,69.9358");
    has(&csv, "\"(0,10%]\",2,1,50.0000,9.4531,90.5469,");
    has(&csv, "all,11,6,54.5455,28.0092,78.7287,0.639251");
    has(&csv, "command/a,T28,ep-w1_t28_level3_none,02_Open_Door,50,4,0.0000,true,false,true");
    has(&csv, "command/a,T21,ep-w2_t21_level3_none,Microwave_Open,1500,,0.0000,false,false,false");
    let md = report::markdown(&batches, REPS, TableChoice::Figure3, &facts());
    has(&md, "| command/c | 4 | 40.0% | 3/4 = 75.0% |");
    has(&md, "| SCR 0 | 4 | 0 | 0/4 = 0.0 [0.0, 49.0] |  |");
    has(&md, "| all | 11 | 6 | 6/11 = 54.5 [28.0, 78.7] | 0.639 |");
    assert!(md.contains("13 opening operations of 10 long-horizon rollouts"), "{md}");
    let figures = dir.path().join("figures");
    let paper = report::tables::paper_tables(&batches, &report::rows(&batches, REPS), REPS, &facts());
    report::tables::write_figures(&paper, &figures).unwrap();
    let svg = std::fs::read_to_string(figures.join("figure3.svg")).unwrap();
    assert!(svg.contains("pooled: n = 11, r = 0.64") && svg.contains("15.8% (n = 3)") && svg.contains(">0/4<") && svg.contains(">3/3<"), "{svg}");
}
