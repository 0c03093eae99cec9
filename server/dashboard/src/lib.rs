//! The browser console of `libero-agent serve`: pages, the live WebSockets, reviews, teleop with demonstration
//! bundles, and the Results page. It is a [`Console`] that `libero-server` mounts behind its operator guard; the
//! episode server, the runner and the worker do not depend on it.
pub mod dashboard;
pub mod error_page;
pub mod expert_sweep;
pub mod login;
pub mod results;
pub mod task_page;
pub mod teleop;

use libero_server::Console;

/// The console's routes, login page and error pages, to set as `ServeArgs::console`.
pub fn console() -> Console {
    Console {
        operator_compressed: || dashboard::compressed_routes().merge(teleop::compressed_routes()).merge(task_page::compressed_routes()),
        operator_raw: || dashboard::raw_routes().merge(teleop::raw_routes()),
        public: || dashboard::static_routes().merge(error_page::public_routes()),
        login_page: login::login_page,
        browser_errors: error_page::browser_errors,
    }
}
