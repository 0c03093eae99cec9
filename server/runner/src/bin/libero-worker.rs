//! `libero-worker`: the queue's worker alone, for machines that only run rollouts. It links the store, the
//! artifact store, the episode server and the runner, and not the browser console: its server answers MCP (for
//! its sandboxed agents) and the operator API, and dashboards elsewhere follow its episodes through the store
//! (`libero-agent worker` is the same worker with the console's live views).
use clap::Parser;

#[derive(Parser, Debug)]
#[command(name = "libero-worker", version, about = "Runs queued rollouts of a shared store (no browser console)")]
struct Cli {
    #[command(flatten)]
    worker: libero_runner::worker::WorkerArgs,
    /// Log lines on stderr as text for people or one JSON object a line for machines (filter: RUST_LOG,
    /// default `info` for libero's own crates and `warn` for the rest).
    #[arg(long, value_enum, default_value_t = libero_logging::LogFormat::Text)]
    log_format: libero_logging::LogFormat,
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    libero_logging::ensure_runtime_dir();
    libero_logging::init(cli.log_format);
    libero_runner::worker::run(cli.worker)
}
