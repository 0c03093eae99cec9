//! The simulation's error type: every fault is a value, never a process exit.
use thiserror::Error;

#[derive(Debug, Error)]
pub enum SimError {
    /// Third-party assets are missing or unreadable.
    #[error("assets: {0}")]
    Assets(String),
    /// A BDDL, MJCF or init-state input could not be used.
    #[error("invalid input: {0}")]
    Input(String),
    /// MuJoCo refused to load or compile a model.
    #[error("model compilation failed: {0}")]
    Compile(String),
    /// MuJoCo raised an error, or the state became non-finite or unstable, during simulation.
    /// The simulation that raised it must not be stepped again.
    #[error("simulator fault: {0}")]
    Fault(String),
    #[error("i/o: {0}")]
    Io(#[from] std::io::Error),
}
