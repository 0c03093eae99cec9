//! Expert for the pool's `vlabench_additional/cluster_series` (VLABench cluster_series on a definition of its own):
//! two apples and two bananas on the table between two LIBERO baskets; the apples go into basket 1, the bananas into
//! basket 2 (the evaluator accepts either assignment). Near miss `wrong_basket`: the same, but the second banana is
//! put into the apples' basket (one fruit in the wrong basket: the first stage completes, the second never does).
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::Vector3;

use crate::TasksError;
use crate::expert::motion::{GRIPPER_OPEN, Goal, Phase, Script};
use crate::expert::skills::{Hold, TargetFn, memo, pos, transfer};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};

const WRONG_BASKET: &str = "wrong_basket";

pub const EXPERTS: &[ExpertEntry] =
    &[ExpertEntry { task: "vlabench_additional/cluster_series", behaviours: &[WRONG_BASKET], build: sort_fruit }];

/// Root height while carrying over the baskets' rims (the basket stands ≈ 0.15 m tall on the table at z ≈ 0.90).
const CARRY_Z_M: f64 = 1.13;
/// Grip-site waypoint between two picks: over the table's middle, in front of the fruit.
const VIA_M: Vector3<f64> = Vector3::new(-0.15, 0.0, 1.15);
/// Height of the LIBERO basket's floor above its root.
const BASKET_FLOOR_M: f64 = 0.022;
/// A fruit is let go with its bottom this far above where it will rest.
const RELEASE_ABOVE_M: f64 = 0.01;

/// Where each fruit goes: `(fruit, basket, offset of its root from the basket's root in x and y, m)`. Two apples
/// (r 3.4 cm) fit the basket's ≈ 13 cm floor only diagonally; the bananas (10 cm along x) lie side by side.
const SOLVE_PLAN: [(&str, &str, [f64; 2]); 4] = [
    ("apple_1", "basket_1", [-0.028, -0.025]),
    ("apple_2", "basket_1", [0.028, 0.025]),
    ("banana_1", "basket_2", [0.0, -0.025]),
    ("banana_2", "basket_2", [0.0, 0.025]),
];

fn sort_fruit(refs: &SceneRefs, behaviour: &str, task_id: &str) -> Result<Box<dyn Expert>, TasksError> {
    let mut plan = SOLVE_PLAN;
    match behaviour {
        SOLVE => {}
        // onto the middle of the apples' basket, where it comes to rest on the apples
        WRONG_BASKET => plan[3] = ("banana_2", "basket_1", [0.0, 0.0]),
        b => return Err(TasksError::Scene(format!("{task_id}: unknown behaviour {b}"))),
    }
    let mut moves = Vec::new();
    for (fruit, basket, [dx_m, dy_m]) in plan {
        let body = refs.instance_body(fruit)?;
        let basket = refs.instance_body(basket)?;
        // the fruit's root above the basket's root as both stand on the table at the start
        let rest = memo(move |sim: &Simulation| pos(sim, body).z - pos(sim, basket).z);
        let target: TargetFn =
            Arc::new(move |sim| pos(sim, basket) + Vector3::new(dx_m, dy_m, BASKET_FLOOR_M + rest(sim) + RELEASE_ABOVE_M));
        // apples from above with the fingers at the centre; bananas across their narrow side
        let hold = if fruit.starts_with("apple") { Hold::Above(0.0) } else { Hold::Across };
        moves.push((fruit, hold, target));
    }
    let mut phases = Vec::new();
    for one in moves.chunks(1) {
        // back over the middle of the table first: straight from a basket toward the far side's fruit the arm stalls
        phases.push(Phase::new("via_middle", move |_, _| Goal::at(VIA_M, GRIPPER_OPEN)).until_reached(0.03).max_steps(80));
        transfer(refs, &mut phases, one, 1, false, CARRY_Z_M)?;
    }
    Ok(Box::new(Script::new(phases)))
}
