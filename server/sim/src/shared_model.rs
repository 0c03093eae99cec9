//! One read-only compiled model per scene, shared by every episode of it, down to the arrays that differ.
//!
//! Each episode composes, compiles and edits its scene's model (fixture placement for its seed, private edits,
//! site visibility), then only reads it: stepping takes `const mjModel*` and all state is in `mjData`. Two
//! levels of sharing follow from that:
//!
//! - **Same content** (same scene, same seed): [`share`] hands every such episode the first one's model.
//!   Identity is by content, through MuJoCo's own serialisation (`mj_saveModel`, every field and array the model
//!   has), so two models are shared only when they are the same model.
//! - **Same layout, other edits** (same scene, another seed: a few fixture poses differ): the new model keeps
//!   private copies of only the arrays that differ or are small, and reads every large array equal to the
//!   first model's (meshes, textures, bounding-volume trees: hundreds of MB for a LIBERO kitchen) from that
//!   model's buffer. The episode gets a copy of only what differs, as the issue asked.
//!
//! A shared model lives as long as an episode holds it: the cache keeps models weakly, and a model whose arrays
//! another one reads is kept by that one until it goes ([`release_unused`]).
//!
//! How a derived model stays a valid MuJoCo model: an `mjModel` is its counts, options and one `buffer` that
//! every array pointer points into (`mj_setPtrModel`). MuJoCo reads arrays only through those pointers
//! (`mj_copyModel` and `mj_saveModel` copy array by array; stepping never looks at `buffer`), and frees only
//! `buffer` (`mj_deleteModel`). A derived model's `buffer` is a smaller private block holding its own arrays,
//! allocated with `mju_malloc` so that `mj_deleteModel` frees it as usual; its shared arrays' pointers point
//! into the base's buffer, which [`DERIVED`] keeps alive.
use std::collections::HashMap;
use std::mem::{offset_of, size_of};
use std::sync::{Arc, LazyLock, Mutex, Weak};

use mujoco_rs::mujoco_c::{mj_saveModel, mj_sizeModel, mjModel, mju_free, mju_malloc};
use mujoco_rs::prelude::MjModel;
use sha2::{Digest, Sha256};

/// Arrays at least this large that equal the base's are read from the base; smaller ones are copied (they are
/// what placement and private edits change, and sharing them would save little).
pub const SHARED_ARRAY_MIN_BYTES: usize = 64 * 1024;

/// MuJoCo aligns every array of a model buffer on 64 bytes (`SKIP` in `mj_setPtrModel`).
const ARRAY_ALIGN: usize = 64;

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

/// Models alive by content.
static MODELS: LazyLock<Mutex<HashMap<[u8; 32], Weak<MjModel>>>> = LazyLock::new(Mutex::default);

/// Models whose own buffer holds all their arrays: what a later model of the same layout can read from.
static BASES: LazyLock<Mutex<Vec<Weak<MjModel>>>> = LazyLock::new(Mutex::default);

/// Derived models and the base each reads from, kept alive while the derived model is.
static DERIVED: LazyLock<Mutex<Vec<(Weak<MjModel>, Arc<MjModel>)>>> = LazyLock::new(Mutex::default);

/// The process's model with this content if one is alive; else `model`, reading the large arrays it has in
/// common with a live model of the same layout from there; now shared. Call once a model is final (no edit
/// after this point may touch it: it is shared read-only).
pub fn share(model: MjModel) -> Arc<MjModel> {
    release_unused();
    let mut model = model;
    let base = BASES.lock().ok().and_then(|bases| bases.iter().filter_map(Weak::upgrade).find(|b| same_layout(b, &model)));
    // SAFETY: `base` is alive and kept alive (below, in DERIVED) for as long as `model` is; `model` is ours alone.
    let derived = base.and_then(|base| unsafe { read_large_arrays_from(&base, &mut model) }.map(|key| (base, key)));
    // A derived model's identity is its base's and its own arrays' (a hash of a few MB); any other model's is
    // its whole serialisation (hundreds of MB, hashed once per scene).
    let key = match &derived {
        Some((_, key)) => *key,
        None => match content_key(&model) {
            Some(key) => key,
            None => return Arc::new(model),
        },
    };
    let Ok(mut cache) = MODELS.lock() else { return Arc::new(model) };
    if let Some(alive) = cache.get(&key).and_then(Weak::upgrade) {
        return alive;
    }
    cache.retain(|_, m| m.strong_count() > 0);
    let model = Arc::new(model);
    match derived {
        Some((base, _)) => {
            if let Ok(mut d) = DERIVED.lock() {
                d.push((Arc::downgrade(&model), base));
            }
        }
        None => {
            if let Ok(mut bases) = BASES.lock() {
                bases.retain(|b| b.strong_count() > 0);
                bases.push(Arc::downgrade(&model));
            }
        }
    }
    cache.insert(key, Arc::downgrade(&model));
    model
}

/// Compiled scenes by the SHA-256 of their MJCF, alive while an episode holds one (see [`compiled`]).
static COMPILED: LazyLock<Mutex<HashMap<[u8; 32], Weak<MjModel>>>> = LazyLock::new(Mutex::default);

/// The model `compile` makes of `mjcf`, compiled once while anyone holds the returned compiled scene: returns a
/// private copy (to edit: placement, private edits) and the compiled scene, shared (so it costs little beside
/// the scene's other models). A copy of a compiled model is that model, array for array (`mj_copyModel`), and
/// MuJoCo's compiler is deterministic, so the copy is what compiling again would give, in a fraction of the
/// time (about 2–3 s for a LIBERO kitchen). The MJCF names its assets by path; they do not change while the
/// process runs.
pub fn compiled<E>(mjcf: &str, compile: impl FnOnce() -> Result<MjModel, E>) -> Result<(MjModel, Arc<MjModel>), E> {
    let key: [u8; 32] = Sha256::digest(mjcf.as_bytes()).into();
    let alive = COMPILED.lock().ok().and_then(|c| c.get(&key).and_then(Weak::upgrade));
    let scene = match alive {
        Some(scene) => scene,
        None => {
            let scene = share(compile()?);
            if let Ok(mut c) = COMPILED.lock() {
                c.retain(|_, m| m.strong_count() > 0);
                c.insert(key, Arc::downgrade(&scene));
            }
            scene
        }
    };
    Ok(((*scene).clone(), scene))
}

/// Lets go of bases that no live derived model reads from any more (their memory goes with their last
/// holder). [`share`] does this on every call; a server calls it when episodes end, so an idle server keeps
/// nothing.
pub fn release_unused() {
    let released: Vec<Arc<MjModel>> = match DERIVED.lock() {
        Ok(mut d) => {
            let (dead, alive): (Vec<_>, Vec<_>) = std::mem::take(&mut *d).into_iter().partition(|(m, _)| m.strong_count() == 0);
            *d = alive;
            dead.into_iter().map(|(_, base)| base).collect()
        }
        Err(_) => Vec::new(),
    };
    drop(released);
}

/// Compiled scenes alive (for tests and benchmarks).
pub fn compiled_scenes_alive() -> usize {
    count_alive(&COMPILED)
}

/// Models alive in the cache (for tests and benchmarks).
pub fn alive() -> usize {
    count_alive(&MODELS)
}

/// Entries of a weak cache whose model is still alive.
fn count_alive(cache: &Mutex<HashMap<[u8; 32], Weak<MjModel>>>) -> usize {
    cache.lock().map(|c| c.values().filter(|m| m.strong_count() > 0).count()).unwrap_or(0)
}

/// The model whose buffer `model` reads its large arrays from, and how many bytes of arrays it reads there;
/// `None` for a model with all its arrays in its own buffer.
pub fn borrowed_from(model: &MjModel) -> Option<(Arc<MjModel>, usize)> {
    let base = DERIVED
        .lock()
        .ok()?
        .iter()
        .find(|(w, _)| w.upgrade().is_some_and(|w| std::ptr::eq(w.ffi(), model.ffi())))
        .map(|(_, b)| b.clone())?;
    let b = base.ffi();
    let (lo, len) = (b.buffer as usize, usize::try_from(b.nbuffer).ok()?);
    let extents = extents(b)?;
    let m = model.ffi();
    // SAFETY: `array_fields` names pointer words of the struct.
    let borrowed: std::collections::BTreeSet<usize> =
        array_fields()?.into_iter().map(|off| unsafe { read_word(m, off) }).filter(|&p| p >= lo && p < lo + len).collect();
    let bytes = borrowed.iter().map(|p| extents.get(&(p - lo)).copied().unwrap_or(0)).sum();
    Some((base, bytes))
}

/// Offsets (in the struct) of the pointer fields after `buffer` and before `signature`: MuJoCo's array pointers
/// (`None` if that span is not whole words: a struct this code does not know).
fn array_fields() -> Option<Vec<usize>> {
    let first = offset_of!(mjModel, buffer) + size_of::<*mut std::ffi::c_void>();
    let last = offset_of!(mjModel, signature);
    if (last - first) % size_of::<usize>() != 0 {
        return None;
    }
    Some((first..last).step_by(size_of::<usize>()).collect())
}

/// The word at byte offset `off` of the struct.
///
/// # Safety
/// `off + 8 <= size_of::<mjModel>()`.
unsafe fn read_word(m: &mjModel, off: usize) -> usize {
    unsafe { std::ptr::read_unaligned((m as *const mjModel).cast::<u8>().add(off).cast::<usize>()) }
}

/// Writes the word at byte offset `off` of the struct.
///
/// # Safety
/// As [`read_word`]; the word is one of the model's array pointers.
unsafe fn write_word(m: &mut mjModel, off: usize, value: usize) {
    unsafe { std::ptr::write_unaligned((m as *mut mjModel).cast::<u8>().add(off).cast::<usize>(), value) }
}

/// Each array's extent in an ordinary model (all arrays in its buffer): from its start to the next array's (the
/// last to the buffer's end), by offset in the buffer. `None` unless every array pointer is null or in the buffer.
fn extents(m: &mjModel) -> Option<HashMap<usize, usize>> {
    let (lo, len) = (m.buffer as usize, usize::try_from(m.nbuffer).ok()?);
    let mut offsets = Vec::new();
    for off in array_fields()? {
        // SAFETY: `off` is a pointer field of the struct.
        let p = unsafe { read_word(m, off) };
        if p == 0 {
            continue;
        }
        if p < lo || p > lo + len {
            return None;
        }
        offsets.push(p - lo);
    }
    offsets.sort_unstable();
    offsets.dedup();
    let mut out = HashMap::with_capacity(offsets.len());
    for (i, &o) in offsets.iter().enumerate() {
        out.insert(o, offsets.get(i + 1).copied().unwrap_or(len) - o);
    }
    Some(out)
}

/// Same counts (every size before the options) and the same compiled signature: the same buffer layout.
fn same_layout(a: &MjModel, b: &MjModel) -> bool {
    let (a, b) = (a.ffi(), b.ffi());
    let n = offset_of!(mjModel, opt);
    // SAFETY: both are valid structs of at least `n` bytes; the bytes before `opt` are integer counts.
    let (sa, sb) = unsafe {
        (
            std::slice::from_raw_parts((a as *const mjModel).cast::<u8>(), n),
            std::slice::from_raw_parts((b as *const mjModel).cast::<u8>(), n),
        )
    };
    sa == sb && a.signature == b.signature
}

/// Points `model`'s large arrays that equal `base`'s at `base`'s, and moves the rest into a new private buffer
/// (freeing the old one). Returns the derived model's identity: a SHA-256 of the base's address (alive as long
/// as the derived model), the model's counts, options and signature, and per array in buffer order whether it
/// is the base's or its own bytes. `None` (and `model` as it was) when the layouts differ, the base is itself
/// derived, or nothing large is in common.
///
/// # Safety
/// `base` must outlive `model`'s use of it (the caller keeps it alive while `model` is); `model` must not be
/// in use elsewhere.
unsafe fn read_large_arrays_from(base: &MjModel, model: &mut MjModel) -> Option<[u8; 32]> {
    if !same_layout(base, model) {
        return None;
    }
    let b = base.ffi();
    // SAFETY: the model is ours alone (caller); only its pointer fields and `buffer` change below.
    let m = unsafe { model.ffi_mut() };
    // Both ordinary (every array in its own buffer), with the same offsets: `extents` checks the first.
    let ext_b = extents(b)?;
    let ext_m = extents(m)?;
    if ext_b != ext_m {
        return None;
    }
    let fields = array_fields()?;
    let (lo_b, lo_m) = (b.buffer as usize, m.buffer as usize);
    // Per array (by buffer offset): shared with the base, or where it goes in the private buffer.
    let mut plan: HashMap<usize, Option<usize>> = HashMap::with_capacity(ext_m.len());
    let mut private_len = 0usize;
    let mut shared_len = 0usize;
    let mut offsets: Vec<(&usize, &usize)> = ext_m.iter().collect();
    offsets.sort_unstable();
    let mut identity = Sha256::new();
    identity.update((b as *const mjModel as usize).to_le_bytes());
    // SAFETY: the struct's bytes before `buffer` are counts and the option/visual/statistic structs.
    identity.update(unsafe { std::slice::from_raw_parts((m as *const mjModel).cast::<u8>(), offset_of!(mjModel, buffer)) });
    identity.update(m.signature.to_le_bytes());
    for (&off, &len) in offsets {
        // SAFETY: both arrays lie within their buffers (`extents`), `len` bytes from `off`.
        let equal = len >= SHARED_ARRAY_MIN_BYTES
            && unsafe {
                std::slice::from_raw_parts((lo_m + off) as *const u8, len) == std::slice::from_raw_parts((lo_b + off) as *const u8, len)
            };
        identity.update((off as u64).to_le_bytes());
        identity.update((len as u64).to_le_bytes());
        if equal {
            identity.update([0u8]);
            plan.insert(off, None);
            shared_len += len;
        } else {
            identity.update([1u8]);
            // SAFETY: as above.
            identity.update(unsafe { std::slice::from_raw_parts((lo_m + off) as *const u8, len) });
            plan.insert(off, Some(private_len));
            private_len += len.div_ceil(ARRAY_ALIGN) * ARRAY_ALIGN;
        }
    }
    if shared_len == 0 {
        return None;
    }
    // SAFETY: `mju_malloc` returns a 64-byte-aligned block (or aborts through mju_error) that `mj_deleteModel`
    // frees with `mju_free`, as it would the original buffer.
    let private = unsafe { mju_malloc(private_len.max(ARRAY_ALIGN)) } as usize;
    if private == 0 {
        return None;
    }
    for (&off, &dest) in &plan {
        if let Some(dest) = dest {
            let len = ext_m[&off];
            // SAFETY: source within the old buffer, destination within the new block (sized above).
            unsafe { std::ptr::copy_nonoverlapping((lo_m + off) as *const u8, (private + dest) as *mut u8, len) };
        }
    }
    for off in fields {
        // SAFETY: `off` is a pointer field of the struct.
        let p = unsafe { read_word(m, off) };
        if p == 0 {
            continue;
        }
        let new = match plan.get(&(p - lo_m)) {
            Some(Some(dest)) => private + dest,
            Some(None) => lo_b + (p - lo_m),
            // An array past the last offset with no extent (zero-sized at the end): anywhere valid.
            None => private,
        };
        // SAFETY: as above.
        unsafe { write_word(m, off, new) };
    }
    let old = m.buffer;
    m.buffer = private as *mut std::ffi::c_void;
    // SAFETY: the old buffer was allocated by MuJoCo (mju_malloc) and nothing points into it any more.
    unsafe { mju_free(old) };
    log::debug!("model reads {shared_len} bytes of arrays from its scene's model; {private_len} bytes of its own");
    Some(identity.finalize().into())
}
