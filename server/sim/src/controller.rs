//! robosuite 1.4.0 `OSC_POSE` with LIBERO's configuration (port notes §1), reproduced operation by
//! operation where the order of floating-point operations is ours to choose.
//!
//! Frames: every vector and matrix here is in the MuJoCo world frame (LIBERO's robot base is unrotated).
//! Units: metres, radians, newtons, newton-metres.
use mujoco_rs::mujoco_c::mj_jacSite;
use mujoco_rs::prelude::*;
use mujoco_rs::wrappers::mj_model::traits::ModelType;
use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

use crate::robot::PandaIds;

pub type Vector7 = SVector<f64, 7>;
pub type Matrix7 = SMatrix<f64, 7, 7>;
pub type Matrix3x7 = SMatrix<f64, 3, 7>;
pub type Matrix6x7 = SMatrix<f64, 6, 7>;
pub type Matrix6 = SMatrix<f64, 6, 6>;

/// `output_max` of `osc_pose.json`: metres (xyz) and radians (axis-angle) per action at input 1.
pub const ACTION_SCALE: [f64; 6] = [0.05, 0.05, 0.05, 0.5, 0.5, 0.5];
/// `kp` of `osc_pose.json`.
pub const KP: f64 = 150.0;
/// Nullspace posture gain (`nullspace_torques(joint_kp=10)`).
pub const NULLSPACE_KP: f64 = 10.0;

/// What `Controller.update()` caches: arm kinematics and dynamics at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmState {
    /// Grip-site position (`ee_pos`).
    pub ee_pos_in_world_m: Vector3<f64>,
    /// Grip-site rotation (`ee_ori_mat`), R_world_from_site.
    pub r_world_from_site: Matrix3<f64>,
    /// `ee_pos_vel` = J_pos · q̇.
    pub ee_lin_vel_in_world_m_s: Vector3<f64>,
    /// `ee_ori_vel` = J_ori · q̇.
    pub ee_ang_vel_in_world_rad_s: Vector3<f64>,
    pub joint_pos_rad: Vector7,
    pub joint_vel_rad_s: Vector7,
    pub jac_pos: Matrix3x7,
    pub jac_ori: Matrix3x7,
    /// Arm block of the joint-space inertia (armature included).
    pub mass: Matrix7,
}

/// Reads [`ArmState`] from `mjData` through reused buffers (no allocation per call).
#[derive(Debug, Clone)]
pub struct ArmStateReader {
    nv: usize,
    jacp: Vec<f64>,
    jacr: Vec<f64>,
    /// (index into `d.M`, arm row, arm column) of the lower-triangle entries of the arm block.
    mass_entries: Vec<(usize, usize, usize)>,
}

impl ArmStateReader {
    /// Buffers for `model`, and the positions of the arm block inside MuJoCo's sparse inertia `d.M`.
    pub fn new(model: &MjModel, ids: &PandaIds) -> Self {
        let nv = model.ffi().nv as usize;
        let (rowadr, rownnz, colind) = (model.m_rowadr(), model.m_rownnz(), model.m_colind());
        let arm_index = |dof: usize| ids.arm_dof_adr.iter().position(|&d| d == dof);
        let mut mass_entries = Vec::new();
        for (i, &row) in ids.arm_dof_adr.iter().enumerate() {
            let start = rowadr[row] as usize;
            for k in start..start + rownnz[row] as usize {
                if let Some(j) = arm_index(colind[k] as usize) {
                    mass_entries.push((k, i, j));
                }
            }
        }
        Self { nv, jacp: vec![0.0; 3 * nv], jacr: vec![0.0; 3 * nv], mass_entries }
    }

    /// Reads the state from `data`, whose position/velocity stages must be current (after
    /// `mj_forward` or `mj_step1`).
    pub fn read<M: ModelType>(&mut self, data: &MjData<M>, ids: &PandaIds) -> ArmState {
        let model = data.model();
        let nv = self.nv;
        // SAFETY: buffers hold 3·nv values each as MuJoCo requires; the site id comes from the model.
        unsafe {
            mj_jacSite(model.ffi(), data.ffi(), self.jacp.as_mut_ptr(), self.jacr.as_mut_ptr(), ids.grip_site as i32);
        }
        let site_pos = data.site_xpos()[ids.grip_site];
        let site_mat = data.site_xmat()[ids.grip_site];
        let qpos = data.qpos();
        let qvel = data.qvel();
        let mut s = ArmState {
            ee_pos_in_world_m: Vector3::new(site_pos[0], site_pos[1], site_pos[2]),
            // site_xmat is row-major.
            r_world_from_site: Matrix3::from_row_slice(&site_mat),
            ee_lin_vel_in_world_m_s: Vector3::zeros(),
            ee_ang_vel_in_world_rad_s: Vector3::zeros(),
            joint_pos_rad: Vector7::zeros(),
            joint_vel_rad_s: Vector7::zeros(),
            jac_pos: Matrix3x7::zeros(),
            jac_ori: Matrix3x7::zeros(),
            mass: Matrix7::zeros(),
        };
        for (i, (&qa, &da)) in ids.arm_qpos_adr.iter().zip(&ids.arm_dof_adr).enumerate() {
            s.joint_pos_rad[i] = qpos[qa];
            s.joint_vel_rad_s[i] = qvel[da];
            for r in 0..3 {
                s.jac_pos[(r, i)] = self.jacp[r * nv + da];
                s.jac_ori[(r, i)] = self.jacr[r * nv + da];
            }
        }
        // The arm block of `mj_fullM`'s dense matrix, copied straight from the sparse `d.M` (same values;
        // avoids densifying nv² entries every substep).
        let sparse_mass = data.m();
        for &(k, i, j) in &self.mass_entries {
            s.mass[(i, j)] = sparse_mass[k];
            s.mass[(j, i)] = sparse_mass[k];
        }
        // robosuite: np.dot(jac(3×nv), qvel(nv)). Only the arm's dofs are ancestors of the grip site, so
        // the other columns are exactly zero; sum in dof order.
        for r in 0..3 {
            let (mut lin, mut ang) = (0.0, 0.0);
            for d in 0..nv {
                lin += self.jacp[r * nv + d] * qvel[d];
                ang += self.jacr[r * nv + d] * qvel[d];
            }
            s.ee_lin_vel_in_world_m_s[r] = lin;
            s.ee_ang_vel_in_world_rad_s[r] = ang;
        }
        s
    }
}

/// robosuite's `quat2mat` of an (x, y, z, w) quaternion, including its float32 cast, as the numba-jitted
/// function computes it (robosuite 1.4 jits it; checked against the golden `goal_ori`): the quaternion is
/// rounded to f32, its squared norm formed as OpenBLAS' sdot does, scaled by `sqrt(2 / n)` in f64 and stored back as f32;
/// diagonal entries are formed in f64 from f32 products, off-diagonal ones in f32.
pub fn quat2mat_f32(q_xyzw: [f64; 4]) -> Matrix3<f64> {
    let q = [q_xyzw[3] as f32, q_xyzw[0] as f32, q_xyzw[1] as f32, q_xyzw[2] as f32];
    // np.dot of two float32 vectors (OpenBLAS sdot): f32 products summed in f64, rounded once to f32.
    // Verified against numpy 1.26 on 20 000 random vectors; f32 or exact-product sums miss the golden
    // goal_ori by ~1.5e-8.
    let n: f32 = q.iter().map(|&x| (x * x) as f64).sum::<f64>() as f32;
    if (n as f64) < 4.0 * f64::EPSILON {
        return Matrix3::identity();
    }
    // `2.0 / n` and the sqrt are f64; numba's in-place `q *= s` multiplies in f64 and stores f32.
    let s = (2.0 / n as f64).sqrt();
    let q = q.map(|x| (x as f64 * s) as f32);
    let o = |i: usize, j: usize| q[i] * q[j];
    let d = |a: f32, b: f32| 1.0 - a as f64 - b as f64;
    Matrix3::new(
        d(o(2, 2), o(3, 3)),
        (o(1, 2) - o(3, 0)) as f64,
        (o(1, 3) + o(2, 0)) as f64,
        (o(1, 2) + o(3, 0)) as f64,
        d(o(1, 1), o(3, 3)),
        (o(2, 3) - o(1, 0)) as f64,
        (o(1, 3) - o(2, 0)) as f64,
        (o(2, 3) + o(1, 0)) as f64,
        d(o(1, 1), o(2, 2)),
    )
}

/// robosuite's `axisangle2quat`: (x, y, z, w); a zero-length vector gives the identity.
pub fn axisangle2quat(v: [f64; 3]) -> [f64; 4] {
    let angle = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if angle == 0.0 {
        return [0.0, 0.0, 0.0, 1.0];
    }
    let axis = [v[0] / angle, v[1] / angle, v[2] / angle];
    let (s, c) = ((angle / 2.0).sin(), (angle / 2.0).cos());
    [axis[0] * s, axis[1] * s, axis[2] * s, c]
}

/// `orientation_error(desired, current)` = ½ Σ cᵢ × dᵢ over the matrices' columns.
pub fn orientation_error(desired: &Matrix3<f64>, current: &Matrix3<f64>) -> Vector3<f64> {
    let mut e = Vector3::zeros();
    for i in 0..3 {
        e += current.column(i).cross(&desired.column(i));
    }
    e * 0.5
}

/// NumPy `linalg.pinv` of a symmetric positive semi-definite matrix. When the matrix is safely positive
/// definite the pseudo-inverse is the inverse, computed by Cholesky (cheap); otherwise the SVD semantics
/// are reproduced exactly: singular values (= |eigenvalues|) ≤ 1e-15·σ_max are dropped.
macro_rules! pinv_symmetric_fn {
    ($name:ident, $n:literal) => {
        fn $name(a: &SMatrix<f64, $n, $n>) -> SMatrix<f64, $n, $n> {
            let sym = (a + a.transpose()) * 0.5;
            if let Some(ch) = sym.cholesky() {
                let d = ch.l_dirty().diagonal();
                let (lo, hi) = d.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &x| (lo.min(x), hi.max(x)));
                // cond(A) = (hi/lo)^2 roughly; far from the 1e15 cutoff, pinv(A) = inv(A).
                if lo > 0.0 && lo * lo > 1e-12 * hi * hi {
                    return ch.inverse();
                }
            }
            let eig = nalgebra::SymmetricEigen::new(sym);
            let sigma_max = eig.eigenvalues.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let cutoff = 1e-15 * sigma_max;
            let mut out = SMatrix::<f64, $n, $n>::zeros();
            for k in 0..$n {
                let l = eig.eigenvalues[k];
                if l.abs() > cutoff {
                    let v = eig.eigenvectors.column(k);
                    out += v * v.transpose() * (1.0 / l);
                }
            }
            out
        }
    };
}
pinv_symmetric_fn!(pinv_symmetric3, 3);
pinv_symmetric_fn!(pinv_symmetric6, 6);

/// The OSC_POSE controller of one robot: goals, gains, nullspace target and the cached state with
/// robosuite's refresh flag.
#[derive(Debug, Clone)]
pub struct OscPose {
    pub goal_pos_in_world_m: Vector3<f64>,
    /// Goal orientation, R_world_from_site_goal.
    pub goal_r_world_from_site: Matrix3<f64>,
    /// Nullspace target `initial_joint`: the arm posture when the controller was created (reset).
    pub initial_joint_rad: Vector7,
    kp: f64,
    kd: f64,
    torque_min: Vector7,
    torque_max: Vector7,
    /// robosuite's `Controller` attributes filled by `update()`.
    cached: ArmState,
    /// robosuite's `new_update`: set at the end of every `run_controller`, cleared by each refresh.
    pub needs_refresh: bool,
}

impl OscPose {
    /// `Controller.__init__`: state read at creation becomes the cache, the nullspace target and the
    /// goals; the refresh flag is cleared, so the first substep after a reset reuses this state.
    pub fn new(initial: ArmState, ids: &PandaIds) -> Self {
        Self {
            goal_pos_in_world_m: initial.ee_pos_in_world_m,
            goal_r_world_from_site: initial.r_world_from_site,
            initial_joint_rad: initial.joint_pos_rad,
            kp: KP,
            kd: 2.0 * KP.sqrt(),
            torque_min: Vector7::from(ids.arm_torque_min),
            torque_max: Vector7::from(ids.arm_torque_max),
            cached: initial,
            needs_refresh: false,
        }
    }

    /// The state the controller last cached.
    pub fn cached_state(&self) -> &ArmState {
        &self.cached
    }

    /// `update()`: refresh the cache only if the flag asks for it.
    pub fn update_with(&mut self, read: impl FnOnce() -> ArmState) {
        if self.needs_refresh {
            self.cached = read();
            self.needs_refresh = false;
        }
    }

    /// `set_goal(action[0:6])` for the fixed-impedance delta mode (after `update_with`).
    pub fn set_goal(&mut self, arm_action: &[f64; 6]) {
        let mut delta = [0.0; 6];
        for i in 0..6 {
            delta[i] = arm_action[i].clamp(-1.0, 1.0) * ACTION_SCALE[i];
        }
        // math.isclose(x, 0.0) with abs_tol 0: only an exact zero counts.
        if delta[3] != 0.0 || delta[4] != 0.0 || delta[5] != 0.0 {
            let r_delta = quat2mat_f32(axisangle2quat([delta[3], delta[4], delta[5]]));
            self.goal_r_world_from_site = matmul3(&r_delta, &self.cached.r_world_from_site);
        }
        self.goal_pos_in_world_m = self.cached.ee_pos_in_world_m + Vector3::new(delta[0], delta[1], delta[2]);
    }

    /// `run_controller()` + `SingleArm.control`'s clip: arm torques for this substep. `bias` is the live
    /// `qfrc_bias` of the arm dofs (robosuite reads it as a property, never cached).
    pub fn run(&mut self, bias: &Vector7) -> Vector7 {
        let s = &self.cached;
        let pos_err = self.goal_pos_in_world_m - s.ee_pos_in_world_m;
        let ori_err = orientation_error(&self.goal_r_world_from_site, &s.r_world_from_site);
        let force = pos_err * self.kp + (-s.ee_lin_vel_in_world_m_s) * self.kd;
        let torque = ori_err * self.kp + (-s.ee_ang_vel_in_world_rad_s) * self.kd;

        let m_inv = match s.mass.cholesky() {
            Some(c) => c.inverse(),
            None => s.mass.try_inverse().unwrap_or_else(Matrix7::zeros),
        };
        let mut jac = Matrix6x7::zeros();
        jac.fixed_view_mut::<3, 7>(0, 0).copy_from(&s.jac_pos);
        jac.fixed_view_mut::<3, 7>(3, 0).copy_from(&s.jac_ori);
        let lambda_full_inv: Matrix6 = (jac * m_inv) * jac.transpose();
        let lambda_pos_inv: Matrix3<f64> = (s.jac_pos * m_inv) * s.jac_pos.transpose();
        let lambda_ori_inv: Matrix3<f64> = (s.jac_ori * m_inv) * s.jac_ori.transpose();
        let lambda_full = pinv_symmetric6(&lambda_full_inv);
        let lambda_pos = pinv_symmetric3(&lambda_pos_inv);
        let lambda_ori = pinv_symmetric3(&lambda_ori_inv);
        let jbar = (m_inv * jac.transpose()) * lambda_full;
        let nullspace = Matrix7::identity() - jbar * jac;

        let f = lambda_pos * force;
        let t = lambda_ori * torque;
        let wrench = SVector::<f64, 6>::new(f[0], f[1], f[2], t[0], t[1], t[2]);
        let mut tau = jac.transpose() * wrench + bias;
        let kv = NULLSPACE_KP.sqrt() * 2.0;
        let posture = (self.initial_joint_rad - s.joint_pos_rad) * NULLSPACE_KP - s.joint_vel_rad_s * kv;
        tau += nullspace.transpose() * (s.mass * posture);
        self.needs_refresh = true;
        tau.zip_zip_map(&self.torque_min, &self.torque_max, |t, lo, hi| t.max(lo).min(hi))
    }
}

/// 3×3 product summed in index order (what BLAS does for k = 3).
fn matmul3(a: &Matrix3<f64>, b: &Matrix3<f64>) -> Matrix3<f64> {
    Matrix3::from_fn(|i, j| a[(i, 0)] * b[(0, j)] + a[(i, 1)] * b[(1, j)] + a[(i, 2)] * b[(2, j)])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quat2mat_f32_is_a_rotation_close_to_the_f64_one() {
        let q = axisangle2quat([0.1, -0.05, 0.02]);
        let r = quat2mat_f32(q);
        let exact = nalgebra::Rotation3::from_scaled_axis(Vector3::new(0.1, -0.05, 0.02));
        let diff = (r - exact.matrix()).abs().max();
        assert!(diff < 1e-7 && diff > 0.0, "float32 path must differ slightly from f64: {diff}");
    }

    #[test]
    fn orientation_error_of_small_rotation_is_its_axis_angle() {
        let cur = Matrix3::identity();
        let des = *nalgebra::Rotation3::from_scaled_axis(Vector3::new(0.0, 0.0, 1e-4)).matrix();
        let e = orientation_error(&des, &cur);
        assert!((e - Vector3::new(0.0, 0.0, 1e-4)).norm() < 1e-12);
    }

    #[test]
    fn pinv_matches_inverse_for_spd_and_drops_null_directions() {
        let a = Matrix3::new(4.0, 1.0, 0.0, 1.0, 3.0, 0.0, 0.0, 0.0, 2.0);
        let p = pinv_symmetric3(&a);
        assert!((p * a - Matrix3::identity()).abs().max() < 1e-14);
        let singular = Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0);
        let p = pinv_symmetric3(&singular);
        assert!((p - Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5)).abs().max() < 1e-15);
    }
}
