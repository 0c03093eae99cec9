//! The browser console of `libero-agent serve`: pages, the live WebSockets, reviews, teleop with demonstration
//! bundles, and the Results page. It is a [`Console`] that `libero-server` mounts behind its operator guard; the
//! episode server, the runner and the worker do not depend on it.
//!
//! One module per page, named like its template in `web/templates/` and its script in `web/static/`: [`home`],
//! [`live`] (with `live_elsewhere`), [`review`], [`tasks`], [`task_page`] (`task.html`), [`results`], [`teleop`]
//! (with `demos`), [`batch_logs`] (`rollout_logs.html`, a rollout's logs), [`login`] and [`error_page`] (`error.html`).
//! [`routes`] assembles the episode, Tasks and
//! Results pages' routes; [`common`] and [`rows`] hold what several pages share.
pub mod annotate;
pub mod batch_logs;
pub mod common;
pub mod error_page;
pub mod expert_sweep;
pub mod home;
pub mod live;
pub mod login;
pub mod results;
pub mod review;
pub mod routes;
pub mod rows;
pub mod task_page;
pub mod tasks;
pub mod teleop;

use libero_server::Console;

/// The console's routes, login page and error pages, to set as `ServeArgs::console`.
pub fn console() -> Console {
    Console {
        operator_compressed: || {
            routes::compressed_routes().merge(teleop::compressed_routes()).merge(task_page::compressed_routes()).merge(annotate::compressed_routes())
                .merge(batch_logs::routes())
        },
        operator_raw: || routes::raw_routes().merge(teleop::raw_routes()),
        public: || routes::static_routes().merge(error_page::public_routes()),
        login_page: login::login_page,
        browser_errors: error_page::browser_errors,
    }
}
