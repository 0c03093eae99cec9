//! An episode's run directory and its records, and the JSON helpers they are written with. Split out of the
//! episode crate so that the store (and, later, the queue and its workers) read run directories without linking the
//! simulator. The records are typed ([`typed`]: `result.json` in [`result`], `actions.jsonl` in [`action_event`],
//! `episode_record.json` in [`episode_record`], a batch's documents in [`batch_doc`], a demonstration bundle's
//! manifest in [`demo_manifest`]) and keep every field they do not name, so a record read and written back is
//! unchanged. The operator API's episode replies, which the server, its client, the runner and the console share,
//! are typed in [`episode_view`].
pub mod action_event;
pub mod agent_events;
pub mod batch_doc;
pub mod demo_manifest;
pub mod episode_record;
pub mod episode_view;
pub mod expert_sweep;
pub mod json;
pub mod records;
pub mod result;
pub mod typed;
