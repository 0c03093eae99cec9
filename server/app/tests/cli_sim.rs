//! The `sim replay`, `sim inspect` and `bench sim` commands, run as a user runs them: through the binary,
//! on stock LIBERO files from the asset cache, checked against the golden trajectories of the real stack.
use std::path::PathBuf;
use std::process::{Command, Output};

use libero_sim::AssetPaths;
use serde_json::Value;

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_libero-agent"));
    c.env("XDG_RUNTIME_DIR", std::env::temp_dir());
    c
}

fn run_ok(cmd: &mut Command) -> Output {
    let out = cmd.output().expect("spawn libero-agent");
    assert!(
        out.status.success(),
        "libero-agent failed ({}):\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// The repository's `tests/reference/golden/` (provenance in `tests/reference/README.md`), or `$LIBERO_GOLDEN_DIR`.
fn golden_dir() -> PathBuf {
    std::env::var_os("LIBERO_GOLDEN_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| libero_testkit::tests_dir().join("reference/golden"))
}

fn read_json(p: &std::path::Path) -> Value {
    serde_json::from_slice(&std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).expect("json")
}

fn max_abs_diff(a: &Value, b: &Value) -> f64 {
    let (a, b) = (a.as_array().expect("array"), b.as_array().expect("array"));
    assert_eq!(a.len(), b.len(), "step counts differ");
    a.iter()
        .zip(b)
        .flat_map(|(x, y)| {
            let (x, y) = (x.as_array().expect("row"), y.as_array().expect("row"));
            assert_eq!(x.len(), y.len(), "row lengths differ");
            x.iter().zip(y).map(|(p, q)| (p.as_f64().expect("num") - q.as_f64().expect("num")).abs()).collect::<Vec<_>>()
        })
        .fold(0.0, f64::max)
}

/// `sim replay --bddl` composes the scene from the stock BDDL (seed 0 as the goldens), restores the stock init
/// state, takes the golden file's actions and tracks the real stack's grip site and joints.
#[test]
fn replay_from_stock_bddl_tracks_the_golden_trajectory() {
    let paths = AssetPaths::discover().expect("assets (run scripts/setup.py)");
    let dir = tempfile::tempdir().expect("tmp");
    for name in ["libero_goal__turn_on_the_stove", "libero_90__KITCHEN_SCENE7_open_the_microwave"] {
        let golden_path = golden_dir().join(format!("{name}__seqA.json"));
        let golden = read_json(&golden_path);
        let lib = &paths.libero_root;
        let bddl = lib.join(golden["bddl_relpath"].as_str().expect("bddl_relpath"));
        let init = lib.join(golden["init_file_relpath"].as_str().expect("init_file_relpath"));
        let out = dir.path().join(format!("{name}.json"));
        run_ok(bin().args(["sim", "replay", "--bddl"]).arg(&bddl).arg("--init-file").arg(&init).arg("--actions").arg(&golden_path).arg("--out").arg(&out));
        let traj = read_json(&out);
        let (ours, theirs) = (&traj["steps"], &golden["steps"]);
        assert_eq!(ours["qpos"].as_array().map(Vec::len), Some(80), "{name}: one record per action");
        let grip = max_abs_diff(&ours["site_grip_xpos_end"], &theirs["site_grip_xpos_end"]);
        let joints = max_abs_diff(&ours["obs_joint_pos"], &theirs["obs_joint_pos"]);
        assert!(grip < 1e-3, "{name}: grip site off by {grip} m");
        assert!(joints < 1e-3, "{name}: joints off by {joints} rad");
        assert_eq!(traj["init_state"], golden["init_state"], "{name}: the init row is the golden one");
    }
}

/// Bad input is one clear error and no output file.
#[test]
fn replay_rejects_bad_actions_and_mismatched_init_files_clearly() {
    let paths = AssetPaths::discover().expect("assets");
    let dir = tempfile::tempdir().expect("tmp");
    let bddl = paths.stock_bddl("libero_goal", "turn_on_the_stove");
    let actions = dir.path().join("a.json");
    std::fs::write(&actions, "[[0,0,0,0,0,0]]").expect("write");
    let out = dir.path().join("t.json");
    let o = bin().args(["sim", "replay", "--bddl"]).arg(&bddl).arg("--actions").arg(&actions).arg("--out").arg(&out).output().expect("spawn");
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("OSC_POSE needs 7"), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!out.exists());

    std::fs::write(&actions, "[[0,0,0,0,0,0,-1]]").expect("write");
    let wrong_init = paths.stock_init("libero_90", "KITCHEN_SCENE7_open_the_microwave");
    let o = bin()
        .args(["sim", "replay", "--bddl"])
        .arg(&bddl)
        .arg("--init-file")
        .arg(&wrong_init)
        .arg("--actions")
        .arg(&actions)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("spawn");
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("is it the init file of this BDDL"), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!out.exists());
}

/// Without an init file the replay starts from LIBERO's seeded reset placement, and the seed matters.
#[test]
fn replay_without_init_file_starts_from_the_seeded_placement() {
    let paths = AssetPaths::discover().expect("assets");
    let dir = tempfile::tempdir().expect("tmp");
    let bddl = paths.stock_bddl("libero_object", "pick_up_the_alphabet_soup_and_place_it_in_the_basket");
    let actions = dir.path().join("a.json");
    std::fs::write(&actions, "[[0,0,0,0,0,0,-1],[0.5,0,0,0,0,0,-1]]").expect("write");
    let mut starts = Vec::new();
    for seed in ["0", "100"] {
        let out = dir.path().join(format!("s{seed}.json"));
        run_ok(bin().args(["sim", "replay", "--seed", seed, "--bddl"]).arg(&bddl).arg("--actions").arg(&actions).arg("--out").arg(&out));
        let t = read_json(&out);
        assert_eq!(t["steps"]["qpos"].as_array().map(Vec::len), Some(2));
        assert_eq!(t["init_state"][0].as_f64(), Some(0.0), "placement starts at t = 0");
        starts.push(t["init_state"].clone());
    }
    assert_ne!(starts[0], starts[1], "seeds 0 and 100 place the objects differently");
}

/// `sim inspect` prints the composed scene with the robot, cameras and the task's objects.
#[test]
fn inspect_lists_cameras_robot_and_task_objects() {
    let paths = AssetPaths::discover().expect("assets");
    let bddl = paths.stock_bddl("libero_90", "KITCHEN_SCENE7_open_the_microwave");
    let out = run_ok(bin().args(["sim", "inspect", "--bddl"]).arg(&bddl));
    let v: Value = serde_json::from_slice(&out.stdout).expect("inspect prints JSON");
    let text = v.to_string();
    for needle in ["agentview", "robot0_eye_in_hand", "robot0_joint1", "microwave_1", "white_bowl_1", "plate_1"] {
        assert!(text.contains(needle), "inspect output lacks {needle}");
    }
}

/// `bench sim --json` measures on the composed kitchen scene and reports the ratio against raw `mj_step`.
#[test]
fn bench_sim_prints_json_with_the_cost_ratio() {
    let out = run_ok(bin().args(["bench", "sim", "--json", "--steps", "20", "--rounds", "1", "--no-libero"]));
    let v: Value = serde_json::from_slice(&out.stdout).expect("bench prints JSON");
    let ratio = v["cost_ratio"].as_f64().expect("cost_ratio");
    assert!(ratio.is_finite() && ratio > 0.0, "{v}");
    assert!(v.to_string().contains("KITCHEN_SCENE10"), "{v}");
}

/// `bench render --json` times both cameras against MuJoCo's renderer in the same run and, beside them, the whole
/// level-3 observation publication; it prints the figures and asserts nothing about time.
#[test]
fn bench_render_prints_the_speedup_and_the_level3_publication() {
    let out = run_ok(bin().args(["bench", "render", "--json", "--frames", "8"]));
    let v: Value = serde_json::from_slice(&out.stdout).expect("bench prints JSON");
    let speedup = v["speedup_vs_mujoco"].as_f64().expect("speedup_vs_mujoco");
    assert!(speedup.is_finite() && speedup > 0.0, "{v}");
    assert_eq!(v["libero_render"]["outputs"], "rgb+depth", "{v}");
    let publication = &v["libero_render"]["observation_publication"];
    assert_eq!(publication["level"], 3, "{v}");
    for field in ["render_ms_p50", "publish_ms_p50", "render_plus_publish_ms_p50"] {
        let ms = publication[field].as_f64().unwrap_or(f64::NAN);
        assert!(ms.is_finite() && ms > 0.0, "{field}: {v}");
    }
    assert!(
        publication["render_plus_publish_ms_p50"].as_f64() >= publication["render_ms_p50"].as_f64(),
        "publication includes its render: {v}"
    );
}
