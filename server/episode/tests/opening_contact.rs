//! Figure 3's sustained-contact ratio is recorded for every opening operation, not only for stages that name a
//! contact body, and counts gripper contact with the mechanism's **handle** only (`tasks/mechanism_handles.json`):
//!
//! * the scripted expert opens the microwave of T16 (a single-goal BDDL task, watched by the generic goal-opening
//!   monitor) and of T21 (an unordered cooking goal), played through the episode's own evaluation path
//!   (`WorldPhysics`, as `libero-agent expert --trace` runs it), and each record carries the operation: its
//!   direction, the door's moving body and handle geoms, its control steps from the first gripper contact, its contact
//!   runs (anywhere on the door, and on its handle) and SCR, and the stage diagnostic it belongs to;
//! * in the real scenes of T15 (a drawer) and T16 (a microwave door), the closed hand pressed on the drawer's front or
//!   the door's panel, off the handle, touches the mechanism but records no handle contact and SCR 0; the same press on
//!   the handle bar records handle contact runs and a positive SCR.
use libero_episode::Level;
use libero_episode::expert_run::run_replica_only;
use libero_episode::physics::{WorldPhysics, WorldSpec};
use libero_episode::task::resolve_task;
use libero_sim::mujoco_rs::prelude::MjtObjBase;
use libero_sim::{AssetPaths, Simulation};
use libero_tasks::expert::motion::{
    GRIPPER_CLOSED, Goal, Phase, PhaseCtx, Script, body_dir, body_point, open_along, rotate_world, rotation_error,
};
use nalgebra::Vector3;
use serde_json::Value;

fn spec(task: &str) -> WorldSpec {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    WorldSpec { task: resolve_task(task, &paths).unwrap(), level: Level::L1, seed: 100, init_index: 0, paths }
}

fn u64s(v: &Value) -> Vec<u64> {
    v.as_array().unwrap_or_else(|| panic!("not an array: {v}")).iter().filter_map(Value::as_u64).collect()
}

/// The expert's `solve` on `task`'s release start, judged as an episode is.
fn solve(task: &str) -> Value {
    let record = run_replica_only(&spec(task), task, "solve", 6_000, |_, _| {}).unwrap();
    assert_eq!(record["success"], true, "{task}: {record}");
    record
}

/// The one opening operation of `record` on stage `stage`, checked to be a completed microwave opening held for a
/// while by the expert.
fn microwave_opening<'a>(task: &str, record: &'a Value, stage: &str) -> &'a Value {
    let ops = record["details"]["opening_operations"].as_array().unwrap_or_else(|| panic!("{task}: no operations: {record}"));
    let op = ops.iter().find(|o| o["stage_name"] == stage).unwrap_or_else(|| panic!("{task}: no operation on {stage}: {ops:?}"));
    eprintln!("{task}: {op}");
    assert_eq!((op["operation"].as_str(), op["window"].as_str(), op["completed"].as_bool()), (Some("open"), Some("first_contact"), Some(true)), "{task}");
    let bodies: Vec<&str> = op["mechanism_bodies"].as_array().unwrap().iter().filter_map(Value::as_str).collect();
    assert!(!bodies.is_empty() && bodies.iter().all(|b| b.starts_with("microwave_1")), "{task}: the door's body: {bodies:?}");
    assert_eq!(op["handle_geoms"], serde_json::json!(["microwave_1_g14", "microwave_1_g15", "microwave_1_g16"]), "{task}");
    let (runs, handle) = (u64s(&op["contact_runs"]), u64s(&op["handle_contact_runs"]));
    let exec = op["exec_steps"].as_u64().unwrap();
    let sustained: u64 = handle.iter().filter(|&&r| r >= 5).sum();
    assert!(exec > 0 && runs.iter().sum::<u64>() <= exec, "{task}: {op}");
    assert!(handle.iter().sum::<u64>() <= runs.iter().sum::<u64>(), "{task}: handle contact is contact with the door: {op}");
    assert_eq!(op["sustained_steps"].as_u64(), Some(sustained), "{task}");
    let scr = op["sustained_contact_ratio_percent"].as_f64().unwrap();
    assert!((scr - 100.0 * sustained as f64 / exec as f64).abs() < 1e-9, "{task}: SCR = N_sustained / N_exec");
    assert!(scr > 0.0, "{task}: the expert holds the door for at least 5 steps: {op}");
    op
}

#[test]
fn the_experts_microwave_openings_record_their_sustained_contact_ratio() {
    // T16: `bddl_terminal`, one stage; the goal's `(open microwave_1)` is the operation of that stage.
    let t16 = solve("T16");
    let op = microwave_opening("T16", &t16, "01_BDDL_Goal_At_Finish");
    assert_eq!(op["goal"], "(open microwave_1)");
    let d = &t16["stage_diagnostics"][0];
    assert_eq!((d["operation"].as_str(), d["sustained_contact_ratio_percent"].as_f64()), (Some("open"), op["sustained_contact_ratio_percent"].as_f64()));

    // T21: the unordered cooking goals; the microwave goal is one of five, all available from the start.
    let t21 = solve("T21");
    let op = microwave_opening("T21", &t21, "Microwave_Open");
    let ops = t21["details"]["opening_operations"].as_array().unwrap();
    assert_eq!(ops.len(), 1, "only the microwave opens a mechanism; the stoves turn on: {ops:?}");
    let d = t21["stage_diagnostics"].as_array().unwrap().iter().find(|d| d["stage_name"] == "Microwave_Open").unwrap();
    assert_eq!((d["type"].as_str(), d["operation"].as_str()), (Some("mechanism_interaction"), Some("open")));
    assert_eq!(d["contact_exec_steps"], op["exec_steps"]);
    let pot = t21["stage_diagnostics"].as_array().unwrap().iter().find(|d| d["stage_name"] == "Moka_Pot_On_Second_Stove").unwrap();
    assert_eq!((pot["type"].as_str(), pot.get("operation")), (Some("object_manipulation"), None));
}

/// The closed hand, pointing into the face (pointing down, the hand above the fingertips meets the board over a drawer
/// first), brought in front of `body`'s point `local_m` from its outward side (the body's
/// local −y), pressed 2 cm past it for 40 control steps, then backed off: in `task`'s episode world, judged as an
/// episode is. Returns the record's one opening operation.
fn press(task: &str, body: &str, local_m: [f64; 3]) -> Value {
    let mut world = WorldPhysics::build(&spec(task), |_, _, _| Ok(())).unwrap();
    world.start(|_| {}).unwrap();
    let b = world.model().name_to_id(MjtObjBase::mjOBJ_BODY, body).unwrap_or_else(|| panic!("{task}: no body {body}"));
    let at = move |sim: &Simulation, out_m: f64| body_point(sim, b, local_m) + body_dir(sim, b, [0.0, -1.0, 0.0]) * out_m;
    // fingers along the push, then tipped a quarter about the horizontal across it, so the hand points into the face
    // and only the closed fingertips meet it (as the T15 expert holds it), and turned a quarter about the push so that
    // the long hand lies along the face, clear of the fixture below it
    let rot = move |sim: &Simulation, ctx: &PhaseCtx| {
        let out = body_dir(sim, b, [0.0, -1.0, 0.0]);
        let into = rotate_world(&open_along(&ctx.home_rot, out), Vector3::z().cross(&out), std::f64::consts::FRAC_PI_2);
        rotate_world(&into, out, std::f64::consts::FRAC_PI_2)
    };
    let goal = move |sim: &Simulation, ctx: &PhaseCtx, out_m: f64, up_m: f64| {
        Goal::at(at(sim, out_m) + Vector3::z() * up_m, GRIPPER_CLOSED).rotated(rot(sim, ctx))
    };
    let mut script = Script::new(vec![
        Phase::new("turn", move |sim, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(rot(sim, ctx)))
            .until(move |sim, ctx| rotation_error(sim, &rot(sim, ctx)) < 0.05)
            .max_steps(100),
        Phase::new("above_in_front", move |sim, ctx| goal(sim, ctx, 0.12, 0.12)).until_reached(0.01).max_steps(200),
        Phase::new("in_front", move |sim, ctx| goal(sim, ctx, 0.10, 0.0).slow(0.5)).until_reached(0.008).max_steps(100),
        Phase::new("onto_face", move |sim, ctx| goal(sim, ctx, 0.0, 0.0).slow(0.3)).until_reached(0.003).max_steps(60),
        Phase::new("press", move |sim, ctx| goal(sim, ctx, -0.02, 0.0).slow(0.2)).for_steps(40),
        Phase::new("back_off", move |sim, ctx| goal(sim, ctx, 0.10, 0.0)).until_reached(0.02).max_steps(60),
    ]);
    while let Some(a) = script.act(&world.sim) {
        world.step(&a).unwrap();
    }
    let record = serde_json::to_value(world.evaluate()).unwrap();
    let ops = record["details"]["opening_operations"].as_array().unwrap_or_else(|| panic!("{task}: no operations: {record}"));
    assert_eq!(ops.len(), 1, "{task}: {ops:?}");
    eprintln!("{task} pressed on {body} {local_m:?}: {} ({:?})", ops[0], script.log);
    ops[0].clone()
}

/// A press's operation touched the mechanism for a sustained while (a contact run of ≥ 5 steps) without opening it.
fn touched_for_a_while(task: &str, op: &Value) -> Vec<u64> {
    let runs = u64s(&op["contact_runs"]);
    assert!(runs.iter().any(|&r| r >= 5), "{task}: the press touches the mechanism: {op}");
    assert_eq!(op["completed"], false, "{task}: a press does not open it: {op}");
    u64s(&op["handle_contact_runs"])
}

#[test]
fn pressing_a_door_or_a_drawer_off_its_handle_counts_no_handle_contact_and_on_it_does() {
    // T15's top drawer: its front (the drawer's local −y face, 7.8 cm in front of the box's centre) 8 cm to the side of
    // the handle bar's centre, which spans ±4.4 cm; then the bar itself (standing 2.4 cm proud of the front).
    let drawer = "wooden_cabinet_1_cabinet_top";
    let front = press("T15", drawer, [0.08, -0.078, 0.184]);
    assert_eq!(front["handle_geoms"], serde_json::json!(["wooden_cabinet_1_g18", "wooden_cabinet_1_g19", "wooden_cabinet_1_g20"]));
    assert_eq!(touched_for_a_while("T15", &front), Vec::<u64>::new(), "the drawer's front is not its handle: {front}");
    assert_eq!((front["sustained_steps"].as_u64(), front["sustained_contact_ratio_percent"].as_f64()), (Some(0), Some(0.0)));
    let bar = press("T15", drawer, [-0.003, -0.1093, 0.184]);
    let handle = touched_for_a_while("T15", &bar);
    assert!(handle.iter().any(|&r| r >= 5), "pressing the bar is a sustained handle contact: {bar}");
    assert!(bar["sustained_contact_ratio_percent"].as_f64().unwrap() > 0.0);

    // T16's microwave door: its panel (the door's local −y face) 15.75 cm from the handle bar, then the bar.
    let door = "microwave_1_microdoorroot";
    let panel = press("T16", door, [0.08, -0.025, -0.03]);
    assert_eq!(touched_for_a_while("T16", &panel), Vec::<u64>::new(), "the door's panel is not its handle: {panel}");
    assert_eq!(panel["sustained_contact_ratio_percent"].as_f64(), Some(0.0));
    let bar = press("T16", door, [0.2375, -0.064, -0.03]);
    let handle = touched_for_a_while("T16", &bar);
    assert!(handle.iter().any(|&r| r >= 5), "pressing the bar is a sustained handle contact: {bar}");
    assert!(bar["sustained_contact_ratio_percent"].as_f64().unwrap() > 0.0);
}
