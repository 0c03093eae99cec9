//! The store's errors: what the caller can tell apart (a bad URL, a batch that exists) and what it can only
//! report (a statement or a stored document that failed), each saying what the store was doing.
use std::fmt::Display;

/// An error of the episode and batch store.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A statement failed: `what` the store was doing and the database's answer.
    #[error("{what}: {cause}")]
    Database { what: String, cause: sqlx::Error },
    /// A stored document is not the JSON it should be.
    #[error("{what}: {cause}")]
    BadDocument { what: String, cause: serde_json::Error },
    /// `--store` names no supported engine (the URL is shown with its password redacted).
    #[error("store URL {0:?}: expected sqlite://PATH or postgres://USER@HOST:PORT/DB")]
    BadUrl(String),
    /// `enqueue` of a batch name the store already has.
    #[error("the store already has a batch named {0:?} (`run --resume` continues it)")]
    BatchExists(String),
}

pub type Result<T, E = StoreError> = std::result::Result<T, E>;

impl From<sqlx::Error> for StoreError {
    fn from(cause: sqlx::Error) -> Self {
        Self::Database { what: "store: cannot read a row".into(), cause }
    }
}

/// `.context(…)` / `.with_context(|| …)` on the results of sqlx and serde_json, as anyhow spells it.
pub(crate) trait Context<T> {
    fn with_context<D: Display>(self, what: impl FnOnce() -> D) -> Result<T>;

    fn context(self, what: &str) -> Result<T>
    where
        Self: Sized,
    {
        self.with_context(|| what)
    }
}

impl<T> Context<T> for std::result::Result<T, sqlx::Error> {
    fn with_context<D: Display>(self, what: impl FnOnce() -> D) -> Result<T> {
        self.map_err(|cause| StoreError::Database { what: what().to_string(), cause })
    }
}

impl<T> Context<T> for std::result::Result<T, serde_json::Error> {
    fn with_context<D: Display>(self, what: impl FnOnce() -> D) -> Result<T> {
        self.map_err(|cause| StoreError::BadDocument { what: what().to_string(), cause })
    }
}
