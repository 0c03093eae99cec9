//! Every one of the 130 benchmark tasks composes, with the dimensions and robot base the real LIBERO env reported
//! (`tests/reference/ref/task_survey.json`); bad inputs fail with messages that name the problem.
mod common;

use libero_bddl::Problem;
use libero_sim::compose::xml::parse_str;
use libero_sim::compose::{compose, compose_file};
use libero_sim::{AssetPaths, SimError};

use common::reference_dir;

fn survey() -> Vec<serde_json::Value> {
    let text = std::fs::read_to_string(reference_dir().join("ref/task_survey.json")).unwrap();
    serde_json::from_str::<serde_json::Value>(&text).unwrap().as_array().unwrap().clone()
}

/// nq/nv from the merged MJCF's joints (free 7/6, ball 4/3, hinge and slide 1/1).
fn dims(mjcf: &str) -> (usize, usize) {
    let root = parse_str(mjcf).unwrap();
    let (mut nq, mut nv) = (0, 0);
    root.child("worldbody").unwrap().walk(None, &mut |e, _| {
        if e.tag == "joint" {
            let (q, v) = match e.get("type").unwrap_or("hinge") {
                "free" => (7, 6),
                "ball" => (4, 3),
                _ => (1, 1),
            };
            nq += q;
            nv += v;
        }
        if e.tag == "freejoint" {
            nq += 7;
            nv += 6;
        }
    });
    (nq, nv)
}

#[test]
fn all_130_stock_tasks_compose_with_the_surveyed_dimensions_and_robot_base() {
    let paths = AssetPaths::discover().expect("assets");
    let rows = survey();
    assert_eq!(rows.len(), 130);
    let mut failures = Vec::new();
    for row in rows {
        let (suite, task) = (row["suite"].as_str().unwrap(), row["task"].as_str().unwrap());
        let scene = match compose_file(&paths.stock_bddl(suite, task), &paths) {
            Ok(s) => s,
            Err(e) => {
                failures.push(format!("{suite}/{task}: {e}"));
                continue;
            }
        };
        let (nq, nv) = dims(&scene.mjcf);
        if (nq as u64, nv as u64) != (row["nq"].as_u64().unwrap(), row["nv"].as_u64().unwrap()) {
            failures.push(format!("{suite}/{task}: nq/nv {nq}/{nv} vs {}/{}", row["nq"], row["nv"]));
        }
        let base: Vec<f64> = row["base_pos"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        if scene.robot_base_pos.iter().zip(&base).any(|(a, b)| (a - b).abs() > 1e-4) {
            failures.push(format!("{suite}/{task}: robot base {:?} vs {base:?}", scene.robot_base_pos));
        }
        let want_mounted = row["robot"].as_str() == Some("MountedPanda");
        if scene.robot_mounted != want_mounted {
            failures.push(format!("{suite}/{task}: mounted {}", scene.robot_mounted));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Slow (compiles 130 models): `cargo test -p libero-sim --test compose_stock -- --ignored`.
#[test]
#[ignore]
fn all_130_stock_tasks_compile() {
    let paths = AssetPaths::discover().expect("assets");
    for row in survey() {
        let (suite, task) = (row["suite"].as_str().unwrap(), row["task"].as_str().unwrap());
        let m = compose_file(&paths.stock_bddl(suite, task), &paths).unwrap().compile().unwrap();
        assert_eq!(m.ffi().nq as u64, row["nq"].as_u64().unwrap(), "{task}");
    }
}

fn compose_text(text: &str) -> Result<libero_sim::compose::ComposedScene, SimError> {
    let paths = AssetPaths::discover().expect("assets");
    compose(&Problem::parse(text).unwrap(), &paths)
}

#[test]
fn unknown_object_category_names_the_category_and_instance() {
    let e = compose_text("(define (problem LIBERO_Tabletop_Manipulation) (:fixtures main_table - table) (:objects u_1 - unicorn))")
        .unwrap_err()
        .to_string();
    assert!(e.contains("unknown object category `unicorn`") && e.contains("u_1"), "{e}");
}

#[test]
fn unknown_problem_class_lists_the_known_ones() {
    let e = compose_text("(define (problem Libero_Moon_Manipulation) (:objects p_1 - plate))").unwrap_err().to_string();
    assert!(e.contains("unknown problem class `libero_moon_manipulation`") && e.contains("libero_floor_manipulation"), "{e}");
}

#[test]
fn workspace_region_without_ranges_is_rejected() {
    let e = compose_text(
        "(define (problem LIBERO_Tabletop_Manipulation) (:regions (r (:target main_table))) (:objects p_1 - plate))",
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("main_table_r") && e.contains("no (:ranges"), "{e}");
}

#[test]
fn authored_scene_gets_region_sites_objects_and_fixtures_in_libero_order() {
    let scene = compose_text(
        "(define (problem LIBERO_Kitchen_Tabletop_Manipulation)
           (:regions (bowl_region (:target kitchen_table) (:ranges ((-0.1 -0.1 0.1 0.1))))
                     (cab_region (:target kitchen_table) (:ranges ((0 -0.3 0.02 -0.28))) (:yaw_rotation ((3.14 3.14))))
                     (top_region (:target wooden_cabinet_1)))
           (:fixtures kitchen_table - kitchen_table wooden_cabinet_1 - wooden_cabinet)
           (:objects bowl_1 - akita_black_bowl plate_1 - plate)
           (:init (On bowl_1 kitchen_table_bowl_region) (On wooden_cabinet_1 kitchen_table_cab_region)))",
    )
    .unwrap();
    let names: Vec<&str> = scene.objects.iter().chain(&scene.fixtures).map(|i| i.name.as_str()).collect();
    assert_eq!(names, ["bowl_1", "plate_1", "wooden_cabinet_1"]);
    assert_eq!(scene.fixtures[0].joints, ["wooden_cabinet_1_top_level", "wooden_cabinet_1_middle_level", "wooden_cabinet_1_bottom_level"]);
    assert_eq!(scene.objects[0].joints, ["bowl_1_joint0"]);
    let top = scene.regions.iter().find(|r| r.key == "wooden_cabinet_1_top_region").unwrap();
    assert_eq!(top.joints, ["wooden_cabinet_1_top_level"], "drawer region keeps the drawer's slide joint");
    let zone = scene.regions.iter().find(|r| r.key == "kitchen_table_bowl_region").unwrap();
    assert_eq!(zone.size, vec![0.1, 0.1, 0.007]);
    assert!(scene.mjcf.contains("name=\"kitchen_table_bowl_region\""));
    let m = scene.compile().unwrap();
    assert_eq!(m.ffi().nq, 9 + 7 + 7 + 3);
}

/// T28's door scene (catalog §2.3, §6.7): robosuite's 0.8 × 0.3 table at (−0.2, −0.35), the mounted Panda's base at
/// (−0.56, 0, 0.912), the door standing on the table (z_offset 0: root at 0.8 + 0.3), and only the hinge exposed as an
/// articulation joint (the latch must not make `Open` true).
#[test]
fn robosuite_door_scene_places_table_robot_and_door_as_robosuite_does() {
    let bddl = libero_testkit::tasks_dir().join("bddl/unlatch_and_open_door.bddl");
    let scene = compose_file(&bddl, &AssetPaths::discover().expect("assets")).unwrap();
    assert_eq!(scene.robot_base_pos, [-0.56, 0.0, 0.912]);
    assert!(scene.robot_mounted);
    assert_eq!(scene.fixture_z_offset, 0.0);
    assert_eq!(scene.fixtures[0].joints, ["latched_door_1_hinge"]);
    assert!(scene.mjcf.contains("name=\"latched_door_1_latch_joint\""));
    let model = scene.compile().unwrap();
    let placement = libero_sim::placement::Placement::sample(&scene, 100, Some(&model)).unwrap();
    let door = &placement.fixtures[0];
    assert!((door.pos[2] - 1.1).abs() < 1e-9, "{door:?}");
    assert!((door.pos[0] + 0.12).abs() <= 0.0100001 && (door.pos[1] + 0.35).abs() <= 0.0100001, "{door:?}");
    let yaw = 2.0 * door.quat_wxyz[3].atan2(door.quat_wxyz[0]);
    assert!((-1.8208..=-1.5707).contains(&yaw), "yaw {yaw}");
    assert!(scene.mjcf.contains("<body name=\"table\" pos=\"-0.2 -0.35 0.775\">"), "table body position");
}
