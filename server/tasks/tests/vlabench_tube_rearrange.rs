//! The pool's `vlabench_tube_precision/1` (rearrange_marked_chemistry_tubes) on its own definition: T18's blue tube
//! and a green one, the NameTag rack with VLABench's hole layout, judged by T18's five checks per tube (K = 2, one
//! stage per tube). The scene composes with the slots at the catalog's offsets, an idle start completes 0 of 2, the
//! expert's `solve` (T18's insertion twice) completes 2 of 2 and `one_tube` 1 of 2; `swapped_slots` (ignored: slow)
//! completes none. Starts are the seed-100 placement, so a run is deterministic.
use libero_sim::mujoco_rs::prelude::MjtObjBase;
use libero_tasks::expert::SOLVE;

mod common;

use common::stages;

const ENTRY: &str = "vlabench_tube_precision/1";

#[test]
fn the_nametag_rack_puts_its_slots_at_the_catalogs_offsets_and_an_idle_start_completes_none() {
    let (_, _, sim, _) = common::start(ENTRY);
    let model = sim.model();
    let rack = model.name_to_id(MjtObjBase::mjOBJ_BODY, "tube_stand_1_main").unwrap();
    let r = sim.data().xpos()[rack];
    for (site, want) in [("tube_stand_1_left_slot", [-0.08, 0.05, 0.055]), ("tube_stand_1_right_slot", [0.08, 0.05, 0.055])] {
        let s = sim.data().site_xpos()[model.name_to_id(MjtObjBase::mjOBJ_SITE, site).unwrap()];
        for k in 0..3 {
            assert!((s[k] - r[k] - want[k]).abs() < 1e-3, "{site}: offset {:?}, want {want:?}", [s[0] - r[0], s[1] - r[1], s[2] - r[2]]);
        }
    }
    let idle = common::idle(ENTRY, 20);
    assert_eq!(stages(&idle), (false, 0, 2), "{idle:?}");
    assert_eq!(idle.terminal_state_checks.len(), 10, "five checks per tube: {:?}", idle.terminal_state_checks);
}

#[test]
fn both_tubes_in_their_tagged_slots_pass_and_one_tube_alone_completes_one_of_two() {
    let solve = common::play(ENTRY, SOLVE);
    assert_eq!(stages(&solve), (true, 2, 2), "{:?}", solve.terminal_state_checks);
    let one = common::play(ENTRY, "one_tube");
    assert_eq!(stages(&one), (false, 1, 2), "{:?}", one.terminal_state_checks);
    assert!(one.terminal_state_checks.iter().filter(|c| !c.passed).all(|c| c.name.starts_with("green_tube_1.")));
}

/// The tubes in each other's slots: both stand upright in a hole, neither in its own. Slow in debug:
/// `cargo test -p libero-tasks --test vlabench_tube_rearrange -- --ignored`.
#[test]
#[ignore]
fn swapped_slots_complete_no_stage() {
    let swapped = common::play(ENTRY, "swapped_slots");
    assert_eq!(stages(&swapped), (false, 0, 2), "{:?}", swapped.terminal_state_checks);
    assert!(swapped.terminal_state_checks.iter().filter(|c| !c.passed).all(|c| c.name.ends_with(".lateral_error")));
}
