//! The LIBERO observation contract of openpi's LIBERO example (`examples/libero/main.py`), built from what
//! this server publishes, and the chunk executor that turns answers into `osc_sequence` actions.
//!
//! What the policy was trained on, and how each piece is made from our files (docs/harnesses.md):
//! * `observation/image`, `observation/wrist_image`: robosuite's raw `agentview_image` /
//!   `robot0_eye_in_hand_image` (OpenGL order, bottom row first) rotated 180° (`img[::-1, ::-1]`), then
//!   `resize_with_pad` to 224, uint8 `[224, 224, 3]`. Our published `head/rgb.png` / `wrist/rgb.png` are
//!   the raw images with rows flipped (`raw[::-1, :]`, docs/protocol.md §3.8), so the policy's image is the
//!   published one mirrored left-right: `published[:, ::-1]`.
//! * `observation/state`: `robot0_eef_pos` (world, the grip site), `quat2axisangle(robot0_eef_quat)` (the
//!   `robot0_right_hand` body's world quaternion, x y z w, as MuJoCo's kinematic chain signs it) and
//!   `robot0_gripper_qpos` (2), float64 `[8]`. We publish the grip site's pose in the robot base frame
//!   with `qw ≥ 0`; the harness adds the base's world pose (a fact of the scene the episode service
//!   holds, not a task secret, and never sent to the policy but through this state), turns the site
//!   into the hand (`R_hand = R_site · Rz(+90°)`, the Panda gripper's mount), and takes the quaternion's
//!   sign from the Panda's chain evaluated at the published joint angles, since the axis-angle of
//!   robosuite's formula depends on it (q and −q give vectors of lengths θ and 2π − θ).
//! * `prompt`: the task's instruction.
use std::collections::VecDeque;
use std::path::Path;

use rmpv::Value;
use serde::Deserialize;

use crate::codec::{NdArray, map_get};
use crate::resize::{Image8, mirror_left_right, resize_with_pad};
use crate::PolicyError;

/// openpi's `LIBERO_DUMMY_ACTION`: still arm, gripper opening.
pub const LIBERO_DUMMY_ACTION: [f64; 7] = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0];

/// The knobs of openpi's LIBERO example (`Args`), with its defaults.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LiberoContract {
    /// `resize_size`: images go out `[h, w, 3]`.
    pub image_height: usize,
    pub image_width: usize,
    /// `replan_steps`: actions executed from each chunk before asking again.
    pub replan_steps: usize,
    /// `num_steps_wait`: dummy steps before the first observation is sent.
    pub warmup_steps: usize,
}

impl Default for LiberoContract {
    fn default() -> Self {
        Self { image_height: 224, image_width: 224, replan_steps: 5, warmup_steps: 10 }
    }
}

impl LiberoContract {
    /// The defaults, with the image size a server states in its metadata: `resize_size` (one integer)
    /// or `image_resolution` (`[h, w]`). openpi's own servers state neither, so 224 stands.
    pub fn with_metadata(mut self, metadata: &Value) -> Result<Self, PolicyError> {
        let Value::Map(entries) = metadata else { return Ok(self) };
        let dim = |v: &Value| v.as_u64().filter(|&d| (1..=1024).contains(&d)).map(|d| d as usize);
        let bad = |k: &str| PolicyError::Protocol(format!("metadata {k:?} must be an image size between 1 and 1024"));
        if let Some(v) = map_get(entries, "resize_size") {
            let d = dim(v).ok_or_else(|| bad("resize_size"))?;
            (self.image_height, self.image_width) = (d, d);
        }
        if let Some(v) = map_get(entries, "image_resolution") {
            match v {
                Value::Array(hw) if hw.len() == 2 => {
                    self.image_height = dim(&hw[0]).ok_or_else(|| bad("image_resolution"))?;
                    self.image_width = dim(&hw[1]).ok_or_else(|| bad("image_resolution"))?;
                }
                _ => return Err(bad("image_resolution")),
            }
        }
        Ok(self)
    }
}

/// openpi's per-suite step caps (after the warm-up), from its LIBERO example: the longest training demo
/// plus a margin.
pub fn suite_max_steps(suite: &str) -> Option<usize> {
    Some(match suite {
        "libero_spatial" => 220,
        "libero_object" => 280,
        "libero_goal" => 300,
        "libero_10" => 520,
        "libero_90" => 400,
        _ => return None,
    })
}

/// The robot base's pose in the world, as the simulation holds it (MuJoCo's `xpos`, `xquat` of `robot0_base`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotBaseInWorld {
    pub p_base_in_world_m: [f64; 3],
    /// `[w, x, y, z]`, MuJoCo's order and sign.
    pub q_world_from_base_wxyz: [f64; 4],
}

/// What one published observation folder gives the contract.
#[derive(Debug, Clone)]
pub struct PublishedFrame {
    /// `head/rgb.png` (agentview), rows top first.
    pub head: Image8,
    /// `wrist/rgb.png` (eye in hand), rows top first.
    pub wrist: Image8,
    /// `state.eef_pose_robot_base_xyzw_7d`.
    pub eef_pose_robot_base_xyzw: [f64; 7],
    /// `state.arm_joint_position_rad_7d`.
    pub arm_joint_position_rad: [f64; 7],
    /// `state.gripper_finger_joint_position_m_2d`.
    pub gripper_finger_joint_position_m: [f64; 2],
}

/// Largest `observation.json` read (the level-3 document is a few KiB).
const MAX_OBSERVATION_JSON_BYTES: u64 = 1 << 20;
/// Largest image side read from a published PNG.
const MAX_IMAGE_SIDE: u32 = 4096;

impl PublishedFrame {
    /// Reads `observation.json`, `head/rgb.png` and `wrist/rgb.png` of one published observation folder.
    pub fn read(dir: &Path) -> Result<Self, PolicyError> {
        let io = |what: &Path, e: &dyn std::fmt::Display| PolicyError::Observation(format!("{}: {e}", what.display()));
        let json_path = dir.join("observation.json");
        let len = std::fs::metadata(&json_path).map_err(|e| io(&json_path, &e))?.len();
        if len > MAX_OBSERVATION_JSON_BYTES {
            return Err(io(&json_path, &format!("{len} bytes, more than an observation document holds")));
        }
        let text = std::fs::read_to_string(&json_path).map_err(|e| io(&json_path, &e))?;
        let doc: ObservationDoc = serde_json::from_str(&text).map_err(|e| io(&json_path, &e))?;
        let s = &doc.state;
        let finite = s.eef_pose_robot_base_xyzw_7d.iter().chain(&s.arm_joint_position_rad_7d).chain(&s.gripper_finger_joint_position_m_2d);
        if !finite.into_iter().all(|v| v.is_finite()) {
            return Err(io(&json_path, &"a state value is not finite"));
        }
        let image = |camera: &CameraDoc| {
            let rel = &camera.rgb.file;
            if rel.contains("..") || rel.starts_with('/') {
                return Err(io(&json_path, &format!("the camera file {rel:?} leaves the folder")));
            }
            read_rgb_png(&dir.join(rel))
        };
        Ok(Self {
            head: image(&doc.cameras.head)?,
            wrist: image(&doc.cameras.wrist)?,
            eef_pose_robot_base_xyzw: s.eef_pose_robot_base_xyzw_7d,
            arm_joint_position_rad: s.arm_joint_position_rad_7d,
            gripper_finger_joint_position_m: s.gripper_finger_joint_position_m_2d,
        })
    }
}

/// The part of `observation.json` (`libero.agent_observation.v2`, docs/protocol.md §3.6) the contract reads.
#[derive(Debug, Deserialize)]
struct ObservationDoc {
    state: StateDoc,
    cameras: CamerasDoc,
}

#[derive(Debug, Deserialize)]
struct StateDoc {
    eef_pose_robot_base_xyzw_7d: [f64; 7],
    arm_joint_position_rad_7d: [f64; 7],
    gripper_finger_joint_position_m_2d: [f64; 2],
}

#[derive(Debug, Deserialize)]
struct CamerasDoc {
    head: CameraDoc,
    wrist: CameraDoc,
}

#[derive(Debug, Deserialize)]
struct CameraDoc {
    rgb: FileDoc,
}

#[derive(Debug, Deserialize)]
struct FileDoc {
    file: String,
}

/// An 8-bit RGB (or RGBA, alpha dropped) PNG.
pub fn read_rgb_png(path: &Path) -> Result<Image8, PolicyError> {
    let bad = |e: &dyn std::fmt::Display| PolicyError::Observation(format!("{}: {e}", path.display()));
    let file = std::fs::File::open(path).map_err(|e| bad(&e))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(|e| bad(&e))?;
    let (w, h) = (reader.info().width, reader.info().height);
    if w == 0 || h == 0 || w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE {
        return Err(bad(&format!("an image of {w}×{h}")));
    }
    let mut buf = vec![0u8; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| bad(&e))?;
    if info.bit_depth != png::BitDepth::Eight {
        return Err(bad(&"not an 8-bit PNG"));
    }
    let channels = match info.color_type {
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        other => return Err(bad(&format!("color type {other:?}, not RGB"))),
    };
    let (w, h) = (w as usize, h as usize);
    let mut data = Vec::with_capacity(w * h * 3);
    for row in buf[..info.buffer_size()].chunks_exact(info.line_size).take(h) {
        for px in row[..w * channels].chunks_exact(channels) {
            data.extend_from_slice(&px[..3]);
        }
    }
    Ok(Image8 { width: w, height: h, channels: 3, data })
}

/// The policy's image from a published one: mirrored left-right (see the module), resized with padding.
pub fn policy_image(published: &Image8, contract: &LiberoContract) -> Image8 {
    resize_with_pad(&mirror_left_right(published), contract.image_height, contract.image_width)
}

type Quat = [f64; 4]; // w, x, y, z

const H: f64 = std::f64::consts::FRAC_1_SQRT_2;

fn quat_mul(a: Quat, b: Quat) -> Quat {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}

fn quat_normalized(q: Quat) -> Quat {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if n > 0.0 { q.map(|v| v / n) } else { [1.0, 0.0, 0.0, 0.0] }
}

fn rotate(q: Quat, v: [f64; 3]) -> [f64; 3] {
    let p = quat_mul(quat_mul(q, [0.0, v[0], v[1], v[2]]), [q[0], -q[1], -q[2], -q[3]]);
    [p[1], p[2], p[3]]
}

/// The body quaternions (`quat` attributes, w x y z) from `robot0_base` to `robot0_right_hand` in robosuite's
/// Panda MJCF (robosuite 1.4 `robots/panda/robot.xml`, whose `0.707107` MuJoCo normalizes to 1/√2); every joint
/// turns about its body's z.
const PANDA_LINK_QUATS: [Quat; 8] = [
    [1.0, 0.0, 0.0, 0.0], // link0
    [1.0, 0.0, 0.0, 0.0], // link1 (joint1)
    [H, -H, 0.0, 0.0], // link2 (joint2)
    [H, H, 0.0, 0.0], // link3 (joint3)
    [H, H, 0.0, 0.0], // link4 (joint4)
    [H, -H, 0.0, 0.0], // link5 (joint5)
    [H, H, 0.0, 0.0], // link6 (joint6)
    [H, H, 0.0, 0.0], // link7 (joint7)
];
/// `robot0_right_hand` in `robot0_link7`.
const PANDA_HAND_QUAT: Quat = [0.924, 0.0, 0.0, -0.383];
/// The grip site's frame in the hand's: `gripper0_right_gripper`'s `quat="0.707107 0 0 -0.707107"`
/// (the eef body and the site add no rotation), so `q_hand = q_site · HAND_IN_SITE`.
const HAND_IN_SITE: Quat = [std::f64::consts::FRAC_1_SQRT_2, 0.0, 0.0, std::f64::consts::FRAC_1_SQRT_2];

/// `robot0_right_hand`'s world quaternion as MuJoCo's forward kinematics composes it (sign included).
pub fn panda_hand_quat_wxyz(base: &RobotBaseInWorld, joints_rad: &[f64; 7]) -> Quat {
    let mut q = base.q_world_from_base_wxyz;
    for (i, body) in PANDA_LINK_QUATS.iter().enumerate() {
        q = quat_normalized(quat_mul(q, quat_normalized(*body)));
        if i >= 1 {
            let half = joints_rad[i - 1] / 2.0;
            q = quat_normalized(quat_mul(q, [half.cos(), 0.0, 0.0, half.sin()]));
        }
    }
    quat_normalized(quat_mul(q, quat_normalized(PANDA_HAND_QUAT)))
}

/// robosuite's `quat2axisangle` of an `[x, y, z, w]` quaternion.
pub fn quat2axisangle(xyzw: [f64; 4]) -> [f64; 3] {
    let w = xyzw[3].clamp(-1.0, 1.0);
    let den = (1.0 - w * w).sqrt();
    if den == 0.0 {
        return [0.0; 3];
    }
    let s = 2.0 * w.acos() / den;
    [xyzw[0] * s, xyzw[1] * s, xyzw[2] * s]
}

/// `robot0_eef_pos` and `robot0_eef_quat` (x y z w) from a published frame and the base's world pose.
pub fn robosuite_eef_pose(frame: &PublishedFrame, base: &RobotBaseInWorld) -> ([f64; 3], [f64; 4]) {
    let p = &frame.eef_pose_robot_base_xyzw;
    let qb = quat_normalized(base.q_world_from_base_wxyz);
    let r = rotate(qb, [p[0], p[1], p[2]]);
    let pos = [r[0] + base.p_base_in_world_m[0], r[1] + base.p_base_in_world_m[1], r[2] + base.p_base_in_world_m[2]];
    let q_site_world = quat_mul(qb, quat_normalized([p[6], p[3], p[4], p[5]]));
    let mut q_hand = quat_normalized(quat_mul(q_site_world, HAND_IN_SITE));
    let chain = panda_hand_quat_wxyz(base, &frame.arm_joint_position_rad);
    if q_hand.iter().zip(chain).map(|(a, b)| a * b).sum::<f64>() < 0.0 {
        q_hand = q_hand.map(|v| -v);
    }
    (pos, [q_hand[1], q_hand[2], q_hand[3], q_hand[0]])
}

/// `observation/state`: eef position (world, m), axis-angle (rad), finger joints (m).
pub fn policy_state(frame: &PublishedFrame, base: &RobotBaseInWorld) -> [f64; 8] {
    let (pos, quat) = robosuite_eef_pose(frame, base);
    let aa = quat2axisangle(quat);
    let g = frame.gripper_finger_joint_position_m;
    [pos[0], pos[1], pos[2], aa[0], aa[1], aa[2], g[0], g[1]]
}

/// The request openpi's LIBERO example sends, keys in its order, as openpi's packer would write it.
pub fn observation_request(frame: &PublishedFrame, base: &RobotBaseInWorld, prompt: &str, contract: &LiberoContract) -> Result<Value, PolicyError> {
    let image = |img: &Image8| {
        let out = policy_image(img, contract);
        NdArray::from_u8(vec![out.height, out.width, 3], out.data).map(|a| a.to_value())
    };
    Ok(Value::Map(vec![
        (Value::from("observation/image"), image(&frame.head)?),
        (Value::from("observation/wrist_image"), image(&frame.wrist)?),
        (Value::from("observation/state"), NdArray::from_f64(vec![8], &policy_state(frame, base))?.to_value()),
        (Value::from("prompt"), Value::from(prompt)),
    ]))
}

/// An action as `osc_sequence` takes it: 7 finite components in [-1, 1]. Values outside are clipped, as
/// robosuite's OSC controller and gripper clip a policy's raw output in openpi's evaluation.
pub fn osc_action(raw: &[f64]) -> Result<([f64; 7], usize), PolicyError> {
    let a: [f64; 7] = raw.try_into().map_err(|_| PolicyError::Protocol(format!("an action of {} components, not 7", raw.len())))?;
    if let Some(i) = a.iter().position(|v| !v.is_finite()) {
        return Err(PolicyError::Protocol(format!("action component {i} is not finite")));
    }
    let clipped = a.iter().filter(|v| v.abs() > 1.0).count();
    Ok((a.map(|v| v.clamp(-1.0, 1.0)), clipped))
}

/// openpi's action plan: a chunk's first `replan_steps` actions, executed before the next request.
#[derive(Debug, Default)]
pub struct ChunkExecutor {
    replan_steps: usize,
    plan: VecDeque<[f64; 7]>,
    /// Components clipped into [-1, 1] so far.
    pub clipped_components: usize,
}

impl ChunkExecutor {
    pub fn new(replan_steps: usize) -> Self {
        Self { replan_steps: replan_steps.max(1), plan: VecDeque::new(), clipped_components: 0 }
    }

    /// True when the next action needs a new request.
    pub fn needs_chunk(&self) -> bool {
        self.plan.is_empty()
    }

    /// Takes the first `replan_steps` actions of a chunk; a shorter chunk is an error, as in openpi.
    pub fn push_chunk(&mut self, actions: &[Vec<f64>]) -> Result<(), PolicyError> {
        if actions.len() < self.replan_steps {
            return Err(PolicyError::Protocol(format!(
                "a chunk of {} actions; replanning every {} steps needs at least that many",
                actions.len(),
                self.replan_steps
            )));
        }
        let mut taken = Vec::with_capacity(self.replan_steps);
        for raw in &actions[..self.replan_steps] {
            let (a, clipped) = osc_action(raw)?;
            self.clipped_components += clipped;
            taken.push(a);
        }
        self.plan.extend(taken);
        Ok(())
    }

    pub fn next_action(&mut self) -> Option<[f64; 7]> {
        self.plan.pop_front()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_angle_is_robosuites() {
        assert_eq!(quat2axisangle([0.0, 0.0, 0.0, 1.0]), [0.0; 3]);
        let h = std::f64::consts::FRAC_PI_4;
        let aa = quat2axisangle([h.sin(), 0.0, 0.0, h.cos()]);
        assert!((aa[0] - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }

    #[test]
    fn chunks_are_cut_to_the_replan_steps_and_clipped() {
        let mut ex = ChunkExecutor::new(2);
        assert!(ex.push_chunk(&[vec![0.0; 7]]).is_err());
        ex.push_chunk(&[vec![1.5, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0], vec![0.1; 7], vec![0.9; 7]]).unwrap();
        assert_eq!(ex.clipped_components, 1);
        assert_eq!(ex.next_action().unwrap()[0], 1.0);
        assert_eq!(ex.next_action().unwrap()[0], 0.1);
        assert!(ex.needs_chunk());
        assert!(ChunkExecutor::new(1).push_chunk(&[vec![0.0; 6]]).is_err());
    }

    #[test]
    fn metadata_may_set_the_image_size() {
        let c = LiberoContract::default();
        assert_eq!(c.clone().with_metadata(&Value::Map(vec![])).unwrap(), c);
        let m = Value::Map(vec![(Value::from("image_resolution"), Value::Array(vec![Value::from(128), Value::from(160)]))]);
        let c2 = c.clone().with_metadata(&m).unwrap();
        assert_eq!((c2.image_height, c2.image_width), (128, 160));
        assert!(c.with_metadata(&Value::Map(vec![(Value::from("resize_size"), Value::from(0))])).is_err());
    }
}
