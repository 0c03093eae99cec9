//! Start pictures of the perception tasks: each task's scene (seeded placement, as `libero-agent render --bddl` composes
//! it) rendered from the 256×256 head camera, written to `target/test-artifacts/perception/<task>_head.png` so the
//! visual cue (colour, stripes, marks, pose, drink, buttons' paired objects) can be checked by eye. The test checks
//! that each picture is written and not blank.
use std::path::{Path, PathBuf};
use std::process::Command;

mod common;

/// `(task, BDDL stem)` of the perception tasks built so far.
const TASKS: &[(&str, &str)] = &[
    ("T01", "select_upright_marker"),
    ("T02", "select_between_condiments"),
    ("T03", "select_red_object"),
    ("T04", "select_striped_object"),
    ("T05", "select_marked_instance"),
    ("T06", "select_ball_shape"),
    ("T07", "select_cola_drink"),
    ("T08", "weigh_and_place_heaviest_mug"),
    ("T09", "select_highest_reflectance"),
    ("T10", "select_largest_cylinder"),
];

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").canonicalize().expect("repo root")
}

#[test]
fn perception_start_pictures_are_rendered_from_the_head_camera() {
    let root = repo_root();
    let out_dir = root.join("target/test-artifacts/perception");
    std::fs::create_dir_all(&out_dir).expect("artifact dir");
    for (task, stem) in TASKS {
        let tmp = tempfile::tempdir().expect("tempdir");
        let out = Command::new(common::bin())
            .env("XDG_RUNTIME_DIR", std::env::temp_dir())
            .args(["render", "--camera", "head", "--size", "256", "--bddl"])
            .arg(root.join(format!("tasks/bddl/{stem}.bddl")))
            .arg("--out")
            .arg(tmp.path())
            .output()
            .expect("run libero-agent render");
        assert!(out.status.success(), "{task}: {}", String::from_utf8_lossy(&out.stderr));
        let png = std::fs::read(tmp.path().join("head/rgb.png")).expect("head/rgb.png");
        // a flat frame compresses to a few kB; a rendered tabletop scene is tens of kB
        assert!(png.len() > 20_000, "{task}: the head picture looks blank ({} bytes)", png.len());
        let calib: serde_json::Value =
            serde_json::from_slice(&std::fs::read(tmp.path().join("head/calibration.json")).expect("calibration")).expect("json");
        assert_eq!(calib["depth_valid_pixels"], 256 * 256, "{task}: every pixel sees geometry");
        std::fs::write(out_dir.join(format!("{task}_head.png")), &png).expect("write artifact");
    }
}
