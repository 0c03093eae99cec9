//! Triangle soups for MuJoCo's primitives, in the unit object coordinates MuJoCo's own renderer uses
//! (so texture generation from object coordinates matches), and for compiled meshes.
use std::f32::consts::PI;

use bytemuck::{Pod, Zeroable};

use crate::scene::MeshData;

/// One vertex: object-space position and normal, explicit texture coordinate (zero when unused).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Vertex {
    pub pos: [f32; 3],
    pub normal: [f32; 3],
    pub uv: [f32; 2],
}

fn v(pos: [f32; 3], normal: [f32; 3]) -> Vertex {
    Vertex { pos, normal, uv: [0.0, 0.0] }
}

/// Push the two triangles of quad a-b-c-d (counter-clockwise seen from outside).
fn quad(out: &mut Vec<Vertex>, a: Vertex, b: Vertex, c: Vertex, d: Vertex) {
    out.extend_from_slice(&[a, b, c, a, c, d]);
}

/// Unit box `[-1,1]^3`.
pub fn unit_box() -> Vec<Vertex> {
    let mut out = Vec::with_capacity(36);
    for axis in 0..3 {
        for sign in [1.0f32, -1.0] {
            let (u, w) = ((axis + 1) % 3, (axis + 2) % 3);
            let corner = |a: f32, b: f32| {
                let mut p = [0.0f32; 3];
                p[axis] = sign;
                p[u] = a;
                p[w] = b;
                let mut n = [0.0f32; 3];
                n[axis] = sign;
                v(p, n)
            };
            if sign > 0.0 {
                quad(&mut out, corner(-1., -1.), corner(1., -1.), corner(1., 1.), corner(-1., 1.));
            } else {
                quad(&mut out, corner(-1., -1.), corner(-1., 1.), corner(1., 1.), corner(1., -1.));
            }
        }
    }
    out
}

/// Unit square in z = 0 facing +z, split into `n × n` quads.
pub fn unit_plane(n: u32) -> Vec<Vertex> {
    let n = n.max(1);
    let mut out = Vec::with_capacity((6 * n * n) as usize);
    let step = 2.0 / n as f32;
    for i in 0..n {
        for j in 0..n {
            let (x0, y0) = (-1.0 + i as f32 * step, -1.0 + j as f32 * step);
            let (x1, y1) = (x0 + step, y0 + step);
            let nz = [0.0, 0.0, 1.0];
            quad(&mut out, v([x0, y0, 0.], nz), v([x1, y0, 0.], nz), v([x1, y1, 0.], nz), v([x0, y1, 0.], nz));
        }
    }
    out
}

/// Point and normal on an ellipsoid-like sphere at (stack angle, slice angle).
fn sphere_pt(theta: f32, phi: f32) -> [f32; 3] {
    [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()]
}

/// Unit sphere.
pub fn unit_sphere(slices: u32, stacks: u32) -> Vec<Vertex> {
    let mut out = Vec::new();
    for i in 0..stacks {
        let (t0, t1) = (PI * i as f32 / stacks as f32, PI * (i + 1) as f32 / stacks as f32);
        for j in 0..slices {
            let (p0, p1) = (2.0 * PI * j as f32 / slices as f32, 2.0 * PI * (j + 1) as f32 / slices as f32);
            let a = sphere_pt(t0, p0);
            let b = sphere_pt(t1, p0);
            let c = sphere_pt(t1, p1);
            let d = sphere_pt(t0, p1);
            quad(&mut out, v(a, a), v(b, b), v(c, c), v(d, d));
        }
    }
    out
}

/// Closed cylinder of radius 1 along z in `[-1, 1]`.
pub fn unit_cylinder(slices: u32) -> Vec<Vertex> {
    let mut out = Vec::new();
    for j in 0..slices {
        let (p0, p1) = (2.0 * PI * j as f32 / slices as f32, 2.0 * PI * (j + 1) as f32 / slices as f32);
        let (c0, s0, c1, s1) = (p0.cos(), p0.sin(), p1.cos(), p1.sin());
        quad(
            &mut out,
            v([c0, s0, -1.], [c0, s0, 0.]),
            v([c1, s1, -1.], [c1, s1, 0.]),
            v([c1, s1, 1.], [c1, s1, 0.]),
            v([c0, s0, 1.], [c0, s0, 0.]),
        );
        out.extend_from_slice(&[
            v([0., 0., 1.], [0., 0., 1.]),
            v([c0, s0, 1.], [0., 0., 1.]),
            v([c1, s1, 1.], [0., 0., 1.]),
            v([0., 0., -1.], [0., 0., -1.]),
            v([c1, s1, -1.], [0., 0., -1.]),
            v([c0, s0, -1.], [0., 0., -1.]),
        ]);
    }
    out
}

/// Capsule of radius `r` and cylinder half-length `h` along z, in metres (its caps do not scale
/// uniformly, so it is built per geom).
pub fn capsule(r: f32, h: f32, slices: u32, stacks: u32) -> Vec<Vertex> {
    let mut out = Vec::new();
    let half = (stacks / 2).max(2);
    let cap_pt = |theta: f32, phi: f32, top: bool| {
        let n = sphere_pt(theta, phi);
        let z = if top { h } else { -h };
        v([r * n[0], r * n[1], r * n[2] + z], n)
    };
    for i in 0..half {
        let (t0, t1) = (0.5 * PI * i as f32 / half as f32, 0.5 * PI * (i + 1) as f32 / half as f32);
        for j in 0..slices {
            let (p0, p1) = (2.0 * PI * j as f32 / slices as f32, 2.0 * PI * (j + 1) as f32 / slices as f32);
            quad(&mut out, cap_pt(t0, p0, true), cap_pt(t1, p0, true), cap_pt(t1, p1, true), cap_pt(t0, p1, true));
            let (b0, b1) = (PI - t0, PI - t1);
            quad(&mut out, cap_pt(b0, p0, false), cap_pt(b0, p1, false), cap_pt(b1, p1, false), cap_pt(b1, p0, false));
        }
    }
    for j in 0..slices {
        let (p0, p1) = (2.0 * PI * j as f32 / slices as f32, 2.0 * PI * (j + 1) as f32 / slices as f32);
        let (c0, s0, c1, s1) = (p0.cos(), p0.sin(), p1.cos(), p1.sin());
        quad(
            &mut out,
            v([r * c0, r * s0, -h], [c0, s0, 0.]),
            v([r * c1, r * s1, -h], [c1, s1, 0.]),
            v([r * c1, r * s1, h], [c1, s1, 0.]),
            v([r * c0, r * s0, h], [c0, s0, 0.]),
        );
    }
    out
}

/// A compiled mesh as vertices.
pub fn mesh_vertices(mesh: &MeshData) -> Vec<Vertex> {
    (0..mesh.positions.len())
        .map(|i| Vertex {
            pos: mesh.positions[i],
            normal: mesh.normals[i],
            uv: mesh.texcoords.as_ref().map(|t| t[i]).unwrap_or([0.0, 0.0]),
        })
        .collect()
}
