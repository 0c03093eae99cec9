//! The episode server (`libero-agent serve`, and the in-process server of `run` and `worker`): every prepared
//! episode at its own MCP endpoint `/mcp/<episode_id>` (rmcp streamable HTTP), guarded by a per-episode bearer
//! token checked before anything reaches rmcp; `GET /api/health`; `POST /api/episodes` to prepare an episode
//! (the CLI's `episode prepare` and the dashboard use it); `GET /api/episodes[/{id}[/video|/result]]` from the
//! episode store, typed as `libero_records::episode_view` (operator-facing; no tokens, no paths), behind the
//! operator guard (`auth`). The browser console is not
//! here: a [`Console`] (the `libero-dashboard` crate's) adds its pages, so a worker's server can run without it.
//! Every listener (the address asked for and its loopback twin) serves through [`listener`]: connection caps per
//! peer address and in total, header, idle and body timeouts, and a file-descriptor reserve for the episodes.
//! Every error answer, the console's included, is an [`ApiError`] (`api_error`: the one place its JSON shape lives).
//!
//! Where things are: the flags (`args`), the shared state and a console's plug (`app`), starting and stopping
//! (`serve`), the routes (`router`), the operator API's handlers (`api`), the MCP endpoint (`mcp_gate`, `mcp`,
//! `episodes`: the per-episode service over `libero_episode::lifecycle`) and the one writer of episode rows
//! (`store_writer`).
pub mod api;
pub mod api_error;
pub mod app;
pub mod args;
pub mod auth;
pub mod batches;
pub mod client;
pub mod credential;
pub mod episodes;
pub mod http_client;
pub mod listener;
pub mod live;
pub mod mcp;
pub mod mcp_gate;
pub mod router;
pub mod serve;
pub mod store_writer;
pub mod thumbnails;
pub mod transcript;

pub use api::{episode_json, episode_video_view, video_part};
pub use api_error::{ApiError, ApiQuery, ApiResult};
pub use app::{App, AppState, Console, TeleopEpisode};
pub use args::{ServeArgs, ServerFlags, StoreFlags, ThumbnailArgs, batch_roots, check_public_url, default_data_dir};
pub use mcp_gate::bearer;
pub use router::router;
pub use serve::{Bound, DRAIN_GRACE, DataLock, InProcess, Listening, SIGNAL_GRACE, run_serve, serve, serve_until, start};

/// Held by this crate's tests that build worlds or read process-wide figures (MuJoCo's asset cache, the shared
/// models): under `cargo test` the tests are threads of one process, and one test's episode showed in the
/// thumbnail pass's before/after counts (under nextest each test is a process of its own).
#[cfg(test)]
pub(crate) static PROCESS_WIDE_TEST_LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
