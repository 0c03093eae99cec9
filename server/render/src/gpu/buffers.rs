//! An upload's geometry as it is assembled: one vertex and one index buffer for every shape of a model (unit
//! primitives, capsules, meshes with their simplified levels and, for large meshes, chunks to cull part by part).
use std::collections::{HashMap, HashSet};

use glam::Vec3;

use crate::geometry::Vertex;
use crate::lod;

/// What to draw for one geom or site.
#[derive(Clone, Copy)]
pub(super) struct Shape {
    /// Range in the model's index buffer.
    pub(super) first_vertex: u32,
    pub(super) vertex_count: u32,
    /// Object scale applied before the pose (unit primitives are scaled by size).
    pub(super) scale: [f32; 3],
    /// Object coordinates are metric (meshes, capsules): texgen divides by size like MuJoCo's
    /// "pre-scaled" geoms.
    pub(super) prescaled: bool,
    /// Bounding-sphere radius in object units (scaled by `scale`), for per-camera frustum culling.
    pub(super) radius: f32,
    /// Simplified levels of a mesh (fine to coarse), chosen per camera by [`super::RenderOptions::mesh_lod_pixel_error`].
    pub(super) lods: LodRanges,
    /// The exact mesh's pieces (start and end in [`super::upload::GpuModel::chunks`]), for culling a large mesh part by part.
    pub(super) chunks: (u32, u32),
}

/// A spatially compact piece of a large mesh's exact index range, with its bounding sphere (object frame).
#[derive(Debug, Clone, Copy)]
pub(super) struct Chunk {
    pub(super) first_index: u32,
    pub(super) index_count: u32,
    pub(super) center: [f32; 3],
    pub(super) radius: f32,
}

/// Meshes with at least this many triangles are cut into chunks of [`CHUNK_TRIANGLES`]: a room's walls hold the
/// camera inside their bounding sphere (so they are drawn exactly and never culled whole), yet most of them lies
/// outside any one camera's view.
const CHUNK_MIN_TRIANGLES: usize = 4096;
const CHUNK_TRIANGLES: usize = 1024;

/// Up to four simplified levels of one mesh inside the model's index buffer (fine to coarse).
#[derive(Clone, Copy, Default)]
pub(super) struct LodRanges {
    levels: [lod::LevelRange; lod::LEVEL_ERRORS_M.len()],
    count: usize,
}

impl LodRanges {
    pub(super) fn ranges(&self) -> &[lod::LevelRange] {
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
pub(super) struct GeometryBuilder {
    pub(super) vertices: Vec<Vertex>,
    pub(super) indices: Vec<u32>,
    seen: HashMap<[u32; 8], u32>,
    pub(super) chunks: Vec<Chunk>,
}

impl GeometryBuilder {
    /// Appends a triangle soup, sharing identical corners; returns its index range.
    pub(super) fn push_soup(&mut self, soup: Vec<Vertex>) -> (u32, u32) {
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
    pub(super) fn push_mesh(&mut self, soup: Vec<Vertex>, uv_textured: bool) -> ((u32, u32), LodRanges, std::ops::Range<u32>) {
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
