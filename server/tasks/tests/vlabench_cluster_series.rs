//! The pool's `vlabench_additional/1` (cluster_series) on its own definition (`tasks/pool.json`): two apples and two
//! primitive bananas between two LIBERO baskets, judged by the staged evaluator from the entry's checker_params with
//! VLABench's rule (K = 2: one class gathered in one basket, then the classes in separate baskets, either assignment;
//! a fruit counts only In the basket's region and touching it). The entry composes and an idle start is judged 0 of 2;
//! the expert's `solve` completes both stages and succeeds, its near miss `wrong_basket` (the second banana into the
//! apples' basket) completes only the first and fails. Starts are the seed-100 placement, so a run is deterministic.
use libero_sim::AssetPaths;
use libero_tasks::expert::SOLVE;
use libero_tasks::pool::Runs;
use libero_tasks::{EvaluationRecord, Pool, expert_behaviours};

mod common;

const ENTRY: &str = "vlabench_additional/1";

fn stages(r: &EvaluationRecord) -> (bool, usize, usize) {
    (r.success, r.completed_required_stage_count, r.required_stage_count)
}

fn terminal(r: &EvaluationRecord, name: &str) -> bool {
    r.terminal_state_checks.iter().any(|c| c.name == name && c.passed)
}

#[test]
fn cluster_series_composes_and_judges_the_idle_start_zero_of_two() {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let pool = Pool::discover().unwrap();
    let e = pool.get(ENTRY).unwrap();
    assert_eq!((e.name.as_str(), e.stage_count), ("cluster_series", 2));
    let Runs::Own(files, checker) = pool.runs(e, &paths).unwrap() else { panic!("{ENTRY} runs on its own definition") };
    assert_eq!((files.placement_seed, checker.kind.as_str()), (Some(100), "private_ordered_stages"));
    let bddl = std::fs::read_to_string(&files.bddl).unwrap();
    assert!(bddl.contains(e.instruction.trim_end_matches('.')), "the scene's language is the registered one");
    let idle = common::idle(ENTRY, 20);
    assert_eq!(stages(&idle), (false, 0, 2), "{idle:?}");
    assert!(!terminal(&idle, "all_objects_physically_relocated"), "{idle:?}");
    assert!(expert_behaviours(&e.reference()).is_some_and(|b| b.contains(&"wrong_basket")), "{ENTRY} has an expert");
}

#[test]
fn the_expert_sorts_apples_and_bananas_into_the_two_baskets() {
    let solve = common::play(ENTRY, SOLVE);
    assert_eq!(stages(&solve), (true, 2, 2), "{solve:?}");
    assert!(solve.terminal_state_checks.iter().all(|c| c.passed), "{solve:?}");
}

#[test]
fn one_banana_in_the_apples_basket_fails_after_the_first_stage() {
    let wrong = common::play(ENTRY, "wrong_basket");
    assert_eq!(stages(&wrong), (false, 1, 2), "{wrong:?}");
    assert!(!terminal(&wrong, "classes_in_separate_baskets"), "{wrong:?}");
}

