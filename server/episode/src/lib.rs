//! One place where an episode's rules live: the MCP tool contract (names, schemas, messages), action
//! validation, budgets, the episode actor thread, observation publishing into the agent's workspace and
//! the evaluator-private records, and the lifecycle of a process's episodes (`lifecycle`). No HTTP here: the
//! `libero-server` crate serves these over MCP.
pub mod actor;
pub mod branch;
pub mod call;
#[cfg(feature = "world")]
pub mod demo;
pub mod dirfd;
pub mod error;
pub mod expert_run;
#[cfg(feature = "world")]
pub mod lifecycle;
pub mod live;
pub mod memory;
pub mod observation;
pub mod physics;
pub mod publish;
pub mod readout;
#[cfg(feature = "world")]
pub mod state_record;
pub mod task;
pub mod tools;
#[cfg(feature = "world")]
pub mod video;
#[cfg(feature = "world")]
pub mod video_queue;
pub mod workspace;
#[cfg(feature = "world")]
pub mod world;

pub use actor::{EpisodeConfig, EpisodeHandle, EpisodeState, EpisodeStatus, Verdict, World, spawn_episode, spawn_episode_live};
pub use live::{LiveEvent, LiveFrame, LiveSink};
pub use call::{MicroAction, ToolCall, ToolError, validate_actions};
pub use error::EpisodeError;
pub use observation::{CameraFrame, Frame, Level, RgbImage, RobotReadout};
pub use libero_records::records::{Outcome, RunDir};
pub use workspace::{WorkspaceContract, WorkspaceLayout};
