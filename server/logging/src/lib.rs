//! The process's logger and the environment the renderer needs to stay quiet: one crate for the `libero-agent` binary
//! and `libero-worker` (which links neither the app nor its CLI).
//!
//! - Logs go to stderr through `tracing`, filtered by `RUST_LOG` (default: `info` for the project's crates,
//!   `warn` for everything else); `--log-format json` writes one JSON object a line for machines. The `log` crate's
//!   macros (used all over the library crates, and by wgpu, MuJoCo's message hook…) are bridged into it.
//! - libwayland prints `error: XDG_RUNTIME_DIR is invalid or not set in the environment.` each time wgpu's GL
//!   backend probes for a Wayland display (every renderer instance) on a machine without a session (a server, a
//!   container, CI): a private 0700 runtime directory is set when the variable is missing.
use std::io::IsTerminal;
use std::path::Path;

use tracing_subscriber::EnvFilter;

/// How log lines are written on stderr.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// One human-readable line per event: time, level, target, message, `key=value` fields.
    #[default]
    Text,
    /// One JSON object per line: `timestamp`, `level`, `target` and `fields` (`message` and the event's fields).
    Json,
}

/// The filter used when `RUST_LOG` is unset or empty: `info` for the project's crates, `warn` for everything else.
/// A directive's target matches every target it is a prefix of, so `libero` covers `libero_server::episodes`,
/// `libero_episode::video_queue`, `libero_agent`… (and names no crate: `libero-worker` must not contain the
/// console's crate name, which its test looks for).
pub fn default_filter() -> &'static str {
    // wgpu probes its GL backend beside Vulkan and logs an error whenever EGL has no driver (servers, containers,
    // CI: rendering runs on Vulkan there); the renderer reports itself when no backend works.
    "warn,wgpu_hal::gles::egl=off,libero=info"
}

/// Installs the global logger (first thing in `main`, after argument parsing): `RUST_LOG` or the default filter,
/// text or JSON lines on stderr, and the bridge from the `log` crate.
pub fn init(format: LogFormat) {
    let (filter, refused) = match std::env::var("RUST_LOG") {
        Ok(spec) if !spec.trim().is_empty() => match EnvFilter::try_new(&spec) {
            Ok(f) => (f, None),
            Err(e) => (EnvFilter::new(default_filter()), Some(format!("RUST_LOG={spec:?} is not a log filter ({e}); using the default"))),
        },
        _ => (EnvFilter::new(default_filter()), None),
    };
    let builder = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr);
    // `try_init` also installs tracing-log's LogTracer, so every `log::warn!` reaches the same subscriber.
    let installed = match format {
        LogFormat::Text => builder.with_ansi(std::io::stderr().is_terminal()).try_init(),
        // The event's fields (its `message` among them) under `fields`: an episode's `level` is not the line's.
        LogFormat::Json => builder.json().with_current_span(false).with_span_list(false).try_init(),
    };
    if let Err(e) = installed {
        eprintln!("warning: no logger installed: {e}");
    }
    if let Some(why) = refused {
        tracing::warn!("{why}");
    }
}

/// Sets `XDG_RUNTIME_DIR` to a private directory (`$TMPDIR/libero-agent-runtime-<uid>`, 0700, owned by this user)
/// when it is unset or not an absolute path, so that libwayland's probe fails quietly instead of printing an error
/// for every renderer. Nothing is ever put in the directory. Must run before any thread starts (it changes the
/// environment).
pub fn ensure_runtime_dir() {
    if std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|v| Path::new(&v).is_absolute()) {
        return;
    }
    // SAFETY: getuid cannot fail.
    let uid = unsafe { libc::getuid() };
    let shared = std::env::temp_dir().join(format!("libero-agent-runtime-{uid}"));
    let own = std::env::temp_dir().join(format!("libero-agent-runtime-{uid}-{}", std::process::id()));
    // Someone else's directory (or a link) under the shared name: one of this process's own instead.
    let Some(dir) = [shared, own].into_iter().find(|d| private_dir(d, uid)) else { return };
    // SAFETY: called at the start of `main`, before any thread exists, so nothing reads the environment meanwhile.
    unsafe { std::env::set_var("XDG_RUNTIME_DIR", &dir) };
}

/// Whether `dir` is (made if missing) a real directory of `uid` that nobody else may enter.
fn private_dir(dir: &Path, uid: u32) -> bool {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt};
    if let Err(e) = std::fs::DirBuilder::new().mode(0o700).create(dir)
        && e.kind() != std::io::ErrorKind::AlreadyExists
    {
        return false;
    }
    std::fs::symlink_metadata(dir).is_ok_and(|m| m.file_type().is_dir() && m.uid() == uid && m.mode() & 0o077 == 0)
}
