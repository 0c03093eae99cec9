//! The physics half of a LIBERO world, without its renderer: the BDDL scene composed and compiled, LIBERO's
//! seeded reset placement, the start row (trusted init state or the seeded placement), the simulation and the
//! task's private evaluator. The episode world renders on top of it; a privileged expert steps a second copy in
//! lockstep with the episode (determinism makes the two bit-identical), so it can read simulator state while
//! acting only through `osc_sequence`.
use std::sync::Arc;

use libero_sim::compose::{ComposedScene, compose_file};
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::placement::Placement;
use libero_sim::{AssetPaths, InitStates, Simulation};
use libero_tasks::catalog::PoseInBody;
use libero_tasks::{Evaluator, Tick, apply_private_model_edits, build_evaluator};

use crate::EpisodeError;
use crate::call::MicroAction;
use crate::observation::Level;
use crate::task::TaskSource;

/// Zero actions run after restoring the init state, before the first observation (§4.2).
pub const SETTLE_STEPS: usize = 10;

/// What to build.
#[derive(Debug, Clone)]
pub struct WorldSpec {
    pub task: TaskSource,
    pub level: Level,
    pub seed: u64,
    pub init_index: usize,
    pub paths: AssetPaths,
}

/// A composed, placed scene with its simulation and evaluator, ready to start.
pub struct WorldPhysics {
    pub scene: ComposedScene,
    pub sim: Simulation,
    /// `[time, qpos, qvel]` restored at start: the trusted init state, or the seeded placement's state (settled for
    /// the task's `init_settle_steps` where it has them).
    pub start_row: Vec<f64>,
    /// The ordinary reset's state (the seeded placement, with the task's `init_poses_in_body`), settled before
    /// `start_row` is restored when `settle_before_restore` is set.
    reset_row: Vec<f64>,
    /// `vlabench_physical` (§4.2): settle on the ordinary reset, restore `start_row`, no settle after.
    settle_before_restore: bool,
    pub evaluator: Box<dyn Evaluator>,
    /// Control steps since the evaluator reset.
    pub control_step: u64,
    /// The scene as compiled, before this world's edits: held so that the next world of the scene copies it
    /// instead of compiling again (`libero_sim::shared_model::compiled`).
    _compiled: Arc<MjModel>,
}

impl WorldPhysics {
    /// Composes, compiles and places the scene and reads the init state. `edit_model` may change what does not
    /// affect physics (the renderer's site visibility) before the model is frozen; it gets the start `qpos`.
    pub fn build(
        spec: &WorldSpec,
        edit_model: impl FnOnce(&ComposedScene, &mut MjModel, &[f64]) -> Result<(), EpisodeError>,
    ) -> Result<Self, EpisodeError> {
        let scene = compose_file(&spec.task.bddl, &spec.paths)?;
        let (mut model, compiled) = scene.compile_shared()?;
        let suite = spec.task.suite.as_ref();
        let layout = spec.task.effective_layout(spec.seed, spec.init_index)?;
        let placement = match adjusted_table_regions(&scene, layout.region_margin_m, layout.scene_shift_m, layout.yaw_margin_rad) {
            Some(moved) => Placement::sample(&moved, layout.placement_seed, Some(&model))?,
            None => Placement::sample(&scene, layout.placement_seed, Some(&model))?,
        };
        placement.apply(&mut model)?;
        // private parameters that shape the physics (T08's mug masses) reach the model here, never through a file
        apply_private_model_edits(suite.map(|s| &s.checker), suite.map(|s| s.id.as_str()), &mut model)
            .map_err(|e| EpisodeError::Evaluator(e.to_string()))?;
        let evaluator = build_evaluator(suite.map(|s| &s.checker), suite.map(|s| s.id.as_str()), &scene, &model)
            .map_err(|e| EpisodeError::Evaluator(e.to_string()))?;
        let init_row = match (&spec.task.init_states, layout.init_index) {
            (Some(path), Some(index)) => Some(InitStates::read(path)?.get(index)?.to_vec()),
            _ => None,
        };
        let qpos = start_qpos(&model, init_row.as_deref(), &placement)?;
        edit_model(&scene, &mut model, &qpos)?;
        // Final from here on: episodes that built the same model share one (libero_sim::shared_model).
        let sim = Simulation::new(libero_sim::shared_model::share(model))?;
        let poses = suite.map_or(&[][..], |s| s.init_poses_in_body.as_slice());
        let reset_row = posed_row(sim.model(), placement_row(&sim, &placement)?, &placement, poses)?;
        let settle_steps = suite.map_or(0, |s| s.init_settle_steps);
        let start_row = match init_row {
            Some(row) => row,
            None if settle_steps > 0 => settled_row(sim.model(), &reset_row, settle_steps)?,
            None => reset_row.clone(),
        };
        let settle_before_restore = suite.is_some_and(|s| s.settle_before_restore);
        Ok(Self { scene, sim, start_row, reset_row, settle_before_restore, evaluator, control_step: 0, _compiled: compiled })
    }

    /// Another world as [`Self::build`] from the same `spec` leaves it, without composing or compiling again: the
    /// same shared model (placement, private edits and site visibility included), a fresh `mjData` and a new
    /// evaluator. Bit-identical to a second build: `build` only reads its simulation, and the evaluator is built
    /// from the same scene and model, whose only later edit (site colours for the images) no evaluator reads.
    /// Whatever state `self` has reached, the fork starts from the build state.
    pub fn fork(&self, spec: &WorldSpec) -> Result<Self, EpisodeError> {
        let suite = spec.task.suite.as_ref();
        let evaluator = build_evaluator(suite.map(|s| &s.checker), suite.map(|s| s.id.as_str()), &self.scene, self.model())
            .map_err(|e| EpisodeError::Evaluator(e.to_string()))?;
        Ok(Self {
            scene: self.scene.clone(),
            sim: Simulation::new(self.model().clone())?,
            start_row: self.start_row.clone(),
            reset_row: self.reset_row.clone(),
            settle_before_restore: self.settle_before_restore,
            evaluator,
            control_step: 0,
            _compiled: self._compiled.clone(),
        })
    }

    pub fn model(&self) -> &Arc<MjModel> {
        self.sim.model()
    }

    pub fn tick(&self, substep: Option<u32>) -> Tick {
        Tick { control_step: self.control_step, substep, sim_time_s: self.sim.time_s() }
    }

    /// §4.2: restore the start row, settle, reset the evaluator. `after_settle_step` sees every settle step.
    /// `vlabench_physical`: settle the ordinary reset first (unrecorded), then restore the start row and do not settle.
    pub fn start(&mut self, mut after_settle_step: impl FnMut(&Simulation)) -> Result<(), EpisodeError> {
        if self.settle_before_restore {
            self.sim.set_init_state(&self.reset_row)?;
            for _ in 0..SETTLE_STEPS {
                self.sim.step([0.0; 7])?;
            }
            self.sim.set_init_state(&self.start_row)?;
        } else {
            self.sim.set_init_state(&self.start_row)?;
            for _ in 0..SETTLE_STEPS {
                self.sim.step([0.0; 7])?;
                after_settle_step(&self.sim);
            }
        }
        self.control_step = 0;
        let tick = self.tick(None);
        self.evaluator.reset(self.sim.data(), tick);
        Ok(())
    }

    /// One 20 Hz control interval; the evaluator observes it (and its substeps where it samples them).
    pub fn step(&mut self, action: &MicroAction) -> Result<(), EpisodeError> {
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
        let tick = self.tick(None);
        self.evaluator.observe_control_step(self.sim.data(), tick);
        Ok(())
    }

    /// The evaluator's record on the current state.
    pub fn evaluate(&mut self) -> libero_tasks::EvaluationRecord {
        let tick = self.tick(None);
        self.evaluator.finish(self.sim.data(), tick).with_stage_diagnostics()
    }
}

/// The `qpos` an episode starts from: the init row's, or the seeded placement written over `qpos0`.
fn start_qpos(model: &MjModel, init_row: Option<&[f64]>, placement: &Placement) -> Result<Vec<f64>, EpisodeError> {
    let nq = model.ffi().nq as usize;
    match init_row {
        Some(row) => row.get(1..1 + nq).map(<[f64]>::to_vec).ok_or_else(|| {
            EpisodeError::Task(format!("init state has {} values, the model needs 1 + nq = {}+", row.len(), 1 + nq))
        }),
        None => {
            let mut qpos = model.qpos0().to_vec();
            placement.write_qpos(model, &mut qpos)?;
            Ok(qpos)
        }
    }
}

/// `row` (the seeded placement) with `poses` applied: objects moved to fixed poses in the frame of a body of the
/// placed scene, where an unavailable trusted state put them (T30's carton on the seesaw's low end).
fn posed_row(model: &Arc<MjModel>, mut row: Vec<f64>, placement: &Placement, poses: &[PoseInBody]) -> Result<Vec<f64>, EpisodeError> {
    if poses.is_empty() {
        return Ok(row);
    }
    let mut scratch = Simulation::new(model.clone())?;
    scratch.set_init_state(&row)?;
    for p in poses {
        let body = model
            .name_to_id(MjtObjBase::mjOBJ_BODY, &p.body)
            .ok_or_else(|| EpisodeError::Task(format!("init pose: model has no body {:?}", p.body)))?;
        let joint = placement
            .objects
            .iter()
            .find(|o| o.name == p.object)
            .and_then(|o| model.name_to_id(MjtObjBase::mjOBJ_JOINT, &o.joint))
            .ok_or_else(|| EpisodeError::Task(format!("init pose: {:?} is not a placed object", p.object)))?;
        let (xpos, xmat, xquat) = {
            let d = scratch.data();
            (d.xpos()[body], d.xmat()[body], d.xquat()[body])
        };
        let a = 1 + model.jnt_qposadr()[joint] as usize;
        for k in 0..3 {
            row[a + k] = xpos[k] + (0..3).map(|j| xmat[3 * k + j] * p.pos_m[j]).sum::<f64>();
        }
        let q = |v: [f64; 4]| nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(v[0], v[1], v[2], v[3]));
        let world = q(xquat) * q(p.quat_wxyz);
        row[a + 3..a + 7].copy_from_slice(&[world.w, world.i, world.j, world.k]);
    }
    Ok(row)
}

/// `row` after `steps` zero-action control steps, on a scratch simulation: the start state of a task whose trusted
/// state is unavailable and whose objects must come to rest first (T30's carton leaning in the seesaw's cage).
fn settled_row(model: &Arc<MjModel>, row: &[f64], steps: u32) -> Result<Vec<f64>, EpisodeError> {
    let mut scratch = Simulation::new(model.clone())?;
    scratch.set_init_state(row)?;
    for _ in 0..steps {
        scratch.step([0.0; 7])?;
    }
    Ok(scratch.state_row())
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

/// The scene to sample a layout variant's placement from (issue 31): every table region (those the reset placement
/// samples on the workspace fixture) widened by `margin_m` on each side and moved by `shift_m`. Only the placement
/// sees it; the episode keeps the task's own scene, so goal regions and evaluators are untouched. None without a
/// variant.
fn adjusted_table_regions(scene: &ComposedScene, margin_m: f64, shift_m: [f64; 2], yaw_margin_rad: f64) -> Option<ComposedScene> {
    if margin_m <= 0.0 && shift_m == [0.0; 2] && yaw_margin_rad <= 0.0 {
        return None;
    }
    let mut moved = scene.clone();
    let workspace = moved.problem_class.workspace_name().to_owned();
    let [dx, dy] = shift_m;
    for region in moved.problem.regions.iter_mut().filter(|r| r.target == workspace) {
        for r in &mut region.ranges {
            *r = [r[0] - margin_m + dx, r[1] - margin_m + dy, r[2] + margin_m + dx, r[3] + margin_m + dy];
        }
        region.yaw_rotation = [region.yaw_rotation[0] - yaw_margin_rad, region.yaw_rotation[1] + yaw_margin_rad];
    }
    Some(moved)
}
