//! Scripted privileged experts: per task, a script that reads the simulator state (privileged: object poses,
//! joint positions, fixture geometry) and emits the normalized `OSC_POSE` actions an agent would send. They prove
//! each task solvable and each evaluator sound (tests and demonstration generation only; never shown to agents).
//!
//! Besides the solving script (`solve`), each task has named **near-miss** behaviours: plausible runs that must fail
//! (wrong object, drawer half open, …). An expert only ever acts through `osc_sequence`; the episode crate runs it on a
//! lockstep replica of the episode's simulation.
mod adapted;
mod articulated;
mod door;
mod hammer;
mod bowls;
mod cooking;
mod long;
pub mod motion;
mod objects;
mod perception;
mod robomem;
mod seesaw;
mod stock;
mod vlabench;

use libero_sim::Simulation;
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::MjModel;

use crate::TasksError;
use crate::predicates::SceneIndex;

/// The behaviour that solves the task.
pub const SOLVE: &str = "solve";

/// T08: the phase at whose end a weighed mug has hung still in the hand (tests read the wrist force there).
pub fn perception_weigh_hold_phase() -> &'static str {
    perception::WEIGH_HOLD_PHASE
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

/// The tasks that have an expert, with their near-miss behaviours.
pub fn behaviours(task_id: &str) -> Option<&'static [&'static str]> {
    stock::behaviours(task_id)
        .or_else(|| vlabench::behaviours(task_id))
        .or_else(|| adapted::behaviours(task_id))
        .or_else(|| long::behaviours(task_id))
        .or_else(|| door::behaviours(task_id))
        .or_else(|| hammer::behaviours(task_id))
        .or_else(|| robomem::behaviours(task_id))
        .or_else(|| bowls::behaviours(task_id))
        .or_else(|| cooking::behaviours(task_id))
        .or_else(|| perception::behaviours(task_id))
        .or_else(|| seesaw::behaviours(task_id))
}

/// The expert for `task_id` playing `behaviour` ([`SOLVE`] or one of [`behaviours`]) on this scene.
pub fn expert_for(
    task_id: &str,
    behaviour: &str,
    scene: &ComposedScene,
    model: &MjModel,
) -> Result<Box<dyn Expert>, TasksError> {
    let refs = SceneRefs::new(scene, model)?;
    let known = behaviours(task_id).ok_or_else(|| TasksError::Scene(format!("no scripted expert for task {task_id}")))?;
    if behaviour != SOLVE && !known.contains(&behaviour) {
        return Err(TasksError::Scene(format!(
            "task {task_id} has no expert behaviour {behaviour:?}; known: {SOLVE}, {}",
            known.join(", ")
        )));
    }
    if stock::behaviours(task_id).is_some() {
        stock::build(task_id, behaviour, &refs)
    } else if vlabench::behaviours(task_id).is_some() {
        vlabench::build(task_id, behaviour, &refs)
    } else if adapted::behaviours(task_id).is_some() {
        adapted::build(task_id, behaviour, &refs)
    } else if long::behaviours(task_id).is_some() {
        long::build(task_id, behaviour, &refs)
    } else if door::behaviours(task_id).is_some() {
        door::build(task_id, behaviour, &refs)
    } else if hammer::behaviours(task_id).is_some() {
        hammer::build(task_id, behaviour, &refs)
    } else if robomem::behaviours(task_id).is_some() {
        robomem::build(task_id, behaviour, &refs)
    } else if bowls::behaviours(task_id).is_some() {
        bowls::build(task_id, behaviour, &refs)
    } else if cooking::behaviours(task_id).is_some() {
        cooking::build(task_id, behaviour, &refs)
    } else if seesaw::behaviours(task_id).is_some() {
        seesaw::build(task_id, behaviour, &refs)
    } else {
        perception::build(task_id, behaviour, &refs)
    }
}
