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
