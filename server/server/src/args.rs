//! The command-line flags of a server, defined once for `serve`, `worker` and the in-process servers of `run`, so
//! their names, defaults and help cannot drift apart, and the defaults they resolve to.
use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::bail;

use crate::app::Console;
use crate::listener;

/// Where a server listens, under which names it is reached and whose token opens it: the flags `serve` and
/// `worker` share, defined once here so their names, defaults and help cannot drift apart. A worker changes
/// only `--addr`'s default (its server is for its own agents first, so any free port will do).
#[derive(clap::Args, Debug, Clone)]
pub struct ServerFlags {
    /// Address to listen on (port 0 picks a free port). `serve` prints the chosen URL as JSON on stdout; a
    /// worker's server answers its agents' MCP calls and, with a console, the live views other dashboards link to.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Data directory for run records and default workspaces (default: $LIBERO_AGENT_DATA or
    /// ~/.local/share/libero-agent). A worker's default is `workers/<worker id>` in there, a directory of its
    /// own, so any number of workers run on one machine without flags (printed at start): its server's data in
    /// `server/`, the runner's files per batch beside it.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// File holding the operator token for the dashboard and operator API (at least 16 characters). Without
    /// it, the token kept in `<data>/operator_token` (0600) is used again, or a random one is made at the first
    /// start. Either way it is kept there and registered for this user's client commands; a one-time login link is
    /// printed to stderr at each start.
    #[arg(long)]
    pub operator_token_file: Option<PathBuf>,
    /// A host name (or `name:port`) besides the loopback names under which this server is reached, e.g. behind
    /// a reverse proxy; requests naming any other `Host` are refused with 421. Repeatable.
    #[arg(long = "public-host", value_name = "NAME")]
    pub public_hosts: Vec<String>,
    /// The URL under which other machines reach this server (e.g. `http://worker-3.lab:8080`): stored with each
    /// episode it runs, so a dashboard elsewhere on the same store links to the episode's live view here
    /// (default: the address it listens on).
    #[arg(long, value_name = "URL")]
    pub public_url: Option<String>,
}

/// The stores a server shares with other machines: `serve` and `worker` take the same two flags (a worker
/// requires both: it claims from the queue in the one and uploads to the other).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct StoreFlags {
    /// The episode store: `sqlite://PATH` (default `<data>/episodes.sqlite`, embedded) or
    /// `postgres://USER@HOST:PORT/DB`, one store several servers can share (the password may come from
    /// `PGPASSWORD` or `~/.pgpass` instead of the URL). A worker needs one: its queue is there. Also
    /// $LIBERO_AGENT_STORE.
    #[arg(long, value_name = "URL", env = "LIBERO_AGENT_STORE")]
    pub store: Option<String>,
    /// The artifact store workers upload run directories to (`/shared/dir`, `file:///…` or `s3://BUCKET[/PREFIX]`
    /// with the `AWS_*` environment): reviews and videos of episodes run on other machines are fetched from there
    /// on first view and kept under `<data>/artifact_cache/`. A worker needs one. Also $LIBERO_AGENT_ARTIFACTS.
    #[arg(long, value_name = "URL", env = "LIBERO_AGENT_ARTIFACTS")]
    pub artifacts: Option<String>,
}

#[derive(clap::Args, Debug, Clone)]
pub struct ServeArgs {
    #[command(flatten)]
    pub server: ServerFlags,
    /// Replace the kept operator token with a new random one: every browser session, unused login link and
    /// client holding the old token is refused from now on.
    #[arg(long, conflicts_with = "operator_token_file")]
    pub rotate_token: bool,
    /// More batch directories for the Results page, besides `<data>/batches/`: a batch directory itself or a
    /// folder of them (e.g. `./agent_runs`, where `run` puts batches by default). Repeatable.
    #[arg(long = "batches", value_name = "DIR")]
    pub batches: Vec<PathBuf>,
    #[command(flatten)]
    pub stores: StoreFlags,
    /// Connection limits and timeouts of every listener (see [`listener`]).
    #[command(flatten)]
    pub limits: listener::ConnLimits,
    /// The browser console this server serves, if any (set by the binary, never from the command line).
    #[arg(skip)]
    pub console: Option<Console>,
    /// Which task thumbnails a server with a console renders ahead, at start.
    #[command(flatten)]
    pub thumbnails: ThumbnailArgs,
    /// Seconds a teleop episode may go without its teleop page's connection before it is ended as abandoned
    /// (aborted, the reason saying so): a page closed or navigated away from leaves nothing running.
    #[arg(long = "teleop-abandon-s", value_name = "SECONDS", default_value_t = DEFAULT_TELEOP_ABANDON_S,
        value_parser = clap::value_parser!(u64).range(1..=86_400))]
    pub teleop_abandon_s: u64,
}

/// `--teleop-abandon-s`'s default: a reload or a short network hiccup never ends an episode, a page left does.
pub const DEFAULT_TELEOP_ABANDON_S: u64 = 180;

/// Task thumbnails rendered ahead at start by a server with a console ([`crate::thumbnails`]).
#[derive(clap::Args, Debug, Clone)]
pub struct ThumbnailArgs {
    /// Task thumbnails a server with a console renders at start, in the background at low priority (cached under
    /// `<data>/thumbnails/`, reused across restarts): `off`, or a task selection (docs/commands.md, "Selecting
    /// tasks"): the default `release,all` is every release task, then every runnable pool entry; `T14,libero_90/35`,
    /// a suite or `group:G` take fewer.
    #[arg(long = "thumbnails-ahead", value_name = "SELECTION", default_value = "release,all", env = "LIBERO_AGENT_THUMBNAILS_AHEAD")]
    pub ahead: String,
    /// How many thumbnails render at once in that background pass (default: a quarter of the CPUs, at least 1).
    #[arg(long = "thumbnail-threads", value_name = "N", value_parser = clap::value_parser!(u16).range(1..=64))]
    pub threads: Option<u16>,
}

impl ThumbnailArgs {
    /// None ahead (in-process servers of `run` and workers: nobody browses their Tasks page first).
    pub fn off() -> Self {
        Self { ahead: "off".into(), threads: None }
    }

    pub(crate) fn threads(&self) -> usize {
        self.threads.map(usize::from).unwrap_or_else(|| {
            std::thread::available_parallelism().map(|n| n.get() / 4).unwrap_or(1).clamp(1, 4)
        })
    }
}

/// A `--public-url` other machines can follow: `http(s)://` and at most 512 printable characters without spaces
/// or quotes (it is stored with every episode and shown as a link).
pub fn check_public_url(url: &str) -> anyhow::Result<()> {
    let ok = (url.starts_with("http://") || url.starts_with("https://"))
        && url.len() <= 512
        && url.chars().all(|c| c.is_ascii_graphic() && !matches!(c, '"' | '\'' | '<' | '>' | '\\'));
    if !ok {
        bail!("--public-url must be an http:// or https:// URL of at most 512 characters without spaces or quotes (got {url:?})");
    }
    Ok(())
}

/// Where the server looks for batches: `<data>/batches/` first, then the `--batches` directories.
pub fn batch_roots(data: &std::path::Path, extra: &[PathBuf]) -> Vec<PathBuf> {
    std::iter::once(data.join("batches")).chain(extra.iter().cloned()).collect()
}

pub fn default_data_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("LIBERO_AGENT_DATA") {
        return PathBuf::from(d);
    }
    let home = std::env::var_os("HOME").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("."));
    home.join(".local/share/libero-agent")
}
