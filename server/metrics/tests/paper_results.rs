//! The metrics reproduce the paper's published numbers (`tests/fixtures/paper_results.json`, transcribed from the
//! LIBERO-Agent paper's Table 1 and per-task tables): the perception and short-horizon stable SR columns of Table 1
//! recomputed from the per-task "successes out of three" tables, every Score from its components, the
//! ablation tables' "Overall" columns, and the stable-vs-mean relation of the long-horizon table. Tables 2 and 3
//! (the ablations): their level-3 rows recomputed from the per-task short-horizon tables through the same
//! [`AblationRow`] the report prints, their no-demonstration rows from Table 1's long-horizon columns (checked
//! against the bounds the per-task stage sums allow), and every Overall from its easy and hard cells; each
//! difference from the paper is printed (`cargo test -p libero-metrics --test paper_results -- --nocapture`).
use libero_metrics::{AblationKind, AblationRow, Outcome, Rollout, ScoreComponents, Split, overall, summarize};
use serde_json::Value;

fn fixture() -> Value {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/paper_results.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn number(task: &str) -> u32 {
    task.trim_start_matches('T').parse().unwrap()
}

/// Three rollouts per task with `successes` of them successful (order does not matter to the stable rule).
fn rollouts_from_counts(counts: &Value) -> Vec<Rollout> {
    let mut out = Vec::new();
    for (task, k) in counts.as_object().unwrap() {
        let n = number(task);
        for rep in 1..=3u32 {
            let ok = u64::from(rep) <= k.as_u64().unwrap();
            out.push(Rollout {
                task_number: n,
                split: Split::of_task(n).unwrap(),
                repetition: rep,
                outcome: if ok { Outcome::Success } else { Outcome::Fail },
                judgment_correct: None,
                completed_stages: None,
                stage_count: 1,
                wall_time_s: None,
                total_tokens: None,
                accepted_agent_steps: None,
            });
        }
    }
    out
}

fn pct(x: Option<f64>) -> f64 {
    100.0 * x.expect("a stable value")
}

#[test]
fn table1_success_columns_follow_from_the_per_task_tables() {
    let f = fixture();
    for agent in f["agents"].as_array().unwrap() {
        let name = agent["agent"].as_str().unwrap();
        let mut rs = rollouts_from_counts(&agent["perception_successes_of_3"]);
        rs.extend(rollouts_from_counts(&agent["short_horizon_successes_of_3"]));
        let s = summarize(&rs, 3);
        let t1 = &agent["table1"];
        for (split, column) in [
            (Split::Perception, "perception_task_sr"),
            (Split::ShortHorizonEasy, "short_easy_sr"),
            (Split::ShortHorizonHard, "short_hard_sr"),
        ] {
            let ours = pct(s.split(split).unwrap().stable);
            let paper = t1[column].as_f64().unwrap();
            assert!((ours - paper).abs() < 0.05, "{name} {column}: ours {ours}, paper {paper}");
            assert!(s.split(split).unwrap().complete());
        }
        // Ordinary success is never below the stable rate (a stable task contributes 3/3).
        for split in [Split::Perception, Split::ShortHorizonEasy, Split::ShortHorizonHard] {
            let sp = s.split(split).unwrap();
            assert!(sp.ordinary.rate.unwrap() + 1e-12 >= sp.stable.unwrap(), "{name} {split:?}");
        }
    }
}

#[test]
fn every_score_follows_from_its_components() {
    let f = fixture();
    for agent in f["agents"].as_array().unwrap() {
        let t1 = &agent["table1"];
        let c = |k: &str| t1[k].as_f64().unwrap() / 100.0;
        let components = ScoreComponents {
            j: c("judgment_accuracy"),
            p: c("perception_task_sr"),
            m_easy: c("short_easy_sr"),
            m_hard: c("short_hard_sr"),
            l_easy: c("long_easy_sc"),
            l_hard: c("long_hard_sc"),
        };
        let ours = components.score();
        let paper = t1["score"].as_f64().unwrap();
        // Components are published to one decimal (16.7 for 1/6), so the Score may differ by rounding only.
        assert!((ours - paper).abs() < 0.06, "{}: ours {ours:.3}, paper {paper}", agent["agent"]);
    }
}

#[test]
fn the_stable_stage_completion_never_exceeds_the_mean_over_rollouts() {
    let f = fixture();
    for agent in f["agents"].as_array().unwrap() {
        let sums = agent["long_horizon_stage_fraction_sum_of_3"].as_object().unwrap();
        for (split, column) in [(Split::LongHorizonEasy, "long_easy_sc"), (Split::LongHorizonHard, "long_hard_sc")] {
            let mean: f64 = split.members().iter().map(|n| sums[&format!("T{n}")].as_f64().unwrap() / 3.0).sum::<f64>()
                / split.members().len() as f64;
            let stable = agent["table1"][column].as_f64().unwrap() / 100.0;
            assert!(stable <= mean + 0.005, "{} {column}: stable {stable} > mean {mean}", agent["agent"]);
        }
    }
}

#[test]
fn ablation_overall_is_the_mean_of_easy_and_hard() {
    let f = fixture();
    for key in ["observation_ablation_short_horizon", "demonstration_ablation_long_horizon"] {
        for row in f[key].as_array().unwrap() {
            let g = |k: &str| row[k].as_f64().unwrap();
            assert!((overall(g("easy"), g("hard")) - g("overall")).abs() < 0.051, "{key}: {row}");
        }
    }
    // The "none" context and level-3 rows are the main table's numbers.
    let astra = &f["agents"][0]["table1"];
    let none = &f["demonstration_ablation_long_horizon"][0];
    assert_eq!((none["easy"].as_f64(), none["hard"].as_f64()), (astra["long_easy_sc"].as_f64(), astra["long_hard_sc"].as_f64()));
    let l3 = &f["observation_ablation_short_horizon"][2];
    assert_eq!((l3["easy"].as_f64(), l3["hard"].as_f64()), (astra["short_easy_sr"].as_f64(), astra["short_hard_sr"].as_f64()));
}

#[test]
fn a_complete_synthetic_suite_gets_a_score_and_the_lower_bound_matches_it() {
    let f = fixture();
    let astra = &f["agents"][0];
    let mut rs = rollouts_from_counts(&astra["perception_successes_of_3"]);
    rs.extend(rollouts_from_counts(&astra["short_horizon_successes_of_3"]));
    for r in &mut rs {
        r.judgment_correct = Some(true);
    }
    // Long horizon: every rollout completes half of its stages (K from the fixture, all even except T26/T29).
    for (task, k) in f["long_horizon_stage_counts"].as_object().unwrap() {
        let n = number(task);
        let k = k.as_u64().unwrap() as u32;
        for rep in 1..=3 {
            rs.push(Rollout {
                task_number: n,
                split: Split::of_task(n).unwrap(),
                repetition: rep,
                outcome: Outcome::Fail,
                judgment_correct: None,
                completed_stages: Some(k / 2),
                stage_count: k,
                wall_time_s: Some(690.0),
                total_tokens: Some(1_380_000),
                accepted_agent_steps: Some(40),
            });
        }
    }
    let s = summarize(&rs, 3);
    let score = s.score.expect("complete suite");
    assert!((score - s.score_lower_bound).abs() < 1e-9);
    let l_easy = (4.0 / 8.0 + 2.0 / 4.0 + 1.0 / 3.0 + 2.0 / 4.0 + 1.0 / 3.0) / 5.0;
    let l_hard = (2.0 / 5.0 + 2.0 / 5.0 + 2.0 / 4.0 + 1.0 / 2.0 + 2.0 / 4.0) / 5.0;
    let expected = 5.0 + 10.0 + 5.0 + 10.0 * 0.4 + 20.0 * l_easy + 50.0 * l_hard;
    assert!((score - expected).abs() < 1e-9, "{score} vs {expected}");
    assert_eq!(s.avg_wall_time_min, Some(11.5));
    assert_eq!(s.avg_tokens_millions, Some(1.38));
}

/// The agent record of the fixture whose short name is `short` (the ablation tables name agents by it).
fn agent<'a>(f: &'a Value, short: &str) -> &'a Value {
    f["agents"].as_array().unwrap().iter().find(|a| a["short"] == short).unwrap_or_else(|| panic!("no agent {short}"))
}

/// `x` rounded to one decimal, as the paper prints percentages.
fn one_decimal(x: f64) -> f64 {
    (x * 10.0).round() / 10.0
}

#[test]
fn table2_level3_rows_follow_from_the_per_task_short_horizon_tables() {
    let f = fixture();
    let rows: Vec<&Value> = f["observation_ablation_short_horizon"].as_array().unwrap().iter().filter(|r| r["level"] == 3).collect();
    assert_eq!(rows.len(), 3, "one level-3 row per ablated agent");
    for paper in rows {
        let short = paper["agent"].as_str().unwrap();
        let a = agent(&f, short);
        let ours = AblationRow::of(AblationKind::Observation, "L3", &summarize(&rollouts_from_counts(&a["short_horizon_successes_of_3"]), 3));
        assert!(ours.complete(), "{short}: every short-horizon task has three rollouts");
        for (column, value) in [("easy", ours.easy), ("hard", ours.hard), ("overall", ours.overall)] {
            let (ours, paper) = (pct(value), paper[column].as_f64().unwrap());
            println!("Table 2 {short} L3 {column}: ours {ours:.2}, paper {paper}");
            assert!((ours - paper).abs() < 0.05, "{short} L3 {column}: ours {ours}, paper {paper}");
        }
        // …and they are Table 1's short-horizon columns, as the paper takes them from the main-table run.
        assert_eq!(paper["easy"], a["table1"]["short_easy_sr"], "{short}");
        assert_eq!(paper["hard"], a["table1"]["short_hard_sr"], "{short}");
    }
}

#[test]
fn table3_none_rows_are_table1_long_horizon_columns_within_the_per_task_bounds() {
    let f = fixture();
    let rows: Vec<&Value> =
        f["demonstration_ablation_long_horizon"].as_array().unwrap().iter().filter(|r| r["context"] == "none").collect();
    assert_eq!(rows.len(), 3, "one no-demonstration row per ablated agent");
    for paper in rows {
        let short = paper["agent"].as_str().unwrap();
        let a = agent(&f, short);
        assert_eq!(paper["easy"], a["table1"]["long_easy_sc"], "{short}");
        assert_eq!(paper["hard"], a["table1"]["long_hard_sc"], "{short}");
        // The per-task table gives each task's sum of c/K over three rollouts, not its minimum: the stable SC lies
        // between max(0, sum − 2) (two rollouts at 1) and sum / 3 (all equal), averaged over the subset.
        let sums = a["long_horizon_stage_fraction_sum_of_3"].as_object().unwrap();
        for (split, column) in [(Split::LongHorizonEasy, "easy"), (Split::LongHorizonHard, "hard")] {
            let n = split.members().len() as f64;
            let sum = |t: &u32| sums[&format!("T{t}")].as_f64().unwrap();
            let low = 100.0 * split.members().iter().map(|t| (sum(t) - 2.0).max(0.0)).sum::<f64>() / n;
            let high = 100.0 * split.members().iter().map(|t| sum(t) / 3.0).sum::<f64>() / n;
            let sc = paper[column].as_f64().unwrap();
            println!("Table 3 {short} none {column}: paper {sc}, per-task bounds [{low:.1}, {high:.1}]");
            assert!(low - 0.05 <= sc && sc <= high + 0.05, "{short} {column}: {sc} outside [{low}, {high}]");
        }
    }
}

#[test]
fn every_ablation_overall_is_recomputed_and_each_rounding_difference_is_shown() {
    let f = fixture();
    let mut differences = Vec::new();
    for (key, by) in [("observation_ablation_short_horizon", "level"), ("demonstration_ablation_long_horizon", "context")] {
        for row in f[key].as_array().unwrap() {
            let g = |k: &str| row[k].as_f64().unwrap();
            let ours = overall(g("easy"), g("hard"));
            let paper = g("overall");
            println!("{key} {} {}: overall of the printed cells {ours:.3} → {:.1}, paper {paper}", row["agent"], row[by], one_decimal(ours));
            // The printed cells are rounded to 0.1, so their mean can miss the paper's by at most 0.05.
            assert!((ours - paper).abs() <= 0.05 + 1e-9, "{key}: {row}");
            if (one_decimal(ours) - paper).abs() > 1e-9 {
                differences.push(format!("{} {}: ours {:.1}, paper {paper}", row["agent"], row[by], one_decimal(ours)));
            }
        }
    }
    // The paper averages its unrounded cells, so three printed Overalls differ from the mean of the printed cells:
    // Opus's and Fable's none rows (easy 16.7 = 1/6 of the stages: (1/6 + 0) / 2 = 8.33 → 8.3, where 16.7 gives
    // 8.35 → 8.4) and Opus's video row (easy 11.7 = 7/60, e.g. minima of 1/4 and 1/3 over five tasks: 5.83 → 5.8).
    println!("differences from the paper's Overall (rounding only): {differences:#?}");
    assert_eq!(
        differences,
        [r#""Opus" "none": ours 8.4, paper 8.3"#, r#""Opus" "video": ours 5.9, paper 5.8"#, r#""Fable" "none": ours 8.4, paper 8.3"#]
    );
    let unrounded_overall = |easy: f64| one_decimal(100.0 * overall(easy, 0.0));
    assert_eq!((unrounded_overall(1.0 / 6.0), unrounded_overall(7.0 / 60.0)), (8.3, 5.8));
    assert_eq!((one_decimal(100.0 / 6.0), one_decimal(700.0 / 60.0)), (16.7, 11.7), "the printed easy cells");
}

#[test]
fn an_ablation_row_has_an_overall_only_when_both_subsets_are_scored() {
    // T11 stable (easy), T12 two of three (hard): 1.0 and 0.0 over one task each, Overall their mean.
    let both = summarize(&rollouts_from_counts(&serde_json::json!({"T11": 3, "T12": 2})), 3);
    let row = AblationRow::of(AblationKind::Observation, "L1", &both);
    assert_eq!((row.easy, row.hard, row.overall), (Some(1.0), Some(0.0), Some(0.5)));
    assert_eq!((row.easy_tasks_scored, row.hard_tasks_scored, row.complete()), (1, 1, false));
    let easy_only = summarize(&rollouts_from_counts(&serde_json::json!({"T11": 3})), 3);
    let row = AblationRow::of(AblationKind::Observation, "L2", &easy_only);
    assert_eq!((row.easy, row.hard, row.overall), (Some(1.0), None, None));
}
