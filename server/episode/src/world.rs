//! The LIBERO world an episode runs on: the BDDL scene composed and compiled by `libero-sim`, LIBERO's
//! seeded reset placement, the trusted init state, the real MuJoCo simulation under robosuite's OSC_POSE,
//! both cameras rendered by `libero-render`, and the task's private evaluator (`libero-tasks`), reset after
//! settling and fed every control step (and every physics substep where the evaluator samples them).
use std::sync::Arc;

use libero_render::{CameraRequest, FrameState, ModelHandle, Outputs, RenderOptions, Renderer};
use libero_sim::compose::{ComposedScene, compose_file};
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::placement::{Placement, TurnOnSites, update_visual_sites};
use libero_sim::{AssetPaths, InitStates, Simulation};
use libero_tasks::{Evaluator, Tick, build_evaluator};

use crate::EpisodeError;
use crate::actor::{Verdict, World};
use crate::call::MicroAction;
use crate::live::{LiveSink, WorldTap};
use crate::observation::{CameraFrame, Frame, Level, RgbImage};
use crate::readout::{BasePose, robot_base_body, robot_readout};
use crate::task::TaskSource;
use crate::video::{VideoCameras, VideoRecorder};

/// Release image size (square, per camera).
pub const RESOLUTION_PX: u32 = 256;
/// Zero actions run after restoring the init state, before the first observation (§4.2).
pub const SETTLE_STEPS: usize = 10;
/// robosuite camera names of the published `head` and `wrist` views.
pub const HEAD_CAMERA: &str = "agentview";
pub const WRIST_CAMERA: &str = "robot0_eye_in_hand";

/// What to build.
#[derive(Debug, Clone)]
pub struct WorldSpec {
    pub task: TaskSource,
    pub level: Level,
    pub seed: u64,
    pub init_index: usize,
    pub paths: AssetPaths,
}

pub struct LiberoWorld {
    sim: Simulation,
    /// `[time, qpos, qvel]` restored at start: the trusted init state, or the seeded placement's state.
    start_row: Vec<f64>,
    renderer: Renderer,
    gpu_model: ModelHandle,
    base_body: usize,
    level: Level,
    evaluator: Box<dyn Evaluator>,
    /// Control steps since the evaluator reset.
    control_step: u64,
    /// LIBERO's per-step stove-burner visibility, applied to every rendered frame.
    toggles: VisualToggles,
    /// The operator's live view and telemetry (see [`LiberoWorld::set_live`]); `None` costs nothing.
    live: Option<WorldTap>,
}

/// LIBERO's `_post_process` after every control step ([`TurnOnSites`]: the stove's burner ring shows iff it is
/// on). The model is shared read-only, so the world keeps the site colours and hands them to the renderer with
/// each frame. An image shows the colours from before the latest step's toggle, as LIBERO renders the
/// observation first (port notes §4.3).
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
        let scene = compose_file(&spec.task.bddl, &spec.paths)?;
        let mut model = scene.compile()?;
        let suite = spec.task.suite.as_ref();
        let seed = match suite.and_then(|s| s.placement_seed) {
            Some(fixed) => fixed,
            None => u32::try_from(spec.seed).map_err(|_| EpisodeError::Task("seed must fit in 32 bits".into()))?,
        };
        let placement = Placement::sample(&scene, seed, Some(&model))?;
        placement.apply(&mut model)?;
        let evaluator = build_evaluator(suite.map(|s| &s.checker), suite.map(|s| s.id.as_str()), &scene, &model)
            .map_err(|e| EpisodeError::Evaluator(e.to_string()))?;
        let init_index = suite.map_or(spec.init_index, |s| s.init_index);
        let init_row = match &spec.task.init_states {
            Some(path) => Some(InitStates::read(path)?.get(init_index)?.to_vec()),
            None => None,
        };
        observation_site_visibility(&scene, &mut model, init_row.as_deref(), &placement)?;
        let model = Arc::new(model);
        let sim = Simulation::new(model.clone())?;
        let start_row = match init_row {
            Some(row) => row,
            None => placement_row(&sim, &placement)?,
        };
        let base_body = robot_base_body(&sim)?;
        let gpu_model = renderer.prepare_model(&model).map_err(|e| EpisodeError::Render(e.to_string()))?;
        let toggles = VisualToggles::new(&scene, &model)?;
        Ok(Self {
            sim,
            start_row,
            renderer,
            gpu_model,
            base_body,
            level: spec.level,
            evaluator,
            control_step: 0,
            toggles,
            live: None,
        })
    }

    /// Whether the next image shows a turned-on fixture's visual site (the stove's burner ring).
    pub fn burner_shown(&self) -> bool {
        self.toggles.any_shown()
    }

    pub fn simulation(&self) -> &Simulation {
        &self.sim
    }

    /// Test hook: edits the `[time, qpos, qvel]` row restored at start (used to provoke a MuJoCo fault).
    #[doc(hidden)]
    pub fn edit_start_state(&mut self, edit: impl FnOnce(&mut [f64])) {
        edit(&mut self.start_row);
    }

    /// Test hook: edits the current `[time, qpos, qvel]` row (LIBERO's `set_init_state`, so derived quantities are
    /// recomputed), e.g. to put a fixture joint past its goal threshold.
    #[doc(hidden)]
    pub fn edit_current_state(&mut self, edit: impl FnOnce(&mut [f64])) -> Result<(), EpisodeError> {
        let mut row = self.sim.state_row();
        edit(&mut row);
        self.sim.set_init_state(&row)?;
        Ok(())
    }

    fn tick(&self, substep: Option<u32>) -> Tick {
        Tick { control_step: self.control_step, substep, sim_time_s: self.sim.time_s() }
    }

    fn render(&self) -> Result<(CameraFrame, CameraFrame), EpisodeError> {
        let outputs = if self.level >= Level::L3 { Outputs::RGB_DEPTH } else { Outputs::RGB };
        let requests = [
            CameraRequest::named(HEAD_CAMERA, RESOLUTION_PX, RESOLUTION_PX, outputs),
            CameraRequest::named(WRIST_CAMERA, RESOLUTION_PX, RESOLUTION_PX, outputs),
        ];
        let mut state = FrameState::from_mujoco(self.sim.model(), self.sim.data());
        self.toggles.apply(&mut state);
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

/// What robosuite's reset does to sites before the first image: hide robot, gripper and object sites in
/// observation images, then LIBERO's `set_visualization` shows a stove burner only if its knob starts on.
fn observation_site_visibility(
    scene: &ComposedScene,
    model: &mut MjModel,
    init_row: Option<&[f64]>,
    placement: &Placement,
) -> Result<(), EpisodeError> {
    libero_render::scene::robosuite_hide_sites(model);
    let nq = model.ffi().nq as usize;
    let qpos = match init_row {
        Some(row) => row
            .get(1..1 + nq)
            .ok_or_else(|| EpisodeError::Task(format!("init state has {} values, the model needs 1 + nq = {}+", row.len(), 1 + nq)))?
            .to_vec(),
        None => {
            let mut qpos = model.qpos0().to_vec();
            placement.write_qpos(model, &mut qpos)?;
            qpos
        }
    };
    update_visual_sites(scene, model, &qpos)?;
    Ok(())
}

/// The state row of the seeded placement, for tasks without trusted init states: the objects' free joints
/// and articulated fixture joints as LIBERO's reset writes them.
fn placement_row(sim: &Simulation, placement: &Placement) -> Result<Vec<f64>, EpisodeError> {
    let model = sim.model();
    let adr = model.jnt_qposadr();
    let joint = |name: &str| {
        model
            .name_to_id(MjtObjBase::mjOBJ_JOINT, name)
            .map(|j| 1 + adr[j] as usize)
            .ok_or_else(|| EpisodeError::Task(format!("model has no joint {name:?}")))
    };
    let mut row = sim.state_row();
    for o in &placement.objects {
        let a = joint(&o.joint)?;
        row[a..a + 7].copy_from_slice(&o.qpos);
    }
    for (name, q) in &placement.joint_qpos {
        row[joint(name)?] = *q;
    }
    Ok(row)
}

impl World for LiberoWorld {
    fn start(&mut self) -> Result<(), EpisodeError> {
        self.sim.set_init_state(&self.start_row)?;
        self.toggles.reset();
        for _ in 0..SETTLE_STEPS {
            self.sim.step([0.0; 7])?;
            self.toggles.after_step(self.sim.data().qpos());
        }
        self.control_step = 0;
        self.evaluator.reset(self.sim.data(), self.tick(None));
        self.report_live();
        Ok(())
    }

    fn step(&mut self, action: &MicroAction) -> Result<(), EpisodeError> {
        let step = self.control_step + 1;
        if self.evaluator.samples_substeps() {
            let evaluator = &mut self.evaluator;
            self.sim.step_with(*action, |k, data| {
                let tick = Tick { control_step: step, substep: Some(k as u32), sim_time_s: data.ffi().time };
                evaluator.observe_substep(data, tick);
            })?;
        } else {
            self.sim.step(*action)?;
        }
        self.control_step = step;
        self.toggles.after_step(self.sim.data().qpos());
        self.evaluator.observe_control_step(self.sim.data(), self.tick(None));
        self.report_live();
        Ok(())
    }

    fn frame(&mut self, frame_index: u64) -> Result<Frame, EpisodeError> {
        let base = BasePose::of(&self.sim, self.base_body);
        let robot = robot_readout(&self.sim, &base);
        let (head, wrist) = self.render()?;
        Ok(Frame { frame_index, robot, head, wrist, task_reference: None })
    }

    fn verdict(&mut self) -> Result<Verdict, EpisodeError> {
        let record = self.evaluator.finish(self.sim.data(), self.tick(None));
        let to_json = |e: serde_json::Error| EpisodeError::Evaluator(format!("evaluation record: {e}"));
        let stage_events =
            record.stage_events.iter().map(serde_json::to_value).collect::<Result<Vec<_>, _>>().map_err(to_json)?;
        let private_evaluation = serde_json::to_value(&record).map_err(to_json)?;
        Ok(Verdict { success: record.success, private_evaluation, stage_events })
    }
}

/// The private video hook, apart from the protocol methods: the simulation reports every control step
/// (settle steps included) to a recorder thread that renders and encodes off the reply path.
impl LiberoWorld {
    /// Records every later control step into `path` (§6.1). The video is finalised and renamed into
    /// place when the world is dropped (episode finished, expired or aborted) or at [`Self::end_video`].
    pub fn record_video(&mut self, path: &std::path::Path) -> Result<(), EpisodeError> {
        let cameras = VideoCameras { head: HEAD_CAMERA.into(), wrist: WRIST_CAMERA.into(), size_px: RESOLUTION_PX };
        let tap = self.live.as_ref().map(WorldTap::frame_tap);
        let counter = self.live.as_ref().map(WorldTap::frame_counter);
        let recorder = VideoRecorder::spawn_with_tap(path, self.renderer.clone(), self.gpu_model.clone(), cameras, tap)
            .map_err(|e| EpisodeError::Render(e.to_string()))?;
        let mut observe = recorder.into_step_observer();
        match counter {
            None => self.sim.set_step_observer(Some(observe)),
            Some(counter) => self.sim.set_step_observer(Some(Box::new(move |model: &MjModel, data: &libero_sim::SimData| {
                observe(model, data);
                counter.fetch_add(1, std::sync::atomic::Ordering::AcqRel);
            }))),
        }
        Ok(())
    }

    /// Stops recording and finalises the video now (waits for the encoder to drain).
    pub fn end_video(&mut self) {
        self.sim.set_step_observer(None);
    }
}

/// The operator's live view, apart from the protocol methods: step and private stage events to a sink, and
/// `telemetry.jsonl` (end-effector position, gripper, wrist force per control step) for the review page.
impl LiberoWorld {
    /// Sends this world's live events to `sink` and writes `telemetry` (the run directory's
    /// `telemetry.jsonl`). Call before [`Self::record_video`], whose frames then feed the live view too.
    pub fn set_live(&mut self, sink: LiveSink, telemetry: Option<&std::path::Path>) -> Result<(), EpisodeError> {
        self.live = Some(WorldTap::new(sink, telemetry)?);
        Ok(())
    }

    fn report_live(&mut self) {
        let Some(tap) = self.live.as_mut() else { return };
        let robot = robot_readout(&self.sim, &BasePose::of(&self.sim, self.base_body));
        let (events, progress) = (self.evaluator.private_events(), self.evaluator.stage_progress());
        if self.control_step == 0 {
            tap.on_reset(&robot, events, progress);
        } else {
            tap.after_step(self.control_step, &robot, events, progress);
        }
    }
}
