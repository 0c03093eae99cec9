// MuJoCo's classic (fixed-function OpenGL) look, evaluated per pixel:
//   colour = clamp(emission·rgba + Σ_l att·spot·(amb_l·rgba + diff_l·rgba·max(n·L,0) + spec_l·specular·max(n·H,0)^shin))
//   final  = colour × texture (GL_MODULATE, single-colour light model), alpha = rgba.a × texture.a
// plus a linear planar depth target (bitcast f32 in R32Uint: portable to GL) and a segmentation id target.

struct Light {
    pos: vec4<f32>,        // w = 1 positional, 0 directional (xyz = direction *towards* the light)
    dir: vec4<f32>,        // spot direction (world)
    ambient: vec4<f32>,
    diffuse: vec4<f32>,
    specular: vec4<f32>,
    spot: vec4<f32>,       // x = cos(cutoff), y = exponent, z = 1 if spot cone applies
    atten: vec4<f32>,
};

struct Camera {
    view_proj: mat4x4<f32>,
    view: mat4x4<f32>,
    inv_view_proj: mat4x4<f32>,
    eye: vec4<f32>,
    counts: vec4<u32>,     // x = number of lights
    lights: array<Light, 9>,
};

struct Draw {
    model: mat4x4<f32>,
    normal0: vec4<f32>,
    normal1: vec4<f32>,
    normal2: vec4<f32>,
    rgba: vec4<f32>,
    material: vec4<f32>,   // emission, specular, shininess exponent, unused
    texgen: vec4<f32>,     // 2D: s scale, t scale; cube: x, y scale
    texgen2: vec4<f32>,    // cube: z scale
    misc: vec4<u32>,       // x = texture mode (0 none, 1 explicit uv, 2 2D texgen, 3 cube), y = segmentation id
};

@group(0) @binding(0) var<uniform> cam: Camera;
@group(1) @binding(0) var<uniform> draw: Draw;
@group(2) @binding(0) var tex2d: texture_2d<f32>;
@group(2) @binding(1) var texcube: texture_cube<f32>;
@group(2) @binding(2) var samp: sampler;

struct VsIn {
    @location(0) pos: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) uv: vec2<f32>,
};

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) obj: vec3<f32>,
    @location(3) uv: vec2<f32>,
    @location(4) view_depth: f32,
};

struct FsOut {
    @location(0) color: vec4<f32>,
    @location(1) depth: u32,
    @location(2) seg: u32,
};

@vertex
fn vs_main(v: VsIn) -> VsOut {
    var o: VsOut;
    let world = draw.model * vec4<f32>(v.pos, 1.0);
    o.world = world.xyz;
    o.clip = cam.view_proj * world;
    let nm = mat3x3<f32>(draw.normal0.xyz, draw.normal1.xyz, draw.normal2.xyz);
    o.normal = nm * v.normal;
    o.obj = v.pos;
    o.uv = v.uv;
    o.view_depth = -(cam.view * world).z;
    return o;
}

// The texture mode is a pipeline constant, not a uniform: a CPU rasteriser runs both sides of every branch under
// a lane mask, so a per-draw `if` on a uniform would sample all three textures for every fragment.
override TEX_MODE: u32 = 0u;

fn texture_color(i: VsOut) -> vec4<f32> {
    let mode = TEX_MODE;
    if (mode == 1u) {
        return textureSample(tex2d, samp, i.uv);
    } else if (mode == 2u) {
        let s = 0.5 * draw.texgen.x * i.obj.x - 0.5;
        let t = -0.5 * draw.texgen.y * i.obj.y - 0.5;
        return textureSample(tex2d, samp, vec2<f32>(s, t));
    } else if (mode == 3u) {
        let d = vec3<f32>(draw.texgen.z * i.obj.x, draw.texgen.w * i.obj.y, draw.texgen2.x * i.obj.z);
        return textureSample(texcube, samp, d);
    }
    return vec4<f32>(1.0);
}

// The scene's light list is fixed per model, so its shape is a pipeline constant too: how many lights, and per
// light (bit k) whether it is positional and whether it has a spot cone. Only the live paths are compiled.
override LIGHT_COUNT: u32 = 0u;
override LIGHT_POSITIONAL: u32 = 0u;
override LIGHT_SPOT: u32 = 0u;

fn light_term(k: u32, world: vec3<f32>, n: vec3<f32>, v: vec3<f32>, rgb: vec3<f32>) -> vec3<f32> {
    let l = cam.lights[k];
    var ldir: vec3<f32>;
    var att = 1.0;
    if (((LIGHT_POSITIONAL >> k) & 1u) != 0u) {
        let d = l.pos.xyz - world;
        let dist = length(d);
        ldir = d / max(dist, 1e-9);
        att = 1.0 / max(l.atten.x + l.atten.y * dist + l.atten.z * dist * dist, 1e-9);
        if (((LIGHT_SPOT >> k) & 1u) != 0u) {
            let cs = dot(-ldir, normalize(l.dir.xyz));
            if (cs < l.spot.x) {
                att = 0.0;
            } else {
                att = att * pow(max(cs, 0.0), l.spot.y);
            }
        }
    } else {
        ldir = normalize(l.pos.xyz);
    }
    let ndl = dot(n, ldir);
    var term = l.ambient.rgb * rgb;
    if (ndl > 0.0) {
        term = term + l.diffuse.rgb * rgb * ndl;
        let h = normalize(ldir + v);
        let ndh = max(dot(n, h), 0.0);
        var sp = 0.0;
        if (ndh > 0.0) {
            sp = pow(ndh, draw.material.z);
        }
        term = term + l.specular.rgb * draw.material.y * sp;
    }
    return att * term;
}

fn lit(i: VsOut) -> vec3<f32> {
    let rgb = draw.rgba.rgb;
    var c = draw.material.x * rgb;
    let n = normalize(i.normal);
    let v = normalize(cam.eye.xyz - i.world);
    // Unrolled by hand: each call is kept or dropped by a constant, in the light list's order.
    if (LIGHT_COUNT > 0u) { c = c + light_term(0u, i.world, n, v, rgb); }
    if (LIGHT_COUNT > 1u) { c = c + light_term(1u, i.world, n, v, rgb); }
    if (LIGHT_COUNT > 2u) { c = c + light_term(2u, i.world, n, v, rgb); }
    if (LIGHT_COUNT > 3u) { c = c + light_term(3u, i.world, n, v, rgb); }
    if (LIGHT_COUNT > 4u) { c = c + light_term(4u, i.world, n, v, rgb); }
    if (LIGHT_COUNT > 5u) { c = c + light_term(5u, i.world, n, v, rgb); }
    if (LIGHT_COUNT > 6u) { c = c + light_term(6u, i.world, n, v, rgb); }
    if (LIGHT_COUNT > 7u) { c = c + light_term(7u, i.world, n, v, rgb); }
    if (LIGHT_COUNT > 8u) { c = c + light_term(8u, i.world, n, v, rgb); }
    return clamp(c, vec3<f32>(0.0), vec3<f32>(1.0));
}

@fragment
fn fs_main(i: VsOut) -> FsOut {
    var o: FsOut;
    let t = texture_color(i);
    o.color = vec4<f32>(lit(i) * t.rgb, clamp(draw.rgba.a, 0.0, 1.0) * t.a);
    o.depth = bitcast<u32>(i.view_depth);
    o.seg = draw.misc.y;
    return o;
}

// Skybox: a full-screen triangle at the far plane; MuJoCo maps the cube texture with (x, z, −y).
struct SkyOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) ndc: vec2<f32>,
};

@vertex
fn vs_sky(@builtin(vertex_index) vi: u32) -> SkyOut {
    var o: SkyOut;
    let x = f32((vi << 1u) & 2u) * 2.0 - 1.0;
    let y = f32(vi & 2u) * 2.0 - 1.0;
    o.clip = vec4<f32>(x, y, 0.0, 1.0);
    o.ndc = vec2<f32>(x, y);
    return o;
}

@fragment
fn fs_sky(i: SkyOut) -> FsOut {
    var o: FsOut;
    let p = cam.inv_view_proj * vec4<f32>(i.ndc, 0.5, 1.0);
    let d = p.xyz / p.w - cam.eye.xyz;
    let c = textureSample(texcube, samp, vec3<f32>(d.x, d.z, -d.y));
    o.color = vec4<f32>(c.rgb, 1.0);
    o.depth = 0x7f800000u;
    o.seg = 0u;
    return o;
}
