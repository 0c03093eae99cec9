//! Errors of the renderer.

/// Everything that can go wrong while setting up the GPU or rendering a frame.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// No Vulkan or GL adapter: the message names the Debian packages that provide one.
    #[error(
        "no GPU adapter found (tried Vulkan and GL/EGL). On a CPU-only Debian/Ubuntu machine install the \
         software drivers: `apt-get install mesa-vulkan-drivers libvulkan1` (Vulkan/lavapipe) or \
         `apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri` (GL/EGL); `python3 scripts/setup.py` does this. ({0})"
    )]
    NoAdapter(String),
    #[error("GPU device request failed: {0}")]
    Device(String),
    /// The model has something the renderer cannot represent.
    #[error("model: {0}")]
    Model(String),
    #[error("unknown camera `{0}`")]
    UnknownCamera(String),
    #[error("invalid request: {0}")]
    Request(String),
    /// The frame state does not belong to the prepared model (array sizes differ).
    #[error("frame state does not match the model: {0}")]
    StateMismatch(String),
    #[error("GPU readback failed: {0}")]
    Readback(String),
    #[error("GPU validation error: {0}")]
    Validation(String),
    #[error("image encoding: {0}")]
    Encode(String),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}
