//! The stock expert's placement of the frying pan (`chefmate_8_frypan`), held by its handle 15 cm from its centre.
//!
//! The hand grips the handle level (pitched 0.35 rad as in the cooking task, a stock stove placement failed), lifts
//! the pan the whole way to its carry height before moving sideways (the generic lift, whose goal is re-read from the
//! rising object, stops halfway, and the pan then sweeps into the top of the shelf), and carries it by the hand's
//! own offset from the pan's root measured once the fingers have closed, not by a fixed handle offset. Into a
//! compartment covered from above (a shelf's), the pan is slid in at its floor's height through the open side, the
//! hand outside holding it by the handle.
use std::sync::{Arc, Mutex};

use libero_sim::Simulation;
use nalgebra::{Matrix3, Vector3};

use crate::expert::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, grip_pose, mat3, rotation_error, vec3};
use crate::expert::skills::{extent, pos, xy_dist};
use crate::judge::predicates::SceneIndex;

use super::stalled;

/// Whether a placement's object is a frying pan (its category).
pub(super) fn is_pan(category: &str) -> bool {
    category.contains("frypan")
}

/// The hand's offset from the pan's root (world, m), latched once after the grasp.
type Latch = Arc<Mutex<Option<Vector3<f64>>>>;

/// The hand's offset from the pan's root now, or the one latched after the grasp.
fn held_offset(latch: &Latch, sim: &Simulation, body: usize) -> Vector3<f64> {
    let mut l = latch.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    *l.get_or_insert_with(|| grip_pose(sim).0 - pos(sim, body))
}

/// A compartment the pan goes into from the side (a shelf under a board): the horizontal direction out of its open
/// face (world, unit) and the compartment's half depth along it (m).
pub(super) struct SideEntry {
    pub(super) out: Vector3<f64>,
    pub(super) half_depth_m: f64,
}

/// Whether the segment from `a` to `b` (world) crosses one of `instance`'s contact geoms (their local bounding
/// boxes; the slab test, exact for the box geoms that fixtures' boards and walls are).
fn blocked(sim: &Simulation, index: &SceneIndex, instance: usize, a: Vector3<f64>, b: Vector3<f64>) -> bool {
    let (aabb, data) = (sim.model().geom_aabb(), sim.data());
    index.contact_geoms(instance).any(|g| {
        let r = mat3(&data.geom_xmat()[g]).transpose();
        let centre = vec3(&data.geom_xpos()[g]);
        let (la, lb) = (r * (a - centre), r * (b - centre));
        let (mut t0, mut t1) = (0.0_f64, 1.0_f64);
        for k in 0..3 {
            let (lo, hi) = (aabb[g][k] - aabb[g][3 + k], aabb[g][k] + aabb[g][3 + k]);
            let d = lb[k] - la[k];
            if d.abs() < 1e-12 {
                if la[k] < lo || la[k] > hi {
                    return false;
                }
            } else {
                let (u, v) = ((lo - la[k]) / d, (hi - la[k]) / d);
                t0 = t0.max(u.min(v));
                t1 = t1.min(u.max(v));
            }
        }
        t0 <= t1
    })
}

/// How the pan goes into `region`, if its fixture covers it from above (a shelf's compartment): out of the open face
/// among the region box's horizontal sides (nothing of the fixture within 5 cm beyond it), the one nearest the handle's
/// direction `handle_m` (the hand, outside, holds the pan in).
pub(super) fn side_entry(sim: &Simulation, index: &SceneIndex, region: usize, handle_m: Vector3<f64>) -> Option<SideEntry> {
    const BEYOND_M: f64 = 0.05;
    let reg = &index.regions[region];
    let parent = reg.parent?;
    let c = vec3(&sim.data().site_xpos()[reg.site]);
    let r = mat3(&sim.data().site_xmat()[reg.site]);
    if !blocked(sim, index, parent, c, c + Vector3::z() * 0.3) {
        return None;
    }
    let handle = Vector3::new(handle_m.x, handle_m.y, 0.0).try_normalize(1e-9)?;
    (0..3)
        .filter(|&k| r[(2, k)].abs() < 0.3)
        .flat_map(|k| [1.0, -1.0].map(|s| (Vector3::new(r[(0, k)], r[(1, k)], 0.0).normalize() * s, reg.half_size_m[k].abs())))
        .filter(|(u, half)| !blocked(sim, index, parent, c, c + u * (half + BEYOND_M)))
        .max_by(|a, b| a.0.dot(&handle).total_cmp(&b.0.dot(&handle)))
        .map(|(out, half_depth_m)| SideEntry { out, half_depth_m })
}

/// Pick the pan (instance `object`) by its handle (the grip point `grasp_offset_m` from its root, the hand at `rot`)
/// and set it down with its root at `to` (world), carried with the root at `carry_z_m`: straight down onto a stove
/// or a board, or, into a compartment of `region` covered from above, slid in at its floor's height from its open
/// side.
pub(super) fn place_phases(
    sim: &Simulation,
    index: &SceneIndex,
    object: usize,
    region: Option<usize>,
    (grasp_offset_m, rot): (Vector3<f64>, Matrix3<f64>),
    to: Vector3<f64>,
    carry_z_m: f64,
) -> Vec<Phase> {
    let body = index.instances[object].body;
    let at_grasp = move |sim: &Simulation| pos(sim, body) + grasp_offset_m;
    let latch: Latch = Arc::new(Mutex::new(None));
    // a phase moving the held pan's root toward `root_at` (world) at `speed`, the hand at the latched offset from it
    let carry_root = |name: &'static str, root_at: Vector3<f64>, speed: f64| {
        let l = latch.clone();
        Phase::new(name, move |sim, _| Goal::at(root_at + held_offset(&l, sim, body), GRIPPER_CLOSED).slow(speed).rotated(rot))
    };
    let l0 = latch.clone();
    let mut lift_rise: Option<f64> = None;
    let mut phases = vec![
        Phase::new("above_handle", move |sim, _| Goal::at(at_grasp(sim) + Vector3::z() * 0.10, GRIPPER_OPEN).rotated(rot))
            .until(move |sim, _| (grip_pose(sim).0 - at_grasp(sim) - Vector3::z() * 0.10).norm() < 0.012 && rotation_error(sim, &rot) < 0.06)
            .max_steps(160),
        Phase::new("down_to_handle", move |sim, _| Goal::at(at_grasp(sim), GRIPPER_OPEN).slow(0.5).rotated(rot)).until_reached(0.007).max_steps(80),
        Phase::new("close", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(rot))
            .until(|sim, ctx| ctx.steps >= 20 || (ctx.steps >= 8 && sim.data().qvel()[sim.ids().finger_dof_adr[0]].abs() < 1e-3))
            .max_steps(20),
        // the hand's offset latched as the lift starts; the whole rise fixed then (a goal re-read from the rising pan
        // meets it halfway)
        Phase::new("lift", move |sim, ctx| {
            held_offset(&l0, sim, body);
            let rise = *lift_rise.get_or_insert_with(|| carry_z_m - pos(sim, body).z);
            Goal::at(ctx.start_pos_m + Vector3::z() * rise, GRIPPER_CLOSED).slow(0.6).rotated(rot)
        })
        .until(move |sim, _| pos(sim, body).z > carry_z_m - 0.015)
        .max_steps(100),
    ];
    let entry = region.and_then(|r| side_entry(sim, index, r, grasp_offset_m));
    // the pan's radius: half its footprint across the handle
    let (lo, hi) = extent(sim, index, object);
    let radius_m = (hi.x - lo.x).min(hi.y - lo.y) / 2.0;
    // into a compartment, its root toward the opening by as much as keeps its far rim 1 cm off the back (and the root
    // 2 cm inside the region)
    let to = match &entry {
        Some(e) => to + e.out * (radius_m + 0.01 - e.half_depth_m).clamp(0.0, (e.half_depth_m - 0.02).max(0.0)),
        None => to,
    };
    let over = |p: Vector3<f64>, z: f64| Vector3::new(p.x, p.y, z);
    if let Some(e) = &entry {
        // in front of the open face with the pan clear of it, then down to 2 cm over the floor, then in
        let front = to + e.out * (e.half_depth_m + radius_m + 0.04);
        let slide_z = to.z + 0.02;
        phases.push(carry_root("carry_before_opening", over(front, carry_z_m), 0.7).until(move |sim, _| xy_dist(pos(sim, body), front) < 0.01).max_steps(200));
        phases.push(carry_root("down_to_opening", over(front, slide_z), 0.5).until(move |sim, _| pos(sim, body).z < slide_z + 0.008).max_steps(150));
        phases.push(carry_root("slide_in", over(to, slide_z), 0.4).until(move |sim, _| xy_dist(pos(sim, body), to) < 0.01).max_steps(200));
    } else {
        phases.push(carry_root("carry_over_target", over(to, carry_z_m), 0.7).until(move |sim, _| xy_dist(pos(sim, body), to) < 0.01).max_steps(200));
    }
    phases.push(
        carry_root("lower", to - Vector3::z() * 0.01, 0.35)
            .until(move |sim, ctx| pos(sim, body).z < to.z + 0.004 || stalled(sim, ctx))
            .max_steps(80),
    );
    phases.push(Phase::new("open", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(rot)).for_steps(10));
    // out of the opening first, then up
    if let Some(e) = &entry {
        let back = e.out * 0.10;
        phases.push(Phase::new("back_out", move |_, ctx| Goal::at(ctx.start_pos_m + back, GRIPPER_OPEN).rotated(rot)).until_reached(0.02).max_steps(40));
    }
    phases.push(
        Phase::new("retreat", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.12, GRIPPER_OPEN).rotated(rot)).until_reached(0.02).max_steps(40),
    );
    phases
}
