//! `libero-agent bench render`: frames per second of both cameras × (RGB + depth) at 256×256 on a LIBERO
//! kitchen scene, beside MuJoCo's own renderer (PyPI `mujoco`, software GL) timed on the same scene in
//! the same run.
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, bail};
use libero_render::{CameraRequest, FrameState, Outputs, RenderOptions, Renderer};
use libero_sim::mujoco_rs::prelude::*;
use serde_json::{Value, json};

/// Arguments of `bench render`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchRenderArgs {
    /// Print only the JSON result.
    #[arg(long)]
    pub json: bool,
    /// Scene MJCF (`${ROBOSUITE_ASSETS}`/`${LIBERO_ASSETS}` placeholders allowed); default: LIBERO's
    /// `libero_90/KITCHEN_SCENE3_turn_on_the_stove` composed from its stock BDDL (both renderers load the
    /// same MJCF).
    #[arg(long)]
    pub xml: Option<PathBuf>,
    /// Timed frames per renderer.
    #[arg(long, default_value_t = 200)]
    pub frames: usize,
    #[arg(long, default_value_t = 256)]
    pub size: u32,
    /// Skip MuJoCo's renderer (no Python needed).
    #[arg(long)]
    pub no_mujoco: bool,
}

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

const DEFAULT_SUITE: &str = "libero_90";
const DEFAULT_TASK: &str = "KITCHEN_SCENE3_turn_on_the_stove";

/// The default kitchen scene composed from its stock BDDL, written as MJCF for both renderers.
fn default_scene(dir: &Path) -> anyhow::Result<PathBuf> {
    let paths = libero_sim::AssetPaths::discover()?;
    let bddl = paths.stock_bddl(DEFAULT_SUITE, DEFAULT_TASK);
    let scene = libero_sim::compose::compose_file(&bddl, &paths).with_context(|| format!("composing {}", bddl.display()))?;
    let path = dir.join(format!("{DEFAULT_TASK}.xml"));
    std::fs::write(&path, &scene.mjcf).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

fn venv_python() -> PathBuf {
    let cache = std::env::var_os("LIBERO_AGENT_CACHE")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(std::env::var("HOME").unwrap_or_default()).join(".cache/libero-agent"));
    cache.join("pyenv/bin/python")
}

const CAMERAS: [&str; 2] = ["agentview", "robot0_eye_in_hand"];

fn bench_ours(xml: &Path, frames: usize, size: u32) -> anyhow::Result<Value> {
    let paths = libero_sim::AssetPaths::discover()?;
    let text = std::fs::read_to_string(xml).with_context(|| format!("reading {}", xml.display()))?;
    let mut model = MjModel::from_xml_string(&paths.substitute_placeholders(&text))?;
    libero_render::scene::robosuite_hide_sites(&mut model);
    let model = Arc::new(model);
    let mut data = MjData::new(model.clone());
    data.forward();
    let t_init = Instant::now();
    let renderer = Renderer::new()?;
    let init_s = t_init.elapsed().as_secs_f64();
    let t_prep = Instant::now();
    let handle = renderer.prepare_model(&model)?;
    let prepare_s = t_prep.elapsed().as_secs_f64();
    let reqs: Vec<CameraRequest> = CAMERAS.iter().map(|c| CameraRequest::named(c, size, size, Outputs::RGB_DEPTH)).collect();
    let opts = RenderOptions::default();
    for _ in 0..5 {
        renderer.render(&handle, &FrameState::from_mujoco(&model, &data), &reqs, &opts)?;
    }
    let t0 = Instant::now();
    let c0 = process_cpu_s();
    for _ in 0..frames {
        // A frame includes reading the poses, as an episode does after each action.
        let state = FrameState::from_mujoco(&model, &data);
        let out = renderer.render(&handle, &state, &reqs, &opts)?;
        std::hint::black_box(&out);
    }
    let wall = t0.elapsed().as_secs_f64();
    let cpu = process_cpu_s() - c0;
    #[cfg(feature = "episode-serve")]
    let publication = bench_publication(&renderer, &handle, &model, &data, (frames / 4).max(20), size)?;
    #[cfg(not(feature = "episode-serve"))]
    let publication = Value::Null;
    Ok(json!({
        "renderer": format!("libero-render wgpu ({})", renderer.adapter_description()),
        "build": if cfg!(debug_assertions) { "debug" } else { "release" },
        "frames": frames, "cameras": CAMERAS, "size": size, "outputs": "rgb+depth",
        "wall_s": wall, "fps": frames as f64 / wall, "cpu_s": cpu, "fps_per_cpu_s": frames as f64 / cpu,
        "renderer_init_s": init_s, "prepare_model_s": prepare_s,
        "observation_publication": publication,
    }))
}

/// The whole level-3 observation publication an episode does after each call, beside the bare render: both
/// cameras (RGB + depth), then PNGs, `.npy` depth, masks and previews, `observation.json`, the evaluator-private
/// copy and the atomic swap into a workspace (`libero_episode`'s own publisher, on a temporary workspace).
#[cfg(feature = "episode-serve")]
fn bench_publication(
    renderer: &Renderer,
    handle: &libero_render::ModelHandle,
    model: &Arc<MjModel>,
    data: &MjData<Arc<MjModel>>,
    frames: usize,
    size: u32,
) -> anyhow::Result<Value> {
    use libero_episode::observation::{CameraFrame, Frame, Level, RgbImage, RobotReadout};
    use libero_episode::publish::ObservationPublisher;
    let dir = tempfile::tempdir().context("creating a temporary workspace")?;
    let (workspace, private) = (dir.path().join("workspace"), dir.path().join("private"));
    std::fs::create_dir_all(&workspace)?;
    std::fs::create_dir_all(&private)?;
    let mut publisher = ObservationPublisher::open(&workspace)?;
    let reqs: Vec<CameraRequest> = CAMERAS.iter().map(|c| CameraRequest::named(c, size, size, Outputs::RGB_DEPTH)).collect();
    let opts = RenderOptions::default();
    let (mut render_ms, mut publish_ms, mut total_ms) = (Vec::new(), Vec::new(), Vec::new());
    for frame_index in 0..frames as u64 {
        let t0 = Instant::now();
        let cams = renderer.render(handle, &FrameState::from_mujoco(model, data), &reqs, &opts)?;
        let t1 = Instant::now();
        let mut cams = cams.into_iter().map(|f| CameraFrame {
            image: RgbImage { width: f.width, height: f.height, rgb: f.rgb },
            depth_m: f.depth_m,
            depth_valid: f.depth_valid,
            intrinsic_matrix_3x3: f.calibration.K,
            t_robot_base_from_camera: f.calibration.T_robot_base_from_camera.unwrap_or_default(),
        });
        let (Some(head), Some(wrist)) = (cams.next(), cams.next()) else { bail!("expected two camera frames") };
        let frame = Frame { frame_index, robot: RobotReadout::default(), head, wrist, task_reference: None };
        publisher.publish(&frame, Level::L3, Some(&private))?;
        let t2 = Instant::now();
        render_ms.push((t1 - t0).as_secs_f64() * 1e3);
        publish_ms.push((t2 - t1).as_secs_f64() * 1e3);
        total_ms.push((t2 - t0).as_secs_f64() * 1e3);
    }
    let p50 = |v: &mut Vec<f64>| crate::bench_mcp::percentile_ms(v, 50.0);
    let total_p50 = p50(&mut total_ms);
    Ok(json!({
        "level": 3,
        "frames": frames,
        "render_ms_p50": p50(&mut render_ms),
        "publish_ms_p50": p50(&mut publish_ms),
        "render_plus_publish_ms_p50": total_p50,
        "observations_per_s_p50": 1e3 / total_p50,
        "what": "render both cameras, then PNG, .npy, masks, previews, observation.json, the private copy and the atomic swap",
    }))
}

fn bench_mujoco(xml: &Path, frames: usize, size: u32) -> anyhow::Result<Value> {
    let py = venv_python();
    if !py.exists() {
        bail!(
            "{} is missing: timing MuJoCo's renderer needs the test venv; run `python3 scripts/setup.py --test` (or pass --no-mujoco)",
            py.display()
        );
    }
    let script = repo_root().join("tests/render_validation/mujoco_reference.py");
    let mut cmd = Command::new(&py);
    cmd.arg(&script).args(["bench", "--xml"]).arg(xml).args(["--size", &size.to_string(), "--frames", &frames.to_string()]);
    let out = cmd.output().with_context(|| format!("running {}", script.display()))?;
    if !out.status.success() {
        bail!("MuJoCo renderer benchmark failed: {}", String::from_utf8_lossy(&out.stderr));
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout.lines().rev().find(|l| l.trim_start().starts_with('{')).unwrap_or("");
    serde_json::from_str(line).with_context(|| format!("parsing MuJoCo benchmark output: {stdout}"))
}

/// Run `bench render`.
/// The figures the speedups compare, of [`bench_ours`]'s report and of `mujoco_reference.py bench`'s (kept as JSON:
/// a report without them, or none at all, gives no speedup).
#[derive(serde::Deserialize, Default)]
struct Timing {
    #[serde(default)]
    fps: Value,
    #[serde(default)]
    cpu_s: Value,
}

impl Timing {
    fn of(report: &Value) -> Self {
        <Self as serde::Deserialize>::deserialize(report).unwrap_or_default()
    }
}

pub fn run(args: &BenchRenderArgs) -> anyhow::Result<()> {
    let tmp = tempfile::tempdir().context("creating a temporary directory")?;
    let xml = match &args.xml {
        Some(p) if !p.exists() => bail!("scene {} not found", p.display()),
        Some(p) => p.clone(),
        None => default_scene(tmp.path())?,
    };
    let ours = bench_ours(&xml, args.frames, args.size)?;
    let mujoco = if args.no_mujoco { Value::Null } else { bench_mujoco(&xml, args.frames, args.size)? };
    let ratio = |a: Option<f64>, b: Option<f64>| match (a, b) {
        (Some(a), Some(b)) if b > 0.0 => json!(a / b),
        _ => Value::Null,
    };
    let (o, m) = (Timing::of(&ours), Timing::of(&mujoco));
    let speedup = ratio(o.fps.as_f64(), m.fps.as_f64());
    // CPU time of all threads (both rasterisers are multi-threaded): steadier than wall time on a shared machine.
    let speedup_cpu = ratio(o.cpu_s.as_f64().map(|c| 1.0 / c), m.cpu_s.as_f64().map(|c| 1.0 / c));
    let result = json!({
        "benchmark": "render",
        "scene": xml.file_name().map(|s| s.to_string_lossy().to_string()),
        "workload": "per frame: both cameras (agentview, robot0_eye_in_hand) x (RGB + depth)",
        "libero_render": ours,
        "mujoco": mujoco,
        "speedup_vs_mujoco": speedup,
        "speedup_vs_mujoco_cpu_time": speedup_cpu,
        "goal_speedup": 3.0,
    });
    if args.json {
        println!("{}", serde_json::to_string(&result)?);
    } else {
        println!("{}", serde_json::to_string_pretty(&result)?);
    }
    Ok(())
}

/// CPU seconds used by this process so far, all threads (the rasteriser's worker threads included).
fn process_cpu_s() -> f64 {
    // SAFETY: getrusage writes into the zeroed struct we own.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) } != 0 {
        return f64::NAN;
    }
    let t = |tv: libc::timeval| tv.tv_sec as f64 + tv.tv_usec as f64 * 1e-6;
    t(usage.ru_utime) + t(usage.ru_stime)
}
