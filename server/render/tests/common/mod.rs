//! Shared helpers of the validation tests: load the reference scenes, render them with our renderer
//! and with MuJoCo's (through the Python package in the test venv), and save both as artifacts.
#![allow(dead_code)]
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, OnceLock};

use libero_render::io::{encode_rgb_png, encode_segmentation_png, npy_f32_bytes};
use libero_render::{CameraFrame, CameraRequest, FrameState, Outputs, RenderOptions, Renderer};
use mujoco_rs::prelude::{MjData, MjModel};

pub const SIZE: u32 = 256;
pub const CAMERAS: [&str; 2] = ["agentview", "robot0_eye_in_hand"];

pub use libero_testkit::repo_root;

/// The compiled LIBERO reference scenes recorded from the real Python stack: the repository's
/// `tests/reference/ref/` (provenance in `tests/reference/README.md`).
pub fn reference_dir() -> PathBuf {
    repo_root().join("tests/reference/ref")
}

/// The compiled LIBERO scenes of `tests/reference/ref/` (sorted).
pub fn scenes() -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(reference_dir())
        .unwrap_or_else(|e| panic!("{}: {e}", reference_dir().display()))
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "xml"))
        .collect();
    v.sort();
    v
}

pub fn artifacts_dir() -> PathBuf {
    repo_root().join("test-artifacts/render")
}

pub use libero_testkit::cache_dir;

/// The test venv's Python (the render validation needs its `mujoco` package).
pub use libero_testkit::venv_python;

pub fn load_model(xml: &Path) -> Arc<MjModel> {
    let cache = cache_dir();
    let text = std::fs::read_to_string(xml)
        .expect("read xml")
        .replace("${ROBOSUITE_ASSETS}", &cache.join("robosuite-1.4.0/assets").to_string_lossy())
        .replace("${LIBERO_ASSETS}", &cache.join("libero-assets-0.1.0/assets").to_string_lossy());
    Arc::new(MjModel::from_xml_string(&text).expect("compile xml (assets: run python3 scripts/setup.py)"))
}

/// Our frames of both cameras at the model's default state (qpos0 + mj_forward).
pub fn render_ours(renderer: &Renderer, model: &Arc<MjModel>) -> (Vec<CameraFrame>, FrameState) {
    render_ours_with(renderer, model, &RenderOptions::default())
}

/// [`render_ours`] with other options (exact meshes: `mesh_lod_pixel_error: 0.0`).
pub fn render_ours_with(renderer: &Renderer, model: &Arc<MjModel>, options: &RenderOptions) -> (Vec<CameraFrame>, FrameState) {
    let handle = renderer.prepare_model(model).expect("prepare model");
    let mut data = MjData::new(model.clone());
    data.forward();
    let mut state = FrameState::from_mujoco(model, &data);
    state.apply_robosuite_site_hiding(handle.scene());
    let reqs: Vec<CameraRequest> = CAMERAS.iter().map(|c| CameraRequest::named(c, SIZE, SIZE, Outputs::ALL)).collect();
    let frames = renderer.render(&handle, &state, &reqs, options).expect("render");
    (frames, state)
}

/// MuJoCo's images of one camera.
pub struct Reference {
    pub rgb: Vec<u8>,
    pub depth_m: Vec<f32>,
    pub seg: Vec<u32>,
}

fn read_npy<T: Copy>(path: &Path, elem: usize, parse: impl Fn(&[u8]) -> T) -> Vec<T> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    bytes[10 + hlen..].chunks_exact(elem).map(parse).collect()
}

fn read_png_rgb(path: &Path) -> Vec<u8> {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).expect("open png")));
    let mut reader = dec.read_info().expect("png header");
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).expect("png frame");
    buf.truncate(info.buffer_size());
    match info.color_type {
        png::ColorType::Rgba => buf.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect(),
        _ => buf,
    }
}

/// Render (when not cached) MuJoCo's reference images into the artifacts folder and read them.
pub fn reference(scene: &Path) -> Vec<Reference> {
    let name = scene.file_stem().unwrap().to_string_lossy().to_string();
    let out = artifacts_dir().join(&name).join("mujoco");
    let script = repo_root().join("tests/render_validation/mujoco_reference.py");
    let mtime = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    // Reuse MuJoCo's images when they are newer than both the scene and the script (they are slow).
    let fresh = match (mtime(&out.join("meta.json")), mtime(scene), mtime(&script)) {
        (Some(m), Some(a), Some(b)) => m > a && m > b,
        _ => false,
    };
    let python = venv_python(); // fails loudly without the test venv, cached or not
    let status = (!fresh).then(|| {
        Command::new(&python)
            .arg(&script)
            .args(["render", "--xml"])
            .arg(scene)
            .arg("--out")
            .arg(&out)
            .args(["--size", &SIZE.to_string()])
            .status()
            .expect("spawn reference renderer")
    });
    assert!(status.is_none_or(|s| s.success()), "MuJoCo reference render failed for {name}");
    CAMERAS
        .iter()
        .map(|c| {
            let d = out.join(c);
            Reference {
                rgb: read_png_rgb(&d.join("rgb.png")),
                depth_m: read_npy(&d.join("depth_m.npy"), 4, |b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                seg: read_npy(&d.join("seg.npy"), 4, |b| u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            }
        })
        .collect()
}

/// Save our images next to MuJoCo's.
pub fn save_ours(scene: &Path, frames: &[CameraFrame]) {
    let name = scene.file_stem().unwrap().to_string_lossy().to_string();
    for (c, f) in CAMERAS.iter().zip(frames) {
        let d = artifacts_dir().join(&name).join("ours").join(c);
        std::fs::create_dir_all(&d).expect("artifacts dir");
        std::fs::write(d.join("rgb.png"), encode_rgb_png(f.width, f.height, &f.rgb).expect("png")).expect("write");
        std::fs::write(d.join("depth_m.npy"), npy_f32_bytes(f.height, f.width, &f.depth_m)).expect("write");
        std::fs::write(d.join("segmentation.png"), encode_segmentation_png(f.width, f.height, &f.segmentation).expect("png"))
            .expect("write");
    }
}

/// Everything the metric tests compare, computed once per test binary.
pub struct SceneComparison {
    pub name: String,
    /// With the default options, as episodes render.
    pub ours: Vec<CameraFrame>,
    /// With exact meshes (no levels of detail).
    pub ours_exact: Vec<CameraFrame>,
    pub reference: Vec<Reference>,
}

pub fn comparisons() -> &'static [SceneComparison] {
    static ALL: OnceLock<Vec<SceneComparison>> = OnceLock::new();
    ALL.get_or_init(|| {
        let renderer = Renderer::new().expect("renderer");
        scenes()
            .iter()
            .map(|scene| {
                let model = load_model(scene);
                let (ours, _) = render_ours(&renderer, &model);
                let exact = RenderOptions { mesh_lod_pixel_error: 0.0, ..RenderOptions::default() };
                let (ours_exact, _) = render_ours_with(&renderer, &model, &exact);
                save_ours(scene, &ours);
                let reference = reference(scene);
                SceneComparison { name: scene.file_stem().unwrap().to_string_lossy().to_string(), ours, ours_exact, reference }
            })
            .collect()
    })
}

pub fn psnr(a: &[u8], b: &[u8]) -> f64 {
    let mse: f64 = a.iter().zip(b).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum::<f64>() / a.len() as f64;
    if mse == 0.0 { f64::INFINITY } else { 10.0 * (255.0f64 * 255.0 / mse).log10() }
}

pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}
