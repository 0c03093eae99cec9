//! Experts for the cooking scene shared by T21 (text goal) and T22 (goal image), task catalog §5.0: moka pot onto
//! the second stove, frying pan onto the first, both knobs on, microwave open.
//!
//! The order avoids disturbing earlier goals: the first stove's knob is turned before the pan goes on (the pan's
//! handle, pointing at the robot, ends above that knob), the moka pot is moved before the hand reaches past it for
//! the pan, both are carried high over the stoves, and the microwave door (which swings away from everything)
//! comes last.
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::Vector3;

use crate::expert::fixtures::{microwave_door_phases, stove_knob_phases};
use crate::expert::skills::{RotFn, TargetFn, memo, partial_count, pick_place_at, pos};
use crate::expert::motion::{
    GRIPPER_OPEN, Goal, Phase, Script, body_dir, body_point, grip_pose, open_along, rotate_world, rotation_error,
};
use crate::expert::{Expert, SOLVE, SceneRefs};
use crate::TasksError;

pub fn behaviours(task_id: &str) -> Option<&'static [&'static str]> {
    Some(match task_id {
        "T21" | "T22" => &["partial_1", "partial_2", "partial_3", "partial_4", "undo", "swapped"],
        _ => return None,
    })
}

pub fn build(task_id: &str, behaviour: &str, refs: &SceneRefs) -> Result<Box<dyn Expert>, TasksError> {
    match task_id {
        "T21" | "T22" => prepare_cooking(refs, behaviour),
        _ => Err(TasksError::Scene(format!("no scripted expert for task {task_id}"))),
    }
}

/// Knob angle the expert turns to (on needs ≥ 0.5 rad; the knob coasts a little past its goal).
const KNOB_ON_RAD: f64 = 0.9;
/// Microwave door angle the expert swings to (open needs < −1.3 rad).
const DOOR_OPEN_RAD: f64 = -1.45;
/// The flat stove's burner plate top above its `cook_region` site (burner base box half height 0.02 plus the
/// collision plate at 0.025 ± 0.0005).
const BURNER_TOP_ABOVE_SITE_M: f64 = 0.0255;
/// Moka pot: its root above the surface it stands on (collision boxes reach 0.0666 below the root), and where the
/// fingers close: across the lid's knob (1 cm wide along the pot's local x), straight down (its body, 6.8 cm across, would
/// nearly fill the gripper's 8 cm opening).
const MOKA_ROOT_ABOVE_SUPPORT_M: f64 = 0.0666;
const MOKA_GRASP_DZ_M: f64 = 0.075;
/// Chefmate frypan: its root lies ≈ 1 mm below the pan's underside; the fingers close across the handle (which runs
/// along the pan's local +x, rising from 3.5 cm) 15 cm from the pan's centre.
const PAN_ROOT_ABOVE_SUPPORT_M: f64 = -0.001;
const PAN_HANDLE_GRASP_LOCAL_M: [f64; 3] = [0.15, 0.0, 0.039];
/// The pan's target sits this far from the burner's centre, away from the robot (inside the ±0.075 m cook region),
/// so that the fingers on its handle stay clear of the stove's knob when the pan is set down.
const PAN_TARGET_OFFSET_X_M: f64 = 0.045;
/// The pan's handle is near the far edge of the arm's reach (the elbow cannot straighten): the hand points forward
/// of straight down by 20° (about world y), which brings the wrist back toward the base. The moka pot (moved nearer
/// the robot, tasks/README.md) is grasped straight down.
const PAN_PITCH_RAD: f64 = 0.35;
const MOKA_PITCH_RAD: f64 = 0.0;
/// Root heights while carrying over the stoves and knobs.
const MOKA_CARRY_Z_M: f64 = 1.06;
const PAN_CARRY_Z_M: f64 = 1.06;
/// Where the hand waits at the end, out of the head camera's view of the stoves (world, m).
const PARK_M: [f64; 3] = [-0.45, 0.0, 1.25];

/// Which goal-completing step comes next, in the order the expert plays them.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Step {
    FirstKnob,
    PanToFirstStove,
    MokaToSecondStove,
    SecondKnob,
    OpenMicrowave,
}

/// The moka pot goes before the pan: the hand reaching for the pan's handle passes close by the pot's start.
const ORDER: [Step; 5] = [Step::FirstKnob, Step::MokaToSecondStove, Step::PanToFirstStove, Step::SecondKnob, Step::OpenMicrowave];
/// Height the hand rises to (and turns for the next grasp at) before travelling to an object (world z, m).
const TRAVEL_Z_M: f64 = 1.15;

/// `solve` plays all five steps, `partial_<n>` the first n (exactly n goals hold at the end), `undo` sets the moka
/// pot on the second stove and carries it back to where it stood (that goal regresses), `swapped` puts the moka
/// pot on the first stove and the pan on the second (the assignment is fixed: no placement goal holds).
fn prepare_cooking(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let moka = refs.instance_body("moka_pot_1")?;
    let pan = refs.instance_body("chefmate_8_frypan_1")?;
    let region1 = refs.site("flat_stove_1_cook_region")?;
    let region2 = refs.site("flat_stove_2_cook_region")?;
    let site = move |sim: &Simulation, s: usize| Vector3::from(sim.data().site_xpos()[s]);
    let moka_on = move |s: usize| -> TargetFn {
        Arc::new(move |sim| site(sim, s) + Vector3::z() * (BURNER_TOP_ABOVE_SITE_M + MOKA_ROOT_ABOVE_SUPPORT_M))
    };
    let pan_on = move |s: usize| -> TargetFn {
        Arc::new(move |sim| {
            site(sim, s) + Vector3::new(PAN_TARGET_OFFSET_X_M, 0.0, BURNER_TOP_ABOVE_SITE_M + PAN_ROOT_ABOVE_SUPPORT_M)
        })
    };
    let mut phases = Vec::new();
    match behaviour {
        "undo" => {
            let start = Arc::new(memo(move |sim: &Simulation| pos(sim, moka)));
            let s = start.clone();
            // note the start before anything moves
            phases.push(Phase::new("note_start", move |sim, ctx| {
                s(sim);
                Goal::at(ctx.start_pos_m, GRIPPER_OPEN)
            }));
            place_moka(&mut phases, moka, moka_on(region2));
            place_moka(&mut phases, moka, Arc::new(move |sim| start(sim)));
        }
        "swapped" => {
            place_pan(&mut phases, pan, pan_on(region2));
            place_moka(&mut phases, moka, moka_on(region1));
        }
        b => {
            let n = if b == SOLVE { ORDER.len() } else { partial_count(b).filter(|&n| n < ORDER.len()).ok_or_else(|| TasksError::Scene(format!("T21/T22: unknown behaviour {b}")))? };
            for step in &ORDER[..n] {
                match step {
                    Step::FirstKnob => phases.extend(stove_knob_phases(refs, "flat_stove_1", KNOB_ON_RAD)?),
                    Step::PanToFirstStove => place_pan(&mut phases, pan, pan_on(region1)),
                    Step::MokaToSecondStove => place_moka(&mut phases, moka, moka_on(region2)),
                    Step::SecondKnob => phases.extend(stove_knob_phases(refs, "flat_stove_2", KNOB_ON_RAD)?),
                    Step::OpenMicrowave => phases.extend(microwave_door_phases(refs, "microwave_1", DOOR_OPEN_RAD)?),
                }
            }
        }
    }
    phases.push(Phase::new("park", |_, _| Goal::at(Vector3::from(PARK_M), GRIPPER_OPEN)).until_reached(0.03).max_steps(120));
    Ok(Box::new(Script::new(phases)))
}

/// Fingers opening along `dir`'s horizontal part, the hand pitched forward by `pitch_rad`.
fn fingers_along(pitch_rad: f64, dir: impl Fn(&Simulation) -> Vector3<f64> + Send + Sync + 'static) -> RotFn {
    Arc::new(move |sim, ctx| rotate_world(&open_along(&ctx.home_rot, dir(sim)), Vector3::y(), -pitch_rad))
}

/// The moka pot by its upper body, fingers across the pot's flats (its local x), onto `target` (root position).
fn place_moka(phases: &mut Vec<Phase>, moka: usize, target: TargetFn) {
    let grasp: TargetFn = Arc::new(move |sim| pos(sim, moka) + Vector3::z() * MOKA_GRASP_DZ_M);
    let rot = fingers_along(MOKA_PITCH_RAD, move |sim| body_dir(sim, moka, [1.0, 0.0, 0.0]));
    rise_and_turn(phases, rot.clone());
    pick_place_at(phases, moka, grasp, MOKA_CARRY_Z_M, target, rot);
}

/// The pan by its handle, fingers across it (along the pan's local y), onto `target` (root position).
fn place_pan(phases: &mut Vec<Phase>, pan: usize, target: TargetFn) {
    let grasp: TargetFn = Arc::new(move |sim| body_point(sim, pan, PAN_HANDLE_GRASP_LOCAL_M));
    let rot = fingers_along(PAN_PITCH_RAD, move |sim| body_dir(sim, pan, [0.0, 1.0, 0.0]));
    rise_and_turn(phases, rot.clone());
    pick_place_at(phases, pan, grasp, PAN_CARRY_Z_M, target, rot);
}

/// Straight up to [`TRAVEL_Z_M`], turning to the next grasp's orientation on the way: a hand that turns while it
/// travels low sags and sweeps through what stands near its path.
fn rise_and_turn(phases: &mut Vec<Phase>, rot: RotFn) {
    let r = rot.clone();
    let up = |ctx: &crate::expert::motion::PhaseCtx| Vector3::new(ctx.start_pos_m.x, ctx.start_pos_m.y, TRAVEL_Z_M.max(ctx.start_pos_m.z));
    phases.push(
        Phase::new("rise_and_turn", move |sim, ctx| Goal::at(up(ctx), GRIPPER_OPEN).rotated(r(sim, ctx)))
            .until(move |sim, ctx| (grip_pose(sim).0 - up(ctx)).norm() < 0.02 && rotation_error(sim, &rot(sim, ctx)) < 0.05)
            .max_steps(120),
    );
}
