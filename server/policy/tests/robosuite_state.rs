//! `observation/state` against robosuite itself: the golden runs (tests/reference/golden, recorded with robosuite
//! 1.4 and LIBERO) hold `robot0_eef_pos`, `robot0_eef_quat` and the joint angles of every step. From what we
//! publish (the grip site's pose in the base frame, quaternion signed `qw ≥ 0`, the joints) and the base's world
//! pose, the contract must give back robosuite's values, sign of the quaternion included.
use libero_policy::libero::{PublishedFrame, RobotBaseInWorld, panda_hand_quat_wxyz, robosuite_eef_pose};
use libero_policy::resize::Image8;
use libero_testkit::tests_dir;

fn golden_runs() -> Vec<serde_json::Value> {
    let mut files: Vec<_> = std::fs::read_dir(tests_dir().join("reference/golden"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    files.sort();
    assert!(!files.is_empty());
    files.iter().map(|p| serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()).collect()
}

fn vec_f64(v: &serde_json::Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

fn qmul(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}

const IDENTITY_BASE: RobotBaseInWorld = RobotBaseInWorld { p_base_in_world_m: [-0.66, 0.0, 0.912], q_world_from_base_wxyz: [1.0, 0.0, 0.0, 0.0] };

#[test]
fn the_panda_chain_gives_robosuites_hand_quaternion_with_its_sign() {
    let mut checked = 0;
    for run in golden_runs() {
        let steps = &run["steps"];
        for t in 0..steps["obs_joint_pos"].as_array().unwrap().len() {
            let joints: [f64; 7] = vec_f64(&steps["obs_joint_pos"][t]).try_into().unwrap();
            let want = vec_f64(&steps["obs_eef_quat"][t]); // x y z w
            let q = panda_hand_quat_wxyz(&IDENTITY_BASE, &joints);
            let got = [q[1], q[2], q[3], q[0]];
            // robosuite samples the joints one sub-step after the kinematics its quaternion comes from: a few
            // 1e-4 apart; the sign (the point of this test) would be 2 apart.
            for k in 0..4 {
                assert!((got[k] - want[k]).abs() < 5e-3, "{} step {t}: {got:?} != {want:?}", run["task"]);
            }
            checked += 1;
        }
    }
    assert!(checked >= 300, "{checked}");
}

#[test]
fn the_published_site_pose_gives_back_robot0_eef_pos_and_quat() {
    // What we publish, made from robosuite's values: the site is the hand turned by the gripper mount
    // (q_site = q_hand · conj(HAND_IN_SITE)), signed qw ≥ 0, in the base frame.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let mut flipped = 0;
    for run in golden_runs() {
        let steps = &run["steps"];
        for t in 0..steps["obs_eef_quat"].as_array().unwrap().len() {
            let q = vec_f64(&steps["obs_eef_quat"][t]);
            let pos = vec_f64(&steps["obs_eef_pos"][t]);
            let mut site = qmul([q[3], q[0], q[1], q[2]], [h, 0.0, 0.0, -h]);
            if site[0] < 0.0 {
                site = site.map(|v| -v);
                flipped += 1;
            }
            let b = IDENTITY_BASE.p_base_in_world_m;
            let frame = PublishedFrame {
                head: Image8 { width: 1, height: 1, channels: 3, data: vec![0; 3] },
                wrist: Image8 { width: 1, height: 1, channels: 3, data: vec![0; 3] },
                eef_pose_robot_base_xyzw: [pos[0] - b[0], pos[1] - b[1], pos[2] - b[2], site[1], site[2], site[3], site[0]],
                arm_joint_position_rad: vec_f64(&steps["obs_joint_pos"][t]).try_into().unwrap(),
                gripper_finger_joint_position_m: [0.0; 2],
            };
            let (p, quat) = robosuite_eef_pose(&frame, &IDENTITY_BASE);
            for k in 0..3 {
                assert!((p[k] - pos[k]).abs() < 1e-12, "{} step {t}: pos", run["task"]);
            }
            for k in 0..4 {
                assert!((quat[k] - q[k]).abs() < 1e-9, "{} step {t}: {quat:?} != {q:?}", run["task"]);
            }
        }
    }
    assert!(flipped > 0, "some published quaternions must have been re-signed for the test to mean anything");
}

#[test]
fn the_site_is_the_hand_turned_by_the_gripper_mount() {
    // The controller's goal orientation of the zero-action steps at the start of each run (the grip site's
    // world rotation the arm is settling to, a few hundredths off the sampled pose) against the hand's
    // quaternion turned by -90° about z (ours) and by +90° (the other mount): only ours is near.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let mut checked = 0;
    for run in golden_runs() {
        let steps = &run["steps"];
        let actions = steps["action"].as_array().unwrap();
        for t in (0..actions.len()).take_while(|&t| vec_f64(&actions[t]).iter().all(|v| *v == 0.0)) {
            let q = vec_f64(&steps["obs_eef_quat"][t]);
            let goal: Vec<Vec<f64>> = (0..3).map(|i| vec_f64(&steps["goal_ori"][t][i])).collect();
            let error = |mount: [f64; 4]| {
                let r = rotation(qmul([q[3], q[0], q[1], q[2]], mount));
                (0..9).map(|k| (r[k / 3][k % 3] - goal[k / 3][k % 3]).abs()).fold(0.0, f64::max)
            };
            assert!(error([h, 0.0, 0.0, -h]) < 0.1, "{} step {t}: {}", run["task"], error([h, 0.0, 0.0, -h]));
            assert!(error([h, 0.0, 0.0, h]) > 1.5);
            checked += 1;
        }
    }
    assert!(checked >= 10, "{checked}");
}

fn rotation(q: [f64; 4]) -> [[f64; 3]; 3] {
    let (w, x, y, z) = (q[0], q[1], q[2], q[3]);
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
    ]
}
