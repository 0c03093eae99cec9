//! An episode's run directory and its records, and the JSON helpers they are written with. Split out of the
//! episode crate so that the store (and, later, the queue and its workers) read run directories without linking the
//! simulator.
pub mod agent_events;
pub mod json;
pub mod records;
