//! `libero-worker`: the queue's worker alone, for machines that only run rollouts. It links the store, the
//! artifact store, the episode server and the runner, and not the browser console: its server answers MCP (for
//! its sandboxed agents) and the operator API, and dashboards elsewhere follow its episodes through the store
//! (`libero-agent worker` is the same worker with the console's live views).
use clap::Parser;

/// The logger and runtime-directory set-up of `libero-agent`, the same source (this binary links no app crate).
#[path = "../../../app/src/logging.rs"]
mod logging;

#[derive(Parser, Debug)]
#[command(name = "libero-worker", version, about = "Runs queued rollouts of a shared store (no browser console)")]
struct Cli {
    #[command(flatten)]
    worker: libero_runner::worker::WorkerArgs,
    /// Log lines on stderr as text for people or one JSON object a line for machines (filter: RUST_LOG,
    /// default `info` for libero's own crates and `warn` for the rest).
    #[arg(long, value_enum, default_value_t = logging::LogFormat::Text)]
    log_format: logging::LogFormat,
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    logging::ensure_runtime_dir();
    logging::init(cli.log_format);
    libero_runner::worker::run(cli.worker)
}
