//! Simulation core: MuJoCo scene composition, Panda + robosuite 1.4 OSC_POSE, stepping, state readout.
pub use mujoco_rs;
