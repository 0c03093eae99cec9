//! Errors of the episode runtime. None of these texts reaches an agent: agents get [`crate::ToolError`]s.
use thiserror::Error;

#[derive(Debug, Error)]
pub enum EpisodeError {
    #[error(transparent)]
    Sim(#[from] libero_sim::SimError),
    #[error("task: {0}")]
    Task(String),
    #[error("renderer: {0}")]
    Render(String),
    #[error("evaluator: {0}")]
    Evaluator(String),
    #[error("i/o: {0}")]
    Io(#[from] std::io::Error),
    #[error("episode thread: {0}")]
    Thread(String),
}

/// Why an observation was not published. The two sides are told apart because they are blamed differently:
/// the server's own side failing is an infrastructure fault (the episode ends INVALID), while the agent's
/// workspace is the agent's to wreck (the agent is told, and the episode goes on).
#[derive(Debug, Error)]
pub enum PublishError {
    /// Encoding the frame or writing the evaluator-private archive in the run directory.
    #[error("observation archive: {0}")]
    Private(#[source] std::io::Error),
    /// The agent's workspace could not be made to hold the observation: the agent changed it under every
    /// attempt, or it cannot take the files (a full disk, the workspace root removed).
    #[error("workspace publication: {0}")]
    Workspace(#[source] std::io::Error),
}
