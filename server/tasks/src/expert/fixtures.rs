//! Experts that work articulated LIBERO fixtures: pull the wooden cabinet's top drawer open (T15), swing the
//! microwave door open (T16), turn the flat stove's knob on (T17).
use nalgebra::{Matrix3, Rotation3, Unit, Vector3};

use libero_sim::Simulation;

use super::motion::{
    GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, PhaseCtx, Script, body_dir, body_point, grip_pose, open_along,
    open_along_near,    rotate_world, rotation_error, vec3,
};
use super::{Expert, SOLVE, SceneRefs};
use crate::TasksError;

const UP: Vector3<f64> = Vector3::new(0.0, 0.0, 1.0);

/// Fingers closing on something: wait until the opening has stopped shrinking (at most `max` steps).
fn settled_grip(max: u32) -> impl Fn(&Simulation, &PhaseCtx) -> bool + Send {
    move |sim, ctx| ctx.steps >= max || (ctx.steps >= 8 && sim.data().qvel()[sim.ids().finger_dof_adr[0]].abs() < 1e-3)
}

/// A hand that turns with a hinged part: at hinge angle `angle`, the home orientation turned about world z so the
/// fingers open along `local_dir` of `body` as it lies at hinge angle 0, then turned by `angle` about the hinge axis.
#[derive(Clone, Copy)]
struct HingeHand {
    body: usize,
    local_dir: [f64; 3],
    joint: usize,
    q_adr: usize,
}

impl HingeHand {
    fn q(&self, sim: &Simulation) -> f64 {
        sim.data().qpos()[self.q_adr]
    }

    fn axis(&self, sim: &Simulation) -> Vector3<f64> {
        vec3(&sim.data().xaxis()[self.joint])
    }

    fn rot(&self, sim: &Simulation, ctx: &PhaseCtx, angle: f64) -> Matrix3<f64> {
        let axis = Unit::new_normalize(self.axis(sim));
        let dir0 = Rotation3::from_axis_angle(&axis, -self.q(sim)) * body_dir(sim, self.body, self.local_dir);
        // prefer a small positive turn: the microwave door's plane lies right at the ±π/2 tie
        rotate_world(&open_along_near(&ctx.home_rot, dir0, 0.3), *axis, angle)
    }

    /// [`Self::rot`] with the hand first pitched by `pitch_rad` about the fingers' opening axis at hinge angle 0, the
    /// sign chosen so that positive pitch tips the fingertips toward the robot's base (world −x).
    fn rot_pitched(&self, sim: &Simulation, ctx: &PhaseCtx, angle: f64, pitch_rad: f64) -> Matrix3<f64> {
        if pitch_rad == 0.0 {
            return self.rot(sim, ctx, angle);
        }
        let axis = Unit::new_normalize(self.axis(sim));
        let dir0 = Rotation3::from_axis_angle(&axis, -self.q(sim)) * body_dir(sim, self.body, self.local_dir);
        let open0 = open_along_near(&ctx.home_rot, dir0, 0.3);
        // the (horizontal) opening axis, signed toward +y: a positive turn about +y swings the downward approach
        // direction toward −x
        let across = Vector3::new(dir0.x, dir0.y, 0.0);
        let across = if across.y < 0.0 { -across } else { across };
        rotate_world(&rotate_world(&open0, across, pitch_rad), *axis, angle)
    }
}

/// Above the grasp point, a few centimetres over it, down onto it slowly (the arm lags its goal; a straight slow
/// descent keeps the fingers off the part), then close until the fingers stop. `names`: the four phases' names.
fn reach_and_grip(
    names: [&'static str; 4],
    grasp: impl Fn(&Simulation) -> Vector3<f64> + Copy + Send + 'static,
    rot: impl Fn(&Simulation, &PhaseCtx) -> Matrix3<f64> + Copy + Send + 'static,
) -> Vec<Phase> {
    vec![
        // turned fully before going down: a hand still turning sweeps its fingers into the part
        Phase::new(names[0], move |sim, ctx| Goal::at(grasp(sim) + UP * 0.10, GRIPPER_OPEN).rotated(rot(sim, ctx)))
            .until(move |sim, ctx| {
                (grip_pose(sim).0 - (grasp(sim) + UP * 0.10)).norm() < 0.01 && rotation_error(sim, &rot(sim, ctx)) < 0.05
            })
            .max_steps(120),
        Phase::new(names[1], move |sim, ctx| Goal::at(grasp(sim) + UP * 0.03, GRIPPER_OPEN).slow(0.4).rotated(rot(sim, ctx)))
            .until_reached(0.006)
            .max_steps(80),
        Phase::new(names[2], move |sim, ctx| Goal::at(grasp(sim), GRIPPER_OPEN).slow(0.25).rotated(rot(sim, ctx)))
            .until_reached(0.004)
            .max_steps(60),
        Phase::new(names[3], move |sim, ctx| Goal::at(grasp(sim), GRIPPER_CLOSED).rotated(rot(sim, ctx)))
            .until(settled_grip(15))
            .max_steps(20),
    ]
}

/// LIBERO wooden cabinet top drawer: handle bar centre in the drawer body's frame and the outward direction.
const DRAWER_HANDLE_LOCAL_M: [f64; 3] = [-0.00278, -0.10161, 0.18393];
const DRAWER_OUT_LOCAL: [f64; 3] = [0.0, -1.0, 0.0];

/// T15: the handle bar stands only 1.6 cm proud of the drawer front, too narrow a slot for a finger from above, so
/// the hand comes at it from the front: pointing into the drawer, fingers opening vertically, it closes on the bar
/// from above and below and pulls outward until the slide reads `q_goal`. `pull_half` stops 7 cm out (open needs
/// q < −0.14).
pub fn open_top_drawer(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let drawer = refs.body("wooden_cabinet_1_cabinet_top")?;
    let (q_adr, _) = refs.joint("wooden_cabinet_1_top_level")?;
    let q_goal = if behaviour == SOLVE { -0.152 } else { -0.07 };
    let handle = move |sim: &Simulation| body_point(sim, drawer, DRAWER_HANDLE_LOCAL_M);
    let out = move |sim: &Simulation| body_dir(sim, drawer, DRAWER_OUT_LOCAL);
    let q = move |sim: &Simulation| sim.data().qpos()[q_adr];
    // fingers along the pull, then the hand tipped a quarter about the horizontal across the pull: it points into
    // the drawer and the fingers open vertically
    let rot = move |sim: &Simulation, ctx: &PhaseCtx| {
        let o = out(sim);
        rotate_world(&open_along(&ctx.home_rot, o), UP.cross(&o), std::f64::consts::FRAC_PI_2)
    };
    // the grip site a few millimetres past the bar's centre: the pads sit just behind the site
    let at = move |sim: &Simulation, out_m: f64| handle(sim) + out(sim) * out_m;
    Ok(Box::new(Script::new(vec![
        Phase::new("in_front_of_handle", move |sim, ctx| Goal::at(at(sim, 0.12), GRIPPER_OPEN).rotated(rot(sim, ctx)))
            .until(move |sim, ctx| {
                (grip_pose(sim).0 - at(sim, 0.12)).norm() < 0.01 && rotation_error(sim, &rot(sim, ctx)) < 0.05
            })
            .max_steps(150),
        Phase::new("onto_handle", move |sim, ctx| Goal::at(at(sim, -0.003), GRIPPER_OPEN).slow(0.3).rotated(rot(sim, ctx)))
            .until_reached(0.004)
            .max_steps(80),
        Phase::new("grip_handle", move |sim, ctx| Goal::at(at(sim, -0.003), GRIPPER_CLOSED).rotated(rot(sim, ctx)))
            .until(settled_grip(15))
            .max_steps(20),
        Phase::new("pull_drawer", move |sim, ctx| {
            // lead the handle outward; the goal follows the drawer as it slides
            let lead = (q(sim) - q_goal).clamp(0.0, 0.05) + 0.01;
            Goal::at(at(sim, lead), GRIPPER_CLOSED).slow(0.5).rotated(rot(sim, ctx))
        })
        .until(move |sim, _| q(sim) <= q_goal)
        .max_steps(200),
        Phase::new("release", move |sim, ctx| Goal::at(at(sim, 0.0), GRIPPER_OPEN).rotated(rot(sim, ctx))).for_steps(8),
        Phase::new("back_away", move |sim, ctx| Goal::at(at(sim, 0.10), GRIPPER_OPEN).rotated(rot(sim, ctx)))
            .until_reached(0.02)
            .max_steps(40),
    ])))
}

/// LIBERO microwave: a point on the door handle (vertical capsule) a little below its upper standoff, in the door
/// body's frame; the door's local +x runs from the hinge toward the handle.
const MICROWAVE_GRASP_LOCAL_M: [f64; 3] = [0.2375, -0.058, 0.050];

/// T16: grasp the handle from above (fingers opening along the door plane), then carry it along the arc about the
/// hinge, the goal leading the door by a fixed angle and the hand turning with the door, until the hinge reads
/// `q_goal` (open needs q < −1.3 rad). `open_partly` stops at −0.9 rad.
pub fn open_microwave(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let q_goal = if behaviour == SOLVE { -1.45 } else { -0.9 };
    Ok(Box::new(Script::new(microwave_door_phases(refs, "microwave_1", q_goal)?)))
}

/// The phases of [`open_microwave`] for the LIBERO microwave `microwave`, swinging its door to `q_goal` (rad).
pub fn microwave_door_phases(refs: &SceneRefs, microwave: &str, q_goal: f64) -> Result<Vec<Phase>, TasksError> {
    let door = refs.body(&format!("{microwave}_microdoorroot"))?;
    let (q_adr, joint) = refs.joint(&format!("{microwave}_microjoint"))?;
    let q = move |sim: &Simulation| sim.data().qpos()[q_adr];
    let grasp = move |sim: &Simulation| body_point(sim, door, MICROWAVE_GRASP_LOCAL_M);
    let anchor = move |sim: &Simulation| vec3(&sim.data().xanchor()[joint]);
    // fingers open along the door plane
    let hand = HingeHand { body: door, local_dir: [1.0, 0.0, 0.0], joint, q_adr };
    let axis = move |sim: &Simulation| hand.axis(sim);
    let rot_at = move |sim: &Simulation, ctx: &PhaseCtx, angle: f64| hand.rot(sim, ctx, angle);
    const LEAD_RAD: f64 = 0.15;
    let mut phases = reach_and_grip(["above_handle", "near_handle", "down_to_handle", "grip_handle"], grasp, move |sim, ctx| {
        rot_at(sim, ctx, q(sim))
    });
    phases.extend([
        Phase::new("swing_door", move |sim, ctx| {
            let lead = LEAD_RAD.min(q(sim) - q_goal + 0.05).max(0.05);
            let spin = Rotation3::from_axis_angle(&Unit::new_normalize(axis(sim)), -lead);
            let a = anchor(sim);
            let target = a + spin * (grasp(sim) - a);
            // the handle ends near the arm's reach: tip the fingers away from the robot as the door opens (about
            // the fingers' opening axis, the door's plane), which brings the wrist back toward the base
            let a = body_dir(sim, door, [1.0, 0.0, 0.0]);
            let tilt = -0.6 * (-q(sim) / 1.45).clamp(0.0, 1.0);
            Goal::at(target, GRIPPER_CLOSED).slow(0.3).rotated(rotate_world(&rot_at(sim, ctx, q(sim) - lead), a, tilt))
        })
        .until(move |sim, _| q(sim) <= q_goal)
        .max_steps(300),
        // keep the tipped hand as it is while letting go and rising: turning it back near the door swats it shut
        Phase::new("release", move |sim, _| Goal::at(grasp(sim), GRIPPER_OPEN).rotated(grip_pose(sim).1)).for_steps(8),
        Phase::new("lift_away", move |sim, ctx| {
            Goal::at(ctx.start_pos_m + UP * 0.12, GRIPPER_OPEN).rotated(grip_pose(sim).1)
        })
        .until_reached(0.02)
        .max_steps(40),
    ]);
    Ok(phases)
}

/// A point on the inner face of the LIBERO microwave's door near its free end, in the door body's frame (the door's
/// local +y faces into the cavity when closed).
const MICROWAVE_DOOR_INNER_LOCAL_M: [f64; 3] = [0.20, 0.06, 0.0];

/// Phases that push the LIBERO microwave `microwave`'s open door wider, to `q_goal` (rad, more negative = wider),
/// with the closed hand on the door's inner face near its free end: [`microwave_door_phases`] leaves it near a right
/// angle, where a hand working in front of the opening still catches it.
pub fn push_microwave_door_wider(refs: &SceneRefs, microwave: &str, q_goal: f64) -> Result<Vec<Phase>, TasksError> {
    let door = refs.body(&format!("{microwave}_microdoorroot"))?;
    let (q_adr, _) = refs.joint(&format!("{microwave}_microjoint"))?;
    let q = move |sim: &Simulation| sim.data().qpos()[q_adr];
    // `out_m` along the door's inward normal from its inner face (negative: past the door, pushing it)
    let at = move |sim: &Simulation, out_m: f64| {
        let [x, y, z] = MICROWAVE_DOOR_INNER_LOCAL_M;
        body_point(sim, door, [x, y + out_m, z])
    };
    Ok(vec![
        Phase::new("above_door_inside", move |sim, _| Goal::at(at(sim, 0.04) + UP * 0.15, GRIPPER_CLOSED)).until_reached(0.015).max_steps(150),
        Phase::new("down_door_inside", move |sim, _| Goal::at(at(sim, 0.04), GRIPPER_CLOSED).slow(0.5)).until_reached(0.01).max_steps(80),
        Phase::new("push_door_wider", move |sim, _| Goal::at(at(sim, -0.05), GRIPPER_CLOSED).slow(0.4))
            .until(move |sim, _| q(sim) <= q_goal)
            .max_steps(150),
        Phase::new("off_door", move |_, ctx| Goal::at(ctx.start_pos_m + UP * 0.15, GRIPPER_CLOSED))
            .until_reached(0.015)
            .max_steps(60),
    ])
}

/// How far the hand leads a knob turned down (off), by the angle left to the goal (rad): the full lead while far,
/// less near the stop, so the knob (inertia 1 kg m²) meets its stop slowly instead of rebounding off it to q > 0; never
/// under 0.1 rad, below which the pinch's play leaves the knob standing.
fn off_lead_rad(left_rad: f64) -> f64 {
    const GAIN: f64 = 2.0;
    const MIN_RAD: f64 = 0.1;
    (GAIN * left_rad + MIN_RAD).clamp(MIN_RAD, KNOB_LEAD_RAD)
}

/// How far the hand leads the knob while turning it (rad).
const KNOB_LEAD_RAD: f64 = 0.3;

/// LIBERO flat stove knob: a point between the fingers on the knob's ridge (which runs along the knob's local y),
/// in the knob body's frame.
const KNOB_GRASP_LOCAL_M: [f64; 3] = [0.0014, 0.012, 0.035];

/// T17: pinch the knob's ridge from above and turn the hand about the knob's axis, leading the knob, until the
/// hinge reads `q_goal` (on needs q ≥ 0.5 rad); hold still until the knob stops, then let go.
/// `turn_slightly` stops the turn at 0.2 rad (the knob coasts to ≈ 0.3).
pub fn turn_on_stove(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let q_goal = if behaviour == SOLVE { 0.9 } else { 0.2 };
    Ok(Box::new(Script::new(stove_knob_phases(refs, "flat_stove_1", q_goal)?)))
}

/// The phases of [`turn_on_stove`] for the LIBERO flat stove `stove`, turning its knob up to `q_goal` (rad).
pub fn stove_knob_phases(refs: &SceneRefs, stove: &str, q_goal: f64) -> Result<Vec<Phase>, TasksError> {
    stove_knob_phases_toward(refs, stove, q_goal)
}

/// As [`stove_knob_phases`], turning the knob toward `q_goal` from wherever it is when the turn starts: up (on) or
/// down (off, a knob left on; slowing near the stop and letting go without turning the hand back, so the knob stays
/// on the stop below 0).
pub fn stove_knob_phases_toward(refs: &SceneRefs, stove: &str, q_goal: f64) -> Result<Vec<Phase>, TasksError> {
    stove_knob_phases_pitched(refs, stove, q_goal, 0.0)
}

/// As [`stove_knob_phases_toward`], the hand pitched by `pitch_rad` about the fingers' opening axis (positive: the
/// fingertips point back toward the robot and the wrist stands out past the knob). For a knob close to the robot's
/// base (the cooking scene's first stove, 26 cm in front of it) a hand pointing straight down turns the knob with
/// the elbow folded onto its joint limit; pitched, the elbow stays off it.
pub fn stove_knob_phases_pitched(refs: &SceneRefs, stove: &str, q_goal: f64, pitch_rad: f64) -> Result<Vec<Phase>, TasksError> {
    let knob = refs.body(&format!("{stove}_button"))?;
    let (q_adr, joint) = refs.joint(&format!("{stove}_button"))?;
    let dof = refs.model.jnt_dofadr()[joint] as usize;
    let q = move |sim: &Simulation| sim.data().qpos()[q_adr];
    // +1 turns up, −1 down; fixed when the turn starts
    let sign = std::sync::Arc::new(std::sync::Mutex::new(None::<f64>));
    let s = sign.clone();
    let dir = move |sim: &Simulation| *s.lock().unwrap_or_else(std::sync::PoisonError::into_inner).get_or_insert_with(|| if q(sim) <= q_goal { 1.0 } else { -1.0 });
    let reached = {
        let dir = dir.clone();
        move |sim: &Simulation| (q(sim) - q_goal) * dir(sim) >= 0.0
    };
    let grasp = move |sim: &Simulation| body_point(sim, knob, KNOB_GRASP_LOCAL_M);
    // fingers open across the ridge (the knob's local x)
    let hand = HingeHand { body: knob, local_dir: [1.0, 0.0, 0.0], joint, q_adr };
    let rot_at = move |sim: &Simulation, ctx: &PhaseCtx, angle: f64| hand.rot_pitched(sim, ctx, angle, pitch_rad);
    const OFF_HOLD_PAST_RAD: f64 = 0.15;
    let mut phases = reach_and_grip(["above_knob", "near_knob", "down_to_knob", "pinch_knob"], grasp, move |sim, ctx| {
        rot_at(sim, ctx, q(sim))
    });
    let (d1, d2, d3, r1) = (dir.clone(), dir.clone(), dir, reached);
    // the hand's orientation when the fingers start to open, kept while they open and rise (see below)
    let frozen = std::sync::Arc::new(std::sync::Mutex::new(None::<Matrix3<f64>>));
    let (f1, f2) = (frozen.clone(), frozen);
    let keep = move |cell: &std::sync::Mutex<Option<Matrix3<f64>>>, sim: &Simulation| {
        *cell.lock().unwrap_or_else(std::sync::PoisonError::into_inner).get_or_insert_with(|| grip_pose(sim).1)
    };
    phases.extend([
        Phase::new("turn_knob", move |sim, ctx| {
            let lead = if d1(sim) < 0.0 { off_lead_rad(q(sim) - q_goal) } else { KNOB_LEAD_RAD };
            Goal::at(grasp(sim), GRIPPER_CLOSED).rotated(rot_at(sim, ctx, q(sim) + lead * d1(sim)))
        })
        .until(move |sim, _| r1(sim))
        .max_steps(200),
        // turning down, the knob ends on its stop (−0.005 rad, off needs q < 0) and its large inertia (1 kg m²)
        // keeps it moving: keep pushing it into the stop until it is still. (Turning the hand back toward the goal
        // here would drag the pinched knob up off the stop.)
        Phase::new("hold_still", move |sim, ctx| {
            let angle = if d2(sim) < 0.0 { q(sim) - OFF_HOLD_PAST_RAD } else { q_goal };
            Goal::at(grasp(sim), GRIPPER_CLOSED).rotated(rot_at(sim, ctx, angle))
        })
            .until(move |sim, ctx| ctx.steps >= 4 && sim.data().qvel()[dof].abs() < 0.02)
            .max_steps(40),
        // turning down, let go without turning the hand at all: any turn back while the fingers still touch the
        // ridge lifts the knob off its stop (the servo holds the orientation the hand has as the fingers open)
        Phase::new("release", move |sim, ctx| {
            let rot = if d3(sim) < 0.0 { keep(&f1, sim) } else { rot_at(sim, ctx, q(sim)) };
            Goal::at(grasp(sim), GRIPPER_OPEN).rotated(rot)
        })
        .for_steps(8),
        Phase::new("lift_away", move |sim, ctx| {
            // (the orientation kept while letting go of a knob turned down, if any)
            let kept = *f2.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            let rot = kept.unwrap_or_else(|| rot_at(sim, ctx, q(sim)));
            Goal::at(grasp(sim) + UP * 0.10, GRIPPER_OPEN).rotated(rot)
        })
        .until_reached(0.02)
        .max_steps(40),
    ]);
    Ok(phases)
}
