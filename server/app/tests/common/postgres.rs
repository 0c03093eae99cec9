//! The throwaway PostgreSQL cluster of the store's tests (`libero_store::testing`), for the integration tests.
#![allow(unused_imports)]
pub use libero_store::testing::TestPostgres;
