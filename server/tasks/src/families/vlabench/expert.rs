//! Experts for the VLABench-derived release tasks on this repository's assets: T13 (press the red button) and
//! T18 (insert the blue chemistry tube into the rack's rear-centre slot), and the pool's
//! `vlabench_tube_precision/rearrange_marked_chemistry_tubes` (T18's insertion twice, on the NameTag rack).
use libero_sim::Simulation;
use nalgebra::Vector3;

use crate::expert::motion::{GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, Script, body_point, grip_pose, vec3};
use crate::expert::{Expert, ExpertEntry, SOLVE, SceneRefs};
use crate::TasksError;
use crate::expert::skills::press;

/// T13, T18 and the pool's two-tube rearrangement (T18's insertion twice), with their near misses.
pub const EXPERTS: &[ExpertEntry] = &[
    ExpertEntry { task: "T13", behaviours: &["tap"], build: |refs, b, _| press_button(refs, b) },
    ExpertEntry { task: "T18", behaviours: &["tilted", "beside_slot"], build: |refs, b, _| insert_tube(refs, b) },
    ExpertEntry {
        task: "vlabench_tube_precision/rearrange_marked_chemistry_tubes",
        behaviours: &["swapped_slots", "one_tube"],
        build: |refs, b, _| rearrange_tubes(refs, b),
    },
];

/// The cap's top face in the button body's frame (`vlabench_single_button.xml`: cap centre 0.085, half height 0.010).
const CAP_TOP_LOCAL_M: [f64; 3] = [0.0, 0.0, 0.095];
/// T13: close the gripper, move above the cap, press down and hold 1.5 s, lift off. `tap`: come down slowly and
/// leave the moment the touch sensor fires, so the contact lasts too few substeps. The expert sees the sensor only
/// at control rate, so how long the tap lasts depends on where in a control step the first touch falls: at the
/// release seed 100 the longest pressed run is 6 samples (< 11), and likewise at seeds 1, 2, 4; at seed 3 the touch
/// began early in a step and lasted 26 samples (a press). The near-miss is therefore only claimed at seed 100.
fn press_button(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    press(refs, "button_1", CAP_TOP_LOCAL_M, behaviour == SOLVE)
}

/// Tube geometry (`vlabench_tube.xml`): the root body's origin is the tube's bottom centre; the grip is taken this
/// far above it (the tube is 0.12 m long).
const TUBE_GRIP_HEIGHT_M: f64 = 0.085;
/// Rack geometry (`vlabench_tube_stand.xml`, rack frame): the rear row of holes at local x = 0.05, columns along
/// local y with a 0.055 m pitch; the base plate's top (where a tube stands) 0.048 m above the root.
const REAR_CENTRE_HOLE_LOCAL_M: [f64; 3] = [0.05, 0.0, 0.048];
const HOLE_PITCH_M: f64 = 0.055;
/// Height of the tube's bottom above the rack root while it is carried (top plate is at 0.080).
const CARRY_BOTTOM_ABOVE_ROOT_M: f64 = 0.15;

/// T18: grasp the tube from above, lift, carry above the hole, lower vertically until it stands on the base plate,
/// release, retreat. `beside_slot` does the same into the neighbouring hole of the rear row; `tilted` inserts the
/// tube, then drags the hand sideways before letting go, so the tube is left leaning against the hole's rim.
fn insert_tube(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let hole_local = match behaviour {
        "beside_slot" => [REAR_CENTRE_HOLE_LOCAL_M[0], HOLE_PITCH_M, REAR_CENTRE_HOLE_LOCAL_M[2]],
        _ => REAR_CENTRE_HOLE_LOCAL_M,
    };
    Ok(Box::new(Script::new(insertion_phases(refs, "blue_tube_1", hole_local, behaviour == "tilted")?)))
}

/// NameTag rack (`vlabench_tube_stand_tagged.xml`, rack frame): the rear-row holes under the sites `left_slot` and
/// `right_slot`, at the height of the base plate's top.
const LEFT_SLOT_HOLE_LOCAL_M: [f64; 3] = [0.05, 0.08, 0.048];
const RIGHT_SLOT_HOLE_LOCAL_M: [f64; 3] = [0.05, -0.08, 0.048];

/// Rearrangement: T18's insertion twice, the blue (CuSO4) tube into the hole under the "CuSO4" tag (`left_slot`),
/// then the green (CuCl2) one under "CuCl2" (`right_slot`). `swapped_slots` exchanges the holes; `one_tube` inserts
/// only the blue tube.
fn rearrange_tubes(refs: &SceneRefs, behaviour: &str) -> Result<Box<dyn Expert>, TasksError> {
    let (blue_hole, green_hole) = match behaviour {
        "swapped_slots" => (RIGHT_SLOT_HOLE_LOCAL_M, LEFT_SLOT_HOLE_LOCAL_M),
        _ => (LEFT_SLOT_HOLE_LOCAL_M, RIGHT_SLOT_HOLE_LOCAL_M),
    };
    let mut phases = insertion_phases(refs, "blue_tube_1", blue_hole, false)?;
    if behaviour != "one_tube" {
        phases.extend(insertion_phases(refs, "green_tube_1", green_hole, false)?);
    }
    Ok(Box::new(Script::new(phases)))
}

/// Phases that insert `tube` into the hole at `hole_local` of the rack `tube_stand_1` (see [`insert_tube`]);
/// `tilted` drags the hand sideways before letting go.
fn insertion_phases(refs: &SceneRefs, tube: &str, hole_local: [f64; 3], tilted: bool) -> Result<Vec<Phase>, TasksError> {
    let tube = refs.instance_body(tube)?;
    let rack = refs.instance_body("tube_stand_1")?;
    let tube_pos = move |sim: &Simulation| vec3(&sim.data().xpos()[tube]);
    let hole = move |sim: &Simulation| body_point(sim, rack, hole_local);
    // grip-site goal that puts the tube's bottom at `bottom`, correcting for where the tube sits in the fingers
    let grip_for_bottom = move |sim: &Simulation, bottom: Vector3<f64>| {
        let (grip, _) = grip_pose(sim);
        bottom + (grip - tube_pos(sim))
    };
    let lateral_error = move |sim: &Simulation| {
        let d = tube_pos(sim) - hole(sim);
        (d.x * d.x + d.y * d.y).sqrt()
    };
    let up = Vector3::z();
    let mut phases = vec![
        Phase::new("above_tube", move |sim, _| Goal::at(tube_pos(sim) + up * (TUBE_GRIP_HEIGHT_M + 0.10), GRIPPER_OPEN))
            .until_reached(0.01),
        Phase::new("down_to_tube", move |sim, _| Goal::at(tube_pos(sim) + up * TUBE_GRIP_HEIGHT_M, GRIPPER_OPEN).slow(0.5))
            .until_reached(0.005),
        Phase::new("grasp", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED)).for_steps(12),
        Phase::new("lift", move |sim, ctx| {
            let z = hole(sim).z - hole_local[2] + CARRY_BOTTOM_ABOVE_ROOT_M + TUBE_GRIP_HEIGHT_M;
            Goal::at(Vector3::new(ctx.start_pos_m.x, ctx.start_pos_m.y, z), GRIPPER_CLOSED).slow(0.6)
        })
        .until_reached(0.01),
        Phase::new("carry_above_hole", move |sim, _| {
            let above = hole(sim) + up * (CARRY_BOTTOM_ABOVE_ROOT_M - hole_local[2]);
            Goal::at(grip_for_bottom(sim, above), GRIPPER_CLOSED).slow(0.6)
        })
        .until(move |sim, _| lateral_error(sim) < 0.002)
        .max_steps(200),
        Phase::new("lower_into_hole", move |sim, _| {
            let xy_hole = hole(sim);
            Goal::at(grip_for_bottom(sim, xy_hole - up * 0.01), GRIPPER_CLOSED).slow(0.25)
        })
        .until(move |sim, _| tube_pos(sim).z - hole(sim).z < 0.003)
        .max_steps(120),
    ];
    if tilted {
        phases.push(
            Phase::new("drag_sideways", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::x() * 0.05, GRIPPER_CLOSED).slow(0.2))
                .for_steps(20),
        );
    }
    phases.extend([
        Phase::new("release", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN)).for_steps(12),
        Phase::new("retreat", move |_, ctx| Goal::at(ctx.start_pos_m + up * 0.10, GRIPPER_OPEN).slow(0.5)).until_reached(0.01),
        Phase::new("wait", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN)).for_steps(10),
    ]);
    Ok(phases)
}
