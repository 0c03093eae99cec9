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
}

fn main() -> anyhow::Result<()> {
    libero_runner::worker::run(Cli::parse().worker)
}
