//! Experts for the RoboMemArena container tasks that run on definitions of their own (`tasks/pool.json`): two
//! objects into the basket (tasks 1–3), two objects from plate 1 onto plate 2 (tasks 25, 26), two objects into the
//! open middle drawer (tasks 13, 17: T27's script without the close) and one object into the top drawer and one into
//! the middle drawer, each drawer opened, filled and closed (tasks 11, 14); and task 5, T23's drawer check with the
//! butter into the empty middle drawer. Each has `solve`, `partial_<n>` (exactly n
//! stages, then stop: a near miss) and, but for the basket, `undo` (the first stage completed, then undone: a
//! regression).
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::Vector3;

use crate::TasksError;
use crate::expert::motion::{Script, mat3, vec3};
use crate::expert::skills::{Hold, TargetFn, main_box, memo, pos, transfer, transfer_count};
use crate::expert::{Expert, ExpertEntry, SceneRefs};
use super::expert::{DrawerLoad, drawer_pack};
use super::robomem_expert::{T23_BEHAVIOURS, drawer_search};

#[derive(Clone, Copy)]
enum Container {
    Basket,
    Plate,
    MiddleDrawer,
    /// T23's drawer check, the butter then into the empty middle drawer (task 5; no second object).
    EmptyDrawer,
    /// The first object into the top drawer, the second into the middle one, each drawer closed after.
    TopThenMiddleDrawer,
}

/// A task: its pool reference, container and its objects in the order the instruction names them.
struct Task {
    id: &'static str,
    container: Container,
    objects: &'static [&'static str],
}

const TASKS: &[Task] = &[
    Task { id: "robomemarena/robomemarena_task_05", container: Container::EmptyDrawer, objects: &["butter_1"] },
    Task { id: "robomemarena/robomemarena_task_01", container: Container::Basket, objects: &["cookies_1", "tomato_sauce_1"] },
    Task { id: "robomemarena/robomemarena_task_02", container: Container::Basket, objects: &["butter_1", "popcorn_1"] },
    Task { id: "robomemarena/robomemarena_task_03", container: Container::Basket, objects: &["cream_cheese_1", "chocolate_pudding_1"] },
    Task { id: "robomemarena/robomemarena_task_11", container: Container::TopThenMiddleDrawer, objects: &["cookies_1", "butter_1"] },
    Task { id: "robomemarena/robomemarena_task_13", container: Container::MiddleDrawer, objects: &["cookies_1", "butter_1"] },
    Task { id: "robomemarena/robomemarena_task_14", container: Container::TopThenMiddleDrawer, objects: &["cookies_1", "chocolate_pudding_1"] },
    Task { id: "robomemarena/robomemarena_task_17", container: Container::MiddleDrawer, objects: &["butter_1", "chocolate_pudding_1"] },
    Task { id: "robomemarena/robomemarena_task_25", container: Container::Plate, objects: &["butter_1", "cream_cheese_1"] },
    Task { id: "robomemarena/robomemarena_task_26", container: Container::Plate, objects: &["chocolate_pudding_1", "cream_cheese_1"] },
];

impl Container {
    /// The near misses a container's tasks have.
    const fn behaviours(self) -> &'static [&'static str] {
        match self {
            Container::MiddleDrawer => &["partial_1", "partial_2", "undo"],
            Container::EmptyDrawer => T23_BEHAVIOURS,
            Container::TopThenMiddleDrawer => &["partial_1", "partial_2", "partial_3", "partial_4", "undo"],
            Container::Plate => &["partial_1", "undo"],
            // no `undo`: the hand cannot take a box back out from between the basket's walls
            Container::Basket => &["partial_1"],
        }
    }
}

/// A row per task of [`TASKS`].
pub fn experts() -> impl Iterator<Item = ExpertEntry> {
    TASKS.iter().map(|t| ExpertEntry { task: t.id, behaviours: t.container.behaviours(), build })
}

fn build(refs: &SceneRefs, behaviour: &str, task_id: &str) -> Result<Box<dyn Expert>, TasksError> {
    let t = TASKS.iter().find(|t| t.id == task_id).ok_or_else(|| TasksError::Scene(format!("no scripted expert for task {task_id}")))?;
    let moves = match t.container {
        // the drawer is opened first, and the objects go in side by side across its width
        Container::MiddleDrawer => {
            let items = [(t.objects[0], -0.045), (t.objects[1], 0.05)];
            return drawer_pack(refs, behaviour, task_id, &[DrawerLoad { which: "middle", items: &items, close: false }]);
        }
        // the near miss `wrong_drawer` puts the butter into the occupied top drawer
        Container::EmptyDrawer => return drawer_search(refs, behaviour, task_id, "middle", "top"),
        Container::TopThenMiddleDrawer => {
            // the first object 5 cm toward the robot from the raised top drawer's centre: let go at the centre, at the
            // arm's full reach, it leaves the elbow straight on joint 4's limit and the arm cannot come back
            let (first, second) = ([(t.objects[0], TOP_DRAWER_ACROSS_M)], [(t.objects[1], 0.0)]);
            let loads = [
                DrawerLoad { which: "top", items: &first, close: true },
                DrawerLoad { which: "middle", items: &second, close: true },
            ];
            return drawer_pack(refs, behaviour, task_id, &loads);
        }
        Container::Basket => into_basket(refs, t)?,
        Container::Plate => onto_plate(refs, t)?,
    };
    let n = transfer_count(behaviour, moves.len(), task_id)?;
    let carry_z_m = if matches!(t.container, Container::Basket) { BASKET_CARRY_Z_M } else { PLATE_CARRY_Z_M };
    let mut phases = Vec::new();
    transfer(refs, &mut phases, &moves, n, behaviour == "undo", carry_z_m)?;
    Ok(Box::new(Script::new(phases)))
}

/// Where the object goes across the top drawer (its local x, world x: negative is toward the robot), from its centre.
const TOP_DRAWER_ACROSS_M: f64 = -0.05;
/// Root height while carrying into the basket (its rim stands ≈ 0.15 m above the coffee table's top at z ≈ 0.42).
const BASKET_CARRY_Z_M: f64 = 0.70;
/// Root height while carrying between the plates.
const PLATE_CARRY_Z_M: f64 = 0.60;
/// Height of the basket's floor above its root.
const BASKET_FLOOR_M: f64 = 0.022;
/// Height of the plate's floor above its root.
const PLATE_FLOOR_M: f64 = 0.0055;
/// An object is let go with its bottom this far above where it will rest.
const RELEASE_ABOVE_M: f64 = 0.006;
/// Fingers close this far above a bottle's root (its upper half).
const BOTTLE_GRASP_DZ_M: f64 = 0.02;

/// Tasks 1–3: each object into the basket, the first toward the basket's −x side, the second toward its +x side, its
/// root as high above the basket floor as it stood above the table (objects start on the table beside the basket).
fn into_basket(refs: &SceneRefs, t: &Task) -> Result<Vec<(&'static str, Hold, TargetFn)>, TasksError> {
    let basket = refs.instance_body("basket_1")?;
    let mut moves = Vec::new();
    for (&name, across_m) in t.objects.iter().zip([-0.025, 0.03]) {
        let body = refs.instance_body(name)?;
        let hold = if name == "tomato_sauce_1" { Hold::Above(BOTTLE_GRASP_DZ_M) } else { Hold::Across };
        // root above the table = above the basket's root, both resting on the table at the start
        let rest = memo(move |sim: &Simulation| pos(sim, body).z - pos(sim, basket).z);
        let target: TargetFn = Arc::new(move |sim| {
            pos(sim, basket) + Vector3::new(across_m, 0.0, BASKET_FLOOR_M + rest(sim) + RELEASE_ABOVE_M)
        });
        moves.push((name, hold, target));
    }
    Ok(moves)
}

/// World z of the bottom and the top of an object's main collision box as it lies now.
fn box_z_extent(sim: &Simulation, geom: usize, half_m: [f64; 3]) -> (f64, f64) {
    let m = mat3(&sim.data().geom_xmat()[geom]);
    let c = vec3(&sim.data().geom_xpos()[geom]);
    let vertical: f64 = (0..3).map(|k| (m[(2, k)] * half_m[k]).abs()).sum();
    (c.z - vertical, c.z + vertical)
}

/// Tasks 25, 26: the first object (on top of the cream cheese on plate 1) onto plate 2's middle, then the cream cheese
/// on top of it, as they were stacked on plate 1 (the LIBERO plate holds one box; both stay within 6 cm of its root).
fn onto_plate(refs: &SceneRefs, t: &Task) -> Result<Vec<(&'static str, Hold, TargetFn)>, TasksError> {
    let plate = refs.instance_body("plate_2")?;
    let &[first, second] = t.objects else { return Err(TasksError::Scene(format!("{}: two objects expected", t.id))) };
    let (b1, b2) = (refs.instance_body(first)?, refs.instance_body(second)?);
    let (g1, h1) = main_box(refs, first)?;
    let (g2, h2) = main_box(refs, second)?;
    // root above the bottom of its box, from the pose each has before it is taken
    let rest1 = memo(move |sim: &Simulation| pos(sim, b1).z - box_z_extent(sim, g1, h1).0);
    let rest2 = memo(move |sim: &Simulation| pos(sim, b2).z - box_z_extent(sim, g2, h2).0);
    let onto_plate: TargetFn =
        Arc::new(move |sim| pos(sim, plate) + Vector3::z() * (PLATE_FLOOR_M + rest1(sim) + RELEASE_ABOVE_M));
    let onto_first: TargetFn = Arc::new(move |sim| {
        let p = pos(sim, b1);
        Vector3::new(p.x, p.y, box_z_extent(sim, g1, h1).1 + rest2(sim) + RELEASE_ABOVE_M)
    });
    Ok(vec![(first, Hold::Across, onto_plate), (second, Hold::Across, onto_first)])
}
