//! Headless wgpu renderer for compiled MuJoCo models, matching MuJoCo's classic renderer and
//! robosuite's camera conventions: RGB (top-left origin), metric planar depth, and a private per-geom
//! segmentation image. Vulkan first (lavapipe on CPU-only machines), GL/EGL as fallback.
//!
//! Use: [`Renderer::new`] once per process; [`Renderer::prepare_model`] once per model; then per
//! frame [`FrameState::from_mujoco`] and [`Renderer::render`].
pub mod calib;
mod error;
pub mod geometry;
mod gpu;
pub mod io;
pub mod lod;
pub mod scene;

pub use calib::{CameraCalibration, camera_calibration, intrinsics};
pub use error::RenderError;
pub use gpu::{
    CameraFrame, CameraRef, CameraRequest, ModelHandle, Outputs, RenderOptions, Renderer, SEG_SITE_FLAG,
};
pub use scene::{FrameState, SceneModel, Visibility};
