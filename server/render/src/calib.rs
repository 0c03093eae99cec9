//! robosuite's camera model (`utils/camera_utils.py`): pinhole intrinsics from the vertical field of
//! view and the extrinsics in the OpenCV convention (x right, y down, looking along +z).
use mujoco_rs::prelude::{MjData, MjModel};
use mujoco_rs::wrappers::mj_model::MjtObjBase;
use mujoco_rs::wrappers::mj_model::traits::ModelType;

use crate::RenderError;

/// Row-major 4×4 rigid transform.
pub type Mat4 = [[f64; 4]; 4];

/// Intrinsics and extrinsics of one camera at one resolution.
#[allow(non_snake_case)]
#[derive(Debug, Clone, PartialEq)]
pub struct CameraCalibration {
    pub width: u32,
    pub height: u32,
    pub fovy_deg: f64,
    /// `[[f,0,W/2],[0,f,H/2],[0,0,1]]`, `f = 0.5·H / tan(fovy/2)`; pixel (u, v) has its centre at (u+0.5, v+0.5).
    pub K: [[f64; 3]; 3],
    /// Camera (OpenCV frame) → world.
    pub T_world_from_camera: Mat4,
    /// Camera (OpenCV frame) → body `robot0_base`; `None` when the model has no such body.
    pub T_robot_base_from_camera: Option<Mat4>,
}

/// robosuite's K for a vertical field of view in degrees.
#[allow(non_snake_case)]
pub fn intrinsics(fovy_deg: f64, width: u32, height: u32) -> [[f64; 3]; 3] {
    let f = 0.5 * height as f64 / (fovy_deg.to_radians() / 2.0).tan();
    [[f, 0.0, width as f64 / 2.0], [0.0, f, height as f64 / 2.0], [0.0, 0.0, 1.0]]
}

/// `[R | p]` from MuJoCo's position and row-major rotation.
pub fn pose_to_mat4(pos: &[f64; 3], xmat: &[f64; 9]) -> Mat4 {
    [
        [xmat[0], xmat[1], xmat[2], pos[0]],
        [xmat[3], xmat[4], xmat[5], pos[1]],
        [xmat[6], xmat[7], xmat[8], pos[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

pub fn mat4_mul(a: &Mat4, b: &Mat4) -> Mat4 {
    let mut c = [[0.0; 4]; 4];
    for i in 0..4 {
        for j in 0..4 {
            c[i][j] = (0..4).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    c
}

/// Inverse of a rigid transform.
pub fn rigid_inverse(t: &Mat4) -> Mat4 {
    let mut inv = [[0.0; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            inv[i][j] = t[j][i];
        }
        inv[i][3] = -(0..3).map(|k| t[k][i] * t[k][3]).sum::<f64>();
    }
    inv[3][3] = 1.0;
    inv
}

/// MuJoCo/OpenGL camera pose (x right, y up, looking along −z) → OpenCV camera pose: post-multiply by
/// `diag(1, −1, −1, 1)`.
pub fn opencv_from_mujoco_camera(cam_xpos: &[f64; 3], cam_xmat: &[f64; 9]) -> Mat4 {
    let mut t = pose_to_mat4(cam_xpos, cam_xmat);
    for row in t.iter_mut().take(3) {
        row[1] = -row[1];
        row[2] = -row[2];
    }
    t
}

/// Calibration from explicit poses (world frame); `base` is the pose of `robot0_base`.
pub fn calibration_from_poses(
    fovy_deg: f64,
    cam_xpos: &[f64; 3],
    cam_xmat: &[f64; 9],
    base: Option<(&[f64; 3], &[f64; 9])>,
    width: u32,
    height: u32,
) -> CameraCalibration {
    let t_world_from_camera = opencv_from_mujoco_camera(cam_xpos, cam_xmat);
    let t_base = base.map(|(p, r)| {
        mat4_mul(&rigid_inverse(&pose_to_mat4(p, r)), &t_world_from_camera)
    });
    CameraCalibration {
        width,
        height,
        fovy_deg,
        K: intrinsics(fovy_deg, width, height),
        T_world_from_camera: t_world_from_camera,
        T_robot_base_from_camera: t_base,
    }
}

/// Calibration of camera `cam_id` at the current kinematics of `data`.
pub fn camera_calibration<M: ModelType>(
    model: &MjModel,
    data: &MjData<M>,
    cam_id: usize,
    width: u32,
    height: u32,
) -> Result<CameraCalibration, RenderError> {
    let ncam = model.ffi().ncam as usize;
    if cam_id >= ncam {
        return Err(RenderError::UnknownCamera(format!("id {cam_id} (model has {ncam})")));
    }
    let fovy = model.cam_fovy()[cam_id];
    let base = model.name_to_id(MjtObjBase::mjOBJ_BODY, "robot0_base");
    let base_pose = base.map(|b| (&data.xpos()[b], &data.xmat()[b]));
    Ok(calibration_from_poses(
        fovy,
        &data.cam_xpos()[cam_id],
        &data.cam_xmat()[cam_id],
        base_pose,
        width,
        height,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intrinsics_match_robosuite_values() {
        // libero_port_notes §4.4: fovy 45° → f = 154.510 px at 128 px, 309.019 px at 256; wrist 75° → 83.406 at 128.
        let k = intrinsics(45.0, 128, 128);
        assert!((k[0][0] - 154.510).abs() < 1e-3 && (k[1][1] - 154.510).abs() < 1e-3);
        assert_eq!((k[0][2], k[1][2]), (64.0, 64.0));
        assert!((intrinsics(45.0, 256, 256)[0][0] - 309.019).abs() < 1e-3);
        assert!((intrinsics(75.0, 128, 128)[0][0] - 83.406).abs() < 1e-3);
        let wide = intrinsics(45.0, 320, 240);
        assert_eq!((wide[0][2], wide[1][2]), (160.0, 120.0));
        assert!((wide[0][0] - 0.5 * 240.0 / (22.5f64.to_radians()).tan()).abs() < 1e-9);
    }

    #[test]
    fn opencv_extrinsic_flips_y_and_z_of_the_mujoco_camera_frame() {
        // A camera at (1,2,3) with identity orientation looks along world −z with image-up +y.
        let t = opencv_from_mujoco_camera(&[1.0, 2.0, 3.0], &[1., 0., 0., 0., 1., 0., 0., 0., 1.]);
        assert_eq!(t[0], [1.0, 0.0, 0.0, 1.0]);
        assert_eq!(t[1], [0.0, -1.0, 0.0, 2.0]);
        assert_eq!(t[2], [0.0, 0.0, -1.0, 3.0]);
        // The OpenCV optical axis (+z) is the MuJoCo viewing direction (−z of the camera body).
        let point_ahead = [0.0, 0.0, 2.0];
        let w: Vec<f64> = (0..3).map(|r| (0..3).map(|c| t[r][c] * point_ahead[c]).sum::<f64>() + t[r][3]).collect();
        assert_eq!(w, vec![1.0, 2.0, 1.0]);
    }

    #[test]
    fn robot_base_extrinsic_composes_inverse_base_pose_with_camera_pose() {
        let base_pos = [-0.66, 0.0, 0.912];
        // base rotated 90° about z
        let base_rot = [0., -1., 0., 1., 0., 0., 0., 0., 1.];
        let cam_pos = [0.6586, 0.0, 1.6103];
        let cam_rot = [0., -0.6, 0.8, 1., 0., 0., 0., 0.8, 0.6];
        let c = calibration_from_poses(45.0, &cam_pos, &cam_rot, Some((&base_pos, &base_rot)), 256, 256);
        let back = mat4_mul(&pose_to_mat4(&base_pos, &base_rot), &c.T_robot_base_from_camera.unwrap());
        for r in 0..4 {
            for k in 0..4 {
                assert!((back[r][k] - c.T_world_from_camera[r][k]).abs() < 1e-12);
            }
        }
        let inv = mat4_mul(&rigid_inverse(&c.T_world_from_camera), &c.T_world_from_camera);
        for r in 0..4 {
            for k in 0..4 {
                assert!((inv[r][k] - if r == k { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
    }
}
