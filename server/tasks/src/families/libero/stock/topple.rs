//! A book into a compartment too low for it standing or on its edge (the study shelf's lower compartment, 7 cm under
//! its middle board; the yellow book is 12.2 × 9.8 × 2.35 cm): it goes in only lying flat, and a hand that holds a
//! flat book by its edge stands taller along its fingers than the board leaves above the table. So the book is tipped
//! over where it stands (pushed near its top across its thickness by the closed fingers, it falls on its face) and
//! then pushed along the table into the compartment by the open fingers spread along its length, the hand staying
//! outside the open face.
//! Where it cannot fall to a place from which it goes in (the black book stands where it would fall; lying along the
//! push its root, the point `In` reads, trails where the hand cannot follow), it is first turned a quarter where it
//! stands.
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::{Matrix3, Vector3};

use crate::expert::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, grip_pose, mat3, open_along, rotate_world, rotation_error};
use crate::expert::skills::{contact_corners, extent, pos};
use crate::judge::predicates::SceneIndex;

/// The closed fingers come down this far (m) behind the standing book's face they tip it by.
const TIP_BEHIND_M: f64 = 0.035;
/// … and this far (m) under its top.
const TIP_BELOW_TOP_M: f64 = 0.03;
/// The book is taken to have fallen once its long axis leans this far from upright (rad).
const FALLEN_RAD: f64 = 0.9;
/// A fallen book lies still once its speed is under this (m/s).
const STILL_M_PER_S: f64 = 0.01;
/// The grip site is carried this far (m) above the table while it pushes (the fingertips about 1 cm lower).
const PUSH_UP_M: f64 = 0.013;
/// The fingers' half thickness along the push (m): the grip site stays this far behind the face it pushes.
const FINGER_HALF_M: f64 = 0.012;
/// The pushing hand's pitch forward of straight down (rad).
const PUSH_PITCH_RAD: f64 = 0.5;
/// … reached once the hand has pushed this far (m).
const PITCH_OVER_M: f64 = 0.10;
/// How far ahead of the book's trailing face the pushing fingers are led (m).
const PUSH_LEAD_M: f64 = 0.07;
/// The hand's front (its body, wider than the fingers) stands this far (m) ahead of the grip site along the push; it
/// stops short of the region's open side by [`FACE_CLEAR_M`] (the board's edge is flush with the region's side).
const HAND_FRONT_M: f64 = 0.03;
const FACE_CLEAR_M: f64 = 0.005;
/// The book's root must end at least this far (m) inside the region's open side.
const MIN_IN_M: f64 = 0.015;
/// … and its leading edge this far (m) short of the region's back.
const BACK_GAP_M: f64 = 0.015;
/// A book turned where it stands is lifted this far (m) first.
const TURN_LIFT_M: f64 = 0.03;
/// A near miss stops its push with the root this far (m) outside the region's open side.
const SHORT_OUT_M: f64 = 0.04;

/// Where the tipped-over book is pushed: the direction into the compartment, the root's depth along it at which the
/// push stops, and the grip site's farthest depth along it (m; the hand stays outside the open face).
#[derive(Clone, Copy)]
struct Push {
    into: Vector3<f64>,
    stop_root_m: f64,
    hand_limit_m: f64,
}

/// The phases that tip `object` (a book standing on the table, picked by `grasp`: the grip point's offset from its
/// root and the hand's orientation) over and push it into `region` (a compartment covered from above, open toward the
/// robot base `base_m`), or `None` where the book fits in it standing or on its edge, does not fit lying flat, or
/// lands nowhere from where it can be pushed in far enough. Where it cannot fall either way across its thickness
/// (something stands there, or it would lie along the push with its root behind, where the hand cannot follow), it
/// is first turned a quarter where it stands. `short`: the push stops with the root outside.
#[allow(clippy::too_many_arguments)] // the step's object, region and grasp, the robot's base and home, and the near miss
pub(super) fn phases(
    sim: &Simulation,
    index: &Arc<SceneIndex>,
    object: usize,
    region: usize,
    (grasp_offset_m, rot): (Vector3<f64>, Matrix3<f64>),
    base_m: Vector3<f64>,
    home: &Matrix3<f64>,
    short: bool,
) -> Option<Vec<Phase>> {
    let e = super::tilt::entry_towards(sim, index, region, base_m)?;
    let into = -e.out;
    let fp = super::fit::object_footprint(sim, index, object)?;
    let (thick_m, wide_m) = (2.0 * fp.narrow_half_m, 2.0 * fp.wide_half_m);
    let (lo, hi) = extent(sim, index, object);
    let tall_m = hi.z - lo.z;
    let (c, _, h_z) = super::region_box(sim, index, region);
    let (floor_z, top_z) = (c.z - h_z, c.z + h_z);
    // standing or on its edge it does not fit; lying on the table, its root (mid-thickness) is inside the region's
    // height and its top under the region's top
    if tall_m < 2.0 * h_z || wide_m + 0.02 < 2.0 * h_z || lo.z + thick_m / 2.0 <= floor_z || lo.z + thick_m + 0.005 >= top_z {
        return None;
    }
    let root = pos(sim, index.instances[object].body);
    let side_m = c.dot(&into) - e.half_depth_m;
    let back_m = c.dot(&into) + e.half_depth_m;
    let hand_limit_m = side_m - FACE_CLEAR_M - HAND_FRONT_M;
    let others = super::other_boxes(sim, index, object);
    // where the root ends when the book falls along `d` and is pushed in: `None` where it lands on something or
    // does not go in far enough
    let pushed_in = |d: Vector3<f64>| {
        let across = Vector3::z().cross(&d);
        // lying, the root (the bottom face's centre) stays at the falling edge; the book reaches `tall_m` along d
        let root_l = root + d * (thick_m / 2.0);
        let corners = [0.0, tall_m].map(|a| [-0.5, 0.5].map(|b| root_l + d * a + across * (b * wide_m))).concat();
        let (lo_l, hi_l) = corners.iter().fold((Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY)), |(l, h), p| (l.inf(p), h.sup(p)));
        let free = others.iter().all(|(_, l, h)| h.z < lo.z + 0.005 || l.z > lo.z + thick_m + 0.01 || h.x < lo_l.x || l.x > hi_l.x || h.y < lo_l.y || l.y > hi_l.y);
        let (trail, lead) = corners.iter().map(|p| p.dot(&into)).fold((f64::INFINITY, f64::NEG_INFINITY), |(t, l), a| (t.min(a), l.max(a)));
        // the push moves the book until the hand meets its limit or the leading edge the back
        let shift = (hand_limit_m - (trail - FINGER_HALF_M)).min(back_m - BACK_GAP_M - lead);
        let root_in = root_l.dot(&into) + shift;
        (free && root_in >= side_m + MIN_IN_M).then_some(root_in)
    };
    // of the ways it can fall (across its thickness, as it stands or turned a quarter first), one that needs no turn,
    // then the one from which it goes in deepest
    let turned_n = Vector3::z().cross(&fp.narrow_dir);
    let (d, turned, stop_root_m) = [(fp.narrow_dir, false), (-fp.narrow_dir, false), (turned_n, true), (-turned_n, true)]
        .into_iter()
        .filter_map(|(d, turned)| pushed_in(d).map(|r| (d, turned, r)))
        .max_by(|a, b| (!a.1).cmp(&!b.1).then(a.2.total_cmp(&b.2)))?;
    let stop_root_m = if short { side_m - SHORT_OUT_M } else { stop_root_m };
    let push = Push { into, stop_root_m, hand_limit_m };
    let mut phases = if turned { Vec::from(turn_in_place(index.instances[object].body, (grasp_offset_m, rot), turned_n, home)) } else { vec![] };
    phases.extend(tip_over(index, object, d, (thick_m, tall_m), home));
    phases.extend(push_in(Arc::clone(index), object, push, home));
    Some(phases)
}

/// Pick the standing book, lift it a little, turn it about world z until its thickness lies along `thickness`, set
/// it down where it stood and let go.
fn turn_in_place(body: usize, (grasp_offset_m, rot): (Vector3<f64>, Matrix3<f64>), thickness: Vector3<f64>, home: &Matrix3<f64>) -> [Phase; 7] {
    let turned = open_along(home, thickness);
    let [above, down, close] = super::pick_phases(body, grasp_offset_m, rot);
    [
        above,
        down,
        close,
        Phase::new("lift_to_turn", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * TURN_LIFT_M, GRIPPER_CLOSED).slow(0.5).rotated(rot))
            .until_reached(0.006)
            .max_steps(60),
        Phase::new("turn", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).slow(0.5).rotated(turned))
            .until(move |sim, _| rotation_error(sim, &turned) < 0.04)
            .max_steps(120),
        Phase::new("set_down", move |_, ctx| Goal::at(ctx.start_pos_m - Vector3::z() * (TURN_LIFT_M + 0.01), GRIPPER_CLOSED).slow(0.3).rotated(turned))
            .until(super::stalled)
            .max_steps(60),
        Phase::new("let_go", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(turned)).for_steps(10),
    ]
}

/// The book's long axis (its body z, the way it stood) leans from world z by this much (rad).
fn lean(sim: &Simulation, body: usize) -> f64 {
    mat3(&sim.data().xmat()[body]).column(2).z.clamp(-1.0, 1.0).acos()
}

/// The root's speed (m/s).
fn speed(sim: &Simulation, body: usize) -> f64 {
    let v = sim.data().cvel()[body];
    Vector3::new(v[3], v[4], v[5]).norm()
}

/// The hand's speed (m/s): the grip site's body's linear velocity.
fn hand_speed(sim: &Simulation) -> f64 {
    speed(sim, sim.model().site_bodyid()[sim.ids().grip_site] as usize)
}

/// Down behind the standing book (on the side away from `d`) with the fingers closed, push its upper part along `d`
/// with them until it has fallen, rise, wait for it to lie still.
fn tip_over(index: &SceneIndex, object: usize, d: Vector3<f64>, (thick_m, tall_m): (f64, f64), home: &Matrix3<f64>) -> Vec<Phase> {
    let body = index.instances[object].body;
    // the fingers closed along `d`: the hand, 20 cm along its fingers' axis, reaches no further aside than its
    // thickness (opened across `d`, it knocked the black book beside the study shelf's yellow book)
    let rot = open_along(home, d);
    let behind = move |sim: &Simulation, below_top_m: f64| {
        let r = pos(sim, body);
        r - d * (thick_m / 2.0 + TIP_BEHIND_M) + Vector3::z() * (tall_m - below_top_m)
    };
    vec![
        Phase::new("above_tip", move |sim, _| Goal::at(behind(sim, -0.06), GRIPPER_CLOSED).rotated(rot)).until_reached(0.012).max_steps(160),
        Phase::new("down_behind", move |sim, _| Goal::at(behind(sim, TIP_BELOW_TOP_M), GRIPPER_CLOSED).slow(0.5).rotated(rot))
            .until_reached(0.008)
            .max_steps(80),
        Phase::new("tip_over", move |_, ctx| Goal::at(ctx.start_pos_m + d * (thick_m + TIP_BEHIND_M + 0.05), GRIPPER_CLOSED).slow(0.3).rotated(rot))
            .until(move |sim, _| lean(sim, body) > FALLEN_RAD)
            .max_steps(150),
        Phase::new("rise_off", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.08, GRIPPER_CLOSED).rotated(rot))
            .until(move |sim, ctx| ctx.steps > 10 && lean(sim, body) > 1.4 && speed(sim, body) < STILL_M_PER_S)
            .max_steps(60),
    ]
}

/// The fallen book's trailing extent along `dir` (the least over its contact boxes' corners), its centre, and its
/// lowest point's height (m), from one walk over the corners.
fn lying(sim: &Simulation, index: &SceneIndex, object: usize, dir: Vector3<f64>) -> (f64, Vector3<f64>, f64) {
    let corners = contact_corners(sim, index, object);
    if corners.is_empty() {
        let p = pos(sim, index.instances[object].body);
        return (p.dot(&dir), p, p.z);
    }
    let trail = corners.iter().map(|p| p.dot(&dir)).fold(f64::INFINITY, f64::min);
    let lo_z = corners.iter().map(|p| p.z).fold(f64::INFINITY, f64::min);
    (trail, corners.iter().sum::<Vector3<f64>>() / corners.len() as f64, lo_z)
}

/// Behind the lying book, the open fingers spread across the push, down to the table, push it along `into` until
/// its root is at the stop depth (the hand never beyond its limit), back out and up.
fn push_in(index: Arc<SceneIndex>, object: usize, p: Push, home: &Matrix3<f64>) -> [Phase; 5] {
    let body = index.instances[object].body;
    let Push { into, stop_root_m, hand_limit_m } = p;
    // pitched forward about the fingers' axis (their tips lead) as the push goes on: upright, the wrist's housing,
    // 20 cm above the fingertips, stands 11 cm ahead of them across the arm and meets the top of a shelf (the study
    // shelf's, 21 cm high) before the fingers reach its open face; pitched from the start, the hand's back leans
    // into whatever stands behind the book
    let rot = open_along(home, Vector3::z().cross(&into));
    let pitched = move |share: f64| rotate_world(&rot, (-Vector3::z()).cross(&into), PUSH_PITCH_RAD * share.clamp(0.0, 1.0));
    let end_rot = pitched(1.0);
    // the grip site behind the book's trailing face by `behind_m` (but never past the hand's limit), level with its
    // centre across the push, `up_m` above its bottom
    let at = move |sim: &Simulation, behind_m: f64, up_m: f64| {
        let (trail, centre, lo_z) = lying(sim, &index, object, into);
        let along = (trail - behind_m).min(hand_limit_m);
        centre - into * (centre.dot(&into) - along) + Vector3::z() * (lo_z + up_m - centre.z)
    };
    let (at1, at2, at3) = (at.clone(), at.clone(), at);
    let done = move |sim: &Simulation| pos(sim, body).dot(&into) >= stop_root_m || grip_pose(sim).0.dot(&into) >= hand_limit_m - 0.005;
    [
        Phase::new("behind_book", move |sim, _| Goal::at(at1(sim, FINGER_HALF_M + 0.03, 0.10), GRIPPER_OPEN).rotated(rot)).until_reached(0.012).max_steps(200),
        Phase::new("down_to_table", move |sim, _| Goal::at(at2(sim, FINGER_HALF_M + 0.03, PUSH_UP_M), GRIPPER_OPEN).slow(0.4).rotated(rot))
            .until_reached(0.006)
            .max_steps(100),
        Phase::new("push_in", move |sim, ctx| {
            // lead the fingers into the book's face (a goal nearer than this moves the hand too slowly to keep
            // up with the sliding book), by less and slower as the root nears its stop
            let left = (stop_root_m - pos(sim, body).dot(&into)).max(0.0);
            let share = (grip_pose(sim).0 - ctx.start_pos_m).dot(&into) / PITCH_OVER_M;
            Goal::at(at3(sim, FINGER_HALF_M - PUSH_LEAD_M.min(0.02 + left), PUSH_UP_M), GRIPPER_OPEN).slow((0.1 + 4.0 * left).min(0.5)).rotated(pitched(share))
        })
        .until(move |sim, ctx| done(sim) || (ctx.steps > 40 && hand_speed(sim) < STILL_M_PER_S / 2.0))
        .max_steps(500),
        Phase::new("back_out", move |_, ctx| Goal::at(ctx.start_pos_m - into * 0.06, GRIPPER_OPEN).rotated(end_rot)).until_reached(0.015).max_steps(40),
        Phase::new("up", move |sim, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.10, GRIPPER_OPEN).rotated(grip_pose(sim).1)).until_reached(0.02).max_steps(40),
    ]
}
