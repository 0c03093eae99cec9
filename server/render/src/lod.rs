//! Mesh levels of detail. On CPU rasterisers (lavapipe, llvmpipe) the cost of a LIBERO frame is dominated by
//! vertex work on a few scanned meshes (the kitchen background alone has 70k triangles) that are far denser
//! than a 256×256 image can show. (Meshes whose bounding sphere holds the camera, like a room's walls, stay
//! exact: a fixed error floor would have sped them up too, but cost up to 7 dB PSNR against MuJoCo because
//! the simplifier ignores texture coordinates.) Each mesh gets a chain of simplified index lists with a bounded geometric
//! error in metres (meshoptimizer's edge-collapse simplifier, attribute seams preserved); per camera, a draw
//! uses the coarsest level whose error projects below a pixel budget, and never one coarser than allowed by
//! the conservative distance of the mesh's bounding sphere. Level 0 is always the exact mesh.
use crate::geometry::Vertex;

/// Geometric errors of the simplified levels, metres (absolute, not relative to the mesh size).
pub const LEVEL_ERRORS_M: [f32; 4] = [0.0002, 0.0006, 0.002, 0.006];
/// A level is kept only when it has at most this fraction of the previous level's triangles.
const MIN_REDUCTION: f32 = 0.8;
/// Meshes smaller than this are drawn exactly (simplifying them saves nothing measurable).
const MIN_TRIANGLES: usize = 256;

/// One level: indices into the mesh's own vertex list and the geometric error it guarantees.
#[derive(Debug, Clone, PartialEq)]
pub struct Level {
    pub indices: Vec<u32>,
    pub error_m: f32,
}

/// Simplified levels of one indexed mesh, coarsest last; empty when the mesh is small or does not simplify.
pub fn simplified_levels(vertices: &[Vertex], indices: &[u32]) -> Vec<Level> {
    if indices.len() / 3 < MIN_TRIANGLES || vertices.is_empty() {
        return Vec::new();
    }
    let bytes: &[u8] = bytemuck::cast_slice(vertices);
    let Ok(adapter) = meshopt::VertexDataAdapter::new(bytes, size_of::<Vertex>(), 0) else {
        return Vec::new();
    };
    let mut levels: Vec<Level> = Vec::new();
    let mut previous = indices.len();
    for &target in &LEVEL_ERRORS_M {
        let mut achieved = 0.0f32;
        let simplified = meshopt::simplify(
            indices,
            &adapter,
            0,
            target,
            meshopt::SimplifyOptions::ErrorAbsolute,
            Some(&mut achieved),
        );
        if simplified.is_empty() || (simplified.len() as f32) > MIN_REDUCTION * previous as f32 {
            continue;
        }
        previous = simplified.len();
        // The simplifier reports the error it reached; keep the larger of it and the target as the bound.
        levels.push(Level { indices: simplified, error_m: achieved.max(target) });
    }
    levels
}

/// A level's place in the model's index buffer.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LevelRange {
    pub first_index: u32,
    pub index_count: u32,
    pub error_m: f32,
}

/// How coarse a mesh may be drawn for one camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LodBudget {
    /// Largest allowed projected error, pixels (0 disables simplification).
    pub pixel_error: f32,
    /// Focal length of the camera, pixels.
    pub focal_px: f32,
}

impl LodBudget {
    /// The allowed geometric error at `distance_m` (the nearest a surface of the mesh can be).
    pub fn allowed_error_m(&self, distance_m: f32) -> f32 {
        if self.pixel_error <= 0.0 || self.focal_px <= 0.0 {
            return 0.0;
        }
        self.pixel_error * distance_m.max(0.0) / self.focal_px
    }
}

/// The coarsest level (from `levels`, ordered fine to coarse) whose error is within `allowed_error_m`.
pub fn pick(levels: &[LevelRange], allowed_error_m: f32) -> Option<LevelRange> {
    levels.iter().rev().find(|l| l.error_m <= allowed_error_m).copied()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A finely tessellated flat grid (a 1 m square): the simplifier may collapse it to very few triangles
    /// because every level's geometric error is zero.
    fn grid(n: u32) -> (Vec<Vertex>, Vec<u32>) {
        let mut v = Vec::new();
        for y in 0..=n {
            for x in 0..=n {
                v.push(Vertex { pos: [x as f32 / n as f32, y as f32 / n as f32, 0.0], normal: [0.0, 0.0, 1.0], uv: [0.0, 0.0] });
            }
        }
        let mut idx = Vec::new();
        for y in 0..n {
            for x in 0..n {
                let i = y * (n + 1) + x;
                idx.extend_from_slice(&[i, i + 1, i + n + 2, i, i + n + 2, i + n + 1]);
            }
        }
        (v, idx)
    }

    #[test]
    fn a_flat_dense_grid_simplifies_to_far_fewer_triangles_with_error_within_its_bound() {
        let (v, idx) = grid(40);
        let levels = simplified_levels(&v, &idx);
        assert!(!levels.is_empty());
        assert!(levels[0].indices.len() * 10 < idx.len(), "{} of {}", levels[0].indices.len(), idx.len());
        for l in &levels {
            assert!(l.error_m <= LEVEL_ERRORS_M[LEVEL_ERRORS_M.len() - 1] * 1.01);
            assert!(l.indices.iter().all(|&i| (i as usize) < v.len()));
        }
    }

    #[test]
    fn small_meshes_are_left_exact() {
        let (v, idx) = grid(4);
        assert!(simplified_levels(&v, &idx).is_empty());
    }

    #[test]
    fn the_pick_is_the_coarsest_level_within_budget_and_none_when_too_close() {
        let levels = [
            LevelRange { first_index: 0, index_count: 300, error_m: 0.0002 },
            LevelRange { first_index: 300, index_count: 90, error_m: 0.002 },
        ];
        let budget = LodBudget { pixel_error: 0.5, focal_px: 309.0 };
        // 0.5 px at 2 m is 3.2 mm: the coarse level fits.
        assert_eq!(pick(&levels, budget.allowed_error_m(2.0)).map(|l| l.first_index), Some(300));
        // at 0.3 m 0.5 px is 0.49 mm: only the fine level fits.
        assert_eq!(pick(&levels, budget.allowed_error_m(0.3)).map(|l| l.first_index), Some(0));
        // at 5 cm nothing fits: the exact mesh is drawn.
        assert_eq!(pick(&levels, budget.allowed_error_m(0.05)), None);
        assert_eq!(pick(&levels, LodBudget { pixel_error: 0.0, focal_px: 309.0 }.allowed_error_m(100.0)), None);
    }
}
