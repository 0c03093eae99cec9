//! Where things are on the host: the system directories a sandbox shows read-only, the search-path lookup of a
//! program, and the cache `scripts/setup.py` fills. The sandbox, the toolbox and the runner's harness versions read them; kept
//! apart so that none imports another for them.
use std::path::{Path, PathBuf};

/// System directories visible read-only (symlinks such as Debian's `/lib -> usr/lib` are recreated as links).
pub const SYSTEM_DIRS: [&str; 7] = ["/usr", "/etc", "/bin", "/sbin", "/lib", "/lib64", "/lib32"];

/// Finds `name` on `PATH` (or takes it as a path).
pub fn which(name: &str) -> Option<PathBuf> {
    which_in(name, &std::env::var_os("PATH").unwrap_or_default())
}

/// Finds `name` on the search path `path` (or takes it as a path).
pub fn which_in(name: &str, path: &std::ffi::OsStr) -> Option<PathBuf> {
    if name.contains('/') {
        return Path::new(name).is_file().then(|| PathBuf::from(name));
    }
    std::env::split_paths(path).map(|d| d.join(name)).find(|p| p.is_file())
}

/// `$LIBERO_AGENT_CACHE`, else `~/.cache/libero-agent` (the cache `scripts/setup.py` fills).
pub fn cache_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("LIBERO_AGENT_CACHE") {
        return PathBuf::from(dir);
    }
    std::env::var_os("HOME").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("/")).join(".cache/libero-agent")
}
