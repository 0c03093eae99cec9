//! The browser console of `libero-agent serve`: pages, the live WebSockets, reviews, teleop with demonstration
//! bundles, and the Results page. It is a [`Console`] that `libero-server` mounts behind its operator guard; the
//! episode server, the runner and the worker do not depend on it.
pub mod dashboard;
pub mod results;
pub mod teleop;

use libero_server::Console;

/// The console's routes and login page, to set as `ServeArgs::console`.
pub fn console() -> Console {
    Console {
        operator_compressed: || dashboard::compressed_routes().merge(teleop::compressed_routes()),
        operator_raw: || dashboard::raw_routes().merge(teleop::raw_routes()),
        public: dashboard::static_routes,
        login_page: dashboard::login_page,
    }
}
