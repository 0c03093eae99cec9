//! Expert for T29 drive_nail_with_hammer: grasp the hammer's handle from above, lift it, turn it half a turn about
//! the vertical (the sampler leaves its head toward the robot; the nail is on the far side), bring the head's flat
//! +y face in front of the nail head at its height and push the nail home along +y with a steady, slow push (the
//! nail has only damping and friction loss: the checker needs contact, then displacement).
//!
//! Near misses: `partial_1` lifts and holds the hammer up; `partial_2` touches the nail with the head and backs
//! off; `undo` lifts the hammer and sets it back down (stage 1 regresses); `push_with_gripper` lifts the hammer,
//! sets it back, then drives the nail with the closed fingers (no hammer–nail contact ever).
use std::f64::consts::PI;
use std::sync::{Arc, Mutex};

use libero_sim::Simulation;
use nalgebra::{Matrix3, Vector3};

use crate::expert::motion::{
    GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, PhaseCtx, Script, body_dir, body_point, grip_pose, open_along, rotate_world,
    rotation_error, vec3,
};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};
use crate::TasksError;

pub const EXPERTS: &[ExpertEntry] = &[ExpertEntry {
    task: "T29",
    behaviours: &["partial_1", "partial_2", "undo", "push_with_gripper"],
    build: drive_nail,
}];

/// Where the fingers close on the handle, along the hammer's local x (0 = handle centre, the head is at 0.16): far
/// enough back that the hand stays clear of the block while the head reaches the nail.
const GRIP_LOCAL_X_M: f64 = 0.0;
/// Half length of the hammer head cylinder along its local y (its flat ends strike).
const HEAD_HALF_LENGTH_M: f64 = 0.060;
/// How high the hammer root is lifted above its resting height before it is turned (stage 1 needs 0.045).
const LIFT_M: f64 = 0.10;
/// The push stops this far past the nail's reset position (the checker needs 0.075; the slide ends at 0.10).
const DRIVE_GOAL_M: f64 = 0.085;
/// `partial_2` stops pushing once the nail has moved this far (touched, far from driven).
const TOUCH_MOVE_M: f64 = 0.005;
/// Turning rate of the hand while the hammer is turned (rad per control step).
const TURN_RATE_RAD: f64 = 0.12;

#[derive(Clone, Copy)]
struct Refs {
    hammer: usize,
    head_site: usize,
    nail_head_site: usize,
    nail_q_adr: usize,
}

impl Refs {
    fn grip_point(&self, sim: &Simulation) -> Vector3<f64> {
        body_point(sim, self.hammer, [GRIP_LOCAL_X_M, 0.0, 0.0])
    }

    fn head(&self, sim: &Simulation) -> Vector3<f64> {
        vec3(&sim.data().site_xpos()[self.head_site])
    }

    /// The centre of the head's flat end that faces world +y.
    fn striking_face(&self, sim: &Simulation) -> Vector3<f64> {
        let axis = body_dir(sim, self.hammer, [0.0, 1.0, 0.0]);
        let toward_y = if axis.y >= 0.0 { axis } else { -axis };
        self.head(sim) + toward_y * HEAD_HALF_LENGTH_M
    }

    fn nail_head(&self, sim: &Simulation) -> Vector3<f64> {
        vec3(&sim.data().site_xpos()[self.nail_head_site])
    }

    fn nail_q(&self, sim: &Simulation) -> f64 {
        sim.data().qpos()[self.nail_q_adr]
    }

    fn hammer_z(&self, sim: &Simulation) -> f64 {
        vec3(&sim.data().xpos()[self.hammer]).z
    }

    /// The grip-site goal that brings the striking face to `target` (closed loop on the hammer's pose in the hand).
    fn face_to(&self, sim: &Simulation, target: Vector3<f64>) -> Vector3<f64> {
        grip_pose(sim).0 + (target - self.striking_face(sim))
    }
}

/// A value captured on the first call (a start state remembered across phases).
#[derive(Clone, Default)]
struct Memo<T>(Arc<Mutex<Option<T>>>);

impl<T: Copy> Memo<T> {
    fn get_or(&self, f: impl FnOnce() -> T) -> T {
        let mut slot = self.0.lock().unwrap_or_else(|e| e.into_inner());
        *slot.get_or_insert_with(f)
    }

    fn get(&self) -> Option<T> {
        *self.0.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The hand orientation of the grasp (fingers across the handle) and, once turned, that orientation turned by π
/// about world z.
fn grasp_rot(sim: &Simulation, r: Refs, home: &Matrix3<f64>) -> Matrix3<f64> {
    open_along(home, body_dir(sim, r.hammer, [0.0, 1.0, 0.0]))
}

fn drive_nail(refs: &SceneRefs, behaviour: &str, task_id: &str) -> Result<Box<dyn Expert>, TasksError> {
    let r = Refs {
        hammer: refs.instance_body("hammer_1")?,
        head_site: refs.site("hammer_1_head_site")?,
        nail_head_site: refs.site("hammer_block_1_nail_head_site")?,
        nail_q_adr: refs.joint("hammer_block_1_nail_slide")?.0,
    };
    if ![SOLVE, "partial_1", "partial_2", "undo", "push_with_gripper"].contains(&behaviour) {
        return Err(TasksError::Scene(format!("{task_id}: unknown behaviour {behaviour}")));
    }
    // start state: the hammer's resting height and the grasp orientation, captured before anything moves
    let rest_z: Memo<f64> = Memo::default();
    let rot0: Memo<Matrix3<f64>> = Memo::default();
    let q0: Memo<f64> = Memo::default();
    let mut phases = Vec::new();
    {
        let (rest_z, rot0, q0) = (rest_z.clone(), rot0.clone(), q0.clone());
        phases.push(Phase::new("note_start", move |sim, ctx| {
            rest_z.get_or(|| r.hammer_z(sim));
            q0.get_or(|| r.nail_q(sim));
            rot0.get_or(|| grasp_rot(sim, r, &ctx.home_rot));
            Goal::at(ctx.start_pos_m, GRIPPER_OPEN)
        }));
    }
    let held_rot = {
        let rot0 = rot0.clone();
        move |ctx: &PhaseCtx| rot0.get().unwrap_or(ctx.home_rot)
    };
    grasp_and_lift(&mut phases, r, held_rot.clone(), rest_z.clone());
    match behaviour {
        "partial_1" => {
            phases.push(Phase::new("hold_lifted", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(held_rot(ctx))).for_steps(20));
        }
        "undo" | "push_with_gripper" => {
            set_down(&mut phases, r, held_rot.clone(), rest_z.clone());
            if behaviour == "push_with_gripper" {
                push_with_fingers(&mut phases, r, q0.clone());
            }
        }
        _ => {
            turn_hammer(&mut phases, held_rot.clone());
            let turned = move |ctx: &PhaseCtx| rotate_world(&held_rot(ctx), Vector3::z(), PI);
            strike(&mut phases, r, turned, q0.clone(), behaviour == "partial_2");
        }
    }
    Ok(Box::new(Script::new(phases)))
}

/// Above the handle, down onto it, close, lift the hammer `LIFT_M` above its resting height.
fn grasp_and_lift(
    phases: &mut Vec<Phase>,
    r: Refs,
    rot: impl Fn(&PhaseCtx) -> Matrix3<f64> + Clone + Send + 'static,
    rest_z: Memo<f64>,
) {
    let (r0, r1, r2, r3, r4) = (rot.clone(), rot.clone(), rot.clone(), rot.clone(), rot);
    phases.push(
        Phase::new("above_handle", move |sim, ctx| Goal::at(r.grip_point(sim) + Vector3::z() * 0.10, GRIPPER_OPEN).rotated(r0(ctx)))
            .until(move |sim, ctx| {
                (grip_pose(sim).0 - (r.grip_point(sim) + Vector3::z() * 0.10)).norm() < 0.012 && rotation_error(sim, &r1(ctx)) < 0.05
            })
            .max_steps(150),
    );
    phases.push(
        Phase::new("down_to_handle", move |sim, ctx| Goal::at(r.grip_point(sim), GRIPPER_OPEN).slow(0.4).rotated(r2(ctx)))
            .until_reached(0.006)
            .max_steps(80),
    );
    phases.push(Phase::new("close_on_handle", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(r3(ctx))).for_steps(15));
    phases.push(
        Phase::new("lift_hammer", move |_, ctx| {
            Goal::at(ctx.start_pos_m + Vector3::z() * (LIFT_M + 0.02), GRIPPER_CLOSED).slow(0.5).rotated(r4(ctx))
        })
        .until(move |sim, _| r.hammer_z(sim) >= rest_z.get().unwrap_or(f64::INFINITY) + LIFT_M)
        .max_steps(80),
    );
}

/// Turns the held hammer by π about world z, a little per step (so the servo always turns the same way: +z keeps
/// the Panda's last joint inside its range), holding the hand where the lift left it.
fn turn_hammer(phases: &mut Vec<Phase>, rot: impl Fn(&PhaseCtx) -> Matrix3<f64> + Clone + Send + 'static) {
    let (r1, r2) = (rot.clone(), rot);
    phases.push(
        Phase::new("turn_hammer", move |_, ctx| {
            let angle = (f64::from(ctx.steps) * TURN_RATE_RAD).min(PI);
            Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(rotate_world(&r1(ctx), Vector3::z(), angle))
        })
        .until(move |sim, ctx| {
            f64::from(ctx.steps) * TURN_RATE_RAD >= PI && rotation_error(sim, &rotate_world(&r2(ctx), Vector3::z(), PI)) < 0.04
        })
        .max_steps(120),
    );
}

/// Brings the striking face in front of the nail head (first 6 cm back and 5 cm up, then down to its height, then
/// 3 cm back), then pushes along +y with the face's goal a little past the nail head until the nail is
/// `DRIVE_GOAL_M` in (`touch_only`: until it has moved `TOUCH_MOVE_M`), then backs the head away along −y and holds.
fn strike(
    phases: &mut Vec<Phase>,
    r: Refs,
    rot: impl Fn(&PhaseCtx) -> Matrix3<f64> + Clone + Send + 'static,
    q0: Memo<f64>,
    touch_only: bool,
) {
    let before = move |sim: &Simulation, back_m: f64, up_m: f64| r.nail_head(sim) - Vector3::y() * back_m + Vector3::z() * up_m;
    let (r1, r2, r3, r4, r5) = (rot.clone(), rot.clone(), rot.clone(), rot.clone(), rot);
    phases.push(
        Phase::new("head_behind_nail_high", move |sim, ctx| {
            Goal::at(r.face_to(sim, before(sim, 0.06, 0.05)), GRIPPER_CLOSED).slow(0.6).rotated(r1(ctx))
        })
        .until(move |sim, _| (r.striking_face(sim) - before(sim, 0.06, 0.05)).norm() < 0.01)
        .max_steps(200),
    );
    phases.push(
        Phase::new("head_down_to_nail_height", move |sim, ctx| {
            Goal::at(r.face_to(sim, before(sim, 0.03, 0.0)), GRIPPER_CLOSED).slow(0.4).rotated(r2(ctx))
        })
        .until(move |sim, _| (r.striking_face(sim) - before(sim, 0.03, 0.0)).norm() < 0.006)
        .max_steps(120),
    );
    let q_start = q0.clone();
    phases.push(
        Phase::new(if touch_only { "touch_nail" } else { "push_nail" }, move |sim, ctx| {
            // the face's goal stays 1.5 cm past the nail head: a steady push that follows the nail in
            Goal::at(r.face_to(sim, before(sim, -0.015, 0.0)), GRIPPER_CLOSED).slow(0.3).rotated(r3(ctx))
        })
        .until(move |sim, _| {
            // a nail that has moved has been touched: nothing else reaches it
            let goal_m = if touch_only { TOUCH_MOVE_M } else { DRIVE_GOAL_M };
            r.nail_q(sim) - q_start.get().unwrap_or(0.0) >= goal_m
        })
        .max_steps(200),
    );
    phases.push(
        Phase::new("back_off", move |_, ctx| Goal::at(ctx.start_pos_m - Vector3::y() * 0.05, GRIPPER_CLOSED).slow(0.4).rotated(r4(ctx)))
            .until_reached(0.008)
            .max_steps(60),
    );
    phases.push(Phase::new("hold", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(r5(ctx))).for_steps(10));
}

/// Lowers the held hammer back to its resting height, opens and moves the hand up.
fn set_down(
    phases: &mut Vec<Phase>,
    r: Refs,
    rot: impl Fn(&PhaseCtx) -> Matrix3<f64> + Clone + Send + 'static,
    rest_z: Memo<f64>,
) {
    let (r1, r2, r3) = (rot.clone(), rot.clone(), rot);
    phases.push(
        Phase::new("set_hammer_down", move |_, ctx| Goal::at(ctx.start_pos_m - Vector3::z() * LIFT_M, GRIPPER_CLOSED).slow(0.4).rotated(r1(ctx)))
            .until(move |sim, _| r.hammer_z(sim) <= rest_z.get().unwrap_or(0.0) + 0.01)
            .max_steps(80),
    );
    phases.push(Phase::new("release_hammer", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(r2(ctx))).for_steps(12));
    phases.push(
        Phase::new("hand_up", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.12, GRIPPER_OPEN).rotated(r3(ctx)))
            .until_reached(0.012)
            .max_steps(60),
    );
}

/// Drives the nail with the closed fingertips (hand turned so its narrow side faces the block), no hammer.
fn push_with_fingers(phases: &mut Vec<Phase>, r: Refs, q0: Memo<f64>) {
    let rot = |ctx: &PhaseCtx| open_along(&ctx.home_rot, Vector3::x());
    let before = move |sim: &Simulation, back_m: f64, up_m: f64| r.nail_head(sim) - Vector3::y() * back_m + Vector3::z() * up_m;
    phases.push(
        Phase::new("fingers_behind_nail_high", move |sim, ctx| Goal::at(before(sim, 0.05, 0.08), GRIPPER_CLOSED).slow(0.7).rotated(rot(ctx)))
            .until(move |sim, ctx| (grip_pose(sim).0 - before(sim, 0.05, 0.08)).norm() < 0.01 && rotation_error(sim, &rot(ctx)) < 0.05)
            .max_steps(200),
    );
    phases.push(
        Phase::new("fingers_down_to_nail", move |sim, ctx| Goal::at(before(sim, 0.03, 0.0), GRIPPER_CLOSED).slow(0.4).rotated(rot(ctx)))
            .until_reached(0.006)
            .max_steps(100),
    );
    phases.push(
        Phase::new("push_nail_with_fingers", move |sim, ctx| Goal::at(before(sim, -0.015, 0.0), GRIPPER_CLOSED).slow(0.3).rotated(rot(ctx)))
            .until(move |sim, _| r.nail_q(sim) - q0.get().unwrap_or(0.0) >= DRIVE_GOAL_M)
            .max_steps(200),
    );
    phases.push(
        Phase::new("fingers_back_off", move |_, ctx| Goal::at(ctx.start_pos_m - Vector3::y() * 0.05, GRIPPER_CLOSED).rotated(rot(ctx)))
            .until_reached(0.01)
            .max_steps(60),
    );
}
