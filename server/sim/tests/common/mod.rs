//! Shared loading of the golden trajectories in the repository's `tests/reference/golden/` (see its README).
#![allow(dead_code)]
use std::path::PathBuf;
use std::sync::Arc;

use libero_sim::AssetPaths;
use libero_sim::model_overrides::{RuntimeOverrides, compile_with_overrides};
use libero_sim::mujoco_rs::prelude::MjModel;
use serde::Deserialize;

#[derive(Debug, Deserialize)]
pub struct GoldenSteps {
    pub qpos: Vec<Vec<f64>>,
    pub qvel: Vec<Vec<f64>>,
    pub time: Vec<f64>,
    pub obs_eef_pos: Vec<Vec<f64>>,
    pub obs_eef_quat: Vec<Vec<f64>>,
    pub obs_joint_pos: Vec<Vec<f64>>,
    pub obs_gripper_qpos: Vec<Vec<f64>>,
    pub site_grip_xpos_end: Vec<Vec<f64>>,
    pub torques: Vec<Vec<f64>>,
    pub ctrl: Vec<Vec<f64>>,
    pub goal_pos: Vec<Vec<f64>>,
    pub goal_ori: Vec<Vec<Vec<f64>>>,
    pub gripper_current_action: Vec<Vec<f64>>,
}

#[derive(Debug, Deserialize)]
pub struct GoldenSubsteps {
    pub qpos: Vec<Vec<f64>>,
    pub qvel: Vec<Vec<f64>>,
    pub ctrl: Vec<Vec<f64>>,
    pub torques: Vec<Vec<f64>>,
}

#[derive(Debug, Deserialize)]
pub struct GoldenInit {
    pub qpos: Vec<f64>,
    pub qvel: Vec<f64>,
    pub obs_eef_pos: Vec<f64>,
    pub obs_eef_quat: Vec<f64>,
    pub controller_initial_joint: Vec<f64>,
    pub controller_goal_pos: Vec<f64>,
    pub controller_goal_ori: Vec<Vec<f64>>,
}

#[derive(Debug, Deserialize)]
pub struct Golden {
    pub suite: String,
    pub task: String,
    pub actions: Vec<[f64; 7]>,
    pub init_file_relpath: String,
    pub init_state_index: usize,
    pub init_state: Vec<f64>,
    pub init: GoldenInit,
    pub runtime_model_overrides: RuntimeOverrides,
    pub steps: GoldenSteps,
    pub instrumented_step: usize,
    pub substeps_of_step6: GoldenSubsteps,
    pub ctrl_substeps: Vec<Vec<Vec<f64>>>,
}

#[derive(Debug, Deserialize)]
pub struct Sensitivity {
    pub eef_div_m: Vec<f64>,
    pub joint_div_rad: Vec<f64>,
    pub object_div_m: Vec<f64>,
}

/// The repository's `tests/reference/`: data recorded from the real Python stack (golden trajectories, reference
/// scenes, the 130-task survey; provenance in its README.md).
pub fn reference_dir() -> PathBuf {
    libero_testkit::tests_dir().join("reference")
}

/// `tests/reference/golden/`, or `$LIBERO_GOLDEN_DIR` (e.g. freshly regenerated trajectories).
pub fn golden_dir() -> PathBuf {
    std::env::var_os("LIBERO_GOLDEN_DIR").map(PathBuf::from).unwrap_or_else(|| reference_dir().join("golden"))
}

/// Names `<suite>__<task>` of every `__seqA.json` golden file, sorted.
pub fn golden_names() -> Vec<String> {
    let dir = golden_dir();
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("golden directory {} unreadable: {e}", dir.display()))
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().to_str().and_then(|n| n.strip_suffix("__seqA.json")).map(str::to_owned))
        .collect();
    names.sort();
    assert!(!names.is_empty(), "no golden files in {}", dir.display());
    names
}

pub fn load_golden(name: &str) -> Golden {
    let path = golden_dir().join(format!("{name}__seqA.json"));
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_slice(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

pub fn load_sensitivity(name: &str) -> Sensitivity {
    let path = golden_dir().join("sensitivity").join(format!("{name}__seqA.json"));
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_slice(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

pub fn assets() -> AssetPaths {
    AssetPaths::discover().expect("third-party assets (run scripts/setup.py)")
}

/// The exact recorded model: `<name>.mjcf_input.xml`, placeholders substituted, compiled, runtime
/// overrides applied.
pub fn golden_model(name: &str, golden: &Golden) -> Arc<MjModel> {
    let path = golden_dir().join(format!("{name}.mjcf_input.xml"));
    let xml = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let xml = assets().substitute_placeholders(&xml);
    Arc::new(compile_with_overrides(&xml, Some(&golden.runtime_model_overrides)).expect("golden model compiles"))
}

pub fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
}
