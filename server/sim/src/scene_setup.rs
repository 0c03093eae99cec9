//! One place for LIBERO's scene set-up as every command needs it: compose a BDDL file, compile it, place the
//! fixtures for a seed as `env.reset()` does, and pick the state an episode starts from (a trusted init-state
//! row, or the seeded placement itself when the task has none).
use std::path::Path;

use mujoco_rs::prelude::{MjModel, MjtObjBase};

use crate::compose::{ComposedScene, compose_file};
use crate::placement::{PANDA_INIT_QPOS, Placement};
use crate::{AssetPaths, InitStates, SimError};

/// Where the start state came from.
#[derive(Debug, Clone, PartialEq)]
pub enum StartSource {
    /// Row `index` of a LIBERO `.pruned_init` file.
    InitFile { index: usize },
    /// The state LIBERO has right after `reset()` with this seed: robot at `init_qpos`, objects and
    /// articulations as sampled, zero velocity.
    SeededPlacement,
}

/// A compiled, placed LIBERO scene and the `[time, qpos, qvel]` row to start from.
pub struct PreparedScene {
    pub scene: ComposedScene,
    /// Compiled with the placement's fixture poses applied (fixtures are model constants, not qpos).
    pub model: MjModel,
    pub placement: Placement,
    /// `[time, qpos…, qvel…]`, the layout of LIBERO's init-state rows.
    pub start_row: Vec<f64>,
    pub start_source: StartSource,
}

impl PreparedScene {
    /// Composes `bddl`, places fixtures and objects for `seed` and reads the start row from
    /// `init` (`(file, index)`) when given; the row's length is checked against the compiled model.
    pub fn prepare(bddl: &Path, paths: &AssetPaths, seed: u32, init: Option<(&Path, usize)>) -> Result<Self, SimError> {
        let scene = compose_file(bddl, paths)?;
        let mut model = scene.compile()?;
        let placement = Placement::sample(&scene, seed, Some(&model))?;
        placement.apply(&mut model)?;
        let nq = model.ffi().nq as usize;
        let nv = model.ffi().nv as usize;
        let (start_row, start_source) = match init {
            Some((file, index)) => {
                let row = InitStates::read(file)?.get(index)?.to_vec();
                if row.len() != 1 + nq + nv {
                    return Err(SimError::Input(format!(
                        "init state {index} of {} has {} values, but this scene needs 1 + nq + nv = {} \
                         (is it the init file of this BDDL?)",
                        file.display(),
                        row.len(),
                        1 + nq + nv
                    )));
                }
                (row, StartSource::InitFile { index })
            }
            None => {
                let mut qpos = model.qpos0().to_vec();
                for (k, v) in PANDA_INIT_QPOS.iter().enumerate() {
                    if let Some(id) = model.name_to_id(MjtObjBase::mjOBJ_JOINT, &format!("robot0_joint{}", k + 1)) {
                        qpos[model.jnt_qposadr()[id] as usize] = *v;
                    }
                }
                placement.write_qpos(&model, &mut qpos)?;
                let mut row = Vec::with_capacity(1 + nq + nv);
                row.push(0.0);
                row.extend_from_slice(&qpos);
                row.extend(std::iter::repeat_n(0.0, nv));
                (row, StartSource::SeededPlacement)
            }
        };
        Ok(Self { scene, model, placement, start_row, start_source })
    }

    /// The `qpos` part of the start row.
    pub fn start_qpos(&self) -> &[f64] {
        let nq = self.model.ffi().nq as usize;
        &self.start_row[1..1 + nq]
    }
}
