//! An upright book into a compartment covered from above (the study shelf's upper compartment, 13.5 cm between its
//! boards): held by a pinch from above, the hand cannot follow the book under the board, and the generic placement
//! lowers it onto the board instead. So the book is laid over in the hand and slid in: picked as usual (a pinch across
//! its thickness a little below its top), lifted, turned about world z, then a quarter about the horizontal across the
//! opening in front of it, so that it points into the compartment, and slid in, the hand at the open face. Laid flat
//! where it fits so (its thickness along the opening first, the fingers then closing vertically: the book's weight
//! pulls across the pinch, not about it), let go from a hand as low as the table lets it onto the compartment's floor;
//! otherwise on its long edge (its thickness across the opening first: its width, 10–11 cm, upright), pushed in at
//! the floor's height.
use libero_sim::Simulation;
use nalgebra::{Matrix3, Vector3};

use crate::expert::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, grip_pose, gripper_width_m, rotate_world, rotation_error};
use crate::expert::skills::{carry, extent, pos, xy_dist};
use crate::judge::predicates::SceneIndex;

use super::pan::{SideEntry, side_entry};
use super::stalled;

/// A book (by category) is laid over into a covered compartment.
pub(super) fn is_book(category: &str) -> bool {
    category.contains("book")
}

/// How far in front of the opening (m) the book is turned over, its far end clear of the shelf.
const TURN_CLEAR_M: f64 = 0.02;
/// An object standing with its root this little (m) under a region's top is taken to stand in it.
const IN_MARGIN_M: f64 = 0.01;
/// A laid-over object is let go this far (m) above the drawer's walls.
const DROP_GAP_M: f64 = 0.015;
/// Control steps over which the book is turned over (3 s).
const LAY_OVER_STEPS: f64 = 60.0;
/// The book's far end stops this far (m) short of the compartment's back.
const BACK_GAP_M: f64 = 0.015;
/// Laid flat, the book's grip stops this far (m) short of the region's open side (the hand's front, about level with
/// the grip, stays out of the shelf's face).
const FLAT_GRIP_OUT_M: f64 = 0.02;
/// The hand laid over with its fingers vertical reaches this far (m) below its grip site (its body, 20 cm along the
/// fingers' axis; measured on the study table), and is carried this far above what the book stood on: as low as it
/// goes, so that the lower finger, opened, drops below the floor's edge instead of propping the let-go book, which it
/// then drags back out.
const FLAT_HAND_BELOW_GRIP_M: f64 = 0.1005;
const FLAT_HAND_GAP_M: f64 = 0.003;
/// The laid-over hand's half thickness across the opening (m) and how far its body reaches behind the grip (m).
const FLAT_HAND_HALF_M: f64 = 0.045;
const FLAT_HAND_BEHIND_M: f64 = 0.12;
/// … and opens its fingers at least this wide (m) to let it go.
const FLAT_OPEN_WIDTH_M: f64 = 0.07;
/// A book laid flat is let go from at most this high (m) over the floor.
const FLAT_MAX_DROP_M: f64 = 0.05;
/// The book's lower edge is carried this far (m) above the compartment's floor while it slides in.
const FLOOR_GAP_M: f64 = 0.012;

/// The compartment `region` of `object`'s placement, if it is covered from above and open on a side: how the book
/// enters it (its open face toward the robot base `base_m`). Only where the book, laid over, stands in the compartment with [`FLOOR_GAP_M`] under and over it (the study
/// shelf's lower compartment, 7 cm high, takes no book on its edge).
pub(super) fn entry(sim: &Simulation, index: &SceneIndex, object: usize, region: usize, base_m: Vector3<f64>) -> Option<SideEntry> {
    let height_m = 2.0 * super::region_box(sim, index, region).2;
    let width_m = 2.0 * super::fit::object_footprint(sim, index, object)?.wide_half_m;
    if width_m + 2.0 * FLOOR_GAP_M > height_m {
        return None;
    }
    entry_towards(sim, index, region, base_m)
}

/// The open face of a covered `region` nearest the robot base (not a drawer's: it is entered from above once open,
/// though its back part stays under the cabinet).
pub(super) fn entry_towards(sim: &Simulation, index: &SceneIndex, region: usize, base_m: Vector3<f64>) -> Option<SideEntry> {
    if !index.regions[region].joints.is_empty() {
        return None;
    }
    side_entry(sim, index, region, base_m - super::region_box(sim, index, region).0)
}

/// Pick the book (`object`; grip point `grasp_offset_m` from its root, the hand at `rot`), lay it over and slide it
/// into `region` through the face `e`.
pub(super) fn place_phases(
    sim: &Simulation,
    index: &SceneIndex,
    object: usize,
    region: usize,
    e: &SideEntry,
    (grasp_offset_m, rot): (Vector3<f64>, Matrix3<f64>),
    home: &Matrix3<f64>,
) -> Vec<Phase> {
    let body = index.instances[object].body;
    let root = pos(sim, body);
    let (lo, hi) = extent(sim, index, object);
    let height_m = hi.z - lo.z;
    let below_top_m = hi.z - (root.z + grasp_offset_m.z);
    // the book's width (its collision box's wide horizontal side, not its world box's, which grows with its yaw),
    // upright once it is laid over
    let width_m = super::fit::object_footprint(sim, index, object).map_or((hi.x - lo.x).max(hi.y - lo.y), |f| 2.0 * f.wide_half_m);
    let (c, _, h_z) = super::region_box(sim, index, region);
    let floor_z = c.z - h_z;
    // into the compartment: against its open face's outward direction
    let into = -e.out;
    if let Some(phases) = flat_phases(sim, index, object, region, e, (grasp_offset_m, rot), home) {
        return phases;
    }
    let t = turns(&rot, home, into);
    let laid = t.laid;
    // laid over, the root (the book's bottom face's centre) is its far end, at the grip's height, ahead by
    // (height − depth of the grip below the top)
    let ahead_m = height_m - below_top_m;
    let slide_z = floor_z + width_m / 2.0 + FLOOR_GAP_M;
    let at_back = c + into * (e.half_depth_m - BACK_GAP_M);
    let root_in = Vector3::new(at_back.x, at_back.y, slide_z);
    let root_front = Vector3::new(c.x, c.y, slide_z) - into * (e.half_depth_m + TURN_CLEAR_M);
    // the hand turns the book over with its grip this far out in front and high enough for the hanging book
    let turn_at = root_front - into * ahead_m;
    let turn_z = (floor_z + height_m + 0.05).max(slide_z + 0.10).max(hi.z + 0.05);
    let turn_at = Vector3::new(turn_at.x, turn_at.y, turn_z);
    let mut phases = pick_and_lay_over(body, (grasp_offset_m, rot), &t, turn_at);
    phases.extend(slide_in_phases(body, laid, into, (root_front, root_in), slide_z - FLOOR_GAP_M));
    phases
}

/// The book laid flat instead, where it fits so (`None` where not): turned about z until its thickness lies along
/// the opening's depth, a quarter about the horizontal across it (the fingers then close vertically, the book ahead
/// of the hand with its bottom foremost), slid in at a height where the hand, 21 cm tall along its fingers, clears
/// what the book stood on, its grip [`FLAT_GRIP_OUT_M`] short of the region's open side, and let go to drop onto the
/// floor. Lying flat, the book's weight pulls across the pinch, not about it: laid on its edge, a heavy book pinched
/// near its top (the black book, 43 g, 2.6 cm) turns in the fingers and meets the floor's edge.
fn flat_phases(sim: &Simulation, index: &SceneIndex, object: usize, region: usize, e: &SideEntry, (grasp_offset_m, rot): (Vector3<f64>, Matrix3<f64>), home: &Matrix3<f64>) -> Option<Vec<Phase>> {
    let body = index.instances[object].body;
    let root = pos(sim, body);
    let (lo, hi) = extent(sim, index, object);
    let fp = super::fit::object_footprint(sim, index, object)?;
    let thick_m = 2.0 * fp.narrow_half_m;
    let below_top_m = hi.z - (root.z + grasp_offset_m.z);
    // laid flat, the root (the bottom face's centre) is ahead of the grip by (height − depth of the grip below the
    // top), at the grip's height
    let ahead_m = hi.z - lo.z - below_top_m;
    let (c, r, h_z) = super::region_box(sim, index, region);
    let (floor_z, top_z) = (c.z - h_z, c.z + h_z);
    let into = -e.out;
    // as low as the hand, standing on its fingers' axis, clears what the book stood on
    let grip_z = (lo.z + FLAT_HAND_BELOW_GRIP_M + FLAT_HAND_GAP_M).max(floor_z + thick_m / 2.0 + FLOOR_GAP_M);
    let drop_m = grip_z - thick_m / 2.0 - floor_z;
    let fits = grip_z + thick_m / 2.0 + FLOOR_GAP_M < top_z && drop_m < FLAT_MAX_DROP_M && ahead_m - FLAT_GRIP_OUT_M < 2.0 * e.half_depth_m - BACK_GAP_M;
    if !fits {
        return None;
    }
    // across the opening, the place nearest its middle where the hand, low behind the book, stands over nothing
    // (the yellow book stands in front of the study shelf's middle)
    let across = Vector3::z().cross(&into);
    let reg = &index.regions[region];
    let half_across_m: f64 = (0..3).map(|k| across.dot(&r.column(k)).abs() * reg.half_size_m[k].abs()).sum();
    let room_m = (half_across_m - fp.wide_half_m - 0.01).max(0.0);
    let middle = c - into * e.half_depth_m;
    let others = super::other_boxes(sim, index, object);
    let side = (0..=2 * (room_m / 0.01) as usize)
        .map(|i| middle + across * (if i % 2 == 0 { 0.01 } else { -0.01 } * i.div_ceil(2) as f64))
        .find(|&p| top_along(&others, reg.parent, (p - into * (ahead_m + TURN_CLEAR_M + FLAT_HAND_BEHIND_M), p), FLAT_HAND_HALF_M) < grip_z - FLAT_HAND_BELOW_GRIP_M)?;
    let root_in = Vector3::new(side.x, side.y, grip_z) + into * (ahead_m - FLAT_GRIP_OUT_M);
    let root_front = Vector3::new(side.x, side.y, grip_z) - into * TURN_CLEAR_M;
    // turned over above: the book, hanging below the grip, clears what it stood on (by 10 cm: the hand dips as it
    // turns about z), the compartment's floor, and what stands along its way there
    let turn_at = root_front - into * ahead_m;
    let half_m = 0.5 * (hi.x - lo.x).max(hi.y - lo.y);
    let turn_z = (lo.z + ahead_m + 0.10)
        .max(floor_z + ahead_m + 0.05)
        .max(grip_z + 0.05)
        .max(top_along(&others, None, (root, turn_at), half_m + 0.03) + ahead_m + 0.03);
    // (the shorter turn about z: the longer one, half a turn, throws the hand down onto the table)
    let [t, _] = turns_to(&rot, home, into, into);
    let mut phases = pick_and_lay_over(body, (grasp_offset_m, rot), &t, Vector3::new(turn_at.x, turn_at.y, turn_z));
    let [down, _, _, _, back_out] = slide_in_phases(body, t.laid, into, (root_front, root_in), root_in.z);
    // in by the hand itself, to its stop at the open side and its height (the grip's offset from the root is not the
    // planned one: the hand stops on the book's top edge, and the book sags in the pinch)
    let (laid, grip_in) = (t.laid, Vector3::new(side.x, side.y, grip_z) - into * FLAT_GRIP_OUT_M);
    let slide = Phase::new("slide_in", move |_, _| Goal::at(grip_in, GRIPPER_CLOSED).slow(0.3).rotated(laid))
        .until_reached(0.006)
        .max_steps(150);
    // opened all the way: the lower finger, part open, props the book's near end 1.6 cm over the floor and drags
    // it back out with the hand
    let open = Phase::new("open_wide", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(laid))
        .until(|sim, ctx| ctx.steps >= 10 && gripper_width_m(sim) > FLAT_OPEN_WIDTH_M)
        .max_steps(40);
    phases.extend([down, slide, open, back_out]);
    Some(phases)
}

/// The highest top (world z, m) of the boxes (instance, min, max; but `skip`'s) within `reach_m` of the horizontal
/// way from `a` to `b` (−∞ where none is).
fn top_along(boxes: &[(usize, Vector3<f64>, Vector3<f64>)], skip: Option<usize>, (a, b): (Vector3<f64>, Vector3<f64>), reach_m: f64) -> f64 {
    const SAMPLES: usize = 24;
    boxes
        .iter()
        .filter(|(i, lo, hi)| {
            Some(*i) != skip
                && (0..=SAMPLES).any(|k| {
                    let p = a + (b - a) * (k as f64 / SAMPLES as f64);
                    let dx = (lo.x - p.x).max(p.x - hi.x).max(0.0);
                    let dy = (lo.y - p.y).max(p.y - hi.y).max(0.0);
                    dx.hypot(dy) <= reach_m
                })
        })
        .map(|(_, _, hi)| hi.z)
        .fold(f64::NEG_INFINITY, f64::max)
}

/// A tall object into an open drawer it cannot stand in (the ketchup, 14.5 cm tall, its root 7.2 cm above its bottom,
/// into a drawer region 6 cm high): laid over above the drawer, pointing along the drawer's width away from the
/// robot, and let go with its lowest point [`DROP_GAP_M`] over the drawer's walls, its root over `to` (the drawer's
/// front part, as a placement aims). `None` where it stands in the region, or does not fit in it lying.
pub(super) fn drawer_drop(
    sim: &Simulation,
    index: &SceneIndex,
    object: usize,
    region: usize,
    (grasp_offset_m, rot): (Vector3<f64>, Matrix3<f64>),
    home: &Matrix3<f64>,
    (to, base_m): (Vector3<f64>, Vector3<f64>),
) -> Option<Vec<Phase>> {
    let body = index.instances[object].body;
    let root = pos(sim, body);
    let (lo, hi) = extent(sim, index, object);
    let reg = &index.regions[region];
    let (c, r, h_z) = super::region_box(sim, index, region);
    if root.z - lo.z < 2.0 * h_z - IN_MARGIN_M {
        return None;
    }
    // along the region's longer horizontal axis, away from the robot
    let k = (0..3).filter(|&k| r[(2, k)].abs() < 0.3).max_by(|&a, &b| reg.half_size_m[a].abs().total_cmp(&reg.half_size_m[b].abs()))?;
    let along = Vector3::new(r[(0, k)], r[(1, k)], 0.0).try_normalize(1e-9)?;
    let into = if along.dot(&(c - base_m)) >= 0.0 { along } else { -along };
    if hi.z - lo.z > 2.0 * reg.half_size_m[k].abs() {
        return None;
    }
    let t = turns(&rot, home, into);
    let laid = t.laid;
    // the root's offset from the grip once laid over (turned with the hand about the grip), and the lowest point's
    // from the root (the object's box corners turned alike)
    let spin = t.laid * rot.transpose();
    let root_from_grip = spin * -grasp_offset_m;
    let lowest_from_root = (0..8)
        .map(|i| {
            let corner = Vector3::new(if i & 1 == 0 { lo.x } else { hi.x }, if i & 2 == 0 { lo.y } else { hi.y }, if i & 4 == 0 { lo.z } else { hi.z });
            (spin * (corner - root)).z
        })
        .fold(f64::INFINITY, f64::min);
    let root_at = Vector3::new(to.x, to.y, c.z + h_z + DROP_GAP_M - lowest_from_root);
    // laid over where the hanging object clears the drawer, then lowered to the drop
    let turn_z = (c.z + h_z + (root.z + grasp_offset_m.z - lo.z) + 0.05).max(root_at.z - root_from_grip.z + 0.05);
    let turn_at = Vector3::new(root_at.x - root_from_grip.x, root_at.y - root_from_grip.y, turn_z);
    let mut phases = pick_and_lay_over(body, (grasp_offset_m, rot), &t, turn_at);
    phases.extend([
        Phase::new("down_to_drop", move |sim, _| Goal::at(carry(sim, body, root_at), GRIPPER_CLOSED).slow(0.3).rotated(laid))
            .until(move |sim, ctx| (pos(sim, body) - root_at).norm() < 0.01 || (ctx.steps > 30 && stalled(sim, ctx)))
            .max_steps(200),
        Phase::new("open", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(laid)).for_steps(10),
        Phase::new("back_off", move |_, ctx| Goal::at(ctx.start_pos_m - into * 0.06 + Vector3::z() * 0.12, GRIPPER_OPEN).rotated(laid))
            .until_reached(0.02)
            .max_steps(60),
    ]);
    Some(phases)
}

/// A held object (a mug pinched at its rim) into a compartment covered from above (the microwave, 14.4 cm high
/// inside: a mug with the hand over it does not pass under its roof): laid over on its side in front of the opening,
/// its bottom ahead, and slid in until its far end is 1.5 cm from the back, its lowest point 1 cm over the floor.
/// `None` where `region` is not covered, or the object does not fit in it lying so.
pub(super) fn lay_in_held(sim: &Simulation, index: &SceneIndex, object: usize, region: usize, base_m: Vector3<f64>, home: &Matrix3<f64>) -> Option<Vec<Phase>> {
    let e = entry_towards(sim, index, region, base_m)?;
    let into = -e.out;
    let body = index.instances[object].body;
    let root = pos(sim, body);
    let (grip, rot) = grip_pose(sim);
    let (lo, hi) = extent(sim, index, object);
    let (c, _, h_z) = super::region_box(sim, index, region);
    let floor_z = c.z - h_z;
    let t = turns(&rot, home, into);
    let laid = t.laid;
    // the object's box corners from its root, turned with the hand about the grip
    let spin = t.laid * rot.transpose();
    let corners: Vec<Vector3<f64>> = (0..8)
        .map(|i| spin * (Vector3::new(if i & 1 == 0 { lo.x } else { hi.x }, if i & 2 == 0 { lo.y } else { hi.y }, if i & 4 == 0 { lo.z } else { hi.z }) - root))
        .collect();
    let lowest = corners.iter().map(|p| p.z).fold(f64::INFINITY, f64::min);
    let highest = corners.iter().map(|p| p.z).fold(f64::NEG_INFINITY, f64::max);
    let ahead = corners.iter().map(|p| p.dot(&into)).fold(f64::NEG_INFINITY, f64::max);
    if highest - lowest + FLOOR_GAP_M > 2.0 * h_z {
        return None;
    }
    let root_from_grip = spin * (root - grip);
    let root_z = floor_z + FLOOR_GAP_M - lowest;
    let root_in = Vector3::new(c.x, c.y, root_z) + into * (e.half_depth_m - BACK_GAP_M - ahead);
    let root_front = Vector3::new(c.x, c.y, root_z) - into * (e.half_depth_m + TURN_CLEAR_M + ahead);
    let turn_at = root_front - root_from_grip;
    let turn_at = Vector3::new(turn_at.x, turn_at.y, turn_at.z.max(grip.z));
    let mut phases = vec![];
    phases.extend(lay_over_phases(&t, turn_at));
    phases.extend(slide_in_phases(body, laid, into, (root_front, root_in), root_z - FLOOR_GAP_M));
    Some(phases)
}

/// Down in front of the opening (root at `root_front`), in (root at `root_in`), down until the root is at
/// `rest_z` or stalls, let go, back out along `into`.
fn slide_in_phases(body: usize, laid: Matrix3<f64>, into: Vector3<f64>, (root_front, root_in): (Vector3<f64>, Vector3<f64>), rest_z: f64) -> [Phase; 5] {
    [
        Phase::new("down_to_opening", move |sim, _| Goal::at(carry(sim, body, root_front), GRIPPER_CLOSED).slow(0.4).rotated(laid))
            .until(move |sim, _| (pos(sim, body) - root_front).norm() < 0.012)
            .max_steps(200),
        Phase::new("slide_in", move |sim, _| Goal::at(carry(sim, body, root_in), GRIPPER_CLOSED).slow(0.3).rotated(laid))
            .until(move |sim, ctx| xy_dist(pos(sim, body), root_in) < 0.01 || (ctx.steps > 60 && stalled(sim, ctx)))
            .max_steps(200),
        Phase::new("lower", move |sim, _| Goal::at(carry(sim, body, root_in - Vector3::z() * 0.01), GRIPPER_CLOSED).slow(0.3).rotated(laid))
            .until(move |sim, ctx| pos(sim, body).z < rest_z + 0.004 || stalled(sim, ctx))
            .max_steps(40),
        Phase::new("open", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(laid)).for_steps(10),
        Phase::new("back_out", move |_, ctx| Goal::at(ctx.start_pos_m - into * 0.14, GRIPPER_OPEN).rotated(laid)).until_reached(0.02).max_steps(60),
    ]
}

/// The hand's orientations of a laying over: turned about z so the fingers close across `into` (the shorter way),
/// then a quarter turn about `axis` that brings the hand's pointing direction (down) onto `into`.
#[derive(Clone, Copy)]
struct Turns {
    yawed: Matrix3<f64>,
    axis: Vector3<f64>,
    laid: Matrix3<f64>,
}

fn turns(rot: &Matrix3<f64>, home: &Matrix3<f64>, into: Vector3<f64>) -> Turns {
    let [a, b] = turns_to(rot, home, into, Vector3::z().cross(&into));
    // of the two, the one whose laid-over hand is farther from home: laid over the other way the last wrist joint
    // winds onto its limit (KITCHEN_SCENE5's ketchup: joint 7 at 2.9 rad, the hand thrown 21 cm up); the study
    // shelf's book goes in either way
    if angle_between(&a.laid, home) > angle_between(&b.laid, home) { a } else { b }
}

/// The two ways (π apart about z, the shorter first) of a laying over whose fingers close along `fingers_to`
/// (horizontal) before the quarter turn: across `into` lays a pinched book on its long edge, along `into` lays it
/// flat (the fingers then close vertically).
fn turns_to(rot: &Matrix3<f64>, home: &Matrix3<f64>, into: Vector3<f64>, fingers_to: Vector3<f64>) -> [Turns; 2] {
    // (the hand at home opens its fingers along world y)
    let fingers = rot * home.transpose() * Vector3::y();
    let fingers_h = Vector3::new(fingers.x, fingers.y, 0.0).try_normalize(1e-9).unwrap_or(Vector3::x());
    let turn = {
        let d = fingers_to.y.atan2(fingers_to.x) - fingers_h.y.atan2(fingers_h.x);
        d - std::f64::consts::PI * (d / std::f64::consts::PI).round()
    };
    let axis = (-Vector3::z()).cross(&into);
    [turn, turn - std::f64::consts::PI * turn.signum()].map(|turn| {
        let yawed = rotate_world(rot, Vector3::z(), turn);
        Turns { yawed, axis, laid: rotate_world(&yawed, axis, std::f64::consts::FRAC_PI_2) }
    })
}

/// The angle (rad) of the rotation from `b` to `a`.
fn angle_between(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    nalgebra::Rotation3::from_matrix_unchecked(a * b.transpose()).angle()
}

/// Pick the object by its pinch (`grasp_offset_m` from its root, the hand at `rot`), lift it until the grip is at
/// `turn_at`'s height, carry it there turning it about z, and lay it over there.
fn pick_and_lay_over(body: usize, (grasp_offset_m, rot): (Vector3<f64>, Matrix3<f64>), t: &Turns, turn_at: Vector3<f64>) -> Vec<Phase> {
    let turn_z = turn_at.z;
    let mut lift_rise: Option<f64> = None;
    let [above, down, close] = super::pick_phases(body, grasp_offset_m, rot);
    let mut phases = vec![
        above,
        down,
        close,
        Phase::new("lift", move |sim, ctx| {
            let rise = *lift_rise.get_or_insert_with(|| (turn_z - grip_pose(sim).0.z).max(0.05));
            Goal::at(ctx.start_pos_m + Vector3::z() * rise, GRIPPER_CLOSED).slow(0.6).rotated(rot)
        })
        .until(move |sim, _| grip_pose(sim).0.z > turn_z - 0.015)
        .max_steps(120),
    ];
    phases.extend(lay_over_phases(t, turn_at));
    phases
}

/// Carry the held object to `turn_at` (the hand's position) turning it about z, then lay it over there.
fn lay_over_phases(t: &Turns, turn_at: Vector3<f64>) -> [Phase; 2] {
    let Turns { yawed, axis, laid } = *t;
    [
        Phase::new("to_turn_point", move |_, _| Goal::at(turn_at, GRIPPER_CLOSED).slow(0.5).rotated(yawed))
            .until(move |sim, _| (grip_pose(sim).0 - turn_at).norm() < 0.015 && rotation_error(sim, &yawed) < 0.08)
            .max_steps(250),
        // the quarter turn led gradually (a goal a quarter turn away asks for the wrist's full speed, and the held
        // object's weight swings the arm off its way)
        Phase::new("lay_over", move |_, ctx| {
            let share = (f64::from(ctx.steps) / LAY_OVER_STEPS).min(1.0);
            Goal::at(turn_at, GRIPPER_CLOSED).slow(0.4).rotated(rotate_world(&yawed, axis, share * std::f64::consts::FRAC_PI_2))
        })
        .until(move |sim, ctx| f64::from(ctx.steps) >= LAY_OVER_STEPS && rotation_error(sim, &laid) < 0.06)
        .max_steps(200),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Laid flat (the fingers first turned along `into`), the hand points `into` with its fingers vertical, whatever
    /// the grasp's yaw; the first of the two ways is the shorter turn about z.
    #[test]
    fn laid_flat_the_hand_points_into_the_opening_with_its_fingers_vertical() {
        let home = Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0);
        for grasp_yaw in [0.0, 0.4, -1.2, 2.0] {
            let rot = rotate_world(&home, Vector3::z(), grasp_yaw);
            for into in [Vector3::x(), Vector3::y(), Vector3::new(-0.6, 0.8, 0.0)] {
                let [t, other] = turns_to(&rot, &home, into, into);
                let pointing = t.laid * rot.transpose() * -Vector3::z();
                assert!((pointing - into).norm() < 1e-9, "yaw {grasp_yaw}, into {into:?}: points {pointing:?}");
                let fingers = t.laid * home.transpose() * Vector3::y();
                assert!((fingers.z.abs() - 1.0).abs() < 1e-9, "fingers {fingers:?}");
                assert!(angle_between(&t.yawed, &rot) <= angle_between(&other.yawed, &rot) + 1e-9);
            }
        }
    }

    /// Laid over, the hand points `into` (its pointing direction: world down under its grasp orientation) with its
    /// fingers level and across `into`, whatever the grasp's yaw.
    #[test]
    fn laid_over_the_hand_points_into_the_opening_with_its_fingers_level_and_across() {
        // a hand pointing down, fingers along world y (the stock expert's start)
        let home = Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0);
        for grasp_yaw in [0.0, 0.4, -1.2, 2.0] {
            let rot = rotate_world(&home, Vector3::z(), grasp_yaw);
            for into in [Vector3::x(), Vector3::y(), Vector3::new(-0.6, 0.8, 0.0)] {
                let t = turns(&rot, &home, into);
                let pointing = t.laid * rot.transpose() * -Vector3::z();
                assert!((pointing - into).norm() < 1e-9, "yaw {grasp_yaw}, into {into:?}: points {pointing:?}");
                let fingers = t.laid * home.transpose() * Vector3::y();
                assert!(fingers.z.abs() < 1e-9 && fingers.dot(&into).abs() < 1e-9, "fingers {fingers:?}");
                // the yaw turn keeps the hand pointing down
                assert!((t.yawed * rot.transpose() * -Vector3::z() + Vector3::z()).norm() < 1e-9);
            }
        }
    }
}
