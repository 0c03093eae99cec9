//! Simulation core: MuJoCo scene composition, Panda + robosuite 1.4 OSC_POSE, stepping, state readout.
//! No rendering and no I/O servers live here.
pub mod error;
pub mod paths;

pub use error::SimError;
pub use mujoco_rs;
pub use paths::AssetPaths;
