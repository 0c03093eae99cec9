//! RoboMemArena's pour tasks (6, 8, 9, 10, 15, 16, 22) and microwave tasks (20, 21, 23, 24) as pool entries with
//! definitions of their own: every one composes and its staged evaluator judges the start 0 of 3; one expert per
//! family completes all three stages while its near misses fail. Starts are the seed-100 placement, so an expert's
//! run is deterministic: one successful run stands for three.
use libero_sim::AssetPaths;
use libero_tasks::judge::evaluator::FailureReason;
use libero_tasks::pool::Runs;
use libero_tasks::{Pool, Tick, build_evaluator, expert::SOLVE};

mod common;

const POURS: [u32; 7] = [6, 8, 9, 10, 15, 16, 22];
const MICROWAVES: [u32; 4] = [20, 21, 23, 24];

#[test]
fn every_pour_and_microwave_entry_composes_and_judges_its_start_0_of_3() {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let pool = Pool::discover().unwrap();
    for t in POURS.into_iter().chain(MICROWAVES) {
        let e = pool.get(&format!("robomemarena/{t}")).unwrap();
        let Runs::Own(files, checker) = pool.runs(e, &paths).unwrap() else { panic!("robomemarena/{t} runs on its own definition") };
        assert_eq!((files.placement_seed, checker.kind.as_str()), (Some(100), "private_ordered_stages"), "robomemarena/{t}");
        let (scene, mut sim) = common::scene_and_sim(&files.bddl);
        for _ in 0..10 {
            sim.step([0.0; 7]).unwrap();
        }
        let mut evaluator = build_evaluator(Some(&checker), Some(&e.reference()), &scene, sim.model()).unwrap();
        evaluator.reset(sim.data(), Tick::at_control_step(0, 0.0));
        for k in 1..=3 {
            evaluator.observe_control_step(sim.data(), Tick::at_control_step(k, 0.05 * k as f64));
        }
        let r = evaluator.finish(sim.data(), Tick::at_control_step(3, 0.15));
        assert_eq!((r.success, r.completed_required_stage_count, r.required_stage_count), (false, 0, 3), "robomemarena/{t}");
        assert!(libero_tasks::expert_behaviours(&e.reference()).is_some_and(|b| b.contains(&"partial_1")), "robomemarena/{t}");
    }
}

#[test]
fn task_6s_expert_pours_twice_and_one_pour_or_three_fail() {
    let solve = common::play("robomemarena/6", SOLVE);
    assert_eq!((solve.success, solve.completed_required_stage_count), (true, 3), "{solve:?}");
    assert_eq!(solve.bddl_final_goal_success, Some(true), "the bottle ends in the drainer, as the instruction says");
    let one = common::play("robomemarena/6", "partial_2");
    assert_eq!((one.success, one.completed_required_stage_count), (false, 2), "{one:?}");
    let three = common::play("robomemarena/6", "three_pours");
    assert!(!three.success && three.completed_required_stage_count == 3, "{three:?}");
    assert_eq!(three.failure_reason, Some(FailureReason::ExtraPour));
}

/// Every pour expert: `cargo test -p libero-tasks --test robomem_pour_microwave -- --ignored` (≈ 15 s for the pours).
#[test]
#[ignore]
fn every_pour_expert_completes_all_three_stages_and_stopping_after_the_lift_fails() {
    solve_all_and_fail_after_one_stage(&POURS);
}

/// `solve` completes 3 of 3 for every task and leaves the diagnostic BDDL goal (the parts of the instruction the
/// checker does not judge) true, except task 10's, which is never true; `partial_1` fails with 1.
fn solve_all_and_fail_after_one_stage(tasks: &[u32]) {
    for t in tasks {
        let solve = common::play(&format!("robomemarena/{t}"), SOLVE);
        assert_eq!((solve.success, solve.completed_required_stage_count), (true, 3), "robomemarena/{t}: {solve:?}");
        assert_eq!(solve.bddl_final_goal_success, Some(*t != 10), "robomemarena/{t}: {:?}", solve.bddl_goal);
        let one = common::play(&format!("robomemarena/{t}"), "partial_1");
        assert_eq!((one.success, one.completed_required_stage_count), (false, 1), "robomemarena/{t}: {one:?}");
    }
}

#[test]
fn task_24s_expert_opens_the_microwave_then_puts_both_objects_in_and_stopping_after_the_first_fails() {
    let solve = common::play("robomemarena/24", SOLVE);
    assert_eq!((solve.success, solve.completed_required_stage_count), (true, 3), "{solve:?}");
    assert_eq!(solve.bddl_final_goal_success, Some(true), "both In the heating region: inside the cavity, not only near it");
    let first = common::play("robomemarena/24", "partial_2");
    assert_eq!((first.success, first.completed_required_stage_count), (false, 2), "{first:?}");
}

/// Every microwave expert: `cargo test -p libero-tasks --test robomem_pour_microwave -- --ignored` (with the pours,
/// ≈ 25 s).
#[test]
#[ignore]
fn every_microwave_expert_completes_all_three_stages_and_only_opening_the_door_fails() {
    solve_all_and_fail_after_one_stage(&MICROWAVES);
}
