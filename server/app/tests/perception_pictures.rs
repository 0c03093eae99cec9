//! Start pictures of the perception tasks: each task's scene (seeded placement, as `libero-agent render --bddl` composes
//! it) rendered from the 256×256 head camera, written to `target/test-artifacts/perception/<task>_head.png` so the
//! visual cue (colour, stripes, marks, pose, drink, buttons' paired objects) can be checked by eye. The test checks
//! what each picture must show: the camera's size in colour, not a flat frame, and every object of the task in it
//! (its segmentation pixels), at the pixel where the calibration projects the object's body, in colours that differ
//! from what surrounds it.
use std::collections::BTreeSet;
use std::process::Command;
use std::sync::Arc;

use libero_sim::AssetPaths;
use libero_sim::mujoco_rs::prelude::*;
use libero_sim::scene_setup::PreparedScene;
use libero_testkit::repo_root;
use serde_json::Value;

mod common;

/// `(task, BDDL stem)` of the perception tasks built so far.
const TASKS: &[(&str, &str)] = &[
    ("T01", "select_upright_marker"),
    ("T02", "select_between_condiments"),
    ("T03", "select_red_object"),
    ("T04", "select_striped_object"),
    ("T05", "select_marked_instance"),
    ("T06", "select_ball_shape"),
    ("T07", "select_cola_drink"),
    ("T08", "weigh_and_place_heaviest_mug"),
    ("T09", "select_highest_reflectance"),
    ("T10", "select_largest_cylinder"),
];

#[test]
fn perception_start_pictures_are_rendered_from_the_head_camera() {
    let root = repo_root();
    let out_dir = root.join("target/test-artifacts/perception");
    std::fs::create_dir_all(&out_dir).expect("artifact dir");
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    for (task, stem) in TASKS {
        let bddl = root.join(format!("tasks/bddl/{stem}.bddl"));
        let tmp = tempfile::tempdir().expect("tempdir");
        let out = Command::new(common::bin())
            .env("XDG_RUNTIME_DIR", std::env::temp_dir())
            .args(["render", "--camera", "head", "--size", "256", "--bddl"])
            .arg(&bddl)
            .arg("--out")
            .arg(tmp.path())
            .output()
            .expect("run libero-agent render");
        assert!(out.status.success(), "{task}: {}", String::from_utf8_lossy(&out.stderr));
        let png = std::fs::read(tmp.path().join("head/rgb.png")).expect("head/rgb.png");
        std::fs::write(out_dir.join(format!("{task}_head.png")), &png).expect("write artifact");
        let calib: Value =
            serde_json::from_slice(&std::fs::read(tmp.path().join("head/calibration.json")).expect("calibration")).expect("json");
        assert_eq!(calib["depth_valid_pixels"], 256 * 256, "{task}: every pixel sees geometry");

        // The picture is the camera's: its size, in colour, and a scene rather than a flat frame.
        let rgb = decode_png(&png, png::ColorType::Rgb, png::BitDepth::Eight);
        assert_eq!((rgb.width, rgb.height), (256, 256), "{task}");
        assert_eq!((calib["width"].as_u64(), calib["height"].as_u64()), (Some(256), Some(256)), "{task}");
        let colours: BTreeSet<&[u8]> = rgb.data.chunks(3).collect();
        assert!(colours.len() > 1000, "{task}: only {} colours: the picture is flat", colours.len());
        let seg_png = std::fs::read(tmp.path().join("head/segmentation.png")).expect("segmentation.png");
        let seg = decode_png(&seg_png, png::ColorType::Grayscale, png::BitDepth::Sixteen);
        assert_eq!((seg.width, seg.height), (256, 256), "{task}");
        let ids: Vec<u16> = seg.data.chunks(2).map(|b| u16::from_be_bytes([b[0], b[1]])).collect();

        // The scene as `render --bddl` composes it (seed 0, no init file): every object and fixture of the task
        // shows in the picture, where the calibration projects its body (measured: within a pixel), and looks unlike
        // what surrounds it.
        let prepared = PreparedScene::prepare(&bddl, &paths, 0, None).unwrap_or_else(|e| panic!("{task}: {e}"));
        let qpos = prepared.start_qpos().to_vec();
        let (scene, model) = (prepared.scene, Arc::new(prepared.model));
        let mut data = MjData::new(model.clone());
        data.qpos_mut().copy_from_slice(&qpos);
        data.forward();
        let camera = Camera::from_calibration(&calib);
        let parents = model.body_parentid();
        let under = |mut body: usize, root: usize| loop {
            if body == root {
                break true;
            }
            if body == 0 {
                break false;
            }
            body = parents[body] as usize;
        };
        assert!(!scene.objects.is_empty() || !scene.fixtures.is_empty(), "{task}: no objects");
        let mut candidate_colours = Vec::new();
        for object in scene.objects.iter().chain(&scene.fixtures) {
            let root_body = model.name_to_id(MjtObjBase::mjOBJ_BODY, &object.root_body).unwrap_or_else(|| panic!("{task}: no body {}", object.root_body));
            // Segmentation ids are geom id + 1 (sites carry the top bit).
            let geoms: BTreeSet<u16> =
                model.geom_bodyid().iter().enumerate().filter(|(_, b)| under(**b as usize, root_body)).map(|(g, _)| g as u16 + 1).collect();
            let pixels: Vec<(usize, usize)> =
                (0..ids.len()).filter(|i| geoms.contains(&ids[*i])).map(|i| (i % 256, i / 256)).collect();
            assert!(pixels.len() >= 20, "{task}: {} shows in {} pixels of the head picture", object.name, pixels.len());
            let (u, v) = camera.project(data.xpos()[root_body]);
            let nearest = pixels.iter().map(|(x, y)| ((*x as f64 + 0.5 - u).powi(2) + (*y as f64 + 0.5 - v).powi(2)).sqrt()).fold(f64::INFINITY, f64::min);
            assert!(nearest <= 3.0, "{task}: {} projects to ({u:.0}, {v:.0}), {nearest:.0} px from its nearest pixel", object.name);
            // Its pixels differ in colour from the pixels around it that are not it.
            let inside = mean_colour(&rgb.data, pixels.iter().map(|(x, y)| y * 256 + x));
            let ring: Vec<usize> = ring_around(&pixels, 4).into_iter().filter(|i| !geoms.contains(&ids[*i])).collect();
            let around = mean_colour(&rgb.data, ring.into_iter());
            let difference: f64 = inside.iter().zip(&around).map(|(a, b)| (a - b).abs()).sum();
            // (Summed over the channels, 0-765; the closest pair measured, a grey basket on the table, differs by ~29.)
            assert!(difference > 15.0, "{task}: {} has the colour of what surrounds it ({inside:?}, around: {around:?})", object.name);
            if object.name.starts_with("candidate_") {
                candidate_colours.push(inside);
            }
        }
        // The cue T03 asks about is in the picture: exactly one of its three candidates is red.
        if *task == "T03" {
            let red = candidate_colours.iter().filter(|[r, g, b]| *r > 2.0 * g && *r > 2.0 * b).count();
            assert_eq!((candidate_colours.len(), red), (3, 1), "T03: one red candidate among three: {candidate_colours:?}");
        }
    }
}

/// A decoded PNG of the kind `render` writes; any other kind fails.
struct Image {
    width: u32,
    height: u32,
    data: Vec<u8>,
}

fn decode_png(bytes: &[u8], colour: png::ColorType, depth: png::BitDepth) -> Image {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder.read_info().expect("png");
    let mut data = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut data).expect("png frame");
    assert_eq!((info.color_type, info.bit_depth), (colour, depth), "png kind");
    data.truncate(info.buffer_size());
    Image { width: info.width, height: info.height, data }
}

/// The pinhole camera of a `calibration.json` (OpenCV frame: x right, y down, z forward).
struct Camera {
    k: [[f64; 3]; 3],
    world_from_camera: [[f64; 4]; 4],
}

impl Camera {
    fn from_calibration(calib: &Value) -> Self {
        let rows = |v: &Value| -> Vec<Vec<f64>> {
            v.as_array().expect("matrix").iter().map(|r| r.as_array().expect("row").iter().map(|x| x.as_f64().expect("number")).collect()).collect()
        };
        let (k, t) = (rows(&calib["intrinsics"]["K"]), rows(&calib["T_world_from_camera"]));
        Camera {
            k: std::array::from_fn(|i| std::array::from_fn(|j| k[i][j])),
            world_from_camera: std::array::from_fn(|i| std::array::from_fn(|j| t[i][j])),
        }
    }

    /// The pixel coordinates (u right, v down, from the top-left corner) of a world point in front of the camera.
    fn project(&self, p: [f64; 3]) -> (f64, f64) {
        let t = &self.world_from_camera;
        let d = [p[0] - t[0][3], p[1] - t[1][3], p[2] - t[2][3]];
        // camera = Rᵀ (world − translation)
        let c: [f64; 3] = std::array::from_fn(|j| (0..3).map(|i| t[i][j] * d[i]).sum());
        assert!(c[2] > 0.0, "the point {p:?} is behind the camera");
        (self.k[0][0] * c[0] / c[2] + self.k[0][2], self.k[1][1] * c[1] / c[2] + self.k[1][2])
    }
}

fn mean_colour(rgb: &[u8], pixels: impl Iterator<Item = usize>) -> [f64; 3] {
    let (mut sum, mut n) = ([0.0; 3], 0.0_f64);
    for i in pixels {
        for c in 0..3 {
            sum[c] += rgb[i * 3 + c] as f64;
        }
        n += 1.0;
    }
    sum.map(|s| s / n.max(1.0))
}

/// The pixel indices within `r` pixels of a set of pixels (the set included), in a 256×256 picture.
fn ring_around(pixels: &[(usize, usize)], r: usize) -> BTreeSet<usize> {
    let mut out = BTreeSet::new();
    for (x, y) in pixels {
        for yy in y.saturating_sub(r)..=(y + r).min(255) {
            for xx in x.saturating_sub(r)..=(x + r).min(255) {
                out.insert(yy * 256 + xx);
            }
        }
    }
    out
}
