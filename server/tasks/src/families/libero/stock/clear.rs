//! An object under a drawer's overhang: a placement into a drawer whose open drawer would stand over the object
//! (the bowl in front of the top drawer) first sets the object down clear of the drawer's sweep, the drawer shut
//! first if it is open, so that neither the pull nor the pick later meets the open drawer (a diagonal approach
//! knocks it half shut, a straight one leaves a finger on it, a pinch on another side lets the bowl slip, its far
//! rim caught under it).
use libero_sim::Simulation;
use libero_sim::mujoco_rs::prelude::MjtObjBase;
use nalgebra::{Matrix3, Vector3};

use super::{Build, Ctx, Done, Grasp, Planned, Slot, Step, Target, place_phases, same_articulation, with_rise};
use crate::TasksError;
use crate::expert::SceneRefs;
use crate::expert::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, body_dir, body_point, grip_pose, mat3, open_along, rotation_error, vec3};
use crate::expert::skills::{extent, into_drawer, pos, push_drawer};
use crate::judge::predicates::SceneIndex;
use std::sync::Arc;

/// Room the hand needs between an object and the open drawer's footprint (m): less counts as under it.
const HAND_CLEARANCE_M: f64 = 0.04;
/// Half the hand's span along its fingers' axis (m): the Panda hand is about 20 cm across there, so a hand whose
/// fingers open toward the drawer needs this much room, not [`HAND_CLEARANCE_M`] (KITCHEN_SCENE10: the pudding,
/// pinched across its 4.6 cm side, 6 cm in front of the open drawer; the hand came down onto the drawer's front).
const HAND_HALF_SPAN_M: f64 = 0.105;
/// The spot an object is set down at keeps this much more than [`hand_margin`] (the set-down's error).
const SET_DOWN_SLACK_M: f64 = 0.02;
/// Room kept between the set-down object and anything else standing on the table (m).
const NEIGHBOUR_CLEARANCE_M: f64 = 0.03;
/// How far inside the table's edge the object stays (m).
const TABLE_EDGE_M: f64 = 0.05;
/// The farthest the object is moved (m), and the search's steps along a direction.
const MAX_SHIFT_M: f64 = 0.25;
const SHIFT_STEP_M: f64 = 0.01;
/// Directions the search tries (evenly around the object).
const DIRECTIONS: usize = 24;
/// The spot's horizontal distance from the robot base stays within this (m): within the arm's comfortable reach.
const REACH_M: (f64, f64) = (0.35, 0.78);
/// A drawer whose slide reads below this (m) is open enough to stand over the object: it is pushed shut first.
const SHUT_ENOUGH_Q_M: f64 = -0.02;
/// Pushing the drawer shut aims here (m; closed reads q > 0).
const SHUT_Q_M: f64 = 0.001;
/// The hand turns to push the drawer shut this far above the handle's height (m).
const HIGH_APPROACH_M: f64 = 0.15;
/// Where the hand starts every stock episode, from the robot base (m).
const START_FROM_BASE_M: [f64; 3] = [0.45, 0.0, 0.27];

/// A drawer's footprint in its own horizontal frame: along `out` (the direction it opens) and `across`, relative
/// to the drawer body's origin; its lowest point; and how far it moves out to fully open / in to shut from now.
struct Footprint {
    origin_m: Vector3<f64>,
    out: Vector3<f64>,
    across: Vector3<f64>,
    out_range_m: (f64, f64),
    across_range_m: (f64, f64),
    bottom_z_m: f64,
    to_open_m: f64,
    to_shut_m: f64,
}

/// The drawer body of a drawer region: (body, slide joint id).
fn drawer_body(sim: &Simulation, index: &SceneIndex, region: usize) -> Option<(usize, usize)> {
    let joint = index.regions[region].joints.first()?;
    let j = sim.model().name_to_id(MjtObjBase::mjOBJ_JOINT, &joint.name)?;
    Some((sim.model().jnt_bodyid()[j] as usize, j))
}

fn footprint(sim: &Simulation, index: &SceneIndex, region: usize) -> Option<Footprint> {
    let (body, j) = drawer_body(sim, index, region)?;
    let cabinet = index.regions[region].parent?;
    let (model, data) = (sim.model(), sim.data());
    let q = data.qpos()[index.regions[region].joints.first()?.qpos_adr];
    let [q_min, q_max] = model.jnt_range()[j];
    // the slide opens toward its lower limit: the drawer moves along −axis as q falls
    let axis = vec3(&data.xaxis()[j]);
    let out = Vector3::new(-axis.x, -axis.y, 0.0).try_normalize(1e-9)?;
    let across = Vector3::z().cross(&out);
    let origin = pos(sim, body);
    let (aabb, geom_body) = (model.geom_aabb(), model.geom_bodyid());
    let (mut u, mut v, mut bottom) = ((f64::INFINITY, f64::NEG_INFINITY), (f64::INFINITY, f64::NEG_INFINITY), f64::INFINITY);
    for g in index.contact_geoms(cabinet).filter(|&g| geom_body[g] as usize == body) {
        let (c, h) = (Vector3::new(aabb[g][0], aabb[g][1], aabb[g][2]), Vector3::new(aabb[g][3], aabb[g][4], aabb[g][5]));
        let (p, r) = (vec3(&data.geom_xpos()[g]), mat3(&data.geom_xmat()[g]));
        for k in 0..8 {
            let s = Vector3::new(if k & 1 == 0 { -1.0 } else { 1.0 }, if k & 2 == 0 { -1.0 } else { 1.0 }, if k & 4 == 0 { -1.0 } else { 1.0 });
            let corner = p + r * (c + h.component_mul(&s)) - origin;
            let (cu, cv) = (corner.dot(&out), corner.dot(&across));
            u = (u.0.min(cu), u.1.max(cu));
            v = (v.0.min(cv), v.1.max(cv));
            bottom = bottom.min(corner.z + origin.z);
        }
    }
    u.0.is_finite().then_some(Footprint {
        origin_m: origin,
        out,
        across,
        out_range_m: u,
        across_range_m: v,
        bottom_z_m: bottom,
        to_open_m: q - q_min,
        to_shut_m: q - q_max,
    })
}

/// Whether the box `lo`–`hi` (an object standing in front of the drawer, below it) lies under the open drawer's
/// footprint or within `margin_m` of it.
fn box_under(f: &Footprint, lo: Vector3<f64>, hi: Vector3<f64>, margin_m: f64) -> bool {
    if hi.z > f.bottom_z_m {
        return false;
    }
    let (mut u, mut v) = ((f64::INFINITY, f64::NEG_INFINITY), (f64::INFINITY, f64::NEG_INFINITY));
    for (x, y) in [(lo.x, lo.y), (lo.x, hi.y), (hi.x, lo.y), (hi.x, hi.y)] {
        let d = Vector3::new(x - f.origin_m.x, y - f.origin_m.y, 0.0);
        u = (u.0.min(d.dot(&f.out)), u.1.max(d.dot(&f.out)));
        v = (v.0.min(d.dot(&f.across)), v.1.max(d.dot(&f.across)));
    }
    // beyond the shut drawer's front (not inside the cabinet), short of the open front plus the margin
    u.1 > f.out_range_m.1 + f.to_shut_m
        && u.0 < f.out_range_m.1 + f.to_open_m + margin_m
        && v.1 > f.across_range_m.0 - margin_m
        && v.0 < f.across_range_m.1 + margin_m
}

/// Whether `object` stands where `region`'s drawer, opened, would be over it (or too close for the hand).
fn under_open_drawer(sim: &Simulation, index: &SceneIndex, object: usize, region: usize) -> bool {
    let (lo, hi) = extent(sim, index, object);
    footprint(sim, index, region).is_some_and(|f| box_under(&f, lo, hi, hand_margin(sim, index, object, &f)))
}

/// The room the hand needs round `object` beside the drawer `f`: its fingers open across the drawer for a bowl or
/// mug (pinched there: [`drawer_pinch`]), else across the object's narrow side.
fn hand_margin(sim: &Simulation, index: &SceneIndex, object: usize, f: &Footprint) -> f64 {
    let category = &index.instances[object].category;
    let fingers = if super::grasp::rim_grasped(category) { f.across } else { super::narrow_dir(sim, index, object) };
    HAND_CLEARANCE_M.max(fingers.dot(&f.out).abs() * HAND_HALF_SPAN_M)
}

/// Before the opening of each drawer something is placed into, a step that sets that object down clear of the
/// drawer (skipped when it is clear already).
pub(super) fn insert_clears(index: &SceneIndex, steps: &mut Vec<Planned>) {
    let into_drawers: Vec<(usize, usize)> = steps
        .iter()
        .filter_map(|p| match p.step {
            Step::Place { object, target: Target::Region { region, inside: true } } if super::container_of(index, Target::Region { region, inside: true }).is_some_and(|c| matches!(c, Step::Drawer { .. })) => {
                Some((object, region))
            }
            _ => None,
        })
        .collect();
    for (object, region) in into_drawers {
        let opening = Step::Drawer { region, open: true };
        if let Some(k) = steps.iter().position(|p| matches!(p.step, Step::Drawer { open: true, .. }) && same_articulation(index, &p.step, &opening)) {
            steps.insert(k, Planned { step: Step::Place { object, target: Target::Aside { region } }, atom: None });
        }
    }
}

/// Before a plate is pushed to its region, a step for each other movable object that sets it down clear of the
/// plate's way (skipped when it is clear already): the stock scene's cream cheese stands where the plate must come to
/// rest.
pub(super) fn insert_path_clears(index: &SceneIndex, steps: &mut Vec<Planned>) {
    let pushes: Vec<(usize, usize)> = steps
        .iter()
        .filter_map(|p| match p.step {
            Step::Place { object, target: Target::Region { region, .. } } if index.instances[object].category == "plate" => Some((object, region)),
            _ => None,
        })
        .collect();
    for (mover, region) in pushes {
        let Some(k) = steps.iter().position(|p| matches!(p.step, Step::Place { object, .. } if object == mover)) else { continue };
        let movable = (0..index.instances.len()).filter(|&i| i != mover && !index.instances[i].is_fixture && !is_ground(&index.instances[i].category));
        let clears: Vec<Planned> = movable.map(|object| Planned { step: Step::Place { object, target: Target::OffPath { mover, region } }, atom: None }).collect();
        steps.splice(k..k, clears);
    }
}

/// Room kept between a pushed plate's rim and what stands beside its way (m), and the more a set-down keeps (its
/// error): small, because the stock goal scene is crowded (the bowl has 3 cm between the plate's way and the bottle).
const PATH_CLEARANCE_M: f64 = 0.01;
const PATH_SET_DOWN_SLACK_M: f64 = 0.01;

/// Whether the box `lo`–`hi` comes within `margin_m` of the way `mover` sweeps from where it stands to `region`'s
/// centre (its footprint taken as the circle round its widest side).
fn box_in_path(sim: &Simulation, index: &SceneIndex, mover: usize, region: usize, lo: Vector3<f64>, hi: Vector3<f64>, margin_m: f64) -> bool {
    let (ml, mh) = extent(sim, index, mover);
    let radius_m = (mh.x - ml.x).max(mh.y - ml.y) / 2.0;
    let from = pos(sim, index.instances[mover].body);
    let to = vec3(&sim.data().site_xpos()[index.regions[region].site]);
    let (a, d) = (Vector3::new(from.x, from.y, 0.0), Vector3::new(to.x - from.x, to.y - from.y, 0.0));
    let c = Vector3::new((lo.x + hi.x) / 2.0, (lo.y + hi.y) / 2.0, 0.0);
    let t = if d.norm_squared() < 1e-12 { 0.0 } else { ((c - a).dot(&d) / d.norm_squared()).clamp(0.0, 1.0) };
    // the object's footprint as a circle round its widest side (a bowl's own; the margin covers a box's corners)
    let half_m = (hi.x - lo.x).max(hi.y - lo.y) / 2.0;
    (c - (a + d * t)).norm() < radius_m + half_m + margin_m
}

/// A clearing step is done when its object is clear of the open drawer, or of the pushed plate's way.
pub(super) fn clear_done(index: &Arc<SceneIndex>, step: &Step) -> Option<Done> {
    let index = index.clone();
    match *step {
        Step::Place { object, target: Target::Aside { region } } => Some(Box::new(move |sim| !under_open_drawer(sim, &index, object, region))),
        Step::Place { object, target: Target::OffPath { mover, region } } => Some(Box::new(move |sim| {
            let (lo, hi) = extent(sim, &index, object);
            !box_in_path(sim, &index, mover, region, lo, hi, PATH_CLEARANCE_M)
        })),
        _ => None,
    }
}

/// Where to set `object` down clear of `region`'s open drawer: its root's target (world) and the root's carry
/// height. The nearest spot clear of the drawer, of everything else on the table and of the table's edge, within
/// reach; the object stays where it is when none is found.
pub(super) fn aside_target(sim: &Simulation, ctx: &Ctx, object: usize, region: usize) -> (Vector3<f64>, f64) {
    let root = pos(sim, ctx.index.instances[object].body);
    match footprint(sim, &ctx.index, region) {
        Some(f) => {
            let margin_m = hand_margin(sim, &ctx.index, object, &f) + SET_DOWN_SLACK_M;
            set_down_spot(sim, ctx, object, |a, b| box_under(&f, a, b, margin_m))
        }
        None => (root + Vector3::z() * 0.012, root.z + 0.06),
    }
}

/// Where to set `object` down clear of the way `mover` is pushed to `region` (as [`aside_target`]).
pub(super) fn off_path_target(sim: &Simulation, ctx: &Ctx, object: usize, mover: usize, region: usize) -> (Vector3<f64>, f64) {
    let index = ctx.index.clone();
    set_down_spot(sim, ctx, object, move |a, b| box_in_path(sim, &index, mover, region, a, b, PATH_CLEARANCE_M + PATH_SET_DOWN_SLACK_M))
}

/// The nearest spot for `object` where `blocked` (its box there) is false, clear of everything else on the table
/// and of the table's edge, within reach: its root's target and carry height (where it stands when none is found).
fn set_down_spot(sim: &Simulation, ctx: &Ctx, object: usize, blocked: impl Fn(Vector3<f64>, Vector3<f64>) -> bool) -> (Vector3<f64>, f64) {
    let index = &ctx.index;
    let root = pos(sim, index.instances[object].body);
    let stay = (root + Vector3::z() * 0.012, root.z + 0.06);
    let (lo, hi) = extent(sim, index, object);
    let others: Vec<(Vector3<f64>, Vector3<f64>)> = (0..index.instances.len())
        .filter(|&i| i != object && !is_ground(&index.instances[i].category))
        .map(|i| extent(sim, index, i))
        .collect();
    let table = (0..index.instances.len()).find(|&i| index.instances[i].category.contains("table")).map(|i| extent(sim, index, i));
    let base = ctx.base_m;
    let reach = |p: Vector3<f64>| (p.x - base.x).hypot(p.y - base.y);
    let fits = |d: Vector3<f64>| {
        let (a, b) = (lo + d, hi + d);
        let c = (a + b) / 2.0;
        !blocked(a, b)
            && (REACH_M.0..=REACH_M.1).contains(&reach(c))
            && table.is_none_or(|(tl, th)| a.x > tl.x + TABLE_EDGE_M && a.y > tl.y + TABLE_EDGE_M && b.x < th.x - TABLE_EDGE_M && b.y < th.y - TABLE_EDGE_M)
            && others.iter().all(|(ol, oh)| {
                let m = NEIGHBOUR_CLEARANCE_M;
                a.x > oh.x + m || b.x < ol.x - m || a.y > oh.y + m || b.y < ol.y - m
            })
    };
    let mut best: Option<(f64, Vector3<f64>)> = None;
    let steps = (MAX_SHIFT_M / SHIFT_STEP_M).round() as usize;
    for k in 0..DIRECTIONS {
        let a = std::f64::consts::TAU * k as f64 / DIRECTIONS as f64;
        let dir = Vector3::new(a.cos(), a.sin(), 0.0);
        if let Some(d) = (1..=steps).map(|s| dir * (s as f64 * SHIFT_STEP_M)).find(|&d| fits(d)) {
            // the shortest move, a spot farther from the robot than now counting double
            let cost = d.norm() + (reach(root + d) - reach(root)).max(0.0);
            if best.is_none_or(|(c, _)| cost < c) {
                best = Some((cost, d));
            }
        }
    }
    match best {
        Some((_, d)) => (root + d + Vector3::z() * 0.012, root.z + 0.06),
        None => stay,
    }
}

/// What the objects stand on (the table, the floor): not in the way of a set-down.
fn is_ground(category: &str) -> bool {
    category.contains("table") || category == "floor"
}

/// The clearing step: the drawer pushed shut if it is open, then `object` picked and set down clear of it.
pub(super) fn aside_builder(refs: &SceneRefs, index: &SceneIndex, object: usize, region: usize) -> Result<Build, TasksError> {
    let joint = index.regions[region].joints.first().ok_or_else(|| TasksError::Scene("drawer region without a joint".into()))?;
    let (q_adr, j) = refs.joint(&joint.name)?;
    let drawer = refs.model.jnt_bodyid()[j] as usize;
    let handle = super::drawer_handle(index, region).unwrap_or(crate::expert::skills::TOP_HANDLE_LOCAL_M);
    let category = index.instances[object].category.clone();
    Ok(Box::new(move |sim, ctx, home| {
        let mut phases = Vec::new();
        if sim.data().qpos()[q_adr] < SHUT_ENOUGH_Q_M {
            // the hand turns into the drawer high above its front and comes down to it: a diagonal approach at the
            // handle's height sweeps the wrist through what stands in front of the cabinet (a bottle)
            let front = move |sim: &Simulation| {
                body_point(sim, drawer, handle) + body_dir(sim, drawer, [0.0, -1.0, 0.0]) * 0.10 + Vector3::z() * HIGH_APPROACH_M
            };
            let home_rot = *home;
            let turned = move |sim: &Simulation| into_drawer(body_dir(sim, drawer, [0.0, -1.0, 0.0]), &home_rot);
            phases.push(
                Phase::new("high_before_drawer", move |sim, _| Goal::at(front(sim), GRIPPER_CLOSED).rotated(turned(sim)))
                    .until(move |sim, _| (grip_pose(sim).0 - front(sim)).norm() < 0.02 && rotation_error(sim, &turned(sim)) < 0.1)
                    .max_steps(150),
            );
            push_drawer(&mut phases, drawer, handle, q_adr, SHUT_Q_M);
            phases = with_rise(phases);
            // back to where the hand starts, as it starts: from the push's pose, the reach for the object stretches
            // the arm onto its elbow limit (KITCHEN_SCENE5: the hand stuck 4 cm short of the bowl's rim)
            phases.push(back_to_start(ctx, home));
        }
        phases.extend(place_phases(sim, ctx, home, object, &category, Target::Aside { region }, Slot { k: 0, n: 1 }, false));
        phases
    }))
}

/// The hand back where it starts every episode, turned as it starts: after working a drawer's handle, the reach
/// for an object beyond it otherwise stretches the arm onto its elbow limit.
pub(super) fn back_to_start(ctx: &Ctx, home: &Matrix3<f64>) -> Phase {
    let (start, rot) = (ctx.base_m + Vector3::from(START_FROM_BASE_M), *home);
    Phase::new("back_to_start", move |_, _| Goal::at(start, GRIPPER_OPEN).rotated(rot)).until_reached(0.02).max_steps(120)
}

/// The drawer region a placement goes into, if it does.
pub(super) fn drawer_target(index: &SceneIndex, target: Target) -> Option<usize> {
    match target {
        Target::Region { region, inside: true } if index.regions[region].joints.len() == 1 && index.regions[region].parent.is_some() => Some(region),
        _ => None,
    }
}

/// A round bowl or mug going into a drawer is pinched at its rim on the side across the drawer (the hand beside it
/// in the drawer's width, not against its front or back wall), on the side away from the robot.
#[allow(clippy::too_many_arguments)] // the placement's target and the object's state as `place_phases` has them
pub(super) fn drawer_pinch(
    sim: &Simulation,
    ctx: &Ctx,
    target: Target,
    category: &str,
    root: Vector3<f64>,
    lo: Vector3<f64>,
    hi: Vector3<f64>,
    home: &Matrix3<f64>,
) -> Option<Grasp> {
    const ROUND_RATIO: f64 = 0.8;
    if !(category.contains("bowl") || category.contains("mug") || category.contains("cup")) {
        return None;
    }
    let f = footprint(sim, &ctx.index, drawer_target(&ctx.index, target)?)?;
    let half = (hi - lo) / 2.0;
    if half.x.min(half.y) < ROUND_RATIO * half.x.max(half.y) {
        return None;
    }
    let centre = (lo + hi) / 2.0;
    let away = Vector3::new(centre.x - ctx.base_m.x, centre.y - ctx.base_m.y, 0.0);
    let axis = if f.across.dot(&away) >= 0.0 { f.across } else { -f.across };
    let r = half.x * axis.x.abs() + half.y * axis.y.abs();
    let rim = Vector3::new(centre.x, centre.y, hi.z - 0.014) + axis * (r - 0.008);
    Some(Grasp { offset_m: rim - root, rot: open_along(home, axis) })
}

/// A placement into a drawer first rises straight up to its carry height (root at `carry_z_m`), so the carry that
/// follows stays level over the drawer's front instead of climbing into it.
pub(super) fn rise_before_carry(index: &SceneIndex, target: Target, body: usize, carry_z_m: f64, phases: &mut Vec<Phase>) {
    if drawer_target(index, target).is_none() {
        return;
    }
    let Some(k) = phases.iter().position(|p| p.name == "carry_over_target") else { return };
    let rise = Phase::new("rise_to_carry", move |sim, ctx| {
        let grip = grip_pose(sim).0;
        let z = carry_z_m + grip.z - pos(sim, body).z;
        Goal::at(Vector3::new(ctx.start_pos_m.x, ctx.start_pos_m.y, z), GRIPPER_CLOSED).slow(0.6).rotated(grip_pose(sim).1)
    })
    .until(move |sim, _| pos(sim, body).z > carry_z_m - 0.01)
    .max_steps(80);
    phases.insert(k, rise);
}
