//! The LIBERO world judges a release task with its evaluator: T16 (stock "open the microwave", `bddl_terminal`)
//! is not solved at the settled start, and is solved once the door hinge is past LIBERO's −1.3 rad threshold.
use libero_episode::World;
use libero_episode::task::resolve_task;
use libero_episode::world::{LiberoWorld, WorldSpec};
use libero_episode::{Level, MicroAction};
use libero_render::Renderer;
use libero_sim::AssetPaths;
use libero_sim::mujoco_rs::prelude::MjtObjBase;

#[test]
fn microwave_verdict_is_false_at_start_and_true_after_the_door_is_opened_past_the_threshold() {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let spec = WorldSpec { task: resolve_task("T16", &paths).unwrap(), level: Level::L1, seed: 100, init_index: 0, paths };
    let mut world = LiberoWorld::new(&spec, Renderer::new().expect("renderer")).unwrap();
    world.start().unwrap();
    let start = world.verdict().unwrap();
    assert!(!start.success);
    let ev = &start.private_evaluation;
    assert_eq!((ev["checker"].as_str(), ev["task_id"].as_str()), (Some("bddl_terminal"), Some("T16")));
    assert_eq!(ev["bddl_goal"]["predicates"][0]["predicate"], "(open microwave_1)");
    assert_eq!(ev["bddl_goal"]["predicates"][0]["value"], false);
    assert_eq!((ev["required_stage_count"].as_u64(), ev["completed_required_stage_count"].as_u64()), (Some(1), Some(0)));
    assert_eq!(ev["failure_reason"], "terminal_state_invalid");
    assert!(start.stage_events.is_empty());

    let model = world.simulation().model().clone();
    let door = model.name_to_id(MjtObjBase::mjOBJ_JOINT, "microwave_1_microjoint").expect("door joint");
    let adr = 1 + model.jnt_qposadr()[door] as usize;
    world.edit_current_state(|row| row[adr] = -1.35).unwrap();
    let hold: MicroAction = [0.0; 7];
    world.step(&hold).unwrap();
    let opened = world.verdict().unwrap();
    assert!(opened.success, "{}", opened.private_evaluation);
    let ev = &opened.private_evaluation;
    assert_eq!(ev["bddl_goal"]["predicates"][0]["value"], true);
    assert_eq!(ev["stage_score_percent"], 100.0);
    assert_eq!(ev["control_steps_observed"], 1);
    assert_eq!(ev["first_commitment"]["kind"], "fixture_articulated");
    assert_eq!(ev["first_commitment"]["subject"], "microwave_1");
    assert_eq!(opened.stage_events.len(), 1);
    assert_eq!(opened.stage_events[0]["stage_name"], "01_BDDL_Goal_At_Finish");
}

/// The pruned repository tasks start from the seeded placement (no trusted state) and are unsolved after settling.
#[test]
fn pruned_release_tasks_start_from_the_seeded_placement_unsolved() {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let renderer = Renderer::new().expect("renderer");
    for (id, atom) in [("T11", "(in alphabet_soup_1 basket_1_contain_region)"), ("T12", "(on plate_1 main_table_stove_front_region)")] {
        let task = resolve_task(id, &paths).unwrap();
        assert!(task.init_states.is_none(), "{id}");
        let spec = WorldSpec { task, level: Level::L1, seed: 100, init_index: 0, paths: paths.clone() };
        let mut world = LiberoWorld::new(&spec, renderer.clone()).unwrap();
        world.start().unwrap();
        let v = world.verdict().unwrap();
        assert!(!v.success, "{id}: {}", v.private_evaluation);
        assert_eq!(v.private_evaluation["bddl_goal"]["predicates"][0]["predicate"], atom, "{id}");
        assert_eq!(v.private_evaluation["task_id"], id);
    }
}

/// LIBERO shows the stove's red burner ring after every step in which the knob is on (its `_post_process`), and
/// the image of a step still shows the state before that step's toggle.
#[test]
fn the_burner_ring_appears_one_step_after_the_stove_is_turned_on() {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let spec = WorldSpec { task: resolve_task("T17", &paths).unwrap(), level: Level::L1, seed: 100, init_index: 0, paths };
    let mut world = LiberoWorld::new(&spec, Renderer::new().expect("renderer")).unwrap();
    world.start().unwrap();
    assert!(!world.burner_shown(), "the stove starts off");
    let model = world.simulation().model().clone();
    let knob = model.name_to_id(MjtObjBase::mjOBJ_JOINT, "flat_stove_1_button").expect("knob joint");
    let adr = 1 + model.jnt_qposadr()[knob] as usize;
    world.edit_current_state(|row| row[adr] = 1.0).unwrap();
    let hold: MicroAction = [0.0; 7];
    world.step(&hold).unwrap();
    assert!(!world.burner_shown(), "the image of the step that found the knob on predates the toggle");
    world.step(&hold).unwrap();
    assert!(world.burner_shown(), "one step later the ring is visible");
    world.edit_current_state(|row| row[adr] = 0.0).unwrap();
    world.step(&hold).unwrap();
    world.step(&hold).unwrap();
    assert!(!world.burner_shown(), "turned off, the ring disappears again");
}
