//! Expert for the pool's `vlabench_additional/find_unseen_object`: the apple lies hidden in the closed middle drawer
//! of LIBERO's wooden cabinet (in the top drawer it would show through the cabinet's roof in the head image); pull
//! that drawer open, take the apple out from above and put it on the wooden tray. Near misses: `wrong_drawer` opens
//! the top drawer (the bottom handle is out of the horizontal hand's reach) and stops; `leave_apple` opens the right
//! drawer and stops.
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::Vector3;

use crate::TasksError;
use crate::expert::motion::{GRIPPER_OPEN, Goal, Phase, PhaseCtx, Script, body_dir, open_along, vec3};
use crate::expert::skills::{RotFn, TargetFn, pick_place_turned};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};
use super::robomem_expert::Drawer;

pub const EXPERTS: &[ExpertEntry] = &[ExpertEntry {
    task: "vlabench_additional/find_unseen_object",
    behaviours: &["wrong_drawer", "leave_apple"],
    build: |refs, b, _| find_apple(refs, b),
}];

/// Apple root height while carried: above the cabinet's roof (kitchen tabletop at 0.90 m, the roof ≈ 0.22 m above
/// it), so the apple clears the closed top drawer on its way out.
const APPLE_CARRY_Z_M: f64 = 1.20;
/// Where the apple is let go, below the tray's region-site centre (the site is 8 cm tall; the floor is near its bottom).
const TRAY_DROP_BELOW_SITE_M: f64 = 0.02;

fn find_apple(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let drawer = Drawer::of(refs, if behaviour == "wrong_drawer" { "top" } else { "middle" })?;
    let mut phases = Vec::new();
    drawer.pull(&mut phases);
    // up and clear of the drawer front before the hand turns back to pointing down
    phases.push(
        Phase::new("clear_drawer", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.12, GRIPPER_OPEN).slow(0.6))
            .until_reached(0.02)
            .max_steps(60),
    );
    if behaviour == SOLVE {
        let apple = refs.instance_body("apple_1")?;
        let tray_region = refs.site("wooden_tray_1_contain_region")?;
        let drawer_body = drawer.body;
        // fingers close across the drawer (along its front): the hand's thin side faces the cabinet
        let rot: RotFn =
            Arc::new(move |sim: &Simulation, ctx: &PhaseCtx| open_along(&ctx.home_rot, body_dir(sim, drawer_body, [1.0, 0.0, 0.0])));
        let on_tray: TargetFn =
            Arc::new(move |sim: &Simulation| vec3(&sim.data().site_xpos()[tray_region]) - Vector3::z() * TRAY_DROP_BELOW_SITE_M);
        pick_place_turned(&mut phases, apple, Vector3::zeros(), APPLE_CARRY_Z_M, on_tray, rot);
    }
    Ok(Box::new(Script::new(phases)))
}
