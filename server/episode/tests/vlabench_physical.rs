//! The pool's seesaw variants on definitions of their own (`tasks/pool.json`), through the episode's own physics
//! (`WorldPhysics`: seeded placement, the private masses written into the model, T30's posed and settled start, the
//! `vlabench_physical` reset order): `vlabench_physical/1` adaptive_seesaw_usage and `/2` active_weight_comparison.
//! An idle start completes nothing; the expert's `solve` completes all four stages; its near misses fail.
use libero_episode::observation::Level;
use libero_episode::physics::{WorldPhysics, WorldSpec};
use libero_episode::task::resolve_task;
use libero_sim::AssetPaths;
use libero_tasks::EvaluationRecord;
use libero_tasks::expert::SOLVE;

/// The world of pool entry `id`, started as an episode starts it, and the id its expert answers to.
fn world(id: &str) -> (WorldPhysics, String) {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let task = resolve_task(id, &paths).unwrap();
    let expert_id = task.suite.as_ref().map_or_else(|| task.task_ref.clone(), |s| s.id.clone());
    let spec = WorldSpec { task, level: Level::L3, seed: 100, init_index: 0, paths };
    let mut w = WorldPhysics::build(&spec, |_, _, _| Ok(())).unwrap();
    w.start(|_| {}).unwrap();
    (w, expert_id)
}

/// An action as an episode receives it (`expert_run.rs::quantize`).
fn as_sent(a: [f64; 7]) -> [f64; 7] {
    a.map(|x| ((x * 1e6).round() / 1e6).clamp(-1.0, 1.0))
}

fn play(id: &str, behaviour: &str) -> EvaluationRecord {
    let (mut w, expert_id) = world(id);
    let mut expert = libero_tasks::expert_for(&expert_id, behaviour, &w.scene, w.model()).unwrap();
    let mut steps = 0;
    while let Some(a) = expert.act(&w.sim) {
        w.step(&as_sent(a)).unwrap();
        steps += 1;
        assert!(steps < 6_000, "{id} {behaviour}: the script ends");
    }
    w.evaluate()
}

fn idle(id: &str, steps: u32) -> EvaluationRecord {
    let (mut w, _) = world(id);
    for _ in 0..steps {
        w.step(&[0.0; 7]).unwrap();
    }
    w.evaluate()
}

fn stages(r: &EvaluationRecord) -> (bool, usize, usize) {
    (r.success, r.completed_required_stage_count, r.required_stage_count)
}

fn check(r: &EvaluationRecord, name: &str) -> bool {
    r.terminal_state_checks.iter().find(|c| c.name == name).is_some_and(|c| c.passed)
}

#[test]
fn idle_starts_complete_nothing() {
    for id in ["vlabench_physical/1", "vlabench_physical/2"] {
        let r = idle(id, 40);
        assert_eq!(stages(&r), (false, 0, 4), "{id}: {r:?}");
    }
}

#[test]
fn adaptive_seesaw_the_heavy_pair_lifts_the_payload_into_the_basket_and_the_light_pair_fails_the_mass_gate() {
    let solve = play("vlabench_physical/1", SOLVE);
    println!("solve: {}", serde_json::to_string(&solve.details).unwrap());
    assert_eq!(stages(&solve), (true, 4, 4), "{solve:?}");
    let d = solve.details.as_ref().unwrap();
    assert_eq!(d["selected_weights"], serde_json::json!(["weight_c", "weight_a"]), "{d}");
    let light = play("vlabench_physical/1", "light_pair");
    println!("light_pair: {}", serde_json::to_string(&light.details).unwrap());
    assert_eq!(stages(&light).0, false, "{light:?}");
    // the board tilts, the payload rises and ends in the basket: only the selection's mass (0.90 < 1.218 kg) fails
    assert_eq!(light.completed_required_stage_count, 2, "{light:?}");
    assert!(!check(&light, "selected_mass_threshold_met") && check(&light, "payload_in_basket"), "{light:?}");
    assert!(check(&light, "payload_lift_observed"), "{light:?}");
    let partial = play("vlabench_physical/1", "partial_3");
    assert_eq!(stages(&partial), (false, 3, 4), "{partial:?}");
}

#[test]
fn weight_comparison_probing_both_then_the_heavier_into_the_basket_passes_and_its_near_misses_fail() {
    let solve = play("vlabench_physical/2", SOLVE);
    println!("solve: {}", serde_json::to_string(&solve.details).unwrap());
    assert_eq!(stages(&solve), (true, 4, 4), "{solve:?}");
    let lighter = play("vlabench_physical/2", "lighter_in_basket");
    println!("lighter: {}", serde_json::to_string(&lighter.details).unwrap());
    assert_eq!(stages(&lighter), (false, 3, 4), "{lighter:?}");
    let skip = play("vlabench_physical/2", "skip_probing");
    println!("skip: {}", serde_json::to_string(&skip.details).unwrap());
    assert_eq!(stages(&skip), (false, 0, 4), "{skip:?}");
}
