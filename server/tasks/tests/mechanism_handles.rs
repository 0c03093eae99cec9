//! The handles `tasks/mechanism_handles.json` declares (Figure 3 counts gripper–handle contact only) are the handles of
//! the composed models: every declared geom of every class is in a scene with that fixture, on its declared body, and
//! has the shape the asset file gives the handle — so a wrong `g<k>` (the composer's name of an unnamed geom) that
//! would point at a drawer's front or a door's panel fails here. A declaration naming a geom the model lacks is refused
//! with a clear error.
use std::path::{Path, PathBuf};

use libero_sim::AssetPaths;
use libero_sim::compose::compose_file;
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_tasks::SceneIndex;
use libero_tasks::judge::mechanism::{GripperContact, class_handles};

const CAPSULE: i32 = 3;
const CYLINDER: i32 = 5;
const BOX: i32 = 6;

/// (geom, MuJoCo type, size) of a class's handle geoms as the asset file writes them (sizes of capsules and cylinders:
/// radius, half-length; a `fromto` cylinder's half-length is half its span).
type Shape = (&'static str, i32, [f64; 3]);

const MICROWAVE: &[Shape] =
    &[("g14", CAPSULE, [0.01, 0.065, 0.0]), ("g15", CAPSULE, [0.01, 0.015, 0.0]), ("g16", CAPSULE, [0.01, 0.015, 0.0])];
/// articulated_objects/wooden_cabinet.xml and white_cabinet.xml, each drawer's bar and two posts.
const CABINET: &[Shape] = &[
    ("g18", BOX, [0.0077, 0.00817, 0.04445]),
    ("g19", BOX, [0.00507, 0.00552, 0.01057]),
    ("g20", BOX, [0.00507, 0.0056, 0.01057]),
    ("g29", BOX, [0.0077, 0.00817, 0.04445]),
    ("g30", BOX, [0.00507, 0.00552, 0.01057]),
    ("g31", BOX, [0.00507, 0.0056, 0.01057]),
    ("g40", BOX, [0.0077, 0.00817, 0.04445]),
    ("g41", BOX, [0.00507, 0.00552, 0.01057]),
    ("g42", BOX, [0.00507, 0.0056, 0.01057]),
];
/// articulated_objects/short_cabinet.xml: each drawer's bent bar, five boxes.
const SHORT_CABINET_BAR: [[f64; 3]; 5] =
    [[0.00102, 0.00228, 0.01031], [0.00104, 0.00228, 0.00806], [0.00104, 0.00228, 0.00806], [0.00129, 0.00203, 0.00228], [0.00129, 0.00203, 0.00228]];
/// assets/objects/robosuite_latched_door: the lever's hub (cylinder from y 0.0625 to −0.125) and arm.
const LATCHED_DOOR: &[Shape] = &[("handle_base", CYLINDER, [0.025, 0.09375, 0.0]), ("handle", BOX, [0.075, 0.015, 0.02])];

fn paths() -> AssetPaths {
    AssetPaths::discover().expect("assets cached by scripts/setup.py")
}

fn compiled(bddl: &Path) -> (SceneIndex, MjModel) {
    let scene = compose_file(bddl, &paths()).unwrap_or_else(|e| panic!("{}: {e}", bddl.display()));
    let model = scene.compile().unwrap();
    (SceneIndex::new(&scene, &model).unwrap(), model)
}

fn repo(path: &str) -> PathBuf {
    libero_testkit::repo_root().join(path)
}

/// Every handle geom declared for `instance`'s class is in `model` on its declared body with the shape `shapes` gives.
fn check(index: &SceneIndex, model: &MjModel, instance: &str, shapes: &[Shape]) {
    let inst = &index.instances[index.instance(instance).unwrap_or_else(|| panic!("no instance {instance}"))];
    let declared = class_handles(&inst.category).unwrap();
    let names: Vec<&str> = declared.iter().flat_map(|h| h.geoms.iter().map(String::as_str)).collect();
    assert_eq!(names, shapes.iter().map(|s| s.0).collect::<Vec<_>>(), "{} ({})", instance, inst.category);
    for h in declared {
        let body = model.name_to_id(MjtObjBase::mjOBJ_BODY, &format!("{instance}_{}", h.body)).expect("declared body");
        for g in &h.geoms {
            let id = model.name_to_id(MjtObjBase::mjOBJ_GEOM, &format!("{instance}_{g}")).expect("declared geom");
            let (_, ty, size) = shapes.iter().find(|s| s.0 == g).unwrap();
            assert_eq!(model.geom_bodyid()[id] as usize, body, "{instance}_{g}");
            assert_eq!((model.geom_type()[id] as i32, model.geom_group()[id]), (*ty, 0), "{instance}_{g}: a collision geom of the handle's type");
            let got = model.geom_size()[id];
            assert!(got.iter().zip(size).all(|(a, b)| (a - b).abs() < 1e-5), "{instance}_{g}: size {got:?}, the asset's handle {size:?}");
        }
    }
    GripperContact::new(index, model).expect("the scene's handles resolve");
}

#[test]
fn every_declared_handle_is_the_assets_handle_in_a_composed_scene() {
    let p = paths();
    let (index, model) = compiled(&p.stock_bddl("libero_90", "KITCHEN_SCENE6_close_the_microwave"));
    check(&index, &model, "microwave_1", MICROWAVE);
    let (index, model) = compiled(&p.stock_bddl("libero_90", "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet"));
    check(&index, &model, "wooden_cabinet_1", CABINET);
    let (index, model) = compiled(&p.stock_bddl("libero_10", "KITCHEN_SCENE4_put_the_black_bowl_in_the_bottom_drawer_of_the_cabinet_and_close_it"));
    check(&index, &model, "white_cabinet_1", CABINET);
    // T23/T27's raised cabinet (wooden_cabinet_tall_bottom): the wooden cabinet on a plinth, geoms unchanged
    let (index, model) = compiled(&repo("tasks/bddl/robomemarena_task_13.bddl"));
    assert_eq!(index.instances[index.instance("wooden_cabinet_1").unwrap()].category, "wooden_cabinet_tall_bottom");
    check(&index, &model, "wooden_cabinet_1", CABINET);
    let (index, model) = compiled(&repo("tasks/bddl/unlatch_and_open_door.bddl"));
    check(&index, &model, "latched_door_1", LATCHED_DOOR);
    // No task opens the short cabinet: a stock scene with the wooden cabinet swapped for it.
    let dir = tempfile::tempdir().unwrap();
    let bddl = std::fs::read_to_string(p.stock_bddl("libero_90", "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet")).unwrap();
    let short = dir.path().join("short_cabinet.bddl");
    std::fs::write(&short, bddl.replace("wooden_cabinet", "short_cabinet")).unwrap();
    let (index, model) = compiled(&short);
    let names = ["g12", "g13", "g14", "g15", "g16", "g23", "g24", "g25", "g26", "g27", "g34", "g35", "g36", "g37", "g38"];
    let shapes: Vec<Shape> = names.iter().enumerate().map(|(k, &g)| (g, BOX, SHORT_CABINET_BAR[k % 5])).collect();
    check(&index, &model, "short_cabinet_1", &shapes);
}

#[test]
fn a_declared_handle_missing_from_the_model_is_refused_by_name() {
    // The microwave asset with its handle's collision capsules removed: the declared `g14` … no longer exist (the
    // composer's numbering of the remaining geoms stops at g14, the door panel).
    let p = paths();
    let dir = tempfile::tempdir().unwrap();
    let assets = dir.path().join("assets");
    link_entries(&p.libero_assets, &assets, "articulated_objects");
    link_entries(&p.libero_assets.join("articulated_objects"), &assets.join("articulated_objects"), "microwave.xml");
    let xml = std::fs::read_to_string(p.libero_assets.join("articulated_objects/microwave.xml")).unwrap();
    let without: String = xml.lines().filter(|l| !(l.contains("micro_collision") && l.contains("capsule"))).map(|l| format!("{l}\n")).collect();
    assert_eq!(xml.lines().count() - without.lines().count(), 3, "the three handle capsules");
    std::fs::write(assets.join("articulated_objects/microwave.xml"), without).unwrap();
    let paths = AssetPaths { libero_assets: assets, ..p.clone() };
    let scene = compose_file(&p.stock_bddl("libero_90", "KITCHEN_SCENE6_close_the_microwave"), &paths).unwrap();
    let model = scene.compile().unwrap();
    let index = SceneIndex::new(&scene, &model).unwrap();
    let err = GripperContact::new(&index, &model).unwrap_err().to_string();
    assert!(err.contains("microwave_1") && err.contains("mechanism_handles.json") && err.contains("microwave_1_g15"), "{err}");
}

/// `to` made a folder whose entries are links to `from`'s, except `except` (made a folder for a directory, left out
/// for a file), so the cached assets are never written through.
fn link_entries(from: &Path, to: &Path, except: &str) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_name() != except {
            std::os::unix::fs::symlink(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}
