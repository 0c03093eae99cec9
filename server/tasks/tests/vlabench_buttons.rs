//! The pool's seven VLABench question-bank buttons (`vlabench_button` tasks 0–6) on definitions of their own
//! (`tasks/pool.json`): three candidate-button pairs each, judged by T06/T09/T10's contact-gated button checker with
//! the private target in the entry's `checker_params`. Every entry composes and judges an idle start 0 of 1; one is
//! played by its expert: `solve` presses the target (1 of 1) and `wrong_target` (the near miss) presses another
//! button and fails on the wrong press. Starts are the seed-100 placement, so a run is deterministic.
use libero_sim::AssetPaths;
use libero_tasks::expert::{SOLVE, SceneRefs};
use libero_tasks::pool::Runs;
use libero_tasks::{EvaluationRecord, Pool, expert_behaviours};

mod common;

/// The entries this file covers.
const ENTRIES: [&str; 7] = [
    "vlabench_button/0",
    "vlabench_button/1",
    "vlabench_button/2",
    "vlabench_button/3",
    "vlabench_button/4",
    "vlabench_button/5",
    "vlabench_button/6",
];

fn stages(r: &EvaluationRecord) -> (bool, usize, usize) {
    (r.success, r.completed_required_stage_count, r.required_stage_count)
}

fn wrong_button_pressed(r: &EvaluationRecord) -> bool {
    r.details.as_ref().is_some_and(|d| d["wrong_button_pressed"] == true)
}

#[test]
fn every_question_button_composes_and_judges_the_idle_start_zero_of_one() {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let pool = Pool::discover().unwrap();
    for id in ENTRIES {
        let e = pool.get(id).unwrap();
        let Runs::Own(files, checker) = pool.runs(e, &paths).unwrap() else { panic!("{id} runs on its own definition") };
        assert_eq!((files.placement_seed, checker.kind.as_str()), (Some(100), "private_contact_gated_button"), "{id}");
        let bddl = std::fs::read_to_string(&files.bddl).unwrap();
        assert!(bddl.contains(e.instruction.trim_end_matches('.')), "{id}: the scene's language is the registered one");
        // an idle robot: nothing presses anything
        let idle = common::idle(id, 20);
        assert_eq!(stages(&idle), (false, 0, 1), "{id}: {idle:?}");
        assert!(!wrong_button_pressed(&idle) && idle.first_commitment.is_none(), "{id}: {idle:?}");
        assert!(expert_behaviours(&e.reference()).is_some_and(|b| b.contains(&"wrong_target")), "{id} has an expert");
    }
}

/// The fixture's mass (its root body and the `object` body under it): the button stack plus the candidate's
/// density × volume.
fn fixture_mass(refs: &SceneRefs, button: &str) -> f64 {
    let root = refs.instance_body(button).unwrap();
    let parents = refs.model.body_parentid();
    (0..parents.len()).filter(|&b| b == root || parents[b] as usize == root).map(|b| refs.model.body_mass()[b]).sum()
}

#[test]
fn candidate_masses_follow_real_densities() {
    let pool = Pool::discover().unwrap();
    let buttons = ["button_1", "button_2", "button_3"];
    let masses = |id: &str| {
        let (_, scene, sim, _) = common::start(id);
        let refs = SceneRefs::new(&scene, sim.model()).unwrap();
        let m: Vec<f64> = buttons.iter().map(|b| fixture_mass(&refs, b)).collect();
        let params = &pool.get(id).unwrap().definition.as_ref().unwrap().checker_params;
        (m, buttons.iter().position(|b| params["target_button"] == *b).unwrap())
    };
    // density: three equal blocks, so the densest is the heaviest
    let (m, target) = masses("vlabench_button/0");
    assert!(m.iter().enumerate().all(|(i, x)| i == target || *x < m[target]), "{m:?}");
    // smallest mass: three objects of the same wood, the smallest is the lightest
    let (m, target) = masses("vlabench_button/1");
    assert!(m.iter().enumerate().all(|(i, x)| i == target || *x > m[target]), "{m:?}");
}

#[test]
fn the_density_expert_presses_the_steel_blocks_button_and_pressing_the_glass_blocks_fails() {
    let solve = common::play("vlabench_button/0", SOLVE);
    assert_eq!(stages(&solve), (true, 1, 1), "{solve:?}");
    assert_eq!(solve.judgment_correct, Some(true), "{solve:?}");
    assert!(!wrong_button_pressed(&solve), "{solve:?}");
    let wrong = common::play("vlabench_button/0", "wrong_target");
    assert!(!wrong.success && wrong_button_pressed(&wrong), "{wrong:?}");
    assert_eq!(wrong.judgment_correct, Some(false), "{wrong:?}");
}

/// Every entry's `solve` and all its near misses (each presses a button other than the target and fails on that
/// press). Slow in debug: `cargo test -p libero-tasks --test vlabench_buttons -- --ignored`.
#[test]
#[ignore]
fn every_question_buttons_expert_solves_it_and_its_near_misses_fail() {
    for id in ENTRIES {
        for (b, r) in common::solved_with_near_misses(id) {
            assert!(!r.success && wrong_button_pressed(&r), "{id} {b}: {r:?}");
            assert_eq!(r.judgment_correct, Some(false), "{id} {b}: {r:?}");
        }
    }
}
