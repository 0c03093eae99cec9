//! Episodes of one scene share its upload (issue 34): every episode compiles its own model, and the renderer
//! hands every model with the same content the same meshes and textures on the GPU — by identity, not by
//! timing —, a scene of other content its own, and frees an upload when the last handle to it goes. The frames
//! rendered through a shared upload are the frames of the model's own.
mod common;

use common::{load_model, render_ours, scenes};
use libero_render::Renderer;

#[test]
fn models_of_one_scene_share_one_upload_until_the_last_handle_goes() {
    let renderer = Renderer::new().expect("renderer");
    let all = scenes();
    assert!(all.len() >= 2, "{all:?}");
    // Two compilations of one scene: two models, one upload.
    let (a, b) = (load_model(&all[0]), load_model(&all[0]));
    assert!(!std::sync::Arc::ptr_eq(&a, &b));
    let (ha, hb) = (renderer.prepare_model(&a).unwrap(), renderer.prepare_model(&b).unwrap());
    assert!(ha.shares_upload_with(&hb) && ha.id() == hb.id(), "one scene, one upload");
    // Another scene gets its own.
    let c = load_model(&all[1]);
    let hc = renderer.prepare_model(&c).unwrap();
    assert!(!hc.shares_upload_with(&ha));
    // The frames through the shared upload are the model's own, byte for byte.
    let (frames_a, _) = render_ours(&renderer, &a);
    let (frames_b, _) = render_ours(&renderer, &b);
    for (fa, fb) in frames_a.iter().zip(&frames_b) {
        assert!(fa.rgb == fb.rgb && fa.depth_m == fb.depth_m, "a shared upload renders the same frames");
    }
    // Released with its last handle: a later model of the scene gets a new upload.
    let id = ha.id();
    drop((ha, hb));
    drop((a, b));
    let again = load_model(&all[0]);
    let h = renderer.prepare_model(&again).unwrap();
    assert_ne!(h.id(), id, "the upload went with its last handle");
}
