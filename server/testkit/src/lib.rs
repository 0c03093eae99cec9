//! What the workspace's tests share, so that no test file carries its own copy: where the repository's folders
//! are ([`paths`]), the day's sample of a long sweep ([`sample`]), a throwaway PostgreSQL cluster (`TestPostgres`,
//! feature `postgres`) and the full `serve` router with the console answering requests in process
//! (`server::TestServer`, feature `router`).
//!
//! Only `[dev-dependencies]` name this crate; its own tests (`tests/`) are the checks of the whole workspace: the
//! crate tower, import circles, documentation links, the repository's layout.
pub mod paths;
pub mod sample;

#[cfg(feature = "router")]
pub mod server;

#[cfg(feature = "postgres")]
pub use libero_store::testing::TestPostgres;

pub use paths::{assets_dir, cache_dir, repo_root, server_dir, tasks_dir, tests_dir, venv_python};
