//! Poses from a recorded `qpos`: the frame a renderer needs (body, geom, site, camera and light poses),
//! recomputed after the fact. The private video records only `qpos` per control step (and the mocap poses,
//! should a model have any); running MuJoCo's own position stages (`mj_kinematics`, `mj_comPos`,
//! `mj_camlight`) on a scratch `mjData` reproduces exactly the poses `mj_step1` computed during the episode,
//! since they are pure functions of the model, `qpos` and the mocap poses.
use std::sync::Arc;

use mujoco_rs::prelude::*;

use crate::SimError;
use crate::fault::ffi::{mj_camlight, mj_comPos, mj_kinematics};
use crate::fault::guarded;
use crate::simulation::SimData;

/// A scratch `mjData` for recomputing poses.
pub struct PoseReplay {
    model: Arc<MjModel>,
    data: SimData,
}

impl PoseReplay {
    pub fn new(model: Arc<MjModel>) -> Self {
        let data = SimData::new(model.clone());
        Self { model, data }
    }

    pub fn model(&self) -> &Arc<MjModel> {
        &self.model
    }

    /// `nq` and `nmocap` of the model, the sizes [`Self::pose`] expects.
    pub fn sizes(&self) -> (usize, usize) {
        let m = self.model.ffi();
        (m.nq as usize, m.nmocap as usize)
    }

    /// Sets `qpos` and the mocap poses (`[x y z qw qx qy qz]` per mocap body) and computes the poses from them.
    pub fn pose(&mut self, qpos: &[f64], mocap: &[f64]) -> Result<&SimData, SimError> {
        let (nq, nmocap) = self.sizes();
        if qpos.len() != nq || mocap.len() != 7 * nmocap {
            return Err(SimError::Input(format!(
                "a recorded pose has {} qpos and {} mocap values; the model needs {nq} and {}",
                qpos.len(),
                mocap.len(),
                7 * nmocap
            )));
        }
        if let Some(i) = qpos.iter().chain(mocap).position(|x| !x.is_finite()) {
            return Err(SimError::Input(format!("recorded pose value {i} is not finite")));
        }
        self.data.qpos_mut().copy_from_slice(qpos);
        // SAFETY: mocap_pos/mocap_quat hold 3 and 4 values per mocap body of this model; only values are written.
        unsafe {
            let d = self.data.ffi_mut();
            for b in 0..nmocap {
                std::ptr::copy_nonoverlapping(mocap[7 * b..].as_ptr(), d.mocap_pos.add(3 * b), 3);
                std::ptr::copy_nonoverlapping(mocap[7 * b + 3..].as_ptr(), d.mocap_quat.add(4 * b), 4);
            }
        }
        let model = self.model.clone();
        let data = &mut self.data;
        guarded(|| {
            // SAFETY: model and data belong together; MuJoCo errors unwind through `guarded`.
            unsafe {
                mj_kinematics(model.ffi(), data.ffi_mut());
                mj_comPos(model.ffi(), data.ffi_mut());
                mj_camlight(model.ffi(), data.ffi_mut());
            }
        })
        .map_err(SimError::Fault)?;
        Ok(&self.data)
    }
}

/// The mocap poses of `data` as [`PoseReplay::pose`] takes them.
pub fn mocap_of(model: &MjModel, data: &SimData) -> Vec<f64> {
    let nmocap = model.ffi().nmocap as usize;
    let d = data.ffi();
    let mut out = Vec::with_capacity(7 * nmocap);
    for b in 0..nmocap {
        // SAFETY: as in `PoseReplay::pose`.
        unsafe {
            out.extend_from_slice(std::slice::from_raw_parts(d.mocap_pos.add(3 * b), 3));
            out.extend_from_slice(std::slice::from_raw_parts(d.mocap_quat.add(4 * b), 4));
        }
    }
    out
}
