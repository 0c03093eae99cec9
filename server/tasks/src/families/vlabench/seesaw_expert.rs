//! Expert for T30 basic_seesaw_usage: set both counterweights down on the seesaw's far end (the board is tilted
//! 0.5 rad at rest, so each weight is lowered until its uphill bottom edge is just above the sloping board and let
//! go), wait while the damped board swings down and raises the carton in its guard cage (≈ 0.45 rad, ≈ 12 cm), then
//! take the carton from above and put it in the basket.
//!
//! Behaviours: `partial_1` (one weight), `partial_2` (both weights; the run ends at the step the second is let go,
//! before the board has lifted the carton), `partial_3` (both weights, wait for the lift),
//! `undo` (one weight on, then back to where it started: stage 1 regresses), `lift_by_hand` (press the board's far
//! end down by hand before any weight is placed, which raises the carton: the premature-lift guard fails the run).
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::Vector3;

use crate::expert::skills::{TargetFn, carry, memo, partial_count, pick_place, pos, xy_dist};
use crate::expert::motion::{
    GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, Script, body_dir, body_point, gripper_width_m, vec3,
};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};
use crate::TasksError;

/// T30 (the pool's seesaw variants, which reuse this script's pieces, are in `seesaw_pool_expert`).
pub const EXPERTS: &[ExpertEntry] = &[ExpertEntry {
    task: "T30",
    behaviours: &["partial_1", "partial_2", "partial_3", "undo", "lift_by_hand"],
    build: seesaw,
}];

/// Counterweight half extents (catalog §6.1: box 4.4 × 2.8 × 4.4 cm).
const WEIGHT_HALF_X_M: f64 = 0.022;
const WEIGHT_HALF_Z_M: f64 = 0.022;
/// Its width across the fingers.
const WEIGHT_WIDTH_M: f64 = 0.028;
/// Board plank half thickness.
const BOARD_HALF_THICKNESS_M: f64 = 0.001;
/// Where the weights go along the board (board frame, from the pivot; the far-end region spans 0.185–0.295): the
/// first nearer the pivot (it alone tilts the board ≈ 0.04 rad and raises the carton ≈ 1 cm), the second 6 cm farther
/// out, clear of the first (which lies tilted with the board) and of the far lip (which leans over a weight held
/// upright near it: touching it, the held weight would press the board down before it is let go).
const FIRST_SPOT_M: f64 = 0.19;
const SECOND_SPOT_M: f64 = 0.25;
/// Gap left under a held weight's uphill bottom edge when it is let go: small for the first (dropped from higher it
/// slides down the slope), larger for the second, which must not bear on the board while the fingers still hold it
/// (before the evaluator sees it released): the board would tilt and lift the carton toward both thresholds before
/// stage 2 — a premature lift.
const FIRST_GAP_M: f64 = 0.008;
const SECOND_GAP_M: f64 = 0.015;
/// Root height of a carried weight or carton: clears the board's high end and the cage roof (1.17 m).
pub(super) const CARRY_Z_M: f64 = 1.30;
/// The fingers close this far above the carton's root, along its axis (its box reaches 0.04 above the root, its
/// gable 0.062): grasped higher, the gable wedges between the fingers and the carton stays in the opened hand.
const CARTON_GRASP_M: f64 = 0.015;
/// The carton is let go with its root this far above the basket's contain-region centre (it drops a few cm onto the
/// basket floor instead of being pressed onto it).
const CARTON_DROP_ABOVE_REGION_M: f64 = 0.04;
/// Seesaw state that counts as "the board has lifted the carton" for the expert (above the evaluator's 0.12 rad and
/// 0.04 m, so stage 3 has completed when the expert moves on).
pub(super) const WAIT_HINGE_RAD: f64 = 0.20;
pub(super) const WAIT_LIFT_M: f64 = 0.05;

/// The root position at which a weight held upright (world-aligned) above board-frame spot `x_b` has its uphill
/// bottom edge `gap_m` above the sloping board.
fn weight_drop_target(sim: &Simulation, board: usize, x_b: f64, gap_m: f64) -> Vector3<f64> {
    let surface = body_point(sim, board, [x_b, 0.0, BOARD_HALF_THICKNESS_M]);
    let along = body_dir(sim, board, [1.0, 0.0, 0.0]);
    // the board rises toward its far end: under the uphill edge the surface is this much higher
    let slope = if along.x.abs() > 1e-6 { along.z / along.x } else { 0.0 };
    let rise = (WEIGHT_HALF_X_M * slope).max(0.0);
    Vector3::new(surface.x, surface.y, surface.z + rise + WEIGHT_HALF_Z_M + gap_m)
}

fn place_weight(phases: &mut Vec<Phase>, weight: usize, board: usize, x_b: f64, gap_m: f64) {
    let target: TargetFn = Arc::new(move |sim| weight_drop_target(sim, board, x_b, gap_m));
    pick_place(phases, weight, 0.0, CARRY_Z_M, target);
}

/// Moves the open hand to a waiting spot high over the table's middle.
pub(super) fn stand_clear(phases: &mut Vec<Phase>) {
    phases.push(
        Phase::new("stand_clear", |_, _| Goal::at(Vector3::new(-0.10, -0.20, 1.30), GRIPPER_OPEN)).until_reached(0.02).max_steps(80),
    );
}

fn seesaw(refs: &SceneRefs, behaviour: &str, task_id: &str) -> Result<Box<dyn Expert>, TasksError> {
    let board = refs.body("seesaw_1_board")?;
    let (hinge_adr, _) = refs.joint("seesaw_1_seesaw_hinge")?;
    let weights = [refs.instance_body("weight_1")?, refs.instance_body("weight_2")?];
    let carton = refs.instance_body("target_1")?;
    let basket_region = refs.site("basket_1_contain_region")?;
    let steps = match behaviour {
        SOLVE | "lift_by_hand" => 4,
        "undo" => 1,
        b => partial_count(b).filter(|&n| (1..4).contains(&n)).ok_or_else(|| TasksError::Scene(format!("{task_id}: unknown behaviour {b}")))?,
    };
    // the seesaw's state when the run began (the evaluator's baselines)
    let start = Arc::new(memo(move |sim: &Simulation| (sim.data().qpos()[hinge_adr], pos(sim, carton).z)));
    let weight1_start = Arc::new(memo(move |sim: &Simulation| pos(sim, weights[0])));
    let (s0, w0) = (start.clone(), weight1_start.clone());
    let mut phases = vec![Phase::new("note_start", move |sim, ctx| {
        s0(sim);
        w0(sim);
        Goal::at(ctx.start_pos_m, GRIPPER_OPEN)
    })];
    let lifted = {
        let start = start.clone();
        move |sim: &Simulation, hinge_rad: f64, lift_m: f64| {
            let (q0, z0) = start(sim);
            sim.data().qpos()[hinge_adr] - q0 >= hinge_rad && pos(sim, carton).z - z0 >= lift_m
        }
    };
    if behaviour == "lift_by_hand" {
        press_board_down(&mut phases, board, lifted.clone());
    }
    place_weight(&mut phases, weights[0], board, FIRST_SPOT_M, FIRST_GAP_M);
    if behaviour == "undo" {
        let back: TargetFn = Arc::new(move |sim| weight1_start(sim));
        pick_place(&mut phases, weights[0], 0.0, CARRY_Z_M, back);
    }
    if steps >= 2 {
        if behaviour == "partial_2" {
            place_weight(&mut phases, weights[1], board, SECOND_SPOT_M, SECOND_GAP_M);
            stop_once_released(&mut phases);
            return Ok(Box::new(Script::new(phases)));
        }
        place_weight(&mut phases, weights[1], board, SECOND_SPOT_M, SECOND_GAP_M);
    }
    if steps >= 3 {
        stand_clear(&mut phases);
        let l = lifted.clone();
        phases.push(
            Phase::new("wait_for_lift", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN))
                .until(move |sim, ctx| ctx.steps >= 10 && l(sim, WAIT_HINGE_RAD, WAIT_LIFT_M))
                .max_steps(200),
        );
    }
    if steps >= 4 {
        pick_carton(&mut phases, carton, basket_region);
    }
    Ok(Box::new(Script::new(phases)))
}

/// Picks the raised carton off the board into the basket: the hand closes on its upper half (fingers on the faces
/// across the board), lifts it straight up beside the cage roof, carries it over the basket, lowers it and lets go.
pub(super) fn pick_carton(phases: &mut Vec<Phase>, carton: usize, basket_region: usize) {
    let axis = move |sim: &Simulation| {
        let a = body_dir(sim, carton, [0.0, 1.0, 0.0]);
        if a.z < 0.0 { -a } else { a }
    };
    let grasp = move |sim: &Simulation| pos(sim, carton) + axis(sim) * CARTON_GRASP_M;
    phases.push(
        Phase::new("above_carton", move |sim, _| Goal::at(grasp(sim) + Vector3::z() * 0.10, GRIPPER_OPEN)).until_reached(0.015).max_steps(150),
    );
    phases.push(Phase::new("down_to_carton", move |sim, _| Goal::at(grasp(sim), GRIPPER_OPEN).slow(0.5)).until_reached(0.006).max_steps(60));
    phases.push(
        Phase::new("grip_carton", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED))
            .until(|sim, ctx| ctx.steps >= 20 || (ctx.steps >= 8 && sim.data().qvel()[sim.ids().finger_dof_adr[0]].abs() < 1e-3))
            .max_steps(20),
    );
    phases.push(
        Phase::new("lift_carton", move |_, ctx| {
            Goal::at(Vector3::new(ctx.start_pos_m.x, ctx.start_pos_m.y, CARRY_Z_M), GRIPPER_CLOSED)
        })
        .until_reached(0.015)
        .max_steps(100),
    );
    let drop = move |sim: &Simulation| vec3(&sim.data().site_xpos()[basket_region]) + Vector3::z() * CARTON_DROP_ABOVE_REGION_M;
    phases.push(
        Phase::new("carry_to_basket", move |sim, _| {
            let t = drop(sim);
            Goal::at(carry(sim, carton, Vector3::new(t.x, t.y, pos(sim, carton).z)), GRIPPER_CLOSED).slow(0.7)
        })
        .until(move |sim, _| xy_dist(pos(sim, carton), drop(sim)) < 0.01)
        .max_steps(200),
    );
    phases.push(
        Phase::new("lower_into_basket", move |sim, _| Goal::at(carry(sim, carton, drop(sim)), GRIPPER_CLOSED).slow(0.4))
            .until(move |sim, _| pos(sim, carton).z < drop(sim).z + 0.015)
            .max_steps(80),
    );
    phases.push(Phase::new("let_go", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN)).for_steps(10));
    phases.push(
        Phase::new("away", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.12, GRIPPER_OPEN))
            .until_reached(0.02)
            .max_steps(40),
    );
}

/// `partial_2`: instead of letting go and retreating, open only until the fingers are clear of the weight (the step at
/// which the evaluator sees both weights released and completes stage 2) and stop there: the episode ends before the
/// board can lift the carton (stage 3 could complete one step later at the earliest).
fn stop_once_released(phases: &mut Vec<Phase>) {
    // pick_place ends with `open` and `retreat`
    phases.truncate(phases.len().saturating_sub(2));
    phases.push(
        Phase::new("let_go_and_stop", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN))
            .until(|sim, _| gripper_width_m(sim) > WEIGHT_WIDTH_M + 0.008)
            .max_steps(20),
    );
}

/// `lift_by_hand`: the closed fingertips press the board's far end down until the carton has risen (before any
/// counterweight), then the hand lets the board swing back.
fn press_board_down(phases: &mut Vec<Phase>, board: usize, lifted: impl Fn(&Simulation, f64, f64) -> bool + Send + 'static) {
    const PRESS_AT_M: f64 = 0.25;
    let over = move |sim: &Simulation, above_m: f64| {
        body_point(sim, board, [PRESS_AT_M, 0.0, 0.0]) + body_dir(sim, board, [0.0, 0.0, 1.0]) * above_m
    };
    phases.push(
        Phase::new("above_far_end", move |sim, _| Goal::at(over(sim, 0.08), GRIPPER_CLOSED)).until_reached(0.015).max_steps(150),
    );
    phases.push(
        Phase::new("press_far_end", move |sim, _| Goal::at(over(sim, -0.03), GRIPPER_CLOSED).slow(0.4))
            .until(move |sim, _| lifted(sim, WAIT_HINGE_RAD, WAIT_LIFT_M))
            .max_steps(150),
    );
    phases.push(Phase::new("hold_pressed", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED)).for_steps(5));
    phases.push(
        Phase::new("let_board_up", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.15, GRIPPER_OPEN))
            .until_reached(0.02)
            .max_steps(60),
    );
}
