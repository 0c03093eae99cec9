//! Episodes per machine (issue 34): episodes of one scene with other seeds (other fixture placements, so other
//! models) keep private copies of only the arrays that differ and read the large ones (meshes, textures,
//! bounding-volume trees) from one model, and nothing an agent or a judge sees changes: the published
//! observation bytes, the trajectory and the verdict of an episode are the same alone (its model all its own)
//! and with 7 other episodes of its scene open at once on 8 threads (its model shared or derived, copied from the
//! scene compiled once instead of compiled again).
//!
//! One test per file section, run in order in one test function: the model cache is process-wide, and the
//! "alone" runs need no other model of the scene alive.
use std::sync::Arc;

use libero_episode::actor::World;
use libero_episode::observation::encode_observation;
use libero_episode::physics::WorldPhysics;
use libero_episode::task::resolve_task;
use libero_episode::world::{LiberoWorld, WorldSpec};
use libero_episode::Level;
use libero_render::Renderer;
use libero_sim::AssetPaths;
use libero_sim::shared_model;
use sha2::{Digest, Sha256};

fn spec(task: &str, seed: u64) -> WorldSpec {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    WorldSpec { task: resolve_task(task, &paths).unwrap(), level: Level::L3, seed, init_index: 0, paths }
}

/// A short scripted motion: reach down and close the gripper, then lift.
fn action(k: usize) -> [f64; 7] {
    [0.4 * (k as f64 * 0.3).sin(), 0.3, if k < 15 { -0.6 } else { 0.5 }, 0.0, 0.1 * (k as f64).cos(), 0.0, if k < 10 { -1.0 } else { 1.0 }]
}

/// Everything the episode shows and decides: the published files of its last observation, the final state row
/// (bitwise) and the verdict.
fn run_episode(world: &mut LiberoWorld, steps: usize) -> (Vec<(String, [u8; 32])>, Vec<u64>, serde_json::Value) {
    world.start().unwrap();
    for k in 0..steps {
        world.step(&action(k)).unwrap();
    }
    let frame = world.frame(1).unwrap();
    let encoded = encode_observation(&frame, Level::L3).unwrap();
    let files = encoded.files.iter().map(|f| (f.rel_path.clone(), Sha256::digest(&f.bytes).into())).collect();
    let state = world.simulation().state_row().iter().map(|x| x.to_bits()).collect();
    let verdict = world.verdict().unwrap();
    (files, state, serde_json::json!({"success": verdict.success, "evaluation": verdict.private_evaluation}))
}

#[test]
fn episodes_of_a_scene_with_other_seeds_read_its_large_arrays_and_publish_the_same_bytes_alone_and_eight_at_once() {
    const TASK: &str = "T14";
    const STEPS: usize = 25;
    let seeds = [100u64, 101, 102];

    // 1. Each seed alone: nothing of the scene alive before it, so each compiles the scene afresh.
    let renderer = Renderer::new().expect("renderer");
    let mut alone = Vec::new();
    let mut keys = Vec::new();
    for &seed in &seeds {
        assert_eq!(shared_model::compiled_scenes_alive(), 0, "seed {seed}: compiled afresh");
        let mut world = LiberoWorld::new(&spec(TASK, seed), renderer.clone()).unwrap();
        let (model, _, _) = world.video_models();
        keys.push(shared_model::content_key(&model).unwrap());
        drop(model);
        alone.push(run_episode(&mut world, STEPS));
        drop(world);
        shared_model::release_unused();
    }
    assert_eq!(shared_model::alive(), 0, "nothing of the scene is left once its worlds are gone");
    assert!(keys.windows(2).any(|w| w[0] != w[1]), "the seeds place the fixtures differently: different models");

    // 2. The physics alone: two seeds' models read their large arrays from one model (the scene as compiled)
    //    and keep it alive between them, whichever goes first; the same seed again gets the same model.
    let a = WorldPhysics::build(&spec(TASK, seeds[0]), |_, _, _| Ok(())).unwrap();
    let mut b = WorldPhysics::build(&spec(TASK, seeds[1]), |_, _, _| Ok(())).unwrap();
    assert!(!Arc::ptr_eq(a.model(), b.model()), "two seeds, two models");
    let (base_a, _) = shared_model::borrowed_from(a.model()).expect("the first seed's model reads the compiled scene's arrays");
    let (base_b, borrowed) = shared_model::borrowed_from(b.model()).expect("so does the second's");
    assert!(Arc::ptr_eq(&base_a, &base_b), "from one model");
    assert!(borrowed > 100 << 20, "the meshes and textures of a kitchen: {borrowed} bytes");
    let mut c = WorldPhysics::build(&spec(TASK, seeds[1]), |_, _, _| Ok(())).unwrap();
    assert!(Arc::ptr_eq(c.model(), b.model()), "the same seed again: the same model");
    drop(c);
    let weak_base = Arc::downgrade(&base_b);
    drop((a, base_a, base_b));
    assert!(weak_base.upgrade().is_some(), "kept by the model that reads it");
    b.start(|_| {}).unwrap();
    for k in 0..STEPS {
        b.step(&action(k)).unwrap();
    }
    c = WorldPhysics::build(&spec(TASK, seeds[1]), |_, _, _| Ok(())).unwrap();
    assert!(Arc::ptr_eq(c.model(), b.model()));
    drop((b, c));
    shared_model::release_unused();
    assert!(weak_base.upgrade().is_none(), "released with the last model reading it");
    assert_eq!(shared_model::compiled_scenes_alive(), 0);

    // 3. Eight episodes at once on eight threads, the seeds in turn (same content shared, other seeds derived).
    let worlds: Vec<LiberoWorld> =
        seeds.iter().cycle().take(8).map(|&seed| LiberoWorld::new(&spec(TASK, seed), renderer.clone()).unwrap()).collect();
    let models: Vec<_> = worlds.iter().map(|w| w.video_models()).collect();
    assert_eq!(shared_model::compiled_scenes_alive(), 1, "compiled once, copied for the other seven");
    for (i, (model, _, upload)) in models.iter().enumerate() {
        // a copy of the compiled scene, edited for its seed, is the model compiling afresh gave (step 1)
        assert_eq!(shared_model::content_key(model).unwrap(), keys[i % seeds.len()], "world {i}: its seed's model, byte for byte");
        assert!(upload.shares_upload_with(&models[0].2), "world {i}: one upload of the scene's meshes and textures");
        let (base, _) = shared_model::borrowed_from(model).expect("every world reads the large arrays of one model");
        let (first_base, _) = shared_model::borrowed_from(&models[0].0).expect("world 0");
        assert!(Arc::ptr_eq(&base, &first_base), "world {i}");
    }
    assert!(Arc::ptr_eq(&models[0].0, &models[seeds.len()].0), "the same seed shares the whole model");
    drop(models);
    let together: Vec<_> = std::thread::scope(|s| {
        let handles: Vec<_> = worlds.into_iter().map(|mut w| s.spawn(move || run_episode(&mut w, STEPS))).collect();
        handles.into_iter().map(|h| h.join().expect("episode thread")).collect()
    });
    for (i, run) in together.iter().enumerate() {
        let seed = seeds[i % seeds.len()];
        let reference = &alone[i % seeds.len()];
        assert_eq!(run.0, reference.0, "seed {seed} (world {i}): the published observation files, byte for byte");
        assert_eq!(run.1, reference.1, "seed {seed} (world {i}): the state after {STEPS} steps, bit for bit");
        assert_eq!(run.2, reference.2, "seed {seed} (world {i}): the verdict");
    }
}
