//! The repository's folders as the tests see them, resolved from this crate's place in it (`server/testkit`).
use std::path::PathBuf;

/// The repository's root (the folder of the workspace's `Cargo.toml`, `README.md`, `docs/`), canonical: the first
/// folder above the running test's package (cargo and nextest set `CARGO_MANIFEST_DIR` for the test process) that
/// holds the workspace's manifest. Read at run time, not baked in when this crate was compiled: checkouts that share
/// one target directory share this crate's build too, and each must read its own files.
pub fn repo_root() -> PathBuf {
    let package = std::env::var_os("CARGO_MANIFEST_DIR").map(PathBuf::from).unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")));
    let root = package
        .ancestors()
        .find(|dir| std::fs::read_to_string(dir.join("Cargo.toml")).is_ok_and(|t| t.lines().any(|l| l.trim() == "[workspace]")))
        .unwrap_or_else(|| panic!("no workspace Cargo.toml above {}", package.display()));
    root.canonicalize().unwrap_or_else(|e| panic!("the repository root {}: {e}", root.display()))
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

/// The test venv's interpreter (`scripts/setup.py --test`: MuJoCo's Python package, numpy, Pillow, the MCP SDK,
/// openpi-client): the independent Python peers of the tests. Fails loudly when the set-up has not been run.
pub fn venv_python() -> PathBuf {
    let py = cache_dir().join("pyenv/bin/python");
    assert!(py.is_file(), "{} is missing: run `python3 scripts/setup.py --test`", py.display());
    py
}
