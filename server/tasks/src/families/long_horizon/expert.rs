//! Experts for T26 (RoboMemArena task 19, cabinet to cabinet; task 18 with two objects) and T27 (task 12, two objects into the middle
//! drawer). Like every long-horizon expert, each has `solve`, `partial_<n>` behaviours that complete exactly n stages
//! and stop, and `undo`, which completes a stage and then undoes it (the evaluator must record the regression).
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::Vector3;

use crate::expert::motion::{GRIPPER_OPEN, Goal, Phase, Script, body_dir, open_along, vec3};
use crate::expert::skills::{
    Hold, RotFn, TargetFn, main_box, memo, narrow_axis, partial_count, pick_place_turned, pos, transfer, transfer_count,
};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};
use crate::TasksError;
use super::robomem_expert::Drawer;

/// T26, RoboMemArena task 18 as a pool entry of its own (`tasks/pool.json`: T26's scene with two low boxes) and T27.
pub const EXPERTS: &[ExpertEntry] = &[
    ExpertEntry {
        task: "T26",
        behaviours: &["partial_1", "partial_2", "undo"],
        // the bottles: fingers on the upper half, hand as at home
        build: |refs, b, id| cabinet_transfer(refs, b, id, &["tomato_sauce_1", "milk_1", "orange_juice_1"], Hold::Above(OBJECT_GRASP_DZ_M)),
    },
    ExpertEntry {
        task: "robomemarena/robomemarena_task_18",
        behaviours: &["partial_1", "undo"],
        // low boxes: fingers at the root across the narrow side
        build: |refs, b, id| cabinet_transfer(refs, b, id, &["chocolate_pudding_1", "butter_1"], Hold::Across),
    },
    ExpertEntry {
        task: "T27",
        behaviours: &["partial_1", "partial_2", "partial_3", "undo"],
        build: |refs, b, id| {
            let items = [("cookies_1", -0.045), ("chocolate_pudding_1", 0.05)];
            drawer_pack(refs, b, id, &[DrawerLoad { which: "middle", items: &items, close: true }])
        },
    },
];

/// T26 and RoboMemArena task 18: move `objects` in order from cabinet 1's roof to cabinet 2's roof, each to the spot
/// it had relative to cabinet 1 (the sampler spread them over the roof without overlap). `partial_<n>` moves the
/// first n; `undo` moves the first over and then back to where it started.
fn cabinet_transfer(refs: &SceneRefs, behaviour: &str, task_id: &str, objects: &[&str], hold: Hold) -> Result<Box<dyn Expert>, TasksError> {
    let cab1 = refs.instance_body("wooden_cabinet_1")?;
    let cab2 = refs.instance_body("wooden_cabinet_2")?;
    let n = transfer_count(behaviour, objects.len(), task_id)?;
    let mut moves = Vec::new();
    for name in objects {
        let body = refs.instance_body(name)?;
        // offset of the object's root from cabinet 1's root at the start
        let offset = memo(move |sim: &Simulation| pos(sim, body) - pos(sim, cab1));
        let to_cab2: TargetFn = Arc::new(move |sim| pos(sim, cab2) + offset(sim));
        moves.push((*name, hold, to_cab2));
    }
    let mut phases = Vec::new();
    transfer(refs, &mut phases, &moves, n, behaviour == "undo", CARRY_Z_M)?;
    Ok(Box::new(Script::new(phases)))
}

/// Fingers close this far above a HOPE object's root (its upper half).
const OBJECT_GRASP_DZ_M: f64 = 0.02;
/// Root height while carrying between the cabinets' roofs.
const CARRY_Z_M: f64 = 0.85;

/// One drawer's part of a packing script: pull drawer `which` (`top`, `middle`, `bottom` of `wooden_cabinet_1`) open,
/// put `items` in in order (each at its offset across the drawer's width, side by side), push it closed if `close`.
pub(super) struct DrawerLoad<'a> {
    pub which: &'a str,
    pub items: &'a [(&'a str, f64)],
    pub close: bool,
}

/// T27 (the cookies and then the chocolate pudding into the middle drawer, closed), RoboMemArena tasks 13, 17 (the
/// same without the close) and 11, 14 (one object into the top drawer, closed, one into the middle drawer): the
/// `loads` in order. `partial_<n>` stops after the first n steps (each pull, placement and push is one); `undo` opens
/// the first drawer and pushes it shut again (stage 1 regresses).
pub(super) fn drawer_pack(refs: &SceneRefs, behaviour: &str, task_id: &str, loads: &[DrawerLoad]) -> Result<Box<dyn Expert>, TasksError> {
    let steps: usize = loads.iter().map(|l| 1 + l.items.len() + usize::from(l.close)).sum();
    let n = match behaviour {
        SOLVE => steps,
        "undo" => 1,
        b => partial_count(b).filter(|&n| n <= steps).ok_or_else(|| TasksError::Scene(format!("{task_id}: unknown behaviour {b}")))?,
    };
    let mut phases = Vec::new();
    let mut done = 0;
    for load in loads {
        let drawer = Drawer::of(refs, load.which)?;
        // the top drawer's walls stand higher: carry over them
        let carry_z_m = if load.which == "top" { TOP_DRAWER_CARRY_Z_M } else { DRAWER_CARRY_Z_M };
        if done < n {
            drawer.pull(&mut phases);
            done += 1;
        }
        if behaviour == "undo" {
            drawer.push(&mut phases);
            break;
        }
        for (name, across_m) in load.items {
            if done == n {
                break;
            }
            let body = refs.instance_body(name)?;
            let (geom, half) = main_box(refs, name)?;
            let across_m = *across_m;
            let target: TargetFn = Arc::new(move |sim| {
                let c = vec3(&sim.data().site_xpos()[drawer.region]);
                // across the drawer = the drawer's local x
                let x_dir = body_dir(sim, drawer.body, [1.0, 0.0, 0.0]);
                c + x_dir * across_m - Vector3::z() * 0.01
            });
            let rot: RotFn = Arc::new(move |sim, ctx| open_along(&ctx.home_rot, narrow_axis(sim, geom, half)));
            // back over the middle of the table first: from the drawer the arm cannot swing straight down to objects
            // near its base
            phases.push(
                Phase::new("via_middle", move |_, _| Goal::at(Vector3::new(0.0, 0.0, 0.70), GRIPPER_OPEN)).until_reached(0.03).max_steps(80),
            );
            pick_place_turned(&mut phases, body, Vector3::zeros(), carry_z_m, target, rot);
            done += 1;
        }
        if load.close && done < n {
            drawer.push(&mut phases);
            done += 1;
        }
    }
    Ok(Box::new(Script::new(phases)))
}

/// Root height while carrying objects over to the drawer (above the cabinet's middle drawer, below the top one's
/// reach problems: the cabinet top is ≈ 0.27 m above the table).
const DRAWER_CARRY_Z_M: f64 = 0.75;
/// The same for the raised cabinet's top drawer (above its open walls).
const TOP_DRAWER_CARRY_Z_M: f64 = 0.82;
