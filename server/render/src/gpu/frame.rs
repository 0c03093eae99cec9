//! One frame: the request checked, the frame's uniforms uploaded, every camera encoded into one submission, and
//! its images read back.
use std::sync::atomic::{AtomicUsize, Ordering};

use glam::Vec3;

use super::draws::{CameraLod, CameraUniform, Draw, DrawUniform, Frustum, camera_uniform, collect_draws, draw_one};
use super::pipelines::LightShape;
use super::upload::GpuModel;
use super::{
    CAMERA_STRIDE, COLOR_FORMAT, CameraFrame, CameraRef, CameraRequest, DEPTH_FORMAT, DRAW_STRIDE, ID_FORMAT, ModelHandle,
    NO_SURFACE_BITS, RenderOptions, Renderer,
};
use crate::calib::{CameraCalibration, calibration_from_poses};
use crate::scene::{FrameState, SceneModel};
use crate::RenderError;

/// Draws in the order a pass draws them: (sort distance in metres, index in the frame's draws).
type DrawOrder = Vec<(f32, usize)>;

/// Per slot, the opaque and the transparent geometry pipelines of every texture mode.
type SlotPipelines = ([wgpu::RenderPipeline; 4], [wgpu::RenderPipeline; 4]);

/// The cameras' uniforms as uploaded: the bind group of every slot's uniform, and per slot its eye and pipelines.
struct Cameras {
    group: wgpu::BindGroup,
    eyes: Vec<Vec3>,
    pipelines: Vec<SlotPipelines>,
}

/// What every camera of a frame draws.
struct FrameDraws<'a> {
    gm: &'a GpuModel,
    state: &'a FrameState,
    options: &'a RenderOptions,
    draws: &'a [Draw],
    draw_group: &'a wgpu::BindGroup,
    cameras: &'a Cameras,
}

/// Where each request's images lie in the readback buffer: per request its padded row length and the offsets of
/// its requested images (rgb, linear depth, segmentation), one request after another.
struct ReadbackLayout {
    slots: Vec<(u64, [Option<u64>; 3])>,
    total: u64,
}

impl ReadbackLayout {
    fn of(requests: &[CameraRequest]) -> Self {
        let mut slots = Vec::with_capacity(requests.len());
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
            slots.push((row, offs));
        }
        Self { slots, total }
    }

    /// The bytes mapped: the images, never none.
    fn mapped_len(&self) -> u64 {
        self.total.max(4)
    }
}

/// Decrements a foreground caller's count once, when the frame is held or however the render ends before.
struct Arrived<'a>(Option<&'a AtomicUsize>);

impl Arrived<'_> {
    fn now(&mut self) {
        if let Some(w) = self.0.take() {
            w.fetch_sub(1, Ordering::SeqCst);
        }
    }
}

impl Drop for Arrived<'_> {
    fn drop(&mut self) {
        self.now();
    }
}

impl Renderer {
    /// Renders once `frame` is held; `waiting` (a foreground caller's count) is released on acquiring it.
    pub(super) fn render_locked(
        &self,
        model: &ModelHandle,
        state: &FrameState,
        requests: &[CameraRequest],
        options: &RenderOptions,
        waiting: Option<&AtomicUsize>,
    ) -> Result<Vec<CameraFrame>, RenderError> {
        let mut arrived = Arrived(waiting);
        let gm = &model.gpu;
        let scene = &gm.scene;
        let cams = check_request(scene, state, requests)?;
        let draws = collect_draws(gm, state, &options.visibility);
        let inner = &self.inner;
        let mut frame = inner.frame.lock().map_err(|e| RenderError::Readback(e.to_string()))?;
        arrived.now();
        let draw_group = self.upload_draw_uniforms(&mut frame.draw_buf, &draws);
        let cameras = self.upload_camera_uniforms(&mut frame.camera_buf, scene, state, requests, &cams)?;
        fit_targets(&inner.device, &mut frame.targets, requests);
        let layout = ReadbackLayout::of(requests);
        let readback = readback_buffer(&inner.device, &mut frame.readback, layout.total);

        let mut encoder = inner.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        let input = FrameDraws { gm, state, options, draws: &draws, draw_group: &draw_group, cameras: &cameras };
        for (slot, r) in requests.iter().enumerate() {
            self.encode_camera(&mut encoder, &input, slot, r, cams[slot], &frame.targets[slot]);
        }
        // Copies after every pass: a copy waits for its pass to be rasterised, so copying between passes would keep
        // a CPU rasteriser from binning the next camera while it draws the last one.
        encode_copies(&mut encoder, &frame.targets, requests, &layout, &readback);
        self.submit_and_map(encoder, &readback, layout.mapped_len())?;
        let out = {
            let view = readback
                .get_mapped_range(0..layout.mapped_len())
                .map_err(|e| RenderError::Readback(format!("{e:?}")))?;
            requests.iter().enumerate().map(|(slot, r)| read_frame(&view, layout.slots[slot], r, cams[slot], scene, state)).collect()
        };
        readback.unmap();
        Ok(out)
    }

    /// Uploads every draw's uniform (camera independent), one per [`DRAW_STRIDE`].
    fn upload_draw_uniforms(&self, slot: &mut Option<(wgpu::Buffer, wgpu::BindGroup, u64)>, draws: &[Draw]) -> wgpu::BindGroup {
        let inner = &self.inner;
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
            ensure_uniform(&inner.device, slot, &inner.draw_layout, draw_data.len() as u64, size_of::<DrawUniform>() as u64);
        inner.queue.write_buffer(&draw_buf, 0, &draw_data);
        draw_group
    }

    /// Uploads every camera's uniform, one per [`CAMERA_STRIDE`], and gets the pipelines of its light list.
    fn upload_camera_uniforms(
        &self,
        slot: &mut Option<(wgpu::Buffer, wgpu::BindGroup, u64)>,
        scene: &SceneModel,
        state: &FrameState,
        requests: &[CameraRequest],
        cams: &[usize],
    ) -> Result<Cameras, RenderError> {
        let inner = &self.inner;
        let mut cam_bytes = vec![0u8; requests.len().max(1) * CAMERA_STRIDE as usize];
        let mut eyes = Vec::with_capacity(requests.len());
        let mut slot_pipelines = Vec::with_capacity(requests.len());
        for (i, (r, &cid)) in requests.iter().zip(cams).enumerate() {
            let (u, eye) = camera_uniform(scene, state, cid, r.width, r.height);
            eyes.push(eye);
            slot_pipelines.push(self.geometry_pipelines(LightShape::of(&u))?);
            let off = i * CAMERA_STRIDE as usize;
            cam_bytes[off..off + size_of::<CameraUniform>()].copy_from_slice(bytemuck::bytes_of(&u));
        }
        let (cam_buf, cam_group) =
            ensure_uniform(&inner.device, slot, &inner.camera_layout, cam_bytes.len() as u64, size_of::<CameraUniform>() as u64);
        inner.queue.write_buffer(&cam_buf, 0, &cam_bytes);
        Ok(Cameras { group: cam_group, eyes, pipelines: slot_pipelines })
    }

    /// One camera's render pass: the skybox, then the draws its frustum may see, opaque ones front to back, then the
    /// transparent ones.
    fn encode_camera(&self, encoder: &mut wgpu::CommandEncoder, input: &FrameDraws, slot: usize, r: &CameraRequest, cam: usize, t: &Targets) {
        let FrameDraws { gm, state, options, draws, draw_group, cameras } = *input;
        let scene = &gm.scene;
        let cview = t.color.create_view(&Default::default());
        let dview = t.depth_lin.create_view(&Default::default());
        let sview = t.seg.create_view(&Default::default());
        let eye = cameras.eyes[slot];
        let (opaque_pipelines, transparent_pipelines) = &cameras.pipelines[slot];
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
        pass.set_bind_group(0, &cameras.group, &[cam_off]);
        if options.skybox
            && let Some(sky) = gm.skybox
        {
            pass.set_pipeline(&self.inner.sky);
            pass.set_bind_group(1, draw_group, &[0]);
            pass.set_bind_group(2, &gm.texture_groups[sky], &[]);
            pass.draw(0..3, 0..1);
        }
        pass.set_vertex_buffer(0, gm.vertices.slice(..));
        pass.set_index_buffer(gm.indices.slice(..), wgpu::IndexFormat::Uint32);
        let frustum = Frustum::new(scene, state, cam, r.width, r.height);
        let lod = CameraLod::new(eye, scene.cameras[cam].fovy_deg, r.height, options.mesh_lod_pixel_error);
        let (opaque, transparent) = draw_order(draws, &frustum, eye);
        let mut bound = None;
        for &(_, i) in &opaque {
            draw_one(&mut pass, opaque_pipelines, &mut bound, gm, draw_group, i, &draws[i], &lod, &frustum);
        }
        if !transparent.is_empty() {
            // MuJoCo draws transparent geoms front-to-back, then back-to-front.
            let mut bound = None;
            for &(_, i) in transparent.iter().chain(transparent.iter().rev()) {
                draw_one(&mut pass, transparent_pipelines, &mut bound, gm, draw_group, i, &draws[i], &lod, &frustum);
            }
        }
    }

    /// Submits the frame, maps the readback buffer once the device is done with it, and fails on any error the
    /// device reported meanwhile.
    fn submit_and_map(&self, encoder: wgpu::CommandEncoder, readback: &wgpu::Buffer, len: u64) -> Result<(), RenderError> {
        let inner = &self.inner;
        let idx = inner.queue.submit([encoder.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        readback.map_async(wgpu::MapMode::Read, 0..len, move |res| {
            let _ = tx.send(res);
        });
        inner
            .device
            .poll(wgpu::PollType::Wait { submission_index: Some(idx), timeout: None })
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        rx.recv()
            .map_err(|e| RenderError::Readback(e.to_string()))?
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        self.take_errors()
    }
}

/// The state fits the model, each camera exists and each image size is in range; returns the cameras' ids.
fn check_request(scene: &SceneModel, state: &FrameState, requests: &[CameraRequest]) -> Result<Vec<usize>, RenderError> {
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
    Ok(cams)
}

/// The draws a camera's frustum may see, as (sort distance, draw index): the opaque ones sorted front to back (the
/// depth test then rejects hidden fragments before shading, which is most of the work on a CPU rasteriser; order
/// does not change the image, depth decides), the transparent ones by their nearest extent.
fn draw_order(draws: &[Draw], frustum: &Frustum, eye: Vec3) -> (DrawOrder, DrawOrder) {
    let mut transparent = Vec::new();
    let mut opaque = Vec::with_capacity(draws.len());
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
    opaque.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    transparent.sort_by(|a, b| a.0.total_cmp(&b.0));
    (opaque, transparent)
}

/// One target per request slot, remade where the slot's size changed.
fn fit_targets(device: &wgpu::Device, targets: &mut Vec<Targets>, requests: &[CameraRequest]) {
    while targets.len() < requests.len() {
        targets.push(make_targets(device, 1, 1));
    }
    for (slot, r) in requests.iter().enumerate() {
        if targets[slot].width != r.width || targets[slot].height != r.height {
            targets[slot] = make_targets(device, r.width, r.height);
        }
    }
}

/// The readback buffer, grown (to a power of two) when `total` bytes do not fit.
fn readback_buffer(device: &wgpu::Device, slot: &mut Option<(wgpu::Buffer, u64)>, total: u64) -> wgpu::Buffer {
    match slot {
        Some((b, size)) if *size >= total.max(4) => b.clone(),
        _ => {
            let size = total.max(4).next_power_of_two();
            let b = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback"),
                size,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            *slot = Some((b.clone(), size));
            b
        }
    }
}

/// Copies each request's requested images into the readback buffer at its layout's offsets.
fn encode_copies(encoder: &mut wgpu::CommandEncoder, targets: &[Targets], requests: &[CameraRequest], layout: &ReadbackLayout, readback: &wgpu::Buffer) {
    for (slot, r) in requests.iter().enumerate() {
        let t = &targets[slot];
        let (row, offs) = layout.slots[slot];
        for (k, tex) in [&t.color, &t.depth_lin, &t.seg].into_iter().enumerate() {
            if let Some(offset) = offs[k] {
                encoder.copy_texture_to_buffer(
                    tex.as_image_copy(),
                    wgpu::TexelCopyBufferInfo {
                        buffer: readback,
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
}

/// One request's images out of the mapped readback (`row`: padded row length; `offs`: where each image starts).
fn read_frame(view: &[u8], (row, offs): (u64, [Option<u64>; 3]), r: &CameraRequest, cam: usize, scene: &SceneModel, state: &FrameState) -> CameraFrame {
    let (w, h) = (r.width as usize, r.height as usize);
    let rows = |off: u64| (0..h).map(move |y| off as usize + y * row as usize);
    let mut f = CameraFrame {
        camera_id: cam,
        width: r.width,
        height: r.height,
        rgb: Vec::new(),
        depth_m: Vec::new(),
        depth_valid: Vec::new(),
        segmentation: Vec::new(),
        calibration: calibration(scene, state, cam, r.width, r.height),
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
    f
}

/// Render targets of one camera slot, reused across frames of the same size.
pub(super) struct Targets {
    width: u32,
    height: u32,
    color: wgpu::Texture,
    depth_lin: wgpu::Texture,
    seg: wgpu::Texture,
    depth: wgpu::TextureView,
}

/// Per-frame GPU buffers, grown on demand.
pub(super) struct FrameResources {
    pub(super) targets: Vec<Targets>,
    pub(super) draw_buf: Option<(wgpu::Buffer, wgpu::BindGroup, u64)>,
    pub(super) camera_buf: Option<(wgpu::Buffer, wgpu::BindGroup, u64)>,
    pub(super) readback: Option<(wgpu::Buffer, u64)>,
}

fn pad_row(bytes: u32) -> u32 {
    let a = wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    bytes.div_ceil(a) * a
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
