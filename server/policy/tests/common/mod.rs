//! The openpi fixture server (`tests/fixtures/policy_server.py`, on the real openpi-client package in the
//! test venv) and synthetic published observation folders.
#![allow(dead_code)]
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};


/// The test venv's Python (openpi-client, numpy, Pillow).
pub use libero_testkit::venv_python;

pub fn fixture_script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/policy_server.py")
}

/// A running fixture server, killed when dropped.
pub struct FixtureServer {
    child: Child,
    pub port: u16,
}

impl FixtureServer {
    pub fn start(args: &[&str]) -> Self {
        let mut child = Command::new(venv_python())
            .arg(fixture_script())
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start the fixture policy server");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        let port = line.trim().strip_prefix("PORT ").unwrap_or_else(|| panic!("fixture server said {line:?}")).parse().unwrap();
        Self { child, port }
    }

    pub fn url(&self) -> String {
        format!("ws://127.0.0.1:{}", self.port)
    }
}

impl Drop for FixtureServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Deterministic bytes (a 64-bit LCG) so that images exercise every value without a fixture file.
pub fn noise(seed: u64, n: usize) -> Vec<u8> {
    let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    (0..n)
        .map(|_| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 56) as u8
        })
        .collect()
}

pub fn write_png(path: &Path, w: u32, h: u32, rgb: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let file = std::fs::File::create(path).unwrap();
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header().unwrap().write_image_data(rgb).unwrap();
}

/// A published observation folder as the episode service writes it (level 1 keys the contract reads), with
/// noisy 256×256 head and wrist images whose smooth gradient makes the resize matter.
pub fn write_published_frame(dir: &Path, seed: u64) {
    let image = |seed: u64| -> Vec<u8> {
        let n = noise(seed, 256 * 256 * 3);
        (0..256 * 256 * 3).map(|i| ((i / 3 % 256) as u8 / 2).wrapping_add(n[i] / 2)).collect()
    };
    write_png(&dir.join("head/rgb.png"), 256, 256, &image(seed));
    write_png(&dir.join("wrist/rgb.png"), 256, 256, &image(seed + 1));
    let doc = serde_json::json!({
        "schema_version": "libero.agent_observation.v2",
        "state": {
            "arm_joint_position_rad_7d": [-0.0193, -0.1846, 0.0086, -2.4097, 0.0051, 2.2407, 0.7931],
            "gripper_finger_joint_position_m_2d": [0.020807129848561545, -0.020803461932707393],
            "gripper_width_m": 0.0416,
            "eef_pose_robot_base_xyzw_7d": [0.469, -0.0047, 0.2887, 0.9238, 0.3826, 0.0054, 0.0041],
        },
        "cameras": {"head": {"rgb": {"file": "head/rgb.png"}}, "wrist": {"rgb": {"file": "wrist/rgb.png"}}},
    });
    std::fs::write(dir.join("observation.json"), serde_json::to_vec_pretty(&doc).unwrap()).unwrap();
}
