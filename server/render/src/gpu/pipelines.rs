//! The render pipelines: the skybox's, and the geometry pipelines specialised per texture mode, opacity and a
//! camera's light list (made on first use and kept).
use super::draws::CameraUniform;
use super::{COLOR_FORMAT, DEPTH_FORMAT, ID_FORMAT, MAX_LIGHTS, Renderer};
use crate::geometry::Vertex;
use crate::RenderError;

impl Renderer {
    /// The opaque and transparent pipelines of every texture mode for one light list, made on first use.
    pub(super) fn geometry_pipelines(
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
}

/// A target of ids (linear depth bits, segmentation ids): never blended; `write` off where a pass must leave it.
fn id_target(write: bool) -> Option<wgpu::ColorTargetState> {
    Some(wgpu::ColorTargetState {
        format: ID_FORMAT,
        blend: None,
        write_mask: if write { wgpu::ColorWrites::ALL } else { wgpu::ColorWrites::empty() },
    })
}

/// The skybox, drawn first behind everything: colour only, depth untouched.
pub(super) fn make_sky_pipeline(
    device: &wgpu::Device,
    shader: &wgpu::ShaderModule,
    layout: &wgpu::PipelineLayout,
) -> wgpu::RenderPipeline {
    let sky_targets = [
        Some(wgpu::ColorTargetState { format: COLOR_FORMAT, blend: None, write_mask: wgpu::ColorWrites::ALL }),
        id_target(false),
        id_target(false),
    ];
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some("skybox"),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module: shader,
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
            module: shader,
            entry_point: Some("fs_sky"),
            compilation_options: Default::default(),
            targets: &sky_targets,
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// What a geometry pipeline is specialised for (see the `override` constants in the shader).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(super) struct PipelineKey {
    transparent: bool,
    tex_mode: u32,
    lights: LightShape,
}

/// The shape of a camera's light list: how many lights, and per light (bit k) positional and spot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(super) struct LightShape {
    count: u32,
    positional: u32,
    spot: u32,
}

impl LightShape {
    /// Read from the uniform the shader gets, with the tests the shader used to make per fragment.
    pub(super) fn of(u: &CameraUniform) -> Self {
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
    let (blend, depth_write) =
        if key.transparent { (Some(wgpu::BlendState::ALPHA_BLENDING), false) } else { (None, true) };
    let targets = [
        Some(wgpu::ColorTargetState { format: COLOR_FORMAT, blend, write_mask: wgpu::ColorWrites::ALL }),
        id_target(depth_write),
        id_target(true),
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
