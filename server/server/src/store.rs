//! The store is the `libero-store` crate (no HTTP, no simulator); the server uses it under this name.
pub use libero_store::*;
