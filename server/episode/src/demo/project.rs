//! The agent-visible copy of a library bundle at `benchmark_inputs/expert_demo/` (§7.4, and our layout for video +
//! trajectory in the paper's Appendix C schema). Nothing private travels: no source episode id, seed, init-state
//! index, layout, task id, evaluator record or verification details; only the instruction, the video, the contact
//! sheets and (video + trajectory) the actions, with no measured end-effector stream.
use std::fs;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use super::*;
use libero_records::demo_manifest::ContactSheets;
use libero_records::json::{compact_sorted, write_json_file};
use crate::workspace::normalize_instruction;

pub const VIDEO_ONLY_SCHEMA: &str = "libero.video_only_demo_bundle.v1";
pub const VIDEO_TRAJECTORY_SCHEMA: &str = "libero_agent.video_trajectory_demo_bundle.v1";
pub const RECEIPT_SCHEMA: &str = "libero_agent.demo_projection_receipt.v1";

/// Demonstration condition of an episode (§7.1; the paper's None / Video / Video + Traj.).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum DemoCondition {
    #[default]
    #[serde(rename = "none")]
    None,
    #[serde(rename = "video")]
    Video,
    #[serde(rename = "video+traj")]
    VideoTraj,
}

impl DemoCondition {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Video => "video",
            Self::VideoTraj => "video+traj",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "none" => Some(Self::None),
            "video" | "video_only" => Some(Self::Video),
            "video+traj" | "video_traj" | "video_plus_trajectory" => Some(Self::VideoTraj),
            _ => None,
        }
    }

    /// `icl_condition` in the workspace contract and the bundle manifest.
    pub fn icl_condition(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Video => "video_only",
            Self::VideoTraj => "video_plus_trajectory",
        }
    }

    /// The notice inserted after the instruction (None for `none`): the paper's one notice for both
    /// demonstration conditions, verbatim (Appendix C). The bundle's files say what the demonstration holds.
    pub fn prompt_notice(self) -> Option<String> {
        match self {
            Self::None => None,
            Self::Video | Self::VideoTraj => Some(DEMO_NOTICE.to_owned()),
        }
    }
}

/// The paper's demonstration notice (Appendix C, "Recorded task and shared execution prompt").
pub const DEMO_NOTICE: &str = "A demonstration from a separate episode of the same task is available at \
benchmark_inputs/expert_demo/. The current scene configuration and object or goal poses may differ.";

/// The private record of what was placed (kept in the run directory, never in the workspace).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ProjectionReceipt {
    pub schema_version: &'static str,
    pub icl_condition: &'static str,
    pub source_bundle: PathBuf,
    pub source_episode_id: String,
    pub target_task_instruction: String,
    pub agent_bundle: PathBuf,
    pub manifest_sha256: String,
    pub frame_count: u64,
}

/// The agent-visible `manifest.json` (§7.4; the paper's Appendix C for video + trajectory). Written with sorted
/// keys; nothing in it names the source episode. Agents read it: `Deserialize` is for our tests and tools.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PublicManifest {
    /// [`VIDEO_ONLY_SCHEMA`] or [`VIDEO_TRAJECTORY_SCHEMA`].
    pub schema_version: String,
    /// The target task's instruction, whitespace-normalised.
    pub task_instruction: String,
    /// `video_only`, `video_plus_trajectory` ([`DemoCondition::icl_condition`]).
    pub icl_condition: String,
    pub demonstration: PublicDemonstration,
    /// Video + trajectory only: §7.3's canonical action semantics.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub action_semantics: Option<Value>,
    /// Video + trajectory only: `trajectory.jsonl`, as an artifact.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trajectory: Option<DemoFile>,
    /// Video + trajectory only: every file but the manifest, sorted by path.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub integrity: Option<DemoIntegrity>,
}

/// What the demonstration is and holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PublicDemonstration {
    /// `verified successful demonstration`.
    pub episode_outcome: String,
    /// `same_task_separate_episode`.
    pub relation_to_target: String,
    /// Always true: the target's configuration differs from the source's.
    pub scene_or_object_poses_may_differ: bool,
    /// `head_rgb`, `wrist_rgb`, and `actions` with the trajectory.
    pub modalities: Vec<String>,
    /// Video + trajectory only: frames (actions + 1) and transitions (actions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_count: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transition_count: Option<u64>,
    /// Video + trajectory only: true.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub actions_present: Option<bool>,
    /// Video + trajectory only: [`ACTION_SCHEMA`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub action_representation: Option<String>,
    /// Video + trajectory only: false (no measured end-effector stream travels).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub measured_eef_states_present: Option<bool>,
    /// Video + trajectory only: false.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stepwise_success_present: Option<bool>,
    /// §7.4 keeps the frame count inside `video`.
    pub video: PublicVideo,
}

/// The head | wrist video and its contact sheets.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PublicVideo {
    pub file: DemoFile,
    /// Frames per second (one per 20 Hz control step).
    pub fps_hz: f64,
    pub frame_count: u64,
    /// `head_rgb_left__wrist_rgb_right`.
    pub layout: String,
    pub contact_sheets: ContactSheets,
    pub sampling: PublicSampling,
}

/// §7.6's sampling of the contact sheets' frames.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PublicSampling {
    /// [`SAMPLING_RULE`].
    pub rule: String,
    pub maximum_frames_per_sheet: u64,
    pub source_frame_count: u64,
    /// Null where the library bundle had none (a valid bundle has them).
    pub sampled_frame_indices: Option<Vec<u64>>,
}

/// The `demonstration` fields every agent-visible manifest shares.
fn demonstration(modalities: &[&str], video: PublicVideo) -> PublicDemonstration {
    PublicDemonstration {
        episode_outcome: "verified successful demonstration".to_owned(),
        relation_to_target: "same_task_separate_episode".to_owned(),
        scene_or_object_poses_may_differ: true,
        modalities: modalities.iter().map(|m| (*m).to_owned()).collect(),
        frame_count: None,
        transition_count: None,
        actions_present: None,
        action_representation: None,
        measured_eef_states_present: None,
        stepwise_success_present: None,
        video,
    }
}

/// Projects the valid, verified library bundle `source` to `dest` (which must not exist) for `condition`. The
/// bundle's instruction must equal `target_instruction` (normalized). Built under `<dest>.partial`, validated,
/// then renamed into place.
pub fn project_bundle(
    source: &Path,
    dest: &Path,
    condition: DemoCondition,
    target_instruction: &str,
) -> Result<ProjectionReceipt, DemoError> {
    if condition == DemoCondition::None {
        return Err(DemoError::Library("the `none` condition places no bundle".into()));
    }
    let violations = validate_bundle(source);
    if !violations.is_empty() {
        return Err(DemoError::Invalid { dir: source.to_owned(), violations });
    }
    let manifest = read_manifest(&source.join(MANIFEST))?;
    if !manifest.verified() {
        return Err(DemoError::Library(format!("{} is not a verified demonstration (run `libero-agent demo verify`)", source.display())));
    }
    let instruction = normalize_instruction(target_instruction);
    if manifest.instruction() != Some(instruction.as_str()) {
        return Err(DemoError::Library(format!(
            "{} demonstrates {:?}, not the target task {instruction:?}",
            source.display(),
            json!(manifest.instruction())
        )));
    }
    if dest.exists() {
        return Err(DemoError::Library(format!("{} already exists", dest.display())));
    }
    let frame_count = manifest.frame_count.unwrap_or(0);
    let partial = PathBuf::from(format!("{}.partial", dest.display()));
    if partial.exists() {
        fs::remove_dir_all(&partial).map_err(io_err(&partial))?;
    }
    fs::create_dir_all(partial.join("video/contact_sheets")).map_err(io_err(&partial))?;
    for rel in [VIDEO_HEAD_WRIST, SHEET_HEAD, SHEET_WRIST] {
        fs::copy(source.join(rel), partial.join(rel)).map_err(io_err(&source.join(rel)))?;
    }
    if condition == DemoCondition::VideoTraj {
        write_public_trajectory(source, &partial)?;
    }
    let sampled = manifest.overview.as_ref().and_then(|o| o.sampling.as_ref()).and_then(|s| s.sampled_frame_indices.as_ref());
    let public = public_manifest(&partial, condition, &instruction, frame_count, sampled)?;
    let manifest_path = partial.join(MANIFEST);
    let public = serde_json::to_value(&public).map_err(|e| DemoError::Source(format!("agent-visible manifest: {e}")))?;
    write_json_file(&manifest_path, &public).map_err(io_err(&manifest_path))?;
    let problems = validate_projection(&partial, condition);
    if !problems.is_empty() {
        return Err(DemoError::Invalid { dir: partial, violations: problems });
    }
    if let Some(parent) = dest.parent() {
        fs::create_dir_all(parent).map_err(io_err(parent))?;
    }
    fs::rename(&partial, dest).map_err(io_err(dest))?;
    let bytes = fs::read(dest.join(MANIFEST)).map_err(io_err(dest))?;
    Ok(ProjectionReceipt {
        schema_version: RECEIPT_SCHEMA,
        icl_condition: condition.icl_condition(),
        source_bundle: source.to_owned(),
        source_episode_id: manifest.source.as_ref().and_then(|s| s.episode_id.clone()).unwrap_or_default(),
        target_task_instruction: instruction,
        agent_bundle: dest.to_owned(),
        manifest_sha256: sha256_hex(&bytes),
        frame_count,
    })
}

/// The agent-visible manifest of the files already in `dir` (artifacts and integrity computed from disk).
fn public_manifest(
    dir: &Path,
    condition: DemoCondition,
    instruction: &str,
    frame_count: u64,
    sampled: Option<&Vec<u64>>,
) -> Result<PublicManifest, DemoError> {
    let video = PublicVideo {
        file: artifact(dir, VIDEO_HEAD_WRIST, "video/mp4")?,
        fps_hz: DEMO_VIDEO_FPS_HZ,
        frame_count,
        layout: "head_rgb_left__wrist_rgb_right".to_owned(),
        contact_sheets: ContactSheets {
            head_rgb: Some(artifact(dir, SHEET_HEAD, "image/png")?),
            wrist_rgb: Some(artifact(dir, SHEET_WRIST, "image/png")?),
            ..ContactSheets::default()
        },
        sampling: PublicSampling {
            rule: SAMPLING_RULE.to_owned(),
            maximum_frames_per_sheet: MAX_FRAMES_PER_SHEET as u64,
            source_frame_count: frame_count,
            sampled_frame_indices: sampled.cloned(),
        },
    };
    let (schema, demonstration, action_semantics, trajectory, integrity) = match condition {
        DemoCondition::Video | DemoCondition::None => (VIDEO_ONLY_SCHEMA, demonstration(&["head_rgb", "wrist_rgb"], video), None, None, None),
        DemoCondition::VideoTraj => (
            VIDEO_TRAJECTORY_SCHEMA,
            PublicDemonstration {
                frame_count: Some(frame_count),
                transition_count: Some(frame_count.saturating_sub(1)),
                actions_present: Some(true),
                action_representation: Some(ACTION_SCHEMA.to_owned()),
                measured_eef_states_present: Some(false),
                stepwise_success_present: Some(false),
                ..demonstration(&["head_rgb", "wrist_rgb", "actions"], video)
            },
            Some(action_semantics()),
            Some(artifact(dir, TRAJECTORY, "application/x-ndjson")?),
            Some(integrity_block(dir)?),
        ),
    };
    Ok(PublicManifest {
        schema_version: schema.to_owned(),
        task_instruction: instruction.to_owned(),
        icl_condition: condition.icl_condition().to_owned(),
        demonstration,
        action_semantics,
        trajectory,
        integrity,
    })
}

/// Public trajectory rows in the paper's schema (Appendix C): a zero-based `action_index` and an `action` object
/// with its schema identifier and `normalized_vector_7d`; no measured end-effector stream and no call indices (how
/// the source batched its calls is about the source episode, not the task).
fn write_public_trajectory(source: &Path, dest: &Path) -> Result<(), DemoError> {
    let path = source.join(TRAJECTORY);
    let text = fs::read_to_string(&path).map_err(io_err(&path))?;
    let mut out = String::new();
    for (n, line) in text.lines().enumerate() {
        let (action, _) = read_trajectory_row(line, n + 1)?;
        out.push_str(&compact_sorted(&public_trajectory_row(n, &action)));
        out.push('\n');
    }
    let p = dest.join(TRAJECTORY);
    fs::write(&p, out).map_err(io_err(&p))
}

/// One agent-visible trajectory row.
pub fn public_trajectory_row(action_index: usize, action: &[f64; 7]) -> Value {
    json!({"action_index": action_index, "action": action_value(action)})
}

/// Keys of an agent-visible trajectory row, exactly (the paper's).
pub const PUBLIC_TRAJECTORY_ROW_KEYS: [&str; 2] = ["action", "action_index"];

/// Checks an agent-visible bundle: the exact file set, manifest keys and schema, artifact sizes and hashes. It reads
/// the files as plain JSON, as [`validate_bundle`] does: it checks exact key sets and reports each ill-typed value,
/// which a typed reading would not see.
pub fn validate_projection(dir: &Path, condition: DemoCondition) -> Vec<Violation> {
    let mk = |file: &str, rule: &'static str, detail: String| Violation { file: file.to_owned(), rule, detail };
    let mut out = Vec::new();
    let (schema, keys, files): (&str, &[&str], Vec<&str>) = match condition {
        DemoCondition::Video => (
            VIDEO_ONLY_SCHEMA,
            &["demonstration", "icl_condition", "schema_version", "task_instruction"],
            vec![MANIFEST, SHEET_HEAD, SHEET_WRIST, VIDEO_HEAD_WRIST],
        ),
        _ => (
            VIDEO_TRAJECTORY_SCHEMA,
            &["action_semantics", "demonstration", "icl_condition", "integrity", "schema_version", "task_instruction", "trajectory"],
            vec![MANIFEST, TRAJECTORY, SHEET_HEAD, SHEET_WRIST, VIDEO_HEAD_WRIST],
        ),
    };
    let mut on_disk = bundle_files(dir).unwrap_or_default();
    on_disk.push(MANIFEST.into());
    on_disk.sort();
    let mut want: Vec<String> = files.iter().map(|s| s.to_string()).collect();
    want.sort();
    if on_disk != want {
        out.push(mk(".", "file_set", format!("files {on_disk:?}, expected exactly {want:?}")));
    }
    let m = match read_json(&dir.join(MANIFEST)) {
        Ok(m) => m,
        Err(e) => return vec![mk(MANIFEST, "bad_json", e.to_string())],
    };
    let got: Vec<&str> = m.as_object().map(|o| o.keys().map(String::as_str).collect()).unwrap_or_default();
    let mut got = got;
    got.sort();
    if got != keys {
        out.push(mk(MANIFEST, "manifest_keys", format!("keys {got:?}, expected {keys:?}")));
    }
    if m["schema_version"] != schema {
        out.push(mk(MANIFEST, "schema_version", format!("{} is not {schema:?}", m["schema_version"])));
    }
    let video = &m["demonstration"]["video"];
    let mut artifacts = vec![&video["file"], &video["contact_sheets"]["head_rgb"], &video["contact_sheets"]["wrist_rgb"]];
    if condition == DemoCondition::VideoTraj {
        artifacts.push(&m["trajectory"]);
        let text = fs::read_to_string(dir.join(TRAJECTORY)).unwrap_or_default();
        for (n, line) in text.lines().enumerate() {
            let row: Value = serde_json::from_str(line).unwrap_or(Value::Null);
            let keys: Vec<&str> = row.as_object().map(|o| o.keys().map(String::as_str).collect()).unwrap_or_default();
            let exact = keys == PUBLIC_TRAJECTORY_ROW_KEYS && row["action_index"] == n && parse_action(&row["action"]).is_some();
            if !exact {
                out.push(mk(TRAJECTORY, "trajectory_keys", format!("line {}: not {{action_index: {n}, action}}", n + 1)));
                break;
            }
        }
    }
    for a in artifacts {
        let Some(rel) = a["path"].as_str() else {
            out.push(mk(MANIFEST, "artifact_mismatch", format!("artifact without a path: {a}")));
            continue;
        };
        match fs::read(dir.join(rel)) {
            Err(_) => out.push(mk(rel, "missing_file", "named in the manifest but absent".into())),
            Ok(bytes) => {
                if a["size_bytes"].as_u64() != Some(bytes.len() as u64) || a["sha256"].as_str() != Some(sha256_hex(&bytes).as_str()) {
                    out.push(mk(rel, "sha256_mismatch", "size or sha256 differs from the manifest".into()));
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conditions_read_and_write_the_cli_and_api_spellings() {
        for c in [DemoCondition::None, DemoCondition::Video, DemoCondition::VideoTraj] {
            assert_eq!(DemoCondition::parse(c.as_str()), Some(c));
            assert_eq!(serde_json::to_value(c).unwrap(), json!(c.as_str()), "the HTTP API uses the CLI spelling");
            assert_eq!(DemoCondition::parse(c.icl_condition()), Some(c), "§7.1 names are accepted too");
        }
        assert_eq!(DemoCondition::parse("trajectory"), None);
        assert_eq!(DemoCondition::None.prompt_notice(), None, "the release prompt has no notice");
        let golden = fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/prompt/demo_notice.txt"))
            .expect("tests/fixtures/prompt/demo_notice.txt");
        for c in [DemoCondition::Video, DemoCondition::VideoTraj] {
            assert_eq!(c.prompt_notice().as_deref(), Some(golden.trim_end()), "the paper's notice, verbatim, for {c:?}");
        }
    }

    /// The paper's row: `action_index` and an `action` object with a schema id and `normalized_vector_7d`; no
    /// measured stream. Byte-for-byte against the golden row.
    #[test]
    fn public_trajectory_rows_have_exactly_the_papers_fields() {
        let row = public_trajectory_row(0, &[0.5, -0.25, 0.0, 0.0, 0.0, 0.125, -1.0]);
        let keys: Vec<&str> = row.as_object().unwrap().keys().map(String::as_str).collect();
        assert_eq!(keys, PUBLIC_TRAJECTORY_ROW_KEYS);
        let action_keys: Vec<&str> = row["action"].as_object().unwrap().keys().map(String::as_str).collect();
        assert_eq!(action_keys, ["normalized_vector_7d", "schema_version"]);
        let golden = fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/prompt/trajectory_row.jsonl"))
            .expect("tests/fixtures/prompt/trajectory_row.jsonl");
        assert_eq!(format!("{}\n", compact_sorted(&row)), golden);
    }

    /// The agent-visible manifests (video only, video + trajectory) are a wire format the agents read: byte for
    /// byte the golden files (placeholder media; `UPDATE_GOLDEN=1` rewrites them after a deliberate change).
    #[test]
    fn public_manifests_match_the_golden_files() {
        let golden = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/demo_projection"));
        for (condition, name) in [(DemoCondition::Video, "video_manifest.json"), (DemoCondition::VideoTraj, "video_traj_manifest.json")] {
            let dir = tempfile::tempdir().unwrap();
            let d = dir.path();
            fs::create_dir_all(d.join("video/contact_sheets")).unwrap();
            for rel in [VIDEO_HEAD_WRIST, SHEET_HEAD, SHEET_WRIST] {
                fs::write(d.join(rel), rel).unwrap();
            }
            if condition == DemoCondition::VideoTraj {
                let row = compact_sorted(&public_trajectory_row(0, &[0.5, -0.25, 0.0, 0.0, 0.0, 0.125, -1.0]));
                fs::write(d.join(TRAJECTORY), format!("{row}\n")).unwrap();
            }
            let sampled = vec![0, 1];
            let m = public_manifest(d, condition, "open the top drawer of the cabinet", 2, Some(&sampled)).unwrap();
            write_json_file(&d.join(MANIFEST), &serde_json::to_value(&m).unwrap()).unwrap();
            let got = fs::read_to_string(d.join(MANIFEST)).unwrap();
            if std::env::var_os("UPDATE_GOLDEN").is_some() {
                fs::create_dir_all(golden).unwrap();
                fs::write(golden.join(name), &got).unwrap();
            }
            let want = fs::read_to_string(golden.join(name)).unwrap_or_else(|e| panic!("{name}: {e} (UPDATE_GOLDEN=1 writes it)"));
            assert_eq!(got, want, "{name} differs from the golden file");
            assert_eq!(validate_projection(d, condition), vec![], "{name} is a valid projection");
            assert_eq!(serde_json::from_str::<PublicManifest>(&got).unwrap(), m, "{name} reads back as written");
        }
    }

    #[test]
    fn a_projection_with_an_extra_file_or_a_wrong_hash_is_rejected() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        fs::create_dir_all(d.join("video/contact_sheets")).unwrap();
        for rel in [VIDEO_HEAD_WRIST, SHEET_HEAD, SHEET_WRIST] {
            fs::write(d.join(rel), rel).unwrap();
        }
        let m = public_manifest(d, DemoCondition::Video, "x", 1, None).unwrap();
        write_json_file(&d.join(MANIFEST), &serde_json::to_value(&m).unwrap()).unwrap();
        assert_eq!(validate_projection(d, DemoCondition::Video), vec![]);
        fs::write(d.join(SHEET_HEAD), "changed").unwrap();
        fs::write(d.join("extra.txt"), "x").unwrap();
        let rules: Vec<&str> = validate_projection(d, DemoCondition::Video).iter().map(|v| v.rule).collect();
        assert_eq!(rules, ["file_set", "sha256_mismatch"]);
    }
}
