//! The stock expert's placement of a bowl or a mug (a rim pinch) as separate plan steps: a grasp that is checked
//! and tried again, then the carry. A rim pinch can miss (the hand comes to rest on the rim or a neighbour and closes
//! on nothing, a tilted bowl's rim is lower on the pinched side, a mug slips): pressing on and carrying anyway moves
//! a hand that holds nothing by the hand-to-object offset, so each try ends with a check that the object rose with
//! the hand, and a failed try lets go and is followed by another (from the other side of the rim), built from the
//! state when it starts.
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use libero_sim::Simulation;
use nalgebra::{Matrix3, Vector3};

use super::{Build, Ctx, Done, Slot, Target, place_target, rise, short_of, stalled};
use crate::expert::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, grip_pose, mat3, open_along, rotation_error};
use crate::expert::skills::{carry, extent, pos, xy_dist};

/// Grasp tries in all (the first and up to two regrasps).
const TRIES: usize = 3;
/// A bowl is pinched this far below its rim; a mug deeper, where its wall is firm and a slip does not tip it.
const BOWL_BELOW_RIM_M: f64 = 0.014;
const MUG_BELOW_RIM_M: f64 = 0.035;
/// The fingers straddle the wall this far inside the rim's outer edge.
const INSIDE_RIM_M: f64 = 0.008;
/// A try holds its object when, over the lift, its root rose at least this fraction of what the hand rose (and the
/// hand rose this much): a pinch that missed leaves it where it was (a bowl held at its rim hangs tilted, its root
/// rising about half as much as the hand).
const HELD_RISE_FRACTION: f64 = 0.3;
const MIN_HAND_RISE_M: f64 = 0.03;
/// A pinch point farther than this from the robot base (horizontally, m) is at the edge of the arm's reach.
const FAR_REACH_M: f64 = 0.78;
/// Carry speed (largest action norm): a mug swings out of a fast-moving pinch.
const BOWL_CARRY_SPEED: f64 = 0.7;
const MUG_CARRY_SPEED: f64 = 0.3;
/// A carried mug has stopped swinging below this angular speed (rad/s).
const STEADY_RAD_PER_S: f64 = 0.15;

/// Objects placed with a rim pinch (and so by these steps).
pub(super) fn rim_grasped(category: &str) -> bool {
    category.contains("bowl") || category.contains("mug") || category.contains("cup")
}

fn is_mug(category: &str) -> bool {
    category.contains("mug") || category.contains("cup")
}

/// The steps of one rim-pinch placement: `TRIES` grasps, each skipped once an earlier one holds the object, then the
/// carry. `done` makes the placement's own skip test (its goal atom holds; `None` for the near miss, which always acts).
pub(super) fn place_steps(object: usize, category: &str, target: Target, slot: Slot, short: bool, done: impl Fn() -> Option<Done>) -> Vec<(Option<Done>, Build)> {
    let held = Arc::new(AtomicBool::new(false));
    let mut steps: Vec<(Option<Done>, Build)> = Vec::with_capacity(TRIES + 1);
    for attempt in 0..TRIES {
        let skip: Option<Done> = if attempt == 0 {
            done()
        } else {
            let (held, atom) = (held.clone(), done());
            Some(Box::new(move |sim| held.load(Ordering::Relaxed) || atom.as_ref().is_some_and(|d| d(sim))))
        };
        let (held, category) = (held.clone(), category.to_owned());
        let build: Build = Box::new(move |sim, ctx, home| grasp_phases(sim, ctx, home, object, &category, target, slot, attempt, held));
        steps.push((skip, build));
    }
    let category = category.to_owned();
    steps.push((done(), Box::new(move |sim, ctx, home| carry_phases(sim, ctx, home, object, &category, target, slot, short))));
    steps
}

/// The pinch point (world) and the direction the fingers close along for a try: on the rim's side along the
/// narrower horizontal extent (a mug's handle sticks out along the wider one), the far side on the second try, the
/// other axis on the third (the forearm can meet a fixture, an open drawer above, on both sides of one axis).
/// The rim's height on that side from the object's up axis, so a bowl resting tilted is pinched at its wall there,
/// not in the air above the lower side of its rim.
fn pinch_point(sim: &Simulation, body: usize, category: &str, (lo, hi): (Vector3<f64>, Vector3<f64>), base_m: Vector3<f64>, attempt: usize) -> (Vector3<f64>, Vector3<f64>) {
    let half = (hi - lo) / 2.0;
    let narrow_y = half.y <= half.x;
    let centre = if is_mug(category) { cup_centre(sim, body, lo, hi) } else { (lo + hi) / 2.0 };
    // the last try turns to the other axis, on the object's side away from the robot's centre line there
    let (axis, r, side) = match (attempt, narrow_y) {
        (0 | 1, true) => (Vector3::y(), half.y, if attempt == 0 { 1.0 } else { -1.0 }),
        (0 | 1, false) => (Vector3::x(), half.x, if attempt == 0 { 1.0 } else { -1.0 }),
        (_, true) => (Vector3::x(), half.x, (centre.x - base_m.x).signum()),
        (_, false) => (Vector3::y(), half.y, (centre.y - base_m.y).signum()),
    };
    // at the edge of the arm's reach the far side's pinch stretches the elbow straight (joint 4 on its limit), and
    // the carry back toward the robot then stalls in the singularity: the near side first there
    let reach = |s: f64| {
        let p = centre + axis * s * (r - INSIDE_RIM_M);
        (p.x - base_m.x).hypot(p.y - base_m.y)
    };
    let side = if attempt < 2 && reach(1.0) > FAR_REACH_M && reach(-1.0) < reach(1.0) { -side } else { side };
    let out = axis * side * (r - INSIDE_RIM_M);
    // the rim's plane: normal the object's up axis, its highest point at the box's top
    let up = mat3(&sim.data().xmat()[body]).column(2).into_owned();
    let up = if up.z > 0.5 { up } else { Vector3::z() };
    let tilt_sin = (1.0 - up.z * up.z).max(0.0).sqrt();
    let rim_centre_z = hi.z - r * tilt_sin;
    let rim_z = rim_centre_z - (up.x * out.x + up.y * out.y) / up.z;
    let below = if is_mug(category) { MUG_BELOW_RIM_M } else { BOWL_BELOW_RIM_M };
    (Vector3::new(centre.x + out.x, centre.y + out.y, rim_z.min(hi.z) - below), axis)
}

/// The centre of a mug's cup, not of its box (which takes in the handle): along the wide horizontal axis the cup's
/// axis lies its radius (half the narrow side) in from the end nearer the mug's centre of mass, the handle being
/// light. Pinched at the box's centre instead, the fingers meet the porcelain mug's faceted wall 2 cm off its axis
/// and it turns out of the pinch in the carry.
fn cup_centre(sim: &Simulation, body: usize, lo: Vector3<f64>, hi: Vector3<f64>) -> Vector3<f64> {
    let (half, mut centre) = ((hi - lo) / 2.0, (lo + hi) / 2.0);
    let com = sim.data().subtree_com()[body];
    let k = if half.y <= half.x { 0 } else { 1 };
    let r = half.x.min(half.y);
    let (near_lo, near_hi) = (lo[k] + r, hi[k] - r);
    centre[k] = if (com[k] - near_lo).abs() < (com[k] - near_hi).abs() { near_lo } else { near_hi };
    centre
}

/// Where the root is let go and the height it is carried at (as the stock placement computes them), the near miss's
/// target moved toward the robot.
fn aim(sim: &Simulation, ctx: &Ctx, object: usize, target: Target, slot: Slot, short: bool) -> (Vector3<f64>, f64) {
    let root = pos(sim, ctx.index.instances[object].body);
    let (lo, hi) = extent(sim, &ctx.index, object);
    let half_width_m = (hi.x - lo.x).max(hi.y - lo.y) / 2.0;
    let (mut to, carry_top) = place_target(sim, ctx, object, target, slot, root.z - lo.z, half_width_m);
    if short {
        to = short_of(ctx, to, target);
    }
    let carry_z = carry_top.max(to.z + 0.08);
    // a mug (tall, its bottom low under the pinch) is carried clear of the movable objects along its way
    let carry_z = if is_mug(&ctx.index.instances[object].category) { carry_z.max(clear_of_path(sim, ctx, object, to) + root.z - lo.z) } else { carry_z };
    (to, carry_z.min(1.30))
}

/// The height (world z) an object's bottom must keep to pass over the other movable objects near the straight
/// horizontal way from where it is to `to` (boxes within its half width and a margin of the way).
fn clear_of_path(sim: &Simulation, ctx: &Ctx, object: usize, to: Vector3<f64>) -> f64 {
    const MARGIN_M: f64 = 0.03;
    let (lo, hi) = extent(sim, &ctx.index, object);
    let half_width = (hi.x - lo.x).max(hi.y - lo.y) / 2.0;
    let from = pos(sim, ctx.index.instances[object].body);
    let (a, d) = (Vector3::new(from.x, from.y, 0.0), Vector3::new(to.x - from.x, to.y - from.y, 0.0));
    let mut top = f64::NEG_INFINITY;
    for (i, inst) in ctx.index.instances.iter().enumerate() {
        if i == object || inst.is_fixture {
            continue;
        }
        let (olo, ohi) = extent(sim, &ctx.index, i);
        let c = Vector3::new((olo.x + ohi.x) / 2.0, (olo.y + ohi.y) / 2.0, 0.0);
        let reach = half_width + ((ohi.x - olo.x).hypot(ohi.y - olo.y)) / 2.0 + MARGIN_M;
        let t = if d.norm_squared() > 1e-12 { ((c - a).dot(&d) / d.norm_squared()).clamp(0.0, 1.0) } else { 0.0 };
        if (a + d * t - c).norm() < reach {
            top = top.max(ohi.z + MARGIN_M);
        }
    }
    top
}

/// One grasp try: above the pinch point, down until there or blocked (the hand stalls on something: it closes
/// there rather than pressing on), close, lift to the carry height; then record whether the object rose with the
/// hand, and if not let go.
#[allow(clippy::too_many_arguments)] // the try's plan (object, target, slot, attempt) plus the state it starts from
fn grasp_phases(
    sim: &Simulation,
    ctx: &Ctx,
    home: &Matrix3<f64>,
    object: usize,
    category: &str,
    target: Target,
    slot: Slot,
    attempt: usize,
    held: Arc<AtomicBool>,
) -> Vec<Phase> {
    let body = ctx.index.instances[object].body;
    let rest_z = pos(sim, body).z;
    let (lo, hi) = extent(sim, &ctx.index, object);
    let (point, axis) = pinch_point(sim, body, category, (lo, hi), ctx.base_m, attempt);
    let rot = open_along(home, axis);
    let off = point - pos(sim, body);
    let (_, carry_z) = aim(sim, ctx, object, target, slot, false);
    let lift_z = carry_z.max(rest_z + 0.10);
    let at_grasp = move |sim: &Simulation| pos(sim, body) + off;
    let held_check = held.clone();
    // root and hand heights when the fingers have closed (f64 bits), the lift's reference
    let closed_z = Arc::new([AtomicU64::new(0), AtomicU64::new(0)]);
    let (closed_z_set, closed_z_lift) = (closed_z.clone(), closed_z.clone());
    // the hand rises by what brings a held root to the lift height
    let lift_goal = move |start: Vector3<f64>| {
        let root_z0 = f64::from_bits(closed_z_lift[0].load(Ordering::Relaxed));
        Vector3::new(start.x, start.y, start.z + (lift_z - root_z0).max(0.0))
    };
    let lift_goal_at = lift_goal.clone();
    vec![
        rise(),
        Phase::new("above_object", move |sim, _| Goal::at(at_grasp(sim) + Vector3::z() * 0.10, GRIPPER_OPEN).rotated(rot))
            .until(move |sim, _| (grip_pose(sim).0 - at_grasp(sim) - Vector3::z() * 0.10).norm() < 0.012 && rotation_error(sim, &rot) < 0.06)
            .max_steps(160),
        Phase::new("down_to_object", move |sim, _| Goal::at(at_grasp(sim), GRIPPER_OPEN).slow(0.5).rotated(rot))
            .until(move |sim, ctx| (grip_pose(sim).0 - at_grasp(sim)).norm() < 0.007 || stalled(sim, ctx))
            .max_steps(80),
        Phase::new("close", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(rot))
            .until(move |sim, ctx| {
                closed_z_set[0].store(pos(sim, body).z.to_bits(), Ordering::Relaxed);
                closed_z_set[1].store(grip_pose(sim).0.z.to_bits(), Ordering::Relaxed);
                ctx.steps >= 20 || (ctx.steps >= 8 && sim.data().qvel()[sim.ids().finger_dof_adr[0]].abs() < 1e-3)
            })
            .max_steps(20),
        // ends when the object is up, or when the hand is up and the object is not with it
        Phase::new("lift", move |_, ctx| Goal::at(lift_goal_at(ctx.start_pos_m), GRIPPER_CLOSED).slow(0.6).rotated(rot))
            .until(move |sim, ctx| pos(sim, body).z > lift_z - 0.015 || (ctx.steps > 10 && (grip_pose(sim).0 - lift_goal(ctx.start_pos_m)).norm() < 0.01))
            .max_steps(80),
        Phase::new("check_lift", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(rot)).until(move |sim, _| {
            let (root_z0, hand_z0) = (f64::from_bits(closed_z[0].load(Ordering::Relaxed)), f64::from_bits(closed_z[1].load(Ordering::Relaxed)));
            let hand_rise = grip_pose(sim).0.z - hand_z0;
            held_check.store(hand_rise > MIN_HAND_RISE_M && pos(sim, body).z - root_z0 > HELD_RISE_FRACTION * hand_rise, Ordering::Relaxed);
            true
        }),
        Phase::new("let_go", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(rot))
            .until(move |_, ctx| held.load(Ordering::Relaxed) || ctx.steps >= 10)
            .max_steps(10),
    ]
}

/// Carry the held object over its target, lower it until it is there or rests on something, let go and back off.
/// The hand keeps the orientation it holds the object with.
/// Into a compartment covered from above (the microwave) a mug is laid on its side and slid in (`tilt`).
#[allow(clippy::too_many_arguments)] // the placement's plan (object, target, slot, short) plus the state it starts from
fn carry_phases(sim: &Simulation, ctx: &Ctx, home: &Matrix3<f64>, object: usize, category: &str, target: Target, slot: Slot, short: bool) -> Vec<Phase> {
    let body = ctx.index.instances[object].body;
    if !short
        && let Target::Region { region, inside: true } = target
        && let Some(phases) = super::tilt::lay_in_held(sim, &ctx.index, object, region, ctx.base_m, home)
    {
        return phases;
    }
    let (to, carry_z) = aim(sim, ctx, object, target, slot, short);
    // no lower than it was lifted to (from a high start, over what it started on), until over the target
    let carry_z = carry_z.max(pos(sim, body).z);
    let rot = grip_pose(sim).1;
    let mug = is_mug(category);
    let speed = if mug { MUG_CARRY_SPEED } else { BOWL_CARRY_SPEED };
    vec![
        Phase::new("carry_over_target", move |sim, _| Goal::at(carry(sim, body, Vector3::new(to.x, to.y, carry_z)), GRIPPER_CLOSED).slow(speed).rotated(rot))
            .until(move |sim, _| xy_dist(pos(sim, body), to) < 0.008)
            .max_steps(if mug { 300 } else { 200 }),
        // a mug pinched at its wall swings about the line through the finger contacts: let it come to rest first
        Phase::new("steady", move |sim, _| Goal::at(carry(sim, body, Vector3::new(to.x, to.y, carry_z)), GRIPPER_CLOSED).slow(speed).rotated(rot))
            .until(move |sim, ctx| !mug || (ctx.steps >= 5 && spin(sim, body) < STEADY_RAD_PER_S))
            .max_steps(40),
        Phase::new("lower", move |sim, _| Goal::at(carry(sim, body, to - Vector3::z() * 0.01), GRIPPER_CLOSED).slow(0.35).rotated(rot))
            .until(move |sim, ctx| pos(sim, body).z < to.z + 0.004 || stalled(sim, ctx))
            .max_steps(70),
        Phase::new("open", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(rot)).for_steps(10),
        Phase::new("retreat", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.12, GRIPPER_OPEN).rotated(rot))
            .until_reached(0.02)
            .max_steps(40),
    ]
}


/// The angular speed (rad/s) of a body (the angular part of its `cvel`).
fn spin(sim: &Simulation, body: usize) -> f64 {
    let v = sim.data().cvel()[body];
    Vector3::new(v[0], v[1], v[2]).norm()
}
