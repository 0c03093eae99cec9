//! Mesh levels of detail against the exact meshes, on the compiled LIBERO reference scenes (both cameras,
//! 256×256, default state): the default budget changes the geom of a few dozen pixels at most, and
//! keeps the image and the depth map close to the exact meshes'. Needs no MuJoCo renderer, only the scenes' assets.
mod common;

use common::{CAMERAS, SIZE, load_model, psnr, render_ours_with, scenes};
use libero_render::{RenderOptions, Renderer};

/// Pixels that may change geom id, of 65,536. The budget is a quarter pixel, but a silhouette along a pixel row
/// flips the whole row for any move, and the simplifier's error is an estimate (a thin rim can thin out).
const MAX_CHANGED_PX: usize = 40;
/// The distance reported for changed pixels (pixels, in x and in y).
const MOVE_PX: i64 = 2;

/// Whether the exact image has `id` within [`MOVE_PX`] of pixel `i`.
fn id_nearby(seg: &[u32], i: usize, id: u32) -> bool {
    let (x, y) = ((i % SIZE as usize) as i64, (i / SIZE as usize) as i64);
    (-MOVE_PX..=MOVE_PX).any(|dy| {
        (-MOVE_PX..=MOVE_PX).any(|dx| {
            let (nx, ny) = (x + dx, y + dy);
            (0..SIZE as i64).contains(&nx) && (0..SIZE as i64).contains(&ny) && seg[(ny * SIZE as i64 + nx) as usize] == id
        })
    })
}

#[test]
fn default_levels_of_detail_move_few_silhouette_pixels_and_keep_image_and_depth() {
    let renderer = Renderer::new().expect("renderer");
    let exact_options = RenderOptions { mesh_lod_pixel_error: 0.0, ..RenderOptions::default() };
    let mut failures = Vec::new();
    for scene in scenes() {
        let name = scene.file_stem().unwrap().to_string_lossy().to_string();
        let model = load_model(&scene);
        let (exact, _) = render_ours_with(&renderer, &model, &exact_options);
        let (lod, _) = render_ours_with(&renderer, &model, &RenderOptions::default());
        for (k, cam) in CAMERAS.iter().enumerate() {
            let (e, l) = (&exact[k], &lod[k]);
            let p = psnr(&e.rgb, &l.rgb);
            let changed: Vec<usize> = (0..e.segmentation.len()).filter(|&i| e.segmentation[i] != l.segmentation[i]).collect();
            let far: Vec<usize> =
                changed.iter().copied().filter(|&i| !id_nearby(&e.segmentation, i, l.segmentation[i])).collect();
            // Depth where both images see the same geom: within the levels' geometric error (under a millimetre
            // here) but at grazing angles and inside a geom's own silhouettes, where a small move is a big step.
            let same: Vec<usize> =
                (0..e.depth_m.len()).filter(|&i| e.segmentation[i] == l.segmentation[i] && e.depth_valid[i] && l.depth_valid[i]).collect();
            let depth_off = same.iter().filter(|&&i| (e.depth_m[i] - l.depth_m[i]).abs() > 0.002).count();
            println!(
                "{name} {cam}: PSNR {p:.2} dB against exact meshes; {} px change id, {} more than {MOVE_PX} px from their id; \
                 {depth_off} of {} px off by more than 2 mm",
                changed.len(),
                far.len(),
                same.len()
            );
            if !(p >= 35.0) || changed.len() > MAX_CHANGED_PX || depth_off * 500 > same.len() {
                failures.push(format!(
                    "{name} {cam}: {p:.2} dB, {} px change id, {} of them move > {MOVE_PX} px, depth {depth_off} px off",
                    changed.len(),
                    far.len()
                ));
            }
        }
    }
    assert!(failures.is_empty(), "levels of detail change the image too much: {failures:?}");
}

/// Meshes with a normal per face corner (robosuite's Panda links among them) simplify only because corners are
/// welded by position: before, no edge could collapse and they were drawn exactly, about half of a frame's
/// triangles.
#[test]
fn faceted_meshes_get_coarser_levels() {
    let renderer = Renderer::new().expect("renderer");
    let scene = scenes().into_iter().next().expect("a reference scene");
    let model = load_model(&scene);
    let full = libero_render::SceneModel::from_mujoco(&model).expect("scene");
    let handle = renderer.prepare_model(&model).expect("prepare model");
    let (mut faceted, mut simplified) = (0, 0);
    for (g, desc) in full.geoms.iter().enumerate() {
        let Some(mesh) = usize::try_from(desc.dataid).ok().and_then(|m| full.meshes.get(m)) else { continue };
        let corners = mesh.positions.len();
        let positions: std::collections::HashSet<[u32; 3]> = mesh.positions.iter().map(|p| p.map(f32::to_bits)).collect();
        let normals: std::collections::HashSet<[u32; 6]> = mesh
            .positions
            .iter()
            .zip(&mesh.normals)
            .map(|(p, n)| [p[0], p[1], p[2], n[0], n[1], n[2]].map(f32::to_bits))
            .collect();
        // Large, and most positions carry several normals.
        if corners / 3 < 5000 || normals.len() < 3 * positions.len() {
            continue;
        }
        faceted += 1;
        let levels = handle.geom_triangle_levels(g).expect("a drawn mesh");
        println!("geom {g}: {} positions, {} (position, normal) pairs, triangles per level {levels:?}", positions.len(), normals.len());
        if levels.len() > 1 && levels[levels.len() - 1] * 4 < levels[0] {
            simplified += 1;
        }
    }
    assert!(faceted >= 8, "the Panda's links are faceted meshes: found {faceted}");
    assert_eq!(simplified, faceted, "every large faceted mesh has a level with under a quarter of its triangles");
}
