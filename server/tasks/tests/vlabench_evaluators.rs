//! `private_tube_insertion` (T18) and `private_button_press` (T13) on constructed states of their real scenes:
//! the tube put into the slot by editing qpos (upright, tilted, beside, moving, hovering), the button pressed by the
//! gripper (the T13 expert script, played on a bare simulation) and by an object resting on the cap.
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjtObjBase;
use libero_sim::Simulation;
use libero_tasks::families::vlabench::button_press::{ButtonPress, ButtonPressParams, PRESSED_CAP_RGBA};
use libero_tasks::judge::commitment::CommitmentKind;
use libero_tasks::families::vlabench::tube_insertion::{TubeInsertion, TubeInsertionParams};
use libero_tasks::{Catalog, Evaluator, Tick, expert};

mod common;
use common::scene_and_sim;

fn task_bddl(id: &str) -> (std::path::PathBuf, serde_json::Value) {
    let catalog = Catalog::discover().unwrap();
    let t = catalog.get(id).unwrap();
    (catalog.dir.join(&t.bddl.path), t.checker.params.clone())
}

fn tick(sim: &Simulation, step: u64) -> Tick {
    Tick::at_control_step(step, sim.time_s())
}

// ---------------------------------------------------------------- T18

struct Tube {
    sim: Simulation,
    ev: TubeInsertion,
    /// qpos address of the tube's free joint.
    adr: usize,
    slot: [f64; 3],
    rack: [f64; 3],
}

fn tube_scene() -> Tube {
    let (bddl, params) = task_bddl("T18");
    let (scene, sim) = scene_and_sim(&bddl);
    let params: TubeInsertionParams = serde_json::from_value(params).unwrap();
    let model = sim.model().clone();
    let ev = TubeInsertion::new(params, &scene, &model, Some("T18".into())).unwrap();
    let joint = model.name_to_id(MjtObjBase::mjOBJ_JOINT, "blue_tube_1_joint0").unwrap();
    let adr = model.jnt_qposadr()[joint] as usize;
    let site = model.name_to_id(MjtObjBase::mjOBJ_SITE, "tube_stand_1_rear_center_slot").unwrap();
    let rack = model.name_to_id(MjtObjBase::mjOBJ_BODY, "tube_stand_1_main").unwrap();
    let (slot, rack) = (sim.data().site_xpos()[site], sim.data().xpos()[rack]);
    Tube { sim, ev, adr, slot, rack }
}

impl Tube {
    /// Puts the tube's root (its bottom centre) at `pos` with orientation `quat` (w, x, y, z) and linear velocity
    /// `vel`, then judges.
    fn judge(&mut self, pos: [f64; 3], quat: [f64; 4], vel: [f64; 3]) -> libero_tasks::EvaluationRecord {
        let nq = self.sim.model().ffi().nq as usize;
        let mut row = self.sim.state_row();
        row[1 + self.adr..1 + self.adr + 3].copy_from_slice(&pos);
        row[1 + self.adr + 3..1 + self.adr + 7].copy_from_slice(&quat);
        let dof = self.sim.model().jnt_dofadr()[self.sim.model().name_to_id(MjtObjBase::mjOBJ_JOINT, "blue_tube_1_joint0").unwrap()]
            as usize;
        row[1 + nq + dof..1 + nq + dof + 3].copy_from_slice(&vel);
        self.sim.set_init_state(&row).unwrap();
        self.ev.reset(self.sim.data(), tick(&self.sim, 0));
        self.ev.finish(self.sim.data(), tick(&self.sim, 0))
    }

    /// Standing in the rear-centre hole, its bottom 0.5 mm into the base plate.
    fn seated(&self) -> [f64; 3] {
        [self.slot[0], self.slot[1], self.rack[2] + 0.048 - 0.0005]
    }
}

fn failed(r: &libero_tasks::EvaluationRecord) -> Vec<&str> {
    r.terminal_state_checks.iter().filter(|c| !c.passed).map(|c| c.name.as_str()).collect()
}

const UPRIGHT: [f64; 4] = [1.0, 0.0, 0.0, 0.0];

#[test]
fn a_tube_standing_upright_in_the_rear_centre_hole_passes_all_five_checks() {
    let mut t = tube_scene();
    let r = t.judge(t.seated(), UPRIGHT, [0.0; 3]);
    assert!(r.success, "{:?}", r.terminal_state_checks);
    let names: Vec<_> = r.terminal_state_checks.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["lateral_error", "insertion_depth", "verticality", "stability", "tube_rack_contact"]);
    assert_eq!((r.required_stage_count, r.completed_required_stage_count), (1, 1));
    assert_eq!(r.bddl_final_goal_success, Some(true), "the tube's origin is inside the slot box");
    let d = &r.details.as_ref().unwrap()["final"];
    assert!((d["insertion_depth_m"].as_f64().unwrap() - 0.0475).abs() < 1e-6, "{d}");
}

#[test]
fn tilted_beside_moving_or_hovering_tubes_fail_exactly_the_matching_check() {
    let mut t = tube_scene();
    // 25° about world x, bottom still on the base plate of the target hole
    let half = 25f64.to_radians() / 2.0;
    let r = t.judge(t.seated(), [half.cos(), half.sin(), 0.0, 0.0], [0.0; 3]);
    assert!(!r.success);
    assert!(failed(&r).contains(&"verticality"), "{:?}", r.terminal_state_checks);
    // 10° is inside the 14° tolerance (|a·z| = cos 10° = 0.985)
    let half = 10f64.to_radians() / 2.0;
    let r = t.judge(t.seated(), [half.cos(), half.sin(), 0.0, 0.0], [0.0; 3]);
    assert!(!failed(&r).contains(&"verticality"), "{:?}", r.terminal_state_checks);

    // the neighbouring hole of the rear row: 5.5 cm along world x after the rack's π/2 yaw
    let mut beside = t.seated();
    beside[0] += 0.055;
    let r = t.judge(beside, UPRIGHT, [0.0; 3]);
    assert_eq!(failed(&r), ["lateral_error"], "{:?}", r.terminal_state_checks);
    assert_eq!(r.bddl_final_goal_success, Some(false));

    let r = t.judge(t.seated(), UPRIGHT, [0.0, 0.0, 0.2]);
    assert_eq!(failed(&r), ["stability"], "0.2 m/s upward is above 0.08 m/s");

    // held upright above the base plate: depth 0.07 is inside the window but nothing touches the rack
    let mut hovering = t.seated();
    hovering[2] = t.rack[2] + 0.07;
    let r = t.judge(hovering, UPRIGHT, [0.0; 3]);
    assert_eq!(failed(&r), ["tube_rack_contact"], "{:?}", r.terminal_state_checks);
    hovering[2] = t.rack[2] + 0.09;
    let r = t.judge(hovering, UPRIGHT, [0.0; 3]);
    assert!(failed(&r).contains(&"insertion_depth"));
}

// ---------------------------------------------------------------- T13

fn button_eval(scene: &ComposedScene, sim: &Simulation) -> ButtonPress {
    let (_, params) = task_bddl("T13");
    let params: ButtonPressParams = serde_json::from_value(params).unwrap();
    ButtonPress::new(params, scene, sim.model(), Some("T13".into())).unwrap()
}

/// Steps `sim` with `action`, the evaluator sampling every substep and the control step.
fn step(sim: &mut Simulation, ev: &mut ButtonPress, n: &mut u64, action: [f64; 7]) {
    *n += 1;
    let step = *n;
    sim.step_with(action, |k, data| ev.observe_substep(data, Tick { control_step: step, substep: Some(k as u32), sim_time_s: data.ffi().time }))
        .unwrap();
    ev.observe_control_step(sim.data(), tick(sim, step));
}

#[test]
fn the_gripper_pressing_the_cap_for_1_5_s_is_a_press_and_the_first_commitment() {
    let (bddl, _) = task_bddl("T13");
    let (scene, mut sim) = scene_and_sim(&bddl);
    let mut ev = button_eval(&scene, &sim);
    let mut script = libero_tasks::expert_for("T13", expert::SOLVE, &scene, sim.model()).unwrap();
    ev.reset(sim.data(), tick(&sim, 0));
    assert!(ev.geom_rgba_overrides().is_empty(), "nothing touches the cap at the start");
    let (mut n, mut green_seen) = (0, false);
    while let Some(a) = script.act(&sim) {
        step(&mut sim, &mut ev, &mut n, a);
        green_seen |= ev.geom_rgba_overrides().iter().any(|(_, rgba)| *rgba == PRESSED_CAP_RGBA);
        assert!(n < 400, "the script ends");
    }
    assert!(green_seen, "the cap turns green while pressed");
    assert!(ev.geom_rgba_overrides().is_empty(), "and back once the gripper has left");
    let r = ev.finish(sim.data(), tick(&sim, n));
    assert!(r.success);
    assert_eq!(r.substeps_observed, 25 * n);
    let c = r.first_commitment.as_ref().unwrap();
    assert_eq!((c.kind, c.subject.as_str()), (CommitmentKind::ButtonPressed, "button_1"));
    let h = &r.details.as_ref().unwrap()["buttons"][0];
    assert_eq!(h["touch_observed_private"], true);
    assert!(h["max_pressed_streak_private"].as_u64().unwrap() >= 11 * 26, "{h}");
}

#[test]
fn an_object_resting_on_the_cap_touches_it_but_is_no_press() {
    // the T13 scene plus a LIBERO butter pack, dropped onto the cap
    let (bddl, _) = task_bddl("T13");
    let text = std::fs::read_to_string(&bddl).unwrap().replace("(:objects\n  )", "(:objects\n    butter_1 - butter\n  )");
    let dir = tempfile_dir();
    let file = dir.join("press_button_with_butter.bddl");
    std::fs::write(&file, text).unwrap();
    let (scene, mut sim) = scene_and_sim(&file);
    let model = sim.model().clone();
    let butter = model.jnt_qposadr()[model.name_to_id(MjtObjBase::mjOBJ_JOINT, "butter_1_joint0").unwrap()] as usize;
    let cap = model.name_to_id(MjtObjBase::mjOBJ_GEOM, "button_1_button_cap").unwrap();
    let mut row = sim.state_row();
    let cap_pos = sim.data().geom_xpos()[cap];
    row[1 + butter..1 + butter + 3].copy_from_slice(&[cap_pos[0], cap_pos[1], cap_pos[2] + 0.04]);
    sim.set_init_state(&row).unwrap();
    let mut ev = button_eval(&scene, &sim);
    ev.reset(sim.data(), tick(&sim, 0));
    let mut n = 0;
    for _ in 0..40 {
        step(&mut sim, &mut ev, &mut n, [0.0; 7]);
    }
    assert!(!ev.geom_rgba_overrides().is_empty(), "the butter's weight reads on the touch sensor");
    let r = ev.finish(sim.data(), tick(&sim, n));
    assert!(!r.success);
    let h = &r.details.as_ref().unwrap()["buttons"][0];
    assert_eq!((h["touch_observed_private"].as_bool(), h["pressed_steps_private"].as_u64()), (Some(true), Some(0)), "{h}");
    assert_eq!(r.first_commitment, None);
}

fn tempfile_dir() -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("libero-tasks-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}
