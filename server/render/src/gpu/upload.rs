//! A model's upload: its buffers and textures on the device, made once per compiled model and shared by every
//! model of the same content.
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Weak};

use glam::Vec3;
use mujoco_rs::prelude::MjModel;

use super::Renderer;
use super::buffers::{Chunk, GeometryBuilder, LodRanges, Shape};
use crate::geometry;
use crate::scene::{GeomKind, SceneModel, TextureKind};
use crate::RenderError;

/// A model uploaded to the GPU. Cheap to clone; keep one per compiled model.
#[derive(Clone)]
pub struct ModelHandle {
    pub(super) id: u64,
    pub(super) gpu: Arc<GpuModel>,
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

pub(super) struct GpuModel {
    pub(super) scene: Arc<SceneModel>,
    pub(super) vertices: wgpu::Buffer,
    pub(super) indices: wgpu::Buffer,
    /// Pieces of the large meshes' exact ranges ([`Shape::chunks`]).
    pub(super) chunks: Vec<Chunk>,
    pub(super) geom_shapes: Vec<Option<Shape>>,
    pub(super) site_shapes: Vec<Option<Shape>>,
    /// One bind group per texture, and a last one with no texture.
    pub(super) texture_groups: Vec<wgpu::BindGroup>,
    pub(super) skybox: Option<usize>,
    /// The renderer's count of live uploads ([`Renderer::live_uploads`]), decremented when this one goes.
    pub(super) live: Arc<AtomicUsize>,
}

impl Drop for GpuModel {
    fn drop(&mut self) {
        self.live.fetch_sub(1, Ordering::SeqCst);
    }
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

/// One entry of the renderer's uploads by compiled model (`Inner::model_cache`).
pub(super) struct CachedUpload {
    model: Weak<MjModel>,
    id: u64,
    gpu: Weak<GpuModel>,
}

impl CachedUpload {
    /// The upload, if it is still alive and was made for `model` (not for a freed model at the same address).
    pub(super) fn handle_for(&self, model: &Arc<MjModel>) -> Option<ModelHandle> {
        let same_model = self.model.upgrade().is_some_and(|m| Arc::ptr_eq(&m, model));
        let gpu = self.gpu.upgrade().filter(|_| same_model)?;
        Some(ModelHandle { id: self.id, gpu })
    }

    pub(super) fn is_dead(&self) -> bool {
        self.model.strong_count() == 0 || self.gpu.strong_count() == 0
    }
}

impl Renderer {
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
}

/// Upload RGBA8 layers with a full box-filtered mip chain (MuJoCo's textures are mipmapped).
#[allow(clippy::too_many_arguments)]
pub(super) fn upload_texture(
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
