//! Errors of task resolution, goal compilation and the catalog. Evaluation itself never fails: a compiled goal
//! only reads the simulation state.
use thiserror::Error;

#[derive(Debug, Error)]
pub enum TasksError {
    /// A goal names something the composed scene does not have, or uses a predicate in a way LIBERO itself
    /// would reject (KeyError / NotImplementedError / AttributeError in the Python stack).
    #[error("goal {atom}: {message}")]
    Goal { atom: String, message: String },
    /// The composed scene and the compiled model disagree (a body, site, joint or geom is missing).
    #[error("scene: {0}")]
    Scene(String),
    #[error("catalog {path}: {message}")]
    Catalog { path: String, message: String },
    #[error(transparent)]
    Sim(#[from] libero_sim::SimError),
}

impl TasksError {
    pub(crate) fn goal(atom: impl std::fmt::Display, message: impl Into<String>) -> Self {
        Self::Goal { atom: atom.to_string(), message: message.into() }
    }
}
