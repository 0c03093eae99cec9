//! The `libero-agent` binary: a thin CLI over the library crates: sim, render, episode, the episode server
//! (`libero-server`), its browser console (`libero-dashboard`) and batches (`libero-runner`).
mod bench_render;
mod bench_sim;
mod cmd_inspect;
mod cmd_render;
mod cmd_sim;
mod cmd_tasks;
#[cfg(feature = "episode-serve")]
mod bench_mcp;
#[cfg(feature = "episode-serve")]
mod bench_queue;
#[cfg(feature = "episode-serve")]
mod bench_teleop;
#[cfg(feature = "episode-serve")]
mod bench_review;
#[cfg(feature = "episode-serve")]
mod bench_soak;
#[cfg(feature = "episode-serve")]
mod bench_scale;
#[cfg(feature = "episode-serve")]
mod bench_thumbnails;
#[cfg(feature = "episode-serve")]
mod cmd_demo;
#[cfg(feature = "episode-serve")]
mod cmd_demo_replay;
#[cfg(feature = "episode-serve")]
mod cmd_episode;
#[cfg(feature = "episode-serve")]
mod cmd_expert;
#[cfg(feature = "episode-serve")]
mod cmd_expert_all;
#[cfg(feature = "episode-serve")]
mod cmd_mcp_stdio;
#[cfg(feature = "episode-serve")]
mod cmd_agent;

use clap::{Parser, Subcommand};

/// LIBERO-Agent: a benchmark server for general-purpose agents doing embodied manipulation.
#[derive(Parser)]
#[command(name = "libero-agent", version, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Log lines on stderr as text for people or one JSON object a line for machines (filter: RUST_LOG,
    /// default `info` for libero-agent's own crates and `warn` for the rest).
    #[arg(long, global = true, value_enum, default_value_t = libero_logging::LogFormat::Text)]
    log_format: libero_logging::LogFormat,
}

#[derive(Subcommand)]
enum Command {
    /// Simulation tools: replay an action sequence, inspect a composed scene.
    #[command(subcommand)]
    Sim(cmd_sim::SimCommand),
    /// Render RGB, metric depth, segmentation and calibration of a scene's cameras.
    Render(cmd_render::RenderArgs),
    /// The task catalog: list the suite, show one task.
    #[command(subcommand)]
    Tasks(cmd_tasks::TasksCommand),
    /// Benchmarks that print JSON, each beside its peer measured in the same run.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Serve prepared episodes over MCP (streamable HTTP) and the HTTP API.
    #[cfg(feature = "episode-serve")]
    Serve(libero_server::ServeArgs),
    /// Episodes on a running server.
    #[cfg(feature = "episode-serve")]
    Episode(cmd_episode::EpisodeArgs),
    /// Run a task's scripted privileged expert as episodes and print each result record as JSON.
    #[cfg(feature = "episode-serve")]
    Expert(cmd_expert::ExpertArgs),
    /// Demonstration bundles: record from a run directory, verify by replay, validate, export to LeRobot v3.
    #[cfg(feature = "episode-serve")]
    Demo(cmd_demo::DemoArgs),
    /// Relay stdio MCP to an episode's HTTP endpoint (for stdio-only agent harnesses).
    #[cfg(feature = "episode-serve")]
    McpStdio(cmd_mcp_stdio::McpStdioArgs),
    /// A benchmark batch: agent CLIs on scheduled rollouts, sandboxed and supervised (`--dry-run` to preview).
    #[cfg(feature = "episode-serve")]
    Run(Box<libero_runner::RunArgs>),
    /// Run queued rollouts on this machine: claim from the store's queue, run, upload to the artifact store.
    #[cfg(feature = "episode-serve")]
    Worker(libero_runner::worker::WorkerArgs),
    /// The paper's tables from batch directories.
    #[cfg(feature = "episode-serve")]
    Report(libero_runner::report::ReportArgs),
    /// The built-in reference agent: a scripted MCP client with no model (for end-to-end tests).
    #[cfg(feature = "episode-serve")]
    Agent(cmd_agent::AgentArgs),
    /// The first process of an agent's sandbox (started by `run` and workers, not by people): relays the agent's
    /// loopback addresses to the runner's sockets, drops every privilege, then starts the agent.
    #[cfg(feature = "episode-serve")]
    #[command(hide = true)]
    SandboxNet(libero_sandbox::sandbox_net::SandboxNetArgs),
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Control steps per second of our OSC loop vs 25 raw `mj_step` calls on the same model.
    Sim(bench_sim::BenchSimArgs),
    /// Frames per second of both cameras (RGB + depth) vs MuJoCo's own renderer.
    Render(bench_render::BenchRenderArgs),
    /// `osc_sequence` latency over MCP for 1, 4 and 8 concurrent episodes vs simulation + one render.
    #[cfg(feature = "episode-serve")]
    Mcp(bench_mcp::BenchMcpArgs),
    /// Teleop key-to-frame latency over the real WebSocket path (control socket → episode → live frame).
    #[cfg(feature = "episode-serve")]
    Teleop(bench_teleop::BenchTeleopArgs),
    /// The queue: claim latency with 1 and 3 claimers, rollouts per hour with 1 and 3 workers, in one run.
    #[cfg(feature = "episode-serve")]
    Queue(bench_queue::BenchQueueArgs),
    /// Many short episodes over MCP: resident memory, threads and open files before, at the peak and after.
    #[cfg(feature = "episode-serve")]
    Soak(bench_soak::BenchSoakArgs),
    /// Episodes per machine: a real `serve`'s resident memory and threads idle and with 1 and N open episodes
    /// over K scenes, per-episode increments, open time cold and warm, `osc_sequence` latency with N open.
    #[cfg(feature = "episode-serve")]
    Scale(bench_scale::BenchScaleArgs),
    /// A paced expert watched live (distinct frames per second of motion) and its review without video (moments
    /// rendered from recorded state: the first, uncached and cached).
    #[cfg(feature = "episode-serve")]
    Review(bench_review::BenchReviewArgs),
    /// The background thumbnail pass: a real `serve`'s resident memory before, during (max) and after it, and a
    /// soak of short episodes beside it.
    #[cfg(feature = "episode-serve")]
    Thumbnails(bench_thumbnails::BenchThumbnailsArgs),
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    // Agents' own processes (the sandbox's first process, the stdio relay, the reference agent) never render.
    #[cfg(feature = "episode-serve")]
    let renders = !matches!(cli.command, Command::SandboxNet(_) | Command::McpStdio(_) | Command::Agent(_));
    #[cfg(not(feature = "episode-serve"))]
    let renders = true;
    if renders {
        libero_logging::ensure_runtime_dir();
    }
    libero_logging::init(cli.log_format);
    match cli.command {
        Command::Sim(c) => cmd_sim::run_sim(&c),
        Command::Render(a) => cmd_render::run(&a),
        Command::Tasks(c) => cmd_tasks::run(&c),
        Command::Bench(BenchCommand::Sim(a)) => bench_sim::run(&a),
        Command::Bench(BenchCommand::Render(a)) => bench_render::run(&a),
        #[cfg(feature = "episode-serve")]
        Command::Bench(BenchCommand::Mcp(a)) => bench_mcp::run(&a),
        #[cfg(feature = "episode-serve")]
        Command::Bench(BenchCommand::Teleop(a)) => bench_teleop::run(&a),
        #[cfg(feature = "episode-serve")]
        Command::Bench(BenchCommand::Soak(a)) => bench_soak::run(&a),
        #[cfg(feature = "episode-serve")]
        Command::Bench(BenchCommand::Scale(a)) => bench_scale::run(&a),
        #[cfg(feature = "episode-serve")]
        Command::Bench(BenchCommand::Thumbnails(a)) => bench_thumbnails::run(&a),
        #[cfg(feature = "episode-serve")]
        Command::Bench(BenchCommand::Queue(a)) => bench_queue::run(&a),
        #[cfg(feature = "episode-serve")]
        Command::Bench(BenchCommand::Review(a)) => bench_review::run(&a),
        #[cfg(feature = "episode-serve")]
        Command::Serve(a) => {
            libero_server::run_serve(libero_server::ServeArgs { console: Some(libero_dashboard::console()), ..a })?;
            tracing::info!("libero-agent serve: stopped");
            Ok(())
        }
        #[cfg(feature = "episode-serve")]
        Command::Episode(a) => cmd_episode::run_episode(a),
        #[cfg(feature = "episode-serve")]
        Command::Expert(a) if a.list => cmd_expert_all::list(),
        #[cfg(feature = "episode-serve")]
        Command::Expert(a) if a.all || !a.tasks.is_empty() => cmd_expert_all::run_all(&a),
        #[cfg(feature = "episode-serve")]
        Command::Expert(a) => cmd_expert::run(&a),
        #[cfg(feature = "episode-serve")]
        Command::Demo(a) => cmd_demo::run(a),
        #[cfg(feature = "episode-serve")]
        Command::McpStdio(a) => cmd_mcp_stdio::run_mcp_stdio(a),
        #[cfg(feature = "episode-serve")]
        Command::Run(a) => libero_runner::run(*a),
        #[cfg(feature = "episode-serve")]
        Command::Worker(a) => libero_runner::worker::run(libero_runner::worker::WorkerArgs { console: Some(libero_dashboard::console()), ..a }),
        #[cfg(feature = "episode-serve")]
        Command::Report(a) => libero_runner::report::run(a),
        #[cfg(feature = "episode-serve")]
        Command::Agent(a) => cmd_agent::run(a),
        #[cfg(feature = "episode-serve")]
        Command::SandboxNet(a) => std::process::exit(libero_sandbox::sandbox_net::run(&a)?),
    }
}
