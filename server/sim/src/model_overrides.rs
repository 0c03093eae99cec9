//! Post-compile edits of a compiled model (the golden files' `runtime_model_overrides`: fixture poses
//! sampled at reset, site colours), and loading an MJCF string with them applied.
//!
//! robosuite writes these into the live `mjModel` after compiling and does not recompute derived
//! constants; we do the same, so the model is bit-identical to the recorded one.
use mujoco_rs::prelude::*;
use serde::Deserialize;

use crate::SimError;

/// One overridden row: `model.<field>[id] = value`.
#[derive(Debug, Clone, Deserialize)]
pub struct OverrideEntry {
    pub id: usize,
    #[serde(default)]
    pub name: Option<String>,
    pub value: serde_json::Value,
}

/// `field → rows`, as in the golden JSON.
pub type RuntimeOverrides = std::collections::BTreeMap<String, Vec<OverrideEntry>>;

/// (object type for the name check, pointer to the f64 array, row width, row count)
fn field_slot(model: &mut MjModel, field: &str) -> Option<(MjtObjBase, *mut f64, usize, usize)> {
    // SAFETY: only pointers into the model's own arrays are taken here; bounds are returned with them.
    let m = unsafe { model.ffi_mut() };
    let (nbody, ngeom, nsite, njnt) = (m.nbody as usize, m.ngeom as usize, m.nsite as usize, m.njnt as usize);
    let slot = match field {
        "body_pos" => (MjtObjBase::mjOBJ_BODY, m.body_pos, 3, nbody),
        "body_quat" => (MjtObjBase::mjOBJ_BODY, m.body_quat, 4, nbody),
        "body_ipos" => (MjtObjBase::mjOBJ_BODY, m.body_ipos, 3, nbody),
        "body_iquat" => (MjtObjBase::mjOBJ_BODY, m.body_iquat, 4, nbody),
        "body_mass" => (MjtObjBase::mjOBJ_BODY, m.body_mass, 1, nbody),
        "geom_pos" => (MjtObjBase::mjOBJ_GEOM, m.geom_pos, 3, ngeom),
        "geom_quat" => (MjtObjBase::mjOBJ_GEOM, m.geom_quat, 4, ngeom),
        "geom_size" => (MjtObjBase::mjOBJ_GEOM, m.geom_size, 3, ngeom),
        "site_pos" => (MjtObjBase::mjOBJ_SITE, m.site_pos, 3, nsite),
        "site_quat" => (MjtObjBase::mjOBJ_SITE, m.site_quat, 4, nsite),
        "site_size" => (MjtObjBase::mjOBJ_SITE, m.site_size, 3, nsite),
        "jnt_range" => (MjtObjBase::mjOBJ_JOINT, m.jnt_range, 2, njnt),
        _ => return None,
    };
    Some(slot)
}

/// (object type, pointer to the f32 array, width, count) for float32 fields (colours).
fn field_slot_f32(model: &mut MjModel, field: &str) -> Option<(MjtObjBase, *mut f32, usize, usize)> {
    // SAFETY: as in `field_slot`.
    let m = unsafe { model.ffi_mut() };
    let slot = match field {
        "site_rgba" => (MjtObjBase::mjOBJ_SITE, m.site_rgba, 4, m.nsite as usize),
        "geom_rgba" => (MjtObjBase::mjOBJ_GEOM, m.geom_rgba, 4, m.ngeom as usize),
        _ => return None,
    };
    Some(slot)
}

fn values(entry: &OverrideEntry, width: usize, field: &str) -> Result<Vec<f64>, SimError> {
    let vals: Vec<f64> = match &entry.value {
        serde_json::Value::Number(n) => n.as_f64().into_iter().collect(),
        serde_json::Value::Array(a) => a.iter().filter_map(|v| v.as_f64()).collect(),
        _ => Vec::new(),
    };
    if vals.len() != width {
        return Err(SimError::Input(format!("override {field}[{}] needs {width} numbers", entry.id)));
    }
    Ok(vals)
}

/// Applies the overrides; unknown fields, out-of-range ids and name mismatches are input errors.
pub fn apply_runtime_overrides(model: &mut MjModel, overrides: &RuntimeOverrides) -> Result<(), SimError> {
    for (field, entries) in overrides {
        for e in entries {
            let check_name = |model: &MjModel, kind: MjtObjBase| -> Result<(), SimError> {
                if let Some(name) = &e.name {
                    let actual = model.id_to_name(kind, e.id);
                    if actual != Some(name.as_str()) {
                        return Err(SimError::Input(format!(
                            "override {field}[{}] names {name:?} but the model has {actual:?} there",
                            e.id
                        )));
                    }
                }
                Ok(())
            };
            if let Some((kind, ptr, width, count)) = field_slot(model, field) {
                if e.id >= count {
                    return Err(SimError::Input(format!("override {field}[{}] out of range ({count})", e.id)));
                }
                check_name(model, kind)?;
                let vals = values(e, width, field)?;
                for (k, v) in vals.into_iter().enumerate() {
                    // SAFETY: e.id < count and k < width, inside the model's array.
                    unsafe { *ptr.add(e.id * width + k) = v };
                }
            } else if let Some((kind, ptr, width, count)) = field_slot_f32(model, field) {
                if e.id >= count {
                    return Err(SimError::Input(format!("override {field}[{}] out of range ({count})", e.id)));
                }
                check_name(model, kind)?;
                let vals = values(e, width, field)?;
                for (k, v) in vals.into_iter().enumerate() {
                    // SAFETY: as above.
                    unsafe { *ptr.add(e.id * width + k) = v as f32 };
                }
            } else {
                return Err(SimError::Input(format!("runtime override of unsupported model field {field:?}")));
            }
        }
    }
    Ok(())
}

/// Compiles an MJCF string (asset paths already absolute) and applies `overrides`.
pub fn compile_with_overrides(mjcf: &str, overrides: Option<&RuntimeOverrides>) -> Result<MjModel, SimError> {
    let mut model = crate::fault::guarded(|| MjModel::from_xml_string(mjcf))
        .map_err(SimError::Compile)?
        .map_err(|e| SimError::Compile(e.to_string()))?;
    if let Some(o) = overrides {
        apply_runtime_overrides(&mut model, o)?;
    }
    Ok(model)
}
