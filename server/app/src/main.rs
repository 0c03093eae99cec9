mod bench_render;
mod bench_sim;
mod cmd_sim;
mod cmd_inspect;
mod cmd_render;
#[cfg(feature = "episode-serve")]
mod bench_mcp;
#[cfg(feature = "episode-serve")]
mod cmd_episode;
#[cfg(feature = "episode-serve")]
mod cmd_mcp_stdio;
#[cfg(feature = "episode-serve")]
mod serve;

/// `sim inspect` (temporary wiring until the CLI is assembled; see cmd_inspect.rs).
fn sim_inspect(argv: &[String]) -> anyhow::Result<()> {
    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        args: cmd_inspect::InspectArgs,
    }
    let cli = <Cli as clap::Parser>::parse_from(argv.iter());
    cmd_inspect::run(&cli.args)
}

/// `serve`, `episode prepare`, `mcp-stdio` (temporary wiring until the CLI is assembled).
#[cfg(feature = "episode-serve")]
fn episode_commands(argv: &[String]) -> Option<anyhow::Result<()>> {
    #[derive(clap::Parser)]
    enum Cli {
        Serve(serve::ServeArgs),
        Episode(cmd_episode::EpisodeArgs),
        McpStdio(cmd_mcp_stdio::McpStdioArgs),
        #[command(subcommand)]
        Bench(Bench),
    }
    #[derive(clap::Subcommand)]
    enum Bench {
        Mcp(bench_mcp::BenchMcpArgs),
    }
    let (a1, a2) = (argv.get(1).map(String::as_str), argv.get(2).map(String::as_str));
    let wanted = matches!(a1, Some("serve" | "episode" | "mcp-stdio")) || (a1 == Some("bench") && a2 == Some("mcp"));
    if !wanted {
        return None;
    }
    Some(match <Cli as clap::Parser>::parse_from(argv.iter()) {
        Cli::Bench(Bench::Mcp(a)) => bench_mcp::run(&a),
        Cli::Serve(a) => serve::run_serve(a),
        Cli::Episode(a) => cmd_episode::run_episode(a),
        Cli::McpStdio(a) => cmd_mcp_stdio::run_mcp_stdio(a),
    })
}

/// `sim replay`, `bench sim`, `render`, `bench render` (temporary wiring until the CLI is assembled).
fn sim_commands(argv: &[String]) -> Option<anyhow::Result<()>> {
    #[derive(clap::Parser)]
    enum Cli {
        #[command(subcommand)]
        Sim(cmd_sim::SimCommand),
        Render(cmd_render::RenderArgs),
        #[command(subcommand)]
        Bench(Bench),
    }
    #[derive(clap::Subcommand)]
    enum Bench {
        Sim(bench_sim::BenchSimArgs),
        Render(bench_render::BenchRenderArgs),
    }
    let (a1, a2) = (argv.get(1).map(String::as_str), argv.get(2).map(String::as_str));
    let wanted = match a1 {
        Some("render") => true,
        Some("bench") => matches!(a2, Some("sim" | "render")),
        Some("sim") => a2 != Some("inspect"),
        _ => false,
    };
    if !wanted {
        return None;
    }
    Some(match <Cli as clap::Parser>::parse_from(argv.iter()) {
        Cli::Sim(c) => cmd_sim::run_sim(&c),
        Cli::Render(a) => cmd_render::run(&a),
        Cli::Bench(Bench::Sim(a)) => bench_sim::run(&a),
        Cli::Bench(Bench::Render(a)) => bench_render::run(&a),
    })
}

fn main() -> anyhow::Result<()> {
    let argv: Vec<String> = std::env::args().collect();
    if let Some(r) = sim_commands(&argv) {
        return r;
    }
    #[cfg(feature = "episode-serve")]
    if let Some(r) = episode_commands(&argv) {
        return r;
    }
    if argv.get(1).map(String::as_str) == Some("sim") && argv.get(2).map(String::as_str) == Some("inspect") {
        return sim_inspect(&argv[2..]);
    }
    anyhow::bail!(
        "usage: libero-agent <sim replay|sim inspect|render|bench sim|bench render|bench mcp|serve|episode prepare|mcp-stdio> ...\n\
         (serve, episode, mcp-stdio and bench mcp need the `episode-serve` feature while they are integrated; `make serve` enables it)"
    )
}
