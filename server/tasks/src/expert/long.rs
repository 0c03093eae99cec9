//! Experts for the long-horizon tasks (T21–T30). Each task has `solve`, `partial_<n>` behaviours that complete
//! exactly n stages and stop, and `undo`, which completes a stage and then undoes it (the evaluator must record the
//! regression).
use std::sync::{Arc, Mutex};

use libero_sim::Simulation;
use nalgebra::{Matrix3, Vector3};

use super::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, PhaseCtx, Script, grip_pose, vec3};
use super::{Expert, SOLVE, SceneRefs};
use crate::TasksError;

pub fn behaviours(task_id: &str) -> Option<&'static [&'static str]> {
    Some(match task_id {
        "T26" => &["partial_1", "partial_2", "undo"],
        _ => return None,
    })
}

pub fn build(task_id: &str, behaviour: &str, refs: &SceneRefs) -> Result<Box<dyn Expert>, TasksError> {
    match task_id {
        "T26" => cabinet_transfer(refs, behaviour),
        _ => Err(TasksError::Scene(format!("no scripted expert for task {task_id}"))),
    }
}

/// `partial_<n>` → n.
fn partial_count(behaviour: &str) -> Option<usize> {
    behaviour.strip_prefix("partial_").and_then(|n| n.parse().ok())
}

fn pos(sim: &Simulation, body: usize) -> Vector3<f64> {
    vec3(&sim.data().xpos()[body])
}

fn xy_dist(a: Vector3<f64>, b: Vector3<f64>) -> f64 {
    (a.x - b.x).hypot(a.y - b.y)
}

/// The grip-site goal that brings a held object's root to `target` (closed loop on the object's pose).
fn carry(sim: &Simulation, body: usize, target: Vector3<f64>) -> Vector3<f64> {
    grip_pose(sim).0 + (target - pos(sim, body))
}

/// A target for an object's root, computed from the state (and whatever the closure captured).
type TargetFn = Arc<dyn Fn(&Simulation) -> Vector3<f64> + Send + Sync>;

/// Pick `body` from above (fingers closing `grasp_dz_m` above its root), carry it at `carry_z_m` (absolute
/// world height of the root) to above `target`, lower it until the root is ≈ 1 cm above `target`, open and retreat.
fn pick_place(phases: &mut Vec<Phase>, body: usize, grasp_dz_m: f64, carry_z_m: f64, target: TargetFn) {
    pick_place_turned(phases, body, grasp_dz_m, carry_z_m, target, Arc::new(|_, ctx| ctx.home_rot));
}

/// The hand's orientation for a pick (from the state and the phase context).
type RotFn = Arc<dyn Fn(&Simulation, &PhaseCtx) -> Matrix3<f64> + Send + Sync>;

/// [`pick_place`] with the hand turned by `rot` throughout.
fn pick_place_turned(phases: &mut Vec<Phase>, body: usize, grasp_dz_m: f64, carry_z_m: f64, target: TargetFn, rot: RotFn) {
    let grasp = move |sim: &Simulation| pos(sim, body) + Vector3::z() * grasp_dz_m;
    let r = move |k: &RotFn| {
        let k = k.clone();
        move |sim: &Simulation, ctx: &PhaseCtx| k(sim, ctx)
    };
    let (r1, r2, r3, r4, r5, r6, r7, r8) = (r(&rot), r(&rot), r(&rot), r(&rot), r(&rot), r(&rot), r(&rot), r(&rot));
    phases.push(Phase::new("above_object", move |sim, ctx| Goal::at(grasp(sim) + Vector3::z() * 0.10, GRIPPER_OPEN).rotated(r1(sim, ctx))).until_reached(0.015).max_steps(150));
    phases.push(Phase::new("down_to_object", move |sim, ctx| Goal::at(grasp(sim), GRIPPER_OPEN).slow(0.5).rotated(r2(sim, ctx))).until_reached(0.008).max_steps(60));
    phases.push(Phase::new("close", move |sim, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(r3(sim, ctx))).for_steps(12));
    phases.push(
        Phase::new("lift", move |sim, ctx| {
            let mut g = ctx.start_pos_m;
            g.z += carry_z_m - pos(sim, body).z;
            Goal::at(g, GRIPPER_CLOSED).slow(0.6).rotated(r4(sim, ctx))
        })
        .until(move |sim, _| pos(sim, body).z > carry_z_m - 0.01)
        .max_steps(60),
    );
    let t1 = target.clone();
    phases.push(
        Phase::new("carry_over_target", move |sim, ctx| {
            let t = t1(sim);
            Goal::at(carry(sim, body, Vector3::new(t.x, t.y, carry_z_m)), GRIPPER_CLOSED).slow(0.7).rotated(r5(sim, ctx))
        })
        .until({
            let t = target.clone();
            move |sim, _| xy_dist(pos(sim, body), t(sim)) < 0.008
        })
        .max_steps(150),
    );
    let t2 = target.clone();
    phases.push(
        Phase::new("lower", move |sim, ctx| {
            Goal::at(carry(sim, body, t2(sim) + Vector3::z() * 0.008), GRIPPER_CLOSED).slow(0.4).rotated(r6(sim, ctx))
        })
            .until({
                let t = target.clone();
                move |sim, _| pos(sim, body).z < t(sim).z + 0.015
            })
            .max_steps(60),
    );
    phases.push(Phase::new("open", move |sim, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(r7(sim, ctx))).for_steps(10));
    phases.push(
        Phase::new("retreat", move |sim, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.10, GRIPPER_OPEN).rotated(r8(sim, ctx)))
            .until_reached(0.015)
            .max_steps(40),
    );
}

/// Remembers a value computed on the first call (positions at the start of the run).
fn memo<T: Copy + Send + 'static>(f: impl Fn(&Simulation) -> T + Send + Sync + 'static) -> impl Fn(&Simulation) -> T + Send + Sync {
    let cell: Arc<Mutex<Option<T>>> = Arc::new(Mutex::new(None));
    move |sim| *cell.lock().expect("memo lock").get_or_insert_with(|| f(sim))
}

/// T26: move tomato sauce, milk and orange juice from cabinet 1's roof to cabinet 2's roof, each to the spot it had
/// relative to cabinet 1 (the sampler spread them over the roof without overlap). `partial_<n>` moves the first n;
/// `undo` moves the tomato sauce over and then back to where it started.
fn cabinet_transfer(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let cab1 = refs.instance_body("wooden_cabinet_1")?;
    let cab2 = refs.instance_body("wooden_cabinet_2")?;
    let objects = ["tomato_sauce_1", "milk_1", "orange_juice_1"];
    let n = match behaviour {
        SOLVE => 3,
        "undo" => 1,
        b => partial_count(b).filter(|&n| n <= 3).ok_or_else(|| TasksError::Scene(format!("T26: unknown behaviour {b}")))?,
    };
    let mut phases = Vec::new();
    for name in &objects[..n] {
        let body = refs.instance_body(name)?;
        // offset of the object's root from cabinet 1's root at the start
        let offset = Arc::new(memo(move |sim: &Simulation| pos(sim, body) - pos(sim, cab1)));
        let start = Arc::new(memo(move |sim: &Simulation| pos(sim, body)));
        let (o1, s1) = (offset.clone(), start.clone());
        // touch the memos before anything moves
        phases.push(Phase::new("note_start", move |sim, ctx| {
            o1(sim);
            s1(sim);
            Goal::at(ctx.start_pos_m, GRIPPER_OPEN)
        }));
        let o2 = offset.clone();
        let to_cab2: TargetFn = Arc::new(move |sim| pos(sim, cab2) + o2(sim));
        pick_place(&mut phases, body, OBJECT_GRASP_DZ_M, CARRY_Z_M, to_cab2);
        if behaviour == "undo" {
            let s2 = start.clone();
            let back: TargetFn = Arc::new(move |sim| s2(sim));
            pick_place(&mut phases, body, OBJECT_GRASP_DZ_M, CARRY_Z_M, back);
        }
    }
    Ok(Box::new(Script::new(phases)))
}

/// Fingers close this far above a HOPE object's root (its upper half).
const OBJECT_GRASP_DZ_M: f64 = 0.02;
/// Root height while carrying between the cabinets' roofs.
const CARRY_Z_M: f64 = 0.85;

