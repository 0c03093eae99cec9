//! Geometry check of depth + calibration together: pixels of a known box, back-projected through K and
//! `T_robot_base_from_camera` from our depth image, must land on that box's surface.
mod common;

use libero_render::calib::{mat4_mul, pose_to_mat4};
use libero_render::Renderer;
use mujoco_rs::prelude::*;

#[test]
fn backprojected_box_pixels_land_within_2mm_of_the_box_surface() {
    let renderer = Renderer::new().expect("renderer");
    let scene = common::reference_dir().join("kitchen3_stove_moka.xml");
    let model = common::load_model(&scene);
    let (frames, state) = common::render_ours(&renderer, &model);
    let mut data = MjData::new(model.clone());
    data.forward();
    let base = model.name_to_id(MjtObjBase::mjOBJ_BODY, "robot0_base").expect("robot0_base");
    let t_world_from_base = pose_to_mat4(&data.xpos()[base], &data.xmat()[base]);
    let mut checked_boxes = 0;
    for (k, frame) in frames.iter().enumerate() {
        let (w, h) = (frame.width as usize, frame.height as usize);
        let calib = &frame.calibration;
        let t_base_cam = calib.T_robot_base_from_camera.expect("robot base calibration");
        let t_world_cam = mat4_mul(&t_world_from_base, &t_base_cam);
        // The largest visible box geom in this view.
        let mut counts = std::collections::HashMap::<u32, usize>::new();
        for &s in &frame.segmentation {
            if s != 0 && s & libero_render::SEG_SITE_FLAG == 0 && model.geom_type()[(s - 1) as usize] as i32 == 6 /* mjGEOM_BOX */ {
                *counts.entry(s).or_default() += 1;
            }
        }
        let Some((&id, &n)) = counts.iter().max_by_key(|(_, n)| **n) else { continue };
        if n < 200 {
            continue;
        }
        let g = (id - 1) as usize;
        let size = model.geom_size()[g];
        let (gp, gr) = (state.geom_xpos[g], state.geom_xmat[g]);
        let (f, cx, cy) = (calib.K[0][0], calib.K[0][2], calib.K[1][2]);
        let mut worst = 0.0f64;
        let mut used = 0;
        for v in 1..h - 1 {
            for u in 1..w - 1 {
                let i = v * w + u;
                // interior pixels only: all four neighbours on the same geom
                if [i, i - 1, i + 1, i - w, i + w].iter().any(|&j| frame.segmentation[j] != id) || !frame.depth_valid[i] {
                    continue;
                }
                let z = frame.depth_m[i] as f64;
                let pc = [(u as f64 + 0.5 - cx) / f * z, (v as f64 + 0.5 - cy) / f * z, z];
                let pw: Vec<f64> = (0..3).map(|r| (0..3).map(|c| t_world_cam[r][c] * pc[c]).sum::<f64>() + t_world_cam[r][3]).collect();
                let d = [pw[0] - gp[0], pw[1] - gp[1], pw[2] - gp[2]];
                // box-local coordinates: R^T d (xmat row-major)
                let local: Vec<f64> = (0..3).map(|c| (0..3).map(|r| gr[3 * r + c] * d[r]).sum()).collect();
                let dist = (0..3).map(|a| local[a].abs() - size[a]).fold(f64::MIN, f64::max);
                worst = worst.max(dist.abs());
                used += 1;
            }
        }
        println!("camera {k}: box geom {g} size {size:?}: {used} interior pixels, worst distance to surface {:.5} m", worst);
        assert!(used > 100, "too few interior pixels on box geom {g}");
        assert!(worst < 0.002, "camera {k}: back-projected point {worst} m off box geom {g}");
        checked_boxes += 1;
    }
    assert!(checked_boxes > 0, "no box geom visible with enough pixels");
}
