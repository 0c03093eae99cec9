//! Experts for the pool's seesaw variants on T30's seesaw, with privileged access to the private masses (read from
//! the compiled model, where the episode wrote them):
//!
//! * `vlabench_physical/1` adaptive_seesaw_usage: set the two heaviest weights down on the far end (heaviest first),
//!   wait while the board tilts and raises the payload, then put the payload in the basket (T30's carton pick).
//!   `light_pair` does the same with the two lightest (0.30 + 0.60 kg: the board tilts and the payload rises, but the
//!   selection's mass fails the gate); `partial_3` stops once the payload has risen.
//! * `vlabench_physical/2` active_weight_comparison: probe each candidate alone (set it down on the far end, stand
//!   clear while the board answers, take it back to where it stood, wait for the board to come back to rest), then
//!   put the heavier in the basket. `lighter_in_basket` probes both and puts the lighter one there;
//!   `skip_probing` carries the heavier straight to the basket.
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::Vector3;

use super::seesaw_expert::{CARRY_Z_M, WAIT_HINGE_RAD, WAIT_LIFT_M, pick_carton, stand_clear};
use crate::TasksError;
use crate::expert::motion::{GRIPPER_OPEN, Goal, Phase, Script, body_dir, body_point, rotate_world, vec3};
use crate::expert::skills::{RotFn, TargetFn, memo, partial_count, pick_place, pick_place_turned, pos};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};

/// The pool's adaptive seesaw (`vlabench_physical/1`) and weight comparison (`vlabench_physical/2`), by reference.
pub const EXPERTS: &[ExpertEntry] = &[
    ExpertEntry {
        task: "vlabench_physical/adaptive_seesaw_usage",
        behaviours: &["light_pair", "partial_3"],
        build: |refs, b, _| adaptive(refs, b),
    },
    ExpertEntry {
        task: "vlabench_physical/active_weight_comparison",
        behaviours: &["skip_probing", "lighter_in_basket"],
        build: |refs, b, _| comparison(refs, b),
    },
];

/// An instance's mass in the compiled model (the episode writes the private masses there).
fn mass_kg(refs: &SceneRefs, instance: &str) -> Result<f64, TasksError> {
    let root = refs.instance_body(instance)?;
    let parents = refs.model.body_parentid();
    let in_subtree = |mut b: usize| loop {
        if b == root {
            return true;
        }
        if b == 0 {
            return false;
        }
        b = parents[b] as usize;
    };
    Ok((0..parents.len()).filter(|&b| in_subtree(b)).map(|b| refs.model.body_mass()[b]).sum())
}

/// The instances sorted by mass, heaviest first.
fn by_mass_desc<'a>(refs: &SceneRefs, names: &[&'a str]) -> Result<Vec<&'a str>, TasksError> {
    let mut with: Vec<(f64, &str)> = names.iter().map(|n| mass_kg(refs, n).map(|m| (m, *n))).collect::<Result<_, _>>()?;
    with.sort_by(|a, b| b.0.total_cmp(&a.0));
    Ok(with.into_iter().map(|(_, n)| n).collect())
}

/// Where the pair goes along the board (board frame, from the pivot; the far-end box reaches in to ≈ 0.11): the first
/// (heavier) weight at 0.17, the second 6 cm nearer the pivot, where the hand still reaches with its elbow well bent.
/// Farther out (T30's 0.19 / 0.25) the arm is nearly stretched over the far end, and drawing the hand back from there
/// can straighten the elbow against its limit, a singular pose from which it no longer reaches the raised payload
/// near the robot. Only the first probe must lie in the far-end box (stage 1); the selection is by contact alone.
const PAIR_SPOTS_M: [f64; 2] = [0.17, 0.11];

/// adaptive_seesaw_usage (see the module doc).
pub fn adaptive(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let board = refs.body("seesaw_1_board")?;
    let (hinge_adr, _) = refs.joint("seesaw_1_seesaw_hinge")?;
    let payload = refs.instance_body("payload_1")?;
    let basket_region = refs.site("basket_1_contain_region")?;
    let sorted = by_mass_desc(refs, &["weight_a", "weight_b", "weight_c"])?;
    let (steps, pair) = match behaviour {
        SOLVE => (4, [sorted[0], sorted[1]]),
        "light_pair" => (4, [sorted[1], sorted[2]]),
        b if partial_count(b) == Some(3) => (3, [sorted[0], sorted[1]]),
        b => return Err(TasksError::Scene(format!("adaptive_seesaw_usage: unknown behaviour {b}"))),
    };
    let start = Arc::new(memo(move |sim: &Simulation| (sim.data().qpos()[hinge_adr], pos(sim, payload).z)));
    let s0 = start.clone();
    let mut phases = vec![Phase::new("note_start", move |sim, ctx| {
        s0(sim);
        Goal::at(ctx.start_pos_m, GRIPPER_OPEN)
    })];
    // the heavier of the pair first, farther out; the other nearer the pivot
    place_on_board(&mut phases, refs.instance_body(pair[0])?, board, PAIR_SPOTS_M[0], PLACE_GAP_M);
    place_on_board(&mut phases, refs.instance_body(pair[1])?, board, PAIR_SPOTS_M[1], PLACE_GAP_M);
    stand_clear(&mut phases);
    phases.push(
        Phase::new("wait_for_lift", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN))
            .until(move |sim, ctx| {
                let (q0, z0) = start(sim);
                ctx.steps >= 10 && sim.data().qpos()[hinge_adr] - q0 >= WAIT_HINGE_RAD && pos(sim, payload).z - z0 >= WAIT_LIFT_M
            })
            .max_steps(200),
    );
    if steps >= 4 {
        pick_carton(&mut phases, payload, basket_region);
    }
    Ok(Box::new(Script::new(phases)))
}

/// Root height at which a weight is carried to the board: enough to pass over the tilted board's high end (≈ 1.20 m)
/// from the side, lower than T30's 1.30 m, which leaves the arm stretched near its reach over the far end.
const BOARD_CARRY_Z_M: f64 = 1.24;

/// Sets a weight down on the board at board-frame spot `x_b` the way it must go onto a sloping board: picked upright
/// from the table, carried high, turned about y to the board's tilt on the way (the fingers hold its ±y faces, which
/// the turn keeps vertical), lowered along the board's normal until its bottom face is `gap_m` above the board and let
/// go flat. A weight let go upright above the 0.5 rad slope lands on its uphill edge, swings down flat and tumbles on
/// down the board.
fn place_on_board(phases: &mut Vec<Phase>, weight: usize, board: usize, x_b: f64, gap_m: f64) {
    let tilt = move |sim: &Simulation| {
        let along = body_dir(sim, board, [1.0, 0.0, 0.0]);
        along.z.atan2(along.x)
    };
    let target: TargetFn = Arc::new(move |sim| {
        body_point(sim, board, [x_b, 0.0, BOARD_HALF_THICKNESS_M]) + body_dir(sim, board, [0.0, 0.0, 1.0]) * (WEIGHT_HALF_M + gap_m)
    });
    let mut upright = Vec::new();
    pick_place(&mut upright, weight, 0.0, BOARD_CARRY_Z_M, target.clone());
    let rot: RotFn = Arc::new(move |sim, ctx| rotate_world(&ctx.home_rot, Vector3::y(), -tilt(sim)));
    let mut turned = Vec::new();
    pick_place_turned(&mut turned, weight, Vector3::zeros(), BOARD_CARRY_Z_M, target, rot);
    // the pick of the upright version, then the carry, lowering and release of the turned one (not its retreat)
    phases.extend(upright.into_iter().take(4));
    let n = turned.len();
    phases.extend(turned.into_iter().take(n - 1).skip(4));
    // back toward the robot, barely rising: over the far end the arm is nearly stretched, and lifting the hand
    // straight up (pick_place's retreat) or swinging it away from there straightens the elbow against its limit,
    // a singular pose from which the hand can no longer be drawn back toward the robot
    phases.push(
        Phase::new("back_off", move |_, ctx| {
            Goal::at(ctx.start_pos_m + Vector3::new(-BACK_OFF_M, 0.0, 0.03), GRIPPER_OPEN).slow(0.6)
        })
        .until_reached(0.015)
        .max_steps(80),
    );
}

/// How far the hand draws back toward the robot after letting a weight go on the board.
const BACK_OFF_M: f64 = 0.20;

/// Where a probe goes along the board (board frame, from the pivot; the far-end site is at 0.24).
const PROBE_SPOT_M: f64 = 0.22;
/// Gap under a weight's bottom face when it is let go, parallel to the board.
const PLACE_GAP_M: f64 = 0.004;
/// The weight's half size (a 4.4 cm cube) and the board plank's half thickness.
const WEIGHT_HALF_M: f64 = 0.022;
const BOARD_HALF_THICKNESS_M: f64 = 0.001;
/// The board counts as settled under a probe, or back at rest, when the hinge moves slower than this (rad/s) …
const SETTLED_RAD_S: f64 = 0.02;
/// … and, back at rest, is this close to where it started (rad): well inside the evaluator's 0.05 rad.
const AT_REST_RAD: f64 = 0.01;
/// A candidate dropped into the basket: its root's target height above the contain region's site.
const BASKET_DROP_ABOVE_REGION_M: f64 = 0.03;

/// Moves the open hand up to the carry height and over `body` (the seesaw stands between the two candidates' spots:
/// a straight move from one to the other at table height runs into its board).
fn over_at_carry_height(phases: &mut Vec<Phase>, body: usize) {
    phases.push(
        Phase::new("up_to_carry_height", move |_, ctx| Goal::at(Vector3::new(ctx.start_pos_m.x, ctx.start_pos_m.y, CARRY_Z_M), GRIPPER_OPEN))
            .until_reached(0.02)
            .max_steps(80),
    );
    phases.push(
        Phase::new("over_next_object", move |sim, _| {
            let p = pos(sim, body);
            Goal::at(Vector3::new(p.x, p.y, CARRY_Z_M), GRIPPER_OPEN)
        })
        .until_reached(0.02)
        .max_steps(150),
    );
}

/// active_weight_comparison (see the module doc).
pub fn comparison(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let board = refs.body("seesaw_1_board")?;
    let (hinge_adr, hinge_dof) = refs.joint("seesaw_1_seesaw_hinge")?;
    let basket_region = refs.site("basket_1_contain_region")?;
    let names = ["candidate_1", "candidate_2"];
    let sorted = by_mass_desc(refs, &names)?;
    let (heavier, lighter) = (refs.instance_body(sorted[0])?, refs.instance_body(sorted[1])?);
    let candidates = [refs.instance_body(names[0])?, refs.instance_body(names[1])?];
    let hinge0 = Arc::new(memo(move |sim: &Simulation| sim.data().qpos()[hinge_adr]));
    let starts = candidates.map(|c| Arc::new(memo(move |sim: &Simulation| pos(sim, c))));
    let (h0, s0, s1) = (hinge0.clone(), starts[0].clone(), starts[1].clone());
    let mut phases = vec![Phase::new("note_start", move |sim, ctx| {
        h0(sim);
        s0(sim);
        s1(sim);
        Goal::at(ctx.start_pos_m, GRIPPER_OPEN)
    })];
    let into_basket: TargetFn =
        Arc::new(move |sim| vec3(&sim.data().site_xpos()[basket_region]) + Vector3::z() * BASKET_DROP_ABOVE_REGION_M);
    let (target, probe) = match behaviour {
        SOLVE => (heavier, true),
        "lighter_in_basket" => (lighter, true),
        "skip_probing" => (heavier, false),
        b => return Err(TasksError::Scene(format!("active_weight_comparison: unknown behaviour {b}"))),
    };
    if probe {
        for (k, &c) in candidates.iter().enumerate() {
            over_at_carry_height(&mut phases, c);
            place_on_board(&mut phases, c, board, PROBE_SPOT_M, PLACE_GAP_M);
            stand_clear(&mut phases);
            phases.push(
                Phase::new("wait_for_response", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN))
                    .until(move |sim, ctx| ctx.steps >= 20 && sim.data().qvel()[hinge_dof].abs() < SETTLED_RAD_S)
                    .max_steps(120),
            );
            let back = starts[k].clone();
            let back: TargetFn = Arc::new(move |sim| back(sim));
            pick_place(&mut phases, c, 0.0, CARRY_Z_M, back);
            let h0 = hinge0.clone();
            phases.push(
                Phase::new("wait_for_rest", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN))
                    .until(move |sim, ctx| {
                        let d = sim.data();
                        ctx.steps >= 10 && (d.qpos()[hinge_adr] - h0(sim)).abs() < AT_REST_RAD && d.qvel()[hinge_dof].abs() < SETTLED_RAD_S
                    })
                    .max_steps(200),
            );
        }
    }
    over_at_carry_height(&mut phases, target);
    pick_place(&mut phases, target, 0.0, CARRY_Z_M, into_basket);
    Ok(Box::new(Script::new(phases)))
}
