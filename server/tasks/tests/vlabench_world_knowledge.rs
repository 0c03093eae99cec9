//! The pool's VLABench world-knowledge selections (`vlabench_world_knowledge` tasks 0–5, 7, 9, 11, 14, 15; task 10
//! is T07) and `vlabench_perception` task 5 (T04's blocks, the spotted one the target) on definitions of their own
//! (`tasks/pool.json`): three candidates and a basket or collection bin each, judged like the release's bin tasks
//! (T02, T04, T07): the BDDL `In` goal on the final state, the first object grasped and lifted judged against the
//! private `judgment_target`. Every entry composes and judges an idle start failed; one is played by its expert:
//! `solve` puts the target in (judged right) and `wrong_target` (the near miss) puts a distractor in and fails, judged
//! wrong. Starts are the seed-100 placement, so a run is deterministic.
use libero_sim::AssetPaths;
use libero_tasks::expert::SOLVE;
use libero_tasks::pool::Runs;
use libero_tasks::{EvaluationRecord, Pool, expert_behaviours};

mod common;

/// The entries this file covers.
const ENTRIES: [&str; 12] = [
    "vlabench_world_knowledge/0",
    "vlabench_world_knowledge/1",
    "vlabench_world_knowledge/2",
    "vlabench_world_knowledge/3",
    "vlabench_world_knowledge/4",
    "vlabench_world_knowledge/5",
    "vlabench_world_knowledge/7",
    "vlabench_world_knowledge/9",
    "vlabench_world_knowledge/11",
    "vlabench_world_knowledge/14",
    "vlabench_world_knowledge/15",
    // the perception suite's spotted block: T04's scene, a selection of the same kind
    "vlabench_perception/5",
];

fn stages(r: &EvaluationRecord) -> (bool, usize, usize) {
    (r.success, r.completed_required_stage_count, r.required_stage_count)
}

#[test]
fn every_world_knowledge_entry_composes_and_judges_the_idle_start_failed() {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let pool = Pool::discover().unwrap();
    for id in ENTRIES {
        let e = pool.get(id).unwrap();
        let Runs::Own(files, checker) = pool.runs(e, &paths).unwrap() else { panic!("{id} runs on its own definition") };
        assert_eq!((files.placement_seed, checker.kind.as_str()), (Some(100), "bddl_terminal"), "{id}");
        let target = checker.params["judgment_target"].as_str().expect("a private judgment target");
        let bddl = std::fs::read_to_string(&files.bddl).unwrap();
        assert!(bddl.contains(e.instruction.trim_end_matches('.')), "{id}: the scene's language is the registered one");
        assert!(bddl.contains(&format!("(In {target} ")), "{id}: the goal puts the judgment target in the receptacle");
        // an idle robot: nothing is in the receptacle, nothing is committed to
        let idle = common::idle(id, 20);
        assert_eq!(stages(&idle), (false, 0, 1), "{id}: {idle:?}");
        assert!(idle.first_commitment.is_none(), "{id}: {idle:?}");
        assert!(expert_behaviours(&e.reference()).is_some_and(|b| b.contains(&"wrong_target")), "{id} has an expert");
    }
}

#[test]
fn the_sweet_condiment_expert_puts_the_sugar_in_the_basket_and_the_salt_fails() {
    let solve = common::play("vlabench_world_knowledge/0", SOLVE);
    assert_eq!(stages(&solve), (true, 1, 1), "{solve:?}");
    assert_eq!(solve.judgment_correct, Some(true), "{solve:?}");
    let wrong = common::play("vlabench_world_knowledge/0", "wrong_target");
    assert_eq!(stages(&wrong), (false, 0, 1), "{wrong:?}");
    assert_eq!(wrong.judgment_correct, Some(false), "{wrong:?}");
}

/// Every entry's `solve` and all its near misses (each puts a distractor in the receptacle and fails, judged wrong).
/// Slow in debug: `cargo test -p libero-tasks --test vlabench_world_knowledge -- --ignored`.
#[test]
#[ignore]
fn every_world_knowledge_expert_solves_it_and_its_near_misses_fail() {
    for id in ENTRIES {
        for (b, r) in common::solved_with_near_misses(id) {
            assert_eq!(stages(&r), (false, 0, 1), "{id} {b}: {r:?}");
            assert_eq!(r.judgment_correct, Some(false), "{id} {b}: {r:?}");
        }
    }
}
