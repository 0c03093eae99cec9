//! The wgpu renderer: one per process, shared by all episodes. Models are uploaded once
//! ([`Renderer::prepare_scene`]); a frame uploads only per-geom poses and per-camera uniforms, renders
//! every requested camera in one submission and reads RGB, linear depth and segmentation back.
use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};

use bytemuck::{Pod, Zeroable};
use glam::{Mat3, Mat4, Vec3};
use mujoco_rs::prelude::MjModel;

use crate::calib::{CameraCalibration, calibration_from_poses};
use crate::geometry::{self, Vertex};
use crate::lod;
use crate::scene::{FrameState, GeomKind, LightKind, SceneModel, TextureKind, Visibility};
use crate::RenderError;

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

/// A model uploaded to the GPU. Cheap to clone; keep one per compiled model.
#[derive(Clone)]
pub struct ModelHandle {
    id: u64,
    gpu: Arc<GpuModel>,
}

impl ModelHandle {
    /// The uploaded scene's description, without mesh vertices and texture pixels ([`SceneModel::without_bulk_data`]).
    pub fn scene(&self) -> &Arc<SceneModel> {
        &self.gpu.scene
    }
    /// Whether both handles use the same upload (episodes of one scene share theirs).
    pub fn shares_upload_with(&self, other: &ModelHandle) -> bool {
        Arc::ptr_eq(&self.gpu, &other.gpu)
    }
    /// Process-unique id of this upload.
    pub fn id(&self) -> u64 {
        self.id
    }
    /// Triangles of a geom's exact shape, then of each simplified level (fine to coarse); `None` for a geom
    /// that is not drawn.
    pub fn geom_triangle_levels(&self, geom: usize) -> Option<Vec<u32>> {
        let shape = self.gpu.geom_shapes.get(geom)?.as_ref()?;
        let levels = shape.lods.ranges().iter().map(|l| l.index_count / 3);
        Some(std::iter::once(shape.vertex_count / 3).chain(levels).collect())
    }
}

/// What to draw for one geom or site.
#[derive(Clone, Copy)]
struct Shape {
    /// Range in the model's index buffer.
    first_vertex: u32,
    vertex_count: u32,
    /// Object scale applied before the pose (unit primitives are scaled by size).
    scale: [f32; 3],
    /// Object coordinates are metric (meshes, capsules): texgen divides by size like MuJoCo's
    /// "pre-scaled" geoms.
    prescaled: bool,
    /// Bounding-sphere radius in object units (scaled by `scale`), for per-camera frustum culling.
    radius: f32,
    /// Simplified levels of a mesh (fine to coarse), chosen per camera by [`RenderOptions::mesh_lod_pixel_error`].
    lods: LodRanges,
    /// The exact mesh's pieces (start and end in [`GpuModel::chunks`]), for culling a large mesh part by part.
    chunks: (u32, u32),
}

/// A spatially compact piece of a large mesh's exact index range, with its bounding sphere (object frame).
#[derive(Debug, Clone, Copy)]
struct Chunk {
    first_index: u32,
    index_count: u32,
    center: [f32; 3],
    radius: f32,
}

/// Meshes with at least this many triangles are cut into chunks of [`CHUNK_TRIANGLES`]: a room's walls hold the
/// camera inside their bounding sphere (so they are drawn exactly and never culled whole), yet most of them lies
/// outside any one camera's view.
const CHUNK_MIN_TRIANGLES: usize = 4096;
const CHUNK_TRIANGLES: usize = 1024;

/// Up to four simplified levels of one mesh inside the model's index buffer (fine to coarse).
#[derive(Clone, Copy, Default)]
struct LodRanges {
    levels: [lod::LevelRange; lod::LEVEL_ERRORS_M.len()],
    count: usize,
}

impl LodRanges {
    fn ranges(&self) -> &[lod::LevelRange] {
        &self.levels[..self.count]
    }
}

/// Interleaves the low 10 bits of three coordinates (a Morton code: nearby points get nearby codes).
fn morton3(q: [f32; 3]) -> u32 {
    let spread = |v: f32| {
        let mut x = (v.clamp(0.0, 1023.0) as u32) & 0x3ff;
        x = (x | (x << 16)) & 0x0300_00ff;
        x = (x | (x << 8)) & 0x0300_f00f;
        x = (x | (x << 4)) & 0x030c_30c3;
        (x | (x << 2)) & 0x0924_9249
    };
    spread(q[0]) | (spread(q[1]) << 1) | (spread(q[2]) << 2)
}

/// A mesh whose corners carry on average at least this many distinct normals is simplified as faceted.
const FACETED_NORMALS_PER_CORNER: usize = 2;

/// The model's shared vertex and index buffers as they are assembled.
#[derive(Default)]
struct GeometryBuilder {
    vertices: Vec<Vertex>,
    indices: Vec<u32>,
    seen: HashMap<[u32; 8], u32>,
    chunks: Vec<Chunk>,
}

impl GeometryBuilder {
    /// Appends a triangle soup, sharing identical corners; returns its index range.
    fn push_soup(&mut self, soup: Vec<Vertex>) -> (u32, u32) {
        let first = self.indices.len() as u32;
        for vert in soup {
            self.push_vertex(vert);
        }
        (first, self.indices.len() as u32 - first)
    }

    /// Appends a mesh and its simplified levels.
    ///
    /// Normal seams would stop most collapses: faceted meshes (robosuite's Panda links among them) carry a normal
    /// per face corner and never got a coarser level. So the simplifier works on corners welded by position and
    /// texture coordinate, and each corner of a simplified triangle takes, of the normals the mesh had there, the
    /// one closest to the simplified triangle's own normal. Smooth meshes that carry a 2D texture by their own
    /// texture coordinates (`uv_textured`) keep their normal seams: simplifying across them distorts the texture.
    fn push_mesh(&mut self, soup: Vec<Vertex>, uv_textured: bool) -> ((u32, u32), LodRanges, std::ops::Range<u32>) {
        let weld_key = |v: &Vertex, with_normal: bool| -> [u32; 8] {
            let n = if with_normal { v.normal } else { [0.0; 3] };
            bytemuck::cast([v.pos[0], v.pos[1], v.pos[2], n[0], n[1], n[2], v.uv[0], v.uv[1]])
        };
        let corners_with_normal: HashSet<[u32; 8]> = soup.iter().map(|v| weld_key(v, true)).collect();
        let corners: HashSet<[u32; 8]> = soup.iter().map(|v| weld_key(v, false)).collect();
        let faceted = corners_with_normal.len() >= FACETED_NORMALS_PER_CORNER * corners.len();
        let weld = faceted || !uv_textured;
        let mut welded_of: HashMap<[u32; 8], u32> = HashMap::new();
        let mut welded: Vec<Vertex> = Vec::new();
        let mut corner_normals: Vec<Vec<[f32; 3]>> = Vec::new();
        let welded_indices: Vec<u32> = soup
            .iter()
            .map(|v| {
                let w = *welded_of.entry(weld_key(v, !weld)).or_insert_with(|| {
                    welded.push(*v);
                    corner_normals.push(Vec::new());
                    welded.len() as u32 - 1
                });
                let normals = &mut corner_normals[w as usize];
                if !normals.contains(&v.normal) {
                    normals.push(v.normal);
                }
                w
            })
            .collect();
        let exact = self.push_soup(soup);
        let chunks = self.cut_into_chunks(exact);
        let mut lods = LodRanges::default();
        for level in lod::simplified_levels(&welded, &welded_indices) {
            let first_index = self.indices.len() as u32;
            for tri in level.indices.chunks_exact(3) {
                let p = |k: usize| Vec3::from(welded[tri[k] as usize].pos);
                let face = (p(1) - p(0)).cross(p(2) - p(0));
                for &w in tri {
                    let mut corner = welded[w as usize];
                    corner.normal = corner_normals[w as usize]
                        .iter()
                        .copied()
                        .max_by(|a, b| face.dot(Vec3::from(*a)).total_cmp(&face.dot(Vec3::from(*b))))
                        .unwrap_or(corner.normal);
                    self.push_vertex(corner);
                }
            }
            let index_count = self.indices.len() as u32 - first_index;
            lods.levels[lods.count] = lod::LevelRange { first_index, index_count, error_m: level.error_m };
            lods.count += 1;
        }
        (exact, lods, chunks)
    }

    /// Reorders a large exact range's triangles along a Morton curve of their centroids and cuts it into chunks
    /// (the order of a mesh's own triangles decides only exact depth ties between them). Returns the range of
    /// [`Self::chunks`] made, empty for a small mesh.
    fn cut_into_chunks(&mut self, (first, count): (u32, u32)) -> std::ops::Range<u32> {
        let start = self.chunks.len() as u32;
        let range = first as usize..(first + count) as usize;
        if count as usize / 3 < CHUNK_MIN_TRIANGLES {
            return start..start;
        }
        let pos = |i: u32| Vec3::from(self.vertices[i as usize].pos);
        let mut triangles: Vec<[u32; 3]> = self.indices[range.clone()].chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect();
        let centroid = |t: &[u32; 3]| (pos(t[0]) + pos(t[1]) + pos(t[2])) / 3.0;
        let (lo, hi) = triangles.iter().fold((Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)), |(lo, hi), t| {
            let c = centroid(t);
            (lo.min(c), hi.max(c))
        });
        let extent = (hi - lo).max(Vec3::splat(1e-9));
        triangles.sort_by_cached_key(|t| morton3(((centroid(t) - lo) / extent * 1023.0).to_array()));
        self.indices[range].copy_from_slice(bytemuck::cast_slice(&triangles));
        for (k, piece) in triangles.chunks(CHUNK_TRIANGLES).enumerate() {
            let corners = piece.iter().flatten().map(|&i| pos(i));
            let (lo, hi) = corners.clone().fold((Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)), |(lo, hi), p| (lo.min(p), hi.max(p)));
            let center = (lo + hi) / 2.0;
            let radius = corners.map(|p| (p - center).length()).fold(0.0, f32::max);
            self.chunks.push(Chunk {
                first_index: first + (k * CHUNK_TRIANGLES * 3) as u32,
                index_count: (piece.len() * 3) as u32,
                center: center.to_array(),
                radius,
            });
        }
        start..self.chunks.len() as u32
    }

    /// Appends one corner, sharing an identical vertex already in the buffer.
    fn push_vertex(&mut self, vert: Vertex) {
        let key: [u32; 8] = bytemuck::cast(vert);
        let idx = *self.seen.entry(key).or_insert_with(|| {
            self.vertices.push(vert);
            self.vertices.len() as u32 - 1
        });
        self.indices.push(idx);
    }
}

struct GpuModel {
    scene: Arc<SceneModel>,
    vertices: wgpu::Buffer,
    indices: wgpu::Buffer,
    /// Pieces of the large meshes' exact ranges ([`Shape::chunks`]).
    chunks: Vec<Chunk>,
    geom_shapes: Vec<Option<Shape>>,
    site_shapes: Vec<Option<Shape>>,
    /// One bind group per texture, and a last one with no texture.
    texture_groups: Vec<wgpu::BindGroup>,
    skybox: Option<usize>,
    /// The renderer's count of live uploads ([`Renderer::live_uploads`]), decremented when this one goes.
    live: Arc<AtomicUsize>,
}

impl Drop for GpuModel {
    fn drop(&mut self) {
        self.live.fetch_sub(1, Ordering::SeqCst);
    }
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct LightUniform {
    pos: [f32; 4],
    dir: [f32; 4],
    ambient: [f32; 4],
    diffuse: [f32; 4],
    specular: [f32; 4],
    spot: [f32; 4],
    atten: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct CameraUniform {
    view_proj: [[f32; 4]; 4],
    view: [[f32; 4]; 4],
    inv_view_proj: [[f32; 4]; 4],
    eye: [f32; 4],
    counts: [u32; 4],
    lights: [LightUniform; MAX_LIGHTS],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct DrawUniform {
    model: [[f32; 4]; 4],
    normal: [[f32; 4]; 3],
    rgba: [f32; 4],
    material: [f32; 4],
    texgen: [f32; 4],
    texgen2: [f32; 4],
    misc: [u32; 4],
}

/// Render targets of one camera slot, reused across frames of the same size.
struct Targets {
    width: u32,
    height: u32,
    color: wgpu::Texture,
    depth_lin: wgpu::Texture,
    seg: wgpu::Texture,
    depth: wgpu::TextureView,
}

/// Per-frame GPU buffers, grown on demand.
struct FrameResources {
    targets: Vec<Targets>,
    draw_buf: Option<(wgpu::Buffer, wgpu::BindGroup, u64)>,
    camera_buf: Option<(wgpu::Buffer, wgpu::BindGroup, u64)>,
    readback: Option<(wgpu::Buffer, u64)>,
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

/// A key of everything an upload is made from: two scenes with the same key get the same upload. The
/// description without bulk data is hashed through its `Debug` text (exact for every number it holds), the
/// vertices and pixels as bytes, every length included.
fn content_key(scene: &SceneModel) -> [u8; 32] {
    use sha2::{Digest, Sha256};
    let mut h = Sha256::new();
    h.update(format!("{:?}", scene.without_bulk_data()).as_bytes());
    for m in &scene.meshes {
        h.update((m.positions.len() as u64).to_le_bytes());
        h.update(bytemuck::cast_slice(&m.positions));
        h.update((m.normals.len() as u64).to_le_bytes());
        h.update(bytemuck::cast_slice(&m.normals));
        let uv = m.texcoords.as_deref().unwrap_or_default();
        h.update((uv.len() as u64).to_le_bytes());
        h.update(bytemuck::cast_slice(uv));
    }
    for t in &scene.textures {
        h.update((t.rgba8.len() as u64).to_le_bytes());
        h.update(&t.rgba8);
    }
    h.finalize().into()
}

/// One entry of [`Inner::model_cache`].
struct CachedUpload {
    model: Weak<MjModel>,
    id: u64,
    gpu: Weak<GpuModel>,
}

impl CachedUpload {
    /// The upload, if it is still alive and was made for `model` (not for a freed model at the same address).
    fn handle_for(&self, model: &Arc<MjModel>) -> Option<ModelHandle> {
        let same_model = self.model.upgrade().is_some_and(|m| Arc::ptr_eq(&m, model));
        let gpu = self.gpu.upgrade().filter(|_| same_model)?;
        Some(ModelHandle { id: self.id, gpu })
    }

    fn is_dead(&self) -> bool {
        self.model.strong_count() == 0 || self.gpu.strong_count() == 0
    }
}

/// Headless renderer. `Clone` shares the same device; `Send + Sync`.
#[derive(Clone)]
pub struct Renderer {
    inner: Arc<Inner>,
}

fn pad_row(bytes: u32) -> u32 {
    let a = wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    bytes.div_ceil(a) * a
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
            source: wgpu::ShaderSource::Wgsl(include_str!("shader.wgsl").into()),
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
        let ids = |write: bool| {
            Some(wgpu::ColorTargetState {
                format: ID_FORMAT,
                blend: None,
                write_mask: if write { wgpu::ColorWrites::ALL } else { wgpu::ColorWrites::empty() },
            })
        };
        let sky_targets = [
            Some(wgpu::ColorTargetState { format: COLOR_FORMAT, blend: None, write_mask: wgpu::ColorWrites::ALL }),
            ids(false),
            ids(false),
        ];
        let sky = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("skybox"),
            layout: Some(&layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs_sky"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: Default::default(),
            depth_stencil: Some(wgpu::DepthStencilState {
                format: DEPTH_FORMAT,
                depth_write_enabled: Some(false),
                depth_compare: Some(wgpu::CompareFunction::Always),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs_sky"),
                compilation_options: Default::default(),
                targets: &sky_targets,
            }),
            multiview_mask: None,
            cache: None,
        });
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

    /// Upload a compiled model, or return the upload already made for this `Arc<MjModel>`.
    pub fn prepare_model(&self, model: &Arc<MjModel>) -> Result<ModelHandle, RenderError> {
        let key = Arc::as_ptr(model) as usize;
        if let Ok(cache) = self.inner.model_cache.lock()
            && let Some(handle) = cache.get(&key).and_then(|c| c.handle_for(model))
        {
            return Ok(handle);
        }
        let scene = SceneModel::from_mujoco(model)?;
        let content = content_key(&scene);
        let shared = self.inner.content_cache.lock().ok().and_then(|c| {
            let (id, gpu) = c.get(&content)?;
            Some(ModelHandle { id: *id, gpu: gpu.upgrade()? })
        });
        let handle = match shared {
            Some(h) => h,
            None => {
                let h = self.prepare_scene(Arc::new(scene))?;
                if let Ok(mut cache) = self.inner.content_cache.lock() {
                    cache.retain(|_, (_, gpu)| gpu.strong_count() > 0);
                    cache.insert(content, (h.id, Arc::downgrade(&h.gpu)));
                }
                h
            }
        };
        if let Ok(mut cache) = self.inner.model_cache.lock() {
            cache.retain(|_, c| !c.is_dead());
            let entry = CachedUpload { model: Arc::downgrade(model), id: handle.id, gpu: Arc::downgrade(&handle.gpu) };
            cache.insert(key, entry);
        }
        Ok(handle)
    }

    /// Upload an extracted model (meshes, primitives, textures).
    pub fn prepare_scene(&self, scene: Arc<SceneModel>) -> Result<ModelHandle, RenderError> {
        let inner = &self.inner;
        // Indexed with shared corners: llvmpipe's cost is dominated by vertex work on the big meshes.
        let mut geo = GeometryBuilder::default();
        let (ns, nt) = (scene.numslices, scene.numstacks);
        let sphere = geo.push_soup(geometry::unit_sphere(ns, nt));
        let cylinder = geo.push_soup(geometry::unit_cylinder(ns));
        let cube = geo.push_soup(geometry::unit_box());
        let plane = geo.push_soup(geometry::unit_plane(1));
        // Meshes some geom maps a 2D texture onto by their own texture coordinates: simplifying across their normal
        // seams distorts the texture (a woven basket lost 2 dB against MuJoCo), so they keep them unless faceted.
        let mut uv_textured = vec![false; scene.meshes.len()];
        for g in &scene.geoms {
            let texture = usize::try_from(g.matid)
                .ok()
                .and_then(|m| scene.materials.get(m))
                .and_then(|m| usize::try_from(m.texid).ok())
                .and_then(|t| scene.textures.get(t));
            if let (Ok(mi), Some(t)) = (usize::try_from(g.dataid), texture)
                && g.kind == GeomKind::Mesh
                && t.kind == TextureKind::Tex2D
                && let Some(flag) = uv_textured.get_mut(mi)
            {
                *flag = scene.meshes[mi].texcoords.is_some();
            }
        }
        let meshes: Vec<((u32, u32), LodRanges, std::ops::Range<u32>)> = scene
            .meshes
            .iter()
            .zip(&uv_textured)
            .map(|(m, &uv_textured)| geo.push_mesh(geometry::mesh_vertices(m), uv_textured))
            .collect();
        let zfar = scene.zfar_m as f32;
        let mesh_radius: Vec<f32> = scene
            .meshes
            .iter()
            .map(|m| m.positions.iter().map(|p| Vec3::from(*p).length()).fold(0.0, f32::max))
            .collect();
        let mut shape_of = |d: &crate::scene::DrawableDesc| -> Option<Shape> {
            let s = d.size;
            let unit = |(first_vertex, vertex_count): (u32, u32), scale: [f32; 3]| Shape {
                first_vertex,
                vertex_count,
                scale,
                prescaled: false,
                radius: 3f32.sqrt(),
                lods: LodRanges::default(),
                chunks: (0, 0),
            };
            match d.kind {
                GeomKind::Sphere => Some(unit(sphere, [s[0], s[0], s[0]])),
                GeomKind::Ellipsoid => Some(unit(sphere, s)),
                GeomKind::Cylinder => Some(unit(cylinder, [s[0], s[0], s[1]])),
                GeomKind::Box => Some(unit(cube, s)),
                GeomKind::Plane => {
                    let sx = if s[0] > 0.0 { s[0] } else { zfar };
                    let sy = if s[1] > 0.0 { s[1] } else { zfar };
                    Some(unit(plane, [sx, sy, 1.0]))
                }
                GeomKind::Capsule => {
                    let r = geo.push_soup(geometry::capsule(s[0], s[1], ns, nt));
                    Some(Shape {
                        first_vertex: r.0,
                        vertex_count: r.1,
                        scale: [1.0; 3],
                        prescaled: true,
                        radius: s[0] + s[1],
                        lods: LodRanges::default(),
                        chunks: (0, 0),
                    })
                }
                GeomKind::Mesh => {
                    let mi = usize::try_from(d.dataid).ok()?;
                    let ((first_vertex, vertex_count), lods, chunks) = meshes.get(mi)?.clone();
                    let radius = mesh_radius.get(mi).copied().unwrap_or(f32::INFINITY);
                    Some(Shape { first_vertex, vertex_count, scale: [1.0; 3], prescaled: true, radius, lods, chunks: (chunks.start, chunks.end) })
                }
                GeomKind::HField | GeomKind::Other => None,
            }
        };
        let geom_shapes: Vec<Option<Shape>> = scene.geoms.iter().map(&mut shape_of).collect();
        let site_shapes: Vec<Option<Shape>> = scene.sites.iter().map(&mut shape_of).collect();
        let GeometryBuilder { vertices, indices, chunks, .. } = geo;
        let vertex_bytes: &[u8] = bytemuck::cast_slice(&vertices);
        let vbuf = inner.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("model vertices"),
            size: (vertex_bytes.len() as u64).max(64),
            usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        inner.queue.write_buffer(&vbuf, 0, vertex_bytes);
        let index_bytes: &[u8] = bytemuck::cast_slice(&indices);
        let ibuf = inner.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("model indices"),
            size: (index_bytes.len() as u64).max(64).next_multiple_of(4),
            usage: wgpu::BufferUsages::INDEX | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        inner.queue.write_buffer(&ibuf, 0, index_bytes);

        let mut texture_groups = Vec::with_capacity(scene.textures.len() + 1);
        for t in &scene.textures {
            let layers = if t.kind == TextureKind::Tex2D { 1 } else { 6 };
            let tex = upload_texture(&inner.device, &inner.queue, t.width, t.height, layers, &t.rgba8, true, t.srgb);
            let group = if layers == 1 {
                self.texture_group(&tex.create_view(&Default::default()), &inner.dummy_cube)
            } else {
                let cube = tex.create_view(&wgpu::TextureViewDescriptor {
                    dimension: Some(wgpu::TextureViewDimension::Cube),
                    ..Default::default()
                });
                self.texture_group(&inner.dummy_2d, &cube)
            };
            texture_groups.push(group);
        }
        texture_groups.push(self.texture_group(&inner.dummy_2d, &inner.dummy_cube));
        let skybox = scene.textures.iter().position(|t| t.kind == TextureKind::Skybox);
        self.take_errors()?;
        Ok(ModelHandle {
            id: inner.next_model_id.fetch_add(1, Ordering::Relaxed),
            gpu: Arc::new(GpuModel {
                scene: Arc::new(scene.without_bulk_data()),
                vertices: vbuf,
                indices: ibuf,
                chunks,
                geom_shapes,
                site_shapes,
                texture_groups,
                skybox,
                live: {
                    inner.live_uploads.fetch_add(1, Ordering::SeqCst);
                    inner.live_uploads.clone()
                },
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

    fn texture_group(&self, v2d: &wgpu::TextureView, vcube: &wgpu::TextureView) -> wgpu::BindGroup {
        self.inner.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("textures"),
            layout: &self.inner.texture_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(v2d) },
                wgpu::BindGroupEntry { binding: 1, resource: wgpu::BindingResource::TextureView(vcube) },
                wgpu::BindGroupEntry { binding: 2, resource: wgpu::BindingResource::Sampler(&self.inner.sampler) },
            ],
        })
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

    /// Renders once `frame` is held; `waiting` (a foreground caller's count) is released on acquiring it.
    /// The opaque and transparent pipelines of every texture mode for one light list, made on first use.
    fn geometry_pipelines(
        &self,
        lights: LightShape,
    ) -> Result<([wgpu::RenderPipeline; 4], [wgpu::RenderPipeline; 4]), RenderError> {
        let inner = &self.inner;
        let mut cache = inner.pipelines.lock().map_err(|e| RenderError::Readback(e.to_string()))?;
        let mut get = |transparent: bool, tex_mode: u32| {
            let key = PipelineKey { transparent, tex_mode, lights };
            cache
                .entry(key)
                .or_insert_with(|| make_geometry_pipeline(&inner.device, &inner.shader, &inner.pipeline_layout, key))
                .clone()
        };
        let opaque = TEX_MODES.map(|m| get(false, m));
        let transparent = TEX_MODES.map(|m| get(true, m));
        Ok((opaque, transparent))
    }

    fn render_locked(
        &self,
        model: &ModelHandle,
        state: &FrameState,
        requests: &[CameraRequest],
        options: &RenderOptions,
        waiting: Option<&AtomicUsize>,
    ) -> Result<Vec<CameraFrame>, RenderError> {
        /// Decrements the foreground count however the render ends.
        struct Arrived<'a>(Option<&'a AtomicUsize>);
        impl Drop for Arrived<'_> {
            fn drop(&mut self) {
                if let Some(w) = self.0.take() {
                    w.fetch_sub(1, Ordering::SeqCst);
                }
            }
        }
        let mut arrived = Arrived(waiting);
        let gm = &model.gpu;
        let scene = &gm.scene;
        check_state(scene, state)?;
        let cams: Vec<usize> = requests
            .iter()
            .map(|r| resolve_camera(scene, &r.camera))
            .collect::<Result<_, _>>()?;
        for r in requests {
            if r.width == 0 || r.height == 0 || r.width > 8192 || r.height > 8192 {
                return Err(RenderError::Request(format!("image size {}x{} out of range", r.width, r.height)));
            }
        }
        let draws = collect_draws(gm, state, &options.visibility);
        let inner = &self.inner;
        let mut frame = inner.frame.lock().map_err(|e| RenderError::Readback(e.to_string()))?;
        if let Some(w) = arrived.0.take() {
            w.fetch_sub(1, Ordering::SeqCst);
        }

        // Per-geom uniforms (camera independent).
        let draw_data: Vec<u8> = {
            let mut bytes = vec![0u8; draws.len().max(1) * DRAW_STRIDE as usize];
            for (i, d) in draws.iter().enumerate() {
                let u = &d.uniform;
                let off = i * DRAW_STRIDE as usize;
                bytes[off..off + size_of::<DrawUniform>()].copy_from_slice(bytemuck::bytes_of(u));
            }
            bytes
        };
        let (draw_buf, draw_group) =
            ensure_uniform(&inner.device, &mut frame.draw_buf, &inner.draw_layout, draw_data.len() as u64, size_of::<DrawUniform>() as u64);
        inner.queue.write_buffer(&draw_buf, 0, &draw_data);

        // Per-camera uniforms.
        let mut cam_bytes = vec![0u8; requests.len().max(1) * CAMERA_STRIDE as usize];
        let mut eyes = Vec::with_capacity(requests.len());
        let mut slot_pipelines = Vec::with_capacity(requests.len());
        for (i, (r, &cid)) in requests.iter().zip(&cams).enumerate() {
            let (u, eye) = camera_uniform(scene, state, cid, r.width, r.height);
            eyes.push(eye);
            slot_pipelines.push(self.geometry_pipelines(LightShape::of(&u))?);
            let off = i * CAMERA_STRIDE as usize;
            cam_bytes[off..off + size_of::<CameraUniform>()].copy_from_slice(bytemuck::bytes_of(&u));
        }
        let (cam_buf, cam_group) =
            ensure_uniform(&inner.device, &mut frame.camera_buf, &inner.camera_layout, cam_bytes.len() as u64, size_of::<CameraUniform>() as u64);
        inner.queue.write_buffer(&cam_buf, 0, &cam_bytes);

        // Targets per request slot.
        while frame.targets.len() < requests.len() {
            frame.targets.push(make_targets(&inner.device, 1, 1));
        }
        for (slot, r) in requests.iter().enumerate() {
            if frame.targets[slot].width != r.width || frame.targets[slot].height != r.height {
                frame.targets[slot] = make_targets(&inner.device, r.width, r.height);
            }
        }
        // Readback layout: for each request, its requested images one after another.
        let mut layout = Vec::with_capacity(requests.len());
        let mut total = 0u64;
        for r in requests {
            let row = pad_row(r.width * 4) as u64;
            let plane = row * r.height as u64;
            let mut offs = [None; 3];
            for (k, want) in [r.outputs.rgb, r.outputs.depth, r.outputs.segmentation].into_iter().enumerate() {
                if want {
                    offs[k] = Some(total);
                    total += plane;
                }
            }
            layout.push((row, offs));
        }
        let readback = match &frame.readback {
            Some((b, size)) if *size >= total.max(4) => b.clone(),
            _ => {
                let size = total.max(4).next_power_of_two();
                let b = inner.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("readback"),
                    size,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                frame.readback = Some((b.clone(), size));
                b
            }
        };

        let mut encoder = inner.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        for (slot, r) in requests.iter().enumerate() {
            let t = &frame.targets[slot];
            let cview = t.color.create_view(&Default::default());
            let dview = t.depth_lin.create_view(&Default::default());
            let sview = t.seg.create_view(&Default::default());
            let eye = eyes[slot];
            let (opaque_pipelines, transparent_pipelines) = &slot_pipelines[slot];
            {
                let clear_u = |v: u32| wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color { r: v as f64, g: 0.0, b: 0.0, a: 0.0 }),
                    store: wgpu::StoreOp::Store,
                };
                let attachments = [
                    Some(wgpu::RenderPassColorAttachment {
                        view: &cview,
                        depth_slice: None,
                        resolve_target: None,
                        ops: wgpu::Operations { load: wgpu::LoadOp::Clear(wgpu::Color::BLACK), store: wgpu::StoreOp::Store },
                    }),
                    Some(wgpu::RenderPassColorAttachment {
                        view: &dview,
                        depth_slice: None,
                        resolve_target: None,
                        ops: clear_u(NO_SURFACE_BITS),
                    }),
                    Some(wgpu::RenderPassColorAttachment {
                        view: &sview,
                        depth_slice: None,
                        resolve_target: None,
                        ops: clear_u(0),
                    }),
                ];
                let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                    label: Some("camera"),
                    color_attachments: &attachments,
                    depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                        view: &t.depth,
                        depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(0.0), store: wgpu::StoreOp::Discard }),
                        stencil_ops: None,
                    }),
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                });
                let cam_off = (slot as u64 * CAMERA_STRIDE) as u32;
                pass.set_bind_group(0, &cam_group, &[cam_off]);
                if options.skybox
                    && let Some(sky) = gm.skybox
                {
                    pass.set_pipeline(&inner.sky);
                    pass.set_bind_group(1, &draw_group, &[0]);
                    pass.set_bind_group(2, &gm.texture_groups[sky], &[]);
                    pass.draw(0..3, 0..1);
                }
                pass.set_vertex_buffer(0, gm.vertices.slice(..));
                pass.set_index_buffer(gm.indices.slice(..), wgpu::IndexFormat::Uint32);
                let mut transparent = Vec::new();
                let mut opaque = Vec::with_capacity(draws.len());
                let frustum = Frustum::new(scene, state, cams[slot], r.width, r.height);
                let lod = CameraLod::new(eye, scene.cameras[cams[slot]].fovy_deg, r.height, options.mesh_lod_pixel_error);
                for (i, d) in draws.iter().enumerate() {
                    if !frustum.may_see(Vec3::from(d.center), d.cull_radius) {
                        continue;
                    }
                    let distance_m = (Vec3::from(d.center) - eye).length();
                    if d.transparent {
                        transparent.push((distance_m - d.rbound, i));
                    } else {
                        opaque.push((distance_m, i));
                    }
                }
                // Opaque geoms front to back: the depth test then rejects hidden fragments before shading, which
                // is most of the work on a CPU rasteriser. Order does not change the image (depth decides).
                opaque.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                let mut bound = None;
                for &(_, i) in &opaque {
                    draw_one(&mut pass, opaque_pipelines, &mut bound, gm, &draw_group, i, &draws[i], &lod, &frustum);
                }
                if !transparent.is_empty() {
                    // MuJoCo draws transparent geoms front-to-back, then back-to-front.
                    transparent.sort_by(|a, b| a.0.total_cmp(&b.0));
                    let mut bound = None;
                    for &(_, i) in transparent.iter().chain(transparent.iter().rev()) {
                        draw_one(&mut pass, transparent_pipelines, &mut bound, gm, &draw_group, i, &draws[i], &lod, &frustum);
                    }
                }
            }
        }
        // Copies after every pass: a copy waits for its pass to be rasterised, so copying between passes would keep
        // a CPU rasteriser from binning the next camera while it draws the last one.
        for (slot, r) in requests.iter().enumerate() {
            let t = &frame.targets[slot];
            let (row, offs) = layout[slot];
            for (k, tex) in [&t.color, &t.depth_lin, &t.seg].into_iter().enumerate() {
                if let Some(offset) = offs[k] {
                    encoder.copy_texture_to_buffer(
                        tex.as_image_copy(),
                        wgpu::TexelCopyBufferInfo {
                            buffer: &readback,
                            layout: wgpu::TexelCopyBufferLayout {
                                offset,
                                bytes_per_row: Some(row as u32),
                                rows_per_image: Some(r.height),
                            },
                        },
                        wgpu::Extent3d { width: r.width, height: r.height, depth_or_array_layers: 1 },
                    );
                }
            }
        }
        let idx = inner.queue.submit([encoder.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        readback.map_async(wgpu::MapMode::Read, 0..total.max(4), move |res| {
            let _ = tx.send(res);
        });
        inner
            .device
            .poll(wgpu::PollType::Wait { submission_index: Some(idx), timeout: None })
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        rx.recv()
            .map_err(|e| RenderError::Readback(e.to_string()))?
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        self.take_errors()?;
        let mut out = Vec::with_capacity(requests.len());
        {
            let view = readback
                .get_mapped_range(0..total.max(4))
                .map_err(|e| RenderError::Readback(format!("{e:?}")))?;
            for (slot, r) in requests.iter().enumerate() {
                let (row, offs) = layout[slot];
                let (w, h) = (r.width as usize, r.height as usize);
                let rows = |off: u64| (0..h).map(move |y| off as usize + y * row as usize);
                let mut f = CameraFrame {
                    camera_id: cams[slot],
                    width: r.width,
                    height: r.height,
                    rgb: Vec::new(),
                    depth_m: Vec::new(),
                    depth_valid: Vec::new(),
                    segmentation: Vec::new(),
                    calibration: calibration(scene, state, cams[slot], r.width, r.height),
                };
                if let Some(off) = offs[0] {
                    f.rgb.reserve(w * h * 3);
                    for start in rows(off) {
                        for px in view[start..start + 4 * w].chunks_exact(4) {
                            f.rgb.extend_from_slice(&px[..3]);
                        }
                    }
                }
                if let Some(off) = offs[1] {
                    f.depth_m.reserve(w * h);
                    f.depth_valid.reserve(w * h);
                    let far = scene.zfar_m as f32;
                    for start in rows(off) {
                        for px in view[start..start + 4 * w].chunks_exact(4) {
                            let bits = u32::from_le_bytes([px[0], px[1], px[2], px[3]]);
                            let z = f32::from_bits(bits);
                            let valid = bits != NO_SURFACE_BITS && z.is_finite() && z > 0.0;
                            f.depth_m.push(if valid { z } else { far });
                            f.depth_valid.push(valid);
                        }
                    }
                }
                if let Some(off) = offs[2] {
                    f.segmentation.reserve(w * h);
                    for start in rows(off) {
                        for px in view[start..start + 4 * w].chunks_exact(4) {
                            f.segmentation.push(u32::from_le_bytes([px[0], px[1], px[2], px[3]]));
                        }
                    }
                }
                out.push(f);
            }
        }
        readback.unmap();
        Ok(out)
    }
}


/// What a geometry pipeline is specialised for (see the `override` constants in the shader).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
struct PipelineKey {
    transparent: bool,
    tex_mode: u32,
    lights: LightShape,
}

/// The shape of a camera's light list: how many lights, and per light (bit k) positional and spot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
struct LightShape {
    count: u32,
    positional: u32,
    spot: u32,
}

impl LightShape {
    /// Read from the uniform the shader gets, with the tests the shader used to make per fragment.
    fn of(u: &CameraUniform) -> Self {
        let count = u.counts[0].min(MAX_LIGHTS as u32);
        let mut shape = Self { count, positional: 0, spot: 0 };
        for (k, l) in u.lights.iter().take(count as usize).enumerate() {
            if l.pos[3] > 0.5 {
                shape.positional |= 1 << k;
                if l.spot[2] > 0.5 {
                    shape.spot |= 1 << k;
                }
            }
        }
        shape
    }
}

/// Texture modes (none, explicit uv, 2D texgen, cube), each compiled into pipelines of its own.
const TEX_MODES: [u32; 4] = [0, 1, 2, 3];

/// Opaque geometry writes depth, linear depth and ids; transparent geometry blends colour and writes ids only.
fn make_geometry_pipeline(
    device: &wgpu::Device,
    shader: &wgpu::ShaderModule,
    layout: &wgpu::PipelineLayout,
    key: PipelineKey,
) -> wgpu::RenderPipeline {
    let ids = |write: bool| {
        Some(wgpu::ColorTargetState {
            format: ID_FORMAT,
            blend: None,
            write_mask: if write { wgpu::ColorWrites::ALL } else { wgpu::ColorWrites::empty() },
        })
    };
    let (blend, depth_write) =
        if key.transparent { (Some(wgpu::BlendState::ALPHA_BLENDING), false) } else { (None, true) };
    let targets = [
        Some(wgpu::ColorTargetState { format: COLOR_FORMAT, blend, write_mask: wgpu::ColorWrites::ALL }),
        ids(depth_write),
        ids(true),
    ];
    let constants = [
        ("TEX_MODE", f64::from(key.tex_mode)),
        ("LIGHT_COUNT", f64::from(key.lights.count)),
        ("LIGHT_POSITIONAL", f64::from(key.lights.positional)),
        ("LIGHT_SPOT", f64::from(key.lights.spot)),
    ];
    let vertex_layout = wgpu::VertexBufferLayout {
        array_stride: size_of::<Vertex>() as u64,
        step_mode: wgpu::VertexStepMode::Vertex,
        attributes: &wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x2],
    };
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(if key.transparent { "transparent" } else { "opaque" }),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module: shader,
            entry_point: Some("vs_main"),
            compilation_options: Default::default(),
            buffers: &[Some(vertex_layout)],
        },
        primitive: wgpu::PrimitiveState {
            topology: wgpu::PrimitiveTopology::TriangleList,
            front_face: wgpu::FrontFace::Ccw,
            cull_mode: Some(wgpu::Face::Back),
            ..Default::default()
        },
        depth_stencil: Some(wgpu::DepthStencilState {
            format: DEPTH_FORMAT,
            depth_write_enabled: Some(depth_write),
            // Reverse Z: near = 1, far = 0, for precision over MuJoCo's wide near/far range.
            depth_compare: Some(wgpu::CompareFunction::Greater),
            stencil: Default::default(),
            bias: Default::default(),
        }),
        multisample: Default::default(),
        fragment: Some(wgpu::FragmentState {
            module: shader,
            entry_point: Some("fs_main"),
            compilation_options: wgpu::PipelineCompilationOptions { constants: &constants, ..Default::default() },
            targets: &targets,
        }),
        multiview_mask: None,
        cache: None,
    })
}

#[allow(clippy::too_many_arguments)]
fn draw_one(
    pass: &mut wgpu::RenderPass<'_>,
    pipelines: &[wgpu::RenderPipeline; 4],
    bound: &mut Option<u32>,
    gm: &GpuModel,
    draw_group: &wgpu::BindGroup,
    i: usize,
    d: &Draw,
    lod: &CameraLod,
    frustum: &Frustum,
) {
    let mode = d.uniform.misc[0].min(3);
    if *bound != Some(mode) {
        pass.set_pipeline(&pipelines[mode as usize]);
        *bound = Some(mode);
    }
    pass.set_bind_group(1, draw_group, &[(i as u64 * DRAW_STRIDE) as u32]);
    pass.set_bind_group(2, &gm.texture_groups[d.texture_group], &[]);
    let (first, count) = lod.index_range(d);
    let exact = first == d.shape.first_vertex && count == d.shape.vertex_count;
    let chunks = gm.chunks.get(d.shape.chunks.0 as usize..d.shape.chunks.1 as usize).unwrap_or_default();
    if !exact || chunks.is_empty() {
        pass.draw_indexed(first..first + count, 0, 0..1);
        return;
    }
    // The exact mesh, chunk by chunk: neighbouring visible chunks are one draw.
    let model = Mat4::from_cols_array_2d(&d.uniform.model);
    let scale = model.x_axis.truncate().length().max(model.y_axis.truncate().length()).max(model.z_axis.truncate().length());
    let mut run: Option<std::ops::Range<u32>> = None;
    for c in chunks {
        let visible = frustum.may_see(model.transform_point3(Vec3::from(c.center)), c.radius * scale);
        match (&mut run, visible) {
            (Some(r), true) if r.end == c.first_index => r.end += c.index_count,
            (_, true) => {
                if let Some(r) = run.replace(c.first_index..c.first_index + c.index_count) {
                    pass.draw_indexed(r, 0, 0..1);
                }
            }
            (_, false) => {
                if let Some(r) = run.take() {
                    pass.draw_indexed(r, 0, 0..1);
                }
            }
        }
    }
    if let Some(r) = run {
        pass.draw_indexed(r, 0, 0..1);
    }
}

/// Per camera: where it is and how coarse meshes may be drawn.
struct CameraLod {
    eye: Vec3,
    budget: lod::LodBudget,
}

impl CameraLod {
    fn new(eye: Vec3, fovy_deg: f64, height_px: u32, pixel_error: f32) -> Self {
        let focal_px = 0.5 * height_px as f32 / ((fovy_deg as f32).to_radians() / 2.0).tan();
        Self { eye, budget: lod::LodBudget { pixel_error, focal_px } }
    }

    /// The index range to draw: the coarsest level whose error stays within budget at the nearest distance
    /// the draw's bounding sphere allows, else the exact mesh.
    fn index_range(&self, d: &Draw) -> (u32, u32) {
        let exact = (d.shape.first_vertex, d.shape.vertex_count);
        let levels = d.shape.lods.ranges();
        if levels.is_empty() {
            return exact;
        }
        let nearest_m = (Vec3::from(d.center) - self.eye).length() - d.cull_radius;
        match lod::pick(levels, self.budget.allowed_error_m(nearest_m)) {
            Some(l) => (l.first_index, l.index_count),
            None => exact,
        }
    }
}

fn ensure_uniform(
    device: &wgpu::Device,
    slot: &mut Option<(wgpu::Buffer, wgpu::BindGroup, u64)>,
    layout: &wgpu::BindGroupLayout,
    size: u64,
    binding_size: u64,
) -> (wgpu::Buffer, wgpu::BindGroup) {
    if let Some((b, g, cap)) = slot
        && *cap >= size
    {
        return (b.clone(), g.clone());
    }
    let cap = size.next_power_of_two().max(4096);
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("uniforms"),
        size: cap,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("uniforms"),
        layout,
        entries: &[wgpu::BindGroupEntry {
            binding: 0,
            resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer: &buffer,
                offset: 0,
                size: wgpu::BufferSize::new(binding_size),
            }),
        }],
    });
    *slot = Some((buffer.clone(), group.clone(), cap));
    (buffer, group)
}

fn make_targets(device: &wgpu::Device, width: u32, height: u32) -> Targets {
    let tex = |format, label, usage| {
        device.create_texture(&wgpu::TextureDescriptor {
            label: Some(label),
            size: wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage,
            view_formats: &[],
        })
    };
    let rt = wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC;
    Targets {
        width,
        height,
        color: tex(COLOR_FORMAT, "color", rt),
        depth_lin: tex(ID_FORMAT, "linear depth", rt),
        seg: tex(ID_FORMAT, "segmentation", rt),
        depth: tex(DEPTH_FORMAT, "depth", wgpu::TextureUsages::RENDER_ATTACHMENT).create_view(&Default::default()),
    }
}

/// Upload RGBA8 layers with a full box-filtered mip chain (MuJoCo's textures are mipmapped).
#[allow(clippy::too_many_arguments)]
fn upload_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    width: u32,
    height: u32,
    layers: u32,
    rgba8: &[u8],
    mipmaps: bool,
    srgb: bool,
) -> wgpu::Texture {
    let levels = if mipmaps { 32 - width.max(height).leading_zeros() } else { 1 };
    let tex = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("model texture"),
        size: wgpu::Extent3d { width, height, depth_or_array_layers: layers },
        mip_level_count: levels,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: if srgb { wgpu::TextureFormat::Rgba8UnormSrgb } else { wgpu::TextureFormat::Rgba8Unorm },
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    let layer_bytes = (width * height * 4) as usize;
    for layer in 0..layers {
        let start = layer as usize * layer_bytes;
        let Some(src) = rgba8.get(start..start + layer_bytes) else { break };
        let mut level_data = src.to_vec();
        let (mut w, mut h) = (width, height);
        for level in 0..levels {
            queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &tex,
                    mip_level: level,
                    origin: wgpu::Origin3d { x: 0, y: 0, z: layer },
                    aspect: wgpu::TextureAspect::All,
                },
                &level_data,
                wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(4 * w), rows_per_image: Some(h) },
                wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
            );
            if level + 1 < levels {
                let (nw, nh) = ((w / 2).max(1), (h / 2).max(1));
                let mut next = vec![0u8; (nw * nh * 4) as usize];
                for y in 0..nh {
                    for x in 0..nw {
                        for c in 0..4 {
                            let mut acc = 0u32;
                            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                                let sx = (2 * x + dx).min(w - 1);
                                let sy = (2 * y + dy).min(h - 1);
                                acc += level_data[((sy * w + sx) * 4 + c) as usize] as u32;
                            }
                            next[((y * nw + x) * 4 + c) as usize] = ((acc + 2) / 4) as u8;
                        }
                    }
                }
                level_data = next;
                (w, h) = (nw, nh);
            }
        }
    }
    tex
}

/// One visible drawable of this frame.
struct Draw {
    shape: Shape,
    uniform: DrawUniform,
    transparent: bool,
    texture_group: usize,
    center: [f32; 3],
    rbound: f32,
    cull_radius: f32,
}

/// One camera's view volume, for culling bounding spheres.
struct Frustum {
    view: Mat4,
    tan_x: f32,
    tan_y: f32,
    near: f32,
    far: f32,
}

impl Frustum {
    fn new(scene: &SceneModel, s: &FrameState, cam: usize, w: u32, h: u32) -> Self {
        let r = rot3(&s.cam_xmat[cam]);
        let p = s.cam_xpos[cam];
        let eye = Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32);
        let world_from_cam = Mat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), eye.extend(1.0));
        let tan_y = ((scene.cameras[cam].fovy_deg as f32).to_radians() / 2.0).tan();
        let tan_x = tan_y * w as f32 / h as f32;
        Self { view: world_from_cam.inverse(), tan_x, tan_y, near: scene.znear_m as f32, far: scene.zfar_m as f32 }
    }

    /// Whether a sphere (world) can be inside the view volume.
    fn may_see(&self, center: Vec3, r: f32) -> bool {
        let p = self.view.transform_point3(center);
        let z = -p.z;
        if z + r < self.near || z - r > self.far {
            return false;
        }
        let sx = (1.0 + self.tan_x * self.tan_x).sqrt();
        let sy = (1.0 + self.tan_y * self.tan_y).sqrt();
        (p.x.abs() - self.tan_x * z) / sx <= r && (p.y.abs() - self.tan_y * z) / sy <= r
    }
}

fn check_state(scene: &SceneModel, s: &FrameState) -> Result<(), RenderError> {
    let checks = [
        ("geom_xpos", s.geom_xpos.len(), scene.geoms.len()),
        ("geom_xmat", s.geom_xmat.len(), scene.geoms.len()),
        ("geom_rgba", s.geom_rgba.len(), scene.geoms.len()),
        ("site_xpos", s.site_xpos.len(), scene.sites.len()),
        ("site_xmat", s.site_xmat.len(), scene.sites.len()),
        ("site_rgba", s.site_rgba.len(), scene.sites.len()),
        ("cam_xpos", s.cam_xpos.len(), scene.cameras.len()),
        ("cam_xmat", s.cam_xmat.len(), scene.cameras.len()),
        ("light_xpos", s.light_xpos.len(), scene.lights.len()),
        ("light_xdir", s.light_xdir.len(), scene.lights.len()),
    ];
    for (name, got, want) in checks {
        if got != want {
            return Err(RenderError::StateMismatch(format!("{name} has {got} entries, model has {want}")));
        }
    }
    Ok(())
}

fn resolve_camera(scene: &SceneModel, c: &CameraRef) -> Result<usize, RenderError> {
    match c {
        CameraRef::Id(i) if *i < scene.cameras.len() => Ok(*i),
        CameraRef::Id(i) => Err(RenderError::UnknownCamera(format!("id {i}"))),
        CameraRef::Name(n) => scene.camera_id(n).ok_or_else(|| RenderError::UnknownCamera(n.clone())),
    }
}

fn calibration(scene: &SceneModel, s: &FrameState, cam: usize, w: u32, h: u32) -> CameraCalibration {
    let base = s.robot_base_pose.as_ref().map(|(p, r)| (p, r));
    calibration_from_poses(scene.cameras[cam].fovy_deg, &s.cam_xpos[cam], &s.cam_xmat[cam], base, w, h)
}

fn rot3(xmat: &[f64; 9]) -> Mat3 {
    // MuJoCo's xmat is row-major; glam is column-major.
    Mat3::from_cols(
        Vec3::new(xmat[0] as f32, xmat[3] as f32, xmat[6] as f32),
        Vec3::new(xmat[1] as f32, xmat[4] as f32, xmat[7] as f32),
        Vec3::new(xmat[2] as f32, xmat[5] as f32, xmat[8] as f32),
    )
}

fn collect_draws(gm: &GpuModel, s: &FrameState, vis: &Visibility) -> Vec<Draw> {
    let scene = &gm.scene;
    let mut out = Vec::with_capacity(scene.geoms.len());
    let no_texture = gm.texture_groups.len() - 1;
    let mut add = |desc: &crate::scene::DrawableDesc,
                   shape: Option<Shape>,
                   rgba_now: [f32; 4],
                   pos: &[f64; 3],
                   xmat: &[f64; 9],
                   seg: u32,
                   is_site: bool| {
        let Some(shape) = shape else { return };
        let group_on = |groups: &[bool; 6]| groups[desc.group.clamp(0, 5) as usize];
        if !group_on(if is_site { &vis.sitegroup } else { &vis.geomgroup }) {
            return;
        }
        // MuJoCo's setMaterial: material colour unless the element's rgba differs from the default.
        let mat = usize::try_from(desc.matid).ok().and_then(|m| scene.materials.get(m));
        let mut rgba = mat.map(|m| m.rgba).unwrap_or(rgba_now);
        if rgba_now != [0.5, 0.5, 0.5, 1.0] || mat.is_none() {
            rgba = rgba_now;
        }
        // Alpha 0 is skipped by MuJoCo; negative alpha (robosuite's hidden sites) is invisible too.
        if rgba[3] <= 0.0 {
            return;
        }
        let (emission, specular, shininess) = mat.map(|m| (m.emission, m.specular, m.shininess)).unwrap_or((0.0, 0.5, 0.5));
        let size = desc.size;
        let mut mode = 0u32;
        let mut texgen = [0.0f32; 4];
        let mut texgen2 = [0.0f32; 4];
        let mut group = no_texture;
        if let Some(m) = mat
            && let Some(tex) = usize::try_from(m.texid).ok().and_then(|t| scene.textures.get(t).map(|x| (t, x)))
        {
            group = tex.0;
            let has_uv = desc.kind == GeomKind::Mesh
                && usize::try_from(desc.dataid).ok().and_then(|i| scene.meshes.get(i)).is_some_and(|mm| mm.texcoords.is_some());
            if tex.1.kind == TextureKind::Tex2D {
                if has_uv {
                    mode = 1;
                } else {
                    mode = 2;
                    let mut scl = m.texrepeat;
                    for k in 0..2 {
                        if shape.prescaled && size[k] > 0.0 {
                            scl[k] /= size[k].max(1e-15);
                        }
                        if m.texuniform && size[k] > 0.0 {
                            scl[k] *= size[k];
                        }
                    }
                    texgen[0] = scl[0];
                    texgen[1] = scl[1];
                }
            } else {
                mode = 3;
                let sc = |k: usize| if m.texuniform { size[k] } else { 1.0 };
                texgen[2] = sc(0);
                texgen[3] = sc(1);
                texgen2[0] = sc(2);
            }
        }
        let r = rot3(xmat);
        let t = Vec3::new(pos[0] as f32, pos[1] as f32, pos[2] as f32);
        let scale = Vec3::from(shape.scale);
        let model = Mat4::from_cols(
            (r.x_axis * scale.x).extend(0.0),
            (r.y_axis * scale.y).extend(0.0),
            (r.z_axis * scale.z).extend(0.0),
            t.extend(1.0),
        );
        let nrm = Mat3::from_cols(r.x_axis / scale.x, r.y_axis / scale.y, r.z_axis / scale.z);
        let uniform = DrawUniform {
            model: model.to_cols_array_2d(),
            normal: [nrm.x_axis.extend(0.0).to_array(), nrm.y_axis.extend(0.0).to_array(), nrm.z_axis.extend(0.0).to_array()],
            rgba,
            material: [emission, specular, shininess * 128.0, 0.0],
            texgen,
            texgen2,
            misc: [mode, seg, 0, 0],
        };
        let rbound = size[0].max(size[1]).max(size[2]);
        let cull_radius = shape.radius * scale.abs().max_element();
        out.push(Draw {
            shape,
            uniform,
            transparent: rgba[3] < 0.995,
            texture_group: group,
            center: t.to_array(),
            rbound,
            cull_radius,
        });
    };
    for (i, g) in scene.geoms.iter().enumerate() {
        add(g, gm.geom_shapes[i], s.geom_rgba[i], &s.geom_xpos[i], &s.geom_xmat[i], i as u32 + 1, false);
    }
    for (i, site) in scene.sites.iter().enumerate() {
        add(site, gm.site_shapes[i], s.site_rgba[i], &s.site_xpos[i], &s.site_xmat[i], SEG_SITE_FLAG | (i as u32 + 1), true);
    }
    out
}

/// View matrix, tangents of the half field of view (x, y) and clip distances of one camera.
/// View/projection (reverse Z) and MuJoCo's light list (headlight first) for one camera.
fn camera_uniform(scene: &SceneModel, s: &FrameState, cam: usize, w: u32, h: u32) -> (CameraUniform, Vec3) {
    let r = rot3(&s.cam_xmat[cam]);
    let p = s.cam_xpos[cam];
    let eye = Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32);
    let world_from_cam = Mat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), eye.extend(1.0));
    let view = world_from_cam.inverse();
    let fovy = (scene.cameras[cam].fovy_deg as f32).to_radians();
    let (near, far) = (scene.znear_m as f32, scene.zfar_m as f32);
    // Swapping near and far gives reverse Z (near → 1, far → 0).
    let proj = Mat4::perspective_rh(fovy, w as f32 / h as f32, far, near);
    let view_proj = proj * view;
    let mut lights = [LightUniform::zeroed(); MAX_LIGHTS];
    let mut n = 0usize;
    let v4 = |a: [f32; 3]| [a[0], a[1], a[2], 1.0];
    if scene.headlight.active {
        // Directional light along the camera's viewing direction.
        let toward = r.z_axis; // −forward
        lights[0] = LightUniform {
            pos: [toward.x, toward.y, toward.z, 0.0],
            dir: [-toward.x, -toward.y, -toward.z, 0.0],
            ambient: v4(scene.headlight.ambient),
            diffuse: v4(scene.headlight.diffuse),
            specular: v4(scene.headlight.specular),
            spot: [-1.0, 0.0, 0.0, 0.0],
            atten: [1.0, 0.0, 0.0, 0.0],
        };
        n = 1;
    }
    for (i, l) in scene.lights.iter().enumerate() {
        if !l.active || n >= MAX_LIGHTS {
            continue;
        }
        let d = s.light_xdir[i];
        let lp = s.light_xpos[i];
        let dir = Vec3::new(d[0] as f32, d[1] as f32, d[2] as f32);
        let u = match l.kind {
            LightKind::Directional => LightUniform {
                pos: [-dir.x, -dir.y, -dir.z, 0.0],
                dir: [dir.x, dir.y, dir.z, 0.0],
                spot: [-1.0, 0.0, 0.0, 0.0],
                atten: [1.0, 0.0, 0.0, 0.0],
                ambient: v4(l.ambient),
                diffuse: v4(l.diffuse),
                specular: v4(l.specular),
            },
            LightKind::Spot | LightKind::Point => LightUniform {
                pos: [lp[0] as f32, lp[1] as f32, lp[2] as f32, 1.0],
                dir: [dir.x, dir.y, dir.z, 0.0],
                spot: if l.kind == LightKind::Spot && l.cutoff_deg < 180.0 {
                    [l.cutoff_deg.to_radians().cos(), l.exponent, 1.0, 0.0]
                } else {
                    [-1.0, 0.0, 0.0, 0.0]
                },
                atten: [l.attenuation[0], l.attenuation[1], l.attenuation[2], 0.0],
                ambient: v4(l.ambient),
                diffuse: v4(l.diffuse),
                specular: v4(l.specular),
            },
        };
        lights[n] = u;
        n += 1;
    }
    (
        CameraUniform {
            view_proj: view_proj.to_cols_array_2d(),
            view: view.to_cols_array_2d(),
            inv_view_proj: view_proj.inverse().to_cols_array_2d(),
            eye: [eye.x, eye.y, eye.z, 1.0],
            counts: [n as u32, 0, 0, 0],
            lights,
        },
        eye,
    )
}
