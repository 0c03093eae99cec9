//! The generic stock expert's planner on real stock scenes: every one of the 130 stock goals plans, and the order is
//! one that works (implicit openings before a placement into a closed drawer, closings after it, articulations
//! before placements, a support object before what is stacked on it, what stands in a pushed plate's way moved first).
use libero_sim::AssetPaths;
use libero_sim::compose::compose_file;
use libero_tasks::{STOCK_SUITES, expert_plan};

fn plan(task: &str) -> Vec<String> {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let (suite, name) = task.split_once('/').expect("suite/name");
    let scene = compose_file(&paths.stock_bddl(suite, name), &paths).expect("compose");
    let model = scene.compile().expect("compile");
    expert_plan(task, &scene, &model).unwrap_or_else(|e| panic!("{task}: {e}"))
}

#[test]
fn stock_goals_plan_in_an_order_that_works() {
    assert_eq!(
        plan("libero_90/KITCHEN_SCENE10_put_the_butter_at_the_back_in_the_top_drawer_of_the_cabinet_and_close_it"),
        [
            "place butter_2 clear of wooden_cabinet_1_top_region (implicit)",
            "open wooden_cabinet_1_top_region (implicit)",
            "place butter_2 in wooden_cabinet_1_top_region",
            "close wooden_cabinet_1_top_region"
        ]
    );
    assert_eq!(
        plan("libero_90/LIVING_ROOM_SCENE4_stack_the_left_bowl_on_the_right_bowl_and_place_them_in_the_tray"),
        ["place akita_black_bowl_2 in wooden_tray_1_contain_region", "place akita_black_bowl_1 on akita_black_bowl_2"]
    );
    assert_eq!(
        plan("libero_10/KITCHEN_SCENE8_put_both_moka_pots_on_the_stove"),
        ["turn on flat_stove_1", "place moka_pot_1 on flat_stove_1_cook_region", "place moka_pot_2 on flat_stove_1_cook_region"]
    );
    assert_eq!(
        plan("libero_10/KITCHEN_SCENE6_put_the_yellow_and_white_mug_in_the_microwave_and_close_it"),
        ["open microwave_1 (implicit)", "place white_yellow_mug_1 in microwave_1_heating_region", "close microwave_1"]
    );
    assert_eq!(plan("libero_90/KITCHEN_SCENE8_turn_off_the_stove"), ["turn off flat_stove_1"]);
    // every other movable object may stand in the pushed plate's way: a clearing step each (skipped when clear)
    assert_eq!(
        plan("libero_goal/push_the_plate_to_the_front_of_the_stove"),
        [
            "place akita_black_bowl_1 clear of plate_1's way to main_table_stove_front_region (implicit)",
            "place cream_cheese_1 clear of plate_1's way to main_table_stove_front_region (implicit)",
            "place wine_bottle_1 clear of plate_1's way to main_table_stove_front_region (implicit)",
            "place plate_1 on main_table_stove_front_region"
        ]
    );
}

/// Composes and compiles all 130 scenes (about a minute in a debug build): `cargo test -- --ignored`; `expert --all`
/// checks the same on every full run.
#[test]
#[ignore]
fn every_stock_goal_plans() {
    let paths = AssetPaths::discover().expect("assets");
    let mut n = 0;
    for suite in STOCK_SUITES {
        let dir = paths.stock_bddl(suite, "x").parent().expect("folder").to_path_buf();
        for entry in std::fs::read_dir(&dir).expect("stock BDDL folder") {
            let file = entry.expect("entry").file_name().to_string_lossy().into_owned();
            let Some(name) = file.strip_suffix(".bddl") else { continue };
            assert!(!plan(&format!("{suite}/{name}")).is_empty(), "{suite}/{name}");
            n += 1;
        }
    }
    assert_eq!(n, 130);
}
