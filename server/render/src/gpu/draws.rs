//! What a frame draws: each visible geom's and site's uniform (pose, material, texture mode, segmentation id), each
//! camera's uniform (view, projection, light list), and per camera the culling and level of detail of each draw.
use bytemuck::{Pod, Zeroable};
use glam::{Mat3, Mat4, Vec3};

use super::buffers::Shape;
use super::upload::GpuModel;
use super::{DRAW_STRIDE, MAX_LIGHTS, SEG_SITE_FLAG};
use crate::lod;
use crate::scene::{FrameState, GeomKind, LightKind, SceneModel, TextureKind, Visibility};

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct LightUniform {
    pub(super) pos: [f32; 4],
    pub(super) dir: [f32; 4],
    pub(super) ambient: [f32; 4],
    pub(super) diffuse: [f32; 4],
    pub(super) specular: [f32; 4],
    pub(super) spot: [f32; 4],
    pub(super) atten: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct CameraUniform {
    pub(super) view_proj: [[f32; 4]; 4],
    pub(super) view: [[f32; 4]; 4],
    pub(super) inv_view_proj: [[f32; 4]; 4],
    pub(super) eye: [f32; 4],
    pub(super) counts: [u32; 4],
    pub(super) lights: [LightUniform; MAX_LIGHTS],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct DrawUniform {
    pub(super) model: [[f32; 4]; 4],
    pub(super) normal: [[f32; 4]; 3],
    pub(super) rgba: [f32; 4],
    pub(super) material: [f32; 4],
    pub(super) texgen: [f32; 4],
    texgen2: [f32; 4],
    pub(super) misc: [u32; 4],
}

/// One visible drawable of this frame.
pub(super) struct Draw {
    pub(super) shape: Shape,
    pub(super) uniform: DrawUniform,
    pub(super) transparent: bool,
    pub(super) texture_group: usize,
    pub(super) center: [f32; 3],
    pub(super) rbound: f32,
    pub(super) cull_radius: f32,
}

/// The drawables of a frame (geoms, then sites) with their uniforms, before any camera's culling.
pub(super) fn collect_draws(gm: &GpuModel, s: &FrameState, vis: &Visibility) -> Vec<Draw> {
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

/// View/projection (reverse Z) and MuJoCo's light list (headlight first) for one camera.
pub(super) fn camera_uniform(scene: &SceneModel, s: &FrameState, cam: usize, w: u32, h: u32) -> (CameraUniform, Vec3) {
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

/// One camera's view volume, for culling bounding spheres.
pub(super) struct Frustum {
    view: Mat4,
    tan_x: f32,
    tan_y: f32,
    near: f32,
    far: f32,
}

impl Frustum {
    pub(super) fn new(scene: &SceneModel, s: &FrameState, cam: usize, w: u32, h: u32) -> Self {
        let r = rot3(&s.cam_xmat[cam]);
        let p = s.cam_xpos[cam];
        let eye = Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32);
        let world_from_cam = Mat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), eye.extend(1.0));
        let tan_y = ((scene.cameras[cam].fovy_deg as f32).to_radians() / 2.0).tan();
        let tan_x = tan_y * w as f32 / h as f32;
        Self { view: world_from_cam.inverse(), tan_x, tan_y, near: scene.znear_m as f32, far: scene.zfar_m as f32 }
    }

    /// Whether a sphere (world) can be inside the view volume.
    pub(super) fn may_see(&self, center: Vec3, r: f32) -> bool {
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

/// Per camera: where it is and how coarse meshes may be drawn.
pub(super) struct CameraLod {
    eye: Vec3,
    budget: lod::LodBudget,
}

impl CameraLod {
    pub(super) fn new(eye: Vec3, fovy_deg: f64, height_px: u32, pixel_error: f32) -> Self {
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

#[allow(clippy::too_many_arguments)]
pub(super) fn draw_one(
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

fn rot3(xmat: &[f64; 9]) -> Mat3 {
    // MuJoCo's xmat is row-major; glam is column-major.
    Mat3::from_cols(
        Vec3::new(xmat[0] as f32, xmat[3] as f32, xmat[6] as f32),
        Vec3::new(xmat[1] as f32, xmat[4] as f32, xmat[7] as f32),
        Vec3::new(xmat[2] as f32, xmat[5] as f32, xmat[8] as f32),
    )
}
