//! Episodes per machine (issue 34): worlds of one scene share its compiled model and its upload on the renderer
//! — by identity, not by timing —, a world of another scene has its own, and both go with the last world
//! holding them. Sharing changes no published byte: the existing golden, determinism and render tests run on
//! shared models too, since every world is built through the same path.
use std::sync::Arc;

use libero_episode::Level;
use libero_episode::task::resolve_task;
use libero_episode::world::{LiberoWorld, WorldSpec};
use libero_render::Renderer;
use libero_sim::AssetPaths;

fn spec(task: &str) -> WorldSpec {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    WorldSpec { task: resolve_task(task, &paths).unwrap(), level: Level::L3, seed: 100, init_index: 0, paths }
}

const KETCHUP: &str = "libero_object/pick_up_the_ketchup_and_place_it_in_the_basket";
const BOWL: &str = "libero_spatial/pick_up_the_black_bowl_between_the_plate_and_the_ramekin_and_place_it_on_the_plate";

#[test]
fn worlds_of_one_scene_share_the_model_and_the_upload_until_the_last_goes() {
    let renderer = Renderer::new().expect("renderer");
    let a = LiberoWorld::new(&spec(KETCHUP), renderer.clone()).unwrap();
    let b = LiberoWorld::new(&spec(KETCHUP), renderer.clone()).unwrap();
    let ((model_a, _, upload_a), (model_b, _, upload_b)) = (a.video_models(), b.video_models());
    assert!(Arc::ptr_eq(&model_a, &model_b), "one compiled model for both episodes");
    assert!(upload_a.shares_upload_with(&upload_b), "one upload of the scene's meshes and textures");

    let c = LiberoWorld::new(&spec(BOWL), renderer.clone()).unwrap();
    let (model_c, _, upload_c) = c.video_models();
    assert!(!Arc::ptr_eq(&model_a, &model_c) && !upload_a.shares_upload_with(&upload_c), "another scene, its own");

    let weak = Arc::downgrade(&model_a);
    drop((model_a, model_b, upload_a, upload_b, a));
    assert!(weak.upgrade().is_some(), "still held by the other world");
    drop(b);
    assert!(weak.upgrade().is_none(), "released with the last world of the scene");
}

/// The live view's preview runs the start on a fork of the episode's physics instead of a second build (no
/// second compile): the fork must be the second build, bit for bit, whatever the original has done since.
#[test]
fn a_fork_of_a_world_is_a_second_build_bit_for_bit_without_compiling_again() {
    use libero_episode::physics::WorldPhysics;
    // T14 (a drawer and its staged evaluator) and a seeded placement without trusted init states (T11)
    for task in ["T14", KETCHUP] {
        let spec = spec(task);
        let mut original = WorldPhysics::build(&spec, |_, _, _| Ok(())).unwrap();
        // the original runs ahead first: the fork starts from the build state regardless
        original.start(|_| {}).unwrap();
        original.step(&[0.0, 0.0, -0.5, 0.0, 0.0, 0.0, -1.0]).unwrap();
        let mut fork = original.fork(&spec).unwrap();
        assert!(Arc::ptr_eq(fork.model(), original.model()), "{task}: the fork reuses the compiled model");
        let mut second = WorldPhysics::build(&spec, |_, _, _| Ok(())).unwrap();
        assert!(Arc::ptr_eq(second.model(), original.model()), "{task}: same content, shared");
        assert_eq!(bits(&fork.sim.state_row()), bits(&second.sim.state_row()), "{task}: before the start");
        fork.start(|_| {}).unwrap();
        second.start(|_| {}).unwrap();
        for k in 0..40 {
            let a = [0.3 * (k as f64 * 0.2).sin(), 0.2, -0.4, 0.0, 0.1, 0.0, if k < 20 { -1.0 } else { 1.0 }];
            fork.step(&a).unwrap();
            second.step(&a).unwrap();
        }
        assert_eq!(bits(&fork.sim.state_row()), bits(&second.sim.state_row()), "{task}: after 40 control steps");
        let (f, s) = (fork.evaluate(), second.evaluate());
        assert_eq!(serde_json::to_value(&f).unwrap(), serde_json::to_value(&s).unwrap(), "{task}: the same verdict");
    }
}

fn bits(row: &[f64]) -> Vec<u64> {
    row.iter().map(|x| x.to_bits()).collect()
}
