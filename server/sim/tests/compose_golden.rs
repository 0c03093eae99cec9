//! The composer reproduces robosuite 1.4.0 + LIBERO's merged MJCF and compiled model for the golden scenes
//! (`tests/reference/golden/*.mjcf_input.xml`) and the reference scenes (`tests/reference/ref/*.xml`).
mod common;

use std::path::PathBuf;

use libero_sim::compose::xml::{parse_str, Element};
use libero_sim::compose::{compose_file, ComposedScene};
use libero_sim::mujoco_rs::prelude::*;
use libero_sim::AssetPaths;

use common::reference_dir;

/// (suite, task) of the golden files.
const GOLDEN: [(&str, &str); 8] = [
    ("libero_object", "pick_up_the_alphabet_soup_and_place_it_in_the_basket"),
    ("libero_90", "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet"),
    ("libero_90", "KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet"),
    ("libero_90", "KITCHEN_SCENE7_open_the_microwave"),
    ("libero_goal", "turn_on_the_stove"),
    ("libero_goal", "push_the_plate_to_the_front_of_the_stove"),
    ("libero_10", "LIVING_ROOM_SCENE2_put_both_the_alphabet_soup_and_the_tomato_sauce_in_the_basket"),
    ("libero_10", "STUDY_SCENE1_pick_up_the_book_and_place_it_in_the_back_compartment_of_the_caddy"),
];

fn nums(s: &str) -> Option<Vec<f64>> {
    s.split_whitespace().map(|t| t.parse::<f64>().ok()).collect()
}

/// Element-by-element comparison: same tags, same children order, same attribute sets, values equal as text or
/// as the same numbers (float formatting may differ, the parsed doubles may not).
fn diff(a: &Element, b: &Element, path: &str, out: &mut Vec<String>) {
    if out.len() > 20 {
        return;
    }
    let here = format!("{path}/{}[{}]", a.tag, a.get("name").unwrap_or(""));
    if a.tag != b.tag {
        out.push(format!("{here}: tag {} vs {}", a.tag, b.tag));
        return;
    }
    for (k, v) in &a.attrs {
        match b.get(k) {
            None => out.push(format!("{here}: attribute {k}={v} only in ours")),
            Some(w) if w != v && (nums(v).is_none() || nums(v) != nums(w)) => {
                out.push(format!("{here}: {k}: ours `{v}` golden `{w}`"))
            }
            _ => {}
        }
    }
    for (k, w) in &b.attrs {
        if a.get(k).is_none() {
            out.push(format!("{here}: attribute {k}={w} only in golden"));
        }
    }
    if a.children.len() != b.children.len() {
        let ta: Vec<String> = a.children.iter().map(|c| format!("{}:{}", c.tag, c.get("name").unwrap_or(""))).collect();
        let tb: Vec<String> = b.children.iter().map(|c| format!("{}:{}", c.tag, c.get("name").unwrap_or(""))).collect();
        out.push(format!("{here}: {} children vs {}\n ours   {:?}\n golden {:?}", ta.len(), tb.len(), ta, tb));
        return;
    }
    for (ca, cb) in a.children.iter().zip(&b.children) {
        diff(ca, cb, &here, out);
    }
}

fn compose_stock(paths: &AssetPaths, suite: &str, task: &str) -> ComposedScene {
    compose_file(&paths.stock_bddl(suite, task), paths).unwrap_or_else(|e| panic!("{suite}/{task}: {e}"))
}

#[test]
fn merged_mjcf_matches_robosuite_input_for_all_golden_scenes() {
    let paths = AssetPaths::discover().expect("assets");
    let mut failures = Vec::new();
    for (suite, task) in GOLDEN {
        let scene = compose_stock(&paths, suite, task);
        let golden_path = reference_dir().join("golden").join(format!("{suite}__{task}.mjcf_input.xml"));
        let golden = std::fs::read_to_string(&golden_path).unwrap();
        let golden = parse_str(&paths.substitute_placeholders(&golden)).unwrap();
        let ours = parse_str(&scene.mjcf).unwrap();
        let mut out = Vec::new();
        diff(&ours, &golden, "", &mut out);
        if !out.is_empty() {
            failures.push(format!("{suite}/{task}:\n  {}", out.join("\n  ")));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Reference scenes of `tests/reference/ref/` (robosuite input MJCF) and the stock BDDL each came from.
const REF: [(&str, &str, &str); 8] = [
    ("goal_open_top_drawer", "libero_goal", "open_the_top_drawer_and_put_the_bowl_inside"),
    ("kitchen3_stove_moka", "libero_10", "KITCHEN_SCENE3_turn_on_the_stove_and_put_the_moka_pot_on_it"),
    ("kitchen4_white_cabinet", "libero_10", "KITCHEN_SCENE4_put_the_black_bowl_in_the_bottom_drawer_of_the_cabinet_and_close_it"),
    ("kitchen6_microwave", "libero_10", "KITCHEN_SCENE6_put_the_yellow_and_white_mug_in_the_microwave_and_close_it"),
    ("living2_basket", "libero_10", "LIVING_ROOM_SCENE2_put_both_the_alphabet_soup_and_the_tomato_sauce_in_the_basket"),
    ("object_alphabet_soup", "libero_object", "pick_up_the_alphabet_soup_and_place_it_in_the_basket"),
    ("spatial_table_center", "libero_spatial", "pick_up_the_black_bowl_from_table_center_and_place_it_on_the_plate"),
    ("study1_caddy", "libero_10", "STUDY_SCENE1_pick_up_the_book_and_place_it_in_the_back_compartment_of_the_caddy"),
];

#[test]
fn merged_mjcf_matches_the_reference_scene_inputs() {
    let paths = AssetPaths::discover().expect("assets");
    let mut failures = Vec::new();
    for (file, suite, task) in REF {
        let scene = compose_stock(&paths, suite, task);
        let text = std::fs::read_to_string(reference_dir().join("ref").join(format!("{file}.xml"))).unwrap();
        let reference = parse_str(&paths.substitute_placeholders(&text)).unwrap();
        let mut out = Vec::new();
        diff(&parse_str(&scene.mjcf).unwrap(), &reference, "", &mut out);
        if !out.is_empty() {
            failures.push(format!("{file}:\n  {}", out.join("\n  ")));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Compare two compiled models: sizes, names in id order, and the listed arrays within `tol` (0 = bitwise).
fn compare_models(a: &MjModel, b: &MjModel, tol: f64) -> Vec<String> {
    let (fa, fb) = (a.ffi(), b.ffi());
    let mut out = Vec::new();
    macro_rules! count {
        ($($f:ident),*) => {$( if fa.$f != fb.$f { out.push(format!("{}: {} vs {}", stringify!($f), fa.$f, fb.$f)); } )*};
    }
    count!(nq, nv, nu, nbody, njnt, ngeom, nsite, ncam, nlight, nmesh, nmat, ntex, nsensor, nsensordata, neq, ntendon, nkey);
    if !out.is_empty() {
        return out;
    }
    for (ty, n, label) in [
        (MjtObjBase::mjOBJ_BODY, fa.nbody, "body"),
        (MjtObjBase::mjOBJ_JOINT, fa.njnt, "joint"),
        (MjtObjBase::mjOBJ_GEOM, fa.ngeom, "geom"),
        (MjtObjBase::mjOBJ_SITE, fa.nsite, "site"),
        (MjtObjBase::mjOBJ_CAMERA, fa.ncam, "camera"),
        (MjtObjBase::mjOBJ_ACTUATOR, fa.nu, "actuator"),
        (MjtObjBase::mjOBJ_MESH, fa.nmesh, "mesh"),
        (MjtObjBase::mjOBJ_MATERIAL, fa.nmat, "material"),
        (MjtObjBase::mjOBJ_TEXTURE, fa.ntex, "texture"),
    ] {
        for i in 0..n as usize {
            let (na, nb) = (a.id_to_name(ty, i), b.id_to_name(ty, i));
            if na != nb {
                out.push(format!("{label} {i}: {na:?} vs {nb:?}"));
                break;
            }
        }
    }
    macro_rules! arr {
        ($($f:ident : $n:ident * $w:expr),* $(,)?) => {$(
            let len = fa.$n as usize * $w;
            // SAFETY: MuJoCo allocates `count * width` entries for each of these model arrays.
            let (xa, xb) = unsafe { (std::slice::from_raw_parts(fa.$f, len), std::slice::from_raw_parts(fb.$f, len)) };
            if let Some(k) = (0..len).find(|&k| !((xa[k] as f64 - xb[k] as f64).abs() <= tol)) {
                out.push(format!("{}[{}] ({} row {}): {} vs {}", stringify!($f), k, stringify!($n), k / $w, xa[k], xb[k]));
            }
        )*};
    }
    arr!(
        qpos0: nq * 1, body_pos: nbody * 3, body_quat: nbody * 4, body_ipos: nbody * 3, body_iquat: nbody * 4,
        body_mass: nbody * 1, body_inertia: nbody * 3, body_parentid: nbody * 1, jnt_type: njnt * 1,
        jnt_qposadr: njnt * 1, jnt_range: njnt * 2, jnt_pos: njnt * 3, jnt_axis: njnt * 3, dof_damping: nv * 1,
        dof_armature: nv * 1, dof_frictionloss: nv * 1, geom_type: ngeom * 1, geom_size: ngeom * 3,
        geom_pos: ngeom * 3, geom_quat: ngeom * 4, geom_bodyid: ngeom * 1, geom_contype: ngeom * 1,
        geom_conaffinity: ngeom * 1, geom_condim: ngeom * 1, geom_friction: ngeom * 3, geom_solref: ngeom * 2,
        geom_solimp: ngeom * 5, geom_margin: ngeom * 1, geom_group: ngeom * 1, geom_rgba: ngeom * 4,
        site_pos: nsite * 3, site_quat: nsite * 4, site_size: nsite * 3, site_rgba: nsite * 4, site_bodyid: nsite * 1,
        cam_pos: ncam * 3, cam_quat: ncam * 4, cam_fovy: ncam * 1, cam_bodyid: ncam * 1,
        actuator_gainprm: nu * 10, actuator_biasprm: nu * 10, actuator_ctrlrange: nu * 2, actuator_forcerange: nu * 2,
        light_pos: nlight * 3, mesh_vertnum: nmesh * 1, tex_width: ntex * 1, mat_rgba: nmat * 4,
    );
    let (oa, ob) = (&fa.opt, &fb.opt);
    if (oa.timestep, oa.impratio, oa.density, oa.viscosity, oa.cone, oa.integrator)
        != (ob.timestep, ob.impratio, ob.density, ob.viscosity, ob.cone, ob.integrator)
    {
        out.push("option differs".into());
    }
    out
}

#[test]
fn compiled_model_equals_robosuite_compile_for_golden_and_reference_scenes() {
    let paths = AssetPaths::discover().expect("assets");
    let mut cases: Vec<(String, &str, &str, PathBuf)> = GOLDEN
        .iter()
        .map(|(s, t)| (format!("golden {s}/{t}"), *s, *t, reference_dir().join("golden").join(format!("{s}__{t}.mjcf_input.xml"))))
        .collect();
    // the ref scenes that are not golden scenes too (merged-MJCF equality covers all of them)
    for (file, s, t) in REF.iter().filter(|(f, _, _)| !matches!(*f, "living2_basket" | "object_alphabet_soup" | "study1_caddy")) {
        cases.push((format!("ref {file}"), *s, *t, reference_dir().join("ref").join(format!("{file}.xml"))));
    }
    let mut failures = Vec::new();
    for (label, suite, task, reference) in cases {
        let scene = compose_stock(&paths, suite, task);
        let ours = scene.compile().unwrap_or_else(|e| panic!("{label}: {e}"));
        let text = paths.substitute_placeholders(&std::fs::read_to_string(&reference).unwrap());
        let theirs = MjModel::from_xml_string(&text).unwrap_or_else(|e| panic!("{label}: {e:?}"));
        let d = compare_models(&ours, &theirs, 0.0);
        if !d.is_empty() {
            failures.push(format!("{label}:\n  {}", d.join("\n  ")));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
