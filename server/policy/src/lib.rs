//! A client of openpi's websocket policy server and the LIBERO observation contract of openpi's LIBERO
//! example, so that a VLA served by openpi (π0, π0.5, …) drives an episode through the same episode service
//! an agent does (docs/harnesses.md, "openpi policies"). The wire format is openpi-client 0.1.2's, checked in
//! the tests against that package itself.
pub mod client;
pub mod codec;
pub mod episode;
pub mod libero;
pub mod resize;

pub use client::{ActionChunk, ClientLimits, Endpoint, PolicyClient, healthz};
pub use codec::{Dtype, NdArray};
pub use libero::{ChunkExecutor, LiberoContract, PublishedFrame, RobotBaseInWorld};

/// Why talking to a policy failed; each kind is reported differently (a policy's own failure carries its
/// traceback for the record).
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    /// Unreachable, refused, handshake failed, or the connection dropped.
    #[error("policy connection: {0}")]
    Connection(String),
    /// The server broke openpi's protocol or this client's bounds (size, shape, dtype, finiteness).
    #[error("policy protocol: {0}")]
    Protocol(String),
    /// The policy raised: openpi sends the traceback as a text frame, then closes with 1011.
    #[error("the policy failed (close code {close_code:?}):\n{traceback}")]
    Policy { traceback: String, close_code: Option<u16> },
    /// No answer in time.
    #[error("policy timeout: {0}")]
    Timeout(String),
    /// A published observation could not be read into the contract.
    #[error("observation: {0}")]
    Observation(String),
}
