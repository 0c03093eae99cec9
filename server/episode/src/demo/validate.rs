//! §7.7 validation of a library bundle. Every violation names the file and the rule it breaks, so a person can
//! tell a tampered action from a missing video without reading code.
//!
//! The bundle is read as plain JSON here, not through the typed [`DemoManifest`] and [`DemoTrajectoryRow`]: a
//! bundle handed in may be malformed, and the rules are about its exact keys and the type of each value (a typed
//! reading keeps an ill-typed value aside as if it were absent, and cannot say which key was unexpected).
use std::collections::BTreeSet;
use std::fs;
use std::path::Path;

use serde_json::Value;

use super::*;
use libero_records::json::compact_sorted;

/// One broken rule.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Violation {
    /// Bundle-relative path (or `.` for the bundle root).
    pub file: String,
    /// Short rule name: `missing_file`, `sha256_mismatch`, `size_mismatch`, `unlisted_file`, `symlink`, `bad_json`,
    /// `manifest_keys`, `schema_version`, `action_semantics`, `trajectory_keys`, `action_schema`,
    /// `action_out_of_range`, `action_index`, `not_canonical`, `frame_count`, `video_frame_count`, `sampling`,
    /// `artifact_mismatch`, `integrity`, `path`.
    pub rule: &'static str,
    pub detail: String,
}

fn v(file: &str, rule: &'static str, detail: impl Into<String>) -> Violation {
    Violation { file: file.to_owned(), rule, detail: detail.into() }
}

const MANIFEST_KEYS: [&str; 11] = [
    "action_semantics", "frame_count", "integrity", "overview", "schema_version", "source", "task", "trajectory",
    "transition_count", "verification", "video",
];

/// Checks a library bundle against §7.7's rules (as they apply to its schema). Empty when valid.
pub fn validate_bundle(dir: &Path) -> Vec<Violation> {
    let mut out = Vec::new();
    match fs::symlink_metadata(dir) {
        Ok(m) if m.is_dir() => {}
        Ok(_) => return vec![v(".", "not_a_directory", format!("{} is not a real directory", dir.display()))],
        Err(e) => return vec![v(".", "missing_file", format!("{}: {e}", dir.display()))],
    }
    check_no_symlinks(dir, dir, &mut out);
    let manifest = match fs::read_to_string(dir.join(MANIFEST)) {
        Err(e) => {
            out.push(v(MANIFEST, "missing_file", e.to_string()));
            return out;
        }
        Ok(text) => match serde_json::from_str::<Value>(&text) {
            Ok(m) => m,
            Err(e) => {
                out.push(v(MANIFEST, "bad_json", e.to_string()));
                return out;
            }
        },
    };
    check_manifest_shape(&manifest, &mut out);
    let listed = check_integrity(dir, &manifest, &mut out);
    check_artifacts(&manifest, &listed, &mut out);
    let frames = manifest["frame_count"].as_u64();
    let transitions = manifest["transition_count"].as_u64();
    if let (Some(f), Some(t)) = (frames, transitions) {
        if f != t + 1 {
            out.push(v(MANIFEST, "frame_count", format!("frame_count {f} must be transition_count {t} + 1")));
        }
    }
    check_trajectory(dir, transitions, &mut out);
    if let Some(f) = frames {
        check_videos(dir, f, &mut out);
        let expected = sample_frame_indices(f as usize, MAX_FRAMES_PER_SHEET);
        let got = &manifest["overview"]["sampling"]["sampled_frame_indices"];
        if *got != serde_json::json!(expected) {
            out.push(v(MANIFEST, "sampling", format!("sampled_frame_indices {got} are not {SAMPLING_RULE} of {f} frames: {expected:?}")));
        }
        check_sheets(dir, expected.len(), &mut out);
    }
    out
}

fn check_no_symlinks(root: &Path, dir: &Path, out: &mut Vec<Violation>) {
    let Ok(entries) = fs::read_dir(dir) else { return };
    for e in entries.flatten() {
        let path = e.path();
        let rel = path.strip_prefix(root).unwrap_or(&path).to_string_lossy().into_owned();
        match e.file_type() {
            Ok(t) if t.is_symlink() => out.push(v(&rel, "symlink", "bundles may not contain symbolic links")),
            Ok(t) if t.is_dir() => check_no_symlinks(root, &path, out),
            _ => {}
        }
    }
}

fn check_manifest_shape(m: &Value, out: &mut Vec<Violation>) {
    let Some(obj) = m.as_object() else {
        out.push(v(MANIFEST, "manifest_keys", "the manifest is not a JSON object"));
        return;
    };
    // `replay_checks` (issue 31) is absent from bundles recorded before replay checks existed
    let keys: BTreeSet<&str> = obj.keys().map(String::as_str).filter(|k| *k != "replay_checks").collect();
    let allowed: BTreeSet<&str> = MANIFEST_KEYS.into_iter().collect();
    if obj.get("replay_checks").is_some_and(|c| !c.is_array()) {
        out.push(v(MANIFEST, "manifest_keys", "replay_checks must be an array"));
    }
    if keys != allowed {
        let extra: Vec<_> = keys.difference(&allowed).collect();
        let missing: Vec<_> = allowed.difference(&keys).collect();
        out.push(v(MANIFEST, "manifest_keys", format!("unexpected keys {extra:?}, missing keys {missing:?}")));
    }
    if m["schema_version"] != BUNDLE_SCHEMA {
        out.push(v(MANIFEST, "schema_version", format!("schema_version {} is not {BUNDLE_SCHEMA:?}", m["schema_version"])));
    }
    if m["action_semantics"] != action_semantics() {
        out.push(v(MANIFEST, "action_semantics", "action_semantics differs from the canonical object of §7.3"));
    }
    if m["task"]["instruction"].as_str().is_none() || m["task"]["id"].as_str().is_none() {
        out.push(v(MANIFEST, "manifest_keys", "task.id and task.instruction must be strings"));
    }
    if m["verification"]["verified"].as_bool().is_none() {
        out.push(v(MANIFEST, "manifest_keys", "verification.verified must be true or false"));
    }
}

/// Checks the integrity block against the files on disk; returns the listed records by path.
fn check_integrity(dir: &Path, m: &Value, out: &mut Vec<Violation>) -> Vec<Value> {
    let integrity = &m["integrity"];
    if integrity["algorithm"] != "sha256" {
        out.push(v(MANIFEST, "integrity", "integrity.algorithm must be \"sha256\""));
    }
    let Some(files) = integrity["files"].as_array() else {
        out.push(v(MANIFEST, "integrity", "integrity.files is not a list"));
        return Vec::new();
    };
    let mut listed = Vec::new();
    for rec in files {
        let Some(rel) = rec["path"].as_str() else {
            out.push(v(MANIFEST, "integrity", format!("a file record without a path: {rec}")));
            continue;
        };
        if !canonical_relative(rel) {
            out.push(v(rel, "path", "artifact paths must be relative, non-empty and free of `.`/`..`"));
            continue;
        }
        listed.push(rel.to_owned());
        let path = dir.join(rel);
        match fs::symlink_metadata(&path) {
            Err(_) => {
                out.push(v(rel, "missing_file", "listed in the manifest's integrity block but absent"));
                continue;
            }
            Ok(meta) if !meta.is_file() => {
                out.push(v(rel, "not_regular_file", "must be a regular file"));
                continue;
            }
            Ok(_) => {}
        }
        let Ok(bytes) = fs::read(&path) else {
            out.push(v(rel, "missing_file", "unreadable"));
            continue;
        };
        if rec["size_bytes"].as_u64() != Some(bytes.len() as u64) {
            out.push(v(rel, "size_mismatch", format!("{} bytes on disk, manifest says {}", bytes.len(), rec["size_bytes"])));
        }
        let digest = sha256_hex(&bytes);
        if rec["sha256"].as_str() != Some(digest.as_str()) {
            out.push(v(rel, "sha256_mismatch", format!("sha256 on disk {digest}, manifest says {}", rec["sha256"])));
        }
    }
    let mut sorted = listed.clone();
    sorted.sort();
    if sorted != listed {
        out.push(v(MANIFEST, "integrity", "integrity.files must be sorted by path"));
    }
    if let Ok(on_disk) = bundle_files(dir) {
        for rel in on_disk.iter().filter(|p| !listed.contains(p)) {
            out.push(v(rel, "unlisted_file", "present in the bundle but not in the integrity block"));
        }
    }
    for required in [TRAJECTORY, VIDEO_HEAD_WRIST, VIDEO_HEAD, VIDEO_WRIST, SHEET_HEAD, SHEET_WRIST] {
        if !listed.iter().any(|p| p == required) && !dir.join(required).exists() {
            out.push(v(required, "missing_file", "every library bundle has this file"));
        }
    }
    files.clone()
}

fn canonical_relative(p: &str) -> bool {
    !p.is_empty() && !p.starts_with('/') && p.split('/').all(|c| !c.is_empty() && c != "." && c != "..")
}

/// Each artifact named in the manifest must match its integrity record.
fn check_artifacts(m: &Value, listed: &[Value], out: &mut Vec<Violation>) {
    let artifacts = [
        &m["trajectory"],
        &m["video"]["file"],
        &m["video"]["head_rgb"],
        &m["video"]["wrist_rgb"],
        &m["overview"]["contact_sheets"]["head_rgb"],
        &m["overview"]["contact_sheets"]["wrist_rgb"],
    ];
    for a in artifacts {
        let Some(path) = a["path"].as_str() else {
            out.push(v(MANIFEST, "artifact_mismatch", format!("an artifact record without a path: {a}")));
            continue;
        };
        match listed.iter().find(|r| r["path"] == path) {
            None => out.push(v(path, "artifact_mismatch", "named as an artifact but not in the integrity block")),
            Some(r) if r["sha256"] != a["sha256"] || r["size_bytes"] != a["size_bytes"] => {
                out.push(v(path, "artifact_mismatch", "artifact record and integrity record disagree"))
            }
            Some(_) => {}
        }
    }
}

fn check_trajectory(dir: &Path, transitions: Option<u64>, out: &mut Vec<Violation>) {
    let Ok(text) = fs::read_to_string(dir.join(TRAJECTORY)) else { return };
    let allowed: BTreeSet<&str> = TRAJECTORY_ROW_KEYS.into_iter().collect();
    let mut rows = 0u64;
    for (n, line) in text.lines().enumerate() {
        let at = |detail: String| format!("line {}: {detail}", n + 1);
        rows += 1;
        let row: Value = match serde_json::from_str(line) {
            Ok(r) => r,
            Err(e) => {
                out.push(v(TRAJECTORY, "bad_json", at(e.to_string())));
                continue;
            }
        };
        let keys: BTreeSet<&str> = row.as_object().map(|o| o.keys().map(String::as_str).collect()).unwrap_or_default();
        if keys != allowed {
            out.push(v(TRAJECTORY, "trajectory_keys", at(format!("keys {keys:?}, expected {allowed:?}"))));
        }
        if row["action_index"].as_u64() != Some(n as u64) || row["frame_before"].as_u64() != Some(n as u64)
            || row["frame_after"].as_u64() != Some(n as u64 + 1)
        {
            out.push(v(TRAJECTORY, "action_index", at("action_index/frame_before/frame_after must count from 0 in order".into())));
        }
        let action = &row["action"];
        if action["schema_version"] != ACTION_SCHEMA {
            out.push(v(TRAJECTORY, "action_schema", at(format!("action.schema_version must be {ACTION_SCHEMA:?}"))));
        }
        if parse_action(action).is_none() {
            out.push(v(
                TRAJECTORY,
                "action_out_of_range",
                at(format!("action.normalized_vector_7d must be 7 finite numbers with |x| ≤ 1: {}", action["normalized_vector_7d"])),
            ));
        }
        if MeasuredState::from_json(&row["state_before"]).is_none() || MeasuredState::from_json(&row["state_after"]).is_none() {
            out.push(v(TRAJECTORY, "trajectory_keys", at("state_before/state_after must hold the measured EEF pose (7) and fingers (2)".into())));
        }
        if compact_sorted(&row) != line {
            out.push(v(TRAJECTORY, "not_canonical", at("the row differs from its canonical re-serialization".into())));
        }
    }
    if let Some(t) = transitions {
        if rows != t {
            out.push(v(TRAJECTORY, "frame_count", format!("{rows} rows, the manifest's transition_count is {t}")));
        }
    }
}

fn check_videos(dir: &Path, frames: u64, out: &mut Vec<Violation>) {
    for rel in [VIDEO_HEAD_WRIST, VIDEO_HEAD, VIDEO_WRIST] {
        let Ok(bytes) = fs::read(dir.join(rel)) else { continue };
        match mp4_sample_count(&bytes) {
            None => out.push(v(rel, "video_frame_count", "not an MP4 with a video track")),
            Some(n) if n != frames => out.push(v(rel, "video_frame_count", format!("{n} video frames, the manifest says {frames}"))),
            Some(_) => {}
        }
    }
}

fn check_sheets(dir: &Path, tiles: usize, out: &mut Vec<Violation>) {
    let (w, h, _) = super::record::contact_sheet(&vec![&[][..]; tiles], crate::world::RESOLUTION_PX);
    for rel in [SHEET_HEAD, SHEET_WRIST] {
        let Ok(file) = fs::File::open(dir.join(rel)) else { continue };
        match png::Decoder::new(std::io::BufReader::new(file)).read_info() {
            Err(e) => out.push(v(rel, "bad_png", e.to_string())),
            Ok(r) => {
                let info = r.info();
                if (info.width, info.height) != (w, h) {
                    out.push(v(rel, "contact_sheet_size", format!("{}x{} px, {tiles} tiles need {w}x{h}", info.width, info.height)));
                }
            }
        }
    }
}
