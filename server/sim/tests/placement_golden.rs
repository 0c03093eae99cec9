//! Seeded placement reproduces LIBERO's reset: for the golden flow `env.seed(0); env.reset()` every entry of the
//! golden `runtime_model_overrides` (fixture body_pos/body_quat, site alphas) and, after applying the stored init
//! state, the object/fixture poses of `poses_after_set_init_state`; for other seeds and scenes, the reference
//! stack's dumps in `tests/fixtures/placement_*.json`.
mod common;

use std::path::{Path, PathBuf};

use libero_sim::compose::{compose_file, ComposedScene};
use libero_sim::mujoco_rs::prelude::*;
use libero_sim::placement::{update_visual_sites, Placement};
use libero_sim::{AssetPaths, InitStates};
use serde_json::Value;

use common::reference_dir;

fn field_row(model: &MjModel, field: &str, id: usize) -> Vec<f64> {
    match field {
        "body_pos" => model.body_pos()[id].to_vec(),
        "body_quat" => model.body_quat()[id].to_vec(),
        "site_rgba" => model.site_rgba()[id].iter().map(|v| *v as f64).collect(),
        other => panic!("unexpected override field {other}"),
    }
}

fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
}

/// Rows of body_pos/body_quat/site_rgba that differ between two models (the overrides a placement made).
fn changed_rows(a: &MjModel, b: &MjModel) -> Vec<(String, usize)> {
    let mut out = Vec::new();
    for i in 0..a.ffi().nbody as usize {
        if a.body_pos()[i] != b.body_pos()[i] {
            out.push(("body_pos".to_string(), i));
        }
        if a.body_quat()[i] != b.body_quat()[i] {
            out.push(("body_quat".to_string(), i));
        }
    }
    for i in 0..a.ffi().nsite as usize {
        if a.site_rgba()[i] != b.site_rgba()[i] {
            out.push(("site_rgba".to_string(), i));
        }
    }
    out
}

fn golden_files() -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(reference_dir().join("golden"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.to_string_lossy().ends_with("__seqA.json"))
        .collect();
    v.sort();
    assert_eq!(v.len(), 8);
    v
}

#[test]
fn seed0_reproduces_golden_runtime_overrides_and_poses_after_set_init_state() {
    let paths = AssetPaths::discover().expect("assets");
    let mut failures = Vec::new();
    for file in golden_files() {
        let g: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
        let label = file.file_name().unwrap().to_string_lossy().to_string();
        let bddl = paths.libero_root.join(g["bddl_relpath"].as_str().unwrap());
        let scene = compose_file(&bddl, &paths).unwrap();
        let mut model = scene.compile().unwrap();
        let pristine = model.clone();
        let placement = Placement::sample(&scene, 0, Some(&model)).unwrap();
        placement.apply(&mut model).unwrap();
        // after set_init_state: LIBERO's stove-burner toggle
        let init = InitStates::read(&paths.libero_root.join(g["init_file_relpath"].as_str().unwrap())).unwrap();
        let row = init.get(0).unwrap().to_vec();
        let nq = model.ffi().nq as usize;
        update_visual_sites(&scene, &mut model, &row[1..1 + nq]).unwrap();
        let overrides = g["runtime_model_overrides"].as_object().unwrap();
        let mut expected = Vec::new();
        for (field, rows) in overrides {
            for r in rows.as_array().unwrap() {
                let id = r["id"].as_u64().unwrap() as usize;
                expected.push((field.clone(), id));
                let want: Vec<f64> = r["value"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
                let got = field_row(&model, field, id);
                if !close(&got, &want, 1e-12) {
                    failures.push(format!("{label}: {field}[{id}] ({}) ours {got:?} golden {want:?}", r["name"]));
                }
            }
        }
        for (field, id) in changed_rows(&model, &pristine) {
            if !expected.contains(&(field.clone(), id)) {
                failures.push(format!("{label}: we changed {field}[{id}] but LIBERO did not"));
            }
        }
        // poses after set_init_state (qpos/qvel/time from the init file, then mj_forward)
        let mut data = MjData::new(&model);
        data.qpos_mut().copy_from_slice(&row[1..1 + nq]);
        let nv = model.ffi().nv as usize;
        data.qvel_mut().copy_from_slice(&row[1 + nq..1 + nq + nv]);
        data.forward();
        let poses = &g["poses_after_set_init_state"];
        for group in ["objects", "fixtures"] {
            for (name, p) in poses[group].as_object().unwrap() {
                let body = p["root_body"].as_str().unwrap();
                let id = model.name_to_id(MjtObjBase::mjOBJ_BODY, body).unwrap_or_else(|| panic!("{label}: no body {body}"));
                let want: Vec<f64> = p["xpos"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
                let got = data.xpos()[id].to_vec();
                if !close(&got, &want, 1e-12) {
                    failures.push(format!("{label}: {group} {name} xpos ours {got:?} golden {want:?}"));
                }
                let want: Vec<f64> = p["xquat_wxyz"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
                if !close(&data.xquat()[id], &want, 1e-12) {
                    failures.push(format!("{label}: {group} {name} xquat ours {:?} golden {want:?}", data.xquat()[id]));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Fixtures written by `scripts/reference_stack/libero_env.py --no-model` (other seeds and scenes).
fn check_reference_dump(paths: &AssetPaths, dump: &Value) -> Vec<String> {
    let mut failures = Vec::new();
    let bddl = paths.libero_root.join(dump["bddl_relpath"].as_str().unwrap());
    let seed = dump["seed"].as_u64().unwrap() as u32;
    let label = format!("{} seed {seed}", dump["bddl_relpath"].as_str().unwrap());
    let scene: ComposedScene = compose_file(&bddl, paths).unwrap();
    let mut model = scene.compile().unwrap();
    let placement = Placement::sample(&scene, seed, Some(&model)).unwrap();
    placement.apply(&mut model).unwrap();
    for (name, f) in dump["fixtures"].as_object().unwrap() {
        let id = model.name_to_id(MjtObjBase::mjOBJ_BODY, f["root_body"].as_str().unwrap()).unwrap();
        let want: Vec<f64> = f["body_pos"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        if !close(&model.body_pos()[id], &want, 1e-12) {
            failures.push(format!("{label}: fixture {name} pos ours {:?} LIBERO {want:?}", model.body_pos()[id]));
        }
        let want: Vec<f64> = f["body_quat_wxyz"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        if !close(&model.body_quat()[id], &want, 1e-12) {
            failures.push(format!("{label}: fixture {name} quat ours {:?} LIBERO {want:?}", model.body_quat()[id]));
        }
    }
    // qpos after reset (objects + articulations); the robot part is LIBERO's init_qpos
    let mut qpos = model.qpos0().to_vec();
    placement.write_qpos(&model, &mut qpos).unwrap();
    let want: Vec<f64> = dump["qpos"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    for k in 9..qpos.len() {
        if (qpos[k] - want[k]).abs() > 1e-9 {
            failures.push(format!("{label}: qpos[{k}] ours {} LIBERO {}", qpos[k], want[k]));
            break;
        }
    }
    failures
}

#[test]
fn other_seeds_and_scenes_match_reference_stack_dumps() {
    let paths = AssetPaths::discover().expect("assets");
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
    let mut n = 0;
    let mut failures = Vec::new();
    for e in std::fs::read_dir(&dir).unwrap() {
        let p = e.unwrap().path();
        if !p.file_name().unwrap().to_string_lossy().starts_with("placement_") {
            continue;
        }
        let dumps: Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        for d in dumps.as_array().unwrap() {
            failures.extend(check_reference_dump(&paths, d));
            n += 1;
        }
    }
    assert!(n >= 10, "expected reference dumps in {}", dir.display());
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
