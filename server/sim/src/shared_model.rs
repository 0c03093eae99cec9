//! One read-only compiled model per content, shared by every episode that compiled the same one.
//!
//! Each episode composes, compiles and edits its scene's model (placement, private edits, site visibility), then
//! only reads it: stepping takes `const mjModel*` and all state is in `mjData`. Episodes of one scene with one
//! configuration therefore end up with byte-identical models — hundreds of MB of meshes and textures for a LIBERO
//! kitchen — and [`share`] hands all of them the first one's. Identity is by content, through MuJoCo's own
//! serialisation (`mj_saveModel`, every field and array the model has), so two models are shared only when
//! they are the same model; nothing about the spec that built them is assumed. A shared model lives as long as
//! an episode holds it (the cache keeps it weakly).
use std::collections::HashMap;
use std::sync::{Arc, LazyLock, Mutex, Weak};

use mujoco_rs::mujoco_c::{mj_saveModel, mj_sizeModel};
use mujoco_rs::prelude::MjModel;
use sha2::{Digest, Sha256};

/// The SHA-256 of the model's MJB serialisation; `None` if MuJoCo reports no size.
pub fn content_key(model: &MjModel) -> Option<[u8; 32]> {
    // SAFETY: `model.ffi()` is a valid compiled model for the call; `mj_saveModel` writes at most `size` bytes
    // into the buffer it is given (and to no file when the name is null).
    let size = unsafe { mj_sizeModel(model.ffi()) };
    let len = usize::try_from(size).ok().filter(|n| *n > 0)?;
    let mut bytes = vec![0u8; len];
    unsafe { mj_saveModel(model.ffi(), std::ptr::null(), bytes.as_mut_ptr().cast(), size) };
    Some(Sha256::digest(&bytes).into())
}

static MODELS: LazyLock<Mutex<HashMap<[u8; 32], Weak<MjModel>>>> = LazyLock::new(Mutex::default);

/// The process's model with this content if one is alive, else `model` itself, now shared. Call once a model
/// is final (no edit after this point may touch it: it is shared read-only).
pub fn share(model: MjModel) -> Arc<MjModel> {
    let Some(key) = content_key(&model) else { return Arc::new(model) };
    let Ok(mut cache) = MODELS.lock() else { return Arc::new(model) };
    if let Some(alive) = cache.get(&key).and_then(Weak::upgrade) {
        return alive;
    }
    cache.retain(|_, m| m.strong_count() > 0);
    let model = Arc::new(model);
    cache.insert(key, Arc::downgrade(&model));
    model
}

/// Models alive in the cache (for tests and benchmarks).
pub fn alive() -> usize {
    MODELS.lock().map(|c| c.values().filter(|m| m.strong_count() > 0).count()).unwrap_or(0)
}
