//! The wgpu renderer: one per process, shared by all episodes. Models are uploaded once
//! ([`Renderer::prepare_scene`]); a frame uploads only per-geom poses and per-camera uniforms, renders
//! every requested camera in one submission and reads RGB, linear depth and segmentation back.
//!
//! By job: this module opens the device and holds the renderer's state; `upload` makes a model's upload and shares
//! it between models of the same content, `buffers` assembles an upload's vertex and index buffers, `pipelines`
//! makes the render pipelines, `draws` turns a frame's state into per-geom and per-camera uniforms, and `frame`
//! encodes one frame and reads its images back.
mod buffers;
mod draws;
mod frame;
mod pipelines;
mod upload;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};

use crate::calib::CameraCalibration;
use crate::scene::{FrameState, Visibility};
use crate::RenderError;
use draws::{CameraUniform, DrawUniform};
use frame::FrameResources;
use pipelines::{PipelineKey, make_sky_pipeline};
use upload::{CachedUpload, GpuModel, upload_texture};

pub use upload::ModelHandle;

const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
const ID_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R32Uint;
const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Uniform slots are addressed with dynamic offsets; 256 is the largest alignment any backend asks.
const DRAW_STRIDE: u64 = 256;
const CAMERA_STRIDE: u64 = 1536;
const MAX_LIGHTS: usize = 9;
/// Segmentation ids of sites carry this bit so they never collide with geom ids.
pub const SEG_SITE_FLAG: u32 = 1 << 31;
/// Depth readback value of pixels with no surface (bit pattern of +inf).
const NO_SURFACE_BITS: u32 = 0x7f80_0000;

/// Which images a camera request wants back.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Outputs {
    pub rgb: bool,
    pub depth: bool,
    pub segmentation: bool,
}

impl Outputs {
    pub const ALL: Self = Self { rgb: true, depth: true, segmentation: true };
    pub const RGB_DEPTH: Self = Self { rgb: true, depth: true, segmentation: false };
    pub const RGB: Self = Self { rgb: true, depth: false, segmentation: false };
}

/// A camera by MuJoCo name or id.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CameraRef {
    Name(String),
    Id(usize),
}

/// One image set to render.
#[derive(Debug, Clone)]
pub struct CameraRequest {
    pub camera: CameraRef,
    pub width: u32,
    pub height: u32,
    pub outputs: Outputs,
}

impl CameraRequest {
    pub fn named(name: &str, width: u32, height: u32, outputs: Outputs) -> Self {
        Self { camera: CameraRef::Name(name.to_string()), width, height, outputs }
    }
}

/// The images of one camera; buffers are row-major with the top-left pixel first.
#[derive(Debug, Clone)]
pub struct CameraFrame {
    pub camera_id: usize,
    pub width: u32,
    pub height: u32,
    /// `H·W·3` bytes (empty unless requested).
    pub rgb: Vec<u8>,
    /// Planar depth along the optical axis in metres; pixels with no surface hold the far plane
    /// distance and are `false` in `depth_valid` (empty unless requested).
    pub depth_m: Vec<f32>,
    pub depth_valid: Vec<bool>,
    /// Private per-pixel id: `geom_id + 1` for geoms, `SEG_SITE_FLAG | (site_id + 1)` for sites,
    /// 0 for background (empty unless requested). Never for agents.
    pub segmentation: Vec<u32>,
    /// K and extrinsics (OpenCV convention) at this resolution.
    pub calibration: CameraCalibration,
}

/// Per-frame rendering options.
#[derive(Debug, Clone, Copy)]
pub struct RenderOptions {
    pub visibility: Visibility,
    /// Draw the model's skybox texture behind everything (MuJoCo default).
    pub skybox: bool,
    /// Largest on-screen error, in pixels, of a simplified mesh level (see [`crate::lod`]); the distance used
    /// is the nearest a mesh's bounding sphere can be to the camera. 0 draws every mesh exactly.
    pub mesh_lod_pixel_error: f32,
}

/// Default LOD budget: a quarter pixel, well inside the depth and silhouette tolerances the renderer is
/// validated to (see `server/render/tests/`).
pub const DEFAULT_MESH_LOD_PIXEL_ERROR: f32 = 0.25;

impl Default for RenderOptions {
    fn default() -> Self {
        Self { visibility: Visibility::ROBOSUITE, skybox: true, mesh_lod_pixel_error: DEFAULT_MESH_LOD_PIXEL_ERROR }
    }
}

struct Inner {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    shader: wgpu::ShaderModule,
    pipeline_layout: wgpu::PipelineLayout,
    /// Geometry pipelines by specialisation, made on first use (a scene's light list decides which).
    pipelines: Mutex<HashMap<PipelineKey, wgpu::RenderPipeline>>,
    sky: wgpu::RenderPipeline,
    camera_layout: wgpu::BindGroupLayout,
    draw_layout: wgpu::BindGroupLayout,
    texture_layout: wgpu::BindGroupLayout,
    sampler: wgpu::Sampler,
    dummy_2d: wgpu::TextureView,
    dummy_cube: wgpu::TextureView,
    frame: Mutex<FrameResources>,
    errors: Arc<Mutex<Vec<String>>>,
    next_model_id: AtomicU64,
    /// Foreground renders waiting for `frame`; background renders (the private video) let them go first.
    foreground_waiting: AtomicUsize,
    /// Uploads by compiled model, held weakly on both sides: an upload lives exactly as long as a world, a
    /// recorder or a caller holds its handle, so ended episodes leave no GPU memory behind.
    model_cache: Mutex<HashMap<usize, CachedUpload>>,
    /// Uploads by content ([`content_key`]), held weakly: every episode of a scene compiles its own model, and
    /// all of them share one upload of its meshes and textures (a LIBERO kitchen's are hundreds of MB) for as long
    /// as any of them holds it.
    content_cache: Mutex<HashMap<[u8; 32], (u64, Weak<GpuModel>)>>,
    /// Uploads alive now, however they were made ([`Renderer::live_uploads`]).
    live_uploads: Arc<AtomicUsize>,
}

/// Headless renderer. `Clone` shares the same device; `Send + Sync`.
#[derive(Clone)]
pub struct Renderer {
    inner: Arc<Inner>,
}

impl Renderer {
    /// Open a GPU: Vulkan first (lavapipe on CPU-only machines), GL/EGL as fallback. `WGPU_BACKEND`
    /// (`vulkan`, `gl`) overrides the choice.
    pub fn new() -> Result<Self, RenderError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::GL;
        let desc = desc.with_env();
        let instance = wgpu::Instance::new(desc);
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..Default::default()
        }))
        .map_err(|e| RenderError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let limits = wgpu::Limits::downlevel_defaults().using_resolution(adapter.limits());
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("libero-render"),
            required_features: wgpu::Features::empty(),
            required_limits: limits,
            ..Default::default()
        }))
        .map_err(|e| RenderError::Device(e.to_string()))?;
        let errors: Arc<Mutex<Vec<String>>> = Arc::default();
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            if let Ok(mut v) = sink.lock() {
                v.push(e.to_string());
            }
        }));
        Self::build(device, queue, info, errors)
    }

    /// Adapter name and backend, e.g. `llvmpipe (LLVM 15.0.6, 256 bits) / Vulkan`.
    pub fn adapter_description(&self) -> String {
        format!("{} / {:?}", self.inner.info.name, self.inner.info.backend)
    }

    fn build(
        device: wgpu::Device,
        queue: wgpu::Queue,
        info: wgpu::AdapterInfo,
        errors: Arc<Mutex<Vec<String>>>,
    ) -> Result<Self, RenderError> {
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("libero-render shader"),
            source: wgpu::ShaderSource::Wgsl(include_str!("../shader.wgsl").into()),
        });
        let uniform_entry = |size: u64| wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: true,
                min_binding_size: wgpu::BufferSize::new(size),
            },
            count: None,
        };
        let camera_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("camera"),
            entries: &[uniform_entry(size_of::<CameraUniform>() as u64)],
        });
        let draw_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("draw"),
            entries: &[uniform_entry(size_of::<DrawUniform>() as u64)],
        });
        let tex_entry = |binding, dim| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::FRAGMENT,
            ty: wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: true },
                view_dimension: dim,
                multisampled: false,
            },
            count: None,
        };
        let texture_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("textures"),
            entries: &[
                tex_entry(0, wgpu::TextureViewDimension::D2),
                tex_entry(1, wgpu::TextureViewDimension::Cube),
                wgpu::BindGroupLayoutEntry {
                    binding: 2,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("libero-render"),
            bind_group_layouts: &[Some(&camera_layout), Some(&draw_layout), Some(&texture_layout)],
            immediate_size: 0,
        });
        let sky = make_sky_pipeline(&device, &shader, &layout);
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("textures"),
            address_mode_u: wgpu::AddressMode::Repeat,
            address_mode_v: wgpu::AddressMode::Repeat,
            address_mode_w: wgpu::AddressMode::Repeat,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Linear,
            ..Default::default()
        });
        let white = [255u8; 4];
        let dummy_2d = upload_texture(&device, &queue, 1, 1, 1, &white, false, false);
        let dummy_cube = upload_texture(&device, &queue, 1, 1, 6, &white.repeat(6), false, false);
        Ok(Self {
            inner: Arc::new(Inner {
                device,
                queue,
                info,
                shader,
                pipeline_layout: layout,
                pipelines: Mutex::new(HashMap::new()),
                sky,
                camera_layout,
                draw_layout,
                texture_layout,
                sampler,
                dummy_2d: dummy_2d.create_view(&Default::default()),
                dummy_cube: dummy_cube.create_view(&wgpu::TextureViewDescriptor {
                    dimension: Some(wgpu::TextureViewDimension::Cube),
                    ..Default::default()
                }),
                frame: Mutex::new(FrameResources {
                    targets: Vec::new(),
                    draw_buf: None,
                    camera_buf: None,
                    readback: None,
                }),
                errors,
                next_model_id: AtomicU64::new(1),
                foreground_waiting: AtomicUsize::new(0),
                model_cache: Mutex::new(HashMap::new()),
                content_cache: Mutex::new(HashMap::new()),
                live_uploads: Arc::default(),
            }),
        })
    }


    /// Uploads (a scene's meshes and textures on the device) some handle still holds: what a released scene
    /// must leave at its earlier value.
    pub fn live_uploads(&self) -> usize {
        self.inner.live_uploads.load(Ordering::SeqCst)
    }

    /// Frees on the device what released uploads still hold there: wgpu destroys a dropped buffer or texture
    /// only when the device is next polled after its last use, so without this the last scene a caller released
    /// stays in memory (process memory on a software renderer) until the next render.
    pub fn release_freed(&self) -> Result<(), RenderError> {
        self.inner.device.poll(wgpu::PollType::wait_indefinitely()).map(drop).map_err(|e| RenderError::Readback(e.to_string()))
    }

    fn take_errors(&self) -> Result<(), RenderError> {
        let mut errs = self.inner.errors.lock().map_err(|e| RenderError::Validation(e.to_string()))?;
        if errs.is_empty() {
            Ok(())
        } else {
            let msg = errs.join("; ");
            errs.clear();
            Err(RenderError::Validation(msg))
        }
    }

    /// Render the requested cameras of one frame in a single GPU submission.
    pub fn render(
        &self,
        model: &ModelHandle,
        state: &FrameState,
        requests: &[CameraRequest],
        options: &RenderOptions,
    ) -> Result<Vec<CameraFrame>, RenderError> {
        let waiting = &self.inner.foreground_waiting;
        waiting.fetch_add(1, Ordering::SeqCst);
        self.render_locked(model, state, requests, options, Some(waiting))
    }

    /// [`render`](Self::render) for work nobody waits on (video frames): it yields the device to every
    /// foreground render that is waiting, so those wait for at most one background frame.
    pub fn render_background(
        &self,
        model: &ModelHandle,
        state: &FrameState,
        requests: &[CameraRequest],
        options: &RenderOptions,
    ) -> Result<Vec<CameraFrame>, RenderError> {
        while self.inner.foreground_waiting.load(Ordering::SeqCst) > 0 {
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        self.render_locked(model, state, requests, options, None)
    }

}
