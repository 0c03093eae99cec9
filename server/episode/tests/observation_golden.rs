//! Golden wire format of a level-3 `observation.json` (key names, nesting, units, JSON layout), written by the
//! real writer from a fixed frame. Regenerate deliberately with `UPDATE_GOLDEN=1`.
use std::path::PathBuf;

use sha2::{Digest, Sha256};

use libero_episode::observation::{CameraFrame, Frame, Level, RgbImage, RobotReadout, write_observation_dir};

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name)
}

/// A fixed 4×2 frame with exactly representable numbers (a writer fixture, not a simulation).
fn fixed_frame() -> Frame {
    let (w, h) = (4u32, 2u32);
    let cam = |z0: f32| CameraFrame {
        image: RgbImage { width: w, height: h, rgb: (0..(w * h * 3) as u8).collect() },
        depth_m: (0..8).map(|i| z0 + 0.25 * i as f32).collect(),
        depth_valid: vec![true, true, true, true, true, true, true, false],
        intrinsic_matrix_3x3: [[2.0, 0.0, 2.0], [0.0, 2.0, 1.0], [0.0, 0.0, 1.0]],
        t_robot_base_from_camera: [
            [0.0, -1.0, 0.0, 0.5],
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 1.25],
            [0.0, 0.0, 0.0, 1.0],
        ],
    };
    Frame {
        frame_index: 12,
        robot: RobotReadout {
            sim_time_s: 1.1,
            arm_joint_position_rad: [0.0, -0.25, 0.0, -2.5, 0.0, 2.25, 0.75],
            gripper_finger_joint_position_m: [0.03125, -0.03125],
            eef_pose_robot_base_xyzw: [0.5, 0.0, 0.25, 1.0, 0.0, 0.0, 0.0],
            arm_joint_velocity_rad_s: [0.0; 7],
            gripper_finger_joint_velocity_m_s: [0.5, -0.25],
            commanded_arm_joint_torque_nm: Some([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]),
            eef_force_sensor_n: [0.0, 0.0, -9.5],
            eef_torque_sensor_nm: [0.0, 0.125, 0.0],
            eef_twist_robot_base: [0.0, 0.0, 0.0625, 0.0, 0.0, 0.0],
        },
        head: cam(0.5),
        wrist: cam(0.125),
        task_reference: None,
    }
}

#[test]
fn level3_observation_json_matches_the_golden_fixture() {
    let dir = tempfile::tempdir().unwrap();
    write_observation_dir(dir.path(), &fixed_frame(), Level::L3).unwrap();
    let text = std::fs::read_to_string(dir.path().join("observation.json")).unwrap();
    if std::env::var_os("UPDATE_GOLDEN").is_some() {
        std::fs::write(fixture("observation_level3.json"), &text).unwrap();
    }
    let golden = std::fs::read_to_string(fixture("observation_level3.json")).unwrap();
    assert_eq!(text, golden, "observation.json wire format changed");
    assert!(text.ends_with("}\n"), "indent-2, sorted keys, trailing newline");
}

/// sha256 of every file of the fixed frame's level-3 directory (with a task reference image): the PNG and
/// `.npy` bytes are part of the wire format too.
#[test]
fn level3_files_match_their_golden_digests() {
    let dir = tempfile::tempdir().unwrap();
    let mut frame = fixed_frame();
    frame.task_reference = Some(RgbImage { width: 2, height: 2, rgb: (0..12).map(|i| i * 20).collect() });
    write_observation_dir(dir.path(), &frame, Level::L3).unwrap();
    let mut digests = serde_json::Map::new();
    for rel in [
        "head/rgb.png",
        "head/depth_m.npy",
        "head/depth_valid_mask.png",
        "head/depth_visualization.png",
        "wrist/rgb.png",
        "wrist/depth_m.npy",
        "wrist/depth_valid_mask.png",
        "wrist/depth_visualization.png",
        "task_reference/rgb.png",
        "observation.json",
    ] {
        let bytes = std::fs::read(dir.path().join(rel)).unwrap();
        let hex: String = Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect();
        digests.insert(rel.to_owned(), serde_json::Value::String(hex));
    }
    let text = serde_json::to_string_pretty(&digests).unwrap() + "\n";
    if std::env::var_os("UPDATE_GOLDEN").is_some() {
        std::fs::write(fixture("observation_level3_files.json"), &text).unwrap();
    }
    let golden = std::fs::read_to_string(fixture("observation_level3_files.json")).unwrap();
    assert_eq!(text, golden, "published file bytes changed");
}

#[test]
fn lower_levels_are_projections_of_level3() {
    let dir = tempfile::tempdir().unwrap();
    let frame = fixed_frame();
    let l3: serde_json::Value =
        write_observation_dir(&dir.path().join("l3"), &frame, Level::L3).unwrap();
    for level in [Level::L1, Level::L2] {
        let v = write_observation_dir(&dir.path().join(level.profile()), &frame, level).unwrap();
        assert_eq!(v["state"], l3["state"]);
        assert_eq!(v["coordinate_conventions"], l3["coordinate_conventions"]);
        assert_eq!(v["cameras"]["head"]["rgb"], l3["cameras"]["head"]["rgb"]);
        assert_eq!(v.get("proprioception"), if level == Level::L2 { l3.get("proprioception") } else { None });
    }
}
