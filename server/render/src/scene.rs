//! The renderer's inputs, extracted from MuJoCo: a [`SceneModel`] once per compiled model (geometry,
//! materials, textures, lights, cameras) and a [`FrameState`] per frame (poses and the few per-frame
//! appearance values robosuite changes at run time). Keeping them as plain data means the GPU code
//! never touches MuJoCo and the crate carries no task knowledge.
use mujoco_rs::mujoco_c::{mjData, mjModel};
use mujoco_rs::prelude::{MjData, MjModel};
use mujoco_rs::wrappers::mj_model::MjtObjBase;
use mujoco_rs::wrappers::mj_model::traits::ModelType;

use crate::RenderError;

/// The body that robot-frame calibration refers to (robosuite's Panda base).
pub const ROBOT_BASE_BODY: &str = "robot0_base";

/// MuJoCo geom types (`mjtGeom`) the renderer draws.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GeomKind {
    Plane,
    HField,
    Sphere,
    Capsule,
    Ellipsoid,
    Cylinder,
    Box,
    Mesh,
    /// Anything else (SDF, flex, skin, decor): not drawn.
    Other,
}

impl GeomKind {
    fn from_mj(t: i32) -> Self {
        match t {
            0 => Self::Plane,
            1 => Self::HField,
            2 => Self::Sphere,
            3 => Self::Capsule,
            4 => Self::Ellipsoid,
            5 => Self::Cylinder,
            6 => Self::Box,
            7 => Self::Mesh,
            _ => Self::Other,
        }
    }
}

/// One drawable: a model geom or a site (sites are drawn like geoms, per MuJoCo's visualiser).
#[derive(Debug, Clone)]
pub struct DrawableDesc {
    pub kind: GeomKind,
    /// `geom_size` / `site_size` (metres; meaning per type as in MuJoCo).
    pub size: [f32; 3],
    /// `geom_rgba` / `site_rgba` at compile time (runtime overrides come with [`FrameState`]).
    pub rgba: [f32; 4],
    pub matid: i32,
    pub group: i32,
    /// Mesh id for mesh geoms, else -1.
    pub dataid: i32,
    pub bodyid: i32,
}

/// A compiled mesh, unrolled to three corners per face so per-face normals and texcoords survive.
#[derive(Debug, Clone, Default)]
pub struct MeshData {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    /// Present when the mesh has texture coordinates (MuJoCo then maps 2D textures explicitly).
    pub texcoords: Option<Vec<[f32; 2]>>,
}

/// `mat_*` fields of one material.
#[derive(Debug, Clone)]
pub struct MaterialDesc {
    pub rgba: [f32; 4],
    pub emission: f32,
    pub specular: f32,
    pub shininess: f32,
    pub reflectance: f32,
    /// Texture used for the RGB role, or -1.
    pub texid: i32,
    pub texrepeat: [f32; 2],
    pub texuniform: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TextureKind {
    Tex2D,
    Cube,
    Skybox,
}

/// A texture as RGBA8; cube and skybox textures hold six faces in MuJoCo's order (+X −X +Y −Y +Z −Z).
#[derive(Debug, Clone)]
pub struct TextureDesc {
    pub kind: TextureKind,
    pub width: u32,
    /// Height of one face.
    pub height: u32,
    /// `layers × height × width × 4` bytes (layers = 1 for 2D, 6 for cube/skybox).
    pub rgba8: Vec<u8>,
    /// `colorspace="sRGB"`: MuJoCo decodes such textures to linear when sampling (darker, more saturated).
    pub srgb: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LightKind {
    Spot,
    Directional,
    Point,
}

#[derive(Debug, Clone)]
pub struct LightDesc {
    pub kind: LightKind,
    pub active: bool,
    pub castshadow: bool,
    pub attenuation: [f32; 3],
    pub cutoff_deg: f32,
    pub exponent: f32,
    pub ambient: [f32; 3],
    pub diffuse: [f32; 3],
    pub specular: [f32; 3],
}

#[derive(Debug, Clone)]
pub struct CameraDesc {
    pub name: String,
    pub fovy_deg: f64,
}

/// `vis.headlight`.
#[derive(Debug, Clone)]
pub struct HeadlightDesc {
    pub active: bool,
    pub ambient: [f32; 3],
    pub diffuse: [f32; 3],
    pub specular: [f32; 3],
}

/// Everything the renderer needs from one compiled model; extracted once and cached per model.
#[derive(Debug, Clone)]
pub struct SceneModel {
    pub geoms: Vec<DrawableDesc>,
    pub sites: Vec<DrawableDesc>,
    pub meshes: Vec<MeshData>,
    pub materials: Vec<MaterialDesc>,
    pub textures: Vec<TextureDesc>,
    pub lights: Vec<LightDesc>,
    pub cameras: Vec<CameraDesc>,
    pub headlight: HeadlightDesc,
    /// Clip planes in metres (`vis.map.znear/zfar × stat.extent`), as MuJoCo's renderer uses them.
    pub znear_m: f64,
    pub zfar_m: f64,
    /// `vis.quality.numslices/numstacks` for tessellating round primitives.
    pub numslices: u32,
    pub numstacks: u32,
}

/// Borrow a MuJoCo array as a slice (empty when the model has none).
///
/// # Safety
/// `p` must point to at least `n` valid elements for the lifetime of the model.
unsafe fn arr<'a, T>(p: *const T, n: usize) -> &'a [T] {
    if p.is_null() || n == 0 { &[] } else { unsafe { std::slice::from_raw_parts(p, n) } }
}

impl SceneModel {
    /// This description without mesh vertices and texture pixels (`texcoords` stays `Some` where present, empty):
    /// what an upload keeps once they are on the GPU. A LIBERO kitchen holds 1.2 M mesh vertices and over
    /// 100 MB of textures, which every live episode otherwise kept twice (here and on the GPU).
    pub fn without_bulk_data(&self) -> Self {
        let meshes = self
            .meshes
            .iter()
            .map(|m| MeshData { positions: Vec::new(), normals: Vec::new(), texcoords: m.texcoords.as_ref().map(|_| Vec::new()) })
            .collect();
        let textures = self
            .textures
            .iter()
            .map(|t| TextureDesc { kind: t.kind, width: t.width, height: t.height, rgba8: Vec::new(), srgb: t.srgb })
            .collect();
        Self {
            geoms: self.geoms.clone(),
            sites: self.sites.clone(),
            meshes,
            materials: self.materials.clone(),
            textures,
            lights: self.lights.clone(),
            cameras: self.cameras.clone(),
            headlight: self.headlight.clone(),
            znear_m: self.znear_m,
            zfar_m: self.zfar_m,
            numslices: self.numslices,
            numstacks: self.numstacks,
        }
    }

    /// Copy the render-relevant parts of a compiled model.
    pub fn from_mujoco(model: &MjModel) -> Result<Self, RenderError> {
        let m: &mjModel = model.ffi();
        // SAFETY: every array below is sized by the corresponding count in the same mjModel, which
        // `model` owns and keeps alive for this function's duration.
        unsafe {
            let ngeom = m.ngeom as usize;
            let nsite = m.nsite as usize;
            let gtype = arr(m.geom_type, ngeom);
            let gsize = arr(m.geom_size, 3 * ngeom);
            let grgba = arr(m.geom_rgba, 4 * ngeom);
            let gmat = arr(m.geom_matid, ngeom);
            let ggroup = arr(m.geom_group, ngeom);
            let gdata = arr(m.geom_dataid, ngeom);
            let gbody = arr(m.geom_bodyid, ngeom);
            let geoms = (0..ngeom)
                .map(|i| DrawableDesc {
                    kind: GeomKind::from_mj(gtype[i]),
                    size: [gsize[3 * i] as f32, gsize[3 * i + 1] as f32, gsize[3 * i + 2] as f32],
                    rgba: [grgba[4 * i], grgba[4 * i + 1], grgba[4 * i + 2], grgba[4 * i + 3]],
                    matid: gmat[i],
                    group: ggroup[i],
                    dataid: gdata[i],
                    bodyid: gbody[i],
                })
                .collect();
            let stype = arr(m.site_type, nsite);
            let ssize = arr(m.site_size, 3 * nsite);
            let srgba = arr(m.site_rgba, 4 * nsite);
            let smat = arr(m.site_matid, nsite);
            let sgroup = arr(m.site_group, nsite);
            let sbody = arr(m.site_bodyid, nsite);
            let sites = (0..nsite)
                .map(|i| DrawableDesc {
                    kind: GeomKind::from_mj(stype[i]),
                    size: [ssize[3 * i] as f32, ssize[3 * i + 1] as f32, ssize[3 * i + 2] as f32],
                    rgba: [srgba[4 * i], srgba[4 * i + 1], srgba[4 * i + 2], srgba[4 * i + 3]],
                    matid: smat[i],
                    group: sgroup[i],
                    dataid: -1,
                    bodyid: sbody[i],
                })
                .collect();

            let meshes = Self::extract_meshes(m);
            let nmat = m.nmat as usize;
            let ntexrole = 10usize; // mjNTEXROLE
            let mrgba = arr(m.mat_rgba, 4 * nmat);
            let memi = arr(m.mat_emission, nmat);
            let mspec = arr(m.mat_specular, nmat);
            let mshin = arr(m.mat_shininess, nmat);
            let mrefl = arr(m.mat_reflectance, nmat);
            let mtex = arr(m.mat_texid, ntexrole * nmat);
            let mrep = arr(m.mat_texrepeat, 2 * nmat);
            let muni = arr(m.mat_texuniform, nmat);
            let materials = (0..nmat)
                .map(|i| {
                    // Prefer the RGB role (MuJoCo's classic renderer reads only that one), else RGBA.
                    let rgb = mtex[ntexrole * i + 1];
                    let texid = if rgb >= 0 { rgb } else { mtex[ntexrole * i + 8] };
                    MaterialDesc {
                        rgba: [mrgba[4 * i], mrgba[4 * i + 1], mrgba[4 * i + 2], mrgba[4 * i + 3]],
                        emission: memi[i],
                        specular: mspec[i],
                        shininess: mshin[i],
                        reflectance: mrefl[i],
                        texid,
                        texrepeat: [mrep[2 * i], mrep[2 * i + 1]],
                        texuniform: muni[i],
                    }
                })
                .collect();
            let textures = Self::extract_textures(m)?;

            let nlight = m.nlight as usize;
            let ltype = arr(m.light_type, nlight);
            let lact = arr(m.light_active, nlight);
            let lshadow = arr(m.light_castshadow, nlight);
            let latt = arr(m.light_attenuation, 3 * nlight);
            let lcut = arr(m.light_cutoff, nlight);
            let lexp = arr(m.light_exponent, nlight);
            let lamb = arr(m.light_ambient, 3 * nlight);
            let ldif = arr(m.light_diffuse, 3 * nlight);
            let lspe = arr(m.light_specular, 3 * nlight);
            let v3 = |a: &[f32], i: usize| [a[3 * i], a[3 * i + 1], a[3 * i + 2]];
            let lights = (0..nlight)
                .map(|i| LightDesc {
                    kind: match ltype[i] {
                        1 => LightKind::Directional,
                        2 => LightKind::Point,
                        _ => LightKind::Spot,
                    },
                    active: lact[i],
                    castshadow: lshadow[i],
                    attenuation: v3(latt, i),
                    cutoff_deg: lcut[i],
                    exponent: lexp[i],
                    ambient: v3(lamb, i),
                    diffuse: v3(ldif, i),
                    specular: v3(lspe, i),
                })
                .collect();

            let ncam = m.ncam as usize;
            let fovy = arr(m.cam_fovy, ncam);
            let cameras = (0..ncam)
                .map(|i| CameraDesc {
                    name: model.id_to_name(MjtObjBase::mjOBJ_CAMERA, i).unwrap_or("").to_string(),
                    fovy_deg: fovy[i],
                })
                .collect();
            let hl = &m.vis.headlight;
            Ok(Self {
                geoms,
                sites,
                meshes,
                materials,
                textures,
                lights,
                cameras,
                headlight: HeadlightDesc {
                    active: hl.active != 0,
                    ambient: hl.ambient,
                    diffuse: hl.diffuse,
                    specular: hl.specular,
                },
                znear_m: m.vis.map.znear as f64 * m.stat.extent,
                zfar_m: m.vis.map.zfar as f64 * m.stat.extent,
                numslices: m.vis.quality.numslices.clamp(8, 128) as u32,
                numstacks: m.vis.quality.numstacks.clamp(4, 64) as u32,
            })
        }
    }

    /// # Safety
    /// `m` must be a valid compiled model.
    unsafe fn extract_meshes(m: &mjModel) -> Vec<MeshData> {
        unsafe {
            let nmesh = m.nmesh as usize;
            let vert = arr(m.mesh_vert, 3 * m.nmeshvert as usize);
            let normal = arr(m.mesh_normal, 3 * m.nmeshnormal as usize);
            let tex = arr(m.mesh_texcoord, 2 * m.nmeshtexcoord as usize);
            let face = arr(m.mesh_face, 3 * m.nmeshface as usize);
            let facen = arr(m.mesh_facenormal, 3 * m.nmeshface as usize);
            let facet = arr(m.mesh_facetexcoord, 3 * m.nmeshface as usize);
            let vadr = arr(m.mesh_vertadr, nmesh);
            let nadr = arr(m.mesh_normaladr, nmesh);
            let tadr = arr(m.mesh_texcoordadr, nmesh);
            let fadr = arr(m.mesh_faceadr, nmesh);
            let fnum = arr(m.mesh_facenum, nmesh);
            (0..nmesh)
                .map(|i| {
                    let nf = fnum[i] as usize;
                    let mut out = MeshData {
                        positions: Vec::with_capacity(3 * nf),
                        normals: Vec::with_capacity(3 * nf),
                        texcoords: (tadr[i] >= 0).then(|| Vec::with_capacity(3 * nf)),
                    };
                    for f in 0..nf {
                        let fi = fadr[i] as usize + f;
                        let p = |c: usize| {
                            let v = vadr[i] as usize + face[3 * fi + c] as usize;
                            [vert[3 * v], vert[3 * v + 1], vert[3 * v + 2]]
                        };
                        let (a, b, cc) = (p(0), p(1), p(2));
                        let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
                        let e2 = [cc[0] - a[0], cc[1] - a[1], cc[2] - a[2]];
                        let fnrm = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
                        for c in 0..3 {
                            out.positions.push(p(c));
                            let n = nadr[i] as usize + facen[3 * fi + c] as usize;
                            let sn = [normal[3 * n], normal[3 * n + 1], normal[3 * n + 2]];
                            // A smoothed normal pointing against its face (sharp creases) would light the
                            // face from behind; use the face normal there, which matches MuJoCo's images.
                            let dot = sn[0] * fnrm[0] + sn[1] * fnrm[1] + sn[2] * fnrm[2];
                            out.normals.push(if dot < 0.0 { fnrm } else { sn });
                            if let Some(tc) = out.texcoords.as_mut() {
                                let t = tadr[i] as usize + facet[3 * fi + c] as usize;
                                tc.push([tex[2 * t], tex[2 * t + 1]]);
                            }
                        }
                    }
                    out
                })
                .collect()
        }
    }

    /// # Safety
    /// `m` must be a valid compiled model.
    unsafe fn extract_textures(m: &mjModel) -> Result<Vec<TextureDesc>, RenderError> {
        unsafe {
            let ntex = m.ntex as usize;
            let ttype = arr(m.tex_type, ntex);
            let th = arr(m.tex_height, ntex);
            let tw = arr(m.tex_width, ntex);
            let tnc = arr(m.tex_nchannel, ntex);
            let tadr = arr(m.tex_adr, ntex);
            let tcs = arr(m.tex_colorspace, ntex);
            let data = arr(m.tex_data, m.ntexdata as usize);
            let mut out = Vec::with_capacity(ntex);
            for i in 0..ntex {
                let (w, h, nc) = (tw[i] as usize, th[i] as usize, tnc[i] as usize);
                let kind = match ttype[i] {
                    1 => TextureKind::Cube,
                    2 => TextureKind::Skybox,
                    _ => TextureKind::Tex2D,
                };
                let src = data.get(tadr[i] as usize..tadr[i] as usize + w * h * nc).ok_or_else(|| {
                    RenderError::Model(format!("texture {i}: data out of range"))
                })?;
                let to_rgba = |px: &[u8]| -> [u8; 4] {
                    match nc {
                        1 => [px[0], px[0], px[0], 255],
                        3 => [px[0], px[1], px[2], 255],
                        4 => [px[0], px[1], px[2], px[3]],
                        _ => [px[0], px[0], px[0], 255],
                    }
                };
                let mut rgba8 = Vec::with_capacity(w * h * 4);
                for px in src.chunks_exact(nc.max(1)) {
                    rgba8.extend_from_slice(&to_rgba(px));
                }
                let (face_h, rgba8) = match kind {
                    TextureKind::Tex2D => (h, rgba8),
                    // A cube made from one image stores a single face that MuJoCo repeats on all six.
                    _ if h == w => (h, rgba8.repeat(6)),
                    _ if h == 6 * w => (w, rgba8),
                    _ => {
                        return Err(RenderError::Model(format!(
                            "cube texture {i}: unexpected size {w}x{h}"
                        )));
                    }
                };
                let srgb = tcs.get(i) == Some(&2); // mjCOLORSPACE_SRGB
                out.push(TextureDesc { kind, width: w as u32, height: face_h as u32, rgba8, srgb });
            }
            Ok(out)
        }
    }

    /// Camera id by name (`agentview`, `robot0_eye_in_hand`, ...).
    pub fn camera_id(&self, name: &str) -> Option<usize> {
        self.cameras.iter().position(|c| c.name == name)
    }
}

/// Which geom and site groups are drawn (MuJoCo's `mjvOption.geomgroup/sitegroup`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Visibility {
    pub geomgroup: [bool; 6],
    pub sitegroup: [bool; 6],
}

impl Visibility {
    /// robosuite's observation images: collision geoms (group 0) hidden, visual (1) and group 2 shown,
    /// site groups 0–2 shown (MuJoCo defaults), libero_port_notes.md §4.3.
    pub const ROBOSUITE: Self = Self {
        geomgroup: [false, true, true, false, false, false],
        sitegroup: [true, true, true, false, false, false],
    };
    /// MuJoCo's default `mjvOption` (groups 0–2 shown).
    pub const MUJOCO_DEFAULT: Self = Self {
        geomgroup: [true, true, true, false, false, false],
        sitegroup: [true, true, true, false, false, false],
    };
}

impl Default for Visibility {
    fn default() -> Self {
        Self::ROBOSUITE
    }
}

/// Poses and run-time appearance for one frame, read from `MjData` (and the model's mutable colours).
#[derive(Debug, Clone, Default)]
pub struct FrameState {
    /// `geom_xpos` (world, metres) and row-major `geom_xmat`.
    pub geom_xpos: Vec<[f64; 3]>,
    pub geom_xmat: Vec<[f64; 9]>,
    pub site_xpos: Vec<[f64; 3]>,
    pub site_xmat: Vec<[f64; 9]>,
    pub cam_xpos: Vec<[f64; 3]>,
    pub cam_xmat: Vec<[f64; 9]>,
    pub light_xpos: Vec<[f64; 3]>,
    pub light_xdir: Vec<[f64; 3]>,
    /// Current `geom_rgba` / `site_rgba` (robosuite edits these at run time: site hiding, burner toggle).
    pub geom_rgba: Vec<[f32; 4]>,
    pub site_rgba: Vec<[f32; 4]>,
    /// World pose (position, row-major rotation) of body `robot0_base`, for `T_robot_base_from_camera`.
    pub robot_base_pose: Option<([f64; 3], [f64; 9])>,
}

fn chunks<const N: usize, T: Copy + Default>(s: &[T]) -> Vec<[T; N]> {
    s.chunks_exact(N)
        .map(|c| {
            let mut a = [T::default(); N];
            a.copy_from_slice(c);
            a
        })
        .collect()
}

impl FrameState {
    /// Read the current kinematics (call after `mj_forward`/`mj_step`) and colours.
    pub fn from_mujoco<M: ModelType>(model: &MjModel, data: &MjData<M>) -> Self {
        let m: &mjModel = model.ffi();
        let d: &mjData = data.ffi();
        let (ng, ns, nc, nl) = (m.ngeom as usize, m.nsite as usize, m.ncam as usize, m.nlight as usize);
        // SAFETY: mjData arrays are sized by the model counts; `data` belongs to `model`'s layout.
        unsafe {
            Self {
                geom_xpos: chunks(arr(d.geom_xpos, 3 * ng)),
                geom_xmat: chunks(arr(d.geom_xmat, 9 * ng)),
                site_xpos: chunks(arr(d.site_xpos, 3 * ns)),
                site_xmat: chunks(arr(d.site_xmat, 9 * ns)),
                cam_xpos: chunks(arr(d.cam_xpos, 3 * nc)),
                cam_xmat: chunks(arr(d.cam_xmat, 9 * nc)),
                light_xpos: chunks(arr(d.light_xpos, 3 * nl)),
                light_xdir: chunks(arr(d.light_xdir, 3 * nl)),
                geom_rgba: chunks(arr(m.geom_rgba, 4 * ng)),
                site_rgba: chunks(arr(m.site_rgba, 4 * ns)),
                robot_base_pose: model
                    .name_to_id(MjtObjBase::mjOBJ_BODY, ROBOT_BASE_BODY)
                    .map(|b| (data.xpos()[b], data.xmat()[b])),
            }
        }
    }

    /// robosuite's `visualize(False)` at reset: every robot, gripper and object site with positive alpha
    /// gets its alpha negated (hidden). Sites on the world body (arena markers) are left alone.
    pub fn apply_robosuite_site_hiding(&mut self, scene: &SceneModel) {
        for (rgba, site) in self.site_rgba.iter_mut().zip(&scene.sites) {
            if site.bodyid != 0 && rgba[3] > 0.0 {
                rgba[3] = -rgba[3];
            }
        }
    }
}

/// robosuite's `visualize(False)` applied to the model itself (as robosuite does): negate the positive
/// alpha of every site not attached to the world body, so they are hidden; a later LIBERO
/// `set_visualization` (stove burner) can show a site again with `alpha ← 1 − alpha`.
pub fn robosuite_hide_sites(model: &mut MjModel) {
    let bodies = model.site_bodyid().to_vec();
    for (rgba, body) in model.site_rgba_mut().iter_mut().zip(bodies) {
        if body != 0 && rgba[3] > 0.0 {
            rgba[3] = -rgba[3];
        }
    }
}
