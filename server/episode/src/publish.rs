//! Atomic publication of `benchmark_inputs/current_observation/` (§3.4): the frame is written and fsync'd
//! into a staging directory beside it, then swapped in with one `renameat2(RENAME_EXCHANGE)` so that a
//! reader always finds a complete directory (the original renamed the old one aside first, leaving a short
//! window with none), then the old frame is deleted — all before the tool returns.
use std::ffi::CString;
use std::fs;
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::json::sync_dir;
use crate::observation::{Frame, Level, observation_id, write_observation_dir};

/// Swaps two existing paths atomically.
fn exchange(a: &Path, b: &Path) -> std::io::Result<()> {
    let a = CString::new(a.as_os_str().as_bytes()).map_err(std::io::Error::other)?;
    let b = CString::new(b.as_os_str().as_bytes()).map_err(std::io::Error::other)?;
    // SAFETY: two valid NUL-terminated paths; renameat2 only reads them.
    let rc = unsafe {
        libc::renameat2(libc::AT_FDCWD, a.as_ptr(), libc::AT_FDCWD, b.as_ptr(), libc::RENAME_EXCHANGE)
    };
    if rc == 0 { Ok(()) } else { Err(std::io::Error::last_os_error()) }
}

/// Publishes `frame` as the workspace's current observation; returns the observation document.
/// `private_copy_root`, when given, receives an evaluator-private copy at `<root>/<observation_id>/`.
pub fn publish_observation(
    benchmark_inputs: &Path,
    frame: &Frame,
    level: Level,
    private_copy_root: Option<&Path>,
) -> std::io::Result<Value> {
    let id = observation_id(frame.frame_index);
    let staging = benchmark_inputs.join(format!(".current_observation.next-{id}"));
    let current = benchmark_inputs.join("current_observation");
    if staging.exists() {
        fs::remove_dir_all(&staging)?;
    }
    fs::create_dir_all(&staging)?;
    let doc = write_observation_dir(&staging, frame, level)?;
    if let Some(root) = private_copy_root {
        let dest = root.join(&id);
        if dest.exists() {
            return Err(std::io::Error::other(format!("duplicate observation id {id} in the private archive")));
        }
        fs::create_dir_all(root)?;
        copy_dir(&staging, &dest)?;
    }
    if current.exists() {
        match exchange(&staging, &current) {
            Ok(()) => {
                sync_dir(benchmark_inputs)?;
                fs::remove_dir_all(&staging)?; // now holds the previous frame
            }
            Err(_) => {
                // Filesystems without RENAME_EXCHANGE: the original rename-aside sequence.
                let previous = benchmark_inputs.join(format!(".current_observation.previous-{id}"));
                fs::rename(&current, &previous)?;
                fs::rename(&staging, &current)?;
                sync_dir(benchmark_inputs)?;
                fs::remove_dir_all(&previous)?;
            }
        }
    } else {
        fs::rename(&staging, &current)?;
    }
    sync_dir(benchmark_inputs)?;
    Ok(doc)
}

fn copy_dir(from: &Path, to: &Path) -> std::io::Result<()> {
    fs::create_dir_all(to)?;
    for entry in fs::read_dir(from)? {
        let entry = entry?;
        let target: PathBuf = to.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            copy_dir(&entry.path(), &target)?;
        } else {
            fs::copy(entry.path(), &target)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observation::{CameraFrame, RgbImage, RobotReadout};
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};

    /// A synthetic frame (writer test only; episodes publish rendered frames).
    fn frame(index: u64, w: u32, h: u32) -> Frame {
        let n = (w * h) as usize;
        let cam = |shade: u8| CameraFrame {
            image: RgbImage { width: w, height: h, rgb: vec![shade; n * 3] },
            depth_m: (0..n).map(|i| 0.5 + i as f32 * 0.01).collect(),
            depth_valid: (0..n).map(|i| i % 7 != 0).collect(),
            intrinsic_matrix_3x3: [[1.0, 0.0, w as f64 / 2.0], [0.0, 1.0, h as f64 / 2.0], [0.0, 0.0, 1.0]],
            t_robot_base_from_camera: [[1.0, 0.0, 0.0, 0.1], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
        };
        Frame {
            frame_index: index,
            robot: RobotReadout { sim_time_s: index as f64 * 0.05, ..Default::default() },
            head: cam(10),
            wrist: cam(200),
            task_reference: None,
        }
    }

    #[test]
    fn levels_publish_exactly_the_level_matrix_files() {
        let dir = tempfile::tempdir().unwrap();
        for level in [Level::L1, Level::L2, Level::L3] {
            let bi = dir.path().join(level.profile());
            fs::create_dir_all(&bi).unwrap();
            let doc = publish_observation(&bi, &frame(0, 4, 3), level, None).unwrap();
            let cur = bi.join("current_observation");
            let depth_files = ["depth_m.npy", "depth_valid_mask.png", "depth_visualization.png"];
            for cam in ["head", "wrist"] {
                assert!(cur.join(cam).join("rgb.png").is_file());
                for f in depth_files {
                    assert_eq!(cur.join(cam).join(f).is_file(), level == Level::L3, "{level:?} {cam}/{f}");
                }
                let keys: Vec<&String> = doc["cameras"][cam].as_object().unwrap().keys().collect();
                let expected: &[&str] = if level == Level::L3 {
                    &["depth", "intrinsic_matrix_3x3", "matrix_T_robot_base_from_camera_opencv_4x4", "rgb"]
                } else {
                    &["rgb"]
                };
                assert_eq!(keys, expected);
            }
            assert_eq!(doc.get("proprioception").is_some(), level >= Level::L2);
            assert_eq!(doc["capabilities"]["metric_depth"], level == Level::L3);
            let on_disk: Value = serde_json::from_slice(&fs::read(cur.join("observation.json")).unwrap()).unwrap();
            assert_eq!(on_disk, doc);
            let leftovers: Vec<_> = fs::read_dir(&bi).unwrap().map(|e| e.unwrap().file_name()).collect();
            assert_eq!(leftovers, vec![std::ffi::OsString::from("current_observation")], "no staging left behind");
        }
    }

    #[test]
    fn a_reader_never_sees_a_partial_or_missing_observation() {
        let dir = tempfile::tempdir().unwrap();
        let bi = dir.path().to_path_buf();
        publish_observation(&bi, &frame(0, 32, 32), Level::L3, None).unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let reader = {
            let (bi, stop) = (bi.clone(), stop.clone());
            std::thread::spawn(move || {
                let mut reads = 0u32;
                while !stop.load(Ordering::Relaxed) {
                    let cur = bi.join("current_observation");
                    let text = fs::read(cur.join("observation.json")).expect("observation.json always present");
                    let doc: Value = serde_json::from_slice(&text).expect("always complete JSON");
                    assert!(doc["observation_id"].as_str().unwrap().starts_with("obs_"));
                    reads += 1;
                }
                reads
            })
        };
        for i in 1..=30 {
            publish_observation(&bi, &frame(i, 32, 32), Level::L3, None).unwrap();
        }
        stop.store(true, Ordering::Relaxed);
        assert!(reader.join().unwrap() > 0);
        let doc: Value =
            serde_json::from_slice(&fs::read(bi.join("current_observation/observation.json")).unwrap()).unwrap();
        assert_eq!(doc["observation_id"], "obs_000030");
    }

    #[test]
    fn private_copy_refuses_a_duplicate_id() {
        let dir = tempfile::tempdir().unwrap();
        let (bi, private) = (dir.path().join("bi"), dir.path().join("private"));
        fs::create_dir_all(&bi).unwrap();
        publish_observation(&bi, &frame(0, 2, 2), Level::L1, Some(&private)).unwrap();
        assert!(private.join("obs_000000/observation.json").is_file());
        assert!(publish_observation(&bi, &frame(0, 2, 2), Level::L1, Some(&private)).is_err());
    }
}
