//! Experts for the release tasks built on stock LIBERO scenes and assets (T11, T12, T14–T17).
use std::f64::consts::FRAC_PI_2;

use nalgebra::Vector3;

use crate::expert::motion::{GRIPPER_CLOSED, Goal, Phase, Script, body_dir, body_point, rotate_world};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};
use crate::TasksError;

/// The release tasks on stock scenes, each with its near misses.
pub const EXPERTS: &[ExpertEntry] = &[
    ExpertEntry { task: "T11", behaviours: &["drop_beside"], build: |refs, b, _| super::objects::pick_soup_into_basket(refs, b) },
    ExpertEntry { task: "T12", behaviours: &["push_short"], build: |refs, b, _| super::objects::push_plate(refs, b) },
    ExpertEntry { task: "T14", behaviours: &["push_half"], build: |refs, b, _| close_top_drawer(refs, b) },
    ExpertEntry { task: "T15", behaviours: &["pull_half"], build: |refs, b, _| crate::expert::fixtures::open_top_drawer(refs, b) },
    ExpertEntry { task: "T16", behaviours: &["open_partly"], build: |refs, b, _| crate::expert::fixtures::open_microwave(refs, b) },
    ExpertEntry { task: "T17", behaviours: &["turn_slightly"], build: |refs, b, _| crate::expert::fixtures::turn_on_stove(refs, b) },
];

/// LIBERO wooden cabinet drawer: the handle bar's centre in the drawer body's frame, and the drawer's outward
/// direction (it opens along local −y, the slide joint's negative direction).
const DRAWER_HANDLE_LOCAL_M: [f64; 3] = [-0.00278, -0.10161, 0.18393];
const DRAWER_OUT_LOCAL: [f64; 3] = [0.0, -1.0, 0.0];

/// T14: a closed fist pushes the top drawer's handle home. `push_half` stops with the drawer still 7 cm out.
fn close_top_drawer(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let drawer = refs.body("wooden_cabinet_1_cabinet_top")?;
    let (q_adr, _) = refs.joint("wooden_cabinet_1_top_level")?;
    // closed ⇔ q > 0; the drawer seats at ≈ +0.0017 (range upper limit 0.01)
    let q_goal = if behaviour == SOLVE { 0.001 } else { -0.07 };
    let handle = move |sim: &libero_sim::Simulation| body_point(sim, drawer, DRAWER_HANDLE_LOCAL_M);
    let out = move |sim: &libero_sim::Simulation| body_dir(sim, drawer, DRAWER_OUT_LOCAL);
    let q = move |sim: &libero_sim::Simulation| sim.data().qpos()[q_adr];
    let up = Vector3::z();
    // the hand is widest along the fingers' opening axis: turn it a quarter so it is thin along the push
    let turned = |ctx: &crate::expert::motion::PhaseCtx| rotate_world(&ctx.home_rot, Vector3::z(), FRAC_PI_2);
    Ok(Box::new(Script::new(vec![
        Phase::new("above_front_of_handle", move |sim, ctx| {
            Goal::at(handle(sim) + out(sim) * 0.08 + up * 0.12, GRIPPER_CLOSED).rotated(turned(ctx))
        })
        .until_reached(0.02),
        Phase::new("down_in_front_of_handle", move |sim, ctx| {
            Goal::at(handle(sim) + out(sim) * 0.08, GRIPPER_CLOSED).rotated(turned(ctx))
        })
            .until_reached(0.012),
        Phase::new("push_drawer", move |sim, ctx| {
            // where the handle will be once the drawer is home, a little beyond so the fist keeps pushing
            let target = handle(sim) - out(sim) * (q_goal - q(sim) + 0.01);
            Goal::at(target, GRIPPER_CLOSED).slow(0.6).rotated(turned(ctx))
        })
        .until(move |sim, _| q(sim) >= q_goal)
        .max_steps(150),
        Phase::new("back_off", move |sim, ctx| {
            Goal::at(ctx.start_pos_m + out(sim) * 0.10 + up * 0.05, GRIPPER_CLOSED).rotated(turned(ctx))
        })
            .until_reached(0.02)
            .max_steps(40),
    ])))
}
