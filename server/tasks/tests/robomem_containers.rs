//! RoboMemArena's container tasks on definitions of their own (`tasks/pool.json`): two objects into the basket
//! (tasks 1–3), from plate 1 onto plate 2 (25, 26), into the open middle drawer (13, 17), into the top drawer and
//! another one (11, 14), the butter into the empty drawer after checking all three (5). Every entry composes and its
//! staged evaluator judges an idle start 0/K; one task of each family is played by its expert: `solve` completes all
//! K stages, `partial_<n>` (a near miss) fails with exactly n. Starts are the seed-100 placement, so a run is
//! deterministic: one `solve` here stands for any number of repeats (3/3 included).
use libero_sim::AssetPaths;
use libero_tasks::expert::SOLVE;
use libero_tasks::pool::Runs;
use libero_tasks::{EvaluationRecord, Pool, Tick, build_evaluator, expert_behaviours};

mod common;

/// The entries this file covers, with K.
const ENTRIES: &[(&str, usize)] = &[
    ("robomemarena/5", 8),
    ("robomemarena/1", 2),
    ("robomemarena/2", 2),
    ("robomemarena/3", 2),
    ("robomemarena/11", 5),
    ("robomemarena/13", 3),
    ("robomemarena/14", 5),
    ("robomemarena/17", 3),
    ("robomemarena/25", 2),
    ("robomemarena/26", 2),
];

fn stages(r: &EvaluationRecord) -> (bool, usize, usize) {
    (r.success, r.completed_required_stage_count, r.required_stage_count)
}

#[test]
fn every_container_entry_composes_and_its_evaluator_judges_the_idle_start_zero_of_k() {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let pool = Pool::discover().unwrap();
    for &(id, k) in ENTRIES {
        let e = pool.get(id).unwrap();
        assert_eq!(e.stage_count, k, "{id}: the pool's K");
        let Runs::Own(files, checker) = pool.runs(e, &paths).unwrap() else { panic!("{id} runs on its own definition") };
        assert_eq!(files.placement_seed, Some(100), "{id}");
        let (scene, mut sim) = common::scene_and_sim(&files.bddl);
        let mut evaluator = build_evaluator(Some(&checker), Some(&e.reference()), &scene, sim.model()).unwrap();
        evaluator.reset(sim.data(), Tick::at_control_step(0, 0.0));
        // an idle robot: nothing moves but what settles
        for k in 1..=20 {
            sim.step([0.0; 7]).unwrap();
            evaluator.observe_control_step(sim.data(), Tick::at_control_step(k, 0.05 * k as f64));
        }
        let idle = evaluator.finish(sim.data(), Tick::at_control_step(20, 1.0));
        assert_eq!(stages(&idle), (false, 0, k), "{id}: {idle:?}");
        assert!(expert_behaviours(&e.reference()).is_some_and(|b| b.contains(&"partial_1")), "{id} has an expert");
    }
}

/// `solve` completes all K stages and succeeds; `partial_<n>` completes exactly n and fails.
fn solves_and_stopping_after_n_stages_fails(id: &str, k: usize, n: usize) {
    let solve = common::play(id, SOLVE);
    assert_eq!(stages(&solve), (true, k, k), "{id}: {solve:?}");
    let partial = common::play(id, &format!("partial_{n}"));
    assert_eq!(stages(&partial), (false, n, k), "{id} partial_{n}: {partial:?}");
}

#[test]
fn basket_expert_puts_cookies_then_tomato_sauce_in_and_stopping_after_the_cookies_fails() {
    solves_and_stopping_after_n_stages_fails("robomemarena/1", 2, 1);
}

#[test]
fn plate_expert_moves_butter_then_cream_cheese_to_plate2_and_stopping_after_the_butter_fails() {
    solves_and_stopping_after_n_stages_fails("robomemarena/25", 2, 1);
}

#[test]
fn drawer_expert_opens_the_middle_drawer_and_puts_cookies_then_butter_in_and_stopping_after_the_cookies_fails() {
    solves_and_stopping_after_n_stages_fails("robomemarena/13", 3, 2);
}

/// Every entry's `solve` and all its near misses: `partial_<n>` completes exactly n stages, `undo` records a
/// regression, any other near miss (task 5's `wrong_drawer`) fails. Slow (≈ 2 min in debug):
/// `cargo test -p libero-tasks --test robomem_containers -- --ignored`.
#[test]
#[ignore]
fn every_container_entrys_expert_solves_it_and_its_near_misses_fail() {
    let pool = Pool::discover().unwrap();
    for &(id, k) in ENTRIES {
        let solve = common::play(id, SOLVE);
        assert_eq!(stages(&solve), (true, k, k), "{id}: {solve:?}");
        for &b in expert_behaviours(&pool.get(id).unwrap().reference()).unwrap() {
            let r = common::play(id, b);
            match b.strip_prefix("partial_").and_then(|n| n.parse::<usize>().ok()) {
                Some(n) => assert_eq!(stages(&r), (false, n, k), "{id} {b}: {r:?}"),
                None if b == "undo" => assert!(!r.success && !r.stage_regressions.is_empty(), "{id} undo: {r:?}"),
                None => assert!(!r.success, "{id} {b}: {r:?}"),
            }
        }
    }
}

