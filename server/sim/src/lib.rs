//! Simulation core: MuJoCo scene composition, Panda + robosuite 1.4 OSC_POSE, stepping, state readout.
//! No rendering and no I/O servers live here.
pub mod error;
pub mod paths;

// BDDL → MJCF composition and LIBERO's reset-time fixture placement
pub mod compose;
pub mod numpy_rng;
pub mod placement;
pub mod scene_setup;
pub mod shared_model;

// Panda, OSC_POSE, stepping, faults, init states (simulation core)
pub mod benchmark;
pub mod controller;
pub mod fault;
pub mod gripper;
pub mod init_state;
pub mod model_overrides;
pub mod pose_replay;
pub mod robot;
pub mod simulation;
pub mod trajectory;

pub use error::SimError;
pub use mujoco_rs;
pub use paths::AssetPaths;
pub use init_state::InitStates;
pub use pose_replay::PoseReplay;
pub use simulation::{ObservationSample, RobotState, SimData, Simulation, StepObserver, StepOutcome};
pub use trajectory::{Trajectory, replay};
