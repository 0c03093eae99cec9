//! The throwaway PostgreSQL cluster of the store's tests (`libero_store::testing`, through the testkit), for the
//! integration tests.
#![allow(unused_imports)]
pub use libero_testkit::TestPostgres;
