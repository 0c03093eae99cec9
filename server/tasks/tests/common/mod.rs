//! Helpers shared by the tasks crate's scene tests.
use std::path::Path;
use std::sync::Arc;

use libero_sim::compose::{ComposedScene, compose_file};
use libero_sim::placement::Placement;
use libero_sim::{AssetPaths, Simulation};
use libero_episode::Level;
use libero_episode::physics::{WorldPhysics, WorldSpec};
use libero_episode::task::resolve_task;
use libero_tasks::{EvaluationRecord, Evaluator, Pool, Tick};

/// A task scene composed from `bddl`, placed with LIBERO's seed-100 sampler (the seed the release tasks without
/// trusted init states use), and a simulation starting from that placement as an episode's does
/// (`server/episode/src/physics.rs`): the robot as its reset leaves it (arm at LIBERO's `init_qpos`), the objects and
/// articulations where the placement put them.
#[allow(dead_code)] // not every test binary composes a raw BDDL file
pub fn scene_and_sim(bddl: &Path) -> (ComposedScene, Simulation) {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let scene = compose_file(bddl, &paths).unwrap();
    let mut model = scene.compile().unwrap();
    let placement = Placement::sample(&scene, 100, Some(&model)).unwrap();
    placement.apply(&mut model).unwrap();
    let mut sim = Simulation::new(Arc::new(model)).unwrap();
    let mut row = sim.state_row();
    let nq = sim.model().ffi().nq as usize;
    placement.write_qpos(sim.model(), &mut row[1..1 + nq]).unwrap();
    sim.set_init_state(&row).unwrap();
    (scene, sim)
}

/// An expert action as an episode steps it: sent as JSON rounded to 1e-6 and clamped to [-1, 1]
/// (`server/episode/src/expert_run.rs::quantize`), so that `play` passes only when `libero-agent expert` does.
#[allow(dead_code)] // not every test binary plays an expert
pub fn as_sent(a: [f64; 7]) -> [f64; 7] {
    a.map(|x| ((x * 1e6).round() / 1e6).clamp(-1.0, 1.0))
}

/// The seed an episode gets when its request names none (`PrepareRequest`'s default), which the pool entries'
/// fixed placement seeds override.
const DEFAULT_SEED: u64 = 100;

/// An entry's world as an episode builds and starts it: the very rule of production
/// (`libero_episode::physics::WorldPhysics`: the task resolved as `POST /api/episodes` resolves it, its placement or
/// init state, private model edits, the settle steps, the evaluator reset), so a test passes only where an episode
/// would.
#[allow(dead_code)] // not every test binary starts an entry
pub fn world(entry: &str) -> WorldPhysics {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let task = resolve_task(entry, &paths).unwrap_or_else(|e| panic!("{entry}: {e}"));
    let spec = WorldSpec { task, level: Level::L3, seed: DEFAULT_SEED, init_index: 0, paths };
    let mut world = WorldPhysics::build(&spec, |_, _, _| Ok(())).unwrap_or_else(|e| panic!("{entry}: {e}"));
    world.start(|_| {}).unwrap();
    world
}

/// An entry's own scene started like an episode ([`world`]), and its evaluator reset there.
#[allow(dead_code)] // not every test binary starts an entry
pub fn start(entry: &str) -> (String, ComposedScene, Simulation, Box<dyn Evaluator>) {
    let pool = Pool::discover().expect("tasks/pool.json loads and validates");
    let reference = pool.get(entry).unwrap().reference();
    let WorldPhysics { scene, sim, evaluator, .. } = world(entry);
    (reference, scene, sim, evaluator)
}

/// A record's (success, completed stages, K), the triple the stage tests compare.
#[allow(dead_code)] // not every test binary compares stage counts
pub fn stages(r: &EvaluationRecord) -> (bool, usize, usize) {
    (r.success, r.completed_required_stage_count, r.required_stage_count)
}

/// An entry's evaluator on an idle robot (zero actions) for `steps` control steps from its start.
#[allow(dead_code)] // not every test binary judges an idle start
pub fn idle(entry: &str, steps: u64) -> EvaluationRecord {
    let (_, _, mut sim, mut evaluator) = start(entry);
    for k in 1..=steps {
        sim.step([0.0; 7]).unwrap();
        evaluator.observe_control_step(sim.data(), Tick::at_control_step(k, 0.05 * k as f64));
    }
    evaluator.finish(sim.data(), Tick::at_control_step(steps, 0.05 * steps as f64))
}

/// Runs `behaviour` of an entry's expert on its own scene under its evaluator, stepped as an episode steps it
/// (`WorldPhysics::step`: the evaluator observes every physics substep where it samples them).
#[allow(dead_code)] // not every test binary plays an expert
pub fn play(entry: &str, behaviour: &str) -> EvaluationRecord {
    let pool = Pool::discover().expect("tasks/pool.json loads and validates");
    let reference = pool.get(entry).unwrap().reference();
    let mut world = world(entry);
    let mut script = libero_tasks::expert_for(&reference, behaviour, &world.scene, world.model()).unwrap();
    while let Some(action) = script.act(&world.sim) {
        world.step(&as_sent(action)).unwrap();
        assert!(world.control_step < 6_000, "{entry} {behaviour}: the script ends");
    }
    world.evaluate()
}

/// Plays an entry's `solve` and asserts it completes every stage with its first commitment judged right; then plays
/// each of its expert's near misses (there is at least one) and returns their records, `(behaviour, record)`.
#[allow(dead_code)] // not every test binary plays every behaviour
pub fn solved_with_near_misses(entry: &str) -> Vec<(&'static str, EvaluationRecord)> {
    let pool = Pool::discover().expect("tasks/pool.json loads and validates");
    let reference = pool.get(entry).unwrap().reference();
    let solve = play(entry, libero_tasks::expert::SOLVE);
    assert!(solve.success && solve.completed_required_stage_count == solve.required_stage_count, "{entry}: {solve:?}");
    assert_eq!(solve.judgment_correct, Some(true), "{entry}: {solve:?}");
    let misses = libero_tasks::expert_behaviours(&reference).unwrap_or_default();
    assert!(!misses.is_empty(), "{entry} has near misses");
    misses.iter().map(|&b| (b, play(entry, b))).collect()
}
