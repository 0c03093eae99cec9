//! Scripted privileged experts: per task, a script that reads the simulator state (privileged: object poses,
//! joint positions, fixture geometry) and emits the normalized `OSC_POSE` actions an agent would send. They prove
//! each task solvable and each evaluator sound (tests and demonstration generation only; never shown to agents).
//!
//! Besides the solving script (`solve`), each task has named **near-miss** behaviours: plausible runs that must fail
//! (wrong object, drawer half open, …). An expert only ever acts through `osc_sequence`; the episode crate runs it on a
//! lockstep replica of the episode's simulation.
//!
//! This module holds what every family's experts share (the [`Expert`] trait, scene look-ups, the motion layer and
//! reusable skills); each family's scripts live in its folder under `families/`, and the registry picks them.
pub mod fixtures;
pub mod motion;
pub mod skills;

use libero_sim::Simulation;
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;

use crate::TasksError;
use crate::judge::predicates::SceneIndex;

/// The behaviour that solves the task.
pub const SOLVE: &str = "solve";

/// Builds a task's expert: `(scene, behaviour, task id)`, the behaviour [`SOLVE`] or one of the entry's near misses.
pub type BuildExpert = fn(&SceneRefs, &str, &str) -> Result<Box<dyn Expert>, TasksError>;

/// One task's scripted expert as a table row: each expert module lists its tasks this way and the registry
/// concatenates the families' tables, so a task id is written once, beside its behaviours and its script.
#[derive(Debug, Clone, Copy)]
pub struct ExpertEntry {
    /// The task id (`T11`, `suite/name`).
    pub task: &'static str,
    /// The near-miss behaviours, in the order they are listed to users (besides [`SOLVE`]).
    pub behaviours: &'static [&'static str],
    pub build: BuildExpert,
}

/// An expert that plays every task of whole suites (`suite/NAME`): the generic stock LIBERO expert, which plans
/// from each scene's own goal, so it has no per-task rows.
#[derive(Debug, Clone, Copy)]
pub struct SuiteExpert {
    pub suites: &'static [&'static str],
    pub behaviours: &'static [&'static str],
    pub build: BuildExpert,
}

impl SuiteExpert {
    /// Whether `task_id` is `suite/NAME` of one of the suites (NAME non-empty, one level).
    pub fn plays(&self, task_id: &str) -> bool {
        task_id.split_once('/').is_some_and(|(s, n)| self.suites.contains(&s) && !n.is_empty() && !n.contains('/'))
    }
}

/// A policy over privileged state, one control step at a time.
pub trait Expert: Send {
    /// The next normalized 7-vector action for the current state, or `None` when the expert is done.
    fn act(&mut self, sim: &Simulation) -> Option<[f64; 7]>;
    /// What the expert is doing now (for progress lines and logs).
    fn phase(&self) -> Option<&'static str> {
        None
    }
}

impl Expert for motion::Script {
    fn act(&mut self, sim: &Simulation) -> Option<[f64; 7]> {
        motion::Script::act(self, sim)
    }

    fn phase(&self) -> Option<&'static str> {
        self.phase_name()
    }
}

/// What an expert may look up about its scene (names → body, joint, site ids).
pub struct SceneRefs<'a> {
    pub scene: &'a ComposedScene,
    pub model: &'a MjModel,
    pub index: SceneIndex,
}

impl<'a> SceneRefs<'a> {
    pub fn new(scene: &'a ComposedScene, model: &'a MjModel) -> Result<Self, TasksError> {
        Ok(Self { scene, model, index: SceneIndex::new(scene, model)? })
    }

    fn id(&self, kind: libero_sim::mujoco_rs::prelude::MjtObjBase, name: &str) -> Result<usize, TasksError> {
        self.model.name_to_id(kind, name).ok_or_else(|| TasksError::Scene(format!("expert: the model has no {kind:?} {name:?}")))
    }

    pub fn body(&self, name: &str) -> Result<usize, TasksError> {
        self.id(libero_sim::mujoco_rs::prelude::MjtObjBase::mjOBJ_BODY, name)
    }

    pub fn site(&self, name: &str) -> Result<usize, TasksError> {
        self.id(libero_sim::mujoco_rs::prelude::MjtObjBase::mjOBJ_SITE, name)
    }

    pub fn geom(&self, name: &str) -> Result<usize, TasksError> {
        self.id(libero_sim::mujoco_rs::prelude::MjtObjBase::mjOBJ_GEOM, name)
    }

    /// `(qpos address, joint id)` of a joint.
    pub fn joint(&self, name: &str) -> Result<(usize, usize), TasksError> {
        let j = self.id(libero_sim::mujoco_rs::prelude::MjtObjBase::mjOBJ_JOINT, name)?;
        Ok((self.model.jnt_qposadr()[j] as usize, j))
    }

    /// Root body of an object or fixture instance.
    pub fn instance_body(&self, name: &str) -> Result<usize, TasksError> {
        let i = self.index.instance(name).ok_or_else(|| TasksError::Scene(format!("expert: no instance {name:?}")))?;
        Ok(self.index.instances[i].body)
    }
}
