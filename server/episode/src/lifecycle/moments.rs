//! Moments of an episode rendered on demand from its recorded state (issue 49): the review shows any control step
//! of an episode that has no private video (`--no-video`, a sweep, a batch run without video) or whose video is
//! not rendered yet. The episode's executed actions (a branch's replayed prefix first) are replayed once on its
//! task, seed, init state and layout, which by the determinism contract passes through the episode's states bit
//! for bit; each control step's poses are kept (about 1 kB a step), and a moment is those poses drawn with the
//! video's renderer and cameras (head | wrist, [`head_wrist_cameras`]), so it is the frame the video would show.
//!
//! One replayed episode is kept at a time (its model and the renderer's upload are large) and let go after
//! [`SCENE_IDLE`] without a request; rendered moments are cached (at most [`MAX_CACHED_MOMENTS`]).
use std::collections::{HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use libero_render::{FrameState, ModelHandle, Renderer};
use libero_sim::PoseReplay;
use libero_sim::mujoco_rs::prelude::MjModel;
use thiserror::Error;

use super::EpisodeSet;
use super::prepare::spec_from_record;
use crate::RunDir;
use crate::actor::World;
use crate::demo::SourceEpisode;
use crate::live::encode_jpeg;
use crate::video::{Lane, render_head_wrist};
use crate::world::{LiberoWorld, head_wrist_cameras};

/// How long a replayed episode is kept after its last moment was asked for.
pub const SCENE_IDLE: Duration = Duration::from_secs(300);
/// Rendered moments kept (about 30 kB each).
pub const MAX_CACHED_MOMENTS: usize = 600;

/// One moment: head | wrist of the state after `control_step`, as a JPEG.
#[derive(Debug, Clone)]
pub struct Moment {
    pub control_step: u64,
    /// Control steps the episode executed (moments exist for 0..=this).
    pub control_steps: u64,
    pub width_px: u32,
    pub height_px: u32,
    pub jpeg: Arc<[u8]>,
}

#[derive(Debug, Error)]
pub enum MomentError {
    #[error("control step {step} is past the episode's last ({steps} control steps were executed)")]
    OutOfRange { step: u64, steps: u64 },
    #[error("the episode cannot be replayed: {0}")]
    NotReplayable(String),
    #[error("the moment could not be rendered: {0}")]
    Render(String),
}

/// An episode replayed once: its model, the renderer's upload and each control step's poses.
struct ReplayedEpisode {
    run: PathBuf,
    model: Arc<MjModel>,
    renderer: Renderer,
    gpu_model: ModelHandle,
    /// `(pose qpos, mocap poses)` of control step c at index c (0 = the settled start).
    poses: Vec<(Vec<f64>, Vec<f64>)>,
}

impl ReplayedEpisode {
    fn control_steps(&self) -> u64 {
        self.poses.len().saturating_sub(1) as u64
    }

    fn render(&self, control_step: u64) -> Result<Moment, MomentError> {
        let (qpos, mocap) = self.poses.get(control_step as usize).ok_or(MomentError::OutOfRange { step: control_step, steps: self.control_steps() })?;
        let mut poses = PoseReplay::new(self.model.clone());
        let data = poses.pose(qpos, mocap).map_err(|e| MomentError::Render(e.to_string()))?;
        let state = FrameState::from_mujoco(&self.model, data);
        let cameras = head_wrist_cameras();
        let rgb = render_head_wrist(&self.renderer, &self.gpu_model, &state, &cameras, Lane::Normal).map_err(|e| MomentError::Render(e.to_string()))?;
        let (width_px, height_px) = (2 * cameras.size_px, cameras.size_px);
        let jpeg = encode_jpeg(&rgb, width_px, height_px).map_err(MomentError::Render)?;
        Ok(Moment { control_step, control_steps: self.control_steps(), width_px, height_px, jpeg: jpeg.into() })
    }
}

/// The one replayed episode, the rendered moments and the lock that keeps two replays from running at once.
#[derive(Default)]
pub(super) struct MomentCache {
    scene: Mutex<Option<(Arc<ReplayedEpisode>, Instant)>>,
    replaying: Mutex<()>,
    moments: Mutex<MomentLru>,
}

/// Rendered moments by (run directory, control step), oldest first out.
#[derive(Default)]
struct MomentLru {
    map: HashMap<(PathBuf, u64), Moment>,
    order: VecDeque<(PathBuf, u64)>,
}

impl MomentLru {
    fn get(&self, key: &(PathBuf, u64)) -> Option<Moment> {
        self.map.get(key).cloned()
    }

    fn put(&mut self, key: (PathBuf, u64), moment: Moment) {
        if self.map.insert(key.clone(), moment).is_none() {
            self.order.push_back(key);
        }
        while self.order.len() > MAX_CACHED_MOMENTS {
            if let Some(old) = self.order.pop_front() {
                self.map.remove(&old);
            }
        }
    }
}

impl EpisodeSet {
    /// Head | wrist of the state after `control_step` of the episode in `run`, rendered from its recorded actions
    /// (see the module's doc). The first moment of an episode replays it (seconds for a long one); later ones
    /// render one frame, or come from the cache. Blocking: call off the async runtime.
    pub fn moment(&self, run: &RunDir, control_step: u64) -> Result<Moment, MomentError> {
        let key = (run.root.clone(), control_step);
        if let Some(m) = self.moments.moments.lock().ok().and_then(|c| c.get(&key)) {
            return Ok(m);
        }
        let scene = self.replayed(run, control_step)?;
        let moment = scene.render(control_step)?;
        if let Ok(mut cache) = self.moments.moments.lock() {
            cache.put(key, moment.clone());
        }
        Ok(moment)
    }

    /// The replayed episode of `run` holding `control_step`: the kept one, or a new replay (of the whole action log
    /// as it stands, so a running episode's newer steps are replayed again when asked for).
    fn replayed(&self, run: &RunDir, control_step: u64) -> Result<Arc<ReplayedEpisode>, MomentError> {
        let kept = || -> Option<Arc<ReplayedEpisode>> {
            let mut slot = self.moments.scene.lock().ok()?;
            let (scene, used) = slot.as_mut()?;
            (scene.run == run.root && control_step <= scene.control_steps()).then(|| {
                *used = Instant::now();
                scene.clone()
            })
        };
        if let Some(scene) = kept() {
            return Ok(scene);
        }
        // An ended episode's action log does not grow: a step past the kept replay is past the episode.
        if let Some(steps) = self.kept_steps(run).filter(|_| libero_records::records::read_result(run).is_some()) {
            return Err(MomentError::OutOfRange { step: control_step, steps });
        }
        let _one_replay = self.moments.replaying.lock().map_err(|_| MomentError::Render("replay lock poisoned".into()))?;
        if let Some(scene) = kept() {
            return Ok(scene);
        }
        // Let the kept episode go before building another: two scenes' uploads at once are what the cap avoids.
        if let Ok(mut slot) = self.moments.scene.lock() {
            *slot = None;
        }
        let scene = Arc::new(self.replay(run)?);
        crate::memory::return_freed_memory();
        if control_step > scene.control_steps() {
            return Err(MomentError::OutOfRange { step: control_step, steps: scene.control_steps() });
        }
        if let Ok(mut slot) = self.moments.scene.lock() {
            *slot = Some((scene.clone(), Instant::now()));
        }
        self.let_go_when_idle(&scene);
        Ok(scene)
    }

    /// The control steps of the kept replay when it is `run`'s.
    fn kept_steps(&self, run: &RunDir) -> Option<u64> {
        let slot = self.moments.scene.lock().ok()?;
        slot.as_ref().filter(|(scene, _)| scene.run == run.root).map(|(scene, _)| scene.control_steps())
    }

    /// Replays the episode in `run`, keeping every control step's poses.
    fn replay(&self, run: &RunDir) -> Result<ReplayedEpisode, MomentError> {
        let not_replayable = |e: String| MomentError::NotReplayable(e);
        let paths = self.asset_paths().cloned().ok_or_else(|| not_replayable("the assets are missing; run `python3 scripts/setup.py`".into()))?;
        let source = SourceEpisode::read(run).map_err(|e| not_replayable(e.to_string()))?;
        let mut spec = spec_from_record(&run.episode_record(), paths).map_err(|e| not_replayable(format!("{e:#}")))?;
        spec.init_index = source.init_state_index;
        let renderer = self.renderer().map_err(|e| MomentError::Render(format!("{e:#}")))?;
        let mut world = LiberoWorld::new(&spec, renderer).map_err(|e| not_replayable(e.to_string()))?;
        let recorded: Arc<Mutex<Vec<(Vec<f64>, Vec<f64>)>>> = Arc::default();
        let sink = recorded.clone();
        world.observe_poses(Box::new(move |qpos: &[f64], mocap: Vec<f64>| {
            if let Ok(mut poses) = sink.lock() {
                poses.push((qpos.to_vec(), mocap));
            }
        }));
        let actions: Vec<[f64; 7]> = source.actions.iter().map(|(_, a)| *a).collect();
        let steps = actions.len();
        world.set_start_prefix(actions);
        world.start().map_err(|e| not_replayable(format!("the replay stopped: {e}")))?;
        let (model, renderer, gpu_model) = world.video_models();
        drop(world);
        let mut poses = std::mem::take(&mut *recorded.lock().map_err(|_| MomentError::Render("poses lock poisoned".into()))?);
        // Settle steps first, then one per action: control step 0 is the last settle step.
        let Some(start) = poses.len().checked_sub(steps + 1) else {
            return Err(not_replayable(format!("{} poses recorded for {steps} actions", poses.len())));
        };
        poses.drain(..start);
        Ok(ReplayedEpisode { run: run.root.clone(), model, renderer, gpu_model, poses })
    }

    /// Drops the kept replay of `scene` once nobody asked for one of its moments for [`SCENE_IDLE`].
    fn let_go_when_idle(&self, scene: &Arc<ReplayedEpisode>) {
        let weak = Arc::downgrade(scene);
        let slot = Arc::downgrade(&self.moments);
        let spawned = std::thread::Builder::new().name("review-replay-idle".into()).spawn(move || {
            loop {
                std::thread::sleep(SCENE_IDLE / 4);
                let Some(slot) = slot.upgrade() else { return };
                let Ok(mut slot) = slot.scene.lock() else { return };
                let Some((kept, used)) = slot.as_ref() else { return };
                if !weak.upgrade().is_some_and(|s| Arc::ptr_eq(&s, kept)) {
                    return; // replaced by another episode's replay
                }
                if used.elapsed() >= SCENE_IDLE {
                    *slot = None;
                    drop(slot);
                    crate::memory::return_freed_memory();
                    return;
                }
            }
        });
        if let Err(e) = spawned {
            tracing::warn!("cannot start the review replay's idle timer: {e}; it is kept until replaced");
        }
    }
}
