//! T28 expert: the robosuite locked door. The hand points into the door with its fingers across the handle lever,
//! grips it, turns it with a wrist roll about the latch axis until the bolt clears the frame post, then pulls the
//! door open along the hinge arc while holding the handle turned. Every goal is recomputed each control step from the
//! door's and the latch's current pose (privileged state), so the hand follows the lever and the door as they move.
//!
//! Behaviours: `solve` (both stages), `partial_1` (unlatch, swing the door just past the bolt, let go: stage 1 only),
//! `undo` (turn the handle, then let it spring back before opening: stage 1 regresses), `pull_without_unlatching`
//! (the bolt holds the door: no stage).
use nalgebra::{Matrix3, Rotation3, Unit, Vector3};

use libero_sim::Simulation;

use crate::expert::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, Script, body_point, grip_pose, mat3, rotation_error};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};
use crate::TasksError;

pub const EXPERTS: &[ExpertEntry] =
    &[ExpertEntry { task: "T28", behaviours: &["partial_1", "undo", "pull_without_unlatching"], build: open_door }];

/// T28: grip the handle, then per behaviour (see the module documentation).
fn open_door(refs: &SceneRefs, behaviour: &str, task_id: &str) -> Result<Box<dyn Expert>, TasksError> {
    let door = Door {
        body: refs.body("latched_door_1_door")?,
        hinge_adr: refs.joint("latched_door_1_hinge")?.0,
        latch_adr: refs.joint("latched_door_1_latch_joint")?.0,
    };
    let mut phases = grasp_handle(door);
    match behaviour {
        SOLVE => {
            phases.push(turn_handle(door));
            phases.push(pull_door(door, "pull_door", TURNED_RAD, OPEN_GOAL_RAD, 200));
            phases.extend(let_go(door, TURNED_RAD));
        }
        "partial_1" => {
            phases.push(turn_handle(door));
            // past the furthest the bolt lets a latched door swing (≈ 0.12 rad), well short of open (0.3 rad)
            phases.push(pull_door(door, "swing_past_bolt", TURNED_RAD, 0.22, 120));
            phases.extend(let_go_unwound(door, TURNED_RAD));
        }
        // the handle goes back to rest with the open hand: the door is latched again
        "undo" => {
            phases.push(turn_handle(door));
            phases.extend(let_go_unwound(door, TURNED_RAD));
        }
        // the bolt meets the post after a few hundredths of a radian; the pull gives up after its step budget
        "pull_without_unlatching" => {
            phases.push(pull_door(door, "pull_latched_door", 0.0, OPEN_GOAL_RAD, 80));
            phases.extend(let_go(door, 0.0));
        }
        b => return Err(TasksError::Scene(format!("{task_id}: unknown behaviour {b}"))),
    }
    Ok(Box::new(Script::new(phases)))
}

/// Handle angle the expert turns to (rad): past the measured bolt clearance (1.23 rad) and short of the joint's
/// ±1.57 stop.
const TURNED_RAD: f64 = 1.42;
/// Hinge angle the pull stops at (rad): past the `Open` threshold 0.3 by enough that the door does not dip below it
/// while the fingers let go, short of the 0.4 stop.
const OPEN_GOAL_RAD: f64 = 0.37;
/// Where the fingers close on the lever, in the latch body's frame (the lever box spans x ∈ [0, 0.15] at y = −0.10;
/// the hidden `handle` site is at x = 0.125): far enough from the hub for leverage, clear of the lever's end.
const GRASP_LOCAL_M: [f64; 3] = [0.11, -0.10, 0.0];
/// Latch body origin in the door body's frame (catalog §6.7).
const LATCH_IN_DOOR_M: [f64; 3] = [-0.175, 0.0, -0.025];
/// Hinge axis point in the door body's frame; the axis is the door's z.
const HINGE_IN_DOOR_M: [f64; 3] = [0.255, 0.0, 0.0];
/// Stand-off from the lever before moving in along the approach direction (m).
const STANDOFF_M: f64 = 0.10;

/// The door's ids; everything else is read from the state.
#[derive(Clone, Copy)]
struct Door {
    body: usize,
    hinge_adr: usize,
    latch_adr: usize,
}

impl Door {
    fn hinge(&self, sim: &Simulation) -> f64 {
        sim.data().qpos()[self.hinge_adr]
    }

    fn latch(&self, sim: &Simulation) -> f64 {
        sim.data().qpos()[self.latch_adr]
    }

    fn rot(&self, sim: &Simulation) -> Matrix3<f64> {
        mat3(&sim.data().xmat()[self.body])
    }

    /// Rotation by `ahead_rad` about the hinge axis (the door opening further), and the hinge point.
    fn swing(&self, sim: &Simulation, ahead_rad: f64) -> (Rotation3<f64>, Vector3<f64>) {
        let axis = Unit::new_normalize(self.rot(sim) * Vector3::z());
        (Rotation3::from_axis_angle(&axis, ahead_rad), body_point(sim, self.body, HINGE_IN_DOOR_M))
    }

    /// The latch frame at handle angle `latch_rad` (the door body's frame turned about its y, the latch axis).
    fn latch_rot(&self, sim: &Simulation, latch_rad: f64) -> Matrix3<f64> {
        self.rot(sim) * Rotation3::from_axis_angle(&Vector3::y_axis(), latch_rad).matrix()
    }

    /// The grasp point on the lever with the handle at `latch_rad` and the door `ahead_rad` further open than now.
    fn grasp(&self, sim: &Simulation, latch_rad: f64, ahead_rad: f64) -> Vector3<f64> {
        let p = body_point(sim, self.body, LATCH_IN_DOOR_M) + self.latch_rot(sim, latch_rad) * Vector3::from(GRASP_LOCAL_M);
        let (r, hinge) = self.swing(sim, ahead_rad);
        hinge + r * (p - hinge)
    }

    /// The grip-site orientation on the lever: its z (approach) along the latch axis into the door, its x (the
    /// fingers' opening) across the lever, i.e. along the latch frame's −z. Of the two finger directions this is the
    /// one a quarter turn from the home pose (pointing down, fingers along world y); the other is a half turn away.
    fn grip_rot(&self, sim: &Simulation, latch_rad: f64, ahead_rad: f64) -> Matrix3<f64> {
        let l = self.latch_rot(sim, latch_rad);
        let z = l * Vector3::y();
        let x = -(l * Vector3::z());
        let r = Matrix3::from_columns(&[x, z.cross(&x), z]);
        self.swing(sim, ahead_rad).0.matrix() * r
    }

    /// Approach direction (into the door), world frame.
    fn inward(&self, sim: &Simulation) -> Vector3<f64> {
        self.rot(sim) * Vector3::y()
    }
}

/// Line up in front of the lever, move in along the latch axis, close on it.
fn grasp_handle(door: Door) -> Vec<Phase> {
    let front = move |sim: &Simulation| door.grasp(sim, 0.0, 0.0) - door.inward(sim) * STANDOFF_M;
    vec![
        // turned fully before moving in: a hand still turning sweeps its fingers into the lever
        Phase::new("in_front_of_handle", move |sim, _| Goal::at(front(sim), GRIPPER_OPEN).rotated(door.grip_rot(sim, 0.0, 0.0)))
            .until(move |sim, _| {
                (grip_pose(sim).0 - front(sim)).norm() < 0.01 && rotation_error(sim, &door.grip_rot(sim, 0.0, 0.0)) < 0.05
            })
            .max_steps(150),
        Phase::new("onto_handle", move |sim, _| {
            Goal::at(door.grasp(sim, 0.0, 0.0), GRIPPER_OPEN).slow(0.3).rotated(door.grip_rot(sim, 0.0, 0.0))
        })
        .until_reached(0.005)
        .max_steps(80),
        Phase::new("grip_handle", move |sim, _| {
            Goal::at(door.grasp(sim, 0.0, 0.0), GRIPPER_CLOSED).rotated(door.grip_rot(sim, 0.0, 0.0))
        })
        .for_steps(15),
    ]
}

/// Roll the wrist about the latch axis, the goal leading the handle by at most 0.2 rad, until it reads
/// [`TURNED_RAD`].
fn turn_handle(door: Door) -> Phase {
    let cmd = move |sim: &Simulation| (door.latch(sim) + 0.2).min(TURNED_RAD);
    Phase::new("turn_handle", move |sim, _| {
        let q = cmd(sim);
        Goal::at(door.grasp(sim, q, 0.0), GRIPPER_CLOSED).rotated(door.grip_rot(sim, q, 0.0))
    })
    .until(move |sim, _| door.latch(sim) >= TURNED_RAD - 0.04)
    .max_steps(120)
}

/// Pull the lever along the hinge arc, the goal leading the door by 0.05 to 0.15 rad (a smaller lead stalls the
/// arm against the handle's spring short of the goal), holding the handle at
/// `latch_rad`, until the hinge reads `goal_rad` (or `max_steps` pass).
fn pull_door(door: Door, name: &'static str, latch_rad: f64, goal_rad: f64, max_steps: u32) -> Phase {
    Phase::new(name, move |sim, _| {
        let ahead = (goal_rad - door.hinge(sim)).clamp(0.0, 0.1) + 0.05;
        Goal::at(door.grasp(sim, latch_rad, ahead), GRIPPER_CLOSED).slow(0.5).rotated(door.grip_rot(sim, latch_rad, ahead))
    })
    .until(move |sim, _| door.hinge(sim) >= goal_rad)
    .max_steps(max_steps)
}

/// Open the fingers with the hand held where the handle was turned to (`latch_rad`; a hand that tracked the lever
/// would push it on to its stop).
fn open_fingers(door: Door, latch_rad: f64) -> Phase {
    Phase::new("release_handle", move |sim, _| {
        Goal::at(door.grasp(sim, latch_rad, 0.0), GRIPPER_OPEN).rotated(door.grip_rot(sim, latch_rad, 0.0))
    })
    .for_steps(10)
}

/// Back straight out along the latch axis, keeping the hand's orientation.
fn back_away(door: Door) -> Phase {
    Phase::new("back_away", move |sim, ctx| {
        Goal::at(ctx.start_pos_m - door.inward(sim) * STANDOFF_M, GRIPPER_OPEN).rotated(grip_pose(sim).1)
    })
    .until_reached(0.02)
    .max_steps(60)
}

/// Let go of an opened door: open the fingers and back out. The turned lever's spring presses it on a pad, whose
/// friction drags the door a little further open on the way out (harmless once it is open).
fn let_go(door: Door, latch_rad: f64) -> Vec<Phase> {
    vec![open_fingers(door, latch_rad), back_away(door)]
}

/// Let go so that the door stays where it is: open the fingers, roll the open hand back to the handle's rest angle so
/// the lever returns with it instead of pressing on a pad, then back out.
fn let_go_unwound(door: Door, latch_rad: f64) -> Vec<Phase> {
    let rest = move |sim: &Simulation| (door.grasp(sim, 0.0, 0.0), door.grip_rot(sim, 0.0, 0.0));
    vec![
        open_fingers(door, latch_rad),
        Phase::new("unwind_hand", move |sim, _| {
            let (p, r) = rest(sim);
            Goal::at(p, GRIPPER_OPEN).slow(0.5).rotated(r)
        })
        .until(move |sim, _| {
            let (p, r) = rest(sim);
            (grip_pose(sim).0 - p).norm() < 0.01 && rotation_error(sim, &r) < 0.05
        })
        .max_steps(60),
        back_away(door),
    ]
}
