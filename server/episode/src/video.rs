//! The evaluator-private continuous video (§6.1): one frame per control step (settle steps included),
//! head | wrist side by side (512×256), 20 fps, H.264 (bundled OpenH264) in a fast-start MP4 (muxide).
//!
//! The episode thread only snapshots poses ([`FrameState`], tens of microseconds) into a bounded queue; a
//! recorder thread renders both cameras and encodes, off the agent's reply path. The file is written under
//! a temporary name and renamed to `continuous_video.mp4` only once the muxer has finalised it, so a crash
//! never leaves a truncated file under the final name.
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{self, SyncSender};
use std::thread::JoinHandle;

use libero_render::{CameraRequest, FrameState, ModelHandle, Outputs, RenderOptions, Renderer};
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::{PoseReplay, SimData, StepObserver};
use muxide::api::{Muxer, MuxerBuilder, VideoCodec};
use openh264::OpenH264API;
use openh264::encoder::{
    BitRate, Encoder, EncoderConfig, FrameRate, FrameType, IntraFramePeriod, RateControlMode, UsageType,
};
use openh264::formats::{RgbSliceU8, YUVBuffer};
use thiserror::Error;

use crate::state_record::StateRecordReader;

/// Frames per second of the video: one frame per 20 Hz control step, so video time equals sim time.
pub const VIDEO_FPS: f64 = 20.0;
/// Target bit rate; about 350 kbit/s comes out for LIBERO scenes (measured in the setup notes).
const VIDEO_BITRATE_BPS: u32 = 1_000_000;
/// One IDR frame per second, so a player can seek and a damaged stretch heals within a second.
const INTRA_PERIOD_FRAMES: u32 = 20;
/// Frames buffered between the episode thread and the recorder: about 20 calls of 50 micro-actions, so
/// where rendering is slow (a software renderer) the recorder catches up while the agent thinks instead
/// of delaying replies. A pose snapshot is tens of kB, so a full queue is tens of MB. Beyond it the
/// episode thread waits rather than drop frames.
pub const VIDEO_QUEUE_FRAMES: usize = 1024;
/// Suffix of the file while it is being written.
pub const PARTIAL_SUFFIX: &str = ".partial";

#[derive(Debug, Error)]
pub enum VideoError {
    #[error("video encoder: {0}")]
    Encode(String),
    #[error("MP4 muxer: {0}")]
    Mux(String),
    #[error("video renderer: {0}")]
    Render(String),
    #[error("video frame: {0}")]
    Frame(String),
    #[error("video i/o: {0}")]
    Io(#[from] std::io::Error),
    #[error("video recorder thread: {0}")]
    Thread(String),
    #[error("video source: {0}")]
    Source(String),
    /// The server is stopping; the video is left to be rebuilt from its state record at the next start.
    #[error("video rendering stopped before the end")]
    Stopped,
}

/// What a finished video holds.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoSummary {
    pub path: PathBuf,
    pub frames: u64,
    pub duration_s: f64,
    pub bytes: u64,
}

/// `<path>.partial`, the name the video has until it is complete.
pub fn partial_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(PARTIAL_SUFFIX);
    PathBuf::from(name)
}

/// Lowers OpenH264's trace level to errors before the encoder is initialised (at its first frame). At the
/// default level its parameter check prints "bEnableFrameSkip = 0, bitrate can't be controlled for RC_QUALITY_MODE,
/// RC_BITRATE_MODE and RC_TIMESTAMP_MODE without enabling skip frame" on stderr for every video: true, and meant
/// (every control step must be in the video, so no frame is skipped); the openh264 crate only quiets the encoder
/// after initialising it. Only what is printed changes, never a byte of the stream.
fn errors_only(encoder: &mut Encoder) {
    let mut level = openh264_sys2::WELS_LOG_ERROR as std::ffi::c_int;
    // SAFETY: the encoder is live; the trace level is an option OpenH264 accepts before initialisation, read as
    // one int from the pointer during the call.
    let _ = unsafe { encoder.raw_api().set_option(openh264_sys2::ENCODER_OPTION_TRACE_LEVEL, (&raw mut level).cast()) };
}

/// Encodes RGB frames of one size into an MP4 at [`partial_path`]; [`finish`](Self::finish) finalises and
/// renames it. The file is created at the first frame (an episode that never stepped has no video).
pub struct Mp4Writer {
    path: PathBuf,
    width_px: u32,
    height_px: u32,
    open: Option<(Encoder, Muxer<BufWriter<File>>)>,
    frames: u64,
}

impl Mp4Writer {
    pub fn new(path: &Path, width_px: u32, height_px: u32) -> Result<Self, VideoError> {
        if width_px == 0 || height_px == 0 || width_px % 2 != 0 || height_px % 2 != 0 {
            return Err(VideoError::Frame(format!("H.264 4:2:0 needs even sizes, got {width_px}x{height_px}")));
        }
        Ok(Self { path: path.to_owned(), width_px, height_px, open: None, frames: 0 })
    }

    fn open(&mut self) -> Result<&mut (Encoder, Muxer<BufWriter<File>>), VideoError> {
        if self.open.is_none() {
            let config = EncoderConfig::new()
                .usage_type(UsageType::CameraVideoRealTime)
                .max_frame_rate(FrameRate::from_hz(VIDEO_FPS as f32))
                .bitrate(BitRate::from_bps(VIDEO_BITRATE_BPS))
                .rate_control_mode(RateControlMode::Bitrate)
                // The default lets rate control drop frames; every control step must be in the video.
                .skip_frames(false)
                .intra_frame_period(IntraFramePeriod::from_num_frames(INTRA_PERIOD_FRAMES));
            let mut encoder = Encoder::with_api_config(OpenH264API::from_source(), config)
                .map_err(|e| VideoError::Encode(e.to_string()))?;
            errors_only(&mut encoder);
            let file = File::create(partial_path(&self.path))?;
            let muxer = MuxerBuilder::new(BufWriter::new(file))
                .video(VideoCodec::H264, self.width_px, self.height_px, VIDEO_FPS)
                .with_fast_start(true)
                .build()
                .map_err(|e| VideoError::Mux(e.to_string()))?;
            self.open = Some((encoder, muxer));
        }
        self.open.as_mut().ok_or_else(|| VideoError::Thread("encoder missing after opening".into()))
    }

    /// Appends one frame (`width × height × 3` bytes, rows top to bottom).
    pub fn push_rgb(&mut self, rgb: &[u8]) -> Result<(), VideoError> {
        let (w, h) = (self.width_px as usize, self.height_px as usize);
        if rgb.len() != w * h * 3 {
            return Err(VideoError::Frame(format!("expected {w}x{h} RGB ({} bytes), got {}", w * h * 3, rgb.len())));
        }
        let index = self.frames;
        let (encoder, muxer) = self.open()?;
        let yuv = YUVBuffer::from_rgb8_source(RgbSliceU8::new(rgb, (w, h)));
        let millis = (index as f64 * 1000.0 / VIDEO_FPS).round() as u64;
        let stream = encoder
            .encode_at(&yuv, openh264::Timestamp::from_millis(millis))
            .map_err(|e| VideoError::Encode(e.to_string()))?;
        let keyframe = match stream.frame_type() {
            FrameType::IDR | FrameType::I => true,
            FrameType::P => false,
            other => return Err(VideoError::Encode(format!("frame {index} came out as {other:?}"))),
        };
        let annexb = stream.to_vec();
        muxer
            .write_video(index as f64 / VIDEO_FPS, &annexb, keyframe)
            .map_err(|e| VideoError::Mux(format!("frame {index}: {e}")))?;
        self.frames += 1;
        Ok(())
    }

    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Writes the index (moov before mdat), syncs, and renames the file to its final name. `None` when no
    /// frame was ever pushed (no file exists then).
    pub fn finish(self) -> Result<Option<VideoSummary>, VideoError> {
        let Some((_encoder, mut muxer)) = self.open else { return Ok(None) };
        let stats = muxer.finish_in_place_with_stats().map_err(|e| VideoError::Mux(e.to_string()))?;
        let mut out = muxer.into_writer();
        out.flush()?;
        let file = out.into_inner().map_err(|e| VideoError::Io(e.into_error()))?;
        // Durable bytes before the rename publishes the final name.
        file.sync_all()?;
        drop(file);
        std::fs::rename(partial_path(&self.path), &self.path)?;
        Ok(Some(VideoSummary {
            path: self.path,
            frames: stats.video_frames,
            duration_s: stats.duration_secs,
            bytes: stats.bytes_written,
        }))
    }
}

/// Head and wrist RGB (same size) concatenated horizontally, head left.
pub fn side_by_side(head: &[u8], wrist: &[u8], width_px: usize, height_px: usize) -> Result<Vec<u8>, VideoError> {
    let row = width_px * 3;
    if head.len() != row * height_px || wrist.len() != row * height_px {
        return Err(VideoError::Frame(format!(
            "camera images must both be {width_px}x{height_px} RGB (got {} and {} bytes)",
            head.len(),
            wrist.len()
        )));
    }
    let mut out = Vec::with_capacity(2 * row * height_px);
    for (h, w) in head.chunks_exact(row).zip(wrist.chunks_exact(row)) {
        out.extend_from_slice(h);
        out.extend_from_slice(w);
    }
    Ok(out)
}

/// Which of the renderer's lanes a render waits in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Lane {
    /// Observations and live frames.
    Normal,
    /// The private video: an episode's observation render never queues behind video frames.
    Background,
}

/// Head | wrist RGB of `state`, side by side: one frame of the video or of the live view.
pub fn render_head_wrist(
    renderer: &Renderer,
    model: &ModelHandle,
    state: &FrameState,
    cameras: &VideoCameras,
    lane: Lane,
) -> Result<Vec<u8>, VideoError> {
    let size = cameras.size_px;
    let requests = [
        CameraRequest::named(&cameras.head, size, size, Outputs::RGB),
        CameraRequest::named(&cameras.wrist, size, size, Outputs::RGB),
    ];
    let options = RenderOptions::default();
    let views = match lane {
        Lane::Normal => renderer.render(model, state, &requests, &options),
        Lane::Background => renderer.render_background(model, state, &requests, &options),
    }
    .map_err(|e| VideoError::Render(e.to_string()))?;
    match views.as_slice() {
        [head, wrist] => side_by_side(&head.rgb, &wrist.rgb, size as usize, size as usize),
        other => Err(VideoError::Render(format!("expected 2 camera images, got {}", other.len()))),
    }
}

/// The cameras a video frame shows, at `size_px` square each.
#[derive(Debug, Clone)]
pub struct VideoCameras {
    pub head: String,
    pub wrist: String,
    pub size_px: u32,
}

/// The recorder thread's side: a bounded queue of pose snapshots. Dropping it (or calling
/// [`finish`](Self::finish)) drains the queue and finalises the file.
pub struct VideoRecorder {
    tx: Option<SyncSender<Snapshot>>,
    thread: Option<JoinHandle<Result<Option<VideoSummary>, VideoError>>>,
    path: PathBuf,
    /// Set once a frame could not be queued (the recorder stopped); reported once.
    broken: bool,
}

/// One queued control step: the poses to render.
type Snapshot = FrameState;

impl VideoRecorder {
    /// Starts the recorder thread for `path` (created at the first frame). It does not feed the live view:
    /// it renders every control step in the background lane and may fall behind the simulation, which a
    /// viewer must never see (live frames come from the world's own on-demand renderer).
    pub fn spawn(path: &Path, renderer: Renderer, model: ModelHandle, cameras: VideoCameras) -> Result<Self, VideoError> {
        let size = cameras.size_px;
        let mut writer = Mp4Writer::new(path, 2 * size, size)?;
        let (tx, rx) = mpsc::sync_channel::<Snapshot>(VIDEO_QUEUE_FRAMES);
        let name = format!("video-{}", path.parent().and_then(|p| p.file_name()).map(|n| n.to_string_lossy()).unwrap_or_default());
        let thread = std::thread::Builder::new().name(name).spawn(move || {
            let mut failure = None;
            while let Ok(state) = rx.recv() {
                if failure.is_some() {
                    continue; // keep draining so the episode thread never blocks on a dead recorder
                }
                let frame = render_head_wrist(&renderer, &model, &state, &cameras, Lane::Background).and_then(|rgb| writer.push_rgb(&rgb));
                if let Err(e) = frame {
                    failure = Some(e);
                }
            }
            match failure {
                // The partial file stays under its temporary name: incomplete, and visibly so.
                Some(e) => Err(e),
                None => writer.finish(),
            }
        })?;
        Ok(Self { tx: Some(tx), thread: Some(thread), path: path.to_owned(), broken: false })
    }

    /// Queues one frame; waits when the encoder is [`VIDEO_QUEUE_FRAMES`] behind.
    pub fn record(&mut self, state: FrameState) {
        let Some(tx) = &self.tx else { return };
        if tx.send(state).is_err() && !self.broken {
            self.broken = true;
            log::error!("video {}: the recorder thread has stopped; later frames are lost", self.path.display());
        }
    }

    /// A simulation hook that records every control step into this video.
    pub fn into_step_observer(mut self) -> StepObserver {
        Box::new(move |model: &MjModel, data: &SimData, _: &[f64]| self.record(FrameState::from_mujoco(model, data)))
    }

    /// Drains the queue, finalises the MP4 and renames it into place.
    pub fn finish(&mut self) -> Result<Option<VideoSummary>, VideoError> {
        self.tx = None;
        match self.thread.take() {
            None => Ok(None),
            Some(t) => t.join().map_err(|_| VideoError::Thread("the recorder thread panicked".into()))?,
        }
    }
}

impl Drop for VideoRecorder {
    fn drop(&mut self) {
        match self.finish() {
            Ok(Some(v)) => log::info!("video {}: {} frames, {:.2} s", v.path.display(), v.frames, v.duration_s),
            Ok(None) => {}
            Err(e) => log::error!("video {}: {e}", self.path.display()),
        }
    }
}

/// Renders the private video at `video` from the state record at `record` (see [`crate::state_record`]): one
/// frame per recorded control step, drawn from the poses [`PoseReplay`] recomputes, which are bit for bit the
/// poses the episode stepped through, so the frames are those a recorder rendering during the episode makes.
/// `progress(done, total)` hears every frame and stops the work by returning `false`.
pub fn render_video_from_record(
    record: &Path,
    video: &Path,
    model: &std::sync::Arc<MjModel>,
    renderer: &Renderer,
    gpu_model: &ModelHandle,
    cameras: &VideoCameras,
    mut progress: impl FnMut(u64, u64) -> bool,
) -> Result<Option<VideoSummary>, VideoError> {
    let mut reader = StateRecordReader::open(record).map_err(|e| VideoError::Source(e.to_string()))?;
    let mut poses = PoseReplay::new(model.clone());
    if poses.sizes() != (reader.nq, reader.nmocap) {
        return Err(VideoError::Source(format!(
            "{} records {} qpos and {} mocap bodies; the model has {:?}",
            record.display(),
            reader.nq,
            reader.nmocap,
            poses.sizes()
        )));
    }
    let size = cameras.size_px;
    let mut writer = Mp4Writer::new(video, 2 * size, size)?;
    let total = reader.frames();
    while let Some((qpos, mocap)) = reader.next_frame().map_err(|e| VideoError::Source(e.to_string()))? {
        if !progress(writer.frames(), total) {
            return Err(VideoError::Stopped);
        }
        let data = poses.pose(&qpos, &mocap).map_err(|e| VideoError::Source(e.to_string()))?;
        let state = FrameState::from_mujoco(model, data);
        writer.push_rgb(&render_head_wrist(renderer, gpu_model, &state, cameras, Lane::Background)?)?;
    }
    progress(writer.frames(), total);
    writer.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn side_by_side_puts_head_left_and_wrist_right_row_by_row() {
        let head = vec![1u8; 2 * 2 * 3];
        let wrist = vec![2u8; 2 * 2 * 3];
        let out = side_by_side(&head, &wrist, 2, 2).unwrap();
        assert_eq!(out, [[1u8; 6], [2u8; 6], [1u8; 6], [2u8; 6]].concat());
        assert!(side_by_side(&head, &wrist[..6], 2, 2).is_err());
    }

    #[test]
    fn odd_sizes_and_wrong_frame_lengths_are_rejected() {
        let dir = tempfile::tempdir().unwrap();
        assert!(Mp4Writer::new(&dir.path().join("v.mp4"), 511, 256).is_err());
        let mut w = Mp4Writer::new(&dir.path().join("v.mp4"), 4, 2).unwrap();
        assert!(w.push_rgb(&[0u8; 10]).is_err());
    }

    #[test]
    fn a_writer_without_frames_leaves_no_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.mp4");
        let w = Mp4Writer::new(&path, 512, 256).unwrap();
        assert_eq!(w.finish().unwrap(), None);
        assert!(!path.exists() && !partial_path(&path).exists());
    }

    #[test]
    fn the_file_keeps_its_temporary_name_until_finished() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.mp4");
        let mut w = Mp4Writer::new(&path, 64, 32).unwrap();
        for i in 0..30u8 {
            let rgb: Vec<u8> = (0..64 * 32 * 3).map(|k| (k as u8).wrapping_add(i * 7)).collect();
            w.push_rgb(&rgb).unwrap();
        }
        assert!(partial_path(&path).exists() && !path.exists());
        let summary = w.finish().unwrap().unwrap();
        assert!(path.is_file() && !partial_path(&path).exists());
        assert_eq!(summary.frames, 30);
        assert!((summary.duration_s - 1.5).abs() < 1e-9, "30 frames at 20 fps: {}", summary.duration_s);
    }
}
