//! Recording a bundle from a finished episode's run directory, and verifying one by replay.
//!
//! Frames are not decoded from the private H.264 video: the actions are replayed from the same task, seed and
//! init state (bit-identical by the determinism contract) and both cameras are rendered after settling (frame 0)
//! and after every action, so the bundle has exactly `actions + 1` frames, as §7.4's video.
use std::fs;
use std::path::{Path, PathBuf};

use libero_records::demo_manifest::{ContactSheets, DemoBranch, DemoOverview, DemoSource, DemoTask, DemoVerification, DemoVideo, FrameSampling, ReplayCheck};
use libero_render::Renderer;
use libero_sim::AssetPaths;
use serde_json::Value;

use super::*;
use crate::actor::World;
use libero_records::json::write_json_file;
use crate::observation::{Frame, Level, write_png};
use crate::physics::{SETTLE_STEPS, WorldPhysics, WorldSpec};
use libero_records::records::{ActionEvent, EpisodeRecord, RunDir, read_result};
use crate::task::resolve_task;
use crate::video::{Mp4Writer, side_by_side};
use crate::world::{LiberoWorld, RESOLUTION_PX};

/// What a bundle is made from: the episode's identity and its accepted actions, read from its run directory.
#[derive(Debug, Clone, PartialEq)]
pub struct SourceEpisode {
    pub episode_id: String,
    /// What `resolve_task` accepts (`T14`, `suite/name`, a `.bddl` path).
    pub task_ref: String,
    pub instruction: String,
    pub level: u8,
    pub seed: u64,
    pub init_state_index: usize,
    /// `(event_index of the osc_sequence call, action)` in execution order.
    pub actions: Vec<(u64, [f64; 7])>,
    /// The evaluator's verdict in `result.json` (None: the episode never finished).
    pub success: Option<bool>,
    /// The layout variant the source episode ran (None: the task's own configuration for its seed).
    pub layout: Option<LayoutVariant>,
    /// Where the episode branched (None: it started at the task's start). Its first `replayed_actions` actions
    /// are the parent's, replayed to reach the branch point; a bundle records only the ones after them.
    pub branch: Option<BranchOrigin>,
}

/// A branch's parent, the control step it continued from, and how many of its actions were replayed.
#[derive(Debug, Clone, PartialEq)]
pub struct BranchOrigin {
    pub parent_episode_id: String,
    pub parent_control_step: u64,
    pub replayed_actions: usize,
}

impl SourceEpisode {
    /// Reads `episode_record.json`, `actions.jsonl` (accepted `osc_sequence` calls only, after a branch's replayed
    /// prefix) and `result.json`.
    pub fn read(run: &RunDir) -> Result<Self, DemoError> {
        let record = EpisodeRecord::from_value(read_json(&run.episode_record())?)
            .map_err(|e| DemoError::Source(format!("episode_record.json is not a JSON object: {e}")))?;
        let missing = |what: &str| DemoError::Source(format!("episode_record.json has no {what}"));
        let task = record.task.clone().unwrap_or_default();
        let episode_id = record.episode_id.clone().ok_or_else(|| missing("episode_id"))?;
        let task_ref = task.task_ref.clone().ok_or_else(|| missing("task.task_ref"))?;
        let instruction = task.instruction.clone().ok_or_else(|| missing("task.instruction"))?;
        let level = u8::try_from(record.level.ok_or_else(|| missing("level"))?).map_err(|_| DemoError::Source("level out of range".into()))?;
        let seed = record.seed.ok_or_else(|| missing("seed"))?;
        // A suite task fixes its init row; the record holds the request's index.
        let init_state_index = record.init_index().ok_or_else(|| missing("init_state_index"))? as usize;
        let path = run.actions_jsonl();
        let log = fs::read_to_string(&path).map_err(io_err(&path))?;
        // A branch's actions begin with the parent's it replayed (at the `branch_from` line's index, 0).
        let mut actions: Vec<(u64, [f64; 7])> =
            crate::branch::read_prefix(run).map_err(DemoError::Source)?.into_iter().map(|a| (0, a)).collect();
        let replayed = actions.len();
        for (n, line) in log.lines().enumerate() {
            let event: ActionEvent = serde_json::from_str(line)
                .map_err(|e| DemoError::Source(format!("actions.jsonl line {}: not a JSON object: {e}", n + 1)))?;
            if event.tool() != Some("osc_sequence") || !event.actions_executed() {
                continue;
            }
            let call_index = event.event_index.unwrap_or(n as u64);
            let list = event.actions().ok_or_else(|| {
                DemoError::Source(format!("actions.jsonl line {}: accepted osc_sequence without actions", n + 1))
            })?;
            for a in list {
                let v = a
                    .as_array()
                    .and_then(|xs| xs.iter().map(Value::as_f64).collect::<Option<Vec<f64>>>())
                    .and_then(|xs| <[f64; 7]>::try_from(xs).ok())
                    .ok_or_else(|| DemoError::Source(format!("actions.jsonl line {}: an action is not 7 numbers", n + 1)))?;
                actions.push((call_index, v));
            }
        }
        let success = read_result(run).and_then(|r| r.success);
        let layout = layout_from_json(record.layout())?;
        let branch = crate::branch::record_branch(&record).map(|(parent_episode_id, parent_control_step)| BranchOrigin {
            parent_episode_id,
            parent_control_step,
            replayed_actions: replayed,
        });
        Ok(Self { episode_id, task_ref, instruction, level, seed, init_state_index, actions, success, layout, branch })
    }

    /// How many of [`Self::actions`] were replayed from a parent (0: not a branch).
    pub fn replayed(&self) -> usize {
        self.branch.as_ref().map_or(0, |b| b.replayed_actions.min(self.actions.len()))
    }

    /// The episode's own actions: after a branch's replayed prefix (what a bundle's trajectory holds).
    pub fn own_actions(&self) -> &[(u64, [f64; 7])] {
        &self.actions[self.replayed()..]
    }

    /// The world the source episode ran on (its layout variant included).
    pub fn spec(&self, paths: &AssetPaths) -> Result<WorldSpec, DemoError> {
        let mut task = resolve_task(&self.task_ref, paths)?;
        task.layout = self.layout;
        Ok(WorldSpec { task, level: Level::L1, seed: self.seed, init_index: self.init_state_index, paths: paths.clone() })
    }
}

/// How a bundle is recorded.
#[derive(Debug, Clone)]
pub struct RecordOptions {
    /// `scripted_expert`, `human_teleop`, `agent`: who produced the actions (ux anchors §3.2 `source_type`).
    pub source_type: String,
    /// Free text next to it (expert behaviour, operator, model).
    pub source_desc: String,
}

/// What [`record_bundle`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct BundleSummary {
    pub dir: PathBuf,
    pub frame_count: usize,
    pub transition_count: usize,
    pub source_success: Option<bool>,
    pub replay_success: bool,
    pub verified: bool,
}

/// Public fields of the library manifest, apart from the files' records.
pub(crate) struct ManifestFields<'a> {
    pub source: &'a SourceEpisode,
    pub options: &'a RecordOptions,
    pub replay_success: Option<bool>,
    /// The configuration the source episode started from (what a target episode must differ from).
    pub effective_layout: Option<EffectiveLayout>,
    /// Replays of the trajectory in other episodes, kept across re-verification (none for a new bundle).
    pub replay_checks: StoredChecks,
}

/// The `replay_checks` a manifest is written with.
pub(crate) enum StoredChecks {
    Typed(Vec<ReplayCheck>),
    /// A stored list the typed view cannot read (not a list of objects), written back as it was read: the
    /// re-verification that rewrites a manifest is not where a foreign list is judged (validation says it).
    AsRead(Value),
}

/// Writes `manifest.json` for the files already in `dir` (artifacts and integrity recomputed from disk).
pub(crate) fn write_manifest(dir: &Path, f: &ManifestFields<'_>) -> Result<DemoManifest, DemoError> {
    let own = f.source.own_actions().len() as u64;
    let frame_count = own + 1;
    let sampled = sample_frame_indices(frame_count as usize, MAX_FRAMES_PER_SHEET).into_iter().map(|i| i as u64).collect();
    let verified = f.source.success == Some(true) && f.replay_success == Some(true);
    let mut source = DemoSource {
        episode_id: Some(f.source.episode_id.clone()),
        source_type: Some(f.options.source_type.clone()),
        source_desc: Some(f.options.source_desc.clone()),
        level: Some(u64::from(f.source.level)),
        seed: Some(f.source.seed),
        init_state_index: Some(f.source.init_state_index as u64),
        // null: the task's own configuration
        layout: Some(json_of("layout", &f.source.layout)?),
        effective_layout: Some(json_of("effective_layout", &f.effective_layout)?),
        settle_steps: Some(SETTLE_STEPS as u64),
        // Only a branch's manifest has the key: every other bundle's manifest stays as it was.
        branch: f.source.branch.as_ref().map(|b| DemoBranch {
            parent_episode_id: Some(b.parent_episode_id.clone()),
            parent_control_step: Some(b.parent_control_step),
            replayed_actions: Some(f.source.replayed() as u64),
            prefix_file: Some(crate::branch::PREFIX_FILE.to_owned()),
            ..DemoBranch::default()
        }),
        ..DemoSource::default()
    };
    source.set_episode_success(f.source.success);
    let mut verification =
        DemoVerification { verified: Some(verified), method: Some("replay_on_world_physics".to_owned()), ..DemoVerification::default() };
    verification.set_replay_success(f.replay_success);
    let mut manifest = DemoManifest {
        schema_version: Some(BUNDLE_SCHEMA.to_owned()),
        task: Some(DemoTask {
            id: Some(f.source.task_ref.clone()),
            instruction: Some(crate::workspace::normalize_instruction(&f.source.instruction)),
            ..DemoTask::default()
        }),
        source: Some(source),
        verification: Some(verification),
        frame_count: Some(frame_count),
        transition_count: Some(own),
        action_semantics: Some(action_semantics()),
        trajectory: Some(artifact(dir, TRAJECTORY, "application/x-ndjson")?),
        video: Some(DemoVideo {
            fps_hz: Some(DEMO_VIDEO_FPS_HZ),
            frame_count: Some(frame_count),
            layout: Some("head_rgb_left__wrist_rgb_right".to_owned()),
            file: Some(artifact(dir, VIDEO_HEAD_WRIST, "video/mp4")?),
            head_rgb: Some(artifact(dir, VIDEO_HEAD, "video/mp4")?),
            wrist_rgb: Some(artifact(dir, VIDEO_WRIST, "video/mp4")?),
            ..DemoVideo::default()
        }),
        overview: Some(DemoOverview {
            sampling: Some(FrameSampling {
                rule: Some(SAMPLING_RULE.to_owned()),
                maximum_frames_per_sheet: Some(MAX_FRAMES_PER_SHEET as u64),
                source_frame_count: Some(frame_count),
                sampled_frame_indices: Some(sampled),
                ..FrameSampling::default()
            }),
            contact_sheets: Some(ContactSheets {
                head_rgb: Some(artifact(dir, SHEET_HEAD, "image/png")?),
                wrist_rgb: Some(artifact(dir, SHEET_WRIST, "image/png")?),
                ..ContactSheets::default()
            }),
            ..DemoOverview::default()
        }),
        integrity: Some(integrity_block(dir)?),
        ..DemoManifest::default()
    };
    match &f.replay_checks {
        StoredChecks::Typed(checks) => manifest.replay_checks = Some(checks.clone()),
        StoredChecks::AsRead(raw) => {
            manifest.rest.insert("replay_checks".to_owned(), raw.clone());
        }
    }
    let path = dir.join(MANIFEST);
    write_json_file(&path, &manifest.to_value()).map_err(io_err(&path))?;
    Ok(manifest)
}

/// A manifest field of the episode crate's own types (layouts) as JSON.
fn json_of<T: serde::Serialize>(what: &str, value: &T) -> Result<Value, DemoError> {
    serde_json::to_value(value).map_err(|e| DemoError::Source(format!("manifest {what}: {e}")))
}

/// Writes `trajectory.jsonl` (compact, keys sorted, one row per action of the episode's own) and, for a branch,
/// the replayed prefix beside it (`branch_prefix.jsonl`).
pub(crate) fn write_trajectory(dir: &Path, source: &SourceEpisode, states: &[MeasuredState]) -> Result<(), DemoError> {
    let own = source.own_actions();
    if states.len() != own.len() + 1 {
        return Err(DemoError::Source(format!("{} states for {} actions", states.len(), own.len())));
    }
    if source.branch.is_some() {
        let prefix: Vec<[f64; 7]> = source.actions[..source.replayed()].iter().map(|(_, a)| *a).collect();
        let path = dir.join(crate::branch::PREFIX_FILE);
        fs::write(&path, crate::branch::prefix_text(&prefix).map_err(io_err(&path))?).map_err(io_err(&path))?;
    }
    let mut text = String::new();
    for (i, (call, a)) in own.iter().enumerate() {
        text.push_str(&trajectory_row(i, *call, a, &states[i], &states[i + 1]).to_string());
        text.push('\n');
    }
    let path = dir.join(TRAJECTORY);
    fs::write(&path, text).map_err(io_err(&path))
}

/// §7.4 contact sheet: the sampled tiles in a grid of `ceil(√n)` columns, 8-px white gutters, no labels.
pub fn contact_sheet(tiles: &[&[u8]], tile_px: u32) -> (u32, u32, Vec<u8>) {
    const GUTTER_PX: u32 = 8;
    let n = tiles.len().max(1) as u32;
    let cols = (1..=n).find(|c| c * c >= n).unwrap_or(1);
    let rows = n.div_ceil(cols);
    let width = cols * tile_px + (cols + 1) * GUTTER_PX;
    let height = rows * tile_px + (rows + 1) * GUTTER_PX;
    let mut out = vec![255u8; (width * height * 3) as usize];
    for (k, tile) in tiles.iter().enumerate() {
        let (c, r) = (k as u32 % cols, k as u32 / cols);
        let (x0, y0) = (GUTTER_PX + c * (tile_px + GUTTER_PX), GUTTER_PX + r * (tile_px + GUTTER_PX));
        for y in 0..tile_px {
            let src = (y * tile_px * 3) as usize;
            let dst = (((y0 + y) * width + x0) * 3) as usize;
            let len = (tile_px * 3) as usize;
            if let (Some(s), Some(d)) = (tile.get(src..src + len), out.get_mut(dst..dst + len)) {
                d.copy_from_slice(s);
            }
        }
    }
    (width, height, out)
}

fn measured(frame: &Frame) -> MeasuredState {
    MeasuredState {
        eef_pose_robot_base_xyzw: frame.robot.eef_pose_robot_base_xyzw,
        gripper_finger_joint_position_m: frame.robot.gripper_finger_joint_position_m,
    }
}

/// Records the bundle of the finished episode in `run_dir` into `out` (which must not exist): replays its actions
/// with rendering, writes videos, contact sheets, `trajectory.jsonl` and the manifest. The bundle is marked
/// verified only if the episode succeeded and the replay reproduces the evaluator's success. Written under
/// `<out>.partial` and renamed, so a crash never leaves a half bundle under the final name. A branch's replayed
/// prefix is stepped without frames: the bundle starts at the branch point.
pub fn record_bundle(
    run_dir: &Path,
    out: &Path,
    options: &RecordOptions,
    renderer: Renderer,
    paths: &AssetPaths,
) -> Result<BundleSummary, DemoError> {
    record_bundle_with_progress(run_dir, out, options, renderer, paths, &mut |_, _| {})
}

/// [`record_bundle`], telling `progress(frames rendered, frames in all)` after each frame (the replay that
/// verifies the bundle takes tens of seconds: the teleop page shows how far it is).
pub fn record_bundle_with_progress(
    run_dir: &Path,
    out: &Path,
    options: &RecordOptions,
    renderer: Renderer,
    paths: &AssetPaths,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<BundleSummary, DemoError> {
    let source = SourceEpisode::read(&RunDir::new(run_dir))?;
    if source.own_actions().is_empty() {
        let what = if source.branch.is_some() { "no actions after its branch point" } else { "no actions" };
        return Err(DemoError::Source(format!("{}: the episode accepted {what}", run_dir.display())));
    }
    if out.exists() {
        return Err(DemoError::Library(format!("{} already exists", out.display())));
    }
    let partial = PathBuf::from(format!("{}.partial", out.display()));
    if partial.exists() {
        fs::remove_dir_all(&partial).map_err(io_err(&partial))?;
    }
    fs::create_dir_all(partial.join("video/contact_sheets")).map_err(io_err(&partial))?;
    let spec = source.spec(paths)?;
    let mut world = LiberoWorld::new(&spec, renderer)?;
    let size = RESOLUTION_PX;
    let mut both = Mp4Writer::new(&partial.join(VIDEO_HEAD_WRIST), 2 * size, size)?;
    let mut head_video = Mp4Writer::new(&partial.join(VIDEO_HEAD), size, size)?;
    let mut wrist_video = Mp4Writer::new(&partial.join(VIDEO_WRIST), size, size)?;
    let own = source.own_actions();
    let frame_count = own.len() + 1;
    let sampled = sample_frame_indices(frame_count, MAX_FRAMES_PER_SHEET);
    let (mut head_tiles, mut wrist_tiles) = (Vec::new(), Vec::new());
    let mut states = Vec::with_capacity(frame_count);
    world.start()?;
    for (_, a) in &source.actions[..source.replayed()] {
        world.step(a)?;
    }
    for index in 0..frame_count {
        if index > 0 {
            world.step(&own[index - 1].1)?;
        }
        let frame = world.frame(index as u64)?;
        states.push(measured(&frame));
        let (head, wrist) = (&frame.head.image.rgb, &frame.wrist.image.rgb);
        both.push_rgb(&side_by_side(head, wrist, size as usize, size as usize)?)?;
        head_video.push_rgb(head)?;
        wrist_video.push_rgb(wrist)?;
        if sampled.contains(&index) {
            head_tiles.push(head.clone());
            wrist_tiles.push(wrist.clone());
        }
        progress(index + 1, frame_count);
    }
    let replay_success = world.verdict()?.success;
    for w in [both, head_video, wrist_video] {
        w.finish()?;
    }
    for (rel, tiles) in [(SHEET_HEAD, &head_tiles), (SHEET_WRIST, &wrist_tiles)] {
        let refs: Vec<&[u8]> = tiles.iter().map(Vec::as_slice).collect();
        let (w, h, rgb) = contact_sheet(&refs, size);
        let path = partial.join(rel);
        write_png(&path, w, h, 3, &rgb).map_err(io_err(&path))?;
    }
    write_trajectory(&partial, &source, &states)?;
    let fields = ManifestFields {
        source: &source,
        options,
        replay_success: Some(replay_success),
        effective_layout: Some(spec.task.effective_layout(spec.seed, spec.init_index)?),
        replay_checks: StoredChecks::Typed(Vec::new()),
    };
    let manifest = write_manifest(&partial, &fields)?;
    fs::rename(&partial, out).map_err(io_err(out))?;
    Ok(BundleSummary {
        dir: out.to_owned(),
        frame_count,
        transition_count: own.len(),
        source_success: source.success,
        replay_success,
        verified: manifest.verified(),
    })
}

/// The source episode a library bundle describes, read back from its manifest and trajectory.
pub fn bundle_source(dir: &Path) -> Result<(DemoManifest, SourceEpisode), DemoError> {
    let manifest = read_manifest(&dir.join(MANIFEST))?;
    let s = manifest.source.clone().unwrap_or_default();
    let path = dir.join(TRAJECTORY);
    let text = fs::read_to_string(&path).map_err(io_err(&path))?;
    // A branch's bundle: the replayed prefix comes first, so replays start where the source episode started.
    let branch = match manifest.branch() {
        None => None,
        Some(b) => {
            let prefix = crate::branch::read_prefix_file(&dir.join(crate::branch::PREFIX_FILE)).map_err(DemoError::Source)?;
            if b.replayed_actions != Some(prefix.len() as u64) {
                return Err(DemoError::Source(format!(
                    "{}: {} actions, the manifest's source.branch.replayed_actions is {:?}",
                    crate::branch::PREFIX_FILE,
                    prefix.len(),
                    b.replayed_actions
                )));
            }
            let missing = |k: &str| DemoError::Source(format!("{MANIFEST}: source.branch.{k} missing"));
            Some((
                BranchOrigin {
                    parent_episode_id: b.parent_episode_id.clone().ok_or_else(|| missing("parent_episode_id"))?,
                    parent_control_step: b.parent_control_step.ok_or_else(|| missing("parent_control_step"))?,
                    replayed_actions: prefix.len(),
                },
                prefix,
            ))
        }
    };
    let mut actions: Vec<(u64, [f64; 7])> = branch.iter().flat_map(|(_, p)| p.iter().map(|a| (0, *a))).collect();
    for (n, line) in text.lines().enumerate() {
        let (a, row) = read_trajectory_row(line, n + 1)?;
        actions.push((row.call_index.unwrap_or(0), a));
    }
    let missing = |k: &str| DemoError::Source(format!("{MANIFEST}: source.{k} missing"));
    let source = SourceEpisode {
        episode_id: s.episode_id.clone().ok_or_else(|| missing("episode_id"))?,
        task_ref: manifest.task_id().ok_or_else(|| missing("task.id"))?.to_owned(),
        instruction: manifest.instruction().ok_or_else(|| missing("task.instruction"))?.to_owned(),
        level: s.level.and_then(|l| u8::try_from(l).ok()).ok_or_else(|| missing("level"))?,
        seed: s.seed.ok_or_else(|| missing("seed"))?,
        init_state_index: s.init_state_index.ok_or_else(|| missing("init_state_index"))? as usize,
        actions,
        success: s.episode_success,
        layout: layout_from_json(s.layout.as_ref().unwrap_or(&Value::Null))?,
        branch: branch.map(|(origin, _)| origin),
    };
    Ok((manifest, source))
}

/// Replays a bundle's actions (a branch's prefix first) from its init state on [`WorldPhysics`] (no rendering)
/// and rewrites its manifest with the outcome: verified only if the evaluator's success is reproduced. Returns the replayed success.
pub fn verify_bundle(dir: &Path, paths: &AssetPaths) -> Result<bool, DemoError> {
    let (manifest, source) = bundle_source(dir)?;
    let spec = source.spec(paths)?;
    let mut physics = WorldPhysics::build(&spec, |_, _, _| Ok(()))?;
    physics.start(|_| {})?;
    for (_, a) in &source.actions {
        physics.step(a)?;
    }
    let success = physics.evaluate().success;
    let recorded = manifest.source.clone().unwrap_or_default();
    let options = RecordOptions {
        source_type: recorded.source_type.unwrap_or_else(|| "unknown".into()),
        source_desc: recorded.source_desc.unwrap_or_default(),
    };
    // The stored checks go on as they are (a list the typed view could not read, too).
    let replay_checks = match (&manifest.replay_checks, manifest.rest.get("replay_checks")) {
        (Some(checks), _) => StoredChecks::Typed(checks.clone()),
        (None, Some(raw)) => StoredChecks::AsRead(raw.clone()),
        (None, None) => StoredChecks::Typed(Vec::new()),
    };
    let fields = ManifestFields {
        source: &source,
        options: &options,
        replay_success: Some(success),
        effective_layout: Some(spec.task.effective_layout(spec.seed, spec.init_index)?),
        replay_checks,
    };
    write_manifest(dir, &fields)?;
    Ok(success)
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOLDEN_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/demo_bundle");

    fn golden_fields<'a>(source: &'a SourceEpisode, options: &'a RecordOptions, replay: Option<bool>) -> ManifestFields<'a> {
        let effective_layout = Some(EffectiveLayout { placement_seed: 100, init_index: Some(0), region_margin_m: 0.0, scene_shift_m: [0.0; 2], yaw_margin_rad: 0.0 });
        ManifestFields { source, options, replay_success: replay, effective_layout, replay_checks: StoredChecks::Typed(Vec::new()) }
    }

    /// A two-action source with made-up states and placeholder media: the wire format only.
    fn synthetic(dir: &Path) -> SourceEpisode {
        let source = SourceEpisode {
            episode_id: "ep-20260101T000000Z-0000abcd".into(),
            task_ref: "T14".into(),
            instruction: "close the top  drawer of the cabinet".into(),
            level: 3,
            seed: 100,
            init_state_index: 0,
            actions: vec![(1, [0.5, -0.25, 0.0, 0.0, 0.0, 0.125, -1.0]), (1, [1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0])],
            success: Some(true),
            layout: None,
            branch: None,
        };
        let state = |k: f64| MeasuredState {
            eef_pose_robot_base_xyzw: [0.5 + k, 0.0, 0.25, 1.0, 0.0, 0.0, 0.0],
            gripper_finger_joint_position_m: [0.04 - k, -0.04 + k],
        };
        fs::create_dir_all(dir.join("video/contact_sheets")).unwrap();
        for (rel, bytes) in [(VIDEO_HEAD_WRIST, &b"mp4 both"[..]), (VIDEO_HEAD, b"mp4 head"), (VIDEO_WRIST, b"mp4 wrist"), (SHEET_HEAD, b"png head"), (SHEET_WRIST, b"png wrist")] {
            fs::write(dir.join(rel), bytes).unwrap();
        }
        write_trajectory(dir, &source, &[state(0.0), state(0.015625), state(0.03125)]).unwrap();
        source
    }

    /// The library manifest and trajectory rows are a wire format (teleop, exports and other tools read them):
    /// byte-for-byte equal to the golden files. `UPDATE_GOLDEN=1` rewrites them after a deliberate change.
    #[test]
    fn manifest_and_trajectory_match_the_golden_files() {
        let dir = tempfile::tempdir().unwrap();
        let source = synthetic(dir.path());
        let options = RecordOptions { source_type: "scripted_expert".into(), source_desc: "golden".into() };
        let manifest = write_manifest(dir.path(), &golden_fields(&source, &options, Some(true))).unwrap();
        assert!(manifest.verified());
        assert_eq!(manifest.instruction(), Some("close the top drawer of the cabinet"), "normalized");
        let golden = Path::new(GOLDEN_DIR);
        for name in [MANIFEST, TRAJECTORY] {
            let got = fs::read_to_string(dir.path().join(name)).unwrap();
            if std::env::var_os("UPDATE_GOLDEN").is_some() {
                fs::create_dir_all(golden).unwrap();
                fs::write(golden.join(name), &got).unwrap();
            }
            let want = fs::read_to_string(golden.join(name)).unwrap_or_else(|e| panic!("{name}: {e} (UPDATE_GOLDEN=1 writes it)"));
            assert_eq!(got, want, "{name} differs from the golden file");
        }
        let (back, read) = bundle_source(dir.path()).unwrap();
        assert_eq!(back, manifest, "what was written reads back as the same typed manifest");
        assert_eq!(read.actions.iter().map(|a| a.1).collect::<Vec<_>>(), source.actions.iter().map(|a| a.1).collect::<Vec<_>>());
        assert_eq!(read.task_ref, "T14");
    }

    /// A branch's bundle (issue 49): the trajectory holds only the actions after the branch point, the manifest
    /// names the parent, its step and the replayed prefix, and reading the bundle back puts the prefix first.
    #[test]
    fn a_branch_bundle_keeps_only_its_own_actions_and_replays_the_prefix_first() {
        let dir = tempfile::tempdir().unwrap();
        let mut source = synthetic(dir.path());
        let prefix = (0, [0.0, 0.0, 0.375, 0.0, 0.0, 0.0, 1.0]);
        source.actions.insert(0, prefix);
        source.branch = Some(BranchOrigin { parent_episode_id: "ep-20251231T000000Z-00000001".into(), parent_control_step: 1, replayed_actions: 1 });
        let state = |k: f64| MeasuredState { eef_pose_robot_base_xyzw: [k, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], gripper_finger_joint_position_m: [0.01, -0.01] };
        write_trajectory(dir.path(), &source, &[state(0.0), state(0.5), state(1.0)]).unwrap();
        let options = RecordOptions { source_type: "human_teleop".into(), source_desc: String::new() };
        let manifest = write_manifest(dir.path(), &golden_fields(&source, &options, Some(true))).unwrap();
        assert_eq!((manifest.transition_count, manifest.frame_count), (Some(2), Some(3)), "only the branch's own actions");
        assert_eq!(
            manifest.branch().map(|b| b.to_value()),
            Some(serde_json::json!({"parent_episode_id": "ep-20251231T000000Z-00000001", "parent_control_step": 1, "replayed_actions": 1, "prefix_file": "branch_prefix.jsonl"}))
        );
        let rows = fs::read_to_string(dir.path().join(TRAJECTORY)).unwrap();
        assert_eq!(rows.lines().count(), 2);
        assert!(!rows.contains("0.375"), "the replayed action is not a trajectory row: {rows}");
        let listed = manifest.integrity.and_then(|i| i.files).unwrap().iter().any(|f| f.path.as_deref() == Some("branch_prefix.jsonl"));
        assert!(listed, "the prefix file is under the integrity block");
        let (back, read) = bundle_source(dir.path()).unwrap();
        assert_eq!(read.actions.iter().map(|a| a.1).collect::<Vec<_>>(), source.actions.iter().map(|a| a.1).collect::<Vec<_>>(), "prefix first, then the trajectory");
        assert_eq!((read.branch.clone(), read.replayed(), back.branch().and_then(|b| b.parent_control_step)), (source.branch.clone(), 1, Some(1)));
        fs::write(dir.path().join(crate::branch::PREFIX_FILE), "").unwrap();
        assert!(bundle_source(dir.path()).is_err(), "a prefix that lost its actions is refused, not replayed from the wrong state");
    }

    #[test]
    fn a_replay_that_fails_or_a_failed_source_is_never_verified() {
        let dir = tempfile::tempdir().unwrap();
        let mut source = synthetic(dir.path());
        let options = RecordOptions { source_type: "agent".into(), source_desc: String::new() };
        let m = write_manifest(dir.path(), &golden_fields(&source, &options, Some(false))).unwrap();
        assert_eq!(m.verification.and_then(|v| v.verified), Some(false));
        source.success = Some(false);
        let m = write_manifest(dir.path(), &golden_fields(&source, &options, Some(true))).unwrap();
        assert_eq!(m.verification.and_then(|v| v.verified), Some(false));
    }

    /// A source that never finished and a bundle never replayed keep their verdict keys, written null (the wire
    /// format's spelling of "unknown"), and a stored replay-check list the typed view cannot read goes on as read.
    #[test]
    fn unknown_verdicts_are_written_null_and_an_unreadable_check_list_is_kept() {
        let dir = tempfile::tempdir().unwrap();
        let mut source = synthetic(dir.path());
        source.success = None;
        let options = RecordOptions { source_type: "agent".into(), source_desc: String::new() };
        let mut fields = golden_fields(&source, &options, None);
        fields.replay_checks = StoredChecks::AsRead(serde_json::json!(["not a check"]));
        write_manifest(dir.path(), &fields).unwrap();
        let written: Value = serde_json::from_str(&fs::read_to_string(dir.path().join(MANIFEST)).unwrap()).unwrap();
        assert_eq!(written["source"]["episode_success"], Value::Null);
        assert!(written["source"].as_object().unwrap().contains_key("episode_success"));
        assert!(written["verification"].as_object().unwrap().contains_key("replay_success"));
        assert_eq!((written["verification"]["replay_success"].clone(), written["verification"]["verified"].clone()), (Value::Null, Value::Bool(false)));
        assert_eq!(written["replay_checks"], serde_json::json!(["not a check"]));
    }

    #[test]
    fn contact_sheets_follow_the_video_only_grid() {
        let tile = vec![0u8; 4 * 4 * 3];
        let tiles: Vec<&[u8]> = vec![&tile; 12];
        let (w, h, rgb) = contact_sheet(&tiles, 4);
        assert_eq!((w, h), (4 * 4 + 5 * 8, 3 * 4 + 4 * 8), "12 tiles: 4 columns, 3 rows, 8-px gutters");
        assert_eq!(&rgb[..3], &[255, 255, 255], "white gutter");
        let at = |x: u32, y: u32| &rgb[((y * w + x) * 3) as usize..][..3];
        assert_eq!(at(8, 8), &[0, 0, 0], "first tile starts after the gutter");
        assert_eq!(contact_sheet(&tiles[..5], 4).0, 3 * 4 + 4 * 8, "5 tiles: ceil(√5) = 3 columns");
    }
}
