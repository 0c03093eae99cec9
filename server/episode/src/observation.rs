//! The public observation (§3.5–§3.8): what one frame holds, how it is projected to levels 1–3, and the
//! files it becomes. Allow-list by construction: only the fields below can ever reach the workspace.
use std::fs::{self, File};
use std::io::Write;
use std::path::Path;

use serde_json::{Value, json};

pub const OBSERVATION_SCHEMA: &str = "libero.agent_observation.v2";

/// Observation level (`profile` `level1`…`level3`), §3.7.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize, serde::Deserialize)]
pub enum Level {
    L1 = 1,
    L2 = 2,
    L3 = 3,
}

impl Level {
    pub fn from_number(n: u8) -> Option<Self> {
        match n {
            1 => Some(Level::L1),
            2 => Some(Level::L2),
            3 => Some(Level::L3),
            _ => None,
        }
    }
    pub fn number(self) -> u8 {
        self as u8
    }
    pub fn profile(self) -> &'static str {
        match self {
            Level::L1 => "level1",
            Level::L2 => "level2",
            Level::L3 => "level3",
        }
    }
}

/// Robot readout for one frame, already in the robot base frame where the name says so.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RobotReadout {
    /// MuJoCo `data.time`.
    pub sim_time_s: f64,
    pub arm_joint_position_rad: [f64; 7],
    /// Finger slide joints as stored in qpos (opposite signs).
    pub gripper_finger_joint_position_m: [f64; 2],
    /// `[x, y, z, qx, qy, qz, qw]` of the controller's end-effector frame in the robot base frame, qw ≥ 0.
    pub eef_pose_robot_base_xyzw: [f64; 7],
    pub arm_joint_velocity_rad_s: [f64; 7],
    pub gripper_finger_joint_velocity_m_s: [f64; 2],
    /// Last commanded arm torques, N·m; `None` when the controller has not run yet.
    pub commanded_arm_joint_torque_nm: Option<[f64; 7]>,
    pub eef_force_sensor_n: [f64; 3],
    pub eef_torque_sensor_nm: [f64; 3],
    /// `[vx, vy, vz, wx, wy, wz]` of the controller's end effector, rotated into the base frame.
    pub eef_twist_robot_base: [f64; 6],
}

/// An 8-bit RGB image, row 0 = top.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    /// `height × width × 3` bytes, row-major.
    pub rgb: Vec<u8>,
}

impl RgbImage {
    /// Reads an 8-bit RGB PNG (a task's reference image, protocol §3.9: it must be RGB, loaded as uint8 H×W×3).
    pub fn read_png(path: &Path) -> std::io::Result<Self> {
        let bad = |why: String| std::io::Error::new(std::io::ErrorKind::InvalidData, format!("{}: {why}", path.display()));
        let file = File::open(path)?;
        let mut reader = png::Decoder::new(std::io::BufReader::new(file)).read_info().map_err(|e| bad(e.to_string()))?;
        let (color, depth) = reader.output_color_type();
        if (color, depth) != (png::ColorType::Rgb, png::BitDepth::Eight) {
            return Err(bad(format!("{color:?} {depth:?}, expected 8-bit RGB")));
        }
        let mut rgb = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut rgb).map_err(|e| bad(e.to_string()))?;
        rgb.truncate(info.buffer_size());
        Ok(Self { width: info.width, height: info.height, rgb })
    }
}

/// One camera's published data. Images are top-left origin (OpenCV).
#[derive(Debug, Clone, PartialEq)]
pub struct CameraFrame {
    pub image: RgbImage,
    /// Planar z-depth along the optical axis, metres, `height × width`, raw even where invalid.
    pub depth_m: Vec<f32>,
    /// The renderer's validity (depth buffer below the far plane); ANDed with finite and positive depth.
    pub depth_valid: Vec<bool>,
    /// `K = [[f, 0, W/2], [0, f, H/2], [0, 0, 1]]`.
    pub intrinsic_matrix_3x3: [[f64; 3]; 3],
    /// Homogeneous `T_robot_base_from_camera` in the OpenCV camera convention.
    pub t_robot_base_from_camera: [[f64; 4]; 4],
}

/// Everything one published frame may contain.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub frame_index: u64,
    pub robot: RobotReadout,
    /// `agentview`.
    pub head: CameraFrame,
    /// `robot0_eye_in_hand`.
    pub wrist: CameraFrame,
    /// The goal image of tasks that have one (§3.9).
    pub task_reference: Option<RgbImage>,
}

/// `obs_%06d` of a frame index.
pub fn observation_id(frame_index: u64) -> String {
    format!("obs_{frame_index:06}")
}

/// How the depth preview's range was chosen (`preview_range_source`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PreviewRangeSource {
    Percentile2To98,
    FiniteMinMaxFallback,
    Degenerate,
    NoValidDepth,
}

impl PreviewRangeSource {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Percentile2To98 => "inverse_depth_percentile_2_98",
            Self::FiniteMinMaxFallback => "finite_min_max_fallback",
            Self::Degenerate => "degenerate",
            Self::NoValidDepth => "no_valid_depth",
        }
    }
}

/// The inverse-depth preview (§3.8) with its metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthPreview {
    pub pixels: Vec<u8>,
    pub near_m: Option<f64>,
    pub far_m: Option<f64>,
    pub source: PreviewRangeSource,
}

/// NumPy's default (`linear`) percentile of sorted values.
fn percentile_sorted(sorted: &[f64], p: f64) -> f64 {
    let pos = (sorted.len() - 1) as f64 * p / 100.0;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

/// Final validity mask: the renderer's flag AND finite AND positive depth.
pub fn valid_mask(cam: &CameraFrame) -> Vec<bool> {
    cam.depth_m.iter().zip(&cam.depth_valid).map(|(&z, &v)| v && z.is_finite() && z > 0.0).collect()
}

/// `inverse_depth_linear_near_white` preview of `depth_m` under `valid`.
pub fn depth_preview(depth_m: &[f32], valid: &[bool]) -> DepthPreview {
    let inv: Vec<f64> = depth_m.iter().zip(valid).filter(|(_, v)| **v).map(|(z, _)| 1.0 / f64::from(*z)).collect();
    if inv.is_empty() {
        return DepthPreview {
            pixels: vec![0; depth_m.len()],
            near_m: None,
            far_m: None,
            source: PreviewRangeSource::NoValidDepth,
        };
    }
    let mut sorted = inv.clone();
    sorted.sort_by(f64::total_cmp);
    let (min, max) = (sorted[0], sorted[sorted.len() - 1]);
    let full_span = max - min;
    let (p2, p98) = (percentile_sorted(&sorted, 2.0), percentile_sorted(&sorted, 98.0));
    let (lower, upper, source) = if full_span > 0.0 && (p98 - p2) <= (0.05 * full_span).max(1e-6) {
        (min, max, PreviewRangeSource::FiniteMinMaxFallback)
    } else if full_span <= 0.0 {
        (min, max, PreviewRangeSource::Degenerate)
    } else {
        (p2, p98, PreviewRangeSource::Percentile2To98)
    };
    let pixels = depth_m
        .iter()
        .zip(valid)
        .map(|(&z, &v)| {
            if !v {
                0
            } else if upper == lower {
                255
            } else {
                let t = ((1.0 / f64::from(z) - lower) / (upper - lower)).clamp(0.0, 1.0);
                (t * 255.0).round_ties_even() as u8
            }
        })
        .collect();
    let positive = |x: f64| (x > 0.0).then(|| 1.0 / x);
    DepthPreview { pixels, near_m: positive(upper), far_m: positive(lower), source }
}

fn coordinate_conventions() -> Value {
    json!({
        "robot_state_frame": "robot_base",
        "eef_delta_frame": "robot_base",
        "eef_rotation_delta": "rotation_vector_rad_left_applied",
        "quaternion_order": "xyzw",
        "camera_frame": "OpenCV: +X right, +Y down, +Z forward",
        "camera_extrinsic": "T_robot_base_from_camera",
        "length_unit": "metre",
    })
}

fn rgb_entry(file: &str, img: &RgbImage) -> Value {
    json!({"file": file, "media_type": "image/png", "shape": [img.height, img.width, 3]})
}

/// The `observation.json` document of `frame` at `level`. `previews` holds each camera's depth preview
/// (level 3 only; computed once by the writer).
pub fn observation_json(frame: &Frame, level: Level, previews: Option<(&DepthPreview, &DepthPreview)>) -> Value {
    let r = &frame.robot;
    let width = r.gripper_finger_joint_position_m[0] - r.gripper_finger_joint_position_m[1];
    let mut doc = json!({
        "schema_version": OBSERVATION_SCHEMA,
        "observation_id": observation_id(frame.frame_index),
        "frame_index": frame.frame_index,
        "sim_time_s": r.sim_time_s,
        "profile": level.profile(),
        "capabilities": {
            "head_rgb": true,
            "wrist_rgb": true,
            "kinematic_state": true,
            "dynamic_proprioception": level >= Level::L2,
            "metric_depth": level >= Level::L3,
            "camera_calibration": level >= Level::L3,
        },
        "coordinate_conventions": coordinate_conventions(),
        "state": {
            "arm_joint_position_rad_7d": r.arm_joint_position_rad,
            "gripper_finger_joint_position_m_2d": r.gripper_finger_joint_position_m,
            "gripper_width_m": width,
            "eef_pose_robot_base_xyzw_7d": r.eef_pose_robot_base_xyzw,
        },
    });
    if level >= Level::L2 {
        let v = r.gripper_finger_joint_velocity_m_s;
        doc["proprioception"] = json!({
            "arm_joint_velocity_rad_s_7d": r.arm_joint_velocity_rad_s,
            "gripper_finger_joint_velocity_m_s_2d": v,
            "gripper_width_velocity_m_s": v[0] - v[1],
            "commanded_arm_joint_torque_nm_7d": r.commanded_arm_joint_torque_nm,
            "commanded_arm_joint_torque_available": r.commanded_arm_joint_torque_nm.is_some(),
            "eef_force_sensor_n_3d": r.eef_force_sensor_n,
            "eef_torque_sensor_nm_3d": r.eef_torque_sensor_nm,
            "eef_twist_robot_base_6d": r.eef_twist_robot_base,
            "force_torque_frame": "eef_ft_sensor",
        });
    }
    let camera = |name: &str, cam: &CameraFrame, preview: Option<&DepthPreview>| {
        let mut c = json!({"rgb": rgb_entry(&format!("{name}/rgb.png"), &cam.image)});
        if level >= Level::L3 {
            let computed;
            let p = match preview {
                Some(p) => p,
                None => {
                    computed = depth_preview(&cam.depth_m, &valid_mask(cam));
                    &computed
                }
            };
            c["depth"] = json!({
                "metric_file": format!("{name}/depth_m.npy"),
                "valid_mask_file": format!("{name}/depth_valid_mask.png"),
                "preview_file": format!("{name}/depth_visualization.png"),
                "dtype": "float32",
                "shape": [cam.image.height, cam.image.width],
                "unit": "metre",
                "preview_near_m": p.near_m,
                "preview_far_m": p.far_m,
                "preview_mapping": "inverse_depth_linear_near_white",
                "preview_range_source": p.source.as_str(),
            });
            c["intrinsic_matrix_3x3"] = json!(cam.intrinsic_matrix_3x3);
            c["matrix_T_robot_base_from_camera_opencv_4x4"] = json!(cam.t_robot_base_from_camera);
        }
        c
    };
    doc["cameras"] = json!({
        "head": camera("head", &frame.head, previews.map(|p| p.0)),
        "wrist": camera("wrist", &frame.wrist, previews.map(|p| p.1)),
    });
    if let Some(reference) = &frame.task_reference {
        doc["task_reference"] = json!({
            "semantics": "desired_object_arrangement",
            "rgb": rgb_entry("task_reference/rgb.png", reference),
        });
    }
    doc
}

/// An 8-bit PNG (`channels` 1 = grayscale, 3 = RGB) encoded in memory.
pub fn encode_png(width: u32, height: u32, channels: u8, data: &[u8]) -> std::io::Result<Vec<u8>> {
    let expected = width as usize * height as usize * channels as usize;
    if data.len() != expected {
        return Err(std::io::Error::other(format!(
            "{} bytes for a {width}×{height}×{channels} image (expected {expected})",
            data.len()
        )));
    }
    let mut bytes = Vec::new();
    let mut enc = png::Encoder::new(&mut bytes, width, height);
    enc.set_color(if channels == 1 { png::ColorType::Grayscale } else { png::ColorType::Rgb });
    enc.set_depth(png::BitDepth::Eight);
    enc.set_compression(png::Compression::Fast);
    let mut w = enc.write_header().map_err(std::io::Error::other)?;
    w.write_image_data(data).map_err(std::io::Error::other)?;
    w.finish().map_err(std::io::Error::other)?;
    Ok(bytes)
}

/// Writes an 8-bit PNG (`channels` 1 = grayscale, 3 = RGB), fsync'd.
pub fn write_png(path: &Path, width: u32, height: u32, channels: u8, data: &[u8]) -> std::io::Result<()> {
    let bytes = encode_png(width, height, channels, data).map_err(|e| std::io::Error::other(format!("{}: {e}", path.display())))?;
    write_synced(path, &bytes)
}

/// A NumPy `.npy` v1.0 file of little-endian float32, C order, encoded in memory.
pub fn npy_f32_bytes(shape: &[usize], data: &[f32]) -> std::io::Result<Vec<u8>> {
    if shape.iter().product::<usize>() != data.len() {
        return Err(std::io::Error::other(format!("shape {shape:?} does not hold {} values", data.len())));
    }
    let dims = match shape {
        [n] => format!("({n},)"),
        _ => format!("({})", shape.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")),
    };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {dims}, }}");
    // magic(6) + version(2) + header length(2) + header, padded with spaces to a multiple of 64, ending in '\n'.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut bytes = Vec::with_capacity(10 + header.len() + 4 * data.len());
    bytes.extend_from_slice(b"\x93NUMPY\x01\x00");
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for v in data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    Ok(bytes)
}

/// Writes a NumPy `.npy` v1.0 file of little-endian float32, C order, fsync'd.
pub fn write_npy_f32(path: &Path, shape: &[usize], data: &[f32]) -> std::io::Result<()> {
    let bytes = npy_f32_bytes(shape, data).map_err(|e| std::io::Error::other(format!("{}: {e}", path.display())))?;
    write_synced(path, &bytes)
}

fn write_synced(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut file = File::create(path)?;
    file.write_all(bytes)?;
    file.sync_all()
}

/// One file of an encoded observation.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodedFile {
    /// `/`-separated path inside the observation directory, e.g. `head/rgb.png` (at most one directory).
    pub rel_path: String,
    pub bytes: Vec<u8>,
}

impl EncodedFile {
    /// The directory part of `rel_path` (None for a top-level file) and the file name.
    pub fn split(&self) -> (Option<&str>, &str) {
        match self.rel_path.split_once('/') {
            Some((dir, name)) => (Some(dir), name),
            None => (None, &self.rel_path),
        }
    }
}

/// A frame encoded once, in memory, so the workspace and the private archive get the same bytes and the
/// server never reads back a directory the agent can write.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodedObservation {
    pub observation_id: String,
    /// The `observation.json` document.
    pub document: Value,
    /// In writing order; `observation.json` last, so a reader that finds it finds every file it names.
    pub files: Vec<EncodedFile>,
}

impl EncodedObservation {
    /// The subdirectories the files live in, in first-use order.
    pub fn dirs(&self) -> Vec<&str> {
        let mut dirs: Vec<&str> = Vec::new();
        for dir in self.files.iter().filter_map(|f| f.split().0) {
            if !dirs.contains(&dir) {
                dirs.push(dir);
            }
        }
        dirs
    }
}

/// Encodes the observation directory of `frame` at `level`: PNGs, depth `.npy` and `observation.json`.
pub fn encode_observation(frame: &Frame, level: Level) -> std::io::Result<EncodedObservation> {
    let file = |rel_path: String, bytes: Vec<u8>| EncodedFile { rel_path, bytes };
    let mut files = Vec::new();
    let mut previews = Vec::new();
    for (name, cam) in [("head", &frame.head), ("wrist", &frame.wrist)] {
        let (w, h) = (cam.image.width, cam.image.height);
        files.push(file(format!("{name}/rgb.png"), encode_png(w, h, 3, &cam.image.rgb)?));
        if level >= Level::L3 {
            let valid = valid_mask(cam);
            files.push(file(format!("{name}/depth_m.npy"), npy_f32_bytes(&[h as usize, w as usize], &cam.depth_m)?));
            let mask: Vec<u8> = valid.iter().map(|&v| if v { 255 } else { 0 }).collect();
            files.push(file(format!("{name}/depth_valid_mask.png"), encode_png(w, h, 1, &mask)?));
            let preview = depth_preview(&cam.depth_m, &valid);
            files.push(file(format!("{name}/depth_visualization.png"), encode_png(w, h, 1, &preview.pixels)?));
            previews.push(preview);
        }
    }
    if let Some(reference) = &frame.task_reference {
        files.push(file("task_reference/rgb.png".into(), encode_png(reference.width, reference.height, 3, &reference.rgb)?));
    }
    let document = observation_json(frame, level, (previews.len() == 2).then(|| (&previews[0], &previews[1])));
    let mut text = libero_records::json::pretty_sorted(&document);
    text.push('\n');
    files.push(file("observation.json".into(), text.into_bytes()));
    Ok(EncodedObservation { observation_id: observation_id(frame.frame_index), document, files })
}

/// Writes `encoded` into `dir` (created with its parents) by path, creating every file new. Only for
/// directories the agent cannot write (the private archive, tests): the workspace goes through
/// [`crate::publish`]. Not fsync'd, like the copy it replaces: a crash ends the episode INVALID anyway.
pub fn write_encoded_dir(dir: &Path, encoded: &EncodedObservation) -> std::io::Result<()> {
    fs::create_dir_all(dir)?;
    for sub in encoded.dirs() {
        fs::create_dir(dir.join(sub))?;
    }
    for f in &encoded.files {
        let mut out = fs::OpenOptions::new().write(true).create_new(true).open(dir.join(&f.rel_path))?;
        out.write_all(&f.bytes)?;
    }
    Ok(())
}

/// Writes the whole observation directory for `frame` at `level` into `dir` (created if missing, holding
/// none of these files); returns the observation document.
pub fn write_observation_dir(dir: &Path, frame: &Frame, level: Level) -> std::io::Result<Value> {
    let encoded = encode_observation(frame, level)?;
    write_encoded_dir(dir, &encoded)?;
    Ok(encoded.document)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_header_is_64_byte_aligned_and_little_endian_f4() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.npy");
        write_npy_f32(&p, &[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.5]).unwrap();
        let bytes = fs::read(&p).unwrap();
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        let header = std::str::from_utf8(&bytes[10..10 + hlen]).unwrap();
        assert!(header.starts_with("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }"));
        assert!(header.ends_with('\n'));
        assert_eq!(&bytes[10 + hlen + 20..], &6.5f32.to_le_bytes());
    }

    #[test]
    fn depth_preview_maps_near_to_white_and_invalid_to_black() {
        // 100 pixels at depths 1..=100 m, the last invalid.
        let depth: Vec<f32> = (1..=100).map(|i| i as f32).collect();
        let mut valid = vec![true; 100];
        valid[99] = false;
        let p = depth_preview(&depth, &valid);
        assert_eq!(p.source, PreviewRangeSource::Percentile2To98);
        assert_eq!(p.pixels[0], 255, "nearest pixel is brighter than the 98th percentile of 1/z");
        assert_eq!(p.pixels[98], 0, "farthest valid pixel is below the 2nd percentile");
        assert_eq!(p.pixels[99], 0, "invalid");
        assert!(p.near_m.unwrap() < p.far_m.unwrap());
        // A flat wall: degenerate, every valid pixel white.
        let flat = depth_preview(&[2.0; 4], &[true, true, false, true]);
        assert_eq!(flat.source, PreviewRangeSource::Degenerate);
        assert_eq!(flat.pixels, vec![255, 255, 0, 255]);
        assert_eq!((flat.near_m, flat.far_m), (Some(2.0), Some(2.0)));
        let none = depth_preview(&[1.0; 3], &[false; 3]);
        assert_eq!((none.source, none.near_m, none.far_m), (PreviewRangeSource::NoValidDepth, None, None));
    }

    #[test]
    fn depth_preview_falls_back_to_min_max_when_percentiles_collapse() {
        // 98 pixels at 1 m and one near, one far outlier: percentile span ≈ 0 < 5 % of the full span.
        let mut depth = vec![1.0f32; 100];
        depth[0] = 0.5;
        depth[1] = 4.0;
        let p = depth_preview(&depth, &[true; 100]);
        assert_eq!(p.source, PreviewRangeSource::FiniteMinMaxFallback);
        assert_eq!((p.pixels[0], p.pixels[1]), (255, 0));
        assert_eq!((p.near_m, p.far_m), (Some(0.5), Some(4.0)));
    }
}
