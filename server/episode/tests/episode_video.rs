//! The private continuous video on real episodes: one frame per control step (10 settle steps + every
//! micro-action), 512×256 at 20 fps, a fast-start MP4 whose every sample decodes, finalised when the
//! episode ends by finish or by wall-clock expiry.
use std::path::Path;
use std::time::{Duration, Instant};

use libero_records::records::RunDir;
use libero_episode::task::resolve_task;
use libero_episode::physics::WorldPhysics;
use libero_episode::state_record::{StateRecordReader, StateRecordWriter};
use libero_episode::video::{VideoRecorder, partial_path, render_video_from_record};
use libero_episode::video_queue::{VideoProgress, VideoQueue};
use libero_episode::world::{LiberoWorld, SETTLE_STEPS, WorldSpec, head_wrist_cameras};
use libero_render::FrameState;
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_episode::{EpisodeConfig, EpisodeHandle, EpisodeState, Level, spawn_episode};
use libero_render::Renderer;
use libero_sim::AssetPaths;
use serde_json::{Map, Value, json};

const TASK: &str = "libero_object/pick_up_the_ketchup_and_place_it_in_the_basket";

fn video_episode(dir: &Path, name: &str, wall_s: f64, renderer: &Renderer) -> (EpisodeHandle, VideoQueue) {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let spec = WorldSpec { task: resolve_task(TASK, &paths).unwrap(), level: Level::L1, seed: 100, init_index: 0, paths };
    let cfg = EpisodeConfig {
        episode_id: name.into(),
        instruction: "pick up the ketchup and place it in the basket".into(),
        level: Level::L1,
        max_agent_steps: 100,
        max_wall_time_s: wall_s,
        workspace: dir.join(name).join("ws"),
        run_dir: dir.join(name).join("run"),
    };
    std::fs::create_dir_all(cfg.workspace.join("benchmark_inputs")).unwrap();
    let run = RunDir::new(&cfg.run_dir);
    let (video, record) = (run.continuous_video(), run.state_record());
    let queue = VideoQueue::start(head_wrist_cameras()).expect("video worker");
    let (r, q) = (renderer.clone(), queue.clone());
    let handle = spawn_episode(cfg, move || {
        let mut w = LiberoWorld::new(&spec, r)?;
        w.record_video(&video, &record, q, None)?;
        Ok(w)
    })
    .expect("episode");
    (handle, queue)
}

/// Waits for the background worker to finish the episode's video.
fn wait_for_video(queue: &VideoQueue, run: &RunDir) {
    let state = queue.wait(&run.continuous_video(), Duration::from_secs(300));
    assert_eq!(state, Some(VideoProgress::Ready), "the video of {}", run.root.display());
}

fn actions(n: usize) -> Option<Map<String, Value>> {
    json!({"actions": vec![[0.2, 0.0, -0.1, 0.0, 0.0, 0.0, -1.0]; n]}).as_object().cloned()
}

/// One ISO BMFF box: type and payload range in the file.
#[derive(Debug, Clone)]
struct Mp4Box {
    kind: String,
    start: usize,
    end: usize,
}

fn boxes(bytes: &[u8], mut pos: usize, end: usize) -> Vec<Mp4Box> {
    let mut out = Vec::new();
    while pos + 8 <= end {
        let size32 = u32::from_be_bytes(bytes[pos..pos + 4].try_into().unwrap()) as usize;
        let kind = String::from_utf8_lossy(&bytes[pos + 4..pos + 8]).into_owned();
        let (header, size) = match size32 {
            1 => (16, u64::from_be_bytes(bytes[pos + 8..pos + 16].try_into().unwrap()) as usize),
            0 => (8, end - pos),
            n => (8, n),
        };
        assert!(size >= header && pos + size <= end, "box {kind} at {pos} overruns its parent");
        out.push(Mp4Box { kind, start: pos + header, end: pos + size });
        pos += size;
    }
    assert_eq!(pos, end, "trailing bytes after the last box");
    out
}

fn child(bytes: &[u8], parent: &Mp4Box, path: &[&str]) -> Mp4Box {
    let mut cur = parent.clone();
    for kind in path {
        cur = boxes(bytes, cur.start, cur.end)
            .into_iter()
            .find(|b| b.kind == *kind)
            .unwrap_or_else(|| panic!("no {kind} box in {}", cur.kind));
    }
    cur
}

fn be32(b: &[u8], at: usize) -> u32 {
    u32::from_be_bytes(b[at..at + 4].try_into().unwrap())
}

/// What the checks need from a single-video-track MP4.
struct VideoFacts {
    top_level: Vec<String>,
    width_px: u32,
    height_px: u32,
    timescale: u32,
    duration: u32,
    /// `stts` expanded: one duration per sample, in `timescale` units.
    sample_deltas: Vec<u32>,
    sample_sizes: Vec<u32>,
    mdat_payload: (usize, usize),
    sps_pps: Vec<Vec<u8>>,
}

fn read_mp4(bytes: &[u8]) -> VideoFacts {
    let top = boxes(bytes, 0, bytes.len());
    let moov = top.iter().find(|b| b.kind == "moov").expect("moov").clone();
    let mdat = top.iter().find(|b| b.kind == "mdat").expect("mdat").clone();
    let tkhd = child(bytes, &moov, &["trak", "tkhd"]);
    // tkhd ends with width and height in 16.16 fixed point.
    let (width_px, height_px) = (be32(bytes, tkhd.end - 8) >> 16, be32(bytes, tkhd.end - 4) >> 16);
    let mdhd = child(bytes, &moov, &["trak", "mdia", "mdhd"]);
    assert_eq!(bytes[mdhd.start], 0, "mdhd version 0 expected");
    let (timescale, duration) = (be32(bytes, mdhd.start + 12), be32(bytes, mdhd.start + 16));
    let stbl = child(bytes, &moov, &["trak", "mdia", "minf", "stbl"]);
    let stts = child(bytes, &stbl, &["stts"]);
    let mut sample_deltas = Vec::new();
    for e in 0..be32(bytes, stts.start + 4) as usize {
        let at = stts.start + 8 + 8 * e;
        sample_deltas.extend(std::iter::repeat_n(be32(bytes, at + 4), be32(bytes, at) as usize));
    }
    let stsz = child(bytes, &stbl, &["stsz"]);
    let (uniform, count) = (be32(bytes, stsz.start + 4), be32(bytes, stsz.start + 8) as usize);
    let sample_sizes = if uniform != 0 {
        vec![uniform; count]
    } else {
        (0..count).map(|i| be32(bytes, stsz.start + 12 + 4 * i)).collect()
    };
    // stsd → avc1 (78-byte visual sample entry) → avcC: SPS and PPS.
    let stsd = child(bytes, &stbl, &["stsd"]);
    let avc1 = boxes(bytes, stsd.start + 8, stsd.end).into_iter().find(|b| b.kind == "avc1").expect("avc1 entry");
    let avcc = boxes(bytes, avc1.start + 78, avc1.end).into_iter().find(|b| b.kind == "avcC").expect("avcC");
    let mut sps_pps = Vec::new();
    let mut at = avcc.start + 5;
    for (i, count_mask) in [0x1fu8, 0xff].into_iter().enumerate() {
        let n = bytes[at] & count_mask;
        at += 1;
        for _ in 0..n {
            let len = u16::from_be_bytes([bytes[at], bytes[at + 1]]) as usize;
            sps_pps.push(bytes[at + 2..at + 2 + len].to_vec());
            at += 2 + len;
        }
        assert!(!sps_pps.is_empty(), "avcC set {i} is empty");
    }
    VideoFacts {
        top_level: top.iter().map(|b| b.kind.clone()).collect(),
        width_px,
        height_px,
        timescale,
        duration,
        sample_deltas,
        sample_sizes,
        mdat_payload: (mdat.start, mdat.end),
        sps_pps,
    }
}

/// Standard deviation of the RGB values of columns `cols` of a `width`-pixel-wide RGB image.
fn half_std(rgb: &[u8], width: usize, cols: std::ops::Range<usize>) -> f64 {
    let values: Vec<f64> = rgb
        .chunks_exact(width * 3)
        .flat_map(|row| row[cols.start * 3..cols.end * 3].iter().map(|&v| v as f64))
        .collect();
    let mean = values.iter().sum::<f64>() / values.len() as f64;
    (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / values.len() as f64).sqrt()
}

/// A decoded picture: its size and how much the head (left) and wrist (right) halves vary.
type Decoded = ((usize, usize), f64, f64);

fn describe(yuv: &openh264::decoder::DecodedYUV<'_>) -> Decoded {
    use openh264::formats::YUVSource;
    let (w, h) = yuv.dimensions();
    let mut rgb = vec![0u8; w * h * 3];
    yuv.write_rgb8(&mut rgb);
    ((w, h), half_std(&rgb, w, 0..w / 2), half_std(&rgb, w, w / 2..w))
}

/// Decodes every sample with OpenH264 (AVCC → Annex-B).
fn decode_all(bytes: &[u8], facts: &VideoFacts) -> Vec<Decoded> {
    use openh264::decoder::Decoder;
    let mut decoder = Decoder::new().expect("decoder");
    let mut sizes = Vec::new();
    let mut annexb = Vec::new();
    for ps in &facts.sps_pps {
        annexb.extend_from_slice(&[0, 0, 0, 1]);
        annexb.extend_from_slice(ps);
    }
    let mut at = facts.mdat_payload.0;
    for (i, &size) in facts.sample_sizes.iter().enumerate() {
        let sample = &bytes[at..at + size as usize];
        at += size as usize;
        let mut p = 0;
        while p < sample.len() {
            let len = be32(sample, p) as usize;
            annexb.extend_from_slice(&[0, 0, 0, 1]);
            annexb.extend_from_slice(&sample[p + 4..p + 4 + len]);
            p += 4 + len;
        }
        let frame = decoder.decode(&annexb).unwrap_or_else(|e| panic!("sample {i} does not decode: {e}"));
        if let Some(yuv) = frame {
            sizes.push(describe(&yuv));
        }
        annexb.clear();
    }
    for yuv in decoder.flush_remaining().expect("flush") {
        sizes.push(describe(&yuv));
    }
    sizes
}

fn check_video(run: &RunDir, control_steps: usize) {
    check_video_file(&run.continuous_video(), control_steps);
}

fn check_video_file(path: &Path, control_steps: usize) {
    let path = path.to_owned();
    assert!(!partial_path(&path).exists(), "the temporary file was renamed away");
    let bytes = std::fs::read(&path).expect("continuous_video.mp4 exists once the episode has ended");
    let facts = read_mp4(&bytes);
    assert_eq!(facts.top_level, ["ftyp", "moov", "mdat"], "fast-start box order");
    assert_eq!((facts.width_px, facts.height_px), (512, 256));
    assert_eq!(facts.sample_sizes.len(), control_steps, "one frame per control step");
    assert_eq!(facts.sample_deltas.len(), control_steps);
    let frame_s: Vec<f64> = facts.sample_deltas.iter().map(|&d| d as f64 / facts.timescale as f64).collect();
    assert!(frame_s.iter().all(|&s| (s - 0.05).abs() < 1e-6), "20 fps: every frame lasts 50 ms");
    let duration_s = facts.duration as f64 / facts.timescale as f64;
    assert!((duration_s - control_steps as f64 / 20.0).abs() < 1e-6, "duration {duration_s} s");
    let payload: usize = facts.sample_sizes.iter().map(|&s| s as usize).sum();
    assert_eq!(payload, facts.mdat_payload.1 - facts.mdat_payload.0, "samples fill mdat exactly");
    let decoded = decode_all(&bytes, &facts);
    assert_eq!(decoded.len(), control_steps, "every sample decodes to a picture");
    for (i, &(size, head_std, wrist_std)) in decoded.iter().enumerate() {
        assert_eq!(size, (512, 256), "frame {i}");
        // Both views show a scene, not a cleared or missing image.
        assert!(head_std > 10.0 && wrist_std > 10.0, "frame {i}: head std {head_std:.1}, wrist std {wrist_std:.1}");
    }
}

fn wait_for_state(h: &EpisodeHandle, state: EpisodeState, within: Duration) {
    let t = Instant::now();
    while h.status().state != state {
        assert!(t.elapsed() < within, "episode did not reach {state:?}: {:?}", h.status());
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn the_video_has_one_decodable_512x256_frame_per_control_step_when_the_episode_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let renderer = Renderer::new().expect("renderer");
    let (h, queue) = video_episode(dir.path(), "finish", 600.0, &renderer);
    let run = RunDir::new(&h.config().run_dir);
    assert!(!run.continuous_video().exists() && !partial_path(&run.continuous_video()).exists(), "made after the episode");
    assert_eq!(h.call("start_episode", None)["ok"], true);
    assert_eq!(h.call("osc_sequence", actions(5))["ok"], true);
    assert_eq!(h.call("osc_sequence", actions(3))["ok"], true);
    // A refused call runs no control step and adds no frame.
    assert_eq!(h.call("osc_sequence", json!({"actions": [[2, 0, 0, 0, 0, 0, 0]]}).as_object().cloned())["ok"], false);
    // finish ends the episode whatever the verdict; the reply comes first, then the world goes and queues
    // its video, which the background worker renders from the state record.
    let _ = h.call("finish_episode", None);
    assert_ne!(h.status().state, EpisodeState::Active);
    h.stop("test over");
    wait_for_video(&queue, &run);
    check_video(&run, SETTLE_STEPS + 8);
}

#[test]
fn the_video_is_finalised_when_the_wall_clock_expires() {
    let dir = tempfile::tempdir().unwrap();
    let renderer = Renderer::new().expect("renderer");
    let (h, queue) = video_episode(dir.path(), "expiry", 3.0, &renderer);
    assert_eq!(h.call("start_episode", None)["ok"], true);
    assert_eq!(h.call("osc_sequence", actions(2))["ok"], true);
    wait_for_state(&h, EpisodeState::Finished, Duration::from_secs(30));
    let run = RunDir::new(&h.config().run_dir);
    wait_for_video(&queue, &run);
    check_video(&run, SETTLE_STEPS + 2);
    h.stop("test over"); // waits until the episode thread let go of its world and renderer
}

/// Issue 19's proof: the video rendered afterwards from the state record is the video a recorder rendering
/// during the episode makes. The same simulation feeds both — today's recorder, which snapshots the poses in
/// MuJoCo's data at every control step, and the state record — over settle steps, pushes, a grasp and a
/// gripper toggle; the recomputed poses equal the snapshots bit for bit and the two MP4 files are identical.
#[test]
fn the_video_from_the_state_record_is_the_recorders_video_frame_for_frame() {
    let dir = tempfile::tempdir().unwrap();
    let renderer = Renderer::new().expect("renderer");
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let spec = WorldSpec { task: resolve_task(TASK, &paths).unwrap(), level: Level::L1, seed: 7, init_index: 2, paths };
    let mut physics = WorldPhysics::build(&spec, |_, _, _| Ok(())).unwrap();
    let model = physics.model().clone();
    let gpu_model = renderer.prepare_model(&model).unwrap();
    let recorded = dir.path().join("recorder.mp4");
    let recorder = VideoRecorder::spawn(&recorded, renderer.clone(), gpu_model.clone(), head_wrist_cameras()).unwrap();
    let mut to_recorder = recorder.into_step_observer();
    let record = dir.path().join("state_record.bin");
    let nq = model.ffi().nq as usize;
    let mut writer = StateRecordWriter::create(&record, nq, model.ffi().nmocap as usize).unwrap();
    let snapshots = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let seen = snapshots.clone();
    physics.sim.set_step_observer(Some(Box::new(move |m: &MjModel, d: &libero_sim::SimData, pose_qpos: &[f64]| {
        to_recorder(m, d, pose_qpos);
        seen.lock().unwrap().push(FrameState::from_mujoco(m, d));
        writer.push(pose_qpos, &libero_sim::pose_replay::mocap_of(m, d)).unwrap();
    })));
    physics.start(|_| {}).unwrap();
    let mut actions: Vec<[f64; 7]> = vec![[0.4, 0.1, -0.3, 0.0, 0.0, 0.1, -1.0]; 15];
    actions.extend(vec![[0.0, 0.0, -0.5, 0.2, 0.0, 0.0, 1.0]; 10]);
    actions.extend(vec![[-0.3, 0.2, 0.5, 0.0, -0.2, 0.0, -1.0]; 10]);
    for a in &actions {
        physics.step(a).unwrap();
    }
    physics.sim.set_step_observer(None); // drains and finalises the recorder's video
    let frames = SETTLE_STEPS + actions.len();

    let mut replay = libero_sim::PoseReplay::new(model.clone());
    let mut reader = StateRecordReader::open(&record).unwrap();
    assert_eq!(reader.frames(), frames as u64);
    let bits = |v: &[[f64; 3]]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
    let bits9 = |v: &[[f64; 9]]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
    for (i, live) in snapshots.lock().unwrap().iter().enumerate() {
        let (qpos, mocap) = reader.next_frame().unwrap().unwrap();
        let again = FrameState::from_mujoco(&model, replay.pose(&qpos, &mocap).unwrap());
        assert_eq!(bits(&again.geom_xpos), bits(&live.geom_xpos), "frame {i}: geom positions");
        assert_eq!(bits9(&again.geom_xmat), bits9(&live.geom_xmat), "frame {i}: geom orientations");
        assert_eq!(bits(&again.cam_xpos), bits(&live.cam_xpos), "frame {i}: camera positions");
        assert_eq!(bits9(&again.cam_xmat), bits9(&live.cam_xmat), "frame {i}: camera orientations");
        assert_eq!(bits(&again.site_xpos), bits(&live.site_xpos), "frame {i}: site positions");
        assert_eq!(bits(&again.light_xpos), bits(&live.light_xpos), "frame {i}: light positions");
        assert_eq!(bits(&again.light_xdir), bits(&live.light_xdir), "frame {i}: light directions");
        assert_eq!(again.robot_base_pose, live.robot_base_pose, "frame {i}: robot base");
    }

    let from_record = dir.path().join("from_record.mp4");
    let mut progress = Vec::new();
    let summary = render_video_from_record(&record, &from_record, &model, &renderer, &gpu_model, &head_wrist_cameras(), |done, total| {
        progress.push((done, total));
        true
    })
    .unwrap()
    .unwrap();
    assert_eq!(summary.frames, frames as u64);
    assert_eq!(progress.first(), Some(&(0, frames as u64)));
    assert_eq!(progress.last(), Some(&(frames as u64, frames as u64)));
    let (a, b) = (std::fs::read(&recorded).unwrap(), std::fs::read(&from_record).unwrap());
    assert!(a == b, "the two videos differ ({} and {} bytes)", a.len(), b.len());
    check_video_file(&from_record, frames);
}
