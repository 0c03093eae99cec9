//! The `bddl_terminal` evaluator on a real composed scene (LIBERO-90 KITCHEN_SCENE7 "open the microwave", stock
//! init state 0): terminal success from the goal only, per-predicate values, first commitment.
use std::sync::Arc;

use libero_sim::compose::compose_file;
use libero_sim::mujoco_rs::prelude::MjtObjBase;
use libero_sim::placement::Placement;
use libero_sim::{AssetPaths, InitStates, Simulation};
use libero_tasks::families::libero::bddl_terminal::BddlTerminal;
use libero_tasks::judge::commitment::{CommitmentKind, CommitmentTracker};
use libero_tasks::judge::evaluator::EventKind;
use libero_tasks::{Evaluator, GoalChecker, Tick};

fn microwave_scene() -> (Simulation, BddlTerminal, usize, usize) {
    let paths = AssetPaths::discover().expect("assets");
    let (suite, task) = ("libero_90", "KITCHEN_SCENE7_open_the_microwave");
    let scene = compose_file(&paths.stock_bddl(suite, task), &paths).unwrap();
    let mut model = scene.compile().unwrap();
    Placement::sample(&scene, 0, Some(&model)).unwrap().apply(&mut model).unwrap();
    let model = Arc::new(model);
    let mut sim = Simulation::new(model.clone()).unwrap();
    let init = InitStates::read(&paths.stock_init(suite, task)).unwrap();
    sim.set_init_state(init.get(0).unwrap()).unwrap();
    let goal = GoalChecker::for_scene(&scene, &model).unwrap();
    let commitment = CommitmentTracker::new(goal.index(), &model).unwrap();
    let door = model.jnt_qposadr()[model.name_to_id(MjtObjBase::mjOBJ_JOINT, "microwave_1_microjoint").unwrap()] as usize;
    let bowl_joint = model.name_to_id(MjtObjBase::mjOBJ_BODY, "white_bowl_1_main").unwrap();
    let bowl = model.jnt_qposadr()[model.body_jntadr()[bowl_joint] as usize] as usize;
    (sim, BddlTerminal::new("bddl_terminal", goal, commitment, Some("T16".into())), door, bowl)
}

fn edit_qpos(sim: &mut Simulation, adr: usize, value: f64) {
    let mut row = sim.state_row();
    row[1 + adr] = value;
    sim.set_init_state(&row).unwrap();
}

#[test]
fn terminal_success_follows_only_the_final_state() {
    let (mut sim, mut ev, door, _) = microwave_scene();
    ev.reset(sim.data(), Tick::at_control_step(0, sim.time_s()));
    edit_qpos(&mut sim, door, -1.5);
    ev.observe_control_step(sim.data(), Tick::at_control_step(1, sim.time_s()));
    edit_qpos(&mut sim, door, -0.2);
    ev.observe_control_step(sim.data(), Tick::at_control_step(2, sim.time_s()));
    let r = ev.finish(sim.data(), Tick::at_control_step(2, sim.time_s()));
    assert!(!r.success, "an opened-then-closed door does not count: nothing is latched");
    assert_eq!((r.required_stage_count, r.completed_required_stage_count, r.stage_score_percent), (1, 0, 0.0));
    let kinds: Vec<_> = r.events.iter().map(|e| e.kind).collect();
    assert_eq!(kinds, [EventKind::GoalSatisfied, EventKind::FirstCommitment, EventKind::GoalUnsatisfied]);
    let c = r.first_commitment.as_ref().expect("the door moved 1.5 rad");
    assert_eq!((c.kind, c.subject.as_str(), c.tick.control_step), (CommitmentKind::FixtureArticulated, "microwave_1", 1));

    edit_qpos(&mut sim, door, -1.31);
    let r = ev.finish(sim.data(), Tick::at_control_step(3, sim.time_s()));
    assert!(r.success && r.terminal_state_success);
    assert_eq!(r.completed_required_stage_count, 1);
    assert_eq!(r.terminal_state_checks.len(), 1);
    assert_eq!(r.terminal_state_checks[0].name, "(open microwave_1)");
    assert_eq!(r.failure_reason, None);
    let json = serde_json::to_value(&r).unwrap();
    assert_eq!(json["bddl_goal"]["predicates"][0]["value"], true);
    assert_eq!(json["stage_events"][0]["stage_name"], "01_BDDL_Goal_At_Finish");
}

#[test]
fn lifting_an_object_without_a_grasp_is_not_a_commitment() {
    let (mut sim, mut ev, _, bowl) = microwave_scene();
    ev.reset(sim.data(), Tick::at_control_step(0, sim.time_s()));
    let z = sim.data().qpos()[bowl + 2];
    edit_qpos(&mut sim, bowl + 2, z + 0.10);
    ev.observe_control_step(sim.data(), Tick::at_control_step(1, sim.time_s()));
    let r = ev.finish(sim.data(), Tick::at_control_step(1, sim.time_s()));
    assert_eq!(r.first_commitment, None, "raised 10 cm but not between the finger pads");
}

/// LIBERO-Object "alphabet soup" with the can put between the finger pads, fingers squeezed onto it.
#[test]
fn a_can_between_both_finger_pads_and_raised_4_cm_is_the_first_commitment() {
    let paths = AssetPaths::discover().expect("assets");
    let (suite, task) = ("libero_object", "pick_up_the_alphabet_soup_and_place_it_in_the_basket");
    let scene = compose_file(&paths.stock_bddl(suite, task), &paths).unwrap();
    let mut model = scene.compile().unwrap();
    Placement::sample(&scene, 0, Some(&model)).unwrap().apply(&mut model).unwrap();
    let model = Arc::new(model);
    let mut sim = Simulation::new(model.clone()).unwrap();
    sim.set_init_state(InitStates::read(&paths.stock_init(suite, task)).unwrap().get(0).unwrap()).unwrap();
    let goal = GoalChecker::for_scene(&scene, &model).unwrap();
    let mut tracker = CommitmentTracker::new(goal.index(), &model).unwrap();
    tracker.reset(goal.index(), sim.data());
    let soup = goal.index().instance("alphabet_soup_1").unwrap();
    let body = model.name_to_id(MjtObjBase::mjOBJ_BODY, "alphabet_soup_1_main").unwrap();
    let soup_qpos = model.jnt_qposadr()[model.body_jntadr()[body] as usize] as usize;
    let grip = model.name_to_id(MjtObjBase::mjOBJ_SITE, "gripper0_grip_site").unwrap();
    let grip_pos = sim.data().site_xpos()[grip];
    let fingers = sim.ids().finger_qpos_adr;
    let mut row = sim.state_row();
    // the can's origin at the grip site (≈ 1 m above the floor it stood on), fingers closed onto it
    row[1 + soup_qpos..1 + soup_qpos + 3].copy_from_slice(&grip_pos);
    row[1 + fingers[0]] = 0.01;
    row[1 + fingers[1]] = -0.01;
    sim.set_init_state(&row).unwrap();
    assert!(tracker.grasped(goal.index(), sim.data(), soup), "both pads touch the can");
    let c = tracker.observe(goal.index(), sim.data(), Tick::at_control_step(1, sim.time_s())).cloned().expect("commitment");
    assert_eq!((c.kind, c.subject.as_str()), (CommitmentKind::ObjectGraspedAndLifted, "alphabet_soup_1"));
    assert!(c.magnitude >= 0.04);
    // only the first counts
    assert!(tracker.observe(goal.index(), sim.data(), Tick::at_control_step(2, sim.time_s())).is_none());
    // opened fingers: no grasp any more
    row[1 + fingers[0]] = 0.04;
    row[1 + fingers[1]] = -0.04;
    sim.set_init_state(&row).unwrap();
    assert!(!tracker.grasped(goal.index(), sim.data(), soup), "fingers wide open around a 7 cm can");
}
