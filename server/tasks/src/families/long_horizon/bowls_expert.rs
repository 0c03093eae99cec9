//! T25 rotate_three_bowls_using_empty_plate: every black bowl moves one plate to the left in the head image, the
//! leftmost wrapping round to the rightmost plate through the empty buffer plate (task catalog §5 T25):
//! bowl_1 → plate_4, bowl_2 → plate_1, bowl_3 → plate_2, bowl_1 → plate_3, each carried high enough that no bowl
//! ever touches the tabletop, set down on the plate's centre and let go.
//!
//! A bowl is too wide for the open hand (≈ 10 cm across the rim, 8 cm of finger travel), so the fingers pinch its
//! wall: the grip site goes to the rim on the bowl's +y side (the hand at its home orientation opens along world y,
//! one finger inside the bowl, one outside) and closes there. Everything is closed loop on the bowls' and plates'
//! current poses.
//!
//! Behaviours: `partial_<n>` (the first n moves), `undo` (bowl_1 to the buffer plate and back to plate_1: stage 1
//! regresses), `touch_table` (bowl_1 set down on the bare tabletop: the contact guard fails the run), `skip_buffer`
//! (bowl_3 to the buffer plate, then bowl_1 straight to plate_3: stage 4 holds before stage 1, an ordering violation).
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::Vector3;

use crate::expert::skills::{RotFn, TargetFn, memo, partial_count, pick_place_turned, pos, xy_dist};
use crate::expert::motion::{GRIPPER_OPEN, Goal, Phase, Script};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};
use crate::TasksError;

pub const EXPERTS: &[ExpertEntry] = &[ExpertEntry {
    task: "T25",
    behaviours: &["partial_1", "partial_2", "partial_3", "undo", "touch_table", "skip_buffer"],
    build: rotate_bowls,
}];

/// Where the fingers pinch a bowl's wall, from its root (world frame): on the +y side, at the wall's radius ≈ 1.4 cm
/// below the rim (the wall rises from 1.5 to 5.2 cm above the root, flaring from 4.2 to 5.4 cm radius).
const RIM_GRASP_OFFSET_M: [f64; 3] = [0.0, 0.048, 0.038];
/// Bowl-root height while carrying: the bowl's bottom ≈ 12 cm above the tabletop (z = 0.90), clear of the other
/// bowls' rims (≈ 0.96) even if the held bowl hangs tilted.
const CARRY_Z_M: f64 = 1.03;
/// How far below a bowl's resting height on a plate the place target is (the hand lets go once the bowl's root is
/// within 1.5 cm above the target, see `pick_place_turned`): the 5.6 g bowl lands gently and stays centred.
const RELEASE_BELOW_REST_M: f64 = 0.006;
/// Control steps the hand waits at the end.
const SETTLE_STEPS: u32 = 15;
/// Candidate table spots (world x, y) for `touch_table`: in front of the plate row, reachable; the one farthest from
/// every plate is used.
const TABLE_SPOTS_XY_M: [[f64; 2]; 3] = [[-0.33, -0.12], [-0.33, 0.05], [-0.33, 0.22]];

fn rotate_bowls(refs: &SceneRefs, behaviour: &str, task_id: &str) -> Result<Box<dyn Expert>, TasksError> {
    let bowl = |k: usize| refs.instance_body(&format!("akita_black_bowl_{k}"));
    let plate = |k: usize| refs.instance_body(&format!("plate_{k}"));
    let (b1, b2, b3) = (bowl(1)?, bowl(2)?, bowl(3)?);
    let (p1, p2, p3, p4) = (plate(1)?, plate(2)?, plate(3)?, plate(4)?);
    // where a bowl's root rests above its plate's root (measured on bowl_1 at the start, before anything moves)
    let rest_dz = Arc::new(memo(move |sim: &Simulation| pos(sim, b1).z - pos(sim, p1).z));
    let solve = [(b1, p4), (b2, p1), (b3, p2), (b1, p3)];
    let moves: Vec<(usize, Target)> = match behaviour {
        SOLVE => solve.iter().map(|&(b, p)| (b, Target::Plate(p))).collect(),
        "undo" => vec![(b1, Target::Plate(p4)), (b1, Target::Plate(p1))],
        "touch_table" => vec![(b1, Target::Table([p1, p2, p3, p4]))],
        "skip_buffer" => vec![(b3, Target::Plate(p4)), (b1, Target::Plate(p3))],
        b => {
            let n = partial_count(b).filter(|&n| (1..4).contains(&n)).ok_or_else(|| TasksError::Scene(format!("{task_id}: unknown behaviour {b}")))?;
            solve[..n].iter().map(|&(b, p)| (b, Target::Plate(p))).collect()
        }
    };
    // measure the resting height before anything moves
    let r0 = rest_dz.clone();
    let mut phases = vec![Phase::new("note_start", move |sim, ctx| {
        r0(sim);
        Goal::at(ctx.start_pos_m, GRIPPER_OPEN)
    })];
    for (body, target) in moves {
        let rest = rest_dz.clone();
        let to: TargetFn = match target {
            // the plate's centre, a little below the bowl's resting height on it, so the bowl is let go at most
            // ≈ 9 mm above where it comes to rest
            Target::Plate(p) => Arc::new(move |sim| pos(sim, p) + Vector3::z() * (rest(sim) - RELEASE_BELOW_REST_M)),
            Target::Table(plates) => {
                let spot = memo(move |sim: &Simulation| table_spot(sim, &plates));
                Arc::new(spot)
            }
        };
        let rot: RotFn = Arc::new(|_, ctx| ctx.home_rot);
        pick_place_turned(&mut phases, body, Vector3::from(RIM_GRASP_OFFSET_M), CARRY_Z_M, to, rot);
    }
    // the hand waits above while the last bowl comes to rest, so the episode ends on a settled state
    phases.push(Phase::new("settle", |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN)).for_steps(SETTLE_STEPS));
    Ok(Box::new(Script::new(phases)))
}

/// Where a bowl goes.
#[derive(Debug, Clone, Copy)]
enum Target {
    Plate(usize),
    /// The free tabletop spot farthest from these plates.
    Table([usize; 4]),
}

/// The [`TABLE_SPOTS_XY_M`] candidate farthest from every plate, at the tabletop (a bowl's root rests ≈ 2 mm above
/// its bottom).
fn table_spot(sim: &Simulation, plates: &[usize; 4]) -> Vector3<f64> {
    let clearance = |xy: &[f64; 2]| {
        let c = Vector3::new(xy[0], xy[1], 0.0);
        plates.iter().map(|&p| xy_dist(pos(sim, p), c)).fold(f64::INFINITY, f64::min)
    };
    let best = TABLE_SPOTS_XY_M.iter().max_by(|a, b| clearance(a).total_cmp(&clearance(b))).copied().unwrap_or(TABLE_SPOTS_XY_M[0]);
    Vector3::new(best[0], best[1], TABLETOP_Z_M)
}

/// Kitchen table top (task catalog §2.3).
const TABLETOP_Z_M: f64 = 0.90;
