//! The LIBERO world an episode runs on: the BDDL scene composed and compiled by `libero-sim`, LIBERO's
//! seeded reset placement, the trusted init state, the real MuJoCo simulation under robosuite's OSC_POSE,
//! both cameras rendered by `libero-render`, and the task's private evaluator (`libero-tasks`), reset after
//! settling and fed every control step (and every physics substep where the evaluator samples them).
use libero_render::{CameraRequest, FrameState, ModelHandle, Outputs, RenderOptions, Renderer};
use libero_sim::Simulation;
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::placement::{TurnOnSites, update_visual_sites};

use crate::EpisodeError;
use crate::actor::{Verdict, World};
use crate::call::MicroAction;
use crate::live::{LiveRenderer, LiveSink, LiveState, LiveViewers, WorldTap};
use crate::observation::{CameraFrame, Frame, Level, RgbImage};
pub use crate::physics::{SETTLE_STEPS, WorldSpec};
use crate::physics::WorldPhysics;
use crate::readout::{BasePose, robot_base_body, robot_readout};
use crate::state_record::StateRecordWriter;
use crate::video::VideoCameras;
use crate::video_queue::{VideoJob, VideoQueue};

/// Release image size (square, per camera).
pub const RESOLUTION_PX: u32 = 256;
/// robosuite camera names of the published `head` and `wrist` views.
pub const HEAD_CAMERA: &str = "agentview";
pub const WRIST_CAMERA: &str = "robot0_eye_in_hand";

pub struct LiberoWorld {
    physics: WorldPhysics,
    /// What the world was built from: the live view's preview of the start state forks its physics with it.
    spec: WorldSpec,
    /// A branch's replayed prefix: the parent episode's first actions, run by [`World::start`] after settling,
    /// the evaluator observing them (see [`LiberoWorld::set_start_prefix`]). Empty for an ordinary episode.
    start_prefix: Vec<MicroAction>,
    renderer: Renderer,
    gpu_model: ModelHandle,
    base_body: usize,
    level: Level,
    /// LIBERO's per-step stove-burner visibility, applied to every rendered frame.
    toggles: VisualToggles,
    /// The operator's live view and telemetry (see [`LiberoWorld::set_live`]); `None` costs nothing.
    live: Option<WorldTap>,
    /// Renders the newest state for the live view while someone watches (see [`LiberoWorld::set_live`]).
    live_frames: Option<LiveRenderer>,
    /// The task's reference image, published with every frame (protocol §3.9).
    task_reference: Option<RgbImage>,
    /// The private video being recorded (see [`LiberoWorld::record_video`]).
    video: Option<PendingVideo>,
}

/// LIBERO's `_post_process` after every control step ([`TurnOnSites`]: the stove's burner ring shows iff it is
/// on). The model is shared read-only, so the world keeps the site colours and hands them to the renderer with
/// each frame. An image shows the colours from before the latest step's toggle, as LIBERO renders the
/// observation first (port notes §4.3).
#[derive(Clone)]
struct VisualToggles {
    sites: TurnOnSites,
    /// `site_rgba` after `set_init_state`'s toggle.
    initial: Vec<[f32; 4]>,
    current: Vec<[f32; 4]>,
    shown: Vec<[f32; 4]>,
}

impl VisualToggles {
    fn new(scene: &ComposedScene, model: &MjModel) -> Result<Self, EpisodeError> {
        let initial = model.site_rgba().to_vec();
        Ok(Self { sites: TurnOnSites::new(scene, model)?, current: initial.clone(), shown: initial.clone(), initial })
    }

    fn reset(&mut self) {
        self.current.clone_from(&self.initial);
        self.shown.clone_from(&self.initial);
    }

    /// After a control step: the frame keeps the colours it was rendered with, then the toggle runs.
    fn after_step(&mut self, qpos: &[f64]) {
        self.shown.clone_from(&self.current);
        self.sites.toggle(qpos, &mut self.current);
    }

    fn apply(&self, state: &mut FrameState) {
        for id in self.sites.site_ids() {
            if let (Some(rgba), Some(shown)) = (state.site_rgba.get_mut(id), self.shown.get(id)) {
                rgba[3] = shown[3];
            }
        }
    }

    /// Whether any turn-on visual site is visible in the next image.
    fn any_shown(&self) -> bool {
        self.sites.site_ids().any(|id| self.shown.get(id).is_some_and(|c| c[3] > 0.0))
    }
}

impl LiberoWorld {
    /// Composes, compiles and places the scene; reads the init state; uploads the model to the renderer.
    pub fn new(spec: &WorldSpec, renderer: Renderer) -> Result<Self, EpisodeError> {
        let physics = WorldPhysics::build(spec, observation_site_visibility)?;
        let base_body = robot_base_body(&physics.sim)?;
        let model = physics.model().clone();
        let gpu_model = renderer.prepare_model(&model).map_err(|e| EpisodeError::Render(e.to_string()))?;
        let toggles = VisualToggles::new(&physics.scene, &model)?;
        let task_reference = spec.task.task_reference.as_deref().map(RgbImage::read_png).transpose()?;
        Ok(Self {
            physics,
            spec: spec.clone(),
            start_prefix: Vec::new(),
            renderer,
            gpu_model,
            base_body,
            level: spec.level,
            toggles,
            live: None,
            live_frames: None,
            task_reference,
            video: None,
        })
    }

    /// Makes this world a branch of another episode: [`World::start`] settles as usual, then replays `actions`
    /// (the parent's first control steps) with the evaluator observing them, so the start state is the parent's
    /// state after them, bit for bit, with the stages it had reached. Call before [`Self::set_live`] and
    /// [`Self::record_video`] (the preview and the video then show the branch's start).
    pub fn set_start_prefix(&mut self, actions: Vec<MicroAction>) {
        self.start_prefix = actions;
    }

    /// The state [`World::start`] will leave (settled, branch prefix replayed) and its sim time, for the live view
    /// before the start: the same start run on a fork of this world's physics (its model, fresh state), so it is
    /// that state bit for bit (the determinism contract) and the episode's own simulation is not touched.
    fn start_preview(&self) -> Result<(FrameState, f64), EpisodeError> {
        let mut twin = self.physics.fork(&self.spec)?;
        let mut toggles = self.toggles.clone();
        toggles.reset();
        twin.start(|sim| toggles.after_step(sim.data().qpos()))?;
        for action in &self.start_prefix {
            twin.step(action)?;
            toggles.after_step(twin.sim.data().qpos());
        }
        Ok((frame_state_of(&twin, &toggles), twin.sim.time_s()))
    }

    /// Whether the next image shows a turned-on fixture's visual site (the stove's burner ring).
    pub fn burner_shown(&self) -> bool {
        self.toggles.any_shown()
    }

    pub fn simulation(&self) -> &Simulation {
        &self.physics.sim
    }

    /// Test hook: edits the `[time, qpos, qvel]` row restored at start (used to provoke a MuJoCo fault).
    #[doc(hidden)]
    pub fn edit_start_state(&mut self, edit: impl FnOnce(&mut [f64])) {
        edit(&mut self.physics.start_row);
    }

    /// Test hook: edits the current `[time, qpos, qvel]` row (LIBERO's `set_init_state`, so derived quantities are
    /// recomputed), e.g. to put a fixture joint past its goal threshold.
    #[doc(hidden)]
    pub fn edit_current_state(&mut self, edit: impl FnOnce(&mut [f64])) -> Result<(), EpisodeError> {
        let mut row = self.physics.sim.state_row();
        edit(&mut row);
        self.physics.sim.set_init_state(&row)?;
        Ok(())
    }

    /// The poses and colours an image of the current state shows (burner rings, evaluator highlights).
    fn frame_state(&self) -> FrameState {
        frame_state_of(&self.physics, &self.toggles)
    }

    fn render(&self) -> Result<(CameraFrame, CameraFrame), EpisodeError> {
        let outputs = if self.level >= Level::L3 { Outputs::RGB_DEPTH } else { Outputs::RGB };
        let requests = [
            CameraRequest::named(HEAD_CAMERA, RESOLUTION_PX, RESOLUTION_PX, outputs),
            CameraRequest::named(WRIST_CAMERA, RESOLUTION_PX, RESOLUTION_PX, outputs),
        ];
        let state = self.frame_state();
        let mut frames = self
            .renderer
            .render(&self.gpu_model, &state, &requests, &RenderOptions::default())
            .map_err(|e| EpisodeError::Render(e.to_string()))?
            .into_iter()
            .map(|f| {
                let t = f.calibration.T_robot_base_from_camera.ok_or_else(|| {
                    EpisodeError::Render("the model has no robot0_base body for camera extrinsics".into())
                })?;
                Ok(CameraFrame {
                    image: RgbImage { width: f.width, height: f.height, rgb: f.rgb },
                    depth_m: f.depth_m,
                    depth_valid: f.depth_valid,
                    intrinsic_matrix_3x3: f.calibration.K,
                    t_robot_base_from_camera: t,
                })
            })
            .collect::<Result<Vec<_>, EpisodeError>>()?;
        if frames.len() != 2 {
            return Err(EpisodeError::Render(format!("expected 2 camera frames, got {}", frames.len())));
        }
        let wrist = frames.pop().expect("length checked");
        let head = frames.pop().expect("length checked");
        Ok((head, wrist))
    }
}

/// The poses and colours an image of `physics`'s current state shows, with `toggles`' burner rings and the
/// evaluator's highlights.
fn frame_state_of(physics: &WorldPhysics, toggles: &VisualToggles) -> FrameState {
    let sim = &physics.sim;
    let mut state = FrameState::from_mujoco(sim.model(), sim.data());
    toggles.apply(&mut state);
    for (geom, rgba) in physics.evaluator.geom_rgba_overrides() {
        if let Some(slot) = state.geom_rgba.get_mut(geom) {
            *slot = rgba;
        }
    }
    state
}

/// What robosuite's reset does to sites before the first image: hide robot, gripper and object sites in
/// observation images, then LIBERO's `set_visualization` shows a stove burner only if its knob starts on.
fn observation_site_visibility(scene: &ComposedScene, model: &mut MjModel, start_qpos: &[f64]) -> Result<(), EpisodeError> {
    libero_render::scene::robosuite_hide_sites(model);
    update_visual_sites(scene, model, start_qpos)?;
    Ok(())
}

impl World for LiberoWorld {
    fn start(&mut self) -> Result<(), EpisodeError> {
        self.toggles.reset();
        let toggles = &mut self.toggles;
        self.physics.start(|sim| toggles.after_step(sim.data().qpos()))?;
        self.report_live();
        // A branch: the parent's actions up to the branch point, each an ordinary control step (evaluator, burner
        // toggles, telemetry, live events and the state record see it as the parent's episode did).
        let prefix = std::mem::take(&mut self.start_prefix);
        let replayed = prefix.iter().try_for_each(|a| self.step(a));
        self.start_prefix = prefix;
        replayed
    }

    fn step(&mut self, action: &MicroAction) -> Result<(), EpisodeError> {
        self.physics.step(action)?;
        self.toggles.after_step(self.physics.sim.data().qpos());
        self.report_live();
        Ok(())
    }

    fn frame(&mut self, frame_index: u64) -> Result<Frame, EpisodeError> {
        let base = BasePose::of(&self.physics.sim, self.base_body);
        let robot = robot_readout(&self.physics.sim, &base);
        let (head, wrist) = self.render()?;
        self.offer_observation_to_live(&head, &wrist);
        Ok(Frame { frame_index, robot, head, wrist, task_reference: self.task_reference.clone() })
    }

    fn verdict(&mut self) -> Result<Verdict, EpisodeError> {
        let record = self.physics.evaluate();
        let to_json = |e: serde_json::Error| EpisodeError::Evaluator(format!("evaluation record: {e}"));
        let stage_events =
            record.stage_events.iter().map(serde_json::to_value).collect::<Result<Vec<_>, _>>().map_err(to_json)?;
        let private_evaluation = serde_json::to_value(&record).map_err(to_json)?;
        if let Some(tap) = self.live.as_mut() {
            tap.on_verdict(&record.stage_events, (record.completed_required_stage_count, record.required_stage_count));
        }
        Ok(Verdict { success: record.success, private_evaluation, stage_events })
    }
}

/// The private video, apart from the protocol methods: the simulation reports every control step (settle steps
/// included) and the world appends its poses' `qpos` to the run directory's state record, microseconds a step.
/// When the world goes (episode finished, expired or aborted) the video is queued on the background worker,
/// which renders it from the record.
impl LiberoWorld {
    /// Records every later control step into `record` and queues `video` on `queue` when the world ends (§6.1).
    /// `rebuild` builds the video's models anew when the video has to queue behind others (see [`VideoJob::rebuild`]).
    pub fn record_video(
        &mut self,
        video: &std::path::Path,
        record: &std::path::Path,
        queue: VideoQueue,
        rebuild: Option<crate::video_queue::ModelSource>,
    ) -> Result<(), EpisodeError> {
        let counter = self.live.as_ref().map(WorldTap::frame_counter);
        let model = self.physics.model().clone();
        let nmocap = model.ffi().nmocap as usize;
        let mut writer = StateRecordWriter::create(record, model.ffi().nq as usize, nmocap)
            .map_err(|e| EpisodeError::Io(std::io::Error::other(e.to_string())))?;
        let mut failed = false;
        let observe = move |model: &MjModel, data: &libero_sim::SimData, pose_qpos: &[f64]| {
            let mocap = if nmocap == 0 { Vec::new() } else { libero_sim::pose_replay::mocap_of(model, data) };
            if let Err(e) = writer.push(pose_qpos, &mocap) {
                if !failed {
                    log::error!("{e}: later frames of the private video are lost");
                    failed = true;
                }
            }
            if let Some(c) = &counter {
                c.fetch_add(1, std::sync::atomic::Ordering::AcqRel);
            }
        };
        self.physics.sim.set_step_observer(Some(Box::new(observe)));
        self.video = Some(PendingVideo { video: video.to_owned(), record: record.to_owned(), queue, rebuild });
        Ok(())
    }

    /// Hands every later control step's poses (settle steps included) to `sink`: the `qpos` the step's poses came
    /// from and the mocap poses, what [`libero_sim::PoseReplay`] turns back into exactly those poses (the review's
    /// moments of an episode without a video are drawn from them).
    pub fn observe_poses(&mut self, mut sink: Box<dyn FnMut(&[f64], Vec<f64>) + Send>) {
        let nmocap = self.physics.model().ffi().nmocap;
        let observe = move |model: &MjModel, data: &libero_sim::SimData, pose_qpos: &[f64]| {
            let mocap = if nmocap == 0 { Vec::new() } else { libero_sim::pose_replay::mocap_of(model, data) };
            sink(pose_qpos, mocap);
        };
        self.physics.sim.set_step_observer(Some(Box::new(observe)));
    }

    /// The simulation model, the renderer and its upload of the model: what a video of this world is drawn with.
    pub fn video_models(&self) -> crate::video_queue::VideoModels {
        (self.physics.model().clone(), self.renderer.clone(), self.gpu_model.clone())
    }

    /// Stops recording and queues the video (the world's end does this too).
    pub fn end_video(&mut self) {
        // Dropping the observer drops the record's writer, which syncs it.
        self.physics.sim.set_step_observer(None);
        let Some(p) = self.video.take() else { return };
        let models = self.video_models();
        p.queue.submit(VideoJob { record: p.record, video: p.video, source: Box::new(move || Ok(models)), rebuild: p.rebuild });
    }
}

/// A video to queue when the world ends.
struct PendingVideo {
    video: std::path::PathBuf,
    record: std::path::PathBuf,
    queue: VideoQueue,
    rebuild: Option<crate::video_queue::ModelSource>,
}

impl Drop for LiberoWorld {
    fn drop(&mut self) {
        self.end_video();
    }
}

/// The cameras of the video and of live frames: head | wrist at the episode resolution.
pub fn head_wrist_cameras() -> VideoCameras {
    VideoCameras { head: HEAD_CAMERA.into(), wrist: WRIST_CAMERA.into(), size_px: RESOLUTION_PX }
}

/// The operator's live view, apart from the protocol methods: step and private stage events to a sink,
/// `telemetry.jsonl` (end-effector position, gripper, wrist force per control step) for the review page, and
/// head | wrist frames of the newest state rendered on demand while `viewers` watch.
impl LiberoWorld {
    /// Sends this world's live events to `sink`, writes `telemetry` (the run directory's `telemetry.jsonl`)
    /// and starts the live renderer, which renders only while `viewers` counts someone. Call before
    /// [`Self::record_video`] so telemetry rows name their video frames.
    pub fn set_live(&mut self, sink: LiveSink, viewers: LiveViewers, telemetry: Option<&std::path::Path>) -> Result<(), EpisodeError> {
        self.live = Some(WorldTap::new(sink.clone(), telemetry)?);
        let frames = LiveRenderer::spawn(self.renderer.clone(), self.gpu_model.clone(), head_wrist_cameras(), sink, viewers)
            .map_err(|e| EpisodeError::Render(format!("live renderer thread: {e}")))?;
        // Before the start a viewer sees the state the start will leave (settled, a branch's prefix replayed),
        // `control_step` null: never the composed scene before its init state, which lacks the placed objects.
        let (state, sim_time_s) = self.start_preview()?;
        frames.publish(LiveState { state, control_step: None, sim_time_s, video_frame: None, rendered: None });
        self.live_frames = Some(frames);
        Ok(())
    }

    /// Test hook: how many live frames this world has rendered (`None` without [`Self::set_live`]).
    #[doc(hidden)]
    pub fn live_render_counter(&self) -> Option<std::sync::Arc<std::sync::atomic::AtomicU64>> {
        self.live_frames.as_ref().map(LiveRenderer::render_counter)
    }

    /// After every control step: events and telemetry, then the state for live frames.
    fn report_live(&mut self) {
        self.report_events();
        self.publish_live_state();
    }

    fn report_events(&mut self) {
        let Some(tap) = self.live.as_mut() else { return };
        let sim = &self.physics.sim;
        let robot = robot_readout(sim, &BasePose::of(sim, self.base_body));
        let evaluator = &self.physics.evaluator;
        let (events, progress) = (evaluator.private_events(), Some(evaluator.stage_progress()));
        let control_step = self.physics.control_step;
        if control_step == 0 {
            tap.on_reset(&robot, &events, progress);
        } else {
            tap.after_step(control_step, &robot, &events, progress);
        }
    }

    /// Leaves the newest state for the live renderer: a pose snapshot, no rendering.
    fn publish_live_state(&self) {
        self.publish_live(None);
    }

    /// Hands the live view the images an observation just rendered of the newest state (the live cameras at
    /// the live size), so that a watched episode's frame after each call costs a JPEG, not another render:
    /// teleop's key-to-frame latency is one render shorter.
    fn offer_observation_to_live(&self, head: &CameraFrame, wrist: &CameraFrame) {
        let live_size = head_wrist_cameras().size_px;
        let sized = |f: &CameraFrame| f.image.width == live_size && f.image.height == live_size;
        if sized(head) && sized(wrist) {
            self.publish_live(Some((&head.image.rgb, &wrist.image.rgb)));
        }
    }

    fn publish_live(&self, rendered: Option<(&Vec<u8>, &Vec<u8>)>) {
        let (Some(frames), Some(tap)) = (self.live_frames.as_ref(), self.live.as_ref()) else { return };
        let control_step = self.physics.control_step;
        frames.publish(LiveState {
            state: self.frame_state(),
            control_step: Some(control_step),
            sim_time_s: self.physics.sim.time_s(),
            video_frame: tap.video_frame(control_step),
            rendered: rendered.map(|(head, wrist)| (head.clone(), wrist.clone())),
        });
    }
}

/// The goal image of a task with a reference (protocol §3.9): `behaviour` (the task's solving expert) plays on a
/// world built from `spec` (its reference input left out, as it is what is being made), then the head camera renders
/// the final state at the episode resolution, with the burner rings as the episode would show them. Returns the
/// image and the evaluation record of the state it shows (so a caller can check that it depicts the goal).
pub fn render_goal_image(
    spec: &WorldSpec,
    renderer: Renderer,
    task_id: &str,
    behaviour: &str,
    max_actions: u64,
) -> Result<(RgbImage, libero_tasks::EvaluationRecord), EpisodeError> {
    let mut spec = spec.clone();
    spec.task.task_reference = None;
    let mut world = LiberoWorld::new(&spec, renderer)?;
    world.start()?;
    let mut expert = libero_tasks::expert_for(task_id, behaviour, &world.physics.scene, world.physics.model())
        .map_err(|e| EpisodeError::Task(e.to_string()))?;
    for _ in 0..max_actions {
        let Some(a) = expert.act(&world.physics.sim) else { break };
        world.step(&a)?;
    }
    // one still step so the image shows the burner toggle of the final state (LIBERO renders before it toggles)
    world.step(&[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0])?;
    let record = world.physics.evaluate();
    let frame = world.frame(0)?;
    Ok((frame.head.image, record))
}
