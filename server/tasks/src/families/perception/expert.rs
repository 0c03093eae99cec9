//! Experts for the perception suite (T01–T10). Each knows the private target (read from the scene, as every expert
//! reads privileged state) and has a `wrong_target` behaviour that does the same thing to a distractor: it must fail,
//! and its first commitment must be judged wrong (`judgment_correct == false`).
//!
//! Button family (T06, T09, T10, and the pool's seven `vlabench_button` questions on their own definitions): press
//! and hold the paired button's cap (the T13 press); `wrong_target` presses another button the same way.
//!
//! Bin family (T01, T03, T04, T05, T07, T02 with LIBERO's basket, and the pool's `vlabench_world_knowledge`
//! selections on definitions of their own): grasp the candidate from above, lift it clear of the bin walls, carry it
//! over the bin, lower it inside, let go, retreat.
use std::sync::{Arc, Mutex};

use libero_sim::Simulation;
use nalgebra::Vector3;

use crate::expert::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, PhaseCtx, Script, grip_pose, rotate_world, vec3};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};
use crate::TasksError;

/// The behaviour that commits to a distractor instead of the target.
pub const WRONG_TARGET: &str = "wrong_target";

/// One bin-family task: target and the distractor `wrong_target` takes, and where on each the fingers close
/// (height of the grip site above the candidate's root-body origin). The hand's lowest part is ≈ 5 cm above the grip
/// site, so on tall candidates the grip is taken ≈ 4.5 cm below the top of their collision geometry.
struct BinTask {
    target: &'static str,
    distractor: &'static str,
    target_grip_m: f64,
    distractor_grip_m: f64,
    /// Hand yaw (about world z, from the home orientation) for the distractor: T01's fallen token lies across y.
    distractor_yaw_rad: f64,
    /// The receptacle, and where over it the object is let go (x offset from its centre, m).
    bin: &'static str,
    bin_offset_x_m: f64,
    /// How far above its resting height the object's root is carried over the receptacle's rim.
    carry_above_rest_m: f64,
}

/// A bin task in the perception bin (`bin`, `bin_offset_x_m` and `carry_above_rest_m` at their usual values).
const fn bin(target: &'static str, distractor: &'static str, target_grip_m: f64, distractor_grip_m: f64) -> BinTask {
    BinTask {
        target,
        distractor,
        target_grip_m,
        distractor_grip_m,
        distractor_yaw_rad: 0.0,
        bin: "perception_bin_1",
        bin_offset_x_m: 0.0,
        carry_above_rest_m: CARRY_ABOVE_REST_M,
    }
}

/// A bin task with LIBERO's basket, carried high over its rim.
const fn condiment(target: &'static str, distractor: &'static str, target_grip_m: f64, distractor_grip_m: f64) -> BinTask {
    BinTask { bin: "basket_1", carry_above_rest_m: 0.20, ..bin(target, distractor, target_grip_m, distractor_grip_m) }
}

/// The bin family, by task id.
const BIN_TASKS: &[(&str, BinTask)] = &[
    // upright token (root at its centre, 12 cm tall) vs a fallen one (7.2 cm tall, 12 cm across y: turn the hand)
    ("T01", BinTask { distractor_yaw_rad: std::f64::consts::FRAC_PI_2, ..bin("marker_1", "marker_2", 0.013, 0.0) }),
    // bottles: root at the centre of the 11 cm colliding body
    ("T03", bin("candidate_1", "candidate_2", 0.01, 0.01)),
    // blocks and balls: root at the centre
    ("T04", bin("candidate_1", "candidate_2", 0.0, 0.0)),
    // (the near slot, x ≈ 0.2, is at the edge of the arm's reach from straight above: the middle one is taken)
    ("T05", bin("candidate_1", "candidate_2", 0.0, 0.0)),
    // LIBERO condiment bottles standing (root 6 cm above the bottom), carried high over the basket's rim (the basket
    // stands 9 cm nearer the robot than in the catalog: at x ≈ 0.2 it is beyond a top-down reach)
    ("T02", condiment("condiment_2", "condiment_1", 0.0, 0.0)),
    // drinks: root at the centre, 15 cm tall
    ("T07", bin("drink_2", "drink_1", 0.028, 0.028)),
    // pool suite vlabench_world_knowledge on definitions of their own (tasks 0–5, 7, 9, 11, 14, 15): the target
    // in the private checker_params, wrong_target takes the distractor nearest in kind (or in the layout's order).
    // Condiments with LIBERO's basket, as T02: sugar jar and salt shaker collide 11.2 cm tall, the hot sauce's body 9 cm
    ("vlabench_world_knowledge/select_sweet_condiment", condiment("condiment_3", "condiment_1", 0.011, 0.011)),
    ("vlabench_world_knowledge/select_salty_condiment", condiment("condiment_2", "condiment_1", 0.011, 0.011)),
    ("vlabench_world_knowledge/select_spicy_condiment", condiment("condiment_3", "condiment_2", 0.0, 0.011)),
    ("vlabench_world_knowledge/select_sweet_condiment_explicit_name", condiment("condiment_2", "condiment_3", 0.011, 0.011)),
    // fruits: T05's balls; drinks: T07's; solution bottles: root at the centre, 12 cm tall
    ("vlabench_world_knowledge/select_vitamin_c_fruit", bin("fruit_2", "fruit_1", 0.0, 0.0)),
    ("vlabench_world_knowledge/select_between_fruit", bin("fruit_2", "fruit_1", 0.0, 0.0)),
    ("vlabench_world_knowledge/select_calcium_drink", bin("drink_2", "drink_1", 0.028, 0.028)),
    ("vlabench_world_knowledge/select_nearest_drink", bin("drink_3", "drink_1", 0.028, 0.028)),
    ("vlabench_world_knowledge/select_copper_sulfate_solution", bin("solution_1", "solution_2", 0.015, 0.015)),
    ("vlabench_world_knowledge/select_green_solution", bin("solution_1", "solution_2", 0.015, 0.015)),
    ("vlabench_world_knowledge/select_nearest_solution", bin("solution_3", "solution_1", 0.015, 0.015)),
    // T04's blocks with the spotted one in the top slot
    ("vlabench_perception/select_spotted_object", bin("candidate_1", "candidate_2", 0.0, 0.0)),
];

/// Button family (T06, T09, T10 and the pool's question-bank buttons, `vlabench_button` tasks 0–6, by their pool
/// reference): `(task, target, the button wrong_target presses)`. The pool entries' target follows the physical
/// property asked (the same button as their private `checker_params`); wrong_target presses the runner-up.
const BUTTON_TASKS: &[(&str, &str, &str)] = &[
    ("T06", "button_1", "button_2"),
    ("T09", "button_2", "button_3"),
    ("T10", "button_3", "button_2"),
    ("vlabench_button/select_highest_density", "button_3", "button_2"),
    ("vlabench_button/select_smallest_mass", "button_2", "button_1"),
    ("vlabench_button/select_magnetic_material", "button_2", "button_3"),
    ("vlabench_button/select_lowest_friction", "button_1", "button_2"),
    ("vlabench_button/select_least_thermal_expansion", "button_1", "button_2"),
    ("vlabench_button/select_slowest_sound", "button_1", "button_2"),
    ("vlabench_button/select_highest_reflectance", "button_3", "button_2"),
];

/// The cap's top face in the property button's frame (cap centre at (−0.045, 0, 0.085), half height 0.010).
const PROPERTY_CAP_TOP_LOCAL_M: [f64; 3] = [-0.045, 0.0, 0.095];

/// Every perception task has the one near miss.
const BEHAVIOURS: &[&str] = &[WRONG_TARGET];

/// The perception experts: a row per button task, per bin task and T08's weighing.
pub fn experts() -> impl Iterator<Item = ExpertEntry> {
    let buttons = BUTTON_TASKS.iter().map(|&(task, ..)| ExpertEntry { task, behaviours: BEHAVIOURS, build: press_button });
    let bins = BIN_TASKS.iter().map(|&(task, _)| ExpertEntry { task, behaviours: BEHAVIOURS, build: bin_task });
    let weigh = ExpertEntry { task: "T08", behaviours: BEHAVIOURS, build: |refs, b, _| weigh_and_place(refs, b) };
    buttons.chain(bins).chain(std::iter::once(weigh))
}

fn no_expert(task_id: &str) -> TasksError {
    TasksError::Scene(format!("no scripted expert for task {task_id}"))
}

fn press_button(refs: &SceneRefs, behaviour: &str, task_id: &str) -> Result<Box<dyn Expert>, TasksError> {
    let &(_, target, other) = BUTTON_TASKS.iter().find(|t| t.0 == task_id).ok_or_else(|| no_expert(task_id))?;
    let button = if behaviour == SOLVE { target } else { other };
    crate::expert::skills::press(refs, button, PROPERTY_CAP_TOP_LOCAL_M, true)
}

fn bin_task(refs: &SceneRefs, behaviour: &str, task_id: &str) -> Result<Box<dyn Expert>, TasksError> {
    let (_, t) = BIN_TASKS.iter().find(|t| t.0 == task_id).ok_or_else(|| no_expert(task_id))?;
    if behaviour == SOLVE {
        place_in_bin(refs, t, t.target, t.target_grip_m, 0.0)
    } else {
        place_in_bin(refs, t, t.distractor, t.distractor_grip_m, t.distractor_yaw_rad)
    }
}

fn pos(sim: &Simulation, body: usize) -> Vector3<f64> {
    vec3(&sim.data().xpos()[body])
}

fn xy_dist(a: Vector3<f64>, b: Vector3<f64>) -> f64 {
    (a.x - b.x).hypot(a.y - b.y)
}

/// Height of the carried object's root above the bin's root while it is carried over the walls (12 cm high) and
/// when it is let go inside.
const CARRY_ABOVE_REST_M: f64 = 0.17;
const RELEASE_ABOVE_REST_M: f64 = 0.025;

/// Grasp `object` `grip_m` above its root with the hand yawed by `yaw_rad`, put it in the task's bin.
fn place_in_bin(refs: &SceneRefs, t: &BinTask, object: &str, grip_m: f64, yaw_rad: f64) -> Result<Box<dyn Expert>, TasksError> {
    Ok(Box::new(Script::new(pick_and_place(refs, object, grip_m, yaw_rad, t.bin, t.bin_offset_x_m, t.carry_above_rest_m)?)))
}

/// The phases that grasp `object` and let it go inside `bin_name`, over a point `bin_offset_x_m` from the bin's centre
/// along x (negative: nearer the robot, for bins at the edge of the arm's reach).
fn pick_and_place(
    refs: &SceneRefs,
    object: &str,
    grip_m: f64,
    yaw_rad: f64,
    bin_name: &str,
    bin_offset_x_m: f64,
    carry_above_rest_m: f64,
) -> Result<Vec<Phase>, TasksError> {
    let obj = refs.instance_body(object)?;
    let bin = refs.instance_body(bin_name)?;
    let up = Vector3::z();
    // the object's resting root height above the bin's root (both stand on the table), captured at the start
    let rest = Arc::new(Mutex::new(0.0_f64));
    let rest_w = rest.clone();
    // grip-site goal that brings the held object's root to `target`
    let carry = move |sim: &Simulation, target: Vector3<f64>| grip_pose(sim).0 + (target - pos(sim, obj));
    // where the object's root goes: over the bin's centre, `above_rest` higher than where it rested on the table
    let over_bin = move |rest: &Arc<Mutex<f64>>, sim: &Simulation, above_rest: f64| {
        let b = pos(sim, bin);
        Vector3::new(b.x + bin_offset_x_m, b.y, b.z + *rest.lock().expect("lock") + above_rest)
    };
    let (r1, r2, r3) = (rest.clone(), rest.clone(), rest);
    let hand = move |ctx: &PhaseCtx| rotate_world(&ctx.home_rot, Vector3::z(), yaw_rad);
    let phases = vec![
        Phase::new("above_object", move |sim, ctx| {
            *rest_w.lock().expect("lock") = pos(sim, obj).z - pos(sim, bin).z;
            Goal::at(pos(sim, obj) + up * (grip_m + 0.12), GRIPPER_OPEN).rotated(hand(ctx))
        })
        .until_reached(0.012),
        Phase::new("down_to_object", move |sim, ctx| Goal::at(pos(sim, obj) + up * grip_m, GRIPPER_OPEN).rotated(hand(ctx)).slow(0.5))
            .until_reached(0.006)
            .max_steps(80),
        Phase::new("grasp", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(hand(ctx))).for_steps(12),
        Phase::new("lift", move |_, ctx| Goal::at(ctx.start_pos_m + up * 0.18, GRIPPER_CLOSED).rotated(hand(ctx)).slow(0.6))
            .until_reached(0.015)
            .max_steps(80),
        Phase::new("carry_over_bin", move |sim, ctx| Goal::at(carry(sim, over_bin(&r1, sim, carry_above_rest_m)), GRIPPER_CLOSED).rotated(hand(ctx)).slow(0.6))
            .until(move |sim, _| xy_dist(pos(sim, obj), pos(sim, bin) + Vector3::x() * bin_offset_x_m) < 0.01)
            .max_steps(150),
        Phase::new("lower_into_bin", move |sim, ctx| {
            Goal::at(carry(sim, over_bin(&r2, sim, RELEASE_ABOVE_REST_M)), GRIPPER_CLOSED).rotated(hand(ctx)).slow(0.4)
        })
        .until(move |sim, _| (pos(sim, obj) - over_bin(&r3, sim, RELEASE_ABOVE_REST_M)).norm() < 0.012)
        .max_steps(100),
        Phase::new("release", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(hand(ctx))).for_steps(12),
        Phase::new("retreat", move |_, ctx| Goal::at(ctx.start_pos_m + up * 0.12, GRIPPER_OPEN).rotated(hand(ctx)).slow(0.6))
            .until_reached(0.015)
            .max_steps(60),
        Phase::new("wait", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(hand(ctx))).for_steps(10),
    ];
    Ok(phases)
}

/// T08 mugs in stage order.
const MUGS: [&str; 3] = ["mug_1", "mug_2", "mug_3"];
/// How high a mug is lifted to weigh it, and how long it is held there (control steps).
pub const WEIGH_LIFT_M: f64 = 0.08;
pub const WEIGH_HOLD_STEPS: u32 = 20;
/// The name of the phase at whose end a weighed mug hangs still in the hand (the wrist-force test reads it there).
pub const WEIGH_HOLD_PHASE: &str = "weigh_hold";

/// A mug's mass in the compiled model (the episode writes the private masses there; the expert reads privileged state).
fn mug_mass(refs: &SceneRefs, mug: &str) -> Result<f64, TasksError> {
    let main = refs.body(&format!("{mug}_main"))?;
    let parents = refs.model.body_parentid();
    let in_mug = |b: usize| b == main || parents[b] as usize == main;
    Ok((0..parents.len()).filter(|&b| in_mug(b)).map(|b| refs.model.body_mass()[b]).sum())
}

/// The phases that weigh one object: grasp across its body, lift it `WEIGH_LIFT_M`, hold still, set it back, let go.
fn weigh(refs: &SceneRefs, object: &str) -> Result<Vec<Phase>, TasksError> {
    let obj = refs.instance_body(object)?;
    let up = Vector3::z();
    Ok(vec![
        Phase::new("above_mug", move |sim, _| Goal::at(pos(sim, obj) + up * 0.12, GRIPPER_OPEN)).until_reached(0.012),
        Phase::new("down_to_mug", move |sim, _| Goal::at(pos(sim, obj), GRIPPER_OPEN).slow(0.5)).until_reached(0.01).max_steps(80),
        Phase::new("grasp_mug", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED)).for_steps(12),
        Phase::new("weigh_lift", move |_, ctx| Goal::at(ctx.start_pos_m + up * WEIGH_LIFT_M, GRIPPER_CLOSED).slow(0.4))
            .until_reached(0.008)
            .max_steps(60),
        Phase::new(WEIGH_HOLD_PHASE, move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED)).for_steps(WEIGH_HOLD_STEPS),
        Phase::new("set_down", move |_, ctx| Goal::at(ctx.start_pos_m - up * (WEIGH_LIFT_M - 0.004), GRIPPER_CLOSED).slow(0.4))
            .until_reached(0.008)
            .max_steps(60),
        Phase::new("let_go", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN)).for_steps(10),
        Phase::new("up_from_mug", move |_, ctx| Goal::at(ctx.start_pos_m + up * 0.10, GRIPPER_OPEN)).until_reached(0.015).max_steps(40),
    ])
}

/// T08: weigh the three mugs in turn, then put the heaviest (by the model's masses) in the green bin; `wrong_target`
/// weighs them all the same way and puts the lightest in the bin.
fn weigh_and_place(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let mut by_mass = MUGS.iter().map(|m| Ok((mug_mass(refs, m)?, *m))).collect::<Result<Vec<_>, TasksError>>()?;
    by_mass.sort_by(|a, b| a.0.total_cmp(&b.0));
    let chosen = if behaviour == SOLVE { by_mass[2].1 } else { by_mass[0].1 };
    let mut phases = Vec::new();
    for m in MUGS {
        phases.extend(weigh(refs, m)?);
    }
    // the bin's centre (x ≈ 0.20) is at the edge of the arm's reach from above: aim 4 cm nearer, still well inside
    phases.extend(pick_and_place(refs, chosen, 0.0, 0.0, "target_bin_1", -0.04, CARRY_ABOVE_REST_M)?);
    Ok(Box::new(Script::new(phases)))
}
