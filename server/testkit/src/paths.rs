//! The repository's folders as the tests see them, resolved from this crate's place in it (`server/testkit`).
use std::path::{Path, PathBuf};

/// The repository's root (the folder of `Cargo.toml`'s workspace, `README.md`, `docs/`), canonical.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").canonicalize().expect("the repository root")
}

/// `server/`: one folder per workspace crate.
pub fn server_dir() -> PathBuf {
    repo_root().join("server")
}

/// `tests/`: the reference data (`tests/reference/`), fixtures, browser scripts and test agents.
pub fn tests_dir() -> PathBuf {
    repo_root().join("tests")
}

/// The repository's `tasks/` folder (BDDL files, the pool, the manifest).
pub fn tasks_dir() -> PathBuf {
    repo_root().join("tasks")
}

/// The repository's own `assets/` folder (MJCF authored for this project, the third-party lock).
pub fn assets_dir() -> PathBuf {
    repo_root().join("assets")
}

/// The cache `scripts/setup.py` fills (third-party assets, MuJoCo, the test venv, node modules):
/// `$LIBERO_AGENT_CACHE`, else `~/.cache/libero-agent`.
pub fn cache_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("LIBERO_AGENT_CACHE") {
        return PathBuf::from(dir);
    }
    PathBuf::from(std::env::var_os("HOME").expect("HOME")).join(".cache/libero-agent")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_folders_are_the_repositorys() {
        assert!(repo_root().join("Cargo.toml").is_file());
        assert!(server_dir().join("testkit/Cargo.toml").is_file());
        assert!(tests_dir().join("reference").is_dir());
        assert!(tasks_dir().is_dir());
        assert!(assets_dir().is_dir());
    }
}
