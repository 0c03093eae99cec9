//! Experts for RoboMemArena tasks 4 and 7: T23 (check every drawer, then put the butter into the one that already
//! held something) and T24 (pour the tomato sauce over the frypan exactly twice, then put the bottle into the
//! drainer). Each has `solve`, `partial_<n>` (exactly n stages, then stop), `undo` (a completed stage is undone, the
//! evaluator records the regression) and a task-specific near miss.
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::Vector3;

use crate::expert::skills::{
    BOTTOM_HANDLE_LOCAL_M, MIDDLE_HANDLE_LOCAL_M, RotFn, TOP_HANDLE_LOCAL_M, TargetFn, carry, grasp_bottle, main_box, memo,
    narrow_axis, partial_count, pick_place_turned, place_held, pos, pour_at, pull_drawer, push_drawer,
};
use crate::expert::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, PhaseCtx, Script, body_dir, open_along, vec3};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};
use crate::TasksError;

/// T23's near misses (the bottom drawer opens because the raised cabinet's close range keeps it off the shelf
/// above, see `TALL_CABINET_CLOSE_RANGE_M`).
pub(super) const T23_BEHAVIOURS: &[&str] = &["partial_1", "partial_2", "partial_4", "partial_5", "partial_6", "partial_7", "undo", "wrong_drawer"];

pub const EXPERTS: &[ExpertEntry] = &[
    ExpertEntry { task: "T23", behaviours: T23_BEHAVIOURS, build: |refs, b, id| drawer_search(refs, b, id, "top", "bottom") },
    ExpertEntry { task: "T24", behaviours: &["partial_1", "partial_2", "partial_3", "undo", "three_pours"], build: pour_twice },
];

/// Slide value the drawers are pulled to (open ⇔ region displaced > 0.10 m; the slide stops at −0.16).
const PULL_TO_M: f64 = -0.152;
/// Slide value a push ends at (closed ⇔ displaced < 0.08 m).
const PUSH_TO_M: f64 = 0.0;
/// Butter root height while carried over to the top drawer (above the raised cabinet's open top drawer walls), and
/// over to a lower drawer (at 0.82 m the arm stalls short of the open middle drawer).
const BUTTER_CARRY_Z_M: f64 = 0.82;
const BUTTER_CARRY_LOW_Z_M: f64 = 0.75;

/// One drawer of the cabinet: body, handle point, slide qpos address, region site.
#[derive(Clone, Copy)]
pub(super) struct Drawer {
    pub body: usize,
    handle_local_m: [f64; 3],
    q_adr: usize,
    pub region: usize,
    is_top: bool,
}

impl Drawer {
    pub(super) fn of(refs: &SceneRefs, which: &str) -> Result<Self, TasksError> {
        let handle_local_m = match which {
            "top" => TOP_HANDLE_LOCAL_M,
            "middle" => MIDDLE_HANDLE_LOCAL_M,
            _ => BOTTOM_HANDLE_LOCAL_M,
        };
        Ok(Self {
            body: refs.body(&format!("wooden_cabinet_1_cabinet_{which}"))?,
            handle_local_m,
            q_adr: refs.joint(&format!("wooden_cabinet_1_{which}_level"))?.0,
            region: refs.site(&format!("wooden_cabinet_1_{which}_region"))?,
            is_top: which == "top",
        })
    }

    pub(super) fn pull(self, phases: &mut Vec<Phase>) {
        pull_drawer(phases, self.body, self.handle_local_m, self.q_adr, PULL_TO_M);
    }

    pub(super) fn push(self, phases: &mut Vec<Phase>) {
        push_drawer(phases, self.body, self.handle_local_m, self.q_adr, PUSH_TO_M);
    }
}

/// Puts the butter into `drawer` (already open): beside the hidden object, toward the drawer's front half.
fn butter_into(refs: &SceneRefs, phases: &mut Vec<Phase>, drawer: Drawer) -> Result<(), TasksError> {
    let butter = refs.instance_body("butter_1")?;
    let (geom, half) = main_box(refs, "butter_1")?;
    let target: TargetFn = Arc::new(move |sim| {
        let c = vec3(&sim.data().site_xpos()[drawer.region]);
        let across = body_dir(sim, drawer.body, [1.0, 0.0, 0.0]);
        let out = body_dir(sim, drawer.body, [0.0, -1.0, 0.0]);
        c + across * 0.05 + out * 0.02 - Vector3::z() * 0.01
    });
    let rot: RotFn = Arc::new(move |sim, ctx| open_along(&ctx.home_rot, narrow_axis(sim, geom, half)));
    // back over the middle of the table first: from the cabinet the arm cannot swing straight down to the butter
    phases.push(Phase::new("via_middle", move |_, _| Goal::at(Vector3::new(0.0, 0.0, 0.75), GRIPPER_OPEN)).until_reached(0.03).max_steps(80));
    let carry_z_m = if drawer.is_top { BUTTER_CARRY_Z_M } else { BUTTER_CARRY_LOW_Z_M };
    pick_place_turned(phases, butter, Vector3::zeros(), carry_z_m, target, rot);
    Ok(())
}

/// T23 (`target` = top, the occupied drawer, where `cream_cheese_1` starts; RoboMemArena task 5: the empty middle
/// drawer): pull/push top, middle, bottom in turn, pull the target drawer again, put the butter in, push it closed
/// (optional stage 09). `partial_<n>` plays the first n of the eight stage steps; `undo` reopens the target drawer
/// (stage 07) and pushes it shut again; `wrong_drawer` checks all three drawers, then opens drawer `wrong` instead and
/// puts the butter there.
pub(super) fn drawer_search(
    refs: &SceneRefs,
    behaviour: &str,
    task_id: &str,
    target: &str,
    wrong: &str,
) -> Result<Box<dyn Expert>, TasksError> {
    let [top, middle, bottom] = ["top", "middle", "bottom"].map(|d| Drawer::of(refs, d));
    let (top, middle, bottom) = (top?, middle?, bottom?);
    let n = match behaviour {
        SOLVE | "wrong_drawer" => 8,
        "undo" => 7,
        b => partial_count(b).filter(|&n| n < 8).ok_or_else(|| TasksError::Scene(format!("{task_id}: unknown behaviour {b}")))?,
    };
    let occupied = Drawer::of(refs, if behaviour == "wrong_drawer" { wrong } else { target })?;
    let mut phases = Vec::new();
    for (k, d) in [top, middle, bottom].into_iter().enumerate().take(n.div_ceil(2).min(3)) {
        d.pull(&mut phases);
        if 2 * k + 2 <= n {
            d.push(&mut phases);
        }
    }
    if n >= 7 {
        occupied.pull(&mut phases);
    }
    if behaviour == "undo" {
        occupied.push(&mut phases);
    }
    if n == 8 {
        butter_into(refs, &mut phases, occupied)?;
        if behaviour == SOLVE {
            occupied.push(&mut phases);
        }
    }
    Ok(Box::new(Script::new(phases)))
}

/// Fingers close this far above the tomato sauce's root (its upper half).
const SAUCE_GRASP_DZ_M: f64 = 0.02;
/// Lift of the bottle above its resting height while pouring.
const POUR_LIFT_M: f64 = 0.15;
/// Bottle tilt commanded for a pour (the counter needs ≥ 0.70 rad from the upright reference).
const POUR_TILT_RAD: f64 = 1.05;
/// Root height while carrying the bottle to the drainer (above its racks).
const DRAINER_CARRY_Z_M: f64 = 0.75;

/// T24: grasp the tomato sauce from above, lift it 15 cm, carry it beside the frypan, tilt it ≈ 1 rad for 20 steps
/// and back upright for 20 (re-arms the counter) — twice — then set it into the drainer's left slot and let go.
/// `partial_<n>`: lift (1), one pour (2), two pours (3), holding the bottle afterwards; `undo` lifts the bottle and
/// puts it back where it stood (the lift stage regresses); `three_pours` pours a third time before placing.
fn pour_twice(refs: &SceneRefs, behaviour: &str, task_id: &str) -> Result<Box<dyn Expert>, TasksError> {
    let sauce = refs.instance_body("tomato_sauce_1")?;
    let pan = refs.instance_body("frypan_1")?;
    let left = refs.site("bowl_drainer_1_left_region")?;
    let (pours, place) = match behaviour {
        SOLVE => (2, true),
        "three_pours" => (3, true),
        "undo" => (0, false),
        b => match partial_count(b).filter(|&n| (1..4).contains(&n)) {
            Some(n) => (n - 1, false),
            None => return Err(TasksError::Scene(format!("{task_id}: unknown behaviour {b}"))),
        },
    };
    let rest_z = Arc::new(memo(move |sim: &Simulation| pos(sim, sauce).z));
    let start = Arc::new(memo(move |sim: &Simulation| pos(sim, sauce)));
    let (s0, r0) = (start.clone(), rest_z.clone());
    let mut phases = vec![Phase::new("note_start", move |sim, ctx: &PhaseCtx| {
        s0(sim);
        r0(sim);
        Goal::at(ctx.start_pos_m, GRIPPER_OPEN)
    })];
    grasp_bottle(&mut phases, sauce, SAUCE_GRASP_DZ_M, POUR_LIFT_M);
    if behaviour == "undo" {
        let back: TargetFn = Arc::new(move |sim| start(sim));
        phases.push(Phase::new("hold", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED)).for_steps(10));
        let rz = rest_z.clone();
        phases.push(
            Phase::new("set_back_down", move |sim, _| {
                let b = back(sim);
                Goal::at(carry(sim, sauce, Vector3::new(b.x, b.y, rz(sim) + 0.005)), GRIPPER_CLOSED).slow(0.4)
            })
            .until(move |sim, _| pos(sim, sauce).z < rest_z(sim) + 0.01)
            .max_steps(80),
        );
        phases.push(Phase::new("open", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN)).for_steps(10));
        phases.push(Phase::new("retreat", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.10, GRIPPER_OPEN)).until_reached(0.015).max_steps(40));
        return Ok(Box::new(Script::new(phases)));
    }
    // beside the pan, at the lifted height
    let spot: TargetFn = Arc::new(move |sim: &Simulation| {
        let p = pos(sim, pan);
        Vector3::new(p.x - 0.05, p.y - 0.05, rest_z(sim) + POUR_LIFT_M)
    });
    pour_at(&mut phases, sauce, spot, pours, POUR_TILT_RAD, 20);
    if !place {
        phases.push(Phase::new("hold_bottle", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED)).for_steps(20));
        return Ok(Box::new(Script::new(phases)));
    }
    // into the drainer: the root at the left slot's centre (the RoboMemArena box keeps 2 cm below it)
    let slot: TargetFn = Arc::new(move |sim| vec3(&sim.data().site_xpos()[left]));
    place_held(&mut phases, sauce, SAUCE_GRASP_DZ_M, DRAINER_CARRY_Z_M, slot);
    Ok(Box::new(Script::new(phases)))
}
