//! `libero-agent render`: render a LIBERO scene (BDDL + init state, or a compiled MJCF) from its cameras
//! and write, per camera, `rgb.png`, `depth_m.npy`, `segmentation.png` and `calibration.json`.
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, bail};
use libero_render::io::{encode_rgb_png, encode_segmentation_png, npy_f32_bytes, write_atomic};
use libero_render::{CameraFrame, CameraRequest, FrameState, Outputs, RenderOptions, Renderer};
use libero_sim::mujoco_rs::prelude::*;
use serde_json::json;

/// Which cameras to write.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum CameraChoice {
    Head,
    Wrist,
    All,
}

/// Arguments of `render`.
#[derive(Debug, Clone, clap::Args)]
pub struct RenderArgs {
    /// BDDL problem file; the scene is composed as LIBERO does.
    #[arg(long, conflicts_with = "xml", required_unless_present = "xml")]
    pub bddl: Option<PathBuf>,
    /// LIBERO init-state file (`.pruned_init` / `.init`) for `--bddl`.
    #[arg(long, requires = "bddl")]
    pub init_file: Option<PathBuf>,
    /// Row of the init-state file.
    #[arg(long, default_value_t = 0)]
    pub init_index: usize,
    /// LIBERO's `env.seed` for the reset-time placement with `--bddl` (fixtures always; objects too when no
    /// `--init-file` is given, as for tasks that start from the seeded placement)
    #[arg(long, default_value_t = 0, requires = "bddl")]
    pub seed: u32,
    /// A compiled MJCF (e.g. `tests/reference/ref/*.xml`; `${ROBOSUITE_ASSETS}`/`${LIBERO_ASSETS}` are substituted).
    #[arg(long)]
    pub xml: Option<PathBuf>,
    /// Keyframe of `--xml` to render (default: the model's default state).
    #[arg(long, requires = "xml")]
    pub keyframe: Option<usize>,
    #[arg(long, value_enum, default_value_t = CameraChoice::All)]
    pub camera: CameraChoice,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = 256)]
    pub size: u32,
    /// Output directory; gets `head/` and/or `wrist/`.
    #[arg(long)]
    pub out: PathBuf,
}

/// MuJoCo camera name of each published camera.
const CAMERAS: [(&str, &str, CameraChoice); 2] =
    [("head", "agentview", CameraChoice::Head), ("wrist", "robot0_eye_in_hand", CameraChoice::Wrist)];

/// A model at the state to render, with robosuite's site visibility already applied to its colours.
struct Posed {
    model: Arc<MjModel>,
    state: FrameState,
}

fn posed_from_xml(xml: &Path, keyframe: Option<usize>) -> anyhow::Result<Posed> {
    let paths = libero_sim::AssetPaths::discover()?;
    let text = std::fs::read_to_string(xml).with_context(|| format!("reading {}", xml.display()))?;
    let mut model = MjModel::from_xml_string(&paths.substitute_placeholders(&text))
        .with_context(|| format!("compiling {}", xml.display()))?;
    libero_render::scene::robosuite_hide_sites(&mut model);
    let model = Arc::new(model);
    let mut data = MjData::new(model.clone());
    if let Some(k) = keyframe {
        let nkey = model.ffi().nkey as usize;
        if k >= nkey {
            bail!("--keyframe {k}: the model has {nkey} keyframes");
        }
        data.reset_keyframe(k)?;
    }
    data.forward();
    let state = FrameState::from_mujoco(&model, &data);
    Ok(Posed { model, state })
}

fn posed_from_bddl(bddl: &Path, init_file: Option<&Path>, init_index: usize, seed: u32) -> anyhow::Result<Posed> {
    use libero_sim::placement::update_visual_sites;
    use libero_sim::scene_setup::PreparedScene;
    let paths = libero_sim::AssetPaths::discover()?;
    let prepared = PreparedScene::prepare(bddl, &paths, seed, init_file.map(|f| (f, init_index)))
        .with_context(|| format!("setting up {}", bddl.display()))?;
    let nq = prepared.model.ffi().nq as usize;
    let qpos = prepared.start_qpos().to_vec();
    let qvel = prepared.start_row[1 + nq..].to_vec();
    let (scene, mut model) = (prepared.scene, prepared.model);
    // robosuite's reset hides robot/gripper/object sites before LIBERO toggles the stove burner.
    libero_render::scene::robosuite_hide_sites(&mut model);
    update_visual_sites(&scene, &mut model, &qpos)?;
    let model = Arc::new(model);
    let mut data = MjData::new(model.clone());
    data.qpos_mut().copy_from_slice(&qpos);
    data.qvel_mut().copy_from_slice(&qvel);
    data.forward();
    let state = FrameState::from_mujoco(&model, &data);
    Ok(Posed { model, state })
}

fn mat_json(m: &[[f64; 4]; 4]) -> serde_json::Value {
    json!(m.iter().map(|r| r.to_vec()).collect::<Vec<_>>())
}

/// Write one camera's files into `dir`.
pub fn write_camera_dir(dir: &Path, camera_name: &str, frame: &CameraFrame) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let (w, h) = (frame.width, frame.height);
    write_atomic(&dir.join("rgb.png"), &encode_rgb_png(w, h, &frame.rgb)?)?;
    write_atomic(&dir.join("depth_m.npy"), &npy_f32_bytes(h, w, &frame.depth_m))?;
    write_atomic(&dir.join("segmentation.png"), &encode_segmentation_png(w, h, &frame.segmentation)?)?;
    let c = &frame.calibration;
    let calib = json!({
        "camera": camera_name,
        "width": w,
        "height": h,
        "fovy_deg": c.fovy_deg,
        "intrinsics": {"K": c.K, "fx": c.K[0][0], "fy": c.K[1][1], "cx": c.K[0][2], "cy": c.K[1][2]},
        "convention": "OpenCV camera frame (x right, y down, z forward); image origin top-left; pixel (u, v) centre at (u+0.5, v+0.5)",
        "T_world_from_camera": mat_json(&c.T_world_from_camera),
        "T_robot_base_from_camera": c.T_robot_base_from_camera.as_ref().map(mat_json),
        "depth_valid_pixels": frame.depth_valid.iter().filter(|v| **v).count(),
    });
    write_atomic(&dir.join("calibration.json"), serde_json::to_string_pretty(&calib)?.as_bytes())?;
    Ok(())
}

/// Run `render`.
pub fn run(args: &RenderArgs) -> anyhow::Result<()> {
    if args.size == 0 || args.size > 4096 {
        bail!("--size must be between 1 and 4096");
    }
    let posed = match (&args.xml, &args.bddl) {
        (Some(xml), _) => posed_from_xml(xml, args.keyframe)?,
        (None, Some(bddl)) => posed_from_bddl(bddl, args.init_file.as_deref(), args.init_index, args.seed)?,
        (None, None) => bail!("give --bddl FILE or --xml FILE"),
    };
    let renderer = Renderer::new()?;
    let handle = renderer.prepare_model(&posed.model)?;
    let chosen: Vec<_> = CAMERAS.iter().filter(|(_, _, c)| args.camera == CameraChoice::All || args.camera == *c).collect();
    let requests: Vec<CameraRequest> =
        chosen.iter().map(|(_, mj, _)| CameraRequest::named(mj, args.size, args.size, Outputs::ALL)).collect();
    let frames = renderer.render(&handle, &posed.state, &requests, &RenderOptions::default())?;
    for ((dir, mj, _), frame) in chosen.iter().zip(&frames) {
        write_camera_dir(&args.out.join(dir), mj, frame)?;
        println!("{}", args.out.join(dir).display());
    }
    Ok(())
}
