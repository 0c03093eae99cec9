//! Demonstration bundles (protocol §7, issue 8): a finished episode's actions, re-rendered by deterministic replay
//! into a self-contained directory (manifest with integrity block, `trajectory.jsonl`, head | wrist MP4, per-camera
//! MP4s, contact sheets), verified by replaying the actions on [`WorldPhysics`](crate::physics::WorldPhysics),
//! validated by the rules of §7.7, projected into an agent's workspace (`benchmark_inputs/expert_demo/`) without
//! private data, and exported to the LeRobot v3 dataset format.
//!
//! The library bundle (schema [`BUNDLE_SCHEMA`]) is private: it names its source episode, seed and init-state
//! index so that it can be replayed. Agents only ever see a projection ([`project`]).
use std::fmt;
use std::path::{Path, PathBuf};

use serde_json::{Value, json};
use thiserror::Error;

use crate::EpisodeError;
pub use libero_records::demo_manifest::{DemoAction, DemoFile, DemoIntegrity, DemoManifest, DemoMeasuredState, DemoTrajectoryRow};
use crate::video::VideoError;

pub mod lerobot;
pub mod library;
pub mod project;
pub mod record;
pub mod replay_attack;
pub mod validate;

pub use project::{DemoCondition, ProjectionReceipt, project_bundle};
pub use record::{BranchOrigin, BundleSummary, RecordOptions, SourceEpisode, record_bundle, record_bundle_with_progress, verify_bundle};
pub use validate::{Violation, validate_bundle};
pub use libero_records::json::sha256_hex;
pub use crate::task::{EffectiveLayout, LayoutVariant};

/// Schema of a library bundle's `manifest.json`.
pub const BUNDLE_SCHEMA: &str = "libero_agent.demonstration_bundle.v1";
/// Schema of one action vector (§7.3).
pub const ACTION_SCHEMA: &str = "libero.normalized_osc_pose_action.v1";
/// §7.6.
pub const SAMPLING_RULE: &str = "uniform_endpoint_preserving_v1";
pub const MAX_FRAMES_PER_SHEET: usize = 12;
/// Video frame rate: one frame per 20 Hz control step, as the private video (§6.1).
pub const DEMO_VIDEO_FPS_HZ: f64 = 20.0;
/// Largest |component| of an accepted action vector (§7.7).
pub const ACTION_LIMIT: f64 = 1.0 + 1e-9;

/// Bundle-relative paths (POSIX).
pub const MANIFEST: &str = "manifest.json";
pub const TRAJECTORY: &str = "trajectory.jsonl";
pub const VIDEO_HEAD_WRIST: &str = "video/head_wrist_rgb.mp4";
pub const VIDEO_HEAD: &str = "video/head_rgb.mp4";
pub const VIDEO_WRIST: &str = "video/wrist_rgb.mp4";
pub const SHEET_HEAD: &str = "video/contact_sheets/head_rgb.png";
pub const SHEET_WRIST: &str = "video/contact_sheets/wrist_rgb.png";

#[derive(Debug, Error)]
pub enum DemoError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// The run directory cannot be turned into a bundle (missing record, no actions, …).
    #[error("source run directory: {0}")]
    Source(String),
    #[error("replay: {0}")]
    Replay(#[from] EpisodeError),
    #[error("video: {0}")]
    Video(#[from] VideoError),
    /// The bundle breaks rules of §7.7; each violation names its file and rule.
    #[error("invalid demonstration bundle {}:\n{}", .dir.display(), violations_text(.violations))]
    Invalid { dir: PathBuf, violations: Vec<Violation> },
    #[error("{0}")]
    Library(String),
    #[error("LeRobot export: {0}")]
    Export(String),
}

fn violations_text(v: &[Violation]) -> String {
    v.iter().map(|v| format!("  {v}")).collect::<Vec<_>>().join("\n")
}

impl fmt::Display for Violation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: [{}] {}", self.file, self.rule, self.detail)
    }
}

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DemoError + '_ {
    move |source| DemoError::Io { path: path.to_owned(), source }
}

/// §7.6 `uniform_endpoint_preserving_v1`: all of `0..n` when `n ≤ limit`, else `round(i·(n−1)/(limit−1))` with
/// Python's round-half-to-even, so first and last frames are always in.
pub fn sample_frame_indices(n: usize, limit: usize) -> Vec<usize> {
    if n <= limit {
        return (0..n).collect();
    }
    if limit < 2 {
        return (0..limit).collect();
    }
    let den = (limit - 1) as u64;
    (0..limit as u64)
        .map(|i| {
            let num = i * (n as u64 - 1);
            let (q, r) = (num / den, num % den);
            let up = 2 * r > den || (2 * r == den && q % 2 == 1);
            (q + u64::from(up)) as usize
        })
        .collect()
}

/// `{path, size_bytes, sha256}` of a bundle file, the integrity record of §7.2.
pub fn file_record(root: &Path, rel: &str) -> Result<DemoFile, DemoError> {
    let path = root.join(rel);
    let bytes = std::fs::read(&path).map_err(io_err(&path))?;
    Ok(DemoFile { path: Some(rel.to_owned()), size_bytes: Some(bytes.len() as u64), sha256: Some(sha256_hex(&bytes)), ..DemoFile::default() })
}

/// An artifact record (`{path, media_type, size_bytes, sha256}`).
pub fn artifact(root: &Path, rel: &str, media_type: &str) -> Result<DemoFile, DemoError> {
    Ok(DemoFile { media_type: Some(media_type.to_owned()), ..file_record(root, rel)? })
}

/// Every regular file under `root` except `manifest.json`, as sorted relative POSIX paths.
pub fn bundle_files(root: &Path) -> Result<Vec<String>, DemoError> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<String>) -> Result<(), DemoError> {
        for entry in std::fs::read_dir(dir).map_err(io_err(dir))? {
            let entry = entry.map_err(io_err(dir))?;
            let path = entry.path();
            let kind = entry.file_type().map_err(io_err(&path))?;
            if kind.is_dir() {
                walk(root, &path, out)?;
            } else {
                let rel = path.strip_prefix(root).unwrap_or(&path);
                out.push(rel.components().map(|c| c.as_os_str().to_string_lossy()).collect::<Vec<_>>().join("/"));
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    walk(root, root, &mut out)?;
    out.retain(|p| p != MANIFEST);
    out.sort();
    Ok(out)
}

/// The `integrity` block: every file except `manifest.json`, sorted by path.
pub fn integrity_block(root: &Path) -> Result<DemoIntegrity, DemoError> {
    let files = bundle_files(root)?.iter().map(|p| file_record(root, p)).collect::<Result<Vec<_>, _>>()?;
    Ok(DemoIntegrity { algorithm: Some("sha256".to_owned()), files: Some(files), ..DemoIntegrity::default() })
}

/// The 7 components of an action vector, in order (§7.3).
pub const ACTION_COMPONENTS: [&str; 7] = [
    "normalized_delta_position_x", "normalized_delta_position_y", "normalized_delta_position_z",
    "normalized_delta_rotation_vector_x", "normalized_delta_rotation_vector_y", "normalized_delta_rotation_vector_z",
    "normalized_gripper_command",
];

/// The canonical `action_semantics` object (§7.3).
pub fn action_semantics() -> Value {
    json!({
        "schema_version": ACTION_SCHEMA,
        "representation": "normalized_libero_osc_pose_7d",
        "component_order": ACTION_COMPONENTS,
        "normalized_range": [-1.0, 1.0],
        "controller_output_scale": {"translation_m_per_unit": 0.05, "rotation_vector_rad_per_unit": 0.5},
        "gripper_command": {"minus_one": "open", "plus_one": "close", "metric_width_semantics": false},
        "liberoctl_step_compatible": false,
        "note": "native per-control-cycle OSC_POSE inputs (one 20 Hz LIBERO policy interval each), not metric commands",
    })
}

/// The measured robot state one trajectory row carries (observations, not actions).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeasuredState {
    /// `[x, y, z, qx, qy, qz, qw]` of the end effector in the robot base frame, metres, `qw ≥ 0`.
    pub eef_pose_robot_base_xyzw: [f64; 7],
    pub gripper_finger_joint_position_m: [f64; 2],
}

impl MeasuredState {
    /// The state as a trajectory row holds it.
    pub fn to_record(&self) -> DemoMeasuredState {
        DemoMeasuredState {
            eef_pose_robot_base_xyzw: Some(self.eef_pose_robot_base_xyzw.to_vec()),
            gripper_finger_joint_position_m: Some(self.gripper_finger_joint_position_m.to_vec()),
            ..DemoMeasuredState::default()
        }
    }

    /// Reads a state of one of our trajectory rows (`None` unless 7 pose numbers and 2 finger positions).
    pub fn from_record(r: &DemoMeasuredState) -> Option<Self> {
        Some(Self {
            eef_pose_robot_base_xyzw: r.eef_pose_robot_base_xyzw.as_deref()?.try_into().ok()?,
            gripper_finger_joint_position_m: r.gripper_finger_joint_position_m.as_deref()?.try_into().ok()?,
        })
    }

    /// Reads a state from plain JSON (the validator's reading of a bundle that may be malformed).
    pub fn from_json(v: &Value) -> Option<Self> {
        let arr = |k: &str, n: usize| -> Option<Vec<f64>> {
            let a = v.get(k)?.as_array()?;
            (a.len() == n).then(|| a.iter().map(Value::as_f64).collect::<Option<Vec<_>>>())?
        };
        let p = arr("eef_pose_robot_base_xyzw", 7)?;
        let g = arr("gripper_finger_joint_position_m", 2)?;
        Some(Self { eef_pose_robot_base_xyzw: p.try_into().ok()?, gripper_finger_joint_position_m: g.try_into().ok()? })
    }
}

/// The `action` object of a trajectory row.
pub fn demo_action(action: &[f64; 7]) -> DemoAction {
    DemoAction { schema_version: Some(ACTION_SCHEMA.to_owned()), normalized_vector_7d: Some(action.to_vec()), ..DemoAction::default() }
}

/// The `action` object of a trajectory row, as JSON (the agent-visible rows are built from it).
pub fn action_value(action: &[f64; 7]) -> Value {
    demo_action(action).to_value()
}

/// One library `trajectory.jsonl` row (keys sorted on write). `call_index` is the `event_index` of the
/// `osc_sequence` call in the source `actions.jsonl`.
pub fn trajectory_row(action_index: usize, call_index: u64, action: &[f64; 7], before: &MeasuredState, after: &MeasuredState) -> DemoTrajectoryRow {
    DemoTrajectoryRow {
        action_index: Some(action_index as u64),
        call_index: Some(call_index),
        action: Some(demo_action(action)),
        frame_before: Some(action_index as u64),
        frame_after: Some(action_index as u64 + 1),
        state_before: Some(before.to_record()),
        state_after: Some(after.to_record()),
        ..DemoTrajectoryRow::default()
    }
}

/// Reads one of our trajectory rows (`line` is 1-based, for the message): its action (checked as [`parse_action`]
/// checks one) and the row.
pub fn read_trajectory_row(text: &str, line: usize) -> Result<([f64; 7], DemoTrajectoryRow), DemoError> {
    let row: DemoTrajectoryRow = serde_json::from_str(text).map_err(|e| DemoError::Source(format!("{TRAJECTORY} line {line}: {e}")))?;
    let action = row
        .action
        .as_ref()
        .and_then(|a| checked_action(a.normalized_vector_7d.as_deref()?))
        .ok_or_else(|| DemoError::Source(format!("{TRAJECTORY} line {line}: not a valid 7-D action")))?;
    Ok((action, row))
}

/// Keys of a library trajectory row, exactly.
pub const TRAJECTORY_ROW_KEYS: [&str; 7] =
    ["action", "action_index", "call_index", "frame_after", "frame_before", "state_after", "state_before"];

/// Reads a 7-D action vector back (`None` unless 7 finite numbers within [`ACTION_LIMIT`]) from plain JSON: the
/// validators' reading of a bundle handed in, which may be malformed (our own rows: [`read_trajectory_row`]).
pub fn parse_action(v: &Value) -> Option<[f64; 7]> {
    let a = v.get("normalized_vector_7d")?.as_array()?;
    let xs: Vec<f64> = a.iter().map(Value::as_f64).collect::<Option<_>>()?;
    checked_action(&xs)
}

/// `xs` as an action: 7 finite numbers within [`ACTION_LIMIT`].
pub fn checked_action(xs: &[f64]) -> Option<[f64; 7]> {
    let xs: [f64; 7] = xs.try_into().ok()?;
    xs.iter().all(|x| x.is_finite() && x.abs() <= ACTION_LIMIT).then_some(xs)
}

/// A manifest's or record's `layout` (absent or null: none); anything else that is not a valid variant is an error.
pub fn layout_from_json(v: &Value) -> Result<Option<LayoutVariant>, DemoError> {
    if v.is_null() {
        return Ok(None);
    }
    let layout: LayoutVariant =
        serde_json::from_value(v.clone()).map_err(|e| DemoError::Source(format!("layout {v}: {e}")))?;
    layout.validate().map_err(|e| DemoError::Source(e.to_string()))?;
    Ok(Some(layout))
}

/// Reads and parses a JSON file.
pub fn read_json(path: &Path) -> Result<Value, DemoError> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    serde_json::from_str(&text).map_err(|e| DemoError::Source(format!("{}: not JSON: {e}", path.display())))
}

/// Reads a bundle's manifest. JSON that is no object has none of its fields, as when it was read as plain JSON (a
/// valid bundle's manifest is an object).
pub fn read_manifest(path: &Path) -> Result<DemoManifest, DemoError> {
    Ok(DemoManifest::from_value(read_json(path)?).unwrap_or_default())
}

/// Video frame count of an MP4 file: `stsz` sample count of the first track (no decoder needed).
pub fn mp4_sample_count(bytes: &[u8]) -> Option<u64> {
    fn find<'a>(mut data: &'a [u8], path: &[&[u8; 4]]) -> Option<&'a [u8]> {
        let (head, rest) = path.split_first()?;
        while data.len() >= 8 {
            let size32 = u32::from_be_bytes(data[0..4].try_into().ok()?) as usize;
            let kind = &data[4..8];
            let (header, size) = match size32 {
                1 => (16, usize::try_from(u64::from_be_bytes(data.get(8..16)?.try_into().ok()?)).ok()?),
                0 => (8, data.len()),
                s => (8, s),
            };
            if size < header || size > data.len() {
                return None;
            }
            if kind == *head {
                let body = &data[header..size];
                return if rest.is_empty() { Some(body) } else { find(body, rest) };
            }
            data = &data[size..];
        }
        None
    }
    let stsz = find(bytes, &[b"moov", b"trak", b"mdia", b"minf", b"stbl", b"stsz"])?;
    Some(u64::from(u32::from_be_bytes(stsz.get(8..12)?.try_into().ok()?)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampling_keeps_endpoints_and_rounds_half_to_even() {
        assert_eq!(sample_frame_indices(5, 12), vec![0, 1, 2, 3, 4]);
        assert_eq!(sample_frame_indices(12, 12), (0..12).collect::<Vec<_>>());
        assert_eq!(sample_frame_indices(0, 12), Vec::<usize>::new());
        // n = 78 (T14's 77 actions + 1): i·77/11 = 7i exactly.
        assert_eq!(sample_frame_indices(78, 12), (0..12).map(|i| 7 * i).collect::<Vec<_>>());
        // n = 14: i·13/11; i = 0..11 → Python: [0, 1, 2, 4, 5, 6, 7, 8, 9, 11, 12, 13]
        assert_eq!(sample_frame_indices(14, 12), vec![0, 1, 2, 4, 5, 6, 7, 8, 9, 11, 12, 13]);
        // n = 23: i·22/11 = 2i; n = 24: i·23/11 → 11.5 at i=5.5 never; check a half case: n = 3, L = 2 → [0, 2].
        assert_eq!(sample_frame_indices(3, 2), vec![0, 2]);
        // Half-way cases: n = 12 + 11/2·… ; (L−1) = 2 with n−1 = 3 gives 1.5 → 2 (even).
        assert_eq!(sample_frame_indices(4, 3), vec![0, 2, 3]);
        assert_eq!(sample_frame_indices(6, 3), vec![0, 2, 5], "2.5 rounds to 2");
    }

    #[test]
    fn mp4_box_walker_finds_nothing_in_garbage() {
        assert_eq!(mp4_sample_count(b"not an mp4 at all"), None);
    }
}
