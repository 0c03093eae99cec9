//! Experts that move loose LIBERO objects: pick the alphabet soup into the basket on the floor (T11), push the plate
//! into the green zone in front of the stove (T12).
use nalgebra::Vector3;

use libero_sim::Simulation;

use crate::expert::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, PhaseCtx, Script, body_dir, body_pos, grip_pose, open_along, vec3};
use crate::expert::{Expert, SOLVE, SceneRefs};
use crate::TasksError;

const UP: Vector3<f64> = Vector3::new(0.0, 0.0, 1.0);

fn flat(v: Vector3<f64>) -> Vector3<f64> {
    Vector3::new(v.x, v.y, 0.0)
}

fn settled_grip(max: u32) -> impl Fn(&Simulation, &PhaseCtx) -> bool + Send {
    move |sim, ctx| ctx.steps >= max || (ctx.steps >= 8 && sim.data().qvel()[sim.ids().finger_dof_adr[0]].abs() < 1e-3)
}

/// T11: grasp the soup can across its axis, lift it over the basket's rim, lower it into the basket and let go.
/// `drop_beside` puts it down on the floor 20 cm beside the basket instead.
pub fn pick_soup_into_basket(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let soup = refs.instance_body("alphabet_soup_1")?;
    let basket = refs.instance_body("basket_1")?;
    let region = refs.site("basket_1_contain_region")?;
    let beside = behaviour != SOLVE;
    let soup_pos = move |sim: &Simulation| body_pos(sim, soup);
    // the can's axis is its body's y; grasp across it (fingers opening perpendicular to the axis, horizontally)
    let grasp_rot = move |sim: &Simulation, ctx: &PhaseCtx| {
        let a = body_dir(sim, soup, [0.0, 1.0, 0.0]);
        if a.z.abs() > 0.7 { ctx.home_rot } else { open_along(&ctx.home_rot, Vector3::new(-a.y, a.x, 0.0)) }
    };
    // where the can's centre should go: the contain region's centre, or the floor beside the basket
    let drop_xy = move |sim: &Simulation| {
        let c = vec3(&sim.data().site_xpos()[region]);
        if beside { flat(c) + Vector3::new(-0.20, 0.0, 0.0) } else { flat(c) }
    };
    let carry_z = move |sim: &Simulation| body_pos(sim, basket).z + 0.26;
    let drop_z = move |sim: &Simulation, start_z: f64| {
        if beside { start_z } else { vec3(&sim.data().site_xpos()[region]).z + 0.035 }
    };
    // the held orientation is whatever the grasp ended with: keep it (the can hangs across the fingers)
    let held = std::sync::Arc::new(std::sync::Mutex::new(None::<nalgebra::Matrix3<f64>>));
    let soup_z0 = std::sync::Arc::new(std::sync::Mutex::new(None::<f64>));
    let (h1, h2, h3, h4, h5) = (held.clone(), held.clone(), held.clone(), held.clone(), held.clone());
    let (z1, z2) = (soup_z0.clone(), soup_z0.clone());
    let hold = move |h: &std::sync::Arc<std::sync::Mutex<Option<nalgebra::Matrix3<f64>>>>, ctx: &PhaseCtx| {
        h.lock().unwrap().unwrap_or(ctx.home_rot)
    };
    Ok(Box::new(Script::new(vec![
        Phase::new("above_soup", move |sim, ctx| {
            let r = grasp_rot(sim, ctx);
            *h1.lock().unwrap() = Some(r);
            *z1.lock().unwrap() = Some(soup_pos(sim).z);
            Goal::at(soup_pos(sim) + UP * 0.12, GRIPPER_OPEN).rotated(r)
        })
        .until_reached(0.01)
        .max_steps(150),
        Phase::new("down_to_soup", move |sim, ctx| Goal::at(soup_pos(sim), GRIPPER_OPEN).slow(0.5).rotated(hold(&h2, ctx)))
            .until_reached(0.006)
            .max_steps(80),
        Phase::new("grip_soup", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(hold(&h3, ctx)))
            .until(settled_grip(15))
            .max_steps(20),
        Phase::new("lift", move |sim, ctx| {
            Goal::at(Vector3::new(ctx.start_pos_m.x, ctx.start_pos_m.y, carry_z(sim)), GRIPPER_CLOSED).rotated(hold(&h4, ctx))
        })
        .until_reached(0.02)
        .max_steps(100),
        Phase::new("carry", move |sim, ctx| {
            Goal::at(drop_xy(sim) + UP * carry_z(sim), GRIPPER_CLOSED).rotated(hold(&h5, ctx))
        })
        .until_reached(0.015)
        .max_steps(150),
        Phase::new("lower", move |sim, ctx| {
            let z = drop_z(sim, z2.lock().unwrap().unwrap_or(ctx.start_pos_m.z));
            Goal::at(drop_xy(sim) + UP * z, GRIPPER_CLOSED).slow(0.5).rotated(hold(&held, ctx))
        })
        .until_reached(0.01)
        .max_steps(50),
        Phase::new("release", move |sim, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(grip_pose(sim).1)).for_steps(10),
        Phase::new("lift_away", move |sim, ctx| Goal::at(ctx.start_pos_m + UP * 0.12, GRIPPER_OPEN).rotated(grip_pose(sim).1))
            .until_reached(0.02)
            .max_steps(40),
    ])))
}

/// T12: the plate starts just in front of the cabinet, whose drawer handles leave no room for the hand behind it,
/// so the hand works from inside the dish: fingers open and turned across the push, lowered onto the plate's floor
/// a little behind its centre, then moved toward the zone's centre with the goal recomputed from the plate every
/// step; the fingers drag the dish and bear on its inner rim. `push_short` stops with the plate 9 cm short of the
/// centre (outside the zone's ±4 cm).
pub fn push_plate(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let plate = refs.instance_body("plate_1")?;
    let zone = refs.site("main_table_stove_front_region")?;
    let stop_m = if behaviour == SOLVE { 0.012 } else { 0.09 };
    Ok(Box::new(Script::new(push_plate_phases(plate, zone, stop_m))))
}

/// The phases of [`push_plate`]: push the plate (root body `plate`) until its centre is within `stop_m` of the
/// region site `zone`'s centre.
pub fn push_plate_phases(plate: usize, zone: usize, stop_m: f64) -> Vec<Phase> {
    let plate_pos = move |sim: &Simulation| body_pos(sim, plate);
    let centre = move |sim: &Simulation| vec3(&sim.data().site_xpos()[zone]);
    let dir = move |sim: &Simulation| {
        let d = flat(centre(sim) - plate_pos(sim));
        if d.norm() < 1e-6 { Vector3::x() } else { d.normalize() }
    };
    let across = move |sim: &Simulation| {
        let d = dir(sim);
        Vector3::new(-d.y, d.x, 0.0)
    };
    let remaining = move |sim: &Simulation| flat(centre(sim) - plate_pos(sim)).norm();
    // the grip site over the dish, `behind_m` back from its centre along the push, `up_m` above its origin
    let over = move |sim: &Simulation, behind_m: f64, up_m: f64| {
        let p = plate_pos(sim);
        Vector3::new(p.x, p.y, p.z + up_m) - dir(sim) * behind_m
    };
    const PUSH_UP_M: f64 = 0.02;
    const BEHIND_M: f64 = 0.02;
    let rot = move |sim: &Simulation, ctx: &PhaseCtx| open_along(&ctx.home_rot, across(sim));
    vec![
        Phase::new("above_plate", move |sim, ctx| Goal::at(over(sim, BEHIND_M, 0.12), GRIPPER_OPEN).rotated(rot(sim, ctx)))
            .until_reached(0.01)
            .max_steps(150),
        Phase::new("into_plate", move |sim, ctx| {
            Goal::at(over(sim, BEHIND_M, PUSH_UP_M), GRIPPER_OPEN).slow(0.4).rotated(rot(sim, ctx))
        })
        .until_reached(0.006)
        .max_steps(80),
        Phase::new("push_plate", move |sim, ctx| {
            // the fingers come to bear on the rim ≈ 4 cm ahead of where they went in: lead beyond that, by less as
            // the plate nears the centre
            let lead = 0.04 + remaining(sim).min(0.04);
            // slower near the centre so the dish does not coast past it
            let speed = (0.1 + 4.0 * remaining(sim)).min(0.4);
            Goal::at(over(sim, BEHIND_M, PUSH_UP_M) + dir(sim) * lead, GRIPPER_OPEN).slow(speed).rotated(rot(sim, ctx))
        })
        .until(move |sim, _| remaining(sim) <= stop_m)
        .max_steps(300),
        Phase::new("lift_away", move |sim, ctx| {
            Goal::at(ctx.start_pos_m + UP * 0.10, GRIPPER_OPEN).rotated(grip_pose(sim).1)
        })
        .until_reached(0.02)
        .max_steps(40),
    ]
}
